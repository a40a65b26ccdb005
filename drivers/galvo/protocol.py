"""The galvo scan controller's line protocol: pure bytes <-> commands and typed replies, no I/O.

Wire format (docs/protocols.md, section "Galvo scan controller", is the reference):

* command: ``[TAG:]MNEMONIC[ ARG]...`` + LF, ASCII; the controller ignores a CR before the LF.
* reply:   ``[TAG:]OK[ PAYLOAD]*CRC`` + LF or ``[TAG:]ERR CODE MESSAGE*CRC`` + LF, where CRC is
  four upper-case hex digits of CRC-16/CCITT-FALSE over every byte before the ``*``, and TAG
  echoes the command's tag (decimal 0..65535) so a late reply to an earlier command is recognised.
* all times are integer nanoseconds, positions are 16-bit DAC codes.

Everything here raises :class:`drivers.errors.ProtocolError` for bytes that do not decode and never
anything else, whatever the input (the hypothesis tests feed it random and truncated bytes).
"""

from __future__ import annotations

import binascii
import re
from dataclasses import dataclass
from enum import IntEnum

from spdepth.drivers.errors import ProtocolError, SettingError

from .errors import ErrorCode, GalvoReplyError, reply_error

TERMINATOR = b"\n"
"""Every command and reply line ends with LF (0x0A)."""
ENCODING = "ascii"
MAX_COMMAND_BYTES = 256
"""Longest command line the controller accepts, terminator included."""
MAX_REPLY_BYTES = 16384
"""Longest reply line (a full ``PIX?`` page); longer input is garbage."""
MAX_TAG = 65535
DAC_MAX_CODE = 65535
"""16-bit DAC: codes 0..65535 on each axis."""
MAX_PIXELS_PER_AXIS = 4096
MAX_FRAMES = 65535
MAX_N_TARGET = 65535
MIN_DWELL_NS = 100
MAX_DWELL_NS = 10_000_000_000
MAX_SETTLE_NS = 100_000_000
PIXEL_LOG_DEPTH = 4096
"""Completed-pixel records the controller keeps; older ones are overwritten."""
MAX_PIX_PAGE = 256
"""Most records one ``PIX?`` reply carries."""


def crc16(data: bytes) -> int:
    """CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF, no reflection, no final xor); check value
    for b"123456789" is 0x29B1."""
    return binascii.crc_hqx(data, 0xFFFF)


class GalvoState(IntEnum):
    """Controller state as reported by ``STAT?`` (the wire token is the member name)."""

    IDLE = 0
    """Not scanning; the mirror holds the last ``POS``."""
    SCANNING = 1
    """A scan runs; configuration and moves are refused with BUSY."""
    PARKED = 2
    """Not scanning; the mirror sits at the park position (after PARK, STOP or a finished scan)."""
    FAULT = 3
    """The servo faulted; the scan was aborted; ``*CLS`` clears it and re-parks."""


class ScanMode(IntEnum):
    """Order in which a frame's pixels are visited."""

    RASTER = 0
    """Every line left to right (increasing column)."""
    SERPENTINE = 1
    """Even lines (0, 2, ...) left to right, odd lines right to left."""

    @property
    def token(self) -> str:
        return _MODE_TOKENS[self]


_MODE_TOKENS = {ScanMode.RASTER: "RASTER", ScanMode.SERPENTINE: "SERP"}
_MODE_BY_TOKEN = {v: k for k, v in _MODE_TOKENS.items()}


class GateMode(IntEnum):
    """How long the controller holds each pixel."""

    COUNT = 0
    """Until ``n_target`` detector pulses were counted or the dwell limit passed."""
    FIXED = 1
    """For a fixed dwell."""


class PixelFlag(IntEnum):
    """How a pixel's dwell ended (one letter in ``PIX?`` records)."""

    GATED = ord("G")
    """Count-gated: the target count was reached."""
    LIMIT = ord("L")
    """Count-gated: the dwell limit passed first (fewer counts than the target)."""
    FIXED = ord("F")
    """Fixed dwell."""


# ---- typed values --------------------------------------------------------------------------------

@dataclass(frozen=True)
class Identity:
    """``*IDN?``: maker, model, serial number, firmware version."""

    maker: str
    model: str
    serial: str
    firmware: str


@dataclass(frozen=True)
class Calibration:
    """``CAL?``: DAC code of 0 optical degrees and micro-degrees (optical) per code, per axis."""

    x_zero_code: int
    x_udeg_per_code: float
    y_zero_code: int
    y_udeg_per_code: float

    def to_deg(self, x_code: int, y_code: int) -> tuple[float, float]:
        """DAC codes -> optical degrees."""
        return ((x_code - self.x_zero_code) * self.x_udeg_per_code * 1e-6,
                (y_code - self.y_zero_code) * self.y_udeg_per_code * 1e-6)

    def to_codes(self, x_deg: float, y_deg: float) -> tuple[int, int]:
        """Optical degrees -> nearest DAC codes (may lie outside 0..65535; callers check)."""
        return (int(round(x_deg / (self.x_udeg_per_code * 1e-6) + self.x_zero_code)),
                int(round(y_deg / (self.y_udeg_per_code * 1e-6) + self.y_zero_code)))


@dataclass(frozen=True)
class Limits:
    """``LIM?``: soft limits in DAC codes, inclusive."""

    x_min: int = 0
    x_max: int = DAC_MAX_CODE
    y_min: int = 0
    y_max: int = DAC_MAX_CODE

    def contains(self, x_code: int, y_code: int) -> bool:
        return self.x_min <= x_code <= self.x_max and self.y_min <= y_code <= self.y_max


@dataclass(frozen=True)
class PatternCodes:
    """``PAT``: visiting order, pixel counts, DAC codes of the first and last column / row centres."""

    mode: ScanMode
    nx: int
    ny: int
    x_first: int
    x_last: int
    y_first: int
    y_last: int

    def x_code(self, col: int) -> int:
        """DAC code of column ``col`` (linear between first and last, rounded half up)."""
        return _lerp_code(self.x_first, self.x_last, col, self.nx)

    def y_code(self, row: int) -> int:
        return _lerp_code(self.y_first, self.y_last, row, self.ny)


def _lerp_code(first: int, last: int, i: int, n: int) -> int:
    if n == 1:
        return first
    # Integer arithmetic so the host and any firmware agree on every code exactly.
    num = (last - first) * i
    den = n - 1
    return first + (2 * num + den) // (2 * den)


@dataclass(frozen=True)
class GateSetting:
    """``GATE``: mode, target count (COUNT only, else 0) and dwell (limit for COUNT) in ns."""

    mode: GateMode
    n_target: int
    dwell_ns: int


@dataclass(frozen=True)
class Status:
    """``STAT?``: state, scan number (STARTs since power-on), the pixel the mirror is on or was
    last on (-1 before the first scan), pixels completed in this scan and the scan's total
    (0 for a continuous scan)."""

    state: GalvoState
    scan_id: int
    frame: int
    row: int
    col: int
    completed: int
    total: int


@dataclass(frozen=True)
class PixelRecord:
    """One completed pixel from the pixel log: ``seq`` counts completed pixels from 0 at START."""

    seq: int
    frame: int
    row: int
    col: int
    count: int
    dwell_ns: int
    flag: PixelFlag

    @property
    def dwell_s(self) -> float:
        return self.dwell_ns * 1e-9


@dataclass(frozen=True)
class PixelPage:
    """One ``PIX?`` reply: records from ``first_seq`` on. ``first_seq > from_seq`` means the
    records in between were overwritten before the host asked (``lost`` of them)."""

    from_seq: int
    first_seq: int
    records: tuple[PixelRecord, ...]

    @property
    def lost(self) -> int:
        return self.first_seq - self.from_seq

    @property
    def next_seq(self) -> int:
        return self.first_seq + len(self.records)


@dataclass(frozen=True)
class Reply:
    """One decoded reply line: ``ok`` with ``payload``, or an error ``code`` and ``message``."""

    tag: int | None
    ok: bool
    payload: str = ""
    code: ErrorCode = ErrorCode.NO_ERROR
    message: str = ""

    def raise_for_error(self, command: str = "") -> str:
        """The payload of an OK reply; raises the matching GalvoReplyError for ERR."""
        if not self.ok:
            raise reply_error(self.code, self.message, command)
        return self.payload


# ---- encoding --------------------------------------------------------------------------------

_MNEMONIC_RE = re.compile(r"^(\*?[A-Z]+\??)$")


def encode_command(mnemonic: str, *args: int | str, tag: int | None = None) -> bytes:
    """One command line: ``encode_command("POS", 100, 200, tag=7) == b"7:POS 100 200\\n"``.

    Arguments are ints (written in decimal) or upper-case keywords. Raises SettingError for
    anything the controller could not parse, so bad values never reach the wire."""
    if not _MNEMONIC_RE.match(mnemonic):
        raise SettingError(f"galvo command mnemonic {mnemonic!r} is not like 'POS' or '*IDN?'")
    parts = [mnemonic]
    for a in args:
        if isinstance(a, bool):
            raise SettingError(f"galvo command {mnemonic}: argument {a!r} is not an integer")
        if isinstance(a, int) or hasattr(a, "__index__"):
            parts.append(str(int(a)))
        elif isinstance(a, str) and re.fullmatch(r"[A-Z]+", a):
            parts.append(a)
        else:
            raise SettingError(f"galvo command {mnemonic}: argument {a!r} is not an integer "
                             f"or an upper-case keyword")
    body = " ".join(parts)
    if tag is not None:
        if not 0 <= tag <= MAX_TAG:
            raise SettingError(f"galvo command tag {tag} outside 0..{MAX_TAG}")
        body = f"{tag}:{body}"
    line = body.encode(ENCODING) + TERMINATOR
    if len(line) > MAX_COMMAND_BYTES:
        raise SettingError(f"galvo command {body[:40]!r}... is longer than {MAX_COMMAND_BYTES} bytes")
    return line


def encode_reply(body: str, tag: int | None = None) -> bytes:
    """A reply line with its tag and CRC (what the controller sends; used by the emulator)."""
    text = (f"{tag}:" if tag is not None else "") + body
    raw = text.encode(ENCODING)
    return raw + b"*%04X" % crc16(raw) + TERMINATOR


def encode_pattern(p: PatternCodes) -> tuple:
    return (p.mode.token, p.nx, p.ny, p.x_first, p.x_last, p.y_first, p.y_last)


def encode_gate(g: GateSetting) -> tuple:
    if g.mode == GateMode.COUNT:
        return ("COUNT", g.n_target, g.dwell_ns)
    return ("FIXED", g.dwell_ns)


# ---- decoding --------------------------------------------------------------------------------

_REPLY_RE = re.compile(r"^(?:(\d{1,5}):)?(OK|ERR)(?: (.*))?$", re.DOTALL)
_ERR_RE = re.compile(r"^(\d{1,3}) (.+)$", re.DOTALL)
_INT_RE = re.compile(r"^-?[0-9]{1,20}\Z")   # \Z, not $: "12\n" is not an integer
_NON_PRINTABLE_RE = re.compile(rb"[^\x20-\x7e]")


def decode_reply(line: bytes) -> Reply:
    """Check framing, characters and CRC of one reply line (LF included) and split it.

    Raises ProtocolError for anything that is not a well-formed reply."""
    if not isinstance(line, (bytes, bytearray)):
        raise ProtocolError(f"galvo reply must be bytes, got {type(line).__name__}")
    line = bytes(line)
    if not line.endswith(TERMINATOR):
        raise ProtocolError(f"galvo reply {line[:60]!r} is truncated (no LF terminator)")
    if len(line) > MAX_REPLY_BYTES:
        raise ProtocolError(f"galvo reply of {len(line)} bytes is longer than {MAX_REPLY_BYTES}")
    body = line[:-1]
    if body.endswith(b"\r"):
        body = body[:-1]
    if _NON_PRINTABLE_RE.search(body):
        raise ProtocolError(f"galvo reply {line[:60]!r} holds non-printable bytes")
    star = body.rfind(b"*")
    if star < 0 or len(body) - star != 5:
        raise ProtocolError(f"galvo reply {line[:60]!r} has no *CRC suffix")
    text, crc_hex = body[:star], body[star + 1:]
    if not re.fullmatch(rb"[0-9A-F]{4}", crc_hex):
        raise ProtocolError(f"galvo reply {line[:60]!r}: CRC {crc_hex!r} is not 4 hex digits")
    if int(crc_hex, 16) != crc16(text):
        raise ProtocolError(f"galvo reply {line[:60]!r} fails its CRC "
                            f"(got {crc_hex.decode()}, computed {crc16(text):04X})")
    m = _REPLY_RE.match(text.decode(ENCODING))
    if m is None:
        raise ProtocolError(f"galvo reply {line[:60]!r} is neither OK nor ERR")
    tag = None
    if m.group(1) is not None:
        tag = int(m.group(1))
        if tag > MAX_TAG:
            raise ProtocolError(f"galvo reply tag {tag} outside 0..{MAX_TAG}")
    rest = m.group(3)
    if m.group(2) == "OK":
        return Reply(tag, True, rest or "")
    em = _ERR_RE.match(rest or "")
    if em is None:
        raise ProtocolError(f"galvo error reply {line[:60]!r} is not 'ERR <code> <message>'")
    code = int(em.group(1))
    if code == 0 or code not in ErrorCode._value2member_map_:
        raise ProtocolError(f"galvo error reply {line[:60]!r}: unknown error code {code}")
    return Reply(tag, False, "", ErrorCode(code), em.group(2))


def _ints(payload: str, n: int, what: str) -> list[int]:
    toks = payload.split(" ")
    if len(toks) != n or not all(_INT_RE.match(t) for t in toks):
        raise ProtocolError(f"galvo {what} reply {payload[:80]!r}: expected {n} integers")
    return [int(t) for t in toks]


def _check_codes(values, what: str, payload: str) -> None:
    if not all(0 <= v <= DAC_MAX_CODE for v in values):
        raise ProtocolError(f"galvo {what} reply {payload[:80]!r}: DAC code outside 0..65535")


def parse_ok(payload: str) -> None:
    """A bare ``OK`` (commands that set or act)."""
    if payload:
        raise ProtocolError(f"galvo reply: expected a bare OK, got payload {payload[:80]!r}")


_SERIAL_RE = re.compile(r"[A-Za-z0-9_.-]{1,32}")
"""A serial number as the spec allows it; the driver compares it after a reconnect."""


def parse_identity(payload: str) -> Identity:
    parts = payload.split(",")
    if len(parts) != 4 or not all(p.strip() for p in parts):
        raise ProtocolError(f"galvo *IDN? reply {payload[:80]!r}: expected maker,model,serial,fw")
    ident = Identity(*(p.strip() for p in parts))
    if not _SERIAL_RE.fullmatch(ident.serial):
        raise ProtocolError(f"galvo *IDN? reply {payload[:80]!r}: serial {ident.serial[:40]!r} is "
                            f"not 1-32 of A-Z a-z 0-9 _ . -")
    return ident


_FLOAT_RE = re.compile(r"^[0-9]{1,10}(?:\.[0-9]{1,12})?\Z")


def parse_calibration(payload: str) -> Calibration:
    toks = payload.split(" ")
    if (len(toks) != 4 or not _INT_RE.match(toks[0]) or not _INT_RE.match(toks[2])
            or not _FLOAT_RE.match(toks[1]) or not _FLOAT_RE.match(toks[3])):
        raise ProtocolError(f"galvo CAL? reply {payload[:80]!r}: expected "
                            f"'<x_zero> <x_udeg_per_code> <y_zero> <y_udeg_per_code>'")
    cal = Calibration(int(toks[0]), float(toks[1]), int(toks[2]), float(toks[3]))
    _check_codes((cal.x_zero_code, cal.y_zero_code), "CAL?", payload)
    if cal.x_udeg_per_code <= 0 or cal.y_udeg_per_code <= 0:
        raise ProtocolError(f"galvo CAL? reply {payload[:80]!r}: scale must be positive")
    return cal


def parse_position(payload: str, what: str = "POS?") -> tuple[int, int]:
    x, y = _ints(payload, 2, what)
    _check_codes((x, y), what, payload)
    return x, y


def parse_limits(payload: str) -> Limits:
    v = _ints(payload, 4, "LIM?")
    _check_codes(v, "LIM?", payload)
    if v[0] > v[1] or v[2] > v[3]:
        raise ProtocolError(f"galvo LIM? reply {payload[:80]!r}: min above max")
    return Limits(*v)


def parse_pattern(payload: str) -> PatternCodes:
    toks = payload.split(" ", 1)
    if len(toks) != 2 or toks[0] not in _MODE_BY_TOKEN:
        raise ProtocolError(f"galvo PAT? reply {payload[:80]!r}: expected RASTER|SERP and 6 ints")
    nx, ny, x0, x1, y0, y1 = _ints(toks[1], 6, "PAT?")
    if not (1 <= nx <= MAX_PIXELS_PER_AXIS and 1 <= ny <= MAX_PIXELS_PER_AXIS):
        raise ProtocolError(f"galvo PAT? reply {payload[:80]!r}: pixel counts out of range")
    _check_codes((x0, x1, y0, y1), "PAT?", payload)
    return PatternCodes(_MODE_BY_TOKEN[toks[0]], nx, ny, x0, x1, y0, y1)


def parse_gate(payload: str) -> GateSetting:
    toks = payload.split(" ", 1)
    if len(toks) == 2 and toks[0] == "COUNT":
        n, dwell = _ints(toks[1], 2, "GATE?")
        if 1 <= n <= MAX_N_TARGET and MIN_DWELL_NS <= dwell <= MAX_DWELL_NS:
            return GateSetting(GateMode.COUNT, n, dwell)
    elif len(toks) == 2 and toks[0] == "FIXED":
        (dwell,) = _ints(toks[1], 1, "GATE?")
        if MIN_DWELL_NS <= dwell <= MAX_DWELL_NS:
            return GateSetting(GateMode.FIXED, 0, dwell)
    raise ProtocolError(f"galvo GATE? reply {payload[:80]!r}: expected 'COUNT <n> <limit_ns>' "
                        f"or 'FIXED <dwell_ns>' in range")


def parse_int(payload: str, what: str, lo: int, hi: int) -> int:
    (v,) = _ints(payload, 1, what)
    if not lo <= v <= hi:
        raise ProtocolError(f"galvo {what} reply {payload[:80]!r}: outside {lo}..{hi}")
    return v


def parse_status(payload: str) -> Status:
    toks = payload.split(" ", 1)
    if len(toks) != 2 or toks[0] not in GalvoState.__members__:
        raise ProtocolError(f"galvo STAT? reply {payload[:80]!r}: expected a state and 6 ints")
    scan_id, frame, row, col, completed, total = _ints(toks[1], 6, "STAT?")
    if min(scan_id, completed, total) < 0 or min(frame, row, col) < -1:
        raise ProtocolError(f"galvo STAT? reply {payload[:80]!r}: negative counter")
    # -1 -1 -1 before the first scan, else a real pixel: never a mix
    if (frame, row, col) != (-1, -1, -1) and (min(frame, row, col) < 0
                                              or max(row, col) >= MAX_PIXELS_PER_AXIS):
        raise ProtocolError(f"galvo STAT? reply {payload[:80]!r}: pixel {frame},{row},{col} "
                            f"is neither -1,-1,-1 nor a pixel of a pattern")
    if total > 0 and completed > total:
        raise ProtocolError(f"galvo STAT? reply {payload[:80]!r}: {completed} pixels done of "
                            f"{total}")
    return Status(GalvoState[toks[0]], scan_id, frame, row, col, completed, total)


_FLAG_BY_LETTER = {chr(f.value): f for f in PixelFlag}
_PIX_RECORD = (r"-?[0-9]{1,20},-?[0-9]{1,20},-?[0-9]{1,20},-?[0-9]{1,20},-?[0-9]{1,20},[%s]"
               % "".join(map(re.escape, _FLAG_BY_LETTER)))
"""One PIX? record: five decimal integers (as _INT_RE) and a flag letter."""
_PIX_RECORDS_RE = re.compile(rf"{_PIX_RECORD}(?: {_PIX_RECORD})*\Z")
_PIX_RECORD_RE = re.compile(rf"{_PIX_RECORD}\Z")
_NUMBER_RE = re.compile(r"-?[0-9]+")


def parse_pixels(payload: str, from_seq: int) -> PixelPage:
    """``PIX?`` reply: ``<first_seq> <n> [<frame>,<row>,<col>,<count>,<dwell_ns>,<flag>]...``."""
    toks = payload.split(" ")
    if len(toks) < 2 or not _INT_RE.match(toks[0]) or not _INT_RE.match(toks[1]):
        raise ProtocolError(f"galvo PIX? reply {payload[:80]!r}: expected '<first_seq> <n> ...'")
    first, n = int(toks[0]), int(toks[1])
    if first < from_seq or not 0 <= n <= MAX_PIX_PAGE or len(toks) != 2 + n:
        raise ProtocolError(f"galvo PIX? reply {payload[:80]!r}: first_seq {first} / count {n} "
                            f"do not match the request from {from_seq} and {len(toks) - 2} records")
    recs = toks[2:]
    # a page holds up to 256 records: checked and split by one regex each, not per record
    text = " ".join(recs)
    if recs and _PIX_RECORDS_RE.match(text) is None:
        bad = next(r for r in recs if _PIX_RECORD_RE.match(r) is None)
        raise ProtocolError(f"galvo PIX? record {bad[:60]!r} is not "
                            f"'frame,row,col,count,dwell_ns,G|L|F'")
    values = iter(map(int, _NUMBER_RE.findall(text)))
    records = []
    for i, (rec, frame, row, col, count, dwell) in enumerate(
            zip(recs, values, values, values, values, values)):
        if min(frame, row, col, count, dwell) < 0:
            raise ProtocolError(f"galvo PIX? record {rec[:60]!r} holds a negative value")
        if max(row, col) >= MAX_PIXELS_PER_AXIS:
            raise ProtocolError(f"galvo PIX? record {rec[:60]!r}: row or column beyond "
                                f"{MAX_PIXELS_PER_AXIS - 1}")
        records.append(PixelRecord(first + i, frame, row, col, count, dwell,
                                   _FLAG_BY_LETTER[rec[-1]]))
    return PixelPage(from_seq, first, tuple(records))


def parse_error_query(payload: str) -> tuple[ErrorCode, str]:
    """``ERR?`` reply: ``<code> <message>``; code 0 means the queue is empty."""
    m = _ERR_RE.match(payload)
    if m is None or int(m.group(1)) not in ErrorCode._value2member_map_:
        raise ProtocolError(f"galvo ERR? reply {payload[:80]!r}: expected '<code> <message>'")
    return ErrorCode(int(m.group(1))), m.group(2)


__all__ = [
    "TERMINATOR", "crc16", "GalvoState", "ScanMode", "GateMode", "PixelFlag", "Identity",
    "Calibration", "Limits", "PatternCodes", "GateSetting", "Status", "PixelRecord", "PixelPage",
    "Reply", "encode_command", "encode_reply", "decode_reply", "GalvoReplyError",
]
