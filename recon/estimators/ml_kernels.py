"""Numba kernels of ml (:mod:`.ml`): the exact Poisson ML over (shift, a >= 0, B >= 0), global over all
integer shifts, refined to 1/fsteps bin and then by a parabola; the likelihood and its bounds are
:mod:`.ml_bounds`'.

Branch and bound, exact: for every shift, U(i) = sum_u w_u max(log(g_u / C_i), -log M) (+ const)
bounds the profile likelihood from above (split the linear term a C + B M evenly over the photons
and maximise each photon's term alone), and only offsets d with g[d] M > min C (dlo..dhi)
contribute above the floor, so U is built over the photons' reach only (intervals of shifts, not
all M: :func:`_upper_bounds`). After the best bound's shift is solved (:func:`_first_solve`), the
shifts whose U beats it get the tangent bound of a Newton pass at about that solve's share (a
bound, by concavity in the signal share): read from tables for interior shifts
(``share_bound``), in sweeps over runs of nearby shifts at the window's edges (``mix_bounds``)
(:func:`_survivors`, :func:`_tighten`); shifts are then solved best bound first and the search
stops at the first bound that cannot beat the best likelihood found (:func:`_solve_best_first`);
each solve also stops after its first Newton pass when its own tangent cannot beat it. The best
1/fsteps shift within a bin of the integer optimum: for any pulse, every fine shift gets its
tangent bound in one sweep too and they are solved best bound first under the same test
(:func:`_fine_sweep`); with ``fine_climb`` (a smooth pulse, see ML_CLIMB_RMS_BINS) a climb from
the integer optimum while the exact likelihood rises finds it with fewer solves
(:func:`_fine_climb`). Then a parabola through its exact neighbours (:func:`_parabola`), and the
variance from the Fisher table (``recon.kernels.fisher_tab``).

:func:`ml_kernel` (the scratch, :func:`ml_scratch`; recon.pixelwise.over_threads shares a fit's pixels among
threads) -> :func:`_ml_pixels` (the compiled loop) -> :func:`ml_pixel` -> the helpers above.
"""

from __future__ import annotations

import math
from collections import namedtuple

import numpy as np
from numba import njit

from spdepth.recon.estimators.ml_bounds import (ML_SHARE_CLAMP, ML_SHARES, _ml_at_fine, _ml_at_int, _photon_range,
                                                mix_bounds, share_bound, share_diffs, share_sweep, share_tables,
                                                swept_bound)
from spdepth.recon.kernels import (INNER, ZERO, fisher_tab, photon_intervals, pixel_bins, pixel_scratch,
                                   sort_desc)

#: ml: logliks within this share of each other are a tie (the pulse on either of two lone
#: detections gives an exact one, which solves from different starts leave ~1e-16 apart), settled
#: for the latest of the tied integer shifts, as the exhaustive scan upwards settled them: a shift
#: whose bound could tie the best is solved, not pruned. (The likelihood cannot tell tied shifts
#: apart; which one is reported moves the error of 2-detection pixels with the scene: on the bench
#: report's bust at SBR 10, the earliest gave 30.7 cm MAE at 2 detections per pixel, the latest
#: 12.7, because its background comes before the bust more often than after.)
ML_TIE = 1e-13

#: ml: the first solve's Newton starts at a share in [ML_START_CLAMP, 1 - ML_START_CLAMP]
ML_START_CLAMP = 0.02
#: ml: when more shifts survive U than this many per distinct detection bin, the interior ones read
#: their tabulated bounds from sums built for every shift at once (:func:`share_sweep`): a
#: detection's sweep costs about what eight survivors' reads do (measured: SBR 0.1, 30 detections
#: a pixel 33k -> 39k pixels/s; 2 and 4 a survivor lost at SBR 1)
ML_SWEEP_PER_DETECTION = 8

#: ml: surviving shifts get their bounds in runs at most ML_RUN long whose neighbours are at most
#: ML_RUN_GAP apart (at the window's edges :func:`mix_bounds` sweeps the shifts between them too)
ML_RUN = 32
ML_RUN_GAP = 4

#: ml: on a log-concave pulse at least this wide (RMS, bins) the best fine shift is found by a climb
#: from the integer optimum (:func:`ml_kernel`'s ``fine_climb``): the likelihood over the fine
#: shifts within a bin has one peak there. Measured against the search of every fine shift, on
#: 30,000 simulated pixels per width (2-60 detections, SBR 0.3-30, sub-bin returns): a different
#: shift on 4 pixels at 1 bin RMS (up to 0.73 bin: two peaks), on none at 1.5, 2, 3, 4 and 9 bins
#: (tests/test_recon_kernels.py checks it at this width). On a narrower pulse, or one that is not
#: log-concave, every fine shift is searched.
ML_CLIMB_RMS_BINS = 2.0


#: ml's tables (:func:`ml_tables`). m bins, uni = 1 / m, logm = log m; the unit-area pulse g with its
#: peak at offset off (nk = g.size), log g (logg_int, -inf where 0), its column sums colsum, their
#: logs and reciprocals, g reversed (grev); the offsets dlo..dhi whose U term can beat the floor;
#: the fine table (fsteps steps a bin), its column sums, their reciprocals, reversed (fine_rev);
#: fine_climb (see ML_CLIMB_RMS_BINS); the share tables stabs and their sweep rows sdiff; dg and
#: the Fisher table ftab (the variance); the interior shifts [ia, ib] (the column wholly inside the
#: window) and there the bound's term by offset, upos.
MlTables = namedtuple("MlTables", [
    "m", "uni", "logm", "g", "off", "nk", "logg_int", "dlo", "dhi", "colsum", "log_colsum", "inv_colsum",
    "grev", "fine", "fine_colsum", "inv_fine_colsum", "fine_rev", "fsteps", "fine_climb", "stabs", "sdiff",
    "dg", "ftab", "ia", "ib", "upos"])
#: A block's scratch (:func:`ml_scratch`): the photons' shift intervals (ivlo, ivhi) and the best U
#: of each (ivmax); U - floor by shift (acc, zero between pixels); survivors (surv) and candidates
#: (cand) with their keys; the sums of a sweep (ssum, zero between pixels); the fine shifts'
#: likelihoods (lls) and which are exact; mix_bounds' photon lists (r0s, ws) and bounds (bnd); the
#: fine shifts' order (fidx).
MlScratch = namedtuple("MlScratch", ["ivlo", "ivhi", "ivmax", "acc", "surv", "cand", "key", "ssum", "lls",
                                     "exact", "r0s", "ws", "bnd", "fidx"])


@njit(cache=True, nogil=True)
def ml_tables(g, off, logg_int, dlo, dhi, colsum, log_colsum, fine, fine_colsum, fsteps, fine_climb, dg, ftab):
    """:class:`MlTables` from the pulse kernel's (recon.model.PulseKernel) over the m = colsum.size
    bins of the window."""
    m = colsum.size
    uni = 1.0 / m
    logm = math.log(m)
    # interior shifts [ia, ib]: the column lies inside the window, so its sum is the kernel's whole
    # sum (the same float at every such shift); there the bound's term depends on the offset only:
    # upos[t] = max(term at d = dhi - t, 0), laid out in shift order
    ia = off
    ib = m - g.size + off
    lc_int = log_colsum[off] if 0 <= off < m else 0.0
    for i in range(max(ia, 0), min(ib, m - 1) + 1):
        if log_colsum[i] != lc_int:
            ib = ia - 1     # not a constant run: every photon takes the general path
            break
    upos = np.zeros(max(dhi - dlo + 1, 0))
    for t in range(upos.size):
        v = logg_int[dhi - t + off] - lc_int + logm
        upos[t] = v if v > 0.0 else 0.0
    stabs = share_tables(g, colsum[off] if 0 <= off < m else 1.0, uni, ML_SHARES)
    # the tables of mix_bounds: the pulse tables reversed and the reciprocal column sums
    return MlTables(m, uni, logm, g, off, g.size, logg_int, dlo, dhi, colsum, log_colsum, 1.0 / colsum,
                    g[::-1].copy(), fine, fine_colsum, 1.0 / fine_colsum, fine[::-1].copy(), fsteps, fine_climb,
                    stabs, share_diffs(stabs), dg, ftab, ia, ib, upos)


@njit(cache=True, nogil=True)
def ml_scratch(maxn, tabs):
    """:class:`MlScratch` for pixels of at most maxn detections."""
    n = max(maxn, 1)
    m = tabs.m
    nf = 2 * tabs.fsteps + 1
    return MlScratch(np.empty(n, np.int64), np.empty(n, np.int64), np.empty(n), np.zeros(m), np.empty(m, np.int64),
                     np.empty(m, np.int64), np.empty(m), np.zeros((4, m)), np.empty(nf), np.empty(nf, np.bool_),
                     np.empty(n, np.int64), np.empty(n), np.empty(max(ML_RUN, nf)), np.empty(nf, np.int64))


@njit(cache=True, nogil=True, _nrt=False, error_model="numpy", **INNER)
def _upper_bounds(kb, kw, nu, tabs, acc):
    """U(i) - floor into acc over the shifts i = k - d, d in [dlo, dhi], of the photons."""
    T = tabs
    for u in range(nu):
        k = kb[u]
        wu = kw[u]
        if k - T.dhi >= T.ia and k - T.dlo <= T.ib:
            # all of this photon's shifts have the interior column sum: one contiguous add of the
            # precomputed terms (the same floating-point values; adding 0.0 where a term is not
            # positive leaves acc as the test below would)
            seg = acc[k - T.dhi:k - T.dlo + 1]
            for t in range(seg.size):
                seg[t] += wu * T.upos[t]
        else:
            for d in range(max(T.dlo, k - T.m + 1), min(T.dhi, k) + 1):
                i = k - d
                v = T.logg_int[d + T.off] - T.log_colsum[i] + T.logm
                if v > 0.0:
                    acc[i] += wu * v


@njit(cache=True, nogil=True, _nrt=False, error_model="numpy", **INNER)
def _best_bound(niv, scr):
    """The shift of the best bound (the first of equal ones; -1: none positive), without listing the
    shifts: most of the photons' reach has a positive bound, so a test per shift would be a coin
    flip. Each interval's best goes into scr.ivmax: the survivors are sought only in intervals whose
    best can beat the likelihood found (a lone background detection's reach seldom can)."""
    S = scr
    i1 = np.int64(-1)
    amax = 0.0
    for t in range(niv):
        imax = 0.0
        ii = np.int64(-1)
        for i in range(S.ivlo[t], S.ivhi[t] + 1):
            if S.acc[i] > imax:
                imax = S.acc[i]
                ii = i
        S.ivmax[t] = imax
        if imax > amax:
            amax = imax
            i1 = ii
    return i1


@njit(cache=True, nogil=True, _nrt=False, error_model="numpy", **INNER)
def _first_solve(kb, kw, nu, ntot, i1, tabs):
    """(s, loglik) at the best bound's shift i1. Newton starts at the share of the photons whose
    bound term is positive there (the return's, and the background's under it), not at 1/2: two
    passes fewer."""
    T = tabs
    nsig = 0.0
    for u in range(nu):
        d = kb[u] - i1
        if d >= T.dlo and d <= T.dhi and T.logg_int[d + T.off] - T.log_colsum[i1] + T.logm > 0.0:
            nsig += kw[u]
    s0 = min(max(nsig / ntot, ML_START_CLAMP), 1.0 - ML_START_CLAMP)
    return _ml_at_int(kb, kw, nu, ntot, i1, T.g, T.off, T.colsum, T.uni, s0, -np.inf)


@njit(cache=True, nogil=True, _nrt=False, error_model="numpy", **INNER)
def _survivors(i1, floor_ll, bar, niv, scr):
    """The shifts but i1 whose U could beat bar (the best likelihood less the tie), ascending, into
    scr.surv with their U as key; returns how many."""
    S = scr
    ns = 0
    for t in range(niv):
        if not floor_ll + S.ivmax[t] > bar:
            continue
        for i in range(S.ivlo[t], S.ivhi[t] + 1):
            if i != i1 and S.acc[i] > 0.0 and floor_ll + S.acc[i] > bar:
                S.surv[ns] = i
                ns += 1
                S.key[i] = floor_ll + S.acc[i]
    return ns


@njit(cache=True, nogil=True, _nrt=False, error_model="numpy", **INNER)
def _run_bounds(kb, kw, nu, ntot, t, t2, sweep, js, sj, sb, tabs, scr):
    """Tighten the keys of the survivors surv[t:t2] (a run: ascending, close together) to their
    first-pass tangent bound: from the sweep's sums (interior, ``sweep``), from the share tables
    over the photons that reach the run (interior), or by mix_bounds at share sb (the window's
    edges, where column sums differ)."""
    T, S = tabs, scr
    wa = S.surv[t]
    wb = S.surv[t2 - 1]
    if wa >= T.ia and wb <= T.ib and sweep:
        for tt in range(t, t2):
            i = S.surv[tt]
            S.key[i] = min(S.key[i], swept_bound(S.ssum, i, ntot, T.stabs, js, sj))
    elif wa >= T.ia and wb <= T.ib:
        ua, ub = _photon_range(kb, nu, wa - T.off, wb - T.off + T.nk - 1)
        w_out = ntot
        for u in range(ua, ub):
            w_out -= kw[u]
        for tt in range(t, t2):
            i = S.surv[tt]
            S.key[i] = min(S.key[i], share_bound(kb, kw, ua, ub, w_out, i, T.off, T.stabs, js, sj))
    else:
        mix_bounds(kb, kw, nu, ntot, T.grev, T.off - wa, np.int64(1), ZERO, wb - wa + 1, T.inv_colsum[wa:], T.uni, sb, S.r0s,
                   S.ws, S.bnd)
        for tt in range(t, t2):
            i = S.surv[tt]
            S.key[i] = min(S.key[i], S.bnd[i - wa])


@njit(cache=True, nogil=True, _nrt=False, error_model="numpy", **INNER)
def _tighten(kb, kw, nu, ntot, ns, best_s, bar, tabs, scr):
    """The survivors' keys tightened to the tangent bound of their first Newton pass at about the
    best share so far (much tighter than U, which overshoots the likelihood by a few nats at every
    shift of a return and of a background detection's reach, so most are dropped without a
    solver call): those still above bar into scr.cand; returns how many. Runs of interior shifts
    read it from tables at the tabulated share nearest the best; runs reaching the window's edges
    get it at the best share in one sweep (:func:`_run_bounds`)."""
    T, S = tabs, scr
    nshares = T.stabs.shape[0]
    js = min(int(best_s * nshares), nshares - 1)
    sj = (js + 0.5) / nshares
    sb = min(max(best_s, ML_SHARE_CLAMP), 1.0 - ML_SHARE_CLAMP)
    # many survivors (much background: U overshoots at every shift a detection reaches): the
    # tabulated sums of every interior shift at once, as U's are built, each detection adding its
    # terms over its reach
    sweep = ns > ML_SWEEP_PER_DETECTION * nu
    slo, shi = 0, -1
    if sweep:
        slo, shi = share_sweep(kb, kw, nu, T.off, T.ia, T.ib, T.sdiff, js, S.ssum)
    # else in runs of nearby survivors (ascending), so the photons that reach a run are found once:
    # at SBR 0.1 a shift's reach holds a sixth of a pixel's detections
    nc = ZERO
    t = ZERO           # not a literal 0: _run_bounds would compile a second time for Literal[int](0)
    while t < ns:
        wa = S.surv[t]
        t2 = t + 1
        while t2 < ns and S.surv[t2] - S.surv[t2 - 1] <= ML_RUN_GAP and S.surv[t2] - wa < ML_RUN:
            t2 += 1
        _run_bounds(kb, kw, nu, ntot, t, t2, sweep, js, sj, sb, T, S)
        for tt in range(t, t2):
            i = S.surv[tt]
            if S.key[i] > bar:
                S.cand[nc] = i
                nc += 1
        t = t2
    if sweep:
        S.ssum[:, slo:shi + 1] = 0.0
    return nc


@njit(cache=True, nogil=True, _nrt=False, error_model="numpy", **INNER)
def _solve_best_first(kb, kw, nu, ntot, nc, best_ll, best_i, best_s, tabs, scr):
    """Solve the candidates best key first until a key cannot beat the best likelihood; ties (see
    ML_TIE) go to the latest shift. Returns the best (loglik, shift, share)."""
    T, S = tabs, scr
    sort_desc(S.key, S.cand, nc)
    for t in range(nc):
        i = S.cand[t]
        tie = ML_TIE * max(1.0, abs(best_ll))
        if S.key[i] <= best_ll - tie:
            break
        s, ll = _ml_at_int(kb, kw, nu, ntot, i, T.g, T.off, T.colsum, T.uni, best_s, best_ll - tie)
        if ll > best_ll + tie or (best_i < 0 and ll > best_ll):
            best_ll = ll
            best_i = i
            best_s = s
        elif ll >= best_ll - tie and best_i >= 0 and i > best_i:
            best_ll = max(best_ll, ll)
            best_i = i
            best_s = s
    return best_ll, best_i, best_s


@njit(cache=True, nogil=True, _nrt=False, error_model="numpy", **INNER)
def integer_optimum(kb, kw, nu, ntot, tabs, scr):
    """(loglik, shift, share) of the best integer shift (shift -1: the all-background fit, at the
    floor, wins). Compiled once, on its own (not inlined): ml's pixels and recon.detect's return
    test call this one copy (inlined into both, it compiled twice: 10 s of CPU on a cold cache; a
    wrapper level around it cost another 0.8-1.2 s, each level optimising and emitting the whole
    tree below again)."""
    T, S = tabs, scr
    floor_ll = -ntot * T.logm          # s = 0: all background
    best_ll, best_i, best_s = floor_ll, np.int64(-1), 0.0
    if T.dhi < T.dlo:
        return best_ll, best_i, best_s
    niv = photon_intervals(kb, nu, T.dhi, -T.dlo, T.m, S.ivlo, S.ivhi)
    _upper_bounds(kb, kw, nu, T, S.acc)
    i1 = _best_bound(niv, S)
    if i1 >= 0:
        s, ll = _first_solve(kb, kw, nu, ntot, i1, T)
        if ll > best_ll:
            best_ll, best_i, best_s = ll, i1, s
        # the shifts whose bound beats it or could tie it (see ML_TIE), best bound first
        bar = best_ll - ML_TIE * max(1.0, abs(best_ll))
        ns = _survivors(i1, floor_ll, bar, niv, S)
        nc = _tighten(kb, kw, nu, ntot, ns, best_s, bar, T, S)
        best_ll, best_i, best_s = _solve_best_first(kb, kw, nu, ntot, nc, best_ll, best_i, best_s, T, S)
    for t in range(niv):
        S.acc[S.ivlo[t]:S.ivhi[t] + 1] = 0.0
    return best_ll, best_i, best_s


@njit(cache=True, nogil=True, _nrt=False, inline="always", error_model="numpy")
def _fine_climb(kb, kw, nu, ntot, best_i, qlo, qhi, bll, bs, tabs, scr):
    """The best fine shift q (qlo <= q <= qhi) of a smooth pulse: climb from the integer optimum
    while the likelihood rises, first towards the side the return's detections lean to (their mean
    offset from best_i: the step the other way is then seldom solved for nothing), then the other
    way when the first step did not rise; every step solved exactly (each is a neighbour of the
    next, as the parabola needs). Returns (q, loglik, share)."""
    T, S = tabs, scr
    lean = 0.0
    for u in range(nu):
        d = kb[u] - best_i
        if d >= T.dlo and d <= T.dhi:
            lean += kw[u] * d
    first = 1 if lean >= 0.0 else -1
    bq = 0
    for d in (first, -first):
        q = d
        sprev = bs
        while q >= qlo and q <= qhi:
            # the share moves almost linearly with the shift: starting at the line through the last
            # two steps' shares saves a Newton pass
            s0 = 1.0 if bs == 1.0 else min(max(2.0 * bs - sprev, ML_SHARE_CLAMP), 1.0 - ML_SHARE_CLAMP)
            s, ll = _ml_at_fine(kb, kw, nu, ntot, best_i, q, T.fine, T.off, T.fine_colsum, T.fsteps, T.uni,
                                s0, -np.inf)
            S.lls[q + T.fsteps] = ll
            S.exact[q + T.fsteps] = True
            if not ll > bll + ML_TIE * max(1.0, abs(bll)):
                break
            bll = ll
            bq = q
            sprev = bs
            bs = s
            q += d
        if bq != 0:
            break
    return bq, bll, bs


@njit(cache=True, nogil=True, _nrt=False, inline="always", error_model="numpy")
def _fine_sweep(kb, kw, nu, ntot, best_i, qlo, qhi, bll, bs, tabs, scr):
    """The best fine shift for any pulse: every fine shift's first-pass bound in one sweep, solved
    best bound first (the optimum usually comes first, and its likelihood then cuts the rest); ties
    as a scan upwards from qlo would take them (0, else the smallest q). Returns (q, loglik, share)."""
    T, S = tabs, scr
    nq = qhi - qlo + 1
    sb = min(max(bs, ML_SHARE_CLAMP), 1.0 - ML_SHARE_CLAMP)
    mix_bounds(kb, kw, nu, ntot, T.fine_rev, T.off - best_i, T.fsteps, qlo, nq,
               T.inv_fine_colsum[best_i * T.fsteps + qlo:], T.uni, sb, S.r0s, S.ws, S.bnd)
    nfc = ZERO
    for t in range(nq):
        if qlo + t != 0:
            S.fidx[nfc] = t
            nfc += 1
    sort_desc(S.bnd, S.fidx, nfc)
    bq = 0
    for a in range(nfc):
        t = S.fidx[a]
        q = qlo + t
        tie = ML_TIE * max(1.0, abs(bll))
        if S.bnd[t] <= bll - tie:
            break
        s, ll = _ml_at_fine(kb, kw, nu, ntot, best_i, q, T.fine, T.off, T.fine_colsum, T.fsteps, T.uni, bs,
                            bll - tie)
        S.lls[q + T.fsteps] = ll
        S.exact[q + T.fsteps] = ll > -np.inf
        if ll > bll + tie:
            bll = ll
            bq = q
            bs = s
        elif ll >= bll - tie and q > bq:
            bll = max(bll, ll)
            bq = q
            bs = s
    return bq, bll, bs


@njit(cache=True, nogil=True, _nrt=False, inline="always", error_model="numpy")
def _parabola(kb, kw, nu, ntot, best_i, bq, bs, qlo, qhi, tabs, scr):
    """The vertex offset (fine steps, within half a step) of the parabola through the best fine
    shift bq and its exact neighbours (solved here when the search did not); 0 at an end."""
    T, S = tabs, scr
    if not (bq - 1 >= qlo and bq + 1 <= qhi):
        return 0.0
    for q in (bq - 1, bq + 1):
        if not S.exact[q + T.fsteps]:
            s, ll = _ml_at_fine(kb, kw, nu, ntot, best_i, q, T.fine, T.off, T.fine_colsum, T.fsteps, T.uni, bs,
                                -np.inf)
            S.lls[q + T.fsteps] = ll
    lm = S.lls[bq - 1 + T.fsteps]
    l0 = S.lls[bq + T.fsteps]
    lp = S.lls[bq + 1 + T.fsteps]
    den = lm - 2.0 * l0 + lp
    frac = 0.0
    if den < 0.0:
        frac = 0.5 * (lm - lp) / den
        frac = min(max(frac, -0.5), 0.5)
    return frac


@njit(cache=True, nogil=True, _nrt=False, inline="always", error_model="numpy")
def ml_pixel(kb, kw, nu, tabs, scr):
    """Exact Poisson ML on one pixel's distinct bins kb[:nu] (counts kw), nu > 0: (shift, amp, bg,
    var, gain); shift and var NaN and amp 0 when the all-background fit wins (or there is no
    photon). gain: the best integer shift's log-likelihood beyond the all-background fit's (nats,
    0 when that wins), the statistic of recon.detect's return test, which takes it from here."""
    T, S = tabs, scr
    if nu == 0:
        return np.nan, 0.0, 0.0, np.nan, 0.0
    ntot = 0.0
    for u in range(nu):
        ntot += kw[u]
    best_ll, best_i, best_s = integer_optimum(kb, kw, nu, ntot, T, S)
    if best_i < 0 or best_s <= 0.0:
        return np.nan, 0.0, ntot * T.uni, np.nan, 0.0
    # sub-bin: the best of the fine shifts strictly between the integer neighbours, then a parabola
    # through its exact neighbours
    fs = T.fsteps
    qlo = -fs if best_i > 0 else 0
    qhi = fs if best_i < T.m - 1 else 0
    S.lls[fs] = best_ll
    S.exact[:] = False
    S.exact[fs] = True
    if T.fine_climb:
        bq, bll, bs = _fine_climb(kb, kw, nu, ntot, best_i, qlo, qhi, best_ll, best_s, T, S)
    else:
        bq, bll, bs = _fine_sweep(kb, kw, nu, ntot, best_i, qlo, qhi, best_ll, best_s, T, S)
    frac = _parabola(kb, kw, nu, ntot, best_i, bq, bs, qlo, qhi, T, S)
    tau = best_i + (bq + frac) / fs
    tau = min(max(tau, 0.0), T.m - 1.0)
    c = T.fine_colsum[best_i * fs + bq]
    a = bs * ntot / c
    bg = (1.0 - bs) * ntot * T.uni
    gain = best_ll + ntot * T.logm
    return tau, a, bg, fisher_tab(int(tau + 0.5), a, bg, T.m, T.g, T.dg, T.off, T.ftab), gain


@njit(cache=True, nogil=True, _nrt=False, error_model="numpy")
def _ml_pixels(ph, tabs, px, scr, out_shift, out_amp, out_bg, out_var, out_n, out_gain):
    """Every pixel of ph with the scratch px and scr: the per-pixel helpers are inlined here, into
    a loop compiled without numba's reference counting (it allocates nothing; called per pixel with
    the tables and scratch as named tuples, they took 13% of ml at 15 detections)."""
    for p in range(ph.offsets.size - 1):
        nu, out_n[p] = pixel_bins(ph, p, px)
        out_shift[p], out_amp[p], out_bg[p], out_var[p], out_gain[p] = ml_pixel(px.kb, px.kw, nu, tabs, scr)


def ml_kernel(ph, tabs, maxn, out_shift, out_amp, out_bg, out_var, out_n, out_gain):
    """Exact Poisson ML (module docstring) per pixel of ph (:class:`recon.kernels.Photons`, at most
    maxn detections a pixel) with :class:`MlTables`. Outputs: out_shift (bins, NaN none), out_amp
    (unit-area amplitude), out_bg (per bin), out_var (bins^2), out_n (photons), out_gain (nats:
    see :func:`ml_pixel`). Releases the GIL.

    The scratch is allocated here and the loop is the compiled function called from Python: numba
    compiles every function a kernel calls on its own and then optimises and emits the whole call
    tree again at each level above, so a kernel that only allocated and called the loop cost ml's
    cold compile about 3 s (the same speed either way)."""
    _ml_pixels(ph, tabs, pixel_scratch(maxn, tabs.m), ml_scratch(maxn, tabs), out_shift, out_amp, out_bg,
               out_var, out_n, out_gain)
