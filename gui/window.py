"""The main window: controls, live maps, pixel inspector, accuracy-versus-time plot, status bar.

The session scans on its own thread; a QTimer pulls ``session.snapshot()`` REFRESH_HZ times a
second (DESIGN.md 4.12) for the status bar and the health indicator, so a slow paint only skips
snapshots. Painting the maps, the accuracy plot and the inspector costs the GUI thread CPU (about
30 ms for 48x48 maps in a 1480x900 window here, mostly Qt's own drawing) and, for pyqtgraph's
Python parts, the GIL that the session's threads (and on the simulated bench the devices' threads)
need. So during a scan they are repainted only as often as keeps the GUI thread within CPU_BUDGET
of one core: the next map paint waits ``cost / CPU_BUDGET`` after the last one, where ``cost`` is
the GUI thread's CPU time between the tick that painted and the next, between REFRESH_HZ and
MIN_REFRESH_HZ. An unchanged map is never set again (``MapPanel.show``'s version).
"""

from __future__ import annotations

import json
import logging
import math
import time
from pathlib import Path

import numpy as np
import pyqtgraph as pg
from PySide6 import QtCore, QtGui, QtWidgets

from spdepth.acq.api import new_run_dir
from spdepth.acq.errors import RequestError
from spdepth.acq.evaluate import evaluate_depth
from spdepth.acq.params import MAX_PIXELS_PER_AXIS, MAX_SURFACES, PARAMS, expand
from spdepth.acq.requests import DEFAULT_METHOD, MAX_TARGET, FileReconRequest, ReplayRequest
from spdepth.gui.health import HealthTracker
from spdepth.acq.flags import AcqFlag
from spdepth.acq.mapdefs import not_estimated, resolve
from spdepth.acq.points import ScanGeometry
from spdepth.gui.maps import C_M_PER_S, PANEL_DEFS, MapPanel, link_panels, snapshot_input
from spdepth.gui.view3d import PointCloudView
from spdepth.gui.pixel_model import pixel_histogram
from spdepth.recon import estimators
from spdepth.gui.sources import (PATH_FIELDS, SETTINGS_KEY, SPEC_OPTIONS, FileJob, Remembered,
                                 ResultView, SessionView, SourceSpec, in_window_words, open_run,
                                 run_kind, spec_fields, spec_param)

log = logging.getLogger(__name__)

REFRESH_HZ = 10
"""Snapshots pulled per second while painting is cheap."""
MIN_REFRESH_HZ = 1
"""Slowest map repaint rate during a scan (at 2 Hz a 60 ms repaint on the loaded 2-core test
machine already took 12% of a core)."""
CPU_BUDGET = 0.05
"""Share of one core the map repaints may use during a scan."""
FIRST_PAINT_COST_S = 0.03
"""Assumed cost of a map repaint until one is measured."""
VIEW3D_STATUS_PERIOD_S = 1.0
"""With the 3D tab shown during a scan, the status bar and plots update at most this often."""
VIEW3D_PERIOD_S = 2.0
"""Shortest interval between two redraws of the 3-D view during a scan."""
HISTORY_PERIOD_S = 0.25
"""Accuracy-plot points are taken at most this often."""
CLOSE_WAIT_S = 15.0
"""Closing during a scan: longest wait for the aborted session to write its files."""
TERMINAL = ("done", "aborted", "failed")
DEFAULT_OUT_ROOT = "~/spdepth-runs"
"""Shown as typed; ``acq.api.new_run_dir`` expands the ``~``."""
STATE_COLOURS = {"idle": "#8a8a8a", "armed": "#1f6fb5", "running": "#1f6fb5", "paused": "#e0a800",
                 "finishing": "#1f6fb5", "done": "#2e9d4a", "aborted": "#e07000",
                 "failed": "#d0342c"}


def _fmt_rate(v: float) -> str:
    if v >= 1e6:
        return f"{v / 1e6:.2f} M"
    if v >= 1e3:
        return f"{v / 1e3:.1f} k"
    return f"{v:.0f} "


def _fmt_eta(s: float | None) -> str:
    if s is None or not math.isfinite(s):
        return "–"
    s = int(round(s))
    return f"{s // 60}:{s % 60:02d}" if s >= 60 else f"{s} s"


def fmt_depth(depth_m: float, sd_m: float) -> str:
    """A depth to the precision its uncertainty gives it: "2.851 m ± 1.4 cm" (the uncertainty to
    two significant digits, the depth to the same decimal place); "–" without a depth."""
    if not math.isfinite(depth_m):
        return "–"
    if not (math.isfinite(sd_m) and sd_m > 0):
        return f"{depth_m:.4f} m"
    sd_cm = sd_m * 100
    cm_places = min(4, max(0, 1 - math.floor(math.log10(sd_cm))))
    return f"{depth_m:.{cm_places + 2}f} m ± {sd_cm:.{cm_places}f} cm"


def fmt_kcps(detections: float, exposure_s: float) -> str:
    """A count over laser time as a rate in kcps, to a hundredth of a detection over that time
    (2.08e-08 kcps is "0.00 kcps" over half a millisecond: the estimate is that fine, no finer)."""
    step_kcps = 0.01 / exposure_s / 1e3
    places = min(6, max(0, math.ceil(-math.log10(step_kcps))))
    return f"{detections / exposure_s / 1e3:.{places}f} kcps"


def readable_span(values: np.ndarray, floor: float) -> tuple[float, float] | None:
    """A plot range about ``values`` when they span less than a tenth of their size (or
    ``floor``), else None (leave the range to the plot)."""
    v = np.asarray(values, dtype=np.float64)
    v = v[np.isfinite(v)]
    if v.size == 0:
        return None
    lo, hi = float(v.min()), float(v.max())
    least = max(0.1 * max(abs(lo), abs(hi)), floor)
    if hi - lo >= least:
        return None
    mid = 0.5 * (lo + hi)
    return mid - least, mid + least


def _pill(label: QtWidgets.QLabel, colour: str) -> None:
    if label.property("pill") == colour:
        return
    label.setProperty("pill", colour)
    label.setStyleSheet(f"QLabel {{ background: {colour}; color: white; border-radius: 8px; "
                        "padding: 1px 8px; font-weight: bold; }")


def _set_text(label: QtWidgets.QLabel, text: str, pill: str | None = None) -> None:
    if label.text() != text:
        label.setText(text)
    if pill is not None:
        _pill(label, pill)


def _path_row(edit: QtWidgets.QLineEdit, browse_slot) -> QtWidgets.QHBoxLayout:
    """A path field with its "…" browse button."""
    browse = QtWidgets.QPushButton("…")
    browse.setFixedWidth(28)
    browse.clicked.connect(browse_slot)
    row = QtWidgets.QHBoxLayout()
    row.addWidget(edit)
    row.addWidget(browse)
    return row


class ControlPanel(QtWidgets.QWidget):
    """Source, scan and estimator settings, and the run buttons. Each setting's control is built
    from its declaration (``acq.params`` through ``gui.sources.SPEC_OPTIONS``): its kind of widget,
    range, unit, "default" text and tooltip (the option's --help), and the source kinds it is
    shown or enabled for. The values are kept per source kind: switching the source shows that
    kind's own (what was last set for it), never another kind's."""

    SOURCE_ROWS = ("scene", "sbr", "seed", "faults", "galvo_port", "tagger_url", "sync_rate_hz",
                   "fov_deg", "recording", "file", "time_unit_ps")
    """The source box: each row shown only for the kinds its option belongs to."""
    SCAN_ROWS = ("size", "mode", "target", "dwell_limit_ms", "method", "pulse_rms_ps", "reflectors")
    """The scan box: each enabled only for the kinds its option belongs to."""

    ATTRS = {"galvo_port": "galvo", "tagger_url": "tagger", "sync_rate_hz": "sync_mhz",
             "fov_deg": "fov", "time_unit_ps": "time_unit", "pulse_rms_ps": "pulse_rms",
             "dwell_limit_ms": "dwell"}
    """The control's attribute where it is not the spec field's name."""
    SYNC_MHZ = 1e6
    """The sync rate is shown in MHz (declared in Hz)."""

    def __init__(self, parent=None):
        super().__init__(parent)
        lay = QtWidgets.QVBoxLayout(self)
        lay.setContentsMargins(6, 6, 6, 6)
        self.widgets: dict[str, QtWidgets.QWidget] = {}
        self._kind = "sim"
        self._per_kind: dict[str, dict] = {}

        src = QtWidgets.QGroupBox("Source")
        f = QtWidgets.QFormLayout(src)
        self.kind = QtWidgets.QComboBox()
        self.kind.addItem("Simulated devices", "sim")
        self.kind.addItem("Real devices", "real")
        self.kind.addItem("Replay a recording", "replay")
        self.kind.addItem("Reconstruct a PTU/.mat file", "file")
        f.addRow("Source", self.kind)
        self._rows = {}
        for name in self.SOURCE_ROWS:
            w, row = self._control(name)
            f.addRow(PARAMS[SPEC_OPTIONS[name]].label, row)
            self._rows[name] = row
        lay.addWidget(src)
        self._src_form = f

        scan = QtWidgets.QGroupBox("Scan")
        g = QtWidgets.QFormLayout(scan)
        for name in self.SCAN_ROWS:
            w, row = self._control(name)
            label = {"size": "Size (W×H)", "dwell_limit_ms": "Dwell limit"}.get(name) or \
                PARAMS[SPEC_OPTIONS[name]].label
            g.addRow(label, row)
        self.out_root = QtWidgets.QLineEdit(DEFAULT_OUT_ROOT)
        self.out_root.setToolTip(expand(PARAMS["--runs-dir"].help))
        out_row = _path_row(self.out_root, self._browse_out)
        g.addRow(PARAMS["--runs-dir"].label, out_row)
        lay.addWidget(scan)
        self._groups = (src, scan)

        buttons = QtWidgets.QGridLayout()
        self.start = QtWidgets.QPushButton("Start")
        self.pause = QtWidgets.QPushButton("Pause")
        self.resume = QtWidgets.QPushButton("Resume")
        self.abort = QtWidgets.QPushButton("Abort")
        self.start.setStyleSheet("font-weight: bold")
        for i, b in enumerate((self.start, self.pause, self.resume, self.abort)):
            buttons.addWidget(b, i // 2, i % 2)
        lay.addLayout(buttons)
        view = QtWidgets.QGroupBox("Maps")
        v = QtWidgets.QHBoxLayout(view)
        self.fit = QtWidgets.QPushButton("Fit levels")
        self.fit.setToolTip("fit every colour bar to the data now (levels otherwise stay put)")
        self.save = QtWidgets.QPushButton("Save maps…")
        self.save.setToolTip("PNG sheet, TIFF stack (tifffile) or npz (spdepth recon's format)")
        v.addWidget(self.fit)
        v.addWidget(self.save)
        lay.addWidget(view)
        self.surface_row = QtWidgets.QWidget()
        sr = QtWidgets.QHBoxLayout(self.surface_row)
        sr.setContentsMargins(6, 0, 6, 0)
        sr.addWidget(QtWidgets.QLabel("Surface shown"))
        self.surface = QtWidgets.QComboBox()
        self.surface.setToolTip("maps of several surfaces per pixel (nearest first): the one the "
                                "depth and uncertainty maps show; the 3D view shows them all")
        sr.addWidget(self.surface, 1)
        lay.addWidget(self.surface_row)
        self.set_surfaces(1)
        lay.addStretch(1)
        self.kind.currentIndexChanged.connect(self._kind_changed)
        self.set_spec(SourceSpec())          # the library's defaults until settings are restored

    # ---- controls from the declarations -----------------------------------------------------
    def _control(self, name: str):
        """The widget of a spec field (and the row holding it, with a browse button for paths),
        made from its declaration."""
        if name == "size":
            side = PARAMS["--size"]
            self.width_px = QtWidgets.QSpinBox(minimum=1, maximum=MAX_PIXELS_PER_AXIS)
            self.height_px = QtWidgets.QSpinBox(minimum=1, maximum=MAX_PIXELS_PER_AXIS)
            row = QtWidgets.QHBoxLayout()
            row.addWidget(self.width_px)
            row.addWidget(QtWidgets.QLabel("×"))
            row.addWidget(self.height_px)
            for w in (self.width_px, self.height_px):
                w.setToolTip(expand(side.help))
            self.widgets[name] = self.width_px
            return self.width_px, row
        p = PARAMS[SPEC_OPTIONS.get(name, "--dwell-limit-ms")]
        if p.kind == "surfaces":
            w = QtWidgets.QComboBox()
            self._fill_surfaces(w, as_recorded=True)
        elif p.choices is not None:
            w = QtWidgets.QComboBox()
            w.setEditable(p.free)
            w.addItems(list(p.choice_list()))
            if name == "method":          # each estimator's own line from the registry
                for i, method in enumerate(p.choice_list()):
                    w.setItemData(i, estimators.get(method).summary, QtCore.Qt.ItemDataRole.ToolTipRole)
        elif p.kind in ("float", "int"):
            w = QtWidgets.QSpinBox() if p.kind == "int" else QtWidgets.QDoubleSpinBox()
            scale = self.SYNC_MHZ if name == "sync_rate_hz" else 1.0
            zero = p.default is None or bool(p.none_label) or name in ("target",)
            low = 0 if zero or p.low is None else p.low / scale
            high = (p.high if p.high is not None else (MAX_TARGET if name == "target" else 1e6 if
                    p.kind == "float" else 2 ** 31 - 1)) / (scale if p.high is not None else 1)
            if p.kind == "float":
                w.setDecimals(3 if p.unit in ("ms", "ps", "Hz") else 2)
                if p.low_open and not zero:
                    low = 10 ** -w.decimals()
            w.setRange(low, high)
            if zero and p.none_label:
                w.setSpecialValueText(p.none_label)
            unit = "MHz" if name == "sync_rate_hz" else {"deg": "°"}.get(p.unit, p.unit)
            if unit:
                w.setSuffix(unit if unit == "°" else f" {unit}")
        else:
            w = QtWidgets.QLineEdit()
            if p.example:
                w.setPlaceholderText(p.example)
        tip = expand(p.help) if name != "method" else estimators.summaries().replace("; ", "\n")
        if name == "dwell_limit_ms":
            tip = "gated: dwell limit per pixel; raster: dwell per pixel and frame"
        w.setToolTip(tip)
        setattr(self, self.ATTRS.get(name, name), w)
        self.widgets[name] = w
        if p.kind == "path":
            browse = {"recording": self._browse_recording, "file": self._browse_file}[name]
            return w, _path_row(w, browse)
        return w, w

    @staticmethod
    def _fill_surfaces(w: QtWidgets.QComboBox, as_recorded: bool) -> None:
        current = w.currentData()
        w.blockSignals(True)
        w.clear()
        if as_recorded:
            w.addItem("as recorded", 0)
        for k in range(1, MAX_SURFACES + 1):
            w.addItem(str(k), k)
        w.addItem("auto", "auto")
        i = w.findData(current)
        w.setCurrentIndex(max(0, i if i >= 0 else w.findData(1)))
        w.blockSignals(False)

    def _value(self, name: str):
        if name == "size":
            return (self.height_px.value(), self.width_px.value())
        w = self.widgets[name]
        if isinstance(w, QtWidgets.QComboBox):
            data = w.currentData()
            return data if data is not None else w.currentText().strip()
        if isinstance(w, QtWidgets.QLineEdit):
            return w.text().strip()
        v = w.value()
        return v * self.SYNC_MHZ if name == "sync_rate_hz" else v

    def _show_value(self, name: str, v) -> None:
        if name == "size":
            self.height_px.setValue(int(v[0]))
            self.width_px.setValue(int(v[1]))
            return
        w = self.widgets[name]
        if isinstance(w, QtWidgets.QComboBox):
            i = w.findData(v) if w.findData(v) >= 0 else w.findText(str(v))
            if i >= 0:
                w.setCurrentIndex(i)
            elif w.isEditable():
                w.setCurrentText(str(v))
        elif isinstance(w, QtWidgets.QLineEdit):
            w.setText(str(v))
        elif v is None:
            w.setValue(w.minimum())      # a declared default of None: the spin box's "default" word
        elif isinstance(w, QtWidgets.QSpinBox):
            w.setValue(int(v))
        else:
            w.setValue(float(v) / (self.SYNC_MHZ if name == "sync_rate_hz" else 1.0))

    def set_surfaces(self, k: int) -> None:
        """Offer surfaces 1..k in the picker (hidden for one)."""
        self.surface.blockSignals(True)
        self.surface.clear()
        self.surface.addItems([f"{i + 1}" + (" (nearest)" if i == 0 else "") for i in range(k)])
        self.surface.blockSignals(False)
        self.surface_row.setVisible(k > 1)

    def _kind_default(self, name: str, kind: str):
        """A control's value for ``kind`` before anything was set for it: the declared default,
        0 (or "") where the kind's default is "as recorded", "from the file" or "estimate"."""
        if name == "dwell_limit_ms":
            return 0.0
        p = spec_param(name, kind)
        if name == "method" and p.default is None:
            return DEFAULT_METHOD        # the estimator picker has no "as recorded"
        if p.default is None:
            return "" if p.kind in ("str", "path") else 0
        return p.default

    def set_remembered(self, per_kind: dict) -> None:
        """Each source kind's stored values (``gui.sources.Remembered.per_kind``), shown when the
        user switches to that kind."""
        self._per_kind = {k: dict(v) for k, v in per_kind.items()}

    def _kind_changed(self) -> None:
        kind = self.kind.currentData()
        old = self._kind
        if kind != old and not getattr(self, "_setting", False):
            # the values of the kind left are kept for it; the new kind shows its own
            self._per_kind[old] = {n: self._value(n) for n in spec_fields(old)}
            mine = self._per_kind.get(kind, {})
            self.target.setMinimum(0)              # the new kind's limits are set below
            self._fill_surfaces(self.reflectors, as_recorded=True)
            for name in spec_fields(kind):
                self._show_value(name, mine.get(name, self._kind_default(name, kind)))
        self._kind = kind
        for name, row in self._rows.items():
            self._src_form.setRowVisible(row, name in spec_fields(kind))
        for name, w in self.widgets.items():       # "default" words as the kind says them
            if isinstance(w, QtWidgets.QAbstractSpinBox) and name not in ("size", "target"):
                label = spec_param(name, kind).none_label
                if label:
                    w.setSpecialValueText(label)
        for name in self.SCAN_ROWS:
            on = name in spec_fields(kind)
            for w in ((self.width_px, self.height_px) if name == "size" else (self.widgets[name],)):
                w.setEnabled(on)
        self.out_root.setEnabled(kind != "file")      # a file's reconstruction writes nothing
        # 0 means "as recorded" (replay) or "all" (file); a scan needs a count: a 0 becomes the
        # declared default rather than a refused start
        scan = kind in ("sim", "real")
        if scan and self.target.value() == 0:
            self.target.setValue(PARAMS["--target"].default)
        self.target.setMinimum(1 if scan else 0)
        self.target.setSpecialValueText(spec_param("target", kind).none_label or "")
        self._fill_surfaces(self.reflectors, as_recorded=kind == "replay")

    def _browse_recording(self) -> None:
        path, _ = QtWidgets.QFileDialog.getOpenFileName(self, "Recording to replay",
                                                        self.recording.text(),
                                                        "PTU recordings (*.ptu);;All files (*)")
        if path:
            self.recording.setText(path)

    def _browse_file(self) -> None:
        path, _ = QtWidgets.QFileDialog.getOpenFileName(
            self, "File to reconstruct", self.file.text(),
            "Photon data (*.ptu *.ht3 *.pt3 *.mat);;All files (*)")
        if path:
            self.file.setText(path)

    def _browse_out(self) -> None:
        path = QtWidgets.QFileDialog.getExistingDirectory(self, "Runs folder", self.out_root.text())
        if path:
            self.out_root.setText(path)

    def spec(self) -> SourceSpec:
        names = [f for f in SourceSpec.__dataclass_fields__ if f not in ("kind", "out_root")]
        return SourceSpec(kind=self.kind.currentData(), out_root=self.out_root.text().strip(),
                          **{n: self._value(n) for n in names})

    def set_spec(self, s: SourceSpec) -> None:
        self._setting = True
        try:
            i = self.kind.findData(s.kind)
            self.kind.setCurrentIndex(max(0, i))
            self._kind = self.kind.currentData()
            self.target.setMinimum(0)              # 0 stays 0 until _kind_changed decides
            self._fill_surfaces(self.reflectors, as_recorded=True)
            # settings shown, not a choice made: the window reconstructs again only on a user's
            # change
            self.method.blockSignals(True)
            for name in SourceSpec.__dataclass_fields__:
                if name in ("kind", "out_root"):
                    continue
                v = getattr(s, name)
                self._show_value(name, 0 if name == "reflectors" and v in (None, "") else v)
            self.method.blockSignals(False)
            if s.out_root:
                self.out_root.setText(s.out_root)
        finally:
            self._setting = False
        self._kind_changed()

    def set_running(self, state: str | None) -> None:
        active = state is not None and state not in TERMINAL
        self.start.setEnabled(not active)
        self.pause.setEnabled(state in ("running", "armed"))
        self.resume.setEnabled(state == "paused")
        self.abort.setEnabled(active and state != "finishing")
        for box in self._groups:
            box.setEnabled(not active)


class Inspector(QtWidgets.QWidget):
    """One pixel: its photon-arrival histogram with the fitted model, and its numbers."""

    def __init__(self, parent=None):
        super().__init__(parent)
        lay = QtWidgets.QVBoxLayout(self)
        lay.setContentsMargins(0, 0, 0, 0)
        self.title = QtWidgets.QLabel("<b>Pixel inspector</b> — hover or click a map pixel")
        lay.addWidget(self.title)
        self.plot = pg.PlotWidget()
        self.plot.setLabel("bottom", "arrival time after sync", units="s")
        self.plot.setLabel("left", "detections per bin")
        self.plot.getAxis("left").enableAutoSIPrefix(False)
        self.plot.addLegend(offset=(-8, 8), labelTextSize="9pt")
        self.hist = self.plot.plot([0, 1], [0], stepMode="center", fillLevel=0,
                                   brush=(70, 110, 200, 120), pen=pg.mkPen("#2a4f9a"),
                                   name="detections")
        self.model = self.plot.plot([], [], pen=pg.mkPen("#d0342c", width=2),
                                    name="fitted model")
        self.surface_lines: list = []
        """One dashed line per fitted surface (K > 1) at its time of flight."""
        self.plot.setMinimumHeight(160)
        lay.addWidget(self.plot, 1)
        self.info = QtWidgets.QLabel()
        self.info.setTextFormat(QtCore.Qt.RichText)
        self.info.setTextInteractionFlags(QtCore.Qt.TextSelectableByMouse)
        self.info.setWordWrap(True)
        lay.addWidget(self.info)
        self.pixel: tuple[int, int] | None = None
        self.last_text = ""

    def clear(self) -> None:
        self.pixel = None
        self.hist.setData([0, 1], [0])
        self.model.setData([], [])
        self.info.setText("")
        self.title.setText("<b>Pixel inspector</b> — hover or click a map pixel")

    def show_pixel(self, info, pixel: tuple[int, int], pinned: bool, truth: float | None = None) -> None:
        """``info``: a ``gui.sources.PixelInfo`` of ``pixel`` (row, col); ``truth``: the true
        depth of a simulated scene there."""
        from spdepth.recon.maps import PixelFlag

        r, c = pixel
        b = info.binning
        tof, bg, sig = info.tof_s, info.background, info.signal
        # the width of a measured response (live several surfaces freeze one) where none is given
        pulse_rms_s = info.pulse_rms_s or (info.irf.rms_s if info.irf is not None else None)
        # display bins about half the pulse RMS wide (raw 40 ps bins hold 0 or 1 photon each)
        rms_bins = (pulse_rms_s or 0.0) / b.bin_width_s
        # the model: every fitted surface's return on the background
        tofs = [x[0] for x in info.surfaces] if info.surfaces else tof
        sigs = [x[2] for x in info.surfaces] if info.surfaces else sig
        ph = pixel_histogram(info.times, b, tof_s=tofs, background=bg, signal=sigs,
                             pulse_rms_s=pulse_rms_s, irf=info.irf,
                             display_bins=int(b.n_bins / max(1.0, rms_bins / 2)))
        self.hist.setData(ph.edges_s, ph.counts)
        if math.isfinite(tof) and pulse_rms_s:
            # the pulse is a sliver of the window: show its neighbourhood (the "A" button: all)
            half = max(3e-9, 10 * pulse_rms_s)
            self.plot.setXRange(tof - half, tof + half, padding=0)
        else:
            self.plot.setXRange(ph.edges_s[0], ph.edges_s[-1], padding=0)
        self.plot.enableAutoRange(axis="y")
        centres = 0.5 * (ph.edges_s[1:] + ph.edges_s[:-1])
        self.model.setData(centres, ph.model) if ph.model is not None else self.model.setData([], [])
        for line in self.surface_lines:
            self.plot.removeItem(line)
        self.surface_lines = []
        for k, (s_tof, *_) in enumerate(info.surfaces):
            colour = ("#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd")[k % 5]
            line = pg.InfiniteLine(s_tof, angle=90, pen=pg.mkPen(colour, width=2,
                                                                 style=QtCore.Qt.DashLine),
                                   label=f"surface {k + 1}", labelOpts={"color": colour})
            self.plot.addItem(line)
            self.surface_lines.append(line)
        if len(info.surfaces) > 1:
            tofs = [t for t, *_ in info.surfaces]
            half = max(3e-9, 10 * (pulse_rms_s or 0))
            self.plot.setXRange(min(tofs) - half, max(tofs) + half, padding=0)
        self.pixel = pixel
        done = info.estimated
        depth = info.depth_m
        sd_cm = info.uncertainty_s * C_M_PER_S / 2 * 100
        n_bins = b.n_bins
        # all surfaces' signal counts against the detections kept (the first alone would not add up)
        sig_all = sum(x[2] for x in info.surfaces) if info.surfaces else sig
        rows = [
            ("depth", fmt_depth(depth, sd_cm / 100)),
            ("time of flight", f"{tof * 1e9:.3f} ns" if math.isfinite(tof) else "–"),
            ("signal", f"{sig:.2f} detections (estimated)" if done else "–"),
            ("background", f"{bg * n_bins:.2f} detections in the window (estimated)"
             if done and math.isfinite(bg) else "–"),
            ("background rate", f"{fmt_kcps(bg * n_bins, info.exposure_s)} over "
             f"{info.exposure_s * 1e3:.3g} ms of laser time"
             if done and math.isfinite(bg) and info.exposure_s > 0 else "–"),
            ("model total", f"{sig_all + bg * n_bins:.2f} = signal + background, against "
             f"{info.n_kept} detections kept" if done and math.isfinite(bg) else "–"),
            ("detections kept", info.kept),
            ("estimate", PixelFlag(info.flag).name.lower().replace("_", " ") if done else "not yet"),
            ("acquisition", info.acquisition),
        ]
        for k, (_t, s_depth, s_sig, s_sd, s_weak) in enumerate(info.surfaces):
            rows.insert(1 + k, (f"surface {k + 1}", f"{fmt_depth(s_depth, s_sd * C_M_PER_S / 2)}, "
                                f"{s_sig:.2f} signal detections"
                                + (" (weak: background could make it)" if s_weak else "")))
        if truth is not None:
            rows.insert(1, ("true depth (simulated)", f"{truth:.4f} m" + (
                f", error {100 * (depth - truth):+.2f} cm" if math.isfinite(depth) else "")))
        self.title.setText(f"<b>Pixel row {r}, col {c}</b>" + (" (pinned: click again to release)"
                                                              if pinned else ""))
        self.last_text = "; ".join(f"{k}: {v}" for k, v in rows)
        self.info.setText("<table>" + "".join(f"<tr><td>{k}&nbsp;&nbsp;</td><td>{v}</td></tr>"
                                              for k, v in rows) + "</table>")


class AccuracyPlot(QtWidgets.QWidget):
    """Median depth uncertainty (and error against the truth of a simulated scene) versus elapsed
    time or detections per pixel, live."""

    def __init__(self, parent=None):
        super().__init__(parent)
        lay = QtWidgets.QVBoxLayout(self)
        lay.setContentsMargins(0, 0, 0, 0)
        top = QtWidgets.QHBoxLayout()
        top.addWidget(QtWidgets.QLabel("<b>Accuracy vs</b>"))
        self.axis = QtWidgets.QComboBox()
        self.axis.addItem("elapsed time", "t")
        self.axis.addItem("detections per pixel", "dpp")
        self.axis.currentIndexChanged.connect(self.redraw)
        top.addWidget(self.axis)
        top.addStretch(1)
        lay.addLayout(top)
        self.plot = pg.PlotWidget()
        self.plot.setLabel("left", "depth uncertainty / error", units="cm")
        self.plot.addLegend(offset=(-8, 8), labelTextSize="9pt")
        self.sigma = self.plot.plot([], [], pen=pg.mkPen("#7a2fb5", width=2), symbol="o",
                                    symbolSize=4, symbolBrush="#7a2fb5",
                                    name="median uncertainty (1σ)")
        self.error = self.plot.plot([], [], pen=pg.mkPen("#d0342c", width=2), symbol="t",
                                    symbolSize=5, symbolBrush="#d0342c",
                                    name="mean |error| vs truth")
        self.plot.setMinimumHeight(140)
        lay.addWidget(self.plot, 1)
        self.history: list[tuple[float, float, float, float]] = []
        self._last_t = -1.0
        self.redraw()

    def clear(self) -> None:
        self.history.clear()
        self._last_t = -1.0
        self.redraw()

    def add(self, snap, truth: np.ndarray | None, pulse_rms_s: float | None = None,
            force: bool = False, draw: bool = True) -> None:
        """Take a point from ``snap`` (at most every HISTORY_PERIOD_S unless ``force``); with
        ``draw`` also redraw (points are cheap, drawing is not: the window draws with the maps).

        The error against ``truth`` is ``acq.evaluate.evaluate_depth``'s MAE over the pixels
        reconstructed so far: a pixel without an estimate counts as a miss (its error is the
        outlier threshold, 3 pulse widths of ``pulse_rms_s``), as in ``spdepth demo`` and the
        bench, so leaving hard pixels out never lowers the curve."""
        if not force and snap.elapsed_s - self._last_t < HISTORY_PERIOD_S:
            if draw and self._stale:
                self.redraw()
            return
        sd = snap.uncertainty_s[np.isfinite(snap.uncertainty_s)]
        if sd.size == 0:
            return
        self._last_t = snap.elapsed_s
        med_cm = float(np.median(sd)) * C_M_PER_S / 2 * 100
        err_cm = math.nan
        if truth is not None and truth.shape == snap.depth_m.shape and pulse_rms_s and \
                snap.reconstructed is not None:
            seen = snap.reconstructed & np.isfinite(truth)
            if seen.any():
                # k = 1 everywhere: every pixel with truth counts (the oracle is not drawn here)
                err_cm = evaluate_depth(snap.depth_m[seen], truth[seen], 1.0,
                                        pulse_rms_s).mae_m * 100
        dpp = snap.detections / max(1, snap.pixels_total)
        self.history.append((snap.elapsed_s, dpp, med_cm, err_cm))
        self._stale = True
        if draw:
            self.redraw()

    _stale = False

    def redraw(self) -> None:
        self._stale = False
        by_time = self.axis.currentData() == "t"
        self.plot.setLabel("bottom", "elapsed scan time" if by_time else "detections per pixel",
                           units="s" if by_time else "")
        if not self.history:
            self.sigma.setData([], [])
            self.error.setData([], [])
            return
        a = np.array(self.history)
        x = a[:, 0] if by_time else a[:, 1]
        self.sigma.setData(x, a[:, 2])
        ok = np.isfinite(a[:, 3])
        self.error.setData(x[ok], a[ok, 3])
        # one point, or a flat line: pyqtgraph would zoom into a span of rounding noise and
        # label its axis "1.453297857435"; give each axis a span worth reading instead
        y = a[:, 2:4][np.isfinite(a[:, 2:4])]
        for axis, values, floor in (("x", x, 0.5), ("y", y, 0.05)):
            span = readable_span(values, floor)
            if span is None:
                self.plot.enableAutoRange(axis=axis)
            else:
                (self.plot.setXRange if axis == "x" else self.plot.setYRange)(*span, padding=0)


class MainWindow(QtWidgets.QMainWindow):
    """The spdepth window. ``settings``: a QSettings (tests pass their own file)."""

    scan_ended = QtCore.Signal(str)
    """Emitted once per run with the final state (done, aborted, failed), after the last paint."""

    def __init__(self, settings: QtCore.QSettings | None = None, parent=None):
        super().__init__(parent)
        self.setWindowTitle("spdepth — single-photon depth imaging")
        self.settings = settings if settings is not None else QtCore.QSettings("spdepth", "spdepth")
        self.run = None
        self.job: FileJob | None = None
        self.view = None
        """What the inspector and Save read: a ``SessionView`` or a ``ResultView``."""
        self.snap = None
        self.health = HealthTracker()
        self._ended_emitted = False
        self._pinned = False
        self._hover: tuple[int, int] | None = None
        self._inspect_key = None
        self._last_sig = None
        self._n_bins = 1

        self.controls = ControlPanel()
        scroll = QtWidgets.QScrollArea()
        scroll.setWidget(self.controls)
        scroll.setWidgetResizable(True)
        # the file source's longer labels must not bring a sideways scroll bar: fields shrink
        scroll.setHorizontalScrollBarPolicy(QtCore.Qt.ScrollBarAlwaysOff)
        scroll.setMinimumWidth(self.controls.sizeHint().width() + 20)

        self._build_banner()
        centre = self._build_centre()

        self.inspector = Inspector()
        self.accuracy = AccuracyPlot()
        right = QtWidgets.QSplitter(QtCore.Qt.Vertical)
        right.addWidget(self.inspector)
        right.addWidget(self.accuracy)
        right.setStretchFactor(0, 3)
        right.setStretchFactor(1, 2)
        self.splitter = QtWidgets.QSplitter(QtCore.Qt.Horizontal)
        self.splitter.addWidget(scroll)
        self.splitter.addWidget(centre)
        self.splitter.addWidget(right)
        self.splitter.setStretchFactor(0, 0)
        self.splitter.setStretchFactor(1, 3)
        self.splitter.setStretchFactor(2, 2)
        self.setCentralWidget(self.splitter)
        for w in (self.maps_view, self.inspector.plot, self.accuracy.plot):
            w.setBackground("w")

        self._build_status_bar()

        c = self.controls
        c.start.clicked.connect(lambda: self.start_run())
        c.pause.clicked.connect(self.pause)
        c.resume.clicked.connect(self.resume)
        c.abort.clicked.connect(self.abort)
        c.fit.clicked.connect(self.fit_levels)
        c.method.currentTextChanged.connect(self._estimator_changed)
        c.surface.currentIndexChanged.connect(lambda _: self.fit_levels())
        c.save.clicked.connect(self._save_dialog)
        c.set_running(None)

        self.timer = QtCore.QTimer(self)
        self.timer.setInterval(int(1000 / REFRESH_HZ))
        self.timer.timeout.connect(self._tick)
        self.timer.start()
        self._tick_cpu = time.thread_time()
        self._painted_last_tick = False
        self.paint_cost_s = FIRST_PAINT_COST_S
        """GUI-thread CPU of one map repaint, measured (a running average)."""
        self._maps_due = 0.0
        self._last_3d = 0.0
        self._status_due = 0.0
        self._maps_stale = False
        self._restore_settings()
        # Ctrl+Q / Ctrl+W close the window (a running scan is aborted, its recording kept)
        self.close_shortcut = QtGui.QShortcut(self)
        self.close_shortcut.setKeys(close_keys())
        self.close_shortcut.setContext(QtCore.Qt.ApplicationShortcut)
        self.close_shortcut.activated.connect(self.close)

    def _build_banner(self) -> None:
        """The banner of errors above the maps, hidden until one is shown."""
        self.banner = QtWidgets.QFrame()
        self.banner.setStyleSheet("QFrame { background: #fbe3e1; border: 1px solid #d0342c; "
                                  "border-radius: 4px; } QLabel { border: none; color: #7a1010; }")
        bl = QtWidgets.QHBoxLayout(self.banner)
        bl.setContentsMargins(8, 4, 4, 4)
        self.banner_text = QtWidgets.QLabel()
        self.banner_text.setWordWrap(True)
        self.banner_text.setSizePolicy(QtWidgets.QSizePolicy.Ignored, QtWidgets.QSizePolicy.Preferred)
        self.banner_text.setTextInteractionFlags(QtCore.Qt.TextSelectableByMouse)
        dismiss = QtWidgets.QToolButton(text="✕")
        dismiss.setAutoRaise(True)
        dismiss.clicked.connect(self.banner.hide)
        bl.addWidget(self.banner_text, 1)
        bl.addWidget(dismiss)
        self.banner.hide()

    def _build_centre(self) -> QtWidgets.QWidget:
        """The run's title, the map panels and the 3D view (tabs), under the banner."""
        self.run_label = QtWidgets.QLabel("No scan yet: choose a source and press Start.")
        self.run_label.setStyleSheet("font-size: 11pt; font-weight: bold; padding: 2px 4px;")
        # a long run folder must not widen the window: the label is clipped, the tooltip has it all
        self.run_label.setSizePolicy(QtWidgets.QSizePolicy.Ignored, QtWidgets.QSizePolicy.Preferred)
        self.run_label.setMinimumWidth(50)
        self.run_label.setWordWrap(True)       # a file's summary goes on two lines, not cut
        self.maps_view = pg.GraphicsLayoutWidget()
        self.maps_view.setBackground("w")
        self.maps_view.ci.setSpacing(4)
        self.panels = [MapPanel(self.maps_view.ci, spec, i // 2, i % 2)
                       for i, spec in enumerate(PANEL_DEFS)]
        link_panels(self.panels)
        for i in range(2):                 # equal cells: the same region shows at the same scale
            self.maps_view.ci.layout.setColumnStretchFactor(i, 1)
        for i in range(3):
            self.maps_view.ci.layout.setRowStretchFactor(i, 1)
        self.view3d = PointCloudView()
        self.views = QtWidgets.QTabWidget()
        self.views.addTab(self.maps_view, "Maps")
        self.views.addTab(self.view3d, "3D")
        self.views.currentChanged.connect(self._view_changed)
        self.maps_view.scene().sigMouseMoved.connect(self._mouse_moved)
        self.maps_view.scene().sigMouseClicked.connect(self._mouse_clicked)
        centre = QtWidgets.QWidget()
        cl = QtWidgets.QVBoxLayout(centre)
        cl.setContentsMargins(4, 4, 4, 4)
        cl.addWidget(self.banner)
        cl.addWidget(self.run_label)
        cl.addWidget(self.views, 1)
        return centre

    def _build_status_bar(self) -> None:
        """State, rate, progress, ETA, losses and the devices' health in the status bar."""
        sb = self.statusBar()
        self.state_label = QtWidgets.QLabel("idle")
        self.rate_label = QtWidgets.QLabel("– det/s")
        self.progress = QtWidgets.QProgressBar()
        self.progress.setMaximumWidth(160)
        self.progress.setFormat("%v / %m px")
        self.eta_label = QtWidgets.QLabel("ETA –")
        self.lost_label = QtWidgets.QLabel("lost 0")
        self.health_label = QtWidgets.QLabel("● no source")
        for w in (self.state_label, self.rate_label, self.progress, self.eta_label, self.lost_label,
                  self.health_label):
            sb.addPermanentWidget(w)
        _pill(self.state_label, STATE_COLOURS["idle"])
        _pill(self.health_label, "#8a8a8a")

    def panel(self, key: str) -> MapPanel:
        """The map panel showing ``acq.mapdefs`` key (depth, uncertainty, background or
        background_rate, sbr, counts), or in that place."""
        return next(p for p in self.panels if key in (p.spec.key, p.place.key))

    def show_view(self, which: str) -> None:
        """Show the "maps" or the "3d" tab."""
        self.views.setCurrentIndex(1 if which == "3d" else 0)

    # ---- settings ------------------------------------------------------------------------------
    def _restore_settings(self) -> None:
        """The controls as last run, per source kind (``gui.sources.Remembered``): each stored
        value checked against its declaration; one that no longer validates gives way to its
        default, with one line in the status bar."""
        self.remembered = Remembered.load(self.settings.value(SETTINGS_KEY),
                                          self.settings.value("source"))
        self.controls.set_remembered(self.remembered.per_kind)
        self.controls.set_spec(self.remembered.spec())
        self.show_notes(self.remembered.notes.get(self.remembered.kind, []))
        # the window's own state, as Qt saved it: anything else (a hand-edited file) is ignored
        geom = self.settings.value("geometry")
        if isinstance(geom, (QtCore.QByteArray, bytes)):
            self.restore_fitting_geometry(geom)
        state = self.settings.value("splitter")
        if isinstance(state, (QtCore.QByteArray, bytes)):
            self.splitter.restoreState(state)

    def show_notes(self, notes: list[str]) -> None:
        """Notes about the settings (stored values that no longer validated): one status-bar
        line, and the log."""
        for note in notes:
            log.warning("%s", note)
        if notes:
            self.statusBar().showMessage("; ".join(notes), 15000)

    def restore_fitting_geometry(self, geom) -> bool:
        """Use a remembered window geometry only if it fits a screen here and holds the window's
        contents (one saved on a larger monitor, or squeezed, would clip the right column)."""
        before = self.saveGeometry()
        if not self.restoreGeometry(geom):
            return False
        screen = QtGui.QGuiApplication.screenAt(self.frameGeometry().center()) or \
            QtGui.QGuiApplication.primaryScreen()
        hint = self.minimumSizeHint()
        if screen is not None and screen.availableGeometry().contains(self.frameGeometry()) and \
                self.width() >= hint.width() and self.height() >= hint.height():
            return True
        self.restoreGeometry(before)
        return False

    def save_settings(self, worked: bool = False) -> None:
        """Remember the window (geometry, splitter) and, when ``worked`` (a run just started, or
        a file was read, with the controls), the controls of that source kind: paths absolute.
        Values typed but never run are not kept, so they cannot change a later run (a command
        line that names a source starts from that kind's remembered values)."""
        if worked:
            spec = self.controls.spec()
            paths = {k: str(Path(getattr(spec, k)).expanduser().resolve())
                     for k in PATH_FIELDS if getattr(spec, k)}
            import dataclasses

            self.settings.setValue(SETTINGS_KEY, self.remembered.store(
                dataclasses.replace(spec, **paths)))
            self.controls.set_remembered(self.remembered.per_kind)
        # a headless run's screen is Qt's invented one (offscreen: 800x800): its geometry would
        # squeeze the window on a real screen, so it is not remembered
        if QtGui.QGuiApplication.platformName() not in ("offscreen", "minimal"):
            self.settings.setValue("geometry", self.saveGeometry())
        self.settings.setValue("splitter", self.splitter.saveState())
        self.settings.sync()

    # ---- errors --------------------------------------------------------------------------------
    def show_error(self, text: str) -> None:
        self.banner_text.setText(text)
        self.banner.show()
        log.warning("%s", text)

    # ---- runs ----------------------------------------------------------------------------------
    @property
    def session(self):
        return self.run.session if self.run is not None else None

    def running(self) -> bool:
        if self.job is not None and not self.job.done:
            return True
        return self.run is not None and not self.run.session.ended.is_set()

    def start_run(self, what=None, out_dir="auto") -> bool:
        """Start ``what``: a ``SourceSpec`` (shown in the controls, then made a request), a
        request (``acq.requests`` scan, replay or file reconstruction: run as given, the controls
        show what they can of it) or None (the controls' settings). Errors go to the banner
        (returns False). out_dir: "auto" (a new locked folder under the runs folder, released
        when the run ends), a path (the caller's folder), or None (in memory)."""
        if self.running():
            self.show_error("A scan is running: abort it first.")
            return False
        self._release_run()
        self.banner.hide()
        try:
            if what is None or isinstance(what, SourceSpec):
                if what is not None:
                    self.controls.set_spec(what)
                request = self.controls.spec().to_request()
            else:
                request = what
                self.controls.set_spec(SourceSpec.from_request(request, self.controls.spec()))
        except RequestError as exc:
            self.show_error(f"Could not start: {in_window_words(str(exc))}")
            self.controls.set_running(None)
            return False
        if isinstance(request, FileReconRequest):
            return self._start_file(request)
        try:
            if out_dir == "auto":
                root = self.controls.out_root.text().strip() or DEFAULT_OUT_ROOT
                out_dir = new_run_dir(root, run_kind(request))
            run = open_run(request, out_dir)
        except Exception as exc:  # noqa: BLE001 - every failure to start is shown, window stays usable
            self.show_error(f"Could not start: {exc}")
            self.controls.set_running(None)
            return False
        self.run = run
        self.view = SessionView(run.session)
        if isinstance(request, ReplayRequest):
            # the recorded plan in the (disabled) scan controls, not the last scan's settings
            plan, c = run.session.plan, self.controls
            c.height_px.setValue(plan.shape[0])
            c.width_px.setValue(plan.shape[1])
            c.mode.setCurrentText(plan.mode)
        self.accuracy.show()
        self.save_settings(worked=True)
        self.health = HealthTracker(live=not isinstance(run.request, ReplayRequest))
        self._n_bins = run.session.live_recon.pixel_settings.binning.n_bins
        # the run's own folder name; the whole path is in the tooltip (and in run.json)
        where = f" — files in …/{run.out_dir.name}/" if run.out_dir else ""
        self._target = run.session.plan.target
        tof = run.session.live_recon.tof_s
        self.controls.set_surfaces(tof.shape[0] if tof.ndim == 3 else 1)
        self._new_run(f"{run.label}{where}", str(run.out_dir or ""),
                      ScanGeometry.from_plan(run.session.plan), run.session.plan.shape)
        h, w = run.session.plan.shape
        self.inspect((h // 2, w // 2), pin=False)     # something to look at until the user points
        # the first paint of a run (new ranges, axes, labels: the whole window) is the dearest:
        # done before the scan starts, it does not take CPU and GIL from the scan's first second
        self.refresh()
        self.repaint()
        try:
            run.session.start()
        except Exception as exc:  # noqa: BLE001 - shown, window stays usable
            run.close(discard=True)
            self.run = None
            self.view = None
            self.show_error(f"Could not start: {exc}")
            self.controls.set_running(None)
            return False
        # what is wrong with a recording but still replays (cut, no event log): said once, here
        self.show_notes(list(getattr(run.session.source, "warnings", ())))
        self._maps_due = time.monotonic() + 1.0 / REFRESH_HZ
        return True

    def _new_run(self, label: str, tooltip: str, geometry=None, shape=(1, 1)) -> None:
        self._ended_emitted = False
        self._last_sig = None
        self._inspect_key = None
        self._pinned = False
        self._hover = None
        for p in self.panels:
            p.reset()
        self.inspector.clear()
        self.accuracy.clear()
        self.view3d.reset(geometry)
        for p in self.panels:
            p.set_geometry(geometry, shape)
        self.run_label.setText(label)
        self.run_label.setToolTip(tooltip)

    def _start_file(self, request: FileReconRequest) -> bool:
        """Reconstruct a PTU/.mat file on a worker thread (the timer polls it)."""
        self.run = None
        self.view = None
        self.snap = None
        self.job = FileJob(request)
        self.health = HealthTracker(live=False)
        self._new_run(f"{request.label()} — reconstructing…", request.input)
        self.view3d.reset(None)
        self.accuracy.hide()                   # accuracy over scan time: a file has no scan
        self.state_label.setText("reconstructing")
        _pill(self.state_label, STATE_COLOURS["running"])
        self.health_label.setText("● file")
        _pill(self.health_label, "#8a8a8a")
        self.controls.set_running("running")
        self.controls.pause.setEnabled(False)
        self.controls.abort.setEnabled(False)      # a reconstruction cannot be stopped midway
        return True

    def _poll_job(self) -> None:
        job = self.job
        if not job.done:
            done, total = job.progress
            if total:
                self.progress.setMaximum(total)
                self.progress.setValue(done)
            self.eta_label.setText(f"{time.monotonic() - job.started_at:.0f} s")
            return
        self.job = None
        self.controls.set_running(None)
        label = job.request.label()
        if job.error is not None or job.result is None:
            exc = job.error
            self.state_label.setText("failed")
            _pill(self.state_label, STATE_COLOURS["failed"])
            self.run_label.setText(f"{label} — failed")
            self.show_error(f"Could not reconstruct {Path(job.request.input).name}: {exc}")
            self.scan_ended.emit("failed")
            return
        res = job.result
        self.save_settings(worked=True)          # the file was read: its path is worth keeping
        view = self.view = ResultView(res)
        self._n_bins = res.binning.n_bins
        snap = self.snap = view.snapshot()
        target = view.target or max(1, int(np.max(res.maps.photons)))
        self._target = target
        from spdepth.acq.points import geometry_of

        geometry = geometry_of(res.maps)
        k = int(np.asarray(res.maps.depth_m).shape[0]) if np.ndim(res.maps.depth_m) == 3 else 1
        self.controls.set_surfaces(k)
        self.view3d.reset(geometry)
        for p in self.panels:
            p.set_geometry(geometry, view.shape)
        self._paint_maps(snap, target, refit=True)
        h, w = view.shape
        self.state_label.setText("done")
        _pill(self.state_label, STATE_COLOURS["done"])
        self.rate_label.setText(f"{snap.detections:,} det")
        self.progress.setMaximum(h * w)
        self.progress.setValue(h * w)
        self.eta_label.setText(f"read {res.read_s:.1f} s, recon {res.recon_s:.1f} s")
        self.lost_label.setText("")
        b = res.binning
        pulse = f", pulse {res.pulse_rms_s * 1e12:.0f} ps RMS" if res.pulse_rms_s else ""
        self.run_label.setText(f"{label} — {w}×{h}, {snap.detections:,} detections, "
                               f"window {b.window_start * b.time_unit_s * 1e9:.1f}–"
                               f"{b.window_stop * b.time_unit_s * 1e9:.1f} ns{pulse}")
        # where the pulse came from is a sentence: in the tooltip, with the file's path, and so are
        # the notes (what the file held and what was used, the pulse model's fit), which the
        # status bar shows for a while and cuts at its width
        source = res.maps.settings.get("pulse_source", "")
        self.run_label.setToolTip(job.request.input + (f"\npulse: {source}" if source else "")
                                  + "".join(f"\n\n{note}" for note in res.notes))
        if res.notes:
            n = len(res.notes)
            self.statusBar().showMessage(f"{n} note{'s' if n > 1 else ''}, whole in the title's tooltip: "
                                         + "; ".join(res.notes), 15000)
        self.inspect((h // 2, w // 2), pin=False)
        self.scan_ended.emit("done")

    def _release_run(self) -> None:
        if self.run is not None and self.run.session.ended.is_set():
            self.run.close()

    def pause(self) -> None:
        self._command("pause")

    def resume(self) -> None:
        self._command("resume")

    def abort(self) -> None:
        self._command("abort")

    def _command(self, name: str) -> None:
        if self.session is None:
            return
        try:
            getattr(self.session, name)()
        except Exception as exc:  # noqa: BLE001 - e.g. SessionStateError: shown, not raised
            self.statusBar().showMessage(f"{name}: {exc}", 5000)
        self.refresh()

    # ---- the timer -----------------------------------------------------------------------------
    def _tick(self) -> None:
        """The timer: the status at every tick; the maps when the CPU budget allows (always once
        the scan has ended). The GUI thread's CPU time from a tick that repainted the maps to the
        next (Qt paints in between) is what a repaint costs."""
        cpu, now = time.thread_time(), time.monotonic()
        if self.running() and self.views.currentWidget() is self.view3d and \
                now < self._status_due:
            # with the 3D tab shown Qt composites the whole window through OpenGL at every
            # update (Mesa: in software, on threads the CPU budget does not see): fewer updates
            return
        self._status_due = now + VIEW3D_STATUS_PERIOD_S
        if self._painted_last_tick:
            self.paint_cost_s = 0.7 * self.paint_cost_s + 0.3 * (cpu - self._tick_cpu)
        paint = not self.running() or now >= self._maps_due
        self._tick_cpu = cpu
        self._painted_last_tick = self.refresh(maps=paint)
        if self._painted_last_tick:
            gap = min(1.0 / MIN_REFRESH_HZ, max(1.0 / REFRESH_HZ, self.paint_cost_s / CPU_BUDGET))
            self._maps_due = now + gap

    def refresh(self, maps: bool = True) -> bool:
        """Pull the latest snapshot and show it: the status bar, and with ``maps`` the maps, the
        accuracy plot and the inspector where they changed. Returns whether a map was set."""
        if self.job is not None:
            self._poll_job()
            return False
        run = self.run
        if run is None:
            return False
        snap = run.session.snapshot(faults_since_s=self.health.last_elapsed_s)
        self.snap = snap
        target = run.session.plan.target
        # what changed: the estimate maps only when the reconstruction finished more pixels, the
        # detections map when detections arrived; an unchanged map is not set again
        versions = {"estimate": (snap.state, snap.pixels_final - snap.recon_lag),
                    "counts": (snap.state, snap.detections, snap.pixels_final)}
        painted = False
        if maps and versions != self._last_sig:
            self._last_sig = versions
            painted = self._paint_maps(snap, target, versions)
        # a point per HISTORY_PERIOD_S whatever the repaint rate; drawn with the maps
        self.accuracy.add(snap, run.truth_depth_m, run.session.live_recon.pixel_settings.pulse_rms_s,
                          force=snap.state in TERMINAL and painted, draw=painted)
        self._status(snap)
        if maps:
            self._update_inspector()
        self.controls.set_running(snap.state)
        if snap.state in TERMINAL and not self._ended_emitted and maps:
            self._ended_emitted = True
            self._on_end(snap)
        return painted

    def _paint_maps(self, snap, target: int, versions=None, refit: bool = False) -> bool:
        """Set the maps (those whose version changed) and the 3-D view if it is shown; returns
        whether anything was set."""
        painted = False
        if self.running() and self.views.currentWidget() is not self.maps_view:
            # hidden maps are set when their tab is shown again (each set renders an image)
            self._maps_stale = True
            self._paint_3d()
            return False
        self._maps_stale = False
        mi = snapshot_input(snap, self._n_bins, target)
        surface = max(0, self.controls.surface.currentIndex())
        method = self._shown_method()
        for p in self.panels:
            v = None if versions is None else versions["counts" if p.spec.key == "counts"
                                                       else "estimate"]
            if v is None or v != p.version or refit:
                spec, data = resolve(p.place, mi)
                p.set_spec(spec)
                if data is None:                 # an optional map these maps do not have
                    p.plot.setVisible(False)
                    continue
                p.plot.setVisible(True)
                p.show(data, target, version=v, refit=refit, surface=surface, weak=snap.weak,
                       missing=not_estimated(spec, method))
                painted = True
        if painted:
            self._paint_3d()
        return painted

    def _shown_method(self) -> str | None:
        """The estimator of the maps shown: the file's or the session's (None: neither)."""
        if isinstance(self.view, ResultView):
            return self.view.result.request.method
        if self.run is not None:
            return self.run.session.live_recon.requested.method
        return None

    def _estimator_changed(self, method: str) -> None:
        """A new estimator chosen after a run: the same detections reconstructed again with it
        (a file, or the finished scan's recording read as a file); a run kept in memory has no
        recording to read again, and the status bar says so."""
        if self.running() or self._in_set_spec or not method:
            return
        request = None
        if isinstance(self.view, ResultView):
            if self.view.result.request.method != method:
                import dataclasses

                request = dataclasses.replace(self.view.result.request, method=method)
        elif self.run is not None and self.run.session.ended.is_set():
            if self.run.session.live_recon.requested.method == method:
                return
            rec = self.run.out_dir / "recording.ptu" if self.run.out_dir is not None else None
            if rec is not None and rec.is_file():
                request = FileReconRequest(input=str(rec), method=method)
            else:
                self.statusBar().showMessage(
                    f"{method} applies to the next run: this run kept no recording to "
                    f"reconstruct again", 10000)
        if request is not None:
            self._in_set_spec = True
            try:
                self.start_run(request)
            finally:
                self._in_set_spec = False

    _in_set_spec = False

    def _view_changed(self, _index: int) -> None:
        if self.views.currentWidget() is self.maps_view and self._maps_stale and self.snap is not None:
            target = self.run.session.plan.target if self.run is not None else 1
            self._last_sig = None
            self._paint_maps(self.snap, target)
        self._last_3d = 0.0
        self._paint_3d()

    def _paint_3d(self) -> None:
        """The point cloud, only while its tab is shown (hidden, it costs nothing)."""
        if self.snap is None or self.views.currentWidget() is not self.view3d:
            return
        now = time.monotonic()
        # software OpenGL (Mesa) renders on threads of its own that the maps' CPU budget does not
        # see: during a scan the cloud is redrawn at most every VIEW3D_PERIOD_S
        if self.running() and now - self._last_3d < VIEW3D_PERIOD_S:
            return
        self._last_3d = now
        self.view3d.set_maps(self.snap.depth_m, self.snap.signal, getattr(self.snap, "weak", None))

    def _status(self, snap) -> None:
        # only what changed: each setText/setStyleSheet re-lays out and repaints the status bar
        h = self.health.update(snap)
        _set_text(self.state_label, snap.state, STATE_COLOURS.get(snap.state, "#8a8a8a"))
        # a rate and an ETA only while detections come: the session's rate is over its running
        # time, pauses included, so paused or ended it would be a rate nobody measured
        live = snap.state in ("armed", "running", "finishing")
        _set_text(self.rate_label, f"{_fmt_rate(snap.detections_per_s)}det/s" if live
                  else f"{snap.detections:,} det")
        if self.progress.maximum() != snap.pixels_total:
            self.progress.setMaximum(snap.pixels_total)
        # progress counts pixels complete (an aborted scan's incomplete pixels are not "done")
        complete = int(np.count_nonzero(snap.acq_flags == AcqFlag.COMPLETE))
        if self.progress.value() != complete:
            self.progress.setValue(complete)
        if live:
            eta = f"ETA {_fmt_eta(snap.eta_s)}"
        elif snap.state == "paused":
            eta = "ETA – (paused)"
        else:
            took = snap.elapsed_s      # what the accuracy plot's time axis counts too
            eta = f"{snap.state} after " + (f"{took:.1f} s" if took < 10 else _fmt_eta(took))
        _set_text(self.eta_label, eta)
        _set_text(self.lost_label, f"lost {snap.lost_records} rec / {snap.lost_spans} spans")
        _set_text(self.health_label, f"● {h.text}", h.colour)
        if self.health_label.toolTip() != (h.tooltip or h.text):
            self.health_label.setToolTip(h.tooltip or h.text)

    def _on_end(self, snap) -> None:
        self._write_run_pictures()
        self.run.close()          # instruments; the session's files are already written
        self.fit_levels()
        if snap.state == "failed":
            self.show_error(f"Scan failed: {snap.error or 'unknown error'}. What was recorded is "
                            f"kept{' in ' + str(self.run.out_dir) if self.run.out_dir else ''}.")
        self.scan_ended.emit(snap.state)

    def _write_run_pictures(self) -> None:
        """The run folder gets what `spdepth scan` writes beside the session's files: maps.png
        and points.ply."""
        if self.run.out_dir is None or not Path(self.run.out_dir).is_dir():
            return
        from spdepth.acq.api import finish_session

        try:
            finish_session(self.run.session, self.run.out_dir, title=self.run.label)
        except Exception as exc:  # noqa: BLE001 - the maps are still shown; say what failed
            self.show_error(f"Could not write maps.png/points.ply: {exc}")

    def fit_levels(self) -> None:
        """Refit every map's levels to what it shows now."""
        target = max(1, self.view.target) if self.view is not None else 1
        if isinstance(self.view, ResultView) and not self.view.target:
            target = max(1, int(np.max(self.view.result.maps.photons)))
        if self.snap is not None:
            self._paint_maps(self.snap, target, refit=True)

    # ---- the inspector -------------------------------------------------------------------------
    def _pixel_at(self, scene_pos):
        for p in self.panels:
            px = p.pixel_at(scene_pos)
            if px is not None:
                return px
        return None

    def _mouse_moved(self, pos) -> None:
        if self._pinned:
            return
        px = self._pixel_at(pos)
        if px is not None:
            self.inspect(px)

    def _mouse_clicked(self, ev) -> None:
        px = self._pixel_at(ev.scenePos())
        if px is None:
            return
        if self._pinned and px == self._hover:
            self._pinned = False
        else:
            self.inspect(px, pin=True)

    def inspect(self, pixel: tuple[int, int], pin: bool | None = None) -> None:
        """Show ``pixel`` (row, col) in the inspector; ``pin`` keeps it there while hovering."""
        if pin is not None:
            self._pinned = pin
        self._hover = pixel
        self._inspect_key = None
        self._update_inspector()

    def _update_inspector(self) -> None:
        view = self.view
        if view is None or self._hover is None:
            return
        r, c = self._hover
        h, w = view.shape
        if not (0 <= r < h and 0 <= c < w):
            return
        key = (self._hover, self._pinned, view.key(r, c))
        if key == self._inspect_key:
            return
        self._inspect_key = key
        for p in self.panels:
            p.mark(self._hover)
        truth = None
        if self.run is not None and self.run.truth_depth_m is not None and \
                self.run.truth_depth_m.shape == (h, w):
            truth = float(self.run.truth_depth_m[r, c])
        self.inspector.show_pixel(view.pixel(r, c), self._hover, self._pinned, truth)

    # ---- files ---------------------------------------------------------------------------------
    def save_maps(self, path: str | Path) -> Path:
        """Write the current maps: .png (a sheet with colour bars), .tif/.tiff (float32 stack
        depth_m, background, photons, depth_sd_m with the settings as JSON; with several surfaces a
        depth_m_k and depth_sd_m_k per surface), .npz (``recon``'s)."""
        from spdepth.recon.errors import InputError

        if self.view is None:
            raise InputError("no maps yet: run a scan first")
        path = Path(path)
        maps = self.view.maps()
        suffix = path.suffix.lower()
        if suffix == ".npz":
            maps.save_npz(path)
        elif suffix in (".tif", ".tiff"):
            import tifffile

            # several surfaces: a depth and a depth_sd channel per surface (depth_m_1, ...)
            depth = np.asarray(maps.depth_m).reshape((-1,) + maps.flags.shape)
            sd = np.asarray(maps.uncertainty_s).reshape(depth.shape) * C_M_PER_S / 2
            k = depth.shape[0]
            each = lambda name: [name] if k == 1 else [f"{name}_{i + 1}" for i in range(k)]  # noqa: E731
            names = each("depth_m") + ["background", "photons"] + each("depth_sd_m")
            stack = np.concatenate([depth, [maps.background, maps.photons.astype(np.float64)],
                                    sd]).astype(np.float32)
            tifffile.imwrite(path, stack, photometric="minisblack",
                             description=json.dumps({"channels": names,
                                                     "settings": maps.settings}, default=str),
                             metadata=None)
        elif suffix == ".png":
            from spdepth.acq.report import render_maps_png

            mi = None if self.snap is None else snapshot_input(self.snap, 1, 0)
            same = mi is not None and mi.counts.shape == maps.flags.shape
            render_maps_png(path, maps, title=self.run_label.text().split(" — ")[0],
                            counts=mi.counts if same else None,
                            exposure_s=mi.exposure_s if same else None)
        elif suffix in (".ply", ".las"):
            from spdepth.acq.points import geometry_of, write_points

            geometry = geometry_of(maps)
            if geometry is None:
                raise InputError("these maps hold no scan geometry (a file needs its field of "
                                 "view): no points to write")
            write_points(maps, geometry, **{suffix[1:]: path})
        else:
            raise InputError(f"save maps: {path.name} must end in .png, .tif, .tiff, .npz, .ply "
                             f"or .las")
        return path

    def _save_dialog(self) -> None:
        if self.view is None:
            self.show_error("No maps to save yet: run a scan first.")
            return
        folder = self.run.out_dir if self.run is not None else None
        start = str((folder or Path.cwd()) / "maps.png")
        path, _ = QtWidgets.QFileDialog.getSaveFileName(
            self, "Save maps", self.settings.value("last_save", start),
            "PNG sheet (*.png);;TIFF stack (*.tif *.tiff);;NumPy (*.npz);;"
            "Point cloud PLY (*.ply);;Point cloud LAS (*.las)")
        if not path:
            return
        try:
            self.save_maps(path)
            self.settings.setValue("last_save", path)
            self.statusBar().showMessage(f"saved {path}", 5000)
        except Exception as exc:  # noqa: BLE001 - a failed save is shown, the window stays
            self.show_error(f"Could not save maps: {exc}")

    def screenshot(self, path: str | Path) -> Path:
        """A grab of the whole window as PNG (with the 3-D view's picture drawn in where it is
        shown: a widget grab does not see into its native window)."""
        path = Path(path)
        pixmap = self.grab()
        v = self.view3d
        if v.gl is not None and self.views.currentWidget() is v and v.gl.isVisible():
            img = v.grab_view()
            if img is not None and not img.isNull():
                painter = QtGui.QPainter(pixmap)
                top_left = v.gl.mapTo(self, QtCore.QPoint(0, 0))
                painter.drawImage(QtCore.QRect(top_left, v.gl.size()), img)
                painter.end()
        if not pixmap.save(str(path)):
            raise OSError(f"could not write screenshot {path}")
        return path

    # ---- closing -------------------------------------------------------------------------------
    def shutdown(self, timeout_s: float = CLOSE_WAIT_S) -> None:
        """Abort a running scan, wait for its files, release the instruments."""
        self.timer.stop()
        run = self.run
        if run is None:
            return
        s = run.session
        aborted_here = False
        if not s.ended.is_set():
            try:
                s.abort()
                aborted_here = True
            except Exception as exc:  # noqa: BLE001 - it may have ended meanwhile
                log.info("abort at close: %s", exc)
            s.wait(timeout_s)
        if s.ended.is_set():
            if aborted_here and not self._ended_emitted:
                self._write_run_pictures()
            run.close()
        else:
            log.error("session did not end within %.0f s of the abort", timeout_s)

    def closeEvent(self, event: QtGui.QCloseEvent) -> None:  # noqa: N802 - Qt override
        self.save_settings()
        self.shutdown()
        self.view3d.release()
        super().closeEvent(event)


def close_keys() -> list[QtGui.QKeySequence]:
    """The platform's Quit and Close keys, plus Ctrl+Q and Ctrl+W where the platform has none
    (offscreen), each once: one shortcut holding a sequence twice, or two shortcuts holding the
    same one (``QKeySequence.Quit`` and a literal "Ctrl+Q" on X11), is ambiguous to Qt and fires
    neither (DESIGN.md section 6)."""
    keys: list[QtGui.QKeySequence] = []
    for standard, fallback in ((QtGui.QKeySequence.StandardKey.Quit, "Ctrl+Q"),
                               (QtGui.QKeySequence.StandardKey.Close, "Ctrl+W")):
        keys += QtGui.QKeySequence.keyBindings(standard)
        keys.append(QtGui.QKeySequence(fallback))
    unique: list[QtGui.QKeySequence] = []
    for k in keys:
        if not k.isEmpty() and k not in unique:
            unique.append(k)
    return unique


__all__ = ["MainWindow", "ControlPanel", "Inspector", "AccuracyPlot", "REFRESH_HZ"]
