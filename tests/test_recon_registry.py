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


def test_estimators_leave_scipy_stats_unimported():
    # importing scipy.stats took 1.15 s here, more than a new process's whole spatial or K-surface
    # reconstruction of a small file: the estimators take what they need from scipy.special
    import subprocess
    import sys

    code = ("import sys\n"
            "import spdepth.recon.multi, spdepth.recon.spatial, spdepth.recon.estimate, spdepth.acq.api\n"
            "print('scipy.stats' in sys.modules)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False", out.stdout + out.stderr


def test_quantiles_from_scipy_special_are_scipy_stats():
    from scipy.stats import chi2, poisson

    from spdepth.recon.multi import auto_threshold_nats
    from spdepth.recon.spatial import poisson_quantile

    mu = np.concatenate([[0.0], np.linspace(1e-6, 60.0, 4001)])
    for q in (0.5, 0.98, 1 - 1e-3, 1 - 1e-6):
        np.testing.assert_array_equal(poisson_quantile(q, mu), poisson.ppf(q, mu))
    # auto's threshold: half the chi2(1) quantile of the per-shift false alarm (recon.multi)
    for fa, n_bins, width in ((1e-3, 800, 19), (1e-6, 4000, 85), (0.05, 100, 10)):
        n_eff = max(1.0, n_bins / width)
        p_one = -np.expm1(np.log1p(-fa) / n_eff)
        assert auto_threshold_nats(fa, n_bins, width) == 0.5 * float(chi2.isf(2 * p_one, 1))
