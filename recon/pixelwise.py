"""The pixelwise estimators (lmf, uos, ml) on a resolved model: window, first ``max_photons`` and
binning in one compiled pass, then the method's numba kernel (:mod:`recon.kernels`) over chunks of
pixels, and the maps. The model (binning and pulse kernel) comes from :mod:`recon.resolve`, or from
the settings alone when they give both (:func:`reconstruct_given`, which needs no pulse estimate:
the IRF estimate's pilot reconstructions use it).

Imports only the forward model, the kernels and the maps: resolve, irf, spatial and the registry
(recon.estimate) sit above it.
"""

from __future__ import annotations

import math
from typing import Callable

import numpy as np

from spdepth.recon import kernels as K
from spdepth.recon.errors import InputError
from spdepth.recon.maps import C_M_PER_S, DepthMaps, PixelFlag
from spdepth.recon.model import (FINE_STEPS, PIXELWISE_METHODS, Binning, Irf, PulseKernel, ReconSettings,
                                 build_kernel, irf_core_rms_s)
from spdepth.recon.photons import PhotonStore

#: Pixels per kernel call; progress is reported between chunks.
CHUNK_PIXELS = 16384
#: K-reflector pursuit: returns closer than this many pulse RMS widths are one return.
MERGE_RMS = 2.0
#: K-reflector pursuit: a return must raise the Poisson log-likelihood by more than this (nats).
LLR_MIN = 3.0


def ml_tables(kern: PulseKernel, m: int) -> tuple:
    """The arguments of :func:`recon.kernels.ml_kernel` from ``g`` to ``fine_climb``, for the pulse
    kernel ``kern`` over a window of m bins."""
    logg_int = np.full(kern.g.size, -np.inf)
    pos = kern.g > 0
    logg_int[pos] = np.log(kern.g[pos])
    above = np.flatnonzero(kern.g * m > float(kern.colsum.min()))
    if above.size:
        dlo, dhi = int(above[0] - kern.off), int(above[-1] - kern.off)
    else:
        # no offset beats the floor (a one-bin window: a return and the background are the
        # same column): every shift's bound is the floor, the all-background fit wins
        dlo, dhi = 0, -1
    fine_climb = bool(kern.log_concave and kern.rms_bins >= K.ML_CLIMB_RMS_BINS)
    return (kern.g, kern.off, logg_int, dlo, dhi, kern.colsum, np.log(kern.colsum), kern.fine,
            kern.fine_colsum, FINE_STEPS, fine_climb)


def check_time_unit(store: PhotonStore, binning: Binning | None) -> None:
    """InputError when ``binning`` counts in another raw unit than ``store``."""
    if binning is not None and not math.isclose(binning.time_unit_s, store.time_unit_s, rel_tol=1e-9):
        raise InputError(f"binning time unit {binning.time_unit_s} s differs from the data's "
                         f"{store.time_unit_s} s")


def given_pulse(settings: ReconSettings) -> tuple[Irf | None, float, float, str] | None:
    """The pulse ``settings`` give: (irf or None for a Gaussian, RMS s, core RMS s, source), the
    core being the width of the response's sharp part (:func:`recon.model.irf_core_rms_s`). None
    when they give neither a width nor an IRF (then the pulse is measured: recon.resolve)."""
    if settings.irf is not None:
        return settings.irf, settings.irf.rms_s, irf_core_rms_s(settings.irf), "irf"
    if settings.pulse_rms_s is not None:
        return None, settings.pulse_rms_s, settings.pulse_rms_s, "given"
    return None


def pulse_kernel(binning: Binning, irf: Irf | None, rms_s: float, core_s: float, notes: dict) -> PulseKernel:
    """The kernel of the pulse (``irf``, else a Gaussian of ``rms_s``) on ``binning``; records the
    widths used in ``notes`` (``pulse_rms_s``, ``pulse_core_rms_s``)."""
    kern = build_kernel(binning, irf=irf) if irf is not None else build_kernel(binning, pulse_rms_s=rms_s)
    notes["pulse_rms_s"] = float(rms_s)
    notes["pulse_core_rms_s"] = float(min(core_s, rms_s))
    return kern


def matched_filter_var(shift: np.ndarray, amp: np.ndarray, bg: np.ndarray, kern: PulseKernel,
                       m: int) -> np.ndarray:
    """Shift variance (bins^2) of uos's returns: the sandwich variance of a matched filter.

    uos places a return at the peak of its proxy ``S_i^T y - B S_i^T 1``, i.e. it solves
    ``psi(t) = sum_k y_k g'(k - t) = 0`` (S_i^T 1 is flat inside the window), not the likelihood
    equation, so the Fisher bound understates its spread (for a Gaussian pulse and no background
    by 1.54x in variance: uos reported ~59% of pixels within one sigma). For Poisson y_k with mean
    ``lambda_k = a g_k + B``: ``var = sum lambda_k g'_k^2 / (a sum g_k g''_k)^2``, over the window's
    bins. shift/amp: (P, K), bg: (P,). NaN where there is no return."""
    g, dg, ddg = kern.g, kern.dg, kern.ddg
    nk = g.size
    pref = np.zeros((3, nk + 1))
    np.cumsum(g * dg * dg, out=pref[0, 1:])
    np.cumsum(dg * dg, out=pref[1, 1:])
    np.cumsum(g * ddg, out=pref[2, 1:])
    has = np.isfinite(shift)
    j = np.where(has, np.rint(np.nan_to_num(shift)), 0).astype(np.int64)
    tlo = np.clip(kern.off - j, 0, nk)
    thi = np.clip(m - j + kern.off, 0, nk)
    sgd2, sd2, sgdd = (pref[r][thi] - pref[r][tlo] for r in range(3))
    bgc = np.asarray(bg, dtype=np.float64)[:, None]
    with np.errstate(divide="ignore", invalid="ignore"):
        v = (amp * sgd2 + bgc * sd2) / (amp * sgdd) ** 2
    return np.where(has & (amp > 0), v, np.nan)


def honest_var(var: np.ndarray, has: np.ndarray, rms_bins: float, n_bins: int, method: str) -> np.ndarray:
    """Shift variance (bins^2) to report, from the kernels' Fisher variance ``var``.

    The Fisher information is the local curvature at the estimate; it says nothing where that
    curvature vanishes. A pulse narrower than a bin puts all its photons in one bin, where the
    likelihood is flat in the shift: the Fisher variance reads ~1e32 (or NaN with background),
    while the shift is known to within that bin. So: a degenerate or larger variance is replaced
    by a bin's uniform variance plus the pulse's (``1/12 + rms^2``) for such pulses, by the whole
    window's uniform variance otherwise, never more than the window's; and the estimator's grid
    adds its quantization (integer shifts for lmf/uos: 1/12; 1/FINE_STEPS for ml)."""
    v = np.where(np.isfinite(var) & (var > 0), var, np.inf)
    window = n_bins * n_bins / 12.0
    if rms_bins < 1.0:
        v = np.minimum(v, 1.0 / 12.0 + rms_bins * rms_bins)
    v = np.minimum(v, window)
    quant = 1.0 / (12.0 * FINE_STEPS * FINE_STEPS) if method == "ml" else 1.0 / 12.0
    return np.where(has, np.minimum(v + quant, window), np.nan)


def settings_record(settings: ReconSettings, notes: dict, binning: Binning, kern: PulseKernel) -> dict:
    """What a result's ``settings`` holds: the settings asked for, what was resolved (binning,
    pulse and where it came from) and the kernel used."""
    rec = settings.to_dict()
    rec.update(notes)
    rec["binning"] = binning.to_dict()
    rec["kernel"] = kern.info
    rec["tof_reference"] = "pulse centroid, from the laser sync"
    if settings.irf is not None:
        rec["irf"]["rms_s"] = settings.irf.rms_s
    return rec


def reconstruct_given(store: PhotonStore, settings: ReconSettings,
                      progress: Callable[[int, int], None] | None = None) -> DepthMaps:
    """:func:`reconstruct_pixelwise` for settings that give the binning and the pulse (a width or
    an IRF): nothing is estimated from the data but the depths. InputError otherwise."""
    b = settings.binning
    pulse = given_pulse(settings)
    if b is None or pulse is None:
        raise InputError("reconstruct_given needs settings with a binning and a pulse width or IRF")
    check_time_unit(store, b)
    irf, rms_s, core_s, source = pulse
    notes = {"pulse_source": source, "binning_source": "given"}
    kern = pulse_kernel(b, irf, rms_s, core_s, notes)
    return reconstruct_pixelwise(store, settings, b, kern, notes, progress)


def reconstruct_pixelwise(store: PhotonStore, settings: ReconSettings, b: Binning, kern: PulseKernel,
                          notes: dict, progress: Callable[[int, int], None] | None = None) -> DepthMaps:
    """Depth, background and signal at every pixel of ``store`` by ``settings.method`` (lmf, uos or
    ml), on the resolved binning ``b`` and pulse kernel ``kern`` (``notes``: what resolving found,
    with ``pulse_core_rms_s``; recorded in the result's settings).

    Keeps the first ``max_photons`` in-window detections of each pixel, bins them, and runs the
    method's kernel over chunks of CHUNK_PIXELS pixels, calling ``progress(done, total)`` after
    each chunk.
    """
    if settings.method not in PIXELWISE_METHODS:
        raise InputError(f"pixelwise estimators are {', '.join(PIXELWISE_METHODS)}, got {settings.method!r}")
    if settings.several:
        # several surfaces are recon.multi's (it sits above this module; recon.estimate routes there)
        raise InputError("reconstruct_pixelwise fits one surface per pixel; several: "
                         "recon.multi.reconstruct_multi (or recon.estimate.reconstruct)")
    notes = dict(notes)
    # window, first max_photons and binning in one compiled pass (the NumPy route of
    # first_in_window + bin_index cost as much as the lmf kernel itself)
    bins, offsets = binned_photons(store, b, settings.max_photons)
    h, w = store.shape
    npix = h * w
    m = b.n_bins
    kk = int(settings.reflectors)
    counts = np.diff(offsets)
    # returns closer than MERGE_RMS widths of the response's sharp part are one (a long tail does
    # not blur two surfaces that its leading edges tell apart)
    merge_bins = MERGE_RMS * notes["pulse_core_rms_s"] / b.bin_width_s

    shift = np.full((npix, kk), np.nan)
    amp = np.zeros((npix, kk))
    var = np.full((npix, kk), np.nan)
    bg = np.zeros(npix)
    n_used = np.zeros(npix, np.int64)
    iters = np.ones(npix, np.int32)
    conv = np.ones(npix, np.bool_)

    if settings.method == "ml":
        ml_tabs = ml_tables(kern, m)

    for p0 in range(0, npix, CHUNK_PIXELS):
        p1 = min(npix, p0 + CHUNK_PIXELS)
        o = offsets[p0:p1 + 1]
        cb = bins[o[0]:o[-1]]
        co = o - o[0]
        maxn = int(counts[p0:p1].max()) if p1 > p0 else 0
        if settings.method == "lmf":
            si = np.empty(p1 - p0, np.int64)
            K.lmf_kernel(cb, co, m, kern.logg, kern.log_concave, maxn, si, var[p0:p1, 0], n_used[p0:p1])
            shift[p0:p1, 0] = np.where(si >= 0, si, np.nan)
            amp[p0:p1, 0] = np.where(si >= 0, counts[p0:p1], 0.0)
        elif settings.method == "uos":
            K.uos_kernel(cb, co, m, kern.g, kern.off, kern.gmax, kern.colsum, kern.pp, kern.dg,
                         kk, float(settings.delta), int(settings.max_iterations),
                         merge_bins, LLR_MIN, maxn,
                         shift[p0:p1], amp[p0:p1], bg[p0:p1], iters[p0:p1], conv[p0:p1],
                         var[p0:p1], n_used[p0:p1])
        else:
            K.ml_kernel(cb, co, m, *ml_tabs, kern.dg, kern.fisher, maxn,
                        shift[p0:p1, 0], amp[p0:p1, 0], bg[p0:p1], var[p0:p1, 0], n_used[p0:p1])
        if progress is not None:
            progress(p1, npix)

    has = np.isfinite(shift)
    # expected signal detections inside the window: amplitude times the column sum at that shift
    q = np.where(has, np.rint(np.nan_to_num(shift) * FINE_STEPS), 0).astype(np.int64)
    signal = np.where(has, amp * kern.fine_colsum[np.clip(q, 0, kern.fine_colsum.size - 1)], 0.0)
    if settings.method == "lmf":
        signal = np.where(has, amp, 0.0)    # the LMF attributes every detection to the return
    tof_s = np.where(has, b.shift_to_time_s(np.nan_to_num(shift)), np.nan)
    if settings.method == "uos":
        var = matched_filter_var(shift, amp, bg, kern, m)
    unc_s = np.sqrt(honest_var(var, has, kern.rms_bins, m, settings.method)) * b.bin_width_s
    if settings.method == "lmf":
        bg = np.full(npix, np.nan)      # the LMF does not estimate background (not "measured none")
        notes["background"] = "not estimated by lmf (NaN)"

    flags = np.full(npix, PixelFlag.OK, np.uint8)
    any_ret = has.any(axis=1)
    flags[~any_ret] = PixelFlag.NO_SIGNAL
    flags[any_ret & ~conv] = PixelFlag.NOT_CONVERGED
    flags[n_used == 0] = PixelFlag.NO_PHOTONS

    def img(a):
        if kk == 1:
            return a[:, 0].reshape(h, w)
        return np.ascontiguousarray(a.T).reshape(kk, h, w)

    rec = settings_record(settings, notes, b, kern)
    tof_img = img(tof_s)
    return DepthMaps(tof_s=tof_img, depth_m=C_M_PER_S * tof_img / 2.0, background=bg.reshape(h, w),
                     signal=img(signal), photons=n_used.reshape(h, w), iterations=iters.reshape(h, w),
                     uncertainty_s=img(unc_s), flags=flags.reshape(h, w), settings=rec)


def binned_photons(store: PhotonStore, b: Binning, max_photons: int | None) -> tuple[np.ndarray, np.ndarray]:
    """The in-window detections of every pixel (the first ``max_photons`` of each, None: all) as
    bin indices, grouped by pixel: (bins int64, offsets int64 (P + 1,)). One compiled pass (the
    NumPy route of first_in_window + bin_index cost as much as the lmf kernel itself)."""
    times = np.ascontiguousarray(store.times, dtype=np.float64)
    bins = np.empty(times.size, np.int64)
    offsets = np.empty(store.offsets.size, np.int64)
    n_kept = K.window_bins(times, np.ascontiguousarray(store.offsets, dtype=np.int64), b.window_start,
                           b.window_stop, b.bin_width, b.n_bins,
                           -1 if max_photons is None else int(max_photons), bins, offsets)
    return bins[:n_kept], offsets
