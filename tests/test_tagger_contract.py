"""What every tagger (simulated or real) must do. ``TaggerContract`` needs a ``tagger`` fixture
(an open, stopped ``Tagger``); ``TestSimTaggerContract`` runs it against the simulated backend and
``tests/hil/test_tagger_hil.py`` against a real device."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from spdepth.drivers.events import EVENT_DTYPE, Marker
from spdepth.drivers.sim.rig import SimRig
from spdepth.drivers.sim.tagger_usb import SimTaggerBackend
from spdepth.drivers.tagger import DEFAULT_URL, Tagger, TaggerSettings
from spdepth.drivers.tagger import protocol as proto
from spdepth.drivers.tagger.transport import EndpointStallError


class TaggerContract:
    def test_identity(self, tagger):
        ident = tagger.identify()
        assert ident == tagger.identity
        assert ident.protocol_version == proto.PROTOCOL_VERSION
        assert 1 <= ident.n_channels <= 64 and ident.fifo_capacity_records > 0
        assert 1e-13 <= ident.base_resolution_s <= 1e-9
        assert ident.serial and ident.serial.isprintable()

    @pytest.mark.parametrize("code", [0, 3, 7])
    def test_binning_round_trip(self, tagger, code):
        b = tagger.set_binning(code)
        assert b.code == code == tagger.binning().code
        assert tagger.resolution_s == pytest.approx(tagger.identity.base_resolution_s * 2 ** code)

    @pytest.mark.parametrize("divider", proto.SYNC_DIVIDERS)
    def test_sync_divider_round_trip(self, tagger, divider):
        tagger.set_sync_divider(divider)
        assert tagger.sync_divider() == divider

    def test_markers_round_trip(self, tagger):
        tagger.set_markers(0b0110, 0b0010)
        assert tagger.markers() == proto.MarkerConfig(0b0110, 0b0010)
        tagger.set_markers(0b1111, 0b1111)
        assert tagger.markers() == proto.MarkerConfig(0b1111, 0b1111)

    def test_start_stop_and_status(self, tagger):
        assert not tagger.status().running
        tagger.start()
        try:
            s = tagger.status()
            assert s.running and s.lost_records == 0 and not s.overrun
        finally:
            tagger.stop()
        assert not tagger.status().running

    def test_settings_refused_while_running(self, tagger):
        tagger.configure(TaggerSettings(binning=3))
        tagger.start()
        try:
            with pytest.raises(EndpointStallError):
                tagger.set_binning(4)
        finally:
            tagger.stop()
        assert tagger.binning().code == 3

    def test_ack_gap_without_gap_stalls(self, tagger):
        with pytest.raises(EndpointStallError):
            tagger.ack_gap()

    def test_reader_streams_ordered_events_and_stops(self, tagger):
        tagger.configure(TaggerSettings())
        ended = []
        reader = tagger.reader(read_timeout_s=0.02, connection_lost=ended.append).start()
        chunks = []
        deadline = time.monotonic() + 0.3
        while time.monotonic() < deadline:
            chunk = reader.get(timeout_s=0.05)
            chunks.append(chunk)
        reader.stop(timeout_s=2.0)
        assert not reader.alive and ended == [None] and reader.error is None
        while (chunk := reader.get(timeout_s=0.1)) is not None:
            chunks.append(chunk)
        events = np.concatenate(chunks) if chunks else np.zeros(0, EVENT_DTYPE)
        assert events.dtype == EVENT_DTYPE
        assert np.all(np.diff(events["sync"].astype(np.int64)) >= 0)
        assert not tagger.status().running


class PoissonWorld:
    """A constant-rate photon world for the simulated rig: every pixel returns photons at
    ``rate_per_sync`` with uniform dtimes in one 100 ns period (8 ps units), two channels."""

    shape = (8, 8)
    sync_period_s = 100e-9
    resolution_s = 8e-12

    def __init__(self, rate_per_sync: float = 0.05, seed: int = 0):
        self.rate = rate_per_sync
        self.rng = np.random.default_rng(seed)

    def _events(self, start_sync: int, n_syncs: int) -> np.ndarray:
        n = self.rng.poisson(self.rate * n_syncs)
        ev = np.zeros(n, dtype=EVENT_DTYPE)
        ev["sync"] = np.sort(self.rng.integers(start_sync, start_sync + n_syncs, n))
        ev["dtime"] = self.rng.integers(0, 12500, n)
        ev["channel"] = self.rng.integers(0, 2, n)
        return ev

    def fixed_dwell(self, row, col, dwell_s, start_sync):
        n = max(1, int(round(dwell_s / self.sync_period_s)))
        return self._events(start_sync, n), n

    def count_gated(self, row, col, n_target, dwell_limit_s, start_sync):
        n_max = max(1, int(round(dwell_limit_s / self.sync_period_s)))
        ev = self._events(start_sync, n_max)
        if ev.size >= n_target:
            ev = ev[:n_target]
            return ev, int(ev["sync"][-1]) - start_sync + 1
        return ev, n_max


class TapRig(SimRig):
    """SimRig that also keeps a copy of everything offered to the tagger FIFO while it ran."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.offered: list[np.ndarray] = []

    def _push(self, events):
        if self.tagger_running and events.size and not getattr(self, "_injecting", False):
            self.offered.append(events.copy())
        super()._push(events)

    def overflow_fifo(self, n_records):
        self._injecting = True   # the injected records are not world events
        try:
            super().overflow_fifo(n_records)
        finally:
            self._injecting = False

    def offered_events(self) -> np.ndarray:
        return np.concatenate(self.offered) if self.offered else np.zeros(0, EVENT_DTYPE)


def drive_pixels(rig: SimRig, n_pixels: int, dwell_s: float = 2e-4, pause_s: float = 0.0,
                 stop: threading.Event | None = None) -> int:
    """Act as the galvo: PIXEL marker (plus LINE_START every 8th) then a fixed dwell, per pixel."""
    h, w = rig.world.shape
    for i in range(n_pixels):
        if stop is not None and stop.is_set():
            return i
        r, c = divmod(i % (h * w), w)
        rig.set_mirror(*rig.fov.centre_deg(r, c, (h, w)))
        rig.pulse_markers(Marker.PIXEL | (Marker.LINE_START if c == 0 else 0))
        rig.fixed_dwell(dwell_s)
        if pause_s:
            time.sleep(pause_s)
    return n_pixels


@pytest.fixture
def sim_bench():
    rig = TapRig(PoissonWorld(), fifo_capacity_records=1 << 16)
    backend = SimTaggerBackend(rig)
    tagger = Tagger.open(DEFAULT_URL, backend=backend)
    yield rig, backend, tagger
    tagger.close()


class TestSimTaggerContract(TaggerContract):
    @pytest.fixture
    def tagger(self, sim_bench):
        rig, backend, tagger = sim_bench
        # photons keep arriving while contract tests stream
        stop = threading.Event()
        t = threading.Thread(target=drive_pixels, args=(rig, 10 ** 6, 1e-4, 0.002, stop), daemon=True)
        t.start()
        yield tagger
        stop.set()
        t.join(2.0)
