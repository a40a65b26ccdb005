"""The estimator registry and THE entry point of a reconstruction, :func:`reconstruct`.

Every estimator is a callable ``(store, settings, progress) -> DepthMaps`` registered here under its
name in :data:`recon.model.METHODS`. The layers below know nothing of this module, so there is no
import cycle: :mod:`recon.pixelwise` (lmf, uos, ml kernels on a resolved model) <- :mod:`recon.irf`
(pulse measured from the data, whose pilot fits call pixelwise directly) <- :mod:`recon.resolve`
(binning and pulse from settings or data) <- :mod:`recon.spatial` <- this module.
"""

from __future__ import annotations

import dataclasses
from types import MappingProxyType
from typing import Callable, Mapping

import numpy as np

from spdepth.recon.errors import InputError
from spdepth.recon.maps import DepthMaps
from spdepth.recon.model import METHODS, PIXELWISE_METHODS, Binning, ReconSettings
from spdepth.recon.photons import PhotonStore
from spdepth.recon.pixelwise import reconstruct_pixelwise
# resolve_model is also imported from here by acq.live_recon (it was defined here before the split)
from spdepth.recon.resolve import resolve_model

#: ``estimator(store, settings, progress)``: the maps of ``store`` by ``settings.method``.
Estimator = Callable[[PhotonStore, ReconSettings, Callable[[int, int], None] | None], DepthMaps]


def reconstruct_each_pixel(store: PhotonStore, settings: ReconSettings,
                           progress: Callable[[int, int], None] | None = None) -> DepthMaps:
    """lmf, uos and ml: resolve the model (estimating the pulse when the settings give none),
    then fit every pixel on its own (:func:`recon.pixelwise.reconstruct_pixelwise`)."""
    b, kern, notes = resolve_model(store, settings)
    if settings.several:
        # recon.multi (its own kernels) is imported on first use, as the spatial
        # estimator is: one surface per pixel, the common case, should not wait for it.
        # A response estimated from the data is re-measured on the surfaces there.
        from spdepth.recon.multi import reconstruct_multi

        return reconstruct_multi(store, settings, b, kern, notes, progress,
                                 measure=notes.get("pulse_source") == "estimated")
    return reconstruct_pixelwise(store, settings, b, kern, notes, progress)


def reconstruct_spatial(store: PhotonStore, settings: ReconSettings,
                        progress: Callable[[int, int], None] | None = None) -> DepthMaps:
    """:func:`recon.spatial.reconstruct_spatial`, imported on first use: the spatial estimator
    brings its own kernels, which a pixelwise reconstruction (``spdepth recon``'s default) has no
    use for and should not wait for in a new process."""
    from spdepth.recon.spatial import reconstruct_spatial as spatial

    return spatial(store, settings, progress)


#: The estimators by name; its keys are exactly :data:`recon.model.METHODS`, in that order.
ESTIMATORS: Mapping[str, Estimator] = MappingProxyType(
    {**{m: reconstruct_each_pixel for m in PIXELWISE_METHODS}, "spatial": reconstruct_spatial})
if tuple(ESTIMATORS) != METHODS:
    raise ImportError(f"recon.estimate: registry {tuple(ESTIMATORS)} differs from METHODS {METHODS}")


def reconstruct(store: PhotonStore, settings: ReconSettings,
                progress: Callable[[int, int], None] | None = None) -> DepthMaps:
    """Estimate depth, background and signal at every pixel of ``store``.

    Steps: resolve the binning and pulse (estimating the pulse RMS from the data when neither a width
    nor an IRF is given), keep the first ``max_photons`` in-window detections of each pixel, bin
    them, and run the estimator ``ESTIMATORS[settings.method]``, which calls ``progress(done,
    total)`` as it goes (per chunk of pixels for the pixelwise methods). Returns
    :class:`DepthMaps`; ``settings`` in it holds everything used (binning, pulse RMS and its source).
    """
    if not isinstance(settings, ReconSettings):
        raise InputError(f"settings must be ReconSettings, got {type(settings).__name__}")
    if not isinstance(store, PhotonStore):
        raise InputError(f"store must be a PhotonStore, got {type(store).__name__}")
    return ESTIMATORS[settings.method](store, settings, progress)


def warm_up(settings: ReconSettings) -> None:
    """Load (or, on a cold numba cache, compile) the kernels that ``settings``' estimator runs, on
    one made-up pixel of four detections, so that a later call on real data does not wait for them
    (a new process loads each kernel from the cache on its first call). Without a binning (a file's
    comes from its data) a made-up one of 64 bins serves: the kernels' code does not depend on it.
    Only the method and the number of surfaces choose kernels; results are discarded."""
    b = settings.binning
    if b is None:
        b = Binning(1e-12, 0.0, 64.0, 1.0)
    times = b.window_start + b.bin_width * (np.arange(4) + 0.5 * b.n_bins)
    one = PhotonStore(times.astype(np.float64), np.array([0, times.size]), (1, 1), b.time_unit_s)
    pulse = settings.pulse_rms_s
    if pulse is None and settings.irf is None:
        pulse = 3 * b.bin_width_s          # any width: only the kernels' loading matters
    reconstruct(one, dataclasses.replace(settings, binning=b, pulse_rms_s=pulse))


__all__ = ["ESTIMATORS", "Estimator", "reconstruct", "reconstruct_each_pixel", "resolve_model", "warm_up"]
