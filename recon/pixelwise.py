"""What every one-surface pixelwise estimator shares (lmf, uos, ml, and any plugin that fits each
pixel on its own): window, first ``max_photons`` and binning in one compiled pass, the estimator's
kernel over chunks of pixels (:func:`fit_pixels`), and the maps (:func:`pixel_maps`).

An estimator's module gives ``fit_chunk(bins, offsets, max_n, out)``, which fills the
:class:`PixelFit` rows ``out`` of the pixels of one chunk (CSR bins of their in-window detections,
at most ``max_n`` a pixel), and says how its result reads (``shift_step``: its grid; ``signal``:
what counts as signal). Imports only the forward model, the photon store and the maps.
"""

from __future__ import annotations

import contextlib
import threading
from concurrent.futures import ThreadPoolExecutor, wait
from typing import Callable, NamedTuple

import numpy as np

from spdepth.recon.errors import InputError
from spdepth.recon.maps import C_M_PER_S, DepthMaps, PixelFlag
from spdepth.recon.model import FINE_STEPS, Binning, PulseKernel, ReconSettings
from spdepth.recon.photons import PhotonStore
from spdepth.recon.threadpool import shared_pool, slices, threads

#: Pixels per kernel call; progress is reported between chunks.
CHUNK_PIXELS = 16384


class PixelFit(NamedTuple):
    """Per-pixel results of a one-surface fit, (P,) each; a chunk's rows are views (:meth:`rows`).

    shift:  float64, bins (fractional allowed), NaN: no return.
    amp:    float64, the return's amplitude on the unit-area pulse (expected signal detections of an
            unclipped pulse; for an estimator without a signal model, its detections).
    bg:     float64, background per bin.
    var:    float64, the shift's variance (bins^2) as the estimator finds it (NaN: degenerate).
    n_used: int64, detections used.
    iters:  int32, iterations (1 for a direct fit).
    conv:   bool, converged.
    gain:   float64, the log-likelihood gain of the best integer shift over background alone (nats),
            where the estimator computes the statistic of recon.detect's return test (ml); NaN:
            the test computes it.
    """

    shift: np.ndarray
    amp: np.ndarray
    bg: np.ndarray
    var: np.ndarray
    n_used: np.ndarray
    iters: np.ndarray
    conv: np.ndarray
    gain: np.ndarray

    @classmethod
    def empty(cls, npix: int) -> "PixelFit":
        return cls(np.full(npix, np.nan), np.zeros(npix), np.zeros(npix), np.full(npix, np.nan),
                   np.zeros(npix, np.int64), np.ones(npix, np.int32), np.ones(npix, np.bool_), np.full(npix, np.nan))

    def rows(self, p0: int, p1: int) -> "PixelFit":
        return PixelFit(*(a[p0:p1] for a in self))


#: This thread's last :func:`binned_photons` while in :func:`binned_once` (else None).
_BINNED = threading.local()


@contextlib.contextmanager
def binned_once():
    """Within, on this thread, :func:`binned_photons` of the store, binning and ``max_photons`` it
    was last called with returns the same arrays again (read-only by every caller): a
    reconstruction bins its detections for the estimator and again for the return test
    (``recon.detect.decide_maps``), 0.05-0.08 s of a 512x512 PTU's. Kept no longer than the block."""
    outer = getattr(_BINNED, "last", False)
    if outer is False:
        _BINNED.last = None
    try:
        yield
    finally:
        if outer is False:
            del _BINNED.last


def binned_photons(store: PhotonStore, b: Binning, max_photons: int | None) -> tuple[np.ndarray, np.ndarray]:
    """The in-window detections of every pixel (the first ``max_photons`` of each, None: all) as
    bin indices, grouped by pixel: (bins int64, offsets int64 (P + 1,)). One compiled pass (the
    NumPy route of first_in_window + bin_index cost as much as the lmf kernel itself)."""
    last = getattr(_BINNED, "last", False)
    key = (b.window_start, b.window_stop, b.bin_width, b.n_bins, max_photons)
    if last and last[0] is store.times and last[1] is store.offsets and last[2] == key:
        return last[3]
    out = _binned_photons(store, b, max_photons)
    if last is not False:         # the arrays themselves are held, so their identity is not reused
        _BINNED.last = (store.times, store.offsets, key, out)
    return out


#: Detections from which :func:`binned_photons` bins on the fit's threads, in parts of about as many
#: detections each (fewer: one call, as a live batch's).
PARALLEL_BINNING = 1 << 20


def _binned_photons(store: PhotonStore, b: Binning, max_photons: int | None) -> tuple[np.ndarray, np.ndarray]:
    times = np.ascontiguousarray(store.times, dtype=np.float64)
    offsets = np.ascontiguousarray(store.offsets, dtype=np.int64)
    bins = np.empty(times.size, np.int64)
    out_offsets = np.empty(offsets.size, np.int64)
    window = (b.window_start, b.window_stop, b.bin_width, b.n_bins, -1 if max_photons is None else int(max_photons))
    workers = threads()
    pool = shared_pool(workers)
    parts = workers if pool is not None and times.size >= PARALLEL_BINNING else 1
    n_kept = bin_in_parts(times, offsets, window, bins, out_offsets, parts, pool)
    return bins[:n_kept], out_offsets


def bin_in_parts(times: np.ndarray, offsets: np.ndarray, window: tuple, bins: np.ndarray,
                 out_offsets: np.ndarray, parts: int, pool: ThreadPoolExecutor | None) -> int:
    """``recon.kernels.window_bins`` over the pixels in ``parts`` runs of about as many detections
    each, side by side on ``pool`` (its kernel is nogil): each run bins its own detections in
    place (it keeps at most as many as it reads, so the runs' writes never meet), then the runs
    are moved down behind each other and their offsets shifted; the bins are the same as one call
    gives (the 512x512 PTU's 7.9 M detections: 0.048 s in one call on the reconstruction's path).
    ``window``: (start, stop, width, n_bins, max_photons or -1). Returns the detections kept."""
    from spdepth.recon.kernels import window_bins

    npix = offsets.size - 1
    if parts <= 1 or pool is None or npix < 2:
        return int(window_bins(times, offsets, *window, bins, out_offsets))
    cuts = np.searchsorted(offsets, np.linspace(0, times.size, parts + 1)[1:-1])
    edges = [0, *sorted({int(c) for c in cuts if 0 < c < npix}), npix]
    runs = [(a, c, np.empty(c - a + 1, np.int64)) for a, c in zip(edges[:-1], edges[1:])]
    futures = [pool.submit(window_bins, times, offsets[a:c + 1], *window, bins[offsets[a]:], local)
               for a, c, local in runs]
    kept = [int(f.result()) for f in futures]
    n = 0
    for (a, c, local), k in zip(runs, kept):
        start = int(offsets[a])
        if start != n:
            bins[n:n + k] = bins[start:start + k]     # overlapping: numpy copies through a buffer
        out_offsets[a:c + 1] = local + n
        n += k
    return n


def store_pairs(store, b: Binning, max_photons: int | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(bins, weights, offsets) of every pixel's in-window detections: a photon list's first
    ``max_photons`` as :func:`binned_photons` gives them, with ``weights`` empty
    (``recon.kernels.NO_WEIGHTS``: each entry one detection), or a
    :class:`recon.counts.CountStore`'s (bin, count) pairs (``CountStore.binned``), which keep no
    detection order (``max_photons`` refused)."""
    from spdepth.recon.counts import CountStore
    from spdepth.recon.kernels import NO_WEIGHTS

    if isinstance(store, CountStore):
        if max_photons is not None:
            raise InputError("counts keep no detection order: max_photons does not apply")
        return store.binned(b)
    bins, offsets = binned_photons(store, b, max_photons)
    return bins, NO_WEIGHTS, offsets


def detections_per_pixel(weights: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """Detections per pixel (int64) of CSR entries: one each (``weights`` empty), else the entries'
    counts summed (rounded: a corrected store's need not be whole)."""
    if not weights.size:
        return np.diff(offsets)
    through = np.zeros(weights.size + 1)
    np.cumsum(weights, out=through[1:])
    return np.rint(through[offsets[1:]] - through[offsets[:-1]]).astype(np.int64)


def fit_pixels(store, settings: ReconSettings, b: Binning,
               fit_chunk: Callable[..., None],
               progress: Callable[[int, int], None] | None = None) -> PixelFit:
    """Bin the first ``settings.max_photons`` in-window detections of every pixel and run
    ``fit_chunk(bins, offsets, max_n, out)`` over chunks of CHUNK_PIXELS pixels (``max_n``: the most
    entries a pixel has), calling ``progress(done, total)`` after each. A
    :class:`recon.counts.CountStore` (given only to estimators with the ``counts`` capability) comes
    as (bin, count) pairs: ``fit_chunk(bins, offsets, max_n, out, weights=counts)``."""
    if settings.several:
        raise InputError("a pixelwise fit gives one surface per pixel; several: recon.estimators.surfaces")
    bins, weights, offsets = store_pairs(store, b, settings.max_photons)
    npix = store.n_pixels
    counts = np.diff(offsets)
    out = PixelFit.empty(npix)
    def fit(p0: int, p1: int) -> None:
        o = offsets[p0:p1 + 1]
        maxn = int(counts[p0:p1].max()) if p1 > p0 else 0
        if weights.size:
            fit_chunk(bins[o[0]:o[-1]], o - o[0], maxn, out.rows(p0, p1), weights=weights[o[0]:o[-1]])
        else:
            fit_chunk(bins[o[0]:o[-1]], o - o[0], maxn, out.rows(p0, p1))

    over_threads(fit, npix, CHUNK_PIXELS, progress)
    return out


def over_threads(fit: Callable[[int, int], None], npix: int, chunk_pixels: int,
                 progress: Callable[[int, int], None] | None = None) -> None:
    """``fit(a, b)`` over the pixels [0, npix) in chunks of ``chunk_pixels``, each shared among
    :func:`threads` threads in slices (:func:`thread_slices`), calling ``progress(done, npix)``
    as each chunk completes, in order. Every chunk's slices are queued at once: a thread that
    ends its share of a chunk goes on with the next instead of waiting for the slowest slice
    (a warm 512x512 ml fit, 16 chunks: 0.534 -> 0.519 s median of 6, alternated, load 1.6). On
    an error the slices not started are cancelled and those running are waited for, so no fit
    writes after this returns."""
    workers = threads()
    pool = shared_pool(workers)
    chunks = [(p0, min(npix, p0 + chunk_pixels)) for p0 in range(0, npix, chunk_pixels)]
    if pool is None:               # called from one of the pool's own threads: no nesting
        for p0, p1 in chunks:
            fit(p0, p1)
            if progress is not None:
                progress(p1, npix)
        return
    queued = [[pool.submit(fit, a, b) for a, b in thread_slices(p0, p1, workers)] for p0, p1 in chunks]
    try:
        for (_, p1), futures in zip(chunks, queued):
            for f in futures:
                f.result()
            if progress is not None:
                progress(p1, npix)
    except BaseException:
        running = [f for futures in queued for f in futures if not f.cancel()]
        wait(running)
        raise


def thread_slices(p0: int, p1: int, workers: int) -> list[tuple[int, int]]:
    """The pixels [p0, p1) in slices of whole kernel blocks, about four per one of ``workers``
    threads. The kernels are nogil loops over blocks: side by side on a pool they go as fast as
    numba's ``prange`` over the same blocks, whose parallel loops compile far slower (cold, CPU s:
    ml 20 -> 15.5, uos 21 -> 12). Pixels are independent, so the maps are the same bit for bit
    however they are sliced."""
    from spdepth.recon.kernels import BLOCK

    return slices(p0, p1, workers, BLOCK)


def honest_var(var: np.ndarray, has: np.ndarray, rms_bins: float, n_bins: int, shift_step: float) -> np.ndarray:
    """Shift variance (bins^2) to report, from the kernels' Fisher variance ``var``.

    The Fisher information is the local curvature at the estimate; it says nothing where that
    curvature vanishes. A pulse narrower than a bin puts all its photons in one bin, where the
    likelihood is flat in the shift: the Fisher variance reads ~1e32 (or NaN with background),
    while the shift is known to within that bin. So: a degenerate or larger variance is replaced
    by a bin's uniform variance plus the pulse's (``1/12 + rms^2``) for such pulses, by the whole
    window's uniform variance otherwise, never more than the window's; and the estimator's grid
    (``shift_step`` bins: 1 for integer shifts, 1/FINE_STEPS for ml) adds its quantization."""
    v = np.where(np.isfinite(var) & (var > 0), var, np.inf)
    window = n_bins * n_bins / 12.0
    if rms_bins < 1.0:
        v = np.minimum(v, 1.0 / 12.0 + rms_bins * rms_bins)
    v = np.minimum(v, window)
    quant = shift_step * shift_step / 12.0
    return np.where(has, np.minimum(v + quant, window), np.nan)


def settings_record(settings: ReconSettings, notes: dict, binning: Binning, kern: PulseKernel) -> dict:
    """What a result's ``settings`` holds: the settings asked for, what was resolved (binning,
    pulse and where it came from) and the kernel used."""
    rec = settings.to_dict()
    rec.update(notes)
    rec["binning"] = binning.to_dict()
    rec["kernel"] = kern.info
    rec["tof_reference"] = "pulse centroid, from the laser sync"
    if settings.irf is not None:
        rec["irf"]["rms_s"] = settings.irf.rms_s
    return rec


def model_signal(fit: PixelFit, kern: PulseKernel) -> np.ndarray:
    """Expected signal detections inside the window: amplitude times the column sum at the shift
    (to the fine table's 1/FINE_STEPS bin)."""
    has = np.isfinite(fit.shift)
    q = np.where(has, np.rint(np.nan_to_num(fit.shift) * FINE_STEPS), 0).astype(np.int64)
    return np.where(has, fit.amp * kern.fine_colsum[np.clip(q, 0, kern.fine_colsum.size - 1)], 0.0)


def pixel_maps(store: PhotonStore, settings: ReconSettings, b: Binning, kern: PulseKernel, notes: dict,
               fit: PixelFit, shift_step: float, signal: np.ndarray | None = None) -> DepthMaps:
    """The maps of a one-surface pixelwise fit: time of flight at the shift, ``signal`` (default
    :func:`model_signal`), uncertainty by :func:`honest_var` on the estimator's grid
    ``shift_step``, flags from the fit; ``notes`` go into the settings record."""
    h, w = store.shape
    has = np.isfinite(fit.shift)
    if signal is None:
        signal = model_signal(fit, kern)
    tof_s = np.where(has, b.shift_to_time_s(np.nan_to_num(fit.shift)), np.nan).reshape(h, w)
    unc_s = np.sqrt(honest_var(fit.var, has, kern.rms_bins, b.n_bins, shift_step)) * b.bin_width_s
    flags = np.full(h * w, PixelFlag.OK, np.uint8)
    flags[~has] = PixelFlag.NO_SIGNAL
    flags[has & ~fit.conv] = PixelFlag.NOT_CONVERGED
    flags[fit.n_used == 0] = PixelFlag.NO_PHOTONS
    return DepthMaps(tof_s=tof_s, depth_m=C_M_PER_S * tof_s / 2.0, background=fit.bg.reshape(h, w),
                     signal=signal.reshape(h, w), photons=fit.n_used.reshape(h, w),
                     iterations=fit.iters.reshape(h, w), uncertainty_s=unc_s.reshape(h, w),
                     flags=flags.reshape(h, w), settings=settings_record(settings, notes, b, kern),
                     gain_nats=fit.gain.reshape(h, w) if np.isfinite(fit.gain).any() else None)
