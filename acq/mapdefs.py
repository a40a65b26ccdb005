"""One definition of every map a person looks at: name, unit, colour map and level rule, used by
the PNG sheets (``acq.report``) and the window (``gui.maps``) alike, so both say the same thing.

A map is computed from a :class:`MapInput` (the arrays of ``recon.maps.DepthMaps`` or of a live
session snapshot, plus the bins per window and the target), never from a particular object.

Level rules:

- ``"robust"``: the 1st to 99th percentile of the finite pixels, so a wall and the object in front
  of it both keep their colours (the whole head of the bust is not one colour) and a few stray
  pixels do not flatten the rest;
- ``"zero"``: 0 to the 99th percentile (a count or ratio whose natural floor is 0);
- ``"target"``: 0 to the scan's target (detections kept).

A map whose finite pixels all hold one value is *constant*: it is drawn in one colour without a
colour bar and says its value instead (:func:`constant_value`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from spdepth.recon.maps import C_M_PER_S

ROBUST_PERCENTILES = (1.0, 99.0)
"""Percentiles of the finite pixels that the robust levels span."""
FADE_RGBA = (255, 255, 255, 180)
"""Laid over a surface that background alone could have made (``DepthMaps.weak``): drawn, but
faded, in the PNG sheet and the window alike."""
NAN_COLOUR = "#9a9a9a"
"""Pixels without a value (not measured, incomplete without an estimate, no return): one grey,
on every path, distinct from the ends of every colour map used here."""


@dataclass(frozen=True)
class MapInput:
    """What the maps are made of. Arrays (H, W), or (K, H, W) for K surfaces (depth_m, signal,
    uncertainty_s); NaN where there is no estimate.

    background: expected background detections per bin (``DepthMaps.background``).
    counts:     detections kept per pixel (float; NaN for pixels not measured).
    n_bins:     bins of the detection window (background in the window = background * n_bins).
    target:     detections wanted per pixel (0: none, e.g. a file read whole).
    """

    depth_m: np.ndarray
    background: np.ndarray
    signal: np.ndarray
    uncertainty_s: np.ndarray
    counts: np.ndarray
    n_bins: int
    target: int = 0
    surfaces: np.ndarray | None = None
    """(H, W) surfaces found per pixel when K > 1 surfaces were looked for (None: one)."""
    exposure_s: np.ndarray | None = None
    """(H, W) laser time each pixel's kept detections span, s (NaN: unknown; None: a file
    without one, e.g. a .mat of photon times)."""

    def __post_init__(self) -> None:
        # a pixel with no detection kept has no background estimate (the estimator says 0): grey,
        # not a clean black background
        counts = np.asarray(self.counts, dtype=np.float64)
        bg = np.array(self.background, dtype=np.float64)
        bg[~(counts > 0)] = np.nan
        object.__setattr__(self, "counts", counts)
        object.__setattr__(self, "background", bg)


def first_surface(a: np.ndarray) -> np.ndarray:
    a = np.asarray(a, dtype=np.float64)
    return a[0] if a.ndim == 3 else a


def _background_window(m: MapInput) -> np.ndarray:
    return np.asarray(m.background, dtype=np.float64) * m.n_bins


def _background_rate(m: MapInput) -> np.ndarray | None:
    """Background detections per second over the window, in thousands (kcps): the background in
    the window over the laser time the pixel was observed. Unlike the count per kept set it does
    not depend on how fast the pixel reached its target, so a bright object leaves no
    silhouette in it."""
    if m.exposure_s is None:
        return None
    t = np.asarray(m.exposure_s, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        r = _background_window(m) / t / 1e3
    r[~(t > 0)] = np.nan
    return r


def _sbr(m: MapInput) -> np.ndarray:
    sig = np.asarray(m.signal, dtype=np.float64)
    if sig.ndim == 3:                    # K surfaces: all the signal over the one background
        sig = np.nansum(sig, axis=0)
    bg = _background_window(m)
    with np.errstate(divide="ignore", invalid="ignore"):
        r = 10.0 * np.log10(sig / bg)
    # a pixel whose estimate found no background has an unbounded ratio: +inf, drawn at the top
    # of the scale (``display``); no return or no estimate: no value
    r[~np.isfinite(first_surface(m.depth_m)) | np.isnan(r) | (r == -np.inf)] = np.nan
    return r


@dataclass(frozen=True)
class MapDef:
    """key, title, unit, matplotlib colour map name (pyqtgraph has the same names), level rule
    (``robust`` | ``zero`` | ``target``), ``extract(MapInput) -> array`` ((H, W), or (K, H, W)
    for per-surface maps), and a tooltip-sized description."""

    key: str
    title: str
    unit: str
    cmap: str
    levels: str
    extract: Callable[[MapInput], np.ndarray]
    about: str = ""
    per_surface: bool = False
    optional: bool = False
    """Drawn only when ``extract`` gives an array (None: the maps do not have it)."""
    replaces: str | None = None
    """Key of the map this one is drawn instead of, in the same place, when it has data (the
    background rate of a scan replaces the background count of a file's maps)."""
    from_background: bool = False
    """Drawn from the estimator's background: without a value where the estimator estimates none
    (``recon.estimators.Estimator.background``: lmf)."""


MAP_DEFS: tuple[MapDef, ...] = (
    MapDef("depth", "Depth", "m", "turbo", "robust",
           lambda m: np.asarray(m.depth_m, dtype=np.float64),
           "range along the beam, c * time of flight / 2", per_surface=True),
    MapDef("uncertainty", "Depth uncertainty (1σ)", "cm", "plasma", "zero",
           lambda m: np.asarray(m.uncertainty_s, dtype=np.float64) * (C_M_PER_S / 2) * 100.0,
           "standard deviation of the depth, from the Poisson likelihood", per_surface=True),
    MapDef("background", "Background", "detections in window", "magma", "zero",
           _background_window,
           "background detections among those kept, over the whole detection window", from_background=True),
    MapDef("background_rate", "Background rate", "kcps", "magma", "zero", _background_rate,
           "background detections per second over the detection window (thousands), from the "
           "laser time each pixel was observed: a flux, independent of the target",
           optional=True, replaces="background", from_background=True),
    MapDef("sbr", "Signal / background", "dB", "viridis", "robust", _sbr,
           "10 log10 of the detections attributed to the return(s) over the background "
           "detections in the window; no background found: above the scale", from_background=True),
    MapDef("counts", "Detections kept", "per pixel", "cividis", "target",
           lambda m: np.asarray(m.counts, dtype=np.float64),
           "in-window detections used by the estimate (at most the target)"),
    MapDef("surfaces", "Surfaces found", "per pixel", "viridis", "zero",
           lambda m: None if m.surfaces is None else np.asarray(m.surfaces, dtype=np.float64),
           "returns found per pixel when several surfaces were looked for (--reflectors K)",
           optional=True),
)
"""Every map, in display order."""

MAPS_BY_KEY = {d.key: d for d in MAP_DEFS}

PANEL_DEFS: tuple[MapDef, ...] = tuple(d for d in MAP_DEFS if d.replaces is None)
"""The places a sheet or window has, in display order (a map that replaces another takes its
place: :func:`resolve`)."""


def resolve(place: MapDef, m: MapInput) -> tuple[MapDef, np.ndarray | None]:
    """What is drawn at ``place`` (one of ``PANEL_DEFS``) for ``m``: the map that replaces it when
    that one has data, else its own; and the data (None: an optional map ``m`` does not have)."""
    for d in MAP_DEFS:
        if d.replaces == place.key:
            got = d.extract(m)
            if got is not None:
                return d, got
    return place, place.extract(m)


def display(data: np.ndarray, levels: tuple[float, float] | None) -> np.ndarray:
    """``data`` ready to draw: +inf (a ratio over no background) at the top of the levels, so
    that it is not mistaken for "no value" (NaN, grey)."""
    a = np.asarray(data, dtype=np.float64)
    if levels is not None and np.isposinf(a).any():
        a = np.where(np.isposinf(a), levels[1], a)
    return a


#: a map of whole numbers spanning at most this many is drawn with a tick per value (the PNG: one
#: colour per value too)
DISCRETE_MAX = 10


def whole_numbers(data: np.ndarray) -> bool:
    """The map's finite values are all whole numbers (counts), and it has some."""
    v = np.asarray(data, dtype=np.float64)
    v = v[np.isfinite(v)]
    return v.size > 0 and bool(np.all(v == np.round(v)))


def constant_value(data: np.ndarray) -> float | None:
    """The one value of a map whose finite pixels all hold it (None: not constant, or empty)."""
    v = np.asarray(data, dtype=np.float64)
    v = v[np.isfinite(v)]
    if v.size == 0:
        return None
    lo, hi = float(v.min()), float(v.max())
    return lo if lo == hi else None


def not_estimated(d: MapDef, method: str | None) -> str | None:
    """What a map says in place of values it cannot have: "not estimated by lmf" for a map drawn
    from the background of an estimator that estimates none (``Estimator.background``); else None."""
    from spdepth.recon import estimators

    if not d.from_background or method not in estimators.names():
        return None
    return None if estimators.get(method).background else f"not estimated by {method}"


def constant_caption(d: MapDef, data: np.ndarray) -> str | None:
    """What a constant map says instead of a colour bar, true whatever the scan's state: "15 in
    every pixel" when every pixel holds the value, "15 in 312 of 1,024 pixels" when the others
    have none (not measured yet, left by a pause or an abort); None when the map is not constant.
    The unit is left out where it is "per pixel" (the caption says where)."""
    const = constant_value(data)
    if const is None:
        return None
    v = np.asarray(data, dtype=np.float64)
    n, total = int(np.count_nonzero(np.isfinite(v))), int(v.size)
    value = f"{const:g}" if d.unit == "per pixel" else f"{const:g} {d.unit}"
    return f"{value} in every pixel" if n == total else f"{value} in {n:,} of {total:,} pixels"


def levels_for(d: MapDef, data: np.ndarray, target: int = 0, weak: np.ndarray | None = None
               ) -> tuple[float, float] | None:
    """Colour levels of ``data`` by the map's rule; None when it has no finite pixel. Always
    ``lo < hi``. ``weak`` (like data, bool): surfaces background alone could have made, left out of
    the levels so that confident surfaces set them (all of them when no other pixel has a value)."""
    a = np.asarray(data, dtype=np.float64)
    v = a[np.isfinite(a)]
    if weak is not None and np.shape(weak) == a.shape:
        strong = a[np.isfinite(a) & ~np.asarray(weak, bool)]
        if strong.size:
            v = strong
    if d.levels == "target" and target > 0:
        return 0.0, float(target)
    if v.size == 0:
        return None
    p_lo, p_hi = ROBUST_PERCENTILES
    if d.levels == "robust":
        lo, hi = (np.percentile(v, (p_lo, p_hi)) if v.size >= 20 else (v.min(), v.max()))
    else:                   # "zero", or "target" without a target
        lo, hi = 0.0, (np.percentile(v, p_hi) if v.size >= 20 else v.max())
    lo, hi = float(lo), float(hi)
    if not hi > lo:
        pad = max(abs(lo) * 0.05, 1e-6)
        lo, hi = (lo, lo + 2 * pad) if d.levels != "robust" else (lo - pad, hi + pad)
    return lo, hi


def widen(old: tuple[float, float] | None, new: tuple[float, float] | None):
    """Levels during a scan: they only ever widen to take in what arrives (never freeze on the
    first rows, never jump back and forth)."""
    if old is None:
        return new
    if new is None:
        return old
    return min(old[0], new[0]), max(old[1], new[1])


def map_input_from_maps(maps, *, n_bins: int | None = None, target: int | None = None,
                        counts=None, exposure_s=None) -> MapInput:
    """A ``recon.maps.DepthMaps`` (settings hold the binning and max_photons) as a MapInput;
    ``counts`` replaces the detections used (e.g. a session's kept counts with NaN where not
    measured); ``exposure_s``: a scan's observed laser time per pixel (the background rate)."""
    s = getattr(maps, "settings", None) or {}
    if n_bins is None:
        b = s.get("binning") or {}
        n_bins = int(np.ceil((b["window_stop"] - b["window_start"]) / b["bin_width"] - 1e-9)) \
            if b else 1
    if target is None:
        target = int(s.get("max_photons") or 0)
    return MapInput(depth_m=maps.depth_m, background=maps.background, signal=maps.signal,
                    uncertainty_s=maps.uncertainty_s,
                    counts=np.asarray(maps.photons if counts is None else counts, dtype=np.float64),
                    n_bins=max(1, int(n_bins)), target=target, surfaces=surfaces_of(maps),
                    exposure_s=exposure_s)


def surfaces_of(maps) -> np.ndarray | None:
    """(H, W) surfaces found per pixel: the maps' own ``surfaces`` map when they have one, else
    counted from (K, H, W) depth maps; None for one surface per pixel."""
    depth = np.asarray(maps.depth_m)
    if depth.ndim != 3 or depth.shape[0] < 2:
        return None                       # one surface looked for: nothing to count
    got = getattr(maps, "surfaces", None)
    return np.asarray(got) if got is not None else np.isfinite(depth).sum(axis=0)


__all__ = ["MapDef", "MapInput", "MAP_DEFS", "MAPS_BY_KEY", "PANEL_DEFS", "resolve", "NAN_COLOUR", "FADE_RGBA", "ROBUST_PERCENTILES",
           "constant_value", "constant_caption", "display", "levels_for", "widen", "map_input_from_maps", "first_surface",
           "surfaces_of", "DISCRETE_MAX", "whole_numbers"]
