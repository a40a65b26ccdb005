"""The estimator registry (recon.estimators): the methods are its names, reconstruct runs what it
holds, a plugin of a test's own shows in ``spdepth recon --method``, a live scan and the window's
list with no other edit, and reading it loads no kernel."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
from hypothesis import given, settings as hsettings, strategies as st

from spdepth.acq.cli import main
from spdepth.recon import estimators
from spdepth.recon.errors import InputError
from spdepth.recon.detect import decide_maps
from spdepth.recon.estimate import reconstruct
from spdepth.recon.maps import DepthMaps
from spdepth.recon.model import METHODS, PIXELWISE_METHODS, SEED_PAPER, ReconSettings
from spdepth.recon.photons import PhotonStore


def centroid_fit(store, settings, b, kern, notes, progress=None):
    """A test's own estimator: each pixel's return at the mean bin of its in-window detections
    (right without background), every detection signal, no background estimated, in plain NumPy
    through the pixelwise helpers every one-surface estimator shares."""
    from spdepth.recon.pixelwise import fit_pixels, pixel_maps

    def chunk(bins, offsets, maxn, out):
        n = np.diff(offsets)
        sums = np.add.reduceat(bins.astype(np.float64), offsets[:-1]) if bins.size else np.zeros(n.size)
        with np.errstate(invalid="ignore", divide="ignore"):
            out.shift[:] = np.where(n > 0, sums / n, np.nan)
            out.var[:] = kern.rms_bins ** 2 / n
        out.amp[:] = n
        out.n_used[:] = n

    fit = fit_pixels(store, settings, b, chunk, progress)
    fit.bg[:] = np.nan
    return pixel_maps(store, settings, b, kern, notes, fit, shift_step=1.0,
                      signal=np.where(np.isfinite(fit.shift), fit.amp, 0.0))


@pytest.fixture
def centroid():
    est = estimators.register(estimators.Estimator(
        "centroid", "mean time of the detections (a test's own estimator)", centroid_fit,
        background=False))
    yield est
    estimators.unregister("centroid")


def test_methods_are_the_registry_names_and_follow_it():
    assert tuple(METHODS) == estimators.names() == ("lmf", "uos", "ml", "spatial")
    assert set(PIXELWISE_METHODS) == {n for n in METHODS if estimators.get(n).pixelwise}
    assert "surfaces" not in METHODS and estimators.get("surfaces", fits=True).max_surfaces > 1
    est = estimators.register(estimators.Estimator("late", "registered late", centroid_fit))
    try:
        assert METHODS[-1] == "late" and "late" in METHODS and "late" in PIXELWISE_METHODS
        with pytest.raises(ValueError, match="registered already"):
            estimators.register(est)
    finally:
        estimators.unregister("late")
    assert "late" not in METHODS


@pytest.mark.parametrize("name", ["", "UOS", "ml ", "spatial2", "surfaces"])
def test_settings_refuse_a_name_the_registry_does_not_hold(name):
    with pytest.raises(InputError, match="method must be one of lmf, uos, ml, spatial"):
        ReconSettings(method=name)


def test_several_surfaces_run_the_fit_each_method_names():
    for name in ("lmf", "uos", "ml"):
        assert estimators.for_settings(ReconSettings(method=name, reflectors=2)).name == "surfaces"
    assert estimators.for_settings(ReconSettings(method="spatial", reflectors="auto")).name == "spatial-surfaces"
    assert "lmf, uos and ml all run the same K-surface fit" in estimators.summaries()


@hsettings(max_examples=12, deadline=None)
@given(method=st.sampled_from(("lmf", "uos", "ml", "spatial")), seed=st.integers(0, 2**16))
def test_reconstruct_is_the_registered_estimator(method, seed):
    from spdepth.recon.resolve import resolve_model

    rng = np.random.default_rng(seed)
    b = SEED_PAPER.binning
    lists = [np.concatenate([rng.normal(3000 + 100 * p, SEED_PAPER.pulse_rms_units, 8),
                             rng.uniform(b.window_start, b.window_stop, 4)]) for p in range(12)]
    store = PhotonStore.from_lists(lists, (3, 4), SEED_PAPER.time_unit_s)
    settings = SEED_PAPER.settings(method)
    a = reconstruct(store, settings)
    # the registered estimator, then the one decision of every estimator's maps (recon.detect)
    b_maps = decide_maps(store, settings, estimators.get(method).run(store, settings, *resolve_model(store, settings)))
    for key in ("tof_s", "background", "signal", "photons", "uncertainty_s", "flags"):
        np.testing.assert_array_equal(getattr(a, key), getattr(b_maps, key))
    assert a.settings == b_maps.settings and a.settings["method"] == method


def test_reading_the_registry_loads_no_kernel():
    """--help and the window's list read the registry: numba is imported when an estimator runs."""
    code = ("import sys\n"
            "from spdepth.recon import estimators\n"
            "from spdepth.recon.model import METHODS\n"
            "print(list(METHODS), estimators.summaries() != '', 'numba' in sys.modules)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "['lmf', 'uos', 'ml', 'spatial'] True False", out.stdout + out.stderr


def test_a_plugin_shows_in_recon_help_a_live_scan_and_a_recording(centroid, tmp_path, capsys):
    assert main(["recon", "--help"]) == 0
    text = " ".join(capsys.readouterr().out.split())      # help wraps its lines
    assert "{lmf,uos,ml,spatial,centroid}" in text and "centroid: mean time of the detections" in text
    run = tmp_path / "run"
    assert main(["scan", "--sim", "--size", "6x5", "--target", "6", "--method", "centroid",
                 "--out", str(run), "--json"]) == 0
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert summary["state"] == "done"
    assert json.loads((run / "run.json").read_text())["recon"]["method"] == "centroid"
    live = DepthMaps.load_npz(run / "maps.npz")
    assert np.all(np.isnan(live.background)) and np.all(live.photons == 6)
    # the live maps are the estimator's own: its mean bin of each pixel's detections
    assert main(["recon", str(run / "recording.ptu"), "--method", "centroid", "--npz",
                 str(tmp_path / "again.npz")]) == 0
    again = DepthMaps.load_npz(tmp_path / "again.npz")
    np.testing.assert_array_equal(again.tof_s, live.tof_s)
    assert np.all(np.isfinite(live.tof_s))


def test_a_plugin_shows_in_the_windows_list(centroid, qtbot, tmp_path):
    pytest.importorskip("pytestqt")
    from PySide6 import QtCore

    from spdepth.gui.window import MainWindow

    win = MainWindow(settings=QtCore.QSettings(str(tmp_path / "s.ini"), QtCore.QSettings.IniFormat))
    qtbot.addWidget(win)
    box = win.controls.method
    items = [box.itemText(i) for i in range(box.count())]
    assert items == ["lmf", "uos", "ml", "spatial", "centroid"]
    assert box.itemData(4, QtCore.Qt.ItemDataRole.ToolTipRole) == centroid.summary
    win.shutdown(timeout_s=10)


def test_estimators_leave_scipy_stats_unimported():
    # importing scipy.stats took 1.15 s here, more than a new process's whole spatial or K-surface
    # reconstruction of a small file: the estimators take what they need from scipy.special
    import subprocess
    import sys

    code = ("import sys\n"
            "import spdepth.recon.estimators.surfaces_fit, spdepth.recon.estimators.spatial, spdepth.recon.estimate, spdepth.acq.api\n"
            "print('scipy.stats' in sys.modules)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False", out.stdout + out.stderr


def test_quantiles_from_scipy_special_are_scipy_stats():
    from scipy.stats import norm, poisson

    from spdepth.recon.estimators import surfaces_fit as SF
    from spdepth.recon.estimators.spatial import poisson_quantile

    mu = np.concatenate([[0.0], np.linspace(1e-6, 60.0, 4001)])
    for q in (0.5, 0.98, 1 - 1e-3, 1 - 1e-6):
        np.testing.assert_array_equal(poisson_quantile(q, mu), poisson.ppf(q, mu))
    # auto's threshold: where the chance of passing somewhere in the window (Rice's formula for the
    # test's field, recon.estimators.surfaces_fit) is the false-alarm rate
    for fa, n_bins, width in ((1e-3, 800, 19), (1e-6, 4000, 85), (0.05, 100, 10)):
        u = SF.auto_threshold_nats(fa, n_bins, width)
        sigma = width / (2 * np.sqrt(2 * np.log(2)))
        rice = norm.sf(np.sqrt(2 * u)) + n_bins / (2 * np.pi * np.sqrt(2) * sigma) * np.exp(-u)
        assert rice == pytest.approx(fa, rel=1e-9)

def test_the_speed_of_light_is_scipy_s():
    # written out (exact by the SI's definition of the metre): scipy.constants' import took 70 ms
    from scipy.constants import c

    from spdepth.drivers.sim.scene import C_M_PER_S as sim_c
    from spdepth.recon.maps import C_M_PER_S

    assert C_M_PER_S == sim_c == c
