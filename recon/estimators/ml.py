"""ml: the exact pixelwise Poisson maximum likelihood of the seed paper's eq. (9) over (shift,
amplitude >= 0, background >= 0), global over the integer shifts (branch and bound), refined to
1/FINE_STEPS bin and by a parabola; Fisher uncertainty. Kernels: :mod:`recon.kernels`
(``ml_kernel``), loaded on the first run."""

from __future__ import annotations

import numpy as np

from spdepth.recon.estimators import Estimator, register


def ml_tables(kern, m: int) -> tuple:
    """The arguments of :func:`recon.kernels.ml_kernel` from ``g`` to ``fine_climb``, for the pulse
    kernel ``kern`` over a window of m bins."""
    from spdepth.recon import kernels as K
    from spdepth.recon.model import FINE_STEPS

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


def fit(store, settings, b, kern, notes, progress=None):
    """:data:`recon.estimators.Fit` of ml on the resolved binning ``b`` and pulse ``kern``."""
    from spdepth.recon import kernels as K
    from spdepth.recon.model import FINE_STEPS
    from spdepth.recon.pixelwise import fit_pixels, pixel_maps

    tabs = ml_tables(kern, b.n_bins)

    def chunk(bins, offsets, maxn, out):
        K.ml_kernel(bins, offsets, b.n_bins, *tabs, kern.dg, kern.fisher, maxn,
                    out.shift, out.amp, out.bg, out.var, out.n_used)

    res = fit_pixels(store, settings, b, chunk, progress)
    return pixel_maps(store, settings, b, kern, notes, res, shift_step=1.0 / FINE_STEPS)


ESTIMATOR = register(Estimator(
    "ml", "exact Poisson maximum likelihood (the paper's eq. 9): 1/8-bin shifts, estimates background",
    fit, pixelwise=True, several="surfaces"))
