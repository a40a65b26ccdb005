"""Where a session's events come from: one interface for a live scan, a replayed recording and
(next) a vendor time tagger, so the session cannot tell them apart (DESIGN.md section 2).

A :class:`Source` owns its instruments or files and drives the acquisition; the session owns the
state machine, the store, the live reconstruction, the flags, the snapshots and the files. The
session hands the source a :class:`SourceHost` (its side of the contract) and calls, on the
session's thread::

    arm(host)  ->  run(host) -> reason  ->  close()        (close always, also after an error)

``run`` delivers chunks of ``drivers.events.EVENT_DTYPE`` events pass by pass
(``host.begin_pass(geom, position)``, ``host.process(chunk)``, ``host.end_pass()``), calls
``host.checkpoint()`` often (pause, abort, time limit, worker and output checks happen there)
and reports faults through ``host.fault(kind, what, action)`` (any thread). It returns the
:class:`AcqFlag` that pixels still short at a normal end get (``TIME_LIMIT``, ``PASS_LIMIT`` or
``INCOMPLETE``). ``health`` gives the per-device verdict the snapshots show.

The sources: ``acq.scan_source.ScanSource`` (our galvo and USB tagger, live) and
``acq.recording.ReplaySource`` (a recording). A vendor tagger (PicoQuant, Swabian) is one more class
with these methods: it may drive the galvo as ``ScanSource`` does and read records through its own
library; a source whose stream comes cut into passes delivers them with :func:`feed_passes`.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Iterable, Protocol, runtime_checkable

import numpy as np

from spdepth.acq.assign import PassGeometry
from spdepth.acq.flags import AcqFlag

HEALTH_RECENT_S = 2.0
"""A device shows "recovering" this long after a fault that touched it."""
RETRIED = "retried; nothing lost"
"""Action of a fault the driver survived without losing data (USB timeout, partial read)."""


@dataclass(frozen=True)
class FaultRecord:
    """One fault a session saw (``faults_seen`` in ``run.json``, ``fault`` lines in
    ``events.jsonl``).

    kind:   what kind ("lost-data", "tagger-reconnect", "galvo-fault", "galvo-reconnect",
            "usb-timeout", "partial-read", ...).
    t_s:    seconds since the session was created.
    what:   what happened, in words.
    action: what was done about it.
    """

    kind: str
    t_s: float
    what: str
    action: str

    def to_dict(self) -> dict:
        return {"kind": self.kind, "t_s": self.t_s, "what": self.what, "action": self.action}

    def __getitem__(self, key: str):
        """``fault["kind"]``, as when faults were dicts (acq/commands/demo.py still reads them
        so)."""
        if key not in ("kind", "t_s", "what", "action"):
            raise KeyError(key)
        return getattr(self, key)


@runtime_checkable
class SourceHost(Protocol):
    """The session as a source sees it."""

    plan: object
    """The ``acq.plan.ScanPlan`` being acquired."""
    store: object
    """The ``acq.store.PixelStore`` the chunks go into (read ``store.lines_closed`` etc.)."""
    out_dir: Path | None
    recon_settings: object
    """The estimator settings asked for (``ReconSettings``), for a recording's header."""
    info: dict

    def begin_pass(self, geom: PassGeometry, position: int | None = None) -> None:
        """A pass over ``geom`` starts; ``position``: its first record in the recording."""

    def end_pass(self, position: int | None = None, lost_end: int | None = None) -> None:
        """The pass is over; ``position``: the record of the recording where its consumed stream
        ends (records after it, up to the next pass, were not used; None: unknown);
        ``lost_end``: lost spans the source had received from the stream by then, used or not
        (a span logged at ``position`` that came later was not used; None: unknown)."""

    def process(self, chunk: np.ndarray) -> bool:
        """Feed a chunk of events; returns whether it held a lost span."""

    def checkpoint(self) -> None:
        """Honour pause (blocks) and abort (raises); raise a live-recon or output error."""

    def stop_requested(self) -> bool:
        """Pause, abort or the time limit asks the current pass to stop."""

    @property
    def pause_requested(self) -> bool: ...

    def time_up(self) -> bool: ...

    def needy(self) -> np.ndarray:
        """bool (H, W): pixels still short of the target and not final."""

    def fault(self, kind: str, what: str, action: str) -> None:
        """Record a fault (any thread)."""

    def log(self, entry: dict) -> None:
        """Append an entry to the session's event log (any thread)."""

    def flush(self) -> None:
        """Flush the session's files if due (call while the stream is quiet)."""


@runtime_checkable
class Source(Protocol):
    """What a session consumes (see the module docstring for the call order)."""

    name: str
    """"live", "replay", ... (``run.json``'s ``source``)."""
    lost_action: str
    """What a lost span in this source's stream leads to (for ``faults_seen``)."""
    warnings: list
    """Problems with the source's data the result must carry (a truncated recording, ...)."""
    first_read_t: float | None
    """monotonic time the first records were read, when the source times its stream."""
    sync_period_s: float | None
    """The laser period (s) its stream counts syncs in (None: not known)."""

    def default_gate_target(self, plan) -> int | None: ...

    def arm(self, host: SourceHost) -> None: ...

    def run(self, host: SourceHost) -> AcqFlag: ...

    def flush(self) -> None: ...

    def close(self) -> None: ...

    def health(self, recent: Iterable[FaultRecord], error: BaseException | None) -> dict: ...

    def identities(self) -> dict: ...

    def statistics(self) -> dict: ...


def feed_passes(host: SourceHost, passes, position=None) -> None:
    """Deliver recorded passes to the session: ``passes`` yields ``(PassGeometry, chunks)``,
    chunks an iterable of event arrays; ``position(i)`` gives pass ``i``'s first record (None:
    unknown). For sources whose stream is already cut into passes (a replay, a file)."""
    for i, (geom, chunks) in enumerate(passes):
        host.begin_pass(geom, None if position is None else position(i))
        for chunk in chunks:
            host.checkpoint()
            host.process(chunk)
        host.end_pass()


__all__ = ["Source", "SourceHost", "FaultRecord", "feed_passes", "RETRIED", "HEALTH_RECENT_S"]
