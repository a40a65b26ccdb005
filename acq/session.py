"""An acquisition session: one scan from plan to files, live or replayed.

A :class:`Session` owns the galvo passes (or a recording's stream), the per-pixel store, the live
reconstruction, the recording and the snapshots its subscribers get. States::

    idle -> armed -> running <-> paused -> finishing -> done | aborted | failed

Pause takes effect at a pixel boundary (the controller finishes the pixel it is on; the stream is
drained up to it); resume scans whatever is still short. Abort is accepted in any state before
finishing. Cleanup always runs, on an exception and on Ctrl-C too: the galvo is stopped and parked,
the tag stream stopped, the recording flushed and closed, the maps and ``run.json`` written.

How the target is reached (the same loop serves the first pass, resume and re-acquisition): while
pixels are short of ``plan.target`` in-window detections and not flagged, the short pixels are
grouped into rectangles (``acq.plan.pass_regions``) and each is one galvo pass (one START). A lost
span (FIFO overrun, USB error, reconnect) stops the current pass at once, since the position is
unknown until the next frame marker, and the next pass scans the affected lines again. Each pixel
keeps its first ``target`` in-window detections of complete dwells (``acq.store``: a rescan tops
up, nothing is counted twice). Pixels are flagged (:class:`AcqFlag`) when a gated dwell hits the
dwell limit, when the pass budget or the time limit runs out, or when the session ends first.
"""

from __future__ import annotations

import json
import logging
import os
import threading
import time
from dataclasses import asdict, dataclass, field, is_dataclass, replace
from enum import Enum, IntEnum
from pathlib import Path
from typing import Callable

import numpy as np

from spdepth.acq.assign import PassGeometry
from spdepth.acq.live_recon import LiveRecon
from spdepth.acq.plan import ScanPlan, pass_regions
from spdepth.acq.store import PixelStore
from spdepth.drivers.errors import DeviceError
from spdepth.drivers.events import EVENT_DTYPE
from spdepth.acq.errors import SessionStateError
from spdepth.recon.errors import InputError
from spdepth.recon.model import ReconSettings

log = logging.getLogger(__name__)

STATUS_POLL_S = 0.05
"""How often the galvo's state and pixel log are read during a pass."""
QUIET_S = 0.3
"""After the galvo stopped, a stream quiet this long has delivered the pass (used after a loss,
when the markers cannot tell)."""
DRAIN_TIMEOUT_S = 5.0
"""Longest wait for the stream to deliver a stopped pass."""
MAX_GALVO_FAULTS = 3
"""Galvo faults cleared and retried before the session fails."""
SNAPSHOT_MAX_HZ = 30.0
FLUSH_WHILE_PAUSED_S = 0.5
HEALTH_RECENT_S = 2.0
_DEVICE_OF_FAULT = {"lost-data": "tagger", "tagger-reconnect": "tagger", "galvo-fault": "galvo",
                    "galvo-reconnect": "galvo"}


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


class AcqFlag(IntEnum):
    """Why a pixel has fewer than the target detections (``acq_flags`` map, uint8)."""

    COMPLETE = 0
    """The pixel holds the target number of in-window detections."""
    DWELL_LIMIT = 1
    """Gated: a dwell reached the dwell limit before the target count."""
    PASS_LIMIT = 2
    """Still short when the pass budget (gated re-acquisition passes, raster frames) ran out."""
    TIME_LIMIT = 3
    """Still short when the scan's time limit passed."""
    INCOMPLETE = 4
    """The session (abort, failure) or the replayed stream ended before the pixel was complete."""


@dataclass(frozen=True)
class Snapshot:
    """What subscribers see: the state of the scan and copies of the maps (H x W).

    depth_m, background, signal, uncertainty_s: the live reconstruction (NaN: not yet).
    counts: in-window detections kept per pixel; acq_flags: :class:`AcqFlag` of final pixels
    (255 while a pixel is still being acquired); final: pixels complete or flagged.
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
    health: dict = field(default_factory=dict)
    """Per device ("galvo", "tagger"): "ok", "recovering" (a loss, reconnect or fault in the last
    HEALTH_RECENT_S), "failed" (the session ended on that device's error) or "replay"."""


class _Aborted(Exception):
    """Internal: unwinds the acquisition thread after ``abort()``."""


class Session:
    """One scan, live (``galvo`` and ``tagger``) or replayed (``replay``, an
    ``acq.recording.ReplaySource``).

    plan:      what to scan; for a replay, the recorded plan with the replay's target.
    recon:     estimator settings with a fixed binning (window and bins in tagger units) and
               ``max_photons`` equal to ``plan.target`` (set here when None).
    out_dir:   where ``recording.ptu`` (live only), ``events.jsonl``, ``maps.npz`` and
               ``run.json`` go; None keeps everything in memory (tests, the GUI's dry runs).
    sync_period_s: the laser period, for the recording's header (live).
    gate_target: the count the galvo gated on when the stream was recorded (replay of a gated
               recording; defaults to ``plan.target`` for a live gated scan): a complete dwell
               with fewer detections ended at the dwell limit.
    info:      extra JSON-able facts for ``run.json`` (scene, seed, software version, ...).
    """

    def __init__(self, plan: ScanPlan, recon: ReconSettings, *, galvo=None, tagger=None,
                 replay=None, out_dir: str | Path | None = None, sync_period_s: float | None = None,
                 gate_target: int | None = None, info: dict | None = None,
                 reader_options: dict | None = None):
        if (replay is None) == (galvo is None or tagger is None):
            raise InputError("a session needs either a galvo and a tagger, or a replay source")
        if recon.binning is None:
            raise InputError("a session needs a fixed binning (window and bin width)")
        if recon.max_photons is None:
            recon = replace(recon, max_photons=plan.target)
        if recon.max_photons != plan.target:
            raise InputError(f"recon max_photons {recon.max_photons} differs from the target "
                             f"{plan.target}")
        self.plan = plan
        self.galvo, self.tagger, self.replay = galvo, tagger, replay
        self.out_dir = Path(out_dir) if out_dir is not None else None
        self.sync_period_s = sync_period_s
        self.info = dict(info or {})
        self.reader_options = dict(reader_options or {})
        if gate_target is None and plan.mode == "gated" and replay is None:
            gate_target = plan.target
        self.gate_target = gate_target
        b = recon.binning
        time_unit_s = b.time_unit_s
        self.store = PixelStore(plan.shape, plan.target,
                                (int(np.floor(b.window_start)), int(np.ceil(b.window_stop))),
                                time_unit_s)
        self.recon = LiveRecon(self.store, recon)
        self.acq_flags = np.full(plan.shape[0] * plan.shape[1], 255, np.uint8)
        self.final = np.zeros(plan.shape[0] * plan.shape[1], bool)
        self.lost: list = []
        self.faults: list[dict] = []
        self.passes = 0
        self.detections = 0
        self.error: BaseException | None = None
        self.recorder = None
        self.reader = None
        self.stream_s: float | None = None
        self._state = SessionState.IDLE
        self._state_lock = threading.RLock()
        self._state_changed = threading.Condition(self._state_lock)
        self._pause_req = False
        self._abort_req = False
        self._ended = threading.Event()
        self._thread: threading.Thread | None = None
        self._t0 = time.monotonic()
        self._t_running: float | None = None
        self._t_end: float | None = None
        self._first_record_t: float | None = None
        self._last_photon_t: float | None = None
        self._stop_reason: AcqFlag = AcqFlag.INCOMPLETE
        self._lost_in_pass = False              # a lost span arrived during the current pass
        self._seen_reconnects = (0, 0, 0)       # galvo, tagger reconnects, tagger restarts
        self._events_log = None

    # ---- commands (any thread) -------------------------------------------------------------------
    @property
    def state(self) -> SessionState:
        return self._state

    def start(self) -> "Session":
        """Arm and start the scan on the session's own thread; returns at once."""
        with self._state_lock:
            if self._state != SessionState.IDLE or self._thread is not None:
                raise SessionStateError(f"cannot start a session that is {self._state.value}")
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
        if not started:   # never started: nothing to clean up but the worker and files
            self._thread = threading.Thread(target=self._main, name="acq-session", daemon=True)
            self._thread.start()

    # ---- what subscribers see ------------------------------------------------------------------
    def snapshot(self) -> Snapshot:
        """The scan as it stands now (map copies; safe from any thread)."""
        h, w = self.plan.shape
        now = self._t_end or time.monotonic()
        running_s = (now - self._t_running) if self._t_running else 0.0
        n_final = int(self.final.sum())
        n_total = h * w
        eta = None
        if running_s > 0 and 0 < n_final < n_total and self._state not in _TERMINAL:
            eta = (n_total - n_final) * running_s / n_final
        r = self.recon
        flags = self.acq_flags.reshape(h, w).copy()
        return Snapshot(
            state=self._state.value, elapsed_s=now - self._t0, pixels_total=n_total,
            pixels_final=n_final, detections=self.detections,
            detections_per_s=self.detections / running_s if running_s > 0 else 0.0,
            lost_spans=len(self.lost), lost_records=sum(s.records_lost for s in self.lost),
            eta_s=eta, recon_lag=r.lag, passes=self.passes, depth_m=r.depth_m.copy(),
            background=r.background.copy(), signal=r.signal.copy(),
            uncertainty_s=r.uncertainty_s.copy(),
            counts=self.store.count.reshape(h, w).copy(), acq_flags=flags,
            faults=tuple(dict(f) for f in self.faults),
            error=None if self.error is None else str(self.error), health=self._health())

    def _health(self) -> dict:
        if self.replay is not None:
            return {"galvo": "replay", "tagger": "replay"}
        now = time.monotonic() - self._t0
        out = {"galvo": "ok", "tagger": "ok"}
        for f in self.faults:
            dev = _DEVICE_OF_FAULT.get(f["kind"])
            if dev and now - f["t_s"] < HEALTH_RECENT_S:
                out[dev] = "recovering"
        if self._state == SessionState.FAILED and self.error is not None:
            reader_failed = self.reader is not None and self.reader.error is not None
            out["tagger" if reader_failed else "galvo"] = "failed"
        return out

    def subscribe(self, fn: Callable[[Snapshot], None], max_hz: float = SNAPSHOT_MAX_HZ):
        """Call ``fn(snapshot)`` from a thread of its own at most ``max_hz`` times a second, and
        once more at the end. A slow ``fn`` only skips snapshots: it always gets the latest, never
        a queue, and never slows the scan. Returns an object whose ``close()`` unsubscribes."""
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

    def _main(self) -> None:
        final = SessionState.DONE
        if self.out_dir is not None:
            from spdepth.acq.recording import EventLog

            self.out_dir.mkdir(parents=True, exist_ok=True)
            self._events_log = EventLog(self.out_dir / "events.jsonl")
            self._log({"event": "session", "plan": self.plan.to_dict(),
                       "recon": self.recon.requested.to_dict(), "replay": self.replay is not None})
        try:
            try:
                if self._abort_req:
                    raise _Aborted
                self._set_state(SessionState.ARMED)
                self._arm()
                if self._abort_req:
                    raise _Aborted
                self._set_state(SessionState.RUNNING)
                self._t_running = time.monotonic()
                if self.replay is not None:
                    self._run_replay()
                else:
                    self._run_live()
            finally:
                self._cleanup()
        except _Aborted:
            final = SessionState.ABORTED
        except BaseException as exc:  # noqa: BLE001 - kept in .error, shown to every subscriber
            log.error("session failed: %s: %s", type(exc).__name__, exc)
            self.error = exc
            final = SessionState.FAILED
        if self._abort_req and final == SessionState.DONE:
            final = SessionState.ABORTED
        try:
            if self._state != SessionState.FINISHING:
                self._set_state(SessionState.FINISHING)
            self._finish(final)
        except BaseException as exc:  # noqa: BLE001
            log.exception("session could not finish")
            if self.error is None:
                self.error = exc
            final = SessionState.FAILED
        finally:
            self._t_end = time.monotonic()
            with self._state_lock:
                self._state = final
                self._state_changed.notify_all()
            self._log({"event": "state", "state": final.value})
            self._close_log()
            self._ended.set()

    def _arm(self) -> None:
        # load (or compile) the store's kernel now, not when the first photons are waiting: two
        # rows of a kind the kernel ignores give the strided field views a real stream has
        warm = np.zeros(2, dtype=EVENT_DTYPE)
        warm["kind"] = 255
        self.store.feed(warm)
        self.recon.warm_up()
        if self.replay is not None:
            return
        from spdepth.acq.recording import Recorder

        if self.out_dir is not None:
            self.recorder = Recorder(self.out_dir, self.plan, self.recon.requested,
                                     resolution_s=self.tagger.resolution_s,
                                     sync_period_s=self.sync_period_s, log=self._log,
                                     info=self.info)
        try:
            self.galvo.stop()             # a scan left running by someone else would mix in
        except DeviceError as exc:
            log.warning("galvo STOP before the scan failed: %s", exc)
        self._clear_leftover_fault()
        self.reader = self.tagger.reader(tap=self.recorder, **self.reader_options).start()

    # ---- live scanning ---------------------------------------------------------------------------
    def _needy(self) -> np.ndarray:
        return (~self.final & (self.store.count < self.plan.target)).reshape(self.plan.shape)

    def _run_live(self) -> None:
        plan = self.plan
        budget_used = 0
        while True:
            self._honour_pause()
            needy = self._needy()
            if not needy.any():
                return
            if self._time_up():
                self._stop_reason = AcqFlag.TIME_LIMIT
                return
            if budget_used >= plan.passes_allowed:
                self._stop_reason = AcqFlag.PASS_LIMIT
                return
            interrupted = False
            for geom in pass_regions(needy, plan.pattern):
                interrupted = self._run_pass(geom)
                if interrupted:
                    break
            if not (interrupted and self._pause_req):
                budget_used += 1

    def _time_up(self) -> bool:
        t = self.plan.time_limit_s
        return t is not None and self._t_running is not None and time.monotonic() - self._t_running > t

    def _honour_pause(self) -> None:
        """Block while a pause is requested; raise _Aborted on abort."""
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

    def _galvo_pattern(self, geom: PassGeometry):
        from spdepth.drivers.galvo import Gate, ScanMode, ScanPattern

        p = self.plan
        mode = ScanMode.RASTER if geom.pattern == "raster" else ScanMode.SERPENTINE
        pattern = ScanPattern(geom.nx, geom.ny, p.col_deg(geom.col0), p.col_deg(geom.col0 + geom.nx - 1),
                              p.row_deg(geom.row0), p.row_deg(geom.row0 + geom.ny - 1), mode=mode)
        gate = Gate.count(p.target, p.dwell_s) if p.mode == "gated" else Gate.fixed(p.dwell_s)
        return pattern, gate

    def _run_pass(self, geom: PassGeometry) -> bool:
        """One galvo pass over ``geom``; returns True when it was cut short (pause, abort, loss,
        fault, time limit)."""
        from spdepth.drivers.galvo import GalvoState

        galvo, reader, store = self.galvo, self.reader, self.store
        store.begin_pass(geom)
        self.passes += 1
        self._log({"event": "pass", "geometry": geom.to_dict(),
                   "record": self.recorder.records if self.recorder else None})
        pattern, gate = self._galvo_pattern(geom)
        galvo.configure_scan(pattern, gate, settle_s=self.plan.settle_s, frames=1)
        galvo.start()
        stop_sent = cut = False
        completed = None
        t_stopped = None
        last_data = time.monotonic()
        next_poll = 0.0
        while True:
            chunk = reader.get(timeout_s=0.02)
            if chunk is None:
                raise DeviceError("the time tagger's stream ended during the scan")
            now = time.monotonic()
            if chunk.size:
                last_data = now
                if self._process(chunk):
                    cut = True     # position unknown until the next frame: rescan, don't go blind
            if not stop_sent and (cut or self._pause_req or self._abort_req or self._time_up()):
                galvo.stop()
                stop_sent = cut = True
            if completed is None and now >= next_poll:
                next_poll = now + STATUS_POLL_S
                self._flush_files()
                self._read_pixel_log()
                st = galvo.status()
                self._note_reconnects()     # after the calls that may have reconnected
                if st.state == GalvoState.FAULT:
                    self._galvo_fault(f"at row {st.row}, col {st.col}")
                    completed, cut = -1, True
                elif st.state != GalvoState.SCANNING:
                    completed = st.completed
            if completed is None:
                continue
            t_stopped = t_stopped or now
            if store.lines_closed >= geom.ny:
                break                       # every line closed: the whole pass is in
            if completed >= 0 and not self._lost_in_pass and store.pixels_opened >= completed \
                    and not store.dwell_open:
                break                       # stopped early: the stream reached its last pixel
            if now - last_data > QUIET_S and now - t_stopped > QUIET_S:
                break
            if now - t_stopped > DRAIN_TIMEOUT_S:
                log.warning("stream still busy %.0f s after the pass ended; going on", DRAIN_TIMEOUT_S)
                break
        store.end_pass()
        self._lost_in_pass = False
        self._read_pixel_log()
        return cut

    def _flush_files(self) -> None:
        for f in (self.recorder, self._events_log):
            if f is not None:
                f.flush_if_due()

    def _note_reconnects(self) -> None:
        """Record reconnects the drivers did on their own (galvo serial link, tagger USB)."""
        g = getattr(self.galvo, "reconnects", 0)
        stats = self.reader.stats if self.reader is not None else {}
        t_rec, t_restart = stats.get("reconnects", 0), stats.get("restarts", 0)
        g0, r0, s0 = self._seen_reconnects
        if g > g0:
            self._fault("galvo-reconnect", f"serial link lost and re-opened ({g - g0}x)",
                        "settings restored, commands retried; the scan went on")
        if t_rec > r0 or t_restart > s0:
            self._fault("tagger-reconnect", f"tagger reconnected {t_rec - r0}x, measurement "
                        f"restarted {t_restart - s0}x", "stream resumed; the lost span is rescanned")
        self._seen_reconnects = (g, t_rec, t_restart)

    def _galvo_fault(self, where: str) -> None:
        """Record a galvo FAULT seen ``where``, clear it (*CLS re-homes the mirror), or give up
        after MAX_GALVO_FAULTS. A FAULT left by an earlier run counts too: it refuses START."""
        n = sum(1 for f in self.faults if f["kind"] == "galvo-fault") + 1
        code, msg = self.galvo.next_error()
        action = "cleared (*CLS); short pixels scanned in the next pass"
        if n > MAX_GALVO_FAULTS:
            action = "too many faults: session failed"
        self._fault("galvo-fault", f"galvo FAULT {where}: {code.name} {msg}", action)
        if n > MAX_GALVO_FAULTS:
            raise DeviceError(f"galvo faulted {n} times (last: {msg}); giving up")
        self.galvo.clear_errors()

    def _clear_leftover_fault(self) -> None:
        from spdepth.drivers.galvo import GalvoState

        if self.galvo.status().state == GalvoState.FAULT:
            self._galvo_fault("before the scan")

    def _read_pixel_log(self) -> None:
        while True:
            page = self.galvo.poll_pixels()
            if page.lost:
                self._log({"event": "pixel_log_overrun", "lost": page.lost})
            if not page.records:
                return
            self._log({"event": "pixels", "first_seq": page.first_seq,
                       "records": [[r.frame, r.row, r.col, r.count, r.dwell_ns, r.flag.name]
                                   for r in page.records]})

    # ---- replay ----------------------------------------------------------------------------------
    def _run_replay(self) -> None:
        for geom, chunks in self.replay.segments():
            self.store.begin_pass(geom)
            self.passes += 1
            for chunk in chunks:
                self._honour_pause()
                if self._first_record_t is None:
                    self._first_record_t = self.replay.first_read_t
                self._process(chunk)
            self.store.end_pass()

    # ---- shared: a chunk of events into the store ------------------------------------------------
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
            self._lost_in_pass = True
            where = "between pixels" if span.pixel < 0 else \
                f"at pixel {tuple(int(v) for v in divmod(span.pixel, self.plan.nx))}"
            what = (f"{span.records_lost} records lost" if span.records_lost
                    else "stream interrupted (USB error or reconnect; count unknown)")
            self._fault("lost-data", f"{what} from sync {span.sync}, {where}",
                        "pass stopped; the pixels without a complete dwell are scanned again"
                        if self.replay is None else "replayed as recorded")
        return bool(acc.lost)

    def _finalise(self, pixels: np.ndarray, flag: AcqFlag) -> None:
        if pixels.size == 0:
            return
        keep = self.acq_flags[pixels] == 255
        self.acq_flags[pixels[keep]] = flag
        self.final[pixels] = True
        self.store.freeze(pixels)
        self.recon.submit(pixels)

    def _fault(self, kind: str, what: str, action: str) -> None:
        entry = {"kind": kind, "t_s": round(time.monotonic() - self._t0, 3), "what": what,
                 "action": action}
        self.faults.append(entry)
        self._log({"event": "fault", **entry})
        log.warning("%s: %s (%s)", kind, what, action)

    # ---- the end ---------------------------------------------------------------------------------
    def _cleanup(self) -> None:
        """Stop the instruments and close the stream and recording, whatever happened."""
        if self.galvo is not None:
            for step in (self.galvo.stop, self.galvo.park):
                try:
                    step()
                except Exception as exc:  # noqa: BLE001 - cleanup goes on; the cause is logged
                    log.warning("galvo %s during cleanup failed: %s", step.__name__, exc)
        if self.reader is not None:
            try:
                self.reader.stop()
            except Exception as exc:  # noqa: BLE001
                log.warning("tagger reader did not stop cleanly: %s", exc)
        self._note_reconnects()
        if self.recorder is not None:
            self.recorder.close()
        if self._last_photon_t is not None and self.replay is not None:
            self.stream_s = self._last_photon_t - (self.replay.first_read_t or self._t_running)

    def _finish(self, final: SessionState) -> None:
        reason = AcqFlag.INCOMPLETE if final != SessionState.DONE else self._stop_reason
        rest = np.flatnonzero(~self.final)
        short = rest[self.store.count[rest] < self.plan.target]
        self.acq_flags[short] = reason
        self._finalise(rest, AcqFlag.COMPLETE)
        self.recon.finish()
        if self.out_dir is not None:
            self.maps().save_npz(self.out_dir / "maps.npz")
            _write_json_atomic(self.out_dir / "run.json", self.run_record(final))

    def maps(self):
        """The maps as they stand, in ``spdepth recon``'s format (``DepthMaps``)."""
        return self.recon.maps()

    def flagged_pixels(self) -> np.ndarray:
        return np.flatnonzero((self.acq_flags != AcqFlag.COMPLETE) & (self.acq_flags != 255))

    def run_record(self, final: SessionState | None = None) -> dict:
        """What ``run.json`` holds."""
        from importlib.metadata import PackageNotFoundError, version

        try:
            ver = version("spdepth")
        except PackageNotFoundError:
            ver = "unknown"
        flagged = self.flagged_pixels()
        snap = self.snapshot()
        identities = {}
        for name, dev in (("galvo", self.galvo), ("tagger", self.tagger)):
            ident = getattr(dev, "identity", None) if dev is not None else None
            if ident is not None:
                identities[name] = _jsonable(ident)
        if self.tagger is not None and getattr(self.tagger, "settings", None) is not None:
            identities["tagger_settings"] = _jsonable(self.tagger.settings)
        return {
            "state": (final or self._state).value,
            "error": None if self.error is None else f"{type(self.error).__name__}: {self.error}",
            "software": {"name": "spdepth", "version": ver},
            "source": "replay" if self.replay is not None else "live",
            "plan": self.plan.to_dict(),
            "recon": self.recon.resolved or self.recon.requested.to_dict(),
            "devices": identities,
            "info": self.info,
            "statistics": {
                "detections": self.detections, "kept": self.store.kept,
                "unassigned_photons": self.store.unassigned,
                "dropped_dwells": self.store.dropped_dwells, "passes": self.passes,
                "lost_spans": len(self.lost), "lost_records": snap.lost_records,
                "elapsed_s": round(snap.elapsed_s, 3),
                "detections_per_s": round(snap.detections_per_s, 1),
                "recon_max_lag_pixels": self.recon.max_lag,
                "recon_busy_s": round(self.recon.busy_s, 3),
                "records_recorded": self.recorder.records if self.recorder else None,
                "stream_s": self.stream_s,
            },
            "flagged_pixels": flagged.tolist(),
            "flag_reasons": {AcqFlag(int(k)).name: int(v) for k, v in
                             zip(*np.unique(self.acq_flags[flagged], return_counts=True))},
            "faults_seen": list(self.faults),
        }

    # ---- event log -------------------------------------------------------------------------------
    def _log(self, entry: dict) -> None:
        if self._events_log is not None:
            self._events_log({"t_s": round(time.monotonic() - self._t0, 4), **entry})

    def _close_log(self) -> None:
        if self._events_log is not None:
            self._events_log.close()
            self._events_log = None


class _Subscription:
    def __init__(self, session: Session, fn, max_hz: float):
        self._session, self._fn = session, fn
        self._period = 1.0 / max(0.1, float(max_hz))
        self._closed = threading.Event()
        self._thread = threading.Thread(target=self._run, name="session-subscriber", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        s = self._session
        while not self._closed.is_set():
            ended = s.ended.wait(self._period)
            try:
                self._fn(s.snapshot())
            except Exception:  # noqa: BLE001 - a broken subscriber must not take others down
                log.exception("snapshot subscriber failed; unsubscribed")
                return
            if ended:
                return

    def close(self, timeout_s: float = 2.0) -> None:
        self._closed.set()
        if self._thread is not threading.current_thread():
            self._thread.join(timeout_s)


def _jsonable(obj):
    if is_dataclass(obj):
        obj = asdict(obj)
    if isinstance(obj, dict):
        return {k: _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, Enum):
        return obj.name
    if isinstance(obj, (np.integer, np.floating)):
        return obj.item()
    return obj


def _write_json_atomic(path: Path, data: dict) -> None:
    tmp = path.with_suffix(path.suffix + ".tmp")
    with open(tmp, "w", encoding="utf-8") as fh:
        json.dump(_jsonable(data), fh, indent=1)
        fh.flush()
        os.fsync(fh.fileno())
    os.replace(tmp, path)


__all__ = ["Session", "SessionState", "SessionStateError", "AcqFlag", "Snapshot", "ScanPlan"]
