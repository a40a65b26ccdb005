"""Settings round-trip typed: ``ReconSettings.from_dict(s.to_dict()) == s``, also from a result's
settings record, with overrides; a damaged saved dict is an InputError."""

from __future__ import annotations

import json

import numpy as np
import pytest

from spdepth.recon.errors import InputError
from spdepth.recon.model import SEED_PAPER, Binning, Irf, ReconSettings, gaussian_irf


@pytest.mark.parametrize("settings", [
    ReconSettings(),
    SEED_PAPER.settings("ml"),
    ReconSettings(method="uos", binning=Binning(8e-12, 100, 4100, 5), irf=gaussian_irf(300e-12),
                  max_photons=30, reflectors=2, delta=1e-3, max_iterations=7),
])
def test_round_trip(settings):
    back = ReconSettings.from_dict(json.loads(json.dumps(settings.to_dict())))
    assert back == settings


def test_a_result_record_and_overrides(rng):
    from spdepth.recon.estimate import reconstruct
    from spdepth.recon.photons import PhotonStore

    store = PhotonStore.from_lists([rng.integers(2000, 6000, 15) for _ in range(4)], (2, 2), 8e-12)
    s = SEED_PAPER.settings("lmf")
    maps = reconstruct(store, s)
    assert ReconSettings.from_dict(maps.settings) == s          # extra keys of the record ignored
    given = ReconSettings.from_dict({**s.to_dict(), "irf": gaussian_irf(1e-10).to_dict(),
                                     "pulse_rms_s": None}, pulse_rms_s=2e-10, method="ml")
    assert given.irf is None and given.pulse_rms_s == 2e-10 and given.method == "ml"
    np.testing.assert_equal(Irf.from_dict(gaussian_irf(1e-10).to_dict()).arrays(),
                            gaussian_irf(1e-10).arrays())


def test_damaged_saved_settings_are_refused():
    with pytest.raises(InputError, match="saved binning"):
        ReconSettings.from_dict({"binning": {"window_start": 0}})
    with pytest.raises(InputError, match="saved pulse shape"):
        Irf.from_dict({"counts": [1, 2]})
    with pytest.raises(InputError, match="must be a dict"):
        ReconSettings.from_dict(None)
