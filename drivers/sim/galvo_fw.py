"""Firmware emulator of the galvo scan controller (docs/protocols.md, "Galvo scan controller").

``GalvoFirmware`` is the whole controller: it parses command lines byte for byte, keeps the
controller's state (position, limits, pattern, gate, error queue, pixel log), and runs scans in
its own thread against a ``drivers.sim.rig.SimRig`` in virtual time: for every pixel it moves the
mirror, settles, pulses the marker lines and dwells (count-gated or fixed), handing the rig runs
of a line's pixels at once (``SimRig.scan_run``) wherever nothing needs to see the pixels one by
one. ``pace`` slows the thread down to watchable speed (real seconds per virtual second; 0 = as
fast as the host takes the data: the scan waits for room in the tagger's FIFO, and keeps to
real time while the tagger is not measuring).

Its serial side (``host_write`` / ``host_read``) is what the two links attach to: the pyserial
URL handler ``galvosim://`` (drivers/sim/protocol_galvosim.py) and a pty pair
(drivers/sim/pty_link.py). The galvo faults of drivers/sim/faults.py act on that side: an unplug
drops the link (a new *generation*; old handles raise ``PortUnplugged``) and re-plugs after
``replug_s`` real seconds; garbled / missing / slow replies act on the next reply after the fault
is due; a servo fault aborts the scan and latches FAULT.
"""

from __future__ import annotations

import itertools
import logging
import math
import re
import threading
import time
import urllib.parse
from collections import deque
from dataclasses import dataclass

import numpy as np

from spdepth.drivers.errors import SettingError
from spdepth.drivers.events import Marker
from spdepth.drivers.galvo.errors import ErrorCode
from spdepth.drivers.galvo.protocol import (DAC_MAX_CODE, MAX_COMMAND_BYTES, MAX_DWELL_NS, MAX_FRAMES,
                                    MAX_N_TARGET, MAX_PIX_PAGE, MAX_PIXELS_PER_AXIS,
                                    MAX_SETTLE_NS, MAX_TAG, MIN_DWELL_NS, PIXEL_LOG_DEPTH,
                                    GalvoState, GateMode, GateSetting, PatternCodes, ScanMode,
                                    encode_reply)
from spdepth.drivers.sim.faults import GALVO_FAULTS, Fault, FaultKind, FaultSchedule, parse_faults

log = logging.getLogger("spdepth.sim.galvo")

MAKER = "SPDEPTH"
MODEL = "GS-16"
FIRMWARE = "1.0"
ZERO_CODE = 32768
UDEG_PER_CODE = 40e6 / 65536
"""Full DAC range spans +-20 optical degrees: 610.3515625 micro-degrees per code."""
ERROR_QUEUE_DEPTH = 16
FIFO_STALL_S = 1.0
"""An unpaced scan waits for the tagger's reader while it keeps reading; a reader silent this
long (real seconds) gets the overflow (``SimRig.wait_for_room``)."""
LEAD_SHARE = 64
"""An unpaced scan runs at most 1/LEAD_SHARE of a frame (at least MIN_LEAD, at most MAX_LEAD
pixels) ahead of what the tagger's reader has taken, in runs of that many pixels: faults the
tagger injects at a share of the stream then find the scan where a real-time scan would be."""
MIN_LEAD, MAX_LEAD = 4, 256


class PortUnplugged(OSError):
    """The emulated USB-serial link is gone (the links turn this into SerialException / EIO)."""


class _Err(Exception):
    def __init__(self, code: ErrorCode, message: str):
        super().__init__(message)
        self.code = code
        self.message = message


_TAG_RE = re.compile(r"^(\d{1,5}):(.*)$", re.DOTALL)
_INT_RE = re.compile(r"^[-+]?\d{1,19}$")


def _int(tok: str) -> int:
    if not _INT_RE.match(tok):
        raise _Err(ErrorCode.BAD_ARGUMENT, f"{tok[:20]} is not a decimal integer")
    return int(tok)


def _nargs(args: list[str], *allowed: int) -> None:
    if len(args) not in allowed:
        want = " or ".join(map(str, allowed))
        raise _Err(ErrorCode.BAD_ARGUMENT, f"expected {want} arguments, got {len(args)}")


def _in(v: int, lo: int, hi: int, name: str) -> int:
    if not lo <= v <= hi:
        raise _Err(ErrorCode.OUT_OF_RANGE, f"{name} {v} outside {lo}..{hi}")
    return v


@dataclass
class _Settings:
    limits: tuple[int, int, int, int] = (0, DAC_MAX_CODE, 0, DAC_MAX_CODE)
    park: tuple[int, int] = (ZERO_CODE, ZERO_CODE)
    pattern: PatternCodes = PatternCodes(ScanMode.RASTER, 1, 1, ZERO_CODE, ZERO_CODE,
                                         ZERO_CODE, ZERO_CODE)
    gate: GateSetting = GateSetting(GateMode.FIXED, 0, 1_000_000)
    settle_ns: int = 0
    frames: int = 1


class GalvoFirmware:
    """The emulated controller.

    rig:          the shared SimRig (mirror, markers, dwell, virtual clock).
    serial_number: reported by ``*IDN?``; the driver checks it after a reconnect.
    faults:       a fault spec (``"serial-unplug@2s,garbled-reply@40%"``) or Fault list; only the
                  galvo kinds (drivers.sim.faults.GALVO_FAULTS) are accepted.
    pace:         real seconds the scan thread spends per virtual second (0: no sleeping).
    replug_s:     real seconds an unplugged port stays away.
    slow_reply_s: real seconds a slow reply is held back (make it longer than the host timeout).
    seed:         seeds the garbling of replies.
    """

    def __init__(self, rig, *, serial_number: str = "SIM0001", faults: str | list[Fault] = "",
                 pace: float = 0.0, replug_s: float = 0.5, slow_reply_s: float = 1.0,
                 seed: int = 0):
        if not re.fullmatch(r"[A-Za-z0-9_.-]{1,32}", serial_number):
            raise SettingError(f"galvo emulator: serial_number {serial_number!r} must be 1-32 "
                             f"letters, digits, '_', '.', '-'")
        if pace < 0 or replug_s < 0 or slow_reply_s < 0:
            raise SettingError("galvo emulator: pace, replug_s and slow_reply_s must be >= 0")
        self.rig = rig
        self.serial_number = serial_number
        self.pace = float(pace)
        self.replug_s = float(replug_s)
        self.slow_reply_s = float(slow_reply_s)
        fault_list = parse_faults(faults, GALVO_FAULTS) if isinstance(faults, str) else list(faults)
        bad = [f for f in fault_list if f.kind not in GALVO_FAULTS]
        if bad:
            raise SettingError(f"galvo emulator: faults {bad} are not galvo faults")
        self.faults = FaultSchedule(fault_list)
        self._rng = np.random.default_rng(seed)

        self._lock = threading.RLock()
        self._cond = threading.Condition(self._lock)
        self._listeners: list = []
        # serial side
        self._inbuf = bytearray()
        self._overlong = False
        self._out: deque[tuple[float, bytes]] = deque()   # (real time when readable, bytes)
        self._plugged = True
        self._generation = 0
        self._replug_at = 0.0
        self._armed: deque[FaultKind] = deque()            # reply faults waiting for a reply
        # controller
        self._errors: deque[tuple[ErrorCode, str]] = deque(maxlen=ERROR_QUEUE_DEPTH)
        self._scan_id = 0
        self._power_on()
        self.thread_error: BaseException | None = None
        """An unexpected exception of the scan thread (it also latches FAULT)."""

    def _power_on(self) -> None:
        self._cfg = _Settings()
        self._pos = (ZERO_CODE, ZERO_CODE)
        self._state = GalvoState.IDLE
        self._cur = (-1, -1, -1)            # frame, row, col of the pixel under the mirror
        self._completed = 0
        self._total = 0
        self._per_frame = 0
        self._log: deque[str] = deque(maxlen=PIXEL_LOG_DEPTH)   # records as PIX? sends them
        self._log_base = 0                  # seq of self._log[0]
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.rig.set_mirror(*self._deg(*self._pos))

    # ---- serial side ---------------------------------------------------------------------------
    @property
    def generation(self) -> int:
        """Changes on every unplug; a link opened in an older generation is dead."""
        return self._generation

    @property
    def is_plugged(self) -> bool:
        with self._lock:
            if not self._plugged and time.monotonic() >= self._replug_at:
                self._plugged = True
                log.info("galvo emulator %s: replugged", self.serial_number)
            return self._plugged

    def add_listener(self, fn) -> None:
        """``fn()`` is called (from any thread) when output is queued or the link drops."""
        with self._lock:
            self._listeners.append(fn)

    def remove_listener(self, fn) -> None:
        with self._lock:
            if fn in self._listeners:
                self._listeners.remove(fn)

    def _notify(self) -> None:
        self._cond.notify_all()
        for fn in list(self._listeners):
            fn()

    def _check_link(self, generation: int) -> None:
        if generation != self._generation or not self._plugged:
            raise PortUnplugged(5, "galvo emulator: device disconnected")

    def host_write(self, data: bytes, generation: int) -> None:
        """Bytes from the host. Complete lines are executed at once; replies queue for
        ``host_read``."""
        with self._lock:
            self._check_link(generation)
            self._inbuf += data
            while True:
                i = self._inbuf.find(b"\n")
                if i < 0:
                    if len(self._inbuf) > MAX_COMMAND_BYTES:
                        # Keep memory bounded; the line is answered with ERR 2 at its LF.
                        self._overlong = True
                        del self._inbuf[:]
                    return
                line = bytes(self._inbuf[:i])
                del self._inbuf[:i + 1]
                overlong, self._overlong = self._overlong, False
                if len(line) + 1 > MAX_COMMAND_BYTES:
                    # Treated like a line that streamed past the buffer: its tag is not trusted.
                    overlong, line = True, b""
                self._take_faults()
                if generation != self._generation:
                    return   # unplugged just now: the rest of the input is lost with the link
                reply = self._handle_line(line, overlong)
                if reply is not None:
                    self._queue_reply(reply)

    def host_read(self, max_bytes: int, timeout_s: float, generation: int) -> bytes:
        """Up to ``max_bytes`` reply bytes; waits up to ``timeout_s`` for the first byte."""
        deadline = time.monotonic() + max(0.0, timeout_s)
        with self._lock:
            while True:
                self._check_link(generation)
                ready = self._ready_bytes(max_bytes)
                if ready:
                    return ready
                now = time.monotonic()
                if now >= deadline:
                    return b""
                wait = deadline - now
                if self._out:
                    wait = min(wait, max(0.0, self._out[0][0] - now))
                self._cond.wait(wait)

    def out_waiting(self, generation: int) -> int:
        """Reply bytes readable now."""
        with self._lock:
            self._check_link(generation)
            now = time.monotonic()
            return sum(len(b) for due, b in self._out if due <= now)

    def next_output_due(self) -> float | None:
        """monotonic() time when the oldest queued reply becomes readable, None if none."""
        with self._lock:
            return self._out[0][0] if self._out else None

    def discard_output(self, generation: int) -> None:
        """Host flushed its input buffer: replies already arrived are dropped; ones still held
        back (slow) stay in flight, as on a real wire."""
        with self._lock:
            self._check_link(generation)
            now = time.monotonic()
            while self._out and self._out[0][0] <= now:
                self._out.popleft()

    def _ready_bytes(self, max_bytes: int) -> bytes:
        now = time.monotonic()
        out = bytearray()
        while self._out and self._out[0][0] <= now and len(out) < max_bytes:
            due, chunk = self._out.popleft()
            take = max_bytes - len(out)
            out += chunk[:take]
            if take < len(chunk):
                self._out.appendleft((due, chunk[take:]))
        return bytes(out)

    def _queue_reply(self, reply: bytes) -> None:
        due = time.monotonic()
        if self._armed:
            kind = self._armed.popleft()
            if kind == FaultKind.MISSING_REPLY:
                log.info("galvo emulator: fault missing-reply drops %r", reply)
                return
            if kind == FaultKind.GARBLED_REPLY:
                reply = self._garble(reply)
                log.info("galvo emulator: fault garbled-reply sends %r", reply)
            elif kind == FaultKind.SLOW_REPLY:
                due += self.slow_reply_s
                log.info("galvo emulator: fault slow-reply holds %r for %g s", reply,
                         self.slow_reply_s)
        # Replies leave in order: a slow one holds back the ones queued after it.
        if self._out:
            due = max(due, self._out[-1][0])
        self._out.append((due, reply))
        self._notify()

    def _garble(self, reply: bytes) -> bytes:
        b = bytearray(reply)
        n = int(self._rng.integers(1, 4))
        for pos in self._rng.choice(len(b) - 1, size=min(n, len(b) - 1), replace=False):
            old = b[pos]
            new = old
            while new in (old, 0x0A):
                new = int(self._rng.integers(0, 256))
            b[pos] = new
        return bytes(b)

    def unplug(self) -> None:
        """The USB cable comes out: the link dies, pending bytes are lost, it comes back after
        ``replug_s`` real seconds. The controller itself (and any scan) keeps running."""
        with self._lock:
            self._plugged = False
            self._generation += 1
            self._replug_at = time.monotonic() + self.replug_s
            self._inbuf.clear()
            self._out.clear()
            log.info("galvo emulator %s: unplugged for %g s", self.serial_number, self.replug_s)
            self._notify()

    def _scan_fraction(self) -> float | None:
        if self._scan_id == 0:
            return None
        denom = self._total or self._per_frame
        return self._completed / denom if denom else None

    def _take_faults(self) -> None:
        for f in self.faults.take_due(self.rig.now_s, self._scan_fraction()):
            log.info("galvo emulator: fault %s fires at %.6g s", f, self.rig.now_s)
            if f.kind == FaultKind.SERIAL_UNPLUG:
                self.unplug()
            elif f.kind == FaultKind.SERVO_FAULT:
                self._servo_fault("servo tracking error")
            else:
                self._armed.append(f.kind)

    def _servo_fault(self, why: str) -> None:
        self._stop.set()
        self._errors.append((ErrorCode.HARDWARE_FAULT, why))
        self._state = GalvoState.FAULT
        self._notify()

    # ---- command interpreter ----------------------------------------------------------------
    def _handle_line(self, raw: bytes, overlong: bool) -> bytes | None:
        if raw.endswith(b"\r"):
            raw = raw[:-1]
        tag = None
        try:
            text = raw.decode("ascii")
            if any(not 0x20 <= ord(c) <= 0x7E for c in text):
                raise UnicodeDecodeError("ascii", raw, 0, len(raw), "control character")
        except UnicodeDecodeError:
            return self._error(None, ErrorCode.BAD_ARGUMENT, "non-ASCII or control bytes in line")
        m = None if overlong else _TAG_RE.match(text)
        if m:
            tag, text = int(m.group(1)), m.group(2)
            if tag > MAX_TAG:
                return self._error(None, ErrorCode.BAD_ARGUMENT, f"tag {tag} outside 0..{MAX_TAG}")
        if overlong:
            return self._error(tag, ErrorCode.BAD_ARGUMENT,
                               f"line longer than {MAX_COMMAND_BYTES} bytes")
        toks = text.split()
        if not toks:
            return None if tag is None else self._error(tag, ErrorCode.UNKNOWN_COMMAND,
                                                         "empty command")
        mnemonic, args = toks[0].upper(), toks[1:]
        handler = self._COMMANDS.get(mnemonic)
        if handler is None:
            return self._error(tag, ErrorCode.UNKNOWN_COMMAND,
                               f"unknown command {_printable(mnemonic[:24])}")
        try:
            body = handler(self, args)
        except _Err as e:
            return self._error(tag, e.code, e.message)
        return encode_reply("OK" + (" " + body if body else ""), tag)

    def _error(self, tag: int | None, code: ErrorCode, message: str) -> bytes:
        message = _printable(message)
        self._errors.append((code, message))
        return encode_reply(f"ERR {int(code)} {message}", tag)

    def _not_scanning(self) -> None:
        if self._state == GalvoState.SCANNING:
            raise _Err(ErrorCode.BUSY, "scan running, STOP first")

    def _not_faulted(self) -> None:
        if self._state == GalvoState.FAULT:
            raise _Err(ErrorCode.HARDWARE_FAULT, "servo fault, clear with *CLS")

    def _deg(self, x_code: int, y_code: int) -> tuple[float, float]:
        return ((x_code - ZERO_CODE) * UDEG_PER_CODE * 1e-6,
                (y_code - ZERO_CODE) * UDEG_PER_CODE * 1e-6)

    def _check_point(self, x: int, y: int, name: str) -> None:
        _in(x, 0, DAC_MAX_CODE, f"{name} x")
        _in(y, 0, DAC_MAX_CODE, f"{name} y")
        x0, x1, y0, y1 = self._cfg.limits
        if not (x0 <= x <= x1 and y0 <= y <= y1):
            raise _Err(ErrorCode.OUT_OF_RANGE, f"{name} {x} {y} outside limits")

    def _cmd_idn(self, args):
        _nargs(args, 0)
        return f"{MAKER},{MODEL},{self.serial_number},{FIRMWARE}"

    def _cmd_rst(self, args):
        _nargs(args, 0)
        self._abort_scan()
        self._power_on()
        return ""

    def _cmd_cls(self, args):
        _nargs(args, 0)
        self._errors.clear()
        if self._state == GalvoState.FAULT:
            self._pos = self._cfg.park
            self.rig.set_mirror(*self._deg(*self._pos))
            self._state = GalvoState.PARKED
        return ""

    def _cmd_err(self, args):
        _nargs(args, 0)
        if not self._errors:
            return "0 no error"
        code, msg = self._errors.popleft()
        return f"{int(code)} {msg}"

    def _cmd_cal(self, args):
        _nargs(args, 0)
        u = format(UDEG_PER_CODE, ".10g")
        return f"{ZERO_CODE} {u} {ZERO_CODE} {u}"

    def _cmd_lim_q(self, args):
        _nargs(args, 0)
        return " ".join(map(str, self._cfg.limits))

    def _cmd_lim(self, args):
        _nargs(args, 4)
        v = [_int(a) for a in args]
        self._not_scanning()
        for val, name in zip(v, ("x_min", "x_max", "y_min", "y_max")):
            _in(val, 0, DAC_MAX_CODE, name)
        if v[0] > v[1] or v[2] > v[3]:
            raise _Err(ErrorCode.OUT_OF_RANGE, "min above max")
        px, py = self._cfg.park
        if not (v[0] <= px <= v[1] and v[2] <= py <= v[3]):
            raise _Err(ErrorCode.OUT_OF_RANGE, "park position outside new limits")
        self._cfg.limits = tuple(v)
        return ""

    def _cmd_pos_q(self, args):
        _nargs(args, 0)
        return f"{self._pos[0]} {self._pos[1]}"

    def _cmd_pos(self, args):
        _nargs(args, 2)
        x, y = (_int(a) for a in args)
        self._not_scanning()
        self._not_faulted()
        self._check_point(x, y, "position")
        self._pos = (x, y)
        self.rig.set_mirror(*self._deg(x, y))
        self._state = GalvoState.IDLE
        return ""

    def _cmd_parkpos_q(self, args):
        _nargs(args, 0)
        return f"{self._cfg.park[0]} {self._cfg.park[1]}"

    def _cmd_parkpos(self, args):
        _nargs(args, 2)
        x, y = (_int(a) for a in args)
        self._not_scanning()
        self._check_point(x, y, "park position")
        self._cfg.park = (x, y)
        return ""

    def _cmd_park(self, args):
        _nargs(args, 0)
        self._not_scanning()
        self._not_faulted()
        self._pos = self._cfg.park
        self.rig.set_mirror(*self._deg(*self._pos))
        self._state = GalvoState.PARKED
        return ""

    def _cmd_pat_q(self, args):
        _nargs(args, 0)
        p = self._cfg.pattern
        return f"{p.mode.token} {p.nx} {p.ny} {p.x_first} {p.x_last} {p.y_first} {p.y_last}"

    def _cmd_pat(self, args):
        _nargs(args, 7)
        tokens = {"RASTER": ScanMode.RASTER, "SERP": ScanMode.SERPENTINE}
        mode = tokens.get(args[0].upper())
        if mode is None:
            raise _Err(ErrorCode.BAD_ARGUMENT, f"mode {args[0][:12]} is not RASTER or SERP")
        nx, ny, x0, x1, y0, y1 = (_int(a) for a in args[1:])
        self._not_scanning()
        _in(nx, 1, MAX_PIXELS_PER_AXIS, "nx")
        _in(ny, 1, MAX_PIXELS_PER_AXIS, "ny")
        self._check_point(x0, y0, "first pixel")
        self._check_point(x1, y1, "last pixel")
        self._cfg.pattern = PatternCodes(mode, nx, ny, x0, x1, y0, y1)
        return ""

    def _cmd_gate_q(self, args):
        _nargs(args, 0)
        g = self._cfg.gate
        if g.mode == GateMode.COUNT:
            return f"COUNT {g.n_target} {g.dwell_ns}"
        return f"FIXED {g.dwell_ns}"

    def _cmd_gate(self, args):
        if not args:
            raise _Err(ErrorCode.BAD_ARGUMENT, "expected COUNT <n> <limit_ns> or FIXED <dwell_ns>")
        mode = args[0].upper()
        if mode == "COUNT":
            _nargs(args, 3)
            n, dwell = _int(args[1]), _int(args[2])
            self._not_scanning()
            _in(n, 1, MAX_N_TARGET, "n_target")
            _in(dwell, MIN_DWELL_NS, MAX_DWELL_NS, "dwell limit ns")
            self._cfg.gate = GateSetting(GateMode.COUNT, n, dwell)
        elif mode == "FIXED":
            _nargs(args, 2)
            dwell = _int(args[1])
            self._not_scanning()
            _in(dwell, MIN_DWELL_NS, MAX_DWELL_NS, "dwell ns")
            self._cfg.gate = GateSetting(GateMode.FIXED, 0, dwell)
        else:
            raise _Err(ErrorCode.BAD_ARGUMENT, f"gate mode {args[0][:12]} is not COUNT or FIXED")
        return ""

    def _cmd_settle_q(self, args):
        _nargs(args, 0)
        return str(self._cfg.settle_ns)

    def _cmd_settle(self, args):
        _nargs(args, 1)
        v = _int(args[0])
        self._not_scanning()
        self._cfg.settle_ns = _in(v, 0, MAX_SETTLE_NS, "settle ns")
        return ""

    def _cmd_frames_q(self, args):
        _nargs(args, 0)
        return str(self._cfg.frames)

    def _cmd_frames(self, args):
        _nargs(args, 1)
        v = _int(args[0])
        self._not_scanning()
        self._cfg.frames = _in(v, 0, MAX_FRAMES, "frames")
        return ""

    def _cmd_start(self, args):
        _nargs(args, 0)
        self._not_scanning()
        self._not_faulted()
        p = self._cfg.pattern
        # Limits may have changed since PAT: every pixel must still lie inside them.
        self._check_point(p.x_first, p.y_first, "first pixel")
        self._check_point(p.x_last, p.y_last, "last pixel")
        self._scan_id += 1
        self._per_frame = p.nx * p.ny
        self._total = self._per_frame * self._cfg.frames
        self._completed = 0
        self._log.clear()
        self._log_base = 0
        self._state = GalvoState.SCANNING
        self._stop = threading.Event()
        cfg = _Settings(self._cfg.limits, self._cfg.park, p, self._cfg.gate,
                        self._cfg.settle_ns, self._cfg.frames)
        self._thread = threading.Thread(target=self._scan_main, args=(cfg, self._stop),
                                        name=f"galvo-fw-scan-{self._scan_id}", daemon=True)
        self._thread.start()
        return ""

    def _cmd_stop(self, args):
        _nargs(args, 0)
        self._abort_scan()
        return ""

    def _abort_scan(self) -> None:
        """Stop the scan thread and wait for it (it finishes at most the pixel it is on)."""
        self._stop.set()
        thread = self._thread
        if thread is not None and thread is not threading.current_thread():
            # Condition.wait releases the (re-entrant) lock so the thread can finish.
            self._cond.wait_for(lambda: not thread.is_alive() or
                                self._state != GalvoState.SCANNING, timeout=5.0)

    def _cmd_stat(self, args):
        _nargs(args, 0)
        f, r, c = self._cur
        return (f"{self._state.name} {self._scan_id} {f} {r} {c} "
                f"{self._completed} {self._total}")

    def _cmd_pix(self, args):
        _nargs(args, 1, 2)
        start = _int(args[0])
        n_max = _int(args[1]) if len(args) == 2 else 64
        _in(start, 0, 2 ** 62, "from_seq")
        _in(n_max, 1, MAX_PIX_PAGE, "max_records")
        end = self._log_base + len(self._log)
        first = max(start, self._log_base)
        if first >= end:
            return f"{start} 0"
        a = first - self._log_base
        recs = list(itertools.islice(self._log, a, a + min(end - first, n_max)))
        return f"{first} {len(recs)} {' '.join(recs)}"

    _COMMANDS = {
        "*IDN?": _cmd_idn, "*RST": _cmd_rst, "*CLS": _cmd_cls, "ERR?": _cmd_err,
        "CAL?": _cmd_cal, "LIM?": _cmd_lim_q, "LIM": _cmd_lim, "POS?": _cmd_pos_q,
        "POS": _cmd_pos, "PARKPOS?": _cmd_parkpos_q, "PARKPOS": _cmd_parkpos, "PARK": _cmd_park,
        "PAT?": _cmd_pat_q, "PAT": _cmd_pat, "GATE?": _cmd_gate_q, "GATE": _cmd_gate,
        "SETTLE?": _cmd_settle_q, "SETTLE": _cmd_settle, "FRAMES?": _cmd_frames_q,
        "FRAMES": _cmd_frames, "START": _cmd_start, "STOP": _cmd_stop, "STAT?": _cmd_stat,
        "PIX?": _cmd_pix,
    }

    # ---- the scan ------------------------------------------------------------------------------
    def _scan_main(self, cfg: _Settings, stop: threading.Event) -> None:
        rig = self.rig
        p, g = cfg.pattern, cfg.gate
        gated = g.mode == GateMode.COUNT
        settle_s = cfg.settle_ns * 1e-9
        x_codes = [p.x_code(col) for col in range(p.nx)]
        x_deg = np.array([self._deg(x, ZERO_CODE)[0] for x in x_codes])
        # Unpaced, virtual time runs as fast as the host takes the data: a run starts when the
        # FIFO holds at most `lead` pixels and room for a quarter of it, and holds at most that
        # (pixel by pixel, the host drained the FIFO while the scan went on; a run must fit).
        fifo_share = max(1, rig.fifo_capacity_records // 4)
        lead = min(MAX_LEAD, max(MIN_LEAD, p.nx * p.ny // LEAD_SHARE))
        line_open = False
        try:
            frame = 0
            while (cfg.frames == 0 or frame < cfg.frames) and not stop.is_set():
                for row in range(p.ny):
                    cols = np.arange(p.nx)
                    if p.mode == ScanMode.SERPENTINE and row % 2 == 1:
                        cols = cols[::-1]
                    y = p.y_code(row)
                    y_deg = self._deg(ZERO_CODE, y)[1]
                    # the line's pixels go to the rig in runs: as many as no fault, stop or pace
                    # needs to see pixel by pixel (see _run_length)
                    j = 0
                    while j < cols.size and not stop.is_set():
                        run = cols[j:j + self._run_length(min(cols.size - j, lead))]
                        if self.pace == 0:
                            rig.wait_for_room(fifo_share, lead, FIFO_STALL_S, stop)
                        bits = np.full(run.size, Marker.PIXEL, np.uint8)
                        if j == 0:
                            bits[0] |= Marker.LINE_START | (Marker.FRAME if row == 0 else 0)
                        with self._lock:
                            self._pos = (x_codes[run[0]], y)
                            self._cur = (frame, row, int(run[0]))
                        done, counts, elapsed = rig.scan_run(
                            x_deg[run], np.full(run.size, y_deg), bits, dwell_s=g.dwell_ns * 1e-9,
                            n_target=g.n_target if gated else None, settle_s=settle_s,
                            stop_s=self._next_fault_s(), max_records=fifo_share)
                        line_open = True
                        with self._lock:
                            for col, count, el in zip(run[:done].tolist(), counts.tolist(),
                                                      elapsed.tolist()):
                                flag = ("G" if count >= g.n_target else "L") if gated else "F"
                                self._log_append(frame, row, col, count, int(round(el * 1e9)),
                                                 flag)
                            self._completed += done
                            self._pos = (x_codes[run[done - 1]], y)
                            self._cur = (frame, row, int(run[done - 1]))
                            self._take_faults()
                            self._notify()
                        if self.pace > 0:
                            stop.wait((float(elapsed[-1]) + settle_s) * self.pace)
                        elif not rig.tagger_running:
                            # Nobody takes the data, so nothing sets the pace: keep to real time
                            # (as the device would) rather than spin, which would starve the
                            # threads that answer the host's commands.
                            stop.wait(float(elapsed[:done].sum()) + done * settle_s)
                        j += done
                    if line_open:
                        rig.pulse_markers(Marker.LINE_STOP)
                        line_open = False
                    if stop.is_set():
                        break
                frame += 1
        except BaseException as e:   # noqa: BLE001 - the owner must learn of it, see thread_error
            log.exception("galvo emulator scan thread failed")
            self.thread_error = e
            with self._lock:
                self._servo_fault(f"internal error {type(e).__name__}")
            return
        finally:
            if line_open:
                rig.pulse_markers(Marker.LINE_STOP)
        with self._lock:
            if self._state == GalvoState.SCANNING:
                self._pos = cfg.park
                rig.set_mirror(*self._deg(*cfg.park))
                self._state = GalvoState.PARKED
            self._notify()

    def _run_length(self, left: int) -> int:
        """Pixels the next run may hold (at most ``left``): one when paced (each pixel takes its
        own wall time), else up to the pixel at which a scan-fraction fault falls due, so it
        fires after that pixel as it would pixel by pixel. (Time faults end a run through
        ``_next_fault_s``.)"""
        if self.pace > 0:
            return 1
        n = left
        denom = self._total or self._per_frame
        for f in self.faults.pending:
            if f.at_fraction is None or not denom:
                continue
            c = max(self._completed + 1, math.ceil(f.at_fraction * denom))
            while c > self._completed + 1 and (c - 1) / denom >= f.at_fraction:
                c -= 1
            while c / denom < f.at_fraction:
                c += 1
            n = min(n, c - self._completed)
        return max(1, n)

    def _next_fault_s(self) -> float:
        """Virtual time of the earliest galvo fault still to fire at a time (inf: none)."""
        return min((f.at_s for f in self.faults.pending if f.at_s is not None), default=math.inf)

    def _log_append(self, frame: int, row: int, col: int, count: int, dwell_ns: int,
                    flag: str) -> None:
        if len(self._log) == self._log.maxlen:
            self._log_base += 1
        self._log.append(f"{frame},{row},{col},{count},{dwell_ns},{flag}")

    # ---- owner API (tests, demos) ------------------------------------------------------------
    @property
    def state(self) -> GalvoState:
        return self._state

    def power_cycle(self) -> None:
        """The controller loses power: the link drops (as ``unplug``), every setting, the error
        queue and the scan counter return to power-on values."""
        with self._lock:
            self._abort_scan()
            self.unplug()
            self._errors.clear()
            self._scan_id = 0
            self._power_on()

    def wait_idle(self, timeout_s: float = 10.0) -> bool:
        """Block (real time) until no scan runs; False on timeout."""
        with self._lock:
            return self._cond.wait_for(lambda: self._state != GalvoState.SCANNING, timeout_s)

    def close(self) -> None:
        """Stop any scan and its thread."""
        with self._lock:
            self._abort_scan()
        if self._thread is not None:
            self._thread.join(5.0)


def _printable(s: str) -> str:
    # '*' would confuse the CRC split, control bytes the line framing.
    return "".join(c if 0x20 <= ord(c) <= 0x7E and c != "*" else "?" for c in s) or "?"


# ---- registry: how a URL finds its emulator -------------------------------------------------------

_REG_LOCK = threading.Lock()
_DEVICES: dict[str, tuple[GalvoFirmware, str]] = {}
_RIGS: dict[str, object] = {}
_URL_OPTIONS = {"rig", "scene", "size", "seed", "faults", "pace", "replug_s", "slow_s", "serial"}


def register_rig(name: str, rig) -> None:
    """Make ``rig`` available to ``galvosim://...?rig=NAME`` (share it with a tagger backend)."""
    with _REG_LOCK:
        _RIGS[name] = rig


def register_device(name: str, fw: GalvoFirmware) -> None:
    """Make an existing emulator reachable as ``galvosim://NAME``."""
    with _REG_LOCK:
        _DEVICES[name] = (fw, "")


def unregister(name: str) -> None:
    """Forget the device and rig registered under ``name`` (closing the device)."""
    with _REG_LOCK:
        dev = _DEVICES.pop(name, None)
        _RIGS.pop(name, None)
    if dev is not None:
        dev[0].close()


def device_for_url(url: str) -> GalvoFirmware:
    """The emulator a ``galvosim://NAME?options`` URL names, created on first use.

    Options (only when the URL creates the device; repeating the creating URL is fine):
    ``rig=NAME`` a registered SimRig, or ``scene=NAME&size=HxW&seed=N`` to build one;
    ``faults=SPEC``; ``pace=F``; ``replug_s=S``; ``slow_s=S``; ``serial=SN``."""
    parts = urllib.parse.urlsplit(url)
    if parts.scheme.lower() != "galvosim":
        raise SettingError(f"not a galvosim:// URL: {url!r}")
    name = (parts.netloc + parts.path).strip("/") or "default"
    opts = {k: v[-1] for k, v in urllib.parse.parse_qs(parts.query, keep_blank_values=True).items()}
    unknown = set(opts) - _URL_OPTIONS
    if unknown:
        raise SettingError(f"galvosim URL {url!r}: unknown options {sorted(unknown)} "
                         f"(known: {sorted(_URL_OPTIONS)})")
    with _REG_LOCK:
        if name in _DEVICES:
            fw, created_query = _DEVICES[name]
            if opts and parts.query != created_query:
                raise SettingError(f"galvosim URL {url!r}: device {name!r} exists; options can "
                                 f"only be given when it is created")
            return fw
        fw = _firmware_from_options(name, opts, url)
        _DEVICES[name] = (fw, parts.query)
        return fw


def _firmware_from_options(name: str, opts: dict, url: str) -> GalvoFirmware:
    def num(key, default, conv=float):
        try:
            return conv(opts[key]) if key in opts else default
        except ValueError:
            raise SettingError(f"galvosim URL {url!r}: {key}={opts[key]!r} is not a number") from None

    if "rig" in opts:
        rig = _RIGS.get(opts["rig"])
        if rig is None:
            raise SettingError(f"galvosim URL {url!r}: no rig registered as {opts['rig']!r}")
    else:
        rig = _rig_from_scene(opts, url, num)
    return GalvoFirmware(rig, serial_number=opts.get("serial", "SIM0001"),
                         faults=opts.get("faults", ""), pace=num("pace", 0.0),
                         replug_s=num("replug_s", 0.5), slow_reply_s=num("slow_s", 1.0),
                         seed=num("seed", 0, int))


def _rig_from_scene(opts: dict, url: str, num):
    from spdepth.drivers.sim.rig import SimRig

    try:
        from spdepth.drivers.sim import PhotonWorld, load_scene
    except ImportError as e:
        raise SettingError(f"galvosim URL {url!r}: building a scene needs drivers.sim.PhotonWorld "
                         f"({e}); register a rig and pass rig=NAME instead") from None
    size = opts.get("size", "32x32")
    m = re.fullmatch(r"(\d+)x(\d+)", size)
    if m is None:
        raise SettingError(f"galvosim URL {url!r}: size={size!r} is not like 32x32 (width x height)")
    shape = (int(m.group(2)), int(m.group(1)))
    scene = load_scene(opts.get("scene", "bust"), shape=shape)
    return SimRig(PhotonWorld(scene, seed=num("seed", 0, int)))
