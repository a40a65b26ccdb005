"""The window of a SPAD-array session (``spdepth array --gui``): depth and counts of the newest maps,
and the 3-D view (``gui.view3d``), refreshed by a timer from the session's snapshots; pause, resume,
abort. The session is built and owned by ``acq`` (``acq.array_session``); this window only reads its
snapshots and sends it commands, as the main window does with a scan.
"""

from __future__ import annotations

import numpy as np
import pyqtgraph as pg
from PySide6 import QtCore, QtWidgets

from spdepth.gui.view3d import PointCloudView

REFRESH_HZ = 15.0
"""Snapshots pulled a second (the acquisition and the estimator run free of the window)."""


class ArrayWindow(QtWidgets.QMainWindow):
    """Shows ``session`` (an ``acq.array_session.ArraySession``, started or not) live; ``geometry``:
    the sensor's ``acq.points.ScanGeometry`` for the 3-D view (None: no points)."""

    def __init__(self, session, geometry=None, parent=None):
        super().__init__(parent)
        pg.setConfigOptions(imageAxisOrder="row-major")
        self.session = session
        self.setWindowTitle(f"spdepth array: {session.source.name}, {session.mode}")
        self.tabs = QtWidgets.QTabWidget()
        maps = pg.GraphicsLayoutWidget()
        self.depth_plot = maps.addPlot(row=0, col=0, title="Depth (m)")
        self.counts_plot = maps.addPlot(row=0, col=1, title="Counts per pixel")
        self.images = {}
        for key, plot in (("depth", self.depth_plot), ("counts", self.counts_plot)):
            img = pg.ImageItem()
            img.setColorMap(pg.colormap.get("turbo", source="matplotlib"))
            plot.addItem(img)
            plot.invertY(True)
            plot.setAspectLocked(True)
            self.images[key] = img
        self.tabs.addTab(maps, "Maps")
        self.view3d = PointCloudView()
        self.view3d.reset(geometry)
        self.tabs.addTab(self.view3d, "3D")
        buttons = QtWidgets.QHBoxLayout()
        for name in ("pause", "resume", "abort"):
            b = QtWidgets.QPushButton(name.capitalize())
            b.clicked.connect(getattr(session, name))
            buttons.addWidget(b)
        self.status = QtWidgets.QLabel("")
        buttons.addWidget(self.status, 1)
        central = QtWidgets.QWidget()
        lay = QtWidgets.QVBoxLayout(central)
        lay.addWidget(self.tabs, 1)
        lay.addLayout(buttons)
        self.setCentralWidget(central)
        self.resize(1000, 520)
        self.shown_frame = 0
        self.timer = QtCore.QTimer(self)
        self.timer.timeout.connect(self.refresh)
        self.timer.start(int(1000 / REFRESH_HZ))

    def refresh(self) -> bool:
        """Pull a snapshot; set the maps when newer ones came. Returns whether they were set."""
        snap = self.session.snapshot()
        self.status.setText(f"{snap.state.value}: frame {snap.frames}"
                            + (f"/{snap.n_frames}" if snap.n_frames else "")
                            + f", maps of frame {self.session.reconstructed}; acquired "
                              f"{snap.acquired_fps:.1f} frames/s, estimator {snap.recon_fps:.1f}/s")
        if snap.maps is None or self.session.reconstructed == self.shown_frame:
            return False
        self.shown_frame = self.session.reconstructed
        depth = np.asarray(snap.maps.depth_m, np.float64)
        finite = depth[np.isfinite(depth)]
        levels = (float(np.percentile(finite, 2)), float(np.percentile(finite, 98))) if finite.size else (0, 1)
        self.images["depth"].setImage(depth, autoLevels=False, levels=levels)
        self.images["counts"].setImage(np.asarray(snap.counts, np.float64), autoLevels=True)
        if self.tabs.currentWidget() is self.view3d:
            self.view3d.set_maps(depth, snap.maps.signal)
        return True

    def closeEvent(self, event) -> None:  # noqa: N802 - Qt override
        self.timer.stop()
        self.session.abort()
        self.session.wait(5.0)
        super().closeEvent(event)


__all__ = ["ArrayWindow", "REFRESH_HZ"]
