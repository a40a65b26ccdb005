"""PicoQuant TCSPC libraries as data: the device families we drive, their function prefixes, the
codes their C functions take and return (from the vendor headers ``*defin.h``/``*lib.h`` and
``errorcodes.h`` of PicoQuant's public demo repositories, see ``FAMILIES``), and the record type
each device writes.
No I/O here: ``transport`` calls the library, ``device`` holds state."""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum, IntFlag

from spdepth.drivers.errors import SettingError
from spdepth.drivers.record_types import RecordType


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
    """``*_GetFlags`` bits (MultiHarp, HydraHarp 400, PicoHarp 330). FIFOFULL and SYNC_LOST are the
    same in every family; the TimeHarp 260 uses 0x0008 for dropped events and 0x0020 for a
    software error (no ACTIVE bit). Only FIFOFULL steers the driver."""

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


class Feature(IntFlag):
    """``*_GetFeatures`` bits we need (the same in mhdefin.h, hhdefin.h, th260defin.h and
    ph330defin.h): options a device may lack (they are licensed per device)."""

    TTTR = 0x0002
    """Time-tagging modes (T2/T3)."""
    MARKERS = 0x0004
    """Marker inputs (the galvo's pixel, line and frame markers)."""


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

class Trigger(IntEnum):
    """How a family's sync and detector inputs are triggered (the calls differ)."""

    EDGE = 0
    """``SetSyncEdgeTrg(level, edge)``/``SetInputEdgeTrg``: MultiHarp."""
    CFD = 1
    """``SetSyncCFD(level, zerocross)``/``SetInputCFD``: HydraHarp 400."""
    BY_MODEL = 2
    """TimeHarp 260: CFD on the PICO, edge trigger on the NANO (``*_GetHardwareInfo`` tells);
    the library exports both and the wrong one fails."""
    SELECTABLE = 3
    """PicoHarp 330: both, chosen per input with ``SetSyncTrgMode``/``SetInputTrgMode``
    (ETR = 0, CFD = 1) before the levels are set. We use the edge trigger."""


TRGMODE_ETR = 0
"""PicoHarp 330 ``*_SetSyncTrgMode``/``*_SetInputTrgMode``: edge trigger (ph330defin.h)."""
CFD_ZEROCROSS_MV = 10
"""CFD zero-cross magnitude we use (the vendor demos' value)."""


@dataclass(frozen=True)
class Family:
    """One device family and how its library is called.

    key:            the name in device strings (``picoquant:KEY``).
    model:          the vendor's model name.
    prefix:         C function prefix (``MH`` -> ``MH_OpenDevice``).
    libraries:      file names of the library: the Linux names the vendor's demos load and the
                    installer writes, then Windows'.
    readfifo_count: ``*_ReadFiFo`` takes a record count (HydraHarp 400, TimeHarp 260) or not.
    ttreadmax:      records one ``*_ReadFiFo`` may return (the buffer must hold them).
    record_type:    PTU record type of its T3 records (``record_types`` overrides it per model).
    n_markers:      marker inputs.
    snapi_name:     the library's name inside the ``snapi`` package.
    init_refsource: ``*_Initialize(devidx, mode, refsource)``; False: ``(devidx, mode)``
                    (TimeHarp 260 has no reference input).
    trigger:        how inputs are triggered (:class:`Trigger`).
    cfd_sign:       the sign the library wants for CFD levels and zero cross: +1 (HydraHarp 400:
                    0..1000 mV, 0..40 mV), -1 (TimeHarp 260 PICO: -1200..0, -40..0 mV).
    cfd_level_max_mv: the largest CFD level magnitude (DISCRMAX/CFDLVLMIN).
    max_devices:    device indices the library scans (MAXDEVNUM).
    sync_div_max:   largest ``*_SetSyncDiv`` divider (SYNCDIVMAX).
    record_types:   (model string of ``*_GetHardwareInfo``, record type) for families whose
                    models write different types (TimeHarp 260 PICO and NANO).
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
    init_refsource: bool = True
    trigger: Trigger = Trigger.EDGE
    cfd_sign: int = 1
    cfd_level_max_mv: int = 1000
    max_devices: int = 8
    sync_div_max: int = 16
    record_types: tuple[tuple[str, int], ...] = ()

    def record_type_of(self, hw_model: str) -> int:
        """The record type a device of this family with ``hw_model`` writes."""
        for name, rtype in self.record_types:
            if hw_model.strip() == name:
                return rtype
        return self.record_type

    def uses_cfd(self, hw_model: str) -> bool:
        """True when a device of this family with ``hw_model`` is triggered by CFDs."""
        if self.trigger == Trigger.BY_MODEL:
            return hw_model.strip() == TH260_PICO
        return self.trigger == Trigger.CFD


TH260_PICO = "TimeHarp 260 P"
TH260_NANO = "TimeHarp 260 N"
"""``TH260_GetHardwareInfo`` model strings (HWIDENT_PICO/HWIDENT_NANO of th260defin.h)."""

_MH_LIBS = ("libmh150.so", "mhlib.so", "libmhlib.so", "mhlib64.dll", "mhlib.dll")
FAMILIES: dict[str, Family] = {
    f.key: f for f in (
        Family("mh150", "MultiHarp 150", "MH", _MH_LIBS, False, 1048576, RecordType.GENERIC_T3,
               snapi_name="libmhlib.so"),
        Family("mh160", "MultiHarp 160", "MH", _MH_LIBS, False, 1048576, RecordType.GENERIC_T3,
               snapi_name="libmhlib.so"),
        Family("hh400", "HydraHarp 400", "HH",
               ("libhh400.so", "hhlib.so", "libhhlib.so", "hhlib64.dll", "hhlib.dll"), True,
               131072, RecordType.HYDRAHARP2_T3, snapi_name="libhhlib.so", trigger=Trigger.CFD,
               cfd_sign=1),
        Family("th260", "TimeHarp 260", "TH260",
               ("th260lib.so", "libth260.so", "th260lib64.dll", "th260lib.dll"), True, 131072,
               RecordType.TIMEHARP260P_T3, init_refsource=False, trigger=Trigger.BY_MODEL,
               cfd_sign=-1, cfd_level_max_mv=1200, max_devices=4, sync_div_max=8,
               record_types=((TH260_PICO, RecordType.TIMEHARP260P_T3),
                             (TH260_NANO, RecordType.TIMEHARP260N_T3))),
        Family("ph330", "PicoHarp 330", "PH330",
               ("libph330.so", "PH330Lib.dll"), False, 1048576, RecordType.GENERIC_T3,
               trigger=Trigger.SELECTABLE, sync_div_max=8),
    )
}
"""The families whose library headers we read: MultiHarp (MH150-Demos ``mhlib.h``/``mhdefin.h``
v3.0), HydraHarp 400 (HH400-v3.x-Demos ``hhlib.h``/``hhdefin.h`` v3.0), TimeHarp 260
(TH260-Demos and TimeHarp260-Linux ``th260lib.h``/``th260defin.h`` v3.2), PicoHarp 330
(``ph330lib.h`` v2.0 and the ``ph330defin.h`` constants as quoted by a public driver). Library
names from the demos' Python ``CDLL`` calls, makefiles and install scripts (PicoHarp 330: from
public drivers that load it)."""

KNOWN_UNSUPPORTED = {"hh500": "HydraHarp 500"}
"""PicoQuant devices named in device strings that this version cannot drive yet, and why: no
public copy of ``hh500lib.h`` was available to check its calls against (PicoQuant's HH500 demo
repository could not be read), and we do not guess a C signature."""

SYNC_DIV_RANGE = (1, 16)
"""Widest divider range; a family's own limit is ``Family.sync_div_max``."""
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
        # the caller names the option or address (``--tagger picoquant:hh500: ...``)
        raise SettingError(f"the {KNOWN_UNSUPPORTED[k]} ({k}) is not supported yet: its "
                           f"library's calls are not checked against a vendor header "
                           f"(supported: {', '.join(FAMILIES)})")
    raise SettingError(f"unknown PicoQuant device {key!r} (supported: {', '.join(FAMILIES)})")


@dataclass(frozen=True)
class PicoQuantSettings:
    """How a PicoQuant device measures in T3 mode; saved with every recording.

    binning:         dtime unit = base resolution * 2**binning.
    sync_divider:    the device counts every n-th laser sync.
    sync_level_mv:   sync trigger level, mV (edge trigger level; for a CFD its magnitude, given
                     to the library with the sign the family's header asks for).
    input_level_mv:  detector input trigger level, mV (the same way).
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


__all__ = ["MeasMode", "RefSource", "Edge", "Flag", "Feature", "LibError", "Family", "FAMILIES", "family",
           "PicoQuantSettings", "PicoQuantIdentity", "DEVICE_GONE_ERRORS",
           "KNOWN_UNSUPPORTED", "Trigger", "TRGMODE_ETR", "CFD_ZEROCROSS_MV", "TH260_PICO",
           "TH260_NANO"]
