"""The decoded event stream: what the time tagger delivers, what the simulator produces, what a
recording replays. One named dtype shared by all of them."""

from __future__ import annotations

from enum import IntEnum

import numpy as np

# the record-type codes live where importing them costs no numpy (spdepth --help lists the taggers)
from spdepth.drivers.record_types import GENERIC_T3_RECORD_TYPES, RecordType  # noqa: F401


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
