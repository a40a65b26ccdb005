"""Per-pixel histogram counts: what a histogram cube holds, stored so that memory and time grow with
the occupied bins, not with the detections.

A SPAD-array sensor or a histogramming TCSPC card delivers, per pixel, counts in time bins; a
photon list is the same thing at the tagger's resolution with every count 1 (or more where two
detections share a time). :class:`CountStore` keeps each pixel's distinct times and their counts,
CSR-like, as :class:`recon.photons.PhotonStore` keeps its detections.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit

from spdepth.recon.errors import InputError
from spdepth.recon.photons import PhotonStore


@dataclass(frozen=True, eq=False)
class CountStore:
    """Counts of an H x W image, pixel by pixel: the distinct times each pixel holds and how many
    detections at each.

    The counts of pixel ``p = row * W + col`` are ``counts[offsets[p]:offsets[p + 1]]`` at
    ``times[offsets[p]:offsets[p + 1]]``, times ascending and distinct within the pixel.

    times:       float64 (n_occupied,): raw time units after the laser sync (``time_unit_s``
                 each). A cube's bin k (``[k, k + 1)`` units) has time k, as the k-th raw unit of
                 a photon list does, so one binning serves both.
    counts:      float64 (n_occupied,), > 0: detections at that time (whole numbers as read; a
                 pile-up-corrected store holds the expected counts without dead time).
    offsets:     int64 (H * W + 1,), rising from 0 to n_occupied.
    shape:       (H, W) pixels, row-major.
    time_unit_s: size of one raw unit in seconds (a cube's bin width).
    periods:     float64 (H * W,) laser periods each pixel integrated over, or None when unknown
                 (needed by the pile-up correction, :mod:`recon.pileup`).
    """

    times: np.ndarray
    counts: np.ndarray
    offsets: np.ndarray
    shape: tuple[int, int]
    time_unit_s: float
    periods: np.ndarray | None = None

    def __post_init__(self) -> None:
        h, w = self.shape
        if h < 1 or w < 1:
            raise InputError(f"count store shape must be at least 1 x 1, got {self.shape}")
        if not (self.time_unit_s > 0 and np.isfinite(self.time_unit_s)):
            raise InputError(f"time_unit_s must be positive, got {self.time_unit_s}")
        times = np.ascontiguousarray(self.times, dtype=np.float64)
        counts = np.ascontiguousarray(self.counts, dtype=np.float64)
        offsets = np.ascontiguousarray(self.offsets, dtype=np.int64)
        if offsets.shape != (h * w + 1,):
            raise InputError(f"offsets must have H*W+1 = {h * w + 1} entries, got {offsets.shape}")
        if times.shape != counts.shape:
            raise InputError(f"times and counts differ in length ({times.size} vs {counts.size})")
        if offsets[0] != 0 or offsets[-1] != times.size or np.any(np.diff(offsets) < 0):
            raise InputError("offsets must rise from 0 to the number of occupied bins")
        if counts.size and not (np.all(np.isfinite(times)) and np.all(np.isfinite(counts))
                                and counts.min() > 0):
            raise InputError("counts must be positive and finite at finite times")
        if self.periods is not None:
            periods = np.ascontiguousarray(np.broadcast_to(np.asarray(self.periods, np.float64), (h * w,)))
            if not np.all(periods > 0) or not np.all(np.isfinite(periods)):
                raise InputError("laser periods per pixel must be positive and finite")
            object.__setattr__(self, "periods", periods)
        object.__setattr__(self, "times", times)
        object.__setattr__(self, "counts", counts)
        object.__setattr__(self, "offsets", offsets)
        object.__setattr__(self, "shape", (int(h), int(w)))

    # ---- building -------------------------------------------------------------------------------
    @classmethod
    def from_cube(cls, cube: np.ndarray, time_unit_s: float, *, periods=None,
                  source: str = "cube") -> "CountStore":
        """From an H x W x T array of counts (any integer or float type holding whole, non-negative
        numbers); bin k of the last axis is raw time k. Only the non-zero bins are kept."""
        cube = np.asarray(cube)
        if cube.ndim != 3:
            raise InputError(f"{source}: a cube is H x W x T, got {cube.ndim} dimensions {cube.shape}")
        if cube.dtype.kind not in "uifb":
            raise InputError(f"{source}: holds {cube.dtype} values, not counts")
        h, w, t = cube.shape
        flat = cube.reshape(h * w, t)
        if cube.dtype.kind == "f":
            if not np.all(np.isfinite(flat)):
                raise InputError(f"{source}: holds NaN or infinite counts")
            if np.any(flat < 0) or np.any(flat != np.floor(flat)):
                raise InputError(f"{source}: holds counts that are not whole non-negative numbers")
        elif cube.dtype.kind == "i" and flat.size and flat.min() < 0:
            raise InputError(f"{source}: holds negative counts")
        pix, tbin = np.nonzero(flat)
        offsets = np.zeros(h * w + 1, np.int64)
        np.cumsum(np.bincount(pix, minlength=h * w), out=offsets[1:])
        return cls(tbin.astype(np.float64), flat[pix, tbin].astype(np.float64), offsets, (h, w),
                   time_unit_s, periods)

    @classmethod
    def from_pairs(cls, keys: np.ndarray, counts: np.ndarray, shape: tuple[int, int], n_bins: int,
                   time_unit_s: float, *, periods=None) -> "CountStore":
        """From a sparse frame: ``keys`` = flat pixel * n_bins + bin, ascending and distinct, with
        their counts (what an array sensor's driver delivers without the zeros)."""
        keys = np.asarray(keys, np.int64)
        h, w = shape
        pix = keys // n_bins
        if keys.size and (keys[0] < 0 or pix[-1] >= h * w or np.any(np.diff(keys) <= 0)):
            raise InputError("frame keys must be distinct, ascending and inside the frame")
        offsets = np.zeros(h * w + 1, np.int64)
        np.cumsum(np.bincount(pix, minlength=h * w), out=offsets[1:])
        return cls((keys - pix * n_bins).astype(np.float64), np.asarray(counts, np.float64), offsets,
                   (h, w), time_unit_s, periods)

    @classmethod
    def from_photons(cls, store: PhotonStore, periods=None) -> "CountStore":
        """The histogram of a photon list at its own raw resolution: each pixel's distinct times
        and how many detections at each (detection order is lost)."""
        times = np.empty(store.n_photons, np.float64)
        counts = np.empty(store.n_photons, np.float64)
        offsets = np.empty(store.offsets.size, np.int64)
        n = _histogram_runs(store.times, store.offsets, times, counts, offsets)
        return cls(times[:n], counts[:n], offsets, store.shape, store.time_unit_s, periods)

    # ---- views ----------------------------------------------------------------------------------
    @property
    def n_pixels(self) -> int:
        return self.shape[0] * self.shape[1]

    @property
    def n_occupied(self) -> int:
        """Occupied (pixel, time) bins: what memory and the estimators' time grow with."""
        return int(self.times.size)

    @property
    def n_detections(self) -> float:
        return float(self.counts.sum())

    def detections(self) -> np.ndarray:
        """Detections per pixel, shape (H, W), float64."""
        return np.bincount(self.pixel_index(), weights=self.counts,
                           minlength=self.n_pixels).reshape(self.shape)

    def pixel_index(self) -> np.ndarray:
        """The flat pixel of each entry, int64 (n_occupied,)."""
        return np.repeat(np.arange(self.n_pixels), np.diff(self.offsets))

    def is_whole(self) -> bool:
        """True when every count is a whole number (as read, not pile-up corrected)."""
        return bool(np.all(self.counts == np.rint(self.counts)))

    def to_photons(self, *, round_counts: bool = False) -> PhotonStore:
        """The equivalent photon list: each time repeated by its count, in time order within each
        pixel. Whole counts only, unless ``round_counts``: then the counts are :meth:`rounded`
        first."""
        if round_counts:
            return self.rounded().to_photons()
        if not self.is_whole():
            raise InputError("only whole counts expand into a photon list (this store is corrected)")
        reps = self.counts.astype(np.int64)
        offsets = np.zeros(self.n_pixels + 1, np.int64)
        np.cumsum(np.bincount(self.pixel_index(), weights=reps, minlength=self.n_pixels).astype(np.int64),
                  out=offsets[1:])
        return PhotonStore(np.repeat(self.times, reps), offsets, self.shape, self.time_unit_s)

    def rounded(self) -> "CountStore":
        """Whole counts for what needs them (the photon list, spatial's censoring, the K-surface
        fit) from a pile-up-corrected store: each pixel's running total is rounded, so every count
        becomes the floor or the ceiling of itself, the pixel's total is kept to within one, and no
        count is rounded away systematically; entries rounded to 0 are dropped. A store of whole
        counts is returned as it is."""
        if self.is_whole():
            return self
        run = np.cumsum(self.counts)
        start = np.zeros(self.n_pixels)
        has = np.diff(self.offsets) > 0
        start[has] = (run - self.counts)[self.offsets[:-1][has]]
        edge = np.floor(run - np.repeat(start, np.diff(self.offsets)) + 0.5)
        prev = np.empty_like(edge)
        prev[1:] = edge[:-1]
        prev[self.offsets[:-1][has]] = 0.0
        reps = edge - prev
        return self._subset(reps > 0, reps, self.periods)

    def binned(self, binning) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The counts in ``binning``'s window (a :class:`recon.model.Binning` in this store's raw
        units) as (bin, count) pairs per pixel: (bins int64, counts float64, offsets int64 (P + 1,)),
        bins distinct and ascending within each pixel, counts of the raw times in one bin summed.
        The bin of a time is ``Binning.bin_index``'s (``floor((t - start) / width)``, the last bin
        taking the window's end), so a photon list and its histogram bin alike."""
        bins = np.empty(self.n_occupied, np.int64)
        counts = np.empty(self.n_occupied, np.float64)
        offsets = np.empty(self.offsets.size, np.int64)
        n = _bin_pairs(self.times, self.counts, self.offsets, float(binning.window_start),
                       float(binning.window_stop), float(binning.bin_width), int(binning.n_bins),
                       bins, counts, offsets)
        return bins[:n], counts[:n], offsets

    def in_window(self, start: float, stop: float) -> "CountStore":
        """Only the times with ``start <= t < stop`` (raw units); never clamped into edge bins."""
        return self._subset((self.times >= start) & (self.times < stop), self.counts, self.periods)

    def _subset(self, keep: np.ndarray, counts: np.ndarray, periods) -> "CountStore":
        """The entries where ``keep``, with ``counts`` (one per entry) in place of this store's."""
        offsets = np.zeros(self.n_pixels + 1, np.int64)
        np.cumsum(np.bincount(self.pixel_index()[keep], minlength=self.n_pixels), out=offsets[1:])
        return CountStore(self.times[keep], counts[keep], offsets, self.shape, self.time_unit_s, periods)

    def split(self, seed: int = 0) -> tuple["CountStore", "CountStore"]:
        """Two halves, each detection sent to one of them at random (a binomial draw per bin):
        independent measurements of the same scene with half the light each, so the maps of the
        two can check each other's error bars. Each half keeps half the periods."""
        if not self.is_whole():
            raise InputError("only whole counts split into halves")
        rng = np.random.default_rng(seed)
        a = rng.binomial(self.counts.astype(np.int64), 0.5).astype(np.float64)
        periods = None if self.periods is None else self.periods / 2
        b = self.counts - a
        return self._subset(a > 0, a, periods), self._subset(b > 0, b, periods)


@njit(cache=True, nogil=True)
def _bin_pairs(times, counts, offsets, start, stop, width, n_bins, out_bins, out_counts, out_offsets):
    """:meth:`CountStore.binned`'s pass: times ascending within each pixel, so equal bins are
    adjacent; the bin expression is recon.kernels.window_bins' (the same bins as for photons)."""
    n = 0
    out_offsets[0] = 0
    for p in range(offsets.size - 1):
        first = n
        for q in range(offsets[p], offsets[p + 1]):
            t = times[q]
            if t >= start and t < stop:
                k = math.floor((t - start) / width)
                if k > n_bins - 1:
                    k = n_bins - 1
                if n > first and out_bins[n - 1] == k:
                    out_counts[n - 1] += counts[q]
                else:
                    out_bins[n] = np.int64(k)
                    out_counts[n] = counts[q]
                    n += 1
        out_offsets[p + 1] = n
    return n


@njit(cache=True, nogil=True)
def _histogram_runs(times, offsets, out_times, out_counts, out_offsets):
    """Each pixel's detections sorted, equal times merged into one entry and a count: the CSR
    histogram of a photon list. Returns the number of entries written."""
    n = 0
    out_offsets[0] = 0
    for p in range(offsets.size - 1):
        t = np.sort(times[offsets[p]:offsets[p + 1]])
        for q in range(t.size):
            if n > out_offsets[p] and out_times[n - 1] == t[q]:
                out_counts[n - 1] += 1.0
            else:
                out_times[n] = t[q]
                out_counts[n] = 1.0
                n += 1
        out_offsets[p + 1] = n
    return n


__all__ = ["CountStore"]
