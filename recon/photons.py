"""The per-pixel photon store: every reader and the acquisition loop produce one, every estimator
consumes one."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

from spdepth.recon.errors import InputError


@dataclass(frozen=True, eq=False)
class PhotonStore:
    """Detection times of an H x W image, pixel by pixel, in detection order.

    Stored compressed (CSR-like) so a 1024 x 1024 scan with millions of detections is two flat
    arrays, and the photons of pixel ``p = row * W + col`` are ``times[offsets[p]:offsets[p + 1]]``.

    times:       float64, shape (n_photons,): arrival time after the laser sync, in units of
                 ``time_unit_s`` (integral for time-tagger data; float keeps ps-unit files exact).
    offsets:     int64, shape (H * W + 1,), non-decreasing, offsets[0] == 0, offsets[-1] == n_photons.
    shape:       (H, W) pixels, row-major.
    time_unit_s: the size of one unit of ``times`` in seconds (e.g. 8e-12 for 8 ps units).
    """

    times: np.ndarray
    offsets: np.ndarray
    shape: tuple[int, int]
    time_unit_s: float

    def __post_init__(self) -> None:
        h, w = self.shape
        if h < 1 or w < 1:
            raise InputError(f"photon store shape must be at least 1 x 1, got {self.shape}")
        if not (self.time_unit_s > 0 and np.isfinite(self.time_unit_s)):
            raise InputError(f"time_unit_s must be positive, got {self.time_unit_s}")
        times = np.ascontiguousarray(self.times, dtype=np.float64)
        offsets = np.ascontiguousarray(self.offsets, dtype=np.int64)
        if offsets.shape != (h * w + 1,):
            raise InputError(f"offsets must have H*W+1 = {h * w + 1} entries, got {offsets.shape}")
        if offsets[0] != 0 or offsets[-1] != times.size or np.any(np.diff(offsets) < 0):
            raise InputError("offsets must rise from 0 to the number of photons")
        if times.size and not np.all(np.isfinite(times)):
            raise InputError("photon times contain NaN or infinity")
        object.__setattr__(self, "times", times)
        object.__setattr__(self, "offsets", offsets)
        object.__setattr__(self, "shape", (int(h), int(w)))

    @classmethod
    def from_lists(cls, per_pixel, shape: tuple[int, int], time_unit_s: float) -> "PhotonStore":
        """Build from a sequence of H*W arrays (row-major pixel order) of detection times."""
        counts = np.fromiter((len(p) for p in per_pixel), dtype=np.int64, count=len(per_pixel))
        offsets = np.zeros(counts.size + 1, dtype=np.int64)
        np.cumsum(counts, out=offsets[1:])
        times = (np.concatenate([np.asarray(p, dtype=np.float64).ravel() for p in per_pixel])
                 if offsets[-1] else np.zeros(0))
        return cls(times, offsets, shape, time_unit_s)

    @classmethod
    def from_pixel_indices(cls, pixel: np.ndarray, times: np.ndarray, shape: tuple[int, int],
                           time_unit_s: float) -> "PhotonStore":
        """Build from parallel arrays of flat pixel index and detection time (any order of pixels;
        detection order within a pixel is kept). A counting sort: linear in the detections.
        int32 indices are grouped as they are (a reader's, half the memory of int64), any other
        integer type as int64."""
        pixel = np.asarray(pixel)
        pixel = np.ascontiguousarray(pixel, dtype=pixel.dtype if pixel.dtype == np.int32 else np.int64)
        times = np.ascontiguousarray(times)
        if pixel.shape != times.shape:
            raise InputError(f"pixel and time arrays differ in length ({pixel.size} vs {times.size})")
        n_pix = shape[0] * shape[1]
        offsets = np.zeros(n_pix + 1, dtype=np.int64)
        out = np.empty(pixel.size, np.float64)
        if not _group_by_pixel(pixel, times, offsets, out):
            raise InputError(f"pixel index out of range for a {shape[0]} x {shape[1]} image")
        return cls(out, offsets, shape, time_unit_s)

    @property
    def n_pixels(self) -> int:
        return self.shape[0] * self.shape[1]

    @property
    def n_photons(self) -> int:
        return int(self.times.size)

    def counts(self) -> np.ndarray:
        """Detections per pixel, shape (H, W), int64."""
        return np.diff(self.offsets).reshape(self.shape)

    def first_in_window(self, start: float, stop: float, max_photons: int | None = None) -> "PhotonStore":
        """Keep only detections with ``start <= t < stop`` (raw units), and of those the first
        ``max_photons`` per pixel in detection order, so one long recording can stand for a shorter
        acquisition. Out-of-window detections are dropped, never clamped into edge bins."""
        if max_photons is not None and max_photons < 1:
            raise InputError(f"max_photons must be at least 1, got {max_photons}")
        keep = (self.times >= start) & (self.times < stop)
        if max_photons is not None:
            # rank of each kept photon within its pixel = running count of kept photons minus the
            # count at the pixel's first photon
            running = np.cumsum(keep)
            before_pixel = np.concatenate(([0], running))[self.offsets[:-1]]
            rank = running - np.repeat(before_pixel, np.diff(self.offsets))
            keep &= rank <= max_photons
        pix = np.repeat(np.arange(self.n_pixels), np.diff(self.offsets))
        counts = np.bincount(pix[keep], minlength=self.n_pixels)
        offsets = np.zeros(self.n_pixels + 1, dtype=np.int64)
        np.cumsum(counts, out=offsets[1:])
        return PhotonStore(self.times[keep], offsets, self.shape, self.time_unit_s)

    def without_pixels(self, flat_pixels) -> "PhotonStore":
        """The same store with the photons of the listed pixels (flat indices) removed, e.g.
        pixels that lost data and must not pass for complete ones."""
        drop = np.zeros(self.n_pixels, dtype=bool)
        drop[np.asarray(flat_pixels, dtype=np.int64)] = True
        counts = np.where(drop, 0, np.diff(self.offsets))
        keep = np.repeat(~drop, np.diff(self.offsets))
        offsets = np.zeros(self.n_pixels + 1, dtype=np.int64)
        np.cumsum(counts, out=offsets[1:])
        return PhotonStore(self.times[keep], offsets, self.shape, self.time_unit_s)

    def pixel(self, row: int, col: int) -> np.ndarray:
        """Detection times of one pixel (a view, in detection order)."""
        p = row * self.shape[1] + col
        return self.times[self.offsets[p]:self.offsets[p + 1]]


def evenly_spaced(idx: np.ndarray, most: int) -> np.ndarray:
    """At most ``most`` of the pixel indices ``idx``, evenly spaced through them (all when fewer):
    a sample that keeps the frame's mix, where the busiest pixels would not."""
    if idx.size <= most:
        return idx
    return idx[np.linspace(0, idx.size - 1, most).astype(np.int64)]


def rows_of(offsets: np.ndarray, idx: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The entries of the pixels ``idx`` in a CSR list grouped by ``offsets``: (their flat indices in
    the pixels' order, the offsets of that list of its own)."""
    counts = np.diff(offsets)[idx]
    sub = np.zeros(idx.size + 1, np.int64)
    np.cumsum(counts, out=sub[1:])
    return np.repeat(offsets[idx] - sub[:-1], counts) + np.arange(sub[-1]), sub


@njit(cache=True, nogil=True)
def _group_by_pixel(pixel, times, offsets, out):
    """Stable counting sort: ``offsets`` (zeros, one more than the pixels) becomes each pixel's
    start and ``out[offsets[p] + j]`` the j-th time (in input order) of pixel p. False, with
    nothing grouped, when an index lies outside [0, pixels). One pass to count (which checks the
    range) and one to place: the range check, count and placing in NumPy read the indices four
    times (0.17 s of a 512x512 PTU's read)."""
    n_pix = offsets.size - 1
    for i in range(pixel.size):
        p = pixel[i]
        if p < 0 or p >= n_pix:
            return False
        offsets[p + 1] += 1
    for p in range(n_pix):
        offsets[p + 1] += offsets[p]
    fill = offsets[:-1].copy()
    for i in range(pixel.size):
        p = pixel[i]
        out[fill[p]] = times[i]
        fill[p] += 1
    return True
