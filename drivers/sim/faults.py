"""Fault injection specs shared by the simulated galvo controller and the simulated time tagger.

A spec string lists faults as ``KIND@WHEN`` items separated by commas (or semicolons), e.g.
``"serial-unplug@2s, garbled-reply@40%"``:

* ``KIND`` is one of :class:`FaultKind` (``serial-unplug``, ``garbled-reply``, ...).
* ``WHEN`` is virtual time since the simulated device powered on (``2s``, ``0.5s``, ``250ms``) or a
  fraction of the current scan's pixels (``40%``; the fault fires when the scan has completed that
  share of its pixels). Each item fires once.

Inside a pyserial URL write ``%`` as ``%25`` if the rest of the URL is percent-encoded; a bare
``40%`` followed by a comma or the end of the value also survives ``urllib.parse`` unchanged.
"""

from __future__ import annotations

import re
import threading
from dataclasses import dataclass
from enum import Enum

from spdepth.drivers.errors import SettingError


class FaultKind(str, Enum):
    """Every fault a simulated device can inject; the value is the spelling used in specs."""

    SERIAL_UNPLUG = "serial-unplug"
    """Galvo: the serial port disappears (host sees SerialException) and comes back later."""
    GARBLED_REPLY = "garbled-reply"
    """Galvo: one reply arrives with corrupted bytes."""
    MISSING_REPLY = "missing-reply"
    """Galvo: one command is executed but its reply is never sent."""
    SLOW_REPLY = "slow-reply"
    """Galvo: one reply arrives later than the host's timeout (it is then stale)."""
    SERVO_FAULT = "servo-fault"
    """Galvo: the mirror servo reports a tracking error; the scan aborts, state FAULT."""
    USB_TIMEOUT = "usb-timeout"
    """Tagger: one bulk read times out."""
    PARTIAL_READ = "partial-read"
    """Tagger: one bulk read returns fewer bytes than are waiting."""
    FIFO_OVERFLOW = "fifo-overflow"
    """Tagger: the hardware FIFO overruns and records are lost (reported in-band)."""
    DEVICE_VANISH = "device-vanish"
    """Tagger: the USB device disappears from the bus."""
    DAQ_UNDERFLOW = "daq-underflow"
    """NI-DAQ galvo: the card's output buffer runs dry; the scan stops with NI's error -200621."""

    @property
    def device(self) -> str:
        """Which simulated device injects this kind: ``"galvo"`` or ``"tagger"``."""
        return "galvo" if self in _GALVO_KINDS else "tagger"


_GALVO_KINDS = frozenset({FaultKind.SERIAL_UNPLUG, FaultKind.GARBLED_REPLY,
                          FaultKind.MISSING_REPLY, FaultKind.SLOW_REPLY,
                          FaultKind.SERVO_FAULT, FaultKind.DAQ_UNDERFLOW})


@dataclass(frozen=True)
class Fault:
    """One scheduled fault: at virtual time ``at_s`` seconds or at scan fraction ``at_fraction``
    (0..1); exactly one of the two is set."""

    kind: FaultKind
    at_s: float | None = None
    at_fraction: float | None = None

    def __post_init__(self):
        if (self.at_s is None) == (self.at_fraction is None):
            raise SettingError(f"fault {self.kind.value}: give exactly one of at_s, at_fraction")

    def is_due(self, now_s: float, scan_fraction: float | None) -> bool:
        """True once virtual time ``now_s`` (seconds) or the completed share of the scan
        ``scan_fraction`` (0..1, None when no scan runs) has reached this fault's trigger."""
        if self.at_s is not None:
            return now_s >= self.at_s
        return scan_fraction is not None and scan_fraction >= self.at_fraction

    def __str__(self) -> str:
        when = f"{self.at_s:g}s" if self.at_s is not None else f"{self.at_fraction * 100:g}%"
        return f"{self.kind.value}@{when}"


_WHEN_RE = re.compile(r"^\s*([0-9]*\.?[0-9]+(?:[eE][-+]?[0-9]+)?)\s*(ms|s|%)\s*$")


def parse_faults(spec: str | None, allowed: set[FaultKind] | frozenset[FaultKind] | None = None
                 ) -> list[Fault]:
    """Parse a ``KIND@WHEN[,KIND@WHEN...]`` spec into faults, in the order given.

    ``allowed`` restricts the kinds (e.g. a galvo rejects ``usb-timeout``). An empty or None spec
    gives no faults. Raises SettingError naming the bad item for anything else."""
    if spec is None or not spec.strip():
        return []
    faults = []
    for item in re.split(r"[,;]", spec):
        item = item.strip()
        if not item:
            continue
        kind_s, sep, when_s = item.partition("@")
        if not sep:
            raise SettingError(f"fault spec {spec!r}: item {item!r} is not KIND@WHEN")
        try:
            kind = FaultKind(kind_s.strip().lower())
        except ValueError:
            known = ", ".join(k.value for k in FaultKind)
            raise SettingError(f"fault spec {spec!r}: unknown kind {kind_s.strip()!r} "
                             f"(known: {known})") from None
        if allowed is not None and kind not in allowed:
            raise SettingError(f"fault spec {spec!r}: {kind.value!r} cannot be injected here "
                             f"(allowed: {', '.join(sorted(k.value for k in allowed))})")
        m = _WHEN_RE.match(when_s)
        if m is None:
            raise SettingError(f"fault spec {spec!r}: time {when_s!r} of {item!r} is not like "
                             f"'2s', '250ms' or '40%'")
        value, unit = float(m.group(1)), m.group(2)
        if unit == "%":
            if not 0.0 <= value <= 100.0:
                raise SettingError(f"fault spec {spec!r}: {when_s!r} is outside 0..100%")
            faults.append(Fault(kind, at_fraction=value / 100.0))
        else:
            faults.append(Fault(kind, at_s=value / 1000.0 if unit == "ms" else value))
    return faults


GALVO_FAULTS = _GALVO_KINDS
"""The kinds a simulated galvo controller injects."""
TAGGER_FAULTS = frozenset(set(FaultKind) - _GALVO_KINDS)
"""The kinds a simulated time tagger injects."""


class FaultSchedule:
    """The faults still to fire for one simulated device. Thread-safe.

    ``take_due(now_s, scan_fraction)`` returns (and removes) every fault that is due, so each
    fires exactly once; ``fired`` keeps the history for tests and logs."""

    def __init__(self, faults: list[Fault] | tuple[Fault, ...] = ()):
        self._pending = list(faults)
        self.fired: list[Fault] = []
        self._lock = threading.Lock()

    @classmethod
    def from_spec(cls, spec: str | None, allowed=None) -> "FaultSchedule":
        return cls(parse_faults(spec, allowed))

    @property
    def pending(self) -> tuple[Fault, ...]:
        with self._lock:
            return tuple(self._pending)

    def take_due(self, now_s: float, scan_fraction: float | None = None) -> list[Fault]:
        """Faults due at virtual time ``now_s`` / scan fraction, removed from the schedule."""
        with self._lock:
            due = [f for f in self._pending if f.is_due(now_s, scan_fraction)]
            if due:
                self._pending = [f for f in self._pending if f not in due]
                self.fired.extend(due)
            return due
