"""The estimator registry: every estimator is a plugin module here that declares what it can do
(:class:`Estimator`) when imported and brings its numba kernels only when it runs, so reading the
registry (``spdepth --help``, the window's list) loads no kernel and not numba.

Consumers ask capabilities, never names: ``get(name).pixelwise`` (live batches, Dask blocks),
``.live`` and ``.live_stand_in`` (what a live scan shows), ``.summary`` (help and tooltips),
``.several`` (which fit runs with several surfaces per pixel). A new estimator is one module that
calls :func:`register`; ``spdepth recon --method``, a live session and the window's list follow.

Built-ins: :mod:`.lmf`, :mod:`.uos`, :mod:`.ml` (one surface, pixel by pixel), :mod:`.spatial`
(the neighbours' help) and :mod:`.surfaces` (the K-surface fit that lmf, uos and ml hand several
surfaces to, and spatial its neighbourhood variant). ``spdepth.recon`` imports them (its
``__init__``), so they are registered before any of recon is used; this module imports none of
them, so everything in recon may ask it (``recon.model`` validates a method here).
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass, field
from typing import Callable

from spdepth.recon.errors import InputError

#: ``fit(store, settings, binning, kernel, notes, progress) -> DepthMaps``: the maps of ``store`` on
#: a resolved model (``recon.resolve.resolve_model``: binning, pulse kernel and notes saying how
#: they were found), calling ``progress(done, total)`` as it goes when not None.
Fit = Callable


@dataclass(frozen=True)
class Estimator:
    """What an estimator is and can do; registered once, read by every front end.

    name:          the ``--method`` value.
    summary:       one line for ``--help`` and the window's tooltip.
    fit:           :data:`Fit`, or ``"module:function"`` imported on the first run (so that
                   declaring the estimator loads none of its kernels).
    pixelwise:     each pixel's maps depend on its own detections only: a live scan reconstructs
                   batches of final pixels with it, a recording can be cut into blocks.
    several:       the registered fit that runs instead when several surfaces per pixel are asked
                   (``reflectors`` K > 1 or "auto"); None: this estimator fits one surface only
                   (several are refused), or it is itself a several-surface fit (``max_surfaces``).
    max_surfaces:  most surfaces per pixel its own fit returns (1, or 8 for a K-surface fit).
    background:    estimates the background (False: its background map is NaN).
    live:          runs on a live scan's batches; else the pixelwise ``live_stand_in`` draws the
                   live maps and this one runs once on the whole final frame.
    method:        offered as a ``--method`` (False: reached only through another's ``several``).
    counts:        its fit takes a ``recon.counts.CountStore`` as (bin, count) pairs
                   (``recon.pixelwise.fit_pixels``, ``store_pairs``); "whole": as pairs of whole
                   counts, a pile-up-corrected store's rounded first (``CountStore.rounded``, as
                   for its photon list); False: it is handed the equivalent photon list.
    gains:         its maps carry the return test's statistic at every pixel
                   (``DepthMaps.gain_nats``: ml's search), which the test takes instead of searching
                   again; a first run then does not compile the test's search for it
                   (``recon.estimate.warm_up``).
    """

    name: str
    summary: str
    fit: Fit | str = field(repr=False)
    pixelwise: bool = True
    several: str | None = None
    max_surfaces: int = 1
    background: bool = True
    live: bool = True
    live_stand_in: str | None = None
    method: bool = True
    counts: bool | str = False
    gains: bool = False

    def run(self, store, settings, binning, kernel, notes: dict, progress=None):
        """:data:`Fit` of this estimator, its module imported on the first call."""
        fit = self.fit
        if isinstance(fit, str):
            module, _, name = fit.partition(":")
            fit = getattr(importlib.import_module(module), name)
        return fit(store, settings, binning, kernel, notes, progress)


_REGISTRY: dict[str, Estimator] = {}


def register(estimator: Estimator, replace: bool = False) -> Estimator:
    """Add ``estimator`` (a name taken already: ValueError unless ``replace``); returns it."""
    if not isinstance(estimator, Estimator):
        raise TypeError(f"register takes an Estimator, got {type(estimator).__name__}")
    name = estimator.name
    if not name or not isinstance(name, str) or name != name.strip() or " " in name:
        raise ValueError(f"an estimator's name is one word, got {name!r}")
    if name in _REGISTRY and not replace:
        raise ValueError(f"an estimator named {name!r} is registered already")
    if not estimator.live and (estimator.live_stand_in is None or estimator.live_stand_in == name):
        raise ValueError(f"{name}: an estimator that does not run live names a pixelwise live_stand_in")
    _REGISTRY[name] = estimator
    return estimator


def unregister(name: str) -> None:
    """Remove the estimator registered as ``name`` (a test's own, once it is done)."""
    _REGISTRY.pop(name, None)


def names(pixelwise: bool | None = None) -> tuple[str, ...]:
    """The ``--method`` names in registration order (only the pixelwise ones, or only the others,
    when ``pixelwise`` is given)."""
    return tuple(n for n, e in _REGISTRY.items()
                 if e.method and (pixelwise is None or e.pixelwise == pixelwise))


def get(name: str, fits: bool = False) -> Estimator:
    """The method registered as ``name`` (with ``fits``, also a fit that is no method of its own,
    such as "surfaces"); InputError naming the methods otherwise."""
    est = _REGISTRY.get(name) if isinstance(name, str) else None
    if est is None or not (est.method or fits):
        raise InputError(f"method must be one of {', '.join(names())}, got {name!r}")
    return est


def for_settings(settings) -> Estimator:
    """The estimator that runs for ``settings`` (``method``, and its ``several`` fit when
    ``settings.several``); InputError when the method fits one surface and several are asked."""
    est = get(settings.method)
    if settings.several and est.max_surfaces == 1:
        if est.several is None:
            raise InputError(f"method {est.name} fits one surface per pixel; give reflectors=1")
        est = get(est.several, fits=True)
    return est


def summaries() -> str:
    """``name: summary`` of every method, then which fit each runs with several surfaces: the text
    of ``--method``'s help and of the window's tooltip."""
    lines = [f"{n}: {get(n).summary}" for n in names()]
    fits: dict[str, list[str]] = {}
    for n in names():
        e = get(n)
        if e.max_surfaces == 1 and e.several is not None:
            fits.setdefault(e.several, []).append(n)
    several = [f"{_and(methods)} {'all run' if len(methods) > 1 else 'runs'} {get(fit, fits=True).summary}"
               for fit, methods in fits.items()]
    if several:
        lines.append("with several surfaces (--reflectors K > 1 or auto): " + "; ".join(several))
    return "; ".join(lines)


def _and(words: list[str]) -> str:
    return words[0] if len(words) == 1 else f"{', '.join(words[:-1])} and {words[-1]}"


def live_note() -> str:
    """What a live scan shows for the methods that do not run live (their stand-ins), for help."""
    parts = [f"{n} shows {get(n).live_stand_in} while the scan runs and replaces it at the end"
             for n in names() if not get(n).live]
    return "; ".join(parts)


__all__ = ["Estimator", "Fit", "for_settings", "get", "live_note", "names", "register", "summaries",
           "unregister"]
