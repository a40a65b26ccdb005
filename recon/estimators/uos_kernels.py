"""Numba kernels of uos (:mod:`.uos`): the seed paper's union-of-subspaces greedy pursuit
(Algorithm 1) with one depth column and the background column, on the published code's scaling
(columns g / gmax, peak 1, so delta means what it means there).

:func:`uos_kernel` (the scratch, :func:`uos_scratch`; recon.pixelwise.over_threads shares a fit's pixels
among threads) -> :func:`_uos_pixels` (the compiled loop) -> :func:`uos_pixel`: :func:`uos_scatter` (S^T y), iterations of
(:func:`_iterate`: the proxy's argmax :func:`uos1_argmax`, pruned -> :func:`union_support` ->
:func:`solve_support` -> :func:`keep_largest` -> :func:`change_norm`), then :func:`refit_nonneg`
when the last fit was clipped. Several surfaces per pixel are the K-surface fit's
(:mod:`.surfaces_kernels`), not this pursuit's.
"""

from __future__ import annotations

from collections import namedtuple

import numpy as np
from numba import njit

from spdepth.recon.kernels import (INNER, ZERO, col_dot, photon_intervals, pinv_solve, pixel_bins,
                                   pixel_scratch)

#: uos's tables and settings (:func:`uos_tables`): m bins; the unit-area pulse g with its peak at
#: offset off (nk = g.size), its column sums colsum and pair prefix sums pp
#: (:class:`recon.model.PulseKernel`); inv_gmax = 1 / max(g) (the peak-1 scaling) and inv_g2 its
#: square; acorr: g's autocorrelation at lag d + nk - 1; grev: g reversed; cmin: min(colsum);
#: delta, max_iter: the stopping threshold and the iteration cap (ReconSettings).
UosTables = namedtuple("UosTables", ["m", "g", "off", "nk", "colsum", "pp", "inv_gmax", "inv_g2", "acorr",
                                     "grev", "cmin", "delta", "max_iter"])
#: A block's scratch (:func:`uos_scratch`): cvec (S^T y, zero between pixels), the photons' shift
#: intervals ivlo/ivhi, the support (supp, amp) and its update (nsupp, namp, newi, om), and the
#: least squares' gram, work, vecs, vals, rhs, sol.
UosScratch = namedtuple("UosScratch", ["cvec", "ivlo", "ivhi", "supp", "amp", "nsupp", "namp", "newi", "om",
                                       "gram", "work", "vecs", "vals", "rhs", "sol"])


@njit(cache=True, nogil=True)
def uos_tables(g, off, gmax, colsum, pp, m, delta, max_iter):
    """:class:`UosTables` of the pulse kernel's g, off, gmax, colsum and pp over m bins."""
    nk = g.size
    inv_gmax = 1.0 / gmax
    # full autocorrelation of g, lag index d + nk - 1
    acorr = np.zeros(2 * nk - 1)
    for d in range(-(nk - 1), nk):
        acc = 0.0
        for t in range(nk):
            if 0 <= t - d < nk:
                acc += g[t] * g[t - d]
        acorr[d + nk - 1] = acc
    return UosTables(m, g, off, nk, colsum, pp, inv_gmax, inv_gmax * inv_gmax, acorr, g[::-1].copy(),
                     colsum.min(), delta, max_iter)


@njit(cache=True, nogil=True)
def uos_scratch(maxn, m):
    """:class:`UosScratch` for pixels of at most maxn detections over m bins (one support column
    and the background: at most 3 columns in a fit)."""
    n = max(maxn, 1)
    return UosScratch(np.zeros(m), np.empty(n, np.int64), np.empty(n, np.int64), np.empty(1, np.int64),
                      np.empty(1), np.empty(1, np.int64), np.empty(1), np.empty(1, np.int64),
                      np.empty(3, np.int64), np.empty((4, 4)), np.empty((4, 4)), np.empty((4, 4)), np.empty(4),
                      np.empty(4), np.empty(4))


@njit(cache=True, nogil=True, inline="always")
def _scan_plain(cvec, colsum, bgc, a, b, best, bi):
    """Running (max, first argmax) of ``cvec[i] - bgc*colsum[i]`` over shifts a..b (inclusive):
    the proxy where the support column does not overlap. A 0-based slice loop (vectorisable)."""
    if b >= a:
        cv = cvec[a:b + 1]
        cs = colsum[a:b + 1]
        for t in range(cv.size):
            v = cv[t] - bgc * cs[t]
            if v > best:
                best = v
                bi = a + t
    return best, bi


@njit(cache=True, nogil=True, **INNER)
def _scan_range(lo, hi, best, bi, cvec, colsum, bgc, j, aj, wlo, whi, clipped, acorr, nk, m, pp, off):
    """Running (max, first argmax) of the proxy over shifts lo..hi (inclusive), continuing from
    (best, bi). The entry is ``cvec[i] - bgc*colsum[i]``, minus ``aj * S_i^T S_j`` inside the support
    window [wlo, whi]: the same floating-point expression in pruned and dense scans, so they agree
    bit for bit. Three plain loops, so the common parts carry no per-shift branches; each runs over
    slices indexed from 0, which spares numba's negative-index wraparound on every load."""
    best, bi = _scan_plain(cvec, colsum, bgc, lo, min(hi, wlo - 1), best, bi)
    a = max(lo, wlo)
    b = min(hi, whi)
    if b >= a:
        if clipped:
            for i in range(a, b + 1):
                v = cvec[i] - bgc * colsum[i] - aj * col_dot(i, j, m, pp, off, nk)
                if v > best:
                    best = v
                    bi = i
        else:
            cv = cvec[a:b + 1]
            cs = colsum[a:b + 1]
            ac = acorr[a - j + nk - 1:b - j + nk]
            for t in range(cv.size):
                v = cv[t] - bgc * cs[t] - aj * ac[t]
                if v > best:
                    best = v
                    bi = a + t
    return _scan_plain(cvec, colsum, bgc, max(lo, whi + 1), hi, best, bi)


@njit(cache=True, nogil=True)
def uos1_argmax(cvec, colsum, cmin, bgc, ns, j, aj, acorr, nk, m, pp, off, ivlo, ivhi, niv):
    """First index of the largest proxy entry (numpy argmax of the dense proxy), K = 1.

    Exact pruning: outside the photon intervals cvec is exactly 0, so there the entry is
    ``0 - bgc*colsum[i] - aj*S_i^T S_j <= 0 - bgc*cmin`` (aj, bgc >= 0, column inner products >= 0,
    and rounding is monotone). If the best entry inside the intervals beats that bound strictly, no
    other index can reach or tie it; otherwise (rare: nothing above the background level) the dense
    scan decides."""
    if ns > 0:
        wlo = max(0, j - (nk - 1))
        whi = min(m - 1, j + (nk - 1))
    else:
        wlo = m          # empty window: no support column to subtract
        whi = m - 1
    clipped = ns > 0 and not (j - off >= 0 and j + (nk - 1 - off) < m)
    best = -np.inf
    bi = np.int64(-1)
    for t in range(niv):
        best, bi = _scan_range(ivlo[t], ivhi[t], best, bi, cvec, colsum, bgc, j, aj, wlo, whi, clipped,
                               acorr, nk, m, pp, off)
    far_bound = 0.0 - bgc * cmin
    if best > far_bound:
        return bi
    best, bi = _scan_range(ZERO, m - 1, -np.inf, np.int64(-1), cvec, colsum, bgc, j, aj, wlo, whi, clipped,
                           acorr, nk, m, pp, off)
    return bi


@njit(cache=True, nogil=True, **INNER)
def refit_nonneg(supp, amp, ns, use_bg, cvec, colsum, ntot, m, pp, off, nk, inv_gmax, inv_g2, gram, rhs,
                 work, vecs, vals, sol):
    """Least squares on the kept support (depth columns supp[:ns], and the background column when
    use_bg), dropping the most negative coefficient until none is negative; amp[:ns] gets the
    peak-1 amplitudes. Returns (ns, bg).

    Algorithm 1's T_0 zeroes negative coefficients of a least-squares fit that included them: the
    kept ones then absorb what the dropped ones explained (one detection in a three-bin window read
    as six signal detections). Run once after the pursuit, so its path is the published one."""
    while True:
        nb = ns + (1 if use_bg else 0)
        if nb == 0:
            return 0, 0.0
        for a in range(ns):
            for b in range(a, ns):
                gab = col_dot(supp[a], supp[b], m, pp, off, nk) * inv_g2
                gram[a, b] = gab
                gram[b, a] = gab
            rhs[a] = cvec[supp[a]]
            if use_bg:
                gram[a, ns] = colsum[supp[a]] * inv_gmax
                gram[ns, a] = gram[a, ns]
        if use_bg:
            gram[ns, ns] = float(m)
            rhs[ns] = ntot
        pinv_solve(gram, rhs, nb, work, vecs, vals, sol)
        worst = -1
        wv = 0.0
        for a in range(nb):
            if sol[a] < wv or (sol[a] == 0.0 and a < ns and wv == 0.0 and worst < 0):
                wv = sol[a]
                worst = a
        if worst < 0:
            for a in range(ns):
                amp[a] = sol[a]
            return ns, (sol[ns] if use_bg else 0.0)
        if worst == ns:
            use_bg = False
        else:
            for a in range(worst, ns - 1):
                supp[a] = supp[a + 1]
            ns -= 1


@njit(cache=True, nogil=True, inline="always")
def uos_scatter(kb, kw, nu, cvec, grev, inv_gmax, nk, off, m):
    """c_i = S_i^T y (peak-1 columns) scattered from the photons into cvec (all zero before)."""
    for u in range(nu):
        k = kb[u]
        wu = kw[u] * inv_gmax
        ilo = max(0, k - (nk - 1 - off))
        ihi = min(m - 1, k + off)
        sh = nk - 1 - k - off      # g[k - i + off] == grev[i + sh]: forward, vectorisable
        # through slices indexed from 0: numba's negative-index wraparound on ``i + sh``
        # kept LLVM from vectorising this loop (3x slower, the largest cost of a pixel)
        cv = cvec[ilo:ihi + 1]
        gr = grev[ilo + sh:ihi + 1 + sh]
        for t in range(cv.size):
            cv[t] += wu * gr[t]


@njit(cache=True, nogil=True, inline="always")
def _among(v, a, n):
    """Whether v is one of a[:n]."""
    for t in range(n):
        if a[t] == v:
            return True
    return False


@njit(cache=True, nogil=True, inline="always")
def union_support(newi, kk, supp, ns, om):
    """Omega = new indices U previous support, sorted and distinct, into om; returns its size."""
    nd = 0
    for r in range(kk):
        if newi[r] >= 0:
            om[nd] = newi[r]
            nd += 1
    for s in range(ns):
        if not _among(supp[s], om, nd):
            om[nd] = supp[s]
            nd += 1
    for a in range(1, nd):
        v = om[a]
        b = a - 1
        while b >= 0 and om[b] > v:
            om[b + 1] = om[b]
            b -= 1
        om[b + 1] = v
    return nd


@njit(cache=True, nogil=True, inline="always")
def solve_support(om, nd, cvec, colsum, ntot, m, pp, off, nk, inv_gmax, inv_g2, gram, rhs, work, vecs,
                  vals, sol):
    """Least squares of y on the columns om[:nd] and the background column (pinv, via the Gram
    matrix): sol[:nd] depth coefficients, sol[nd] background. Returns True if any is negative."""
    for a in range(nd):
        for b in range(a, nd):
            gab = col_dot(om[a], om[b], m, pp, off, nk) * inv_g2
            gram[a, b] = gab
            gram[b, a] = gab
        gram[a, nd] = colsum[om[a]] * inv_gmax
        gram[nd, a] = gram[a, nd]
        rhs[a] = cvec[om[a]]
    gram[nd, nd] = float(m)
    rhs[nd] = ntot
    pinv_solve(gram, rhs, nd + 1, work, vecs, vals, sol)
    for a in range(nd + 1):
        if sol[a] < 0.0:
            return True
    return False


@njit(cache=True, nogil=True, inline="always")
def keep_largest(sol, nd, kk, om, nsupp, namp):
    """The kk largest positive depth coefficients of sol[:nd] (T_0 drops the rest), as column
    indices nsupp and amplitudes namp; returns how many."""
    nn = 0
    for r in range(kk):
        best = -np.inf
        bi = -1
        for a in range(nd):
            if sol[a] > best and not _among(a, nsupp, nn):
                best = sol[a]
                bi = a
        if bi < 0 or not best > 0.0:
            break
        nsupp[nn] = bi
        namp[nn] = best
        nn += 1
    for t in range(nn):
        nsupp[t] = om[nsupp[t]]
    return nn


@njit(cache=True, nogil=True, inline="always")
def change_norm(supp, amp, ns, nsupp, namp, nn, bg, nbg):
    """(||x_k - x_{k-1}||^2 over the union of the two supports, ||x_k||^2)."""
    diff = (nbg - bg) * (nbg - bg)
    for t in range(nn):
        prev = 0.0
        for s in range(ns):
            if supp[s] == nsupp[t]:
                prev = amp[s]
        diff += (namp[t] - prev) * (namp[t] - prev)
    for s in range(ns):
        if not _among(supp[s], nsupp, nn):
            diff += amp[s] * amp[s]
    xnorm2 = nbg * nbg
    for t in range(nn):
        xnorm2 += namp[t] * namp[t]
    return diff, xnorm2


@njit(cache=True, nogil=True, _nrt=False, **INNER)
def _iterate(ns, bg, ntot, niv, tabs, scr):
    """One iteration of the pursuit from the support (scr.supp[:ns], scr.amp[:ns]) and background
    bg: the proxy's largest entry joins the support, least squares on it, the largest positive
    coefficient kept (T_0). Returns (ns, bg, converged, clipped): the new support in scr, whether
    the change passed delta, whether the least squares had a negative coefficient."""
    T, S = tabs, scr
    S.newi[0] = uos1_argmax(S.cvec, T.colsum, T.cmin, bg * T.inv_gmax, ns, S.supp[0] if ns > 0 else 0,
                            S.amp[0] * T.inv_g2 if ns > 0 else 0.0, T.acorr, T.nk, T.m, T.pp, T.off,
                            S.ivlo, S.ivhi, niv)
    nd = union_support(S.newi, 1, S.supp, ns, S.om)
    clipped = solve_support(S.om, nd, S.cvec, T.colsum, ntot, T.m, T.pp, T.off, T.nk, T.inv_gmax, T.inv_g2,
                            S.gram, S.rhs, S.work, S.vecs, S.vals, S.sol)
    nn = keep_largest(S.sol, nd, 1, S.om, S.nsupp, S.namp)
    nbg = S.sol[nd] if S.sol[nd] > 0.0 else 0.0
    diff, xnorm2 = change_norm(S.supp, S.amp, ns, S.nsupp, S.namp, nn, bg, nbg)
    for t in range(nn):
        S.supp[t] = S.nsupp[t]
        S.amp[t] = S.namp[t]
    # relative for large x: the paper's absolute test (peak-1 columns) reads a change of 1e-2 in an
    # amplitude of 10^4 as not converged, so high-count pixels hit the cap
    return nn, nbg, diff < T.delta * max(1.0, xnorm2), clipped


# inlined into _uos_pixels, its one caller, as ml_pixel is into _ml_pixels: a compiled level of its
# own optimised and emitted the whole pursuit twice on a cold cache
@njit(cache=True, nogil=True, _nrt=False, inline="always")
def uos_pixel(kb, kw, nu, tabs, scr):
    """Algorithm 1 on one pixel's distinct bins kb[:nu] (counts kw): (shift, amp, bg, iterations,
    converged); shift NaN when no return is kept (or no photon), amp on the unit-area pulse."""
    T, S = tabs, scr
    if nu == 0:
        return np.nan, 0.0, 0.0, 0, True
    ntot = 0.0
    for u in range(nu):
        ntot += kw[u]
    # cvec is all zero between pixels: only the photon intervals are touched, reset below
    niv = photon_intervals(kb, nu, T.nk - 1 - T.off, T.off, T.m, S.ivlo, S.ivhi)
    uos_scatter(kb, kw, nu, S.cvec, T.grev, T.inv_gmax, T.nk, T.off, T.m)
    ns = ZERO
    bg = 0.0
    it = 0
    clipped = False
    conv = False
    while it < T.max_iter and not conv:
        it += 1
        ns, bg, conv, clipped = _iterate(ns, bg, ntot, niv, T, S)
    if clipped:
        ns, bg = refit_nonneg(S.supp, S.amp, ns, bg > 0.0, S.cvec, T.colsum, ntot, T.m, T.pp, T.off, T.nk,
                              T.inv_gmax, T.inv_g2, S.gram, S.rhs, S.work, S.vecs, S.vals, S.sol)
    for t in range(niv):
        S.cvec[S.ivlo[t]:S.ivhi[t] + 1] = 0.0
    if ns >= 1:
        return float(S.supp[0]), S.amp[0] * T.inv_gmax, bg, it, conv
    return np.nan, 0.0, bg, it, conv


@njit(cache=True, nogil=True, _nrt=False)
def _uos_pixels(ph, tabs, px, scr, out_shift, out_amp, out_bg, out_iter, out_conv, out_n):
    """Every pixel of ph with the scratch px and scr (it allocates nothing: compiled without
    numba's reference counting, as uos_pixel is)."""
    for p in range(ph.offsets.size - 1):
        nu, out_n[p] = pixel_bins(ph, p, px)
        out_shift[p], out_amp[p], out_bg[p], out_iter[p], out_conv[p] = uos_pixel(px.kb, px.kw, nu, tabs, scr)


def uos_kernel(ph, tabs, maxn, out_shift, out_amp, out_bg, out_iter, out_conv, out_n):
    """Union-of-subspaces greedy pursuit (Algorithm 1) per pixel of ph (:class:`recon.kernels.Photons`,
    at most maxn detections a pixel) with :class:`UosTables`. Outputs per pixel p: out_shift
    (bins, float; NaN none), out_amp (amplitude on the unit-area kernel: expected signal detections
    of an unclipped pulse), out_bg (background per bin), out_iter (iterations), out_conv
    (converged), out_n (photons). Its variance is the caller's (a matched filter's, from these).
    Releases the GIL. The scratch is allocated here, so that the compiled loop is the function
    called from Python (see :func:`.ml_kernels.ml_kernel`: one level of compiled calls fewer)."""
    _uos_pixels(ph, tabs, pixel_scratch(maxn, tabs.m), uos_scratch(maxn, tabs.m), out_shift, out_amp, out_bg,
                out_iter, out_conv, out_n)
