"""Numba kernels of the per-pixel estimators. Plain arrays in, disjoint per-pixel outputs out; all
validation and allocation of outputs happens in :mod:`recon.estimate`.

Every kernel works from per-pixel photon lists (CSR: ``bins[offsets[p]:offsets[p+1]]`` are the bin
indices, all inside ``[0, M)``) turned into sorted (bin, count) pairs, and from the 1-D pulse tables
of :class:`recon.model.PulseKernel`, so ``S_i^T y = sum over photons of g[k - i]`` and no N x N
matrix is ever formed. Pixels are processed in blocks of BLOCK under ``prange``; each block owns its
scratch arrays.

Shift ``i`` means the pulse centroid is at the centre of bin ``i`` (0 <= i < M).

The leaf helpers that ml calls per pixel and that allocate nothing are compiled with ``_nrt=False``
(numba's switch for its reference counting, off): numba otherwise adds an atomic increment and
decrement of every array argument at each call, which it cannot prune around the calls to ``log``;
that was 10% of ml's time at 15 detections a pixel. ml's functions are also compiled with
``error_model="numpy"``: a division by zero gives inf or NaN instead of raising, so numba adds no
zero-divisor test to each division (3% of ml; its divisors are rates and column sums, never 0).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange
from numba.core.extending import overload
from numba.cpython.unsafe.numbers import trailing_zeros

from spdepth.recon.model import FISHER_RHO0, FISHER_STEPS


BLOCK = 64
#: Sorts of up to this many items are insertion sorts, longer ones heap sorts (a million detections
#: must not be quadratic). At the 50 detections of `spdepth bench surfaces` insertion sort took 1.1
#: us a pixel against 2.5 for the heap sort (--reflectors 1: 102k -> 122k pixels/s at 64, not 48).
SMALL_SORT = 64
#: :func:`unique_bins` marks a pixel's detections in a bitmap of the window's bins when the 64-bin
#: words they span are at most this many per detection; above, it sorts them (:func:`unique_counts`)
BITMAP_WORDS = 4
#: LMF on a log-concave pulse: up to this many distinct photon bins, hill-climb from their mean
#: (cost O(photons x steps), steps < bins); above it, bisect (O(photons log bins)).
CLIMB_MAX_PHOTONS = 64


# ------------------------------------------------------------------------------------------------
# shared helpers


@njit(cache=True, nogil=True)
def window_bins(times, offsets, start, stop, width, n_bins, max_photons, out_bins, out_offsets):
    """First ``max_photons`` (all when < 0) detections of each pixel with ``start <= t < stop``, as
    bin indices ``floor((t - start) / width)`` capped at n_bins - 1, in detection order: one pass
    doing what PhotonStore.first_in_window followed by Binning.bin_index do (same floating-point
    expressions, so the same bins). out_bins needs times.size entries, out_offsets offsets.size;
    returns the number of detections kept (out_bins[:n] is the CSR list under out_offsets)."""
    npix = offsets.size - 1
    n = 0
    out_offsets[0] = 0
    for p in range(npix):
        kept = 0
        for q in range(offsets[p], offsets[p + 1]):
            if max_photons >= 0 and kept >= max_photons:
                break
            t = times[q]
            if t >= start and t < stop:
                k = math.floor((t - start) / width)
                if k > n_bins - 1:
                    k = n_bins - 1
                out_bins[n] = np.int64(k)
                n += 1
                kept += 1
        out_offsets[p + 1] = n
    return n



@njit(cache=True, nogil=True)
def heap_sort(a, n):
    """Sort a[:n] ascending in place: heapsort, O(n log n) with no recursion and no allocation.
    Used instead of np.sort inside kernels: numba compiles numpy's sort (its quicksort and the
    shape checks of the slice assignment) into every kernel that calls it, seconds on a cold cache
    and more symbols to load from a warm one, for a path only big pixels take."""
    for root in range(n // 2 - 1, -1, -1):
        _sift_down(a, root, n)
    for end in range(n - 1, 0, -1):
        v = a[0]
        a[0] = a[end]
        a[end] = v
        _sift_down(a, 0, end)


@njit(cache=True, nogil=True)
def _sift_down(a, root, n):
    v = a[root]
    while True:
        c = 2 * root + 1
        if c >= n:
            break
        if c + 1 < n and a[c + 1] > a[c]:
            c += 1
        if not a[c] > v:
            break
        a[root] = a[c]
        root = c
    a[root] = v


@njit(cache=True, nogil=True)
def sort_run(a, lo, hi):
    """Sort a[lo:hi] ascending in place: insertion sort for the usual handful of detections,
    :func:`heap_sort` above SMALL_SORT (a million detections must not be quadratic)."""
    if hi - lo > SMALL_SORT:
        heap_sort(a[lo:hi], hi - lo)
        return
    for j in range(lo + 1, hi):
        v = a[j]
        b = j - 1
        while b >= lo and a[b] > v:
            a[b + 1] = a[b]
            b -= 1
        a[b + 1] = v


@njit(cache=True, nogil=True, _nrt=False)
def unique_counts(bins, o0, o1, tmp, kb, kw):
    """Sorted distinct bins of one pixel and their counts into kb/kw; returns how many.

    tmp, kb, kw need at least o1 - o0 entries."""
    n = o1 - o0
    if n == 0:
        return 0
    for a in range(n):
        tmp[a] = bins[o0 + a]
    sort_run(tmp, 0, n)
    nu = 0
    kb[0] = tmp[0]
    kw[0] = 1.0
    for a in range(1, n):
        if tmp[a] == kb[nu]:
            kw[nu] += 1.0
        else:
            nu += 1
            kb[nu] = tmp[a]
            kw[nu] = 1.0
    return nu + 1


_BIT = np.uint64(1)


def lowest_set_bit(x):
    """Index of the lowest set bit of x > 0: LLVM's count of trailing zeros where compiled (below),
    plain Python under NUMBA_DISABLE_JIT (when debugging a kernel)."""
    x = int(x)
    return (x & -x).bit_length() - 1


@overload(lowest_set_bit)
def _lowest_set_bit_compiled(x):
    return lambda x: trailing_zeros(x)


@njit(cache=True, nogil=True, _nrt=False)
def unique_bins(bins, o0, o1, tally, bits, tmp, kb, kw):
    """:func:`unique_counts`'s result (kb, kw, how many) without a sort when the detections lie close
    enough (BITMAP_WORDS): each detection is counted in tally and marked in the bitmap bits (one bit
    a window bin), and the words they span are read back in bin order, a set bit at a time. That
    is O(detections + words); an insertion sort of a usual pixel's 15 detections costs a branch
    mispredicted per detection (0.3 us, more than lmf's whole search). tally (int64, one per window
    bin) and bits (uint64, one per 64 bins) must be zero, and are left zero."""
    n = o1 - o0
    if n == 0:
        return 0
    lo = bins[o0]
    hi = lo
    for i in range(o0 + 1, o1):
        v = bins[i]
        lo = min(lo, v)
        hi = max(hi, v)
    wlo = lo >> 6
    whi = hi >> 6
    if whi - wlo >= BITMAP_WORDS * n:
        return unique_counts(bins, o0, o1, tmp, kb, kw)
    for i in range(o0, o1):
        k = bins[i]
        tally[k] += 1
        bits[k >> 6] |= _BIT << np.uint64(k & 63)
    nu = 0
    for w in range(wlo, whi + 1):
        x = bits[w]
        if x == 0:
            continue
        bits[w] = 0
        while x != 0:
            k = (w << 6) + lowest_set_bit(x)     # the next bin in order
            kb[nu] = k
            kw[nu] = tally[k]
            tally[k] = 0
            nu += 1
            x &= x - _BIT
    return nu


@njit(cache=True, nogil=True)
def col_dot(i, j, m, pp, off, nk):
    """S_i^T S_j for the unit-area kernel g (rows restricted to the window's m bins), from the prefix
    table pp (row d + dmax holds cumulative sums over offset index of g[o] g[o - d], d = j - i)."""
    d = j - i
    dmax = (pp.shape[0] - 1) // 2
    if d > dmax or d < -dmax:
        return 0.0
    lo = -i + off
    hi = m - i + off
    if lo < 0:
        lo = 0
    if lo > nk:
        lo = nk
    if hi < 0:
        hi = 0
    if hi > nk:
        hi = nk
    return pp[d + dmax, hi] - pp[d + dmax, lo]


@njit(cache=True, nogil=True)
def sym_eig(a, n, vecs, vals):
    """Eigen-decomposition of the leading n x n block of symmetric a (cyclic Jacobi; a is
    overwritten). Columns of vecs are eigenvectors. n is at most 2K+1, so this is a few dozen flops."""
    for r in range(n):
        for c in range(n):
            vecs[r, c] = 1.0 if r == c else 0.0
    for _sweep in range(50):
        off = 0.0
        for p in range(n):
            for q in range(p + 1, n):
                off += a[p, q] * a[p, q]
        scale = 0.0
        for p in range(n):
            scale += a[p, p] * a[p, p]
        if off <= 1e-30 * scale or off == 0.0:
            break
        for p in range(n):
            for q in range(p + 1, n):
                apq = a[p, q]
                if apq == 0.0:
                    continue
                theta = (a[q, q] - a[p, p]) / (2.0 * apq)
                t = (1.0 if theta >= 0 else -1.0) / (abs(theta) + math.sqrt(theta * theta + 1.0))
                c = 1.0 / math.sqrt(t * t + 1.0)
                s = t * c
                for k in range(n):
                    akp = a[k, p]
                    akq = a[k, q]
                    a[k, p] = c * akp - s * akq
                    a[k, q] = s * akp + c * akq
                for k in range(n):
                    apk = a[p, k]
                    aqk = a[q, k]
                    a[p, k] = c * apk - s * aqk
                    a[q, k] = s * apk + c * aqk
                for k in range(n):
                    vkp = vecs[k, p]
                    vkq = vecs[k, q]
                    vecs[k, p] = c * vkp - s * vkq
                    vecs[k, q] = s * vkp + c * vkq
    for p in range(n):
        vals[p] = a[p, p]


@njit(cache=True, nogil=True)
def pinv_solve(gram, rhs, n, work, vecs, vals, out):
    """out = pinv(A) y from the Gram matrix A^T A (n x n) and rhs = A^T y, dropping directions whose
    eigenvalue is below 1e-12 of the largest (singular value ratio 1e-6): what pinv's tolerance does
    for numerically collinear columns, at the precision a Gram matrix can resolve."""
    # Fast path: when det > 1e-10 trace^n every eigenvalue exceeds 1e-10 of the largest
    # (lambda_min >= det / lambda_max^(n-1) and lambda_max <= trace), so no direction is dropped and
    # pinv is the inverse: a Cholesky solve gives it at a fraction of the Jacobi sweeps' cost.
    tr = 0.0
    for r in range(n):
        tr += gram[r, r]
    det = 1.0
    chol_ok = tr > 0.0
    for c in range(n if chol_ok else 0):
        d = gram[c, c]
        for k in range(c):
            d -= work[c, k] * work[c, k]
        if not d > 0.0:
            chol_ok = False
            break
        det *= d / tr
        lc = math.sqrt(d)
        work[c, c] = lc
        for r in range(c + 1, n):
            s = gram[r, c]
            for k in range(c):
                s -= work[r, k] * work[c, k]
            work[r, c] = s / lc
    if chol_ok and det > 1e-10:
        for r in range(n):          # L z = rhs
            s = rhs[r]
            for k in range(r):
                s -= work[r, k] * vals[k]
            vals[r] = s / work[r, r]
        for r in range(n - 1, -1, -1):   # L^T out = z
            s = vals[r]
            for k in range(r + 1, n):
                s -= work[k, r] * out[k]
            out[r] = s / work[r, r]
        return
    for r in range(n):
        for c in range(n):
            work[r, c] = gram[r, c]
    sym_eig(work, n, vecs, vals)
    lmax = 0.0
    for p in range(n):
        if vals[p] > lmax:
            lmax = vals[p]
    for r in range(n):
        out[r] = 0.0
    if lmax <= 0.0:
        return
    for p in range(n):
        if vals[p] > 1e-12 * lmax:
            proj = 0.0
            for r in range(n):
                proj += vecs[r, p] * rhs[r]
            proj /= vals[p]
            for r in range(n):
                out[r] += proj * vecs[r, p]


@njit(cache=True, nogil=True, _nrt=False, error_model="numpy")
def fisher_var(shift, a, bg, m, g, dg, off):
    """Variance (bins^2) of the shift from the Poisson Fisher information of
    lambda_k = a g[k - shift] + bg over the window's m bins, with a (and bg when > 0) profiled out.
    NaN when the information is degenerate (no signal)."""
    if not a > 0.0:
        return np.nan
    nk = g.size
    # offsets t whose bin k = shift + t - off lies in the window: a plain range, no per-t test
    tlo = max(0, off - shift)
    thi = min(nk, m - shift + off)
    i00 = 0.0
    i01 = 0.0
    i02 = 0.0
    i11 = 0.0
    i12 = 0.0
    i22 = 0.0
    n_in = max(0, thi - tlo)
    for t in range(tlo, thi):
        lam = a * g[t] + bg
        # one reciprocal instead of six divisions (this loop dominated a 15-photon pixel's cost)
        inv = 1.0 / lam if lam > 0.0 else 0.0
        d0 = -a * dg[t]
        d1 = g[t]
        i00 += d0 * d0 * inv
        i01 += d0 * d1 * inv
        i02 += d0 * inv
        i11 += d1 * d1 * inv
        i12 += d1 * inv
        i22 += inv
    if bg > 0.0:
        i22 += (m - n_in) / bg
    return shift_var(i00, i01, i02, i11, i12, i22, bg > 0.0)


@njit(cache=True, nogil=True, _nrt=False, error_model="numpy")
def shift_var(i00, i01, i02, i11, i12, i22, with_bg):
    """1 / the shift's information once the amplitude (and the background, with_bg) are profiled
    out of the Fisher matrix [[i00, i01, i02], [., i11, i12], [., ., i22]] (shift, a, bg); NaN when
    degenerate."""
    if with_bg:
        det12 = i11 * i22 - i12 * i12
        if det12 <= 0.0:
            return np.nan
        # Schur complement of the (a, bg) block
        schur = i00 - (i01 * (i22 * i01 - i12 * i02) + i02 * (i11 * i02 - i12 * i01)) / det12
    else:
        if i11 <= 0.0:
            return np.nan
        schur = i00 - i01 * i01 / i11
    if not schur > 0.0:
        return np.nan
    return 1.0 / schur


@njit(cache=True, nogil=True, _nrt=False, inline="always", error_model="numpy")
def _catmull_rom(tab, i, c, w0, w1, w2, w3):
    """Column c of tab between rows i and i + 1, weights w0..w3 on rows i - 1..i + 2."""
    return w0 * tab[i - 1, c] + w1 * tab[i, c] + w2 * tab[i + 1, c] + w3 * tab[i + 2, c]


@njit(cache=True, nogil=True, _nrt=False, error_model="numpy")
def fisher_tab(shift, a, bg, m, g, dg, off, ftab):
    """:func:`fisher_var`, its sums read from ftab (:func:`fisher_table`) when the pulse at shift
    lies inside the window: for bg > 0, Catmull-Rom between the rows around log(a / bg), within
    ~4e-6 (relative) of the loop's variance, instead of a division per bin of the pulse (a tenth of
    ml's time at 15 detections a pixel); for bg = 0 (every detection under the pulse: a quarter of
    the pixels at 15 detections and SBR 10) from the last row, the same sums as the loop's, in
    another order. Otherwise (the window's edges, a / bg off the table) the loop."""
    nk = g.size
    last = ftab.shape[0] - 1
    if a > 0.0 and bg == 0.0 and shift >= off and shift - off + nk <= m:
        # the rate is a g_t: i00 = a sum dg^2 / g, i01 = -sum dg, i11 = sum g / a (the limit row)
        return shift_var(a * ftab[last, 0], -ftab[last, 1], 0.0, ftab[last, 3] / a, 0.0, 0.0, False)
    if a > 0.0 and bg > 0.0 and shift >= off and shift - off + nk <= m:
        x = (math.log(a / bg) - FISHER_RHO0) * FISHER_STEPS
        if x >= 1.0 and x < last - 2:
            i = int(x)
            t = x - i
            t2 = t * t
            t3 = t2 * t
            w0 = -0.5 * t3 + t2 - 0.5 * t
            w1 = 1.5 * t3 - 2.5 * t2 + 1.0
            w2 = -1.5 * t3 + 2.0 * t2 + 0.5 * t
            w3 = 0.5 * t3 - 0.5 * t2
            s0 = _catmull_rom(ftab, i, 0, w0, w1, w2, w3)
            s1 = _catmull_rom(ftab, i, 1, w0, w1, w2, w3)
            s2 = _catmull_rom(ftab, i, 2, w0, w1, w2, w3)
            s3 = _catmull_rom(ftab, i, 3, w0, w1, w2, w3)
            s4 = _catmull_rom(ftab, i, 4, w0, w1, w2, w3)
            s5 = _catmull_rom(ftab, i, 5, w0, w1, w2, w3)
            ib = 1.0 / bg
            return shift_var(a * a * s0 * ib, -a * s1 * ib, -a * s2 * ib, s3 * ib, s4 * ib,
                             (s5 + (m - nk)) * ib, True)
    return fisher_var(shift, a, bg, m, g, dg, off)


# ------------------------------------------------------------------------------------------------
# log-matched filter, eq. (11): argmax_i sum_k y_k log S_{k,i}


@njit(cache=True, nogil=True)
def _lmf_score(kb, kw, nu, i, logg, m):
    s = 0.0
    # unsigned index: spares numba's negative-index wraparound on each gather (the index is >= 0)
    for u in range(nu):
        s += kw[u] * logg[np.uint64(kb[u] - i + m - 1)]
    return s


@njit(cache=True, nogil=True)
def _lmf_block(blk, bins, offsets, m, logg, log_concave, maxn, out_shift, out_var, out_n, npix, nt):
    """The pixels of block blk of :func:`lmf_kernel`, compiled on its own and called from the
    kernel's parallel loop (see :func:`_ml_block`)."""
    tmp = np.empty(max(maxn, 1), np.int64)
    tally = np.zeros(m, np.int64)
    bits = np.zeros(m // 64 + 1, np.uint64)
    kb = np.empty(max(maxn, 1), np.int64)
    kw = np.empty(max(maxn, 1), np.float64)
    for p in range(blk * BLOCK, min(npix, (blk + 1) * BLOCK)):
        o0 = offsets[p]
        o1 = offsets[p + 1]
        out_n[p] = o1 - o0
        nu = unique_bins(bins, o0, o1, tally, bits, tmp, kb, kw)
        if nu == 0:
            out_shift[p] = -1
            out_var[p] = np.nan
            continue
        if log_concave and nu > CLIMB_MAX_PHOTONS:
            # a sum of concave sequences is concave: its first argmax is the first shift where
            # the score stops rising, found by bisection in O(photons log bins) (a climb from
            # the photons' mean could walk O(bins) steps of O(photons) each on a huge pixel)
            lo = 0
            hi = m - 1
            while lo < hi:
                mid = (lo + hi) // 2
                if _lmf_score(kb, kw, nu, mid + 1, logg, m) > _lmf_score(kb, kw, nu, mid, logg, m):
                    lo = mid + 1
                else:
                    hi = mid
            i = lo
        elif log_concave:
            # few photons: climb from their mean bin (a handful of steps, cheaper than bisection)
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
        else:
            i = 0
            best = _lmf_score(kb, kw, nu, 0, logg, m)
            for j in range(1, m):
                s = _lmf_score(kb, kw, nu, j, logg, m)
                if s > best:
                    best = s
                    i = j
        out_shift[p] = i
        curv = 0.0
        for u in range(nu):
            t = kb[u] - i + m - 1
            tl = max(t - 1, 0)
            th = min(t + 1, nt - 1)
            if th - tl == 2:
                curv += kw[u] * (logg[th] - 2.0 * logg[t] + logg[tl])
        out_var[p] = -1.0 / curv if curv < 0.0 else np.nan


@njit(parallel=True, cache=True, nogil=True)
def lmf_kernel(bins, offsets, m, logg, log_concave, maxn, out_shift, out_var, out_n):
    """Log-matched filter per pixel. out_shift: argmax shift (int64, -1 without photons), out_var:
    shift variance in bins^2 from the observed curvature of the log-likelihood, out_n: photons."""
    npix = offsets.size - 1
    nblk = (npix + BLOCK - 1) // BLOCK
    nt = logg.size
    for blk in prange(nblk):
        _lmf_block(np.int64(blk), bins, offsets, m, logg, log_concave, maxn, out_shift, out_var, out_n,
                   npix, nt)


# ------------------------------------------------------------------------------------------------
# Algorithm 1 (uos) and its K-sparse generalization


@njit(cache=True, nogil=True, _nrt=False, error_model="numpy")
def photon_intervals(kb, nu, lo_reach, hi_reach, m, ivlo, ivhi):
    """Merge the shift ranges ``[k - lo_reach, k + hi_reach]`` (clipped to [0, m)) of the sorted
    distinct photon bins kb[:nu] into disjoint ascending intervals ivlo/ivhi; returns how many.
    Outside them ``S_i^T y`` is exactly zero (no photon under column i)."""
    niv = 0
    for u in range(nu):
        lo = max(0, kb[u] - lo_reach)
        hi = min(m - 1, kb[u] + hi_reach)
        if niv > 0 and lo <= ivhi[niv - 1] + 1:
            if hi > ivhi[niv - 1]:
                ivhi[niv - 1] = hi
        else:
            ivlo[niv] = lo
            ivhi[niv] = hi
            niv += 1
    return niv


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


@njit(cache=True, nogil=True)
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
    bi = -1
    for t in range(niv):
        best, bi = _scan_range(ivlo[t], ivhi[t], best, bi, cvec, colsum, bgc, j, aj, wlo, whi, clipped,
                               acorr, nk, m, pp, off)
    far_bound = 0.0 - bgc * cmin
    if best > far_bound:
        return bi
    best, bi = _scan_range(0, m - 1, -np.inf, -1, cvec, colsum, bgc, j, aj, wlo, whi, clipped,
                           acorr, nk, m, pp, off)
    return bi


@njit(cache=True, nogil=True)
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


@njit(cache=True, nogil=True)
def uos_proxy(prox, cvec, colsum, bgc, supp, amp, ns, inv_g2, acorr, nk, m, pp, off):
    """The dense proxy A^T (y - A x) for K > 1: ``cvec - bgc * colsum`` minus each support
    column's inner products (the autocorrelation for a column inside the window)."""
    for i in range(m):
        prox[i] = cvec[i] - bgc * colsum[i]
    for s in range(ns):
        j = supp[s]
        aj = amp[s] * inv_g2
        ilo = max(0, j - (nk - 1))
        ihi = min(m - 1, j + (nk - 1))
        if j - off >= 0 and j + (nk - 1 - off) < m:
            for i in range(ilo, ihi + 1):
                prox[i] -= aj * acorr[i - j + nk - 1]
        else:
            for i in range(ilo, ihi + 1):
                prox[i] -= aj * col_dot(i, j, m, pp, off, nk)


@njit(cache=True, nogil=True)
def top_k(prox, m, kk, taken, newi):
    """The kk largest entries of prox[:m] into newi (first index among ties, like a descending
    sort; -1 when fewer); taken is all False before and after."""
    for r in range(kk):
        best = -np.inf
        bi = -1
        for i in range(m):
            if not taken[i] and prox[i] > best:
                best = prox[i]
                bi = i
        newi[r] = bi
        if bi >= 0:
            taken[bi] = True
    for r in range(kk):
        if newi[r] >= 0:
            taken[newi[r]] = False


@njit(cache=True, nogil=True, inline="always")
def union_support(newi, kk, supp, ns, om):
    """Omega = new indices U previous support, sorted and distinct, into om; returns its size."""
    nd = 0
    for r in range(kk):
        if newi[r] >= 0:
            om[nd] = newi[r]
            nd += 1
    for s in range(ns):
        dup = False
        for t in range(nd):
            if om[t] == supp[s]:
                dup = True
        if not dup:
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
            if sol[a] > best:
                dup = False
                for t in range(nn):
                    if nsupp[t] == a:
                        dup = True
                if not dup:
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
        found = False
        for t in range(nn):
            if supp[s] == nsupp[t]:
                found = True
        if not found:
            diff += amp[s] * amp[s]
    xnorm2 = nbg * nbg
    for t in range(nn):
        xnorm2 += namp[t] * namp[t]
    return diff, xnorm2


@njit(cache=True, nogil=True)
def merge_close(supp, amp, ns, merge_bins, pos):
    """Sort the returns by shift, then merge those closer than merge_bins into one at their
    amplitude-weighted position (amp[:nm] summed, pos[:nm] positions); returns nm."""
    for a in range(1, ns):
        v = supp[a]
        va = amp[a]
        b = a - 1
        while b >= 0 and supp[b] > v:
            supp[b + 1] = supp[b]
            amp[b + 1] = amp[b]
            b -= 1
        supp[b + 1] = v
        amp[b + 1] = va
    for s in range(ns):
        pos[s] = supp[s]
    nm = 0
    for s in range(ns):
        if nm > 0 and pos[s] - pos[nm - 1] < merge_bins:
            at = amp[nm - 1] + amp[s]
            pos[nm - 1] = (pos[nm - 1] * amp[nm - 1] + pos[s] * amp[s]) / at
            amp[nm - 1] = at
        else:
            pos[nm] = pos[s]
            amp[nm] = amp[s]
            nm += 1
    return nm


@njit(cache=True, nogil=True)
def return_llr(s, pos, amp, nm, bg, kb, kw, nu, g, off, nk, colsum):
    """Poisson log-likelihood lost by dropping return s of nm (unit-area amplitudes)."""
    js = int(pos[s] + 0.5)
    llr = -amp[s] * colsum[js]
    for u in range(nu):
        lam = bg
        mine = 0.0
        for t in range(nm):
            jt = int(pos[t] + 0.5)
            d = kb[u] - jt + off
            if d >= 0 and d < nk:
                v = amp[t] * g[d]
                lam += v
                if t == s:
                    mine = v
        rest = lam - mine
        if mine > 0.0:
            if rest <= 0.0:
                return np.inf
            llr += kw[u] * math.log(lam / rest)
    return llr


@njit(parallel=True, cache=True, nogil=True)
def uos_kernel(bins, offsets, m, g, off, gmax, colsum, pp, dg, n_refl, delta, max_iter,
               merge_bins, llr_min, maxn,
               out_shift, out_amp, out_bg, out_iter, out_conv, out_var, out_n):
    """Union-of-subspaces greedy pursuit (Algorithm 1) with K = n_refl depth columns.

    The pursuit runs on the published code's scaling (columns g / gmax, peak 1) so delta means what
    it means there. Outputs per pixel p and return r (r < K):
    out_shift[p, r]: shift (bins, float; NaN none), sorted ascending;
    out_amp[p, r]: amplitude on the unit-area kernel (expected signal detections of an unclipped
    pulse); out_bg[p]: background per bin; out_iter[p]: iterations; out_conv[p]: converged;
    out_var[p, r]: shift variance (bins^2, Fisher information); out_n[p]: photons.
    For K > 1, returns closer than merge_bins are merged (amplitude-weighted) and a return is kept only
    if dropping it costs more than llr_min in Poisson log-likelihood.

    Per pixel: uos_scatter (S^T y), then iterations of: proxy argmax (uos1_argmax for K = 1,
    pruned; uos_proxy + top_k for K > 1) -> union_support -> solve_support -> keep_largest ->
    change_norm; then refit_nonneg if the last fit was clipped, and for K > 1 merge_close and
    return_llr.
    """
    npix = offsets.size - 1
    nblk = (npix + BLOCK - 1) // BLOCK
    nk = g.size
    kk = n_refl
    inv_gmax = 1.0 / gmax
    inv_g2 = inv_gmax * inv_gmax
    # full autocorrelation of g, lag index d + nk - 1
    acorr = np.zeros(2 * nk - 1)
    for d in range(-(nk - 1), nk):
        acc = 0.0
        for t in range(nk):
            if 0 <= t - d < nk:
                acc += g[t] * g[t - d]
        acorr[d + nk - 1] = acc
    grev = g[::-1].copy()
    cmin = colsum.min()
    for blk in prange(nblk):
        tmp = np.empty(max(maxn, 1), np.int64)
        tally = np.zeros(m, np.int64)
        bits = np.zeros(m // 64 + 1, np.uint64)
        kb = np.empty(max(maxn, 1), np.int64)
        kw = np.empty(max(maxn, 1), np.float64)
        cvec = np.zeros(m)
        prox = np.empty(m)
        ivlo = np.empty(max(maxn, 1), np.int64)
        ivhi = np.empty(max(maxn, 1), np.int64)
        supp = np.empty(kk, np.int64)
        amp = np.empty(kk)
        nsupp = np.empty(kk, np.int64)
        namp = np.empty(kk)
        newi = np.empty(kk, np.int64)
        om = np.empty(3 * kk, np.int64)
        gram = np.empty((3 * kk + 1, 3 * kk + 1))
        work = np.empty((3 * kk + 1, 3 * kk + 1))
        vecs = np.empty((3 * kk + 1, 3 * kk + 1))
        vals = np.empty(3 * kk + 1)
        rhs = np.empty(3 * kk + 1)
        sol = np.empty(3 * kk + 1)
        taken = np.zeros(m, np.bool_)
        pos = np.empty(kk)
        for p in range(blk * BLOCK, min(npix, (blk + 1) * BLOCK)):
            o0 = offsets[p]
            o1 = offsets[p + 1]
            out_n[p] = o1 - o0
            for r in range(kk):
                out_shift[p, r] = np.nan
                out_amp[p, r] = 0.0
                out_var[p, r] = np.nan
            nu = unique_bins(bins, o0, o1, tally, bits, tmp, kb, kw)
            if nu == 0:
                out_bg[p] = 0.0
                out_iter[p] = 0
                out_conv[p] = True
                continue
            ntot = 0.0
            for u in range(nu):
                ntot += kw[u]
            # cvec is all zero between pixels: only the photon intervals are touched, reset below
            niv = photon_intervals(kb, nu, nk - 1 - off, off, m, ivlo, ivhi)
            uos_scatter(kb, kw, nu, cvec, grev, inv_gmax, nk, off, m)
            ns = 0          # support size
            bg = 0.0
            it = 0
            clipped_ls = False
            conv = False
            while it < max_iter:
                it += 1
                # the proxy A^T (y - A x) and its largest entries
                if kk == 1:
                    newi[0] = uos1_argmax(cvec, colsum, cmin, bg * inv_gmax, ns, supp[0] if ns > 0 else 0,
                                          amp[0] * inv_g2 if ns > 0 else 0.0, acorr, nk, m, pp, off,
                                          ivlo, ivhi, niv)
                else:
                    uos_proxy(prox, cvec, colsum, bg * inv_gmax, supp, amp, ns, inv_g2, acorr, nk, m, pp, off)
                    top_k(prox, m, kk, taken, newi)
                nd = union_support(newi, kk, supp, ns, om)
                clipped_ls = solve_support(om, nd, cvec, colsum, ntot, m, pp, off, nk, inv_gmax, inv_g2,
                                           gram, rhs, work, vecs, vals, sol)
                nn = keep_largest(sol, nd, kk, om, nsupp, namp)
                nbg = sol[nd] if sol[nd] > 0.0 else 0.0
                diff, xnorm2 = change_norm(supp, amp, ns, nsupp, namp, nn, bg, nbg)
                ns = nn
                for t in range(nn):
                    supp[t] = nsupp[t]
                    amp[t] = namp[t]
                bg = nbg
                # relative for large x: the paper's absolute test (peak-1 columns) reads a change of
                # 1e-2 in an amplitude of 10^4 as not converged, so high-count pixels hit the cap
                if diff < delta * max(1.0, xnorm2):
                    conv = True
                    break
            if clipped_ls:
                ns, bg = refit_nonneg(supp, amp, ns, bg > 0.0, cvec, colsum, ntot, m, pp, off, nk,
                                      inv_gmax, inv_g2, gram, rhs, work, vecs, vals, sol)
            for t in range(niv):
                cvec[ivlo[t]:ivhi[t] + 1] = 0.0
            out_iter[p] = it
            out_conv[p] = conv
            out_bg[p] = bg
            # amplitudes on the unit-area kernel
            for s in range(ns):
                amp[s] = amp[s] * inv_gmax
            if kk > 1 and ns > 1:
                nm = merge_close(supp, amp, ns, merge_bins, pos)
                r = 0
                for s in range(nm):
                    # kept only if dropping it (from all nm merged returns) costs more than llr_min
                    if return_llr(s, pos, amp, nm, bg, kb, kw, nu, g, off, nk, colsum) > llr_min:
                        out_shift[p, r] = pos[s]
                        out_amp[p, r] = amp[s]
                        out_var[p, r] = fisher_var(int(pos[s] + 0.5), amp[s], bg, m, g, dg, off)
                        r += 1
            elif ns >= 1:
                out_shift[p, 0] = supp[0]
                out_amp[p, 0] = amp[0]
                out_var[p, 0] = fisher_var(supp[0], amp[0], bg, m, g, dg, off)


# ------------------------------------------------------------------------------------------------
# exact pixelwise Poisson ML, eq. (9), global over shifts


#: ml: logliks within this share of each other are a tie (the pulse on either of two lone
#: detections gives an exact one, which solves from different starts leave ~1e-16 apart), settled
#: for the latest of the tied integer shifts, as the exhaustive scan upwards settled them: a shift
#: whose bound could tie the best is solved, not pruned. (The likelihood cannot tell tied shifts
#: apart; which one is reported moves the error of 2-detection pixels with the scene: on the bench
#: report's bust at SBR 10, the earliest gave 30.7 cm MAE at 2 detections per pixel, the latest
#: 12.7, because its background comes before the bust more often than after.)
ML_TIE = 1e-13

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
        if wu <= ML_POWER_MAX:
            # a bin detected a few times (common under a return): its rate once per detection,
            # chosen by selects (a loop of unknown length mispredicted its exit)
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


@njit(cache=True, nogil=True, _nrt=False, error_model="numpy")
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


@njit(cache=True, nogil=True, _nrt=False, error_model="numpy")
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


@njit(cache=True, nogil=True, error_model="numpy")
def first_above(a, n, v, strict):
    """First index i of the sorted a[:n] with a[i] > v (strict) or a[i] >= v (not strict), n when
    none: np.searchsorted's right and left sides, written out because numba compiles string
    handling into every kernel for searchsorted's ``side`` argument (seconds on a cold cache)."""
    lo = 0
    hi = n
    while lo < hi:
        mid = (lo + hi) // 2
        if a[mid] > v or (not strict and a[mid] == v):
            hi = mid
        else:
            lo = mid + 1
    return lo


@njit(cache=True, nogil=True, error_model="numpy")
def _photon_range(kb, nu, lo, hi):
    """[ua, ub): the sorted distinct photon bins kb[:nu] lying in [lo, hi] (binary search)."""
    return first_above(kb, nu, lo, False), first_above(kb, nu, hi, True)


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
    return mix_ml(kb, kw, ua, ub, w_out, g, off - i, 1, 0, 1.0 / colsum[i], uni, s0, cut)


@njit(cache=True, nogil=True, _nrt=False, error_model="numpy")
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


#: ml: the shares that :func:`mix_bounds` takes at least and at most: a solve can end at 0 or 1 exactly,
#: where the tangent's terms diverge; any share inside (0, 1) gives a valid bound, one near the
#: optimum a tight one
ML_SHARE_CLAMP = 1e-3


@njit(cache=True, nogil=True, _nrt=False, error_model="numpy")
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
        ua = first_above(kb, nu, -((-qa) // step) - base, False)
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


@njit(cache=True, nogil=True, inline="always")
def _after(keys, x, y):
    """x goes after y in :func:`_sort_desc`'s order: smaller key, or the same key and larger index."""
    return keys[x] < keys[y] or (keys[x] == keys[y] and x > y)


@njit(cache=True, nogil=True)
def _sift_after(keys, idx, root, n):
    v = idx[root]
    while True:
        c = 2 * root + 1
        if c >= n:
            break
        if c + 1 < n and _after(keys, idx[c + 1], idx[c]):
            c += 1
        if not _after(keys, idx[c], v):
            break
        idx[root] = idx[c]
        root = c
    idx[root] = v


@njit(cache=True, nogil=True, _nrt=False)
def _sort_desc(keys, idx, n):
    """Reorder idx[:n] (ascending on entry) by keys[idx] descending, equal keys in index order
    (a stable sort's result): insertion sort for the usual dozen, heapsort on that total order for
    more (numpy's argsort would compile its mergesort into the kernel, see :func:`heap_sort`)."""
    if n > SMALL_SORT:
        # a max-heap on "goes after": its root, the last in order, moves to the end each round
        for root in range(n // 2 - 1, -1, -1):
            _sift_after(keys, idx, root, n)
        for end in range(n - 1, 0, -1):
            v = idx[0]
            idx[0] = idx[end]
            idx[end] = v
            _sift_after(keys, idx, 0, end)
        return
    for a in range(1, n):
        v = idx[a]
        kv = keys[v]
        b = a - 1
        while b >= 0 and keys[idx[b]] < kv:
            idx[b + 1] = idx[b]
            b -= 1
        idx[b + 1] = v


@njit(cache=True, nogil=True, error_model="numpy")
def _ml_block(blk, bins, offsets, m, g, off, logg_int, dlo, dhi, colsum, log_colsum, fine, fine_colsum,
              fsteps, fine_climb, stabs, sdiff, dg, ftab, maxn, out_shift, out_amp, out_bg, out_var, out_n, nf,
              npix, logm, fine_rev, uni, inv_fine_colsum, ia, ib, upos, grev, inv_colsum):
    """The pixels of block blk of :func:`ml_kernel` (its arguments and tables). Compiled on its
    own and called from the kernel's parallel loop: numba compiles a parallel loop's body a
    second time, 5-7 s of ml's cold compile when the body was this code (the same speed either
    way, unlike uos, whose loops lose the noalias numba gives a parallel body)."""
    tmp = np.empty(max(maxn, 1), np.int64)
    tally = np.zeros(m, np.int64)
    bits = np.zeros(m // 64 + 1, np.uint64)
    kb = np.empty(max(maxn, 1), np.int64)
    kw = np.empty(max(maxn, 1), np.float64)
    ivlo = np.empty(max(maxn, 1), np.int64)
    ivhi = np.empty(max(maxn, 1), np.int64)
    ivmax = np.empty(max(maxn, 1))
    acc = np.zeros(m)           # zero between pixels: only the photons' intervals are touched
    cand = np.empty(m, np.int64)
    lls = np.empty(nf)
    exact = np.empty(nf, np.bool_)
    r0s = np.empty(max(maxn, 1), np.int64)
    ws = np.empty(max(maxn, 1))
    bnd = np.empty(max(ML_RUN, nf))
    surv = np.empty(m, np.int64)
    ssum = np.zeros((4, m))     # zero between pixels: only a sweep's span is touched
    nk = g.size
    nshares = stabs.shape[0]
    key = np.empty(m)
    fidx = np.empty(nf, np.int64)
    for p in range(blk * BLOCK, min(npix, (blk + 1) * BLOCK)):
        o0 = offsets[p]
        o1 = offsets[p + 1]
        out_n[p] = o1 - o0
        out_shift[p] = np.nan
        out_amp[p] = 0.0
        out_var[p] = np.nan
        nu = unique_bins(bins, o0, o1, tally, bits, tmp, kb, kw)
        if nu == 0:
            out_bg[p] = 0.0
            continue
        ntot = 0.0
        for u in range(nu):
            ntot += kw[u]
        floor_ll = -ntot * logm          # s = 0: all background
        best_ll = floor_ll
        best_i = -1
        best_s = 0.0
        if dhi >= dlo:
            # U(i) - floor over the shifts i = k - d, d in [dlo, dhi], of the photons
            niv = photon_intervals(kb, nu, dhi, -dlo, m, ivlo, ivhi)
            for u in range(nu):
                k = kb[u]
                wu = kw[u]
                if k - dhi >= ia and k - dlo <= ib:
                    # all of this photon's shifts have the interior column sum: one contiguous
                    # add of the precomputed terms (the same floating-point values; adding 0.0
                    # where a term is not positive leaves acc as the test below would)
                    seg = acc[k - dhi:k - dlo + 1]
                    for t in range(seg.size):
                        seg[t] += wu * upos[t]
                else:
                    for d in range(max(dlo, k - m + 1), min(dhi, k) + 1):
                        i = k - d
                        v = logg_int[d + off] - log_colsum[i] + logm
                        if v > 0.0:
                            acc[i] += wu * v
            # the best bound first (the first of equal ones), without listing the shifts: most
            # of the photons' reach has a positive bound, so a test per shift would be a coin flip
            i1 = -1
            amax = 0.0
            for t in range(niv):
                # each interval's best too: the survivors below are sought only in intervals
                # whose best can beat the likelihood found (a lone background detection's reach
                # seldom can)
                imax = 0.0
                ii = -1
                for i in range(ivlo[t], ivhi[t] + 1):
                    if acc[i] > imax:
                        imax = acc[i]
                        ii = i
                ivmax[t] = imax
                if imax > amax:
                    amax = imax
                    i1 = ii
            if i1 >= 0:
                # Newton starts at the share of the photons whose bound term is positive there
                # (the return's, and the background's under it), not at 1/2: two passes fewer
                nsig = 0.0
                for u in range(nu):
                    d = kb[u] - i1
                    if d >= dlo and d <= dhi and logg_int[d + off] - log_colsum[i1] + logm > 0.0:
                        nsig += kw[u]
                s0 = min(max(nsig / ntot, ML_START_CLAMP), 1.0 - ML_START_CLAMP)
                s, ll = _ml_at_int(kb, kw, nu, ntot, i1, g, off, colsum, uni, s0, -np.inf)
                if ll > best_ll:
                    best_ll = ll
                    best_i = i1
                    best_s = s
                # the shifts whose bound beats it or could tie it (see ML_TIE), best bound first.
                # Each also gets the tangent bound of its first Newton pass at about the best
                # share so far: much tighter than U, which overshoots the likelihood by a few nats
                # at every shift of a return and at every shift of a background detection's reach,
                # so most are dropped without a solver call. Runs of interior shifts read it from
                # tables at the tabulated share nearest the best (:func:`share_bound`); a run that
                # reaches the window's edges (column sums differ there) gets it at the best share
                # in one sweep (:func:`mix_bounds`)
                tie = ML_TIE * max(1.0, abs(best_ll))
                js = min(int(best_s * nshares), nshares - 1)
                sj = (js + 0.5) / nshares
                sb = min(max(best_s, ML_SHARE_CLAMP), 1.0 - ML_SHARE_CLAMP)
                ns = 0
                for t in range(niv):
                    if not floor_ll + ivmax[t] > best_ll - tie:
                        continue
                    for i in range(ivlo[t], ivhi[t] + 1):
                        if i != i1 and acc[i] > 0.0 and floor_ll + acc[i] > best_ll - tie:
                            surv[ns] = i
                            ns += 1
                            key[i] = floor_ll + acc[i]
                # many survivors (much background: U overshoots at every shift a detection
                # reaches): the tabulated sums of every interior shift at once, as U's are built,
                # each detection adding its terms over its reach
                sweep = ns > ML_SWEEP_PER_DETECTION * nu
                if sweep:
                    slo, shi = share_sweep(kb, kw, nu, off, ia, ib, sdiff, js, ssum)
                # else in runs of nearby survivors (ascending), so the photons that reach a run are
                # found once: at SBR 0.1 a shift's reach holds a sixth of a pixel's detections
                nc = 0
                t = 0
                while t < ns:
                    wa = surv[t]
                    t2 = t + 1
                    while t2 < ns and surv[t2] - surv[t2 - 1] <= ML_RUN_GAP and surv[t2] - wa < ML_RUN:
                        t2 += 1
                    wb = surv[t2 - 1]
                    if wa >= ia and wb <= ib and sweep:
                        for tt in range(t, t2):
                            i = surv[tt]
                            key[i] = min(key[i], swept_bound(ssum, i, ntot, stabs, js, sj))
                    elif wa >= ia and wb <= ib:
                        ua, ub = _photon_range(kb, nu, wa - off, wb - off + nk - 1)
                        w_out = ntot
                        for u in range(ua, ub):
                            w_out -= kw[u]
                        for tt in range(t, t2):
                            i = surv[tt]
                            key[i] = min(key[i], share_bound(kb, kw, ua, ub, w_out, i, off, stabs, js, sj))
                    else:
                        mix_bounds(kb, kw, nu, ntot, grev, off - wa, 1, 0, wb - wa + 1, inv_colsum[wa:], uni,
                                   sb, r0s, ws, bnd)
                        for tt in range(t, t2):
                            i = surv[tt]
                            key[i] = min(key[i], bnd[i - wa])
                    for tt in range(t, t2):
                        i = surv[tt]
                        if key[i] > best_ll - tie:
                            cand[nc] = i
                            nc += 1
                    t = t2
                if sweep:
                    ssum[:, slo:shi + 1] = 0.0
                _sort_desc(key, cand, nc)
                for t in range(nc):
                    i = cand[t]
                    tie = ML_TIE * max(1.0, abs(best_ll))
                    if key[i] <= best_ll - tie:
                        break
                    s, ll = _ml_at_int(kb, kw, nu, ntot, i, g, off, colsum, uni, best_s, best_ll - tie)
                    if ll > best_ll + tie or (best_i < 0 and ll > best_ll):
                        best_ll = ll
                        best_i = i
                        best_s = s
                    elif ll >= best_ll - tie and best_i >= 0 and i > best_i:
                        best_ll = max(best_ll, ll)
                        best_i = i
                        best_s = s
            for t in range(niv):
                acc[ivlo[t]:ivhi[t] + 1] = 0.0
        if best_i < 0 or best_s <= 0.0:
            out_bg[p] = ntot * uni
            continue
        # sub-bin: the best of the fine shifts strictly between the integer neighbours, then a
        # parabola through its exact neighbours
        qlo = -fsteps if best_i > 0 else 0
        qhi = fsteps if best_i < m - 1 else 0
        bq = 0
        bll = best_ll
        bs = best_s
        lls[fsteps] = best_ll
        exact[:] = False
        exact[fsteps] = True
        if fine_climb:
            # a smooth pulse: climb from the integer optimum while the likelihood rises, upwards,
            # then downwards when the first step up did not rise; every step solved exactly (each
            # is a neighbour of the next, as the parabola needs)
            # first towards the side the return's detections lean to (their mean offset from
            # best_i): the step the other way is then seldom solved for nothing
            lean = 0.0
            for u in range(nu):
                d = kb[u] - best_i
                if d >= dlo and d <= dhi:
                    lean += kw[u] * d
            first = 1 if lean >= 0.0 else -1
            for d in (first, -first):
                q = d
                sprev = bs
                while q >= qlo and q <= qhi:
                    # the share moves almost linearly with the shift: starting at the line through
                    # the last two steps' shares saves a Newton pass
                    s0 = 1.0 if bs == 1.0 else min(max(2.0 * bs - sprev, ML_SHARE_CLAMP), 1.0 - ML_SHARE_CLAMP)
                    s, ll = _ml_at_fine(kb, kw, nu, ntot, best_i, q, fine, off, fine_colsum, fsteps, uni,
                                        s0, -np.inf)
                    lls[q + fsteps] = ll
                    exact[q + fsteps] = True
                    if not ll > bll + ML_TIE * max(1.0, abs(bll)):
                        break
                    bll = ll
                    bq = q
                    sprev = bs
                    bs = s
                    q += d
                if bq != 0:
                    break
        else:
            # any pulse: every fine shift's first-pass bound in one sweep, solved best bound first
            # (the optimum usually comes first, and its likelihood then cuts the rest)
            nq = qhi - qlo + 1
            sb = min(max(best_s, ML_SHARE_CLAMP), 1.0 - ML_SHARE_CLAMP)
            mix_bounds(kb, kw, nu, ntot, fine_rev, off - best_i, fsteps, qlo, nq,
                       inv_fine_colsum[best_i * fsteps + qlo:], uni, sb, r0s, ws, bnd)
            nfc = 0
            for t in range(nq):
                if qlo + t != 0:
                    fidx[nfc] = t
                    nfc += 1
            _sort_desc(bnd, fidx, nfc)
            for a in range(nfc):
                t = fidx[a]
                q = qlo + t
                tie = ML_TIE * max(1.0, abs(bll))
                if bnd[t] <= bll - tie:
                    break
                s, ll = _ml_at_fine(kb, kw, nu, ntot, best_i, q, fine, off, fine_colsum, fsteps, uni, bs,
                                    bll - tie)
                lls[q + fsteps] = ll
                exact[q + fsteps] = ll > -np.inf
                # ties as a scan upwards from qlo would take them: 0, else the smallest q
                if ll > bll + tie:
                    bll = ll
                    bq = q
                    bs = s
                elif ll >= bll - tie and q > bq:
                    bll = max(bll, ll)
                    bq = q
                    bs = s
        frac = 0.0
        if bq - 1 >= qlo and bq + 1 <= qhi:
            for q in (bq - 1, bq + 1):
                if not exact[q + fsteps]:
                    s, ll = _ml_at_fine(kb, kw, nu, ntot, best_i, q, fine, off, fine_colsum, fsteps,
                                        uni, bs, -np.inf)
                    lls[q + fsteps] = ll
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
        out_var[p] = fisher_tab(int(tau + 0.5), a, bg, m, g, dg, off, ftab)


@njit(parallel=True, cache=True, nogil=True)
def ml_kernel(bins, offsets, m, g, off, logg_int, dlo, dhi, colsum, log_colsum, fine, fine_colsum,
              fsteps, fine_climb, dg, ftab, maxn, out_shift, out_amp, out_bg, out_var, out_n):
    """Exact Poisson ML over (shift, a >= 0, B >= 0), global over all integer shifts, refined to
    1/fsteps bin and then by a parabola.

    Branch and bound, exact: for every shift, U(i) = sum_u w_u max(log(g_u / C_i), -log M) (+ const)
    bounds the profile likelihood from above (split the linear term a C + B M evenly over the
    photons and maximise each photon's term alone), and only offsets d with g[d] M > min C
    (dlo..dhi) contribute above the floor, so U is built over the photons' reach only (intervals of
    shifts, not all M). After the best bound's shift is solved, the shifts whose U beats it get the
    tangent bound of a Newton pass at about that solve's share (a bound, by concavity in the signal
    share): read from tables for interior shifts (:func:`share_bound`), in sweeps over runs of
    nearby shifts at the window's edges (:func:`mix_bounds`); shifts are then
    solved best bound first and the search stops at the first bound that cannot beat the best
    likelihood found; each solve also stops after its first Newton pass when its own tangent cannot
    beat it. The best 1/fsteps shift within a bin of the integer optimum: for any pulse, every fine
    shift gets its tangent bound in one sweep too and they are solved best bound first under the
    same test; with ``fine_climb`` (set by the caller for a smooth pulse, see ML_CLIMB_RMS_BINS) a
    climb from the integer optimum while the exact likelihood rises finds it with fewer solves.
    Then a parabola through its exact neighbours. ftab: :func:`fisher_table` of the pulse (the
    variance, :func:`fisher_tab`). Outputs: out_shift (bins, NaN none), out_amp (unit-area
    amplitude), out_bg (per bin), out_var (bins^2), out_n (photons).
    """
    npix = offsets.size - 1
    nblk = (npix + BLOCK - 1) // BLOCK
    uni = 1.0 / m
    logm = math.log(m)
    nf = 2 * fsteps + 1
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
    sdiff = share_diffs(stabs)
    # the tables of mix_bounds: the pulse tables reversed and the reciprocal column sums
    grev = g[::-1].copy()
    fine_rev = fine[::-1].copy()
    inv_colsum = 1.0 / colsum
    inv_fine_colsum = 1.0 / fine_colsum
    for blk in prange(nblk):
        _ml_block(np.int64(blk), bins, offsets, m, g, off, logg_int, dlo, dhi, colsum, log_colsum, fine,
                  fine_colsum, fsteps, fine_climb, stabs, sdiff, dg, ftab, maxn, out_shift, out_amp, out_bg,
                  out_var, out_n, nf, npix, logm, fine_rev, uni, inv_fine_colsum, ia, ib, upos, grev, inv_colsum)
