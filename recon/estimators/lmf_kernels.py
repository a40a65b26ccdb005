"""Numba kernels of lmf (:mod:`.lmf`): the log-matched filter of eq. (11), ``argmax_i sum_k y_k log
S_{k,i}`` per pixel over integer shifts, and the variance from that score's curvature there.

:func:`lmf_kernel` (the scratch; recon.pixelwise.over_threads shares a fit's pixels among threads) ->
:func:`_lmf_pixels` (the compiled loop) -> :func:`lmf_pixel` (:func:`lmf_shift`, :func:`lmf_var`) on one pixel's distinct bins and counts
(:func:`recon.kernels.pixel_bins`).
"""

from __future__ import annotations

from collections import namedtuple

import numpy as np
from numba import njit

from spdepth.recon.kernels import INNER, ZERO, pixel_bins, pixel_scratch

#: LMF on a log-concave pulse: up to this many distinct photon bins, hill-climb from their mean
#: (cost O(photons x steps), steps < bins); above it, bisect (O(photons log bins)).
CLIMB_MAX_PHOTONS = 64

#: lmf's tables: m bins in the window; logg (2m - 1,): log(g / gmax) at offsets d in [-(m-1), m-1]
#: (index d + m - 1, :class:`recon.model.PulseKernel`); log_concave: logg is concave.
LmfTables = namedtuple("LmfTables", ["m", "logg", "log_concave"])


@njit(cache=True, nogil=True, _nrt=False, **INNER)
def _lmf_score(kb, kw, nu, i, logg, m):
    s = 0.0
    # unsigned index: spares numba's negative-index wraparound on each gather (the index is >= 0)
    for u in range(nu):
        s += kw[u] * logg[np.uint64(kb[u] - i + m - 1)]
    return s


@njit(cache=True, nogil=True, _nrt=False, inline="always")
def _bisect(kb, kw, nu, logg, m):
    """The first argmax of a concave score: the first shift where it stops rising, by bisection in
    O(photons log bins) (a climb from the photons' mean could walk O(bins) steps of O(photons)
    each on a huge pixel)."""
    lo = 0
    hi = m - 1
    while lo < hi:
        mid = (lo + hi) // 2
        if _lmf_score(kb, kw, nu, mid + 1, logg, m) > _lmf_score(kb, kw, nu, mid, logg, m):
            lo = mid + 1
        else:
            hi = mid
    return lo


@njit(cache=True, nogil=True, _nrt=False, inline="always")
def _climb(kb, kw, nu, logg, m):
    """The first argmax of a concave score for few photons: climb from their mean bin (a handful of
    steps, cheaper than bisection)."""
    mean = 0.0
    tot = 0.0
    for u in range(nu):
        mean += kw[u] * kb[u]
        tot += kw[u]
    i = int(mean / tot + 0.5)
    i = min(max(i, 0), m - 1)
    best = _lmf_score(kb, kw, nu, i, logg, m)
    moved = False
    while i + 1 < m:
        s = _lmf_score(kb, kw, nu, i + 1, logg, m)
        if s > best:
            best = s
            i += 1
            moved = True
        else:
            break
    if not moved:
        while i > 0:
            s = _lmf_score(kb, kw, nu, i - 1, logg, m)
            if s >= best:   # >= : first index among ties, like argmax
                best = s
                i -= 1
            else:
                break
    else:
        while i > 0 and _lmf_score(kb, kw, nu, i - 1, logg, m) >= best:
            i -= 1
    return i


@njit(cache=True, nogil=True, _nrt=False, inline="always")
def _scan(kb, kw, nu, logg, m):
    """The first argmax over every shift (a score that is not concave)."""
    i = 0
    best = _lmf_score(kb, kw, nu, ZERO, logg, m)
    for j in range(1, m):
        s = _lmf_score(kb, kw, nu, j, logg, m)
        if s > best:
            best = s
            i = j
    return i


@njit(cache=True, nogil=True, _nrt=False, inline="always")
def lmf_pixel(kb, kw, nu, tabs):
    """(shift, var) of one pixel's distinct bins kb[:nu] (counts kw): :func:`lmf_shift` and
    :func:`lmf_var`; (-1, NaN) without photons."""
    if nu == 0:
        return -1, np.nan
    i = lmf_shift(kb, kw, nu, tabs)
    return i, lmf_var(kb, kw, nu, i, tabs)


@njit(cache=True, nogil=True, _nrt=False, inline="always")
def lmf_shift(kb, kw, nu, tabs):
    """The first argmax shift of the score of the distinct bins kb[:nu] (counts kw), nu > 0."""
    if tabs.log_concave and nu > CLIMB_MAX_PHOTONS:
        return _bisect(kb, kw, nu, tabs.logg, tabs.m)
    if tabs.log_concave:
        return _climb(kb, kw, nu, tabs.logg, tabs.m)
    return _scan(kb, kw, nu, tabs.logg, tabs.m)


@njit(cache=True, nogil=True, _nrt=False, inline="always")
def lmf_var(kb, kw, nu, i, tabs):
    """Shift variance (bins^2) from the observed curvature of the score at shift i (NaN: none)."""
    logg = tabs.logg
    nt = logg.size
    m = tabs.m
    curv = 0.0
    for u in range(nu):
        t = kb[u] - i + m - 1
        tl = max(t - 1, 0)
        th = min(t + 1, nt - 1)
        if th - tl == 2:
            curv += kw[u] * (logg[th] - 2.0 * logg[t] + logg[tl])
    return -1.0 / curv if curv < 0.0 else np.nan


@njit(cache=True, nogil=True, _nrt=False)
def _lmf_pixels(ph, tabs, px, out_shift, out_var, out_n):
    """Every pixel of ph with the scratch px: the per-pixel helpers are inlined here, into a loop
    compiled without numba's reference counting (it allocates nothing)."""
    for p in range(ph.offsets.size - 1):
        nu, out_n[p] = pixel_bins(ph, p, px)
        out_shift[p], out_var[p] = lmf_pixel(px.kb, px.kw, nu, tabs)


def lmf_kernel(ph, tabs, maxn, out_shift, out_var, out_n):
    """Log-matched filter per pixel of ph (:class:`recon.kernels.Photons`, at most maxn detections
    a pixel) with :class:`LmfTables`. out_shift: argmax shift (int64, -1 without photons), out_var:
    shift variance in bins^2 from the observed curvature of the log-likelihood, out_n: photons.
    Releases the GIL. The scratch is allocated here, so that the compiled loop is the function
    called from Python (see :func:`.ml_kernels.ml_kernel`: one level of compiled calls fewer)."""
    _lmf_pixels(ph, tabs, pixel_scratch(maxn, tabs.m), out_shift, out_var, out_n)
