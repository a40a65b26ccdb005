"""ml's likelihood and its bounds (:mod:`.ml_kernels` searches with them): the profile likelihood of
one shift solved in the signal share (:func:`mix_ml`, safeguarded Newton on a concave function), and
the upper bounds that spare most solves, first-pass tangents (:func:`mix_bounds`, many positions in
one sweep) and their tabulated form at interior shifts (:func:`share_tables`, :func:`share_bound`,
:func:`share_sweep`). Every function allocates nothing but the tables' builders, and the leaves are
compiled with ``_nrt=False`` and ``error_model="numpy"`` (see :mod:`recon.kernels`).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from spdepth.recon.kernels import INNER, ZERO, first_above

#: ml: pixels with at most this many distinct photon bins run every pass over all their photons
#: (one out of the pulse's reach reads rate 0, as the w_out term does), sparing the binary search
#: for the ones under the pulse; bigger pixels search, so a pass costs O(pulse support).
ML_SCAN_ALL = 64
#: ml: a solve stops when its quadratic model's value is within this share of |loglik| (at least 1
#: nat) of the maximum: 1/100 of ML_TIE, so no tie is decided by it
ML_MODEL_TOL = 1e-15
#: ml: a photon bin detected at most this many times enters a likelihood's product of rates as that
#: many factors, not through a log of its own: a rate is >= uni (1 - s) > 1e-25 (s < 1 - 1e-16,
#: under 10^9 bins), so four of them take a product the pass kept >= 1e-200 no lower than 1e-300
#: (:func:`_mix_pass` picks the power among 1 to 4 by selects)
ML_POWER_MAX = 4
#: ml: a surviving interior shift's tangent bound is read from tables at ML_SHARES signal shares,
#: (j + 1/2) / ML_SHARES (:func:`share_tables`): any share gives a bound, the one nearest the best
#: solve's share a tight one (1/64 off it adds ~1e-2 nats where U adds a few). 32 rows cost ~0.1
#: ms a kernel call to build and searched as fast as 64 (SBR 1 and 10, 15 detections a pixel)
ML_SHARES = 32
#: ml: the shares that :func:`mix_bounds` takes at least and at most: a solve can end at 0 or 1 exactly,
#: where the tangent's terms diverge; any share inside (0, 1) gives a valid bound, one near the
#: optimum a tight one
ML_SHARE_CLAMP = 1e-3


@njit(cache=True, nogil=True, inline="always", error_model="numpy")
def _mix_pass(kb, kw, ua, ub, w_out, tab, base, step, q, inv_c, uni, s, bound):
    """One pass at signal share s (0 < s < 1) over the photons kb[ua:ub] (weights kw) of
    f(s) = sum_u w_u log(uni + s e_u), e_u = r_u - uni, r_u = tab[(kb[u] + base) * step - q] * inv_c
    (0 outside the table), plus w_out photons at r = 0. Returns (f, f', -f'', kap_hi, kap_lo, c3):
    kap_hi and kap_lo bound -f'' from below over [s, 1] and [0, s]. Each photon's -f'' term
    w (e / (uni + s e))^2 falls with s where e > 0 and rises where e < 0, so over [0, s] it is at
    least its value at s (e > 0) or at 0, (e M)^2 (e < 0); over [s, 1] at least its value at 1,
    w (e / r)^2 >= w (s e / (uni + s e))^2 (e > 0, as uni + s e >= s r), or at s (e < 0).
    c3 = sum_u w_u |q_u|^3 (q = e / lam) is half of |f'''| at s (see :func:`mix_ml`'s stop).
    The kaps are computed only when ``bound`` (the first pass of a solve with a cut, the only one
    that reads them; 0 otherwise): a fifth of a pass's work per photon, and a branch on the sign
    of e. f is a product of the rates (one log per pass, not one per photon), renormalised long
    before it could underflow."""
    m_uni = 1.0 / uni
    nt = tab.size
    qo = -1.0 / (1.0 - s)
    f1 = w_out * qo
    pos2 = 0.0                  # sum over e > 0 of w q^2
    neg2 = w_out * qo * qo      # sum over e <= 0 of w q^2
    neg0 = w_out                # sum over e < 0 of w (e M)^2 (r = 0: e M = -1)
    c3 = -w_out * qo * qo * qo
    ll = w_out * math.log(uni - s * uni) if w_out > 0.0 else 0.0
    prod = 1.0
    for u in range(ua, ub):
        j = (kb[u] + base) * step - q
        # selects, not branches: which photons are signal-like is data, a mispredicted branch a
        # photon would cost more than the arithmetic
        jc = min(max(j, 0), nt - 1)
        rr = tab[jc] * inv_c
        rr = rr if jc == j else 0.0
        e = rr - uni
        lam = uni + s * e
        qq = e / lam
        wu = kw[u]
        f1 += wu * qq
        wq2 = wu * qq * qq
        c3 += wq2 * abs(qq)
        if bound:
            em = e * m_uni
            pos = e > 0.0
            pos2 += wq2 if pos else 0.0
            neg2 += 0.0 if pos else wq2
            neg0 += 0.0 if pos else wu * em * em
        else:
            neg2 += wq2
        if wu <= ML_POWER_MAX and wu == math.floor(wu):
            # a bin detected a few times (common under a return): its rate once per detection,
            # chosen by selects (a loop of unknown length mispredicted its exit); a count that is
            # not whole (pile-up corrected) takes the log
            l2 = lam * lam
            fac = lam if wu == 1.0 else l2
            fac = fac * lam if wu == 3.0 else fac
            fac = l2 * l2 if wu == 4.0 else fac
            prod *= fac
            if prod < 1e-200:       # see ML_POWER_MAX: no underflow before this
                ll += math.log(prod)
                prod = 1.0
        else:
            ll += wu * math.log(lam)
    return ll + math.log(prod), f1, pos2 + neg2, s * s * pos2 + neg2, pos2 + neg0, c3


@njit(cache=True, nogil=True, inline="always", error_model="numpy")
def _mix_bound(ll, f1, s, kap_hi, kap_lo):
    """Upper bound of max over [0, 1] of a concave f with f(s) = ll, f'(s) = f1 and -f'' at least
    kap_hi on [s, 1], kap_lo on [0, s]: the best of the parabola f(s) + f1 t - kap t^2 / 2."""
    if f1 >= 0.0:
        t = 1.0 - s
        if kap_hi > 0.0 and f1 / kap_hi < t:
            t = f1 / kap_hi
        return ll + f1 * t - 0.5 * kap_hi * t * t
    t = s
    if kap_lo > 0.0 and -f1 / kap_lo < t:
        t = -f1 / kap_lo
    return ll - f1 * t - 0.5 * kap_lo * t * t


@njit(cache=True, nogil=True, _nrt=False, error_model="numpy", **INNER)
def _mix_end(kb, kw, ua, ub, w_out, tab, base, step, q, inv_c, uni, f1):
    """Whether :func:`mix_ml`'s maximum lies at s = 0 (f1, the slope at some s, <= 0) or at s = 1
    (f1 > 0), and there (s, loglik): (False, 0, 0) when it does not."""
    nt = tab.size
    wtot = w_out
    for u in range(ua, ub):
        wtot += kw[u]
    if f1 <= 0.0:
        # the maximum lies in [0, s]: at 0 when f'(0) = M (sum w r - n uni) <= 0
        d0 = -wtot * uni
        for u in range(ua, ub):
            j = (kb[u] + base) * step - q
            if j >= 0 and j < nt:
                d0 += kw[u] * tab[j] * inv_c
        if d0 <= 0.0:
            return True, 0.0, wtot * math.log(uni)
    elif w_out <= 0.0:
        # the maximum lies in [s, 1]: at 1 when every photon is under the pulse and f'(1) >= 0
        d1 = 0.0
        at_one = True
        for u in range(ua, ub):
            j = (kb[u] + base) * step - q
            rr = tab[j] * inv_c if (j >= 0 and j < nt) else 0.0
            if rr <= 0.0:
                at_one = False
                break
            d1 += kw[u] * (rr - uni) / rr
        if at_one and d1 >= 0.0:
            # the logs only once the maximum is known to lie at 1
            l1 = 0.0
            prod = 1.0
            for u in range(ua, ub):
                rr = tab[(kb[u] + base) * step - q] * inv_c
                if kw[u] <= ML_POWER_MAX and rr > 1e-20:
                    for _rep in range(int(kw[u])):
                        prod *= rr
                    if prod < 1e-200:
                        l1 += math.log(prod)
                        prod = 1.0
                else:
                    l1 += kw[u] * math.log(rr)
            return True, 1.0, l1 + math.log(prod)
    return False, 0.0, 0.0


@njit(cache=True, nogil=True, _nrt=False, error_model="numpy", **INNER)
def mix_ml(kb, kw, ua, ub, w_out, tab, base, step, q, inv_c, uni, s0, cut):
    """max over s in [0, 1] of sum_u w_u log((1 - s) uni + s r_u): the Poisson likelihood of eq. (9)
    with (a, B) profiled onto a C + B M = n (where its maximum lies), s = a C / n the signal share,
    r_u = g_u / C the pulse's density at photon u, uni = 1 / M. Concave in s: safeguarded Newton
    from s0.

    The photons kb[ua:ub] (weights kw) read their rates from the pulse table as
    :func:`_mix_pass` says; the weight w_out of all others (r = 0) enters as one term, so a call
    costs O(pulse support), not O(photons), when ua:ub is the pulse's reach.

    ``cut``: when the first pass's bound (:func:`_mix_bound`) cannot beat cut, the call returns
    (s0, -inf) after that one pass; pass -inf for an exact answer. s0 = 1 (a neighbouring shift's
    maximum lay at 1, as it does when every detection is under the pulse): whether this one's lies
    there too is checked first, without a pass. Returns (s, loglik)."""
    if s0 == 1.0:
        at, s_end, ll_end = _mix_end(kb, kw, ua, ub, w_out, tab, base, step, q, inv_c, uni, 1.0)
        if at:
            return s_end, ll_end
    s = s0
    if not (s > 0.0 and s < 1.0):
        s = 0.5
    ll, f1, f2, kh, kl, c3 = _mix_pass(kb, kw, ua, ub, w_out, tab, base, step, q, inv_c, uni, s, cut > -np.inf)
    if cut > -np.inf and _mix_bound(ll, f1, s, kh, kl) <= cut:
        return s, -np.inf
    lo = 0.0
    hi = 1.0
    ends_checked = False
    for _it in range(60):
        if f1 > 0.0:
            lo = s
        else:
            hi = s
        newton = f2 > 0.0
        sn = s + f1 / f2 if newton else 0.5 * (lo + hi)
        if newton and sn == s:
            # a step below the share's resolution: s is the maximum to rounding
            return s, ll
        if not (sn > lo and sn < hi):
            newton = False
            if not ends_checked and (sn <= 0.0 or sn >= 1.0):
                # Newton heads out of (0, 1): the maximum may lie at that end (checked once, and
                # only then: an interior maximum never sends a concave function's step out)
                ends_checked = True
                at, s_end, ll_end = _mix_end(kb, kw, ua, ub, w_out, tab, base, step, q, inv_c, uni, f1)
                if at:
                    return s_end, ll_end
            sn = 0.5 * (lo + hi)
        if hi - lo < 1e-14:
            break
        t = sn - s
        if (newton and c3 * abs(t) ** 3 <= ML_MODEL_TOL * max(1.0, abs(ll))
                and abs(t) < 1e-3 * min(sn, 1.0 - sn)):
            # a Newton step to the quadratic model's maximum: its value is the loglik's to
            # |f'''| |t|^3 / 6 = c3 |t|^3 / 3 (f''' barely moves over a step this small beside the
            # distance to 0 and 1), and sn is within ~(c3 / f'') t^2 of the maximum; from a
            # neighbour's share this usually holds after one pass (a fixed tolerance on the step,
            # 1e-7, took two). Never after a bisection: its step is not the model's maximum
            return sn, ll + f1 * t - 0.5 * f2 * t * t
        s = sn
        ll, f1, f2, kh, kl, c3 = _mix_pass(kb, kw, ua, ub, w_out, tab, base, step, q, inv_c, uni, s, False)
    return s, ll


@njit(cache=True, nogil=True, error_model="numpy", **INNER)
def _photon_range(kb, nu, lo, hi):
    """[ua, ub): the sorted distinct photon bins kb[:nu] lying in [lo, hi] (binary search)."""
    return first_above(kb, nu, lo, np.bool_(False)), first_above(kb, nu, hi, np.bool_(True))


@njit(cache=True, nogil=True, _nrt=False, error_model="numpy")
def _ml_at_int(kb, kw, nu, wtot, i, g, off, colsum, uni, s0, cut):
    """Profile at integer shift i (g[k - i + off] is photon k's share of column i)."""
    nk = g.size
    if nu <= ML_SCAN_ALL:
        ua, ub, w_out = 0, nu, 0.0
    else:
        ua, ub = _photon_range(kb, nu, i - off, i - off + nk - 1)
        w_out = wtot
        for u in range(ua, ub):
            w_out -= kw[u]
    return mix_ml(kb, kw, ua, ub, w_out, g, off - i, np.int64(1), ZERO, 1.0 / colsum[i], uni, s0, cut)


@njit(cache=True, nogil=True, _nrt=False, error_model="numpy", **INNER)
def _ml_at_fine(kb, kw, nu, wtot, i, q, fine, off, fine_colsum, fsteps, uni, s0, cut):
    """Profile at shift i + q / fsteps (|q| <= fsteps), from the fine kernel table."""
    nf = fine.size
    nk = (nf - 1) // fsteps + 1
    if nu <= ML_SCAN_ALL:
        ua, ub, w_out = 0, nu, 0.0
    else:
        # fine index (k - i + off) * fsteps - q lies in [0, nf) only for k - i + off in [-1, nk]
        ua, ub = _photon_range(kb, nu, i - off - 1, i - off + nk)
        w_out = wtot
        for u in range(ua, ub):
            w_out -= kw[u]
    return mix_ml(kb, kw, ua, ub, w_out, fine, off - i, fsteps, q, 1.0 / fine_colsum[i * fsteps + q], uni,
                  s0, cut)


@njit(cache=True, nogil=True, _nrt=False, error_model="numpy", **INNER)
def mix_bounds(kb, kw, nu, wtot, trev, base, step, qa, nq, inv_c, uni, s, r0s, ws, out):
    """:func:`mix_ml`'s first-pass bound (:func:`_mix_bound` of :func:`_mix_pass` at share s, which
    must lie in (0, 1)) for nq consecutive positions of a pulse table in one call: position t reads
    photon u's rate tab[(kb[u] + base) * step - qa - t] * inv_c[t] (0 outside the table; trev is
    the table reversed). The photons kb[:nu] (sorted; weights kw, whole numbers, total wtot) that
    reach some position are listed once (r0s, ws: scratch of nu entries); the rest count as rate 0
    without a visit. Per position the sums stay in registers: a call costs about what nq first
    passes cost without nq solver calls. out[:nq] gets the bounds."""
    nt = trev.size
    m_uni = 1.0 / uni
    s2 = s * s
    ua = 0
    if nu > ML_SCAN_ALL:
        # the first photon with (k + base) * step - qa >= 0 (a binary search on a big pixel)
        ua = first_above(kb, nu, -((-qa) // step) - base, np.bool_(False))
    n = 0
    for u in range(ua, nu):
        jj = (kb[u] + base) * step - qa
        if jj - (nq - 1) >= nt:
            break
        if jj < 0:
            continue
        r0s[n] = nt - 1 - jj        # trev[r0 + t] == tab[jj - t]
        ws[n] = kw[u]
        n += 1
    qo = -1.0 / (1.0 - s)
    lo0 = math.log(uni - s * uni)
    # every rate is >= uni (1 - s) (e <= 0) or > uni, and <= 1: a product of `chunk` detections
    # stays inside (1e-290, 1]
    chunk = max(1.0, float(int(-667.0 / lo0)))
    for t in range(nq):
        ict = inv_c[t]
        f1 = 0.0
        kh = 0.0            # -f'' bound over [s, 1] (see _mix_pass)
        kl = 0.0            # and over [0, s]
        prod = 1.0
        ll = 0.0
        cnt = 0.0
        zin = 0.0           # weight of the photons inside the table at t
        for v in range(n):
            r = r0s[v] + t
            if r >= 0 and r < nt:
                w = ws[v]
                e = trev[r] * ict - uni
                lam = uni + s * e
                qq = e / lam
                wq2 = w * qq * qq
                em = e * m_uni
                pos = e > 0.0
                f1 += w * qq
                kh += s2 * wq2 if pos else wq2
                kl += wq2 if pos else w * em * em
                zin += w
                if cnt + w > chunk:
                    ll += math.log(prod)
                    prod = 1.0
                    cnt = 0.0
                if w <= chunk:
                    cnt += w
                    prod *= lam
                    # a bin detected more than once: its rate once per detection (a loop, not
                    # lam ** w: a select would compute the power for every photon)
                    for _rep in range(1, int(w)):
                        prod *= lam
                else:
                    ll += w * math.log(lam)     # so many in one bin that the product could underflow
        z = wtot - zin
        ll += math.log(prod) + (z * lo0 if z > 0.0 else 0.0)
        out[t] = _mix_bound(ll, f1 + z * qo, s, kh + z * qo * qo, kl + z)


@njit(cache=True, nogil=True)
def share_tables(g, c, uni, nshares):
    """Per signal share s_j = (j + 1/2) / nshares and pulse offset d (d = g.size: outside the
    pulse, rate 0), the terms one photon adds to :func:`_mix_pass`'s sums at an interior shift
    (column sum c): out[j, d] = (log lam, q, its -f'' term over [s, 1], over [0, s]), with
    e = g[d] / c - uni, lam = uni + s e, q = e / lam (see :func:`_mix_pass`). A bound then costs
    four lookups a photon, with no division and no log (:func:`share_bound`)."""
    nk = g.size
    out = np.empty((nshares, nk + 1, 4))
    m_uni = 1.0 / uni
    inv_c = 1.0 / c
    for j in range(nshares):
        s = (j + 0.5) / nshares
        for d in range(nk + 1):
            e = (g[d] * inv_c if d < nk else 0.0) - uni
            lam = uni + s * e
            q = e / lam
            out[j, d, 0] = math.log(lam)
            out[j, d, 1] = q
            out[j, d, 2] = s * s * q * q if e > 0.0 else q * q
            out[j, d, 3] = q * q if e > 0.0 else (e * m_uni) * (e * m_uni)
    return out


@njit(cache=True, nogil=True, inline="always", error_model="numpy")
def share_bound(kb, kw, ua, ub, w_out, i, off, stabs, j, s):
    """:func:`mix_ml`'s first-pass bound (:func:`_mix_bound`) at interior shift i and the tabulated
    share s = (j + 1/2) / stabs.shape[0], from :func:`share_tables`: the same sums, read instead
    of computed (rounded differently, in the last bits). The photons kb[ua:ub] (weights kw) are
    read (those outside the pulse's reach at i count as rate 0), the weight w_out of all others
    counts as rate 0 without a visit."""
    nk = stabs.shape[1] - 1
    ll = w_out * stabs[j, nk, 0]
    f1 = w_out * stabs[j, nk, 1]
    kh = w_out * stabs[j, nk, 2]
    kl = w_out * stabs[j, nk, 3]
    for u in range(ua, ub):
        d = kb[u] - i + off
        d = d if (d >= 0 and d < nk) else nk
        w = kw[u]
        ll += w * stabs[j, d, 0]
        f1 += w * stabs[j, d, 1]
        kh += w * stabs[j, d, 2]
        kl += w * stabs[j, d, 3]
    return _mix_bound(ll, f1, s, kh, kl)


@njit(cache=True, nogil=True)
def share_diffs(stabs):
    """:func:`share_sweep`'s rows: per share j and sum c, the terms of a photon at offset
    nk - 1 - t beyond a rate-0 photon's, out[j, c, t] (reversed: in shift order)."""
    ns, nk1, nc = stabs.shape
    nk = nk1 - 1
    out = np.empty((ns, nc, nk))
    for j in range(ns):
        for c in range(nc):
            for t in range(nk):
                out[j, c, t] = stabs[j, nk - 1 - t, c] - stabs[j, nk, c]
    return out


@njit(cache=True, nogil=True, _nrt=False, error_model="numpy")
def share_sweep(kb, kw, nu, off, ia, ib, sdiff, j, ssum):
    """:func:`share_bound`'s sums beyond the all-rate-0 ones (wtot stabs[j, nk]) at every interior
    shift [ia, ib] the photons kb[:nu] (weights kw) reach, into ssum[c, i] (zero there on entry):
    each photon adds its row of sdiff over its reach, a contiguous add. Returns the span of
    shifts touched (lo > hi: none)."""
    nk = sdiff.shape[2]
    lo = max(ia, kb[0] + off - nk + 1)
    hi = min(ib, kb[nu - 1] + off)
    for u in range(nu):
        i0 = kb[u] + off - nk + 1          # the shift where the photon sits at offset nk - 1
        w = kw[u]
        t0 = max(0, ia - i0)
        t1 = min(nk, ib - i0 + 1)
        if t1 <= t0:
            continue
        for c in range(4):
            # contiguous slices: numba's views let the add vectorise (indexing did not)
            seg = ssum[c, i0 + t0:i0 + t1]
            row = sdiff[j, c, t0:t1]
            for t in range(seg.size):
                seg[t] += w * row[t]
    return lo, hi


@njit(cache=True, nogil=True, inline="always", error_model="numpy")
def swept_bound(ssum, i, wtot, stabs, j, s):
    """:func:`share_bound` at interior shift i from :func:`share_sweep`'s sums: those plus all wtot
    detections' rate-0 terms."""
    nk = stabs.shape[1] - 1
    return _mix_bound(ssum[0, i] + wtot * stabs[j, nk, 0], ssum[1, i] + wtot * stabs[j, nk, 1], s,
                      ssum[2, i] + wtot * stabs[j, nk, 2], ssum[3, i] + wtot * stabs[j, nk, 3])
