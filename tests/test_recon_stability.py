"""Hard cases of the estimators: empty, degenerate, extreme and invalid input."""

from __future__ import annotations


import numpy as np
import pytest
from hypothesis import given, settings as hsettings, strategies as st

from spdepth.recon.errors import InputError
from spdepth.recon.estimate import reconstruct
from spdepth.recon.maps import DepthMaps, PixelFlag
from spdepth.recon.model import (DEFAULT_MAX_BINS, METHODS, Binning, Irf, ReconSettings, build_kernel,
                                 default_bin_width, default_binning, estimate_pulse_rms_s, load_irf)
from spdepth.recon.photons import PhotonStore

UNIT_S = 8e-12
M = 201
BIN = Binning(UNIT_S, 0.0, M * 5.0, 5.0)
RMS_S = 4 * 40e-12

pytestmark = pytest.mark.filterwarnings("error")


def run(lists, method, binning=BIN, rms_s=RMS_S, **kw):
    store = PhotonStore.from_lists([np.asarray(x, dtype=float) for x in lists], (1, len(lists)), UNIT_S)
    return reconstruct(store, ReconSettings(method=method, binning=binning, pulse_rms_s=rms_s, **kw))


def check_sane(maps, binning=BIN):
    """Finite or explicitly flagged; non-negative amplitudes; tof inside the window."""
    # spatial fills a pixel without detections from its neighbours, flagged INTERPOLATED
    ok = (maps.flags != PixelFlag.NO_PHOTONS) & (maps.flags != PixelFlag.INTERPOLATED)
    has = np.isfinite(maps.tof_s)
    if maps.settings["method"] == "lmf":
        # the log-matched filter does not estimate background: NaN, and the settings say so
        assert np.all(np.isnan(maps.background)) and "lmf" in maps.settings["background"]
    else:
        assert np.all(np.isfinite(maps.background)) and np.all(maps.background >= 0)
    assert np.all(np.isfinite(maps.signal)) and np.all(maps.signal >= 0)
    assert np.all(~has | ((maps.tof_s >= binning.window_start_s) & (maps.tof_s < binning.window_stop_s)))
    # a missing tof is always explained by a flag
    assert np.all(has | (maps.flags != PixelFlag.OK))
    assert np.all(~ok | (maps.photons > 0))


@pytest.mark.parametrize("method", METHODS)
def test_zero_detections(method):
    maps = run([[], []], method)
    assert np.all(np.isnan(maps.tof_s)) and np.all(maps.flags == PixelFlag.NO_PHOTONS)
    assert np.all(maps.photons == 0) and np.all(maps.signal == 0)
    assert np.all(maps.background == 0) if method != "lmf" else np.all(np.isnan(maps.background))
    assert np.all(np.isnan(maps.uncertainty_s))


@pytest.mark.parametrize("method", METHODS)
def test_one_detection_and_one_bin(method):
    maps = run([[502.0], [502.0] * 20], method)
    check_sane(maps)
    # the return sits on the detections' bin (bin 100 holds 500..505)
    np.testing.assert_allclose(maps.tof_s[0, 1] / UNIT_S, 502.5, atol=5.0)
    assert maps.flags[0, 1] == PixelFlag.OK
    if method != "spatial":
        # one detection on its neighbour's strong return: the neighbour supports it (recon.detect)
        assert maps.flags[0, 0] == PixelFlag.OK
        np.testing.assert_allclose(maps.tof_s[0, 0] / UNIT_S, 502.5, atol=5.0)
        # one detection far from its neighbour's return is no evidence of a return
        far = run([[102.0], [802.0] * 20], method)
        check_sane(far)
        assert np.isnan(far.tof_s[0, 0]) and far.flags[0, 0] == PixelFlag.NO_RETURN


@pytest.mark.parametrize("method", METHODS)
def test_pure_background_is_sane(method, rng):
    lists = [rng.uniform(0, M * 5.0, 15) for _ in range(50)]
    check_sane(run(lists, method))


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("centre", [2.5, M * 5.0 - 2.5, -10.0, M * 5.0 + 10.0])
def test_return_at_window_edges(method, centre, rng):
    # returns at the first / last bin, and half outside the window (out-of-window photons dropped)
    lists = [centre + 20.0 * rng.standard_normal(30) for _ in range(20)]
    maps = run(lists, method)
    check_sane(maps)
    has = np.isfinite(maps.tof_s)
    assert has.sum() >= 15
    err = np.abs(maps.tof_s[has] / UNIT_S - np.clip(centre, 0, M * 5.0))
    assert np.median(err) < 40.0


@pytest.mark.parametrize("method", METHODS)
def test_million_detections_in_one_bin(method):
    maps = run([np.full(1_000_000, 300.0), np.concatenate([np.full(10, 300.0), [900.0]])], method)
    check_sane(maps)
    np.testing.assert_allclose(maps.tof_s[0, 0] / UNIT_S, 302.5, atol=2.5)
    assert maps.photons[0, 0] == 1_000_000


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("rms_s", [5000 * 40e-12, 0.05 * 40e-12])
def test_pulse_wider_than_window_and_narrower_than_bin(method, rms_s, rng):
    lists = [rng.uniform(0, M * 5.0, 15) for _ in range(10)] + [np.full(5, 500.0)]
    maps = run(lists, method, rms_s=rms_s)
    check_sane(maps)


@pytest.mark.parametrize("method", METHODS)
def test_nearly_identical_neighbouring_columns(method, rng):
    # 1 ps bins under a 360 ps pulse: adjacent columns differ by ~0.3%
    b = Binning(1e-12, 0.0, 300.0, 1.0)
    lists = [150 + 100 * rng.standard_normal(15) for _ in range(10)]
    store = PhotonStore.from_lists(lists, (1, 10), 1e-12)
    maps = reconstruct(store, ReconSettings(method=method, binning=b, pulse_rms_s=360e-12))
    check_sane(maps, b)


@pytest.mark.parametrize("method", METHODS)
def test_float32_input_same_result(method, rng):
    lists = [np.floor(rng.uniform(0, M * 5.0, 15)) for _ in range(20)]
    a = run(lists, method)
    b = run([x.astype(np.float32) for x in lists], method)
    np.testing.assert_array_equal(a.tof_s, b.tof_s)


def test_invalid_settings_refused(tmp_path):
    with pytest.raises(InputError, match="holds no bin"):
        Binning(UNIT_S, 100.0, 100.0, 5.0)
    with pytest.raises(InputError, match="positive"):
        ReconSettings(pulse_rms_s=-1e-12)
    with pytest.raises(InputError, match="bin_width"):
        Binning(UNIT_S, 0.0, 100.0, 0.0)
    with pytest.raises(InputError, match="NaN"):
        Irf((0.0, 1e-12, 2e-12), (1.0, np.nan, 1.0))
    f = tmp_path / "irf.csv"
    f.write_text("time_ps,counts\n0,1\n8,nan\n16,2\n")
    with pytest.raises(InputError, match="irf.csv"):
        load_irf(f)
    f.write_text("0,1\n8,-3\n")
    with pytest.raises(InputError, match="negative"):
        load_irf(f)
    f.write_text("0,1\nabc,def\n")
    with pytest.raises(InputError, match="line 2"):
        load_irf(f)
    with pytest.raises(InputError):
        ReconSettings(method="magic")
    with pytest.raises(InputError):
        ReconSettings(method="ml", reflectors="two")


def test_one_default_bin_rule():
    assert DEFAULT_MAX_BINS == 4096
    assert default_bin_width(4000, 45) == 5          # the paper: 360 ps pulse, 8 ps units -> 40 ps
    assert default_bin_width(4000) == 1              # pulse width unknown: one raw unit
    assert default_bin_width(10, 2) == 1             # never below one unit
    assert default_bin_width(4096 * 5, 45) == 5      # exactly at the cap
    assert default_bin_width(4096 * 5 + 1, 45) == 6  # one unit more: widened to whole units
    assert default_bin_width(200_000) == 49          # 1 ps units, 200 ns gate: 4082 bins
    for span in (1.0, 4097.0, 12345.5, 1e6):
        w = default_bin_width(span, 3.0)
        assert w == int(w) >= 1 and np.ceil(span / w) <= DEFAULT_MAX_BINS
    # from data: the window holds every detection in at most DEFAULT_MAX_BINS bins
    for hi in (4096 * 5 - 1, 4096 * 5, 4096 * 5 + 3):
        b = default_binning(np.array([0.0, float(hi)]), 8e-12, 360e-12)
        assert b.n_bins <= DEFAULT_MAX_BINS and b.bin_index(np.array([0.0, float(hi)])).min() >= 0


def test_load_irf_text_and_npy(tmp_path):
    t = np.arange(0, 400, 4.0)
    c = np.exp(-0.5 * ((t - 200) / 30) ** 2)
    (tmp_path / "a.txt").write_text("# my irf\n" + "\n".join(f"{a}\t{b}" for a, b in zip(t, c)))
    np.save(tmp_path / "b.npy", np.stack([t, c], axis=1))
    for name in ("a.txt", "b.npy"):
        irf = load_irf(tmp_path / name)
        assert irf.rms_s == pytest.approx(30e-12, rel=0.02)
    # an IRF reconstructs like the Gaussian it samples
    kern = build_kernel(BIN, irf=load_irf(tmp_path / "b.npy"))
    assert kern.rms_bins == pytest.approx(30 / 40, rel=0.03)


def test_pulse_width_estimated_from_data(rng):
    # depth varies across pixels; the within-pixel estimate must not see that
    lists = []
    for _ in range(3000):
        c = rng.uniform(1000, 3000)
        ns = rng.binomial(15, 10 / 11)
        lists.append(np.concatenate([c + 45 * rng.standard_normal(ns), rng.uniform(0, 4005, 15 - ns)]))
    store = PhotonStore.from_lists(lists, (30, 100), UNIT_S)
    est = estimate_pulse_rms_s(store.times, store.offsets, UNIT_S)
    assert est == pytest.approx(360e-12, rel=0.05)
    maps = reconstruct(store, ReconSettings(method="uos", binning=Binning(UNIT_S, 0, 4005, 5)))
    assert maps.settings["pulse_source"] == "estimated"
    assert maps.settings["pulse_rms_s"] == pytest.approx(360e-12, rel=0.05)
    # and with no binning either: derived from the data's range
    maps2 = reconstruct(store, ReconSettings(method="uos"))
    assert maps2.settings["binning_source"].startswith("derived")
    assert np.nanmedian(np.abs(maps2.tof_s - maps.tof_s)) < 40e-12


def test_npz_round_trip(tmp_path, rng):
    maps = run([rng.uniform(0, 1000, 15), []], "ml")
    maps.save_npz(tmp_path / "m.npz")
    back = DepthMaps.load_npz(tmp_path / "m.npz")
    np.testing.assert_array_equal(back.tof_s, maps.tof_s)
    np.testing.assert_array_equal(back.flags, maps.flags)
    assert back.settings == maps.settings
    with np.load(tmp_path / "m.npz") as z:
        assert set(z.files) == {"tof_s", "depth_m", "background", "signal", "photons", "iterations",
                                "uncertainty_s", "flags", "surfaces", "weak", "settings"}


def test_progress_and_reflectors(rng):
    lists = [np.concatenate([200 + 20 * rng.standard_normal(12), 700 + 20 * rng.standard_normal(12)])
             for _ in range(30)]
    calls = []
    store = PhotonStore.from_lists(lists, (5, 6), UNIT_S)
    maps = reconstruct(store, ReconSettings(binning=BIN, pulse_rms_s=RMS_S, reflectors=2),
                       progress=lambda d, t: calls.append((d, t)))
    assert calls[-1] == (30, 30)
    assert maps.tof_s.shape == (2, 5, 6)
    np.testing.assert_allclose(np.nanmedian(maps.tof_s[0]) / UNIT_S, 200, atol=10)
    np.testing.assert_allclose(np.nanmedian(maps.tof_s[1]) / UNIT_S, 700, atol=10)
    # a single surface leaves the second return empty
    one = reconstruct(PhotonStore.from_lists([200 + 20 * rng.standard_normal(15)], (1, 1), UNIT_S),
                      ReconSettings(binning=BIN, pulse_rms_s=RMS_S, reflectors=2))
    assert np.isfinite(one.tof_s[0, 0, 0]) and np.isnan(one.tof_s[1, 0, 0])


pixel_lists = st.lists(st.lists(st.floats(-50, M * 5.0 + 50, allow_nan=False), max_size=20),
                       min_size=1, max_size=6)


@hsettings(max_examples=40, deadline=None)
@given(pixel_lists, st.sampled_from(METHODS))
def test_property_outputs_sane_and_order_invariant(lists, method):
    maps = run(lists, method)
    check_sane(maps)
    rev = run([list(reversed(x)) for x in lists], method)
    np.testing.assert_array_equal(maps.tof_s, rev.tof_s)
    np.testing.assert_allclose(maps.background, rev.background, rtol=1e-9, atol=1e-15)


@pytest.mark.parametrize("method", ("uos", "ml"))
def test_error_shrinks_with_detections(method):
    rng = np.random.default_rng(5)
    errs = []
    for k in (5, 20, 80):
        lists = []
        for _ in range(300):
            ns = rng.binomial(k, 0.8)
            lists.append(np.concatenate([500 + 20 * rng.standard_normal(ns), rng.uniform(0, M * 5.0, k - ns)]))
        maps = run(lists, method)
        errs.append(np.nanmean(np.abs(maps.tof_s / UNIT_S - 500)))
    assert errs[0] > errs[1] > errs[2]
