"""The galvo contract against a real controller: ``pytest tests/hil --galvo-port /dev/ttyUSB0``
(any pyserial port or URL). Skipped unless --galvo-port is given. The mirror moves inside the
controller's soft limits; set them to something safe for the optics before running."""

from __future__ import annotations

import pytest

from spdepth.drivers.galvo import Galvo, ScanMode
from tests import galvo_contract as C

pytestmark = pytest.mark.hardware


@pytest.fixture(scope="module")
def galvo(request):
    port = request.config.getoption("--galvo-port")
    if not port:
        pytest.skip("no --galvo-port given")
    g = Galvo.open(port)
    yield g
    g.reset()
    g.close()


@pytest.mark.parametrize("check", C.CONTRACT, ids=lambda f: f.__name__)
def test_contract(galvo, check):
    check(galvo)


def test_contract_serpentine(galvo):
    C.check_fixed_dwell_raster(galvo, ScanMode.SERPENTINE)
