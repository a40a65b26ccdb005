"""The estimator registry and THE entry point of a reconstruction, :func:`reconstruct`.

Every estimator is a callable ``(store, settings, progress) -> DepthMaps`` registered here under its
name in :data:`recon.model.METHODS`. The layers below know nothing of this module, so there is no
import cycle: :mod:`recon.pixelwise` (lmf, uos, ml kernels on a resolved model) <- :mod:`recon.irf`
(pulse measured from the data, whose pilot fits call pixelwise directly) <- :mod:`recon.resolve`
(binning and pulse from settings or data) <- :mod:`recon.spatial` <- this module.
"""

from __future__ import annotations

from types import MappingProxyType
from typing import Callable, Mapping

from spdepth.recon.errors import InputError
from spdepth.recon.maps import DepthMaps
from spdepth.recon.model import METHODS, PIXELWISE_METHODS, ReconSettings
from spdepth.recon.multi import reconstruct_multi
from spdepth.recon.photons import PhotonStore
from spdepth.recon.pixelwise import reconstruct_pixelwise
# resolve_model is also imported from here by acq.live_recon (it was defined here before the split)
from spdepth.recon.resolve import resolve_model
from spdepth.recon.spatial import reconstruct_spatial

#: ``estimator(store, settings, progress)``: the maps of ``store`` by ``settings.method``.
Estimator = Callable[[PhotonStore, ReconSettings, Callable[[int, int], None] | None], DepthMaps]


def reconstruct_each_pixel(store: PhotonStore, settings: ReconSettings,
                           progress: Callable[[int, int], None] | None = None) -> DepthMaps:
    """lmf, uos and ml: resolve the model (estimating the pulse when the settings give none),
    then fit every pixel on its own (:func:`recon.pixelwise.reconstruct_pixelwise`)."""
    b, kern, notes = resolve_model(store, settings)
    if settings.several:
        # a response estimated from the data is re-measured on the surfaces (recon.multi)
        return reconstruct_multi(store, settings, b, kern, notes, progress,
                                 measure=notes.get("pulse_source") == "estimated")
    return reconstruct_pixelwise(store, settings, b, kern, notes, progress)


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


__all__ = ["ESTIMATORS", "Estimator", "reconstruct", "reconstruct_each_pixel", "resolve_model"]
