"""Live reconstruction: pixels are reconstructed in batches on a worker thread as they become final,
never as a full-frame recompute.

Every pixel is reconstructed exactly once, with the same ``ReconSettings`` (fixed binning and pulse),
and each pixel's return decided on its own detections (a batch is not a frame). Once every pixel
is final, where some pixel with detections holds no return of its own, the rows of the final store
that hold detections are reconstructed once more with the return test's frame rules (its
neighbours' support and regions, ``recon.detect``), so the live maps at the end equal
``recon.estimate.reconstruct`` of the final store bit for bit, and ``spdepth recon`` of the
recording; a worker that ends before every pixel is final keeps the batches' decisions
(``settings['neighbour_rules']`` says so). When no pulse width is given, it is estimated once
from the first ``PULSE_SAMPLE_PIXELS`` pixels to become final (in stream order, so a replay of the same
stream estimates the same width) and then frozen.

Several surfaces per pixel (``reflectors`` K > 1 or "auto", :mod:`recon.estimators.surfaces_fit`): the maps of
tof_s, depth_m, signal, uncertainty_s and weak are (K, H, W) (K the most surfaces looked for), with
a ``surfaces`` count map, as ``spdepth recon`` writes them. A file's multi-surface reconstruction
measures its response on the surfaces of all its pixels; live there are no "all pixels" yet, so
when no pulse is given the same measurement (``recon.estimate.reconstruct`` on them) runs once on
the first ``RESPONSE_SAMPLE_PIXELS`` final pixels and its measured shape is frozen as the IRF of
every pixel (recorded in the settings, so a replay and ``spdepth recon`` of the recording use the
same response). The simulated bench gives its pulse, so its scans measure nothing.

Pile-up (``recon.pileup``): a pixel whose kept detections per laser period (``PixelStore.periods``:
the periods they span) exceed ``recon.pileup.PILEUP_THRESHOLD`` is estimated from its Coates-corrected
histogram (a detector that re-arms at each sync), as ``spdepth recon --pileup auto`` corrects a
file; decided per pixel, so a pixel's maps do not depend on the batch it came in. ``pileup``
(and the maps' ``settings['pileup']``) says how many pixels were corrected.

An estimator that does not run live (``recon.estimators.get(method).live`` False: spatial, which
needs each pixel's neighbours) cannot run pixel by pixel: the live maps come from its pixelwise
``live_stand_in`` (spatial's: ml) and, once every pixel is final, one full-frame reconstruction of
the final store by the estimator asked for replaces them (a replay does the same, so it still
equals the live run).
"""

from __future__ import annotations

import dataclasses
import logging
import threading
import time

import numpy as np

from spdepth.recon import estimators
from spdepth.recon.estimate import reconstruct, resolve_model, warm_up
from spdepth.recon.maps import DepthMaps, PixelFlag
from spdepth.recon.model import Irf, ReconSettings

log = logging.getLogger(__name__)

PULSE_SAMPLE_PIXELS = 256
"""Pixels pooled for the pulse-width estimate when none is given."""
RESPONSE_SAMPLE_PIXELS = 1024
"""Several surfaces: pixels whose surfaces the response is measured on when none is given (the
pooled shape needs surfaces of several detections each, and a tail or bump a few hundred)."""
MAX_BATCH_PIXELS = 16384
"""Largest batch one reconstruction call takes (keeps the maps fresh during a fast replay)."""
CLOSING_BATCH_FACTOR = 16
"""Batches are this many times larger once the session is finishing."""
MIN_BATCH_PIXELS = 1024
"""A batch starts once this many pixels wait, ..."""
BATCH_WAIT_S = 0.2
"""... or once the oldest has waited this long (the maps lag the scan by at most about this)."""


class LiveRecon:
    """Reconstructs the pixels handed to ``submit`` on its own thread and keeps full-frame maps.

    store:    ``acq.store.PixelStore`` (the submitted pixels must be frozen in it).
    settings: ``ReconSettings`` with a binning (a live scan cannot derive one from data it has not
              seen) and ``max_photons`` equal to the store's target.
    """

    def __init__(self, store, settings: ReconSettings):
        if settings.binning is None:
            raise ValueError("live reconstruction needs a fixed binning")
        self.store = store
        self.requested = settings
        """The settings asked for, as given: what recordings keep."""
        est = estimators.get(settings.method)
        # an estimator that does not run live runs once at the end; its stand-in draws the live maps
        self.frame_settings = None if est.live else settings
        """The settings of the one reconstruction of the whole final store, for an estimator
        that does not run live (spatial); None for one that does."""
        if self.frame_settings is not None:
            settings = dataclasses.replace(settings, method=est.live_stand_in)
        self.pixel_settings = settings
        """What each batch of pixels is reconstructed with: the requested settings, or the live
        stand-in of an estimator that does not run live, with the pulse frozen once measured."""
        h, w = store.shape
        # several surfaces: (K, H, W) per-surface maps, K the most looked for (recon.maps.DepthMaps)
        k = () if not settings.several else (
            settings.max_reflectors if settings.reflectors == "auto" else settings.reflectors,)
        self.fields = _MAP_FIELDS + (_SURFACE_FIELDS if settings.several else ())
        """The maps kept (the several-surface ones only with several surfaces)."""
        # each map's shape, dtype and the value it is made with, where no pixel has been written
        # yet; made on first use (_allocate), not here: a 4096 x 4096 frame's NaN maps are half a
        # GB, which took 0.3 s of a time-limited scan's start (the session has them made while
        # the scan runs, warm_up(wait=False))
        self._layout = {name: (k + (h, w) if name in _PER_SURFACE else (h, w), dtype, fill)
                        for name, (dtype, fill) in _MAP_MADE_WITH.items()
                        if name in self.fields or name == "done"}
        self._made_with = {name: np.asarray(fill, dtype)[()] for name, (_, dtype, fill)
                           in self._layout.items() if name in self.fields}
        self._allocated = False
        self._allocate_lock = threading.Lock()
        self._warm_thread: threading.Thread | None = None
        self._empty_as_made: dict = {}
        self.settings_used: dict | None = None   # the maps' settings record (the first batch's)
        self._pulse_note: dict = {}             # how the pulse width was found, when estimated
        self.submitted = 0
        self.processed = 0
        self.max_lag = 0
        self.busy_s = 0.0
        self._pending: list[np.ndarray] = []
        self._n_pending = 0
        self._cond = threading.Condition()
        self.lock = threading.Lock()
        """Held while a batch's results are written into the maps and while they are copied
        (``maps``, ``copy_maps``): a copy never holds part of a batch."""
        self._closing = False
        self._error: BaseException | None = None
        self._empty: dict | None = None         # one empty pixel's results (pixelwise estimators)
        self._thread: threading.Thread | None = None
        self.pileup_pixels = 0
        """Pixels estimated from their Coates-corrected histogram (module docstring)."""
        self.pileup_max_per_period = 0.0

    def __getattr__(self, name: str):
        # the maps (and ``done``) exist once first asked for (_allocate)
        layout = self.__dict__.get("_layout")
        if layout is None or name not in layout:
            raise AttributeError(f"{type(self).__name__!r} object has no attribute {name!r}")
        self._allocate()
        return self.__dict__[name]

    def _allocate(self) -> None:
        """Make the maps, each filled with the value it is made with (idempotent, any thread)."""
        with self._allocate_lock:
            if self._allocated:
                return
            for name, (shape, dtype, fill) in self._layout.items():
                # zeros are pages the system maps on first write (nothing to fill now)
                self.__dict__[name] = (np.zeros(shape, dtype) if fill == 0
                                       else np.full(shape, fill, dtype))
            self._allocated = True

    @property
    def pileup(self) -> dict:
        """What the pile-up rule did so far (JSON-able), for the summary and the maps' settings."""
        from spdepth.recon.pileup import PILEUP_THRESHOLD

        n = self.pileup_pixels
        return {"mode": "auto", "applied": n > 0, "pixels": n, "threshold_per_period": PILEUP_THRESHOLD,
                "max_per_period": self.pileup_max_per_period,
                "reason": (f"{n} pixels above {PILEUP_THRESHOLD:g} detections per laser period (up to "
                           f"{self.pileup_max_per_period:.3g}): Coates' correction (detector re-arms at each sync)"
                           if n else f"at most {self.pileup_max_per_period:.3g} detections per laser period: "
                                     "pile-up negligible")}

    def corrected(self, pixels: np.ndarray | None = None, tally: bool = True):
        """The store's pixels (flat indices, a 1 x n image; None: the whole frame) to estimate
        from: their photon list, or counts with Coates' correction at the pixels whose detections
        per laser period pass PILEUP_THRESHOLD (module docstring). ``tally``: listed pixels count
        in :attr:`pileup` (False: pixels already counted, estimated again)."""
        from spdepth.recon.counts import CountStore
        from spdepth.recon.pileup import PILEUP_THRESHOLD, coates

        photons = self.store.photons(pixels)
        known = getattr(self.store, "periods", None)
        if known is None:            # a store that does not count periods: nothing to correct by
            return photons
        idx = np.arange(self.store.n_pixels) if pixels is None else np.asarray(pixels, np.int64)
        periods = known[idx].astype(np.float64)
        n = self.store.count[idx].astype(np.float64)
        rate = np.divide(n, periods, out=np.zeros_like(n), where=periods > 0)
        hot = (periods > 0) & (rate > PILEUP_THRESHOLD)
        if pixels is not None and tally:
            self.pileup_max_per_period = max(self.pileup_max_per_period, float(rate.max(initial=0.0)))
            self.pileup_pixels += int(hot.sum())
        if not hot.any():
            return photons
        counts = CountStore.from_photons(photons, np.where(periods > 0, periods, 1.0))
        fixed = coates(counts)
        entry_hot = hot[counts.pixel_index()]
        return dataclasses.replace(counts, counts=np.where(entry_hot, fixed.counts, counts.counts))

    def start(self) -> "LiveRecon":
        """Start the worker thread (the session does, on ``Session.start``)."""
        with self._cond:
            if self._thread is not None:
                raise RuntimeError("live reconstruction already started")
            self._thread = threading.Thread(target=self._run, name="live-recon", daemon=True)
            self._thread.start()
        return self

    def close(self, timeout_s: float | None = 5.0) -> None:
        """End the worker without reconstructing what is still queued (idempotent; a worker
        never started has nothing to end)."""
        with self._cond:
            self._closing = True
            self._pending, self._n_pending = [], 0
            self._cond.notify_all()
            thread = self._thread
        if thread is not None and thread is not threading.current_thread():
            thread.join(timeout_s)

    @property
    def error(self) -> BaseException | None:
        """The exception that ended the worker, if any."""
        return self._error

    def raise_if_failed(self) -> None:
        """Re-raise the worker's exception in the caller's thread."""
        if self._error is not None:
            raise self._error

    @property
    def lag(self) -> int:
        """Pixels handed over and not yet reconstructed."""
        return self.submitted - self.processed

    def warm_up(self, wait: bool = True) -> None:
        """Load (or compile) the estimator's kernels on one made-up pixel, and make the maps, so
        the first real batch does not wait for them. ``wait`` False: on a thread of its own,
        started now, that the first batch waits for (the session asks for this while armed: the
        scan starts at once and its first pixels are scanned while the kernels load; a time
        limit then bounds the wait from the command's start, and a first run's compile no longer
        holds the scan in "armed")."""
        if wait:
            self._warm_up()
            return
        if self._warm_thread is None:
            self._warm_thread = threading.Thread(target=self._warm_up, name="live-recon-warm-up",
                                                 daemon=True)
            self._warm_thread.start()

    def _warm_up(self) -> None:
        try:
            warm_up(self.pixel_settings)
        except Exception:  # noqa: BLE001 - the first batch runs the same kernels and says what fails
            log.debug("live reconstruction warm-up failed; the first batch loads its kernels",
                      exc_info=True)
        self._allocate()

    def _wait_warm_up(self) -> None:
        thread = self._warm_thread
        if thread is not None and thread is not threading.current_thread():
            thread.join()

    def submit(self, pixels: np.ndarray) -> None:
        """Queue flat pixel indices (frozen in the store) for reconstruction."""
        if pixels.size == 0:
            return
        with self._cond:
            if self._error is not None:
                raise self._error
            self._pending.append(np.asarray(pixels, np.int64))
            self._n_pending += pixels.size
            self.submitted += int(pixels.size)
            self.max_lag = max(self.max_lag, self.lag)
            self._cond.notify()

    def finish(self, timeout_s: float | None = None) -> None:
        """Reconstruct everything queued, then end the thread; re-raises a worker error. A
        worker never started is started for it (a session ended before it began)."""
        with self._cond:
            if self._thread is None and self._error is None:
                self._thread = threading.Thread(target=self._run, name="live-recon", daemon=True)
                self._thread.start()
            self._closing = True
            self._cond.notify()
            thread = self._thread
        if thread is not None:
            thread.join(timeout_s)
        if self._error is not None:
            raise self._error

    def _take(self) -> np.ndarray | None:
        """The next batch: at least MIN_BATCH_PIXELS, or whatever waited BATCH_WAIT_S (each call
        of the estimator costs milliseconds of set-up, so a pixel at a time would burn a core)."""
        with self._cond:
            oldest = None
            while True:
                need = MIN_BATCH_PIXELS
                if self.settings_used is None and self._needs_pulse():
                    need = max(need, self._sample_pixels)
                if self._n_pending and oldest is None:
                    oldest = time.monotonic()
                waited = oldest is not None and time.monotonic() - oldest >= BATCH_WAIT_S
                if self._n_pending >= need or (self._n_pending and (self._closing or (
                        waited and not (self.settings_used is None and self._needs_pulse())))):
                    break
                if self._closing:
                    return None
                self._cond.wait(BATCH_WAIT_S / 4)
            # up to MAX_BATCH_PIXELS from the front; the rest stays as it was queued (copying
            # the whole queue for every batch was quadratic: a huge scan cut by its time limit
            # queues millions of pixels at once)
            # at the end nobody watches the maps fill: bigger batches, fewer set-ups
            most = MAX_BATCH_PIXELS * (CLOSING_BATCH_FACTOR if self._closing else 1)
            parts, n = [], 0
            while self._pending and n < most:
                head = self._pending[0]
                room = most - n
                if head.size <= room:
                    parts.append(self._pending.pop(0))
                else:
                    parts.append(head[:room])
                    self._pending[0] = head[room:]
                n += parts[-1].size
            self._n_pending -= n
            return parts[0] if len(parts) == 1 else np.concatenate(parts)

    def _needs_pulse(self) -> bool:
        return self.pixel_settings.pulse_rms_s is None and self.pixel_settings.irf is None

    @property
    def _sample_pixels(self) -> int:
        """Final pixels the pulse (one surface) or the response (several) is measured on."""
        return RESPONSE_SAMPLE_PIXELS if self.pixel_settings.several else PULSE_SAMPLE_PIXELS

    def _run(self) -> None:
        try:
            while (batch := self._take()) is not None:
                self._wait_warm_up()
                t0 = time.perf_counter()
                self._reconstruct(batch)
                self.busy_s += time.perf_counter() - t0
            if self.frame_settings is not None and self.processed:
                t0 = time.perf_counter()
                self._reconstruct_frame(dataclasses.replace(
                    self.frame_settings, pulse_rms_s=self.pixel_settings.pulse_rms_s,
                    irf=self.pixel_settings.irf))
                self.busy_s += time.perf_counter() - t0
            elif self.processed:
                self._frame_rules()
        except BaseException as exc:  # noqa: BLE001 - handed to the owner at submit/finish
            # the owner reports it (one line); the traceback only at debug level
            log.debug("live reconstruction failed", exc_info=True)
            with self._cond:
                self._error = exc
                self._pending, self._n_pending = [], 0

    def _reconstruct(self, pixels: np.ndarray) -> None:
        if self._needs_pulse():
            # freeze the model estimated from this first batch for every later pixel
            n = min(self._sample_pixels, pixels.size)
            sample = self.store.photons(pixels[:n])
            if self.pixel_settings.several:
                # recon.estimators.surfaces' own measurement of the response on the surfaces (module docstring)
                measured = reconstruct(sample, self.pixel_settings).settings
                self.pixel_settings = dataclasses.replace(self.pixel_settings, irf=Irf.from_dict(measured["irf"]))
                self._pulse_note = {"pulse_source": f"measured on the surfaces of the first {n} "
                                                    "final pixels, then frozen"}
            else:
                _, _, notes = resolve_model(sample, self.pixel_settings)
                self.pixel_settings = dataclasses.replace(self.pixel_settings, pulse_rms_s=notes["pulse_rms_s"])
                self._pulse_note = {"pulse_source": f"estimated from the first {n} final pixels"}
        # pixels without a detection all come out alike (each estimator works pixel by pixel):
        # reconstruct one such pixel once and copy it, so a huge scan cut short by its time
        # limit does not run the estimator over millions of empty pixels
        empty = self.store.count[pixels] == 0
        full = pixels[~empty]
        # a batch is a list of pixels, not a frame: each pixel is tested on its own detections (the
        # neighbours' rules, recon.detect, need the frame: _frame_rules, once every pixel is final)
        m = _reconstruct_store(self.corrected(full), self.pixel_settings, neighbours=False) if full.size else None
        if self._empty is None and empty.any():
            self._empty = self._empty_result()
            # a map whose empty-pixel value is the one it was made with needs no writes for them
            # (each pixel is submitted once): a 4096 x 4096 scan cut by its time limit hands
            # over 16 M empty pixels at its end
            self._empty_as_made = {
                name: bool(np.array_equal(v, np.broadcast_to(self._made_with[name], v.shape),
                                          equal_nan=True))
                for name, v in ((n, np.asarray(self._empty[n])) for n in self.fields)}
        if self.settings_used is None:
            self.settings_used = dict(m.settings if m is not None else self._empty["settings"])
            self.settings_used.update(self._pulse_note)
        with self.lock:        # one batch appears in the maps at once
            for name in self.fields:
                dst = getattr(self, name)
                flat = dst.reshape(dst.shape[:-2] + (-1,))       # (K, H*W) for a surface's maps
                if m is not None:
                    flat[..., full] = getattr(m, name).reshape(flat.shape[:-1] + (-1,))
                if empty.any() and not self._empty_as_made[name]:
                    flat[..., pixels[empty]] = self._empty[name][..., None]
            self.done.reshape(-1)[pixels] = True
            self.settings_used["pileup"] = self.pileup
        self.processed += int(pixels.size)

    def _empty_result(self) -> dict:
        """What the estimator gives a pixel without detections (with the frozen settings)."""
        from spdepth.recon.photons import PhotonStore

        one = PhotonStore(np.zeros(0), np.array([0, 0]), (1, 1), self.store.time_unit_s)
        m = reconstruct(one, self.pixel_settings)
        out = {name: np.asarray(getattr(m, name))[..., 0, 0] for name in self.fields}
        out["settings"] = m.settings
        return out

    def _frame_rules(self) -> None:
        """Once every pixel is final, the return test's rules that need the frame (a pixel that
        fails on its own detections, tested with its neighbours': recon.detect) as ``spdepth
        recon`` of the recording applies them: a batch is not a frame. Only where they could
        change a pixel (one surface, some pixel with detections and no return), and over the rows
        that hold detections (a scan cut by its time limit reached a few of a large frame's: the
        others hold none, so they neither change nor lend support). A session that ended before
        every pixel was final keeps each pixel's own decision, and its record says so."""
        if self.pixel_settings.several:
            return
        with self.lock:
            no_return = int(np.count_nonzero(self.flags == PixelFlag.NO_RETURN))
            final = int(np.count_nonzero(self.done))
        if not no_return:
            return
        if final < self.done.size:
            self.settings_used["neighbour_rules"] = (
                f"not applied: {final} of {self.done.size} pixels final (a pixel's neighbours may be "
                f"missing); each pixel's return decided on its own detections")
            return
        t0 = time.perf_counter()
        h, w = self.store.shape
        rows = np.flatnonzero(np.asarray(self.store.count).reshape(h, w).any(axis=1))
        self._reconstruct_frame(self.pixel_settings, rows=(int(rows[0]), int(rows[-1]) + 1))
        self.settings_used.update(self._pulse_note)
        self.settings_used["live_maps"] += ("; once every pixel was final, the frame reconstructed with the "
                                            "neighbours' rules of the return test")
        self.busy_s += time.perf_counter() - t0

    def _reconstruct_frame(self, settings: ReconSettings, rows: tuple[int, int] | None = None) -> None:
        """One reconstruction of the whole final store (the last step of an estimator that does not
        run live), or of its rows [r0, r1) (the return test's frame rules: :meth:`_frame_rules`)."""
        if rows is None:
            m = _reconstruct_store(self.corrected(), settings)
            at = (...,)
        else:
            h, w = self.store.shape
            part = self.corrected(np.arange(rows[0] * w, rows[1] * w), tally=False)
            m = _reconstruct_store(dataclasses.replace(part, shape=(rows[1] - rows[0], w)), settings)
            at = (..., slice(*rows), slice(None))
        with self.lock:
            for name in self.fields:
                getattr(self, name)[at] = getattr(m, name)
        self.settings_used = dict(m.settings)
        self.settings_used["pileup"] = self.pileup
        self.settings_used["live_maps"] = f"{self.pixel_settings.method} pixel by pixel during the scan"

    def maps(self, copy: bool = True) -> DepthMaps:
        """The maps as they stand (copies), in ``spdepth recon``'s format. ``copy=False`` gives
        the arrays themselves: only once the worker has ended (``finish``), for writing them."""
        settings = dict(self.settings_used) if self.settings_used is not None else self.pixel_settings.to_dict()
        settings["pileup"] = self.pileup
        if copy:
            return DepthMaps(settings=settings, **self.copy_maps(*self.fields))
        return DepthMaps(settings=settings, **{name: getattr(self, name) for name in self.fields})

    def copy_maps(self, *names: str) -> dict:
        """Copies of the named maps, all taken between two batches (never half a batch)."""
        with self.lock:
            return {name: getattr(self, name).copy() for name in names}


def _reconstruct_store(store, settings: ReconSettings, **options) -> DepthMaps:
    """``reconstruct`` (``options`` passed on); corrected counts (LiveRecon.corrected) keep no
    detection order, and the store already holds only each pixel's first ``max_photons``, so they
    go without it."""
    from spdepth.recon.counts import CountStore

    if isinstance(store, CountStore) and settings.max_photons is not None:
        settings = dataclasses.replace(settings, max_photons=None)
    return reconstruct(store, settings, **options)


_MAP_FIELDS = ("tof_s", "depth_m", "background", "signal", "photons", "iterations",
               "uncertainty_s", "flags")
_SURFACE_FIELDS = ("surfaces", "weak")
"""Maps of several surfaces only (``DepthMaps`` derives them for one)."""
_PER_SURFACE = ("tof_s", "depth_m", "signal", "uncertainty_s", "weak")
"""Maps that are (K, H, W) with several surfaces."""
_MAP_MADE_WITH = {"tof_s": (np.float64, np.nan), "depth_m": (np.float64, np.nan),
                  "background": (np.float64, np.nan), "signal": (np.float64, 0),
                  "photons": (np.int64, 0), "iterations": (np.int32, 0),
                  "uncertainty_s": (np.float64, np.nan),
                  "flags": (np.uint8, int(PixelFlag.NO_PHOTONS)), "surfaces": (np.int16, 0),
                  "weak": (np.bool_, 0), "done": (np.bool_, 0)}
"""Each map's dtype and the value of a pixel not reconstructed (``done``: whether it was)."""
