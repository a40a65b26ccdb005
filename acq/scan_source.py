"""The live scan source: a galvo (passes over the pixels still short) and a time tagger (reader
thread, recording tap), behind the ``acq.sources.Source`` interface.

The galvo is our serial controller (``drivers.galvo.Galvo``) or one with its scan interface
(``drivers.daq.DaqGalvo``: configure_scan, start, status, stop, park, poll_pixels, next_error,
clear_errors); the tagger is our USB tagger (``drivers.tagger.Tagger``) or one with its reader
interface (``drivers.picoquant.PicoQuantTagger``: ``reader(tap=, notice=)`` giving a
``TaggerReader``, ``resolution_s``, optionally ``record_type`` for the recording's header). So
faults, in-band lost spans, re-acquisition, recording and replay are the same for every backend."""

from __future__ import annotations

import logging
import threading
import time
from typing import Iterable

import numpy as np

from spdepth.acq.assign import PassGeometry
from spdepth.acq.flags import AcqFlag
from spdepth.acq.plan import pass_regions
from spdepth.acq.recording import Recorder
from spdepth.acq.sources import RETRIED, FaultRecord, SourceHost
from spdepth.drivers.errors import DeviceError
from spdepth.drivers.events import EventKind

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


_DEVICE_OF_FAULT = {"lost-data": "tagger", "tagger-reconnect": "tagger", "galvo-fault": "galvo",
                    "galvo-reconnect": "galvo", "galvo-garbled-reply": "galvo", "galvo-missing-reply": "galvo",
                    "galvo-slow-reply": "galvo", "galvo-serial-unplug": "galvo"}


class ScanSource:
    """A live scan: our galvo (passes over the pixels still short) and our USB tagger (reader
    thread, recording tap).

    galvo, tagger:   opened ``drivers.galvo.Galvo`` and ``drivers.tagger.Tagger`` (configured).
    sync_period_s:   the laser period, for the recording's header.
    reader_options:  more arguments of ``Tagger.reader`` (e.g. ``reconnect_timeout_s``).
    """

    name = "live"
    lost_action = "pass stopped; the pixels without a complete dwell are scanned again"

    def __init__(self, galvo, tagger, *, sync_period_s: float | None = None,
                 reader_options: dict | None = None):
        self.galvo, self.tagger = galvo, tagger
        self.sync_period_s = sync_period_s
        self.reader_options = dict(reader_options or {})
        self.recorder = None
        self.reader = None
        self.warnings: list[str] = []
        self.first_read_t = None
        self._host: SourceHost | None = None
        self._lost_in_pass = False              # a lost span arrived during the current pass
        self._losts_received = 0                # LOST events in every chunk taken, used or not
        self._seen_reconnects = (0, 0, 0)       # galvo, tagger reconnects, tagger restarts
        self._galvo_faults = 0
        self._dwell_ns = [0.0, 0]               # sum and count of the galvo's logged pixel dwells
        self._lock = threading.Lock()

    def default_gate_target(self, plan) -> int | None:
        return plan.target if plan.mode == "gated" else None

    # ---- arming ----------------------------------------------------------------------------------
    def arm(self, host: SourceHost) -> None:
        self._host = host
        # every galvo exchange that failed and was retried goes on record (faults_seen)
        self.galvo.on_fault = lambda kind, what: host.fault(f"galvo-{kind}", what, RETRIED)
        if host.out_dir is not None:
            self.recorder = Recorder(host.out_dir, host.plan, host.recon_settings,
                                     resolution_s=self.tagger.resolution_s,
                                     sync_period_s=self.sync_period_s, log=host.log,
                                     info={**host.info, **getattr(self.tagger, "header_info", {})},
                                     record_type=getattr(self.tagger, "record_type", None))
        try:
            self.galvo.stop()             # a scan left running by someone else would mix in
        except DeviceError as exc:
            log.warning("galvo STOP before the scan failed: %s", exc)
        if self.galvo.status().state.name == "FAULT":
            self._galvo_fault("before the scan")
        self.reader = self.tagger.reader(tap=self.recorder, notice=self._notice,
                                         **self.reader_options)
        # returns once the tagger measures: the first pass's markers must not go unrecorded
        # (a failed START is the tagger's: health() finds it on the reader)
        self.reader.start()

    def _notice(self, kind: str, what: str) -> None:
        """A read anomaly the tagger reader survived with nothing lost (reader thread)."""
        if self._host is not None:
            self._host.fault(kind, what, RETRIED)

    # ---- scanning --------------------------------------------------------------------------------
    def run(self, host: SourceHost) -> AcqFlag:
        plan = host.plan
        budget_used = 0
        while True:
            host.checkpoint()
            needy = host.needy()
            if not needy.any():
                return AcqFlag.INCOMPLETE           # nothing is short: no pixel gets it
            if host.time_up():
                return AcqFlag.TIME_LIMIT
            if budget_used >= plan.passes_allowed:
                return AcqFlag.PASS_LIMIT
            interrupted = False
            for geom in pass_regions(needy, plan.pattern):
                interrupted = self._run_pass(host, geom)
                if interrupted:
                    break
            if not (interrupted and host.pause_requested):
                budget_used += 1

    def _galvo_pattern(self, plan, geom: PassGeometry):
        from spdepth.drivers.galvo import Gate, ScanMode, ScanPattern

        mode = ScanMode.RASTER if geom.pattern == "raster" else ScanMode.SERPENTINE
        pattern = ScanPattern(geom.nx, geom.ny, plan.col_deg(geom.col0),
                              plan.col_deg(geom.col0 + geom.nx - 1), plan.row_deg(geom.row0),
                              plan.row_deg(geom.row0 + geom.ny - 1), mode=mode)
        gate = Gate.count(plan.target, plan.dwell_s) if plan.mode == "gated" \
            else Gate.fixed(plan.dwell_s)
        return pattern, gate

    def _run_pass(self, host: SourceHost, geom: PassGeometry) -> bool:
        """One galvo pass over ``geom``; returns True when it was cut short (pause, abort, loss,
        fault, time limit)."""
        from spdepth.drivers.galvo import GalvoState

        galvo, reader, store = self.galvo, self.reader, host.store
        start = self.recorder.records if self.recorder else None
        host.begin_pass(geom, start)
        pattern, gate = self._galvo_pattern(host.plan, geom)
        if hasattr(galvo, "counter"):
            # a galvo the host gates (NI-DAQ): it watches the pixel's count in the session's store
            width = store.shape[1]
            galvo.counter = lambda r, c, g=geom: store.pixel_count((g.row0 + r) * width + g.col0 + c)
        galvo.configure_scan(pattern, gate, settle_s=host.plan.settle_s, frames=1)
        galvo.start()
        stop_sent = cut = False
        # where this pass stopped using the recording: a pass that used no chunk (its data came
        # after it stopped waiting, and the next pass drops them as stale) ends where it began,
        # so that a replay leaves those records out as well
        used_through = start
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
                self._losts_received += int(np.count_nonzero(chunk["kind"] == EventKind.LOST))
            stale = chunk.size > 0 and start is not None and reader.recorded_through is not None \
                and reader.recorded_through <= start
            if stale:
                # recorded before this pass began: the tail of the last pass, which stopped
                # waiting for it (a replay leaves it out too: the pass ends where it was cut).
                # Its lost spans are kept: a hole logged before this pass's first record may
                # reach into the pass (a failed first read loses its frame marker and first lines,
                # whose photons would then go to the wrong rows), so this pass rescans too
                chunk = chunk[chunk["kind"] == EventKind.LOST]
                if not chunk.size:
                    continue
            if chunk.size:
                last_data = now
                if start is not None and not stale:
                    used_through = reader.recorded_through
                if host.process(chunk):
                    self._lost_in_pass = True
                    cut = True     # position unknown until the next frame: rescan, don't go blind
            if not stop_sent and (cut or host.stop_requested()):
                galvo.stop()
                stop_sent = cut = True
            if completed is None and now >= next_poll:
                next_poll = now + STATUS_POLL_S
                host.flush()
                self._read_pixel_log(host)
                st = galvo.status()
                self._note_reconnects(host)     # after the calls that may have reconnected
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
                log.warning("stream still busy %.0f s after the pass ended; going on",
                            DRAIN_TIMEOUT_S)
                break
        host.end_pass(used_through, self._losts_received if start is not None else None)
        self._lost_in_pass = False
        self._read_pixel_log(host)
        return cut

    def _note_reconnects(self, host: SourceHost) -> None:
        """Record reconnects the drivers did on their own (galvo serial link, tagger USB)."""
        g = getattr(self.galvo, "reconnects", 0)
        stats = self.reader.stats if self.reader is not None else {}
        t_rec, t_restart = stats.get("reconnects", 0), stats.get("restarts", 0)
        g0, r0, s0 = self._seen_reconnects
        if g > g0:
            host.fault("galvo-reconnect", f"serial link lost and re-opened ({g - g0}x)",
                       "settings restored, commands retried; the scan went on")
        if t_rec > r0 or t_restart > s0:
            host.fault("tagger-reconnect", f"tagger reconnected {t_rec - r0}x, measurement "
                       f"restarted {t_restart - s0}x", "stream resumed; the lost span is rescanned")
        self._seen_reconnects = (g, t_rec, t_restart)

    def _galvo_fault(self, where: str) -> None:
        """Record a galvo FAULT seen ``where``, clear it (*CLS re-homes the mirror), or give up
        after MAX_GALVO_FAULTS. A FAULT left by an earlier run counts too: it refuses START."""
        self._galvo_faults += 1
        n = self._galvo_faults
        code, msg = self.galvo.next_error()
        action = "cleared (*CLS); short pixels scanned in the next pass"
        if n > MAX_GALVO_FAULTS:
            action = "too many faults: session failed"
        self._host.fault("galvo-fault", f"galvo FAULT {where}: {code.name} {msg}", action)
        if n > MAX_GALVO_FAULTS:
            raise DeviceError(f"galvo faulted {n} times (last: {msg}); giving up")
        self.galvo.clear_errors()

    def _read_pixel_log(self, host: SourceHost) -> None:
        while True:
            page = self.galvo.poll_pixels()
            if page.lost:
                host.log({"event": "pixel_log_overrun", "lost": page.lost})
            if not page.records:
                return
            host.log({"event": "pixels", "first_seq": page.first_seq,
                      "records": [[r.frame, r.row, r.col, r.count, r.dwell_ns, r.flag.name]
                                  for r in page.records]})
            self._dwell_ns[0] += float(sum(r.dwell_ns for r in page.records))
            self._dwell_ns[1] += len(page.records)

    # ---- the end ---------------------------------------------------------------------------------
    def flush(self) -> None:
        if self.recorder is not None:
            self.recorder.flush_if_due()

    def close(self) -> None:
        """Stop and park the galvo, stop the reader, close the recording; whatever happened."""
        with self._lock:
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
            if self._host is not None:
                self._note_reconnects(self._host)
            if self.recorder is not None:
                self.recorder.close(pixel_time_s=self._typical_pixel_s())

    def _typical_pixel_s(self) -> float | None:
        """A count-gated scan's mean pixel time (the galvo's logged dwells plus the settle time),
        for the recording's ``ImgHdr_TimePerPixel``: interpolating readers place photons by it
        from each line start. None for fixed dwell (the header's is right) or without a log."""
        plan = getattr(self._host, "plan", None)
        total, n = self._dwell_ns
        if plan is None or plan.mode != "gated" or n == 0:
            return None
        return total / n * 1e-9 + float(plan.settle_s)

    # ---- what the session reports ----------------------------------------------------------------
    def health(self, recent: Iterable[FaultRecord], error: BaseException | None) -> dict:
        out = {"galvo": "ok", "tagger": "ok"}
        for f in recent:
            dev = _DEVICE_OF_FAULT.get(f.kind)
            if dev:
                out[dev] = "recovering"
        if error is not None:
            if self.reader is not None and self.reader.error is not None:
                out["tagger"] = "failed"
            elif isinstance(error, DeviceError):
                out["galvo"] = "failed"
        return out

    def identities(self) -> dict:
        out = {}
        for name, dev in (("galvo", self.galvo), ("tagger", self.tagger)):
            ident = getattr(dev, "identity", None)
            if ident is not None:
                out[name] = ident
        if getattr(self.tagger, "settings", None) is not None:
            out["tagger_settings"] = self.tagger.settings
        return out

    def statistics(self) -> dict:
        return {"records_recorded": self.recorder.records if self.recorder else None}


__all__ = ["ScanSource", "STATUS_POLL_S", "QUIET_S", "DRAIN_TIMEOUT_S", "MAX_GALVO_FAULTS"]
