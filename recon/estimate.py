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
                progress: Callable[[int, int], None] | None = None, neighbours: bool = True,
                spreads: bool = True, dispersion: bool | dict = True) -> DepthMaps:
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
    RMS and its source). ``spreads`` False: the decision without the uncertainty's spreads (each
    depth's uncertainty the estimator's own, as the record says), for a caller that writes no map.
    ``dispersion`` False: ml's uncertainties are not scaled by the pulse model's dispersion here
    (``recon.detect.with_dispersion``; a block of a frame leaves it to the frame's), nor lmf's
    test's spreads tempered by it; a dict: the frame's, by which lmf's are tempered
    (``recon.detect.TEMPERED_METHODS``, measured before the test).
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
    _wait_apart(settings.method)        # its kernels compiling in another process: load them
    # the one place every estimator's maps pass: is there a return, and how sure is each depth
    from spdepth.recon.detect import decide_maps
    from spdepth.recon.pixelwise import binned_once

    with binned_once():                 # the test reads the detections the estimator binned
        maps = est.run(store, settings, b, kern, notes, progress)
        _wait_apart(DECIDE)
        return decide_maps(store, settings, maps, neighbours=neighbours, spreads=spreads, dispersion=dispersion)


def as_photons(counts: CountStore) -> PhotonStore:
    """The photon list of ``counts`` for what takes photons only (an estimator without the
    ``counts`` capability, the pulse measured from the data): exact for whole counts, running
    totals rounded for pile-up-corrected ones (:meth:`CountStore.to_photons`)."""
    return counts.to_photons(round_counts=not counts.is_whole())


def warm_up(settings: ReconSettings, decide: bool = True, estimator: bool = True, spreads: bool = True) -> None:
    """Load (or, on a cold numba cache, compile) the kernels that ``settings``' estimator runs, on
    one made-up pixel of four detections, so that a later call on real data does not wait for them
    (a new process loads each kernel from the cache on its first call). Without a binning (a file's
    comes from its data) a made-up one of 64 bins serves: the kernels' code does not depend on it.
    Only the method and the number of surfaces choose kernels; results are discarded. ``decide``:
    also the return test's (:mod:`recon.detect`, which every reconstruction runs, with the
    neighbours' support); False: the estimator's alone. ``estimator`` False: the return test's
    alone (what :func:`compile_apart` compiles beside an estimator compiled here). With
    ``estimator``, settings that give no pulse also load what measures it (:func:`recon.irf.warm_up`).
    ``spreads`` False: not the test's spreads either (a reconstruction with ``spreads`` False never
    runs their kernel, :func:`recon.detect.detect_kernel`).
    Beside a process of :func:`compile_apart` compiling the return test, each of the test's kernels
    is compiled by the one of the two that claims it first (:func:`_claim`) and loaded by the other."""
    if estimator and given_pulse(settings) is None:
        from spdepth.recon.irf import warm_up as warm_pulse_estimate

        warm_pulse_estimate()            # the pulse is measured from the data before the estimator runs
    b = settings.binning
    if b is None:
        b = Binning(1e-12, 0.0, 64.0, 1.0)
    times = b.window_start + b.bin_width * (np.arange(4) + 0.5 * b.n_bins)
    one = PhotonStore(times.astype(np.float64), np.array([0, times.size]), (1, 1), b.time_unit_s)
    pulse = settings.pulse_rms_s
    if pulse is None and settings.irf is None:
        pulse = 3 * b.bin_width_s          # any width: only the kernels' loading matters
    settings = dataclasses.replace(settings, binning=b, pulse_rms_s=pulse)
    if estimator:
        # the estimator's kernels first: while a second process compiles the test's (compile_apart),
        # this one compiles these instead of waiting for it (the cold mannequin recon waited 17 s
        # for the test, then compiled uos for 6)
        _wait_apart(settings.method)
        bb, kern, notes = resolve_model(one, settings)
        estimators.for_settings(settings).run(one, settings, bb, kern, notes)
    if not decide:
        return
    steps = _test_steps(one, settings, spreads)
    # the process compiling the test apart (compile_apart) takes its kernels in order (ml's search
    # first, the largest), the one that started it, its estimator done, the test itself next (the
    # second largest) and then the rest from the end: each compiles those it claims first. (From
    # the end alone, the cold mannequin recon's two processes ended their compiles at 12.5 and 15.0 s:
    # the other had taken the test after the search.)
    apart = isinstance(_CLAIMS, str)
    left = []
    mine = [st for st in steps if st[0] == "test"] + [st for st in reversed(steps) if st[0] != "test"]
    for name, call in steps if apart else mine:
        if _claim(name):
            call()
        else:
            left.append(call)
    _wait_apart(DECIDE)
    if estimator:
        reconstruct(one, settings, spreads=spreads)     # its maps through the test, as a reconstruction runs them
    if apart:
        # a process compiling for the one that started it loads nothing it did not compile: a kernel
        # the other had claimed and not finished would be compiled here again (the cold mannequin
        # recon's neighbours' regions twice, 0.8 s)
        return
    for call in left:                   # load what the other process compiled
        call()


def _test_steps(one: PhotonStore, settings: ReconSettings,
                spreads: bool = True) -> list[tuple[str, Callable[[], object]]]:
    """The return test's kernels (:mod:`recon.detect`) as (name, call) in the order a
    reconstruction first runs them, each call running one kernel on the made-up pixel ``one`` as
    :func:`recon.detect.decide_maps` calls it: ml's search, the test given its result, the pulse
    model's dispersion from the likelihood's terms (ml's and lmf's, with the spreads), then the
    neighbours' support, regions and fit there (which run only where a pixel fails). Without the
    search for an estimator that gives its gains (:attr:`recon.estimators.Estimator.gains`), and
    without the test's spreads (``spreads`` False) without the test itself: its kernel computes
    them, the decision alone reads the search's gains."""
    from spdepth.recon.detect import (TEMPERED_METHODS, detect, likelihood_terms, neighbour_regions,
                                      neighbour_support, region_fit, search)
    from spdepth.recon.pixelwise import binned_photons

    bb, kern, _ = resolve_model(one, settings)
    bins, offsets = binned_photons(one, bb, settings.max_photons)
    est = np.full(1, 0.5 * bb.n_bins)
    cand = np.zeros(1, np.int64)
    fa = settings.false_alarm
    steps = [
        ("search", lambda: search(bins, offsets, kern)),
        ("test", lambda: detect(bins, offsets, kern, est, fa, known_gain=np.zeros(1), known_share=np.zeros(1))),
        # the pulse model's dispersion from the likelihood's terms (ml's maps, lmf's before its test),
        # which a reconstruction writing maps measures on its pixels with a depth (a made-up pixel
        # without one never reaches it)
        ("dispersion", lambda: likelihood_terms(bins, np.empty(0), offsets, np.full(1, 4.0), kern,
                                                 np.zeros(1, np.int64), est, np.full(1, 0.5))),
        ("support", lambda: neighbour_support(bins, np.empty(0), offsets, (1, 1), kern, est, cand, fa, 1)),
        ("regions", lambda: neighbour_regions(bins, np.empty(0), offsets, 1, kern, cand, 1, 0.0)),
        ("region fit", lambda: region_fit(bins, np.empty(0), offsets, kern, cand, np.ones((1, bb.n_bins), np.uint8))),
    ]
    unused = set() if spreads else {"test", "dispersion"}
    if settings.several or settings.method not in ("ml",) + TEMPERED_METHODS:
        # measured on one surface's maps from the likelihood's terms (ml's, and lmf's before its
        # test; uos's from its matched filter's, without a kernel of its own)
        unused.add("dispersion")
    if estimators.for_settings(settings).gains:
        unused.add("search")            # the estimator gives the test its statistic (ml)
    return [st for st in steps if st[0] not in unused]


#: What :func:`compile_apart` names the return test's kernels (:mod:`recon.detect`) beside the methods'.
DECIDE = "decide"
#: The processes compiling kernels into numba's cache for this one (:func:`compile_apart`), each with
#: what it compiles (method names, DECIDE): :func:`reconstruct` and :func:`warm_up` wait for one
#: before they need its kernels, so that this process loads them rather than compiling them too.
_APART: list[tuple[subprocess.Popen, frozenset]] = []


def _wait_apart(what: str) -> None:
    """Wait for the processes of :func:`compile_apart` that compile ``what`` (a method, DECIDE)."""
    global _CLAIMS
    for child, covers in list(_APART):
        if what in covers:
            child.wait()
    _APART[:] = [(c, w) for c, w in _APART if c.poll() is None]
    claims = _CLAIMS                    # once: a thread of the demo's compiles may be here too
    if hasattr(claims, "cleanup") and not any(DECIDE in w for _, w in _APART):
        claims.cleanup()                # its owner: no process compiles the test beside this one any more
        _CLAIMS = None


#: The folder where this process and the one compiling the return test beside it (compile_apart)
#: claim its kernels (:func:`_claim`), while there is one: in the process that started it the
#: ``tempfile.TemporaryDirectory`` it owns (removed once the child is done), in the child its path.
_CLAIMS = None


def _claim(name: str) -> bool:
    """Whether this process compiles the return test's kernel ``name`` now: True unless the other
    process compiling the test (:func:`compile_apart`) claimed it first (an empty file created
    once, by whichever comes first; without such a process, always)."""
    import os

    folder = _CLAIMS if isinstance(_CLAIMS, str) else getattr(_CLAIMS, "name", None)
    if folder is None:
        return True
    try:
        os.close(os.open(os.path.join(folder, name), os.O_CREAT | os.O_EXCL | os.O_WRONLY))
    except FileExistsError:
        return False
    except OSError:
        return True                     # the folder is gone: the other process is done
    return True


def compile_apart(settings: list[ReconSettings], decide: bool = False,
                  estimator: bool = True, spreads: bool = True) -> subprocess.Popen | None:
    """The first run after an install: compile the kernels of each of ``settings`` (as
    :func:`warm_up` with the same ``decide``, ``estimator`` and ``spreads``: the estimator's, and
    with ``decide`` the return test's) into numba's cache in a new interpreter, started now, and return it;
    :func:`reconstruct` and :func:`warm_up` here wait for it before they need those kernels, and
    then load them from the cache (``wait()`` on it waits for all). None when each is in the cache
    already (or its kernels are not found: then its first call compiles it here, as without
    this). Numba compiles one function at a time in a process (one lock for every thread), so only
    another process puts a second core to compiling while this one compiles or runs other kernels.
    The child inherits the environment (NUMBA_CACHE_DIR, the path)."""
    import json
    import sys

    todo, covers = [], set()
    # what a process started earlier still compiles is not started again (the demo's, before the
    # session's live reconstruction asks for the same)
    running = set().union(*(w for c, w in _APART if c.poll() is None))
    test_cold = decide and DECIDE not in running and not _test_cached(spreads)
    for s in settings:
        est_cold = estimator and s.method not in running and not _kernels_cached(estimators.for_settings(s))
        if est_cold or test_cold:
            todo.append({"settings": s.to_dict(), "estimator": est_cold, "decide": test_cold, "spreads": spreads})
            covers |= {s.method} if est_cold else set()
            covers |= {DECIDE} if test_cold else set()
            test_cold = False               # the first one compiles the test for all
    if not todo:
        return None
    global _CLAIMS
    claims = ""
    if DECIDE in covers:
        if _CLAIMS is None:
            import tempfile

            _CLAIMS = tempfile.TemporaryDirectory(prefix="spdepth-compile-")
        claims = _CLAIMS.name
    code = ("import json, sys\nfrom spdepth.recon import estimate\n"
            "from spdepth.recon.model import ReconSettings\n"
            "estimate._CLAIMS = sys.argv[2] or None\n"
            "for d in json.loads(sys.argv[1]):\n"
            "    estimate.warm_up(ReconSettings.from_dict(d['settings']), decide=d['decide'], "
            "estimator=d['estimator'], spreads=d['spreads'])\n")
    child = subprocess.Popen([sys.executable, "-c", code, json.dumps(todo), claims],
                             stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    _APART.append((child, frozenset(covers)))
    return child


def kernels_cached(settings: ReconSettings, decide: bool = False, spreads: bool = True) -> bool:
    """Whether numba's cache holds the kernels of ``settings``' estimator (and, with ``decide``,
    the return test's, with ``spreads`` its spreads' too), as :func:`compile_apart` judges them."""
    return _kernels_cached(estimators.for_settings(settings)) and (not decide or _test_cached(spreads))


def _test_cached(spreads: bool) -> bool:
    """Whether numba's cache holds the return test's kernels, with ``spreads`` the one of its
    spreads too (:func:`recon.detect.detect_kernel`, which a run without them leaves uncompiled)."""
    if not module_cached("spdepth.recon.detect"):
        return False
    from spdepth.recon.detect import detect_kernel

    return not spreads or _any_cached([detect_kernel])


def _kernels_cached(est) -> bool:
    """Whether numba's cache holds compiled code of any kernel of ``est``'s kernel module (the fit's
    module with ``_kernels`` after it, as lmf, uos and ml have; True when there is none)."""
    fit = est.fit
    module = fit.partition(":")[0] if isinstance(fit, str) else getattr(fit, "__module__", "")
    return module_cached(module + "_kernels")


def module_cached(module: str) -> bool:
    """Whether numba's cache holds compiled code of any kernel of ``module`` (True when it has none
    or cannot be imported), read from the cache's index files without loading any code (numba's own
    FunctionCache reader: an index left by other sources reads as empty)."""
    import importlib

    try:
        kernels = importlib.import_module(module)
    except ImportError:
        return True
    return _any_cached([v for v in vars(kernels).values()
                        if getattr(getattr(v, "py_func", None), "__module__", None) == kernels.__name__])


def _any_cached(dispatchers: list) -> bool:
    """Whether numba's cache holds compiled code of any of ``dispatchers`` (True when none has a
    cache), from their index files."""
    files = [getattr(getattr(d, "_cache", None), "_cache_file", None) for d in dispatchers]
    files = [f for f in files if f is not None and hasattr(f, "_load_index")]
    if not files:
        return True
    return any(f._load_index() for f in files)


__all__ = ["DECIDE", "as_photons", "compile_apart", "kernels_cached", "module_cached", "reconstruct", "resolve_model",
           "warm_up"]
