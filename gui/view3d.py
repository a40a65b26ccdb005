"""The live 3-D view: the maps as a point cloud (``acq.points``' scanner frame), coloured by depth
or by intensity, one colour per surface when a pixel holds several; rotate with the left mouse
button, zoom with the wheel, pan with the middle button (pyqtgraph's ``GLViewWidget``).

It needs OpenGL: pyqtgraph.opengl (PyOpenGL) and a platform that gives an OpenGL context (a real
display, or Xvfb with Mesa). It is pyqtgraph's ``GLViewWidget`` (a QOpenGLWidget), made when the
3D tab is first shown: from then on Qt composites the whole window through OpenGL, so every
status-bar update costs an OpenGL frame (in software under Mesa). A ``QOpenGLWindow`` in a window
container avoids that, but crashed Qt (xcb, Mesa) when a second window ran a scan.

Qt's ``offscreen`` platform gives no OpenGL context ("QOpenGLWidget is not supported
on this platform"), so there :func:`opengl_unavailable` names the reason and the window shows a
note instead of the view.
"""

from __future__ import annotations

import os

import numpy as np
from PySide6 import QtCore, QtGui, QtWidgets

from spdepth.acq.mapdefs import levels_for, MAPS_BY_KEY

# Mesa's software renderer (llvmpipe: Xvfb, machines without a GPU driver) renders on a thread per
# core by default, outside the GUI thread whose CPU time the window budgets, and those threads took
# cores from the scan; rendering in the GUI thread keeps the budget honest. No effect on GPU drivers.
os.environ.setdefault("LP_NUM_THREADS", "0")

if QtCore.QCoreApplication.instance() is None:
    # one GL resource space for every 3-D view of the process (set before the QApplication exists,
    # also when a test or another program makes it): pyqtgraph compiles each item's shader once
    # per process, and a second view (a new window) must be able to use it
    QtCore.QCoreApplication.setAttribute(QtCore.Qt.AA_ShareOpenGLContexts)

SURFACE_COLOURS = ((0.12, 0.47, 0.71, 1.0), (1.0, 0.50, 0.05, 1.0), (0.17, 0.63, 0.17, 1.0),
                   (0.84, 0.15, 0.16, 1.0), (0.58, 0.40, 0.74, 1.0))
"""One colour per surface (nearest first), coloured by surface."""
WEAK_COLOUR = (0.72, 0.72, 0.72, 0.6)
"""Points of weak surfaces (background alone could have made them): grey, whatever the colouring."""
POINT_SIZE_PX = 3.0


def opengl_unavailable() -> str | None:
    """Why the 3-D view cannot be shown here, or None when it can."""
    app = QtGui.QGuiApplication.instance()
    platform = app.platformName() if app is not None else ""
    if platform in ("offscreen", "minimal"):
        return (f"Qt's '{platform}' platform has no OpenGL: the 3-D view needs a display "
                f"(or Xvfb with Mesa: xvfb-run spdepth gui ...)")
    try:
        import OpenGL.GL  # noqa: F401
        import pyqtgraph.opengl  # noqa: F401
    except Exception as exc:  # noqa: BLE001 - any import failure means no 3-D view
        return f"no OpenGL for Python ({exc}): pip install PyOpenGL"
    return None


def _turbo(values: np.ndarray, levels: tuple[float, float]) -> np.ndarray:
    import pyqtgraph as pg

    lo, hi = levels
    t = np.clip((values - lo) / (hi - lo if hi > lo else 1.0), 0.0, 1.0)
    return pg.colormap.get("turbo", source="matplotlib").map(t, mode="float")


class PointCloudView(QtWidgets.QWidget):
    """The 3-D view with its colour choice; ``set_maps`` draws a (live) map set."""

    def __init__(self, parent=None):
        super().__init__(parent)
        lay = QtWidgets.QVBoxLayout(self)
        lay.setContentsMargins(0, 0, 0, 0)
        top = QtWidgets.QHBoxLayout()
        top.addWidget(QtWidgets.QLabel("<b>Colour by</b>"))
        self.colour = QtWidgets.QComboBox()
        self.colour.addItem("depth", "depth")
        self.colour.addItem("intensity (signal detections)", "intensity")
        self.colour.addItem("surface", "surface")
        self.colour.currentIndexChanged.connect(self._redraw)
        top.addWidget(self.colour)
        self.info = QtWidgets.QLabel("")
        top.addWidget(self.info, 1)
        reset = QtWidgets.QPushButton("Reset view")
        reset.clicked.connect(self.reset_camera)
        top.addWidget(reset)
        lay.addLayout(top)
        self.reason = opengl_unavailable()
        self.gl = None
        self.scatter = None
        self._layout = lay
        if self.reason is None:
            pass                               # the GL view is made when first shown (showEvent)
        else:
            note = QtWidgets.QLabel(f"3-D view not available: {self.reason}")
            note.setWordWrap(True)
            note.setAlignment(QtCore.Qt.AlignCenter)
            note.setStyleSheet("color: #555; padding: 20px;")
            lay.addWidget(note, 1)
        self._dirs = None
        self._geometry = None
        self._last = None
        self._camera_set = False
        self.n_points = 0

    @property
    def available(self) -> bool:
        return self.reason is None

    def showEvent(self, event) -> None:  # noqa: N802 - Qt override
        self._ensure_view()
        super().showEvent(event)

    def _ensure_view(self) -> None:
        """Make the GL view the first time the tab is shown: a window that never shows its 3-D
        view never pays for OpenGL (a QOpenGLWidget makes Qt composite the whole window through
        OpenGL)."""
        if self.gl is not None or self.reason is not None:
            return
        import pyqtgraph.opengl as gl

        self.gl = gl.GLViewWidget()
        self.gl.setBackgroundColor("w")
        self.scatter = gl.GLScatterPlotItem(pos=np.zeros((0, 3)), size=POINT_SIZE_PX, pxMode=True)
        self.scatter.setGLOptions("opaque")
        self.gl.addItem(self.scatter)
        self.axes = gl.GLAxisItem()
        self.gl.addItem(self.axes)
        self._layout.addWidget(self.gl, 1)
        self._camera_set = False
        self._redraw()

    def reset(self, geometry) -> None:
        """A new run: its geometry (``acq.points.ScanGeometry``; None: no 3-D)."""
        self._geometry = geometry
        self._dirs = geometry.directions() if geometry is not None else None
        self._last = None
        self._camera_set = False
        self.n_points = 0
        if self.scatter is not None:
            self.scatter.setData(pos=np.zeros((0, 3)))
        self.info.setText("" if geometry is not None else
                          "  this source has no scan geometry: no points")

    def set_maps(self, depth_m: np.ndarray, signal: np.ndarray, weak: np.ndarray | None = None) -> None:
        """Depth (H, W) or (K, H, W), the signal detections and the weak surfaces (background
        alone could have made them: drawn grey, left out of the colour levels and the framing) of
        the same shape."""
        depth_m = np.asarray(depth_m, dtype=np.float64)
        weak = np.zeros(depth_m.shape, bool) if weak is None or np.shape(weak) != depth_m.shape \
            else np.asarray(weak, bool)
        self._last = (depth_m, np.asarray(signal, dtype=np.float64), weak)
        self._redraw()

    def _redraw(self) -> None:
        if self._last is None or self._dirs is None:
            return
        depth, signal, weak = self._last
        depth = depth if depth.ndim == 3 else depth[None]
        signal = signal if signal.ndim == 3 else signal[None]
        weak = weak if weak.ndim == 3 else weak[None]
        ok = np.isfinite(depth)
        surf, rr, cc = np.nonzero(ok)
        rng = depth[ok]
        faint = weak[ok]
        # confident points set the levels and the framing (all points when none is)
        sure = ~faint if np.any(~faint) else np.ones(faint.shape, bool)
        pos = self._dirs[rr, cc] * rng[:, None]
        self.n_points = int(rng.size)
        how = self.colour.currentData()
        if how == "surface":
            colours = np.array(SURFACE_COLOURS)[surf % len(SURFACE_COLOURS)]
        elif how == "intensity":
            s = signal[np.minimum(surf, signal.shape[0] - 1), rr, cc]
            colours = _turbo(s, (0.0, float(np.nanpercentile(s[sure], 99)) if s.size else 1.0))
        else:
            lv = levels_for(MAPS_BY_KEY["depth"], rng[sure]) or (0.0, 1.0)
            colours = _turbo(rng, lv)
        colours = np.array(colours, dtype=np.float64)
        colours[faint] = WEAK_COLOUR
        k = depth.shape[0]
        self.info.setText(f"  {self.n_points:,} points" + (f", {k} surfaces" if k > 1 else "")
                          + "; drag to rotate, wheel to zoom")
        if self.scatter is None:
            return
        # the frame of acq.points has y down (image rows) and z away from the scanner; the GL view's
        # z is up: shown as (x, z, -y), so the scene stands upright in front of the scanner
        shown = np.stack([pos[:, 0], pos[:, 2], -pos[:, 1]], axis=1)
        self.scatter.setData(pos=shown, color=colours.astype(np.float32), size=POINT_SIZE_PX)
        if not self._camera_set and rng.size:
            self._aim(shown[sure])

    def _aim(self, shown: np.ndarray) -> None:
        """Frame the points: centred on their median, sized by their 2-98% spread (a few stray
        points far behind or in front must not shrink the scene to a wedge)."""
        centre = np.median(shown, axis=0)
        lo, hi = np.percentile(shown, [2, 98], axis=0) if len(shown) >= 20 else (shown.min(0), shown.max(0))
        span = float(np.max(hi - lo)) or 1.0
        self.gl.opts["center"] = QtGui.QVector3D(*centre)
        # from behind the scanner, a little above and to the side: depth and relief both show
        self.gl.setCameraPosition(distance=max(2.5 * span, 0.5), elevation=15, azimuth=-115)
        self.axes.setSize(span / 4, span / 4, span / 4)
        self._camera_set = True

    def reset_camera(self) -> None:
        self._camera_set = False
        self._redraw()

    def release(self) -> None:
        """Nothing to hand back (kept for the window's close)."""

    def grab_view(self):
        """The rendered picture (a QImage), None before the view was first shown."""
        return self.gl.grabFramebuffer() if self.gl is not None else None


__all__ = ["PointCloudView", "opengl_unavailable", "SURFACE_COLOURS"]
