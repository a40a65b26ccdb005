"""A real PicoQuant device: ``pytest tests/hil --picoquant mh150[:SERIAL] [--picoquant-lib PATH]``
(any supported family: mh150, mh160, hh400, th260, ph330).

Marked ``hardware``: skipped unless ``--picoquant`` names a device. Needs the laser sync on the
SYNC input (the checks hold with or without light on the detector). Untested so far: no lab has
run it (README, "Vendor instruments")."""

from __future__ import annotations

import sys
from contextlib import closing
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
from hil_support import chunks_for, named, open_picoquant  # noqa: E402

from spdepth.drivers.events import GENERIC_T3_RECORD_TYPES  # noqa: E402
from spdepth.drivers.events import EventKind  # noqa: E402
from spdepth.drivers.picoquant import FAMILIES, Flag, PicoQuantSettings  # noqa: E402

pytestmark = pytest.mark.hardware


@pytest.fixture
def device(request):
    spec = named(request, "--picoquant", "no PicoQuant device named (--picoquant mh150[:SERIAL])")
    with closing(open_picoquant(request, spec)) as t:
        yield t


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
    chunks = chunks_for(r)
    assert r.error is None
    assert r.stats["fifo_full"] == 0 and r.stats["restarts"] == 0
    if chunks:
        ev = np.concatenate(chunks)
        assert np.all(np.diff(ev["sync"].astype(np.int64)) >= 0)
        assert not np.any(ev["kind"] == EventKind.LOST)
    assert Flag.FIFOFULL not in device.flags()
