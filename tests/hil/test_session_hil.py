"""A whole session against real devices: ``pytest tests/hil --galvo-port PORT --tagger usb:VID:PID
[--sync-rate-hz HZ]``. Marked ``hardware``: skipped unless both devices are named. The galvo's
marker outputs must be wired to the tagger's marker inputs (docs/protocols.md); light on the
detector is optional (dark pixels end at the dwell limit and are flagged, which is checked too)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from spdepth.acq.api import scan_settings
from spdepth.acq.flags import ACQUIRING
from spdepth.acq.instruments import open_real
from spdepth.acq.plan import ScanPlan
from spdepth.acq.requests import ScanRequest
from spdepth.acq.scan_source import ScanSource
from spdepth.acq.session import AcqFlag, Session, SessionState
from spdepth.recon.model import SEED_PAPER

pytestmark = pytest.mark.hardware


@pytest.fixture
def instruments(request):
    port, url = request.config.getoption("--galvo-port"), request.config.getoption("--tagger")
    if not (port and url):
        pytest.skip("a session needs both --galvo-port and --tagger")
    inst = open_real(port, url, sync_period_s=1 / 20e6)
    try:
        yield inst
    finally:
        inst.close()


@pytest.mark.parametrize("mode", ["gated", "raster"])
def test_session_on_real_devices_ends_complete_or_flagged(instruments, tmp_path, mode):
    plan = ScanPlan(8, 6, -1.0, 1.0, -1.0, 1.0, mode=mode, target=5, dwell_s=2e-3, max_passes=3)
    request = ScanRequest(target=5, method="lmf", pulse_rms_s=SEED_PAPER.pulse_rms_s)
    settings = scan_settings(request, instruments.tagger.resolution_s)
    source = ScanSource(instruments.galvo, instruments.tagger, sync_period_s=instruments.sync_period_s)
    s = Session(plan, settings, source, out_dir=tmp_path)
    assert s.run(), "session ended"
    assert s.state == SessionState.DONE, s.error
    count, flags = s.store.count, s.acq_flags
    assert np.all(flags != ACQUIRING)
    assert np.all(count[flags == AcqFlag.COMPLETE] == 5)
    assert np.all(flags[count < 5] != AcqFlag.COMPLETE)
    run = json.loads((tmp_path / "run.json").read_text())
    assert run["devices"]["galvo"] and run["devices"]["tagger"]
    assert (tmp_path / "recording.ptu").stat().st_size > 0
