"""Tag stream -> pixels: assign each decoded photon to the scan pixel the mirror was on.

The galvo controller pulses marker lines into the tagger (docs/protocols.md, "Scan order,
markers, timing"): ``[FRAME|]LINE_START|PIXEL`` opens a line's first pixel, ``PIXEL`` each next one,
``LINE_STOP`` closes the line. A photon belongs to the pixel opened by the last PIXEL marker before
it; photons after LINE_STOP (settling, fly-back) or before the first marker belong to no pixel.
Combined marker bits act in the order FRAME, LINE_START, PIXEL, LINE_STOP, so a stream whose
combined markers were split into one record per bit (in that order) assigns identically.

After a LOST event the markers inside the hole are gone too, so the position is unknown: photons
are left unassigned until the next FRAME marker, and the hole is reported so acquisition can
re-acquire or flag the pixels involved — never silently short.

Two consumers share the marker state machine below (``_on_*`` helpers), so there is one assignment
path: :class:`PixelAssigner` labels every event with its pixel (file readers, tests), and
:func:`accumulate` feeds a live scan's store dwell by dwell. A *dwell* is the stretch of stream
from a PIXEL marker to the next PIXEL or LINE_STOP marker; it is *complete* when that closing
marker arrives with no LOST event in between. :func:`accumulate` keeps the photons of the open
dwell aside and adds them to their pixel only when the dwell completes, so a dwell cut by a loss,
a pause or the end of a pass contributes nothing (its pixel is scanned again).

A pass may scan a sub-rectangle of the image (:class:`PassGeometry`): its local rows and columns
map to the image's flat pixel index.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numba import njit

from spdepth.drivers.events import EVENT_DTYPE, EventKind, Marker
from spdepth.drivers.jit import call_strided
from spdepth.recon.errors import InputError

UNASSIGNED = -1

# The kernels compare against these module-level ints (numba freezes them as constants).
_PHOTON = int(EventKind.PHOTON)
_MARKER = int(EventKind.MARKER)
_LOST = int(EventKind.LOST)
_M_PIXEL = int(Marker.PIXEL)
_M_LINE_START = int(Marker.LINE_START)
_M_LINE_STOP = int(Marker.LINE_STOP)
_M_FRAME = int(Marker.FRAME)

# state vector slots (int64)
_FRAME = 0          # frames started, minus one
_ROW = 1            # line of the pass (-1 before the first LINE_START)
_VISIT = 2          # pixel of the line in visiting order (-1 before the first PIXEL)
_OPEN = 3           # a pixel is open (1) or not (0: after LINE_STOP)
_KNOWN = 4          # position known (0 after a LOST event until the next FRAME)
_LINES_CLOSED = 5   # LINE_STOP markers seen
_PIXELS_OPENED = 6  # PIXEL markers seen
# accumulate() only: the open dwell
_DWELL_PIXEL = 7    # flat pixel of the open dwell, -1 when none
_DWELL_SYNC = 8     # sync of its PIXEL marker
_DWELL_TOTAL = 9    # detections in it (all, in or out of the window)
_DWELL_KEPT = 10    # of those, buffered in ``pend`` for its pixel
_DWELL_LAST = 11    # sync of the last of them
_DWELL_CUT = 12     # 1 once an in-window detection found its pixel full (not kept)
STATE_SLOTS = 13

# geometry vector (int64): pass origin and size in the image, image width, serpentine flag
_G_ROW0, _G_COL0, _G_NY, _G_NX, _G_WIDTH, _G_SERP = range(6)


@dataclass(frozen=True)
class PassGeometry:
    """Which pixels one galvo pass visits: lines ``row0 .. row0+ny-1`` of the image, columns
    ``col0 .. col0+nx-1``, in ``pattern`` order ("raster", or "serp": odd lines of the pass right
    to left). ``width`` is the image width (flat index = row * width + col)."""

    row0: int
    col0: int
    ny: int
    nx: int
    width: int
    pattern: str = "raster"

    def __post_init__(self) -> None:
        if self.pattern not in ("raster", "serp"):
            raise InputError(f"scan pattern must be 'raster' or 'serp', got {self.pattern!r}")
        if self.ny < 1 or self.nx < 1 or self.row0 < 0 or self.col0 < 0 \
                or self.col0 + self.nx > self.width:
            raise InputError(f"pass geometry {self} does not fit an image {self.width} wide")

    @classmethod
    def full(cls, shape: tuple[int, int], pattern: str = "raster") -> "PassGeometry":
        """The whole ``(H, W)`` image."""
        return cls(0, 0, int(shape[0]), int(shape[1]), int(shape[1]), pattern)

    def vector(self) -> np.ndarray:
        return np.array([self.row0, self.col0, self.ny, self.nx, self.width,
                         1 if self.pattern == "serp" else 0], dtype=np.int64)

    def flat_pixels(self) -> np.ndarray:
        """Flat indices of the pixels of this pass (row-major, not visiting order)."""
        rows = np.arange(self.row0, self.row0 + self.ny)[:, None]
        cols = np.arange(self.col0, self.col0 + self.nx)[None, :]
        return (rows * self.width + cols).ravel()

    def to_dict(self) -> dict:
        return {"row0": self.row0, "col0": self.col0, "ny": self.ny, "nx": self.nx,
                "width": self.width, "pattern": self.pattern}


def new_state() -> np.ndarray:
    """Assignment state at the start of a stream or pass. Before the first FRAME marker the
    position counts as known, so a stream without FRAME markers (one-frame scans of some
    controllers) still works: LINE_START counts lines from -1."""
    s = np.zeros(STATE_SLOTS, dtype=np.int64)
    s[_FRAME] = s[_ROW] = s[_VISIT] = s[_DWELL_PIXEL] = -1
    s[_KNOWN] = 1
    return s


# ---- the marker state machine (shared) ------------------------------------------------------------

@njit(cache=True, nogil=True, inline="always")
def _open_pixel(state, geom):
    """Flat index of the pixel open in ``state``, or -1 (none open, position unknown, off grid)."""
    if state[_OPEN] == 0 or state[_KNOWN] == 0:
        return -1
    row = state[_ROW]
    visit = state[_VISIT]
    if not (0 <= row < geom[_G_NY] and 0 <= visit < geom[_G_NX]):
        return -1
    col = geom[_G_NX] - 1 - visit if geom[_G_SERP] != 0 and row % 2 == 1 else visit
    return (geom[_G_ROW0] + row) * geom[_G_WIDTH] + geom[_G_COL0] + col


@njit(cache=True, nogil=True, inline="always")
def _on_frame(state):
    # a fresh frame re-establishes the position after a loss
    state[_FRAME] += 1
    state[_ROW] = -1
    state[_OPEN] = 0
    state[_KNOWN] = 1


@njit(cache=True, nogil=True, inline="always")
def _on_line_start(state):
    state[_ROW] += 1
    state[_VISIT] = -1


@njit(cache=True, nogil=True, inline="always")
def _on_pixel(state):
    state[_VISIT] += 1
    state[_OPEN] = 1
    state[_PIXELS_OPENED] += 1


@njit(cache=True, nogil=True, inline="always")
def _on_line_stop(state):
    state[_OPEN] = 0
    state[_LINES_CLOSED] += 1


@njit(cache=True, nogil=True, inline="always")
def _on_lost(state):
    state[_KNOWN] = 0


# ---- labelling every event ------------------------------------------------------------------------

@njit(cache=True, nogil=True)
def _assign_kernel(kind, marker, geom, state, pixel_out, lost_pixel_out):
    """Fill ``pixel_out[i]`` with the flat pixel index of photon event i (-1 for anything else or
    an unknown position) and ``lost_pixel_out[j]`` with the pixel open at the j-th LOST event
    (-1 if none). ``state`` is updated in place. Returns the number of LOST events seen."""
    n_lost = 0
    # the open pixel changes only at markers and losses: photons (most events) reuse it
    current = _open_pixel(state, geom)
    for i in range(kind.size):
        k = kind[i]
        if k == _PHOTON:
            pixel_out[i] = current
            continue
        pixel_out[i] = -1
        if k == _MARKER:
            m = marker[i]
            if m & _M_FRAME:
                _on_frame(state)
            if m & _M_LINE_START:
                _on_line_start(state)
            if m & _M_PIXEL:
                _on_pixel(state)
            if m & _M_LINE_STOP:
                _on_line_stop(state)
            current = _open_pixel(state, geom)
        elif k == _LOST:
            lost_pixel_out[n_lost] = current
            n_lost += 1
            _on_lost(state)
            current = _open_pixel(state, geom)
    return n_lost


@dataclass(frozen=True)
class LostSpan:
    """A hole in the stream: records lost from ``sync`` on; ``pixel`` is the flat index of the
    pixel open when the loss began (-1 if none); every pixel after it is unknown until the next
    frame starts, so acquisition must re-acquire from ``pixel`` on."""

    sync: int
    records_lost: int
    pixel: int


def _check_events(events: np.ndarray) -> None:
    if events.dtype != EVENT_DTYPE:
        raise InputError(f"events must have drivers.events.EVENT_DTYPE, got {events.dtype}")


@dataclass
class PixelAssigner:
    """Stateful marker-driven pixel assignment for an ``shape = (H, W)`` scan.

    pattern: "raster" (every line left to right) or "serp" (odd lines right to left)."""

    shape: tuple[int, int]
    pattern: str = "raster"
    lost: list[LostSpan] = field(default_factory=list)

    def __post_init__(self) -> None:
        h, w = self.shape
        if h < 1 or w < 1:
            raise InputError(f"scan shape must be at least 1 x 1, got {self.shape}")
        self._geom = PassGeometry.full(self.shape, self.pattern).vector()
        self._state = new_state()

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

    def assign(self, events: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        """Flat pixel index (int64) for each event; -1 for markers, lost spans, photons outside a
        pixel and photons while the position is unknown. LOST events are appended to ``lost``.
        ``out``: an int64 buffer of at least ``events.size`` to fill (a reader reuses one for every
        chunk instead of faulting in fresh pages); the result is a view of it."""
        _check_events(events)
        if out is None:
            out = np.empty(events.size, dtype=np.int64)
        if out.dtype != np.int64 or out.size < events.size:
            raise InputError(f"assign: out must be int64 with at least {events.size} entries")
        pixel = out[:events.size]
        lost_pixel = self._lost_buffer(events.size)
        n_lost = call_strided(_assign_kernel, (0, 1), events["kind"], events["marker"], self._geom,
                              self._state, pixel, lost_pixel)
        if n_lost:
            self.lost.extend(_lost_spans(events, lost_pixel))
        return pixel


    def kernel_arguments(self, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(geometry, state, scratch for ``n`` events' lost pixels): what :func:`_assign_kernel`
        takes besides the events, for a reader that calls it from a kernel of its own
        (``acq.readers.picoquant``); the state is this assigner's, updated in place."""
        return self._geom, self._state, self._lost_buffer(n)

    def _lost_buffer(self, n: int) -> np.ndarray:
        """Scratch for the pixel open at each LOST event, kept between chunks."""
        buf = getattr(self, "_lost_scratch", None)
        if buf is None or buf.size < n:
            buf = self._lost_scratch = np.empty(n, dtype=np.int64)
        return buf[:n]


def _lost_spans(events: np.ndarray, lost_pixel: np.ndarray) -> list[LostSpan]:
    """The chunk's LOST events as spans; ``lost_pixel[j]`` is the pixel open at the j-th."""
    at = np.flatnonzero(events["kind"] == _LOST)
    return [LostSpan(int(events["sync"][i]), int(events["dtime"][i]), int(lost_pixel[j]))
            for j, i in enumerate(at)]


def photons_by_pixel(events: np.ndarray, pixel: np.ndarray):
    """The assigned photons of a chunk: (flat pixel index, dtime) arrays, in stream order."""
    ok = pixel >= 0
    return pixel[ok], events["dtime"][ok]


# ---- feeding a store dwell by dwell -----------------------------------------------------------------

@njit(cache=True, nogil=True, inline="always")
def _close_dwell(state, sync, pend, times, count, detected, dwells, periods, frozen,
                 closed_pixel, closed_total, closed_syncs, n_closed):
    """Complete the open dwell: its buffered photons join its pixel. Returns the new n_closed."""
    p = state[_DWELL_PIXEL]
    if p < 0:
        return n_closed
    if frozen[p] == 0:
        c = count[p]
        if c < times.shape[1]:
            # the laser periods the kept detections were collected over: the whole dwell, or up to
            # the detection that filled the pixel when later ones could not be kept
            if state[_DWELL_CUT]:
                periods[p] += state[_DWELL_LAST] - state[_DWELL_SYNC] + 1
            else:
                periods[p] += sync - state[_DWELL_SYNC]
        for j in range(state[_DWELL_KEPT]):
            times[p, c + j] = pend[j]
        count[p] = c + state[_DWELL_KEPT]
        detected[p] += state[_DWELL_TOTAL]
        dwells[p] += 1
    closed_pixel[n_closed] = p
    closed_total[n_closed] = state[_DWELL_TOTAL]
    closed_syncs[n_closed] = sync - state[_DWELL_SYNC]
    state[_DWELL_PIXEL] = -1
    return n_closed + 1


@njit(cache=True, nogil=True, inline="always")
def _drop_dwell(state):
    """Discard the open dwell (cut by a loss or a pass boundary). Returns 1 if one was open."""
    had = 1 if state[_DWELL_PIXEL] >= 0 else 0
    state[_DWELL_PIXEL] = -1
    return had


@njit(cache=True, nogil=True, inline="always")
def _open_dwell(state, geom, sync):
    p = _open_pixel(state, geom)
    state[_DWELL_PIXEL] = p
    state[_DWELL_SYNC] = sync
    state[_DWELL_TOTAL] = 0
    state[_DWELL_KEPT] = 0
    state[_DWELL_LAST] = sync
    state[_DWELL_CUT] = 0


@njit(cache=True, nogil=True, inline="always")
def _dwell_locals(state, count, frozen, n_keep):
    """(pixel, detections, kept, room left) of the open dwell; room is 0 without a dwell or for a
    frozen pixel."""
    p = state[_DWELL_PIXEL]
    kept = state[_DWELL_KEPT]
    room = 0
    if p >= 0 and frozen[p] == 0:
        room = n_keep - count[p] - kept
    return p, state[_DWELL_TOTAL], kept, room


@njit(cache=True, nogil=True)
def _accumulate_kernel(sync, dtime, kind, marker, geom, state, lo, hi, pend, times, count,
                       detected, dwells, periods, frozen, closed_pixel, closed_total, closed_syncs,
                       lost_pixel_out, counters):
    """Feed one chunk of events into the store arrays (see :func:`accumulate`).

    counters (int64[5]) accumulates: photons outside any dwell, dwells dropped, LOST events,
    photons kept, photons seen. ``lost_pixel_out[j]`` gets the pixel open at the j-th LOST event
    of the chunk (-1: none). Returns the number of dwells closed in this chunk."""
    n_keep = times.shape[1]
    n_closed = 0
    n_lost0 = counters[2]
    # The photon path runs on locals (the open dwell's pixel, counts and room left in its
    # pixel); they are written back to ``state`` around the rarer markers and losses, where the
    # shared helpers take over. Arrays the compiler must assume aliased would cost a load and a
    # store per photon.
    dp, dtot, dkept, room = _dwell_locals(state, count, frozen, n_keep)
    dlast, dcut = state[_DWELL_LAST], state[_DWELL_CUT]
    n_seen = 0
    n_outside = 0
    n_kept = 0
    for i in range(kind.size):
        k = kind[i]
        if k == _PHOTON:
            n_seen += 1
            if dp < 0:
                n_outside += 1
                continue
            dtot += 1
            t = dtime[i]
            if lo <= t < hi:
                if room > 0:
                    pend[dkept] = t
                    dkept += 1
                    room -= 1
                    n_kept += 1
                    dlast = np.int64(sync[i])
                else:
                    dcut = 1
            continue
        state[_DWELL_TOTAL] = dtot
        state[_DWELL_KEPT] = dkept
        state[_DWELL_LAST] = dlast
        state[_DWELL_CUT] = dcut
        if k == _MARKER:
            m = marker[i]
            s = np.int64(sync[i])
            if m & _M_FRAME:
                counters[1] += _drop_dwell(state)
                _on_frame(state)
            if m & _M_LINE_START:
                _on_line_start(state)
            if m & _M_PIXEL:
                n_closed = _close_dwell(state, s, pend, times, count, detected, dwells, periods,
                                        frozen, closed_pixel, closed_total, closed_syncs, n_closed)
                _on_pixel(state)
                _open_dwell(state, geom, s)
            if m & _M_LINE_STOP:
                n_closed = _close_dwell(state, s, pend, times, count, detected, dwells, periods,
                                        frozen, closed_pixel, closed_total, closed_syncs, n_closed)
                _on_line_stop(state)
        elif k == _LOST:
            lost_pixel_out[counters[2] - n_lost0] = _open_pixel(state, geom)
            counters[2] += 1
            counters[1] += _drop_dwell(state)
            _on_lost(state)
        dp, dtot, dkept, room = _dwell_locals(state, count, frozen, n_keep)
        dlast, dcut = state[_DWELL_LAST], state[_DWELL_CUT]
    state[_DWELL_TOTAL] = dtot
    state[_DWELL_KEPT] = dkept
    state[_DWELL_LAST] = dlast
    state[_DWELL_CUT] = dcut
    counters[0] += n_outside
    counters[3] += n_kept
    counters[4] += n_seen
    return n_closed


@dataclass(frozen=True)
class Accumulated:
    """What one chunk did to the store.

    closed_pixel, closed_total, closed_syncs: one row per completed dwell, in stream order: flat
        pixel, detections in the dwell (all, in or out of the window) and its length in syncs.
    lost: the chunk's LOST events as :class:`LostSpan` (pixel open at the loss).
    """

    closed_pixel: np.ndarray
    closed_total: np.ndarray
    closed_syncs: np.ndarray
    lost: list


def accumulate(events: np.ndarray, geom: np.ndarray, state: np.ndarray, window: tuple[int, int],
               pend: np.ndarray, times: np.ndarray, count: np.ndarray, detected: np.ndarray,
               dwells: np.ndarray, periods: np.ndarray, frozen: np.ndarray,
               counters: np.ndarray) -> Accumulated:
    """Feed ``events`` dwell by dwell into per-pixel arrays (``acq.store.PixelStore`` owns them).

    A completed dwell adds its in-window detections (``window = (lo, hi)``, raw units,
    ``lo <= dtime < hi``) to its pixel's row of ``times`` (n_pixels x n_keep) until the pixel holds
    n_keep; later ones are not kept. Pixels with ``frozen`` set keep what they have (they were
    handed to the reconstruction). ``pend`` (n_keep) buffers the open dwell between chunks.
    ``periods`` gets, per pixel, the laser periods its kept detections were collected over: each
    complete dwell that found the pixel short adds its length in syncs, or, when the pixel filled
    up during it and later in-window detections were not kept, the span up to the sync of the
    detection that filled it (so kept detections / periods is a rate whatever the target did)."""
    _check_events(events)
    n = events.size
    closed_pixel = np.empty(n + 1, np.int64)
    closed_total = np.empty(n + 1, np.int64)
    closed_syncs = np.empty(n + 1, np.int64)
    lost_pixel = np.empty(n, np.int64)
    n_lost0 = int(counters[2])
    n_closed = call_strided(_accumulate_kernel, (0, 1, 2, 3), events["sync"], events["dtime"],
                            events["kind"], events["marker"], geom, state, np.int64(window[0]),
                            np.int64(window[1]), pend, times, count, detected, dwells, periods,
                            frozen, closed_pixel, closed_total, closed_syncs, lost_pixel, counters)
    lost = _lost_spans(events, lost_pixel) if counters[2] > n_lost0 else []
    return Accumulated(closed_pixel[:n_closed], closed_total[:n_closed], closed_syncs[:n_closed], lost)


__all__ = ["PixelAssigner", "PassGeometry", "LostSpan", "Accumulated", "accumulate",
           "photons_by_pixel", "new_state", "UNASSIGNED"]
