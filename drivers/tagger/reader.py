"""The tagger's reader thread: bulk reads into one preallocated buffer, decoding, lost-data events,
recovery, and a bounded queue of event chunks for the owner.

Lost data is reported in-band as ``EventKind.LOST`` events (``sync`` where the hole starts,
``dtime`` = records lost, 0 when unknown):

* FIFO overrun: the device latches the gap (stream position, sync, count) and holds back every
  record after it until ACK_GAP, so the LOST event sits exactly where the hole is.
* endpoint stall (pipe error): the failed transfer's bytes are gone and the record alignment of
  the stream is no longer known, so the reader restarts the measurement (the device clears its
  FIFO) and emits LOST at the last decoded sync, count unknown.
* device vanished: LOST at the last decoded sync, then the tagger is reopened (same serial),
  reconfigured and restarted; if it does not come back the error reaches the owner.

After a restart the device's sync counter begins again at 0; the reader offsets it so syncs keep
increasing across the hole (they then count from an estimate, which is why the LOST event is there).
A bulk timeout loses nothing (libusb hands over whatever arrived; the device keeps the rest), so
the reader simply reads again; nor does a read that ends mid-record (the record's first bytes wait
for the next read). Both are survived anomalies: they are counted in ``stats`` and, when the device
still held records after the timeout or a record was split, reported to ``notice`` so an owner can
prove that an injected fault ran.
"""

from __future__ import annotations

import array
import logging
import queue
import threading
import time
from enum import Enum
from typing import Callable

import numpy as np

from spdepth.drivers.errors import DeviceError, DeviceTimeoutError, ProtocolError, SettingError
from spdepth.drivers.events import EVENT_DTYPE, EventKind
from spdepth.drivers.tagger.t3 import T3DecoderState, decode_t3, warm_up as warm_up_decoding
from spdepth.drivers.tagger.transport import DeviceGoneError, EndpointStallError

log = logging.getLogger(__name__)


class ReadAnomaly(str, Enum):
    """A read problem the reader survived with nothing lost (``notice`` kinds)."""

    USB_TIMEOUT = "usb-timeout"
    """A bulk read timed out while the device held records."""
    PARTIAL_READ = "partial-read"
    """A bulk read ended in the middle of a record."""


def lost_event(sync: int, n_records: int) -> np.ndarray:
    """One LOST event at ``sync`` for ``n_records`` lost records (0: unknown)."""
    ev = np.zeros(1, dtype=EVENT_DTYPE)
    ev["sync"] = max(0, int(sync))
    ev["kind"] = EventKind.LOST
    ev["dtime"] = min(int(n_records), 2 ** 32 - 1)
    return ev


class TaggerReader:
    """Reads a tagger in a thread and queues decoded ``EVENT_DTYPE`` chunks.

    tagger:              a ``drivers.tagger.Tagger`` (configured).
    queue_chunks:        bound of the chunk queue; when the owner falls behind the thread waits,
                         the device FIFO fills and an overrun is reported in-band.
    buffer_bytes:        size of the preallocated bulk buffer (a multiple of 512).
    read_timeout_s:      bulk read timeout; also how quickly ``stop`` is noticed.
    start_measurement:   send START when the thread starts and STOP when it ends; ``start``
                         returns only once START has been done (see there).
    start_timeout_s:     how long ``start`` waits for START (DeviceTimeoutError after it).
    reconnect_timeout_s: how long to wait for a vanished device to come back.
    connection_lost:     called from the thread as ``connection_lost(exc)`` when it ends (``exc``
                         None after ``stop``), like pyserial's ``ReaderThread``.
    tap:                 an object with ``on_records(raw)`` and ``on_lost(sync, n_records, restart)``,
                         called from the thread in stream order with every whole raw record
                         (uint32 array, valid only during the call) and every hole, before the
                         records are decoded: a recorder sees the stream exactly as it came.
                         ``restart`` says the device restarted (its sync counter from 0).
    notice:              called from the thread as ``notice(kind, what)`` for an anomaly survived
                         with nothing lost: ``kind`` a :class:`ReadAnomaly` value ("usb-timeout":
                         a bulk read timed out while the device held records; "partial-read": a
                         read ended mid-record), ``what`` in words.

    Consume with ``get`` (or iterate): a thread error is re-raised there once the chunks queued
    before it have been taken, so it never dies silently.
    """

    def __init__(self, tagger, queue_chunks: int = 64, buffer_bytes: int = 1 << 20,
                 read_timeout_s: float = 0.05, start_measurement: bool = True,
                 start_timeout_s: float = 10.0, reconnect_timeout_s: float = 5.0,
                 connection_lost: Callable[[BaseException | None], None] | None = None,
                 tap=None, notice: Callable[[str, str], None] | None = None):
        if buffer_bytes < 512 or buffer_bytes % 512:
            raise SettingError(f"reader buffer_bytes={buffer_bytes} must be a positive multiple of 512")
        if queue_chunks < 1:
            raise SettingError(f"reader queue_chunks={queue_chunks} must be >= 1")
        self.tagger = tagger
        self.read_timeout_s = float(read_timeout_s)
        self.start_measurement = bool(start_measurement)
        self.start_timeout_s = float(start_timeout_s)
        self.reconnect_timeout_s = float(reconnect_timeout_s)
        self.connection_lost = connection_lost
        self.tap = tap
        self.notice = notice
        # (events, the tap's record count once their records were in it)
        self._queue: queue.Queue[tuple[np.ndarray, int | None]] = queue.Queue(maxsize=queue_chunks)
        self.recorded_through: int | None = None
        """Records the tap (a recording) held once the records of the last chunk ``get`` returned
        were in it: where that chunk ends in the recording (None: no tap that counts records).
        A session ends a galvo pass there, and a replay ends the pass at the same record."""
        # One buffer for the life of the reader; pyusb fills array.array objects in place and the
        # NumPy view below sees the bytes without a copy.
        self._buffer = array.array("B", bytes(buffer_bytes))
        self._buffer_u8 = np.frombuffer(self._buffer, dtype=np.uint8)
        self._carry = np.zeros(0, dtype=np.uint8)   # bytes of a record split across two reads
        self.state = T3DecoderState()
        self._position = 0         # records received since the device's START
        self._offset = 0           # reader sync of the device's sync 0 (grows at each restart)
        self._stop = threading.Event()
        self._measuring = threading.Event()    # set once the thread has done START (or skipped it)
        self._done = threading.Event()
        self._error: BaseException | None = None
        self._thread: threading.Thread | None = None
        self.stats = {"records": 0, "events": 0, "lost_events": 0, "timeouts": 0,
                      "timeouts_with_data": 0, "partial_reads": 0, "restarts": 0, "reconnects": 0}
        self._timed_out = False    # the last bulk read timed out

    # ---- owner side ------------------------------------------------------------------------------
    def start(self) -> "TaggerReader":
        """Start the thread and return once the device measures. Markers and photons that arrive
        before START are never recorded, so an owner that started its scan as soon as the thread
        existed could lose a pass's first FRAME/LINE_START markers and assign every line to the
        one before it. Raises the thread's error when START failed (``get`` raises it as well) and
        DeviceTimeoutError when START took longer than ``start_timeout_s`` (the thread is asked
        to end)."""
        if self._thread is not None:
            raise DeviceError("tagger reader already started")
        warm_up_decoding()             # before START: the FIFO fills while a kernel compiles
        self._thread = threading.Thread(target=self._run, name="tagger-reader", daemon=True)
        self._thread.start()
        deadline = time.monotonic() + self.start_timeout_s
        while not self._measuring.wait(0.01):
            if self._done.is_set():     # only START's error ends the thread before it is set
                raise self._error
            if time.monotonic() > deadline:
                self._stop.set()
                raise DeviceTimeoutError(f"the tagger did not start measuring within "
                                         f"{self.start_timeout_s:g} s")
        return self

    def stop(self, timeout_s: float = 2.0) -> None:
        """Ask the thread to end and join it. Raises DeviceTimeoutError if it does not end in
        ``timeout_s``. Chunks still queued stay available to ``get``."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout_s)
            if self._thread.is_alive():
                raise DeviceTimeoutError(f"tagger reader did not stop within {timeout_s:g} s")

    @property
    def error(self) -> BaseException | None:
        """The exception that ended the thread, if any."""
        return self._error

    @property
    def alive(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def get(self, timeout_s: float | None = None) -> np.ndarray | None:
        """The next chunk of events (oldest first). Returns an empty array when nothing came
        within ``timeout_s`` (None: wait), None once the thread has ended and every chunk was
        taken. Re-raises the thread's exception after the chunks queued before it."""
        waited = 0.0
        while True:
            step = 0.05 if timeout_s is None else min(0.05, max(0.0, timeout_s - waited))
            try:
                events, through = self._queue.get(timeout=step) if step > 0 \
                    else self._queue.get_nowait()
                if through is not None:
                    self.recorded_through = through
                return events
            except queue.Empty:
                # nothing yet: see whether the thread has ended, else keep waiting
                pass
            if self._done.is_set() and self._queue.empty():
                if self._error is not None:
                    raise self._error
                return None
            waited += step
            if timeout_s is not None and waited >= timeout_s:
                return np.zeros(0, dtype=EVENT_DTYPE)

    def __iter__(self):
        while (chunk := self.get()) is not None:
            if chunk.size:
                yield chunk

    def __enter__(self) -> "TaggerReader":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    # ---- thread side -----------------------------------------------------------------------------
    def _run(self) -> None:
        exc: BaseException | None = None
        try:
            if self.start_measurement:
                self.tagger.start()
            self._measuring.set()
            while not self._stop.is_set():
                self.step()
        except BaseException as e:  # noqa: BLE001 - handed to the owner, never swallowed
            exc = e
            log.error("tagger reader stopped by %s: %s", type(e).__name__, e)
        finally:
            if self.start_measurement:
                try:
                    self.tagger.stop()
                except DeviceError as e:
                    log.debug("STOP at reader end failed: %s", e)
            self._error = exc
            self._done.set()
            if self.connection_lost is not None:
                try:
                    self.connection_lost(exc)
                except Exception:  # a faulty callback must not hide the reader's own error
                    log.exception("connection_lost callback failed")

    def _push(self, events: np.ndarray) -> None:
        if events.size == 0:
            return
        self.stats["events"] += int(events.size)
        self.stats["lost_events"] += int(np.count_nonzero(events["kind"] == EventKind.LOST))
        # the tap took these events' records before they come here (same thread), so its count
        # now is where they end in the recording
        through = getattr(self.tap, "records", None)
        while True:
            try:
                self._queue.put((events, through), timeout=0.05)
                return
            except queue.Full:
                if self._stop.is_set():
                    # Owner is stopping and no longer consuming; say what is dropped.
                    log.warning("reader stopping with a full queue: %d events dropped", events.size)
                    return

    def _lost(self, sync: int, n_records: int, restart: bool) -> None:
        if self.tap is not None:
            self.tap.on_lost(sync, n_records, restart)
        self._push(lost_event(sync, n_records))

    def _gap_sync(self) -> int:
        """Sync where a hole after the events decoded so far starts."""
        return self.state.last_sync if self.state.last_sync >= 0 else self.state.sync_base

    def _restart_session(self) -> None:
        """Device restarted from sync 0 and record 0: continue syncs after everything seen."""
        self._offset = max(self.state.sync_base, self.state.last_sync + 1)
        self.state.sync_base = self._offset
        self._position = 0
        self._carry = np.zeros(0, dtype=np.uint8)

    def step(self) -> None:
        """One bulk read, its decoding and the status check (the thread's loop body)."""
        try:
            n = self.tagger.read_into(self._buffer, self.read_timeout_s)
        except DeviceTimeoutError:
            self.stats["timeouts"] += 1
            self._timed_out = True
            n = 0
        except EndpointStallError as exc:
            log.warning("bulk endpoint stalled (%s): restarting the measurement", exc)
            self._lost(self._gap_sync(), 0, restart=True)
            self.tagger.transport.clear_halt()
            self.tagger.stop()
            self.tagger.start()
            self.stats["restarts"] += 1
            self._restart_session()
            return
        except DeviceGoneError as exc:
            self._device_gone(exc)
            return
        try:
            self._consume(n)
        except DeviceGoneError as exc:
            self._device_gone(exc)

    def _device_gone(self, exc: DeviceGoneError) -> None:
        log.warning("tagger vanished (%s): reconnecting", exc)
        self._lost(self._gap_sync(), 0, restart=True)
        self.tagger.reconnect(timeout_s=self.reconnect_timeout_s)
        self.stats["reconnects"] += 1
        self._restart_session()

    def _consume(self, n: int) -> None:
        if n:
            data = self._buffer_u8[:n]
            if self._carry.size:
                # Rare (a read ended mid-record): only then are the bytes copied.
                data = np.concatenate([self._carry, data])
            whole = data.size - data.size % 4
            records = data[:whole].view(np.uint32)
            self._carry = data[whole:].copy()
            if self._carry.size:
                self.stats["partial_reads"] += 1
                self._notify(ReadAnomaly.PARTIAL_READ, f"a bulk read of {n} bytes ended "
                             f"mid-record; the record's {self._carry.size} bytes waited for the "
                             "next read")
        else:
            records = np.zeros(0, dtype=np.uint32)
        status = self.tagger.status()
        end = self._position + records.size
        if self._timed_out:
            self._timed_out = False
            # An idle stream times out all the time; one that times out while the device holds
            # records is an anomaly (USB hiccup), survived by reading again, unless the records
            # wait behind a gap the host has read up to: the device sends none of them before
            # ACK_GAP (docs/protocols.md, "FIFO overrun"), so that timeout is the protocol.
            held_for_gap = status.overrun and status.gap_position <= end
            if status.fifo_fill_records > 0 and not held_for_gap:
                self.stats["timeouts_with_data"] += 1
                self._notify(ReadAnomaly.USB_TIMEOUT, "a bulk read timed out while the tagger "
                             f"held {status.fifo_fill_records} records; read again")
        if status.overrun and status.gap_position <= end:
            split = status.gap_position - self._position
            if split < 0:
                raise ProtocolError(f"tagger reports a gap at record {status.gap_position}, but "
                                    f"records up to {self._position} were already delivered")
            gap = self.tagger.ack_gap()
            if gap.position != status.gap_position:
                raise ProtocolError(f"tagger gap moved from record {status.gap_position} "
                                    f"(status) to {gap.position} (ACK_GAP)")
            if self.tap is not None:
                self.tap.on_records(records[:split])
                self.tap.on_lost(self._session_sync(gap.sync), gap.lost_records, False)
                self.tap.on_records(records[split:])
            before = decode_t3(records[:split], self.state)
            lost_sync = self._session_sync(gap.sync)
            if lost_sync < self.state.last_sync:
                raise ProtocolError(f"tagger gap at device sync {gap.sync} precedes the record "
                                    f"before it (sync {self.state.last_sync})")
            after = decode_t3(records[split:], self.state)
            log.warning("FIFO overrun: %d records lost from sync %d", gap.lost_records, lost_sync)
            self._push(np.concatenate([before, lost_event(lost_sync, gap.lost_records), after]))
        elif records.size:
            if self.tap is not None:
                self.tap.on_records(records)
            self._push(decode_t3(records, self.state))
        self._position = end
        self.stats["records"] += int(records.size)

    def _notify(self, kind: "ReadAnomaly", what: str) -> None:
        log.info("%s: %s", kind.value, what)
        if self.notice is not None:
            try:
                self.notice(kind.value, what)
            except Exception:  # noqa: BLE001 - a faulty callback must not end the stream
                log.exception("notice callback failed")

    def _session_sync(self, device_sync: int) -> int:
        """A device sync (since its START) in the reader's sync count."""
        return self._offset + int(device_sync)
