"""An acquisition session: one scan from plan to files, from any source (live scan or replay).

A :class:`Session` consumes a :class:`~spdepth.acq.sources.Source` (``acq.scan_source.ScanSource``:
our galvo and tagger; ``acq.recording.ReplaySource``: a recording; next, vendor taggers) through
one interface and cannot tell them apart. The source delivers chunks of events pass by pass and
reports faults; the session owns the state machine, the per-pixel store, the live
reconstruction, the flags, the snapshots its subscribers get and the files. States::

    idle -> armed -> running <-> paused -> finishing -> done | aborted | failed

Pause takes effect at a pixel boundary (the source finishes the pixel it is on; the stream is
drained up to it); resume acquires whatever is still short. Abort is accepted in any state before
finishing. Cleanup always runs, on an exception and on Ctrl-C too: the source is closed (galvo
stopped and parked, tag stream stopped, recording flushed and closed), the live reconstruction's
worker ended, the maps and ``run.json`` written.

How the target is reached (live, ``ScanSource``; the same loop serves the first pass, resume and
re-acquisition): while pixels are short of ``plan.target`` in-window detections and not flagged,
the short pixels are grouped into rectangles (``acq.plan.pass_regions``) and each is one galvo
pass. A lost span (FIFO overrun, USB error, reconnect) stops the current pass at once, and the
next pass scans the affected lines again. Each pixel keeps its first ``target`` in-window
detections of complete dwells (``acq.store``: a rescan tops up, nothing is counted twice).
Pixels are flagged (:class:`AcqFlag`) when a gated dwell hits the dwell limit, when the pass
budget or the time limit runs out, or when the session ends first.

Files: ``maps.npz`` holds the maps and the ``acq_flags`` map (uint8 :class:`AcqFlag` per pixel),
the laser time per pixel (``exposure_s``) and the scan angles (``row_deg``, ``col_deg``); a scan
of more than ``SPARSE_MIN_PIXELS`` pixels that reached fewer than half of them (a time limit on
a large frame) keeps its frame-sized maps (all but ``acq_flags``) only at the pixels reached
(``layout`` "pixels", see ``recon.maps.sparse_arrays``; ``DepthMaps.load_npz`` and
``recon.maps.npz_arrays`` give the full maps back). Pixels never reached (no complete dwell, nothing kept) are not reconstructed:
NaN depth, background and uncertainty, NO_PHOTONS, NaN exposure, and their ``acq_flags`` say why;
``run.json`` the settings, statistics, counts per flag reason (``flag_reasons``), the source's
``warnings`` and every fault seen (``faults_seen``, :class:`~spdepth.acq.sources.FaultRecord`).
"""

from __future__ import annotations

import functools
import json
import logging
import os
import threading
import time
import zipfile
from dataclasses import dataclass, field, replace
from enum import Enum
from pathlib import Path
from typing import Callable

import numpy as np

from spdepth.acq.assign import PassGeometry
from spdepth.acq.errors import OutputError, RequestError, SessionStateError
from spdepth.acq.flags import ACQUIRING, AcqFlag
from spdepth.acq.jsonable import jsonable, write_json_atomic
from spdepth.acq.live_recon import LiveRecon
from spdepth.acq.plan import ScanPlan
from spdepth.acq.recording import RecordedEnd
from spdepth.acq.sources import HEALTH_RECENT_S, FaultRecord, Source
from spdepth.acq.store import PixelStore
from spdepth.drivers.events import EVENT_DTYPE
from spdepth.recon.model import ReconSettings

log = logging.getLogger(__name__)

SNAPSHOT_MAX_HZ = 30.0
FLUSH_WHILE_PAUSED_S = 0.5
OUTPUT_CHECK_S = 0.5
"""How often the session checks that its output folder still exists."""
SPARSE_MIN_PIXELS = 1 << 20
"""A scan of more pixels than this that reached fewer than half of them writes ``maps.npz`` in
the sparse layout (``recon.maps.sparse_arrays``): its maps at the pixels reached only."""
MAX_FAULTS_LISTED = 1000
"""Faults of one kind listed in ``faults_seen``; more are only counted (``faults_not_listed``),
so a flood of survived read anomalies cannot bloat ``run.json``."""


class SessionState(str, Enum):
    """Where a session is in its life."""

    IDLE = "idle"
    """Created, not started."""
    ARMED = "armed"
    """Devices configured, stream and recording open, scan not yet moving."""
    RUNNING = "running"
    """Scanning (or replaying)."""
    PAUSED = "paused"
    """Stopped at a pixel boundary; resume continues with the pixels still short."""
    FINISHING = "finishing"
    """Stream closed; last pixels reconstructed, files written."""
    DONE = "done"
    """Every pixel complete or flagged."""
    ABORTED = "aborted"
    """Stopped by the user; what was recorded is kept."""
    FAILED = "failed"
    """Ended by an error (``Session.error``); what was recorded is kept."""


_TRANSITIONS = {
    SessionState.IDLE: {SessionState.ARMED, SessionState.FINISHING},
    SessionState.ARMED: {SessionState.RUNNING, SessionState.FINISHING},
    SessionState.RUNNING: {SessionState.PAUSED, SessionState.FINISHING},
    SessionState.PAUSED: {SessionState.RUNNING, SessionState.FINISHING},
    SessionState.FINISHING: {SessionState.DONE, SessionState.ABORTED, SessionState.FAILED},
    SessionState.DONE: set(), SessionState.ABORTED: set(), SessionState.FAILED: set(),
}
_TERMINAL = {SessionState.DONE, SessionState.ABORTED, SessionState.FAILED}


@dataclass(frozen=True)
class Snapshot:
    """What subscribers see: the state of the scan and copies of the maps (H x W).

    depth_m, background, signal, uncertainty_s: the live reconstruction (NaN: not yet), copied
    between two reconstruction batches (a pixel's depth never comes without its background);
    with several surfaces per pixel depth_m, signal and uncertainty_s are (K, H, W), nearest first,
    and ``surfaces`` (H, W) counts those found, ``weak`` (K, H, W) marks those background alone
    could have made (both None for one surface per pixel).
    counts: in-window detections kept per pixel; acq_flags: :class:`AcqFlag` of final pixels
    (``ACQUIRING`` while a pixel is still being acquired); final: pixels complete or flagged.
    faults: ``FaultRecord.to_dict()`` of each fault so far.
    """

    state: str
    elapsed_s: float
    pixels_total: int
    pixels_final: int
    detections: int
    detections_per_s: float
    lost_spans: int
    lost_records: int
    eta_s: float | None
    recon_lag: int
    passes: int
    depth_m: np.ndarray
    background: np.ndarray
    signal: np.ndarray
    uncertainty_s: np.ndarray
    counts: np.ndarray
    acq_flags: np.ndarray
    faults: tuple = ()
    error: str | None = None
    exposure_s: np.ndarray | None = None
    """Laser time each pixel's kept detections were collected over, s (NaN: none, or the laser
    period is not known): background detections over it are a rate."""
    surfaces: np.ndarray | None = None
    weak: np.ndarray | None = None
    running_s: float = 0.0
    """Time since scanning (or replaying) began, s: ``detections_per_s`` counts over it, and
    ``elapsed_s`` minus it went on preparing (on a fresh install numba compiles the kernels)."""
    pixels_complete: int = 0
    """Final pixels that reached the target (``AcqFlag.COMPLETE``): ``pixels_final`` less those
    flagged short (a time limit flags every pixel not reached yet)."""
    health: dict = field(default_factory=dict)
    reconstructed: np.ndarray | None = None
    """(H, W) pixels the live reconstruction has finished: their estimate (or its absence, a
    miss) is final."""
    """Per device ("galvo", "tagger"), from the source: "ok", "recovering" (a loss, reconnect or
    fault in the last HEALTH_RECENT_S, or since the caller's previous snapshot: ``snapshot``'s
    ``faults_since_s``), "failed" (the session ended on that device's error) or "replay"."""


class _Aborted(Exception):
    """Internal: unwinds the acquisition thread after ``abort()``."""


class Session:
    """One scan from a :class:`~spdepth.acq.sources.Source`: a live scan
    (``acq.scan_source.ScanSource``), a replay (``acq.recording.ReplaySource``) or any other
    source; the session cannot tell them apart. ``acq.api.build_session`` builds one from a request.

    plan:      what to scan; for a replay, the recorded plan with the replay's target.
    settings:  estimator settings with a fixed binning (window and bins in tagger units) and
               ``max_photons`` equal to ``plan.target`` (set here when None).
    source:    where the events come from.
    out_dir:   where the source's files (a live scan's ``recording.ptu``), ``events.jsonl``,
               ``maps.npz`` and ``run.json`` go; None keeps everything in memory (tests, the
               GUI's dry runs).
    gate_target: the count the galvo gated on when the stream was recorded (replay of a gated
               recording; defaults to the source's, ``plan.target`` for a live gated scan): a
               complete dwell with fewer detections ended at the dwell limit.
    info:      extra JSON-able facts for ``run.json`` (the request, scene, seed, ...).

    Building a session starts no thread: ``start`` (or ``run``) starts the session's thread and
    the live reconstruction's worker, and both end with the session.
    """

    def __init__(self, plan: ScanPlan, settings: ReconSettings, source: Source, *,
                 out_dir: str | Path | None = None, gate_target: int | None = None,
                 info: dict | None = None):
        if source is None or not hasattr(source, "run"):
            raise RequestError(f"a session needs a source (a scan, a replay, ...), got {source!r}")
        if settings.binning is None:
            raise RequestError("a session needs a fixed binning (window and bin width)")
        if settings.max_photons is None:
            settings = replace(settings, max_photons=plan.target)
        if settings.max_photons != plan.target:
            raise RequestError(f"recon max_photons {settings.max_photons} differs from the target "
                               f"{plan.target}")
        self.source: Source = source
        self.plan = plan
        self.out_dir = Path(out_dir) if out_dir is not None else None
        self.info = dict(info or {})
        if gate_target is None:
            gate_target = source.default_gate_target(plan)
        self.gate_target = gate_target
        b = settings.binning
        self.store = PixelStore(plan.shape, plan.target,
                                (int(np.floor(b.window_start)), int(np.ceil(b.window_stop))),
                                b.time_unit_s)
        self.live_recon = LiveRecon(self.store, settings)
        self.acq_flags = np.full(plan.shape[0] * plan.shape[1], ACQUIRING, np.uint8)
        self.final = np.zeros(plan.shape[0] * plan.shape[1], bool)
        self.lost: list = []
        self.faults: list[FaultRecord] = []
        self.faults_not_listed: dict[str, int] = {}
        self.passes = 0
        self.detections = 0
        self.error: BaseException | None = None
        self.stream_s: float | None = None
        self._state = SessionState.IDLE
        self._state_lock = threading.RLock()
        self._state_changed = threading.Condition(self._state_lock)
        self._fault_lock = threading.Lock()
        self._pause_req = False
        self._abort_req = False
        self._ended = threading.Event()
        self._thread: threading.Thread | None = None
        self._t0 = time.monotonic()
        self._t_running: float | None = None
        self._t_end: float | None = None
        self._last_photon_t: float | None = None
        self._next_output_check = 0.0
        self._stop_reason: AcqFlag = AcqFlag.INCOMPLETE
        self._n_complete = 0
        self._events_log = None
        self._exposure_end: np.ndarray | None = None
        self._host = _Host(self)

    @property
    def recorder(self):
        """The source's recording (``acq.recording.Recorder``), if it writes one."""
        return getattr(self.source, "recorder", None)

    # ---- commands (any thread) -------------------------------------------------------------------
    @property
    def state(self) -> SessionState:
        return self._state

    def start(self) -> "Session":
        """Arm and start the scan on the session's own thread; returns at once."""
        with self._state_lock:
            if self._state != SessionState.IDLE or self._thread is not None:
                raise SessionStateError(f"cannot start a session that is {self._state.value}")
            self.live_recon.start()
            self._thread = threading.Thread(target=self._main, name="acq-session", daemon=True)
            self._thread.start()
        return self

    def run(self) -> SessionState:
        """Start and wait for the end; Ctrl-C aborts cleanly (everything recorded is kept) and is
        re-raised once the files are written."""
        self.start()
        try:
            return self.wait()
        except KeyboardInterrupt:
            self.abort()
            self.wait()
            raise

    def wait(self, timeout_s: float | None = None) -> SessionState:
        """Block until the session has ended (or ``timeout_s``); returns the state."""
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        while not self._ended.is_set():
            step = 0.1 if deadline is None else min(0.1, max(0.0, deadline - time.monotonic()))
            if self._ended.wait(step) or (deadline is not None and time.monotonic() >= deadline):
                break
        if self._ended.is_set() and self._thread is not None \
                and self._thread is not threading.current_thread():
            self._thread.join()          # its last steps after the end was signalled
        return self._state

    def wait_for_state(self, state: SessionState, timeout_s: float = 10.0) -> bool:
        with self._state_changed:
            return self._state_changed.wait_for(
                lambda: self._state == state or self._state in _TERMINAL, timeout_s) \
                and self._state == state

    def pause(self) -> None:
        """Ask the scan to stop at the next pixel boundary (state becomes PAUSED once the pass
        is drained)."""
        with self._state_lock:
            if self._state not in (SessionState.RUNNING, SessionState.ARMED) or self._abort_req:
                raise SessionStateError(f"cannot pause a session that is {self._state.value}")
            self._pause_req = True
            self._state_changed.notify_all()

    def resume(self) -> None:
        """Continue a paused session (or cancel a pause not yet taken)."""
        with self._state_lock:
            if not (self._state == SessionState.PAUSED or self._pause_req) or self._abort_req:
                raise SessionStateError(f"cannot resume a session that is {self._state.value}")
            self._pause_req = False
            self._state_changed.notify_all()

    def abort(self) -> None:
        """Stop now; cleanup and files follow on the session's thread (``wait`` for them)."""
        with self._state_lock:
            if self._state in _TERMINAL:
                raise SessionStateError(f"cannot abort a session that is {self._state.value}")
            self._abort_req = True
            self._state_changed.notify_all()
            started = self._thread is not None
            if not started:   # never started: nothing to clean up but the files
                self._thread = threading.Thread(target=self._main, name="acq-session",
                                                daemon=True)
                self._thread.start()

    # ---- what subscribers see ------------------------------------------------------------------
    def snapshot(self, faults_since_s: float | None = None) -> Snapshot:
        """The scan as it stands now (map copies; safe from any thread).

        faults_since_s: the ``elapsed_s`` of the caller's previous snapshot. A device with a fault
        recorded after it is "recovering" in this one's ``health`` even when the fault is older
        than HEALTH_RECENT_S: a caller that looked late (a window whose paint stalled for seconds
        on a busy machine, a slow subscriber) still sees every recovery, not only those that fell
        within its looks."""
        h, w = self.plan.shape
        st = self._stats()
        n_final, n_total, running_s = st["pixels_final"], h * w, st["running_s"]
        eta = None
        if running_s > 0 and 0 < n_final < n_total and self._state not in _TERMINAL:
            eta = (n_total - n_final) * running_s / n_final
        r = self.live_recon
        maps = r.copy_maps("depth_m", "background", "signal", "uncertainty_s", "done",
                           *(("surfaces", "weak") if "surfaces" in r.fields else ()))
        maps["reconstructed"] = maps.pop("done")
        return Snapshot(
            state=self._state.value, elapsed_s=st["elapsed_s"], running_s=running_s,
            pixels_total=n_total,
            pixels_final=n_final, pixels_complete=self._n_complete, detections=self.detections,
            detections_per_s=st["detections_per_s"], lost_spans=len(self.lost),
            lost_records=st["lost_records"], eta_s=eta, recon_lag=r.lag, passes=self.passes,
            **maps, counts=self.store.count.reshape(h, w).copy(),
            acq_flags=self.acq_flags.reshape(h, w).copy(),
            faults=tuple(f.to_dict() for f in list(self.faults)),
            error=None if self.error is None else str(self.error),
            health=self._health(faults_since_s), exposure_s=self.exposure_s())

    def exposure_s(self, pixel: int | None = None):
        """(H, W) laser time, s, that each pixel's kept detections span (``PixelStore.periods``
        times the laser period); NaN for pixels with none, or when the period is not known.
        ``pixel``: that flat pixel's alone (a float). Once the session has written its files the
        map no longer changes: the same read-only array is returned (a 4096 x 4096 frame's took
        a third of a second a call)."""
        if pixel is None and self._exposure_end is not None:
            return self._exposure_end
        period = getattr(self.source, "sync_period_s", None)
        periods = self.store.periods if pixel is None else self.store.periods[pixel:pixel + 1]
        out = np.full(periods.shape, np.nan)
        if period:
            # only the pixels with periods are multiplied (a masked multiply over the whole of a
            # 4096 x 4096 frame took 0.6-0.9 s here, most of its pixels never reached)
            kept = np.flatnonzero(periods > 0)
            out[kept] = periods[kept] * float(period)
        return float(out[0]) if pixel is not None else out.reshape(self.plan.shape)

    def progress(self) -> dict:
        """What a progress bar shows, copying no map (a snapshot copies the maps, half a GB for a
        4096 x 4096 frame, which at 10 Hz took a third of the scan's speed): ``state``,
        ``pixels_complete`` (final pixels that reached the target), ``pixels_total``,
        ``detections_per_s`` and ``lost_spans``."""
        st = self._stats()
        return {"state": self._state.value, "pixels_complete": self._n_complete,
                "pixels_total": self.plan.nx * self.plan.ny,
                "detections_per_s": st["detections_per_s"], "lost_spans": len(self.lost)}

    def stats(self) -> dict:
        """The scalar figures of a snapshot (``elapsed_s``, ``running_s``, ``pixels_final``,
        ``detections_per_s``, ``lost_records``) without its copies of the maps."""
        return self._stats()

    def _stats(self) -> dict:
        now = self._t_end or time.monotonic()
        running_s = (now - self._t_running) if self._t_running else 0.0
        return {"elapsed_s": now - self._t0, "running_s": running_s,
                "pixels_final": int(np.count_nonzero(self.final)),
                "detections_per_s": self.detections / running_s if running_s > 0 else 0.0,
                "lost_records": sum(s.records_lost for s in list(self.lost))}

    def _health(self, since_s: float | None = None) -> dict:
        now = time.monotonic() - self._t0
        # t_s is rounded to the ms: a fault within a ms before the last look counts once more
        recent = [f for f in list(self.faults) if now - f.t_s < HEALTH_RECENT_S
                  or (since_s is not None and f.t_s > since_s - 1e-3)]
        failed = self.error if self._state == SessionState.FAILED else None
        return self.source.health(recent, failed)

    def subscribe(self, fn: Callable[[Snapshot], None], max_hz: float = SNAPSHOT_MAX_HZ):
        """Call ``fn(snapshot)`` from a thread of its own at most ``max_hz`` times a second, and
        once more at the end. A slow ``fn`` only skips snapshots: it always gets the latest, never
        a queue, and never slows the scan. A ``fn`` that raises is logged once and unsubscribed
        (the others go on). Returns an object whose ``close()`` unsubscribes and whose
        ``join()`` waits for the last call after the session's end."""
        return _Subscription(self, fn, max_hz)

    @property
    def ended(self) -> threading.Event:
        return self._ended

    # ---- the session's thread --------------------------------------------------------------------
    def _set_state(self, new: SessionState) -> None:
        with self._state_lock:
            if new not in _TRANSITIONS[self._state]:
                raise SessionStateError(f"session cannot go from {self._state.value} to {new.value}")
            self._state = new
            self._state_changed.notify_all()
        self._log({"event": "state", "state": new.value})
        log.info("session %s", new.value)

    def _fail(self, exc: BaseException) -> None:
        """Keep the error that ended the session and say so in one line."""
        if self.error is None:
            self.error = exc
            log.error("session failed: %s: %s", type(exc).__name__, exc)

    def _main(self) -> None:
        final = SessionState.DONE
        try:
            self._acquire()
        except _Aborted:
            final = SessionState.ABORTED
        except RecordedEnd as end:
            # a replay ends where and as the recorded session ended
            if end.state == "failed":
                self._fail(end)
                final = SessionState.FAILED
            else:
                final = SessionState.ABORTED
                self._log({"event": "replay_end", "state": end.state})
        except BaseException as exc:  # noqa: BLE001 - kept in .error, shown to every subscriber
            self._fail(exc)
            final = SessionState.FAILED
        try:
            self.source.close()
        except BaseException as exc:  # noqa: BLE001
            if final == SessionState.FAILED:
                log.warning("closing the source after the failure failed too: %s", exc)
            else:
                self._fail(exc)
                final = SessionState.FAILED
        if self._last_photon_t is not None and self.source.first_read_t is not None:
            self.stream_s = self._last_photon_t - self.source.first_read_t
        if self._abort_req and final == SessionState.DONE:
            final = SessionState.ABORTED
        try:
            if self._state != SessionState.FINISHING:
                self._set_state(SessionState.FINISHING)
            final = self._finish(final)
        except BaseException as exc:  # noqa: BLE001
            self._fail(exc)
            final = SessionState.FAILED
        finally:
            self.live_recon.close()
            self._t_end = time.monotonic()
            with self._state_lock:
                self._state = final
                self._state_changed.notify_all()
            self._log({"event": "state", "state": final.value})
            self._close_log()
            self._ended.set()

    def _acquire(self) -> None:
        if self.out_dir is not None:
            from spdepth.acq.recording import EventLog

            try:
                self.out_dir.mkdir(parents=True, exist_ok=True)
                self._events_log = EventLog(self.out_dir / "events.jsonl")
            except OSError as exc:
                raise OutputError(f"output folder {self.out_dir}: cannot write "
                                  f"({exc.strerror or exc})") from None
            self._log({"event": "session", "plan": self.plan.to_dict(),
                       "recon": self.live_recon.requested.to_dict(), "source": self.source.name})
        if self._abort_req:
            raise _Aborted
        self._set_state(SessionState.ARMED)
        self._arm()
        if self._abort_req:
            raise _Aborted
        self._set_state(SessionState.RUNNING)
        self._t_running = time.monotonic()
        self._stop_reason = self.source.run(self._host)

    def _arm(self) -> None:
        # load (or compile) the store's kernel now, not when the first photons are waiting: two
        # rows of a kind the kernel ignores give the strided field views a real stream has
        warm = np.zeros(2, dtype=EVENT_DTYPE)
        warm["kind"] = 255
        self.store.feed(warm)
        # the estimator's kernels load (and its maps are made) on a thread while the source arms
        # and the first pixels are scanned: a time limit counts from RUNNING, so what is done
        # while armed adds to the wait (a 4096 x 4096 scan waited 0.4-1.1 s here)
        self.live_recon.warm_up(wait=False)
        self.source.arm(self._host)
        if self.source.warnings:
            self._log({"event": "warnings", "warnings": list(self.source.warnings)})

    # ---- what a source calls (through _Host) -----------------------------------------------------
    def _needy(self) -> np.ndarray:
        return (~self.final & (self.store.count < self.plan.target)).reshape(self.plan.shape)

    def _time_up(self) -> bool:
        t = self.plan.time_limit_s
        return t is not None and self._t_running is not None and time.monotonic() - self._t_running > t

    def _checkpoint(self) -> None:
        """Block while a pause is requested; raise _Aborted on abort, a live-recon error, or an
        OutputError when the output folder went away."""
        self._check_health()
        if self._abort_req:
            raise _Aborted
        if not self._pause_req:
            return
        self._set_state(SessionState.PAUSED)
        with self._state_changed:
            while not self._state_changed.wait_for(lambda: not self._pause_req or self._abort_req,
                                                   timeout=FLUSH_WHILE_PAUSED_S):
                self._flush_files()
        if self._abort_req:
            raise _Aborted
        self._set_state(SessionState.RUNNING)

    def _check_health(self) -> None:
        self.live_recon.raise_if_failed()
        now = time.monotonic()
        if self.out_dir is not None and now >= self._next_output_check:
            self._next_output_check = now + OUTPUT_CHECK_S
            if not self.out_dir.is_dir():
                raise OutputError(f"output folder {self.out_dir} was removed while the session "
                                  "wrote into it")

    def _flush_files(self) -> None:
        self._check_health()
        self.source.flush()
        if self._events_log is not None:
            self._events_log.flush_if_due()

    def _begin_pass(self, geom: PassGeometry, position: int | None) -> None:
        self.store.begin_pass(geom)
        self.passes += 1
        self._log({"event": "pass", "geometry": geom.to_dict(), "record": position})

    def _end_pass(self, position: int | None, lost_end: int | None = None) -> None:
        self.store.end_pass()
        if position is not None:
            self._log({"event": "pass_end", "record": position,
                       **({} if lost_end is None else {"lost_end": lost_end})})

    def _process(self, chunk: np.ndarray) -> bool:
        """Feed a chunk; hand pixels that became final to the reconstruction. Returns whether
        the chunk held a lost span."""
        seen = self.store.photons_seen
        acc = self.store.feed(chunk)
        if self.store.photons_seen > seen:
            self.detections = self.store.photons_seen
            self._last_photon_t = time.monotonic()
        px = acc.closed_pixel
        if px.size:
            if self.gate_target is not None:
                short = px[acc.closed_total < self.gate_target]
                short = short[~self.final[short]]
                self.acq_flags[short] = AcqFlag.DWELL_LIMIT
            _, first = np.unique(px, return_index=True)
            cand = px[np.sort(first)]          # stream order: a replay hands them over alike
            ready = cand[~self.final[cand] & ((self.store.count[cand] >= self.plan.target)
                                              | (self.acq_flags[cand] == AcqFlag.DWELL_LIMIT))]
            self._finalise(ready, AcqFlag.COMPLETE)
        for span in acc.lost:
            self.lost.append(span)
            where = "between pixels" if span.pixel < 0 else \
                f"at pixel {tuple(int(v) for v in divmod(span.pixel, self.plan.nx))}"
            what = (f"{span.records_lost} records lost" if span.records_lost
                    else "stream interrupted (USB error or reconnect; count unknown)")
            self._fault("lost-data", f"{what} from sync {span.sync}, {where}",
                        self.source.lost_action)
        return bool(acc.lost)

    def _finalise(self, pixels: np.ndarray, flag: AcqFlag) -> None:
        if pixels.size == 0:
            return
        keep = self.acq_flags[pixels] == ACQUIRING
        self.acq_flags[pixels[keep]] = flag
        if flag == AcqFlag.COMPLETE:
            # a pixel is finalised once (callers pass pixels not final yet)
            self._n_complete += int(np.count_nonzero(keep))
        self.final[pixels] = True
        self.store.freeze(pixels)
        self.live_recon.submit(pixels)

    def _fault(self, kind: str, what: str, action: str) -> None:
        """Record a fault (any thread: the tagger reader reports survived anomalies)."""
        entry = FaultRecord(kind, round(time.monotonic() - self._t0, 3), what, action)
        with self._fault_lock:
            if sum(1 for f in self.faults if f.kind == kind) >= MAX_FAULTS_LISTED:
                self.faults_not_listed[kind] = self.faults_not_listed.get(kind, 0) + 1
                return
            self.faults.append(entry)
        self._log({"event": "fault", **entry.to_dict()})
        log.warning("%s: %s (%s)", kind, what, action)

    # ---- the end ---------------------------------------------------------------------------------
    def _finish(self, final: SessionState) -> SessionState:
        """Flag what is short, reconstruct the rest, write maps.npz and run.json; returns the
        final state (FAILED when the reconstruction or the files fail)."""
        reason = AcqFlag.INCOMPLETE if final != SessionState.DONE else self._stop_reason
        # whole-frame masks, not index lists: a 4096 x 4096 scan cut by its time limit ends with
        # 16 M pixels not final
        rest = ~self.final
        self.acq_flags[rest & (self.store.count < self.plan.target)] = reason
        # pixels never reached (no complete dwell, nothing kept) are flagged and left out of the
        # reconstruction: their maps keep the values of "not reconstructed" (NaN depth and
        # background, NO_PHOTONS), not an estimate of an empty pixel
        reached = rest & ((self.store.count > 0) | (self.store.dwells > 0))
        complete = rest & (self.acq_flags == ACQUIRING)
        self.acq_flags[complete] = AcqFlag.COMPLETE
        self._n_complete += int(np.count_nonzero(complete))
        self.final[rest] = True
        self.store.freeze(rest)
        try:
            self.live_recon.submit(np.flatnonzero(reached))
            self.live_recon.finish()
        except BaseException as exc:  # noqa: BLE001 - the worker's error ends the session
            self._fail(exc)
            final = SessionState.FAILED
        if self.out_dir is None:
            return final
        if not self.out_dir.is_dir():
            if not isinstance(self.error, OutputError):
                self._fail(OutputError(f"output folder {self.out_dir} was removed before the "
                                       "session could write its maps and run.json"))
            return SessionState.FAILED
        maps = self.live_recon.maps(copy=self.live_recon.error is not None)   # the worker has ended
        exposure = self.exposure_s()
        exposure.flags.writeable = False
        self._exposure_end = exposure           # final: every later call returns it
        # the pixels' scan angles (degrees), so the maps can be turned into points later
        p = self.plan
        reached = (self.store.count > 0) | (self.store.dwells > 0)
        n = reached.size
        _save_maps_npz(self.out_dir / "maps.npz", maps,
                       keep=reached if n > SPARSE_MIN_PIXELS and 2 * np.count_nonzero(reached) < n else None,
                       acq_flags=self.acq_flags.reshape(self.plan.shape),
                       exposure_s=exposure,
                       row_deg=np.linspace(p.y_first_deg, p.y_last_deg, p.ny),
                       col_deg=np.linspace(p.x_first_deg, p.x_last_deg, p.nx))
        write_json_atomic(self.out_dir / "run.json", self.run_record(final))
        return final

    def maps(self):
        """The maps as they stand, in ``spdepth recon``'s format (``DepthMaps``)."""
        return self.live_recon.maps()

    def flagged_pixels(self) -> np.ndarray:
        """Flat indices of the final pixels short of the target (``maps.npz`` holds them as the
        ``acq_flags`` map)."""
        return np.flatnonzero((self.acq_flags != AcqFlag.COMPLETE) & (self.acq_flags != ACQUIRING))

    def run_record(self, final: SessionState | None = None) -> dict:
        """What ``run.json`` holds (small for any scan size: the flags per pixel are in
        ``maps.npz`` as ``acq_flags``; here only their counts per reason)."""
        ver = _version()
        st = self._stats()
        # one count per flag value (np.bincount widens the uint8 map to int64 first: 0.7 s on a
        # 4096 x 4096 frame)
        per_flag = {f: int(np.count_nonzero(self.acq_flags == f)) for f in AcqFlag}
        out = {
            "state": (final or self._state).value,
            "error": None if self.error is None else f"{type(self.error).__name__}: {self.error}",
            "software": {"name": "spdepth", "version": ver},
            "source": self.source.name,
            "plan": self.plan.to_dict(),
            "recon": self.live_recon.settings_used or self.live_recon.requested.to_dict(),
            "devices": jsonable(self.source.identities()),
            "info": self.info,
            "statistics": {
                "detections": self.detections, "kept": self.store.kept,
                "unassigned_photons": self.store.unassigned,
                "dropped_dwells": self.store.dropped_dwells, "passes": self.passes,
                "lost_spans": len(self.lost), "lost_records": st["lost_records"],
                "elapsed_s": round(st["elapsed_s"], 3),
                "detections_per_s": round(st["detections_per_s"], 1),
                "recon_max_lag_pixels": self.live_recon.max_lag,
                "recon_busy_s": round(self.live_recon.busy_s, 3),
                **self.source.statistics(),
                "stream_s": self.stream_s,
            },
            "flag_reasons": {f.name: int(per_flag[f]) for f in AcqFlag
                             if f != AcqFlag.COMPLETE and per_flag[f]},
            "flags_map": "maps.npz: acq_flags (uint8 AcqFlag per pixel)",
            "warnings": list(self.source.warnings),
            "faults_seen": [f.to_dict() for f in list(self.faults)],
        }
        if self.faults_not_listed:
            out["faults_not_listed"] = dict(self.faults_not_listed)
        return out

    # ---- event log -------------------------------------------------------------------------------
    def _log(self, entry: dict) -> None:
        if self._events_log is not None:
            self._events_log({"t_s": round(time.monotonic() - self._t0, 4), **entry})

    def _close_log(self) -> None:
        if self._events_log is not None:
            try:
                self._events_log.close()
            except OSError as exc:
                log.warning("events.jsonl did not close cleanly: %s", exc)
            self._events_log = None


@functools.lru_cache(maxsize=1)
def _version() -> str:
    """The installed spdepth's version (importlib.metadata's lookup costs tens of milliseconds, and
    a session's end asks for its run record more than once)."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("spdepth")
    except PackageNotFoundError:
        return "unknown"


class _Host:
    """The session as its source sees it (``acq.sources.SourceHost``)."""

    def __init__(self, session: Session):
        self._s = session
        self.plan = session.plan
        self.store = session.store
        self.out_dir = session.out_dir
        self.info = session.info

    @property
    def recon_settings(self):
        return self._s.live_recon.requested

    @property
    def pause_requested(self) -> bool:
        return self._s._pause_req

    def begin_pass(self, geom: PassGeometry, position: int | None = None) -> None:
        self._s._begin_pass(geom, position)

    def end_pass(self, position: int | None = None, lost_end: int | None = None) -> None:
        self._s._end_pass(position, lost_end)

    def process(self, chunk: np.ndarray) -> bool:
        return self._s._process(chunk)

    def checkpoint(self) -> None:
        self._s._checkpoint()

    def stop_requested(self) -> bool:
        s = self._s
        return s._pause_req or s._abort_req or s._time_up()

    def time_up(self) -> bool:
        return self._s._time_up()

    def needy(self) -> np.ndarray:
        return self._s._needy()

    def fault(self, kind: str, what: str, action: str) -> None:
        self._s._fault(kind, what, action)

    def log(self, entry: dict) -> None:
        self._s._log(entry)

    def flush(self) -> None:
        self._s._flush_files()


class _Subscription:
    def __init__(self, session: Session, fn, max_hz: float):
        self._session, self._fn = session, fn
        self._period = 1.0 / max(0.1, float(max_hz))
        self._closed = threading.Event()
        self.failed: BaseException | None = None
        self._thread = threading.Thread(target=self._run, name="session-subscriber", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        s = self._session
        last = None
        while not self._closed.is_set():
            ended = s.ended.wait(self._period)
            try:
                snap = s.snapshot(faults_since_s=last)
                last = snap.elapsed_s
                self._fn(snap)
            except Exception as exc:  # noqa: BLE001 - a broken subscriber must not take others down
                self.failed = exc
                log.error("snapshot subscriber %r failed (%s: %s); unsubscribed",
                          getattr(self._fn, "__name__", self._fn), type(exc).__name__, exc)
                return
            if ended:
                return

    def join(self, timeout_s: float | None = None) -> bool:
        """Wait for the subscription to end by itself (its last call after the session's end,
        or its failure); returns whether it has ended."""
        self._thread.join(timeout_s)
        return not self._thread.is_alive()

    def close(self, timeout_s: float = 2.0) -> None:
        self._closed.set()
        if self._thread is not threading.current_thread():
            self._thread.join(timeout_s)


def _save_maps_npz(path: Path, maps, keep: np.ndarray | None = None, **extra: np.ndarray) -> None:
    """``maps`` as ``DepthMaps.save_npz`` writes them (same keys, ``DepthMaps.load_npz`` reads
    it) plus ``extra`` arrays, deflated at level 1: a 4096 x 4096 scan's maps are most of a GB and
    the default level took seconds per map. ``keep`` (flat bool mask, the pixels reached): the
    sparse layout (``recon.maps.sparse_arrays``: the frame-sized maps only at those pixels, and
    the one value of the pixels never reached). Written to a temporary name, then renamed."""
    from spdepth.recon.maps import NPZ_KEYS, sparse_arrays

    arrays = {k: np.asarray(getattr(maps, k)) for k in NPZ_KEYS if k != "settings"}
    arrays["settings"] = np.array(json.dumps(maps.settings))
    arrays.update(extra)
    if keep is not None:
        # the flags stay whole (a uniform uint8 map deflates to kilobytes): np.load(...)["acq_flags"]
        # is the frame in either layout
        arrays = sparse_arrays(arrays, maps.shape, keep, dense=("acq_flags",))
    tmp = path.with_name(path.name + ".tmp")
    with zipfile.ZipFile(tmp, "w", compression=zipfile.ZIP_DEFLATED, compresslevel=1,
                         allowZip64=True) as zf:
        for name, arr in arrays.items():
            with zf.open(name + ".npy", "w", force_zip64=True) as fh:
                np.lib.format.write_array(fh, np.asanyarray(arr), allow_pickle=False)
    os.replace(tmp, path)


__all__ = ["Session", "SessionState", "SessionStateError", "AcqFlag", "ACQUIRING", "Snapshot",
           "ScanPlan"]
