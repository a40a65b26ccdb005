"""The tagger's USB protocol as pure data: vendor control requests, their payloads, status bits.

No I/O here. ``docs/protocols.md`` (section "TCSPC time tagger") is the human-readable twin of this
module; keep them in step. All multi-byte fields are little endian.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from enum import IntEnum, IntFlag

from spdepth.drivers.errors import ProtocolError, SettingError

VENDOR_ID = 0x1209
"""pid.codes (open-source hardware) vendor id; the simulated tagger enumerates with it."""
PRODUCT_ID = 0x7A64
"""Product id of the spdepth time tagger (simulated device); a real unit is opened by its own ids."""

INTERFACE = 0
"""The one interface: control requests on endpoint 0, records on the bulk IN endpoint."""
BULK_IN_EP = 0x81
"""Bulk IN endpoint streaming T3 records (wMaxPacketSize 512, USB 2.0 high speed)."""
BULK_MAX_PACKET = 512

REQUEST_TYPE_IN = 0xC0
"""bmRequestType of device-to-host vendor requests (direction IN | type vendor | recipient device)."""
REQUEST_TYPE_OUT = 0x40
"""bmRequestType of host-to-device vendor requests (direction OUT | type vendor | recipient device)."""

MAGIC = b"SPDT"
"""First four bytes of the identity reply."""
PROTOCOL_VERSION = 1
"""Protocol version this driver speaks (identity reply field)."""

MAX_BINNING = 15
"""Binning codes 0..15: resolution = base resolution * 2**binning."""
SYNC_DIVIDERS = (1, 2, 4, 8, 16)
"""Accepted sync dividers: the tagger counts every n-th laser sync."""
MARKER_INPUTS = 4
"""Marker inputs 1..4 (bit n-1 of masks)."""


class Request(IntEnum):
    """bRequest codes of the vendor control requests."""

    GET_IDENTITY = 0x01
    """IN, 32 bytes: magic, protocol and firmware version, channels, base resolution, FIFO depth, serial."""
    SET_BINNING = 0x10
    """OUT, no data: wValue = binning code 0..15 (resolution = base * 2**code). Refused while running."""
    GET_BINNING = 0x11
    """IN, 8 bytes: u16 binning code, u16 reserved (0), u32 resolution in femtoseconds."""
    SET_SYNC_DIVIDER = 0x12
    """OUT, no data: wValue = sync divider (1, 2, 4, 8, 16). Refused while running."""
    GET_SYNC_DIVIDER = 0x13
    """IN, 2 bytes: u16 sync divider."""
    SET_MARKERS = 0x14
    """OUT, no data: wValue = enabled marker inputs (bit n-1 = input n), wIndex = rising-edge mask
    (bit set: the input triggers on its rising edge, clear: falling)."""
    GET_MARKERS = 0x15
    """IN, 4 bytes: u16 enabled mask, u16 rising-edge mask."""
    START = 0x20
    """OUT, no data: clear the FIFO, the counters and the sync counter, start streaming records."""
    STOP = 0x21
    """OUT, no data: stop measuring; records already in the FIFO can still be read."""
    GET_STATUS = 0x30
    """IN, 24 bytes: u32 flags (StatusFlag), u32 FIFO fill (records), u32 records lost since START
    (saturating), u32 records lost in the pending gap, u64 stream position of the pending gap."""
    ACK_GAP = 0x31
    """IN, 20 bytes: u64 stream position of the gap, u64 sync (since START) where loss began,
    u32 records lost in the gap. Clears OVERRUN and releases the records held after the gap.
    Stalls (pipe error) when no gap is pending."""


class StatusFlag(IntFlag):
    """Bits of the GET_STATUS flags word."""

    RUNNING = 0x1
    """A measurement runs (between START and STOP)."""
    OVERRUN = 0x2
    """The FIFO overran: records were lost. Latched until ACK_GAP; the device holds back every
    record after the gap until then, so the gap sits exactly at the reported stream position."""
    FIFO_FULL = 0x4
    """The FIFO is full right now (records are being dropped)."""


_IDENTITY = struct.Struct("<4sHBBHBBII12s")
_BINNING = struct.Struct("<HHI")
_U16 = struct.Struct("<H")
_MARKERS = struct.Struct("<HH")
_STATUS = struct.Struct("<IIIIQ")
_GAP = struct.Struct("<QQI")

IDENTITY_LENGTH = _IDENTITY.size      # 32
BINNING_LENGTH = _BINNING.size        # 8
SYNC_DIVIDER_LENGTH = _U16.size       # 2
MARKERS_LENGTH = _MARKERS.size        # 4
STATUS_LENGTH = _STATUS.size          # 24
GAP_LENGTH = _GAP.size                # 20


@dataclass(frozen=True)
class Setup:
    """One control transfer as sent: the setup packet fields and the OUT data (or IN length)."""

    bmRequestType: int
    bRequest: int
    wValue: int = 0
    wIndex: int = 0
    data: bytes = b""
    wLength: int = 0


@dataclass(frozen=True)
class TaggerIdentity:
    """Reply of GET_IDENTITY."""

    protocol_version: int
    firmware_version: tuple[int, int, int]
    n_channels: int
    n_marker_inputs: int
    base_resolution_s: float
    fifo_capacity_records: int
    serial: str

    @property
    def firmware(self) -> str:
        return ".".join(map(str, self.firmware_version))


@dataclass(frozen=True)
class Binning:
    """Reply of GET_BINNING: code and the resulting dtime unit (seconds)."""

    code: int
    resolution_s: float


@dataclass(frozen=True)
class MarkerConfig:
    """Marker inputs: enabled mask and rising-edge mask (bit n-1 = input n)."""

    enabled_mask: int
    rising_mask: int


@dataclass(frozen=True)
class TaggerStatus:
    """Reply of GET_STATUS."""

    flags: StatusFlag
    fifo_fill_records: int
    lost_records: int
    gap_lost_records: int
    gap_position: int

    @property
    def running(self) -> bool:
        return bool(self.flags & StatusFlag.RUNNING)

    @property
    def overrun(self) -> bool:
        return bool(self.flags & StatusFlag.OVERRUN)


@dataclass(frozen=True)
class Gap:
    """Reply of ACK_GAP: where the stream has a hole. ``position`` counts records since START
    (the first record after the gap has this index); ``sync`` is the device sync since START
    where loss began; ``lost_records`` how many records were dropped."""

    position: int
    sync: int
    lost_records: int


# ---- requests ------------------------------------------------------------------------------------

def _in(request: Request, length: int, value: int = 0, index: int = 0) -> Setup:
    return Setup(REQUEST_TYPE_IN, int(request), value, index, b"", length)


def _out(request: Request, value: int = 0, index: int = 0) -> Setup:
    return Setup(REQUEST_TYPE_OUT, int(request), value, index, b"", 0)


def get_identity() -> Setup:
    return _in(Request.GET_IDENTITY, IDENTITY_LENGTH)


def set_binning(code: int) -> Setup:
    if not 0 <= int(code) <= MAX_BINNING:
        raise SettingError(f"tagger binning code {code} is outside 0..{MAX_BINNING}")
    return _out(Request.SET_BINNING, int(code))


def get_binning() -> Setup:
    return _in(Request.GET_BINNING, BINNING_LENGTH)


def set_sync_divider(divider: int) -> Setup:
    if int(divider) not in SYNC_DIVIDERS:
        raise SettingError(f"tagger sync divider {divider} is not one of {SYNC_DIVIDERS}")
    return _out(Request.SET_SYNC_DIVIDER, int(divider))


def get_sync_divider() -> Setup:
    return _in(Request.GET_SYNC_DIVIDER, SYNC_DIVIDER_LENGTH)


def set_markers(enabled_mask: int, rising_mask: int) -> Setup:
    full = (1 << MARKER_INPUTS) - 1
    for name, m in (("enabled", enabled_mask), ("rising-edge", rising_mask)):
        if not 0 <= int(m) <= full:
            raise SettingError(f"tagger {name} marker mask {m:#x} is outside 0..{full:#x}")
    return _out(Request.SET_MARKERS, int(enabled_mask), int(rising_mask))


def get_markers() -> Setup:
    return _in(Request.GET_MARKERS, MARKERS_LENGTH)


def start() -> Setup:
    return _out(Request.START)


def stop() -> Setup:
    return _out(Request.STOP)


def get_status() -> Setup:
    return _in(Request.GET_STATUS, STATUS_LENGTH)


def ack_gap() -> Setup:
    return _in(Request.ACK_GAP, GAP_LENGTH)


# ---- replies -------------------------------------------------------------------------------------

def _exact(name: str, data: bytes, length: int) -> bytes:
    data = bytes(data)
    if len(data) != length:
        raise ProtocolError(f"tagger {name} reply has {len(data)} bytes, expected {length}: "
                            f"{data[:40].hex()}")
    return data


def decode_identity(data: bytes) -> TaggerIdentity:
    data = _exact("GET_IDENTITY", data, IDENTITY_LENGTH)
    magic, proto, major, minor, patch, n_ch, n_mk, base_fs, fifo, serial = _IDENTITY.unpack(data)
    if magic != MAGIC:
        raise ProtocolError(f"tagger identity starts with {magic!r}, expected {MAGIC!r}")
    if proto != PROTOCOL_VERSION:
        raise ProtocolError(f"tagger speaks protocol version {proto}, this driver {PROTOCOL_VERSION}")
    if base_fs == 0 or n_ch == 0 or n_ch > 64 or n_mk > 15 or fifo == 0:
        raise ProtocolError(f"tagger identity has impossible values: channels={n_ch}, "
                            f"markers={n_mk}, base resolution={base_fs} fs, FIFO={fifo}")
    try:
        text = serial.rstrip(b"\0").decode("ascii")
    except UnicodeDecodeError:
        raise ProtocolError(f"tagger serial number {serial!r} is not ASCII") from None
    if not text.isprintable():
        raise ProtocolError(f"tagger serial number {serial!r} is not printable")
    return TaggerIdentity(proto, (major, minor, patch), n_ch, n_mk, base_fs * 1e-15, fifo, text)


def encode_identity(identity: TaggerIdentity) -> bytes:
    """Device side (simulator): the GET_IDENTITY reply."""
    return _IDENTITY.pack(MAGIC, identity.protocol_version, *identity.firmware_version,
                          identity.n_channels, identity.n_marker_inputs,
                          int(round(identity.base_resolution_s * 1e15)),
                          identity.fifo_capacity_records, identity.serial.encode("ascii"))


def decode_binning(data: bytes) -> Binning:
    code, reserved, res_fs = _BINNING.unpack(_exact("GET_BINNING", data, BINNING_LENGTH))
    if code > MAX_BINNING or reserved != 0 or res_fs == 0:
        raise ProtocolError(f"tagger binning reply is invalid: code={code}, reserved={reserved}, "
                            f"resolution={res_fs} fs")
    return Binning(code, res_fs * 1e-15)


def encode_binning(code: int, resolution_s: float) -> bytes:
    return _BINNING.pack(code, 0, int(round(resolution_s * 1e15)))


def decode_sync_divider(data: bytes) -> int:
    (div,) = _U16.unpack(_exact("GET_SYNC_DIVIDER", data, SYNC_DIVIDER_LENGTH))
    if div not in SYNC_DIVIDERS:
        raise ProtocolError(f"tagger reports sync divider {div}, not one of {SYNC_DIVIDERS}")
    return div


def encode_sync_divider(divider: int) -> bytes:
    return _U16.pack(divider)


def decode_markers(data: bytes) -> MarkerConfig:
    en, rising = _MARKERS.unpack(_exact("GET_MARKERS", data, MARKERS_LENGTH))
    full = (1 << MARKER_INPUTS) - 1
    if en & ~full or rising & ~full:
        raise ProtocolError(f"tagger marker masks {en:#x}/{rising:#x} name inputs beyond "
                            f"{MARKER_INPUTS}")
    return MarkerConfig(en, rising)


def encode_markers(config: MarkerConfig) -> bytes:
    return _MARKERS.pack(config.enabled_mask, config.rising_mask)


def decode_status(data: bytes) -> TaggerStatus:
    flags, fill, lost, gap_lost, gap_pos = _STATUS.unpack(_exact("GET_STATUS", data, STATUS_LENGTH))
    if flags & ~int(StatusFlag.RUNNING | StatusFlag.OVERRUN | StatusFlag.FIFO_FULL):
        raise ProtocolError(f"tagger status has undefined flag bits: {flags:#010x}")
    if not flags & StatusFlag.OVERRUN and (gap_lost or gap_pos):
        raise ProtocolError(f"tagger status reports a gap ({gap_lost} records at {gap_pos}) "
                            f"without the OVERRUN flag")
    return TaggerStatus(StatusFlag(flags), fill, lost, gap_lost, gap_pos)


def encode_status(status: TaggerStatus) -> bytes:
    return _STATUS.pack(int(status.flags), status.fifo_fill_records,
                        min(status.lost_records, 2 ** 32 - 1),
                        min(status.gap_lost_records, 2 ** 32 - 1), status.gap_position)


def decode_gap(data: bytes) -> Gap:
    pos, sync, lost = _GAP.unpack(_exact("ACK_GAP", data, GAP_LENGTH))
    if pos >= 2 ** 63 or sync >= 2 ** 63:
        raise ProtocolError(f"tagger gap reply out of range: position={pos}, sync={sync}")
    return Gap(pos, sync, lost)


def encode_gap(gap: Gap) -> bytes:
    return _GAP.pack(gap.position, gap.sync, min(gap.lost_records, 2 ** 32 - 1))


def parse_url(url: str) -> tuple[int, int]:
    """``usb:VID:PID`` (hex, with or without 0x) -> (vid, pid). Raises SettingError."""
    parts = str(url).split(":")
    if len(parts) != 3 or parts[0].lower() != "usb":
        raise SettingError(f"tagger address {url!r} is not like 'usb:1209:7a64'")
    try:
        vid, pid = (int(p, 16) for p in parts[1:])
    except ValueError:
        raise SettingError(f"tagger address {url!r}: VID and PID must be hexadecimal") from None
    if not (0 <= vid <= 0xFFFF and 0 <= pid <= 0xFFFF):
        raise SettingError(f"tagger address {url!r}: VID and PID must fit 16 bits")
    return vid, pid
