"""The decoded event stream: what the time tagger delivers, what the simulator produces, what a
recording replays. One named dtype shared by all of them."""

from __future__ import annotations

from enum import IntEnum

import numpy as np


class EventKind(IntEnum):
    """What one event row means."""

    PHOTON = 0
    """A detection: ``dtime`` after laser sync ``sync`` on detector ``channel``."""
    MARKER = 1
    """External marker inputs fired at sync ``sync``; ``marker`` holds the bit mask (bit n-1 = input n)."""
    LOST = 2
    """Records were lost (FIFO overrun, USB error) starting at sync ``sync``; ``dtime`` holds the
    number of records lost (saturating at 2**32-1, 0 when unknown); the gap ends at the next event."""


class Marker(IntEnum):
    """Marker inputs the galvo controller drives into the tagger (bit masks in ``marker``)."""

    PIXEL = 1
    """Pixel clock: the mirror stepped to the next pixel of the line."""
    LINE_START = 2
    """A scan line starts (first pixel of the line)."""
    LINE_STOP = 4
    """A scan line ends (after its last pixel)."""
    FRAME = 8
    """A frame starts."""


class RecordType(IntEnum):
    """PTU ``TTResultFormat_TTTRRecType`` codes of the T3 records we read and write (ptufile's
    ``PtuRecordType``); the one list of them (drivers, recordings and readers all use it)."""

    PICOHARP_T3 = 0x00010303
    """PicoHarp 300: ``channel:4 | dtime:12 | nsync:16``, channel 15 special."""
    HYDRAHARP_T3 = 0x00010304
    """HydraHarp v1: the Generic T3 bit layout, but each overflow record counts one."""
    HYDRAHARP2_T3 = 0x01010304
    """HydraHarp 400 with library v3 (HydraHarp V2 T3), what our tagger writes: Generic T3 layout."""
    TIMEHARP260N_T3 = 0x00010305
    """TimeHarp 260 NANO T3: Generic T3 layout."""
    TIMEHARP260P_T3 = 0x00010306
    """TimeHarp 260 PICO T3: Generic T3 layout."""
    GENERIC_T3 = 0x00010307
    """MultiHarp, PicoHarp 330, HydraHarp 500: Generic T3 records."""


GENERIC_T3_RECORD_TYPES = frozenset({RecordType.HYDRAHARP2_T3, RecordType.TIMEHARP260N_T3,
                                     RecordType.TIMEHARP260P_T3, RecordType.GENERIC_T3})
"""Record types whose 32-bit records are ``special:1 | channel:6 | dtime:15 | nsync:10`` with
overflow counts in nsync, which ``drivers.tagger.t3`` decodes (PicoQuant's file demos decode
the TimeHarp 260 and HydraHarp V2 types with the Generic T3 routine; ptufile likewise)."""


EVENT_DTYPE = np.dtype(
    [
        ("sync", "<u8"),     # laser sync index since the start of the stream (overflows resolved)
        ("dtime", "<u4"),    # PHOTON: arrival after the sync, in tagger resolution units; LOST: records lost
        ("channel", "u1"),   # PHOTON: detector channel, 0-based
        ("kind", "u1"),      # EventKind
        ("marker", "u1"),    # MARKER: marker bit mask (Marker flags)
        ("_pad", "u1"),      # keeps rows 16 bytes wide
    ]
)
"""One decoded event, 16 bytes. Photons, markers and lost-data spans share the stream so that
their order (which is what assigns photons to pixels) survives every stage."""


def empty_events(n: int = 0) -> np.ndarray:
    """A zeroed event array of length ``n``."""
    return np.zeros(n, dtype=EVENT_DTYPE)
