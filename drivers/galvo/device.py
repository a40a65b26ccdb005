"""The galvo scan controller as a device: units (optical degrees, seconds), limits checked before
anything is sent, tagged command/reply exchanges with retries, reconnect with back-off.

``Galvo(transport)`` takes any object with ``lock``, ``write_line``, ``read_line``,
``reset_input``, ``reopen`` and ``close`` (``SerialTransport`` or a test transcript);
``Galvo.open(url_or_port)`` builds the serial transport and connects.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass

from spdepth.drivers.errors import DeviceError, DeviceTimeoutError, ProtocolError, SettingError

from . import protocol as P
from .errors import ConnectionLostError, ErrorCode
from .protocol import (Calibration, GalvoState, GateMode, GateSetting, Identity, Limits,
                       PatternCodes, PixelPage, ScanMode, Status)

log = logging.getLogger("spdepth.galvo")


@dataclass(frozen=True)
class ScanPattern:
    """A frame of ``ny`` lines of ``nx`` pixels; the first/last column and row centres in optical
    degrees (x along a line, y across lines); ``mode`` the visiting order."""

    nx: int
    ny: int
    x_first_deg: float
    x_last_deg: float
    y_first_deg: float
    y_last_deg: float
    mode: ScanMode = ScanMode.RASTER


@dataclass(frozen=True)
class Gate:
    """How long each pixel is held: ``COUNT`` until ``n_target`` detector pulses or ``dwell_s``
    (the limit) passed; ``FIXED`` for ``dwell_s``."""

    mode: GateMode
    dwell_s: float
    n_target: int = 0

    @classmethod
    def count(cls, n_target: int, dwell_limit_s: float) -> "Gate":
        return cls(GateMode.COUNT, float(dwell_limit_s), int(n_target))

    @classmethod
    def fixed(cls, dwell_s: float) -> "Gate":
        return cls(GateMode.FIXED, float(dwell_s), 0)

    def to_wire(self) -> GateSetting:
        """Nanosecond integers as the controller takes them; SettingError when out of range."""
        dwell_ns = int(round(self.dwell_s * 1e9))
        if not P.MIN_DWELL_NS <= dwell_ns <= P.MAX_DWELL_NS:
            raise SettingError(f"galvo gate: dwell_s={self.dwell_s!r} outside "
                             f"{P.MIN_DWELL_NS * 1e-9:g}..{P.MAX_DWELL_NS * 1e-9:g} s")
        if self.mode == GateMode.COUNT:
            if not 1 <= self.n_target <= P.MAX_N_TARGET:
                raise SettingError(f"galvo gate: n_target={self.n_target!r} outside "
                                 f"1..{P.MAX_N_TARGET}")
            return GateSetting(GateMode.COUNT, int(self.n_target), dwell_ns)
        return GateSetting(GateMode.FIXED, 0, dwell_ns)


# Settings the host re-sends after a reconnect, in this order (limits first, so the others fit).
_CONFIG_ORDER = ("LIM", "PARKPOS", "PAT", "GATE", "SETTLE", "FRAMES")
_CONFIG_QUERY = {"LIM": "LIM?", "PARKPOS": "PARKPOS?", "PAT": "PAT?", "GATE": "GATE?",
                 "SETTLE": "SETTLE?", "FRAMES": "FRAMES?"}


class Galvo:
    """A galvo scan controller speaking the protocol of docs/protocols.md.

    transport:          see the module docstring.
    retries:            re-sends of a command whose reply was garbled or missing, when re-sending
                        is safe (every command but START, which is checked via STAT? instead):
                        a budget per exchange and per kind of failure (garbled, missing or late,
                        port lost), so faults that each survive alone survive on one exchange.
    reconnect_timeout_s: how long to keep re-opening a vanished port before giving up.
    backoff_s:          first wait between re-open attempts; doubles up to ``max_backoff_s``.
    """

    def __init__(self, transport, *, retries: int = 2, reconnect_timeout_s: float = 5.0,
                 backoff_s: float = 0.05, max_backoff_s: float = 1.0):
        self.transport = transport
        self.retries = int(retries)
        self.reconnect_timeout_s = float(reconnect_timeout_s)
        self.backoff_s = float(backoff_s)
        self.max_backoff_s = float(max_backoff_s)
        self._tag = 0
        self._identity: Identity | None = None
        self._cal: Calibration | None = None
        self._limits: Limits | None = None
        self._config: dict[str, tuple] = {}
        self._next_seq = 0
        self.reconnects = 0
        """How many times the port was re-opened after it vanished."""
        self.on_fault = None
        """``on_fault(kind, what)``, called for every failed exchange that is retried (kind:
        "garbled-reply", "missing-reply", "slow-reply", "serial-unplug"): the owner's record of
        faults survived (a session's ``faults_seen``)."""

    # ---- construction ----------------------------------------------------------------------
    @classmethod
    def open(cls, url_or_port: str, *, timeout_s: float = 0.5, baudrate: int = 115200,
             **kwargs) -> "Galvo":
        """Open a serial port or pyserial URL (``/dev/ttyUSB0``, ``galvosim://bench``) and
        connect (identify, read calibration and limits)."""
        from .transport import SerialTransport

        transport = SerialTransport(url_or_port, timeout_s=timeout_s, baudrate=baudrate)
        galvo = cls(transport, **kwargs)
        try:
            galvo.connect()
        except BaseException:
            transport.close()
            raise
        return galvo

    def connect(self) -> Identity:
        """Identify the controller and read its calibration and soft limits."""
        self._identity = self.identify()
        self._cal = self.calibration()
        self._limits = self.limits()
        return self._identity

    def close(self) -> None:
        self.transport.close()

    def __enter__(self) -> "Galvo":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    @property
    def identity(self) -> Identity | None:
        """What ``*IDN?`` said at connect (None before)."""
        return self._identity

    # ---- exchanges ---------------------------------------------------------------------------
    def _next_tag(self) -> int:
        self._tag = self._tag % P.MAX_TAG + 1
        return self._tag

    def _exchange_once(self, mnemonic: str, args: tuple, wait_factor: int = 1) -> P.Reply:
        """Send one tagged command and return its reply; replies with another tag are stale
        answers to earlier attempts and are dropped. ``wait_factor`` stretches the port's
        timeout (the n-th re-send after a timeout waits n + 1 timeouts)."""
        tag = self._next_tag()
        line = P.encode_command(mnemonic, *args, tag=tag)
        with self.transport.lock:
            self.transport.write_line(line)
            timeout_s = getattr(self.transport, "timeout_s", 0.5)
            sent = time.monotonic()
            deadline = sent + wait_factor * timeout_s
            while True:
                reply = P.decode_reply(self.transport.read_line(
                    max(0.0, deadline - time.monotonic())))
                if reply.tag == tag:
                    took = time.monotonic() - sent
                    if took > timeout_s:
                        self._fault("slow-reply", f"the reply to {mnemonic} came after {took:.3g} s "
                                                  f"(timeout {timeout_s:.3g} s)")
                    return reply
                log.warning("galvo: dropped stale reply (tag %s, expected %s)", reply.tag, tag)
                self._fault("slow-reply", f"a late reply (tag {reply.tag}) to an earlier {mnemonic} dropped")
                # Replies leave in order, so this attempt's own reply comes right behind: wait
                # for it one timeout more, once (a port repeating old replies still times out).
                deadline = min(max(deadline, time.monotonic() + timeout_s), sent + (wait_factor + 1) * timeout_s)

    def _query(self, mnemonic: str, *args, safe: bool = True) -> str:
        """Payload of the OK reply to one command, with recovery.

        A garbled or missing reply is retried up to ``retries`` times when ``safe``, each re-send
        after a timeout waiting one timeout longer: at the deadline a late reply cannot be told
        from a lost one, and a late one holds back the replies queued behind it; a vanished
        port is re-opened (and the configuration restored) and the command re-sent when ``safe``.
        Numbered error replies raise their GalvoReplyError at once."""
        command = " ".join([mnemonic, *map(str, args)])
        attempts = {"serial-unplug": 0, "garbled-reply": 0, "missing-reply": 0}
        while True:
            try:
                return self._exchange_once(
                    mnemonic, args, 1 + attempts["missing-reply"]).raise_for_error(command)
            except ConnectionLostError as e:
                log.warning("galvo: %s; reconnecting", e)
                self._reconnect()
                if not safe or attempts["serial-unplug"] >= self.retries:
                    raise
                kind = "serial-unplug"
            except (ProtocolError, DeviceTimeoutError) as e:
                kind = "garbled-reply" if isinstance(e, ProtocolError) else "missing-reply"
                if not safe or attempts[kind] >= self.retries:
                    raise
                log.warning("galvo: %s after %r; re-sending", e, command)
                self._fault(kind, f"{e} after {command!r}; re-sent")
                if kind == "garbled-reply":
                    # Only a garbled line can leave a fragment behind; after a timeout the input
                    # is kept, so a late reply arriving now is dropped by its tag and on record.
                    self._reset_input()
            attempts[kind] += 1

    def _fault(self, kind: str, what: str) -> None:
        if self.on_fault is not None:
            try:
                self.on_fault(kind, what)
            except Exception as exc:  # noqa: BLE001 - a record keeper's failure must not fail the scan
                log.warning("galvo: fault record failed: %s", exc)

    def _reset_input(self) -> None:
        try:
            self.transport.reset_input()
        except ConnectionLostError:
            self._reconnect()

    def _reconnect(self) -> None:
        """Re-open the port with back-off, check it is the same controller, restore the
        configuration this object sent. ConnectionLostError when the budget runs out."""
        deadline = time.monotonic() + self.reconnect_timeout_s
        delay = self.backoff_s
        while True:
            try:
                self.transport.reopen()
                self._restore()
                self.reconnects += 1
                log.warning("galvo: reconnected to %s", getattr(self.transport, "url", "?"))
                return
            except (ConnectionLostError, DeviceTimeoutError, ProtocolError) as e:
                if time.monotonic() + delay > deadline:
                    raise ConnectionLostError(
                        f"galvo: port {getattr(self.transport, 'url', '?')} did not come back "
                        f"within {self.reconnect_timeout_s:g} s: {e}") from e
                log.info("galvo: re-open failed (%s); retrying in %.3g s", e, delay)
                time.sleep(delay)
                delay = min(2 * delay, self.max_backoff_s)

    def _restore(self) -> None:
        """After a re-open: same controller? Then put back the settings, unless it is scanning,
        in which case it must still hold them (else its state is not what the host believes)."""
        ident = P.parse_identity(self._exchange_once("*IDN?", ()).raise_for_error("*IDN?"))
        if self._identity is not None and ident.serial != self._identity.serial:
            raise DeviceError(f"galvo: after reconnect the port holds controller {ident.serial}, "
                              f"not {self._identity.serial}")
        st = P.parse_status(self._exchange_once("STAT?", ()).raise_for_error("STAT?"))
        for mnemonic in _CONFIG_ORDER:
            if mnemonic not in self._config:
                continue
            args = self._config[mnemonic]
            if st.state == GalvoState.SCANNING:
                q = _CONFIG_QUERY[mnemonic]
                now = self._exchange_once(q, ()).raise_for_error(q)
                if now != " ".join(map(str, args)):
                    raise DeviceError(f"galvo: after reconnect {q} reads {now!r}, the host set "
                                      f"{' '.join(map(str, args))!r}, and a scan is running")
            else:
                self._exchange_once(mnemonic, args).raise_for_error(mnemonic)

    def _set(self, mnemonic: str, *args) -> None:
        P.parse_ok(self._query(mnemonic, *args))
        self._config[mnemonic] = tuple(args)

    # ---- identity, calibration, limits ---------------------------------------------------------
    def identify(self) -> Identity:
        """``*IDN?``: maker, model, serial number, firmware version."""
        return P.parse_identity(self._query("*IDN?"))

    def calibration(self) -> Calibration:
        """``CAL?``: DAC code of 0 degrees and micro-degrees per code, per axis."""
        self._cal = P.parse_calibration(self._query("CAL?"))
        return self._cal

    def limits(self) -> Limits:
        """``LIM?``: soft limits in DAC codes."""
        self._limits = P.parse_limits(self._query("LIM?"))
        return self._limits

    def set_limits(self, limits: Limits) -> None:
        """``LIM``: new soft limits (codes, inclusive)."""
        v = (limits.x_min, limits.x_max, limits.y_min, limits.y_max)
        if not all(0 <= c <= P.DAC_MAX_CODE for c in v) or v[0] > v[1] or v[2] > v[3]:
            raise SettingError(f"galvo limits {limits}: codes must be 0..65535 with min <= max")
        self._set("LIM", *v)
        self._limits = limits

    def _cal_known(self) -> Calibration:
        return self._cal or self.calibration()

    def _limits_known(self) -> Limits:
        return self._limits or self.limits()

    def _check_point(self, x: int, y: int, what: str) -> None:
        lim = self._limits_known()
        if not lim.contains(x, y):
            raise SettingError(f"galvo {what}: codes ({x}, {y}) outside the soft limits "
                             f"x {lim.x_min}..{lim.x_max}, y {lim.y_min}..{lim.y_max}")

    def to_codes(self, x_deg: float, y_deg: float) -> tuple[int, int]:
        """Optical degrees -> DAC codes with the controller's calibration."""
        return self._cal_known().to_codes(x_deg, y_deg)

    def to_deg(self, x_code: int, y_code: int) -> tuple[float, float]:
        """DAC codes -> optical degrees."""
        return self._cal_known().to_deg(x_code, y_code)

    # ---- position -------------------------------------------------------------------------------
    def position_codes(self) -> tuple[int, int]:
        """``POS?``: where the mirror is commanded to, in DAC codes."""
        return P.parse_position(self._query("POS?"))

    def position_deg(self) -> tuple[float, float]:
        return self.to_deg(*self.position_codes())

    def move_codes(self, x_code: int, y_code: int) -> None:
        """``POS``: move the mirror (not while scanning)."""
        self._check_point(int(x_code), int(y_code), "move")
        P.parse_ok(self._query("POS", int(x_code), int(y_code)))

    def move_deg(self, x_deg: float, y_deg: float) -> None:
        self.move_codes(*self.to_codes(x_deg, y_deg))

    def park_position_codes(self) -> tuple[int, int]:
        """``PARKPOS?``: where PARK, STOP and the end of a scan leave the mirror."""
        return P.parse_position(self._query("PARKPOS?"), "PARKPOS?")

    def set_park_position_codes(self, x_code: int, y_code: int) -> None:
        self._check_point(int(x_code), int(y_code), "park position")
        self._set("PARKPOS", int(x_code), int(y_code))

    def set_park_position_deg(self, x_deg: float, y_deg: float) -> None:
        self.set_park_position_codes(*self.to_codes(x_deg, y_deg))

    def park(self) -> None:
        """``PARK``: move to the park position (state PARKED)."""
        P.parse_ok(self._query("PARK"))

    # ---- scan configuration ----------------------------------------------------------------------
    def pattern_codes(self, pattern: ScanPattern) -> PatternCodes:
        """The wire form of a pattern; SettingError when it does not fit counts or limits."""
        for name in ("nx", "ny"):
            n = getattr(pattern, name)
            if not 1 <= n <= P.MAX_PIXELS_PER_AXIS:
                raise SettingError(f"galvo pattern: {name}={n!r} outside 1..{P.MAX_PIXELS_PER_AXIS}")
        x0, y0 = self.to_codes(pattern.x_first_deg, pattern.y_first_deg)
        x1, y1 = self.to_codes(pattern.x_last_deg, pattern.y_last_deg)
        return PatternCodes(ScanMode(pattern.mode), pattern.nx, pattern.ny, x0, x1, y0, y1)

    def set_pattern(self, pattern: ScanPattern | PatternCodes) -> PatternCodes:
        """``PAT``: the frame to scan (degrees are converted with the calibration)."""
        codes = pattern if isinstance(pattern, PatternCodes) else self.pattern_codes(pattern)
        if not (1 <= codes.nx <= P.MAX_PIXELS_PER_AXIS and 1 <= codes.ny <= P.MAX_PIXELS_PER_AXIS):
            raise SettingError(f"galvo pattern {codes}: pixel counts outside 1..{P.MAX_PIXELS_PER_AXIS}")
        self._check_point(codes.x_first, codes.y_first, "pattern first pixel")
        self._check_point(codes.x_last, codes.y_last, "pattern last pixel")
        self._set("PAT", *P.encode_pattern(codes))
        return codes

    def pattern(self) -> PatternCodes:
        """``PAT?``."""
        return P.parse_pattern(self._query("PAT?"))

    def set_gate(self, gate: Gate | GateSetting) -> None:
        """``GATE``: count-gated or fixed dwell."""
        wire = gate.to_wire() if isinstance(gate, Gate) else gate
        self._set("GATE", *P.encode_gate(wire))

    def gate(self) -> GateSetting:
        """``GATE?``."""
        return P.parse_gate(self._query("GATE?"))

    def set_settle(self, settle_s: float) -> None:
        """``SETTLE``: wait after each step before the pixel marker and the dwell."""
        ns = int(round(settle_s * 1e9))
        if not 0 <= ns <= P.MAX_SETTLE_NS:
            raise SettingError(f"galvo settle_s={settle_s!r} outside 0..{P.MAX_SETTLE_NS * 1e-9:g} s")
        self._set("SETTLE", ns)

    def settle_s(self) -> float:
        """``SETTLE?`` in seconds."""
        return P.parse_int(self._query("SETTLE?"), "SETTLE?", 0, P.MAX_SETTLE_NS) * 1e-9

    def set_frames(self, frames: int) -> None:
        """``FRAMES``: frames per START; 0 scans until STOP."""
        if not 0 <= int(frames) <= P.MAX_FRAMES:
            raise SettingError(f"galvo frames={frames!r} outside 0..{P.MAX_FRAMES}")
        self._set("FRAMES", int(frames))

    def frames(self) -> int:
        """``FRAMES?``."""
        return P.parse_int(self._query("FRAMES?"), "FRAMES?", 0, P.MAX_FRAMES)

    def configure_scan(self, pattern: ScanPattern | PatternCodes, gate: Gate | GateSetting, *,
                       settle_s: float = 0.0, frames: int = 1) -> PatternCodes:
        """Pattern, gate, settle and frames in one call; returns the pattern's wire form."""
        codes = self.set_pattern(pattern)
        self.set_gate(gate)
        self.set_settle(settle_s)
        self.set_frames(frames)
        return codes

    # ---- running -------------------------------------------------------------------------------
    def status(self) -> Status:
        """``STAT?``: state, scan number, current pixel, progress."""
        return P.parse_status(self._query("STAT?"))

    def start(self) -> Status:
        """``START``: run the configured scan; returns the status read just before.

        START is not safe to re-send blindly (a second START to a running scan is BUSY and one to
        a finished scan starts another), so after a lost or garbled reply the scan number in
        STAT? decides whether it took effect."""
        before = self.status()
        self._next_seq = 0
        try:
            P.parse_ok(self._query("START", safe=False))
            return before
        except (ProtocolError, DeviceTimeoutError, ConnectionLostError) as e:
            log.warning("galvo: START reply lost (%s); checking STAT?", e)
            if isinstance(e, ConnectionLostError) and not self.transport.is_open:
                raise
        after = self.status()
        if after.scan_id == before.scan_id + 1:
            return before
        if after.scan_id == before.scan_id:
            P.parse_ok(self._query("START", safe=False))
            return before
        raise DeviceError(f"galvo: scan number went from {before.scan_id} to {after.scan_id} "
                          f"around one START; someone else is driving the controller")

    def stop(self) -> None:
        """``STOP``: abort the scan and park (OK also when not scanning)."""
        P.parse_ok(self._query("STOP"))

    def pixels(self, from_seq: int, max_records: int = P.MAX_PIX_PAGE) -> PixelPage:
        """``PIX?``: completed-pixel records of the current scan from ``from_seq`` on."""
        if from_seq < 0 or not 1 <= max_records <= P.MAX_PIX_PAGE:
            raise SettingError(f"galvo pixels: from_seq={from_seq!r} must be >= 0 and "
                             f"max_records={max_records!r} in 1..{P.MAX_PIX_PAGE}")
        return P.parse_pixels(self._query("PIX?", int(from_seq), int(max_records)), from_seq)

    def poll_pixels(self, max_records: int = P.MAX_PIX_PAGE) -> PixelPage:
        """The next page of the pixel log after what this object has already read (since its
        last ``start()``); ``page.lost`` says how many records were overwritten unread."""
        page = self.pixels(self._next_seq, max_records)
        self._next_seq = page.next_seq
        return page

    def wait_until_done(self, timeout_s: float, poll_s: float = 0.02) -> Status:
        """Poll STAT? until the scan is no longer running; DeviceTimeoutError after
        ``timeout_s`` of real time."""
        deadline = time.monotonic() + timeout_s
        while True:
            st = self.status()
            if st.state != GalvoState.SCANNING:
                return st
            if time.monotonic() > deadline:
                raise DeviceTimeoutError(f"galvo: scan still running after {timeout_s:g} s "
                                         f"({st.completed}/{st.total} pixels)")
            time.sleep(poll_s)

    # ---- errors, reset -----------------------------------------------------------------------------
    def next_error(self) -> tuple[ErrorCode, str]:
        """``ERR?``: oldest queued error (``NO_ERROR`` when the queue is empty)."""
        return P.parse_error_query(self._query("ERR?"))

    def clear_errors(self) -> None:
        """``*CLS``: empty the error queue; a FAULT is cleared and the mirror re-parked."""
        P.parse_ok(self._query("*CLS"))

    def reset(self) -> None:
        """``*RST``: abort any scan, every setting back to power-on defaults, mirror centred."""
        P.parse_ok(self._query("*RST"))
        self._config.clear()
        self._limits = None
