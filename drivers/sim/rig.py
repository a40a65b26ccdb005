"""The simulated bench: one photon world, one virtual clock, one mirror, one time-tagger FIFO.

The simulated galvo controller and the simulated time tagger both hold the same ``SimRig``. The
galvo firmware moves the mirror, pulses the marker lines and dwells (count-gated or fixed); the rig
turns each dwell into the photons of the scene pixel under the mirror, pushes them (and the
markers) into the tagger's FIFO in time order, and advances the virtual clock. The tagger backend
drains the FIFO. Nothing here knows about bytes on wires.
"""

from __future__ import annotations

import math
import threading
import time
from collections import deque
from dataclasses import dataclass

import numpy as np

from spdepth.drivers.events import EVENT_DTYPE, EventKind, Marker


@dataclass(frozen=True)
class FieldOfView:
    """Mirror angles (optical degrees) that map onto the scene's pixel grid: x spans the columns,
    y the rows; the centre of pixel (0, 0) sits half a pixel inside (x_min_deg, y_min_deg)."""

    x_min_deg: float = -10.0
    x_max_deg: float = 10.0
    y_min_deg: float = -10.0
    y_max_deg: float = 10.0

    def pixel_of(self, x_deg: float, y_deg: float, shape: tuple[int, int]) -> tuple[int, int] | None:
        """The (row, col) the mirror points at, or None when it points outside the scene."""
        p = int(self.pixels_of(np.array([x_deg], np.float64), np.array([y_deg], np.float64),
                               shape)[0])
        return None if p < 0 else divmod(p, shape[1])

    def pixels_of(self, x_deg: np.ndarray, y_deg: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
        """Flat scene pixel (row * W + col) under each mirror position, -1 outside the scene."""
        h, w = shape
        col = np.floor((x_deg - self.x_min_deg) / (self.x_max_deg - self.x_min_deg) * w)
        row = np.floor((y_deg - self.y_min_deg) / (self.y_max_deg - self.y_min_deg) * h)
        inside = (row >= 0) & (row < h) & (col >= 0) & (col < w)
        return np.where(inside, row * w + col, -1).astype(np.int64)

    def centre_deg(self, row: int, col: int, shape: tuple[int, int]) -> tuple[float, float]:
        """Mirror angles (x_deg, y_deg) of the centre of pixel (row, col)."""
        h, w = shape
        x = self.x_min_deg + (col + 0.5) * (self.x_max_deg - self.x_min_deg) / w
        y = self.y_min_deg + (row + 0.5) * (self.y_max_deg - self.y_min_deg) / h
        return x, y


@dataclass
class FifoStatus:
    """What the tagger's status request reports about its FIFO."""

    fill_records: int
    capacity_records: int
    overflowed: bool
    lost_records: int


def _pixel_markers(events: np.ndarray) -> int:
    """PIXEL marker rows among ``events``."""
    return int(np.count_nonzero((events["kind"] == EventKind.MARKER)
                                & (events["marker"] & Marker.PIXEL != 0)))


class SimRig:
    """Shared state of the simulated instruments. Thread-safe: the galvo emulator and the tagger
    backend run in different threads (serial reader, USB reader).

    world: a ``drivers.sim.PhotonWorld`` (anything with ``shape``, ``sync_period_s``,
           ``count_gated(row, col, n_target, dwell_limit_s, start_sync)`` and
           ``fixed_dwell(row, col, dwell_s, start_sync)`` returning ``(events, n_syncs)``).
    fov:   mirror angles that cover the scene.
    fifo_capacity_records: the tagger FIFO depth; events beyond it are dropped and counted as lost
           (HydraHarp 400: 2M records).
    keep_truth: keep every dwell's (row, col, photon events) in ``truth`` so tests can check that
           the decoded stream assigns each detection to the pixel that produced it.
    """

    def __init__(self, world, fov: FieldOfView | None = None, fifo_capacity_records: int = 2 ** 21,
                 keep_truth: bool = False):
        self.world = world
        self.fov = fov or FieldOfView()
        self.fifo_capacity_records = int(fifo_capacity_records)
        self._lock = threading.RLock()
        self._has_events = threading.Condition(self._lock)   # the tagger waits on it, never polls
        self._has_room = threading.Condition(self._lock)     # an unpaced scan waits on it
        self._last_read = 0.0               # monotonic() of the tagger's last FIFO read
        self._fifo_pixels = 0               # PIXEL markers in the FIFO: how far the host lags
        self._sync = 0                      # laser syncs since power-on; the virtual clock
        self._mirror_deg = (0.0, 0.0)
        self._fifo: deque[np.ndarray] = deque()
        self._fifo_fill = 0
        self._lost = 0
        self._overflowed = False
        self._lost_since_sync: int | None = None   # set while the FIFO is dropping records
        self._pending_lost = 0
        self.tagger_running = False
        self.truth: list[tuple[int, int, np.ndarray]] | None = [] if keep_truth else None
        self.pixels_pulsed = 0              # PIXEL marker pulses since power-on: scan progress
        self._scheduled_losses: list[tuple[str, float, int]] = []

    # ---- clock -------------------------------------------------------------------------------
    @property
    def sync(self) -> int:
        """Laser syncs since power-on."""
        return self._sync

    @property
    def now_s(self) -> float:
        """Virtual time since power-on, seconds."""
        return self._sync * self.world.sync_period_s

    def wait(self, dt_s: float) -> None:
        """Let virtual time pass with the mirror still (no dwell counting, e.g. settling)."""
        with self._lock:
            n = max(0, int(round(dt_s / self.world.sync_period_s)))
            self._sync += n

    # ---- what the galvo controller does --------------------------------------------------------
    def set_mirror(self, x_deg: float, y_deg: float) -> None:
        with self._lock:
            self._mirror_deg = (float(x_deg), float(y_deg))

    @property
    def mirror_deg(self) -> tuple[float, float]:
        return self._mirror_deg

    def current_pixel(self) -> tuple[int, int] | None:
        """Scene pixel under the mirror, or None outside the scene."""
        return self.fov.pixel_of(*self._mirror_deg, self.world.shape)

    def pulse_markers(self, mask: int) -> None:
        """The controller pulses marker lines (``drivers.events.Marker`` bits) now."""
        ev = np.zeros(1, dtype=EVENT_DTYPE)
        ev["sync"] = self._sync
        ev["kind"] = EventKind.MARKER
        ev["marker"] = mask
        with self._lock:
            if mask & Marker.PIXEL:
                self.pixels_pulsed += 1
                self._fire_scheduled_losses()
            self._push(ev)

    def count_gated_dwell(self, n_target: int, dwell_limit_s: float) -> tuple[int, float]:
        """Hold the mirror until the detector has fired ``n_target`` times or ``dwell_limit_s``
        passed. Returns (detector pulses counted, elapsed seconds)."""
        with self._lock:
            pix = self.current_pixel()
            if pix is None:
                # Pointing off the scene: nothing returns, the dwell limit expires.
                self.wait(dwell_limit_s)
                return 0, dwell_limit_s
            events, n_syncs = self.world.count_gated(pix[0], pix[1], int(n_target),
                                                     float(dwell_limit_s), self._sync)
            return self._dwell_done(pix, events, n_syncs)

    def fixed_dwell(self, dwell_s: float) -> tuple[int, float]:
        """Hold the mirror for ``dwell_s``. Returns (detector pulses counted, elapsed seconds)."""
        with self._lock:
            pix = self.current_pixel()
            if pix is None:
                self.wait(dwell_s)
                return 0, dwell_s
            events, n_syncs = self.world.fixed_dwell(pix[0], pix[1], float(dwell_s), self._sync)
            return self._dwell_done(pix, events, n_syncs)

    def scan_run(self, x_deg: np.ndarray, y_deg: np.ndarray, marker_bits: np.ndarray, *,
                 dwell_s: float, n_target: int | None = None, settle_s: float = 0.0,
                 stop_s: float = math.inf, max_records: int = 2 ** 62
                 ) -> tuple[int, np.ndarray, np.ndarray]:
        """What the galvo controller does for a run of pixels, in one step: for each pixel it
        moves the mirror to (x_deg, y_deg), waits ``settle_s``, pulses ``marker_bits`` and dwells
        (``count_gated_dwell`` with ``n_target``, else ``fixed_dwell``), exactly as those calls
        one by one would, but with one call into the world for the whole run.

        The run ends early after the first pixel that ends (with the settle after it) at or after
        virtual time ``stop_s`` (a fault due then), and before any pixel whose PIXEL pulse would
        fire a scheduled FIFO loss, so every fault hits the pixel it would hit pixel by pixel; and
        after the pixel that brings its records (markers included) to ``max_records``.
        Returns (pixels done, detector pulses counted per pixel, elapsed seconds per pixel)."""
        period = self.world.sync_period_s
        with self._lock:
            self.set_mirror(x_deg[0], y_deg[0])
            self.wait(settle_s)
            self.pixels_pulsed += 1          # the first pixel's pulse; its photons follow
            self._fire_scheduled_losses()
            n = len(x_deg)
            for kind, at, _ in self._scheduled_losses:
                if kind == "pixel":          # pulse j of the run makes pixels_pulsed + j
                    n = min(n, max(1, math.ceil(at) - self.pixels_pulsed))
                else:
                    stop_s = min(stop_s, at)
            pix = self.fov.pixels_of(np.asarray(x_deg[:n], np.float64),
                                     np.asarray(y_deg[:n], np.float64), self.world.shape)
            run = self._world_run(pix, dwell_s, n_target,
                                  max(0, int(round(settle_s / period))),
                                  max(0, int(round(dwell_s / period))), stop_s, max_records,
                                  np.asarray(marker_bits[:n], np.uint8))
            done = run.n_done
            self.pixels_pulsed += done - 1
            self._mirror_deg = (float(x_deg[done - 1]), float(y_deg[done - 1]))
            if self.truth is not None and self.tagger_running:
                opens = np.flatnonzero(run.events["kind"] == EventKind.MARKER)
                ends = np.append(opens[1:], run.events.size)
                h, w = self.world.shape
                for j in np.flatnonzero(pix[:done] >= 0):
                    r, c = divmod(int(pix[j]), w)
                    self.truth.append((r, c, run.events[opens[j] + 1:ends[j]].copy()))
            self._push(run.events)
            self._sync = int(run.starts[-1] + run.n_syncs[-1])
            self._fire_scheduled_losses()
            # an off-scene pixel waited the dwell (limit) itself, as count_gated_dwell reports it
            elapsed = np.where(pix[:done] >= 0, run.n_syncs * period, float(dwell_s))
            return done, run.counts, elapsed

    def _world_run(self, pix, dwell_s, n_target, settle, off_syncs, stop_s, max_records, bits):
        """The world's ``dwell_run`` over flat pixels ``pix``; a world that only answers pixel by
        pixel (``count_gated`` / ``fixed_dwell``, e.g. a test double) is asked pixel by pixel."""
        if hasattr(self.world, "dwell_run"):
            return self.world.dwell_run(pix, self._sync, dwell_s, n_target=n_target,
                                        settle_syncs=settle, off_syncs=off_syncs, stop_s=stop_s,
                                        max_records=max_records, marker_bits=bits)
        from spdepth.drivers.sim.world import DwellRun

        w = self.world.shape[1]
        s = self._sync
        records = 0
        parts, starts, n_syncs, counts = [], [], [], []
        for j, p in enumerate(pix):
            s += settle if j else 0
            mark = np.zeros(1, dtype=EVENT_DTYPE)
            mark["sync"], mark["kind"], mark["marker"] = s, EventKind.MARKER, bits[j]
            parts.append(mark)
            if p < 0:
                n, ev = off_syncs, mark[:0]
            elif n_target is None:
                ev, n = self.world.fixed_dwell(int(p) // w, int(p) % w, float(dwell_s), s)
            else:
                ev, n = self.world.count_gated(int(p) // w, int(p) % w, int(n_target),
                                               float(dwell_s), s)
            parts.append(ev)
            starts.append(s)
            n_syncs.append(int(n))
            counts.append(int(ev.size))
            s += int(n)
            records += 1 + ev.size
            if (s + settle) * self.world.sync_period_s >= stop_s or records >= max_records:
                break
        return DwellRun(np.concatenate(parts), None, np.array(starts, np.int64),
                        np.array(n_syncs, np.int64), np.array(counts, np.int64))

    def _dwell_done(self, pix: tuple[int, int], events: np.ndarray, n_syncs: int) -> tuple[int, float]:
        if self.truth is not None and self.tagger_running:
            self.truth.append((pix[0], pix[1], events.copy()))
        self._push(events)
        self._sync += int(n_syncs)
        self._fire_scheduled_losses()
        return int(events.size), n_syncs * self.world.sync_period_s

    # ---- what the time tagger does ---------------------------------------------------------------
    def _push(self, events: np.ndarray) -> None:
        """Append events to the FIFO if the tagger is measuring; drop and count what does not fit.

        A dropped span is reported in-band as one LOST event at the sync where loss began, so the
        stream says exactly where it has a hole."""
        if not self.tagger_running or events.size == 0:
            return
        self._has_events.notify_all()
        room = self.fifo_capacity_records - self._fifo_fill
        if room >= events.size and self._lost_since_sync is None:
            self._fifo.append(events)
            self._fifo_fill += events.size
            self._fifo_pixels += _pixel_markers(events)
            return
        if room > 0 and self._lost_since_sync is None:
            self._fifo.append(events[:room])
            self._fifo_fill += room
            self._fifo_pixels += _pixel_markers(events[:room])
            events = events[room:]
        if self._lost_since_sync is None:
            self._lost_since_sync = int(events["sync"][0])
            self._pending_lost = 0
        self._pending_lost += int(events.size)
        self._lost += int(events.size)
        self._overflowed = True

    def overflow_fifo(self, n_records: int) -> None:
        """Fault injection: the host fell behind by ``n_records``; those records are lost."""
        with self._lock:
            ev = np.zeros(int(n_records), dtype=EVENT_DTYPE)
            ev["sync"] = self._sync
            ev["kind"] = EventKind.PHOTON
            fill = self._fifo_fill
            self._fifo_fill = self.fifo_capacity_records   # force the overflow path
            self._push(ev)
            self._fifo_fill = fill

    def schedule_overflow(self, n_records: int, *, at_pixel: int | None = None,
                          at_s: float | None = None) -> None:
        """Fault injection tied to the scan, not to when the host reads: the FIFO overflows
        (``n_records`` lost) when the galvo opens pixel number ``at_pixel`` (counting PIXEL pulses
        from power-on) or when virtual time reaches ``at_s``."""
        if (at_pixel is None) == (at_s is None):
            raise ValueError("give exactly one of at_pixel, at_s")
        with self._lock:
            if at_pixel is not None:
                self._scheduled_losses.append(("pixel", float(at_pixel), int(n_records)))
            else:
                self._scheduled_losses.append(("time", float(at_s), int(n_records)))

    def _fire_scheduled_losses(self) -> None:
        if not self._scheduled_losses:
            return
        due = [x for x in self._scheduled_losses
               if (x[0] == "pixel" and self.pixels_pulsed >= x[1])
               or (x[0] == "time" and self.now_s >= x[1])]
        for item in due:
            self._scheduled_losses.remove(item)
            self.overflow_fifo(item[2])

    def wait_for_events(self, timeout_s: float) -> bool:
        """Block until the FIFO holds events (or a loss to report), at most ``timeout_s``.
        Returns whether there is something to read."""
        with self._lock:
            return self._has_events.wait_for(
                lambda: bool(self._fifo) or self._lost_since_sync is not None, timeout_s)

    def wait_for_room(self, records: int, pixels: int, stall_s: float,
                      stop: threading.Event | None = None) -> None:
        """Block (real time) while the tagger measures and its FIFO lacks room for ``records`` or
        holds more than ``pixels`` pixels (PIXEL markers), as long as its reader keeps reading
        (it read within the last ``stall_s``) and ``stop`` is not set. A scan running faster than
        real time thus stays within a few pixels of what the host has taken, as a real-time scan
        does, instead of overflowing a FIFO that real time would have drained; a reader that
        stopped reading gets the overflow."""
        with self._lock:
            while (self.tagger_running
                   and (self.fifo_capacity_records - self._fifo_fill < records
                        or self._fifo_pixels > pixels)
                   and time.monotonic() - self._last_read < stall_s
                   and not (stop is not None and stop.is_set())):
                self._has_room.wait(0.05)

    def read_events(self, max_events: int) -> np.ndarray:
        """Drain up to ``max_events`` events from the FIFO, oldest first. After a loss, the LOST
        event comes first once the FIFO holds room again, so readers see the hole in order."""
        with self._lock:
            self._last_read = time.monotonic()
            out = []
            n = 0
            while self._fifo and n < max_events:
                chunk = self._fifo[0]
                take = min(chunk.size, max_events - n)
                out.append(chunk[:take])
                self._fifo_pixels -= _pixel_markers(chunk[:take])
                n += take
                if take == chunk.size:
                    self._fifo.popleft()
                else:
                    self._fifo[0] = chunk[take:]
            self._fifo_fill -= n
            if n:
                self._has_room.notify_all()
            if self._lost_since_sync is not None and n < max_events:
                lost = np.zeros(1, dtype=EVENT_DTYPE)
                lost["sync"] = self._lost_since_sync
                lost["kind"] = EventKind.LOST
                lost["dtime"] = min(self._pending_lost, 2 ** 32 - 1)
                out.append(lost)
                self._lost_since_sync = None
            return np.concatenate(out) if out else np.zeros(0, dtype=EVENT_DTYPE)

    def clear_fifo(self) -> None:
        """Drop every queued event and any pending loss report (the tagger's START does this);
        the lost-records total since power-on is kept."""
        with self._lock:
            self._fifo.clear()
            self._fifo_fill = 0
            self._fifo_pixels = 0
            self._has_room.notify_all()
            self._lost_since_sync = None
            self._pending_lost = 0

    def fifo_status(self) -> FifoStatus:
        with self._lock:
            return FifoStatus(self._fifo_fill, self.fifo_capacity_records, self._overflowed,
                              self._lost)

    def clear_fifo_flags(self) -> None:
        """The overflow flag is sticky until the host clears it (like a hardware status latch)."""
        with self._lock:
            self._overflowed = False

    def start_tagger(self) -> None:
        with self._lock:
            self.tagger_running = True
            self._last_read = time.monotonic()   # its reader gets stall time to begin

    def stop_tagger(self) -> None:
        with self._lock:
            self.tagger_running = False
            self._has_room.notify_all()
