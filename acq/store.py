"""The live scan's per-pixel photon store: what the maps need and nothing else.

Each pixel keeps its first ``n_keep`` in-window detection times (uint32 tagger units, in detection
order) in one dense ``(H*W, n_keep)`` array, plus counters. A 1024 x 1024 scan at 30 detections per
pixel is 126 MB of times and 17 MB of counters, allocated once at the start: nothing grows during
a scan.

**The rule for rescans** (one rule for every way a pixel can be visited again): a pixel's photons
are those of its *complete* dwells, in time order, up to ``n_keep`` in-window detections; later
detections are not kept. A dwell cut short (by a lost span, a pause, an abort or a fault) adds
nothing (``acq.assign``), so a rescan tops a pixel up and no detection is ever counted twice
(each detection belongs to exactly one dwell). Once a pixel is handed to the reconstruction it
is frozen: a later visit leaves it as it was.
"""

from __future__ import annotations

import threading

import numpy as np

from spdepth.acq.assign import Accumulated, PassGeometry, accumulate, new_state
from spdepth.recon.errors import InputError
from spdepth.recon.photons import PhotonStore


class PixelStore:
    """Photons of an ``shape = (H, W)`` scan, fed from the event stream dwell by dwell.

    n_keep:      in-window detections kept per pixel (the target).
    window:      (lo, hi) raw dtime units; a detection counts when ``lo <= dtime < hi``.
    time_unit_s: the tagger's dtime unit.

    One thread feeds (``feed``); others may read ready pixels (``photons``) and copy the counters
    (their rows of ``times`` never change again once frozen).
    """

    def __init__(self, shape: tuple[int, int], n_keep: int, window: tuple[int, int],
                 time_unit_s: float):
        h, w = (int(v) for v in shape)
        if h < 1 or w < 1:
            raise InputError(f"scan shape must be at least 1 x 1, got {shape}")
        if n_keep < 1:
            raise InputError(f"target detections per pixel must be at least 1, got {n_keep}")
        lo, hi = (int(v) for v in window)
        if not 0 <= lo < hi:
            raise InputError(f"detection window [{lo}, {hi}) in tagger units holds nothing")
        self.shape = (h, w)
        self.n_keep = int(n_keep)
        self.window = (lo, hi)
        self.time_unit_s = float(time_unit_s)
        n = h * w
        self.times = np.zeros((n, self.n_keep), np.uint32)
        self.count = np.zeros(n, np.int32)        # in-window detections kept
        self.detected = np.zeros(n, np.int64)     # all detections of complete dwells
        self.dwells = np.zeros(n, np.int32)       # complete dwells
        self.frozen = np.zeros(n, np.uint8)       # handed to the reconstruction
        self._pend = np.zeros(self.n_keep, np.uint32)
        # photons outside any dwell, dwells dropped, LOST events, photons kept, photons seen
        self._counters = np.zeros(5, np.int64)
        self._state = new_state()
        self._geom = PassGeometry.full(self.shape).vector()
        self._lock = threading.Lock()

    @property
    def n_pixels(self) -> int:
        return self.shape[0] * self.shape[1]

    @property
    def unassigned(self) -> int:
        """Photons that arrived outside any dwell (fly-back, parked mirror, unknown position)."""
        return int(self._counters[0])

    @property
    def photons_seen(self) -> int:
        """Photon events fed so far (assigned or not)."""
        return int(self._counters[4])

    @property
    def dropped_dwells(self) -> int:
        """Dwells cut short and discarded."""
        return int(self._counters[1])

    @property
    def kept(self) -> int:
        """In-window detections kept in the store."""
        return int(self._counters[3])

    @property
    def lines_closed(self) -> int:
        """LINE_STOP markers seen in the current pass."""
        return int(self._state[5])

    @property
    def pixels_opened(self) -> int:
        """PIXEL markers seen in the current pass."""
        return int(self._state[6])

    @property
    def dwell_open(self) -> bool:
        return bool(self._state[7] >= 0)

    def begin_pass(self, geometry: PassGeometry) -> None:
        """The next events belong to a galvo pass over ``geometry``: fresh marker state (any dwell
        still open from before is dropped)."""
        if geometry.width != self.shape[1] or geometry.row0 + geometry.ny > self.shape[0]:
            raise InputError(f"pass {geometry} does not fit a {self.shape} scan")
        self.end_pass()
        self._geom = geometry.vector()
        self._state = new_state()

    def end_pass(self) -> None:
        """The pass is over: a dwell still open was cut short and is dropped."""
        if self._state[7] >= 0:
            self._state[7] = -1
            self._counters[1] += 1

    def feed(self, events: np.ndarray) -> Accumulated:
        """Assign one chunk of events (``drivers.events.EVENT_DTYPE``) and keep its photons."""
        with self._lock:
            return accumulate(events, self._geom, self._state, self.window, self._pend, self.times,
                              self.count, self.detected, self.dwells, self.frozen, self._counters)

    def freeze(self, pixels: np.ndarray) -> None:
        with self._lock:
            self.frozen[pixels] = 1

    def pixel_count(self, p: int) -> int:
        """In-window detections flat pixel ``p`` holds, counting those of its dwell still open
        (buffered until the dwell completes): what a galvo that the host gates watches. Read
        without the lock from another thread: a count one chunk old only delays the step."""
        st = self._state
        kept = int(self.count[p])
        if int(st[7]) == p:               # _DWELL_PIXEL: this pixel's dwell is open
            kept += int(st[10])           # _DWELL_KEPT: its detections buffered so far
        return kept

    def complete(self) -> np.ndarray:
        """Mask of pixels holding ``n_keep`` detections."""
        return self.count >= self.n_keep

    def photons(self, pixels: np.ndarray | None = None) -> PhotonStore:
        """A :class:`PhotonStore` of the listed flat pixels as a 1 x n image (None: the whole
        H x W image), times in tagger units."""
        if pixels is None:
            idx = np.arange(self.n_pixels)
            shape = self.shape
        else:
            idx = np.asarray(pixels, dtype=np.int64)
            shape = (1, int(idx.size))
        counts = self.count[idx].astype(np.int64)
        offsets = np.zeros(idx.size + 1, np.int64)
        np.cumsum(counts, out=offsets[1:])
        # rows of `times` are filled from the left, so a mask picks each pixel's photons in order
        rows = self.times[idx]
        mask = np.arange(self.n_keep)[None, :] < counts[:, None]
        return PhotonStore(rows[mask].astype(np.float64), offsets, shape, self.time_unit_s)
