"""The library every front end calls: requests in, sessions and maps out.

- :func:`open_instruments` opens what a :class:`~acq.requests.ScanRequest` names (the simulated
  bench or real devices);
- :func:`build_session` turns a scan or replay request into a :class:`~acq.session.Session` (not
  started) with its plan, estimator settings and the request itself saved with it;
- :func:`reconstruct_file` reads a recorded file and reconstructs it, writing the outputs the
  request names, and returns the maps with a small JSON-able summary;
- :class:`OutputDir` is a session's output folder, created and locked while a session writes
  into it; :func:`finish_session` writes ``maps.png`` beside a finished session's files and
  returns its summary.

The CLI, the window, Dask workers, the demo and the benchmarks only build requests and call these.
"""

from __future__ import annotations

import fcntl
import logging
import math
import os
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Callable

import numpy as np

from spdepth.acq.errors import OutputError, RecordingError, RequestError
from spdepth.acq.jsonable import jsonable
from spdepth.acq.requests import (DEFAULT_DWELL_S, DEFAULT_METHOD, FileReconRequest, ReplayRequest,
                                  ScanRequest, SimBench)
from spdepth.recon.counts import CountStore
from spdepth.recon.errors import InputError
from spdepth.recon.model import Binning, ReconSettings
from spdepth.recon.pileup import PILEUP_THRESHOLD

log = logging.getLogger(__name__)

SESSION_FILES = ("recording.ptu", "events.jsonl", "maps.npz", "maps.png", "points.ply", "run.json")
"""What a session writes into its folder (``--overwrite`` replaces exactly these)."""
SPARSE_PER_PIXEL = 2.0
"""Below this many detections used per pixel, a file's summary suggests ``--method spatial``."""
LOCK_NAME = ".spdepth.lock"
"""Held (``flock``) by the process whose session writes into the folder; the kernel drops it when
that process dies, so a killed session never leaves a folder locked."""


# ---- output folders ------------------------------------------------------------------------------
class OutputDir:
    """A session's output folder: created if missing, refused when it holds other files (unless
    ``overwrite``) or when another running session holds it (``overwrite`` or not). The lock is
    held until :meth:`close`; an empty folder made here is removed again by ``close(discard=True)``
    (a run that failed before writing anything leaves nothing behind)."""

    def __init__(self, path: str | Path, *, overwrite: bool = False, name: str = "--out"):
        self.path = Path(path)
        if self.path.exists() and not self.path.is_dir():
            raise OutputError(f"{name} {self.path} exists and is not a folder")
        self._created = not self.path.exists()
        from spdepth.acq.outputs import check_output_folder, probe_folder

        check_output_folder(name, self.path)      # before a folder is made: nothing left behind
        try:
            self.path.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise OutputError(f"{name} {self.path}: cannot create the folder ({exc.strerror})") from None
        probe_folder(name, self.path)
        try:
            self._fh = open(self.path / LOCK_NAME, "a+", encoding="utf-8")
        except OSError as exc:
            raise OutputError(f"{name} {self.path}: cannot be written ({exc.strerror})") from None
        try:
            fcntl.flock(self._fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            self._fh.seek(0)
            holder = self._fh.read().strip() or "another process"
            self._fh.close()
            raise OutputError(f"{name} {self.path} is in use by a running session ({holder}); "
                              f"pick another folder") from None
        others = [p for p in self.path.iterdir() if p.name != LOCK_NAME]
        if others and not overwrite:
            self._release()
            raise OutputError(f"{name} {self.path} is not empty (pass --overwrite to write into it)")
        for n in SESSION_FILES:
            (self.path / n).unlink(missing_ok=True)
        self._fh.seek(0)
        self._fh.truncate()
        self._fh.write(f"pid {os.getpid()}\n")
        self._fh.flush()

    def _release(self) -> None:
        if self._fh is not None:
            fcntl.flock(self._fh, fcntl.LOCK_UN)
            self._fh.close()
            self._fh = None
            (self.path / LOCK_NAME).unlink(missing_ok=True)

    def close(self, *, discard: bool = False) -> None:
        """Release the folder; with ``discard``, remove it if this object made it and it is empty."""
        self._release()
        if discard and self._created and self.path.is_dir() and not any(self.path.iterdir()):
            self.path.rmdir()

    def __enter__(self) -> "OutputDir":
        return self

    def __exit__(self, exc_type, *_) -> None:
        self.close(discard=exc_type is not None)


def new_run_dir(root: str | Path, kind: str) -> OutputDir:
    """A fresh, locked ``root/YYYYmmdd-HHMMSS-kind`` folder (suffixed when taken): the window's runs."""
    root = Path(root).expanduser().resolve()
    stem = time.strftime("%Y%m%d-%H%M%S") + f"-{kind}"
    path, n = root / stem, 1
    while path.exists():
        n += 1
        path = root / f"{stem}-{n}"
    return OutputDir(path)


# ---- scans -----------------------------------------------------------------------------------------
def open_instruments(request: ScanRequest):
    """The instruments a scan request names, opened (``acq.instruments.Instruments``; a context
    manager: close it when the session has ended)."""
    from spdepth.acq.instruments import open_devices, open_sim

    src = request.instruments
    if isinstance(src, SimBench):
        return open_sim(src.scene, request.size, ppp=src.ppp or float(request.target), sbr=src.sbr,
                        seed=src.seed, faults=src.faults, tagger=src.tagger, galvo=src.galvo)
    return open_devices(src)


def scan_plan(request: ScanRequest, instruments):
    """The :class:`~acq.plan.ScanPlan` of a scan request on opened instruments: the simulated
    bench's whole field of view (dwell limit: 20 scene dwells), or ``fov_deg`` centred for real
    devices."""
    from spdepth.acq.instruments import sim_plan
    from spdepth.acq.plan import ScanPlan

    h, w = request.size
    dwell = request.dwell_limit_s if request.mode == "gated" else request.dwell_s
    common = dict(mode=request.mode, target=request.target, pattern=request.pattern,
                  settle_s=request.settle_s, max_passes=request.max_passes,
                  time_limit_s=request.time_limit_s)
    if instruments.scene is not None:
        return sim_plan(instruments, (h, w), dwell_s=dwell, **common)
    fov = request.instruments.fov_deg
    half = fov / 2
    x = [-half + (c + 0.5) * fov / w for c in (0, w - 1)]
    y = [-half + (r + 0.5) * fov / h for r in (0, h - 1)]
    return ScanPlan(w, h, x[0], x[1], y[0], y[1], dwell_s=dwell or DEFAULT_DWELL_S[request.mode],
                    **common)


def scan_settings(request: ScanRequest, resolution_s: float, scene=None) -> ReconSettings:
    """Estimator settings of a scan: the request's window and bins in the tagger's units, its
    pulse width (else the simulated scene's, else measured from the first pixels) and surfaces."""
    binning = Binning.from_window(resolution_s, request.window, request.bin_s)
    pulse = request.pulse_rms_s or (scene.pulse_rms_s if scene is not None else None)
    return ReconSettings(method=request.method, binning=binning, pulse_rms_s=pulse,
                         max_photons=request.target, reflectors=request.reflectors,
                         max_reflectors=request.max_reflectors, false_alarm=request.false_alarm)


def build_session(request: ScanRequest | ReplayRequest, out_dir: str | Path | OutputDir | None = None,
                  instruments=None):
    """The session a request asks for, not started. A scan needs its ``instruments`` opened
    (:func:`open_instruments`); a replay opens its recording. The request is saved with the session
    (``run.json`` ``info.request`` and the recording's header)."""
    from spdepth.acq.scan_source import ScanSource
    from spdepth.acq.session import Session

    out = out_dir.path if isinstance(out_dir, OutputDir) else out_dir
    if isinstance(request, ScanRequest):
        if instruments is None:
            raise RequestError("a scan session needs its instruments opened (open_instruments)")
        plan = scan_plan(request, instruments)
        settings = scan_settings(request, instruments.tagger.resolution_s, instruments.scene)
        source = ScanSource(instruments.galvo, instruments.tagger,
                            sync_period_s=instruments.sync_period_s)
        return Session(plan, settings, source, out_dir=out,
                       info={**instruments.info, "request": request.to_dict()})
    if isinstance(request, ReplayRequest):
        if out is not None and Path(out).resolve() == request.folder.resolve():
            raise OutputError(f"--out {out} is the recording's own folder: pick another")
        return _replay_session(request, out)
    raise RequestError(f"build_session takes a scan or replay request, got {type(request).__name__}")


def _replay_session(request: ReplayRequest, out):
    from spdepth.acq.plan import ScanPlan
    from spdepth.acq.recording import ReplaySource, recon_settings_from_dict
    from spdepth.acq.session import Session

    src = ReplaySource(request.recording, speed=request.speed)
    info = src.info
    if info.plan is not None:
        plan = ScanPlan.from_dict(info.plan)
    else:
        # a foreign file (e.g. `spdepth simulate`'s): one fixed-dwell frame of the header's size
        if request.target is None:
            raise RequestError(f"{src.path} records no target of ours: give --target N (the "
                               f"detections per pixel to keep)")
        h, w = info.shape
        dwell_s = float(src.layout.tags.get("ImgHdr_TimePerPixel", 0) or 0) * 1e-3
        plan = ScanPlan(w, h, 0.0, 0.0, 0.0, 0.0, mode="raster", target=request.target,
                        dwell_s=dwell_s if dwell_s > 0 else DEFAULT_DWELL_S["raster"])
    gate_target = plan.target if plan.mode == "gated" else None
    if request.target is not None:
        plan = replace(plan, target=request.target)
    surfaces = dict(reflectors=request.reflectors, max_reflectors=request.max_reflectors,
                    false_alarm=request.false_alarm)
    if info.recon is not None:
        settings = recon_settings_from_dict(info.recon, method=request.method,
                                            pulse_rms_s=request.pulse_rms_s, max_photons=plan.target,
                                            **surfaces)
    else:
        range_bins = int(src.layout.tags.get("SPDepth_RangeBins", 0) or 0) or \
            int(round(info.sync_period_s / info.resolution_s))
        units = max(1, int(round(request.bin_s / info.resolution_s)))
        window_s = (0.0, (range_bins // units) * units * info.resolution_s)
        settings = ReconSettings(method=request.method or DEFAULT_METHOD,
                                 binning=Binning.from_window(info.resolution_s, window_s,
                                                             units * info.resolution_s),
                                 pulse_rms_s=request.pulse_rms_s, max_photons=plan.target,
                                 **{k: v for k, v in surfaces.items() if v is not None})
    return Session(plan, settings, src, out_dir=out, gate_target=gate_target,
                   info={"replay_of": str(src.path), **info.info, "request": request.to_dict()})


def session_maps(session):
    """A session's maps (``DepthMaps``) with its scan geometry in the settings
    (``acq.points.geometry_of`` reads it), its kept counts with NaN for pixels never
    measured (none kept and not complete), as the PNG sheets and the window draw them, and the
    laser time each pixel was observed over (``Session.exposure_s``)."""
    from spdepth.acq.flags import AcqFlag
    from spdepth.acq.points import GEOMETRY_KEY, ScanGeometry

    # once the session has ended its live reconstruction is over: the maps themselves, not
    # copies (a 4096 x 4096 frame's are a gigabyte)
    ended = session.ended.is_set() and session.live_recon.error is None
    maps = session.live_recon.maps(copy=False) if ended else session.maps()
    p = session.plan
    geometry = ScanGeometry.from_plan(p)
    if geometry is not None:
        maps = replace(maps, settings={**maps.settings, GEOMETRY_KEY: geometry.to_dict()})
    h, w = session.plan.shape
    # NaN but where something was kept or the pixel is complete (a large frame cut by its time
    # limit: a few of its pixels, so only those are converted)
    count = session.store.count
    measured = np.flatnonzero((count != 0) | (session.acq_flags == AcqFlag.COMPLETE))
    counts = np.full(h * w, np.nan)
    counts[measured] = count[measured]
    return maps, counts.reshape(h, w), session.exposure_s()


def finish_session(session, out_dir: str | Path | None, title: str | None = None,
                   progress=None) -> dict:
    """After a session has ended: ``maps.png`` and ``points.ply`` (``acq.points``: one point per
    estimated pixel and surface) beside its files (when it has a folder), and the summary every
    front end reports (JSON-able, small). ``progress(name, done, total)`` is called as each file
    starts (done of total written) and once all are written."""
    out = Path(out_dir) if out_dir is not None else None
    n_points = None
    if out is not None and out.is_dir():
        from spdepth.acq.points import geometry_of, write_points
        from spdepth.acq.report import render_maps_png

        step = progress or (lambda name, done, total: None)
        maps, counts, exposure_s = session_maps(session)
        geometry = geometry_of(maps)
        total = 1 + (geometry is not None)
        step("maps.png", 0, total)
        render_maps_png(out / "maps.png", maps, title=title, counts=counts,
                        exposure_s=exposure_s, target=session.plan.target)
        if geometry is not None:
            step("points.ply", 1, total)
            n_points = write_points(maps, geometry, ply=out / "points.ply", note=title or "",
                                    acq_flags=session.acq_flags.reshape(session.plan.shape))
        step("", total, total)
    st = session.stats()            # the figures of a snapshot without its map copies
    run = session.run_record()
    return {
        "state": session.state.value, "out": None if out is None else str(out),
        "no_pixel_complete": no_pixel_cause(session),
        "error": run["error"], "pixels": session.plan.nx * session.plan.ny,
        "flagged": int(sum(run["flag_reasons"].values())), "flag_reasons": run["flag_reasons"],
        "detections": session.detections, "detections_per_s": round(st["detections_per_s"], 1),
        "stream_s": session.stream_s, "passes": session.passes,
        "lost_spans": len(session.lost), "lost_records": st["lost_records"],
        "faults_seen": len(run["faults_seen"]), "warnings": list(run.get("warnings", ())),
        "recon_max_lag_pixels": session.live_recon.max_lag, "elapsed_s": round(st["elapsed_s"], 3),
        "points": n_points, "pileup": live_pileup(session),
    }


def live_pileup(session) -> dict | None:
    """What the live reconstruction's pile-up rule did (``acq.live_recon``: Coates' correction of
    the pixels with many detections per laser period), None for a session without it."""
    live = getattr(session, "live_recon", None)
    pileup = getattr(live, "pileup", None)
    return dict(pileup) if isinstance(pileup, dict) else None


def no_pixel_cause(session) -> str | None:
    """None when a session completed a pixel; else one line naming the likely cause (a run that
    completes nothing is not "done": its command exits 1 with this line)."""
    from spdepth.acq.flags import AcqFlag

    flags = np.asarray(session.acq_flags)
    if flags.size == 0 or np.any(flags == AcqFlag.COMPLETE):
        return None
    st, plan = session.store, session.plan
    unit_ps = st.time_unit_s * 1e12
    lo, hi = (v * unit_ps for v in st.window)
    seen, kept = st.photons_seen, st.kept
    if seen == 0:
        return "no detection arrived at all (laser, detector, sync or cabling?)"
    if st.unassigned == seen:
        return f"none of the {seen} detections fell in a pixel's dwell (pixel markers missing?)"
    if kept < 0.05 * (seen - st.unassigned):
        return (f"{'none' if kept == 0 else f'only {kept}'} of the {seen} detections fell in the window "
                f"{lo:g}:{hi:g} ps: widen --window-ps (the returns arrive elsewhere)")
    most = int(np.max(st.count))
    reasons = np.bincount(flags[flags != AcqFlag.COMPLETE], minlength=len(AcqFlag))
    why = AcqFlag(int(np.argmax(reasons)))
    hint = {AcqFlag.DWELL_LIMIT: "each dwell reached its limit first: more flux, a longer dwell limit or a lower "
                                 "--target",
            AcqFlag.PASS_LIMIT: "the passes ran out first: more flux, more passes or a lower --target",
            AcqFlag.TIME_LIMIT: "the time limit came first",
            AcqFlag.INCOMPLETE: "the stream ended first (a replay holds no more than its recording)"}.get(why, "")
    return (f"no pixel reached the target of {plan.target} in-window detections (at most {most} in a pixel, "
            f"{kept} of {seen} detections in the window {lo:g}:{hi:g} ps): {hint}")


# ---- files -----------------------------------------------------------------------------------------
@dataclass
class FileResult:
    """A file reconstructed as a whole.

    maps:    ``recon.maps.DepthMaps`` (its ``settings`` hold everything used).
    store:   the photons read (all of them; the window and ``max_photons`` apply in the estimator);
             None when they were read in blocks on a cluster (``acq.distributed``).
    binning, irf, pulse_rms_s: the model used (irf None for a Gaussian pulse).
    summary: what ``spdepth recon --json`` prints (small: no arrays).
    """

    request: FileReconRequest
    maps: object
    store: object
    binning: Binning
    pulse_rms_s: float | None
    irf: object
    is_image: bool
    kind: str
    notes: tuple = ()
    read_s: float = 0.0
    recon_s: float = 0.0
    photons_in_file: int = 0
    load_s: float = 0.0
    summary: dict = field(default_factory=dict)
    pileup: dict | None = None


RUN_JSON = "run.json"
"""A session's record (``Session.run_record``), written beside its files when it ends."""


def read_run_record(path: str | Path) -> dict | None:
    """The ``run.json`` of a session folder (or of the folder holding ``path``, a file in it):
    None when there is none (a run cut before its end); a ``RecordingError`` naming it when it
    cannot be read or is not a JSON object. The one reader of run.json."""
    import json

    p = Path(path)
    run_json = (p if p.is_dir() else p.parent) / RUN_JSON
    if not run_json.is_file():
        return None
    try:
        record = json.loads(run_json.read_text(encoding="utf-8"))
    except json.JSONDecodeError:
        raise RecordingError(f"{run_json}: not JSON") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise RecordingError(f"{run_json}: cannot be read ({exc})") from None
    if not isinstance(record, dict):
        raise RecordingError(f"{run_json}: not a JSON object")
    return record


class KernelWarmUp:
    """Loads the kernels a file reconstruction runs on a thread of its own, started at once: a new
    process pays numba's first dispatch and each kernel's load from the cache (on a fresh install:
    its compile) on the first call, which would otherwise land inside the read and the
    reconstruction. The reader's kernels come first (PTU files), then the estimator's, which load
    while the file is read. :meth:`wait_reader` and :meth:`wait` return the seconds the caller
    waited; a failure here is ignored (the real call then loads the kernel, or says what is
    wrong). ``spreads`` False: for a reconstruction without the test's spreads, which never runs
    their kernel (recon.estimate.warm_up)."""

    def __init__(self, request: FileReconRequest, notice: Callable[[str], None] | None = None,
                 spreads: bool = True):
        import threading

        self._request = request
        self._spreads = spreads
        self._notice = notice
        self._reader = threading.Event()
        self._thread = threading.Thread(target=self._run, name="kernel-warm-up", daemon=True)
        self._thread.start()

    def _settings(self) -> ReconSettings:
        req = self._request
        return ReconSettings(method=req.method, pulse_rms_s=req.pulse_rms_s, max_photons=req.max_photons,
                             reflectors=req.reflectors, max_reflectors=req.max_reflectors,
                             false_alarm=req.false_alarm, neighbour_false_alarm=req.neighbour_false_alarm)

    def _run(self) -> None:
        req = self._request
        ptu = Path(req.input).suffix.lower() == ".ptu"
        # with the reader's kernels in numba's cache (a warm install) they load first: the check
        # for a cold return test imports recon.detect and reads its cache index (0.045 s), which
        # the read need not wait for; on a cold cache the second process starts first, to compile
        # beside the reader's kernels
        try:
            from spdepth.recon.estimate import module_cached

            reader_first = ptu and module_cached("spdepth.acq.readers.picoquant")
        except Exception:  # noqa: BLE001 - then the order of a cold cache
            reader_first = False
        if reader_first:
            self._warm_reader()
        try:
            # a cold cache: the return test's kernels, most of a first run's compile, in a second
            # process (recon.estimate.compile_apart) while this one reads and compiles the estimator
            from spdepth.recon.estimate import compile_apart

            if compile_apart([self._settings()], decide=True, estimator=False,
                             spreads=self._spreads) is not None and self._notice:
                self._notice("compiling the return test's kernels in a second process while the file is read "
                             "and the estimator's compile here (first run; later runs load them from numba's cache)")
        except Exception:  # noqa: BLE001 - then the warm-up below compiles them here
            log.debug("compiling apart failed; the warm-up compiles here", exc_info=True)
        if not reader_first:
            if ptu:
                self._warm_reader()
            self._reader.set()
        try:
            from spdepth.recon.estimate import warm_up

            warm_up(self._settings(), spreads=self._spreads)
        except Exception:  # noqa: BLE001 - the reconstruction itself reports what is wrong
            log.debug("estimator warm-up failed; the reconstruction compiles what it needs",
                      exc_info=True)

    def _warm_reader(self) -> None:
        try:
            from spdepth.acq.readers.picoquant import warm_up as warm_reader

            warm_reader()
        except Exception:  # noqa: BLE001 - the read itself reports what is wrong
            log.debug("reader warm-up failed; the read compiles what it needs", exc_info=True)
        finally:
            self._reader.set()

    def wait_reader(self) -> float:
        """Wait for the reader's kernels; returns the seconds waited."""
        t0 = time.perf_counter()
        self._reader.wait()
        return time.perf_counter() - t0

    def wait(self) -> float:
        """Wait for all of them; returns the seconds waited."""
        t0 = time.perf_counter()
        self._thread.join()
        return time.perf_counter() - t0


def recorded_recon_settings(path: str | Path) -> dict | None:
    """The estimator settings a session recording was reconstructed with: ``run.json``'s resolved
    ``recon`` beside it (the pulse width the live maps used, also when it was measured), else the
    header's requested ``SPDepth_Recon``; None for files that are not our recordings. A damaged
    tag or file is a ``RecordingError`` naming it."""
    import json

    from spdepth.acq.ptu import RECON_TAG, read_layout
    from spdepth.acq.readers import sniff_kind

    if sniff_kind(path) != "ptu":
        return None
    raw = read_layout(path).tags.get(RECON_TAG)
    if raw is None:
        return None
    where = f"{path}: header tag {RECON_TAG}"
    try:
        run = read_run_record(Path(path).parent)
    except RecordingError:
        run = None        # a run cut before its end has no (or a half) run.json: the header holds
    if run is not None and run.get("recon"):
        raw, where = run["recon"], f"{Path(path).parent / RUN_JSON}: field recon"
    try:
        d = json.loads(raw) if isinstance(raw, str) else raw
    except json.JSONDecodeError:
        raise RecordingError(f"{where} is damaged (not JSON)") from None
    if not isinstance(d, dict) or (d.get("binning") is not None and not isinstance(d["binning"], dict)):
        raise RecordingError(f"{where} is damaged (not a settings object)")
    from spdepth.recon.model import ReconSettings

    try:     # what is used from it (window, bins, pulse, response, detections kept) is checked
        ReconSettings.from_dict(d)
    except Exception as exc:  # noqa: BLE001 - any failure to parse means a damaged record
        raise RecordingError(f"{where} is damaged ({exc})") from None
    return d


def recorded_request(path: str | Path):
    """The request a session folder (or its ``recording.ptu``) was made with, typed
    (``ScanRequest``/``ReplayRequest``): from ``run.json`` when the run ended, else from the
    recording's header, where it was written before the first record. None for a recording made
    before requests were saved; a damaged one is a ``RecordingError``/``RequestError``."""
    from spdepth.acq.recording import ReplaySource
    from spdepth.acq.requests import request_from_dict

    p = Path(path)
    run = read_run_record(p)
    saved = ((run or {}).get("info") or {}).get("request")
    if saved is None:
        saved = ReplaySource(p).info.info.get("request")
    return None if saved is None else request_from_dict(saved)


def file_binning(request: FileReconRequest, time_unit_s: float, recorded: dict | None = None,
                 store=None) -> Binning | None:
    """The binning of a file reconstruction: the request's window and bins (a missing one from the
    data, ``store``, or from the recorded session settings), or None to let the estimator derive
    both."""
    if request.window_s is None and request.bin_s is None:
        if recorded and recorded.get("binning"):
            return Binning.from_dict({**recorded["binning"], "time_unit_s": time_unit_s})
        return None
    if request.window_s is not None and request.bin_s is not None:
        return Binning.from_window(time_unit_s, request.window_s, request.bin_s)
    return Binning.from_data(store.times, time_unit_s, window_s=request.window_s,
                             bin_s=request.bin_s, pulse_rms_s=request.pulse_rms_s)


def file_settings(request: FileReconRequest, time_unit_s: float, recorded: dict | None = None,
                  store=None) -> ReconSettings:
    """The estimator settings of a file reconstruction: the request's, with what it leaves open
    taken from a session recording's ``recorded`` settings (binning, the response the live maps
    used, the target) or the data (``store``: needed only when one of window and bins is given)."""
    from spdepth.recon.model import Irf, load_irf

    binning = file_binning(request, time_unit_s, recorded, store)
    pulse_rms_s, irf = request.pulse_rms_s, load_irf(request.irf) if request.irf else None
    max_photons = request.max_photons
    if recorded:
        # the response the live maps used: a shape measured on several surfaces, else a width
        if pulse_rms_s is None and irf is None and recorded.get("irf"):
            irf = Irf.from_dict(recorded["irf"])
        elif pulse_rms_s is None and irf is None and recorded.get("pulse_rms_s"):
            pulse_rms_s = float(recorded["pulse_rms_s"])
        if max_photons is None and recorded.get("max_photons"):
            max_photons = int(recorded["max_photons"])
    return ReconSettings(method=request.method, binning=binning, pulse_rms_s=pulse_rms_s,
                         irf=irf, max_photons=max_photons, reflectors=request.reflectors,
                         max_reflectors=request.max_reflectors, false_alarm=request.false_alarm,
                         neighbour_false_alarm=request.neighbour_false_alarm)


def reconstruct_file(request: FileReconRequest, progress=None,
                     notice: Callable[[str], None] | None = None, spreads: bool = True) -> FileResult:
    """Read ``request.input``, reconstruct it, write the outputs it names (``out`` .npz, ``png``,
    ``save_irf``), and return the maps with their summary. A session's own recording is read with
    its recorded settings unless the request overrides them. Raises ``InputError``/
    ``RecordingError`` naming the file for what cannot be read. ``notice(text)``: told what a first
    run compiles apart (:class:`KernelWarmUp`). ``spreads`` False: the maps' uncertainties are the
    estimator's own, without the return test's spreads (``recon.estimate.reconstruct``), for a
    caller that uses the summary alone and writes no map (``spdepth recon`` without outputs)."""
    from spdepth.acq.readers import read_photons
    from spdepth.recon.estimate import reconstruct

    warm = KernelWarmUp(request, notice, spreads)
    load_s = warm.wait_reader()
    t0 = time.perf_counter()
    result = read_photons(request.input, time_unit_s=request.time_unit_s, mat_var=request.mat_var,
                          channel=request.channel, keep=request.max_photons)
    if result.counts is not None and request.max_photons is not None:
        raise RequestError(f"{request.input}: a histogram cube keeps no detection order, so "
                           f"--max-photons (the first N detections) does not apply")
    counts, pileup = file_counts(request, result)
    # counts (a cube, or a corrected photon list) go to the estimators as (bin, count) pairs
    store = result.store if counts is None else counts
    if (store.n_photons if counts is None else counts.n_detections) == 0:
        raise InputError(f"{request.input}: holds no photons")
    recorded = recorded_recon_settings(request.input) if result.kind == "ptu" else None
    settings = file_settings(request, store.time_unit_s, recorded, store)
    binning = settings.binning
    if binning is not None and request.window_s is not None:
        lo, hi = binning.window_start, binning.window_stop
        inside = np.count_nonzero((store.times >= lo) & (store.times < hi))
        if inside == 0:
            from spdepth.acq.report import ps_text, window_text

            unit_ps = store.time_unit_s * 1e12
            raise InputError(f"{request.input}: no detections in the window "
                             f"{window_text(lo * unit_ps, hi * unit_ps)} (the file's detections "
                             f"span {ps_text(store.times.min() * unit_ps)} to "
                             f"{ps_text(store.times.max() * unit_ps)} ps)")
    if counts is not None and settings.max_photons is not None:
        # counts of a session's recording come from its store: its first target already
        settings = replace(settings, max_photons=None)
    read_s = time.perf_counter() - t0
    set_threads(request)
    load_s += warm.wait()
    t1 = time.perf_counter()
    maps = reconstruct(store, settings, progress=progress, spreads=spreads)
    recon_s = time.perf_counter() - t1
    return file_result(request, maps, result, read_s=read_s, recon_s=recon_s, pileup=pileup, load_s=load_s)


def set_threads(request: FileReconRequest) -> None:
    """Numba's threads for the reconstruction (``--threads``; None: leave them)."""
    if request.threads is not None:
        import numba

        if request.threads > numba.config.NUMBA_NUM_THREADS:
            raise RequestError(f"--threads {request.threads}: this machine allows at most "
                               f"{numba.config.NUMBA_NUM_THREADS}")
        numba.set_num_threads(request.threads)


def file_result(request: FileReconRequest, maps, read, *, read_s: float = 0.0,
                recon_s: float = 0.0, photons_in_file: int | None = None,
                pileup: dict | None = None, load_s: float = 0.0) -> FileResult:
    """A file's reconstructed maps finished as ``spdepth recon`` finishes them: the scan geometry
    and range offset added, the outputs the request names written (npz, png, pulse shape, points)
    and the summary made. ``read``: the reader's ``ReadResult`` (its ``store`` may be None when
    the photons were read in blocks elsewhere; then give ``photons_in_file``; a cube's are its
    ``counts``). ``pileup``: the pile-up decision (:func:`file_counts`). The pulse model's
    dispersion, where the maps' uncertainties were scaled by it (``recon.detect.with_dispersion``),
    is in the summary, and in a note when the model's width is off by more than DISPERSION_OFF."""
    from spdepth.recon import estimators

    store = read.store
    maps = _with_geometry_and_offset(maps, request, maps.shape, read.meta)
    if pileup is not None and pileup["applied"]:
        # the maps say how their counts were corrected (a decision not to is in the summary), and
        # their detections used are as detected, not the corrected counts the estimator saw
        raw = CountStore.from_photons(read.store) if read.counts is None else read.counts
        b = Binning.from_dict(maps.settings["binning"])
        maps = replace(maps, settings={**maps.settings, "pileup": pileup},
                       photons=np.rint(raw.in_window(b.window_start, b.window_stop).detections())
                       .astype(np.int64))
    used = maps.settings
    used_binning = Binning.from_dict(used["binning"])
    irf_used = _irf_used(used)
    notes = tuple(read.notes)
    if pileup is not None and (pileup["applied"] or pileup.get("max_per_period", 0) > PILEUP_THRESHOLD):
        notes += (f"pile-up: {pileup['reason']}",)
    if photons_in_file is None:
        recorded_in = (read.meta or {}).get("photons_in_file")
        photons_in_file = int(recorded_in) if recorded_in is not None else _photons_in(read)
    account = photon_account(request.input, read, maps, photons_in_file)
    if account and int(np.sum(maps.photons)) < photons_in_file:
        notes += (account,)          # said on every run that left detections out
    h, w = maps.shape
    per_pixel = float(np.sum(maps.photons)) / max(1, h * w)
    neighbours = estimators.names(pixelwise=False)
    if read.is_image and request.method not in neighbours and neighbours and per_pixel < SPARSE_PER_PIXEL:
        notes += (f"about {per_pixel:.1f} detections per pixel: too few for a pixel on its own; "
                  f"--method {' or '.join(neighbours)} uses the neighbours",)
    dispersion = maps.settings.get("pulse_dispersion")
    if dispersion is not None and abs(math.log(dispersion["width_ratio"])) > math.log(DISPERSION_OFF):
        notes += (dispersion_note(dispersion, request.pulse_rms_s is not None and request.irf is None),)
    res = FileResult(request, maps, store, used_binning, used.get("pulse_rms_s"),
                     irf_used if used.get("irf") else None, read.is_image, read.kind,
                     notes, read_s, recon_s, pileup=pileup,
                     photons_in_file=photons_in_file, load_s=load_s)
    _write_file_outputs(res, read)
    res.summary = _file_summary(res, read)
    res.summary["photons_account"] = account
    res.summary["pulse_dispersion"] = None if dispersion is None else \
        {k: dispersion.get(k) for k in ("dispersion", "pixels", "width_ratio", "width_ratio_se", "score")}
    return res


#: The pulse model's width, as the detections about their depths say it (its dispersion's square
#: root), is noted when off by more than this factor either way.
DISPERSION_OFF = 1.25


def dispersion_note(d: dict, stated: bool) -> str:
    """What a dispersion ``d`` (``recon.detect.dispersion_of``) off the model means, in a line;
    ``stated``: the pulse was the user's (``--pulse-rms-ps``)."""
    r = d["width_ratio"]
    closer = r < 1.0
    # ml's is about the width ratio squared; uos's filter's is not (its slope's ratio counts twice)
    like = f": as from a response {r:.2f} times its width" if d.get("score", "the likelihood's") == "the likelihood's" \
        else f", of {d['score']} score"
    # lmf's (recon.detect.TEMPERED_METHODS) tempers the test's likelihood spreads by it instead
    scaled = (f"the likelihood's spreads of every depth are tempered by it and the estimator's own "
              f"uncertainty scaled by {r:.2f}") if "tempered" in d.get("applied", "") else \
        f"every depth's uncertainty is scaled by {r:.2f} for it"
    head = (f"the detections lie {'closer to' if closer else 'wider about'} their depths than the pulse model "
            f"says (dispersion {d['dispersion']:.2f} over {d['pixels']} pixels{like}); {scaled}, and the depths "
            f"themselves are those of a model {'wider' if closer else 'narrower'} than the returns")
    if stated:
        return head + f" (--pulse-rms-ps may be too {'wide' if closer else 'narrow'}: without it the pulse is " \
                      "measured from the data)"
    return head + " (the pulse width measured from the data does not fit its returns)"


def _photons_in(read) -> int:
    """Detections a reader found: a photon list's, or a cube's counts."""
    return read.store.n_photons if read.store is not None else int(round(read.counts.n_detections))


def pileup_decided(request: FileReconRequest, periods_known: bool, cube: bool) -> tuple[bool, dict | None]:
    """(True, the record) when the pile-up decision needs no data: the periods unknown and not
    asked for (None), ``--max-photons`` on a photon list (the first N detections' periods are not
    known: not corrected), ``--pileup off``; (False, None) when it needs each pixel's histogram."""
    if not periods_known and request.pileup == "auto":
        return True, None
    if request.max_photons is not None and not cube:
        if request.pileup == "on":
            raise RequestError(f"{request.input}: --pileup on needs every detection: drop --max-photons")
        return True, {"mode": request.pileup, "applied": False,
                      "reason": "--max-photons keeps the first N detections: not corrected"}
    if request.pileup == "off":
        return True, {"mode": "off", "applied": False, "reason": "switched off"}
    return False, None


def file_counts(request: FileReconRequest, result):
    """The counts a file is estimated from (None: its photon list as read) and the pile-up record
    (None when the file's laser periods are unknown and correction was not asked for).

    The periods come from ``--periods`` (per frame of a cube), else the file; Coates' correction
    (``recon.pileup``) runs on the whole histogram at the file's own resolution, before any
    window, since detections before the window shadow it too."""
    from spdepth.recon.pileup import Detector, correct_pileup

    counts = result.counts
    frames = int(result.meta.get("frames", 1) or 1) if counts is not None else 1
    periods = result.periods if request.periods is None else np.full(
        int(np.prod(result.shape)), float(request.periods) * frames)
    if periods is None and counts is not None:
        periods = counts.periods          # a cube whose file records them
    decided, record = pileup_decided(request, periods is not None, counts is not None)
    if decided:
        return counts, record
    # a photon list is histogrammed only if the correction applies (correct_pileup)
    counts = result.store if counts is None else replace(counts, periods=periods)
    unit_s = counts.time_unit_s
    period_s = result.meta.get("period_s") or (1.0 / result.meta["sync_rate_hz"]
                                               if result.meta.get("sync_rate_hz") else None)
    if request.dead_time_s is not None and period_s is None:
        raise RequestError(f"{request.input}: --dead-time-ns needs the laser period, which the file "
                           f"does not record")
    detector = Detector(None if period_s is None else period_s / unit_s,
                        None if request.dead_time_s is None else request.dead_time_s / unit_s)
    corrected, record = correct_pileup(counts, request.pileup, detector, periods=periods)
    if not record["applied"]:
        return result.counts, record
    return corrected, record


def photon_account(path, read, maps, in_file: int) -> str:
    """One line: the detections in the file, those used, and why the rest were not (outside
    lines, pixels or dwells; outside the window or past the per-pixel limit; kept by a session).
    From the reader's meta and the maps only, so a file read in blocks elsewhere says the same."""
    meta = read.meta or {}
    used = int(np.sum(maps.photons))
    parts = []
    rest = in_file - used
    for key, what in (("photons_outside_lines", "outside the scan lines"),
                      ("photons_outside_pixels", "outside any pixel"),
                      ("photons_outside_dwells", "outside any complete dwell (fly-back, parked mirror, cut passes)")):
        if meta.get(key):
            parts.append(f"{meta[key]} {what}")
            rest -= int(meta[key])
    if rest > 0:
        if "kept_per_pixel" in meta:
            parts.append(f"{rest} beyond the first {meta['kept_per_pixel']} in-window per pixel "
                         f"({meta['kept_why']}) or outside the window")
        elif maps.settings.get("max_photons"):
            parts.append(f"{rest} outside the window or beyond the first {maps.settings['max_photons']} "
                         f"per pixel (--target)")
        else:
            parts.append(f"{rest} outside the window")
    return (f"{Path(path).name}: {in_file} detections in the file, {used} used"
            + (": " + "; ".join(parts) if parts else ""))


def _with_geometry_and_offset(maps, request: FileReconRequest, shape, meta: dict | None = None):
    """The maps with their scan geometry in the settings (``--fov-deg``, else a sensor's field of
    view from the file (a cube's ``fov_deg``, or ``pixel_pitch_m`` and ``focal_length_m``), else a
    session recording's plan) and the range offset of gated data added to depth and time of
    flight."""
    from spdepth.acq.plan import ScanPlan
    from spdepth.acq.points import GEOMETRY_KEY, ScanGeometry, range_offset_m
    from spdepth.recon.maps import C_M_PER_S

    settings = dict(maps.settings)
    geometry = None
    meta = meta or {}
    sensor = sensor_fov_deg(shape, meta)
    if sensor is not None:
        settings["sensor"] = {k: meta[k] for k in ("fov_deg", "pixel_pitch_m", "focal_length_m")
                              if k in meta}
    if request.fov_deg is not None:
        geometry = ScanGeometry.from_fov(shape, request.fov_deg)
    elif sensor is not None:
        geometry = ScanGeometry.from_fov(shape, sensor)
    elif Path(request.input).suffix.lower() == ".ptu":
        try:
            run = read_run_record(Path(request.input).parent)
            p = ScanPlan.from_dict(run["plan"]) if run is not None else None
            if p is not None and p.shape == tuple(shape):
                geometry = ScanGeometry.from_plan(p)
        except (ValueError, TypeError, KeyError, AttributeError, InputError, RecordingError):
            geometry = None          # a run.json cut short: no geometry rather than a wrong one
    if geometry is not None:
        settings[GEOMETRY_KEY] = geometry.to_dict()
    offset = range_offset_m(request.range_offset_m, request.gate_delay_s)
    changes = {"settings": settings}
    if offset:
        settings["range_offset_m"] = offset
        changes["depth_m"] = maps.depth_m + offset
        changes["tof_s"] = maps.tof_s + 2 * offset / C_M_PER_S
    return replace(maps, **changes)


def sensor_fov_deg(shape, meta: dict) -> tuple[float, float] | None:
    """(x, y) field of view in degrees of an array sensor a file describes: ``fov_deg`` (one
    number: square; or (x, y)), else from ``pixel_pitch_m`` and
    ``focal_length_m`` (``2 atan(n pitch / 2 f)`` per axis); None when it says neither."""
    h, w = shape
    fov = meta.get("fov_deg")
    if fov is not None:
        fx, fy = (float(fov), float(fov)) if np.ndim(fov) == 0 else (float(fov[0]), float(fov[1]))
        return fx, fy
    pitch, focal = meta.get("pixel_pitch_m"), meta.get("focal_length_m")
    if pitch and focal:
        deg = lambda n: math.degrees(2 * math.atan(n * float(pitch) / (2 * float(focal))))  # noqa: E731
        return deg(w), deg(h)
    return None


def _irf_used(settings: dict):
    """The pulse shape a reconstruction used, as an Irf (a sampled Gaussian for a Gaussian pulse)."""
    from spdepth.recon.model import Irf, gaussian_irf

    irf = settings.get("irf")
    if irf:
        return Irf.from_dict(irf)
    return gaussian_irf(settings["pulse_rms_s"], source=f"Gaussian, {settings['pulse_source']}")


def _write_file_outputs(res: FileResult, read) -> None:
    req, maps = res.request, res.maps
    if req.out:
        maps.save_npz(req.out)
    if req.ply or req.las:
        from spdepth.acq.points import geometry_of, write_points

        geometry = geometry_of(maps)
        if geometry is None:
            raise RequestError(f"{req.input} holds no scan geometry: give --fov-deg to write "
                               f"points (--ply/--las)")
        write_points(maps, geometry, ply=req.ply, las=req.las, note=Path(req.input).name)
    irf_used = _irf_used(maps.settings)
    if req.save_irf:
        from spdepth.recon.model import save_irf

        save_irf(irf_used, req.save_irf)
    if req.png:
        from spdepth.acq.report import render_maps_png, render_point_png, window_text

        b = res.binning
        unit_ps = b.time_unit_s * 1e12
        photons = int(np.sum(maps.photons))
        title = (f"{Path(req.input).name}: {req.method}, {photons} photons, "
                 f"window {window_text(b.window_start * unit_ps, b.window_stop * unit_ps)}")
        t_irf, c_irf = irf_used.arrays()
        drawn = (t_irf, c_irf, f"{maps.settings['pulse_source']}: RMS {irf_used.rms_s * 1e12:.0f} ps")
        if res.is_image:
            render_maps_png(req.png, maps, title=title, irf=drawn)
        else:
            shown = res.store.first_in_window(b.window_start, b.window_stop,
                                               maps.settings.get("max_photons"))
            render_point_png(req.png, shown.times * res.store.time_unit_s,
                             tof_s=float(np.ravel(maps.tof_s)[0]), title=title, irf=drawn)


def _small_settings(settings: dict) -> dict:
    """A result's settings without its sampled arrays (the pulse shape lives in the npz)."""
    out = {}
    for k, v in settings.items():
        if k == "irf" and isinstance(v, dict):
            v = {kk: vv for kk, vv in v.items() if kk not in ("times_s", "counts")}
        elif k == "kernel" and isinstance(v, dict):
            v = {kk: vv for kk, vv in v.items() if not isinstance(vv, (list, tuple, np.ndarray))}
        out[k] = v
    return out


def _file_summary(res: FileResult, read) -> dict:
    maps, b = res.maps, res.binning
    unit_ps = b.time_unit_s * 1e12
    depth = np.asarray(maps.depth_m, dtype=float)
    finite = depth[np.isfinite(depth)]
    req = res.request
    h, w = maps.shape
    return {
        "input": req.input, "kind": res.kind, "is_image": res.is_image,
        "shape": [h, w], "pixels": h * w,
        "pixels_with_estimate": int(np.isfinite(depth).sum() if depth.ndim == 2
                                    else np.isfinite(depth).any(axis=0).sum()),
        "photons": int(np.sum(maps.photons)), "photons_in_file": res.photons_in_file,
        "method": req.method, "read_s": round(res.read_s, 4), "recon_s": round(res.recon_s, 4),
        "load_s": round(res.load_s, 4),
        "time_unit_ps": unit_ps, "window_ps": [b.window_start * unit_ps, b.window_stop * unit_ps],
        "bin_ps": b.bin_width * unit_ps, "n_bins": b.n_bins,
        "pulse_rms_ps": None if res.pulse_rms_s is None else res.pulse_rms_s * 1e12,
        "max_photons": maps.settings.get("max_photons"),
        "settings": jsonable(_small_settings(maps.settings)),
        "depth_m_median": float(np.median(finite)) if finite.size else None,
        "out": req.out, "png": req.png, "save_irf": req.save_irf, "ply": req.ply, "las": req.las,
        "range_offset_m": maps.settings.get("range_offset_m", 0.0), "request": req.to_dict(),
        "source": jsonable(read.meta), "notes": list(res.notes), "pileup": jsonable(res.pileup),
    }


__all__ = ["OutputDir", "live_pileup", "new_run_dir", "open_instruments", "scan_plan", "scan_settings",
           "build_session", "finish_session", "no_pixel_cause", "FileResult", "reconstruct_file", "file_binning",
           "file_settings", "file_result", "set_threads", "file_counts", "pileup_decided", "sensor_fov_deg",
           "recorded_recon_settings", "recorded_request", "read_run_record", "RUN_JSON", "SESSION_FILES"]
