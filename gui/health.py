"""Device health for the status bar, from the session's own per-device verdict (``Snapshot.health``:
"ok", "recovering", "failed" or "replay" for the galvo and the tagger).

The session marks a device "recovering" once a loss, reconnect or fault of that device has been
recorded (for HEALTH_RECENT_S). While a device is still gone nothing is recorded yet (the tagger's
reconnect is counted when it succeeds, the lost span when the stream resumes), so a secondary hint
remains: a running scan whose detections stopped for STALL_S shows "no data" until the session's
verdict catches up.
"""

from __future__ import annotations

from dataclasses import dataclass

from spdepth.acq.sources import HEALTH_RECENT_S

STALL_S = 0.75
"""Running without a new detection this long counts as a stalled stream (a gated dwell limit on the
simulated bench is tens of ms; a real dark pixel is capped by the dwell limit too)."""

DEVICES = ("galvo", "tagger")
OK, RECOVERED, RECOVERING, FAILED, IDLE = "ok", "recovered", "recovering", "failed", "idle"

COLOURS = {OK: "#2e9d4a", RECOVERED: "#2e9d4a", RECOVERING: "#e0a800", FAILED: "#d0342c",
           IDLE: "#8a8a8a"}
_TERMINAL = ("done", "aborted", "failed")


@dataclass(frozen=True)
class Health:
    """level: one of ok, recovered (faults seen, all well now), recovering, failed, idle;
    text: what the indicator says; devices: the per-device words shown."""

    level: str
    text: str
    tooltip: str = ""
    devices: tuple = ()

    @property
    def colour(self) -> str:
        return COLOURS[self.level]


class HealthTracker:
    """Feed every snapshot (``update``); ``health`` is the current verdict."""

    def __init__(self, live: bool = True):
        self.live = live
        self._last_det = -1
        self._last_det_t = 0.0
        self._recovering_until: dict[str, float] = {}
        self.last_elapsed_s: float | None = None
        """``elapsed_s`` of the last snapshot fed: pass it as the next ``Session.snapshot``'s
        ``faults_since_s`` so a fault recorded while the window could not look is not missed."""
        self.health = Health(IDLE, "no source")

    def update(self, snap) -> Health:
        t = snap.elapsed_s
        self.last_elapsed_s = t
        if snap.detections != self._last_det:
            self._last_det, self._last_det_t = snap.detections, t
        faults = list(snap.faults)
        tip = "\n".join(f"{f['t_s']:.1f} s  {f['kind']}: {f['what']} ({f['action']})"
                        for f in faults[-8:])
        ended = snap.state in _TERMINAL
        per = dict(snap.health or {})
        if not self.live or "replay" in per.values():
            level = FAILED if snap.state == "failed" else (IDLE if snap.state == "idle" else OK)
            text = f"recording {'failed' if level == FAILED else 'ok'}"
            tip = f"{snap.error}\n{tip}".strip() if snap.error else tip
            self.health = Health(level, text, tip, (("recording", text.split()[1]),))
            return self.health
        words = {d: per.get(d, "ok") for d in DEVICES}
        # a recovery first seen late (the window stalled) is still shown for HEALTH_RECENT_S
        # from that look, as one seen at once is
        for d, w in words.items():
            held = t < self._recovering_until.get(d, -1.0)
            if w == RECOVERING and not held:
                self._recovering_until[d] = t + HEALTH_RECENT_S
            elif w == OK and held:
                words[d] = RECOVERING
        if ended:       # nothing recovers after the end: a recent fault is history now
            words = {d: ("ok" if w == "recovering" else w) for d, w in words.items()}
        stalled = (snap.state == "running" and snap.pixels_final < snap.pixels_total
                   and self._last_det_t > 0 and t - self._last_det_t > STALL_S)
        text = " · ".join(f"{d} {w}" for d, w in words.items())
        if FAILED in words.values():
            level = FAILED
            tip = f"{snap.error or 'session failed'}\n{tip}".strip()
        elif RECOVERING in words.values():
            level = RECOVERING
        elif stalled:
            level = RECOVERING
            text += f" · no data {t - self._last_det_t:.1f} s"
        elif snap.state == "idle":
            level, text = IDLE, "connecting"
        elif faults:
            n = len(faults)
            level = RECOVERED
            text += f" ({n} fault{'s' * (n != 1)} recovered)"
        else:
            level = OK
        self.health = Health(level, text, tip or text, tuple(words.items()))
        return self.health


__all__ = ["Health", "HealthTracker", "STALL_S", "DEVICES"]
