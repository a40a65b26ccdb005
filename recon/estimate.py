"""THE entry point of a reconstruction, :func:`reconstruct`: resolve the model, then run the
estimator the registry (:mod:`recon.estimators`) holds for the settings.

Layers: :mod:`recon.pixelwise` (what the one-surface pixelwise estimators share) <- the estimator
modules (:mod:`recon.estimators`, their kernels loaded on first use) <- :mod:`recon.resolve`
(binning and pulse from settings or data; :mod:`recon.irf` for a pulse measured from the data,
whose pilot fits run an estimator on a given model) <- this module.
"""

from __future__ import annotations

import dataclasses
from typing import Callable

import numpy as np

from spdepth.recon import estimators
from spdepth.recon.counts import CountStore
from spdepth.recon.errors import InputError
from spdepth.recon.given import given_pulse
from spdepth.recon.maps import DepthMaps
from spdepth.recon.model import Binning, ReconSettings
from spdepth.recon.photons import PhotonStore
# resolve_model is also imported from here by acq.live_recon (it was defined here before the split)
from spdepth.recon.resolve import resolve_model


def reconstruct(store: PhotonStore, settings: ReconSettings,
                progress: Callable[[int, int], None] | None = None, neighbours: bool = True) -> DepthMaps:
    """Estimate depth, background and signal at every pixel of ``store``.

    ``store``: a photon list, or counts (``recon.counts.CountStore``: a histogram cube, or a
    pile-up-corrected histogram), which an estimator with the ``counts`` capability takes as (bin,
    count) pairs and any other as the equivalent photon list.

    Steps: resolve the binning and pulse (estimating the pulse RMS from the data when neither a width
    nor an IRF is given), then run the estimator of ``settings`` (``recon.estimators.for_settings``:
    the method, or the K-surface fit it hands several surfaces to), which keeps the first
    ``max_photons`` in-window detections of each pixel, bins them, and calls ``progress(done,
    total)`` as it goes (per chunk of pixels for the pixelwise methods). Returns :class:`DepthMaps`;
    then decides per pixel whether the data hold a return and sets every depth's uncertainty
    (:mod:`recon.detect`, the one place every estimator's maps pass), with the neighbours' support
    for pixels that fail on their own detections unless ``neighbours`` is False (a batch of pixels
    that are not a frame: a live scan's). ``settings`` in it holds everything used (binning, pulse
    RMS and its source).
    """
    if not isinstance(settings, ReconSettings):
        raise InputError(f"settings must be ReconSettings, got {type(settings).__name__}")
    if not isinstance(store, (PhotonStore, CountStore)):
        raise InputError(f"store must be a PhotonStore or a CountStore, got {type(store).__name__}")
    est = estimators.for_settings(settings)
    if isinstance(store, CountStore) and not est.counts:
        store = as_photons(store)
    model_from = store
    if isinstance(store, CountStore) and given_pulse(settings) is None:
        model_from = as_photons(store)    # the pulse is measured on photon times (recon.irf)
    b, kern, notes = resolve_model(model_from, settings)
    maps = est.run(store, settings, b, kern, notes, progress)
    # the one place every estimator's maps pass: is there a return, and how sure is each depth
    from spdepth.recon.detect import decide_maps

    return decide_maps(store, settings, maps, neighbours=neighbours)


def as_photons(counts: CountStore) -> PhotonStore:
    """The photon list of ``counts`` for what takes photons only (an estimator without the
    ``counts`` capability, the pulse measured from the data): exact for whole counts, running
    totals rounded for pile-up-corrected ones (:meth:`CountStore.to_photons`)."""
    return counts.to_photons(round_counts=not counts.is_whole())


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


__all__ = ["as_photons", "reconstruct", "resolve_model", "warm_up"]
