"""A real NI-DAQ card driving a galvo: ``pytest tests/hil --nidaq Dev1[/ao0:1]`` (moves the mirror
within +-1 V; check the servo driver's input range first). With ``--picoquant`` as well, the
card's marker lines must be wired to the PicoQuant marker inputs 1-4 (pixel, line start, line
stop, frame) and a short raster session is run end to end.

Marked ``hardware``: skipped unless ``--nidaq`` names a device. Untested so far: no lab has run it
(README, "Vendor instruments")."""

from __future__ import annotations

import sys
import time
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
from hil_support import named, open_picoquant  # noqa: E402

from spdepth.drivers.daq import DaqCalibration, DaqGalvo  # noqa: E402
from spdepth.drivers.galvo import Gate, GalvoState, ScanPattern  # noqa: E402

pytestmark = pytest.mark.hardware

SAFE = DaqCalibration(deg_per_volt_x=1.0, deg_per_volt_y=1.0, v_min=-1.0, v_max=1.0)


@pytest.fixture
def galvo(request):
    g = DaqGalvo.open(named(request, "--nidaq", "no NI-DAQ device named (--nidaq Dev1[/ao0:1])"),
                      calibration=SAFE)
    try:
        yield g
    finally:
        g.stop()
        g.park()
        g.close()


def test_a_raster_runs_to_its_last_pixel_and_parks(galvo):
    galvo.configure_scan(ScanPattern(8, 4, -0.5, 0.5, -0.5, 0.5), Gate.fixed(1e-3))
    galvo.start()
    deadline = time.monotonic() + 5
    while galvo.status().state == GalvoState.SCANNING and time.monotonic() < deadline:
        time.sleep(0.01)
    st = galvo.status()
    assert st.state == GalvoState.PARKED and st.completed == st.total == 32


def test_a_raster_beyond_the_voltage_limits_is_refused(galvo):
    from spdepth.drivers.errors import SettingError

    with pytest.raises(SettingError, match="limits"):
        galvo.configure_scan(ScanPattern(2, 2, -5, 5, 0, 0), Gate.fixed(1e-3))


def test_session_with_a_picoquant_device(request, galvo, tmp_path):
    spec = named(request, "--picoquant", "also name a PicoQuant device (--picoquant) for a session")
    from spdepth.acq.api import scan_settings
    from spdepth.acq.plan import ScanPlan
    from spdepth.acq.requests import ScanRequest
    from spdepth.acq.scan_source import ScanSource
    from spdepth.acq.session import Session, SessionState
    from spdepth.drivers.picoquant import PicoQuantSettings

    t = open_picoquant(request, spec)
    try:
        t.configure(PicoQuantSettings())
        sync = t.sync_rate_hz()
        plan = ScanPlan(8, 8, -0.5, 0.5, -0.5, 0.5, mode="raster", target=1, dwell_s=2e-3,
                        max_passes=3)
        s = Session(plan, scan_settings(ScanRequest(mode="raster", target=1), t.resolution_s),
                    ScanSource(galvo, t, sync_period_s=1 / sync), out_dir=tmp_path)
        assert s.run() == SessionState.DONE, s.error
        assert s.store.pixels_opened >= 64, "pixel markers did not reach the tagger: check wiring"
    finally:
        t.close()
