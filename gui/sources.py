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
from spdepth.acq.requests import (DEFAULT_METHOD, DEFAULT_SIZE, DEFAULT_TARGET, MODES, Devices,
                                  FileReconRequest, ReplayRequest, ScanRequest, SimBench)
from spdepth.recon.model import METHODS

SOURCES = ("sim", "real", "replay", "file")
"""Simulated bench, real devices, a recording replayed through the same pipeline, or a PTU/.mat
file reconstructed as a whole (``spdepth recon``'s path, on a worker thread)."""

CONTROL_NAMES = {
    "--scene": "scene", "--sbr": "SBR", "--seed": "seed", "--faults": "faults",
    "--galvo PORT": "galvo port", "--tagger usb:VID:PID": "tagger (usb:VID:PID)",
    "--sync-rate-hz": "sync rate", "--fov-deg": "field of view", "--size": "size",
    "--target": "target", "--mode": "mode",
    "--dwell-limit-ms": "dwell limit (ms)", "--dwell-ms": "dwell (ms)", "--method": "estimator",
    "--time-unit-ps": "time unit (ps)", "--pulse-rms-ps": "pulse RMS (ps)",
}
"""The request's messages name fields in the CLI's words; the banner names the window's controls."""
_OPTION = re.compile("|".join(re.escape(k) for k in sorted(CONTROL_NAMES, key=len, reverse=True)))


def in_window_words(message: str) -> str:
    """A request's error message with the CLI's option names replaced by the controls' names."""
    return _OPTION.sub(lambda m: CONTROL_NAMES[m.group(0)], message)


def _ms(v: float) -> float | None:
    return v * 1e-3 if v else None      # 0 in a control: the request's default


def _ps(v: float) -> float | None:
    return v * 1e-12 if v else None


@dataclass
class SourceSpec:
    """Everything the control panel holds (also what QSettings remembers), in the controls' units.
    Zero in a numeric field means "the default" (the request's, or as recorded / from the file).

    size:           (H, W) pixels, rows first.
    dwell_limit_ms: gated dwell limit / raster dwell.
    sync_rate_hz:   real devices: the laser repetition rate.
    fov_deg:        real devices: square field of view in optical degrees, centred.
    target:         detections per pixel; replay: 0 keeps the recorded target; file: detections
                    kept per pixel, 0 all.
    file:           a PTU/HT3/PT3 or .mat file to reconstruct (kind "file").
    time_unit_ps:   file: size of one raw time unit (required for .mat, 0: the PTU header's).
    pulse_rms_ps:   file: Gaussian pulse RMS (0: as recorded, else estimated from the data).
    reflectors:     surfaces per pixel to look for (K); 0: one, and a replay keeps the recorded
                    number.
    out_root:       a folder under which each run gets its own directory (recording, maps,
                    run.json).
    """

    kind: str = "sim"
    scene: str = SimBench.scene
    size: tuple[int, int] = DEFAULT_SIZE
    target: int = DEFAULT_TARGET
    mode: str = "gated"
    method: str = DEFAULT_METHOD
    dwell_limit_ms: float = 0.0
    sbr: float = SimBench.sbr
    seed: int = SimBench.seed
    faults: str = ""
    galvo_port: str = ""
    tagger_url: str = ""
    sync_rate_hz: float = 0.0
    fov_deg: float = Devices.fov_deg
    recording: str = ""
    file: str = ""
    time_unit_ps: float = 0.0
    pulse_rms_ps: float = 0.0
    reflectors: int = 0
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

    def to_request(self) -> ScanRequest | ReplayRequest | FileReconRequest:
        """The request these settings stand for, validated by the request itself: a
        ``RequestError`` names the field and value (in the CLI's words; ``in_window_words``)."""
        if self.kind not in SOURCES:
            raise RequestError(f"source must be one of {', '.join(SOURCES)}, got {self.kind!r}")
        if self.kind == "replay":
            return ReplayRequest(recording=self.recording, target=self.target or None,
                                 method=self.method, reflectors=self.reflectors or None)
        if self.kind == "file":
            if Path(self.file).suffix.lower() == ".mat" and not self.time_unit_ps:
                # the reader would say so only on its worker thread; refused before the start
                raise RequestError(f"{Path(self.file).name}: a .mat file does not record its time "
                                   f"unit; set the time unit (8 ps for first-photon-imaging "
                                   f"files, 1 ps for times in ps)")
            return FileReconRequest(input=self.file, method=self.method,
                                    time_unit_s=_ps(self.time_unit_ps),
                                    pulse_rms_s=_ps(self.pulse_rms_ps),
                                    max_photons=self.target or None,
                                    reflectors=int(self.reflectors or 1))
        if self.kind == "sim":
            instruments = SimBench(scene=self.scene, sbr=self.sbr, seed=self.seed,
                                   faults=self.faults)
        else:
            instruments = Devices(galvo=self.galvo_port, tagger=self.tagger_url,
                                  sync_rate_hz=self.sync_rate_hz, fov_deg=self.fov_deg)
        gated = self.mode == "gated"
        return ScanRequest(instruments=instruments, size=tuple(self.size), target=self.target,
                           mode=self.mode, method=self.method, reflectors=int(self.reflectors or 1),
                           dwell_limit_s=_ms(self.dwell_limit_ms) if gated else None,
                           dwell_s=None if gated else _ms(self.dwell_limit_ms))

    @classmethod
    def from_request(cls, request, base: "SourceSpec | None" = None) -> "SourceSpec":
        """The controls showing ``request`` (on top of ``base`` for what it does not name). A
        request can hold more than the controls (window, bins, pattern): the run uses the request
        itself; the controls show what they can."""
        d = (base or cls()).to_dict()
        if isinstance(request, ReplayRequest):
            d.update(kind="replay", recording=request.recording, target=request.target or 0,
                     reflectors=request.reflectors or 0)
            if request.method is not None:
                d["method"] = request.method
        elif isinstance(request, FileReconRequest):
            d.update(kind="file", file=request.input, method=request.method,
                     target=request.max_photons or 0,
                     time_unit_ps=(request.time_unit_s or 0.0) * 1e12,
                     pulse_rms_ps=(request.pulse_rms_s or 0.0) * 1e12,
                     reflectors=_surfaces_control(request.reflectors))
        elif isinstance(request, ScanRequest):
            src = request.instruments
            d.update(size=list(request.size), target=request.target, mode=request.mode,
                     method=request.method, reflectors=_surfaces_control(request.reflectors),
                     dwell_limit_ms=(request.dwell_limit_s or request.dwell_s or 0.0) * 1e3)
            if isinstance(src, SimBench):
                d.update(kind="sim", scene=src.scene, sbr=src.sbr, seed=src.seed, faults=src.faults)
            else:
                d.update(kind="real", galvo_port=src.galvo, tagger_url=src.tagger,
                         sync_rate_hz=src.sync_rate_hz, fov_deg=src.fov_deg)
        else:
            raise RequestError(f"the window runs scan, replay and file requests, got "
                               f"{type(request).__name__}")
        return cls.from_dict(d)


def _surfaces_control(reflectors) -> int:
    """A request's surfaces as ``SourceSpec.reflectors``: 0 for the default of one."""
    return 0 if reflectors == 1 else reflectors


def run_kind(request) -> str:
    """The run folder's suffix for a request: sim, real or replay."""
    if isinstance(request, ReplayRequest):
        return "replay"
    return "sim" if isinstance(request.instruments, SimBench) else "real"


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


__all__ = ["SourceSpec", "Run", "open_run", "run_kind", "in_window_words", "SOURCES", "MODES",
           "METHODS", "PixelInfo", "SessionView", "ResultView", "FileJob"]
