"""The live map panels: one image per map of ``acq.mapdefs.MAP_DEFS`` (the PNG sheets' maps, same
names, units, colour maps and level rules), drawn in scan degrees with each pixel's true aspect,
axes linked between the panels, pixels without a value grey.

Levels: during a scan they follow the map's rule on what has arrived and only ever widen (a scan's
first rows never fix them); "Fit levels" and the end of a run refit them to what is shown.
"""

from __future__ import annotations

import types

import numpy as np
import pyqtgraph as pg
from PySide6 import QtCore, QtWidgets

from spdepth.acq.flags import AcqFlag
from spdepth.acq.mapdefs import (DISCRETE_MAX, FADE_RGBA, MAP_DEFS, NAN_COLOUR, PANEL_DEFS, MapDef, MapInput,
                                 constant_caption, display, levels_for, whole_numbers, widen)
from spdepth.recon.maps import C_M_PER_S

VIEW_BACKGROUND = NAN_COLOUR
"""Behind the images: pixels without a value (NaN draws transparent) show this grey, as in the PNG."""

# dark axes and labels on the white plots (pyqtgraph's default grey is faint there)
pg.setConfigOptions(imageAxisOrder="row-major", antialias=True, foreground="#303030")


def measured_counts(snap) -> np.ndarray:
    """Detections kept per pixel, NaN (grey) for pixels with none that are not complete: not
    visited yet, or left unmeasured by an abort."""
    c = snap.counts.astype(np.float64)
    c[(snap.counts == 0) & (snap.acq_flags != AcqFlag.COMPLETE)] = np.nan
    return c


def snapshot_input(snap, n_bins: int, target: int) -> MapInput:
    """A session snapshot (or a file result's) as the maps' input (with its (H, W) surfaces-found
    map when it holds K > 1 surfaces)."""
    return MapInput(depth_m=snap.depth_m, background=snap.background, signal=snap.signal,
                    uncertainty_s=snap.uncertainty_s, counts=measured_counts(snap),
                    n_bins=n_bins, target=target, surfaces=snap.surfaces,
                    exposure_s=getattr(snap, "exposure_s", None))


def _height_only_min(label) -> None:
    """``LabelItem.updateMin`` without the width: the text's height is the label's minimum."""
    h = label.itemRect().height()
    w = label.itemRect().width()
    label.setMinimumWidth(0)
    label.setMinimumHeight(h)
    label._sizeHint = {QtCore.Qt.SizeHint.MinimumSize: (0, h),
                       QtCore.Qt.SizeHint.PreferredSize: (w, h),
                       QtCore.Qt.SizeHint.MaximumSize: (-1, -1),
                       QtCore.Qt.SizeHint.MinimumDescent: (0, 0)}
    label.updateGeometry()


class MapPanel:
    """One map in a GraphicsLayout cell: plot (title), image placed in scan degrees, colour bar
    with the unit, and a square marking the inspected pixel.

    geometry: an ``acq.points.ScanGeometry`` (or None: pixel indices, square pixels), set by
    ``set_geometry`` before the first data of a run."""

    def __init__(self, layout: pg.GraphicsLayout, spec: MapDef, row: int, col: int):
        self.place = spec
        """The place (one of ``PANEL_DEFS``); ``spec`` is what it shows now (``resolve``)."""
        self.spec = spec
        self.plot = layout.addPlot(row=row, col=col)
        # pyqtgraph makes a title's width the plot's minimum width: a long caption in the left
        # column made the layout wider than the window at the default size, and the right
        # column's colour-bar ticks were cut off. Its height only, then.
        self.plot.titleLabel.updateMin = types.MethodType(_height_only_min, self.plot.titleLabel)
        self._title(spec.title)
        self.plot.setAspectLocked(True)
        self.plot.invertY(True)
        self.plot.hideButtons()
        self.plot.setMenuEnabled(False)
        for side in ("left", "bottom"):
            self.plot.getAxis(side).setStyle(tickLength=-4)
        self.plot.vb.setBackgroundColor(VIEW_BACKGROUND)
        self.image = pg.ImageItem(axisOrder="row-major")
        self.plot.addItem(self.image)
        cmap = pg.colormap.get(spec.cmap, source="matplotlib")
        self.bar = pg.ColorBarItem(values=(0.0, 1.0), colorMap=cmap,
                                   label=f"{spec.title} ({spec.unit})", width=14,
                                   interactive=True, pen="#444", colorMapMenu=False)
        self.bar.setImageItem(self.image, insert_in=self.plot)
        # several surfaces: a surface background alone could have made is faded, not a finding
        self.faded = pg.ImageItem(axisOrder="row-major")
        self.faded.setZValue(5)
        self.plot.addItem(self.faded, ignoreBounds=True)     # the map alone sets the view
        self.bar.setToolTip(spec.about)
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
        self.geometry = None
        self._shape = None
        self._const = None

    def set_spec(self, spec: MapDef) -> None:
        """Show another map in this place (a scan's background rate where a file's maps have the
        background count): its title, unit, colour map and levels from scratch."""
        if spec is self.spec:
            return
        self.spec = spec
        self.bar.setColorMap(pg.colormap.get(spec.cmap, source="matplotlib"))
        self.bar.getAxis("left").setLabel(f"{spec.title} ({spec.unit})")    # where the bar's label is
        self.bar.setToolTip(spec.about)
        self.reset()

    # ---- geometry ------------------------------------------------------------------------------
    def set_geometry(self, geometry, shape: tuple[int, int]) -> None:
        """Place the image: in scan degrees (true pixel aspect) or, without a geometry, in pixel
        indices; axes labelled to match."""
        self.geometry = geometry
        self._shape = tuple(shape)
        h, w = self._shape
        if geometry is not None:
            left, right, top, bottom = geometry.extent_deg
            self.rect = QtCore.QRectF(left, top, right - left, bottom - top)
            self.plot.setLabel("bottom", "scan angle x (°)")
            self.plot.setLabel("left", "scan angle y (°)")
        else:
            self.rect = QtCore.QRectF(0, 0, w, h)
            self.plot.setLabel("bottom", "column")
            self.plot.setLabel("left", "row")
        self.image.setRect(self.rect)
        self.plot.setRange(self.rect, padding=0.02)

    def pixel_rect(self, r: int, c: int) -> QtCore.QRectF:
        """Pixel (row, col) in view coordinates."""
        h, w = self._shape
        pw, ph = self.rect.width() / w, self.rect.height() / h
        return QtCore.QRectF(self.rect.left() + c * pw, self.rect.top() + r * ph, pw, ph)

    # ---- data ----------------------------------------------------------------------------------
    def reset(self) -> None:
        self.levels = None
        self.data = None
        self.version = None
        self._const = None
        self.image.clear()
        self.faded.clear()
        self.marker.setData([], [])
        self._title(self.spec.title)

    def _title(self, text: str) -> None:
        self.plot.setTitle(text, size="10pt")

    def show(self, data: np.ndarray, target: int, version=None, *, refit: bool = False,
             surface: int = 0, weak: np.ndarray | None = None, missing: str | None = None) -> None:
        """New data. Levels by the map's rule on the data, widened (never narrowed) during a run,
        or refitted with ``refit``. ``version``: equal to the last one shown, the data is unchanged
        and the image is not set again (each setImage re-renders the whole image in Python).
        ``surface``, ``weak``: of (K, H, W) data, the surface shown and the (K, H, W) mask of weak
        surfaces, drawn faded. ``missing``: what the title says when no pixel holds a value
        because none is estimated (the background of an estimator without one)."""
        if version is not None and version == self.version and not refit:
            return
        self.version = version
        data = np.asarray(data, dtype=np.float64)
        faded = None
        if data.ndim == 3:                       # K surfaces: the one picked
            k = min(surface, data.shape[0] - 1)
            if weak is not None and np.shape(weak) == data.shape:
                faded = np.asarray(weak[k], bool) & np.isfinite(data[k])
            data = data[k]
        self.data = data
        new = levels_for(self.spec, data, target, weak=faded)     # confident surfaces set the levels
        lv = new if (refit or self.levels is None) else widen(self.levels, new)
        if lv is not None and lv != self.levels:
            self.levels = lv
            self.bar.setLevels(lv)
            # a map of a few counts (surfaces per pixel): a tick per count, not 0.5 steps
            few = whole_numbers(data) and lv[1] - lv[0] <= DISCRETE_MAX
            self.bar.axis.setTickSpacing(*((1, 1) if few else (None, None)))
        caption = constant_caption(self.spec, data)
        if caption is None and missing and not np.isfinite(data).any():
            caption = missing
        if caption != self._const:
            # one value everywhere: say it in the title (the bar's ends would be rounding noise)
            self._const = caption
            self._title(self.spec.title + (f": {caption}" if caption else ""))
        # the bar holds the levels (the user may drag them); streaming never auto-levels
        self.image.setImage(display(data, self.levels), autoLevels=False, levels=self.bar.levels())
        if faded is not None and faded.any():
            rgba = np.zeros(faded.shape + (4,), np.uint8)
            rgba[faded] = FADE_RGBA
            self.faded.setImage(rgba, autoLevels=False)
        else:
            self.faded.clear()
        if self.rect is not None:
            self.image.setRect(self.rect)
            self.faded.setRect(self.rect)

    rect = None

    def fit(self, target: int) -> None:
        """Levels refitted to the data now."""
        if self.data is not None:
            self.show(self.data, target, self.version, refit=True)

    def mark(self, pixel: tuple[int, int] | None) -> None:
        if pixel is None or self._shape is None:
            self.marker.setData([], [])
            return
        q = self.pixel_rect(*pixel)
        x0, x1, y0, y1 = q.left(), q.right(), q.top(), q.bottom()
        self.marker.setData([x0, x1, x1, x0, x0], [y0, y0, y1, y1, y0])

    def pixel_at(self, scene_pos) -> tuple[int, int] | None:
        """(row, col) under a scene position, None outside this map's image."""
        if self._shape is None or not self.plot.vb.sceneBoundingRect().contains(scene_pos):
            return None
        p = self.plot.vb.mapSceneToView(scene_pos)
        h, w = self._shape
        c = int(np.floor((p.x() - self.rect.left()) / self.rect.width() * w))
        r = int(np.floor((p.y() - self.rect.top()) / self.rect.height() * h))
        return (r, c) if 0 <= r < h and 0 <= c < w else None


def link_panels(panels: list[MapPanel]) -> None:
    """Zoom and pan one map, and all follow: the same region of the scan in every panel, each
    with its aspect locked. (pyqtgraph's setXLink/setYLink fight the aspect locks of views of
    different sizes and zoom out without end, so the region is copied instead.)"""
    busy = [False]

    def follow(source: MapPanel) -> None:
        if busy[0]:
            return
        busy[0] = True
        try:
            rect = source.plot.vb.viewRect()
            for p in panels:
                if p is not source:
                    p.plot.vb.setRange(rect, padding=0)
        finally:
            busy[0] = False

    for p in panels:
        p.plot.vb.sigRangeChangedManually.connect(lambda *_, src=p: follow(src))


__all__ = ["MapPanel", "MAP_DEFS", "PANEL_DEFS", "link_panels", "snapshot_input", "measured_counts",
           "C_M_PER_S", "VIEW_BACKGROUND"]
