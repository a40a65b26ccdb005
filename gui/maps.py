"""The live map panels: one image per map with a colour bar in physical units, unmeasured pixels
transparent (over a grey view background), levels that stay put during a scan until asked to fit."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np
import pyqtgraph as pg
from PySide6 import QtWidgets

from spdepth.acq.flags import ACQUIRING
from spdepth.recon.maps import C_M_PER_S

VIEW_BACKGROUND = "#d4d4d4"
"""Behind the images: unmeasured (NaN) pixels show this grey, apart from every colour map end."""
FIT_PERCENTILES = (1.0, 99.0)
"""Fitted levels span these percentiles of the finite pixels (a few outliers do not flatten the
rest of the map)."""

# dark axes and labels on the white plots (pyqtgraph's default grey is faint there)
pg.setConfigOptions(imageAxisOrder="row-major", antialias=True, foreground="#303030")


def _measured_counts(snap) -> np.ndarray:
    c = snap.counts.astype(np.float64)
    c[(snap.counts == 0) & (snap.acq_flags == ACQUIRING)] = np.nan    # not visited yet: transparent
    return c


def _background_window(snap, n_bins: int) -> np.ndarray:
    return snap.background * n_bins


def _sigma_cm(snap) -> np.ndarray:
    return snap.uncertainty_s * (C_M_PER_S / 2) * 100.0


@dataclass(frozen=True)
class MapSpec:
    """key, title, unit for the colour bar, colour map, and how to get the (H, W) array from a
    snapshot (``extract(snap, n_bins)``); fixed_levels(target) for maps with natural limits."""

    key: str
    title: str
    unit: str
    cmap: str
    extract: Callable
    fixed_levels: Callable | None = None


MAP_SPECS = (
    MapSpec("depth", "Depth", "m", "viridis", lambda s, n: s.depth_m),
    # reversed: most pixels of a short dwell estimate no background at all, and magma's black
    # low end made them one black field; light for none reads as "clean"
    MapSpec("background", "Background", "detections in window", "magma_r", _background_window),
    MapSpec("counts", "Detections kept", "per pixel", "cividis", lambda s, n: _measured_counts(s),
            fixed_levels=lambda target: (0.0, float(target))),
    MapSpec("uncertainty", "Depth uncertainty (1 sigma)", "cm", "plasma", lambda s, n: _sigma_cm(s)),
)


def fit_levels(data: np.ndarray) -> tuple[float, float] | None:
    """Robust levels of the finite pixels, None when there are none."""
    v = data[np.isfinite(data)]
    if v.size == 0:
        return None
    lo, hi = np.percentile(v, FIT_PERCENTILES) if v.size >= 20 else (v.min(), v.max())
    lo, hi = float(lo), float(hi)
    if not hi > lo:
        pad = max(abs(lo) * 0.05, 1e-6)
        lo, hi = lo - pad, hi + pad
    return lo, hi


class MapPanel:
    """One map in a GraphicsLayout cell: plot (title), image, colour bar with the unit, and a
    square marking the inspected pixel."""

    def __init__(self, layout: pg.GraphicsLayout, spec: MapSpec, row: int, col: int):
        self.spec = spec
        self.plot = layout.addPlot(row=row, col=col)
        self.plot.setTitle(spec.title, size="11pt")
        self.plot.setAspectLocked(True)
        self.plot.invertY(True)
        self.plot.hideButtons()
        self.plot.setMenuEnabled(False)
        for side in ("left", "bottom"):
            self.plot.getAxis(side).setStyle(tickLength=-4)
        self.plot.vb.setBackgroundColor(VIEW_BACKGROUND)
        self.image = pg.ImageItem(axisOrder="row-major")
        self.plot.addItem(self.image)
        cmap = pg.colormap.get(spec.cmap.removesuffix("_r"))
        if spec.cmap.endswith("_r"):
            cmap.reverse()
        self.bar = pg.ColorBarItem(values=(0.0, 1.0), colorMap=cmap,
                                   label=f"{spec.title} ({spec.unit})", width=16,
                                   interactive=True, pen="#444", colorMapMenu=False)
        self.bar.setImageItem(self.image, insert_in=self.plot)
        # an image update repaints what overlaps it; the axes and the bar's axis are the dearest
        # items to paint (pyqtgraph draws them in Python) and rarely change: keep them as pixmaps
        for item in (self.plot.getAxis("left"), self.plot.getAxis("bottom"), self.bar.axis,
                     self.plot.titleLabel):
            item.setCacheMode(QtWidgets.QGraphicsItem.DeviceCoordinateCache)
        self.marker = pg.PlotDataItem(pen=pg.mkPen("#ff2d2d", width=2))
        self.marker.setZValue(10)
        self.plot.addItem(self.marker)
        self.levels: tuple[float, float] | None = None
        self.data: np.ndarray | None = None
        self.version = None
        self._shape = None

    def reset(self) -> None:
        self.levels = None
        self.data = None
        self.version = None
        self._shape = None
        self.image.clear()
        self.marker.setData([], [])

    def show(self, data: np.ndarray, target: int, version=None) -> None:
        """New data; levels fixed on the first data (or the spec's natural limits) and then kept.
        ``version``: when given and equal to the last one shown, the data is unchanged and the
        image is not set again (each setImage re-renders the whole image in Python)."""
        if version is not None and version == self.version:
            return
        self.version = version
        self.data = data
        if self.levels is None:
            self.levels = (self.spec.fixed_levels(target) if self.spec.fixed_levels
                           else fit_levels(data))
            if self.levels is not None:
                self.bar.setLevels(self.levels)
        # the bar holds the levels (the user may drag them); streaming never auto-levels
        self.image.setImage(data, autoLevels=False, levels=self.bar.levels())
        if data.shape != self._shape:
            self._shape = data.shape
            h, w = data.shape
            self.plot.setRange(xRange=(0, w), yRange=(0, h), padding=0.02)

    def fit(self, target: int) -> None:
        """Levels to the data now (the spec's natural limits for counts)."""
        if self.data is None:
            return
        lv = self.spec.fixed_levels(target) if self.spec.fixed_levels else fit_levels(self.data)
        if lv is not None:
            self.levels = lv
            self.bar.setLevels(lv)

    def mark(self, pixel: tuple[int, int] | None) -> None:
        if pixel is None:
            self.marker.setData([], [])
            return
        r, c = pixel
        self.marker.setData([c, c + 1, c + 1, c, c], [r, r, r + 1, r + 1, r])

    def pixel_at(self, scene_pos) -> tuple[int, int] | None:
        """(row, col) under a scene position, None outside this map's image."""
        if self._shape is None or not self.plot.vb.sceneBoundingRect().contains(scene_pos):
            return None
        p = self.plot.vb.mapSceneToView(scene_pos)
        r, c = int(np.floor(p.y())), int(np.floor(p.x()))
        h, w = self._shape
        return (r, c) if 0 <= r < h and 0 <= c < w else None


__all__ = ["MapPanel", "MapSpec", "MAP_SPECS", "fit_levels", "C_M_PER_S"]
