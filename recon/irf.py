"""The instrument response measured from the data itself, when no pulse width or IRF is given.

Real single-photon detectors respond with a sharp peak and a long diffusion tail, not a Gaussian; a
Gaussian model calls the tail a surface or the background. So the response is measured from the
recording: reconstruct with the current model, align every pixel's detections on its estimated
return, pool them, subtract the background floor, and repeat with that measured shape.

Start: the pulse width from within-pixel pair differences (:func:`recon.model.estimate_pulse_rms_s`)
when pixels hold several detections, else (a point measurement: one pixel) the width of the pooled
histogram's leading edge. Each round (ROUNDS of them) runs the ml estimator on at most MAX_PIXELS
pixels (those with the most detections) and histograms the residuals ``t - tof`` on a grid of
``step`` raw units. The floor is the pooled level before the leading edge (background is flat in
time). Aligning a pixel on an estimate made from its own k detections pulls them towards it (the
mean of k has ``(1 - 1/k)`` of the spread left), so each pixel's residuals are widened by
``sqrt(k / (k - 1))`` with k its estimated signal count; pixels with fewer than 3 signal detections
are left out.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from spdepth.recon.errors import InputError
from spdepth.recon.model import (Binning, Irf, ReconSettings, default_binning, edge_core_rms,
                                 estimate_pulse_rms_s, pair_difference_histogram)
from spdepth.recon.photons import PhotonStore, evenly_spaced, rows_of
from spdepth.recon.given import reconstruct_given

ROUNDS = 3
MAX_PIXELS = 20_000
#: pixels' median detections from which they are aligned on their own estimates (fewer: a pixel's
#: estimate follows its own few detections, and the pooled shape comes out too narrow)
ALIGN_MIN_PHOTONS = 200
#: samples of the leading edge: the grid step is the core RMS over this (at least one raw unit)
STEPS_PER_RMS = 4.0
#: the response is cut where its smoothed level stays below this many floor standard errors
CUT_SIGMAS = 2.0
#: longest response kept, in core RMS widths (a fluorescence decay can fill the whole window)
MAX_SPAN_RMS = 400.0

NO_PEAK_HINT = "give --pulse-rms-ps PS (a Gaussian of that RMS) or --irf FILE (a measured response)"


@dataclass(frozen=True)
class IrfEstimate:
    """A response measured from the data and how it was found.

    irf:         the response (times relative to its centroid, counts), source "estimated".
    core_rms_s:  the width of the sharp part, as a Gaussian's RMS: the EMG's own Gaussian
                 ("emg-pairs"), or the leading edge's 10-90% rise read as a Gaussian's
                 (``recon.model.edge_core_rms``, "aligned"); with a long tail, far less than the
                 FWHM's Gaussian (the mannequin's: 62 ps against 132). The default bin width is a
                 ninth of it, so a long tail does not blur the leading edge.
    fwhm_s:      full width at half maximum.
    tail_share:  share of the response later than 3 core RMS after its peak.
    photons:     detections used; pixels: pixels used.
    method:      "aligned" (pooled on each pixel's estimate) or "emg-pairs" (fitted to differences).
    tau_s:       the EMG tail's mean delay (emg-pairs with a tail only).
    """

    irf: Irf
    core_rms_s: float
    fwhm_s: float
    tail_share: float
    photons: int
    pixels: int
    method: str = "aligned"
    tau_s: float | None = None

    def to_dict(self) -> dict:
        return {"method": self.method, "rms_s": self.irf.rms_s, "core_rms_s": self.core_rms_s,
                "fwhm_s": self.fwhm_s, "tail_share": self.tail_share, "tail_tau_s": self.tau_s,
                "photons": self.photons, "pixels": self.pixels}


def _edge_rms_units(times: np.ndarray, time_unit_s: float) -> float:
    """Core RMS (raw units) of the pooled histogram's main peak from its leading edge: the rise from
    the floor to the peak spans about 2.4 RMS for a Gaussian (10% to peak ~ 2.15 sigma).
    ``time_unit_s`` only words the error (the bin in ps, not in raw units)."""
    lo, hi = float(times.min()), float(times.max())
    if not hi > lo:
        raise InputError(f"cannot estimate the pulse shape: all detections at one time; {NO_PEAK_HINT}")
    nb = int(min(4096, max(64, (hi - lo) + 1)))
    hist, edges = np.histogram(times, bins=nb, range=(lo, hi + 1e-9 * max(1.0, abs(hi))))
    step = edges[1] - edges[0]
    smooth = np.convolve(hist, np.ones(3) / 3, mode="same")
    floor = float(np.median(smooth))
    pk = int(np.argmax(smooth))
    height = smooth[pk] - floor
    noise = math.sqrt(max(floor, 1.0))
    if not height > 5 * noise or not smooth[pk] > 3 * max(floor, 0.5):
        raise InputError(f"cannot estimate the pulse shape: the pooled arrival histogram holds no peak "
                         f"above its background ({smooth[pk]:.1f} vs a median of {floor:.1f} per "
                         f"{step * time_unit_s * 1e12:.3g} ps bin); {NO_PEAK_HINT}")
    left = pk
    while left > 0 and smooth[left - 1] > floor + 0.1 * height:
        left -= 1
    right = pk
    while right < nb - 1 and smooth[right + 1] > floor + 0.5 * height:
        right += 1
    rise = (pk - left + 1) * step / 2.15
    return float(max(rise, step / 2, 0.5))


def _initial_rms_units(store: PhotonStore) -> float:
    counts = np.diff(store.offsets)
    if np.sum(np.minimum(counts, 32) * (np.minimum(counts, 32) - 1)) >= 200:
        try:
            return estimate_pulse_rms_s(store.times, store.offsets, 1.0)
        except InputError:
            pass   # no usable pairs after all: fall back to the histogram edge below
    return _edge_rms_units(store.times, store.time_unit_s)


def _sample(store: PhotonStore, max_pixels: int) -> PhotonStore:
    """The store restricted to at most max_pixels of its pixels that hold a pair of detections,
    evenly spaced in raster order (1 x n): the scene's mix of signal and background. The busiest
    pixels were the most background under daylight (a 256 x 256 scan at SBR 0.05: a pair peak
    2.8 times its floor among them, 4.3 over the frame, so the frame was refused)."""
    counts = np.diff(store.offsets)
    if store.n_pixels <= max_pixels:
        return store
    pairs = np.flatnonzero(counts >= 2)
    keep = evenly_spaced(pairs, max_pixels)
    at, offsets = rows_of(store.offsets, keep)        # one gather (a list per pixel took 0.05 s)
    return PhotonStore(store.times[at], offsets, (1, keep.size), store.time_unit_s)


def _emg_pdf(x: np.ndarray, sigma: float, tau: float) -> np.ndarray:
    """Density of N(0, sigma^2) + Exp(mean tau) at x (log-space, no overflow far out)."""
    from scipy.special import log_ndtr

    z = x / sigma - sigma / tau
    return np.exp(np.minimum(sigma * sigma / (2 * tau * tau) - x / tau + log_ndtr(z), 700.0)) / tau


def emg_response(t: np.ndarray, sigma: float, share: float, tau: float) -> np.ndarray:
    """Detector response: a Gaussian of RMS sigma, of which ``share`` is delayed by an exponential
    diffusion tail of mean tau (all in the same units as t; unit area)."""
    g = np.exp(-0.5 * (t / sigma) ** 2) / (sigma * math.sqrt(2 * math.pi))
    return (1.0 - share) * g + (share * _emg_pdf(t, sigma, tau) if share > 0 else 0.0)


def _pair_model(d: np.ndarray, sigma: float, share: float, tau: float) -> np.ndarray:
    """Density of |t1 - t2| for two independent detections of :func:`emg_response` (d >= 0)."""
    s2 = math.sqrt(2.0) * sigma
    g = np.exp(-0.5 * (d / s2) ** 2) / (s2 * math.sqrt(2 * math.pi))
    mixed = share - share * share / 2        # one tail and one not, or both (a Laplace)
    return 2.0 * ((1 - share) ** 2 * g + mixed * (_emg_pdf(d, s2, tau) + _emg_pdf(-d, s2, tau)))


def _first_dip(h: np.ndarray, w: float, sigma0: float) -> float:
    """Where the pair histogram (bins of w) has its first clear dip before a later rise, in raw
    units (inf if none). A response's pair density falls monotonically to the floor; pixels seeing
    two surfaces add pairs at their separation, a bump the fit must not read as a tail."""
    k = max(1, int(round(sigma0 / w)))
    sm = np.convolve(h, np.ones(k) / k, mode="same")
    start = int(np.argmax(sm[:max(2, 3 * k)]))
    run_min = np.minimum.accumulate(sm[start:])
    rise = sm[start:] - run_min
    # a rise of 5 standard errors (of a k-bin mean) above the lowest level reached so far
    sig = 5.0 * np.sqrt(np.maximum(run_min, 1.0) / k)
    hit = np.flatnonzero(rise > sig)
    if hit.size == 0:
        return np.inf
    j = start + int(hit[0])
    dip = start + int(np.argmin(sm[start:j + 1]))
    return float(max(dip, 3 * k) * w)


def _return_background_floor(times: np.ndarray, c: np.ndarray, w: float) -> np.ndarray:
    """Shape over |dt| = c of the pairs of a return with a background detection, from the pooled
    detection times: background is flat over the detections' span [t0, t0 + W), so a return at t
    pairs with it at |dt| = d with density proportional to [t - t0 >= d] + [t0 + W - t > d]. The
    returns' times are the pooled histogram above its median (the background level). Flat until d
    reaches the returns' distance from the window's edges, then falling: at low SBR these pairs
    outnumber the return-return ones, and a fit without them reads the fall as a diffusion tail."""
    t = np.asarray(times, dtype=np.float64)
    t0, span = float(t.min()), float(t.max() - t.min()) + 1.0
    nb = max(1, int(math.ceil(span / w)))
    pooled = np.bincount(np.minimum(((t - t0) / w).astype(np.int64), nb - 1), minlength=nb).astype(np.float64)
    ret = np.maximum(pooled - np.median(pooled), 0.0)
    if not ret.sum() > 0:
        return np.zeros_like(c)
    centre = (np.arange(nb) + 0.5) * w
    # sum over the returns' bins of [centre >= d] + [span - centre > d], for each d in c (the
    # centres ascend: after[k] is the returns' sum from bin k on)
    after = np.concatenate([np.cumsum(ret[::-1])[::-1], [0.0]])
    from_start = after[np.searchsorted(centre, c, side="left")]
    before_end = after[np.searchsorted(centre, span - c, side="left")]
    g = from_start + (ret.sum() - before_end)
    return g / g[0]


def fit_emg_pairs(store: PhotonStore) -> tuple[float, float, float, int]:
    """(sigma, share, tau) in raw units of the detector response, fitted to the histogram of
    within-pixel detection-time differences (scene depth cancels in them), and the pairs used.

    The differences of two signal detections follow :func:`_pair_model`; pairs with a background
    detection add a floor, linear in |dt| over the fitted range. Least squares weighted by the
    Poisson variance, over |dt| < 60 initial widths. Raises InputError without a clear peak."""
    from scipy.optimize import least_squares

    hist, step = pair_difference_histogram(store.times, store.offsets)
    # initial width from the peak's half width at half height above the far floor
    smooth = np.convolve(hist, np.ones(5) / 5, mode="same")
    floor0 = float(np.median(smooth[hist.size // 4:]))
    peak = float(smooth[:8].max())
    if not peak > 3 * max(floor0, 1.0):
        raise InputError(f"cannot estimate the pulse shape: no peak of coincident detections in the "
                         f"data (pairs of detections {peak:.0f} at 0 vs a floor of {floor0:.0f}); "
                         f"{NO_PEAK_HINT}")
    # (searched from the peak on: the smoothing's zero padding lowers the first bins)
    top = int(np.argmax(smooth[:8]))
    half = top + np.flatnonzero(smooth[top:] < floor0 + 0.5 * (peak - floor0))
    sigma0 = max((half[0] + 0.5) * step if half.size else hist.size * step / 8, step) / 1.1774 / math.sqrt(2)
    # rebin to about a quarter of the width
    f = max(1, int(sigma0 / 4 / step))
    n = hist.size // f
    h = hist[:n * f].reshape(n, f).sum(axis=1).astype(np.float64)
    w = step * f
    c = (np.arange(n) + 0.5) * w
    use = c < min(60 * sigma0, _first_dip(h, w, sigma0))
    c, h = c[use], h[use]
    if c.size < 12:
        raise InputError(f"cannot estimate the pulse shape: the detections span too little time; {NO_PEAK_HINT}")
    edge = _return_background_floor(store.times, c, w)
    far = h[c > 0.6 * c[-1]]
    a0 = float(np.median(far)) if far.size else 0.0
    amp0 = max(float(np.sum(h - a0)), 1.0)

    # a tail is told from the floor's slope only if it decays within the fitted range: an
    # exponential of mean beyond a quarter of it is nearly straight there, and the fit trades it
    # for the floor (simulated daylight, SBR 0.05: a 73% "tail" of mean 44 ns over a 44 ns range,
    # which put every depth 4.4 m late)
    tau_hi = min(60 * sigma0, c[-1] / 4)

    def unpack(p, tail):
        # p: log sigma, amplitude, floor, floor slope, return-background pairs[, logit share, log tau]
        return math.exp(p[0]), (1 / (1 + math.exp(-p[5])) if tail else 0.0), (math.exp(p[6]) if tail else 1.0)

    def fit(tail):
        def resid(p):
            sig, sh, tau = unpack(p, tail)
            mu = p[1] * w * _pair_model(c, sig, sh, tau) + p[2] + p[3] * c / c[-1] + p[4] * edge
            return (h - mu) / np.sqrt(np.maximum(mu, 1.0))

        best = None
        for tau0 in ((1.0, 3.0, 10.0) if tail else (None,)):
            p0 = [math.log(sigma0), amp0, a0, 0.0, 0.0]
            lo = [math.log(sigma0 / 10), 0.0, 0.0, -np.inf, 0.0]
            hi = [math.log(sigma0 * 10), np.inf, np.inf, np.inf, np.inf]
            if tail:
                p0 += [-1.0, math.log(min(tau0 * sigma0, 0.5 * tau_hi))]
                lo += [-12.0, math.log(min(0.2 * sigma0, 0.1 * tau_hi))]
                hi += [12.0, math.log(tau_hi)]
            p0 = np.clip(p0, np.add(lo, 1e-9), np.subtract(hi, 1e-9))
            try:
                f = least_squares(resid, p0, bounds=(lo, hi), method="trf", x_scale="jac", max_nfev=400)
            except (ValueError, FloatingPointError):
                continue
            if best is None or f.cost < best.cost:
                best = f
        return best

    best = fit(tail=True)
    if best is not None:
        sig, sh, tau = unpack(best.x, True)
        # a sliver of tail, or one pressed against the longest delay allowed, is the floor's
        # slope, not a response: the shape is fitted again without one
        if sh < 1e-3 or (sh < 0.05 and tau > 0.5 * c[-1]) or tau > 0.95 * tau_hi:
            best = fit(tail=False)
    if best is None or not best.x[1] > 0:
        raise InputError(f"cannot estimate the pulse shape: no peak of coincident detections; {NO_PEAK_HINT}")
    tail = best.x.size > 5
    sig, sh, tau = unpack(best.x, tail)
    return sig, sh, tau, int(hist.sum())


def warm_up() -> None:
    """Load (on a cold numba cache: compile) what measuring the pulse from the data runs first in
    a new process: the pair-difference kernels (:mod:`recon.pair_kernels`), on two made-up pixels,
    and scipy's least squares, whose import took 0.15-0.25 s of a fresh 512x512 recon's pulse
    estimate (:func:`recon.estimate.warm_up` runs this on a thread while the file is read)."""
    from scipy.optimize import least_squares  # noqa: F401 - imported here so the fit finds it loaded

    pair_difference_histogram(np.array([0.0, 1.0, 5.0, 2.0]), np.array([0, 2, 4]))


def estimate_irf(store: PhotonStore, binning: Binning | None = None,
                 max_photons: int | None = None) -> IrfEstimate:
    """Measure the instrument response from ``store`` (see the module docstring).

    binning: the window and bins of the reconstruction, when given (detections outside the window
             are ignored); otherwise derived from the data each round.
    Raises InputError naming the options to pass when the data hold no usable peak.
    """
    try:
        return _estimate_irf(store, binning, max_photons)
    except InputError as exc:
        if NO_PEAK_HINT in str(exc):
            raise
        # the pair-difference helpers speak of the library's settings; name the command's options
        raise InputError(f"{str(exc).split('; give')[0]}; {NO_PEAK_HINT}") from None


def _estimate_irf(store: PhotonStore, binning: Binning | None, max_photons: int | None) -> IrfEstimate:
    if store.n_photons == 0:
        raise InputError(f"cannot estimate the pulse shape: no detections; {NO_PEAK_HINT}")
    if binning is not None or max_photons is not None:
        lo = binning.window_start if binning is not None else -np.inf
        hi = binning.window_stop if binning is not None else np.inf
        store = store.first_in_window(lo, hi, max_photons)
        if store.n_photons == 0:
            raise InputError(f"cannot estimate the pulse shape: no detections in the window; {NO_PEAK_HINT}")
    sample = _sample(store, MAX_PIXELS)
    counts = np.diff(sample.offsets)
    if np.median(counts[counts > 0]) < ALIGN_MIN_PHOTONS:
        return _from_pairs(sample)
    return _aligned(sample, binning)


def _from_pairs(sample: PhotonStore) -> IrfEstimate:
    """Few detections per pixel: an EMG fitted to the within-pixel differences, sampled."""
    unit_s = sample.time_unit_s
    try:
        sig, share, tau, pairs = fit_emg_pairs(sample)
    except InputError:
        raise
    step = max(sig / STEPS_PER_RMS, 1e-3)
    reach = 6 * sig + (tau * math.log(1e4) if share > 0 else 0.0)
    t = np.arange(-6 * sig, reach + step, step)
    shape = emg_response(t, sig, share, tau)
    irf = Irf(tuple(t * unit_s), tuple(shape), source="estimated from the data (EMG fitted to "
              "within-pixel time differences)")
    fwhm_u = _fwhm(shape, step)
    return IrfEstimate(irf=irf, core_rms_s=sig * unit_s, fwhm_s=fwhm_u * unit_s,
                       tail_share=float(share), photons=int(sample.n_photons), pixels=int(sample.n_pixels),
                       method="emg-pairs", tau_s=float(tau * unit_s) if share > 0 else None)


def _aligned(sample: PhotonStore, binning: Binning | None) -> IrfEstimate:
    """Many detections per pixel: pool them aligned on each pixel's estimate, iterate. Each round's
    pilot is a pixelwise ml reconstruction with the current pulse given (no estimate needed)."""
    unit_s = sample.time_unit_s
    rms_u = _initial_rms_units(sample)
    irf: Irf | None = None
    core_u = rms_u
    integral = bool(np.all(np.mod(sample.times, 1) == 0))
    result = None
    for _ in range(ROUNDS):
        # whole raw units on integer data (a fractional step would alias into a comb)
        step = max(1.0, round(core_u / STEPS_PER_RMS)) if integral else core_u / STEPS_PER_RMS
        b = binning if binning is not None else default_binning(sample.times, unit_s, core_u * unit_s)
        if irf is None:
            settings = ReconSettings(method="ml", binning=b, pulse_rms_s=rms_u * unit_s)
        else:
            settings = ReconSettings(method="ml", binning=b, irf=irf)
        maps = reconstruct_given(sample, settings)
        # tof is the response's centroid, which a long tail puts far after its peak: pool around
        # the peak, so the floor window before it stays clear of the edge
        peak_u = 0.0
        if irf is not None:
            t, c = irf.arrays()
            peak_u = float(t[np.argmax(c)] - np.sum(t * c) / c.sum()) / unit_s
        result = _pool(sample, maps, b, step, core_u, peak_u)
        irf = result.irf
        core_u = result.core_rms_s / unit_s
    assert result is not None
    return result


def _fwhm(shape: np.ndarray, step: float) -> float:
    above = np.flatnonzero(shape >= 0.5 * shape.max())
    return float((above[-1] - above[0] + 1) * step)


def _pool(store: PhotonStore, maps, b: Binning, step: float, core_u: float, peak_u: float) -> IrfEstimate:
    """One round: residuals of the aligned pixels -> floor-subtracted response."""
    unit_s = store.time_unit_s
    tof_u = np.ravel(maps.tof_s) / unit_s
    k = np.ravel(maps.signal)
    counts = np.diff(store.offsets)
    ok = np.isfinite(tof_u) & (k >= 3)
    if not np.any(ok):
        raise InputError(f"cannot estimate the pulse shape: no pixel holds a clear return; {NO_PEAK_HINT}")
    pix = np.repeat(np.arange(store.n_pixels), counts)
    sel = ok[pix] & (store.times >= b.window_start) & (store.times < b.window_stop)
    widen = np.sqrt(k / np.maximum(k - 1.0, 1e-9))
    r = (store.times[sel] - tof_u[pix[sel]] - peak_u) * widen[pix[sel]]
    # the grid: before the edge for the floor, after it as far as the window allows
    left_u = 25.0 * core_u
    right_u = min(MAX_SPAN_RMS * core_u, float(b.window_stop - b.window_start))
    n_left = int(math.ceil(left_u / step))
    n_right = int(math.ceil(right_u / step))
    edges = (np.arange(-n_left, n_right + 1) - 0.5) * step
    hist = np.histogram(r, bins=edges)[0].astype(np.float64)
    centres = 0.5 * (edges[1:] + edges[:-1])
    # the floor: the level well before the leading edge (background is flat in time)
    pre = (centres < -8.0 * core_u) & (centres >= -left_u)
    floor = float(hist[pre].mean()) if np.any(pre) else 0.0
    net = hist - floor
    pk = int(np.argmax(net))
    if not net[pk] > 5.0 * math.sqrt(max(floor, 1.0)):
        raise InputError(f"cannot estimate the pulse shape: the aligned detections hold no peak above "
                         f"their background; {NO_PEAK_HINT}")
    # the response ends where its running mean (a window growing with the distance from the peak,
    # so the tail's noise averages out) stays below CUT_SIGMAS floor standard errors
    csum = np.concatenate(([0.0], np.cumsum(net)))
    end = net.size - 1
    for j in range(pk + 1, net.size):
        half = max(1, (j - pk) // 4)
        a, z = max(pk + 1, j - half), min(net.size, j + half + 1)
        level = (csum[z] - csum[a]) / (z - a)
        if level < CUT_SIGMAS * math.sqrt(max(floor, 1.0) / (z - a)):
            end = j
            break
    start = pk
    while start > 0 and net[start - 1] > CUT_SIGMAS * math.sqrt(max(floor, 1.0)):
        start -= 1
    start = max(0, start - 1)
    shape = np.clip(net[start:end + 1], 0.0, None)
    out = smooth_tail(shape, pk - start)
    t_u = centres[start:end + 1]
    irf = Irf(tuple(t_u * unit_s), tuple(out), source="estimated from the data")
    fwhm_u = _fwhm(out, step)
    core = max(edge_core_rms(out, step), 0.5)
    tail = float(out[t_u > t_u[int(np.argmax(out))] + 3 * core].sum() / out.sum())
    return IrfEstimate(irf=irf, core_rms_s=core * unit_s, fwhm_s=fwhm_u * unit_s, tail_share=tail,
                       photons=int(r.size), pixels=int(ok.sum()))


def smooth_tail(shape: np.ndarray, peak: int) -> np.ndarray:
    """A measured response with its tail (not its edge) smoothed by a window growing with the
    distance from the ``peak`` index, so the sparse far tail is not noise."""
    out = shape.copy()
    cs = np.concatenate(([0.0], np.cumsum(shape)))
    for j in range(peak + 4, shape.size):
        half = (j - peak) // 8
        if half < 1:
            continue
        a, z = max(peak + 1, j - half), min(shape.size, j + half + 1)
        out[j] = (cs[z] - cs[a]) / (z - a)
    return out
