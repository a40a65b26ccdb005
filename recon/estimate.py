"""THE entry point of a reconstruction, :func:`reconstruct`: resolve the model, then run the
estimator the registry (:mod:`recon.estimators`) holds for the settings.

Layers: :mod:`recon.pixelwise` (what the one-surface pixelwise estimators share) <- the estimator
modules (:mod:`recon.estimators`, their kernels loaded on first use) <- :mod:`recon.resolve`
(binning and pulse from settings or data; :mod:`recon.irf` for a pulse measured from the data,
whose pilot fits run an estimator on a given model) <- this module.
"""

from __future__ import annotations

import dataclasses
import subprocess
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
    count) pairs (of whole counts, rounded first, for the "whole" ones) and any other as the
    equivalent photon list.

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
    elif isinstance(store, CountStore) and est.counts == "whole":
        store = store.rounded()
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


def warm_up(settings: ReconSettings, decide: bool = True) -> None:
    """Load (or, on a cold numba cache, compile) the kernels that ``settings``' estimator runs, on
    one made-up pixel of four detections, so that a later call on real data does not wait for them
    (a new process loads each kernel from the cache on its first call). Without a binning (a file's
    comes from its data) a made-up one of 64 bins serves: the kernels' code does not depend on it.
    Only the method and the number of surfaces choose kernels; results are discarded. ``decide``:
    also the return test's (:mod:`recon.detect`, which every reconstruction runs); False: the
    estimator's alone."""
    b = settings.binning
    if b is None:
        b = Binning(1e-12, 0.0, 64.0, 1.0)
    times = b.window_start + b.bin_width * (np.arange(4) + 0.5 * b.n_bins)
    one = PhotonStore(times.astype(np.float64), np.array([0, times.size]), (1, 1), b.time_unit_s)
    pulse = settings.pulse_rms_s
    if pulse is None and settings.irf is None:
        pulse = 3 * b.bin_width_s          # any width: only the kernels' loading matters
    settings = dataclasses.replace(settings, binning=b, pulse_rms_s=pulse)
    if decide:
        reconstruct(one, settings)
        return
    bb, kern, notes = resolve_model(one, settings)
    estimators.for_settings(settings).run(one, settings, bb, kern, notes)


def compile_apart(settings: list[ReconSettings]) -> subprocess.Popen | None:
    """The first run after an install: compile the estimator kernels of each of ``settings`` (as
    :func:`warm_up` with ``decide=False``) into numba's cache in a new interpreter, started now, and
    return it; wait for it before their first call here, which then loads them from the cache.
    None when each is in the cache already (or its kernels are not found: then its first call
    compiles it here, as without this). Numba compiles one function at a time in a process (one
    lock for every thread), so only another process puts a second core to compiling while this one
    compiles or runs other kernels. The child inherits the environment (NUMBA_CACHE_DIR, the path)."""
    import json
    import sys

    cold = [s for s in settings if not _kernels_cached(estimators.for_settings(s))]
    if not cold:
        return None
    code = ("import json, sys\nfrom spdepth.recon.estimate import warm_up\n"
            "from spdepth.recon.model import ReconSettings\n"
            "for d in json.loads(sys.argv[1]):\n    warm_up(ReconSettings.from_dict(d), decide=False)\n")
    return subprocess.Popen([sys.executable, "-c", code, json.dumps([s.to_dict() for s in cold])],
                            stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)


def _kernels_cached(est) -> bool:
    """Whether numba's cache holds compiled code of any kernel of ``est``'s kernel module (the fit's
    module with ``_kernels`` after it, as lmf, uos and ml have; True when there is none), read from
    the cache's index files without loading any code (numba's own FunctionCache reader: an index
    left by other sources reads as empty)."""
    import importlib

    fit = est.fit
    module = fit.partition(":")[0] if isinstance(fit, str) else getattr(fit, "__module__", "")
    try:
        kernels = importlib.import_module(module + "_kernels")
    except ImportError:
        return True
    caches = [getattr(v, "_cache", None) for v in vars(kernels).values()
              if getattr(getattr(v, "py_func", None), "__module__", None) == kernels.__name__]
    files = [getattr(c, "_cache_file", None) for c in caches]
    files = [f for f in files if f is not None and hasattr(f, "_load_index")]
    if not files:
        return True
    return any(f._load_index() for f in files)


__all__ = ["as_photons", "compile_apart", "reconstruct", "resolve_model", "warm_up"]
