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
from typing import Callable

import numpy as np

from spdepth.drivers.errors import SettingError
from spdepth.drivers.events import EVENT_DTYPE, Marker

from spdepth.drivers.sim import kernels as K
from spdepth.drivers.sim.effects import Batch, Counting, DetectorState, build_effects


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
        self._sig_pp = np.ascontiguousarray(scene.signal_pp.reshape(k, h * w).T)
        self._tof_s = np.ascontiguousarray(scene.tof_s.reshape(k, h * w).T)
        self._bg_pp = np.ascontiguousarray(scene.background_pp.reshape(h * w))
        self._lam = self._sig_pp.sum(axis=1) + self._bg_pp
        self._period_s = s.sync_period_s
        if scene.irf is None:
            self._pulse = (K.PULSE_GAUSSIAN, float(s.pulse_rms_s), np.zeros(1), 0.0, 1.0)
        else:
            w_irf = scene.irf / scene.irf.sum()
            b = float(s.irf_bin_s)
            t0 = -float((w_irf * (np.arange(w_irf.size) + 0.5) * b).sum())  # mean delay -> 0
            cdf = np.cumsum(w_irf)
            cdf[-1] = 1.0
            self._pulse = (K.PULSE_TABLE, 0.0, cdf, t0, b)
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
        p = self._check_pixel(row, col)
        n_sync = _syncs(dwell_s, self._period_s, "dwell_s")
        start_sync = int(start_sync)
        if start_sync < 0:
            raise SettingError(f"start_sync must be >= 0, got {start_sync}")
        with self._lock:
            self._det.start_at(start_sync)
            batch = self._base(np.array([p], np.int64), np.array([start_sync], np.int64),
                               np.array([n_sync], np.int64))
            batch, _ = self._effects(batch, start_sync + n_sync, Counting())
            ev, origin = self._pack(batch)
        return (ev, n_sync, origin) if with_origin else (ev, n_sync)

    def count_gated(self, row: int, col: int, n_target: int, dwell_limit_s: float,
                    start_sync: int, window=None, *, with_origin: bool = False):
        """Detections of pixel (row, col) from sync ``start_sync`` until the one that brings the
        count to ``n_target`` or until ``dwell_limit_s`` worth of syncs has passed.

        Counts every recorded detection, or with ``window=(start, stop)`` only those with
        start <= dtime < stop (tagger units); the returned events include the uncounted ones in
        between. Returns (events, n_syncs): n_syncs = syncs elapsed (up to and including the
        target detection's sync, or the whole limit); plus origin when ``with_origin``.
        """
        p = self._check_pixel(row, col)
        n_target = int(n_target)
        if n_target < 1:
            raise SettingError(f"n_target must be >= 1, got {n_target}")
        limit = _syncs(dwell_limit_s, self._period_s, "dwell_limit_s")
        start_sync = int(start_sync)
        if start_sync < 0:
            raise SettingError(f"start_sync must be >= 0, got {start_sync}")
        lo, hi = self._window(window)
        res = self.scene.resolution_s
        rb = self._range_bins
        with self._lock:
            self._det.start_at(start_sync)
            lam = float(self._lam[p])
            pix = np.array([p], np.int64)
            parts = []
            done = 0        # syncs generated so far
            counted = 0
            reached_sync = -1
            rate = lam      # counted detections per sync, refined as we go
            while done < limit and counted < n_target:
                need = n_target - counted
                chunk = int(need / rate * 1.25 + 16) if rate > 0 else limit
                chunk = min(max(chunk, 16), limit - done)
                s0 = start_sync + done
                batch = self._base(pix, np.array([s0], np.int64), np.array([chunk], np.int64))
                batch, n_seq = self._effects(
                    batch, s0 + chunk, Counting(need, res, rb, lo, hi) if self._sequential else Counting())
                if n_seq >= 0:
                    got = n_seq
                    if got >= need:
                        reached_sync = int(batch.sync[-1])
                else:
                    d = (batch.t / res).astype(np.int64)
                    cs = np.cumsum((d < rb) & (d >= lo) & (d < hi))
                    got = int(cs[-1]) if cs.size else 0
                    if got >= need:
                        cut = int(np.searchsorted(cs, need)) + 1
                        batch = batch.take(cut)
                        reached_sync = int(batch.sync[-1])
                        got = need
                parts.append(batch.copy())
                counted += got
                done += chunk
                if counted < n_target:
                    rate = max(counted / done, 0.5 * rate) if counted else rate / 4
            n_syncs = reached_sync - start_sync + 1 if reached_sync >= 0 else limit
            ev, origin = self._pack(Batch.concat(parts))
        return (ev, n_syncs, origin) if with_origin else (ev, n_syncs)

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

    def _line_markers(self, line_start: int, pixel_starts: np.ndarray, line_stop: int, frame: bool):
        """The marker pulses of one line, as the galvo controller drives them (docs/protocols.md):
        ``[FRAME|]LINE_START|PIXEL`` at the first pixel, ``PIXEL`` at each later one, ``LINE_STOP``
        after the last."""
        w = pixel_starts.size
        m_sync = np.empty(w + 1, np.int64)
        m_bits = np.empty(w + 1, np.uint8)
        m_sync[0] = line_start
        m_bits[0] = Marker.LINE_START | Marker.PIXEL | (Marker.FRAME if frame else 0)
        m_sync[1:w], m_bits[1:w] = pixel_starts[1:], Marker.PIXEL
        m_sync[w], m_bits[w] = line_stop, Marker.LINE_STOP
        return m_sync, m_bits

    def _raster_fixed(self, n_dwell, gap, start_sync, progress):
        h, w = self.scene.shape
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
        for r in range(h):
            starts = np.empty(w, np.int64)
            line_ev, line_or = [], []
            for c in range(w):
                starts[c] = s
                ev, n, origin = self.count_gated(r, c, n_target, limit_s, s, window, with_origin=True)
                line_ev.append(ev)
                line_or.append(origin)
                s += n
            m_sync, m_bits = self._line_markers(int(starts[0]), starts, s, frame=(r == 0))
            # markers are interleaved where each pixel's events begin
            pieces, opieces = [], []
            mk = np.zeros(m_sync.size, EVENT_DTYPE)
            mk["sync"], mk["kind"], mk["marker"] = m_sync, K.KIND_MARKER, m_bits
            mo = np.full(m_sync.size, K.ORIGIN_MARKER, np.uint8)
            j0 = 1     # [FRAME|]LINE_START|PIXEL opens the line's first pixel
            pieces.append(mk[:j0])
            opieces.append(mo[:j0])
            for c in range(w):
                if c > 0:
                    pieces.append(mk[j0 + c - 1:j0 + c])
                    opieces.append(mo[j0 + c - 1:j0 + c])
                pieces.append(line_ev[c])
                opieces.append(line_or[c])
            pieces.append(mk[-1:])
            opieces.append(mo[-1:])
            evs.append(np.concatenate(pieces))
            origins.append(np.concatenate(opieces))
            s += gap
            if progress is not None:
                progress((r + 1) * w, h * w)
        return evs, origins
