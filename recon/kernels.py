"""The numba helpers every estimator's kernels share (theirs sit beside each estimator in
:mod:`recon.estimators`): binning, a pixel's distinct bins and their counts, blocks of pixels,
sorting, the small linear algebra, and the shift's Fisher information.

Every kernel works from per-pixel photon lists (:class:`Photons`, CSR:
``bins[offsets[p]:offsets[p+1]]`` are the bin indices, all inside ``[0, M)``) turned into sorted (bin, count) pairs by ONE helper,
:func:`pixel_bins` (scratch from :func:`pixel_scratch`), and from the 1-D pulse tables of
:class:`recon.model.PulseKernel`, so ``S_i^T y = sum over photons of g[k - i]`` and no N x N matrix
is ever formed. The shape, after stumpy's ``stump`` -> ``_stump``: a public kernel, plain Python
(validated, allocated arguments and scratch), -> the compiled pixel loop, nogil, that
``recon.pixelwise.over_threads`` runs over slices of whole BLOCKs of pixels side by side -> a
per-pixel fit made of small named helpers. No ``parallel=True`` loop (numba compiles its body
twice) and no compiled level that only allocates and calls the next: numba compiles every called
function on its own, then optimises and emits the whole call tree again at each level above it.
Arguments are never literals where a callee is compiled (:data:`ZERO`): a literal's type is a
signature of its own.

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
from collections import namedtuple

import numpy as np
from numba import njit
from numba.core.extending import overload
from numba.cpython.unsafe.numbers import trailing_zeros

from spdepth.recon.model import FISHER_RHO0, FISHER_STEPS

#: Pixels per block: the threads of a fit take slices of whole blocks (recon.pixelwise.over_threads).
BLOCK = 64
#: Sorts of up to this many items are insertion sorts, longer ones heap sorts (a million detections
#: must not be quadratic). At the 50 detections of `spdepth bench surfaces` insertion sort took 1.1
#: us a pixel against 2.5 for the heap sort (--reflectors 1: 102k -> 122k pixels/s at 64, not 48).
SMALL_SORT = 64
#: :func:`unique_bins` marks a pixel's detections in a bitmap of the window's bins when the 64-bin
#: words they span are at most this many per detection; above, it sorts them (:func:`unique_counts`)
BITMAP_WORDS = 4
#: A zero of numba type int64 for kernels to pass where a literal 0 would go: numba compiles a
#: callee once per argument type, and a literal's type (Literal[int](0), also a loop-carried
#: variable's before type inference unifies it) is another than int64's: one more compile of
#: the callee and of everything it calls, each for seconds on a cold cache.
ZERO = np.int64(0)
#: numba options of a kernel helper that only compiled code calls: no CPython and C wrappers, which
#: numba otherwise compiles for every function, each unboxing all its arguments (a helper taking
#: ml's 26-field tables had one unboxing them all, compiled and emitted for nothing): ml's cold
#: compile 17.7-18.9 -> 16.3-16.6 s of CPU with its search's helpers so. Such a function cannot be
#: called from Python (the call crashes), so none that a test or Python code calls gets it.
INNER = dict(no_cpython_wrapper=True, no_cfunc_wrapper=True)


# ------------------------------------------------------------------------------------------------
# binning and a pixel's distinct bins


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
        _sift_down(a, ZERO, end)


@njit(cache=True, nogil=True, **INNER)
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


@njit(cache=True, nogil=True, _nrt=False, **INNER)
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
    return marked_in_order(bits, wlo, whi, tally, kb, kw)


@njit(cache=True, nogil=True, _nrt=False, inline="always")
def marked_in_order(bits, wlo, whi, tally, kb, kw):
    """The bins marked in the bitmap words wlo..whi (one bit a bin), ascending, into kb and their
    tallies into kw; returns how many. The words and the tallies read are left zero."""
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


# ------------------------------------------------------------------------------------------------
# a pixel's photons

#: Every pixel's in-window detections as bins (CSR): ``bins[offsets[p]:offsets[p + 1]]`` (int64,
#: inside [0, M)) are pixel p's, in detection order; P = offsets.size - 1.
#: The ``weights`` of :class:`Photons` whose bins are per detection (every detection counts one).
NO_WEIGHTS = np.empty(0)
#: A chunk's pixels (CSR): ``bins[offsets[p]:offsets[p + 1]]`` per detection (``weights`` empty,
#: the default), or a pixel's distinct bins, ascending, with their counts in ``weights`` (a histogram
#: cube, or one corrected for pile-up: ``recon.counts.CountStore.binned``).
Photons = namedtuple("Photons", ["bins", "offsets", "weights"], defaults=(NO_WEIGHTS,))
#: :func:`pixel_bins`' scratch and result (:func:`pixel_scratch`): kb[:nu] a pixel's distinct bins,
#: ascending, kw[:nu] their counts (float64); tmp, tally, bits its working space.
PixelBins = namedtuple("PixelBins", ["kb", "kw", "tmp", "tally", "bits"])


@njit(cache=True, nogil=True)
def pixel_scratch(maxn, m):
    """:class:`PixelBins` for pixels of at most maxn detections in a window of m bins (tally and bits
    zero, as :func:`unique_bins` needs them and leaves them)."""
    n = max(maxn, 1)
    return PixelBins(np.empty(n, np.int64), np.empty(n, np.float64), np.empty(n, np.int64),
                     np.zeros(m, np.int64), np.zeros(m // 64 + 1, np.uint64))


@njit(cache=True, nogil=True, inline="always")
def pixel_bins(ph, p, px):
    """(nu, n): pixel p's distinct bins and their counts into px.kb[:nu], px.kw[:nu] (ascending), and
    its detections n (rounded, for pairs whose counts are not whole). The one place every
    estimator reads a pixel's photons from."""
    o0 = ph.offsets[p]
    o1 = ph.offsets[p + 1]
    if ph.weights.size == 0:
        return unique_bins(ph.bins, o0, o1, px.tally, px.bits, px.tmp, px.kb, px.kw), o1 - o0
    # (bin, count) pairs already: copied as they are; the detections are the counts' sum
    n = 0.0
    for a in range(o1 - o0):
        px.kb[a] = ph.bins[o0 + a]
        w = ph.weights[o0 + a]
        px.kw[a] = w
        n += w
    return o1 - o0, np.int64(n + 0.5)


@njit(cache=True, nogil=True, inline="always")
def n_blocks(ph):
    """Blocks of BLOCK pixels over ph's pixels (recon.detect's loop over them)."""
    return (ph.offsets.size - 1 + BLOCK - 1) // BLOCK


@njit(cache=True, nogil=True, inline="always")
def block_pixels(ph, blk):
    """The pixels of block blk (a range)."""
    return range(blk * BLOCK, min(ph.offsets.size - 1, (blk + 1) * BLOCK))


# ------------------------------------------------------------------------------------------------
# small linear algebra


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


@njit(cache=True, nogil=True, inline="always")
def _rotate(x, n, p, q, c, s):
    """Columns p and q of x[:n] rotated by (c, s): a Jacobi sweep's step (rows through x.T)."""
    for k in range(n):
        xkp = x[k, p]
        xkq = x[k, q]
        x[k, p] = c * xkp - s * xkq
        x[k, q] = s * xkp + c * xkq


@njit(cache=True, nogil=True, **INNER)
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
                _rotate(a, n, p, q, c, s)
                _rotate(a.T, n, p, q, c, s)
                _rotate(vecs, n, p, q, c, s)
    for p in range(n):
        vals[p] = a[p, p]


@njit(cache=True, nogil=True, **INNER)
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


# ------------------------------------------------------------------------------------------------
# the shift's Fisher information


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
    return shift_var(i00, i01, i02, i11, i12, i22, np.bool_(bg > 0.0))


@njit(cache=True, nogil=True, _nrt=False, error_model="numpy", **INNER)
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
        return shift_var(a * ftab[last, 0], -ftab[last, 1], 0.0, ftab[last, 3] / a, 0.0, 0.0, np.bool_(False))
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
                             (s5 + (m - nk)) * ib, np.bool_(True))
    return fisher_var(shift, a, bg, m, g, dg, off)


# ------------------------------------------------------------------------------------------------
# searching and sorting


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


@njit(cache=True, nogil=True, inline="always")
def _after(keys, x, y):
    """x goes after y in :func:`sort_desc`'s order: smaller key, or the same key and larger index."""
    return keys[x] < keys[y] or (keys[x] == keys[y] and x > y)


@njit(cache=True, nogil=True, **INNER)
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
def sort_desc(keys, idx, n):
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
            _sift_after(keys, idx, ZERO, end)
        return
    for a in range(1, n):
        v = idx[a]
        kv = keys[v]
        b = a - 1
        while b >= 0 and keys[idx[b]] < kv:
            idx[b + 1] = idx[b]
            b -= 1
        idx[b + 1] = v
