"""The tagger contract against a real device: ``pytest tests/hil --tagger usb:VID:PID``.

Marked ``hardware``: skipped unless ``--tagger`` names a device. The real unit must speak the
protocol of docs/protocols.md ("TCSPC time tagger"); photons are optional (the stream checks hold
with or without light on the detector)."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))   # tests/ holds the shared contract
sys.path.insert(0, str(Path(__file__).resolve().parent))
from hil_support import named  # noqa: E402
from test_tagger_contract import TaggerContract  # noqa: E402

from spdepth.drivers.tagger import Tagger  # noqa: E402

pytestmark = pytest.mark.hardware


@pytest.fixture
def tagger(request):
    t = Tagger.open(named(request, "--tagger", "no real tagger named (--tagger usb:VID:PID)"))
    try:
        t.stop()   # a previous run may have left it measuring
        yield t
    finally:
        t.close()


class TestRealTaggerContract(TaggerContract):
    """The shared tagger contract, run against the device named by --tagger."""
