"""Test helpers for the galvo driver: a transcript transport (pymeasure's ``expected_protocol``
idea at the transport layer), the reply-line builder, a small Poisson photon world and rigs."""

from __future__ import annotations

import threading

import numpy as np

from spdepth.drivers.errors import DeviceTimeoutError
from spdepth.drivers.events import EVENT_DTYPE, EventKind
from spdepth.drivers.galvo.errors import ConnectionLostError
from spdepth.drivers.galvo.protocol import encode_reply
from spdepth.drivers.sim.rig import SimRig


def reply(body: str, tag: int | None) -> bytes:
    """A reply line with tag and CRC, as the controller sends it."""
    return encode_reply(body, tag)


LOST = object()
"""Transcript marker: the port vanishes when this exchange's command is written."""


class ExpectedTransport:
    """Plays a transcript: each write must be the next expected command; its reply (bytes, a
    list of lines, None for silence, or LOST for an unplug) becomes readable. ``reopens`` counts
    re-opens; ``assert_consumed()`` checks every exchange happened."""

    def __init__(self, exchanges):
        self.exchanges = list(exchanges)
        self.pos = 0
        self.lock = threading.RLock()
        self.timeout_s = 0.01
        self.url = "transcript://"
        self.is_open = True
        self.reopens = 0
        self._pending: list[bytes] = []

    def write_line(self, line: bytes) -> None:
        if not self.is_open:
            raise ConnectionLostError("transcript port is closed")
        assert self.pos < len(self.exchanges), f"unexpected extra command {line!r}"
        cmd, rep = self.exchanges[self.pos]
        self.pos += 1
        assert line == cmd, f"exchange {self.pos}: sent {line!r}, expected {cmd!r}"
        if rep is LOST:
            self.is_open = False
            raise ConnectionLostError("transcript port vanished")
        if rep is None:
            return
        self._pending.extend(rep if isinstance(rep, list) else [rep])

    def read_line(self, timeout_s=None) -> bytes:
        if not self.is_open:
            raise ConnectionLostError("transcript port is closed")
        if not self._pending:
            raise DeviceTimeoutError("transcript: no reply")
        return self._pending.pop(0)

    def reset_input(self) -> None:
        self._pending.clear()

    def reopen(self) -> None:
        self.reopens += 1
        self.is_open = True
        self._pending.clear()

    def close(self) -> None:
        self.is_open = False

    def assert_consumed(self) -> None:
        assert self.pos == len(self.exchanges), (
            f"only {self.pos} of {len(self.exchanges)} exchanges happened; next expected "
            f"{self.exchanges[self.pos][0]!r}")
        assert not self._pending, f"replies never read: {self._pending!r}"


class PoissonWorld:
    """A flat world: every pixel returns photons at ``rate_per_sync`` (Poisson per sync) with
    uniform dtimes; the same method signatures as ``drivers.sim.PhotonWorld``."""

    def __init__(self, shape=(8, 8), rate_per_sync=0.05, seed=0, sync_period_s=100e-9):
        self.shape = tuple(shape)
        self.sync_period_s = sync_period_s
        self.rate = rate_per_sync
        self.rng = np.random.default_rng(seed)
        self.calls: list[tuple] = []

    def _events(self, row, col, start_sync, n_syncs):
        k = self.rng.poisson(self.rate * n_syncs)
        syncs = np.sort(self.rng.integers(start_sync, start_sync + n_syncs, size=k))
        ev = np.zeros(k, dtype=EVENT_DTYPE)
        ev["sync"] = syncs
        ev["dtime"] = self.rng.integers(0, 1000, size=k)
        ev["kind"] = EventKind.PHOTON
        return ev

    def fixed_dwell(self, row, col, dwell_s, start_sync):
        self.calls.append(("fixed", row, col))
        n = max(1, int(dwell_s / self.sync_period_s + 1e-9))
        return self._events(row, col, start_sync, n), n

    def count_gated(self, row, col, n_target, dwell_limit_s, start_sync):
        self.calls.append(("gated", row, col))
        limit = max(1, int(dwell_limit_s / self.sync_period_s + 1e-9))
        ev = self._events(row, col, start_sync, limit)
        if ev.size >= n_target:
            ev = ev[:n_target]
            return ev, int(ev["sync"][-1]) - start_sync + 1
        return ev, limit


def poisson_rig(shape=(8, 8), rate_per_sync=0.05, seed=0) -> SimRig:
    return SimRig(PoissonWorld(shape, rate_per_sync, seed))
