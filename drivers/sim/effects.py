"""Physical effects beyond equation (3), each a separate piece the world runs only when the scene
calls for it.

A ``Batch`` of ideal detections (sorted by sync, then time) passes through the active effects in
order: ``Jitter`` (stateless, per detection), then at most one sequential detector stage:
``DeadTime`` alone, or ``Afterpulsing`` (which also applies the dead time when the scene has
both, since an afterpulse can only follow a detection the dead detector did register).
"""

from __future__ import annotations

from abc import ABC, abstractmethod

from dataclasses import dataclass

import numpy as np

from spdepth.drivers.sim import kernels as K

PENDING_CAP = 256
"""Afterpulses waiting to fire; with afterpulse_prob < 0.5 more than a handful never pend."""


@dataclass
class Batch:
    """Detections in flight: absolute sync (int64), time after that sync in seconds (float64),
    origin code (uint8, see ``drivers.sim.kernels``), list item the detection belongs to (int32)."""

    sync: np.ndarray
    t: np.ndarray
    origin: np.ndarray
    item: np.ndarray

    @classmethod
    def empty(cls, n: int = 0) -> "Batch":
        return cls(np.empty(n, np.int64), np.empty(n, np.float64), np.empty(n, np.uint8),
                   np.empty(n, np.int32))

    def __len__(self) -> int:
        return int(self.sync.size)

    def copy(self) -> "Batch":
        return Batch(self.sync.copy(), self.t.copy(), self.origin.copy(), self.item.copy())

    def take(self, n: int) -> "Batch":
        return Batch(self.sync[:n], self.t[:n], self.origin[:n], self.item[:n])

    @classmethod
    def concat(cls, parts: list["Batch"]) -> "Batch":
        if not parts:
            return cls.empty()
        if len(parts) == 1:
            return parts[0]
        return cls(*(np.concatenate([getattr(p, f) for p in parts])
                     for f in ("sync", "t", "origin", "item")))


class DetectorState:
    """What the detector remembers between calls: its last registered detection (dead time) and
    afterpulses still to fire. Shared by all pixels, as the real detector is."""

    def __init__(self) -> None:
        self.state_i = np.zeros(3, np.int64)    # has_last, last_sync, n_pending
        self.state_t = np.zeros(1, np.float64)  # last_t
        self.pend_sync = np.zeros(PENDING_CAP, np.int64)
        self.pend_t = np.zeros(PENDING_CAP, np.float64)
        self.pend_item = np.zeros(PENDING_CAP, np.int32)

    def copy(self) -> "DetectorState":
        c = DetectorState()
        for name in ("state_i", "state_t", "pend_sync", "pend_t", "pend_item"):
            getattr(c, name)[:] = getattr(self, name)
        return c

    def restore(self, other: "DetectorState") -> None:
        for name in ("state_i", "state_t", "pend_sync", "pend_t", "pend_item"):
            getattr(self, name)[:] = getattr(other, name)

    def start_at(self, sync: int) -> None:
        """Forget what cannot affect detections from ``sync`` on: pending afterpulses that would
        have fired before it (nobody was listening), and everything when time went backwards."""
        K.start_at_kernel(self.state_i, self.pend_sync, self.pend_t, self.pend_item, int(sync))


@dataclass(frozen=True)
class Counting:
    """How a count-gated call counts: stop after ``stop_count`` detections (0 = never) that are
    recorded (dtime < range_bins) and in [win_lo, win_hi) tagger units."""

    stop_count: int = 0
    res_s: float = 1.0
    range_bins: int = 1
    win_lo: int = 0
    win_hi: int = 1


class Effect(ABC):
    """One physical effect. ``sequential`` effects need the detector state and the whole stream
    in time order; the others act on each detection alone."""

    name = ""
    sequential = False

    @abstractmethod
    def apply(self, rng, batch: Batch, state: DetectorState, sync_end: int,
              counting: Counting) -> tuple[Batch, int]:
        """Transform ``batch``; return it and how many counted detections a sequential effect
        registered (stateless effects return -1: the caller counts)."""


class Jitter(Effect):
    """Gaussian timing jitter of detector and tagger: widens the pulse to sqrt(rms^2 + jitter^2)."""

    name = "jitter"

    def __init__(self, rms_s: float, period_s: float) -> None:
        self.rms_s = float(rms_s)
        self.period_s = float(period_s)

    def apply(self, rng, batch, state, sync_end, counting):
        K.jitter_kernel(rng, batch.t, self.rms_s, self.period_s)
        K.sort_within_sync(batch.sync, batch.t, batch.origin, batch.item)
        return batch, -1


class _Sequential(Effect):
    sequential = True
    dead_s = 0.0
    ap_prob = 0.0
    ap_tau_s = 0.0

    def __init__(self, period_s: float) -> None:
        self.period_s = float(period_s)
        self._out: Batch | None = None

    def apply(self, rng, batch, state, sync_end, counting):
        n = len(batch)
        cap = n + int(n * 3 * self.ap_prob / (1 - self.ap_prob)) + PENDING_CAP + 64
        saved = state.copy()
        while True:
            # reuse the output buffer between calls: its contents are consumed before the next
            if self._out is None or len(self._out) < cap:
                self._out = Batch.empty(cap)
            out = self._out
            n_out, counted = K.detector_kernel(
                rng, batch.sync, batch.t, batch.origin, batch.item, self.period_s,
                self.dead_s, self.ap_prob, self.ap_tau_s,
                K.DetState(state.state_i, state.state_t, state.pend_sync, state.pend_t, state.pend_item),
                int(sync_end), int(counting.stop_count), float(counting.res_s),
                int(counting.range_bins), int(counting.win_lo), int(counting.win_hi),
                out.sync, out.t, out.origin, out.item)
            if n_out >= 0:
                return out.take(n_out), int(counted)
            # an afterpulse cascade overflowed the guess: start again with room to spare
            state.restore(saved)
            cap = 2 * len(out)


class DeadTime(_Sequential):
    """Non-paralysable dead time: the detector is blind for ``dead_s`` after each detection it
    registers, so at high flux early arrivals in each period shadow later ones (pile-up)."""

    name = "dead_time"

    def __init__(self, dead_s: float, period_s: float) -> None:
        super().__init__(period_s)
        self.dead_s = float(dead_s)


class Afterpulsing(_Sequential):
    """Afterpulsing: each registered detection releases, with probability ``ap_prob``, a spurious
    detection ``dead_s + Exponential(ap_tau_s)`` later (``dead_s`` = 0 without dead time)."""

    name = "afterpulsing"

    def __init__(self, ap_prob: float, ap_tau_s: float, period_s: float, dead_s: float = 0.0) -> None:
        super().__init__(period_s)
        self.ap_prob = float(ap_prob)
        self.ap_tau_s = float(ap_tau_s)
        self.dead_s = float(dead_s)


def build_effects(scene) -> list[Effect]:
    """The effect pipeline a scene calls for, in order; empty for a pure equation-(3) scene."""
    s = scene.settings
    active = scene.active_effects
    T = s.sync_period_s
    out: list[Effect] = []
    if "jitter" in active and s.jitter_rms_s > 0:
        out.append(Jitter(s.jitter_rms_s, T))
    dead = s.dead_time_s if "dead_time" in active else 0.0
    if "afterpulsing" in active and s.afterpulse_prob > 0:
        out.append(Afterpulsing(s.afterpulse_prob, s.afterpulse_tau_s, T, dead))
    elif dead > 0:
        out.append(DeadTime(dead, T))
    return out
