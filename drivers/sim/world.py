"""The simulated photon world: the detections a scene produces, as the devices would deliver them.

``PhotonWorld(scene, seed)`` answers per-pixel questions (``count_gated``, ``fixed_dwell``) for a
simulated scanner and tagger, and writes whole scans (``raster``) with pixel/line/frame markers.
Generation skips empty laser pulses (exponential gaps between detections), so cost grows with
detections, not pulses. ``VirtualClock`` lets a simulated scan run faster than real time or be
paced at a chosen speed.
"""

from __future__ import annotations

import math
import threading
import time
from dataclasses import dataclass
from typing import Callable

import numpy as np

from spdepth.drivers.errors import SettingError
from spdepth.drivers.events import EVENT_DTYPE, Marker

from spdepth.drivers.sim import kernels as K
from spdepth.drivers.sim.effects import Batch, Counting, DetectorState, Jitter, build_effects


BAND_ROWS = 16
"""Rows of a lazy scene (``drivers.sim.scene.LazyScene``) built at once when a dwell first
reaches one of them."""


class VirtualClock:
    """Simulated time in seconds.

    ``now_s`` only moves when someone calls ``advance``. With ``speed`` set, ``advance`` also
    sleeps so that simulated time runs ``speed`` times faster than the wall clock (1.0 = real
    time); with ``speed=None`` it never sleeps. Thread-safe.
    """

    def __init__(self, start_s: float = 0.0, speed: float | None = None) -> None:
        if speed is not None and not speed > 0:
            raise SettingError(f"clock speed must be positive, got {speed}")
        self._lock = threading.Lock()
        self._now_s = float(start_s)
        self._start_s = float(start_s)
        self.speed = speed
        self._wall0 = time.monotonic()

    @property
    def now_s(self) -> float:
        with self._lock:
            return self._now_s

    def advance(self, dt_s: float) -> float:
        """Move simulated time forward by ``dt_s`` >= 0; pace if ``speed`` is set. Returns now_s."""
        if not dt_s >= 0:
            raise SettingError(f"clock can only advance by dt_s >= 0, got {dt_s}")
        with self._lock:
            self._now_s += dt_s
            now = self._now_s
        if self.speed is not None:
            due = self._wall0 + (now - self._start_s) / self.speed
            delay = due - time.monotonic()
            if delay > 0:
                time.sleep(delay)
        return now


def _syncs(duration_s: float, period_s: float, what: str) -> int:
    if not (duration_s > 0) or math.isinf(duration_s):
        raise SettingError(f"{what} must be positive and finite, got {duration_s}")
    return max(1, int(duration_s / period_s + 1e-9))


@dataclass
class DwellRun:
    """What ``PhotonWorld.dwell_run`` gives back, per pixel done (the run may stop early):
    ``starts`` first sync, ``n_syncs`` syncs taken, ``counts`` PHOTON rows recorded; ``events``
    all rows in time order (markers included when asked for) and their ``origin`` (when asked
    for, else None)."""

    events: np.ndarray
    origin: np.ndarray | None
    starts: np.ndarray
    n_syncs: np.ndarray
    counts: np.ndarray

    @property
    def n_done(self) -> int:
        return int(self.starts.size)


class PhotonWorld:
    """Detections of a scene, pixel by pixel, reproducible from ``seed``.

    Rows of the returned event arrays are ``drivers.events.EVENT_DTYPE``: PHOTON rows with the
    absolute laser ``sync``, ``dtime`` in tagger units (``scene.resolution_s``) and the scene's
    ``channel``; MARKER rows (``raster`` only) with ``Marker`` bits. Calls are serialised by a
    lock, so one thread may drive the world while others read the arrays it returned (every call
    returns new arrays). The detector's state (dead time, pending afterpulses) carries from one
    call to the next, as a real detector's does across pixels.

    ``with_origin=True`` on any call also returns a uint8 array aligned with the events: 0
    background/dark, 1 + k signal from surface k, 250 afterpulse, 251 marker (the oracle's view).
    """

    def __init__(self, scene, seed: int = 0) -> None:
        self.scene = scene
        s = scene.settings
        self.seed = seed
        self._rng = np.random.default_rng(seed)
        self._lock = threading.Lock()
        h, w = scene.shape
        k = scene.n_surfaces
        # a lazy scene's rows are filled in as the dwells reach them (_ensure_rows); until then
        # their pages of these zeroed arrays are never touched, so they take no memory
        self._rows_built = None if getattr(scene, "lazy", False) else np.ones(h, bool)
        if self._rows_built is None:
            self._rows_built = np.zeros(h, bool)
            self._sig_pp = np.zeros((h * w, k))
            self._tof_s = np.zeros((h * w, k))
            self._bg_pp = np.zeros(h * w)
            self._lam = np.zeros(h * w)
        else:
            self._sig_pp = np.ascontiguousarray(scene.signal_pp.reshape(k, h * w).T)
            self._tof_s = np.ascontiguousarray(scene.tof_s.reshape(k, h * w).T)
            self._bg_pp = np.ascontiguousarray(scene.background_pp.reshape(h * w))
            self._lam = self._sig_pp.sum(axis=1) + self._bg_pp
        self._period_s = s.sync_period_s
        self._rates = K.Rates(self._sig_pp, self._tof_s, self._bg_pp, self._lam, float(self._period_s))
        if scene.irf is None:
            self._pulse = K.Pulse(K.PULSE_GAUSSIAN, float(s.pulse_rms_s), np.zeros(1), 0.0, 1.0)
        else:
            w_irf = scene.irf / scene.irf.sum()
            b = float(s.irf_bin_s)
            t0 = -float((w_irf * (np.arange(w_irf.size) + 0.5) * b).sum())  # mean delay -> 0
            cdf = np.cumsum(w_irf)
            cdf[-1] = 1.0
            self._pulse = K.Pulse(K.PULSE_TABLE, 0.0, cdf, t0, b)
        self.effects = build_effects(scene)
        self._stateless = [e for e in self.effects if not e.sequential]
        seq = [e for e in self.effects if e.sequential]
        self._sequential = seq[0] if seq else None
        self._det = DetectorState()
        self._scratch: Batch | None = None
        self._range_bins = s.range_bins

    @property
    def shape(self) -> tuple[int, int]:
        """Scene pixels (H, W)."""
        return self.scene.shape

    def _ensure_rows(self, pixels: np.ndarray | None = None) -> None:
        """Build the rates of a lazy scene's rows that ``pixels`` (flat indices, -1 off the
        scene; None: every row) reach and that are not built yet, in bands of ``BAND_ROWS``.
        Called with the world's lock held."""
        built = self._rows_built
        if pixels is None:
            rows = np.flatnonzero(~built)
        else:
            on = pixels[pixels >= 0]
            if not on.size:
                return
            h, w = self.scene.shape
            r0, r1 = int(on.min()) // w, int(on.max()) // w + 1
            if built[r0:r1].all():
                return
            rows = np.unique(on // w)
            rows = rows[~built[rows]]
        h, w = self.scene.shape
        for b0 in np.unique(rows // BAND_ROWS) * BAND_ROWS:
            b1 = min(h, int(b0) + BAND_ROWS)
            sig, tof, bg = self.scene.band(int(b0), b1)
            k = sig.shape[0]
            lo, hi = int(b0) * w, b1 * w
            self._sig_pp[lo:hi] = sig.reshape(k, -1).T
            self._tof_s[lo:hi] = tof.reshape(k, -1).T
            self._bg_pp[lo:hi] = bg.reshape(-1)
            self._lam[lo:hi] = self._sig_pp[lo:hi].sum(axis=1) + self._bg_pp[lo:hi]
            built[int(b0):b1] = True

    @property
    def sync_period_s(self) -> float:
        """Laser repetition period, seconds."""
        return self._period_s

    # ------------------------------------------------------------------ internals
    def _check_pixel(self, row: int, col: int) -> int:
        h, w = self.scene.shape
        if not (0 <= row < h and 0 <= col < w):
            raise SettingError(f"pixel ({row}, {col}) outside the {h} x {w} scene")
        return row * w + col

    def _base(self, pix: np.ndarray, start_sync: np.ndarray, n_sync: np.ndarray) -> Batch:
        """Ideal detections of the listed pixels (equation (3)), sorted by (sync, t).

        Written into a scratch buffer the world reuses (fresh memory costs more than generating
        into it), so the result is only valid until the next call."""
        expected = float((self._lam[pix] * n_sync).sum())
        need = int(expected + 6.0 * math.sqrt(expected) + 64)
        if self._scratch is None or len(self._scratch) < need:
            self._scratch = Batch.empty(max(need, 4096))
        buf = self._scratch
        n_tot = 0
        i, u = 0, 0.0
        kind, rms, cdf, t0, b = self._pulse
        while True:
            n, i, u = K.generate_chain(self._rng, pix, start_sync, n_sync, i, u,
                                       self._sig_pp, self._tof_s, self._bg_pp, self._period_s,
                                       kind, rms, cdf, t0, b,
                                       buf.sync[n_tot:], buf.t[n_tot:], buf.origin[n_tot:],
                                       buf.item[n_tot:])
            n_tot += n
            if i >= pix.size:
                break
            bigger = Batch.empty(2 * len(buf))
            for f in ("sync", "t", "origin", "item"):
                getattr(bigger, f)[:n_tot] = getattr(buf, f)[:n_tot]
            self._scratch = buf = bigger
        batch = buf.take(n_tot)
        K.sort_within_sync(batch.sync, batch.t, batch.origin, batch.item)
        return batch

    def _effects(self, batch: Batch, sync_end: int, counting: Counting) -> tuple[Batch, int]:
        """Run the active effects; returns the batch and the count a sequential stage made (-1
        when there is none)."""
        for e in self._stateless:
            batch, _ = e.apply(self._rng, batch, self._det, sync_end, counting)
        if self._sequential is None:
            return batch, -1
        return self._sequential.apply(self._rng, batch, self._det, sync_end, counting)

    def _pack(self, batch: Batch, m_sync=None, m_bits=None, ev=None, origin=None):
        """Batch (+ markers sorted by sync) -> (events, origin). Packs into the given arrays
        (capacity len(batch) + markers) when passed, else into new ones; returns the filled part."""
        if m_sync is None:
            m_sync = np.zeros(0, np.int64)
            m_bits = np.zeros(0, np.uint8)
        if ev is None:
            ev = np.empty(len(batch) + m_sync.size, EVENT_DTYPE)
            origin = np.empty(ev.size, np.uint8)
        n = K.pack_events(batch.sync, batch.t, batch.origin, self.scene.resolution_s,
                          self._range_bins, self.scene.settings.channel, m_sync, m_bits,
                          ev["sync"], ev["dtime"], ev["channel"], ev["kind"], ev["marker"], origin)
        ev["_pad"][:n] = 0
        return ev[:n], origin[:n]

    def _window(self, window) -> tuple[int, int]:
        if window is None:
            return 0, self._range_bins
        try:
            lo, hi = int(window[0]), int(window[1])
        except (TypeError, ValueError, IndexError):
            raise SettingError(f"window must be (start, stop) in tagger units, got {window!r}") from None
        if not 0 <= lo < hi:
            raise SettingError(f"window must satisfy 0 <= start < stop, got {window!r}")
        return lo, hi

    # ------------------------------------------------------------------ per pixel
    def fixed_dwell(self, row: int, col: int, dwell_s: float, start_sync: int, *,
                    with_origin: bool = False):
        """Everything pixel (row, col) yields in ``dwell_s`` from laser sync ``start_sync``.

        Returns (events, n_syncs): PHOTON rows with sync in [start_sync, start_sync + n_syncs),
        n_syncs = max(1, floor(dwell_s / sync_period_s)); plus origin when ``with_origin``.
        """
        run = self.dwell_run(np.array([self._check_pixel(row, col)], np.int64), start_sync,
                             dwell_s, with_origin=with_origin)
        n_sync = int(run.n_syncs[0])
        return (run.events, n_sync, run.origin) if with_origin else (run.events, n_sync)

    def count_gated(self, row: int, col: int, n_target: int, dwell_limit_s: float,
                    start_sync: int, window=None, *, with_origin: bool = False):
        """Detections of pixel (row, col) from sync ``start_sync`` until the one that brings the
        count to ``n_target`` or until ``dwell_limit_s`` worth of syncs has passed.

        Counts every recorded detection, or with ``window=(start, stop)`` only those with
        start <= dtime < stop (tagger units); the returned events include the uncounted ones in
        between. Returns (events, n_syncs): n_syncs = syncs elapsed (up to and including the
        target detection's sync, or the whole limit); plus origin when ``with_origin``.
        """
        run = self.dwell_run(np.array([self._check_pixel(row, col)], np.int64), start_sync,
                             dwell_limit_s, n_target=n_target, window=window,
                             with_origin=with_origin)
        n_syncs = int(run.n_syncs[0])
        return (run.events, n_syncs, run.origin) if with_origin else (run.events, n_syncs)

    def dwell_run(self, pixels: np.ndarray, start_sync: int, dwell_s: float, *,
                  n_target: int | None = None, window=None, settle_syncs: int = 0,
                  off_syncs: int = 0, stop_s: float = math.inf, max_records: int = 2 ** 62,
                  marker_bits=None, end_marker: int = 0, with_origin: bool = False) -> "DwellRun":
        """Dwells on several pixels one after another from sync ``start_sync``, as a scanner
        holding its mirror on each: ``fixed_dwell`` (``n_target`` None, ``dwell_s`` each) or
        ``count_gated`` (until ``n_target`` counted detections, ``window`` as there, or the limit
        ``dwell_s``), each pixel exactly as that call for it alone would give it, in one compiled
        call instead of one per pixel.

        pixels: flat scene pixel indices (row * W + col), -1 for a pixel off the scene (nothing
        returns; it takes ``off_syncs``). ``settle_syncs`` pass before every pixel but the first.
        The run stops early after the first pixel that ends (plus the settle after it) at or after
        virtual time ``stop_s``, and after the pixel that brings its detections plus one marker per
        pixel to ``max_records``. ``marker_bits`` (uint8 per pixel): a MARKER row with those bits
        opens each pixel (at its first sync, before its photons); ``end_marker`` bits: one more at
        the sync after the last pixel done.
        """
        pixels = np.ascontiguousarray(pixels, dtype=np.int64)
        h, w = self.scene.shape
        if pixels.ndim != 1 or np.any((pixels < -1) | (pixels >= h * w)):
            raise SettingError(f"pixels must be flat indices into the {h} x {w} scene or -1")
        gated = n_target is not None
        if gated:
            n_target = int(n_target)
            if n_target < 1:
                raise SettingError(f"n_target must be >= 1, got {n_target}")
        limit = _syncs(dwell_s, self._period_s, "dwell_limit_s" if gated else "dwell_s")
        start_sync = int(start_sync)
        if start_sync < 0:
            raise SettingError(f"start_sync must be >= 0, got {start_sync}")
        lo, hi = self._window(window)
        n = pixels.size
        starts, n_syncs, counts = (np.zeros(n, np.int64) for _ in range(3))
        seq = self._sequential
        jitter = [e for e in self._stateless if isinstance(e, Jitter)]
        # first guess of the detections (the kernel grows its arrays when it is short)
        if not gated:
            with self._lock:
                self._ensure_rows(pixels)     # the guess reads their rates
        guess = n * (n_target * 1.25 + 16.0) if gated else \
            float(self._lam[pixels[pixels >= 0]].sum() * limit) + 16.0 * n
        det = self._det
        dwell = K.Dwell(n_target if gated else 0, limit, int(settle_syncs), int(off_syncs), start_sync,
                        float(stop_s), int(max_records), int(min(guess, 1 << 20)) + 64)
        fx = K.Effects(float(jitter[0].rms_s) if jitter else 0.0, seq is not None,
                       float(seq.dead_s) if seq else 0.0, float(seq.ap_prob) if seq else 0.0,
                       float(seq.ap_tau_s) if seq else 0.0)
        gate = K.Gate(float(self.scene.resolution_s), int(self._range_bins), lo, hi)
        with self._lock:
            self._ensure_rows(pixels)
            done, sync, t, origin = K.dwell_run(
                self._rng, pixels, dwell, self._rates, self._pulse, fx,
                K.DetState(det.state_i, det.state_t, det.pend_sync, det.pend_t, det.pend_item),
                gate, starts, n_syncs, counts)
        m_sync, m_bits = np.zeros(0, np.int64), np.zeros(0, np.uint8)
        if marker_bits is not None:
            m_sync, m_bits = starts[:done], np.asarray(marker_bits, np.uint8)[:done]
        if end_marker:
            end = starts[done - 1] + n_syncs[done - 1] if done else start_sync
            m_sync = np.append(m_sync, end)
            m_bits = np.append(m_bits, np.uint8(end_marker))
        ev, org = self._pack(Batch(sync, t, origin, np.zeros(0, np.int32)), m_sync, m_bits)
        return DwellRun(ev, org if with_origin else None, starts[:done], n_syncs[:done],
                        counts[:done])

    # ------------------------------------------------------------------ whole scans
    def raster(self, n_target: int | None = None, dwell_s: float | None = None, *,
               dwell_limit_s: float | None = None, window=None, start_sync: int = 0,
               line_gap_s: float = 0.0, progress: Callable[[int, int], None] | None = None,
               with_origin: bool = False):
        """A whole frame, row by row, left to right, as the tagger would stream it.

        Fixed dwell (``n_target=None``): every pixel gets ``dwell_s`` (default the scene's).
        Count-gated (``n_target`` given): each pixel until ``n_target`` counted detections
        (``window`` as in ``count_gated``) or ``dwell_limit_s`` (default 100 x dwell_s); the next
        pixel starts at the next sync.

        Markers: FRAME at the first sync; per line LINE_START at the first sync of its first
        pixel, PIXEL at the first sync of each later pixel, LINE_STOP at the sync after its last
        pixel; ``line_gap_s`` of flyback follows each LINE_STOP. A marker row comes before the
        photons of its sync. ``progress(done_pixels, total_pixels)`` is called as lines finish.
        Returns events (and origin with ``with_origin``).
        """
        h, w = self.scene.shape
        T = self._period_s
        dwell_s = self.scene.dwell_s if dwell_s is None else dwell_s
        n_dwell = _syncs(dwell_s, T, "dwell_s")
        gap = 0 if line_gap_s == 0 else _syncs(line_gap_s, T, "line_gap_s")
        if start_sync < 0:
            raise SettingError(f"start_sync must be >= 0, got {start_sync}")
        if n_target is None:
            evs, origins = self._raster_fixed(n_dwell, gap, int(start_sync), progress)
        else:
            limit_s = 100 * dwell_s if dwell_limit_s is None else dwell_limit_s
            evs, origins = self._raster_gated(int(n_target), limit_s, window, gap,
                                              int(start_sync), progress)
        ev = np.concatenate(evs) if len(evs) > 1 else evs[0]
        if with_origin:
            return ev, np.concatenate(origins) if len(origins) > 1 else origins[0]
        return ev

    @staticmethod
    def _line_marker_bits(w: int, frame: bool) -> np.ndarray:
        """The marker pulses of one line of ``w`` pixels, as the galvo controller drives them
        (docs/protocols.md): ``[FRAME|]LINE_START|PIXEL`` at the first pixel, ``PIXEL`` at each
        later one, ``LINE_STOP`` after the last (w + 1 values)."""
        m_bits = np.full(w + 1, Marker.PIXEL, np.uint8)
        m_bits[0] |= Marker.LINE_START | (Marker.FRAME if frame else 0)
        m_bits[w] = Marker.LINE_STOP
        return m_bits

    def _line_markers(self, line_start: int, pixel_starts: np.ndarray, line_stop: int, frame: bool):
        """(sync, bits) of the marker pulses of one line (``_line_marker_bits``)."""
        w = pixel_starts.size
        m_sync = np.empty(w + 1, np.int64)
        m_sync[0] = line_start
        m_sync[1:w] = pixel_starts[1:]
        m_sync[w] = line_stop
        return m_sync, self._line_marker_bits(w, frame)

    def _raster_fixed(self, n_dwell, gap, start_sync, progress):
        h, w = self.scene.shape
        with self._lock:
            self._ensure_rows()           # a whole frame is written: every row's rates
        line_len = w * n_dwell + gap
        # Blocks of ~1M detections keep the scratch buffers small and reused; the output is
        # allocated once for the whole frame (fresh memory is the dearest part of the job).
        per_line = float(self._lam.reshape(h, w).sum(axis=1).mean() * n_dwell) + 1.0
        lines_per_block = int(min(h, max(1, 1e6 // per_line)))
        expected = float(self._lam.sum() * n_dwell)
        ap = self.scene.settings.afterpulse_prob if "afterpulsing" in self.scene.active_effects else 0.0
        cap = int(expected * (1 + 2 * ap) + 6 * math.sqrt(expected) + h * (w + 2) + 1024)
        ev = np.empty(cap, EVENT_DTYPE)
        origin = np.empty(cap, np.uint8)
        n_out = 0
        cols = np.arange(w, dtype=np.int64)
        with self._lock:
            self._det.start_at(start_sync)
            for r0 in range(0, h, lines_per_block):
                r1 = min(h, r0 + lines_per_block)
                rows = np.arange(r0, r1, dtype=np.int64)
                pix = (rows[:, None] * w + cols[None, :]).ravel()
                line_starts = start_sync + rows * line_len
                starts = (line_starts[:, None] + cols[None, :] * n_dwell).ravel()
                batch = self._base(pix, starts, np.full(pix.size, n_dwell, np.int64))
                block_end = start_sync + r1 * line_len
                batch, _ = self._effects(batch, block_end, Counting())
                ms, mb = [], []
                for r, ls in zip(rows, line_starts):
                    a, b = self._line_markers(int(ls), ls + cols * n_dwell, int(ls + w * n_dwell),
                                              frame=(r == 0))
                    ms.append(a)
                    mb.append(b)
                m_sync, m_bits = np.concatenate(ms), np.concatenate(mb)
                need = len(batch) + m_sync.size
                if n_out + need > ev.size:
                    grow = max(ev.size * 3 // 2, n_out + need)
                    ev2 = np.empty(grow, EVENT_DTYPE)
                    ev2[:n_out] = ev[:n_out]
                    o2 = np.empty(grow, np.uint8)
                    o2[:n_out] = origin[:n_out]
                    ev, origin = ev2, o2
                e, _ = self._pack(batch, m_sync, m_bits, ev[n_out:n_out + need],
                                  origin[n_out:n_out + need])
                n_out += e.size
                if progress is not None:
                    progress(r1 * w, h * w)
        return [ev[:n_out]], [origin[:n_out]]

    def _raster_gated(self, n_target, limit_s, window, gap, start_sync, progress):
        h, w = self.scene.shape
        evs, origins = [], []
        s = start_sync
        cols = np.arange(w, dtype=np.int64)
        for r in range(h):
            bits = self._line_marker_bits(w, frame=(r == 0))
            run = self.dwell_run(r * w + cols, s, limit_s, n_target=n_target, window=window,
                                 marker_bits=bits[:w], end_marker=int(bits[w]), with_origin=True)
            evs.append(run.events)
            origins.append(run.origin)
            s = int(run.starts[-1] + run.n_syncs[-1]) + gap
            if progress is not None:
                progress((r + 1) * w, h * w)
        return evs, origins


def warm_up() -> None:
    """Load (on a cold numba cache: compile) the kernels a scan's dwells run, on a throwaway
    two-pixel world. Opening a simulated bench calls it: otherwise the first dwell compiles them in
    the galvo emulator's thread, stalling a fresh install's first scan for tens of seconds after it
    started. The worlds of a session are untouched (their random streams stay as seeded)."""
    from spdepth.drivers.sim.scene import load_scene

    world = PhotonWorld(load_scene("bust", (1, 2), ppp=2.0, sbr=1.0), seed=0)
    bits = np.ones(2, np.uint8)
    world.dwell_run(np.array([0, -1]), 0, 1e-6, n_target=1, marker_bits=bits, end_marker=1)
    world.dwell_run(np.array([0, 1]), 10 ** 6, 1e-7, marker_bits=bits)
