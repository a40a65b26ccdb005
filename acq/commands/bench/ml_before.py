"""The ml kernel as it was before issue 18 (main at 76204b1), kept verbatim so that
``spdepth bench recon`` can time it side by side with today's :func:`recon.kernels.ml_kernel` in one
run (the machine's load moves absolute figures, not a ratio measured within one run). Not used by
any estimator."""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from spdepth.recon.kernels import BLOCK, fisher_var, unique_counts


@njit(cache=True, nogil=True)
def mix_ml(r, w, n_in, w_out, uni, s0):
    """max over s in [0, 1] of sum_u w_u log((1 - s) uni + s r_u): the Poisson likelihood of eq. (9)
    with (a, B) profiled onto a C + B M = n (where its maximum lies), s = a C / n the signal share,
    r_u = g_u / C the pulse's density at photon u, uni = 1 / M. Concave in s: safeguarded Newton.

    Only the n_in photons under the pulse are listed (r[:n_in], w[:n_in]); the weight w_out of all
    others (r = 0) enters as one term, so a call costs O(pulse support), not O(photons).
    Returns (s, loglik)."""
    d0 = -w_out * uni
    zero_r = w_out > 0.0
    for u in range(n_in):
        d0 += w[u] * (r[u] - uni)
        if r[u] <= 0.0:
            zero_r = True
    if d0 <= 0.0:
        ll = w_out
        for u in range(n_in):
            ll += w[u]
        return 0.0, ll * math.log(uni)
    if not zero_r:
        d1 = 0.0
        for u in range(n_in):
            d1 += w[u] * (r[u] - uni) / r[u]
        if d1 >= 0.0:
            ll = 0.0
            for u in range(n_in):
                ll += w[u] * math.log(r[u])
            return 1.0, ll
    lo = 0.0
    hi = 1.0
    s = s0
    if not (s > 0.0 and s < 1.0):
        s = 0.5
    for _ in range(60):
        e = -uni
        q = e / (uni + s * e)
        f1 = w_out * q
        f2 = w_out * q * q
        for u in range(n_in):
            e = r[u] - uni
            q = e / (uni + s * e)
            f1 += w[u] * q
            f2 += w[u] * q * q
        if f1 > 0.0:
            lo = s
        else:
            hi = s
        sn = s + f1 / f2 if f2 > 0.0 else 0.5 * (lo + hi)
        if not (sn > lo and sn < hi):
            sn = 0.5 * (lo + hi)
        if abs(sn - s) < 1e-12:
            s = sn
            break
        s = sn
        if hi - lo < 1e-14:
            break
    ll = w_out * math.log(uni - s * uni) if w_out > 0.0 else 0.0
    for u in range(n_in):
        ll += w[u] * math.log(uni + s * (r[u] - uni))
    return s, ll


@njit(cache=True, nogil=True)
def _photon_range(kb, nu, lo, hi):
    """[ua, ub): the sorted distinct photon bins kb[:nu] lying in [lo, hi] (binary search)."""
    ua = np.searchsorted(kb[:nu], lo, side="left")
    ub = np.searchsorted(kb[:nu], hi, side="right")
    return ua, ub


@njit(cache=True, nogil=True)
def _ml_at_int(kb, kw, nu, wtot, i, g, off, colsum, uni, s0, r):
    nk = g.size
    c = colsum[i]
    # photons under column i: offset d = k - i + off in [0, nk)
    ua, ub = _photon_range(kb, nu, i - off, i - off + nk - 1)
    w_in = 0.0
    for u in range(ua, ub):
        r[u - ua] = g[kb[u] - i + off] / c
        w_in += kw[u]
    return mix_ml(r, kw[ua:ub], ub - ua, wtot - w_in, uni, s0)


@njit(cache=True, nogil=True)
def _ml_at_fine(kb, kw, nu, wtot, i, q, fine, off, fine_colsum, fsteps, uni, s0, r):
    """Profile at shift i + q / fsteps (|q| <= fsteps), from the fine kernel table."""
    nf = fine.size
    nk = (nf - 1) // fsteps + 1
    c = fine_colsum[i * fsteps + q]
    # fine index (k - i + off) * fsteps - q lies in [0, nf) only for k - i + off in [-1, nk]
    ua, ub = _photon_range(kb, nu, i - off - 1, i - off + nk)
    w_in = 0.0
    for u in range(ua, ub):
        j = (kb[u] - i + off) * fsteps - q
        r[u - ua] = fine[j] / c if (j >= 0 and j < nf) else 0.0
        w_in += kw[u]
    return mix_ml(r, kw[ua:ub], ub - ua, wtot - w_in, uni, s0)


@njit(parallel=True, cache=True, nogil=True)
def ml_kernel(bins, offsets, m, g, off, logg_int, dlo, dhi, colsum, log_colsum, fine, fine_colsum,
              fsteps, dg, maxn, out_shift, out_amp, out_bg, out_var, out_n):
    """Exact Poisson ML over (shift, a >= 0, B >= 0), global over all integer shifts, refined to
    1/fsteps bin and then by a parabola.

    Pruning is exact: for every shift, U(i) = sum_u w_u max(log(g_u / C_i), -log M) (+ const) bounds
    the profile likelihood from above (split the linear term a C + B M evenly over the photons and
    maximise each photon's term alone), and only offsets d with g[d] M > min C (dlo..dhi) contribute
    above the floor. Shifts whose bound cannot beat the best likelihood found are skipped.
    Outputs: out_shift (bins, NaN none), out_amp (unit-area amplitude), out_bg (per bin),
    out_var (bins^2), out_n (photons).
    """
    npix = offsets.size - 1
    nblk = (npix + BLOCK - 1) // BLOCK
    uni = 1.0 / m
    logm = math.log(m)
    for blk in prange(nblk):
        tmp = np.empty(max(maxn, 1), np.int64)
        kb = np.empty(max(maxn, 1), np.int64)
        kw = np.empty(max(maxn, 1), np.float64)
        r = np.empty(max(maxn, 1), np.float64)
        acc = np.empty(m)
        lls = np.empty(2 * fsteps + 1)
        for p in range(blk * BLOCK, min(npix, (blk + 1) * BLOCK)):
            o0 = offsets[p]
            o1 = offsets[p + 1]
            out_n[p] = o1 - o0
            out_shift[p] = np.nan
            out_amp[p] = 0.0
            out_var[p] = np.nan
            nu = unique_counts(bins, o0, o1, tmp, kb, kw)
            if nu == 0:
                out_bg[p] = 0.0
                continue
            ntot = 0.0
            for u in range(nu):
                ntot += kw[u]
            for i in range(m):
                acc[i] = 0.0
            for u in range(nu):
                k = kb[u]
                for d in range(dlo, dhi + 1):
                    i = k - d
                    if i < 0 or i >= m:
                        continue
                    v = logg_int[d + off] - log_colsum[i] + logm
                    if v > 0.0:
                        acc[i] += kw[u] * v
            floor_ll = -ntot * logm          # s = 0: all background
            best_ll = floor_ll
            best_i = -1
            best_s = 0.0
            i1 = 0
            for i in range(1, m):
                if acc[i] > acc[i1]:
                    i1 = i
            if acc[i1] > 0.0:
                s, ll = _ml_at_int(kb, kw, nu, ntot, i1, g, off, colsum, uni, 0.5, r)
                if ll > best_ll:
                    best_ll = ll
                    best_i = i1
                    best_s = s
            for i in range(m):
                if i == i1 or floor_ll + acc[i] <= best_ll + 1e-12 * abs(best_ll):
                    continue
                s, ll = _ml_at_int(kb, kw, nu, ntot, i, g, off, colsum, uni, best_s, r)
                if ll > best_ll:
                    best_ll = ll
                    best_i = i
                    best_s = s
            if best_i < 0 or best_s <= 0.0:
                out_bg[p] = ntot * uni
                continue
            # sub-bin: best of the fine shifts strictly between the integer neighbours, then a parabola
            qlo = -fsteps if best_i > 0 else 0
            qhi = fsteps if best_i < m - 1 else 0
            bq = 0
            bll = best_ll
            bs = best_s
            lls[fsteps] = best_ll
            for q in range(qlo, qhi + 1):
                if q == 0:
                    continue
                s, ll = _ml_at_fine(kb, kw, nu, ntot, best_i, q, fine, off, fine_colsum, fsteps, uni, bs, r)
                lls[q + fsteps] = ll
                if ll > bll:
                    bll = ll
                    bq = q
                    bs = s
            frac = 0.0
            if bq - 1 >= qlo and bq + 1 <= qhi:
                lm = lls[bq - 1 + fsteps]
                l0 = lls[bq + fsteps]
                lp = lls[bq + 1 + fsteps]
                den = lm - 2.0 * l0 + lp
                if den < 0.0:
                    frac = 0.5 * (lm - lp) / den
                    frac = min(max(frac, -0.5), 0.5)
            tau = best_i + (bq + frac) / fsteps
            tau = min(max(tau, 0.0), m - 1.0)
            c = fine_colsum[best_i * fsteps + bq]
            a = bs * ntot / c
            bg = (1.0 - bs) * ntot * uni
            out_shift[p] = tau
            out_amp[p] = a
            out_bg[p] = bg
            out_var[p] = fisher_var(int(tau + 0.5), a, bg, m, g, dg, off)
