"""Depth maps against the truth: error statistics with one denominator, beside the per-pixel oracle.

The yardstick (DESIGN.md section 3) is the oracle that knows which detections are signal and
averages their times: for k signal detections of a pulse with RMS width sigma its time error is
Gaussian with RMS sigma / sqrt(k), so its mean absolute error is sigma * sqrt(2/pi) / sqrt(k).
Here k is per pixel (bright pixels have more signal among the same number of detections), so the
bound follows the scene rather than its mean SBR.

    k = signal_detections(scene.truth(), maps.photons, window_s=...)
    summary = evaluate_depth(maps.depth_m, truth["depth_m"], k, pulse_rms_s)
    print(f"{100 * summary.mae_m:.2f} cm, {summary.ratio_to_oracle:.2f} x oracle")
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from spdepth.recon.errors import InputError
from spdepth.recon.maps import C_M_PER_S

OUTLIER_PULSE_WIDTHS = 3.0
"""Default outlier threshold, in pulse RMS widths of depth (c/2 * sigma each): an estimate that
far off has locked onto something other than the return. For the paper's 360 ps pulse that is
16 cm, about 13 times the oracle's 1.2 cm at 15 detections and SBR 10."""


@dataclass(frozen=True)
class DepthErrors:
    """Errors of one depth map over the pixels with valid truth (all shares and means over the
    same ``n_pixels``; see :func:`evaluate_depth` for the rule for pixels without an estimate).

    mae_m, rmse_m:   mean absolute and root-mean-square depth error, metres.
    outlier_share:   share of pixels off by more than ``outlier_m``, misses included.
    miss_share:      share of pixels without an estimate (NaN depth).
    oracle_mae_m:    mean over the same pixels of the per-pixel oracle bound, metres.
    ratio_to_oracle: mae_m / oracle_mae_m (about 1 for exact Poisson ML, >1 for worse methods).
    n_pixels:        pixels evaluated.
    outlier_m:       the outlier threshold used, metres (also the error a miss counts as).
    """

    mae_m: float
    rmse_m: float
    outlier_share: float
    miss_share: float
    oracle_mae_m: float
    ratio_to_oracle: float
    n_pixels: int
    outlier_m: float


def oracle_mae_m(k_signal, pulse_rms_s: float) -> np.ndarray:
    """Per-pixel oracle bound on the mean absolute depth error, metres:
    ``c/2 * sigma * sqrt(2/pi) / sqrt(k)``.

    k_signal:    signal detections per pixel (array or scalar; expected values may be fractional).
                 NaN where k <= 0: with no signal there is no return to find.
    pulse_rms_s: RMS spread of a signal detection's time, seconds (the pulse, and the detector
                 jitter when there is any).

    With k the expected count (``signal_detections``) rather than the realised one, the bound is
    a little optimistic, as 1/sqrt(k) is convex: by a fraction of a percent at k = 14, a few
    percent at k = 3.
    """
    if not (pulse_rms_s > 0 and math.isfinite(pulse_rms_s)):
        raise InputError(f"oracle: pulse_rms_s must be positive and finite, got {pulse_rms_s!r}")
    k = np.asarray(k_signal, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(k > 0, C_M_PER_S / 2 * pulse_rms_s * math.sqrt(2 / math.pi) / np.sqrt(k),
                        np.nan)


def signal_detections(truth: dict, detections, *, window_s: float | None = None,
                      surface: int = 0) -> np.ndarray:
    """Expected signal detections per pixel, ``detections * SBR_p / (1 + SBR_p)``, with SBR_p the
    pixel's ratio of the surface's signal to everything else recorded in the window.

    truth:      a simulated scene's ``truth()`` (``signal_pp``, ``background_pp``, ``settings``).
    detections: detections per pixel the estimator used (``maps.photons``, or the count-gate
                target as a scalar), in the window.
    window_s:   length of the recorded window after each laser sync, seconds: background is
                uniform over the laser period, so only this share of it is among the detections.
                None: the scene's ``tagger_range_s`` (what the tagger records), else the period.
    surface:    which surface is the return for scenes with several (the others' signal counts
                as background here).

    Signal is taken as wholly inside the window (returns near its edges lose some).
    """
    sig = np.asarray(truth["signal_pp"], dtype=np.float64)
    bg = np.asarray(truth["background_pp"], dtype=np.float64)
    if sig.ndim == 3:
        if not 0 <= surface < sig.shape[0]:
            raise InputError(f"truth has {sig.shape[0]} surfaces, no surface {surface}")
        sig, others = sig[surface], sig.sum(axis=0) - sig[surface]
    elif surface != 0:
        raise InputError(f"truth has one surface, no surface {surface}")
    else:
        others = np.zeros_like(sig)
    settings = truth.get("settings", {})
    period_s = float(settings.get("sync_period_s", 0.0) or 0.0)
    if window_s is None:
        window_s = settings.get("tagger_range_s") or period_s
    share = 1.0 if not period_s > 0 else min(1.0, float(window_s) / period_s)
    if not share > 0:
        raise InputError(f"signal_detections: window_s must be positive, got {window_s!r}")
    total = sig + others + bg * share
    with np.errstate(divide="ignore", invalid="ignore"):
        fraction = np.where(total > 0, sig / total, 0.0)
    return np.asarray(detections, dtype=np.float64) * fraction


def evaluate_depth(depth_m, true_depth_m, k_signal, pulse_rms_s: float, *,
                   outlier_m: float | None = None) -> DepthErrors:
    """Errors of a depth map against the truth, with one denominator for every statistic.

    depth_m, true_depth_m: (H, W) metres; NaN in ``depth_m`` is a pixel without an estimate.
    k_signal:    (H, W) or scalar signal detections per pixel (``signal_detections``).
    pulse_rms_s: RMS time spread of a signal detection, seconds (for the oracle and the default
                 outlier threshold).
    outlier_m:   error beyond which a pixel is an outlier, metres; default
                 ``OUTLIER_PULSE_WIDTHS`` pulse widths of depth, ``3 * c/2 * pulse_rms_s``.

    The pixels evaluated are those with valid truth: finite true depth and k > 0 (a pixel with
    no expected signal has no return to find). Every one of them counts in every statistic.

    The rule for a miss (no estimate): it counts as an outlier, and its error in ``mae_m`` and
    ``rmse_m`` is ``outlier_m``: no answer costs as much as a wrong one at the threshold. So a
    method cannot improve its MAE by leaving hard pixels out and then being averaged over fewer,
    and methods that do and do not flag pixels are compared over the same pixels. Errors of
    estimates are not clipped (a wild estimate costs what it is off by).
    """
    est = np.asarray(depth_m, dtype=np.float64)
    true = np.asarray(true_depth_m, dtype=np.float64)
    if est.shape != true.shape:
        raise InputError(f"depth map shape {est.shape} differs from the truth's {true.shape}")
    k = np.broadcast_to(np.asarray(k_signal, dtype=np.float64), true.shape)
    if outlier_m is None:
        outlier_m = OUTLIER_PULSE_WIDTHS * C_M_PER_S / 2 * pulse_rms_s
    if not (outlier_m > 0 and math.isfinite(outlier_m)):
        raise InputError(f"outlier_m must be positive and finite, got {outlier_m!r}")
    oracle = oracle_mae_m(k, pulse_rms_s)
    valid = np.isfinite(true) & np.isfinite(oracle)
    n = int(valid.sum())
    if n == 0:
        raise InputError("no pixel with valid truth (finite depth and expected signal) to evaluate")
    e, t = est[valid], true[valid]
    miss = ~np.isfinite(e)
    err = np.where(miss, outlier_m, np.abs(e - t))
    mae = float(err.mean())
    oracle_mean = float(oracle[valid].mean())
    return DepthErrors(
        mae_m=mae,
        rmse_m=float(np.sqrt(np.mean(err ** 2))),
        outlier_share=float(np.mean(miss | (err > outlier_m))),
        miss_share=float(miss.mean()),
        oracle_mae_m=oracle_mean,
        ratio_to_oracle=mae / oracle_mean,
        n_pixels=n,
        outlier_m=float(outlier_m),
    )
