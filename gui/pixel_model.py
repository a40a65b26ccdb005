"""One pixel's photon histogram and the fitted forward model drawn over it (no Qt here).

The model is the seed paper's: expected counts per bin ``B + S * g(k - shift)`` with ``g`` the
bin-integrated pulse of ``recon.model.build_kernel`` (Gaussian or measured IRF), ``shift`` the
estimated time of flight in bins, ``B`` the estimated background per bin and ``S`` the estimated
signal count. Both are summed into coarser display bins (a handful of photons over 801 bins of
40 ps would be a row of zeros and ones).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from spdepth.recon.model import Binning, build_kernel

DISPLAY_BINS = 80
"""About this many bins across the window in the inspector."""


@dataclass(frozen=True)
class PixelHistogram:
    """edges_s: display bin edges after the sync (s), len n+1; counts: detections per display
    bin; model: expected detections per display bin (None without an estimate)."""

    edges_s: np.ndarray
    counts: np.ndarray
    model: np.ndarray | None


@lru_cache(maxsize=8)
def _gaussian_kernel(binning: Binning, pulse_rms_s: float):
    return build_kernel(binning, pulse_rms_s=pulse_rms_s)


def _kernel(binning: Binning, pulse_rms_s: float | None, irf):
    if irf is not None:          # a measured IRF holds arrays: not hashable, not cached
        return build_kernel(binning, irf=irf)
    return _gaussian_kernel(binning, float(pulse_rms_s))


def pixel_histogram(times: np.ndarray, binning: Binning, *, tof_s=np.nan,
                    background: float = np.nan, signal=np.nan,
                    pulse_rms_s: float | None = None, irf=None,
                    display_bins: int = DISPLAY_BINS) -> PixelHistogram:
    """times: one pixel's detection times in tagger units (``binning.time_unit_s``); tof_s and
    signal: one return's, or sequences of several surfaces' (the model sums their returns)."""
    tofs, signals = np.atleast_1d(np.asarray(tof_s, float)), np.atleast_1d(np.asarray(signal, float))
    m = binning.n_bins
    r = max(1, int(round(m / display_bins)))
    n_disp = -(-m // r)
    k = binning.bin_index(np.asarray(times, dtype=np.float64))
    k = k[k >= 0]
    counts = np.bincount(k // r, minlength=n_disp)[:n_disp].astype(np.float64)
    edges_bins = np.minimum(np.arange(n_disp + 1) * r, m)
    edges_s = (binning.window_start + edges_bins * binning.bin_width) * binning.time_unit_s
    model = None
    have_pulse = pulse_rms_s is not None or irf is not None
    bg = background if np.isfinite(background) else 0.0
    if np.isfinite(bg) and (np.isfinite(background) or np.isfinite(tofs).any()) and have_pulse:
        per_bin = np.full(m, bg)
        for tof, sig in zip(tofs, signals):
            if not (np.isfinite(tof) and np.isfinite(sig) and sig > 0):
                continue
            kern = _kernel(binning, pulse_rms_s, irf)
            shift = tof / binning.time_unit_s
            shift = (shift - binning.window_start) / binning.bin_width - 0.5   # shift_to_time_s^-1
            # g at offsets d = k - shift, from the fine table (FINE_STEPS samples per bin)
            steps = (kern.fine.size - 1) / max(1, kern.g.size - 1)
            x = np.arange(m) - shift
            xf = np.arange(kern.fine.size) / steps - kern.off
            per_bin = per_bin + sig * np.interp(x, xf, kern.fine, left=0.0, right=0.0)
        model = np.add.reduceat(per_bin, np.arange(0, m, r))
    return PixelHistogram(edges_s, counts, model)


__all__ = ["PixelHistogram", "pixel_histogram", "DISPLAY_BINS"]
