"""Is there a return? The per-pixel detection test and the honest uncertainty of every depth.

Every estimator's maps pass through :func:`decide_maps` (called by :func:`recon.estimate.reconstruct`,
the one place maps are assembled), so the decision and the uncertainty mean the same for all of them.

**The test** is the one ``--reflectors auto`` uses for K = 0 against 1 (:mod:`recon.estimators.surfaces_fit`): the
statistic is the Poisson log-likelihood gain of one return over a flat background,
``max_s max_{a, B >= 0} log L(s, a, B) - max_B log L(B)``, its shift searched over every whole bin of
the window (ml's exact branch and bound, :func:`recon.estimators.ml_kernels.integer_optimum`) and its
amplitude and background profiled; a pixel holds a return when the gain exceeds
:func:`auto_threshold_nats` at the false-alarm rate ``ReconSettings.false_alarm``
(default 1e-3 per pixel: about one background-only pixel in a thousand is taken for a return).
Where the neighbours' support applies (next), the own test and the support each get half of it,
so that the rate is the pixel's and not each rule's (:func:`decide_maps`).

**The neighbours' support.** A pixel that fails on its own detections holds a return when the
detections of the 24 pixels around it (5 x 5, SUPPORT_RADIUS), pooled with its own left out, pass
the same test within NEIGHBOUR_HALF_CORES pulse-core widths of the pixel's own estimate, at half the
false-alarm rate for that span of shifts (:func:`neighbour_support`). Leaving its own detections out keeps the two independent under the
null: the estimate chose nothing among the neighbours' detections. A surface that several pixels
see lends each its evidence (tower_9km.mat: ml reports a depth on 24.3% of pixels, 19.3% by the own
test, of the 39.8% with any detection); the depth stays the pixel's own estimate. A pixel whose own estimate lies
elsewhere (a background detection beside a wall) is not supported.

**Where the neighbours see returns.** A pixel that fails both (a background cluster beat its faint
return for its own best shift) holds a return when its own detections pass the test within the
region where its 8 neighbours see returns (:func:`neighbour_fill`: within the support's span of a
shift at which their pooled detections, its own left out, pass the support test) at the
false-alarm rate ``ReconSettings.neighbour_false_alarm`` (default 0.05) for that region's span of shifts; its depth is then ml's best
within the region, whatever the estimator. Background alone all around passes only where the
neighbours passed the support's test somewhere too (measured below); beside a surface a
pixel without a return of its own at those shifts is given one at that rate at most (a
faint wall with holes, test_recon_detect: holes 4.8 -> 4.8%, the wall's pixels 37.0 -> 39.0%).
art_top.mat, ml: a depth on 28.0 -> 34.6% of pixels, halves within 3 / 1 sigma 96.7 / 65.7% ->
96.6 / 65.0% on 606 -> 922 pixels; tower_9km.mat 25.2% with it. The thresholds count the search
over shifts by Rice's formula (:func:`auto_threshold_nats`): on
frames of background alone (10 / 60 detections a pixel) at 1e-3 the own test and the support, at
half of it each, pass on 0.53e-3 / 0.76e-3 of the pixels in all, and with this rule 0.80e-3 /
0.93e-3 (at the whole rate each: 1.73e-3 / 1.60e-3 and 2.04e-3 / 2.09e-3; art_top.mat 34.6 ->
34.3%, the tower 25.2% either way).

**The uncertainty** of a reported depth is the largest of three spreads, each used only where it
exceeds the estimator's own (its Fisher or sandwich variance) beyond its resolution:

- the likelihood's over the whole window: the 68.27% and (halved) 95.45% quantiles of |s - estimate|
  under the likelihood of the shift at the best signal share, with a flat prior (a shift that sees
  no detection costs the whole return, n log(1 - pi)). Where the likelihood has several peaks (low
  SBR: a background cluster nearly as likely as the return) the far ones widen it. Its shifts come
  from one sweep of tabulated log rates (:func:`_spread`); those more than log M + 12 nats below
  the peak are left out (a shift no detection reaches within the pulse's offsets dlo..dhi, where
  its rate beats the background's, lies below ntot log(1/M) and is skipped unseen when that is);
- the sandwich (robust) variance at the estimate: the detections' score spread over the curvature;
- a bootstrap's, on pixels of fewer than BOOT_MAX_N detections or with several likely peaks: the
  68.27% quantile of |s_b - estimate| over BOOTSTRAP resamples of the pixel's detections, s_b each
  resample's best shift; among several peaks (BOOT_MAX_N detections or more) only those that
  are returns in their own right (gain over the test's threshold) are candidates, and the
  spread is the larger of the 68.27% quantile and half the 95.45%, as the likelihood's: a pane
  and a wall behind it (two_layer_top.mat, ml halves within 3 sigma 92.5% -> 95.8%), not a
  background cluster, whose resamples' duplicates make coincidences the halves do not pick. The
  bootstrap sees what a model that fits badly hides from the likelihood: on tower_9km.mat
  returns spread over ~2 ns in pixels whose pulse core is 241 ps, and the halves of such a pixel
  chose different clusters, each with a "2 cm" sigma.

A pixel its neighbours support gets the same spreads of its own detections, taken only over the
shifts where its neighbours see returns (:func:`neighbour_region_kernel`: within the support's
span of a shift at which their pooled detections pass the support test): its depth lies there by
the support's rule, and its own likelihood's and bootstrap's far modes elsewhere, background
peaks it would not have been reported at, gave sigmas of metres and halves that agreed within
1 sigma on 94-100% (simulated daylight, art_top.mat). Split halves within 3 / 1 sigma, ml, with
this and the several-peaks rule above: tower_9km.mat 96.5 / 71.6% -> 95.5 / 68.6%, daylight
99.9 / 94.3% -> 99.3 / 71.7%, art_top.mat 100 / 100% -> 96.5 / 65.9% (median combined sigma
687 -> 2.4 cm), two_layer_top.mat 92.7 / 61.3% -> 95.8 / 64.2%. Measured without
truth by ``spdepth bench honesty FILE`` (each pixel's detections split in two
halves, reconstructed apart, agreement within 1 and 3 combined sigma).

Pixels of the spatial estimator keep their decision (their neighbours support them, which this
pixelwise test cannot see) and get the larger of the two uncertainties only where their own
detections alone would pass the test (elsewhere the pixel's own likelihood says nothing of the
neighbours' support). Several surfaces per pixel: the pixel's surfaces are dropped when the test
finds no return at all; the surfaces found keep their weak flags, and a pixelwise fit's get the
sandwich's and the bootstrap's spreads of each surface's own part of the window
(:func:`surface_spreads`) where they exceed its Fisher sigma; spatial's got them before its smoothing
(``recon.estimators.surfaces_fit``), which averages them.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections import namedtuple

import numpy as np
from numba import njit

from spdepth.recon.estimators.ml_bounds import ML_SCAN_ALL, _ml_at_int, _photon_range
from spdepth.recon.estimators.ml_kernels import integer_optimum, ml_scratch
from spdepth.recon.kernels import (INNER, NO_WEIGHTS, block_pixels, first_above, fisher_tab, heap_sort, n_blocks,
                                   photon_intervals, pixel_bins, pixel_scratch)
from spdepth.recon.maps import C_M_PER_S, PixelFlag
from spdepth.recon.model import FWHM_PER_RMS, Binning, Irf, build_kernel
from spdepth.recon.pixelwise import over_threads

#: spatial: the pixel's own likelihood spread replaces the estimator's uncertainty when it is more
#: than this many times larger (decide_maps).
SPATIAL_OVERRULE = 3.0
#: The test is not applied to windows shorter than this many FWHM of the response (time cannot tell
#: a return from background there; every pixel keeps the estimator's decision).
UNDECIDABLE_FWHM = 4.0
#: A pixel that fails the test on its own detections is given its neighbours' support within this
#: many pulse-core RMS widths of its own estimate (:func:`neighbour_support`).
NEIGHBOUR_HALF_CORES = 2.0
#: The neighbours' support pools the pixels within this many rows and columns (5 x 5, the pixel's own
#: left out), the regions where neighbours see returns those within REGION_RADIUS (3 x 3). Measured
#: against 3 x 3 for the support, share of pixels with a depth (ml) and halves within 3 / 1 sigma:
#: art_top.mat 30.2 -> 34.6% (each half alone 14.0 -> 18.5%; 96.9 / 66.2 -> 96.6 / 65.0%), the
#: daylight scene 60.2 -> 61.8% (99.4 / 71.3 -> 98.9 / 70.3%), chart_depth.mat 61.9 -> 62.3%
#: (81.8 -> 79.8% within 1), the tower 24.9 -> 25.2%, the mannequin 94.9 -> 95.8%; the regions over
#: 5 x 5 spread wider, and the faint wall's filled pixels fell to 90% within 3 sigma (95% or more
#: with 3 x 3), so they stay 3 x 3. The 256 x 256 daylight frame's decide_maps: 18% more CPU.
SUPPORT_RADIUS = 2
REGION_RADIUS = 1
#: The neighbours' support first tries these signal shares, in this order, on the tabulated log
#: rates (:func:`neighbour_gain_kernel`): a pooled gain over the threshold at one of them is
#: enough, and ml's solve at every shift is left for the pixels that pass at none.
SUPPORT_SHARES = (1 / 2, 7 / 8, 1 / 8)
#: ... over the threshold by more than this many nats: the fixed share's gain and the solve's
#: differ by rounding (about 1e-13 nats) and the solve's stop (ML_MODEL_TOL of the likelihood),
#: so no pixel within it of the threshold is decided by the tables.
SUPPORT_MARGIN = 1e-6
#: Rows a block of a frame needs beside it to decide its edge rows as the whole frame does
#: (``acq.distributed``'s halo).
NEIGHBOUR_ROWS = max(SUPPORT_RADIUS, REGION_RADIUS)
#: Pixels whose surfaces' spreads are taken at once (:func:`surface_spreads`: a region of shifts each).
SURFACE_CHUNK = 4096
#: Pixels pooled for the pulse model's dispersion (:func:`dispersion_terms`): about this many, every
#: (frame's pixels // this)-th of the frame; 7,600 pixels of a simulated bust gave it to 1%.
DISPERSION_PIXELS = 20_000
#: ... and it is said where its width ratio (its square root, by which the uncertainties scale) is
#: known to this relative standard error or better, across the pooled pixels (:func:`dispersion_of`),
#: from at least DISPERSION_MIN_PIXELS of them. (A floor of 200 pixels left a 14 x 14 crop of the
#: mannequin unscaled, uos's uncertainties 2.2x too wide, where its dispersion was 0.23 +- 0.02 against
#: the whole frame's 0.20.)
DISPERSION_MAX_SE = 0.1
DISPERSION_MIN_PIXELS = 10
#: The estimators whose uncertainties the pulse model's dispersion scales (:func:`dispersion_terms`).
DISPERSION_METHODS = ("ml", "uos")
#: ... and those whose depths are not the likelihood's optimum, nor have a background: lmf's. The
#: likelihood's terms at ml's search's shifts give theirs (:func:`search_dispersion_terms`), before
#: the test, whose likelihood spreads are then tempered by it (:func:`decide_maps`): the widths
#: scale, the distances between the likelihood's modes and lmf's depth (the background's pull on
#: it) stay. Scaling lmf's whole uncertainty instead, as ml's is, shrank those distances too: on
#: simulated returns with background and a pulse stated twice as wide 10.6% of the depths lay
#: within 1 sigma of the truth.
TEMPERED_METHODS = ("lmf",)
#: Bootstrap resamples of each pixel's detections (the spread of the best shift among them).
BOOTSTRAP = 40
#: Largest table (grid shifts x distinct bins) a pixel's bootstrap builds; larger pixels go without.
BOOT_MAX_TABLE = 2_000_000
#: The bootstrap looks for each resample's best shift among those whose likelihood is within this
#: many nats of the best (a resample of n detections moves a shift's log-likelihood by about its
#: square root; far below the best, none wins).
BOOT_NATS = 15.0
#: Relative sampling error of the bootstrap's 68% quantile from BOOTSTRAP resamples (about 1/sqrt(
#: 0.68 * BOOTSTRAP) plus the grid): a bootstrap spread counts only beyond it.
BOOT_NOISE = 0.25
#: The bootstrap runs on pixels of fewer detections than this, where the sandwich variance of a
#: few detections is itself too noisy to trust (its relative error about sqrt(2 / n), over 37%),
#: and on any pixel whose likelihood has several modes within BOOT_NATS of its peak; on one mode
#: of this many detections or more the spread is the sandwich variance's (their asymptotic
#: agreement), and the bootstrap, most of the test's time (40 resamples), is spared. Measured on
#: tower_9km.mat's split halves (ml, share within 3 sigma): bootstrap on pixels below 10
#: detections 94.6%, below 15 96.3%, below 20 and 30 96.4%, everywhere 96.4%.
BOOT_MAX_N = 15


#: The likelihood over shifts leaves out the shifts more than log M + this many nats below its
#: peak: all of them together weigh under e^-12 = 6e-6 of the peak shift alone, beside the 4.6%
#: beyond the 95.45% quantile.
SPREAD_NATS_BEYOND = 12.0
#: The log rates of the likelihood over shifts are tabulated at this many signal shares and
#: interpolated between them (:func:`_log_rates`).
RATE_SHARES = 256

#: A pixel's scratch for the likelihood over shifts (:func:`_spread`): the shifts evaluated
#: (ascending), their log-likelihoods and weights relative to the peak, the log rates by pulse offset (:func:`_log_rates`) and
#: those beyond the off-pulse rate's in shift order; the sweep's sums by shift (zero between
#: pixels) and the detections' reach as intervals of shifts.
#: What the test reads of ml's tables (:class:`recon.estimators.ml_kernels.MlTables`), on its own:
#: numba compiles every function a tuple is passed to for all its fields (ml's 26 took 12 s of CPU
#: on a cold cache to compile the test's functions).
DetTables = namedtuple("DetTables", ["m", "uni", "logm", "nk", "off", "g", "colsum", "inv_colsum", "ia", "ib",
                                     "dlo", "dhi", "fine", "fine_colsum", "fsteps"])


# the test's threshold: Rice's formula for the largest gain over a window's shifts
def search_false_alarm(gain_nats: float, window_bins: float, width_bins: float) -> float:
    """Chance that background alone passes ``gain_nats`` at some shift of a window of
    ``window_bins`` (Rice's formula for the test's field, a response of FWHM ``width_bins``: the
    module docstring of ``recon.estimators.surfaces_fit``, whose ``auto`` test it is), at most 1."""
    z = math.sqrt(2.0 * max(gain_nats, 0.0))
    sigma = max(width_bins, 1.0) / FWHM_PER_RMS
    ups = max(window_bins, 1.0) / (2.0 * math.pi * math.sqrt(2.0) * sigma) * math.exp(-gain_nats)
    return min(1.0, 0.5 * math.erfc(z / math.sqrt(2.0)) + ups)     # P(N > z) + upcrossings


@functools.lru_cache(maxsize=4096)
def auto_threshold_nats(false_alarm: float, window_bins: float, width_bins: float) -> float:
    """Gain (nats, half the statistic) a surface needs under the test (the module docstring of
    ``recon.estimators.surfaces_fit``), at ``false_alarm`` over a window of ``window_bins``;
    width_bins: the response's FWHM (bins). The
    root of :func:`search_false_alarm` (decreasing in the gain), by bisection."""
    if not false_alarm > 0:
        return math.inf
    lo, hi = 0.0, 1.0
    while search_false_alarm(hi, window_bins, width_bins) > false_alarm:
        hi *= 2.0
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        if search_false_alarm(mid, window_bins, width_bins) > false_alarm:
            lo = mid
        else:
            hi = mid
    return hi


def fwhm_bins(g: np.ndarray) -> int:
    """Full width at half maximum of the binned response (bins, contiguous around its peak)."""
    pk = int(np.argmax(g))
    half = 0.5 * g[pk]
    lo, hi = pk, pk
    while lo > 0 and g[lo - 1] >= half:
        lo -= 1
    while hi < g.size - 1 and g[hi + 1] >= half:
        hi += 1
    return hi - lo + 1


def det_tables(tabs) -> DetTables:
    """:class:`DetTables` of ml's tables ``tabs``."""
    return DetTables(*(getattr(tabs, f) for f in DetTables._fields))
SpreadScratch = namedtuple("SpreadScratch", ["pos", "logw", "wt", "row", "rrow", "acc", "ivlo", "ivhi"])


@njit(cache=True, nogil=True)
def rate_tables(tabs):
    """log(uni + s (g[d] / C - uni)) at the signal shares s = j / RATE_SHARES, j = 0..RATE_SHARES,
    and pulse offsets d (d = nk: off the pulse, rate 0), C the interior column sum: the rows
    :func:`_log_rates` interpolates (once per reconstruction, not a log per offset and pixel)."""
    T = tabs
    c = T.colsum[T.off] if 0 <= T.off < T.m else 1.0
    out = np.empty((RATE_SHARES + 1, T.nk + 1))
    for j in range(RATE_SHARES + 1):
        s = min(j / RATE_SHARES, 1.0 - 1e-12)
        for d in range(T.nk):
            out[j, d] = math.log(T.uni + s * (T.g[d] / c - T.uni))
        out[j, T.nk] = math.log(T.uni * (1.0 - s))
    return out


@njit(cache=True, nogil=True, _nrt=False, error_model="numpy", **INNER)
def _log_rates(s, tabs, rates, row):
    """row[d] = log(uni + s (g[d] / C - uni)), the log rate of a detection at pulse offset d at
    an interior shift (column sum C) and signal share s, interpolated between the two nearest
    rows of ``rates`` (:func:`rate_tables`; concave in s, so the chord lies below it by at most
    (1 / RATE_SHARES)^2 q^2 / 8 nats, q = e / lam: 2e-5 nats a detection at s = 0.9, 3e-3 at
    0.02), exact at the row's own share; row[nk] that of a detection off the pulse,
    log(uni (1 - s)), exact. The likelihood at a shift is then a sum of lookups."""
    T = tabs
    x = s * RATE_SHARES
    j = min(int(x), RATE_SHARES - 1)
    f = x - j
    a = rates[j]
    b = rates[j + 1]
    for d in range(T.nk):
        row[d] = a[d] + f * (b[d] - a[d])
    row[T.nk] = math.log(T.uni * (1.0 - s))


@njit(cache=True, nogil=True, _nrt=False, error_model="numpy", **INNER)
def _ll_at(kb, kw, nu, ntot, i, s, tabs, row):
    """The log-likelihood at integer shift i and the fixed signal share s (0 <= s < 1):
    sum_u w_u log(uni + s (r_u - uni)), r_u = g[k_u - i + off] / C_i (0 off the pulse), over the
    distinct bins kb[:nu] (counts kw, total ntot); ``row`` (:func:`_log_rates`) holds the terms
    of the interior shifts, whose column sum is the same. A big pixel reads only the photons
    under the pulse, the others as one term."""
    T = tabs
    nk = T.nk
    interior = T.ia <= i <= T.ib
    inv_c = T.inv_colsum[i]
    lo0 = row[nk]
    if nu <= ML_SCAN_ALL:
        ua, ub, w_out = 0, nu, 0.0
    else:
        ua, ub = _photon_range(kb, nu, i - T.off, i - T.off + nk - 1)
        w_out = ntot
        for u in range(ua, ub):
            w_out -= kw[u]
    ll = w_out * lo0
    base = T.off - i
    for u in range(ua, ub):
        j = kb[u] + base
        if j < 0 or j >= nk:
            ll += kw[u] * lo0
        elif interior:
            ll += kw[u] * row[j]
        else:
            ll += kw[u] * math.log(T.uni + s * (T.g[j] * inv_c - T.uni))
    return ll


@njit(cache=True, nogil=True, _nrt=False, error_model="numpy", **INNER)
def _sweep(kb, kw, nu, s, tabs, rates, row, rrow, acc, lo, hi):
    """Add into acc[i] (zero outside the last pixel's span) the log-likelihood beyond all
    detections off the pulse of the return at each shift i of lo..hi (interior: within ia..ib)
    at the signal share s: each detection adds its row of tabulated log rates over its reach,
    contiguous. Returns the log rate of a detection off the pulse (the likelihood at such a
    shift i is then ntot * that + acc[i]); row gets the log rates by pulse offset
    (:func:`_log_rates`)."""
    T = tabs
    nk = T.nk
    _log_rates(s, T, rates, row)
    lo0 = row[nk]
    for t in range(nk):
        rrow[t] = row[nk - 1 - t] - lo0     # shift order: i = k + off - (nk - 1) + t sees offset nk - 1 - t
    for u in range(nu):
        i0 = kb[u] + T.off - nk + 1
        t0 = max(0, lo - i0)
        t1 = min(nk, hi - i0 + 1)
        if t1 <= t0:
            continue
        seg = acc[i0 + t0:i0 + t1]
        sub = rrow[t0:t1]
        w = kw[u]
        for t in range(seg.size):
            seg[t] += w * sub[t]
    return lo0


@njit(cache=True, nogil=True, _nrt=False, error_model="numpy", **INNER)
def _sweep_clear(kb, nu, tabs, acc, lo, hi):
    """acc back to zero over the span :func:`_sweep` wrote for the detections kb (ascending) over
    the shifts lo..hi."""
    T = tabs
    lo = max(lo, kb[0] + T.off - T.nk + 1)
    hi = min(hi, kb[nu - 1] + T.off)
    if hi >= lo:
        acc[lo:hi + 1] = 0.0


@njit(cache=True, nogil=True, _nrt=False, error_model="numpy", **INNER)
def _spread(kb, kw, nu, ntot, e, s, best_i, tabs, rates, sp, region, temper):
    """The likelihood over the integer shifts at the fixed signal share s, to the power ``temper``
    (1: itself): (sd, ns, top), sd the larger of the 68.27% quantile and half the 95.45% quantile
    of |shift - e| under it (a flat prior), the ns shifts within (SPREAD_NATS_BEYOND + log M) /
    temper nats of its peak in sp (ascending, with
    their log-likelihoods; the rest weigh under e^-SPREAD_NATS_BEYOND together), and the peak.
    The interior shifts' likelihoods come from one sweep, each detection adding its log rates
    over its reach (contiguous adds into sp.acc, zero between pixels); the few at the
    window's edges, whose column sums differ, one by one."""
    T = tabs
    row = sp.row
    acc = sp.acc
    lo0 = _sweep(kb, kw, nu, s, T, rates, row, sp.rrow, acc, T.ia, T.ib)
    base_ll = ntot * lo0                 # every detection off the pulse
    ref = _ll_at(kb, kw, nu, ntot, best_i, s, T, row)
    bar = ref - (SPREAD_NATS_BEYOND + T.logm) / temper
    # a shift where no detection's rate beats the background's, uni (every detection at an offset
    # outside dlo..dhi), has a likelihood below ntot log uni; when
    # that floor lies below the bar only the shifts that some detection reaches within dlo..dhi
    # count, else (low SBR) every shift
    if -ntot * T.logm >= bar:
        sp.ivlo[0], sp.ivhi[0] = 0, T.m - 1
        niv = 1
    else:
        niv = photon_intervals(kb, nu, T.dhi, -T.dlo, T.m, sp.ivlo, sp.ivhi)
    ns = 0
    top = -math.inf
    for t in range(niv):
        for i in range(sp.ivlo[t], sp.ivhi[t] + 1):
            if T.ia <= i <= T.ib:
                v = base_ll + acc[i]
            else:
                v = _ll_at(kb, kw, nu, ntot, i, s, T, row)
            if v >= bar:
                sp.pos[ns] = i
                sp.logw[ns] = v
                top = max(top, v)
                ns += 1
    _sweep_clear(kb, nu, T, acc, T.ia, T.ib)
    if ns == 0:
        return np.nan, 0, top
    total = 0.0
    r = ns
    for k in range(ns):
        # outside the region the shifts weigh nothing (they stay in sp for _modes)
        sp.wt[k] = math.exp((sp.logw[k] - top) * temper) if region.size == 0 or region[sp.pos[k]] else 0.0
        total += sp.wt[k]
        if r == ns and sp.pos[k] >= e:
            r = k
    # the shifts in order of their distance from e: the two sides merged outwards
    left = r - 1
    mass = 0.0
    q68 = -1.0
    d = 0.0
    while left >= 0 or r < ns:
        if r >= ns or (left >= 0 and e - sp.pos[left] <= sp.pos[r] - e):
            k = left
            left -= 1
        else:
            k = r
            r += 1
        d = abs(sp.pos[k] - e)
        mass += sp.wt[k]
        if q68 < 0.0 and mass >= 0.6827 * total:
            q68 = d
        if mass >= 0.9545 * total:
            break
    if q68 < 0.0:
        q68 = d
    return max(q68, d / 2.0), ns, top


@njit(cache=True, nogil=True, _nrt=False, error_model="numpy", **INNER)
def _is_peak(sp, ns, k):
    """Whether the k-th shift of sp is a local maximum of the likelihood over shifts (a run of
    adjacent shifts with one maximum has one)."""
    v = sp.logw[k]
    up = k == 0 or sp.pos[k - 1] != sp.pos[k] - 1 or sp.logw[k - 1] < v
    down = k == ns - 1 or sp.pos[k + 1] != sp.pos[k] + 1 or sp.logw[k + 1] <= v
    return up and down


@njit(cache=True, nogil=True, _nrt=False, error_model="numpy", **INNER)
def _modes(sp, ns, top):
    """How many local maxima the likelihood over shifts has among the shifts within BOOT_NATS of
    its peak."""
    n = 0
    for k in range(ns):
        if sp.logw[k] >= top - BOOT_NATS and _is_peak(sp, ns, k):
            n += 1
    return n


@njit(cache=True, nogil=True, _nrt=False, error_model="numpy", **INNER)
def _interp(table, x):
    """table at fractional index x (linear), 0 outside."""
    if x < 0.0 or x > table.size - 1:
        return 0.0
    i = int(x)
    if i >= table.size - 1:
        return table[table.size - 1]
    f = x - i
    return table[i] * (1.0 - f) + table[i + 1] * f


@njit(cache=True, nogil=True, _nrt=False, error_model="numpy", **INNER)
def _term(k, e, s, c, tabs):
    """A detection's log rate ratio log(1 + s (g(k - e) M / C_e - 1)) at the fractional shift e
    (column sum c there)."""
    T = tabs
    gk = _interp(T.fine, (k - e + T.off) * T.fsteps)
    rk = gk * T.m / c - 1.0 if c > 0.0 else -1.0
    return math.log(max(1.0 + s * rk, 1e-300))


@njit(cache=True, nogil=True, _nrt=False, error_model="numpy", **INNER)
def _score_curv(kb, kw, nu, e, s, tabs):
    """(sum of the detections' squared scores, the likelihood's curvature) of the shift at e, by
    central differences half a bin wide: the sandwich variance's parts (:func:`_sandwich_var`),
    summed over pixels by :func:`pulse_dispersion`. NaN at the window's edge."""
    T = tabs
    h = 0.5
    if e - h < 0.0 or e + h > T.m - 1:
        return np.nan, np.nan, np.nan
    fs = T.fsteps
    c0 = _interp(T.fine_colsum, e * fs)
    cp = _interp(T.fine_colsum, (e + h) * fs)
    cm = _interp(T.fine_colsum, (e - h) * fs)
    curv = 0.0
    score2 = 0.0
    score = 0.0
    for j in range(nu):
        t0 = _term(kb[j], e, s, c0, T)
        tp = _term(kb[j], e + h, s, cp, T)
        tm = _term(kb[j], e - h, s, cm, T)
        curv -= kw[j] * (tp - 2.0 * t0 + tm) / (h * h)
        sj = (tp - tm) / (2.0 * h)
        score2 += kw[j] * sj * sj
        score += kw[j] * sj
    return score2, curv, score


@njit(cache=True, nogil=True, _nrt=False, error_model="numpy", **INNER)
def _sandwich_var(kb, kw, nu, e, s, tabs):
    """Robust (sandwich) variance of the shift at e (bins^2): the spread of the detections' scores
    over the likelihood's curvature squared (:func:`_score_curv`). It equals the Fisher variance
    when the pulse model fits, and grows where the detections spread wider than it (a mixed or
    tilted footprint, a response that differs from the model). NaN when not concave."""
    score2, curv, _ = _score_curv(kb, kw, nu, e, s, tabs)
    if not curv > 0.0:
        return np.nan
    return score2 / (curv * curv)


@njit(cache=True, nogil=True, inline="always")
def _uniform(state):
    """(next state, uniform in [0, 1)): splitmix64, a counter-based generator a few instructions
    long, seeded per pixel (numpy's generator cost more than the bootstrap's sums)."""
    state = state + np.uint64(0x9E3779B97F4A7C15)
    z = state
    z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    z = z ^ (z >> np.uint64(31))
    return state, float(z >> np.uint64(11)) * (1.0 / 9007199254740992.0)


@njit(cache=True, nogil=True, _nrt=False, error_model="numpy", **INNER)
def _candidate(sp, ns, k, bar, peaks_only, region):
    """Whether the k-th shift of sp is one of the bootstrap's candidates (:func:`_bootstrap_sd`)."""
    if sp.logw[k] < bar or (peaks_only and not _is_peak(sp, ns, k)):
        return False
    return region.size == 0 or region[sp.pos[k]] != 0


@njit(cache=True, nogil=True, _nrt=False, error_model="numpy", **INNER)
def _resample_best(cnt, nu, tab, n_cand, v):
    """The candidate (index) of the largest likelihood of a resample of counts cnt[:nu] by
    distinct bin, the first of equals: each bin's row of ``tab`` (nu x n_cand, flat) times its
    count summed in v."""
    v[:] = 0.0
    for u in range(nu):
        w = cnt[u]
        if w > 0.0:
            a0 = u * n_cand
            for q in range(n_cand):
                v[q] += w * tab[a0 + q]
    best = 0
    for q in range(1, n_cand):
        if v[q] > v[best]:
            best = q
    return best


@njit(cache=True, nogil=True, error_model="numpy", **INNER)
def _bootstrap_sd(kb, kw, nu, ntot, e, s, sp, ns, top, tabs, n_boot, seed, peaks_only, region, mode_thr):
    """Spread of the shift about e (bins) over ``n_boot`` bootstrap resamples of the pixel's
    detections (n = ntot draws, each a distinct bin with probability count / ntot, also for
    counts that are not whole): the 68.27% quantile of |s_b - e| (its core: a
    resample's far jumps at low SBR are the likelihood's to weigh), s_b each resample's best
    shift at the signal share s among the shifts within BOOT_NATS of the likelihood's peak (a
    resample of n detections moves a shift's log-likelihood by about its square root; far below
    the peak, none wins). With ``peaks_only`` the candidates are the likelihood's local maxima
    among them: a resample then picks a mode, and the spread within one is the sandwich
    variance's (a pixel of BOOT_MAX_N detections or more; at low SBR its many likely shifts made
    the table most of a frame's time). NaN when too large to tabulate."""
    T = tabs
    nk = T.nk
    bar = top - BOOT_NATS
    if peaks_only:
        # a mode is a candidate only as a return in its own right: a background cluster's
        # resamples (their duplicates make coincidences) are picked far more often than the
        # halves of the data pick it (simulated daylight: 76% within 1 sigma -> 85% with them)
        bar = max(bar, mode_thr - ntot * T.logm)
    n_cand = np.int64(0)     # not 0: numba would also compile _resample_best for a literal 0 on its way
    for k in range(ns):
        if _candidate(sp, ns, k, bar, peaks_only, region):
            n_cand += 1
    if n_cand == 0 or n_cand * nu > BOOT_MAX_TABLE:
        return np.nan
    cand = np.empty(n_cand, np.int64)
    # by distinct bin, its log rate beyond the background's at each candidate (0 off its pulse;
    # the interior shifts' from the rate row of _spread): a resample adds each bin's row times
    # its count, contiguous
    tab = np.zeros(nu * n_cand)
    row = sp.row
    lo0 = row[nk]
    q = 0
    for k in range(ns):
        if not _candidate(sp, ns, k, bar, peaks_only, region):
            continue
        i = int(sp.pos[k])
        cand[q] = i
        inv_c = T.inv_colsum[i]
        interior = T.ia <= i <= T.ib
        ua, ub = _photon_range(kb, nu, i - T.off, i - T.off + nk - 1)
        for u in range(ua, ub):
            d = kb[u] - i + T.off
            lr = row[d] if interior else math.log(T.uni + s * (T.g[d] * inv_c - T.uni))
            tab[u * n_cand + q] = lr - lo0
        q += 1
    n = max(1, int(ntot + 0.5))
    # each detection's distinct bin, drawn in one step; counts that are not whole (pile-up
    # corrected) by a search of their running totals instead
    whole = True
    for u in range(nu):
        if kw[u] != math.floor(kw[u]):
            whole = False
    di = np.empty(n if whole else 0, np.int64)
    cum = np.empty(nu)
    c = 0.0
    for u in range(nu):
        if whole:
            for k in range(int(c), int(c + kw[u])):
                di[k] = u
        c += kw[u]
        cum[u] = c
    v = np.empty(n_cand)
    cnt = np.empty(nu)
    dist = np.empty(n_boot)
    # a resample's counts as one number (base n + 1), where that fits: a few detections have few
    # distinct resamples (2 detections: 3), and a repeated one has the same best shift
    # (an open-addressed table of twice the resamples' slots, -1 empty)
    memo = nu * math.log(n + 1.0) < 62.0 * math.log(2.0)
    slots = 1
    while slots < 2 * n_boot:
        slots *= 2
    keys = np.full(slots if memo else 0, -1, np.int64)
    bests = np.empty(slots if memo else 0, np.int64)
    at = 0
    state = np.uint64(seed)
    for b in range(n_boot):
        cnt[:] = 0.0
        for _ in range(n):
            state, x = _uniform(state)
            if whole:
                cnt[di[min(int(x * n), n - 1)]] += 1.0
            else:
                cnt[min(first_above(cum, nu, x * c, np.bool_(True)), nu - 1)] += 1.0
        best = -1
        if memo:
            key = 0
            for u in range(nu):
                key = key * (n + 1) + int(cnt[u])
            at = (key * 40503) & (slots - 1)
            while keys[at] != -1 and keys[at] != key:
                at = (at + 1) & (slots - 1)
            best = bests[at] if keys[at] == key else -1
        if best < 0:
            best = _resample_best(cnt, nu, tab, n_cand, v)
            if memo:
                keys[at] = key
                bests[at] = best
        dist[b] = abs(cand[best] - e)
    heap_sort(dist, n_boot)      # not dist.sort(): numpy's quicksort cost about 1 s more to compile
    q68 = dist[min(n_boot - 1, int(math.ceil(0.6827 * n_boot)) - 1)]
    if not peaks_only:
        return q68
    # among modes, as the likelihood's (:func:`_spread`): the larger of the 68.27% quantile and
    # half the 95.45%, which a second mode picked by more than 1 resample in 22 reaches
    q95 = dist[min(n_boot - 1, int(math.ceil(0.9545 * n_boot)) - 1)]
    return max(q68, q95 / 2.0)


@njit(cache=True, nogil=True, error_model="numpy", **INNER)
def _pixel_seed(kb, kw, nu):
    """A bootstrap seed from the pixel's own (bin, count) pairs, not its index: a pixel gets the
    same spread in a live batch, a Dask block, the whole frame, or from a cube."""
    seed = nu
    for u in range(nu):
        seed = (seed * 1000003 + kb[u] * 7919 + int(kw[u] * 64.0) + 1) % 2147483647
    return seed


@njit(cache=True, nogil=True, inline="always")
def _total(kw, nu):
    """The detections of a pixel's distinct bins' counts kw[:nu], summed in order."""
    ntot = 0.0
    for u in range(nu):
        ntot += kw[u]
    return ntot


# inlined into detect_kernel: as a function of its own it was compiled, then optimised and emitted
# again inside detect_kernel (1.8-3.9 s of CPU on a cold cache for a loop over blocks)
@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _detect_block(blk, ph, dt, rates, maxn, est_shift, gain_in, index_in, share_in, thr, mode_thr, n_boot, temper, regions, out_gain, out_sd, out_sandwich, out_boot):
    """The pixels of block blk of :func:`detect_kernel` with their scratch."""
    T = dt
    px = pixel_scratch(maxn, T.m)
    sp = SpreadScratch(np.empty(T.m, np.int64), np.empty(T.m), np.empty(T.m), np.empty(T.nk + 1), np.empty(T.nk),
                       np.zeros(T.m), np.empty(max(maxn, 1), np.int64), np.empty(max(maxn, 1), np.int64))
    no_region = np.zeros(0, np.uint8)
    for p in block_pixels(ph, blk):
        out_gain[p] = 0.0
        out_sd[p] = np.nan
        out_sandwich[p] = np.nan
        out_boot[p] = np.nan
        nu, n = pixel_bins(ph, p, px)
        if nu == 0:
            continue
        kb, kw = px.kb, px.kw
        ntot = _total(kw, nu)
        e = est_shift[p]
        gain = gain_in[p]
        best_i = index_in[p]
        best_s = share_in[p]
        out_gain[p] = gain
        if not (gain > thr and math.isfinite(e) and best_i >= 0):
            continue       # no return, or no depth to give an uncertainty: nothing more to say
        # at a share of 1 a shift that leaves one detection off the pulse would be impossible;
        # half a detection's worth of background keeps it possible
        s = min(best_s, 1.0 - 0.5 / ntot)
        region = regions[p] if regions.shape[0] else no_region
        out_sd[p], ns, top = _spread(kb, kw, nu, ntot, e, s, best_i, T, rates, sp, region, temper)
        out_sandwich[p] = _sandwich_var(kb, kw, nu, e, best_s, T)
        if n_boot > 0 and n >= 2 and ns > 0 and (n < BOOT_MAX_N or _modes(sp, ns, top) > 1):
            out_boot[p] = _bootstrap_sd(kb, kw, nu, ntot, e, s, sp, ns, top, T, n_boot, _pixel_seed(kb, kw, nu),
                                        n >= BOOT_MAX_N, region, mode_thr)


# numpy's error model as in _detect_block, which is inlined here and compiled under these options
# (python's would add a zero check to every division and raise on one)
@njit(cache=True, nogil=True, error_model="numpy")
def detect_kernel(ph, dt, rates, maxn, est_shift, gain_in, index_in, share_in, thr, mode_thr, n_boot, temper, regions, out_gain, out_sd, out_sandwich, out_boot):
    """Per pixel of ph (:class:`recon.kernels.Photons`, at most maxn entries a pixel) with the
    test's tables ``dt`` (:class:`DetTables`), given its largest log-likelihood gain of one return
    over background alone ``gain_in`` (nats), the integer shift ``index_in`` (-1: none) and signal
    share ``share_in`` where it is reached (:func:`search_kernel`, or the estimator's own search):
    the gain (0 without a detection), and where it passes ``thr`` and the estimator gave a shift
    ``est_shift`` (bins, NaN: none) the spreads of the shift about it (bins; NaN: none): the
    likelihood's (:func:`_spread`), the sandwich variance (bins^2) and the bootstrap's."""
    for blk in range(n_blocks(ph)):
        _detect_block(np.int64(blk), ph, dt, rates, maxn, est_shift, gain_in, index_in, share_in, thr, mode_thr,
                      n_boot, temper, regions, out_gain, out_sd, out_sandwich, out_boot)


# a kernel of its own, not a branch of detect_kernel: ml's search is most of the test's compile
# (ml's estimator gives its gains, and then never runs it), and on a cold cache a second process
# compiles one while this one compiles the other (recon.estimate.warm_up)
@njit(cache=True, nogil=True, error_model="numpy")
def search_kernel(ph, tabs, maxn, todo, out_gain, out_index, out_share):
    """Per pixel of ph where ``todo``: the largest log-likelihood gain of one return over
    background alone (nats, 0 where that wins or without a detection; ml's exact search over every
    integer shift with ml's tables ``tabs``), its integer shift (-1: none) and signal share."""
    px = pixel_scratch(maxn, tabs.m)
    scr = ml_scratch(maxn, tabs)
    for p in range(ph.offsets.size - 1):
        if not todo[p]:
            continue
        out_gain[p] = 0.0
        out_index[p] = -1
        out_share[p] = 0.0
        nu, _ = pixel_bins(ph, p, px)
        if nu == 0:
            continue
        kb, kw = px.kb, px.kw
        ntot = _total(kw, nu)
        best_ll, best_i, best_s = integer_optimum(kb, kw, nu, ntot, tabs, scr)
        out_gain[p] = best_ll + ntot * tabs.logm if best_i >= 0 else 0.0
        out_index[p] = best_i
        out_share[p] = best_s


@njit(cache=True, nogil=True, error_model="numpy", **INNER)
def _pool_neighbours(bins, weights, offsets, w, p, dense, r):
    """The detections of the pixels within r rows and columns of pixel p (row-major in a frame w
    pixels wide; r = 1: its 8 neighbours) pooled, its own left out: (distinct bins ascending, their
    counts, how many, total). ``dense``: zeros, one per bin (the counts gather there and it is zero
    again on return; bins are few against the pooled pixels' detections, so a pass over them orders
    the pool without a sort)."""
    npix = offsets.size - 1
    h = npix // w
    y, x = p // w, p % w
    total = 0
    for yy in range(max(0, y - r), min(h, y + r + 1)):
        for xx in range(max(0, x - r), min(w, x + r + 1)):
            q = yy * w + xx
            if q == p:
                continue
            for a in range(offsets[q], offsets[q + 1]):
                if dense[bins[a]] == 0.0:
                    total += 1
                dense[bins[a]] += weights[a] if weights.size else 1.0
    kb = np.empty(total, np.int64)
    kw = np.empty(total)
    nu = 0
    ntot = 0.0
    for b in range(dense.size):
        if nu == total:
            break
        if dense[b] != 0.0:
            kb[nu] = b
            kw[nu] = dense[b]
            ntot += dense[b]
            dense[b] = 0.0
            nu += 1
    return kb, kw, nu, ntot


@njit(cache=True, nogil=True, _nrt=False, error_model="numpy", **INNER)
def _passes_at_shares(kb, kw, nu, ntot, lo, hi, bar, tabs, rates, shares, row, rrow, acc):
    """Whether the gain of the detections kb (counts kw) at some fixed share of ``shares`` exceeds
    ``bar`` at an interior shift of lo..hi, the likelihood at each read from the tabulated rows
    (:func:`_sweep`, restricted to those shifts). The rows' chords lie below the log rates, so such
    a gain is one the profiled gain at that shift reaches too (to the sums' rounding)."""
    T = tabs
    lo = max(lo, T.ia)
    hi = min(hi, T.ib)
    if hi < lo:
        return False
    passed = False
    for j in range(shares.size):
        lo0 = _sweep(kb, kw, nu, shares[j], T, rates, row, rrow, acc, lo, hi)
        base = ntot * (lo0 + T.logm)
        for i in range(lo, hi + 1):
            if base + acc[i] > bar:
                passed = True
                break
        _sweep_clear(kb, nu, T, acc, lo, hi)
        if passed:
            return True
    return False


@njit(cache=True, nogil=True, error_model="numpy")
def neighbour_gain_kernel(bins, weights, offsets, w, cand, est, half, radius, thr, tabs, rates, shares, out):
    """For each candidate pixel cand[c] (row-major index in a frame w pixels wide): whether the
    profiled gain of one return over background alone (nats) of the detections of the pixels
    within ``radius`` of it pooled (its own left out) exceeds ``thr`` at an integer shift within
    ``half`` bins of its own estimate est[cand[c]] (bins). bins/weights/offsets: every pixel's
    in-window bins (weights empty: one detection each); ``tabs``: the test's :class:`DetTables`,
    ``rates`` its :func:`rate_tables`. out[c]: over ``thr`` where one passes (inf where a fixed
    share did), else the largest (0 at least).

    Most candidates of a surface pass at a fixed share of ``shares`` (:func:`_passes_at_shares`,
    by SUPPORT_MARGIN beyond ``thr``), a sweep of table lookups; the rest get ml's solve at each
    shift in turn (:func:`recon.estimators.ml_bounds._ml_at_int`), which stops at the first
    that passes."""
    T = tabs
    dense = np.zeros(T.m)
    row = np.empty(T.nk + 1)
    rrow = np.empty(T.nk)
    acc = np.zeros(T.m)
    for c in range(cand.size):
        p = cand[c]
        kb, kw, nu, ntot = _pool_neighbours(bins, weights, offsets, w, p, dense, radius)
        out[c] = 0.0
        if nu == 0:
            continue
        centre = int(round(est[p]))
        lo = max(0, centre - half)
        hi = min(T.m - 1, centre + half)
        if _passes_at_shares(kb, kw, nu, ntot, lo, hi, thr + SUPPORT_MARGIN, T, rates, shares, row, rrow, acc):
            out[c] = np.inf
            continue
        best = 0.0
        s0 = 0.5
        for i in range(lo, hi + 1):
            s, ll = _ml_at_int(kb, kw, nu, ntot, i, T.g, T.off, T.colsum, T.uni, s0, -np.inf)
            if 0.0 < s < 1.0:
                s0 = s
            best = max(best, ll + ntot * T.logm)
            if best > thr:
                break
        out[c] = best


#: Signal shares at which :func:`neighbour_region_kernel` weighs the neighbours' likelihood (the
#: largest gain over them stands for the profiled one, a little below it between grid points).
#: Four shares, not eight (1/64 ... 15/16): the same halves within 3 / 1 sigma on the tower, daylight,
#: mannequin and art_top.mat (within 0.2%), the regions of an array frame 5.1 -> 2.9 ms.
REGION_SHARES = (1 / 32, 1 / 8, 1 / 2, 7 / 8)


@njit(cache=True, nogil=True, _nrt=False, error_model="numpy", **INNER)
def _most_within(kb, kw, nu, span):
    """The most detections (counts kw of the ascending bins kb[:nu]) within any span bins."""
    most = 0.0
    inside = 0.0
    a = 0
    for b in range(nu):
        inside += kw[b]
        while kb[b] - kb[a] >= span:
            inside -= kw[a]
            a += 1
        most = max(most, inside)
    return most


@njit(cache=True, nogil=True, _nrt=False, error_model="numpy", **INNER)
def _edge_reach(kb, kw, nu, tabs, out):
    """out[i] at the window's edge shifts (below ia, above ib): the detections (counts kw of the
    bins kb[:nu]) whose pulse reaches shift i, a detection at bin k those of k + off - nk + 1 ..
    k + off."""
    T = tabs
    out[:T.ia] = 0.0
    out[T.ib + 1:] = 0.0
    for u in range(nu):
        a = kb[u] + T.off - T.nk + 1
        b = kb[u] + T.off
        for i in range(max(a, 0), min(b, T.ia - 1) + 1):
            out[i] += kw[u]
        for i in range(max(a, T.ib + 1), min(b, T.m - 1) + 1):
            out[i] += kw[u]


@njit(cache=True, nogil=True, error_model="numpy")
def neighbour_region_kernel(bins, weights, offsets, w, cand, half, thr, tabs, rates, shares, out):
    """For each supported pixel cand[c]: out[c, i] = 1 where a return at shift i is within
    ``half`` bins of a shift at which its neighbours' pooled detections (its own left out) pass
    the support test (gain over ``thr`` nats at the best of the signal ``shares``), else 0: where
    its neighbours see returns. ``tabs``: the test's :class:`DetTables`, ``rates`` its
    :func:`rate_tables`; the likelihood at every interior shift from one sweep a share
    (:func:`_sweep`), at the window's edges (other column sums) one by one where a bound allows
    a pass."""
    T = tabs
    m = T.m
    row = np.empty(T.nk + 1)
    rrow = np.empty(T.nk)
    acc = np.zeros(m)
    dense = np.zeros(m)
    reach = np.zeros(m)
    # a detection's term beyond the off-pulse rate's is at most log(1 + s g_max / (C_min uni (1 - s)))
    # (the pulse's peak, the smallest column sum: a window's edge), and only within nk bins of the
    # shift: a share whose bound with the most detections any nk bins hold cannot pass is not swept
    # (at a high background the large shares: their off-pulse term, ntot log(1 - s), sinks them)
    gmax = 0.0
    for d in range(T.nk):
        gmax = max(gmax, T.g[d])
    cmin = np.inf
    for i in range(m):
        if T.colsum[i] > 0.0:
            cmin = min(cmin, T.colsum[i])
    for c in range(cand.size):
        # np.int64: a global constant would compile a second _pool_neighbours for its literal value
        kb, kw, nu, ntot = _pool_neighbours(bins, weights, offsets, w, cand[c], dense, np.int64(REGION_RADIUS))
        reg = out[c]
        reg[:] = 0
        if nu == 0:
            continue
        most = _most_within(kb, kw, nu, T.nk)
        _edge_reach(kb, kw, nu, T, reach)
        for j in range(shares.size):
            s = shares[j]
            floor = ntot * math.log(1.0 - s)
            lmax = math.log(1.0 + s * gmax * m / (cmin * (1.0 - s)))
            if floor + most * lmax <= thr:
                continue
            lo0 = _sweep(kb, kw, nu, s, T, rates, row, rrow, acc, T.ia, T.ib)
            base = ntot * (lo0 + T.logm)
            upto = -1             # marked up to here at this share
            for i in range(m):
                if T.ia <= i <= T.ib:
                    g = base + acc[i]
                elif T.colsum[i] > 0.0 and floor + reach[i] * lmax <= thr - SUPPORT_MARGIN:
                    # the same bound at this shift, with the detections that reach it: the
                    # logs of an edge shift's likelihood were most of the regions' time
                    continue
                else:
                    g = _ll_at(kb, kw, nu, ntot, i, s, T, row) + ntot * T.logm
                if g > thr:
                    for k in range(max(upto + 1, i - half), min(m, i + half + 1)):
                        reg[k] = 1
                    upto = i + half
            _sweep_clear(kb, nu, T, acc, T.ia, T.ib)


@njit(cache=True, nogil=True, error_model="numpy")
def region_ml_kernel(ph, tabs, maxn, cand, regions, out_shift, out_amp, out_bg, out_var, out_gain, out_share):
    """ml within where the neighbours see returns: for each pixel cand[c] of ph, its own detections'
    best integer shift among those with regions[c, i] set (profiled share, ml's likelihood),
    refined by the parabola through its integer neighbours: out_shift (bins, NaN: none), out_amp
    (unit-area amplitude), out_bg (per bin), out_var (Fisher, bins^2), out_gain (nats: the best
    region shift's log-likelihood beyond the all-background fit's) and out_share (its signal
    share). Not ml's 1/8-bin search: that compiled, inlined here, for 3 s of CPU on a cold cache,
    and these pixels' spreads are many bins."""
    T = tabs
    px = pixel_scratch(maxn, T.m)
    for c in range(cand.size):
        nu, n = pixel_bins(ph, cand[c], px)
        kb, kw = px.kb, px.kw
        ntot = _total(kw, nu)
        out_shift[c], out_amp[c], out_bg[c], out_var[c], out_gain[c], out_share[c] = np.nan, 0.0, 0.0, np.nan, 0.0, 0.0
        best_ll, best_i, best_s = -ntot * T.logm, -1, 0.0
        s0 = 0.5
        reg = regions[c]
        for i in range(T.m):
            if reg[i] == 0 or nu == 0:
                continue
            s, ll = _ml_at_int(kb, kw, nu, ntot, i, T.g, T.off, T.colsum, T.uni, s0, -np.inf)
            if 0.0 < s < 1.0:
                s0 = s
            if ll > best_ll:
                best_ll, best_i, best_s = ll, i, s
        if best_i < 0 or best_s <= 0.0:
            continue
        frac = 0.0
        if 0 < best_i < T.m - 1:
            lm = _ml_at_int(kb, kw, nu, ntot, best_i - 1, T.g, T.off, T.colsum, T.uni, best_s, -np.inf)[1]
            lp = _ml_at_int(kb, kw, nu, ntot, best_i + 1, T.g, T.off, T.colsum, T.uni, best_s, -np.inf)[1]
            den = lm - 2.0 * best_ll + lp
            if den < 0.0:
                frac = min(max(0.5 * (lm - lp) / den, -0.5), 0.5)
        tau = best_i + frac
        a = best_s * ntot / T.colsum[best_i]
        bg = (1.0 - best_s) * ntot * T.uni
        out_shift[c], out_amp[c], out_bg[c], out_share[c] = tau, a, bg, best_s
        out_var[c] = fisher_tab(int(tau + 0.5), a, bg, T.m, T.g, T.dg, T.off, T.ftab)
        out_gain[c] = best_ll + ntot * T.logm


@dataclasses.dataclass(frozen=True)
class Detection:
    """The decision at every pixel (flat arrays, P pixels)."""

    has_return: np.ndarray
    """bool: the gain passes the threshold (a return at the stated false-alarm rate)."""
    gain_nats: np.ndarray
    """the largest log-likelihood gain of one return over background alone."""
    sd_bins: np.ndarray
    """spread of the shift about the estimate under the likelihood (bins; NaN: no estimate)."""
    sandwich_var_bins2: np.ndarray
    """robust (sandwich) variance of the shift at the estimate (bins^2; NaN: none)."""
    bootstrap_sd_bins: np.ndarray
    """spread of the best shift over bootstrap resamples of the detections (bins; NaN: none)."""
    threshold_nats: float
    false_alarm: float


_TEST_TABLES: dict = {}


def _tables_of(tabs):
    """(DetTables, rate_tables) of ml's tables ``tabs``, kept with them: ml_tables gives the same
    object for one pulse and window, so a live batch or an array frame does not rebuild them."""
    hit = _TEST_TABLES.get(id(tabs))
    if hit is None or hit[0] is not tabs:
        dt = det_tables(tabs)
        hit = (tabs, dt, rate_tables(dt))
        if len(_TEST_TABLES) >= 2:      # as many as ml_tables keeps
            _TEST_TABLES.clear()
        _TEST_TABLES[id(tabs)] = hit
    return hit[1], hit[2]


def _slice(bins, weights, offsets, p0: int, p1: int):
    """(Photons, most entries a pixel) of the pixels [p0, p1) of a frame's arrays."""
    from spdepth.recon.kernels import Photons

    o = offsets[p0:p1 + 1]
    w = weights[o[0]:o[-1]] if weights.size else NO_WEIGHTS
    return Photons(bins[o[0]:o[-1]], o - o[0], w), int(np.diff(o).max()) if p1 > p0 else 0


def search(bins: np.ndarray, offsets: np.ndarray, kern, weights: np.ndarray = NO_WEIGHTS,
           todo: np.ndarray | None = None, gain: np.ndarray | None = None, index: np.ndarray | None = None,
           share: np.ndarray | None = None):
    """(gain, index, share) per pixel of the detections ``bins`` (grouped by ``offsets``, as
    :func:`detect` takes them): the test's statistic by ml's exact search over every integer
    shift (:func:`search_kernel`) at the pixels ``todo`` (default all), written into ``gain``,
    ``index`` and ``share`` where given. On numba's threads, as :func:`detect`."""
    from spdepth.recon.estimators.ml import ml_tables

    bins = np.ascontiguousarray(bins, np.int64)
    offsets = np.ascontiguousarray(offsets, np.int64)
    weights = np.ascontiguousarray(weights, np.float64)
    npix = offsets.size - 1
    todo = np.ones(npix, np.bool_) if todo is None else todo
    gain = np.zeros(npix) if gain is None else gain
    index = np.full(npix, -1, np.int64) if index is None else index
    share = np.zeros(npix) if share is None else share
    tabs = ml_tables(kern, int(kern.n_bins))

    def run(p0: int, p1: int) -> None:
        if todo[p0:p1].any():
            ph, maxn = _slice(bins, weights, offsets, p0, p1)
            search_kernel(ph, tabs, maxn, todo[p0:p1], gain[p0:p1], index[p0:p1], share[p0:p1])

    over_threads(run, npix, max(npix, 1))
    return gain, index, share


def detect(bins: np.ndarray, offsets: np.ndarray, kern, est_shift: np.ndarray, false_alarm: float,
           weights: np.ndarray = NO_WEIGHTS, spread_all: bool = False, known_gain: np.ndarray | None = None,
           known_share: np.ndarray | None = None, regions: np.ndarray | None = None,
           spreads: bool = True, temper: float = 1.0, known_index: np.ndarray | None = None,
           bootstrap: bool = True) -> Detection:
    """The test and the spreads (module docstring) of every pixel's in-window detections ``bins``
    (bin indices grouped by ``offsets``; with ``weights``, distinct bins and their counts) about
    the estimated shifts ``est_shift`` (bins, NaN where the estimator reports none), for the pulse
    kernel ``kern`` over ``kern.n_bins`` bins; the spreads where the test passes, or at every
    pixel with an estimate when ``spread_all``. ``known_gain`` (nats, NaN: unknown) and
    ``known_share``: the estimator's own gain and signal share where it ran the same search (ml's
    :attr:`recon.maps.DepthMaps.gain_nats`), taken instead of searching again. Runs on numba's threads (``recon.pixelwise.threads``)
    in slices of whole blocks, as the pixelwise estimators do: the result is the same however the
    pixels are sliced. ``spreads`` False: the test alone, every spread NaN. ``known_index``: the
    shifts where ``known_gain`` is reached (-1: none; default the integer nearest ``est_shift``,
    where ml's search reached it). ``temper``: the
    likelihood's spread is that of its power ``temper`` (1 / the pulse model's dispersion: a
    quasi-likelihood's, TEMPERED_METHODS). ``bootstrap`` False: no bootstrap spread (NaN), for a
    caller that reads the likelihood's spreads alone."""
    from spdepth.recon.estimators.ml import ml_tables

    m = int(kern.n_bins)
    npix = offsets.size - 1
    gain = np.zeros(npix)
    sd = np.full(npix, np.nan)
    sw = np.full(npix, np.nan)
    boot = np.full(npix, np.nan)
    thr = float(auto_threshold_nats(false_alarm, m, fwhm_bins(kern.g)))
    tabs = ml_tables(kern, m)
    dt, rates = _tables_of(tabs)
    bins = np.ascontiguousarray(bins, np.int64)
    offsets = np.ascontiguousarray(offsets, np.int64)
    weights = np.ascontiguousarray(weights, np.float64)
    est = np.ascontiguousarray(est_shift, np.float64)
    counts = np.diff(offsets)
    reg = np.zeros((0, 1), np.uint8) if regions is None else np.ascontiguousarray(regions, np.uint8)
    # the kernel spreads the pixels whose gain passes this (none above infinity)
    spread_thr = np.inf if not spreads else -np.inf if spread_all else thr
    if known_gain is None:
        g_in, i_in, s_in = np.zeros(npix), np.full(npix, -1, np.int64), np.zeros(npix)
        todo = np.ones(npix, np.bool_)
    else:
        g_in = np.array(known_gain, np.float64)
        s_in = np.array(known_share, np.float64)
        todo = ~np.isfinite(g_in)
        if known_index is not None:
            i_in = np.array(known_index, np.int64)
        else:
            # where the estimator ran the search (ml): the integer shift nearest its estimate
            i_in = np.full(npix, -1, np.int64)
            fin = np.isfinite(est)
            i_in[fin] = np.clip(np.rint(est[fin]), 0, m - 1).astype(np.int64)

    if todo.any():
        search(bins, offsets, kern, weights, todo, g_in, i_in, s_in)
    if not spreads:
        # the test alone on the searched (or the estimator's) gains: what the kernel would give (0
        # without a detection; a pixel's entries are its detections or, weighted, its distinct
        # bins), without its pass over every pixel's detections, and without
        # compiling it on a cold cache (most of the test's compile beside the search: a command
        # that writes no map, such as the summary of `spdepth recon FILE`, never needs it)
        gain = np.where(counts > 0, g_in, 0.0)
        return Detection(gain > thr, gain, sd, sw, boot, thr, float(false_alarm))

    def run(p0: int, p1: int) -> None:
        ph, maxn = _slice(bins, weights, offsets, p0, p1)
        detect_kernel(ph, dt, rates, maxn, est[p0:p1], g_in[p0:p1], i_in[p0:p1], s_in[p0:p1], spread_thr, thr,
                      BOOTSTRAP if bootstrap else 0, float(temper), reg[p0:p1] if reg.shape[0] else reg, gain[p0:p1], sd[p0:p1], sw[p0:p1],
                      boot[p0:p1])

    over_threads(run, npix, max(npix, 1))
    return Detection(gain > thr, gain, sd, sw, boot, thr, float(false_alarm))


@njit(cache=True, nogil=True, error_model="numpy")
def dispersion_kernel(ph, dt, maxn, est_shift, share, out_score2, out_curv, out_score):
    """Per pixel of ph with a shift ``est_shift`` (bins) and signal share: :func:`_score_curv` there
    (NaN where the pixel has no shift or none at the window's edge)."""
    px = pixel_scratch(maxn, dt.m)
    for p in range(ph.offsets.size - 1):
        out_score2[p] = np.nan
        out_curv[p] = np.nan
        out_score[p] = np.nan
        nu, _ = pixel_bins(ph, p, px)
        if nu == 0 or not math.isfinite(est_shift[p]):
            continue
        out_score2[p], out_curv[p], out_score[p] = _score_curv(px.kb, px.kw, nu, est_shift[p], share[p], dt)


def dispersion_terms(store, settings, maps, first_pixel: int = 0, frame_pixels: int | None = None,
                     rows: tuple[int, int] | None = None) -> tuple[np.ndarray, ...] | None:
    """Each sampled pixel's terms of the pulse model's dispersion (:func:`dispersion_of`) in
    ``maps`` of ``store`` (one surface, ml or uos, a Gaussian pulse; else None). ml's two: its detections' squared
    score about its depth, corrected for the depth being fitted to them (k / (k - 1) for k signal
    detections, as a sample variance is), and the likelihood's curvature there. The pixels are
    those with a depth and at least two signal detections among every ``stride``-th pixel of the
    frame, counted from its first (``frame_pixels // DISPERSION_PIXELS``, at least 1): the
    maps' pixels are the frame's from ``first_pixel`` on (of ``frame_pixels``, default the maps'
    own), and ``rows`` (of the maps) limits them, so that blocks of rows give, concatenated in
    order, the terms of the whole frame (``acq.distributed``).

    Not for a sampled response (an IRF): the curvature of a likelihood whose rates have a sharp edge
    is no measure of its information there (the response measured from chart_depth.mat: 0.06, with
    halves agreeing within 1 sigma on 79.7% of the pixels; the tower's, 0.49, with 70.0%), while
    with Gaussian pulses it follows the halves' agreement (below). uos's depths are not the
    likelihood's optimum (ml's terms at those of the bust fitted with a 720 ps pulse: 160), and its
    uncertainty is its matched filter's: its terms are the filter's own, four a pixel
    (:func:`recon.estimators.uos.matched_filter_terms`). Not lmf's: it measures the dispersion
    before its test, at ml's search's shifts (:func:`search_dispersion_terms`)."""
    from spdepth.recon.photons import rows_of

    tof = np.asarray(maps.tof_s, np.float64)
    if tof.ndim == 3 or settings.method not in DISPERSION_METHODS \
            or maps.settings.get("kernel", {}).get("pulse") != "gaussian":
        return None
    b, kern = _kernel_of(maps.settings)
    bins, weights, offsets, n = _binned_frame(store, settings, b)
    share = _signal_share(maps, b, n)
    est = (tof.ravel() / b.time_unit_s - b.window_start) / b.bin_width - 0.5
    k = share * n
    local = _sampled_pixels(tof.shape, first_pixel, frame_pixels, rows)
    pix = local[np.isfinite(est[local]) & (k[local] >= 2.0)]
    if settings.method == "uos":
        from spdepth.recon.estimators.uos import MIN_DETECTIONS, matched_filter_terms

        pix = pix[n[pix] >= MIN_DETECTIONS]   # by the count alone: the fit chose none of them
        at, so = rows_of(offsets, pix)
        return matched_filter_terms(bins[at], weights[at] if weights.size else NO_WEIGHTS, so, est[pix], k[pix],
                                    np.asarray(maps.background, np.float64).ravel()[pix], kern, b.n_bins)
    return likelihood_terms(bins, weights, offsets, n, kern, pix, est[pix], share[pix])


def search_dispersion_terms(store, settings, b, kern, first_pixel: int = 0, frame_pixels: int | None = None,
                            rows: tuple[int, int] | None = None, found=None) -> tuple[np.ndarray, ...]:
    """The likelihood's two terms of the pulse model's dispersion, as :func:`dispersion_terms` takes
    ml's, at ml's search's best integer shift and signal share (:func:`search`) of every sampled
    pixel of ``store`` with at least two signal detections there, whatever the estimator: the
    dispersion of an estimator whose depths are not the likelihood's optimum (lmf's, TEMPERED_METHODS),
    measured before its test. ``b``, ``kern``: the resolved binning and pulse (a Gaussian's: as
    for :func:`dispersion_terms`, not for a sampled response, which the caller checks). ``found``:
    the search's (gain, index, share) of every pixel of ``store`` where the caller ran it (the
    test's own, :func:`decide_maps`); else it runs on the sampled pixels alone, so that blocks of
    rows with :func:`dispersion_terms`'s ``first_pixel``, ``frame_pixels`` and ``rows`` give the
    frame's (``acq.distributed``)."""
    from spdepth.recon.photons import rows_of

    bins, weights, offsets, n = _binned_frame(store, settings, b)
    local = _sampled_pixels(store.shape, first_pixel, frame_pixels, rows)
    local = local[n[local] > 0]
    if found is None:
        at, so = rows_of(offsets, local)
        _, index, share = search(bins[at], so, kern, weights[at] if weights.size else NO_WEIGHTS)
    else:
        index, share = found[1][local], found[2][local]
    ok = (index >= 0) & (share * n[local] >= 2.0)
    return likelihood_terms(bins, weights, offsets, n, kern, local[ok], index[ok].astype(np.float64), share[ok])


def _sampled_pixels(shape, first_pixel: int, frame_pixels: int | None, rows: tuple[int, int] | None) -> np.ndarray:
    """Every stride-th pixel of a frame among those of ``shape`` (the frame's from ``first_pixel``
    on, of ``frame_pixels``, default their own), within ``rows`` (:func:`dispersion_terms`)."""
    h, w = shape[-2], shape[-1]
    stride = max(1, (h * w if frame_pixels is None else frame_pixels) // DISPERSION_PIXELS)
    lo, hi = (0, h) if rows is None else rows
    # without an index of every pixel (a 4096 x 4096 frame's: 134 MB)
    start = -(-(first_pixel + lo * w) // stride) * stride - first_pixel
    return np.arange(start, hi * w, stride)


def likelihood_terms(bins, weights, offsets, n, kern, pix, est, share):
    """ml's two terms (:func:`dispersion_terms`) of the pixels ``pix`` at shifts ``est`` (bins) and
    signal shares ``share`` (theirs)."""
    from spdepth.recon.estimators.ml import ml_tables
    from spdepth.recon.kernels import Photons
    from spdepth.recon.photons import rows_of

    at, so = rows_of(offsets, pix)
    ph = Photons(np.ascontiguousarray(bins[at], np.int64), np.ascontiguousarray(so, np.int64),
                 np.ascontiguousarray(weights[at], np.float64) if weights.size else NO_WEIGHTS)
    dt, _ = _tables_of(ml_tables(kern, int(kern.n_bins)))
    score2 = np.empty(pix.size)
    curv = np.empty(pix.size)
    score = np.empty(pix.size)
    if pix.size:
        dispersion_kernel(ph, dt, int(np.diff(so).max()), np.ascontiguousarray(est, np.float64),
                          np.ascontiguousarray(share, np.float64), score2, curv, score)
    # about their mean: at a refined optimum (ml's depth) the scores sum to nearly zero, at the
    # search's integer shift near it they need not
    score2 = score2 - score ** 2 / n[pix]
    ok = np.isfinite(score2) & np.isfinite(curv)
    kk = (share * n[pix])[ok]
    return score2[ok] * kk / (kk - 1.0), curv[ok]


def dispersion_of(terms: tuple[np.ndarray, ...] | None) -> dict | None:
    """Does the pulse model fit the detections about their depths? The dispersion pooled from the
    pixels' ``terms`` (:func:`dispersion_terms`): the sum of their squared scores over the sum of
    the likelihood's curvatures, a quasi-likelihood's dispersion (a pixel's own sandwich variance
    of a few detections is too noisy to say it). 1 when the model fits; a response narrower than
    the model gives less, about the width ratio squared where background is scarce (the simulated
    bust, 362 ps RMS, fitted with a 720 ps pulse: 0.27; with 250 ps: 1.94; with its own: 0.99;
    background near the returns moves it towards 1), and the model's uncertainties (Fisher, the
    likelihood's spread, the bootstrap's) are then too large by about 1 / sqrt of it
    (:func:`with_dispersion`). uos's four terms a pixel (:func:`recon.estimators.uos.matched_filter_terms`):
    its matched filter's variance is its score's variance over its slope squared, each pooled data
    over model, ``(sum s2 / sum s2_model) / (sum slope / sum slope_model)^2`` (simulated returns
    of a 45-unit pulse fitted with one twice as wide: 0.26, and the depths within 1 sigma of
    the truth 96% -> 70%; 0.7 as wide: 1.20, 64% -> 68%). ``width_ratio_se``: the width ratio's
    relative standard error, from the pixels' spread about the pooled ratio (the delta method, each
    pixel's terms one sample). None without terms, with fewer than DISPERSION_MIN_PIXELS pixels,
    where a pooled sum has the wrong sign, or where that error exceeds DISPERSION_MAX_SE.
    ``score``: whose terms they were."""
    if terms is None or terms[0].size < DISPERSION_MIN_PIXELS:
        return None
    sums = [float(np.sum(t)) for t in terms]
    if len(sums) == 2:              # ml: squared scores over curvatures
        phi = sums[0] / sums[1] if sums[1] > 0.0 else math.nan
    else:                           # uos's filter: its score's variance, then its slope's, data over model
        slope = sums[2] / sums[3] if sums[3] != 0.0 else math.nan       # both < 0 about a peak
        phi = (sums[0] / sums[1]) / slope ** 2 if sums[1] > 0.0 and slope > 0.0 else math.nan
    if not math.isfinite(phi) or phi <= 0.0:
        return None
    # log phi's change with each pixel's terms: +-1 each for ml's ratio, and for uos's (s2 / s2_model)
    # / (slope / slope_model)^2 also -+2 for the slope's pair; its variance is their sum of squares
    signs = (1.0, -1.0) if len(sums) == 2 else (1.0, -1.0, -2.0, 2.0)
    change = sum(c * np.asarray(t, np.float64) / total for c, t, total in zip(signs, terms, sums))
    se = 0.5 * math.sqrt(float(np.sum(change ** 2)))        # the width ratio's, sqrt(phi)
    if not se <= DISPERSION_MAX_SE:
        return None
    return {"dispersion": phi, "pixels": int(terms[0].size), "width_ratio": math.sqrt(phi),
            "width_ratio_se": se, "score": "the likelihood's" if len(sums) == 2 else "uos's matched filter's"}


def with_dispersion(maps, d: dict | None):
    """``maps`` with every uncertainty scaled by the square root of the pulse model's dispersion
    ``d`` (:func:`dispersion_of`), which ``settings['pulse_dispersion']`` records; None: as they
    are. Measured on real scans' split halves (ml, a Gaussian pulse stated too wide or too narrow;
    within 3 / 1 combined sigma before -> after): the mannequin at 360 ps (dispersion 0.48) 99.6% /
    87.6% -> 99.2% / 72.0%, at 240 ps (0.83) 99.4% / 77.0% -> 99.2% / 72.1%, at 160 ps (1.38) 98.2% /
    65.9% -> 99.0% / 73.6%; tower_9km.mat at 530 ps (0.85) 97.7% / 81.4% -> 97.4% / 77.5%, at 250 ps
    (1.78) 96.2% / 66.4% -> 97.5% / 78.7%; chart_depth.mat at 126 ps (1.74) 96.9% / 59.5% -> 99.6% /
    70.9%. Each half's own dispersion was within 0.04 of the whole file's."""
    if d is None:
        return maps
    rec = dict(maps.settings)
    rec["pulse_dispersion"] = dict(d, applied="every depth's uncertainty scaled by sqrt(dispersion)")
    return dataclasses.replace(maps, uncertainty_s=np.asarray(maps.uncertainty_s) * d["width_ratio"], settings=rec)


def pulse_dispersion(store, settings, maps) -> dict | None:
    """The pulse model's dispersion of a frame's one-surface ml ``maps`` (:func:`dispersion_of` of
    :func:`dispersion_terms`), None where it is not said."""
    return dispersion_of(dispersion_terms(store, settings, maps))


def neighbour_support(bins, weights, offsets, shape, kern, est, cand, false_alarm: float, half: int):
    """Which pixels ``cand`` (indices) their neighbours support: the detections of the pixels within
    SUPPORT_RADIUS of each pooled (the pixel's own left out, so the pixel's estimate ``est`` chose
    nothing among them) hold a return within ``half`` bins of the pixel's estimate, at the false-alarm rate
    ``false_alarm`` for that span of shifts (:func:`auto_threshold_nats`).
    Returns (supported indices, threshold nats)."""
    from spdepth.recon.estimators.ml import ml_tables

    thr = float(auto_threshold_nats(false_alarm, 2 * half + 1, fwhm_bins(kern.g)))
    gains = np.zeros(cand.size)
    bins, weights, offsets, cand = _frame_arrays(bins, weights, offsets, cand)
    est = np.ascontiguousarray(est, np.float64)
    dt, rates = _tables_of(ml_tables(kern, int(kern.n_bins)))
    shares = np.array(SUPPORT_SHARES)
    over_threads(lambda a, b: neighbour_gain_kernel(bins, weights, offsets, int(shape[1]), cand[a:b], est,
                                                    int(half), SUPPORT_RADIUS, thr, dt, rates, shares, gains[a:b]),
                 cand.size, max(cand.size, 1))
    return cand[gains > thr], thr


def neighbour_regions(bins, weights, offsets, width: int, kern, cand, half: int, thr: float) -> np.ndarray:
    """uint8 (cand.size, bins): where the pixels ``cand`` (indices of a frame ``width`` pixels
    wide) have their neighbours see returns (:func:`neighbour_region_kernel`)."""
    from spdepth.recon.estimators.ml import ml_tables

    dt, rates = _tables_of(ml_tables(kern, int(kern.n_bins)))
    shares = np.array(REGION_SHARES)
    bins, weights, offsets, cand = _frame_arrays(bins, weights, offsets, cand)
    regions = np.empty((cand.size, int(kern.n_bins)), np.uint8)
    over_threads(lambda a, b: neighbour_region_kernel(bins, weights, offsets, int(width), cand[a:b], int(half),
                                                      float(thr), dt, rates, shares, regions[a:b]), cand.size,
                 max(cand.size, 1))
    return regions


Fill = namedtuple("Fill", ["pixels", "shift", "amp", "bg", "var", "gain", "share"])
#: Pixels whose neighbours' regions (pixels x bins, uint8) are held at once.
REGION_CHUNK = 8192


def neighbour_fill(bins, weights, offsets, width: int, kern, cand, half: int, thr: float, rate: float,
                   det: Detection, false_alarm: float, spreads: bool = True) -> Fill:
    """Of the pixels ``cand`` (indices of a frame ``width`` pixels wide), those whose own detections
    hold a return within where their neighbours see returns (:func:`neighbour_regions` at the
    support's ``half`` and threshold ``thr``): ml's best shift there (:func:`region_ml_kernel`),
    its gain over the threshold at the false-alarm rate ``rate`` for the region's span of shifts
    (0: none). Under background alone around it a pixel is given a return only where its
    neighbours passed the support's test too; beside a surface, a pixel without one at those
    shifts is given one at the rate ``rate``. Their decision and their spreads over the region
    (at the test's ``false_alarm``; without ``spreads``, the decision alone) go into ``det``."""

    parts = []
    fw = fwhm_bins(kern.g)
    # a region spans at least the support's 2 half + 1 shifts, and no gain within it exceeds the
    # pixel's best anywhere (det.gain_nats): a pixel below the smallest region's threshold is out
    # without its region (most of them at a high background)
    if rate > 0:
        cand = cand[det.gain_nats[cand] > auto_threshold_nats(rate, 2 * half + 1, fw)]
    for c0 in range(0, cand.size if rate > 0 else 0, REGION_CHUNK):
        c = cand[c0:c0 + REGION_CHUNK]
        regions = neighbour_regions(bins, weights, offsets, width, kern, c, half, thr)
        span = regions.sum(axis=1, dtype=np.int64)
        keep = span > 0
        c, regions, span = c[keep], regions[keep], span[keep]
        out = region_fit(bins, weights, offsets, kern, c, regions)
        thr_of = {int(k): auto_threshold_nats(rate, int(k), fw) for k in np.unique(span)}
        need = np.array([thr_of[int(k)] for k in span]) if c.size else np.zeros(0)
        ok = np.isfinite(out[0]) & (out[4] > need)
        part = Fill(c[ok], *(o[ok] for o in out))
        _region_spreads(det, bins, weights, offsets, kern, part.pixels, part.shift, regions[ok], false_alarm,
                        known_gain=part.gain, known_share=part.share, spreads=spreads)
        parts.append(part)
    if not parts:
        return Fill(np.empty(0, np.int64), *(np.empty(0) for _ in range(6)))
    return Fill(*(np.concatenate(f) for f in zip(*parts)))


def _region_spreads(det: Detection, bins, weights, offsets, kern, pix, est, regions, false_alarm: float,
                    known_gain=None, known_share=None, known_index=None, spreads: bool = True,
                    temper: float = 1.0) -> None:
    """``det`` with the pixels ``pix`` holding a return and their spreads about ``est`` (bins)
    taken over their ``regions`` only (:func:`detect` with ``spread_all`` and ``temper``; without
    ``spreads``, the decision alone)."""
    from spdepth.recon.photons import rows_of

    det.has_return[pix] = True
    if not pix.size or not spreads:
        return
    at, so = rows_of(offsets, pix)
    sub = detect(bins[at], so, kern, est, false_alarm, weights[at] if weights.size else NO_WEIGHTS,
                 spread_all=True, regions=regions, known_gain=known_gain, known_share=known_share,
                 known_index=known_index, temper=temper)
    det.sd_bins[pix] = sub.sd_bins
    det.sandwich_var_bins2[pix] = sub.sandwich_var_bins2
    det.bootstrap_sd_bins[pix] = sub.bootstrap_sd_bins


def region_fit(bins, weights, offsets, kern, cand, regions) -> list:
    """[shift, amp, bg, var, gain, share] of the pixels ``cand`` (indices), each ml's best within
    its row of ``regions`` (:func:`region_ml_kernel`)."""
    from spdepth.recon.estimators.ml import ml_tables
    from spdepth.recon.kernels import Photons

    n = cand.size
    out = [np.full(n, np.nan), np.zeros(n), np.zeros(n), np.full(n, np.nan), np.zeros(n), np.zeros(n)]
    if n:
        tabs = ml_tables(kern, int(kern.n_bins))
        bins, weights, offsets, cand = _frame_arrays(bins, weights, offsets, cand)
        ph = Photons(bins, offsets, weights)
        maxn = int(np.diff(offsets)[cand].max())
        regions = np.ascontiguousarray(regions, np.uint8)
        over_threads(lambda a, b: region_ml_kernel(ph, tabs, maxn, cand[a:b], regions[a:b],
                                                   *(o[a:b] for o in out)), n, n)
    return out


def _frame_arrays(bins, weights, offsets, cand):
    """The frame's arrays as the neighbour kernels take them."""
    return (np.ascontiguousarray(bins, np.int64), np.ascontiguousarray(weights, np.float64),
            np.ascontiguousarray(offsets, np.int64), np.ascontiguousarray(cand, np.int64))



def _kernel_of(settings: dict):
    """The binning and pulse kernel a result's ``settings`` record says were used (the same cached
    object the estimator built: :func:`recon.model.build_kernel`)."""
    b = Binning.from_dict(settings["binning"])
    irf = settings.get("irf")
    if isinstance(irf, dict) and irf.get("times_s"):
        return b, build_kernel(b, irf=Irf.from_dict(irf))
    return b, build_kernel(b, pulse_rms_s=float(settings["pulse_rms_s"]))


def _filled_maps(maps, b, kern, fill: Fill):
    """(tof_s, uncertainty_s, signal, background) of ``maps`` with the pixels of ``fill`` given
    ml's estimate within where their neighbours see returns (as :func:`recon.pixelwise.pixel_maps`
    makes ml's own maps, on a grid of whole bins refined by a parabola); the background stays NaN
    where the estimator does not estimate it."""
    from spdepth.recon.model import FINE_STEPS
    from spdepth.recon.pixelwise import honest_var

    tof, unc = np.array(maps.tof_s, np.float64), np.array(maps.uncertainty_s, np.float64)
    signal, bg = np.array(maps.signal, np.float64), np.array(maps.background, np.float64)
    f = fill.pixels
    tof.ravel()[f] = b.shift_to_time_s(fill.shift)
    has = np.ones(f.size, bool)
    unc.ravel()[f] = np.sqrt(honest_var(fill.var, has, kern.rms_bins, b.n_bins, 1.0)) * b.bin_width_s
    q = np.clip(np.rint(fill.shift * FINE_STEPS).astype(np.int64), 0, kern.fine_colsum.size - 1)
    signal.ravel()[f] = fill.amp * kern.fine_colsum[q]
    if np.isfinite(bg).any():
        bg.ravel()[f] = fill.bg
    return tof, unc, signal, bg


def _own_width(bins, weights, offsets, kern, pix, gain, index, share, false_alarm: float) -> np.ndarray:
    """The width (bins) of the peak of the pixels ``pix``'s own likelihood at their own most
    likely return (``index``, with ``gain`` and ``share`` there: ml's search's, :func:`search`):
    the sandwich's, which reads that peak's curvature alone;
    0 where the likelihood has other peaks (its spread about that return, as :func:`_spreads`
    reads it, beyond SPATIAL_OVERRULE of the peak's width) and NaN where there is no return."""
    from spdepth.recon.photons import rows_of

    if pix.size == 0:
        return np.zeros(0)
    at, so = rows_of(offsets, pix)
    w = weights[at] if weights.size else NO_WEIGHTS
    own = detect(bins[at], so, kern, np.where(index >= 0, index, np.nan).astype(np.float64), false_alarm, w,
                 spread_all=True, known_gain=gain, known_share=share, known_index=index, bootstrap=False)
    peak = np.sqrt(own.sandwich_var_bins2 + 1.0 / 12.0)
    whole = np.sqrt(own.sd_bins ** 2 + 1.0 / 12.0)
    # a likelihood of other peaks too (its spread about its own return far beyond that peak's
    # width): 0, so that those peaks may overrule the neighbours' depth
    return np.where(whole > SPATIAL_OVERRULE * peak, 0.0, peak)


def _spreads(det: Detection, unc: np.ndarray, bw: float):
    """(post, boot, use_post, use_boot), shaped like ``unc`` (s): the likelihood's spread (with
    the sandwich variance) and the bootstrap's of ``det``, and where each replaces the estimator's
    uncertainty ``unc``: only where larger beyond its own resolution (the likelihood's and the
    bootstrap's are read on a grid of whole bins, a bin; the bootstrap's quantile from BOOTSTRAP
    resamples is good to about BOOT_NOISE)."""
    post = np.sqrt(np.fmax(det.sd_bins ** 2 + 1.0 / 12.0, det.sandwich_var_bins2)).reshape(unc.shape) * bw
    boot = np.sqrt(det.bootstrap_sd_bins ** 2 + 1.0 / 12.0).reshape(unc.shape) * bw
    return post, boot, np.isfinite(post) & (post > unc + bw), np.isfinite(boot) & (boot > (1.0 + BOOT_NOISE) * unc + bw)


def surface_spreads(bins, weights, offsets, kern, b, tof, unc, signal, n_photons, false_alarm: float) -> np.ndarray:
    """The uncertainties ``unc`` (K x H x W, s) of the K-surface fit's surfaces ``tof`` widened by
    the sandwich variance and the bootstrap's spread (:func:`_spreads`) of each surface, taken over
    the shifts between the midpoints to its neighbouring surfaces (its own part of the window):
    the fit's Fisher variance reads a response's sharp edge and misses the flat top beside it
    (two_layer_top.mat's pane and wall: 0.2 cm sigmas on halves 1-3 cm apart; halves within 3 / 1
    sigma 92.8 / 61.8% -> 95.6 / 67.5% on the pane, 92.5 / 60.4% -> 96.6 / 69.0% on the wall)."""
    from spdepth.recon.photons import rows_of

    k_all, h, w = tof.shape
    m = int(b.n_bins)
    shift = (tof.reshape(k_all, -1) / b.time_unit_s - b.window_start) / b.bin_width - 0.5
    out = np.array(unc, np.float64, copy=True).reshape(k_all, -1)
    i = np.arange(m)
    for r in range(k_all):
        idx = np.flatnonzero(np.isfinite(shift[r]))
        for c0 in range(0, idx.size, SURFACE_CHUNK):
            p = idx[c0:c0 + SURFACE_CHUNK]
            e = shift[r, p]
            lo = np.zeros(p.size)
            hi = np.full(p.size, m - 1.0)
            if r > 0:
                lo = np.where(np.isfinite(shift[r - 1, p]), 0.5 * (shift[r - 1, p] + e), lo)
            if r + 1 < k_all:
                hi = np.where(np.isfinite(shift[r + 1, p]), 0.5 * (e + shift[r + 1, p]), hi)
            regions = ((i[None, :] >= lo[:, None]) & (i[None, :] <= hi[:, None])).astype(np.uint8)
            at, so = rows_of(offsets, p)
            share = np.clip(signal.reshape(k_all, -1)[r, p] / np.maximum(n_photons[p], 1.0), 0.0, 1.0)
            det = detect(bins[at], so, kern, e, false_alarm, weights[at] if weights.size else NO_WEIGHTS,
                         spread_all=True, regions=regions, known_gain=np.full(p.size, np.inf), known_share=share)
            u = out[r, p]
            _, boot, _, use_boot = _spreads(det, u, b.bin_width_s)
            # the sandwich's and the bootstrap's, not the likelihood's: each surface's region holds one
            # return, the likelihood's far peaks of a low SBR are not there, and over a flat top its
            # spread is the shift's posterior, wider than the estimate's (halves within 1 sigma 83%)
            sw = np.sqrt(det.sandwich_var_bins2) * b.bin_width_s
            out[r, p] = np.fmax(u, np.fmax(np.where(np.isfinite(sw), sw, 0.0), np.where(use_boot, boot, 0.0)))
    return out.reshape(k_all, h, w)


def _binned_frame(store, settings, b):
    """(bins, weights, offsets, detections per pixel) of a frame's in-window detections, as the
    estimator binned them: a count store's (bin, count) pairs (no photon list), else each pixel's
    first ``settings.max_photons`` (weights empty)."""
    from spdepth.recon.counts import CountStore
    from spdepth.recon.pixelwise import binned_photons

    if isinstance(store, CountStore):
        bins, weights, offsets = store.binned(b)
        total = np.concatenate([[0.0], np.cumsum(weights)])
        return bins, weights, offsets, total[offsets[1:]] - total[offsets[:-1]]
    bins, offsets = binned_photons(store, b, settings.max_photons)
    return bins, NO_WEIGHTS, offsets, np.diff(offsets)


def _signal_share(maps, b, n_photons) -> np.ndarray:
    """Each pixel's signal share by the estimator's background (flat per bin), in [0, 1]."""
    with np.errstate(divide="ignore", invalid="ignore"):
        share = 1.0 - np.asarray(maps.background, np.float64).ravel() * b.n_bins / n_photons
    return np.clip(np.nan_to_num(share), 0.0, 1.0)


def decide_maps(store, settings, maps, neighbours: bool = True, spreads: bool = True,
                dispersion: bool | dict = True):
    """``maps`` with the test applied and honest uncertainties (module docstring): pixels without a
    return get no depth and the flag NO_RETURN; ``settings['detection']`` records the test. With
    ``neighbours`` (the store is a frame, its pixels' neighbours beside them) a pixel that fails on
    its own detections may be supported by its neighbours'. ``spreads`` False: the decision alone,
    every uncertainty the estimator's own (for a caller that writes and shows no map: the spreads
    were about half of a 512x512 recon's estimation time), as the record says. With ``spreads``,
    ``neighbours`` and ``dispersion``, the uncertainties of ml's and uos's one-surface maps with a
    Gaussian pulse are scaled by the pulse model's dispersion (:func:`with_dispersion`), measured
    on these maps (uos's: its matched filter's); ``dispersion`` False: left to the caller
    (``acq.distributed`` pools it over blocks). lmf's (TEMPERED_METHODS, with ``spreads``): the
    dispersion at ml's search's shifts (:func:`search_dispersion_terms`, on this store, or
    ``dispersion`` as a dict: the frame's), measured before the test, tempers its likelihood
    spreads, and scales lmf's own uncertainty by its square root."""
    rec = dict(maps.settings)
    b, kern = _kernel_of(rec)
    bins, weights, offsets, n_photons = _binned_frame(store, settings, b)
    tof = np.asarray(maps.tof_s, np.float64)
    unc = np.asarray(maps.uncertainty_s, np.float64)
    several = tof.ndim == 3
    first = tof[0] if several else tof
    est = (first.ravel() / b.time_unit_s - b.window_start) / b.bin_width - 0.5
    if several:
        est = np.full(est.shape, np.nan)    # only the test here; each surface's spreads below
    core_s = float(rec.get("pulse_core_rms_s", rec["pulse_rms_s"]))
    known = dict(known_gain=None, known_share=None)
    if maps.gain_nats is not None and not several:
        known = dict(known_gain=np.asarray(maps.gain_nats, np.float64).ravel(),
                     known_share=_signal_share(maps, b, n_photons))
    h, w = maps.shape
    spatial = settings.method == "spatial"

    # a window hardly wider than the pulse: time cannot tell a return from background
    decidable = b.n_bins >= UNDECIDABLE_FWHM * fwhm_bins(kern.g)
    rules = neighbours and decidable and not spatial and not several
    # the stated rate is the pixel's: where the neighbours' support applies, a pixel of background
    # alone has two chances (its own test, then the support), and each is given half of it
    rate = settings.false_alarm / 2 if rules else settings.false_alarm
    tempered = None
    found = None        # the test's own search (gain, index, share of every pixel), where run here
    # on a frame, as ml's scaling (a live batch is none: acq.live_recon's frame pass applies both)
    if settings.method in TEMPERED_METHODS and spreads and neighbours and not several and dispersion is not False \
            and rec.get("kernel", {}).get("pulse") == "gaussian":
        if isinstance(dispersion, dict):
            tempered = dispersion           # the frame's (acq.distributed)
        else:
            # the test's own search, run once: its statistic at every pixel, and the terms' shifts
            found = search(bins, offsets, kern, weights)
            tempered = dispersion_of(search_dispersion_terms(store, settings, b, kern, found=found))
    elif spatial and spreads and not several and known["known_gain"] is None:
        # run once too: its statistic, and the own best shifts the spatial overrule reads (_own_width)
        found = search(bins, offsets, kern, weights)
    if found is not None:
        known = dict(known_gain=found[0], known_share=found[2], known_index=found[1])
    # the likelihood's spreads of a quasi-likelihood (its log over the dispersion): their widths
    # scale by its square root, and the distances between its modes and the depth stay
    temper = 1.0 / tempered["dispersion"] if tempered is not None else 1.0
    det = detect(bins, offsets, kern, est, rate, weights, spreads=spreads, temper=temper, **known)
    filled = None
    thr_n = math.nan
    half = max(1, int(round(NEIGHBOUR_HALF_CORES * core_s / b.bin_width_s)))
    if rules:
        # a pixel whose own detections are too few for the test: its neighbours may hold the
        # return at its depth (a surface seen by several pixels), with its own spreads
        cand = np.flatnonzero(~det.has_return & np.isfinite(est) & (n_photons > 0))
        supported, thr_n = neighbour_support(bins, weights, offsets, (h, w), kern, est, cand, rate, half)
        # their spreads only over where their neighbours see returns: the reported depth lies there
        # by the support's rule (the likelihood's and the bootstrap's far modes elsewhere would not
        # have been reported); in slices, so the regions (pixels x bins) stay bounded
        det.has_return[supported] = True
        for c0 in range(0, supported.size if spreads else 0, REGION_CHUNK):
            sup = supported[c0:c0 + REGION_CHUNK]
            regions = neighbour_regions(bins, weights, offsets, w, kern, sup, half, thr_n)
            _region_spreads(det, bins, weights, offsets, kern, sup, est[sup], regions, rate, temper=temper,
                            **{k: None if v is None else v[sup] for k, v in known.items()})
        # a pixel whose own estimate lies elsewhere (a background cluster beat a faint return):
        # its own detections tested where its neighbours see returns, and given ml's depth there
        fill = neighbour_fill(bins, weights, offsets, w, kern, np.flatnonzero(~det.has_return & (n_photons > 0)),
                              half, thr_n, settings.neighbour_false_alarm, det, rate, spreads)
        if fill.pixels.size:
            filled = _filled_maps(maps, b, kern, fill)
    has = det.has_return.reshape(h, w)
    flags = np.array(maps.flags, np.uint8, copy=True)
    n_photons = n_photons.reshape(h, w)
    changes = {}
    signal = maps.signal
    if filled is not None:
        tof, unc, signal, changes["background"] = filled
        flags.ravel()[fill.pixels] = PixelFlag.OK
    if spatial or not decidable:
        drop = np.zeros((h, w), bool)          # the neighbours' support is the spatial estimator's to judge
    else:
        drop = ~has & (n_photons > 0)
    if several:
        keep = ~drop[None]
        new_tof = np.where(keep, tof, np.nan)
        changes["surfaces"] = np.where(drop, 0, maps.surfaces).astype(np.int16)
        changes["weak"] = np.asarray(maps.weak) & keep
        changes["signal"] = np.where(keep, maps.signal, 0.0)
        if decidable and not spatial and spreads:       # spatial's took them before its smoothing
            unc = surface_spreads(bins, weights, offsets, kern, b, tof, unc, maps.signal, n_photons.ravel(),
                                   settings.false_alarm)
        new_unc = np.where(keep, unc, np.nan)
    else:
        new_tof = np.where(drop, np.nan, tof)
        bw = b.bin_width_s
        # each spread replaces the estimator's uncertainty only where it is larger beyond its own
        # resolution: the likelihood's and the bootstrap's are read on a grid of whole bins (a
        # bin), the bootstrap's quantile from BOOTSTRAP resamples is good to about BOOT_NOISE
        if tempered is not None:
            unc = unc * tempered["width_ratio"]       # the estimator's own, filled pixels' included
        post, boot, use_post, use_boot = _spreads(det, unc, bw)
        if spatial:
            # the neighbours narrow a spatial depth beyond what the pixel's own detections say;
            # those overrule them only where they put the return far from the spatial depth
            # (beyond 3 of its sigma and the pulse's sharp part): another likely return
            far = has & (np.fmax(np.where(use_post, post, 0), np.where(use_boot, boot, 0)) > SPATIAL_OVERRULE * unc)
            far &= np.fmax(post, boot) > core_s
            # and beyond its own peak's width about its own most likely return: a few detections of a
            # sharp core with a long tail (the mannequin's measured response) spread far beyond the core
            # about the neighbours' depth and their own peak alike, which is no other return
            far = far.reshape(-1)
            cand = np.flatnonzero(far)
            gain, index, share = found if found is not None else search(bins, offsets, kern, weights, todo=far)
            width = _own_width(bins, weights, offsets, kern, cand, gain[cand], index[cand], share[cand], rate) * bw
            far[cand[np.fmax(post, boot).reshape(-1)[cand] <= SPATIAL_OVERRULE * width]] = False
            far = far.reshape(unc.shape)
            use_post &= far
            use_boot &= far
        sd = np.fmax(np.where(use_post & decidable, post, 0.0), np.where(use_boot & decidable, boot, 0.0))
        new_unc = np.where(np.isfinite(new_tof), np.fmax(unc, sd), np.nan)
        changes["signal"] = np.where(drop, 0.0, signal)
    flags[drop] = PixelFlag.NO_RETURN
    rec["detection"] = {
        "rule": (f"likelihood-ratio test of one return against background alone, false-alarm rate "
                 f"{settings.false_alarm:g} per pixel (gain > {det.threshold_nats:.2f} nats"
                 + (f", at {det.false_alarm:g}: the other half is the neighbours' support's)" if rules else ")")),
        "false_alarm": settings.false_alarm, "own_false_alarm": det.false_alarm,
        "threshold_nats": det.threshold_nats,
        "applied": ("decision kept (neighbours' support)" if spatial else
                    "not applied: the window is hardly wider than the pulse" if not decidable else
                    "no return: no depth, flag NO_RETURN"),
        "uncertainty": ("larger of the estimator's and the profile likelihood's spread about the estimate"
                        if spreads else "the estimator's own (the test's spreads not computed: no maps written)"),
    }
    if tempered is not None:
        rec["pulse_dispersion"] = dict(tempered, applied="the likelihood's spreads tempered by it (its log over the "
                                       "dispersion) and the estimator's own uncertainty scaled by sqrt(dispersion)")
    if np.isfinite(thr_n):
        rec["detection"]["neighbours"] = {
            "rule": (f"a pixel that fails the test holds a return when the detections of the "
                     f"{(2 * SUPPORT_RADIUS + 1) ** 2 - 1} pixels around it pooled (its "
                     f"own left out) pass the same test within {half} bins of its estimate (gain > {thr_n:.2f} "
                     f"nats, false-alarm rate {det.false_alarm:g} for that span)"),
            "threshold_nats": thr_n, "half_bins": half}
        rec["detection"]["neighbours_region"] = {
            "rule": (f"a pixel that fails both holds a return when its own detections, where its neighbours see "
                     f"returns (within {half} bins of a shift at which they pass), pass the test at a false-alarm "
                     f"rate of {settings.neighbour_false_alarm:g} for that region's span; its depth is ml's best there"),
            "false_alarm": settings.neighbour_false_alarm}
    changes.update(tof_s=new_tof, depth_m=C_M_PER_S * new_tof / 2.0,
                   uncertainty_s=new_unc, flags=flags, settings=rec, gain_nats=det.gain_nats.reshape(h, w))
    out = dataclasses.replace(maps, **changes)
    if spreads and neighbours and dispersion:
        out = with_dispersion(out, pulse_dispersion(store, settings, out))
    return out


__all__ = ["Detection", "auto_threshold_nats", "detect", "fwhm_bins", "search_false_alarm", "surface_spreads", "decide_maps", "detect_kernel", "search", "search_kernel", "dispersion_of", "dispersion_terms",
           "likelihood_terms", "pulse_dispersion", "search_dispersion_terms", "with_dispersion"]
