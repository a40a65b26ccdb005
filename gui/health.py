"""Device health for the status bar, derived from the session's snapshots alone.

The snapshot has no live device state, so health is read from what it does carry: the faults the
session logged (``lost-data`` appears as soon as the stream says so; reconnect counts only at the
end), the state and error, and whether detections still arrive while the scan runs (a tagger that
left the bus shows first as a stream that went quiet).
"""

from __future__ import annotations

from dataclasses import dataclass

STALL_S = 0.75
"""Running without a new detection this long counts as a stalled stream (a gated dwell limit on the
simulated bench is tens of ms; a real dark pixel is capped by the dwell limit too)."""
RECENT_FAULT_S = 1.5
"""A lost span or fault this recent keeps the indicator amber while the scan recovers."""

OK, RECOVERED, RECONNECTING, FAILED, IDLE = "ok", "recovered", "reconnecting", "failed", "idle"

COLOURS = {OK: "#2e9d4a", RECOVERED: "#2e9d4a", RECONNECTING: "#e0a800", FAILED: "#d0342c",
           IDLE: "#8a8a8a"}

_DEVICE_WORDS = ("device", "tagger", "galvo", "usb", "serial", "port", "stream")


@dataclass(frozen=True)
class Health:
    level: str
    text: str
    tooltip: str = ""

    @property
    def colour(self) -> str:
        return COLOURS[self.level]


class HealthTracker:
    """Feed every snapshot (``update``); ``health`` is the current verdict."""

    def __init__(self, live: bool = True):
        self.live = live
        self._last_det = -1
        self._last_det_t = 0.0
        self.health = Health(IDLE, "no source")

    def update(self, snap) -> Health:
        t = snap.elapsed_s
        if snap.detections != self._last_det:
            self._last_det, self._last_det_t = snap.detections, t
        faults = list(snap.faults)
        tip = "\n".join(f"{f['t_s']:.1f} s  {f['kind']}: {f['what']} ({f['action']})"
                        for f in faults[-8:])
        n = len(faults)
        what = "devices" if self.live else "recording"
        if snap.state == "failed":
            err = snap.error or "session failed"
            dev = any(w in err.lower() for w in _DEVICE_WORDS)
            self.health = Health(FAILED, f"{'device ' if dev else ''}failed", f"{err}\n{tip}".strip())
        elif snap.state == "running" and snap.pixels_final < snap.pixels_total \
                and t - self._last_det_t > STALL_S and self._last_det_t > 0:
            self.health = Health(RECONNECTING, f"no data {t - self._last_det_t:.1f} s: reconnecting",
                                 tip)
        elif snap.state == "running" and faults and t - faults[-1]["t_s"] < RECENT_FAULT_S:
            self.health = Health(RECONNECTING, f"{faults[-1]['kind']}: recovering", tip)
        elif snap.state in ("idle", "armed") and not faults:
            self.health = Health(IDLE if snap.state == "idle" else OK,
                                 "connecting" if snap.state == "idle" else f"{what} ready", tip)
        elif faults:
            self.health = Health(RECOVERED, f"{what} ok ({n} fault{'s' * (n != 1)} recovered)", tip)
        else:
            self.health = Health(OK, f"{what} ok", tip)
        return self.health


__all__ = ["Health", "HealthTracker", "STALL_S", "RECENT_FAULT_S"]
