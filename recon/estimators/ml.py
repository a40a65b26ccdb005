"""ml: the exact pixelwise Poisson maximum likelihood of the seed paper's eq. (9) over (shift,
amplitude >= 0, background >= 0), global over the integer shifts (branch and bound), refined to
1/FINE_STEPS bin and by a parabola; Fisher uncertainty. Kernels: :mod:`.ml_kernels` (the
search) and :mod:`.ml_bounds` (the likelihood and its bounds), loaded on the first run."""

from __future__ import annotations

import functools

from spdepth.recon.estimators import Estimator, register


def ml_tables(kern, m: int, fine_climb: bool | None = None):
    """:class:`.ml_kernels.MlTables` for the pulse kernel ``kern`` over a window of m bins;
    ``fine_climb`` overrides the choice of the fine search (default: climb on a smooth pulse, see
    ML_CLIMB_RMS_BINS). The same kernel object (``recon.model.build_kernel`` keeps one per binning
    and pulse) gets the same tables, kept from an earlier call: ml's fit and the return test's two
    passes built them anew for every live batch and array frame (about 0.6 ms of a 64 x 64 frame).
    Shared, so read-only."""
    from spdepth.recon.estimators import ml_kernels as MK

    if fine_climb is None:
        fine_climb = bool(kern.log_concave and kern.rms_bins >= MK.ML_CLIMB_RMS_BINS)
    return _tables(kern, int(m), bool(fine_climb))


@functools.lru_cache(maxsize=2)
def _tables(kern, m: int, fine_climb: bool):
    """:func:`ml_tables`, computed: keyed on the kernel's identity (a PulseKernel compares by
    identity), which the cache holds on to, so a key is never another kernel's; as many as
    recon.model.KERNEL_CACHE keeps kernels (a measured response's can be large)."""
    import numpy as np

    from spdepth.recon.estimators import ml_kernels as MK
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
    return MK.ml_tables(kern.g, kern.off, logg_int, dlo, dhi, kern.colsum, np.log(kern.colsum), kern.fine,
                        kern.fine_colsum, FINE_STEPS, bool(fine_climb), kern.dg, kern.fisher)


def fit(store, settings, b, kern, notes, progress=None):
    """:data:`recon.estimators.Fit` of ml on the resolved binning ``b`` and pulse ``kern``."""
    from spdepth.recon.estimators.ml_kernels import ml_kernel
    from spdepth.recon.kernels import NO_WEIGHTS, Photons
    from spdepth.recon.model import FINE_STEPS
    from spdepth.recon.pixelwise import fit_pixels, pixel_maps

    tabs = ml_tables(kern, b.n_bins)

    def chunk(bins, offsets, maxn, out, weights=NO_WEIGHTS):
        ml_kernel(Photons(bins, offsets, weights), tabs, maxn, out.shift, out.amp, out.bg, out.var, out.n_used,
                  out.gain)

    res = fit_pixels(store, settings, b, chunk, progress)
    return pixel_maps(store, settings, b, kern, notes, res, shift_step=1.0 / FINE_STEPS)


ESTIMATOR = register(Estimator(
    "ml", "exact Poisson maximum likelihood (the paper's eq. 9): 1/8-bin shifts, estimates background",
    fit, pixelwise=True, several="surfaces", counts=True, gains=True))
