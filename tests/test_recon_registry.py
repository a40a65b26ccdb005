"""The estimator registry: one entry per name in METHODS, and reconstruct dispatches through it."""

from __future__ import annotations

import ast
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings as hsettings, strategies as st

from spdepth.recon.errors import InputError
from spdepth.recon.estimate import ESTIMATORS, reconstruct
from spdepth.recon.model import METHODS, PIXELWISE_METHODS, SEED_PAPER, ReconSettings
from spdepth.recon.photons import PhotonStore

RECON = Path(__file__).resolve().parents[1] / "recon"


def test_registry_names_are_methods():
    assert tuple(ESTIMATORS) == METHODS
    assert set(PIXELWISE_METHODS) < set(METHODS)
    assert all(callable(f) for f in ESTIMATORS.values())
    with pytest.raises(TypeError):
        ESTIMATORS["new"] = ESTIMATORS["ml"]     # read-only: a method is added in recon, not by a caller


@pytest.mark.parametrize("name", ["", "UOS", "ml ", "spatial2"])
def test_settings_refuse_a_name_the_registry_does_not_hold(name):
    with pytest.raises(InputError, match="method must be one of lmf, uos, ml, spatial"):
        ReconSettings(method=name)


@hsettings(max_examples=12, deadline=None)
@given(method=st.sampled_from(METHODS), seed=st.integers(0, 2**16))
def test_reconstruct_is_the_registered_estimator(method, seed):
    rng = np.random.default_rng(seed)
    b = SEED_PAPER.binning
    lists = [np.concatenate([rng.normal(3000 + 100 * p, SEED_PAPER.pulse_rms_units, 8),
                             rng.uniform(b.window_start, b.window_stop, 4)]) for p in range(12)]
    store = PhotonStore.from_lists(lists, (3, 4), SEED_PAPER.time_unit_s)
    settings = SEED_PAPER.settings(method)
    a = reconstruct(store, settings)
    b_maps = ESTIMATORS[method](store, settings, None)
    for key in ("tof_s", "background", "signal", "photons", "uncertainty_s", "flags"):
        np.testing.assert_array_equal(getattr(a, key), getattr(b_maps, key))
    assert a.settings == b_maps.settings and a.settings["method"] == method


def test_estimators_never_import_the_registry():
    """recon.estimate imports the estimators; no other recon module imports it (at any level)."""
    for path in RECON.glob("*.py"):
        if path.stem in ("estimate", "__init__"):
            continue    # the registry itself
        tree = ast.parse(path.read_text(encoding="utf-8"))
        names = {n.module for n in ast.walk(tree) if isinstance(n, ast.ImportFrom) and n.module} | \
            {a.name for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names}
        assert not any(n.endswith("recon.estimate") for n in names), path.name
