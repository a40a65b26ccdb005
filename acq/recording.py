"""Recording a session as it goes, and replaying a recording (DESIGN.md section 5).

A recording directory holds:

* ``recording.ptu``: the tagger's raw Generic T3 records as they came (combined marker records
  split one kind per record), after a PTU header that carries the plan and the estimator
  settings as tags. ``TTResult_NumberOfRecords`` stays 0 until a clean close patches it, so after a
  crash (``kill -9``) ptufile and our replay read every whole record up to the last flush.
* ``events.jsonl``: append-only, one JSON object a line, flushed with the records: state changes,
  faults, every galvo pass (its geometry, the record position where it starts and, as
  ``pass_end``, where the session stopped using the stream: a replay ends the pass there), every lost
  span (record position, sync, count, whether the device restarted), and the galvo's pixel log.
* ``run.json``: written at the end (write-to-temp-then-rename) by the session.

Replay (:class:`ReplaySource`) reads the records back in chunks through the same decoder as the
live reader, puts the logged lost spans back at their record positions (restoring the sync offset
a device restart caused, as the live reader did), and cuts the stream at the logged passes, so the
session assigns the replayed stream exactly as it assigned the live one. A PTU without our event
log (``spdepth simulate``, or another program's file with pixel markers) replays as one pass over
the header's image size. ``ReplaySource`` is an ``acq.sources.Source``: a session consumes it as it
consumes a live scan.

Damage: a header whose settings tags (``SPDepth_Plan``, ``SPDepth_Recon``, ``SPDepth_Info``) do
not parse is refused (``RecordingError`` naming the file and the tag: no invented plan). A PTU
holding fewer records than its header counts, or a session recording whose ``events.jsonl`` is
missing or stops before the session's end, still replays, with one line each in
``ReplaySource.warnings``, which the session's ``run.json`` lists and its caller shows once (the
CLI in its summary, ``spdepth recon`` as a note, the window in its status bar). A count of 0 is a
recording that was not closed (``kill -9``): every whole record is read, and that alone is no
warning.
"""

from __future__ import annotations

import json
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numba import njit

from spdepth.acq.assign import PassGeometry
from spdepth.acq.errors import RecordingError, RequestError
from spdepth.acq.flags import AcqFlag
from spdepth.acq.ptu import (INFO_TAG, PIXEL_MARKER_TAG, PLAN_TAG, RECON_TAG, iter_records,
                             marker_map, patch_pixel_time, patch_record_count, ptu_header, read_layout,
                             split_marker_records)
from spdepth.acq.sources import feed_passes
from spdepth.drivers.errors import ProtocolError
from spdepth.drivers.events import EVENT_DTYPE, GENERIC_T3_RECORD_TYPES, EventKind, RecordType
from spdepth.drivers.tagger.t3 import T3DecoderState, decode_t3
from spdepth.recon.errors import InputError
from spdepth.recon.model import ReconSettings


FLUSH_S = 0.5
"""Longest time records and events sit in Python's buffers before they go to the OS (the
recording survives a killed process up to the last flush)."""
T3_RANGE_BINS = 32768
_MARKER = int(EventKind.MARKER)
_END_STATES = {"done", "aborted", "failed"}


class Recorder:
    """Writes ``recording.ptu`` in ``out_dir``; lost spans go to ``log`` (the session's event log,
    ``EventLog``) with their record position.

    The tagger reader calls ``on_records`` and ``on_lost`` from its thread (it is its ``tap``).
    ``records`` counts the records written: the position the event log refers to.
    """

    def __init__(self, out_dir: Path, plan, recon_settings, *, resolution_s: float,
                 sync_period_s: float | None, log=None, info: dict | None = None,
                 record_type: int | None = None):
        out_dir = Path(out_dir)
        if sync_period_s is None:
            raise RequestError("recording needs the laser sync period (sync_period_s)")
        header = ptu_header(plan.shape, sync_period_s, resolution_s, plan.dwell_s, T3_RANGE_BINS,
                            comment="spdepth session recording",
                            tags={PLAN_TAG: plan.to_dict(), RECON_TAG: recon_settings.to_dict(),
                                  INFO_TAG: info or {}},
                            record_type=record_type or RecordType.HYDRAHARP2_T3)
        self.path = out_dir / "recording.ptu"
        self._fh = open(self.path, "w+b")
        self._fh.write(header)
        self._fh.flush()
        self._log = log
        self._lock = threading.Lock()
        self.records = 0
        self._last_flush = time.monotonic()
        self.closed = False

    # reader thread
    def on_records(self, raw: np.ndarray) -> None:
        if raw.size == 0 or self.closed:
            return
        out = split_marker_records(raw)
        with self._lock:
            self._fh.write(out.tobytes())
            self.records += int(out.size)
            self._maybe_flush()

    def on_lost(self, sync: int, n_records: int, restart: bool) -> None:
        if self._log is not None:
            self._log({"event": "lost", "record": self.records, "sync": int(sync),
                       "records_lost": int(n_records), "restart": bool(restart)})

    def _maybe_flush(self) -> None:
        self._last_flush = _flush_if_due(self._fh, self._last_flush)

    def flush_if_due(self) -> None:
        """Flush what waits in Python's buffer if FLUSH_S passed (the session calls this while
        the stream is quiet, so the last records never wait for the next ones)."""
        with self._lock:
            if not self.closed:
                self._maybe_flush()

    def close(self, pixel_time_s: float | None = None) -> None:
        """Flush, patch the record count (the file is complete) and, given the scan's typical pixel
        time (a count-gated scan's mean dwell), the header's ``ImgHdr_TimePerPixel``; close."""
        with self._lock:
            if self.closed:
                return
            self.closed = True
            self._fh.flush()
            patch_record_count(self._fh, self.records)
            if pixel_time_s is not None and pixel_time_s > 0:
                patch_pixel_time(self._fh, pixel_time_s)
            self._fh.close()


def _flush_if_due(fh, last_flush: float) -> float:
    """Flush ``fh`` when FLUSH_S has passed since ``last_flush``; returns the new last flush."""
    now = time.monotonic()
    if now - last_flush >= FLUSH_S:
        fh.flush()
        return now
    return last_flush


class EventLog:
    """``events.jsonl``: one JSON object a line, appended from any thread, flushed at least every
    FLUSH_S (and on close), so a killed process leaves whole lines up to its last flush."""

    def __init__(self, path: Path):
        self._fh = open(path, "a", encoding="utf-8")
        self._lock = threading.Lock()
        self._last_flush = time.monotonic()

    def __call__(self, entry: dict) -> None:
        with self._lock:
            if self._fh is None:
                return
            self._fh.write(json.dumps(entry) + "\n")
            self._last_flush = _flush_if_due(self._fh, self._last_flush)

    def flush_if_due(self) -> None:
        with self._lock:
            if self._fh is not None:
                self._last_flush = _flush_if_due(self._fh, self._last_flush)

    def close(self) -> None:
        with self._lock:
            if self._fh is not None:
                self._fh.close()
                self._fh = None


@dataclass(frozen=True)
class RecordingInfo:
    """What a recording says about itself: its plan (None for a foreign file), estimator
    settings, image shape, dtime unit and laser period."""

    plan: dict | None
    recon: dict | None
    info: dict
    shape: tuple[int, int]
    resolution_s: float
    sync_period_s: float
    n_records: int
    has_event_log: bool


class RecordedEnd(Exception):
    """Raised by a replay at the end of a recording whose session was aborted or failed: the
    replay ends the same way (the session catches it: state ``state``, the recorded error kept)."""

    def __init__(self, state: str, error: str | None):
        self.state, self.error = state, error
        super().__init__(f"the recorded session {state} here" + (f" ({error})" if error else ""))


class ReplaySource:
    """A recording (``DIR`` or ``DIR/recording.ptu``, or any T3 PTU with pixel markers) as a stream
    of event chunks, cut into the passes the live session made.

    speed: "max" (as fast as the pipeline takes it) or 1 (paced to the recorded laser time).
    """

    def __init__(self, path: str | Path, *, speed: str | float = "max",
                 chunk_records: int = 1 << 20):
        p = Path(path)
        if p.is_dir():
            p = p / "recording.ptu"
        if not p.is_file():
            raise RecordingError(f"recording {p} not found")
        self.path = p
        try:
            self.layout = read_layout(p)
        except InputError as exc:
            raise RecordingError(f"recording {p}: {exc}") from None
        except Exception as exc:  # ptufile's own errors for a file that is not a PTU
            raise RecordingError(f"recording {p}: not a readable PTU file ({exc})") from None
        tags = self.layout.tags
        if int(tags.get("TTResultFormat_TTTRRecType", 0)) not in GENERIC_T3_RECORD_TYPES:
            raise RecordingError(f"recording {p}: record type "
                             f"0x{int(tags.get('TTResultFormat_TTTRRecType', 0)):08x} is not "
                             "Generic T3 (HydraHarp v2 / TimeHarp 260 / MultiHarp); use "
                             "`spdepth recon` for other PicoQuant files")
        try:
            lut = marker_map(tags)
        except InputError as exc:
            raise RecordingError(f"recording {p}: {exc}") from None
        if lut is None or not tags.get(PIXEL_MARKER_TAG):
            raise RecordingError(f"recording {p}: the header names no pixel marker "
                             f"({PIXEL_MARKER_TAG}); replay needs pixel markers; "
                             "`spdepth recon FILE` interpolates pixels between line markers")
        self._lut = lut
        _Decoder(lut, []).decode(np.zeros(0, np.uint32))   # load the kernels before timing starts
        self.speed = speed
        self.chunk_records = int(chunk_records)
        self.first_read_t: float | None = None
        self.warnings: list[str] = []
        """What is wrong with the recording but still replays (a cut file, a missing or cut
        event log), one line each: not logged here (the caller shows them once) and listed in the
        session's ``run.json``."""
        self.events_path = p.parent / "events.jsonl"
        plan = _json_tag(p, tags, PLAN_TAG)
        recon = _json_tag(p, tags, RECON_TAG)
        _check_settings(p, plan, recon)
        try:
            shape = (int(tags.get("ImgHdr_PixY", 1)), int(tags.get("ImgHdr_PixX", 1)))
            resolution_s = float(tags["MeasDesc_Resolution"])
            sync_period_s = float(tags["MeasDesc_GlobalResolution"])
        except KeyError as exc:
            raise RecordingError(f"recording {p}: header tag {exc.args[0]} is missing") from None
        except (TypeError, ValueError) as exc:
            raise RecordingError(f"recording {p}: a header tag of the image or time base is "
                                 f"not a number ({exc})") from None
        self._passes, self._lost, ended = self._read_event_log(shape)
        self.info = RecordingInfo(
            plan=plan, recon=recon, info=_json_tag(p, tags, INFO_TAG) or {},
            shape=shape, resolution_s=resolution_s, sync_period_s=sync_period_s,
            n_records=min(self.layout.n_records, self.layout.records_in_file),
            has_event_log=self.events_path.is_file())
        self.sync_period_s = sync_period_s
        self._check_complete(plan is not None, ended)

    def _check_complete(self, ours: bool, log_ended: bool | None) -> None:
        """Fill ``warnings``: a record count in the header above the records in the file (a
        count of 0 is a recording that did not close and no warning by itself), an event log
        missing beside a session recording, or cut before the session's end."""
        lay = self.layout
        if lay.truncation:
            self.warnings.append(lay.truncation)
        if ours and log_ended is None:
            self.warnings.append(f"{self.events_path.name} is missing beside {self.path.name}: "
                                 "the stream is replayed as one full-frame pass (re-acquisition "
                                 "passes and lost spans cannot be placed)")
        elif ours and not log_ended:
            self.warnings.append(f"{self.events_path.name} is truncated (it stops before the "
                                 "session's end): passes and lost spans after the cut are "
                                 "unknown")

    def _read_event_log(self, shape: tuple[int, int]):
        """(passes as [first record, geometry, record where the session stopped using its
        stream or None, lost spans the session had received by then or None], lost spans,
        whether the log ends with the session's end: None without a log). Every field replay
        uses is checked (``_LogLine``): a damaged one is a ``RecordingError`` naming the line."""
        passes: list[list] = []
        lost: list[dict] = []
        self.recorded_end: str | None = None
        """How the recorded session ended ("done", "aborted", "failed"; None: not logged)."""
        if not self.events_path.is_file():
            return passes, lost, None
        ended = False
        try:
            fh = open(self.events_path, encoding="utf-8", errors="strict")
            with fh:
                lines = list(fh)
        except (OSError, UnicodeDecodeError) as exc:
            raise RecordingError(f"{self.events_path}: cannot be read as text "
                                 f"({type(exc).__name__})") from None
        for n, line in enumerate(lines, 1):
            if not line.endswith("\n"):
                ended = False
                break                 # the last line of a killed session may be cut
            e = _LogLine(self.events_path, n, line)
            kind = e.kind
            if kind == "pass" and e.get("record") is not None:
                passes.append([e.whole("record"), e.geometry(shape), None, None])
            elif kind == "pass_end" and passes and passes[-1][2] is None:
                passes[-1][2] = e.whole("record")
                passes[-1][3] = e.whole("lost_end", optional=True)
            elif kind == "lost":
                lost.append({"record": e.whole("record"), "sync": e.whole("sync"),
                             "records_lost": e.whole("records_lost"),
                             "restart": e.flag("restart")})
            ended = kind == "state" and e.text("state") in _END_STATES
            if ended:
                self.recorded_end = e.text("state")
        return passes, lost, ended

    # ---- the Source interface (acq.sources) ------------------------------------------------------
    name = "replay"
    lost_action = "replayed as recorded"

    def default_gate_target(self, plan) -> int | None:
        return None          # the caller knows what the recording gated on

    def arm(self, host) -> None:
        """Nothing to open: the file is open since the source was made."""

    def run(self, host):
        """The recorded passes with their chunks and lost spans, as the live session saw them; a
        session that was aborted or failed ends the replay where and as it ended
        (:class:`RecordedEnd`), not as "done"."""
        feed_passes(host, self.segments())
        if self.recorded_end in ("aborted", "failed"):
            raise RecordedEnd(self.recorded_end, self._recorded_error())
        return AcqFlag.INCOMPLETE

    def _recorded_error(self) -> str | None:
        """The recorded session's error line (``run.json``), when it has one."""
        run = self.path.parent / "run.json"
        try:
            return json.loads(run.read_text(encoding="utf-8")).get("error")
        except (OSError, json.JSONDecodeError, AttributeError):
            return None

    def flush(self) -> None:
        """Nothing to flush: a replay writes no recording."""

    def close(self) -> None:
        """Nothing to close (the records are read through short-lived memory maps)."""

    def health(self, recent, error) -> dict:
        return {"galvo": "replay", "tagger": "replay"}

    def identities(self) -> dict:
        return {}

    def statistics(self) -> dict:
        return {"records_recorded": None}

    def segments(self):
        """(PassGeometry, iterator of EVENT_DTYPE chunks) for each pass, in stream order: each
        pass from its first record to where the session stopped using the stream (the event
        log's ``pass_end``); records outside every pass (before the first, or the tail of a
        pass the session had stopped waiting for) are decoded, for the sync count, and left
        out, as the live session left them out, but for their lost spans, which open the next
        pass as they did live. A recording from before ``pass_end`` was logged
        runs each pass up to the next one, the first from record 0."""
        n = self.info.n_records
        if self._passes:
            starts = [max(0, min(r, n)) for r, _, _, _ in self._passes]
            geoms = [g for _, g, _, _ in self._passes]
            logged_ends = [e for _, _, e, _ in self._passes]
            lost_ends = [k for _, _, _, k in self._passes]
            if all(e is None for e in logged_ends):
                starts[0] = 0             # records before the first pass are idle stream
        else:
            starts, geoms, logged_ends = [0], [PassGeometry.full(self.info.shape)], [None]
            lost_ends = [None]
        nexts = starts[1:] + [n]
        ends = [nx if e is None else max(a, min(e, nx))
                for a, e, nx in zip(starts, logged_ends, nexts)]
        decoder = _Decoder(self._lut, self._lost)
        for g, a, b, k in zip(geoms, starts, ends, lost_ends):
            yield g, self._chunks(decoder, a, b, k)

    def _skip_to(self, decoder: "_Decoder", a: int) -> np.ndarray:
        """Decode the records up to ``a`` and drop their events (the T3 sync count runs on
        through them, as it did in the live reader), but for the lost spans among them and those
        logged at ``a``, which are returned: the live pass kept them (a hole logged before its
        first record may reach into it)."""
        decoder.lost_limit = None
        lost = []
        for records in iter_records(self.layout, self.chunk_records, start=decoder.position):
            take = min(records.size, a - decoder.position)
            if take <= 0:
                break
            ev = decoder.decode(np.asarray(records[:take]))
            lost.append(ev[ev["kind"] == EventKind.LOST])
        ev = decoder.decode(_NO_RECORDS)
        lost.append(ev[ev["kind"] == EventKind.LOST])
        return np.concatenate(lost)

    def _chunks(self, decoder: "_Decoder", a: int, b: int, lost_end: int | None = None):
        lost_before = self._skip_to(decoder, a)
        if lost_before.size:
            yield lost_before
        # a lost span logged at the pass's last record that reached the live session only after
        # the pass ended (``pass_end``'s lost_end) was left out there, and the next pass took it
        # (``_skip_to``): here too
        decoder.lost_limit = lost_end
        pace = self.speed not in ("max", None)
        t_wall0 = None
        for records in iter_records(self.layout, self.chunk_records, start=a):
            if self.first_read_t is None:
                self.first_read_t = time.monotonic()
            take = min(records.size, b - decoder.position)
            if take <= 0:
                break
            events = decoder.decode(np.asarray(records[:take]))
            if pace and events.size:
                # paced within the chunk too (one chunk often holds a whole pass): slices of
                # PACE_SLICE_S of replayed time, each let out when the recorded laser time of its
                # last event has passed
                t = events["sync"].astype(np.float64) * (self.info.sync_period_s / float(self.speed))
                t = np.maximum.accumulate(t)          # inserted loss events carry no time order
                if t_wall0 is None:
                    t_wall0 = time.monotonic() - t[0]
                cuts = np.searchsorted(t, np.arange(t[0] + PACE_SLICE_S, t[-1], PACE_SLICE_S))
                bounds = np.unique(np.concatenate([[0], cuts, [events.size]]))
                for lo, hi in zip(bounds[:-1], bounds[1:]):
                    delay = t_wall0 + t[hi - 1] - time.monotonic()
                    if delay > 0:
                        time.sleep(delay)
                    yield events[lo:hi]
            else:
                yield events
            if decoder.position >= b:
                break
        tail = decoder.decode(_NO_RECORDS)    # lost spans logged at the pass's last record
        if tail.size:
            yield tail


_NO_RECORDS = np.zeros(0, np.uint32)

PACE_SLICE_S = 0.05
"""A paced replay lets its events out in slices of this much replayed time."""


class _Decoder:
    """Records -> events with the file's marker numbering mapped to ours and the logged lost spans
    put back at their record positions."""

    def __init__(self, lut: np.ndarray, lost: list[dict]):
        # our recordings use the device's numbering: then there is nothing to map
        self.lut = None if np.array_equal(lut, np.arange(lut.size)) else lut
        self._out = np.empty(0, dtype=EVENT_DTYPE)
        self.state = T3DecoderState()
        self.position = 0
        self._lost = sorted(lost, key=lambda e: int(e["record"]))     # stable: log order
        self._next = 0
        self.lost_limit: int | None = None
        """Put back only the first this many lost spans of the log (None: all in reach)."""

    def decode(self, records: np.ndarray) -> np.ndarray:
        """Events of ``records`` (the next records of the file). The result is a view of a buffer
        reused by the next call: the session consumes a chunk before it asks for the next (and
        fresh pages for every chunk cost more than the decoding)."""
        if self._out.size < records.size:
            self._out = np.empty(records.size, dtype=EVENT_DTYPE)
        parts = []
        start = used = 0
        end = self.position + records.size
        while self._next < len(self._lost) and int(self._lost[self._next]["record"]) <= end \
                and (self.lost_limit is None or self._next < self.lost_limit):
            e = self._lost[self._next]
            cut = int(e["record"]) - self.position
            if cut >= start:
                parts.append(self._decode(records[start:cut], used))
                used += parts[-1].size
                start = cut
            ev = np.zeros(1, dtype=EVENT_DTYPE)
            ev["sync"] = int(e["sync"])
            ev["kind"] = EventKind.LOST
            ev["dtime"] = min(int(e["records_lost"]), 2 ** 32 - 1)
            parts.append(ev)
            if e.get("restart"):
                # as the live reader did: the device counted syncs from 0 again
                self.state.sync_base = max(self.state.sync_base, self.state.last_sync + 1)
            self._next += 1
        parts.append(self._decode(records[start:], used))
        self.position = end
        return parts[0] if len(parts) == 1 else np.concatenate(parts)

    def _decode(self, records: np.ndarray, used: int) -> np.ndarray:
        try:
            ev = decode_t3(records, self.state, out=self._out[used:])
        except ProtocolError as exc:
            raise RecordingError(f"recording: {exc}") from None
        if self.lut is not None:
            _map_markers(ev["kind"], ev["marker"], self.lut)
        return ev


@njit(cache=True, nogil=True)
def _map_markers(kind, marker, lut):
    """Marker bits of the file's numbering -> ours, in place."""
    for i in range(kind.size):
        if kind[i] == _MARKER:
            marker[i] = lut[marker[i] & 15]


class _LogLine:
    """One line of ``events.jsonl``, its fields checked as replay reads them: a damaged line is
    one ``RecordingError`` naming the file, the line and the field, never a traceback."""

    _MAX = 2 ** 63 - 1

    def __init__(self, path: Path, n: int, line: str):
        self.where = f"{path}, line {n}"
        try:
            e = json.loads(line)
        except (json.JSONDecodeError, RecursionError):
            raise RecordingError(f"{self.where}: not JSON") from None
        if not isinstance(e, dict):
            raise RecordingError(f"{self.where}: a JSON {type(e).__name__}, not an event object")
        self.e = e
        kind = e.get("event")
        if not isinstance(kind, str):
            raise RecordingError(f"{self.where}: field 'event' is {kind!r}, not an event name")
        self.kind = kind

    def get(self, key: str):
        return self.e.get(key)

    def _bad(self, key: str, what: str):
        return RecordingError(f"{self.where}: {self.kind} field {key!r} is {self.e.get(key)!r}, "
                              f"not {what}")

    def whole(self, key: str, optional: bool = False) -> int | None:
        v = self.e.get(key)
        if v is None and optional:
            return None
        if isinstance(v, bool) or not isinstance(v, int) or not 0 <= v <= self._MAX:
            raise self._bad(key, "a whole number >= 0")
        return v

    def flag(self, key: str) -> bool:
        v = self.e.get(key, False)
        if not isinstance(v, bool):
            raise self._bad(key, "true or false")
        return v

    def text(self, key: str) -> str | None:
        v = self.e.get(key)
        if v is not None and not isinstance(v, str):
            raise self._bad(key, "a name")
        return v

    def geometry(self, shape: tuple[int, int]) -> PassGeometry:
        g = self.e.get("geometry")
        keys = ("row0", "col0", "ny", "nx", "width")
        if not isinstance(g, dict) or any(isinstance(g.get(k), bool) or not isinstance(g.get(k), int)
                                          for k in keys) or not isinstance(g.get("pattern", ""), str):
            raise self._bad("geometry", "a pass geometry (row0, col0, ny, nx, width, pattern)")
        try:
            geom = PassGeometry(**{k: g[k] for k in keys}, pattern=g.get("pattern", "raster"))
        except InputError as exc:
            raise RecordingError(f"{self.where}: {exc}") from None
        h, w = shape
        if geom.width != w or geom.row0 + geom.ny > h:
            raise RecordingError(f"{self.where}: pass geometry {geom.to_dict()} does not fit the "
                                 f"recording's {w} x {h} image")
        return geom


def session_photons(path: str | Path, keep: int | None = None):
    """The photons a session kept, rebuilt from its recording (``acq.store``'s rule: the first
    ``target`` in-window detections of complete dwells, passes placed by the event log): what
    ``spdepth recon`` reconstructs from a recording. ``keep``: that many per pixel instead of the
    session's target (``--target``). Returns (PhotonStore, notes, meta); meta says what was in
    the file (``photons_in_file``, ``photons_outside_dwells``) and what was kept and why."""
    from spdepth.acq.plan import ScanPlan
    from spdepth.acq.store import PixelStore

    src = ReplaySource(path)
    for name, value in ((PLAN_TAG, src.info.plan), (RECON_TAG, src.info.recon)):
        if value is None:
            raise RecordingError(f"recording {src.path}: header tag {name} is missing")
    plan = ScanPlan.from_dict(src.info.plan)
    b = recon_settings_from_dict(src.info.recon).binning
    n_keep = int(keep) if keep is not None else plan.target
    store = PixelStore(plan.shape, n_keep,
                       (int(np.floor(b.window_start)), int(np.ceil(b.window_stop))),
                       src.info.resolution_s)
    passes = 0
    for geom, chunks in src.segments():
        store.begin_pass(geom)
        passes += 1
        for chunk in chunks:
            store.feed(chunk)
        store.end_pass()
    notes = list(src.warnings)
    short = int(np.count_nonzero(store.count < n_keep))
    if short:
        notes.append(f"{src.path.name}: {short} pixels hold fewer than "
                     + (f"the session's target of {plan.target} detections" if keep is None
                        else f"the {n_keep} detections asked for"))
    meta = {"assignment": "session recording (pixel markers, complete dwells)", "passes": passes,
            "target": plan.target, "window": list(store.window), "records": src.info.n_records,
            "photons_in_file": int(store.photons_seen), "photons_outside_dwells": int(store.unassigned),
            "kept_per_pixel": n_keep,
            "kept_why": "the session's target per pixel" if keep is None else "--target"}
    return store.photons(), tuple(notes), meta, store.periods.astype(np.float64)


def recon_settings_from_dict(d: dict, **override) -> ReconSettings:
    """``ReconSettings`` from its ``to_dict`` form (as a recording's header keeps it), with any
    field replaced by ``override`` (None values are ignored): ``ReconSettings.from_dict``."""
    return ReconSettings.from_dict(d, **override)


def _json_tag(path: Path, tags: dict, name: str):
    """A header tag holding our JSON settings, parsed; None when the file has no such tag.
    Raises RecordingError naming the file and the tag when the value does not parse to an
    object (a damaged header must not be replaced by invented settings)."""
    v = tags.get(name)
    if v is None:
        return None
    try:
        out = json.loads(v) if isinstance(v, str) else v
    except json.JSONDecodeError as exc:
        raise RecordingError(f"recording {path}: header tag {name} is damaged (not JSON: "
                             f"{exc.msg} at character {exc.pos})") from None
    if not isinstance(out, dict):
        raise RecordingError(f"recording {path}: header tag {name} is damaged (a "
                             f"{type(out).__name__}, not the settings object)")
    return out


def _check_settings(path: Path, plan: dict | None, recon: dict | None) -> None:
    """Refuse a header whose plan or estimator settings parse as JSON but not as settings."""
    from spdepth.acq.plan import ScanPlan

    for name, value, parse in ((PLAN_TAG, plan, ScanPlan.from_dict),
                               (RECON_TAG, recon, recon_settings_from_dict)):
        if value is None:
            continue
        try:
            parse(value)
        except Exception as exc:  # noqa: BLE001 - any failure means a damaged tag
            raise RecordingError(f"recording {path}: header tag {name} is damaged "
                                 f"({type(exc).__name__}: {exc})") from None
