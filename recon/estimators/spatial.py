"""The spatial estimator (``method="spatial"``): depth from a pixel's detections *and* its
neighbours', for scenes that are piecewise smooth. Not pixelwise, so a live scan shows ml's maps
and runs it once on the final frame; with several surfaces, each surface supported by its
neighbours (:mod:`.surfaces`, "spatial-surfaces"). Allocation and constants here; the numba
kernels are in :mod:`.spatial_kernels`, loaded on the first run.

Three steps, each after a paper, with what was changed:

1. **Censoring** of likely background detections, after Rapp and Goyal, "A few photons among many:
   unmixing signal and noise for photon-efficient active imaging", IEEE TCI 2017. They keep a
   detection when the detections of an adaptive superpixel around it hold enough others close in
   time. Here the neighbourhood is a fixed square (the pixel's own other detections included) of (2 r + 1)^2 pixels (r = 2 when pixels hold
   fewer than ``WIDE_BELOW`` detections, else 1), "close" is within ``TAU_RMS`` pulse RMS widths,
   and "enough" is the Poisson upper quantile of what uniform background alone would bring (every
   neighbour detection treated as background: a conservative threshold that needs no background
   estimate) at the level per detection that holds the pixel's false-alarm rate
   (``ReconSettings.false_alarm``, ``--false-alarm``, the rate recon.detect's test states per pixel:
   :func:`censor_alpha`), since one kept detection gives a pixel a depth. A detection on a surface edge keeps the support of the pixels on its own
   side, so censoring does not need the edge.
2. **Pixelwise fit** of the detections: the densest cluster of kept detections seeds a few EM steps
   on all the pixel's detections for a Gaussian pulse over a flat background (the exact Poisson
   model of the seed paper, Shin, Shapiro and Goyal 2015, restricted to one return with the
   background a free mixture weight). Its outputs are the shift, the expected signal count (sum of
   responsibilities: the Fisher weight of the shift, in pulse widths) and the background per bin
   from the detections not attributed to the return. Rapp and Goyal estimate depth from the kept
   detections by ML too; they then regularise with TV as Shin et al. (IEEE TCI 2015) do.
3. **Edge-preserving regulariser**: weighted total-variation denoising of the shift map, as in Shin
   et al., "Photon-efficient computational 3-D and reflectivity imaging with single-photon
   detectors", IEEE TCI 2015, but with a quadratic data term weighted by each pixel's signal count
   (its Fisher information) instead of their penalised Poisson likelihood: ``min sum_p k_p (z_p -
   f_p)^2 / 2 + LAMBDA * TV(z)`` in units of the pulse RMS, solved by Chambolle and Pock's
   primal-dual algorithm. The weights make the smoothing fade where the data are strong (many
   detections) and fill pixels that have none (``k_p = 0``): those are flagged
   ``PixelFlag.INTERPOLATED``. A pixel with no data within ``FILL_RADIUS`` is left NaN.

Uncertainty: what the regulariser makes of the pixelwise fits' own noise: the TV step runs again
on ``PROBES`` copies of the fitted shifts with that noise added (variance ``D sigma^2 / k``, k the
signal count, D the fits' dispersion: the spread of a return's detections about one another
against the model's, from every pair of a pixel's detections weighted by their responsibilities,
pooled over the frame (:func:`fit_dispersion`); with chance exp(-k) a weak pixel's
shift is replaced by a neighbour's, its detections having been background the neighbours kept),
and a pixel's variance is the mean square of its change (:func:`regulariser_variance`, a
parametric bootstrap of the regularisation); ``recon.detect`` then widens it where the pixel's own
detections spread its return beyond ``SPATIAL_OVERRULE`` times it. It replaced a rule calibrated on simulated scenes (the pixel's
count plus half its 8 like neighbours'), which TV's plateaus over weak data made far too wide
(art_top.mat halves: 93% within 1 sigma, median sigma 3.5 m on filled pixels).

Filling: a pixel whose detections were all censored is filled only where one of them lies within
tau of the filled depth; a pixel without detections only where its neighbours' surface is not
ruled out at the stated false-alarm rate (exp(-k) for their mean signal count k); else NO_RETURN.

The Gaussian pulse model has the width of the response's FWHM (:func:`pulse_width_s`: the RMS
itself for a Gaussian pulse, never narrower than a measured response's sharp core); the rest of a
measured response's tail is left to the flat background term (its shape is not used). With the full
RMS, a tail the response estimate took from background (the simulated daylight scene at SBR 0.05:
RMS 42.6 ns, core 339 ps) made the pulse as wide as the window.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Callable

from spdepth.recon.estimators import Estimator, register

if TYPE_CHECKING:
    import numpy as np

    from spdepth.recon.maps import DepthMaps
    from spdepth.recon.model import ReconSettings
    from spdepth.recon.photons import PhotonStore

#: The pixelwise fits' dispersion (:func:`fit_dispersion`) needs pairs of detections weighing more than this,
#: and is taken on at most this many pixels.
DISPERSION_MIN_PAIRS = 100.0
DISPERSION_PIXELS = 20_000
#: Censoring: support within this many pulse RMS widths of a detection.
TAU_RMS = 1.5
#: Censoring: pixels with a median below this many detections pool a 5 x 5 window, else 3 x 3.
WIDE_BELOW = 8
#: Censoring: frames with a median of at least this many detections per pixel bound each detection's
#: support by coarse counts of its window first (measured at SBR 10: break-even at 22-25, 6% slower
#: at 20, 12% faster at 60).
BOUND_FROM = 25
#: ... and from this median on when at least BOUND_BACKGROUND_SHARE of the detections are background
#: (:func:`background_share`): the bounds then rule out the background detections that would be
#: counted against every neighbour. 256 x 256, 1 thread, at 15 / 20 detections, pixels/s without ->
#: with these bounds: SBR 1 345k / 281k -> 391k / 344k, SBR 3 370k / 317k -> 387k / 346k, SBR 0.1
#: 317k / 246k -> 338k / 316k; at SBR 10 (share 0.09) they would cost about 2%, and at 10
#: detections they won at SBR 1 (+7%) but lost at SBR 0.1 (-4%) and 3 (-1%).
BOUND_FROM_BACKGROUND = 15
BOUND_BACKGROUND_SHARE = 0.15
#: Censoring: width of those coarse bins, in censoring widths tau; NARROW_COUNT_BIN_TAU in frames
#: mostly of background. Narrower bins bound more tightly (a detection's interval of 2 tau touches
#: bins spanning less than 2 tau + 2 widths) but cost more to count (4x the bins): they pay where
#: most detections are background, whose support is counted against every neighbour unless a bound
#: rules it out. 128 x 128, 60 detections per pixel, 1 thread, 2 / 0.5 tau: SBR 0.1 52k / 121k
#: pixels/s, SBR 1 128k / 128k, SBR 10 159k / 151k (same maps).
COUNT_BIN_TAU = 2.0
NARROW_COUNT_BIN_TAU = 0.5
#: Censoring: the narrow bins when at least this share of the detections is background
#: (:func:`background_share`, measured on SHARE_SAMPLE pixels spread over the frame).
NARROW_FROM_BACKGROUND = 0.5
SHARE_SAMPLE = 512
#: EM steps of the pixelwise fit.
EM_ITERS = 4
#: TV weight, in pulse RMS widths per unit of signal count.
LAMBDA = 1.0
#: TV iterations (primal-dual), started from a local weighted mean.
TV_ITERS = 60
#: Pixels with no data within this radius are not filled (NaN, flagged).
FILL_RADIUS = 2
#: Uncertainty: noisy copies of the frame the regulariser runs on (regulariser_variance; the
#: variance of each pixel is then good to about sqrt(2 / PROBES)).
PROBES = 16


def poisson_quantile(q: float, mu: np.ndarray) -> np.ndarray:
    """The smallest k with P(Poisson(mu) <= k) >= q (0 < q < 1, mu >= 0): scipy.stats.poisson.ppf,
    computed as it does, from scipy.special (importing scipy.stats alone took 1.15 s, more than the
    spatial estimator's whole run on a small frame in a new process)."""
    import numpy as np

    from scipy import special

    k = np.ceil(special.pdtrik(q, mu))
    below = np.maximum(k - 1, 0)
    return np.where(special.pdtr(below, mu) >= q, below, k)


def censor_alpha(false_alarm: float, n: np.ndarray) -> np.ndarray:
    """The chance a single background detection may have of passing censoring so that a pixel of
    ``n`` detections, all background, keeps none with probability ``1 - false_alarm`` (the pixel's
    false-alarm rate, ``ReconSettings.false_alarm``, as recon.detect states its own): each of the
    n detections is one test, so by Sidak ``1 - (1 - false_alarm)^(1/n)`` (conservative: tests of
    detections close in time are positively correlated). A kept detection is what gives a spatial
    pixel a depth, so a fixed level per detection (the former ALPHA 0.02) let about
    ``1 - 0.98^n`` of background-only pixels through: 64% at 50 detections."""
    import numpy as np

    n = np.maximum(np.asarray(n, np.float64), 1.0)
    return -np.expm1(np.log1p(-false_alarm) / n)


def support_needed(counts: np.ndarray, window: np.ndarray, share: float, false_alarm: float) -> np.ndarray:
    """s_min per pixel: the fewest other detections of the pixel's window within +-tau of one of
    its detections that background alone brings with chance below :func:`censor_alpha` (the
    Poisson upper quantile of ``share`` (2 tau / window length) times the window's other
    detections, every one treated as background: a conservative threshold that needs no
    background estimate), plus one. counts: each pixel's detections; window: the detections of
    its (2 r + 1)^2 window, its own included."""
    import numpy as np

    win = np.maximum(np.rint(window) - 1, 0).astype(np.int64)
    own = counts.astype(np.int64)
    # whole counts, so a frame has few distinct (window, own) pairs: the quantile once per pair
    # (scipy's ppf per pixel took longer than all the kernels together), found as one integer key
    # (np.unique over columns sorted 5x slower)
    span = int(own.max(initial=0)) + 1
    keys, index = np.unique(win * span + own, return_inverse=True)
    pair_win, pair_own = keys // span, keys % span
    s = poisson_quantile(1.0 - censor_alpha(false_alarm, pair_own), pair_win * share) + 1.0
    return np.maximum(s.astype(np.int64)[index.ravel()], 1)


def background_share(x: np.ndarray, wx: np.ndarray, offsets: np.ndarray, sigma: float,
                     sample: int = SHARE_SAMPLE) -> float:
    """About the share of the frame's detections that are background, without a model: on up to
    ``sample`` pixels spread over the frame, the detections outside each pixel's densest span of
    5 pulse RMS (the cluster censor_fit seeds its fit with) over all of them. x: each pixel's
    sorted detection shifts (bins), wx the detections at each; sigma: the pulse RMS (bins)."""
    import numpy as np

    npix = offsets.size - 1
    pix = np.unique(np.linspace(0, npix - 1, min(npix, sample)).astype(np.int64))
    counts = offsets[pix + 1] - offsets[pix]
    keep = counts > 0
    pix, counts = pix[keep], counts[keep]
    if not counts.size:
        return 0.0
    from spdepth.recon.photons import rows_of

    # one sorted key per entry (pixel, then time): the detections of a span are a key range
    idx = rows_of(offsets, pix)[0]
    span = 5.0 * sigma
    xs = x[idx]
    through = np.zeros(idx.size + 1, np.int64)      # the detections before each entry
    np.cumsum(wx[idx], out=through[1:])
    apart = float(xs.max() - xs.min()) + span + 1.0
    key = np.repeat(np.arange(pix.size) * apart, counts) + xs
    in_span = through[np.searchsorted(key, key + span, side="right")] - through[:-1]
    densest = np.maximum.reduceat(in_span, np.cumsum(counts) - counts)
    return 1.0 - float(densest.sum()) / float(through[-1])


def fit(store: PhotonStore, settings: ReconSettings, b, kern, notes: dict,
        progress: Callable[[int, int], None] | None = None) -> DepthMaps:
    """:data:`recon.estimators.Fit` of the spatial estimator (one surface per pixel; several are
    :mod:`recon.estimators.surfaces_fit`'s): depth, background and signal at every pixel of ``store`` from the pixel
    and its neighbours, on the resolved binning ``b`` and pulse ``kern``.

    ``settings['spatial']`` in the result holds this module's constants. Pixels whose depth comes
    from their neighbours only are flagged ``INTERPOLATED`` (their photons, signal and background
    are their own: 0 with no detections).
    """
    import numpy as np

    # the kernels (numba) and the maps load when the estimator runs, not when it is declared
    from spdepth.recon.estimators import spatial_kernels as SK
    from spdepth.recon.maps import C_M_PER_S, DepthMaps, PixelFlag
    from spdepth.recon.pixelwise import detections_per_pixel, settings_record

    h, w = store.shape
    npix = h * w
    m = b.n_bins
    sigma = pulse_width_s(settings, notes) / b.bin_width_s

    x, wx, offsets = _shifts(store, b, settings.max_photons, SK)
    entries = np.diff(offsets)
    counts = detections_per_pixel(wx, offsets)
    nonzero = counts[counts > 0]
    typical = float(np.median(nonzero)) if nonzero.size else 0.0
    radius = 2 if typical < WIDE_BELOW else 1

    # censoring threshold per pixel: what background alone would bring, at the per-detection level
    # that holds the pixel's false-alarm rate (censor_alpha)
    tau = TAU_RMS * sigma
    s_min = support_needed(counts, _box_sum(counts.reshape(h, w).astype(np.float64), radius).ravel(),
                           min(1.0, 2.0 * tau / m), settings.false_alarm)
    if 2.0 * tau > 0.5 * m:
        # a window hardly wider than the pulse: time cannot tell background from signal, so
        # nothing is censored (the fit's flat term still takes its share)
        s_min[:] = 0

    mu = np.empty(npix)
    k = np.empty(npix)
    bg = np.empty(npix)
    n_used = np.empty(npix, np.int64)
    n_cens = np.empty(npix, np.int64)
    # identical results either way; the coarse counts cost a pass over the detections and save the
    # neighbour counts of most background detections, which pays with many detections per pixel or
    # much background
    count_width = COUNT_BIN_TAU * tau
    share = background_share(x, wx, offsets, sigma) if typical >= BOUND_FROM_BACKGROUND else 0.0
    if typical >= BOUND_FROM or share >= BOUND_BACKGROUND_SHARE:
        if share >= NARROW_FROM_BACKGROUND:
            count_width = NARROW_COUNT_BIN_TAU * tau
        win_counts = np.empty((npix, int(math.ceil(m / count_width))), np.int32)
        SK.window_counts(x, wx, offsets, h, w, radius, count_width, win_counts)
    else:
        win_counts = np.empty((npix, 0), np.int32)
    cs = SK.CensorSettings(h, w, radius, tau, sigma, float(m), EM_ITERS, count_width)
    SK.censor_fit(x, wx, offsets, s_min, win_counts, cs, mu, k, bg, n_used, n_cens)
    if progress is not None:
        progress(npix // 2, npix)

    # TV in units of the pulse RMS, weighted by the signal counts
    has = np.isfinite(mu) & (k > 1e-6)
    wt = np.where(has, k, 0.0).reshape(h, w)
    f = np.where(has, mu / sigma, 0.0).reshape(h, w)
    z, reach = _regularise(f, wt, SK)
    # a pixel whose detections were all censored is filled from its neighbours only where one of
    # them lies within tau of the filled depth (its own light agrees with their surface): filling
    # every such pixel reported the neighbours' surface over background-only pixels (the halves of
    # art_top.mat disagreed beyond 3 sigma on 27% of them). A pixel without detections is filled
    # unless its neighbours' surface is ruled out at the stated false-alarm rate: where they hold k
    # signal detections on average, a like surface leaves none with chance exp(-k) (tower_9km.mat:
    # pixels without a detection, so without background either, beside strong returns of the tower)
    zs = z.ravel() * sigma
    near = np.zeros(npix, bool)
    pix = np.repeat(np.arange(npix), entries)
    close = np.abs(x - zs[pix]) <= tau
    near[pix[close]] = True
    n_near = _box_sum((wt > 0).astype(np.float64), 1).ravel()
    k_near = _box_sum(wt, 1).ravel() / np.maximum(n_near, 1.0)
    dropout = (n_used == 0) & (n_near > 0.5) & (k_near <= -math.log(settings.false_alarm))
    report = reach.ravel() & (has.ravel() | dropout | near)
    shift = np.where(report, zs, np.nan)
    if progress is not None:
        progress(npix, npix)

    # uncertainty: what the regulariser makes of the data's own noise (regulariser_variance)
    finite = np.isfinite(shift)
    # in that noise, the detections' own spread about their returns, not the model's: the core's
    # Gaussian leaves out a response's tail near it (chart_depth.mat with its measured response,
    # core 126 ps of 225 RMS: dispersion 1.44, halves 94.0% / 49.6% within 3 / 1 sigma -> 98.7% / 59.7%)
    # and a stated pulse wider than the response (the mannequin at 360 ps: 0.48, 99.3% / 94.3% ->
    # 99.2% / 79.6%)
    disp = fit_dispersion(x, wx, offsets, mu, n_used, np.clip(k / np.maximum(n_used, 1), 1e-3, 0.999), sigma, m)
    var = sigma * sigma * regulariser_variance(f, wt, z, reach, SK, chosen=(~has & (n_used > 0)).reshape(h, w),
                                               dispersion=disp).ravel()
    var = np.where(np.isfinite(var), var, np.inf)
    var = np.minimum(var, m * m / 12.0)          # never more than the window's uniform spread
    unc_s = np.where(finite, np.sqrt(var), np.nan) * b.bin_width_s

    tof_s = np.where(finite, b.shift_to_time_s(np.nan_to_num(shift)), np.nan)
    signal = np.where(has, k, 0.0)
    flags = np.full(npix, PixelFlag.OK, np.uint8)
    flags[finite & ~has] = PixelFlag.INTERPOLATED
    flags[~finite & (n_used > 0)] = PixelFlag.NO_SIGNAL
    flags[~finite & (n_used == 0)] = PixelFlag.NO_PHOTONS

    rec = settings_record(settings, notes, b, kern)
    rec["spatial"] = {"radius": radius, "tau_rms": TAU_RMS, "pulse_width_rms_s": sigma * b.bin_width_s,
                      "censoring_false_alarm": (f"{settings.false_alarm:g} per pixel (each of its n "
                                                f"detections at 1 - (1 - {settings.false_alarm:g})^(1/n))"), "em_iters": EM_ITERS,
                      "tv_lambda": LAMBDA, "tv_iterations": TV_ITERS, "fill_radius": FILL_RADIUS,
                      "fit_dispersion": disp,
                      "interpolated": int((flags == PixelFlag.INTERPOLATED).sum()),
                      "detections_kept_by_censoring": int(n_cens.sum())}
    tof_img = tof_s.reshape(h, w)
    return DepthMaps(tof_s=tof_img, depth_m=C_M_PER_S * tof_img / 2.0, background=bg.reshape(h, w),
                     signal=signal.reshape(h, w), photons=n_used.reshape(h, w),
                     iterations=np.full((h, w), TV_ITERS, np.int32),
                     uncertainty_s=unc_s.reshape(h, w), flags=flags.reshape(h, w), settings=rec)


def pulse_width_s(settings: ReconSettings, notes: dict) -> float:
    """The RMS of the estimator's Gaussian pulse (s): the Gaussian of the response's FWHM
    (``recon.model.irf_fwhm_rms_s``), never narrower than its sharp core; a Gaussian pulse's RMS.

    Not the response's RMS: a measured response's tail (tower_9km.mat: 26% of it, 707 ps mean
    delay) or a background mistaken for one (the simulated daylight scene: an RMS of 42.6 ns over
    a 100 ns window, which left nothing to censor) is no part of a return's cluster (tower: depths
    0.2 cm nearer than with the RMS width, median; halves 96.3% / 71.9% within 3 / 1 sigma, were
    97.6% / 84.7%). Not the sharp core alone either (its leading edge, ``pulse_core_rms_s``): where
    a sharp edge leads a long tail, most of a return's detections lie beyond it, and a Gaussian
    of the edge's width fits a few of them, a different few in each draw (the mannequin, its
    response measured with an edge of 62 ps and a 233 ps tail: the pixelwise fits of the two
    halves differed by 1.78 times their stated sigma (robust SD), and each half reported a depth
    on 93.6% / 91.9% of the pixels; with the FWHM's Gaussian, 128 ps: 1.09, and 96.0% / 94.4%)."""
    from spdepth.recon.model import Irf, irf_fwhm_rms_s

    core_s = float(notes.get("pulse_core_rms_s", notes["pulse_rms_s"]))
    irf = settings.irf if settings.irf is not None else Irf.from_dict(notes["irf"]) if notes.get("irf") else None
    return core_s if irf is None else max(core_s, irf_fwhm_rms_s(irf))


def fit_dispersion(x, wx, offsets, mu, n_used, pi, sigma: float, m: int) -> float:
    """The pixelwise fits' dispersion: the spread of a return's detections about one another,
    sigma_eff^2 / sigma^2, from every pair of detections of a pixel weighted by both their
    responsibilities (E (x_i - x_j)^2 = 2 sigma_eff^2 for two of one return; no shift is fitted,
    so no correction for it), pooled over the frame's pixels with a fit (at most
    DISPERSION_PIXELS, evenly spaced). 1 when the Gaussian of the core width describes the
    detections about their returns; above 1 where a response's tail near the core widens them,
    below where the stated pulse is wider than the returns."""
    import numpy as np

    from spdepth.recon.photons import evenly_spaced, rows_of

    # a sample of the frame: a numpy pass over every detection cost 19% of the estimate's time at
    # 30 detections a pixel
    some = evenly_spaced(np.flatnonzero(np.isfinite(mu) & (n_used >= 2)), DISPERSION_PIXELS)
    at, sub = rows_of(offsets, some)
    n = some.size
    pp = np.repeat(np.arange(n), np.diff(sub))
    xs = x[at]
    d = xs - mu[some][pp]
    pi_d = pi[some][pp]
    rho = pi_d / (math.sqrt(2.0 * math.pi) * sigma) * np.exp(-0.5 * d * d / (sigma * sigma))
    rho = rho / (rho + (1.0 - pi_d) / m)
    w = np.asarray(wx, np.float64)[at]
    s1 = np.bincount(pp, w * rho, minlength=n)
    s2 = np.bincount(pp, w * rho * rho, minlength=n)
    a1 = np.bincount(pp, w * rho * xs, minlength=n)
    b1 = np.bincount(pp, w * rho * xs * xs, minlength=n)
    pairs = np.sum(s1 * s1 - s2)
    if not pairs > DISPERSION_MIN_PAIRS:
        return 1.0
    # never below a bin's own spread (detections one bin apart or in one bin: the bins are the resolution)
    return max(float(np.sum(s1 * b1 - a1 * a1) / pairs), 1.0 / 12.0) / (sigma * sigma)


def _shifts(store, b, max_photons: int | None, SK) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(x, wx, offsets): each pixel's in-window detections as sorted shifts (bins, spatial_kernels'
    module docstring) and the detections at each (int32): a photon list's first ``max_photons``
    one by one, or a count store's (time, count) pairs as they are (its times ascending and
    distinct within a pixel; whole counts, a corrected store's rounded), so that the work grows
    with the occupied bins and the results are those of its photon list."""
    import numpy as np

    from spdepth.recon.counts import CountStore
    from spdepth.recon.errors import InputError

    if isinstance(store, CountStore):
        if max_photons is not None:
            raise InputError("counts keep no detection order: max_photons does not apply")
        store = store.rounded()
        t = store.times
        keep = (t >= b.window_start) & (t < b.window_stop)
        # the same arithmetic as SK.window_shifts', so a pair's shift is its detections' to the bit
        x = (t[keep] - float(b.window_start)) / float(b.bin_width) - 0.5
        offsets = np.zeros(store.n_pixels + 1, np.int64)
        np.cumsum(np.bincount(store.pixel_index()[keep], minlength=store.n_pixels), out=offsets[1:])
        return x, store.counts[keep].astype(np.int32), offsets
    x = np.empty(store.times.size, np.float64)
    offsets = np.empty(store.n_pixels + 1, np.int64)
    n_kept = SK.window_shifts(store.times, store.offsets, b.window_start, b.window_stop, b.bin_width,
                              -1 if max_photons is None else int(max_photons), x, offsets)
    return x[:n_kept], np.ones(n_kept, np.int32), offsets


def _start(f: np.ndarray, wt: np.ndarray, SK) -> tuple[np.ndarray, np.ndarray]:
    """(z0, reach): the TV iterations' start, the local weighted mean of ``f`` (the weighted mean of
    all where no data lie within FILL_RADIUS), and where data lie within FILL_RADIUS."""
    import numpy as np

    z = np.empty(f.shape)
    SK.local_mean(f, wt, FILL_RADIUS, z)
    reach = np.isfinite(z)
    if reach.any():
        z[~reach] = np.average(f[wt > 0], weights=wt[wt > 0])
    return z, reach


def _regularise(f: np.ndarray, wt: np.ndarray, SK) -> tuple[np.ndarray, np.ndarray]:
    """(z, reach): the TV solution of the shifts ``f`` (pulse RMS) with weights ``wt``, started from
    the local weighted mean, and where data lie within FILL_RADIUS (z elsewhere: meaningless)."""
    import numpy as np

    z, reach = _start(f, wt, SK)
    if reach.any():
        scratch = [np.empty(f.shape) for _ in range(3)]
        SK.tv_pdhg(f, wt, LAMBDA, z, TV_ITERS, *scratch)
    return z, reach


def regulariser_variance(f: np.ndarray, wt: np.ndarray, z: np.ndarray, reach: np.ndarray, SK,
                         probes: int | None = None, seed: int = 0,
                         chosen: np.ndarray | None = None, dispersion: float = 1.0) -> np.ndarray:
    """Variance of each regularised shift z (pulse RMS^2; NaN outside ``reach``), by a parametric
    bootstrap of the regularisation: the pixelwise shifts f carry noise of variance dispersion / wt
    (wt the fit's Fisher weight, in pulse widths; ``dispersion`` :func:`fit_dispersion`'s), which
    the regulariser averages over as many neighbours
    as it fuses (far beyond the 8 next to a pixel on a flat patch of weak data, where TV makes
    plateaus; none across an edge), so the whole regulariser runs again on ``probes`` copies of
    the fitted model, z plus that noise, and each pixel's variance is the mean square of its
    result about z. A filled pixel (wt 0) gets the spread of the neighbours it is filled from. A
    fit of weak data may be no return of the pixel's own: with chance exp(-wt) its detections were
    background kept by the neighbours' support, so in each copy such a pixel takes a random
    neighbour's value. ``chosen`` pixels (filled where one of their own detections agrees with the
    fill) add the spread of the depths around them: which neighbour's surface their detection
    matched is a choice the noise does not make. Seeded: the same frame gets the same
    uncertainties. (Copies of f instead of z, noisier than the data by sqrt 2, gave the simulated
    scene of test_uncertainty_roughly_calibrated an error IQR of 0.61 sigma-units of 1.35.)"""
    import numpy as np

    probes = PROBES if probes is None else probes
    rng = np.random.default_rng(seed)
    has = wt > 0
    sd = np.where(has, math.sqrt(dispersion) / np.sqrt(np.where(has, wt, 1.0)), 0.0)
    h, w = f.shape
    rows, cols = np.indices(f.shape)
    # a fit of weak data may not be the pixel's own return at all: with chance exp(-wt) (no signal
    # detection of its own, for wt signal detections expected) its detections were background that
    # the neighbours' support kept, and its shift is one of theirs (tower_9km.mat's halves, before
    # recon.detect: 92.5% within 3 sigma without this, 95.7% with it; art_top.mat 98.3%, 98.5%)
    stray = np.exp(-np.where(has, wt, 0.0))
    fs = np.empty((probes, h, w))
    zs = np.empty((probes, h, w))
    for j in range(probes):
        fj = np.where(has, z + sd * rng.standard_normal(f.shape), 0.0)
        pick = has & (rng.random(f.shape) < stray)
        dr, dc = rng.integers(-1, 2, f.shape), rng.integers(-1, 2, f.shape)
        rr, cc = np.clip(rows + dr, 0, h - 1), np.clip(cols + dc, 0, w - 1)
        pick &= has[rr, cc]
        fs[j] = np.where(pick, fj[rr, cc], fj)
        zs[j] = _start(fs[j], wt, SK)[0]
    if reach.any():
        # the copies' smoothing in parallel (as _regularise runs it, one copy at a time: same results)
        SK.tv_pdhg_many(fs, wt, LAMBDA, zs, TV_ITERS)
    acc = ((zs - z[None]) ** 2).sum(axis=0)
    var = acc / probes
    # measured on the halves of art_top.mat: without the spread 89% of such pixels agreed within 3
    # sigma, with it 97%; a pixel filled without detections (tower_9km.mat) is right without it
    # (96%) and too wide with it (99%, 91% within 1 sigma)
    filled = reach & ~has & (chosen if chosen is not None else False)
    if filled.any():
        zf = np.where(has, z, 0.0)
        one = has.astype(np.float64)
        s0 = _box_sum(one, FILL_RADIUS)
        s1 = _box_sum(one * zf, FILL_RADIUS)
        s2 = _box_sum(one * zf * zf, FILL_RADIUS)
        with np.errstate(invalid="ignore", divide="ignore"):
            spread = np.maximum(s2 / s0 - (s1 / s0) ** 2, 0.0)
        var = np.where(filled, var + np.nan_to_num(spread), var)
    return np.where(reach, var, np.nan)


def _box_sum(a: np.ndarray, radius: int) -> np.ndarray:
    """Sum of ``a`` over the (2 radius + 1)^2 window around each pixel, clipped at the border."""
    import numpy as np

    h, w = a.shape
    c = np.zeros((h + 1, w + 1))
    c[1:, 1:] = a.cumsum(0).cumsum(1)
    r = np.arange(h)
    col = np.arange(w)
    r0 = np.clip(r - radius, 0, h)[:, None]
    r1 = np.clip(r + radius + 1, 0, h)[:, None]
    c0 = np.clip(col - radius, 0, w)[None, :]
    c1 = np.clip(col + radius + 1, 0, w)[None, :]
    return c[r1, c1] - c[r0, c1] - c[r1, c0] + c[r0, c0]


ESTIMATOR = register(Estimator(
    "spatial", "uses the neighbours: censoring, a pixelwise fit and edge-preserving TV", fit,
    pixelwise=False, several="spatial-surfaces", live=False, live_stand_in="ml", counts="whole"))
