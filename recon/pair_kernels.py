"""The compiled loops of the pair-difference histogram (:func:`recon.model.pair_difference_histogram`,
the pulse measured from the data): the largest within-pixel spread of the first detections, and the
histogram of ``|t_i - t_j|`` over their pairs.

NumPy built the pairs a block of pixels at a time, stacked them and binned them with
``np.histogram``'s index arithmetic; on a 512x512 scan (20,000 pixels of 30 detections, 9 M pairs)
that took 0.21 s of the pulse estimate's 0.35 s, every time a file is reconstructed without a
given pulse. Here each pair is binned as it is formed, with the same arithmetic and the same
corrections at the edges (``np.histogram``'s, kept in ``tests/reference.py``), so the counts are
the same bin for bin. Loaded on a new process's warm-up thread with the estimator's kernels
(:func:`recon.estimate.warm_up`).
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def pair_span(times, starts, counts, multi):
    """The largest ``max - min`` of ``times[starts[p]:starts[p] + counts[p]]`` over the pixels
    ``multi`` (0.0 when there are none)."""
    span = 0.0
    for k in range(multi.size):
        p = multi[k]
        s = starts[p]
        lo = times[s]
        hi = lo
        for j in range(1, counts[p]):
            t = times[s + j]
            lo = min(lo, t)
            hi = max(hi, t)
        span = max(span, hi - lo)
    return span


@njit(cache=True, nogil=True)
def pair_histogram(times, starts, counts, multi, edges, scale, hist):
    """Add to ``hist`` (nh bins over ``edges``, nh + 1 ascending from 0) ``|t_j - t_i|`` of every
    pair i < j among ``times[starts[p]:starts[p] + counts[p]]`` of each pixel p of ``multi``, binned
    as ``np.histogram(x, bins=nh, range=(0, edges[-1]))`` bins x >= 0 (``scale`` = nh / edges[-1]):
    the index from the scaled value, then moved down one where the value lies below its bin's
    lower edge and up one where it reaches the upper edge (not past the last bin)."""
    nh = hist.size
    for k in range(multi.size):
        p = multi[k]
        s = starts[p]
        for j in range(1, counts[p]):
            tj = times[s + j]
            for i in range(j):
                x = abs(tj - times[s + i])
                idx = min(int(x * scale), nh)     # the cap only keeps a value beyond the range in bounds
                if idx == nh:
                    idx -= 1
                if x < edges[idx]:
                    idx -= 1
                if idx != nh - 1 and x >= edges[idx + 1]:
                    idx += 1
                hist[idx] += 1


__all__ = ["pair_histogram", "pair_span"]

