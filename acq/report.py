"""What a person looks at after a reconstruction: PNG map sheets and a progress bar on stderr.

Used by ``spdepth recon`` and by any other command that produces maps (demo, replay). Rendering
uses matplotlib's Agg canvas directly (no pyplot), so it never needs a display and never touches
global figure state.
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Sequence, TextIO

import numpy as np

from spdepth.recon.maps import C_M_PER_S

#: colour for pixels without an estimate (NaN): a mid grey, distinct from every colour of the maps
NAN_COLOUR = "#9a9a9a"

#: the panels of a standard sheet: (attribute of the maps object, title, unit, colour map, limits).
#: limits "dense": the shortest interval holding 75% of the pixels, so a scene in front of a far
#: wall shows its own relief instead of spending the colours on the gap to the wall;
#: "percentile": the 2nd to 98th percentile.
DEFAULT_PANELS: tuple[tuple[str, str, str, str, str], ...] = (
    ("depth_m", "depth", "m", "turbo", "dense"),
    ("background", "background", "detections per bin", "magma", "percentile"),
    ("photons", "detections used", "photons per pixel", "viridis", "percentile"),
)


def robust_limits(values: np.ndarray, lower_pct: float = 2.0, upper_pct: float = 98.0) -> tuple[float, float]:
    """Colour limits from percentiles of the finite values, so a few outliers (a stray detection
    placing one pixel kilometres away) do not wash out the map. Returns ``(vmin, vmax)`` with
    ``vmin < vmax`` even for constant or all-NaN maps."""
    finite = np.asarray(values, dtype=np.float64)
    finite = finite[np.isfinite(finite)]
    if finite.size == 0:
        return 0.0, 1.0
    lo, hi = np.percentile(finite, [lower_pct, upper_pct])
    if not hi > lo:
        # a constant map (e.g. background 0 everywhere): put the value at the bottom of the scale
        span = abs(lo) * 1e-3 or 1.0
        lo, hi = (lo, lo + span) if lo == 0 else (lo - span, hi + span)
    return float(lo), float(hi)


def dense_limits(values: np.ndarray, coverage: float = 0.75) -> tuple[float, float]:
    """Colour limits: the shortest interval that holds ``coverage`` of the finite values (the
    densest part of the map). Falls back to :func:`robust_limits` when that interval is empty."""
    finite = np.sort(np.asarray(values, dtype=np.float64)[np.isfinite(values)], axis=None)
    k = int(np.ceil(coverage * finite.size))
    if finite.size < 2 or k < 2:
        return robust_limits(values)
    widths = finite[k - 1:] - finite[:finite.size - k + 1]
    i = int(np.argmin(widths))
    lo, hi = float(finite[i]), float(finite[i + k - 1])
    return (lo, hi) if hi > lo else robust_limits(values)


def render_maps_png(path: str | Path, maps, *, title: str | None = None,
                    panels: Sequence[tuple[str, str, str, str, str]] = DEFAULT_PANELS,
                    dpi: int = 110, irf: tuple[np.ndarray, np.ndarray, str] | None = None) -> Path:
    """Write a PNG with one panel per map: image, colour bar with unit, title.

    maps:   any object with the panel attributes as 2-D arrays of equal shape (``DepthMaps`` has
            ``depth_m``, ``background``, ``photons``); a missing attribute raises AttributeError.
            (K, H, W) maps of K returns per pixel: one panel per return for the first panel's
            map (depth: "surface 1", "surface 2", ... nearest first), the first return elsewhere.
    irf:    ``(times_s, counts, label)`` of the pulse shape used: an extra panel draws it (log
            counts against ps from its peak).
    panels: ``(attribute, title, unit, colour map, "dense" | "percentile")`` for each panel; values
            beyond the colour limits saturate (the colour bar's pointed ends say so).
    Pixels that are NaN show in NAN_COLOUR, named under the panel when there are any.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    import matplotlib

    path = Path(path)
    # K > 1 returns per pixel come as (K, H, W): the first panel's map (depth) gets one panel per
    # return, the others show the first (nearest) return
    arrays, specs = [], []
    for i, spec in enumerate(panels):
        a = np.asarray(getattr(maps, spec[0]), dtype=np.float64)
        if a.ndim == 3 and i == 0 and a.shape[0] > 1:
            for r in range(a.shape[0]):
                arrays.append(a[r])
                specs.append((spec[0], f"{spec[1]}, surface {r + 1}", *spec[2:]))
            continue
        arrays.append(a[0] if a.ndim == 3 else a)
        specs.append(tuple(spec))
    h, w = arrays[0].shape
    aspect = h / w
    panel_w = 4.2
    n_ax = len(specs) + (irf is not None)
    fig = Figure(figsize=(panel_w * n_ax, panel_w * min(max(aspect, 0.3), 3.0) + 0.9),
                 layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(1, n_ax, squeeze=False)[0]
    if irf is not None:
        _draw_irf(axes[-1], *irf)
    for ax, arr, (attr, name, unit, cmap_name, limits) in zip(axes, arrays, specs):
        cmap = matplotlib.colormaps[cmap_name].with_extremes(bad=NAN_COLOUR)
        vmin, vmax = dense_limits(arr) if limits == "dense" else robust_limits(arr)
        im = ax.imshow(np.ma.masked_invalid(arr), cmap=cmap, vmin=vmin, vmax=vmax,
                       interpolation="nearest", origin="upper")
        ax.set_title(f"{name} ({unit})")
        ax.set_xlabel("column")
        ax.set_ylabel("row")
        finite = arr[np.isfinite(arr)]
        extend = {(False, False): "neither", (True, False): "min", (False, True): "max",
                  (True, True): "both"}[(bool(np.any(finite < vmin)), bool(np.any(finite > vmax)))]
        bar = fig.colorbar(im, ax=ax, shrink=0.85, extend=extend)
        bar.set_label(unit)
        n_nan = int(np.sum(~np.isfinite(arr)))
        if n_nan:
            ax.text(0.0, -0.16 if h >= 8 else -0.3, f"grey: no estimate ({n_nan} px)",
                    transform=ax.transAxes, fontsize=8, color="#444444", va="top")
    if title:
        fig.suptitle(title)
    fig.savefig(path, dpi=dpi)
    return path


class ProgressBar:
    """The one progress bar of every long command (simulate, recon, bench report): tqdm on a
    stream (stderr by default), silent when that stream is not a terminal (tqdm's
    ``disable=None``), so logs and captured stderr of scripted runs hold no ``\\r`` redraws.

    Use it as the ``progress(done, total)`` callback of ``recon.estimate.reconstruct`` or
    ``PhotonWorld.raster``, or step it with ``update(n, note)``; ``close()`` (or ``with``) ends its
    line. ``force`` draws it on any stream (tests); ``max_rate_hz`` caps the redraws.
    """

    def __init__(self, label: str = "", total: int | None = None, *, unit: str = "px",
                 stream: TextIO | None = None, max_rate_hz: float = 10.0,
                 force: bool = False) -> None:
        from tqdm import tqdm

        self._bar = tqdm(total=total, desc=label, unit=unit,
                         file=stream if stream is not None else sys.stderr,
                         disable=False if force else None, mininterval=1.0 / max_rate_hz,
                         dynamic_ncols=True)

    @property
    def enabled(self) -> bool:
        """False when nothing is drawn (not a terminal): callers may skip work done for the bar."""
        return not self._bar.disable

    def __call__(self, done: int, total: int) -> None:
        if self._bar.disable:
            return
        if total != self._bar.total:
            self._bar.total = total
        self._bar.update(done - self._bar.n)

    def update(self, n: int = 1, note: str | None = None) -> None:
        """``n`` more done; ``note`` (what is being worked on) shown after the counts."""
        if self._bar.disable:
            return
        if note is not None:
            self._bar.set_postfix_str(note, refresh=False)
        self._bar.update(n)

    def close(self) -> None:
        """Draw the final state and end the bar's line (once the work is done or given up)."""
        self._bar.close()

    def __enter__(self) -> "ProgressBar":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _draw_irf(ax, times_s, counts, label: str) -> None:
    """The pulse shape on log counts against ps from its peak."""
    t = np.asarray(times_s, dtype=np.float64)
    c = np.asarray(counts, dtype=np.float64)
    c = c / c.max()
    t_ps = (t - t[np.argmax(c)]) * 1e12
    ax.semilogy(t_ps, np.where(c > 0, c, np.nan), color="#3b6ea5")
    ax.set_ylim(max(1e-4, float(np.nanmin(np.where(c > 0, c, np.nan)))), 1.5)
    ax.set_xlabel("ps from the peak")
    ax.set_ylabel("response (peak 1)")
    ax.set_title("pulse shape used")
    ax.text(0.98, 0.97, label, transform=ax.transAxes, fontsize=8, ha="right", va="top")


def render_point_png(path: str | Path, times_s: np.ndarray, *, tof_s: float | None = None,
                     title: str | None = None, bins: int = 200, dpi: int = 110,
                     irf: tuple[np.ndarray, np.ndarray, str] | None = None) -> Path:
    """Write a PNG for a point measurement (one pixel): the histogram of detection times in ns,
    log counts, with the estimated time of flight marked.

    times_s: detection times after the laser sync (s), shape (n,).
    tof_s:   estimated time of flight (s); NaN or None draws no marker.
    irf:     ``(times_s, counts, label)`` of the pulse shape used: drawn in a second panel.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    path = Path(path)
    times_ns = np.asarray(times_s, dtype=np.float64) * 1e9
    fig = Figure(figsize=(7.5 + 4.5 * (irf is not None), 4.2), layout="constrained")
    FigureCanvasAgg(fig)
    if irf is not None:
        ax, ax_irf = fig.subplots(1, 2)
        _draw_irf(ax_irf, *irf)
    else:
        ax = fig.subplots()
    if times_ns.size:
        ax.hist(times_ns, bins=bins, color="#3b6ea5", log=True)
    ax.set_xlabel("time after laser sync (ns)")
    ax.set_ylabel("detections per bin")
    if tof_s is not None and np.isfinite(tof_s):
        ax.axvline(tof_s * 1e9, color="#d62728", linestyle="--",
                   label=f"estimated time of flight {tof_s * 1e9:.3f} ns "
                         f"(depth {tof_s * C_M_PER_S / 2:.3f} m)")
        ax.legend(loc="upper right", fontsize=8)
    ax.set_title(title or f"point measurement: {times_ns.size} detections")
    fig.savefig(path, dpi=dpi)
    return path
