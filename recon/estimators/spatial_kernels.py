"""Numba kernels of the spatial estimator (:mod:`recon.estimators.spatial`). Plain arrays in, disjoint outputs
out; validation, allocation and the choice of constants happen in :mod:`recon.estimators.spatial`.

Times here are continuous shifts in bins: a detection at raw time ``t`` is at
``(t - window_start) / bin_width - 0.5``, the shift whose pulse centroid it would be (so the mean of a
return's signal detections estimates the return's shift directly). Photon lists are CSR
(``x[offsets[p]:offsets[p + 1]]``, pixels row-major over an H x W image), each pixel's list sorted,
with ``wx`` the detections at each entry (int32, >= 1): 1 each for a photon list, a time's count for
a histogram's (time, count) pairs, so that the work grows with the occupied bins. An entry of count c
is c detections at one time: every result is the one of its photon list (each count expanded), the
support counts exactly, the sums of the fit to rounding.
"""

from __future__ import annotations

import math
from collections import namedtuple

import numpy as np
from llvmlite import ir
from numba import njit, types
from numba.extending import intrinsic

from spdepth.recon.threadpool import on_slices, on_threads

#: window_shifts: lists longer than this are bucket sorted, shorter ones by rank counting (its k^2
#: comparisons vectorise: 2x faster than the bucket sort at 60 and 100 detections, 1.2x at 160).
BUCKET_ABOVE = 128
#: window_shifts: buckets per detection; a return's detections crowd a few pulse widths, so
#: more buckets than detections keep each bucket's share of them small.
BUCKETS_PER_DETECTION = 4
#: _exp_neg: below this argument exp() is taken as 0 (the exact value is under 3.3e-308: no
#: responsibility worth a bit of the sums, and 2^n below it would need subnormal scaling).
EXP_IS_ZERO = -708.0
#: censor_fit: a neighbour's list is walked with two pointers when (undecided detections) x (its
#: detections) exceeds this many times their sum, else compared pair by pair (vectorised).
WALK_ABOVE = 12
#: censor_fit: pixels per parallel task (each allocates its scratch once).
PIXEL_BLOCK = 256


@njit(cache=True, nogil=True)
def window_shifts(times, offsets, start, stop, width, max_photons, out_x, out_offsets):
    """First ``max_photons`` (all when < 0) detections of each pixel with ``start <= t < stop``, as
    shifts ``(t - start) / width - 0.5``, each pixel's list then sorted ascending. out_x needs
    times.size entries, out_offsets offsets.size; returns the number kept."""
    npix = offsets.size - 1
    longest = 0
    for p in range(npix):
        longest = max(longest, offsets[p + 1] - offsets[p])
    if max_photons >= 0:
        longest = min(longest, max_photons)
    tmp = np.empty(longest, np.float64)
    fill = np.empty(BUCKETS_PER_DETECTION * longest + 1, np.int64)
    n_bins = (stop - start) / width
    n = 0
    out_offsets[0] = 0
    for p in range(npix):
        kept = 0
        first = n
        for q in range(offsets[p], offsets[p + 1]):
            if max_photons >= 0 and kept >= max_photons:
                break
            t = times[q]
            if t >= start and t < stop:
                out_x[n] = (t - start) / width - 0.5
                n += 1
                kept += 1
        if kept > BUCKET_ABOVE:
            # rank counting is quadratic and heap sort branchy: a few buckets per detection leave
            # only the order within each bucket to sort
            _bucket_sort(out_x, first, n, n_bins, tmp, fill)
        elif kept > 1:
            _rank_sort(out_x, first, n, tmp, fill)   # in place: np.sort allocated a new array per pixel
        out_offsets[p + 1] = n
    return n


@njit(cache=True, nogil=True)
def _rank_sort(a, lo, hi, tmp, rank):
    """Sort a[lo:hi] (no NaN) ascending in place by counting each value's rank, the values below
    it: one branch-free pass over the whole list per value, which the compiler vectorises (two
    passes split at the value's own position, to order equal values, ran at half the speed).
    Equal values share a rank (the ranks then sum to less than k (k - 1) / 2) and take the free
    slots after it in their input order. tmp and rank need hi - lo entries."""
    k = hi - lo
    v = a[lo:hi]      # indices from 0 on a view: numba checks no negative index, so loops vectorise
    total = 0
    for i in range(k):
        vi = v[i]
        r = 0
        for j in range(k):
            r += v[j] < vi
        rank[i] = r
        total += r
    if total == k * (k - 1) // 2:
        # each rank is at most the value's place and the places sum to this: all values differ
        for i in range(k):
            tmp[rank[i]] = v[i]
    else:
        for i in range(k):
            tmp[i] = np.nan       # free slot
        for i in range(k):
            pos = rank[i]
            while tmp[pos] == tmp[pos]:      # taken by an equal value (NaN marks a free slot)
                pos += 1
            tmp[pos] = v[i]
    for i in range(k):
        v[i] = tmp[i]


@njit(cache=True, nogil=True)
def _bucket_sort(a, lo, hi, n_bins, tmp, fill):
    """Sort a[lo:hi] (shifts in [-0.5, n_bins - 0.5)) ascending in place: a counting pass over
    BUCKETS_PER_DETECTION buckets per detection, each detection inserted in order within its
    bucket as it is placed. tmp and fill need hi - lo and BUCKETS_PER_DETECTION * (hi - lo) + 1
    entries."""
    k = hi - lo
    src = a[lo:hi]        # indices from 0 (no negative-index fix-up)
    nb = BUCKETS_PER_DETECTION * k
    scale = nb / n_bins
    for j in range(nb + 1):
        fill[j] = 0
    for i in range(k):
        fill[min(nb - 1, max(0, int((src[i] + 0.5) * scale))) + 1] += 1
    for j in range(nb):
        fill[j + 1] += fill[j]
    for j in range(k):
        tmp[j] = -np.inf      # an unfilled slot stops the insertion at its bucket's start
    for i in range(k):
        v = src[i]
        j = min(nb - 1, max(0, int((v + 0.5) * scale)))
        pos = fill[j]
        fill[j] += 1
        # bucket index grows with the value, so earlier buckets hold smaller values or -inf
        while pos > 0 and tmp[pos - 1] > v:
            tmp[pos] = tmp[pos - 1]
            pos -= 1
        tmp[pos] = v
    for i in range(k):
        src[i] = tmp[i]


#: censor_fit's settings: an h x w image, (2 radius + 1)^2 pixels around each, support within tau
#: bins, a Gaussian pulse of sigma bins over n_bins, em_iters EM steps; count_width: window_counts'
#: bin width (its bounds, when given).
CensorSettings = namedtuple("CensorSettings", ["h", "w", "radius", "tau", "sigma", "n_bins", "em_iters",
                                               "count_width"])


def censor_fit(x, wx, offsets, s_min, win_counts, cs, out_mu, out_k, out_bg, out_n, out_kept):
    """Per pixel: censor, then fit a pulse-plus-flat mixture to the detections kept
    (:class:`CensorSettings` cs).

    Censoring (after Rapp and Goyal 2017): a detection is kept when at least ``s_min[p]`` other
    detections of the (2 radius + 1)^2 window (the pixel's own included) lie within ``tau`` bins;
    a background detection finds such support only by chance. Of the kept detections, the
    densest cluster (most kept within 2.5 sigma) seeds the fit. Fit: ``em_iters`` EM steps on all
    of the pixel's detections for ``pi N(mu, sigma^2) + (1 - pi) / n_bins``, mu and pi free.

    win_counts (window_counts' output, or (h w) x 0 for none) and its bin width count_width bound each
    detection's support before the neighbours are counted: the outputs are the same with or without.

    x, wx: each pixel's sorted shifts and the detections at each (module docstring).

    Outputs per pixel: out_mu (shift, bins; NaN when nothing kept), out_k (signal detections, the
    sum of responsibilities; 0 when nothing kept), out_bg (background detections per bin),
    out_n (detections used), out_kept (detections that passed censoring)."""
    npix = cs.h * cs.w
    longest = np.int64(np.diff(offsets[:npix + 1]).max()) if npix else np.int64(0)
    # slices of whole blocks of pixels on the thread pool, each a call of the nogil block kernel:
    # numba's prange over them cost 2.1 s of cold compile more (censor_fit's parallel lowering) at
    # the same speed
    on_slices(lambda a, b: _censor_fit_block(a, b, longest, x, wx, offsets, s_min, win_counts, cs, out_mu, out_k,
                                             out_bg, out_n, out_kept), npix, PIXEL_BLOCK)


@njit(cache=True, nogil=True, _nrt=False)
def _own_support(xp, wp, n, need, tau, sup, sure, todo):
    """Each entry's support from the pixel's own sorted list xp[:n] of counts wp (one of the entry's
    own detections excluded) into sup; the entries still short of ``need`` into todo; returns how
    many. An entry whose `half` predecessors and `half` successors all lie within tau has >= need
    supporters (each entry holds at least one detection): the core of a return is decided by this
    test (it vectorises) and the walk, whose loops mispredict, skips it."""
    half = (need + 1) // 2
    for i in range(n):
        sure[i] = False
    if n > 2 * half:
        # as shifted views from 0, so the loop loads without gathers
        before = xp[:n - 2 * half]
        at = xp[half:n - half]
        after = xp[2 * half:]
        mid = sure[half:n - half]
        for j in range(n - 2 * half):
            mid[j] = (before[j] >= at[j] - tau) & (after[j] <= at[j] + tau)
    a = 0
    b = 0
    inside = 0        # the detections of entries a..b-1
    nt = 0
    for i in range(n):
        if sure[i]:
            sup[i] = need
            continue
        t = xp[i]
        while xp[a] < t - tau:
            if a < b:
                inside -= wp[a]
            a += 1
        if b < a:
            b = a
            inside = 0
        while b < n and xp[b] <= t + tau:
            inside += wp[b]
            b += 1
        sup[i] = inside - 1
        if sup[i] < need:
            todo[nt] = i
            nt += 1
    return nt


@njit(cache=True, nogil=True, _nrt=False)
def _bounded(xp, nt, need, tau, wc, count_width, todo):
    """Keep in todo[:nt] only the detections whose support the window's detections in the coarse
    bins that [t - tau, t + tau] touches (wc: a row of window_counts, the detection itself among
    them) can raise to more than need: one whose bound falls short is censored without counting any
    neighbour. Returns how many are left."""
    nc = wc.size
    inv_width = 1.0 / count_width
    keep = 0
    for j in range(nt):
        i = todo[j]
        k0 = _count_bin(xp[i] - tau, inv_width, nc)
        k1 = _count_bin(xp[i] + tau, inv_width, nc)
        bound = wc[k1] - (wc[k0 - 1] if k0 > 0 else 0)
        todo[keep] = i
        keep += bound > need
    return keep


@njit(cache=True, nogil=True, _nrt=False)
def _support_from(xp, xq, wq, nt, tau, sup, todo):
    """Add to sup[todo[:nt]] each undecided entry's supporters among a neighbour's sorted list xq
    of counts wq."""
    nq = xq.size
    if nt * nq <= WALK_ABOVE * (nt + nq):
        # a comparison per pair without a branch (the loop vectorises): for the few detections still
        # undecided cheaper than a walk over the neighbour's list, whose branches the processor
        # mispredicts
        for j in range(nt):
            i = todo[j]
            lo_t = xp[i] - tau
            hi_t = xp[i] + tau
            cnt = 0
            for k in range(nq):
                cnt += ((xq[k] >= lo_t) & (xq[k] <= hi_t)) * wq[k]
            sup[i] += cnt
        return
    # many undecided (a background-dominated pixel): two pointers walk both sorted lists once,
    # O(nt + nq)
    a = 0
    b = 0
    inside = 0        # the detections of entries a..b-1
    for j in range(nt):
        i = todo[j]
        t = xp[i]
        while a < nq and xq[a] < t - tau:
            if a < b:
                inside -= wq[a]
            a += 1
        if b < a:
            b = a
            inside = 0
        while b < nq and xq[b] <= t + tau:
            inside += wq[b]
            b += 1
        sup[i] += inside


@njit(cache=True, nogil=True, _nrt=False)
def _neighbour_support(p, xp, nt, need, x, wx, offsets, cs, sup, todo):
    """The undecided detections todo[:nt] of pixel p counted against each neighbour in turn, those
    still short kept after each; returns how many stay short."""
    r0 = p // cs.w
    c0 = p - r0 * cs.w
    for r in range(max(0, r0 - cs.radius), min(cs.h - 1, r0 + cs.radius) + 1):
        for c in range(max(0, c0 - cs.radius), min(cs.w - 1, c0 + cs.radius) + 1):
            q = r * cs.w + c
            if q == p or offsets[q + 1] == offsets[q] or nt == 0:
                continue
            _support_from(xp, x[offsets[q]:offsets[q + 1]], wx[offsets[q]:offsets[q + 1]], nt, cs.tau, sup, todo)
            keep = 0
            for j in range(nt):
                todo[keep] = todo[j]
                keep += sup[todo[j]] < need
            nt = keep
    return nt


@njit(cache=True, nogil=True, _nrt=False)
def _densest_mean(kept, kw, nk, reach):
    """(mean, count) of the densest cluster of the sorted kept[:nk] of counts kw: the most
    detections within reach of one of them (two pointers), and the mean of those within reach of
    it."""
    best = 0
    bi = 0
    lo = 0
    hi = 0
    inside = 0        # the detections of entries lo..hi-1
    for i in range(nk):
        while kept[lo] < kept[i] - reach:
            inside -= kw[lo]
            lo += 1
        while hi < nk and kept[hi] <= kept[i] + reach:
            inside += kw[hi]
            hi += 1
        if inside > best:
            best = inside
            bi = i
    acc = 0.0
    cnt = 0
    for i in range(nk):
        near = abs(kept[i] - kept[bi]) <= reach
        acc += kept[i] * kw[i] if near else 0.0
        cnt += kw[i] if near else 0
    return acc / cnt, cnt


@njit(cache=True, nogil=True)
def _censor_fit_block(first, last, longest, x, wx, offsets, s_min, win_counts, cs, out_mu, out_k, out_bg,
                      out_n, out_kept):
    """censor_fit of pixels first..last - 1 (longest: the longest list)."""
    inv_m = 1.0 / cs.n_bins
    inv_s2 = 1.0 / (cs.sigma * cs.sigma)
    norm = 1.0 / (math.sqrt(2.0 * math.pi) * cs.sigma)
    # scratch once per block of pixels (three allocations per pixel cost 10% at 2 detections)
    sup = np.empty(longest, np.int64)
    todo = np.empty(longest, np.int64)
    sure = np.empty(longest, np.bool_)
    kept = np.empty(longest, np.float64)
    kept_w = np.empty(longest, wx.dtype)
    for p in range(first, last):
        o0 = offsets[p]
        o1 = offsets[p + 1]
        n = o1 - o0
        wp = wx[o0:o1]
        nd = 0            # the pixel's detections
        for i in range(n):
            nd += wp[i]
        out_n[p] = nd
        out_mu[p] = np.nan
        out_k[p] = 0.0
        out_bg[p] = nd * inv_m
        out_kept[p] = 0
        if n == 0:
            continue
        # Each detection's support: the window's detections in [t - tau, t + tau], the detection
        # itself excluded. Only "support >= s_min" matters, so a detection stops collecting once it
        # has enough: the pixel's own list first (where a return's detections find most of theirs),
        # then each neighbour for the detections still short. The undecided ones (background, a
        # return's tails) are counted exactly against every neighbour unless an upper bound rules
        # them out, so the decision is the same as with full counts.
        need = s_min[p]
        # views indexed from 0: numba then omits its negative-index fix-up, which kept the
        # comparison loops from vectorising (2x in the pair counts)
        xp = x[o0:o1]
        nt = _own_support(xp, wp, n, need, cs.tau, sup, sure, todo)
        if win_counts.shape[1] > 0 and nt > 0:
            nt = _bounded(xp, nt, need, cs.tau, win_counts[p], cs.count_width, todo)
        _neighbour_support(p, xp, nt, need, x, wx, offsets, cs, sup, todo)
        # kept detections: their positions in x (the pixel's list is sorted, so kept ones are too)
        nk = 0
        n_kept = 0
        for i in range(n):
            kept[nk] = xp[i]
            kept_w[nk] = wp[i]
            keep = sup[i] >= need
            nk += keep
            n_kept += wp[i] if keep else 0
        out_kept[p] = n_kept
        if nk == 0:
            continue
        mu, cnt = _densest_mean(kept, kept_w, nk, 2.5 * cs.sigma)
        pi = min(0.999, max(cnt / nd, 1e-3))
        # EM over all the pixel's detections: a censored detection close to the return still
        # counts as signal in proportion to its likelihood, a kept one far from it does not
        mu, ksum = _em_fit(xp, wp, nd, mu, pi, float(cnt), cs.em_iters, inv_s2, norm, inv_m)
        out_mu[p] = mu
        out_k[p] = ksum
        out_bg[p] = max(0.0, nd - ksum) * inv_m


@njit(cache=True, nogil=True)
def window_counts(x, wx, offsets, h, w, radius, width, out):
    """out[p, k]: the detections of pixel p's (2 radius + 1)^2 window (clipped at the border) whose
    coarse bin (_count_bin with this width) is at most k, cumulative so that any range of bins
    costs two look-ups: censor_fit's upper bounds on a detection's support. Each pixel's list
    sorted; out is (h w) x n_coarse, any content. Serial: a few percent of censor_fit's time, and
    the parallel version took 2.5 s more to compile."""
    nc = out.shape[1]
    npix = h * w
    inv_width = 1.0 / width
    longest = 0
    for p in range(npix):
        longest = max(longest, offsets[p + 1] - offsets[p])
    bins = np.empty(longest, np.int64)
    own = np.empty((npix, nc), out.dtype)
    for p in range(npix):
        # cumulative counts from the sorted list: the last detection of each bin writes its rank,
        # then a running maximum fills the empty bins. The bins first, in a loop of their own:
        # stores at computed places amid the loads of x ran 3x slower.
        xp = x[offsets[p]:offsets[p + 1]]
        wp = wx[offsets[p]:offsets[p + 1]]
        for i in range(xp.size):
            bins[i] = _count_bin(xp[i], inv_width, nc)
        row = own[p]
        for k in range(nc):
            row[k] = 0
        through = 0       # the detections up to entry i
        for i in range(xp.size):
            through += wp[i]
            row[bins[i]] = through
        run = 0
        for k in range(nc):
            run = max(run, row[k])
            row[k] = run
    col = np.empty((w, nc), out.dtype)
    for r in range(h):
        # sums over the window's rows, then along the row
        col[:] = 0
        for rr in range(max(0, r - radius), min(h, r + radius + 1)):
            src = own[rr * w:(rr + 1) * w]
            for c in range(w):
                for k in range(nc):
                    col[c, k] += src[c, k]
        dst = out[r * w:(r + 1) * w]
        for c in range(w):
            for k in range(nc):
                dst[c, k] = 0
            for cc in range(max(0, c - radius), min(w, c + radius + 1)):
                for k in range(nc):
                    dst[c, k] += col[cc, k]


@njit(cache=True, nogil=True)
def _count_bin(v, inv_width, nc):
    """window_counts' coarse bin of shift v, clamped to [0, nc): non-decreasing in v, so the
    detections in [lo, hi] lie in the bins from _count_bin(lo) to _count_bin(hi)."""
    return min(nc - 1, max(0, int((v + 0.5) * inv_width)))


@njit(cache=True, nogil=True, fastmath={"contract", "reassoc"}, error_model="numpy")
def _em_fit(xp, wp, nd, mu, pi, ksum, em_iters, inv_s2, norm, inv_m):
    """``em_iters`` EM steps of ``pi N(mu, sigma^2) + (1 - pi) inv_m`` on the nd detections at xp
    (wp at each) from (mu, pi); returns (mu, sum of responsibilities), or (mu, ksum) as given when
    the first step finds none.

    Written for the compiler to vectorise the loop over detections: exp inlined as a polynomial
    (libm's is a call per detection), divisions without numba's zero check (error_model; no
    divisor here is 0), fused multiply-adds and reassociated sums (fastmath): a few ulp from the
    plain loop."""
    n = xp.size
    for _ in range(em_iters):
        pn = pi * norm
        c = (1.0 - pi) * inv_m
        sr = 0.0
        srt = 0.0
        for i in range(n):
            d = xp[i] - mu
            a = pn * _exp_neg(-0.5 * d * d * inv_s2)
            rr = wp[i] * (a / (a + c))
            sr += rr
            srt += rr * xp[i]
        if sr <= 1e-9:
            break
        mu = srt / sr
        pi = min(0.999, max(sr / nd, 1e-3))
        ksum = sr
    return mu, ksum


@intrinsic
def _bits_as_float(typingctx, bits):
    """The float64 whose IEEE 754 bits are the int64 ``bits`` (a reinterpretation, no instruction)."""
    def codegen(context, builder, signature, args):
        return builder.bitcast(args[0], ir.DoubleType())
    return types.float64(types.int64), codegen


@intrinsic
def _float_as_bits(typingctx, v):
    """The IEEE 754 bits of the float64 ``v`` as an int64."""
    def codegen(context, builder, signature, args):
        return builder.bitcast(args[0], ir.IntType(64))
    return types.int64(types.float64), codegen


_LOG2E = 1.4426950408889634
#: ln 2 split so that n * _LN2_HI is exact for |n| < 2^11 (Cody and Waite's reduction)
_LN2_HI = 6.93147180369123816490e-01
_LN2_LO = 1.90821492927058770002e-10
#: added to an integer-valued float in [-1022, 0], leaves that integer + 1023 in the low mantissa bits
_EXPONENT_SHIFT = 4503599627370496.0 + 1023.0


@njit(inline="always", cache=True, nogil=True)
def _exp_neg(e):
    """exp(e) for e <= 0 within a few ulp of libm (0 below EXP_IS_ZERO), in instructions a loop can
    vectorise: e = n ln2 + r with |r| <= ln2 / 2, exp(r) by its Taylor series to r^12 (the next
    term is below 2e-16 relative), 2^n written straight into the exponent bits."""
    n = np.floor(e * _LOG2E + 0.5)     # a float: math.floor's int cost two scalar conversions per lane
    r = (e - n * _LN2_HI) - n * _LN2_LO
    p = 1.0 / 479001600.0
    p = p * r + 1.0 / 39916800.0
    p = p * r + 1.0 / 3628800.0
    p = p * r + 1.0 / 362880.0
    p = p * r + 1.0 / 40320.0
    p = p * r + 1.0 / 5040.0
    p = p * r + 1.0 / 720.0
    p = p * r + 1.0 / 120.0
    p = p * r + 1.0 / 24.0
    p = p * r + 1.0 / 6.0
    p = p * r + 0.5
    p = p * r + 1.0
    p = p * r + 1.0
    scale = _bits_as_float(_float_as_bits(max(n, -1022.0) + _EXPONENT_SHIFT) << 52)
    return p * scale if e >= EXP_IS_ZERO else 0.0


def local_mean(f, wt, radius, out):
    """Weighted mean of ``f`` over the (2 radius + 1)^2 window with weights ``wt`` (NaN where the
    window holds no weight): the start of the TV iterations and the fill of empty pixels. In bands
    of rows on the thread pool (:func:`_local_mean_rows`)."""
    on_slices(lambda r0, r1: _local_mean_rows(f, wt, radius, out, r0, r1), f.shape[0])


@njit(cache=True, nogil=True)
def _local_mean_rows(f, wt, radius, out, r0, r1):
    """local_mean of rows r0..r1 - 1."""
    h, w = f.shape
    for r in range(r0, r1):
        for c in range(w):
            a = 0.0
            s = 0.0
            for rr in range(max(0, r - radius), min(h, r + radius + 1)):
                for cc in range(max(0, c - radius), min(w, c + radius + 1)):
                    v = wt[rr, cc]
                    if v > 0.0:
                        a += v * f[rr, cc]
                        s += v
            out[r, c] = a / s if s > 0.0 else np.nan


@njit(cache=True, nogil=True, error_model="numpy")
def tv_pdhg(f, wt, lam, z, iters, px, py, zbar):
    """Weighted isotropic-TV denoising by the primal-dual algorithm of Chambolle and Pock (2011):
    minimise ``sum wt (z - f)^2 / 2 + lam * TV(z)`` over z (H x W). Pixels with wt = 0 carry no
    data and are filled by the regulariser. ``z`` holds the start and receives the result;
    px, py, zbar are scratch (H x W, any content). Steps tau = sigma = 1/sqrt(8).

    Serial on purpose: two parallel regions per iteration are 120 fork-joins a call, and on a
    loaded machine one descheduled thread stalls every one of them (measured: 64 x 64 took 1.5 s
    with 2 threads under load 5, 0.04 s with 1)."""
    h, w = f.shape
    step = 1.0 / math.sqrt(8.0)
    for r in range(h):
        for c in range(w):
            px[r, c] = 0.0
            py[r, c] = 0.0
            zbar[r, c] = z[r, c]
    # No branch per pixel and no zero check on the divisions (error_model), so the row loops
    # vectorise (3x): the last column's px and the last row's py stay exactly 0 (their gradient
    # component is 0), so the divergence may add them; the last row takes its own row as the next
    # one (a difference of exactly 0); row 0 subtracts a row of zeros. Same arithmetic as a loop
    # with a branch per edge.
    zero = np.zeros(w)
    for _ in range(iters):
        # dual ascent on the forward-difference gradient, projected on |p| <= lam
        for r in range(h):
            zb = zbar[r]
            zn = zbar[r + 1] if r + 1 < h else zb
            pxr = px[r]
            pyr = py[r]
            for c in range(w - 1):
                _dual(pxr, pyr, c, zb[c + 1] - zb[c], zn[c] - zb[c], step, lam)
            _dual(pxr, pyr, w - 1, 0.0, zn[w - 1] - zb[w - 1], step, lam)
        # primal descent: divergence (minus the adjoint of the gradient), then the data prox
        for r in range(h):
            pxr = px[r]
            pyr = py[r]
            pyu = py[r - 1] if r > 0 else zero
            zr = z[r]
            zbr = zbar[r]
            fr = f[r]
            wr = wt[r]
            _primal(zr, zbr, fr, wr, 0, pxr[0] + pyr[0] - pyu[0], step)
            for c in range(1, w):
                _primal(zr, zbr, fr, wr, c, pxr[c] - pxr[c - 1] + pyr[c] - pyu[c], step)


def tv_pdhg_many(fs, wt, lam, zs, iters):
    """tv_pdhg of each frame fs[j] (the same weights wt) into zs[j] (holding each start): the
    copies of the uncertainty's bootstrap (recon.estimators.spatial.regulariser_variance) side by
    side on the thread pool, one whole serial run per copy and thread."""
    n, h, w = fs.shape

    def one(j: int) -> None:
        tv_pdhg(fs[j], wt, lam, zs[j], iters, np.empty((h, w)), np.empty((h, w)), np.empty((h, w)))

    on_threads(one, n)


@njit(inline="always", cache=True, nogil=True)
def _dual(pxr, pyr, c, gx, gy, step, lam):
    """tv_pdhg's dual step at one pixel of a row."""
    ax = pxr[c] + step * gx
    ay = pyr[c] + step * gy
    nrm = math.sqrt(ax * ax + ay * ay)
    sc = 1.0 if nrm <= lam else lam / nrm
    pxr[c] = ax * sc
    pyr[c] = ay * sc


@njit(inline="always", cache=True, nogil=True)
def _primal(zr, zbr, fr, wr, c, div, step):
    """tv_pdhg's primal step at one pixel of a row, given its divergence."""
    old = zr[c]
    v = old + step * div
    a = step * wr[c]
    new = (v + a * fr[c]) / (1.0 + a)
    zr[c] = new
    zbr[c] = 2.0 * new - old
