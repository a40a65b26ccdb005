"""Several surfaces per pixel: the pixelwise K-surface estimator, its response and its test.

``reflectors`` K > 1 or "auto" (the pixelwise methods): every pixel is fitted by a greedy Poisson
pursuit in the union of K shifted copies of the response plus a flat background
(:mod:`recon.estimators.surfaces_kernels`): a surface is added where it raises the Poisson log-likelihood most,
with its amplitude profiled out, then the amplitudes and background are refitted and the shifts
re-refined. K fixed keeps up to K surfaces that each lower Akaike's criterion (``LLR_MIN``), the
doubtful ones flagged weak; "auto" keeps adding surfaces (up to ``max_reflectors``) while the
likelihood-ratio test below rejects "no further surface" at the false-alarm rate asked for.

**The test** (auto): the statistic of a candidate surface is ``Lambda = 2 (log L1 - log L0)``, the
log-likelihood ratio with its shift searched over the window and its amplitude (>= 0) profiled. At
one fixed shift it is distributed under "no surface there" as ``0.5 chi2_0 + 0.5 chi2_1`` (an
amplitude on the boundary, so ``z = sqrt(Lambda)`` is a standard normal's positive part). Searched
over the window, ``z`` is a smooth random field in the shift whose correlation is the matched
filter's, ``exp(-d^2 / (4 sigma^2))`` for a response of RMS ``sigma`` (from its FWHM); by Rice's
formula for its upcrossings (the look-elsewhere effect of Gross and Vitells, Eur. Phys. J. C 70,
2010), the chance that it passes ``z`` somewhere in a window of ``L`` bins is about
``P(N > z) + L / (2 pi sqrt(2) sigma) exp(-z^2 / 2)``. The threshold makes that chance
``false_alarm`` (per pixel and per added surface; default 1e-3). Counting ``window / FWHM``
independent shifts instead made background alone pass 1.7-2.8 times as often as stated
(background-only frames: recon.detect's own test and its neighbours' support at 1.7-2.6e-3 for
1e-3; now 0.7-0.8e-3 at 10 and 60 detections a pixel).
A pixel whose first surface fails the test has none (flag NO_SIGNAL), not a background guess.

**The response** (when the settings give none): a single-surface response measured from data with
two surfaces per pixel would be blurred by the second one, and a response that misses the detector's
diffusion tail or the afterpulse bump turns them into surfaces. So the model is measured from the
data in two rounds: fit the surfaces with the pulse measured by :mod:`recon.irf` (their number
decided by the test, up to max_reflectors whatever K was asked, so the response does not depend on
K), then pool every detection on the surface before it (up to the next surface's leading edge,
counting for each lag how many surfaces were observed there, so a second surface never enters the
first one's tail; see :func:`pooled_response` for the surfaces that may be the first fit's
phantoms), subtract the flat floor and refit with that shape; the shape keeps the tail and any later
bump as part of every return.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Callable

import numpy as np

from spdepth.recon.counts import CountStore
from spdepth.recon.detect import auto_threshold_nats, fwhm_bins, surface_spreads
from spdepth.recon.estimators import surfaces_kernels as MK
from spdepth.recon.errors import InputError
from spdepth.recon.irf import smooth_tail
from spdepth.recon.kernels import Photons
from spdepth.recon.maps import C_M_PER_S, DepthMaps, PixelFlag
from spdepth.recon.model import Binning, Irf, PulseKernel, ReconSettings, build_kernel, edge_core_rms
from spdepth.recon.photons import PhotonStore
from spdepth.recon.pixelwise import (CHUNK_PIXELS, detections_per_pixel, honest_var, over_threads, settings_record,
                                     store_pairs)

#: K fixed: a surface is kept when it raises the Poisson log-likelihood by more than this (nats):
#: Akaike's criterion for its two parameters (shift, amplitude). The user gave the number, so the bar
#: is the lowest standard one: a real surface of 2-3 detections gains 2-5 nats (with 3, the real
#: two-surface file had one surface on 1.8% of its pixels, with 2 on 0.7%), while one cluster of 15
#: detections without background is split in two on 1.7% of draws (31% with no bar at all). The weak
#: flag says which kept surfaces background alone could have made: those the test of auto would not
#: keep at the user's false-alarm rate (``ReconSettings.false_alarm``). (At 1e-6 instead, the
#: surfaces of 7 clean detections each on the simulated two-layer pane were weak on 70% of pixels.)
LLR_MIN = 2.0
#: surfaces closer than this many FWHM of the response are one.
SEP_FWHM = 1.0
#: one candidate shift per this many core RMS widths of detections (the pattern search that refines
#: the best one starts at half a core RMS, so it reaches every shift between candidates).
CAND_CORE = 1.0
#: spatial: a pixel's own surface counts as strong (needs no support from its neighbours) when it
#: passes the test of auto at this false-alarm rate.
STRONG_FALSE_ALARM = 1e-6
#: response pooling: lags before the leading edge used for the floor, in core RMS widths.
FLOOR_CORE = (8.0, 25.0)
#: response pooling: longest lag kept after a surface, in RMS widths of the first estimate of the
#: response (tail included: a longer tail reaches farther); an afterpulse bump ~4 RMS later is kept.
REACH_RMS = 10.0
#: response pooling: a later surface within reach of an earlier one and below this share of its signal
#: may be the earlier one's tail or bump, which the first fit's response lacks (pooled_response).
ABSORB_SHARE = 0.25
#: response pooling: it ends where its running mean (a window growing with the lag) falls below this
#: many standard errors of the floor (as recon.irf does for one surface).
CUT_SIGMAS = 2.0
#: response pooling: surfaces need this many expected signal detections to be pooled on.
POOL_MIN_SIGNAL = 5.0


def kmax_and_gain(settings: ReconSettings, b: Binning, width_bins: float) -> tuple[int, float, str]:
    """(surfaces at most, gain each needs in nats, how the number is decided)."""
    if settings.reflectors == "auto":
        thr = auto_threshold_nats(settings.false_alarm, b.n_bins, width_bins)
        return int(settings.max_reflectors), thr, (
            f"likelihood-ratio test, false-alarm rate {settings.false_alarm:g} per pixel and surface "
            f"(2 dlogL > {2 * thr:.2f})")
    return int(settings.reflectors), LLR_MIN, (f"fixed K={int(settings.reflectors)} (each surface that raises the "
                                               f"likelihood by more than {LLR_MIN:g} nats; weak ones flagged)")


def _step0(core_bins: float) -> int:
    """First step of the shift pattern search: the largest power of 2 up to half the core RMS."""
    step0 = 1
    while step0 * 2 <= max(1.0, core_bins / 2):
        step0 *= 2
    return step0


def fit_surfaces(store: PhotonStore, settings: ReconSettings, b: Binning, kern: PulseKernel, core_s: float,
                 progress: Callable[[int, int], None] | None = None):
    """Run the K-surface kernel on every pixel (a photon list's detections, or a count store's (bin,
    count) pairs). Returns (shift bins (P, K), amp (P, K), bg (P,), var (P, K), gain (P, K), n_used
    (P,), kmax, gain_min, rule)."""
    bins, weights, offsets = store_pairs(store, b, settings.max_photons)
    npix = store.n_pixels
    kmax, gain_min, rule = kmax_and_gain(settings, b, fwhm_bins(kern.g))
    tabs = surface_tables(b, kern, core_s)
    out = surface_outputs(npix, kmax)
    counts = np.diff(offsets)

    def fit(p0: int, p1: int) -> None:
        o = offsets[p0:p1 + 1]
        maxn = int(counts[p0:p1].max()) if p1 > p0 else 0
        ph = Photons(bins[o[0]:o[-1]], o - o[0], weights[o[0]:o[-1]] if weights.size else weights)
        MK.multi_return_kernel(ph, tabs, kmax, float(gain_min), maxn,
                               MK.SurfOut(*(a[p0:p1] for a in out)))

    over_threads(fit, npix, CHUNK_PIXELS, progress)
    return out.shift, out.amp, out.bg, out.var, out.gain, out.n, kmax, gain_min, rule


def surface_tables(b: Binning, kern: PulseKernel, core_s: float):
    """The K-surface kernels' tables (``surfaces_kernels.SurfTables``) for the pulse ``kern`` on ``b``
    whose sharp part has RMS ``core_s``: surfaces SEP_FWHM apart, a candidate every CAND_CORE core
    RMS, the pattern search's first step."""
    core_bins = core_s / b.bin_width_s
    sep = max(1, int(round(SEP_FWHM * fwhm_bins(kern.g))))
    cand = max(1, int(round(CAND_CORE * core_bins)))
    return MK.surf_tables(b.n_bins, kern.g, kern.off, kern.colsum, kern.dg, sep, cand, _step0(core_bins))


def surface_outputs(npix: int, kmax: int):
    """``surfaces_kernels.SurfOut`` of npix pixels and kmax surfaces, NaN / 0 past the surfaces."""
    return MK.SurfOut(np.full((npix, kmax), np.nan), np.zeros((npix, kmax)), np.zeros(npix),
                      np.full((npix, kmax), np.nan), np.zeros((npix, kmax)), np.zeros(npix, np.int64))


def pooled_response(store: PhotonStore, b: Binning, tof_units: np.ndarray, signal: np.ndarray,
                    core_u: float, reach_u: float) -> Irf:
    """The response pooled on each pixel's surfaces (module docstring). tof_units: (P, K) surface
    times in raw units, sorted, NaN past the last; signal: (P, K) expected signal detections;
    core_u: the sharp part's RMS (the lag step and the leading edge); reach_u: how far after a
    surface its response may still hold another (raw units, from the first estimate).

    A later surface smaller than ABSORB_SHARE of an earlier one within reach_u may be that one's
    tail or bump fitted as a surface (the first fit's response lacks them): it neither ends the
    earlier one's span nor is pooled on. A surface's span starts after the previous surface's
    leading part and ends before the next one's leading edge (FLOOR_CORE[0] core RMS from each)."""
    step = max(1.0, round(core_u / 4.0)) if np.all(np.mod(store.times, 1) == 0) else core_u / 4.0
    left = FLOOR_CORE[1] * core_u
    # lags pooled: up to half the window (a later surface's floor region ends a span sooner); the
    # response ends where the pooled rate stops being significant (below), not at a fixed lag that
    # would cut an afterpulse bump of a short pulse (the mannequin's, ~15 core RMS later) in half
    right = 0.5 * float(b.window_stop - b.window_start)
    nl, nr_ = int(math.ceil(left / step)), int(math.ceil(right / step))
    edges = (np.arange(-nl, nr_ + 1) - 0.5) * step
    nb = edges.size - 1
    hist = np.zeros(nb)
    expo = np.zeros(nb + 1)
    counts = np.diff(store.offsets)
    pix = np.repeat(np.arange(store.n_pixels), counts)
    t = store.times
    # a count store's entries are (time, count) pairs: each adds its count to the pooled histogram
    weights = store.counts if isinstance(store, CountStore) else None
    inwin = (t >= b.window_start) & (t < b.window_stop)
    kk = tof_units.shape[1]
    has = np.isfinite(tof_units)
    sig = np.where(has, signal, 0.0)
    # absorbed: within reach of an earlier, not absorbed surface and below ABSORB_SHARE of it
    major = has.copy()
    for r in range(1, kk):
        for q in range(r):
            near = major[:, q] & (tof_units[:, r] - tof_units[:, q] < reach_u)
            major[:, r] &= ~(near & (sig[:, r] < ABSORB_SHARE * sig[:, q]))
    for r in range(kk):
        tr = tof_units[:, r]
        nxt = np.full(tr.shape, float(b.window_stop))
        for s in range(kk - 1, r, -1):
            nxt = np.where(major[:, s], tof_units[:, s] - FLOOR_CORE[0] * core_u, nxt)
        prv = np.full(tr.shape, float(b.window_start))
        for q in range(r):
            prv = np.where(major[:, q], tof_units[:, q] + FLOOR_CORE[0] * core_u, prv)
        lo = np.maximum(tr - left, prv)
        hi = np.minimum(np.minimum(nxt, tr + right), b.window_stop)
        use = major[:, r] & (sig[:, r] >= POOL_MIN_SIGNAL) & (hi > lo)
        sel = inwin & use[pix] & (t >= lo[pix]) & (t < hi[pix])
        res = t[sel] - tr[pix[sel]]
        hist += np.histogram(res, bins=edges, weights=None if weights is None else weights[sel])[0]
        # exposure per lag bin: surfaces whose observed span covers the bin
        a = np.clip(np.searchsorted(edges, (lo - tr)[use]), 0, nb)
        z = np.clip(np.searchsorted(edges, (hi - tr)[use]), 0, nb)
        np.add.at(expo, a, 1.0)
        np.add.at(expo, z, -1.0)
    ex = np.cumsum(expo)[:nb]
    centres = 0.5 * (edges[1:] + edges[:-1])
    rate = np.where(ex > 0, hist / np.maximum(ex, 1.0), 0.0)
    pre = (centres < -FLOOR_CORE[0] * core_u) & (ex > 0)
    floor = float(np.sum(hist[pre]) / np.sum(ex[pre])) if np.any(pre) else 0.0
    net = rate - floor
    pk = int(np.argmax(net))
    if not net[pk] > 0:
        raise InputError("cannot measure the response on the surfaces: no peak above the floor")
    # standard error of the rate per lag bin; the response ends where it stays below 2 of them
    se = np.sqrt(np.maximum(floor, 1e-12) / np.maximum(ex, 1.0))
    csum = np.concatenate(([0.0], np.cumsum(net)))
    csq = np.concatenate(([0.0], np.cumsum(se * se)))
    end = nb - 1
    for j in range(pk + 1, nb):
        half = max(1, (j - pk) // 4)
        a, z = max(pk + 1, j - half), min(nb, j + half + 1)
        if (csum[z] - csum[a]) / (z - a) < CUT_SIGMAS * math.sqrt(csq[z] - csq[a]) / (z - a):
            end = j
            break
    start = pk
    while start > 0 and net[start - 1] > 2.0 * se[start - 1]:
        start -= 1
    start = max(0, start - 1)
    shape = np.clip(net[start:end + 1], 0.0, None)
    out = smooth_tail(shape, pk - start)
    unit_s = store.time_unit_s
    return Irf(tuple(centres[start:end + 1] * unit_s), tuple(out),
               source="estimated from the data (pooled on each pixel's surfaces)")


def _measured_model(store: PhotonStore, settings: ReconSettings, b: Binning, kern: PulseKernel, notes: dict):
    """Re-measure the response on the surfaces of a first fit (module docstring): (kern, core_s)
    and the notes updated."""
    core_s = float(notes["pulse_core_rms_s"])
    # the first fit decides its surfaces by the test (up to max_reflectors, or K if more), whatever K
    # was asked: the response is the instrument's, the same for every K, and a third surface a fixed
    # K=2 leaves out would otherwise enter another's tail
    first = dataclasses.replace(settings, reflectors="auto", max_reflectors=max(
        settings.max_reflectors, settings.reflectors if settings.reflectors != "auto" else 1))
    shift, amp, *_ = fit_surfaces(store, first, b, kern, core_s)
    has = np.isfinite(shift)
    tof_u = np.where(has, b.shift_to_time_s(np.nan_to_num(shift)), np.nan) / store.time_unit_s
    sig = np.where(has, amp * kern.colsum[np.clip(np.nan_to_num(shift).astype(np.int64), 0, b.n_bins - 1)], 0.0)
    irf = pooled_response(store, b, tof_u, sig, core_s / store.time_unit_s,
                          REACH_RMS * kern.rms_bins * b.bin_width)
    kern = build_kernel(b, irf=irf)
    t, c = irf.arrays()
    core_s = max(edge_core_rms(c, float(t[1] - t[0])), 0.5 * float(t[1] - t[0]))
    notes["irf"] = dict(irf.to_dict(), rms_s=irf.rms_s)
    notes["pulse_rms_s"] = float(irf.rms_s)
    notes["pulse_core_rms_s"] = float(core_s)
    notes["pulse_source"] = "estimated, then measured on the surfaces"
    return kern, core_s


def _images(a: np.ndarray, shape) -> np.ndarray:
    """Per-pixel surfaces' values (pixels x K) as K images of ``shape`` (the maps' layout)."""
    return np.ascontiguousarray(a.T).reshape(a.shape[1], *shape)


def _times_and_sigmas(shift, var, b, kern) -> tuple[np.ndarray, np.ndarray]:
    """(times of flight, uncertainties; s, NaN without a surface) of the surfaces' shifts and shift
    variances (bins, bins^2), as the maps report them (:func:`recon.pixelwise.honest_var`)."""
    has = np.isfinite(shift)
    tof_s = np.where(has, b.shift_to_time_s(np.nan_to_num(shift)), np.nan)
    return tof_s, np.sqrt(honest_var(var, has, kern.rms_bins, b.n_bins, 1.0)) * b.bin_width_s


def _maps(store, settings, b, kern, notes, shift, amp, bg, var, gain, n_used) -> DepthMaps:
    h, w = store.shape
    npix = h * w
    has = np.isfinite(shift)
    j = np.clip(np.nan_to_num(shift).astype(np.int64), 0, b.n_bins - 1)
    signal = np.where(has, amp * kern.colsum[j], 0.0)
    tof_s, unc_s = _times_and_sigmas(shift, var, b, kern)
    # weak: a surface the test of auto would not keep at the user's false-alarm rate
    weak_thr = auto_threshold_nats(settings.false_alarm, b.n_bins, fwhm_bins(kern.g))
    weak = has & (gain <= weak_thr)
    surfaces = has.sum(axis=1)
    flags = np.full(npix, PixelFlag.OK, np.uint8)
    flags[surfaces == 0] = PixelFlag.NO_SIGNAL
    flags[n_used == 0] = PixelFlag.NO_PHOTONS
    notes["weak_below_nats"] = float(weak_thr)
    rec = settings_record(settings, notes, b, kern)
    tof_img = _images(tof_s, (h, w))
    return DepthMaps(tof_s=tof_img, depth_m=C_M_PER_S * tof_img / 2.0, background=bg.reshape(h, w),
                     signal=_images(signal, (h, w)), photons=n_used.reshape(h, w),
                     iterations=np.ones((h, w), np.int32), uncertainty_s=_images(unc_s, (h, w)),
                     flags=flags.reshape(h, w), settings=rec, surfaces=surfaces.reshape(h, w).astype(np.int16),
                     weak=_images(weak, (h, w)))


def reconstruct_multi(store: PhotonStore, settings: ReconSettings, b: Binning, kern: PulseKernel, notes: dict,
                      progress: Callable[[int, int], None] | None = None) -> DepthMaps:
    """:data:`recon.estimators.Fit` of the K-surface fit: K surfaces per pixel (``settings.reflectors``
    > 1 or "auto"), on the resolved binning ``b`` and pulse ``kern``; when the pulse was estimated
    (``notes["pulse_source"]``), the response is re-measured on the surfaces first (module
    docstring)."""
    notes = dict(notes)
    core_s = float(notes["pulse_core_rms_s"])
    if notes.get("pulse_source") == "estimated":
        kern, core_s = _measured_model(store, settings, b, kern, notes)
    shift, amp, bg, var, gain, n_used, kmax, gain_min, rule = fit_surfaces(store, settings, b, kern, core_s, progress)
    notes["surfaces_rule"] = rule
    notes["surface_gain_min_nats"] = float(gain_min)
    notes["kernel_k_surfaces"] = "greedy Poisson pursuit (recon.estimators.surfaces)"
    return _maps(store, settings, b, kern, notes, shift, amp, bg, var, gain, n_used)


#: spatial, several surfaces: neighbourhood radius (pixels) of censoring, proposals and smoothing.
SPATIAL_RADIUS = 1
#: spatial, several surfaces: "the same surface" in a neighbour: within this many response FWHM.
SPATIAL_TAU_FWHM = 1.0
#: spatial: pixels fitted per call of the neighbourhood kernel, between progress reports.
SPATIAL_SLICE = 4096


def _own_spreads(bins, weights, offsets, counts, shape, settings, b, kern, shift, sig, var):
    """Each surface's shift variance (npix x K, bins^2) before the smoothing: its Fisher variance
    ``var`` widened by the sandwich variance and the bootstrap's spread of its own part of the
    window, as recon.detect widens a pixelwise fit's (:func:`recon.detect.surface_spreads`), so that
    the smoothing averages the noise each surface has rather than what its Fisher variance says.
    The Fisher information of a sampled response read its sharp steps: the simulated bust at
    --reflectors 2, 8 a pixel, had 1.8 mm sigmas where the halves lay 2 cm apart; and averaging
    Fisher variances alone gave two_layer_top.mat's halves 94.8 / 55.3% (pane) and 93.4 / 53.5%
    (wall) within 3 / 1 sigma."""
    tof, unc = _times_and_sigmas(shift, var, b, kern)
    wide = surface_spreads(bins, weights, offsets, kern, b, _images(tof, shape), _images(unc, shape),
                           _images(sig, shape), np.asarray(counts, np.float64), settings.false_alarm)
    # less the integer grid's quantization, which honest_var adds once more after the smoothing
    out = (wide.reshape(shift.shape[1], -1).T / b.bin_width_s) ** 2 - 1.0 / 12.0
    return np.where(np.isfinite(shift), np.fmax(out, var), var)


def reconstruct_multi_spatial(store: PhotonStore, settings: ReconSettings, b: Binning, kern: PulseKernel,
                              notes: dict, progress: Callable[[int, int], None] | None = None) -> DepthMaps:
    """:data:`recon.estimators.Fit` of ``method="spatial"`` with several surfaces: every surface
    supported by its neighbours.

    1. The pixelwise K-surface fit (:func:`reconstruct_multi`'s, response re-measured when the pulse
       was estimated); its strong surfaces (passing the test at a false-alarm rate of 1e-6 on their
       own) stand.
    2. Per pixel, the detections of its 3 x 3 neighbourhood are pooled and fitted the same way (up to
       K + 1 surfaces: an edge inside the neighbourhood shows both sides), each surface passing the
       likelihood-ratio test at ``false_alarm`` on the pooled data: what the neighbourhood supports,
       where a pixel's own 1-3 detections could not be told from chance.
    3. Censoring per surface: the pixel keeps a candidate (its own strong surfaces first, then the
       pooled ones, largest first; up to K) only when it holds a detection within one response FWHM
       of it; the surface's shift is the pixel's own best within that FWHM, then amplitudes and
       background by EM. A pixel that sees nothing of a surface does not get it (no interpolation).
    4. Weighted smoothing per surface that keeps edges: each surface's shift becomes the
       signal-weighted mean of the surfaces within one FWHM of it in its 3 x 3 neighbourhood (a
       neighbour across an edge, farther in time, does not enter).
    """
    notes = dict(notes)
    core_s = float(notes["pulse_core_rms_s"])
    if notes.get("pulse_source") == "estimated":
        kern, core_s = _measured_model(store, settings, b, kern, notes)
    shift0, _, _, _, gain0, _, kmax, gain_min, rule = fit_surfaces(store, settings, b, kern, core_s)
    fw = fwhm_bins(kern.g)
    tau = SPATIAL_TAU_FWHM * fw
    strong = auto_threshold_nats(STRONG_FALSE_ALARM, b.n_bins, fw)
    pool = auto_threshold_nats(settings.false_alarm, b.n_bins, fw)
    bins, weights, offsets = store_pairs(store, b, settings.max_photons)
    h, w = store.shape
    npix = h * w
    counts = detections_per_pixel(weights, offsets)
    out = surface_outputs(npix, kmax)
    shift, amp, bg, var, gain = out.shift, out.amp, out.bg, out.var, out.gain
    src = np.full((npix, kmax), -1, np.int64)
    nb = MK.Neighbourhood(h, w, SPATIAL_RADIUS, float(strong), float(pool), float(tau), kmax + 1)
    tabs = surface_tables(b, kern, core_s)
    ph, maxn = Photons(bins, offsets, weights), int(np.diff(offsets).max())

    def fit(p0: int, p1: int) -> None:
        MK.neighbour_surfaces(ph, shift0, gain0, nb, tabs, maxn, out, src, p0, p1)

    # in slices of pixels, so that a long run shows its progress (the pooled fits are ~85% of it)
    over_threads(fit, npix, SPATIAL_SLICE, progress)
    has = np.isfinite(shift)
    sig = np.where(has, amp * kern.colsum[np.clip(np.nan_to_num(shift).astype(np.int64), 0, b.n_bins - 1)], 0.0)
    var = _own_spreads(bins, weights, offsets, counts, store.shape, settings, b, kern, shift, sig, var)
    sm_shift = np.empty_like(shift)
    sm_var = np.empty_like(var)
    MK.smooth_surfaces(shift, sig, var, h, w, SPATIAL_RADIUS, float(tau), sm_shift, sm_var)
    notes["surfaces_rule"] = rule
    notes["surface_gain_min_nats"] = float(gain_min)
    notes["kernel_k_surfaces"] = "greedy Poisson pursuit with the neighbours' proposals (recon.estimators.surfaces)"
    notes["spatial_surfaces"] = {"radius": SPATIAL_RADIUS, "tau_bins": float(tau), "strong_nats": float(strong),
                                 "pooled_nats": float(pool), "own_strong": int(np.sum(src == 0)),
                                 "from_neighbourhood": int(np.sum(src == 1))}
    return _maps(store, settings, b, kern, notes, sm_shift, amp, bg, sm_var, gain, counts)
