"""Numba kernel of the K-surface pixelwise estimator (:mod:`recon.estimators.surfaces_fit`): a greedy Poisson pursuit.

Per pixel the model is ``lambda_k = B + sum_r a_r g[k - j_r + off]`` (g: the unit-area response on
the bins, measured from the data, tail and afterpulse bump included, so they are never a surface).
Returns are added one at a time: each candidate shift (one per cluster of detections, aligned on the
response's peak) is screened by the second-order expansion of the log-likelihood it adds; the
SCREEN best are scored exactly (amplitude profiled out by Newton on a concave function), the best
one is refined by a pattern search over shifts, and kept
when its gain exceeds ``gain_min`` nats; then every amplitude and the background are refitted by EM
and every earlier return's shift is re-refined with the others fixed. Plain reference:
``tests/reference.py::multi_return``.

The kernel takes the reference's path (same candidates, Newton's form of step, EM sweeps and
stopping rule); what makes it cheaper leaves every decision unchanged: a shift whose gain an upper
bound puts below the one to beat is not scored exactly (:func:`add_gain`; for a screened candidate
the bound comes from the screen's own sums, :func:`screen_score`), a pattern search never scores a
shift twice (:func:`refine_shift`), each candidate's detections under the pulse are found once per
pixel, not once per round, EM looks the response up once per refit and the rate after it comes from
that table (:func:`irate_table`), a pixel's detections are counted on the window's bins rather than
sorted (:func:`unique_bins`), and the scratch is allocated once per block of pixels. Newton on an
amplitude starts where the caller already is when it can (a neighbouring shift's amplitude, EM's),
the reference from the detections' count: the amplitudes agree to Newton's tolerance. Its
arithmetic differs from the reference's in the last bits only, where it is cheaper: the rate's
inverse is kept per detection (:func:`model_irate`), a gain's logs are summed as the log of one
product (:func:`log_sum`), and the sums over detections are reordered so that they vectorise
(:func:`slopes`, :func:`gather`, :func:`em_refit`). On fixed input that moves a shift on few
pixels, always a weak surface on a flat profile, where a pattern search's local maximum follows the
last bits of the gains it compares: on the real two-surface file with its measured response (the
pulse ~100 bins of 8 ps wide), the rate's inverse, the one product and EM's vectorised sums moved
23 of 5,000 by 1-2 bins, and the reciprocal Newton step with the reordered sums (against the kernel
before them) 23 of 5,000, all on the first surface (2-20 nats), by 1-17 bins, the share of both
surfaces found the same (90.2%).

The helpers a pixel's fit calls allocate nothing and are compiled with ``_nrt=False``, as in
:mod:`recon.kernels` (no atomic reference counting of their array arguments at each call: 4% here).
The pixel loops and what they call are compiled with ``error_model="numpy"`` (as numba compiled the
parallel loops they were before): a division by zero gives inf or NaN instead of raising, so numba adds no
zero-divisor check to each division (4-6% of the K-surface fit at 50 detections per pixel, same
outputs bit for bit).
"""

from __future__ import annotations

import math
from collections import namedtuple

import numpy as np
from numba import njit

from spdepth.recon.kernels import ZERO, marked_in_order, pixel_bins, pixel_scratch, unique_bins

#: Newton steps on a return's amplitude.
NEWTON_STEPS = 12
#: Newton on an amplitude stops at this relative step.
NEWTON_TOL = 1e-7
#: EM sweeps of the amplitudes and background after each added return, at most.
EM_SWEEPS = 12
#: EM stops when no amplitude nor the background changes by more than this (relative).
EM_TOL = 1e-7
#: candidates scored exactly per round: the best by the second-order screen (screen_score).
SCREEN = 4
#: shifts a pattern search remembers as scored (refine_shift); more are scored again (same result).
MEMO = 32
#: add_gain's running product of factors >= 1 is rescaled (exactly, by a power of 2) above this.
PROD_RESCALE = 2.0 ** 512
LN2 = math.log(2.0)
#: EM keeps the background at least this share of the flat fit's (ntot / m): a pixel whose every
#: detection is under a return keeps a rate above 0 where no return reaches (its inverse is taken).
BG_FLOOR_SHARE = 1e-9
#: add_gain's bound must be below the bar by this (relative) to skip the exact gain: far more than
#: the rounding of either, so the skip never changes a comparison.
BAR_MARGIN = 1e-9
#: _pool_pairs' bitmap: one bit a window bin.
ONE_BIT = np.uint64(1)


@njit(cache=True, nogil=True, _nrt=False, inline="always", error_model="numpy")
def first_at_least(kb, nu, v):
    """Index of the first of the sorted kb[:nu] that is >= v (nu when none)."""
    a, z = 0, nu
    while a < z:
        h = (a + z) // 2
        if kb[h] < v:
            a = h + 1
        else:
            z = h
    return a


@njit(cache=True, nogil=True, _nrt=False, inline="always", error_model="numpy")
def near_return(j, shifts, nr, sep_bins, skip):
    """Whether shift j lies within sep_bins of one of shifts[:nr] but shifts[skip] (-1: none)."""
    near = False
    for r in range(nr):
        if r != skip and abs(j - shifts[r]) < sep_bins:
            near = True
    return near


@njit(cache=True, nogil=True, _nrt=False, error_model="numpy", fastmath={"reassoc"})
def slopes(a, c, wk, n):
    """(f'(a), f''(a)) of the gain f of a return of column sum c over the gathered detections
    under it: wk[0, :n] the response values over the model's rate, x_u = g_u / lam_u, wk[1, :n]
    the counts. ``reassoc`` lets the sums vectorise (they are reordered: the last bits differ);
    compiled on its own, not inlined by numba, which would compile it with the caller's flags
    (3% of the K-surface fit)."""
    f1 = -c
    f2 = 0.0
    for i in range(n):
        q = wk[0, i] / (1.0 + a * wk[0, i])
        f1 += wk[1, i] * q
        f2 -= wk[1, i] * q * q
    return f1, f2


@njit(cache=True, nogil=True, _nrt=False, inline="always", error_model="numpy")
def log_sum(a, wk, n):
    """sum_i w_i log(1 + a x_i) over wk (:func:`slopes`), as the log of one product: one log
    instead of one log1p per detection (a third of an exact gain's time), the weights being counts,
    whole numbers; rescaled by exact powers of 2 so that it stays in range. Every factor is >= 1
    and rounded once, so the sum is off by about an ulp per factor in absolute terms (~1e-15 nats
    for tens of detections), as a sum of log1p is: far below BAR_MARGIN and any gain compared."""
    prod = 1.0
    e2 = 0
    for i in range(n):
        f = 1.0 + a * wk[0, i]
        w = wk[1, i]
        if w == 1.0:
            # most bins hold one detection: no loop of unknown length (4% of the K-surface fit)
            prod *= f
        else:
            for _ in range(int(w)):
                prod *= f
                if prod > PROD_RESCALE:
                    prod, e = math.frexp(prod)
                    e2 += e
        if prod > PROD_RESCALE:
            prod, e = math.frexp(prod)
            e2 += e
    return math.log(prod) + e2 * LN2


@njit(cache=True, nogil=True, _nrt=False, error_model="numpy", fastmath={"reassoc"})
def gather(kb, kw, u0, n, ilam, g, lo, wk):
    """wk[0, i] = x = g[kb[u] - lo] / lam_u and wk[1, i] = kw[u] for u = u0 + i, i < n (the
    detections under the pulse placed at bin lo); returns (sum w x, sum w). Every detection in the
    pulse's reach is kept, a zero of the response included (it adds nothing to f and its slopes,
    and only loosens add_gain's bound, which counts it): no test per detection, so it vectorises."""
    s1 = 0.0
    nin = 0.0
    for i in range(n):
        u = u0 + i
        x = g[kb[u] - lo] * ilam[u]
        w = kw[u]
        wk[0, i] = x
        wk[1, i] = w
        s1 += w * x
        nin += w
    return s1, nin


@njit(cache=True, nogil=True, _nrt=False, error_model="numpy")
def add_gain(j, kb, kw, nu, ilam, g, off, colsum, a0, bar, wk):
    """(gain, amplitude) of adding a return at shift j to the model whose rate at the photons' bins is
    lam (ilam = 1 / lam): ``max_a f(a) = sum_u kw_u log(1 + a g_u / lam_u) - a colsum[j]`` over
    a >= 0 (nats), by Newton from a0 when > 0, else from a = (detections under the pulse) /
    colsum[j]. Only the detections under the pulse (kb sorted) enter. wk: scratch (2, >= nu).

    bar: the caller only wants a gain above it (a ``gain > bar`` test); when an upper bound on the
    gain is below it by more than rounding (:data:`BAR_MARGIN`), that bound is returned instead of
    the exact gain, which the test would have rejected too; otherwise Newton goes on from a1, its
    slopes known. The bound, from f at a1 (Newton's start: a0, a neighbouring shift's amplitude,
    when > 0; f concave, its curvature -sum w q^2 shrinking as a grows): when f'(a1) <= 0 the
    optimum a* is below a1, where the curvature is at least f''(a1)'s, so
    ``f(a*) <= f(a1) + f'(a1)^2 / (2 |f''(a1)|)``; when f'(a1) > 0, Jensen on the concave
    q / (1 + d q) gives ``f'(a1 + d) <= S1 / (1 + d S1 / N) - c`` (S1 = f'(a1) + c, N the
    detections under the pulse), so a* <= a1 + N f'(a1) / (c S1) and, f lying under its tangent,
    ``f(a*) <= f(a1) + N f'(a1)^2 / (c S1)``."""
    nk = g.size
    lo = j - off
    hi = lo + nk
    c = colsum[j]
    if c <= 0.0:
        return 0.0, 0.0
    u0 = first_at_least(kb, nu, lo)
    u1 = first_at_least(kb, nu, hi)
    # slope at a = 0 and the start: the detections under the pulse, gathered once for the Newton steps
    n = u1 - u0
    d0, nin = gather(kb, kw, u0, n, ilam, g, lo, wk)
    d0 -= c
    if d0 <= 0.0:
        return 0.0, 0.0
    # Newton starts at a0 when given (a neighbouring shift's amplitude, or this shift's own from EM):
    # 1-2 steps from there against ~5 from the detections' count
    a = a0 if a0 > 0.0 else max(nin / c, 1e-6)
    f1, f2 = slopes(a, c, wk, n)
    if bar > 0.0:
        fa = log_sum(a, wk, n) - a * c
        if f1 <= 0.0:
            ub = fa + f1 * f1 / (-2.0 * f2) if f2 < 0.0 else np.inf
        else:
            ub = fa + nin * f1 * f1 / (c * (f1 + c))
        if ub < bar - BAR_MARGIN * (1.0 + bar):
            return ub, a
    for _ in range(NEWTON_STEPS):
        if f2 >= 0.0:
            break
        # Newton on 1 / phi(a) = 1 / c, phi = f' + c = sum w x / (1 + a x): 1 / phi is nearly linear
        # in a (exactly so for one detection), where phi itself is ~N / a, so plain Newton on f'
        # crept up by doublings from below or overshot below zero from above (4-12 steps from the
        # detections' count, 3-5 now). 1 / phi is concave (a harmonic mean of lines), so every step
        # lands at or below the root and climbs to it: the same root, Newton's step times phi / c
        na = a - f1 / f2 * (f1 + c) / c
        if na <= 0.0:
            na = 0.5 * a
        if abs(na - a) <= NEWTON_TOL * a:
            a = na
            break
        a = na
        f1, f2 = slopes(a, c, wk, n)
    return log_sum(a, wk, n) - a * c, a


@njit(cache=True, nogil=True, _nrt=False, error_model="numpy")
def screen_score(j, kb, kw, u0, u1, ilam, g, off, colsum):
    """(score, N, r) of adding a return at shift j. score: its gain to second order in the
    amplitude at 0, ``d0^2 / (2 c2)`` (slope d0 and curvature c2 there; 0 when the slope is not
    positive), to pick the candidates worth the exact :func:`add_gain`; N (detections under the
    pulse) and r = S1 / c (S1 = d0 + c = sum w x) give an upper bound on the exact gain,
    ``N (log r - 1 + 1 / r)`` (Jensen), which spares a candidate's exact gain when it cannot beat
    the best (about half of those after the first on ``spdepth bench surfaces``' scene). One pass.
    kb[u0:u1]: the detections under the pulse at j; ilam: 1 / the model's rate at the photons."""
    lo = j - off
    c = colsum[j]
    if c <= 0.0:
        return 0.0, 0.0, 0.0
    d0 = -c
    c2 = 0.0
    nin = 0.0
    for u in range(u0, u1):
        gu = g[kb[u] - lo]
        if gu > 0.0:
            q = gu * ilam[u]
            d0 += kw[u] * q
            c2 += kw[u] * q * q
            nin += kw[u]
    if d0 <= 0.0 or c2 <= 0.0:
        return 0.0, 0.0, 0.0
    # Jensen: sum w log(1 + a x) <= N log(1 + a S1 / N), so the gain is at most N (log r - 1 + 1 / r),
    # r = S1 / c (S1 = d0 + c): tight when the x are alike (detections of background)
    return d0 * d0 / (2.0 * c2), nin, (d0 + c) / c


@njit(cache=True, nogil=True, _nrt=False, error_model="numpy")
def refine_shift(j, best, amp, kb, kw, nu, ilam, g, off, colsum, m, step0, shifts, nr, skip, sep_bins, wk, seen,
                 nseen):
    """Pattern search (steps step0, step0/2, ..., 1 bins) for the shift of most gain from j, never
    within sep_bins of shifts[:nr] (but shifts[skip]).

    seen[:nseen]: shifts whose gain on this model (ilam: 1 / its rate) is known not to exceed
    ``best`` (scored before the search). A shift scored once is never scored again: it was either
    below the best at the time or the best that the search left for a higher one, and the best only
    grows, so it could not be taken (the search moves on a strictly higher gain): skipping it leaves
    the path unchanged."""
    if nseen < seen.size:
        seen[nseen] = j
        nseen += 1
    step = step0
    while step >= 1:
        moved = True
        while moved:
            moved = False
            for sgn in (-1, 1):
                jj = j + sgn * step
                if jj < 0 or jj >= m:
                    continue
                near = near_return(jj, shifts, nr, sep_bins, skip)
                for i in range(nseen):
                    if seen[i] == jj:
                        near = True
                if near:
                    continue
                gn, an = add_gain(jj, kb, kw, nu, ilam, g, off, colsum, amp, best, wk)
                if nseen < seen.size:
                    seen[nseen] = jj
                    nseen += 1
                if gn > best:
                    best, amp, j = gn, an, jj
                    moved = True
                    break
        step //= 2
    return j, best, amp


@njit(cache=True, nogil=True, _nrt=False, error_model="numpy")
def model_irate(kb, nu, shifts, amps, nr, bg, g, off, ilam):
    """ilam[u] = 1 / lam_u, lam_u = bg + sum_r amps[r] g[kb_u - shifts[r] + off]: the gains and the
    screen divide by the rate, once per detection and model rather than once per shift tried."""
    nk = g.size
    for u in range(nu):
        v = bg
        for r in range(nr):
            d = kb[u] - shifts[r] + off
            if d >= 0 and d < nk:
                v += amps[r] * g[d]
        ilam[u] = 1.0 / v


@njit(cache=True, nogil=True, _nrt=False, error_model="numpy", fastmath={"reassoc"})
def em_refit(kb, kw, nu, shifts, amps, nr, bg, bg_floor, g, off, colsum, m, ilam, sweeps, gt, newa):
    """EM for the amplitudes and background at fixed shifts (monotone in the likelihood); returns bg
    and leaves ilam at the final model (:func:`model_irate`). gt (>= nr, >= nu), newa (>= nr):
    scratch; the shifts being fixed, every detection's response values are looked up once into gt,
    not once per sweep (zero outside a return's reach, which adds nothing).

    A sweep is loops over the detections, one per quantity (rate, its inverse, each sum), which
    vectorise; ``reassoc`` lets the sums do so too (a fourth of the K-surface fit's time was EM in
    scalar loops). It reorders additions only: the sums differ in the last bits, far below EM_TOL.
    With one or two returns (the usual fits) a sweep is a single loop, the rate, its inverse and
    every sum together (4% of the K-surface fit at K=2); more returns take a loop per quantity, ilam
    holding each detection's count over its rate during the sweeps."""
    nk = g.size
    for r in range(nr):
        for u in range(nu):
            d = kb[u] - shifts[r] + off
            gt[r, u] = g[d] if d >= 0 and d < nk else 0.0
    for _ in range(sweeps):
        if nr <= 2:
            # one or two returns (the usual fits): the rate, its inverse and every sum in one loop
            a0 = amps[0]
            a1 = amps[1] if nr == 2 else 0.0
            g1 = gt[1] if nr == 2 else gt[0]
            g0 = gt[0]
            nb = 0.0
            s0 = 0.0
            s1 = 0.0
            for u in range(nu):
                v = kw[u] / (bg + a0 * g0[u] + a1 * g1[u])
                nb += v
                s0 += g0[u] * v
                s1 += g1[u] * v
            newa[0] = a0 * s0
            if nr == 2:
                newa[1] = a1 * s1
        else:
            rate_table(gt, nu, amps, nr, bg, ilam)
            nb = 0.0
            for u in range(nu):
                ilam[u] = kw[u] / ilam[u]
                nb += ilam[u]
            for r in range(nr):
                sr = 0.0
                for u in range(nu):
                    sr += gt[r, u] * ilam[u]
                newa[r] = amps[r] * sr
        nb *= bg
        change = 0.0
        for r in range(nr):
            na = newa[r] / colsum[shifts[r]]
            change = max(change, abs(na - amps[r]) / max(na, 1e-300))
            amps[r] = na
        nbg = max(nb / m, bg_floor)
        change = max(change, abs(nbg - bg) / nbg)
        bg = nbg
        if change < EM_TOL:
            break
    irate_table(gt, nu, amps, nr, bg, ilam)
    return bg


@njit(cache=True, nogil=True, _nrt=False, error_model="numpy")
def rate_table(gt, nu, amps, nr, bg, lam):
    """lam[u] = bg + sum_r amps[r] gt[r, u]: the model's rate at the detections from
    :func:`em_refit`'s table gt of the response there (valid while the shifts are EM's), in loops
    without a test, which vectorise."""
    for u in range(nu):
        lam[u] = bg
    for r in range(nr):
        a = amps[r]
        for u in range(nu):
            lam[u] += a * gt[r, u]


@njit(cache=True, nogil=True, _nrt=False, error_model="numpy")
def irate_table(gt, nu, amps, nr, bg, ilam):
    """:func:`model_irate` from the table (:func:`rate_table`): the same sums in the same order (gt
    is 0 where model_irate adds nothing), so bit for bit the same."""
    rate_table(gt, nu, amps, nr, bg, ilam)
    for u in range(nu):
        ilam[u] = 1.0 / ilam[u]


@njit(cache=True, nogil=True, _nrt=False, error_model="numpy")
def shift_fisher(r, shifts, amps, nr, bg, g, dg, off, m):
    """Expected Fisher information of return r's shift (1/bins^2) over the window's bins."""
    nk = g.size
    info = 0.0
    lo = shifts[r] - off
    for t in range(nk):
        k = lo + t
        if k < 0 or k >= m:
            continue
        lam = bg
        for s in range(nr):
            d = k - shifts[s] + off
            if d >= 0 and d < nk:
                lam += amps[s] * g[d]
        if lam > 0.0:
            v = amps[r] * dg[t]
            info += v * v / lam
    return info


#: The K-surface fit's tables (:func:`surf_tables`): m bins; the unit-area response g with its peak
#: at offset off, its column sums colsum and derivative dg (:class:`recon.model.PulseKernel`); dpk:
#: the offset of g's peak; surfaces closer than sep_bins are one; one candidate shift per cand_step
#: bins; step0: the pattern search's first step.
SurfTables = namedtuple("SurfTables", ["m", "g", "off", "colsum", "dg", "dpk", "sep_bins", "cand_step", "step0"])
#: Scratch of :func:`fit_pixel` (:func:`fit_work`) for up to n distinct bins and kmax returns: ilam and
#: tmp_ilam (1 / the rate at the detections), cand (candidate shifts), the returns (shifts, amps,
#: gains) and a copy (tmp_s, tmp_a), wk (the gathered detections), EM's gt and newa, the screen's
#: best candidates (top_s: score, N, r; top_j: shift), seen (shifts a pattern search scored), cand_u
#: (each candidate's first and end index of the detections under its pulse).
FitWork = namedtuple("FitWork", ["ilam", "tmp_ilam", "cand", "shifts", "amps", "gains", "tmp_s", "tmp_a", "wk", "gt",
                                 "newa", "top_s", "top_j", "seen", "cand_u"])
#: Per-pixel outputs (P,) or (P, kmax): shift (bins, NaN past the returns), amp (unit-area
#: amplitude), bg (per bin), var (1 / Fisher information, bins^2), gain (nats the return added when
#: taken), n (detections).
SurfOut = namedtuple("SurfOut", ["shift", "amp", "bg", "var", "gain", "n"])
#: The neighbourhood of :func:`neighbour_surfaces`: an h x w image, (2 radius + 1)^2 pixels pooled,
#: a pixel's own surface strong above strong_nats, a pooled one kept above pool_nats (up to kpool),
#: a candidate within tau_bins of a detection.
Neighbourhood = namedtuple("Neighbourhood", ["h", "w", "radius", "strong_nats", "pool_nats", "tau_bins", "kpool"])


@njit(cache=True, nogil=True)
def surf_tables(m, g, off, colsum, dg, sep_bins, cand_step, step0):
    """:class:`SurfTables` of the pulse kernel's g, off, colsum, dg over m bins."""
    return SurfTables(m, g, off, colsum, dg, int(np.argmax(g)), sep_bins, cand_step, step0)


@njit(cache=True, nogil=True, error_model="numpy")
def fit_work(n, kmax):
    """:class:`FitWork` for up to n distinct bins and kmax returns, allocated once per block of pixels."""
    n = max(n, 1)
    k = max(kmax, 1)
    return FitWork(np.empty(n), np.empty(n), np.empty(n, np.int64), np.empty(k, np.int64), np.empty(k),
                   np.empty(k), np.empty(k, np.int64), np.empty(k), np.empty((2, n)), np.empty((k, n)), np.empty(k),
                   np.empty((3, SCREEN)), np.empty(SCREEN, np.int64), np.empty(MEMO, np.int64),
                   np.empty((2, n), np.int64))


@njit(cache=True, nogil=True, _nrt=False, error_model="numpy")
def _candidates(kb, nu, tabs, work):
    """Candidate shifts, the response's peak on a detection, one per cand_step bins, into work.cand,
    and the detections under each candidate's pulse into work.cand_u, once for every round (found
    again in each round, they cost 5% of the fit): candidates ascend, so do both ends. Returns how
    many."""
    T, W = tabs, work
    nc = 0
    for u in range(nu):
        j = kb[u] + T.off - T.dpk
        if j < 0:
            j = 0
        if j >= T.m:
            j = T.m - 1
        if nc == 0 or j - W.cand[nc - 1] >= T.cand_step:
            W.cand[nc] = j
            nc += 1
    nk = T.g.size
    u0 = 0
    u1 = 0
    for c in range(nc):
        j = W.cand[c]
        while u0 < nu and kb[u0] < j - T.off:
            u0 += 1
        while u1 < nu and kb[u1] < j - T.off + nk:
            u1 += 1
        W.cand_u[0, c] = u0
        W.cand_u[1, c] = u1
    return nc


@njit(cache=True, nogil=True, _nrt=False, error_model="numpy")
def _screen(kb, kw, nc, nr, tabs, work):
    """The SCREEN best candidates not within sep_bins of the nr returns, by the second-order screen
    (:func:`screen_score`), into work.top_s / work.top_j (ties keep the earlier candidate first);
    returns how many."""
    T, W = tabs, work
    ns = 0
    for c in range(nc):
        j = W.cand[c]
        if near_return(j, W.shifts, nr, T.sep_bins, -1):
            continue
        sc, nin, ratio = screen_score(j, kb, kw, W.cand_u[0, c], W.cand_u[1, c], W.ilam, T.g, T.off, T.colsum)
        if sc <= 0.0:
            continue
        # insertion into the top list
        t = ns if ns < SCREEN else SCREEN - 1
        if ns == SCREEN and not sc > W.top_s[0, t]:
            continue
        while t > 0 and sc > W.top_s[0, t - 1]:
            W.top_s[0, t] = W.top_s[0, t - 1]
            W.top_s[1, t] = W.top_s[1, t - 1]
            W.top_s[2, t] = W.top_s[2, t - 1]
            W.top_j[t] = W.top_j[t - 1]
            t -= 1
        W.top_s[0, t] = sc
        W.top_s[1, t] = nin
        W.top_s[2, t] = ratio
        W.top_j[t] = j
        if ns < SCREEN:
            ns += 1
    return ns


@njit(cache=True, nogil=True, _nrt=False, error_model="numpy")
def _best_screened(kb, kw, nu, ns, tabs, work):
    """(gain, shift, amplitude) of the best of the ns screened candidates by their exact gains
    (shift -1: none gains); a candidate after the first is skipped when the screen's Jensen bound
    says it cannot beat the best (its exact gain would lose the comparison too)."""
    T, W = tabs, work
    best = 0.0
    bj = -1
    ba = 0.0
    for t in range(ns):
        W.seen[t] = W.top_j[t]
        if t > 0:
            ratio = W.top_s[2, t]
            if W.top_s[1, t] * (math.log(ratio) - 1.0 + 1.0 / ratio) < best - BAR_MARGIN * (1.0 + best):
                continue
        gn, an = add_gain(W.top_j[t], kb, kw, nu, W.ilam, T.g, T.off, T.colsum, 0.0, best, W.wk)
        if gn > best:
            best, bj, ba = gn, W.top_j[t], an
    return best, bj, ba


@njit(cache=True, nogil=True, _nrt=False, error_model="numpy")
def _rerefine(kb, kw, nu, nr, bg, tabs, work):
    """Re-refine each return's shift with the others (and the background) fixed: the rate without
    return r from EM's table of the response at the detections while no shift has moved since."""
    T, W = tabs, work
    fresh = True
    for r in range(nr):
        for s in range(nr):
            W.tmp_s[s] = W.shifts[s]
            W.tmp_a[s] = W.amps[s]
        W.tmp_a[r] = 0.0
        if fresh:
            irate_table(W.gt, nu, W.tmp_a, nr, bg, W.tmp_ilam)
        else:
            model_irate(kb, nu, W.tmp_s, W.tmp_a, nr, bg, T.g, T.off, W.tmp_ilam)
        g0, a0 = add_gain(W.shifts[r], kb, kw, nu, W.tmp_ilam, T.g, T.off, T.colsum, W.amps[r], 0.0, W.wk)
        jn, gn, an = refine_shift(W.shifts[r], g0, a0, kb, kw, nu, W.tmp_ilam, T.g, T.off, T.colsum, T.m, np.int64(2),
                                  W.shifts, nr, r, T.sep_bins, W.wk, W.seen, ZERO)
        if jn != W.shifts[r]:
            fresh = False
        W.shifts[r] = jn
        W.amps[r] = an


@njit(cache=True, nogil=True, _nrt=False, error_model="numpy")
def sort_returns(nr, shifts, amps, gains, src):
    """Sort the nr returns by shift, stably (src: a label per return, moved with them): insertion by
    swaps, a handful of returns."""
    for a in range(1, nr):
        b = a
        while b > 0 and shifts[b - 1] > shifts[b]:
            shifts[b - 1], shifts[b] = shifts[b], shifts[b - 1]
            amps[b - 1], amps[b] = amps[b], amps[b - 1]
            gains[b - 1], gains[b] = gains[b], gains[b - 1]
            src[b - 1], src[b] = src[b], src[b - 1]
            b -= 1


@njit(cache=True, nogil=True, _nrt=False, error_model="numpy")
def fit_pixel(kb, kw, nu, tabs, kmax, gain_min, work):
    """Greedy K-return fit of one pixel's unique bins (kb, kw); returns (nr, bg): work.shifts[:nr]
    (sorted), amps[:nr], gains[:nr] (nats each return added when it was taken)."""
    T, W = tabs, work
    ntot = 0.0
    for u in range(nu):
        ntot += kw[u]
    bg_floor = BG_FLOOR_SHARE * ntot / T.m
    bg = ntot / T.m
    for u in range(nu):
        W.ilam[u] = 1.0 / bg
    nc = _candidates(kb, nu, T, W)
    nr = ZERO
    while nr < kmax:
        ns = _screen(kb, kw, nc, nr, T, W)
        best, bj, ba = _best_screened(kb, kw, nu, ns, T, W)
        if bj < 0:
            break
        bj, best, ba = refine_shift(bj, best, ba, kb, kw, nu, W.ilam, T.g, T.off, T.colsum, T.m, T.step0, W.shifts,
                                    nr, np.int64(-1), T.sep_bins, W.wk, W.seen, ns)
        if not best > gain_min:
            break
        W.shifts[nr] = bj
        W.amps[nr] = ba
        W.gains[nr] = best
        nr += 1
        bg = em_refit(kb, kw, nu, W.shifts, W.amps, nr, bg, bg_floor, T.g, T.off, T.colsum, T.m, W.ilam, EM_SWEEPS,
                      W.gt, W.newa)
        if nr > 1:
            _rerefine(kb, kw, nu, nr, bg, T, W)
            bg = em_refit(kb, kw, nu, W.shifts, W.amps, nr, bg, bg_floor, T.g, T.off, T.colsum, T.m, W.ilam,
                          EM_SWEEPS, W.gt, W.newa)
    sort_returns(nr, W.shifts, W.amps, W.gains, W.tmp_s)
    return nr, bg


@njit(cache=True, nogil=True, _nrt=False, error_model="numpy")
def write_returns(p, nr, bg, tabs, work, out):
    """Pixel p's nr returns (work.shifts, amps, gains) and background into out (:class:`SurfOut`),
    with each shift's variance; NaN / 0 past them."""
    T, W = tabs, work
    kmax = out.shift.shape[1]
    for r in range(kmax):
        out.shift[p, r] = np.nan
        out.amp[p, r] = 0.0
        out.var[p, r] = np.nan
        out.gain[p, r] = 0.0
    out.bg[p] = bg
    for r in range(nr):
        out.shift[p, r] = W.shifts[r]
        out.amp[p, r] = W.amps[r]
        out.gain[p, r] = W.gains[r]
        info = shift_fisher(r, W.shifts, W.amps, nr, bg, T.g, T.dg, T.off, T.m)
        out.var[p, r] = 1.0 / info if info > 0.0 else np.nan


@njit(cache=True, nogil=True, _nrt=False, error_model="numpy")
def _multi_pixels(ph, tabs, kmax, gain_min, px, work, out):
    """Every pixel of ph with the scratch px and work (it allocates nothing)."""
    for p in range(ph.offsets.size - 1):
        nu, out.n[p] = pixel_bins(ph, p, px)
        nr, bg = (ZERO, 0.0) if nu == 0 else fit_pixel(px.kb, px.kw, nu, tabs, kmax, gain_min, work)
        write_returns(p, nr, bg, tabs, work, out)


def multi_return_kernel(ph, tabs, kmax, gain_min, maxn, out):
    """K-return greedy Poisson pursuit over the pixels of ph (:class:`recon.kernels.Photons`, at most
    maxn detections a pixel) with :class:`SurfTables` (see the module docstring): up to kmax returns a
    pixel, each gaining more than gain_min nats, into out (:class:`SurfOut`, sorted by shift).
    Releases the GIL (``recon.pixelwise.over_threads`` shares a fit's pixels among threads); the
    scratch is allocated here, the compiled loop called from Python (no ``parallel=True`` loop,
    whose compile numba pays twice, and one level of compiled calls fewer)."""
    _multi_pixels(ph, tabs, np.int64(kmax), float(gain_min), pixel_scratch(maxn, tabs.m),
                  fit_work(max(maxn, 1), kmax), out)


# ------------------------------------------------------------------------------------------------
# several surfaces with the neighbours' help (recon.estimators.surfaces_fit.reconstruct_multi_spatial)


@njit(cache=True, nogil=True, _nrt=False, error_model="numpy")
def _pool_neighbourhood(ph, p, nb, pbins):
    """The bins of every detection of pixel p's neighbourhood into pbins; returns how many."""
    y0, x0 = p // nb.w, p % nb.w
    n = 0
    for y in range(max(0, y0 - nb.radius), min(nb.h, y0 + nb.radius + 1)):
        for x in range(max(0, x0 - nb.radius), min(nb.w, x0 + nb.radius + 1)):
            q = y * nb.w + x
            for i in range(ph.offsets[q], ph.offsets[q + 1]):
                pbins[n] = ph.bins[i]
                n += 1
    return n


@njit(cache=True, nogil=True, _nrt=False, error_model="numpy")
def _pool_pairs(ph, p, nb, dense, bits, kb, kw):
    """The (bin, count) pairs of pixel p's neighbourhood merged: its distinct bins ascending into
    kb, their summed counts into kw (what unique_bins gives for the detections pooled one by one,
    without them); returns how many. dense (float64, one per window bin) and bits (one bit a bin)
    must be zero, and are left zero."""
    y0, x0 = p // nb.w, p % nb.w
    lo = dense.size
    hi = -1
    for y in range(max(0, y0 - nb.radius), min(nb.h, y0 + nb.radius + 1)):
        for x in range(max(0, x0 - nb.radius), min(nb.w, x0 + nb.radius + 1)):
            q = y * nb.w + x
            for i in range(ph.offsets[q], ph.offsets[q + 1]):
                k = ph.bins[i]
                dense[k] += ph.weights[i]
                bits[k >> 6] |= ONE_BIT << np.uint64(k & 63)
                lo = min(lo, k)
                hi = max(hi, k)
    if hi < 0:
        return ZERO
    return marked_in_order(bits, lo >> 6, hi >> 6, dense, kb, kw)


@njit(cache=True, nogil=True, _nrt=False, error_model="numpy")
def _own_and_pooled(p, shift_in, gain_in, nb, npr, pshift, pamp, cand, csrc):
    """Candidates of pixel p: its own pixelwise surfaces that are strong (csrc 0), then the pooled
    ones by amplitude (csrc 1); returns how many. pamp is spent (set to -1)."""
    nc = 0
    for r in range(shift_in.shape[1]):
        v = shift_in[p, r]
        if v == v and gain_in[p, r] > nb.strong_nats:
            cand[nc] = int(v)
            csrc[nc] = 0
            nc += 1
    for _ in range(npr):
        bi = -1
        for r in range(npr):
            if pamp[r] >= 0.0 and (bi < 0 or pamp[r] > pamp[bi]):
                bi = r
        cand[nc] = pshift[bi]
        csrc[nc] = 1
        nc += 1
        pamp[bi] = -1.0
    return nc


@njit(cache=True, nogil=True, _nrt=False, error_model="numpy")
def _best_candidate(kb, kw, nu, nr, nc, cand, csrc, tabs, tau_bins, work):
    """(gain, shift, amplitude, candidate) of the candidate the pixel's own detections support most:
    the gain at the best detection-aligned shift within tau_bins of it, none within sep_bins of the
    nr returns (candidate -1: none gains)."""
    T, W = tabs, work
    best = 0.0
    bj = -1
    ba = 0.0
    bc = -1
    for c in range(nc):
        if csrc[c] < 0:
            continue
        j0 = cand[c]
        for u in range(nu):
            j = kb[u] + T.off - T.dpk
            if j < 0 or j >= T.m or abs(j - j0) > tau_bins:
                continue
            if near_return(j, W.shifts, nr, T.sep_bins, -1):
                continue
            gn, an = add_gain(j, kb, kw, nu, W.ilam, T.g, T.off, T.colsum, 0.0, best, W.wk)
            if gn > best:
                best, bj, ba, bc = gn, j, an, c
    return best, bj, ba, bc


@njit(cache=True, nogil=True, _nrt=False, error_model="numpy")
def _censored_fit(kb, kw, nu, nc, cand, csrc, tabs, nb, kmax, work, src):
    """Pixel p's surfaces from the candidates: greedily the one its own detections support most
    (:func:`_best_candidate`), refined by pattern search, then amplitudes and background by EM, up
    to kmax; every candidate within sep_bins of the one taken is spent. Returns (nr, bg); src[:nr]
    the candidates' sources."""
    T, W = tabs, work
    ntot = 0.0
    for u in range(nu):
        ntot += kw[u]
    bg_floor = BG_FLOOR_SHARE * ntot / T.m
    nr = 0
    bg = ntot / T.m
    for u in range(nu):
        W.ilam[u] = 1.0 / bg
    while nr < kmax:
        best, bj, ba, c = _best_candidate(kb, kw, nu, nr, nc, cand, csrc, T, nb.tau_bins, W)
        if c < 0:
            break
        bj, best, ba = refine_shift(bj, best, ba, kb, kw, nu, W.ilam, T.g, T.off, T.colsum, T.m, T.step0, W.shifts,
                                    nr, np.int64(-1), T.sep_bins, W.wk, W.seen, ZERO)
        for d in range(nc):
            if csrc[d] >= 0 and abs(cand[d] - cand[c]) < T.sep_bins and d != c:
                csrc[d] = -1
        W.shifts[nr] = bj
        W.amps[nr] = ba
        W.gains[nr] = best
        src[nr] = csrc[c]
        csrc[c] = -1
        nr += 1
        bg = em_refit(kb, kw, nu, W.shifts, W.amps, nr, bg, bg_floor, T.g, T.off, T.colsum, T.m, W.ilam, EM_SWEEPS,
                      W.gt, W.newa)
    sort_returns(nr, W.shifts, W.amps, W.gains, src)
    return nr, bg


@njit(cache=True, nogil=True, error_model="numpy")
def neighbour_surfaces(ph, shift_in, gain_in, nb, tabs, maxn, out, out_src, p_start, p_stop):
    """Each pixel's surfaces with its neighbours' help (:class:`Neighbourhood` nb).

    shift_in, gain_in: (P, K) the pixelwise fit (NaN / 0 past the surfaces found). Per pixel:
    1. the detections of its (2 radius + 1)^2 neighbourhood pooled and fitted by the greedy pursuit
       (up to kpool surfaces, each raising the pooled likelihood by more than pool_nats): the
       surfaces the neighbourhood supports;
    2. the pixel's surfaces, from the candidates: its own pixelwise surfaces that are strong
       (gain > strong_nats, not chance even alone) and the pooled surfaces. Greedily, the candidate
       whose best shift within tau_bins (the response peak on each of the pixel's detections there,
       refined by pattern search) raises the pixel's likelihood most is kept, then amplitudes and
       background by EM, up to kmax (out's), none closer than sep_bins to another. A candidate needs
       at least one of the pixel's detections within tau_bins (censoring: a detection the
       neighbourhood supports in time is signal; a pixel that sees none of a surface does not get
       it).
    Outputs as multi_return_kernel's (out.n untouched); out_src[p, r]: 0 the pixel's own strong
    surface, 1 from the neighbourhood's pooled fit, -1 none. Only the pixels p_start <= p < p_stop
    are fitted (their neighbours' detections come from the whole image): the caller goes through the
    image in slices, each shared among threads (it releases the GIL; no ``parallel=True`` loop, whose
    compile numba pays twice), and reports progress between them."""
    kmax = out.shift.shape[1]
    npool = max((2 * nb.radius + 1) * (2 * nb.radius + 1) * maxn, 1)
    pbins = np.empty(npool, np.int64)
    ppx = pixel_scratch(npool, tabs.m)
    pdense = np.zeros(tabs.m)
    pwork = fit_work(npool, nb.kpool)
    px = pixel_scratch(maxn, tabs.m)
    work = fit_work(max(maxn, 1), kmax)
    cand = np.empty(shift_in.shape[1] + nb.kpool, np.int64)
    csrc = np.empty(shift_in.shape[1] + nb.kpool, np.int64)
    src = np.empty(kmax, np.int64)
    for p in range(p_start, p_stop):
        nu, _ = pixel_bins(ph, p, px)
        nr, bg = ZERO, 0.0
        if nu > 0:
            # 1. the neighbourhood's pooled fit; 2. candidates: own strong surfaces, then pooled ones
            if ph.weights.size == 0:
                n = _pool_neighbourhood(ph, p, nb, pbins)
                pnu = unique_bins(pbins, ZERO, n, ppx.tally, ppx.bits, ppx.tmp, ppx.kb, ppx.kw)
            else:
                pnu = _pool_pairs(ph, p, nb, pdense, ppx.bits, ppx.kb, ppx.kw)
            npr, _ = fit_pixel(ppx.kb, ppx.kw, pnu, tabs, nb.kpool, nb.pool_nats, pwork)
            nc = _own_and_pooled(p, shift_in, gain_in, nb, npr, pwork.shifts, pwork.amps, cand, csrc)
            nr, bg = _censored_fit(px.kb, px.kw, nu, nc, cand, csrc, tabs, nb, kmax, work, src)
        write_returns(p, nr, bg, tabs, work, out)
        for r in range(kmax):
            out_src[p, r] = src[r] if r < nr else -1


@njit(cache=True, nogil=True)
def smooth_surfaces(shift, sig, var, h, w, radius, tau_bins, out_shift, out_var):
    """Weighted smoothing per surface that keeps edges: each surface's shift becomes the mean of the
    surfaces within tau_bins of it in its (2 radius + 1)^2 neighbourhood (itself included), weighted
    by their signal counts; surfaces farther than tau_bins (another surface, or the other side of an
    edge) do not enter. out_var: the weighted mean's variance, sum(w^2 var) / (sum w)^2, never
    above the surface's own."""
    npix = shift.shape[0]
    kk = shift.shape[1]
    for p in range(npix):
        y0, x0 = p // w, p % w
        for r in range(kk):
            s = shift[p, r]
            out_shift[p, r] = s
            out_var[p, r] = var[p, r]
            if s != s:
                continue
            sw = 0.0
            sws = 0.0
            swv = 0.0
            for y in range(max(0, y0 - radius), min(h, y0 + radius + 1)):
                for x in range(max(0, x0 - radius), min(w, x0 + radius + 1)):
                    q = y * w + x
                    for t in range(kk):
                        v = shift[q, t]
                        if v == v and abs(v - s) <= tau_bins and sig[q, t] > 0.0:
                            wt = sig[q, t]
                            sw += wt
                            sws += wt * v
                            vv = var[q, t]
                            swv += wt * wt * (vv if vv == vv else 0.0)
            if sw > 0.0:
                out_shift[p, r] = sws / sw
                mv = swv / (sw * sw)
                if mv < var[p, r] or var[p, r] != var[p, r]:
                    out_var[p, r] = mv
