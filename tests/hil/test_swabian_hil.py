"""A real Swabian Time Tagger: ``pytest tests/hil --swabian SERIAL`` (or ``any``), with the laser
sync on input 1 and its rate in ``SPDEPTH_SYNC_RATE_HZ`` (default 20 MHz).

Marked ``hardware``: skipped unless ``--swabian`` names a device. Untested so far: no lab has run it
(README, "Vendor instruments")."""

from __future__ import annotations

import os
import sys
from contextlib import closing
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
from hil_support import chunks_for, named  # noqa: E402

from spdepth.drivers.events import EventKind  # noqa: E402
from spdepth.drivers.swabian import SwabianSettings, SwabianTagger  # noqa: E402

pytestmark = pytest.mark.hardware


@pytest.fixture
def tagger(request):
    spec = named(request, "--swabian", "no Swabian tagger named (--swabian SERIAL|any)")
    rate = float(os.environ.get("SPDEPTH_SYNC_RATE_HZ", 20e6))
    with closing(SwabianTagger.open(None if spec == "any" else spec,
                                    SwabianSettings(sync_period_s=1 / rate, event_divider=16))) as t:
        yield t


def test_stream_places_events_after_syncs_without_loss(tagger):
    r = tagger.reader().start()
    chunks = chunks_for(r)
    assert r.error is None and r.stats["overflows"] == 0
    assert r.stats["records"] > 0, "no tags: is the laser sync on input 1?"
    if chunks:
        ev = np.concatenate(chunks)
        assert np.all(np.diff(ev["sync"].astype(np.int64)) >= 0)
        assert not np.any(ev["kind"] == EventKind.LOST)
        ph = ev[ev["kind"] == EventKind.PHOTON]
        assert np.all(ph["dtime"] * tagger.resolution_s < tagger._settings.sync_period_s * 1.001)
