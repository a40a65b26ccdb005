"""Pile-up: a detector and its timing channel register at most one detection per dead time, so at
high flux early photons shadow later ones, the histogram leans early (depth biased early) and the
signal is underestimated. Coates' correction undoes it on the histogram itself, before any estimator
sees it, so every estimator gains it at once.

Coates (1968): of N laser periods, a bin i that was live (the detector not dead) in L_i of them and
caught y_i detections had the probability p_i = y_i / L_i of a detection given it was live, and the
mean photons per period in it were ``lambda_i = -ln(1 - p_i)``; ``N * lambda_i`` is the count an ideal
detector would have registered. A detector that re-arms at each laser sync (one stop per period, the
classic TCSPC case) is dead after its first detection until the period ends, so ``L_i = N - sum_{j<i}
y_j``. A detector with a dead time d shorter than the period is dead at time t only when it
registered a detection within the last d (wrapping into the previous period), and registered
detections lie at least d apart, so at most one covers t: ``L_i = N - sum_{t_i - d < t_j < t_i} y_j``,
the sum taken cyclically over the period.

Bins must cover the period from the sync on (all of the histogram, not only the estimator's window:
a detection before the window shadows the window too).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit

from spdepth.recon.counts import CountStore
from spdepth.recon.errors import InputError
from spdepth.recon.photons import PhotonStore

#: Detections per laser period (in a pixel's whole histogram) above which the correction switches
#: itself on: the first-bin bias of the uncorrected histogram is of the order of this share, and the
#: simulator adds dead time from the same level (drivers.sim.scene.PILEUP_THRESHOLD).
PILEUP_THRESHOLD = 0.05
#: ``"auto"``: correct when some pixel's detections per period pass PILEUP_THRESHOLD (and the
#: periods are known); ``"on"``: always (the periods must be known); ``"off"``: never.
PILEUP_MODES = ("auto", "on", "off")
#: p_i is capped below 1 by this much (a bin holding every live period would mean infinite flux)
_P_CAP = 1e-9


@dataclass(frozen=True)
class Detector:
    """What the correction needs to know of the detector and the laser, in raw time units.

    period_units: laser period (None: unknown; then the detector is taken to re-arm at each sync).
    dead_units:   dead time after a registered detection (None: until the next sync, the classic
                  TCSPC case; a dead time of a period or more is the same).
    """

    period_units: float | None = None
    dead_units: float | None = None

    def __post_init__(self) -> None:
        for name in ("period_units", "dead_units"):
            v = getattr(self, name)
            if v is not None and not (v > 0 and math.isfinite(v)):
                raise InputError(f"{name} must be positive, got {v}")
        if self.dead_units is not None and self.period_units is None:
            raise InputError("a dead time needs the laser period (to wrap into the previous period)")

    @property
    def rearms_at_sync(self) -> bool:
        return self.dead_units is None or self.dead_units >= self.period_units


def detections_per_period(counts: CountStore | PhotonStore, periods=None) -> np.ndarray:
    """Mean detections per laser period of each pixel, (H, W); InputError when the periods are
    not known. ``counts``: a histogram (its own periods), or a photon list with ``periods`` (one
    per pixel), whose detections per pixel are its row lengths."""
    if isinstance(counts, PhotonStore):
        if periods is None:
            raise InputError("the laser periods each pixel saw are not known")
        return np.diff(counts.offsets).astype(np.float64).reshape(counts.shape) / \
            np.asarray(periods, np.float64).reshape(counts.shape)
    if counts.periods is None:
        raise InputError("the laser periods each pixel saw are not known")
    return counts.detections() / counts.periods.reshape(counts.shape)


def coates(counts: CountStore, detector: Detector = Detector()) -> CountStore:
    """The pile-up-free counts ``N * lambda_i`` of every occupied bin (module docstring), as a new
    store (same times, float counts). ``counts`` must hold the whole histogram, and its periods."""
    if counts.periods is None:
        raise InputError("Coates' correction needs the laser periods each pixel saw")
    out = np.empty_like(counts.counts)
    period = 0.0 if detector.period_units is None else float(detector.period_units)
    dead = -1.0 if detector.rearms_at_sync else float(detector.dead_units)
    _coates_kernel(counts.times, counts.counts, counts.offsets, counts.periods, period, dead, _P_CAP, out)
    return CountStore(counts.times, out, counts.offsets, counts.shape, counts.time_unit_s, counts.periods)


@njit(cache=True, nogil=True)
def _coates_kernel(times, y, offsets, periods, period, dead, cap, out):
    """out = N * -ln(1 - y / L) per entry; L the live periods of the bin (module docstring). dead < 0:
    the detector re-arms at each sync (L = N - detections earlier in the period); else the dead
    window (t - dead, t) is summed, wrapping by ``period`` before the sync."""
    for p in range(offsets.size - 1):
        o0, o1 = offsets[p], offsets[p + 1]
        n = periods[p]
        if dead < 0.0:
            before = 0.0
            for q in range(o0, o1):
                live = n - before
                pr = min(y[q] / live, 1.0 - cap) if live > 0.0 else 1.0 - cap
                out[q] = -n * math.log1p(-pr)
                before += y[q]
            continue
        # dead window sums from a running total: the entries in (t - dead, t) start at the first
        # time past t - dead (a pointer that only moves forward as t rises); before the sync, the
        # wrapped part (t - dead + period, period) is the tail past a second such pointer
        total = 0.0
        for q in range(o0, o1):
            total += y[q]
        r = o0
        r2 = o0
        cum_r = 0.0      # sum of y[o0:r]
        cum_r2 = 0.0     # sum of y[o0:r2]
        cum_q = 0.0      # sum of y[o0:q]
        for q in range(o0, o1):
            t = times[q]
            lo = t - dead
            while r < q and times[r] <= lo:
                cum_r += y[r]
                r += 1
            shade = cum_q - cum_r
            if lo < 0.0:
                while r2 < o1 and times[r2] <= lo + period:
                    cum_r2 += y[r2]
                    r2 += 1
                if r2 > q + 1:
                    shade += total - cum_r2
                else:
                    shade += total - cum_q - y[q]
            live = n - shade
            pr = min(y[q] / live, 1.0 - cap) if live > 0.0 else 1.0 - cap
            out[q] = -n * math.log1p(-pr)
            cum_q += y[q]


def correct_pileup(counts: CountStore | PhotonStore, mode: str = "auto",
                   detector: Detector = Detector(), threshold: float = PILEUP_THRESHOLD,
                   periods=None) -> tuple[CountStore | PhotonStore, dict]:
    """Coates' correction when ``mode`` (PILEUP_MODES) asks for it; returns the counts to estimate
    from and a JSON-able record of what was decided (``applied``, ``reason``, the detections per
    period seen), for the result's settings and the summary. ``counts`` may be a photon list with
    its ``periods`` (one per pixel): it is histogrammed (``CountStore.from_photons``) only when the
    correction applies, and returned as it is when not (the decision needs each pixel's detections
    only; a 512x512 file's histogram took 0.4 s)."""
    if mode not in PILEUP_MODES:
        raise InputError(f"pile-up mode must be one of {', '.join(PILEUP_MODES)}, got {mode!r}")
    rec = {"mode": mode, "applied": False, "threshold_per_period": threshold}
    if mode == "off":
        rec["reason"] = "switched off"
        return counts, rec
    if isinstance(counts, CountStore):
        periods = counts.periods
    if periods is None:
        if mode == "on":
            raise InputError("pile-up correction asked for, but the laser periods each pixel saw are "
                             "not known: give them (--periods)")
        rec["reason"] = "laser periods per pixel unknown: not corrected"
        return counts, rec
    rate = detections_per_period(counts, periods)
    worst = float(rate.max()) if rate.size else 0.0
    rec.update(max_per_period=worst, mean_per_period=float(rate.mean()) if rate.size else 0.0,
               detector={"period_units": detector.period_units, "dead_units": detector.dead_units})
    if mode == "auto" and worst <= threshold:
        rec["reason"] = f"at most {worst:.3g} detections per period: pile-up negligible"
        return counts, rec
    rec["applied"] = True
    rec["reason"] = (f"up to {worst:.3g} detections per period: Coates' correction"
                     + (f" (dead time {detector.dead_units * counts.time_unit_s * 1e9:g} ns)"
                        if not detector.rearms_at_sync else " (detector re-arms at each sync)"))
    if isinstance(counts, PhotonStore):
        counts = CountStore.from_photons(counts, periods)
    return coates(counts, detector), rec


__all__ = ["PILEUP_MODES", "PILEUP_THRESHOLD", "Detector", "coates", "correct_pileup",
           "detections_per_period"]
