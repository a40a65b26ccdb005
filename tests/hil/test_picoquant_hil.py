"""A real PicoQuant device: ``pytest tests/hil --picoquant mh150[:SERIAL] [--picoquant-lib PATH]``
(any supported family: mh150, mh160, hh400, th260, ph330).

Marked ``hardware``: skipped unless ``--picoquant`` names a device. Needs the laser sync on the
SYNC input (the checks hold with or without light on the detector). Untested so far: no lab has
run it (README, "Vendor instruments")."""

from __future__ import annotations

import numpy as np
import pytest

from spdepth.drivers.events import GENERIC_T3_RECORD_TYPES
from spdepth.drivers.events import EventKind
from spdepth.drivers.picoquant import FAMILIES, Flag, PicoQuantSettings, PicoQuantTagger

pytestmark = pytest.mark.hardware


@pytest.fixture
def device(request):
    spec = request.config.getoption("--picoquant")
    if not spec:
        pytest.skip("no PicoQuant device named (--picoquant mh150[:SERIAL])")
    model, _, serial = spec.partition(":")
    t = PicoQuantTagger.open(model, serial or None,
                             lib_path=request.config.getoption("--picoquant-lib"))
    try:
        yield t
    finally:
        t.close()


def test_identity_and_settings(device):
    assert device.identity["serial"] and device.identity["model"]
    device.configure(PicoQuantSettings())
    assert 0 < device.resolution_s < 1e-9
    # the model the device reports picks the record type (TimeHarp 260 PICO/NANO), and it is one
    # our recorder writes (the Generic T3 layout)
    assert device.hw_model in device.identity["model"]
    assert device.record_type == FAMILIES[device.family.key].record_type_of(device.hw_model)
    assert device.record_type in GENERIC_T3_RECORD_TYPES
    assert device.sync_rate_hz() > 0, "no laser sync on the SYNC input"


def test_stream_decodes_with_increasing_syncs_and_no_loss(device):
    device.configure(PicoQuantSettings())
    r = device.reader().start()
    chunks = []
    try:
        import time

        t_end = time.monotonic() + 2.0
        while time.monotonic() < t_end:
            c = r.get(timeout_s=0.1)
            if c is not None and c.size:
                chunks.append(c)
    finally:
        r.stop()
    assert r.error is None
    assert r.stats["fifo_full"] == 0 and r.stats["restarts"] == 0
    if chunks:
        ev = np.concatenate(chunks)
        assert np.all(np.diff(ev["sync"].astype(np.int64)) >= 0)
        assert not np.any(ev["kind"] == EventKind.LOST)
    assert Flag.FIFOFULL not in device.flags()
