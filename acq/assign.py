"""Tag stream -> pixels: assign each decoded photon to the scan pixel the mirror was on.

The galvo controller pulses marker lines into the tagger (docs/protocols.md, "Scan order,
markers, timing"): ``[FRAME|]LINE_START|PIXEL`` opens a line's first pixel, ``PIXEL`` each next one,
``LINE_STOP`` closes the line. A photon belongs to the pixel opened by the last PIXEL marker before
it; photons after LINE_STOP (settling, fly-back) or before the first marker belong to no pixel.
The assigner keeps that state across chunks, so a stream can be fed in any chunking.

After a LOST event the markers inside the hole are gone too, so the position is unknown: photons
are left unassigned (-1) until the next FRAME marker, and the hole is reported so acquisition can
re-acquire or flag the pixels involved — never silently short.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numba import njit

from drivers.events import EVENT_DTYPE, EventKind, Marker
from recon.errors import InputError

UNASSIGNED = -1

# state vector layout (int64): frame, row, visit (column in visiting order), pixel open (0/1),
# position known (0/1), lines closed (LINE_STOP markers seen)
_FRAME, _ROW, _VISIT, _OPEN, _KNOWN, _LINES_CLOSED = range(6)


@njit(cache=True, nogil=True)
def _open_pixel(state, height, width, serpentine):
    """Flat index of the pixel open in ``state``, or -1 (none open, position unknown, off grid)."""
    if state[3] == 0 or state[4] == 0:
        return -1
    row = state[1]
    visit = state[2]
    if not (0 <= row < height and 0 <= visit < width):
        return -1
    col = width - 1 - visit if serpentine and row % 2 == 1 else visit
    return row * width + col


@njit(cache=True, nogil=True)
def _assign_kernel(sync, kind, marker, height, width, serpentine, state, pixel_out, lost_pixel_out):
    """Fill ``pixel_out[i]`` with the flat pixel index of photon event i (-1 for anything else or
    an unknown position) and ``lost_pixel_out[i]`` for LOST events with the pixel open at the loss
    (-1 if none). ``state`` is updated in place. Returns the number of LOST events seen."""
    n_lost = 0
    for i in range(sync.size):
        pixel_out[i] = -1
        lost_pixel_out[i] = -1
        k = kind[i]
        if k == 1:  # MARKER
            m = marker[i]
            if m & 8:  # FRAME: a fresh frame re-establishes the position after a loss
                state[0] += 1
                state[1] = -1
                state[3] = 0
                state[4] = 1
            if m & 2:  # LINE_START
                state[1] += 1
                state[2] = -1
            if m & 1:  # PIXEL
                state[2] += 1
                state[3] = 1
            if m & 4:  # LINE_STOP
                state[3] = 0
                state[5] += 1
        elif k == 0:  # PHOTON
            pixel_out[i] = _open_pixel(state, height, width, serpentine)
        elif k == 2:  # LOST
            n_lost += 1
            lost_pixel_out[i] = _open_pixel(state, height, width, serpentine)
            state[4] = 0
    return n_lost


@dataclass(frozen=True)
class LostSpan:
    """A hole in the stream: records lost from ``sync`` on; ``pixel`` is the flat index of the
    pixel open when the loss began (-1 if none); every pixel after it is unknown until the next
    frame starts, so acquisition must re-acquire from ``pixel`` on."""

    sync: int
    records_lost: int
    pixel: int


@dataclass
class PixelAssigner:
    """Stateful marker-driven pixel assignment for an ``shape = (H, W)`` scan.

    pattern: "raster" (every line left to right) or "serp" (odd lines right to left)."""

    shape: tuple[int, int]
    pattern: str = "raster"
    lost: list[LostSpan] = field(default_factory=list)

    def __post_init__(self) -> None:
        if self.pattern not in ("raster", "serp"):
            raise InputError(f"scan pattern must be 'raster' or 'serp', got {self.pattern!r}")
        h, w = self.shape
        if h < 1 or w < 1:
            raise InputError(f"scan shape must be at least 1 x 1, got {self.shape}")
        # Before the first FRAME marker the position is known only if the stream starts at a
        # scan start: a stream without FRAME markers (one-frame scans of some controllers)
        # still works because LINE_START counts rows from -1.
        self._state = np.array([-1, -1, -1, 0, 1, 0], dtype=np.int64)

    @property
    def frame(self) -> int:
        """Frames started so far, minus one (0 during the first frame)."""
        return int(self._state[_FRAME])

    @property
    def lines_closed(self) -> int:
        """LINE_STOP markers seen so far: a one-frame scan of H lines is complete at H."""
        return int(self._state[_LINES_CLOSED])

    @property
    def position_known(self) -> bool:
        return bool(self._state[_KNOWN])

    def assign(self, events: np.ndarray) -> np.ndarray:
        """Flat pixel index (int64) for each event; -1 for markers, lost spans, photons outside a
        pixel and photons while the position is unknown. LOST events are appended to ``lost``."""
        if events.dtype != EVENT_DTYPE:
            raise InputError(f"events must have drivers.events.EVENT_DTYPE, got {events.dtype}")
        pixel = np.empty(events.size, dtype=np.int64)
        lost_pixel = np.empty(events.size, dtype=np.int64)
        n_lost = _assign_kernel(events["sync"], events["kind"], events["marker"],
                                self.shape[0], self.shape[1], self.pattern == "serp",
                                self._state, pixel, lost_pixel)
        if n_lost:
            for i in np.flatnonzero(events["kind"] == EventKind.LOST):
                self.lost.append(LostSpan(int(events["sync"][i]), int(events["dtime"][i]),
                                          int(lost_pixel[i])))
        return pixel


def photons_by_pixel(events: np.ndarray, pixel: np.ndarray):
    """The assigned photons of a chunk: (flat pixel index, dtime) arrays, in stream order."""
    ok = pixel >= 0
    return pixel[ok], events["dtime"][ok]


__all__ = ["PixelAssigner", "LostSpan", "photons_by_pixel", "UNASSIGNED", "Marker"]
