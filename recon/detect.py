"""Is there a return? The per-pixel detection test and the honest uncertainty of every depth.

Every estimator's maps pass through :func:`decide_maps` (called by :func:`recon.estimate.reconstruct`,
the one place maps are assembled), so the decision and the uncertainty mean the same for all of them.

**The test** is the one ``--reflectors auto`` uses for K = 0 against 1 (:mod:`recon.estimators.surfaces_fit`): the
statistic is the Poisson log-likelihood gain of one return over a flat background,
``max_s max_{a, B >= 0} log L(s, a, B) - max_B log L(B)``, its shift searched over every whole bin of
the window and its amplitude and background profiled; a pixel holds a return when the gain exceeds
:func:`recon.estimators.surfaces_fit.auto_threshold_nats` at the false-alarm rate ``ReconSettings.false_alarm``
(default 1e-3 per pixel: about one background-only pixel in a thousand is taken for a return).
The profile is exact: with the signal share ``pi`` of the expected detections the gain at shift s is
``sum_j w_j log(1 + pi (g_j M / C_s - 1))`` over the pixel's distinct bins j (counts w_j, pulse
g_j at that shift, column sum C_s, M bins), concave in pi, solved by Newton's method.

**The uncertainty** of a reported depth is the largest of three spreads, each used only where it
exceeds the estimator's own (its Fisher or sandwich variance) beyond its resolution:

- the likelihood's over the whole window: the 68.27% and (halved) 95.45% quantiles of |s - estimate|
  under the likelihood of the shift at the best signal share, with a flat prior (a shift that sees
  no detection costs the whole return, n log(1 - pi)). Where the likelihood has several peaks (low
  SBR: a background cluster nearly as likely as the return) the far ones widen it;
- the sandwich (robust) variance at the estimate: the detections' score spread over the curvature;
- a bootstrap's: the 68.27% quantile of |s_b - estimate| over BOOTSTRAP resamples of the pixel's
  detections, s_b each resample's best shift. It sees what a model that fits badly hides from the
  likelihood: on tower_9km.mat returns spread over ~2 ns in pixels whose pulse core is 241 ps, and
  the halves of such a pixel chose different clusters, each with a "2 cm" sigma.

Measured without truth by ``spdepth bench honesty FILE`` (each pixel's detections split in two
halves, reconstructed apart, agreement within 1 and 3 combined sigma).

Pixels of the spatial estimator keep their decision (their neighbours support them, which this
pixelwise test cannot see) and get the larger of the two uncertainties only where their own
detections alone would pass the test (elsewhere the pixel's own likelihood says nothing of the
neighbours' support). Several surfaces per pixel: the pixel's surfaces are dropped when the test
finds no return at all; the surfaces found keep their own uncertainties and weak flags.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
from numba import njit, prange

from spdepth.recon.maps import C_M_PER_S, PixelFlag
from spdepth.recon.model import FINE_STEPS, Binning, Irf, build_kernel

#: Newton steps on the signal share at one shift (converges in 4-6; the cap guards a flat gain).
NEWTON_STEPS = 30
#: spatial: the pixel's own likelihood spread replaces the estimator's uncertainty when it is more
#: than this many times larger (decide_maps).
SPATIAL_OVERRULE = 3.0
#: The test is not applied to windows shorter than this many FWHM of the response (time cannot tell
#: a return from background there; every pixel keeps the estimator's decision).
UNDECIDABLE_FWHM = 4.0
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


@njit(cache=True, nogil=True)
def _share_gain(r, w, lo, hi, n_out, pi0):
    """(gain, pi): max over the signal share pi in [0, 1] of sum_{j in [lo, hi)} w_j log(1 + pi r_j)
    + n_out log(1 - pi), and its argument; entries with r_j <= -1 (no pulse there) are skipped:
    their counts are in n_out."""
    d0 = -n_out
    for j in range(lo, hi):
        if r[j] > -1.0:
            d0 += w[j] * r[j]
    if d0 <= 0.0:
        return 0.0, 0.0
    if n_out == 0.0:
        d1 = 0.0
        for j in range(lo, hi):
            if r[j] > -1.0:
                d1 += w[j] * r[j] / (1.0 + r[j])
        if d1 >= 0.0:
            return _fixed_gain(r, w, lo, hi, 0.0, 1.0), 1.0
    a, b = 0.0, 1.0
    pi = pi0 if 0.0 < pi0 < 1.0 else 0.5
    for _ in range(NEWTON_STEPS):
        f1 = -n_out / (1.0 - pi)
        f2 = -n_out / ((1.0 - pi) * (1.0 - pi))
        for j in range(lo, hi):
            if r[j] > -1.0:
                q = r[j] / (1.0 + pi * r[j])
                f1 += w[j] * q
                f2 -= w[j] * q * q
        if f1 > 0.0:
            a = pi
        else:
            b = pi
        nxt = pi - f1 / f2 if f2 < 0.0 else 0.5 * (a + b)
        if not (a < nxt < b):
            nxt = 0.5 * (a + b)
        if nxt >= 1.0:
            break
        done = abs(nxt - pi) < 1e-12
        pi = nxt
        if done:
            break
    return _fixed_gain(r, w, lo, hi, n_out, pi), pi


@njit(cache=True, nogil=True)
def _fixed_gain(r, w, lo, hi, n_out, pi):
    """sum_{j in [lo, hi)} w_j log(1 + pi r_j) + n_out log(1 - pi) (r_j <= -1 skipped: in n_out)."""
    gain = 0.0
    if n_out > 0.0:
        gain = n_out * math.log1p(-pi) if pi < 1.0 else -math.inf
    for j in range(lo, hi):
        if r[j] > -1.0:
            gain += w[j] * math.log1p(pi * r[j])
        elif pi >= 1.0:
            return -math.inf
    return gain


@njit(cache=True, nogil=True)
def _ratios(ud, wd, lo, hi, s, g, off, m, colsum, r):
    """r_j = g_j M / C_s - 1 of the distinct bins [lo, hi) at shift s (-1 where the pulse is 0);
    returns the counts with a pulse there."""
    n_in = 0.0
    for j in range(lo, hi):
        gj = g[ud[j] - s + off]
        if gj > 0.0:
            r[j] = gj * m / colsum[s] - 1.0
            n_in += wd[j]
        else:
            r[j] = -1.0
    return n_in


@njit(cache=True, nogil=True)
def _profile_scan(ud, wd, nd, n, s0, s1, step, g, off, m, colsum, r, best, best_s, best_pi):
    """The profiled gain at shifts s0, s0 + step, ... < s1; returns the best (gain, shift, share)
    seen, starting from (best, best_s, best_pi). Newton starts from the previous shift's share."""
    ng = g.size
    lo, hi = 0, 0
    pi0 = 0.5
    for s in range(s0, s1, step):
        while lo < nd and ud[lo] < s - off:
            lo += 1
        while hi < nd and ud[hi] <= s + ng - 1 - off:
            hi += 1
        if hi <= lo or colsum[s] <= 0.0:
            continue
        n_in = _ratios(ud, wd, lo, hi, s, g, off, m, colsum, r)
        gs, pi = _share_gain(r, wd, lo, hi, n - n_in, pi0)
        if pi > 0.0:
            pi0 = pi
        if gs > best:
            best, best_s, best_pi = gs, s, pi
    return best, best_s, best_pi


@njit(cache=True, nogil=True)
def _interp(table, x):
    """table at fractional index x (linear), 0 outside."""
    if x < 0.0 or x > table.size - 1:
        return 0.0
    i = int(x)
    if i >= table.size - 1:
        return table[table.size - 1]
    f = x - i
    return table[i] * (1.0 - f) + table[i + 1] * f


@njit(cache=True, nogil=True)
def _terms(ud, wd, nd, e, pi, fine, fine_colsum, fsteps, off, m, out):
    """Each distinct bin's term w_j log(1 + pi (g(u_j - e) M / C_e - 1)) at the fractional shift e."""
    c = _interp(fine_colsum, e * fsteps)
    for j in range(nd):
        gj = _interp(fine, (ud[j] - e + off) * fsteps)
        rj = gj * m / c - 1.0 if c > 0.0 else -1.0
        out[j] = wd[j] * math.log(max(1.0 + pi * rj, 1e-300))


@njit(cache=True, nogil=True)
def _sandwich_var(ud, wd, nd, e, pi, fine, fine_colsum, fsteps, off, m):
    """Robust (sandwich) variance of the shift at e (bins^2): the spread of the detections' scores
    over the likelihood's curvature squared, by central differences half a bin wide. It equals the
    Fisher variance when the pulse model fits, and grows where the detections spread wider than it
    (a mixed or tilted footprint, a response that differs from the model). NaN when not concave."""
    h = 0.5
    if e - h < 0.0 or e + h > m - 1:
        return np.nan
    t0 = np.empty(nd)
    tp = np.empty(nd)
    tm = np.empty(nd)
    _terms(ud, wd, nd, e, pi, fine, fine_colsum, fsteps, off, m, t0)
    _terms(ud, wd, nd, e + h, pi, fine, fine_colsum, fsteps, off, m, tp)
    _terms(ud, wd, nd, e - h, pi, fine, fine_colsum, fsteps, off, m, tm)
    curv = 0.0
    score2 = 0.0
    for j in range(nd):
        curv -= (tp[j] - 2.0 * t0[j] + tm[j]) / (h * h)
        sj = (tp[j] - tm[j]) / (2.0 * h) / wd[j]
        score2 += wd[j] * sj * sj
    if not curv > 0.0:
        return np.nan
    return score2 / (curv * curv)


@njit(cache=True, nogil=True)
def _bootstrap_sd(ud, wd, nd, n, e, pi, cand, n_cand, g, off, m, colsum, r, n_boot, seed):
    """Spread of the shift about e (bins) over ``n_boot`` bootstrap resamples of the detections:
    the 68.27% quantile of |s_b - e| (its core: a resample's far jumps at low SBR are the
    likelihood's to weigh), s_b each resample's best shift among ``cand[:n_cand]`` (the shifts the
    likelihood does not rule out, BOOT_NATS) at the signal share ``pi``. It sees what a model that
    fits badly hides from the likelihood: detections spread wider than the pulse (a mixed
    footprint) make resamples pick different clusters. NaN when too large to tabulate."""
    ng = g.size
    pi = min(pi, 1.0 - 0.5 / n)
    lq = math.log1p(-pi)
    if n_cand == 0 or n_cand * nd > BOOT_MAX_TABLE:
        return np.nan
    glo = np.empty(n_cand, np.int64)
    ghi = np.empty(n_cand, np.int64)
    start = np.empty(n_cand, np.int64)
    tab = np.empty(n_cand * nd, np.float64)
    at = 0
    for k in range(n_cand):
        s = int(cand[k])
        lo, hi = 0, nd
        while lo < nd and ud[lo] < s - off:
            lo += 1
        hi = lo
        while hi < nd and ud[hi] <= s + ng - 1 - off:
            hi += 1
        glo[k], ghi[k], start[k] = lo, hi, at
        if hi > lo:
            _ratios(ud, wd, lo, hi, s, g, off, m, colsum, r)
            for j in range(lo, hi):
                tab[at] = (math.log1p(pi * r[j]) - lq) if r[j] > -1.0 else 0.0
                at += 1
    # each detection's distinct bin, to resample detections (not bins)
    di = np.empty(n, np.int64)
    i = 0
    for j in range(nd):
        for _ in range(int(wd[j])):
            di[i] = j
            i += 1
    np.random.seed(seed)
    wb = np.zeros(nd, np.float64)
    dist = np.empty(n_boot, np.float64)
    for b in range(n_boot):
        wb[:] = 0.0
        for _ in range(n):
            wb[di[np.random.randint(0, n)]] += 1.0
        best, best_s = -math.inf, e
        for q in range(n_cand):
            v = 0.0
            a0 = start[q] - glo[q]
            for j in range(glo[q], ghi[q]):
                v += wb[j] * tab[a0 + j]
            if v > best:
                best, best_s = v, cand[q]
        dist[b] = abs(best_s - e)
    dist.sort()
    return dist[min(n_boot - 1, int(math.ceil(0.6827 * n_boot)) - 1)]


@njit(parallel=True, cache=True, nogil=True)
def detect_kernel(bins, offsets, m, g, off, colsum, fine, fine_colsum, fsteps, step, est_shift, thr, n_boot,
                  out_gain, out_best, out_sd, out_sandwich, out_boot):
    """Per pixel: the largest gain over shifts (nats, amplitude and background profiled; every
    ``step`` bins, then every bin around the best and around the estimate), its shift, and the spread
    of the shift about ``est_shift`` (NaN: none; bins): the larger of the 68.27% quantile and the
    95.45% quantile / 2 of |s - est| under the likelihood over shifts with the signal share at its
    best value (a flat prior; every bin within 2 steps of the estimate, every step bins elsewhere).
    bins: in-window bin indices grouped by pixel (``offsets``); g/off/colsum: the pulse kernel's."""
    npix = offsets.size - 1
    ng = g.size
    for p in prange(npix):
        o0, o1 = offsets[p], offsets[p + 1]
        n = o1 - o0
        out_gain[p] = 0.0
        out_best[p] = -1.0
        out_sd[p] = np.nan
        out_sandwich[p] = np.nan
        out_boot[p] = np.nan
        if n == 0:
            continue
        u = np.sort(bins[o0:o1])
        # distinct bins and their counts
        ud = np.empty(n, np.int64)
        wd = np.empty(n, np.float64)
        nd = 0
        for i in range(n):
            if nd > 0 and ud[nd - 1] == u[i]:
                wd[nd - 1] += 1.0
            else:
                ud[nd] = u[i]
                wd[nd] = 1.0
                nd += 1
        r = np.empty(nd, np.float64)
        e = est_shift[p]
        has_e = np.isfinite(e)
        best, best_s, best_pi = _profile_scan(ud, wd, nd, n, 0, m, step, g, off, m, colsum, r, 0.0, -1, 0.0)
        if step > 1 and best_s >= 0:
            best, best_s, best_pi = _profile_scan(ud, wd, nd, n, max(0, best_s - step + 1),
                                                  min(m, best_s + step), 1, g, off, m, colsum, r,
                                                  best, best_s, best_pi)
        if step > 1 and has_e:
            ce = int(round(e))
            best, best_s, best_pi = _profile_scan(ud, wd, nd, n, max(0, ce - 2 * step), min(m, ce + 2 * step + 1),
                                                  1, g, off, m, colsum, r, best, best_s, best_pi)
        out_gain[p] = best
        out_best[p] = best_s
        if not has_e or best_s < 0:
            continue
        # the likelihood over shifts at the best signal share: a shift no detection reaches costs the
        # whole return's detections (n log(1 - pi)), not nothing
        ce = int(round(e))
        fine_lo, fine_hi = ce - 2 * step, ce + 2 * step
        ns = 0
        pos = np.empty(m, np.float64)
        logw = np.empty(m, np.float64)
        lo, hi = 0, 0
        top = -math.inf
        for s in range(m):
            near = fine_lo <= s <= fine_hi
            if not near and s % step != 0:
                continue
            while lo < nd and ud[lo] < s - off:
                lo += 1
            while hi < nd and ud[hi] <= s + ng - 1 - off:
                hi += 1
            if colsum[s] <= 0.0:
                continue
            n_in = _ratios(ud, wd, lo, hi, s, g, off, m, colsum, r) if hi > lo else 0.0
            v = _fixed_gain(r, wd, lo, hi, n - n_in, best_pi)
            if v == -math.inf:
                continue
            # a coarse shift stands for the step bins around it
            pos[ns] = s
            logw[ns] = v + (0.0 if near else math.log(step))
            if logw[ns] > top:
                top = logw[ns]
            ns += 1
        if ns == 0:
            continue
        # the shifts the likelihood does not rule out: where a bootstrap resample may land
        cand = np.empty(ns, np.float64)
        n_cand = 0
        for i in range(ns):
            if logw[i] >= top - BOOT_NATS:
                cand[n_cand] = pos[i]
                n_cand += 1
        total = 0.0
        dist = np.empty(ns, np.float64)
        for i in range(ns):
            logw[i] = math.exp(logw[i] - top)
            total += logw[i]
            dist[i] = abs(pos[i] - e)
        order = np.argsort(dist)
        acc = 0.0
        q68, q95 = -1.0, -1.0
        for i in range(ns):
            acc += logw[order[i]]
            if q68 < 0.0 and acc >= 0.6827 * total:
                q68 = dist[order[i]]
            if acc >= 0.9545 * total:
                q95 = dist[order[i]]
                break
        if q95 < 0.0:
            q95 = dist[order[ns - 1]]
        if q68 < 0.0:
            q68 = q95
        out_sd[p] = max(q68, q95 / 2.0)
        out_sandwich[p] = _sandwich_var(ud, wd, nd, e, best_pi, fine, fine_colsum, fsteps, off, m)
        if n_boot > 0 and best > thr and n >= 2:
            # seeded by the pixel's own detections, not its index: a pixel gets the same spread in
            # a live batch, a Dask block or the whole frame
            seed = n
            for i in range(n):
                seed = (seed * 1000003 + u[i] + 1) % 2147483647
            out_boot[p] = _bootstrap_sd(ud, wd, nd, n, e, best_pi, cand, n_cand, g, off, m, colsum, r, n_boot, seed)


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


def detect(bins: np.ndarray, offsets: np.ndarray, kern, est_shift: np.ndarray, false_alarm: float,
           core_bins: float = 3.0) -> Detection:
    """The test and the likelihood's spread (module docstring) of every pixel's in-window detections
    ``bins`` (bin indices grouped by ``offsets``) about the estimated shifts ``est_shift`` (bins,
    NaN where the estimator reports none), for the pulse kernel ``kern`` over ``kern.n_bins`` bins;
    the shifts are scanned every ``core_bins`` (the RMS of the response's sharp part, bins),
    every bin near the best and near the estimate."""
    from spdepth.recon.estimators.surfaces_fit import auto_threshold_nats, fwhm_bins

    m = int(kern.n_bins)
    npix = offsets.size - 1
    gain = np.empty(npix)
    best = np.empty(npix)
    sd = np.empty(npix)
    sw = np.empty(npix)
    boot = np.empty(npix)
    thr = auto_threshold_nats(false_alarm, m, fwhm_bins(kern.g))
    step = max(1, int(core_bins))
    detect_kernel(np.ascontiguousarray(bins, np.int64), np.ascontiguousarray(offsets, np.int64), m,
                  kern.g, int(kern.off), kern.colsum, kern.fine, kern.fine_colsum, FINE_STEPS, step,
                  np.ascontiguousarray(est_shift, np.float64), float(thr), BOOTSTRAP, gain, best, sd, sw, boot)
    return Detection(gain > thr, gain, sd, sw, boot, float(thr), float(false_alarm))


def _kernel_of(settings: dict):
    """The binning and pulse kernel a result's ``settings`` record says were used (the same cached
    object the estimator built: :func:`recon.model.build_kernel`)."""
    b = Binning.from_dict(settings["binning"])
    irf = settings.get("irf")
    if isinstance(irf, dict) and irf.get("times_s"):
        return b, build_kernel(b, irf=Irf.from_dict(irf))
    return b, build_kernel(b, pulse_rms_s=float(settings["pulse_rms_s"]))


def decide_maps(store, settings, maps):
    """``maps`` with the test applied and honest uncertainties (module docstring): pixels without a
    return get no depth and the flag NO_RETURN; ``settings['detection']`` records the test."""
    from spdepth.recon.pixelwise import binned_photons

    rec = dict(maps.settings)
    b, kern = _kernel_of(rec)
    bins, offsets = binned_photons(store, b, settings.max_photons)
    tof = np.asarray(maps.tof_s, np.float64)
    unc = np.asarray(maps.uncertainty_s, np.float64)
    several = tof.ndim == 3
    first = tof[0] if several else tof
    est = (first.ravel() / b.time_unit_s - b.window_start) / b.bin_width - 0.5
    if several:
        est = np.full(est.shape, np.nan)    # the surfaces keep their own uncertainties: only the test
    core_s = float(rec.get("pulse_core_rms_s", rec["pulse_rms_s"]))
    det = detect(bins, offsets, kern, est, settings.false_alarm, core_s / b.bin_width_s)
    h, w = maps.shape
    has = det.has_return.reshape(h, w)
    flags = np.array(maps.flags, np.uint8, copy=True)
    n_photons = np.diff(offsets).reshape(h, w)
    spatial = settings.method == "spatial"
    changes = {}
    from spdepth.recon.estimators.surfaces_fit import fwhm_bins

    # a window hardly wider than the pulse: time cannot tell a return from background
    decidable = b.n_bins >= UNDECIDABLE_FWHM * fwhm_bins(kern.g)
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
        new_unc = np.where(keep, unc, np.nan)
    else:
        new_tof = np.where(drop, np.nan, tof)
        bw = b.bin_width_s
        # each spread replaces the estimator's uncertainty only where it is larger beyond its own
        # resolution: the likelihood's and the bootstrap's are read on a grid of whole bins (a
        # bin), the bootstrap's quantile from BOOTSTRAP resamples is good to about BOOT_NOISE
        post = np.sqrt(np.fmax(det.sd_bins ** 2 + 1.0 / 12.0, det.sandwich_var_bins2)).reshape(h, w) * bw
        boot = np.sqrt(det.bootstrap_sd_bins ** 2 + 1.0 / 12.0).reshape(h, w) * bw
        use_post = np.isfinite(post) & (post > unc + bw)
        use_boot = np.isfinite(boot) & (boot > (1.0 + BOOT_NOISE) * unc + bw)
        if spatial:
            # the neighbours narrow a spatial depth beyond what the pixel's own detections say;
            # those overrule them only where they put the return far from the spatial depth
            # (beyond 3 of its sigma and the pulse's sharp part): another likely return
            far = has & (np.fmax(np.where(use_post, post, 0), np.where(use_boot, boot, 0)) > SPATIAL_OVERRULE * unc)
            far &= np.fmax(post, boot) > core_s
            use_post &= far
            use_boot &= far
        sd = np.fmax(np.where(use_post & decidable, post, 0.0), np.where(use_boot & decidable, boot, 0.0))
        new_unc = np.where(np.isfinite(new_tof), np.fmax(unc, sd), np.nan)
        changes["signal"] = np.where(drop, 0.0, maps.signal)
    flags[drop] = PixelFlag.NO_RETURN
    rec["detection"] = {
        "rule": (f"likelihood-ratio test of one return against background alone, false-alarm rate "
                 f"{det.false_alarm:g} per pixel (gain > {det.threshold_nats:.2f} nats)"),
        "false_alarm": det.false_alarm, "threshold_nats": det.threshold_nats,
        "applied": ("decision kept (neighbours' support)" if spatial else
                    "not applied: the window is hardly wider than the pulse" if not decidable else
                    "no return: no depth, flag NO_RETURN"),
        "uncertainty": "larger of the estimator's and the profile likelihood's spread about the estimate",
    }
    changes.update(tof_s=new_tof, depth_m=C_M_PER_S * new_tof / 2.0,
                   uncertainty_s=new_unc, flags=flags, settings=rec)
    return dataclasses.replace(maps, **changes)


__all__ = ["Detection", "detect", "decide_maps", "detect_kernel"]
