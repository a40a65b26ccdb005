"""What the window runs: the control panel's settings (no Qt here) turned into an ``acq`` request,
and the request into a running session or a file reconstruction through :mod:`acq.api`.

The window is a client of the library like the CLI: :meth:`SourceSpec.to_request` makes the
request (which validates itself), :func:`open_run` asks ``acq.api`` to open the instruments and
build the session, and ``FileJob`` calls ``acq.api.reconstruct_file``. The window never touches a
device; ``Run.close`` hands the instruments and the run folder's lock back once the session has
ended.
"""

from __future__ import annotations

import math
import re
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from spdepth.acq.errors import RequestError
from spdepth.acq.flags import ACQUIRING, AcqFlag
from spdepth.acq.params import (DEFAULT_METHOD, DEFAULT_SIZE, DEFAULT_TARGET, MODES, PARAMS,
                                SOURCES)
from spdepth.acq.requests import (FileReconRequest, ReplayRequest, ScanRequest, SimBench,
                                  build_request)

SPEC_OPTIONS = {
    "scene": "--scene", "sbr": "--sbr", "seed": "--seed", "faults": "--faults",
    "galvo_port": "--galvo", "tagger_url": "--tagger", "sync_rate_hz": "--sync-rate-hz",
    "fov_deg": "--fov-deg", "recording": "--replay", "file": "--file", "size": "--size",
    "target": "--target", "mode": "--mode", "method": "--method", "time_unit_ps": "--time-unit-ps",
    "pulse_rms_ps": "--pulse-rms-ps", "reflectors": "--reflectors",
}
"""Each control's declared option (``acq.params``): its unit, range, default, help (the tooltip)
and source kinds. ``dwell_limit_ms`` holds ``--dwell-limit-ms`` (gated) or ``--dwell-ms`` (raster);
``out_root`` is ``--runs-dir``."""
DWELL_OPTIONS = {"gated": "--dwell-limit-ms", "raster": "--dwell-ms"}
PATH_FIELDS = ("out_root", "recording", "file")
"""The controls' paths: remembered absolute (with the rest, only from a run that started)."""


FIELD_SOURCES = {"galvo_port": ("real",), "tagger_url": ("real",), "fov_deg": ("real",)}
"""Controls used by fewer kinds than their option: the window's simulated source is the bench
itself (``spdepth gui --sim --tagger picoquant:mh150`` reaches a vendor driver from the command
line), and its field of view is the real galvo's (a file's ``--fov-deg`` is a command-line one)."""


def spec_fields(kind: str) -> tuple[str, ...]:
    """The ``SourceSpec`` fields a source kind uses (the others are another kind's)."""
    own = tuple(f for f, opt in SPEC_OPTIONS.items()
                if kind in FIELD_SOURCES.get(f, PARAMS[opt].sources))
    return own + (("dwell_limit_ms",) if kind in ("sim", "real") else ())


def spec_param(field_name: str, kind: str, mode: str = "gated"):
    """The declaration (as it applies to ``kind``) behind a ``SourceSpec`` field."""
    opt = DWELL_OPTIONS.get(mode, "--dwell-limit-ms") if field_name == "dwell_limit_ms" \
        else SPEC_OPTIONS[field_name]
    return PARAMS[opt].for_source(kind)


def _control_names() -> dict[str, str]:
    names = {}
    for p in PARAMS.values():
        if p.label:
            name = p.label if p.label[:2].isupper() else p.label[0].lower() + p.label[1:]
            names[p.option] = name + (f" ({p.unit})" if p.unit in ("ps", "ms") else "")
    names.update({"--dwell-limit-ms": "dwell limit (ms)", "--dwell-ms": "dwell (ms)",
                  "--galvo": "galvo port"})
    return names


CONTROL_NAMES = _control_names()
"""The request's messages name fields in the CLI's words; the banner names the window's controls
(each declaration's ``label``)."""
_OPTION = re.compile("|".join(re.escape(k) + r"(?![\w-])"
                              for k in sorted(CONTROL_NAMES, key=len, reverse=True)))


def in_window_words(message: str) -> str:
    """A request's error message with the CLI's option names replaced by the controls' names."""
    return _OPTION.sub(lambda m: CONTROL_NAMES[m.group(0)], message)


@dataclass
class SourceSpec:
    """Everything the control panel holds (also what QSettings remembers, per source kind), in
    the controls' units (each field's declared option: ``SPEC_OPTIONS``). Zero (or "") in a field
    whose option has no default for the kind means that kind's default: as recorded (replay),
    from the file (file), the request's (dwell, sync rate: required).

    size:           (H, W) pixels, rows first.
    dwell_limit_ms: gated dwell limit / raster dwell.
    target:         detections per pixel; replay: 0 keeps the recorded target; file: detections
                    kept per pixel, 0 all.
    reflectors:     surfaces per pixel to look for (K or "auto"); 0: the kind's default (one; a
                    replay keeps the recorded number).
    out_root:       a folder under which each run gets its own directory (recording, maps,
                    run.json).
    """

    kind: str = "sim"
    scene: str = PARAMS["--scene"].default
    size: tuple[int, int] = DEFAULT_SIZE
    target: int = DEFAULT_TARGET
    mode: str = PARAMS["--mode"].default
    method: str = DEFAULT_METHOD
    dwell_limit_ms: float = 0.0
    sbr: float = 0.0                     # 0: the scene's own (``--sbr``'s default)
    seed: int = PARAMS["--seed"].default
    faults: str = ""
    galvo_port: str = ""
    tagger_url: str = ""
    sync_rate_hz: float = 0.0
    fov_deg: float = PARAMS["--fov-deg"].default
    recording: str = ""
    file: str = ""
    time_unit_ps: float = 0.0
    pulse_rms_ps: float = 0.0
    reflectors: int | str = 0
    out_root: str = ""

    def to_dict(self) -> dict:
        d = asdict(self)
        d["size"] = list(self.size)
        return d

    @classmethod
    def from_dict(cls, d: dict) -> "SourceSpec":
        known = {k: v for k, v in d.items() if k in cls.__dataclass_fields__}
        if "size" in known:
            known["size"] = tuple(int(v) for v in known["size"])
        return cls(**known)

    def values(self) -> dict:
        """The option values (``acq.params`` dest -> value in the option's unit) of this kind's
        fields; a field holding its "default" zero is left out (the request's default applies)."""
        out = {}
        for name in spec_fields(self.kind):
            p = spec_param(name, self.kind, self.mode)
            v = getattr(self, name)
            if v is None or (v in (0, "") and (p.default is None or p.kind == "surfaces")):
                continue
            out[p.dest] = tuple(v) if name == "size" else v
        return out

    def to_request(self) -> ScanRequest | ReplayRequest | FileReconRequest:
        """The request these settings stand for (``acq.params.build_request``, as the CLI makes
        it), validated by the request itself: a ``RequestError`` names the field and value (in
        the CLI's words; ``in_window_words``)."""
        if self.kind not in SOURCES:
            raise RequestError(f"source must be one of {', '.join(SOURCES)}, got {self.kind!r}")
        if self.kind == "file" and Path(self.file).suffix.lower() == ".mat" and not self.time_unit_ps:
            # the reader would say so only on its worker thread; refused before the start
            raise RequestError(f"{Path(self.file).name}: a .mat file does not record its time "
                               f"unit; set the time unit (8 ps for first-photon-imaging "
                               f"files, 1 ps for times in ps)")
        return build_request(self.kind, self.values())

    @classmethod
    def from_request(cls, request, base: "SourceSpec | None" = None) -> "SourceSpec":
        """The controls showing ``request`` (on top of ``base`` for what it does not name). A
        request can hold more than the controls (window, bins, pattern): the run uses the request
        itself; the controls show what they can."""
        d = (base or cls()).to_dict()
        kind = source_kind(request)
        d["kind"] = kind
        inst = getattr(request, "instruments", None)
        for name in spec_fields(kind):
            if name == "dwell_limit_ms":
                v = request.dwell_limit_s or request.dwell_s
                d[name] = (v or 0.0) * 1e3
                continue
            p = spec_param(name, kind)
            holder = inst if inst is not None and hasattr(inst, p.field) else request
            v = p.from_si(getattr(holder, p.field))
            if v is None or (p.kind == "surfaces" and v == p.default):
                v = "" if p.kind in ("str", "path") else 0
            d[name] = list(v) if name == "size" else v
        return cls.from_dict(d)


def source_kind(request) -> str:
    """The source kind ("sim", "real", "replay", "file") of a request."""
    if isinstance(request, ReplayRequest):
        return "replay"
    if isinstance(request, FileReconRequest):
        return "file"
    if isinstance(request, ScanRequest):
        return "sim" if isinstance(request.instruments, SimBench) else "real"
    raise RequestError(f"the window runs scan, replay and file requests, got "
                       f"{type(request).__name__}")


def clean_values(kind: str, stored: dict) -> tuple[dict, list[str]]:
    """Stored control values of one source kind checked against the declarations: each that no
    longer validates (a target of 0 for a scan, an estimator that is gone, a size past the
    controller's limit) is dropped, so its default applies, with one line saying so. Unknown keys
    (another kind's, a removed control's) are dropped silently."""
    kept, notes = {}, []
    mode = stored.get("mode", PARAMS["--mode"].default)
    if mode not in MODES:
        mode = PARAMS["--mode"].default
    for name in spec_fields(kind):
        if name not in stored:
            continue
        v = stored[name]
        p = spec_param(name, kind, mode)
        if name == "size" and isinstance(v, list):
            v = tuple(v)
        try:
            if not (v in (0, "") and (p.default is None or p.kind == "surfaces")):
                p.check(v)
        except (RequestError, TypeError, ValueError) as exc:
            notes.append(f"stored {kind} setting {in_window_words(p.option)} {v!r} ignored "
                         f"({in_window_words(str(exc))}); using the default")
            continue
        kept[name] = v
    return kept, notes


@dataclass
class Remembered:
    """The window's stored settings: each source kind's control values (checked against the
    declarations when loaded), the kind shown last, the runs folder, and one note per stored
    value that no longer validated (the window's status bar shows them)."""

    kind: str = "sim"
    per_kind: dict = field(default_factory=dict)
    out_root: str = ""
    notes: dict = field(default_factory=dict)

    def spec(self, kind: str | None = None) -> SourceSpec:
        """The controls of ``kind`` (default: the last one shown): its stored values on the
        declared defaults."""
        kind = kind or self.kind
        return SourceSpec(kind=kind, out_root=self.out_root, **self.per_kind.get(kind, {}))

    @classmethod
    def load(cls, raw: str | None, legacy: str | None = None) -> "Remembered":
        """From the JSON the window stored (``SETTINGS_KEY``); ``legacy``: the single source dict
        of earlier versions (key "source"), whose values count for its own kind only."""
        import json

        # a hand-edited or damaged file: QSettings gives a list for a value with commas
        try:
            d = json.loads(raw) if isinstance(raw, str) and raw else None
        except (ValueError, RecursionError):
            d = None
        if not isinstance(d, dict):
            d = {}
            try:
                old = json.loads(legacy) if isinstance(legacy, str) and legacy else None
            except (ValueError, RecursionError):
                old = None
            if isinstance(old, dict) and old.get("kind") in SOURCES:
                d = {"kind": old["kind"], "out_root": old.get("out_root", ""), old["kind"]: old}
        rem = cls(kind=d.get("kind") if d.get("kind") in SOURCES else "sim",
                  out_root=d.get("out_root") if isinstance(d.get("out_root"), str) else "")
        for kind in SOURCES:
            if isinstance(d.get(kind), dict):
                rem.per_kind[kind], rem.notes[kind] = clean_values(kind, d[kind])
        return rem

    def store(self, spec: SourceSpec) -> str:
        """The JSON to keep after ``spec`` ran: its kind's remembered values replaced (a
        declaration with ``remembered=False``, such as faults, is never kept)."""
        import json

        values = {}
        for name in spec_fields(spec.kind):
            p = spec_param(name, spec.kind, spec.mode)
            if p.remembered:
                v = getattr(spec, name)
                values[name] = list(v) if name == "size" else v
        self.per_kind[spec.kind] = values
        self.kind = spec.kind
        if spec.out_root:
            self.out_root = spec.out_root
        return json.dumps({"kind": self.kind, "out_root": self.out_root, **self.per_kind})


SETTINGS_KEY = "sources"
"""The QSettings key of the window's per-kind settings (``Remembered``)."""


def run_kind(request) -> str:
    """The run folder's suffix for a request: sim, real or replay."""
    return source_kind(request)


@dataclass
class Run:
    """A session being shown, with what it needs closed afterwards.

    out_dir:       the session's folder (None: in memory); it stays readable after ``close``.
    folder:        the ``acq.api.OutputDir`` whose lock this run holds (a folder the window made),
                   None when the caller owns the folder.
    truth_depth_m: (H, W) true depth of a simulated one-surface scene, else None.
    """

    session: object
    request: ScanRequest | ReplayRequest
    out_dir: Path | None
    instruments: object = None
    folder: object = None
    truth_depth_m: np.ndarray | None = None
    started_at: float = field(default_factory=time.time)

    @property
    def label(self) -> str:
        if isinstance(self.request, ReplayRequest):   # the estimator: as recorded unless replaced
            return f"{self.request.label()}, {self.session.live_recon.requested.method}"
        return self.request.label()

    def close(self, *, discard: bool = False) -> None:
        """Release the instruments and the run folder's lock; call once the session has ended.
        ``discard``: remove the folder the window made if it is still empty (a start that failed)."""
        if self.instruments is not None:
            self.instruments.close()
            self.instruments = None
        if self.folder is not None:
            self.folder.close(discard=discard)
            self.folder = None


def open_run(request: ScanRequest | ReplayRequest, out_dir=None) -> Run:
    """Open the request's source and build its session (not started). ``out_dir``: None keeps
    the run in memory; a path is the caller's folder (the caller holds any lock on it); an
    ``acq.api.OutputDir`` (e.g. ``new_run_dir``'s) is handed to the run, which releases it in
    ``close``. Raises the ``acq``/``drivers`` errors as they come (the window shows them); nothing
    stays open when it fails (a folder handed over is released and, when empty, removed)."""
    from spdepth.acq.api import OutputDir, build_session, open_instruments

    folder = out_dir if isinstance(out_dir, OutputDir) else None
    out = folder.path if folder is not None else (Path(out_dir) if out_dir is not None else None)
    inst = None
    try:
        if isinstance(request, ReplayRequest):
            session = build_session(request, out)
            return Run(session, request, out, folder=folder)
        inst = open_instruments(request)
        session = build_session(request, out, inst)
    except BaseException:
        if inst is not None:
            inst.close()
        if folder is not None:
            folder.close(discard=True)
        raise
    truth = None
    if inst.scene is not None:
        depth = np.asarray(inst.scene.truth()["depth_m"], dtype=np.float64)
        truth = depth if depth.ndim == 2 else None
    return Run(session, request, out, instruments=inst, folder=folder, truth_depth_m=truth)


@dataclass(frozen=True)
class PixelInfo:
    """One pixel as the inspector shows it: its kept detection times (tagger units of
    ``binning.time_unit_s``), the estimate, the model used, and words for its counts and state."""

    times: np.ndarray
    binning: object
    pulse_rms_s: float | None
    irf: object
    tof_s: float
    depth_m: float
    background: float
    signal: float
    uncertainty_s: float
    estimated: bool
    flag: int
    kept: str
    acquisition: str
    n_kept: int = 0
    exposure_s: float = math.nan
    """Laser time the kept detections span, s (NaN: not known, e.g. a file of photon times)."""
    surfaces: tuple = ()
    """K > 1 surfaces: (tof_s, depth_m, signal, uncertainty_s, weak) of each surface fitted, nearest
    first (weak: background alone could have made it, ``recon.maps.DepthMaps.weak``)."""


def estimate_at(maps, r: int, c: int) -> dict:
    """Pixel (r, c) of maps of one or several surfaces (``DepthMaps`` or the live
    reconstruction's arrays): the nearest surface's tof_s, depth_m, signal and uncertainty_s, and
    with several surfaces ``surfaces``, each found one's (tof_s, depth_m, signal, uncertainty_s,
    weak)."""
    names = ("tof_s", "depth_m", "signal", "uncertainty_s")
    arrays = [np.asarray(getattr(maps, n)) for n in names]
    if arrays[0].ndim == 2:
        return {n: float(a[r, c]) for n, a in zip(names, arrays)}
    out = {n: float(a[0, r, c]) for n, a in zip(names, arrays)}
    weak = np.asarray(maps.weak)
    out["surfaces"] = tuple((*(float(a[k, r, c]) for a in arrays), bool(weak[k, r, c]))
                            for k in range(arrays[0].shape[0]) if np.isfinite(arrays[0][k, r, c]))
    return out


class SessionView:
    """What the inspector and the saving need from a live or replayed session."""

    def __init__(self, session):
        self.session = session

    @property
    def shape(self) -> tuple[int, int]:
        return self.session.plan.shape

    @property
    def target(self) -> int:
        return self.session.plan.target

    def maps(self):
        """The maps with the scan's geometry in their settings (``acq.api.session_maps``)."""
        from spdepth.acq.api import session_maps

        return session_maps(self.session)[0]

    def key(self, r: int, c: int):
        """Changes whenever what ``pixel(r, c)`` shows may have changed."""
        s = self.session
        flat = r * self.shape[1] + c
        return (int(s.store.count[flat]), int(s.acq_flags[flat]), bool(s.live_recon.done[r, c]),
                s.live_recon.pixel_settings.pulse_rms_s)

    def pixel(self, r: int, c: int) -> PixelInfo:
        s = self.session
        rc = s.live_recon
        flat = r * self.shape[1] + c
        acq = int(s.acq_flags[flat])
        with rc.lock:          # one batch's results, never half of one
            est = estimate_at(rc, r, c)
        return PixelInfo(
            times=s.store.photons([flat]).times, binning=rc.pixel_settings.binning,
            pulse_rms_s=rc.pixel_settings.pulse_rms_s, irf=rc.pixel_settings.irf, **est,
            background=float(rc.background[r, c]), estimated=bool(rc.done[r, c]),
            flag=int(rc.flags[r, c]), kept=f"{int(s.store.count[flat])} of {s.plan.target}",
            n_kept=int(s.store.count[flat]), exposure_s=s.exposure_s(flat),
            acquisition="acquiring" if acq == ACQUIRING
            else AcqFlag(acq).name.lower().replace("_", " "))


class ResultView:
    """``SessionView``'s interface over a file reconstruction (``acq.api.FileResult``).

    target: the detections kept per pixel (the request's, or the recording's), 0 for all."""

    def __init__(self, result):
        self.result = result
        self.path = Path(result.request.input)
        self.target = int(result.maps.settings.get("max_photons") or 0)

    @property
    def shape(self) -> tuple[int, int]:
        return tuple(self.result.maps.flags.shape)

    def maps(self):
        return self.result.maps

    def key(self, r: int, c: int):
        return ()

    def snapshot(self):
        """The maps as an ``acq.session.Snapshot`` (state done), for the map panels."""
        from spdepth.acq.mapdefs import surfaces_of
        from spdepth.acq.session import Snapshot

        res, m = self.result, self.result.maps
        h, w = self.shape
        surfaces = surfaces_of(m)
        return Snapshot(state="done", elapsed_s=res.read_s + res.recon_s, pixels_total=h * w,
                        pixels_final=h * w, detections=int(m.photons.sum()), detections_per_s=0.0,
                        lost_spans=0, lost_records=0, eta_s=None, recon_lag=0, passes=0,
                        depth_m=m.depth_m, background=m.background, signal=m.signal,
                        uncertainty_s=m.uncertainty_s, counts=m.photons,
                        acq_flags=np.zeros((h, w), np.uint8), surfaces=surfaces,
                        weak=None if surfaces is None else m.weak)

    def pixel(self, r: int, c: int) -> PixelInfo:
        res, m = self.result, self.result.maps
        b = res.binning
        t = res.store.pixel(r, c)
        t = t[(t >= b.window_start) & (t < b.window_stop)]
        if self.target:
            t = t[:self.target]
        n = int(m.photons[r, c])
        return PixelInfo(
            times=t, binning=b, pulse_rms_s=res.pulse_rms_s, irf=res.irf, **estimate_at(m, r, c),
            background=float(m.background[r, c]), estimated=n > 0, flag=int(m.flags[r, c]),
            kept=f"{n} in the window" + (f" (first {self.target})" if self.target else ""),
            n_kept=n, acquisition=f"from {self.path.name}")


class FileJob:
    """``acq.api.reconstruct_file`` on a worker thread; the window polls ``done``/``result``/
    ``error`` and ``progress`` (pixels done, total) from its timer, so it never blocks."""

    def __init__(self, request: FileReconRequest):
        import threading

        self.request = request
        self.result = None
        """The ``acq.api.FileResult`` once done."""
        self.error: BaseException | None = None
        self.progress = (0, 0)
        self.started_at = time.monotonic()
        self._done = threading.Event()
        self._thread = threading.Thread(target=self._run, name="gui-file-recon", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        from spdepth.acq.api import reconstruct_file

        try:
            self.result = reconstruct_file(self.request, progress=self._progress)
        except BaseException as exc:  # noqa: BLE001 - handed to the window, shown in its banner
            self.error = exc
        finally:
            self._done.set()

    def _progress(self, done: int, total: int) -> None:
        self.progress = (int(done), int(total))

    @property
    def done(self) -> bool:
        return self._done.is_set()

    def wait(self, timeout_s: float | None = None) -> bool:
        return self._done.wait(timeout_s)


__all__ = ["SourceSpec", "Remembered", "SETTINGS_KEY", "Run", "open_run", "run_kind", "source_kind", "clean_values", "spec_fields",
           "in_window_words", "SOURCES", "MODES",
           "PixelInfo", "SessionView", "ResultView", "FileJob"]
