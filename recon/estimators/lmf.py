"""lmf: the log-matched filter (the seed paper's eq. 11), ``argmax_i sum_k y_k log S_{k,i}`` per
pixel over integer shifts. It ignores background: every detection counts as signal, and its
background map is NaN. Kernels: :mod:`.lmf_kernels`, loaded on the first run."""

from __future__ import annotations

from spdepth.recon.estimators import Estimator, register


def fit(store, settings, b, kern, notes, progress=None):
    """:data:`recon.estimators.Fit` of lmf on the resolved binning ``b`` and pulse ``kern``."""
    import numpy as np

    from spdepth.recon.estimators.lmf_kernels import LmfTables, lmf_kernel
    from spdepth.recon.kernels import NO_WEIGHTS, Photons
    from spdepth.recon.pixelwise import fit_pixels, pixel_maps

    tabs = LmfTables(b.n_bins, kern.logg, kern.log_concave)

    def chunk(bins, offsets, maxn, out, weights=NO_WEIGHTS):
        si = np.empty(out.shift.size, np.int64)
        lmf_kernel(Photons(bins, offsets, weights), tabs, maxn, si, out.var, out.n_used)
        out.shift[:] = np.where(si >= 0, si, np.nan)
        # the LMF attributes every detection to the return
        out.amp[:] = np.where(si >= 0, out.n_used, 0.0)

    res = fit_pixels(store, settings, b, chunk, progress)
    res.bg[:] = np.nan          # not estimated (not "measured none")
    notes = dict(notes, background="not estimated by lmf (NaN)")
    signal = np.where(np.isfinite(res.shift), res.amp, 0.0)
    return pixel_maps(store, settings, b, kern, notes, res, shift_step=1.0, signal=signal)


ESTIMATOR = register(Estimator(
    "lmf", "log-matched filter (the paper's eq. 11): integer shifts, ignores background (NaN map)",
    fit, pixelwise=True, several="surfaces", counts=True, background=False))
