"""PicoQuant TCSPC libraries as data: the device families we drive, their function prefixes, the
codes their C functions take and return (from the vendor headers ``mhdefin.h``/``hhdefin.h`` and
``errorcodes.h`` of PicoQuant's public demo repositories), and the record type each device writes.
No I/O here: ``transport`` calls the library, ``device`` holds state."""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum, IntFlag

from spdepth.drivers.errors import SettingError


class MeasMode(IntEnum):
    """``*_Initialize`` modes."""

    HIST = 0
    """Histogramming (not used here)."""
    T2 = 2
    """Time-tagged T2 (absolute times; not used here)."""
    T3 = 3
    """Time-tagged T3: sync count and time after the sync, the mode we record."""


class RefSource(IntEnum):
    """``*_Initialize`` reference clock (the first two of mhdefin.h's list)."""

    INTERNAL = 0
    """The device's own clock."""
    EXTERNAL_10MHZ = 1
    """A 10 MHz reference on the REF input."""


class Edge(IntEnum):
    """Marker, sync and input edges."""

    FALLING = 0
    """Trigger on the falling edge."""
    RISING = 1
    """Trigger on the rising edge."""


class Flag(IntFlag):
    """``*_GetFlags`` bits."""

    OVERFLOW = 0x0001
    """Histogram mode only: a histogram bin overflowed."""
    FIFOFULL = 0x0002
    """TTTR mode: the FIFO overran; records are lost and the measurement halted."""
    SYNC_LOST = 0x0004
    """The sync signal is gone."""
    REF_LOST = 0x0008
    """The external reference clock is gone."""
    SYSERROR = 0x0010
    """Hardware error (the vendor says: contact support)."""
    ACTIVE = 0x0020
    """A measurement is running."""
    CNTS_DROPPED = 0x0040
    """Counts were dropped (input rate beyond what the device transfers)."""


class LibError(IntEnum):
    """Return codes of the library functions we meet (errorcodes.h; 0 is success). Others are
    reported with the library's own error string."""

    NONE = 0
    """Success."""
    DEVICE_OPEN_FAIL = -1
    """No device at this index (or it is used by another program)."""
    DEVICE_BUSY = -2
    """The device is busy."""
    DEVICE_NOT_OPEN = -10
    """The index was not opened (or the device went away)."""
    DEVICE_LOCKED = -11
    """Another process holds the device."""
    INSTANCE_RUNNING = -16
    """Another instance of the library runs."""
    INVALID_ARGUMENT = -17
    """An argument is out of range."""
    INVALID_MODE = -18
    """The call does not fit the initialised mode."""
    NOT_INITIALIZED = -22
    """``*_Initialize`` was not called."""
    USB_BULKRD_FAIL = -37
    """A USB bulk read failed (cable, hub, power)."""


DEVICE_GONE_ERRORS = frozenset({LibError.DEVICE_NOT_OPEN, LibError.DEVICE_OPEN_FAIL})
"""Codes after which the device must be reopened."""

# T3 record types written to PTU files (``TTResultFormat_TTTRRecType``; ptufile's PtuRecordType)
RECORD_TYPE_GENERIC_T3 = 0x00010307
"""MultiHarp, PicoHarp 330, HydraHarp 500: Generic T3 records."""
RECORD_TYPE_HYDRAHARP2_T3 = 0x01010304
"""HydraHarp 400 with library v3 (HydraHarp V2 T3): the same bit layout as Generic T3."""


@dataclass(frozen=True)
class Family:
    """One device family and how its library is called.

    key:            the name in device strings (``picoquant:KEY``).
    model:          the vendor's model name.
    prefix:         C function prefix (``MH`` -> ``MH_OpenDevice``).
    libraries:      file names of the library, per platform.
    readfifo_count: ``*_ReadFiFo`` takes a record count (HydraHarp 400) or not (MultiHarp).
    ttreadmax:      records one ``*_ReadFiFo`` may return (the buffer must hold them).
    record_type:    PTU record type of its T3 records.
    n_markers:      marker inputs.
    snapi_name:     the library's name inside the ``snapi`` package.
    """

    key: str
    model: str
    prefix: str
    libraries: tuple[str, ...]
    readfifo_count: bool
    ttreadmax: int
    record_type: int
    n_markers: int = 4
    snapi_name: str = ""


FAMILIES: dict[str, Family] = {
    f.key: f for f in (
        Family("mh150", "MultiHarp 150", "MH", ("libmhlib.so", "mhlib64.dll", "mhlib.dll"), False,
               1048576, RECORD_TYPE_GENERIC_T3, snapi_name="libmhlib.so"),
        Family("mh160", "MultiHarp 160", "MH", ("libmhlib.so", "mhlib64.dll", "mhlib.dll"), False,
               1048576, RECORD_TYPE_GENERIC_T3, snapi_name="libmhlib.so"),
        Family("hh400", "HydraHarp 400", "HH", ("libhhlib.so", "hhlib64.dll", "hhlib.dll"), True,
               131072, RECORD_TYPE_HYDRAHARP2_T3, snapi_name="libhhlib.so"),
    )
}
"""The families whose headers we read (MH150-Demos, HH400-v3.x-Demos). HydraHarp 500, PicoHarp
330 and TimeHarp 260 have libraries of the same shape but differ in calls we have not checked."""

KNOWN_UNSUPPORTED = {"hh500": "HydraHarp 500", "ph330": "PicoHarp 330", "th260": "TimeHarp 260"}
"""PicoQuant devices named in device strings that this version cannot drive yet."""

MAX_DEVICES = 8
"""Device indices the libraries scan (MAXDEVNUM)."""
SYNC_DIV_RANGE = (1, 16)
BINNING_RANGE = (0, 24)
"""Binning codes (dtime unit = base resolution * 2**code); the device's own limit is
``binsteps`` from ``*_GetBaseResolution``."""
TRG_LEVEL_MV_RANGE = (-1200, 1200)
CHAN_OFFSET_PS_RANGE = (-99999, 99999)


def family(key: str) -> Family:
    """The family named ``key`` (``mh150``); SettingError naming the supported ones."""
    k = key.lower()
    if k in FAMILIES:
        return FAMILIES[k]
    if k in KNOWN_UNSUPPORTED:
        raise SettingError(f"picoquant:{key}: the {KNOWN_UNSUPPORTED[k]} is not supported yet "
                           f"(supported: {', '.join(FAMILIES)})")
    raise SettingError(f"picoquant:{key}: unknown PicoQuant device (supported: "
                       f"{', '.join(FAMILIES)})")


@dataclass(frozen=True)
class PicoQuantSettings:
    """How a PicoQuant device measures in T3 mode; saved with every recording.

    binning:         dtime unit = base resolution * 2**binning.
    sync_divider:    the device counts every n-th laser sync.
    sync_level_mv:   sync trigger level (MultiHarp edge trigger / HydraHarp CFD level).
    input_level_mv:  detector input trigger level.
    sync_offset_ps:  sync channel offset (cable delay) in ps.
    input_offset_ps: detector input offset in ps.
    marker_enabled:  marker inputs that produce records (bit n-1 = input n).
    marker_rising:   marker inputs triggering on the rising edge (others falling).
    ref_source:      reference clock.
    """

    binning: int = 0
    sync_divider: int = 1
    sync_level_mv: int = -50
    input_level_mv: int = -50
    sync_offset_ps: int = 0
    input_offset_ps: int = 0
    marker_enabled: int = 0b1111
    marker_rising: int = 0b1111
    ref_source: RefSource = RefSource.INTERNAL

    def __post_init__(self) -> None:
        def rng(name, v, lo, hi):
            if not isinstance(v, int) or isinstance(v, bool) or not lo <= v <= hi:
                raise SettingError(f"PicoQuant {name}={v!r} outside {lo}..{hi}")
        rng("binning", self.binning, *BINNING_RANGE)
        rng("sync_divider", self.sync_divider, *SYNC_DIV_RANGE)
        if self.sync_divider & (self.sync_divider - 1):
            raise SettingError(f"PicoQuant sync_divider={self.sync_divider} must be a power of 2")
        rng("sync_level_mv", self.sync_level_mv, *TRG_LEVEL_MV_RANGE)
        rng("input_level_mv", self.input_level_mv, *TRG_LEVEL_MV_RANGE)
        rng("sync_offset_ps", self.sync_offset_ps, *CHAN_OFFSET_PS_RANGE)
        rng("input_offset_ps", self.input_offset_ps, *CHAN_OFFSET_PS_RANGE)
        rng("marker_enabled", self.marker_enabled, 0, 15)
        rng("marker_rising", self.marker_rising, 0, 15)

    def marker_args(self) -> tuple[tuple[int, ...], tuple[int, ...]]:
        """(edges, enables) of ``*_SetMarkerEdges``/``*_SetMarkerEnable``, inputs 1..4."""
        edges = tuple(int(Edge.RISING if self.marker_rising >> i & 1 else Edge.FALLING)
                      for i in range(4))
        enables = tuple(self.marker_enabled >> i & 1 for i in range(4))
        return edges, enables

    def to_dict(self) -> dict:
        return {"binning": self.binning, "sync_divider": self.sync_divider,
                "sync_level_mv": self.sync_level_mv, "input_level_mv": self.input_level_mv,
                "sync_offset_ps": self.sync_offset_ps, "input_offset_ps": self.input_offset_ps,
                "marker_enabled": self.marker_enabled, "marker_rising": self.marker_rising,
                "ref_source": int(self.ref_source)}


@dataclass(frozen=True)
class PicoQuantIdentity:
    """Who the device is (``*_GetHardwareInfo``, ``*_GetSerialNumber``, ``*_GetLibraryVersion``)."""

    family: str
    model: str
    part_no: str
    version: str
    serial: str
    library_version: str
    index: int

    def to_dict(self) -> dict:
        return dict(self.__dict__)


__all__ = ["MeasMode", "RefSource", "Edge", "Flag", "LibError", "Family", "FAMILIES", "family",
           "PicoQuantSettings", "PicoQuantIdentity", "RECORD_TYPE_GENERIC_T3",
           "RECORD_TYPE_HYDRAHARP2_T3", "MAX_DEVICES", "DEVICE_GONE_ERRORS", "KNOWN_UNSUPPORTED"]
