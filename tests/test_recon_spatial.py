"""The spatial estimator (recon.estimators.spatial): its kernels against NumPy references, beating the pixelwise
oracle at 2 detections per pixel, keeping a 1 cm step, interpolated pixels flagged, and every output
finite or flagged. Scenes are simulated here with NumPy (count-gated: N in-window detections per pixel,
each signal with probability SBR / (1 + SBR)), so the oracle is exact: the mean of each pixel's
signal detection times."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from numpy.testing import assert_allclose, assert_array_equal

import reference_spatial as ref
from spdepth.recon.estimators import spatial_kernels as SK
from spdepth.recon.errors import InputError
from spdepth.recon.estimate import reconstruct
from spdepth.recon.maps import C_M_PER_S, PixelFlag
from spdepth.recon.model import Binning, ReconSettings
from spdepth.recon.photons import PhotonStore

UNIT_S = 8e-12
BIN_UNITS, M = 5.0, 801
RMS_UNITS = 45.0            # 360 ps: 5.4 cm of depth per detection
BINNING = Binning(UNIT_S, 0.0, M * BIN_UNITS, BIN_UNITS)
CM_UNITS = 0.02 / C_M_PER_S / UNIT_S    # raw units of round-trip time per cm of depth


def settings(method):
    return ReconSettings(method=method, binning=BINNING, pulse_rms_s=RMS_UNITS * UNIT_S)


def simulate(tof_units, n, sbr, seed):
    """(store, oracle tof in units) for a count-gated scan of the (H, W) map of return times."""
    rng = np.random.default_rng(seed)
    h, w = tof_units.shape
    npx = h * w
    ns = rng.binomial(n, sbr / (1 + sbr), npx)
    is_sig = np.arange(n)[None, :] < ns[:, None]
    t = np.where(is_sig, tof_units.ravel()[:, None] + RMS_UNITS * rng.standard_normal((npx, n)),
                 rng.uniform(0, M * BIN_UNITS, (npx, n)))
    with np.errstate(invalid="ignore"):
        oracle = np.where(ns > 0, np.where(is_sig, t, 0).sum(axis=1) / np.maximum(ns, 1), np.nan)
    t = rng.permuted(t, axis=1)
    lists = [row[(row >= 0) & (row < M * BIN_UNITS)] for row in t]
    return PhotonStore.from_lists(lists, (h, w), UNIT_S), oracle.reshape(h, w)


def smooth_scene(h=48, w=48):
    """A tilted plane with a bump and a 30 cm step: piecewise smooth."""
    yy, xx = np.mgrid[0:h, 0:w]
    depth_cm = 300 + 0.4 * xx + 0.2 * yy + 3 * np.exp(-((xx - 16) ** 2 + (yy - 20) ** 2) / 60.0)
    depth_cm = depth_cm + np.where(xx > 30, 30.0, 0.0)
    return 1500 + (depth_cm - 300) * CM_UNITS


def mae(maps, tof_units):
    return float(np.mean(np.abs(maps.tof_s / UNIT_S - tof_units)))


# ------------------------------------------------------------------------------------------------
# kernels against their references


@pytest.fixture(scope="module", params=[(6, 1.0, 3), (50, 0.3, 40), (200, 0.3, 150)],
                ids=["6-per-pixel", "50-per-pixel", "200-per-pixel"])
def small_store(request):
    """(store, largest s_min to draw): a few detections per pixel, and enough that the kernels take
    their other paths (the censoring's two-pointer walk when many detections of a pixel are still
    short of support; the bucket sort above BUCKET_ABOVE detections)."""
    n, sbr, s_max = request.param
    store, _ = simulate(smooth_scene(9, 11), n, sbr, seed=4)
    return store, s_max


def _shifts(store, max_photons=-1):
    x = np.empty(store.times.size)
    off = np.empty(store.offsets.size, np.int64)
    n = SK.window_shifts(store.times, store.offsets, 100.0, 3900.0, BIN_UNITS, max_photons, x, off)
    return x[:n], off


def test_window_shifts_matches_reference(small_store):
    small_store, _ = small_store
    for maxp in (-1, 3):
        x, off = _shifts(small_store, maxp)
        want = ref.window_shifts(small_store.times, small_store.offsets, 100.0, 3900.0, BIN_UNITS, maxp)
        assert_array_equal(np.diff(off), [v.size for v in want])
        assert_allclose(x, np.concatenate(want))


@pytest.mark.parametrize("n", [20, 60, 200])
def test_window_shifts_sorts_equal_times_like_the_reference(n):
    # times on a coarse grid repeat within a pixel: the rank sort's equal-value branch (up to
    # BUCKET_ABOVE) and the bucket sort above it must still give each pixel's sorted list
    store, _ = simulate(smooth_scene(5, 6), n, 0.3, seed=2)
    times = np.round(store.times / 50.0) * 50.0
    assert np.unique(times[store.offsets[0]:store.offsets[1]]).size < n
    x = np.empty(times.size)
    off = np.empty(store.offsets.size, np.int64)
    k = SK.window_shifts(times, store.offsets, 100.0, 3900.0, BIN_UNITS, -1, x, off)
    want = ref.window_shifts(times, store.offsets, 100.0, 3900.0, BIN_UNITS, -1)
    assert_array_equal(np.diff(off), [v.size for v in want])
    assert_array_equal(x[:k], np.concatenate(want))


@pytest.mark.parametrize("width", [3.0, 27.0, 400.0])
def test_window_counts_matches_reference(small_store, width):
    small_store, _ = small_store
    x, off = _shifts(small_store)
    h, w = small_store.shape
    lists = [x[off[p]:off[p + 1]] for p in range(h * w)]
    nc = int(np.ceil(M / width))
    for radius in (1, 2):
        got = np.empty((h * w, nc), np.int32)
        SK.window_counts(x, np.ones(x.size, np.int32), off, h, w, radius, width, got)
        assert_array_equal(got, ref.window_counts(lists, h, w, radius, width, nc))


def _support_bound(counts, x, tau, width):
    """The window's detections in the coarse bins that [x - tau, x + tau] touches (counts cumulative)."""
    last = counts.size - 1
    k0 = np.clip(((x - tau + 0.5) / width).astype(np.int64), 0, last)
    k1 = np.clip(((x + tau + 0.5) / width).astype(np.int64), 0, last)
    return counts[k1] - np.where(k0 > 0, counts[k0 - 1], 0)


def test_censor_fit_matches_reference(small_store):
    # with and without the coarse window counts: the bounds only skip counting detections that
    # cannot reach their threshold, so every output is the same
    small_store, s_max = small_store
    x, off = _shifts(small_store)
    h, w = small_store.shape
    rng = np.random.default_rng(0)
    s_min = rng.integers(1, s_max + 1, h * w)
    sigma = RMS_UNITS / BIN_UNITS
    tau = 1.5 * sigma
    lists = [x[off[p]:off[p + 1]] for p in range(h * w)]
    for radius in (1, 2):
        want = ref.censor_fit(lists, h, w, radius, tau, s_min, sigma, float(M), 4)
        unbounded = None
        for width in (None, 2 * tau, 7.0):
            nc = 0 if width is None else int(np.ceil(M / width))
            counts = np.empty((h * w, nc), np.int32)
            if width is not None:
                SK.window_counts(x, np.ones(x.size, np.int32), off, h, w, radius, width, counts)
                # some detection's bound does fall short of its threshold (the path is taken)
                assert any((_support_bound(counts[p], lists[p], tau, width) <= s_min[p]).any()
                           for p in range(h * w))
            got = [np.empty(h * w), np.empty(h * w), np.empty(h * w), np.empty(h * w, np.int64),
                   np.empty(h * w, np.int64)]
            cs = SK.CensorSettings(h, w, radius, tau, sigma, float(M), 4, width or 1.0)
            SK.censor_fit(x, np.ones(x.size, np.int32), off, s_min, counts, cs, *got)
            for g, wv in zip(got, want):
                assert_allclose(g, wv, rtol=1e-10, atol=1e-12)
            assert (got[4] > 0).any() and (got[4] < got[3]).any()      # some kept, some censored
            if unbounded is None:
                unbounded = got
            for g, u in zip(got, unbounded):
                assert_array_equal(g, u)


@pytest.mark.parametrize("n, sbr, bins", [(50, 0.3, "narrow"), (50, 10.0, "wide"), (20, 1.0, "wide"),
                                           (20, 10.0, None)])
def test_bounded_censoring_changes_no_output(monkeypatch, n, sbr, bins):
    # frames with many detections per pixel (spatial.BOUND_FROM), or fewer but with much background
    # (BOUND_FROM_BACKGROUND), bound the support by coarse window counts first, narrow ones where
    # background dominates: the maps are the same bits as with exact counts alone
    from spdepth.recon.estimators import spatial

    store, _ = simulate(smooth_scene(24, 24), n, sbr, seed=7)
    widths = []
    real = SK.window_counts
    monkeypatch.setattr(SK, "window_counts", lambda *a: widths.append(a[6]) or real(*a))
    bounded = reconstruct(store, settings("spatial"))
    tau = spatial.TAU_RMS * RMS_UNITS / BIN_UNITS
    want = {"narrow": [pytest.approx(spatial.NARROW_COUNT_BIN_TAU * tau)],
            "wide": [pytest.approx(spatial.COUNT_BIN_TAU * tau)], None: []}[bins]
    assert widths == want
    monkeypatch.setattr(spatial, "BOUND_FROM", 10 ** 9)
    monkeypatch.setattr(spatial, "BOUND_FROM_BACKGROUND", 10 ** 9)
    exact = reconstruct(store, settings("spatial"))
    assert len(widths) == len(want)
    for name in ("tof_s", "background", "signal", "uncertainty_s", "flags", "photons"):
        assert_array_equal(getattr(bounded, name), getattr(exact, name))
    assert bounded.settings == exact.settings


def test_local_mean_and_tv_match_reference():
    rng = np.random.default_rng(1)
    f = rng.normal(size=(13, 17))
    wt = np.where(rng.uniform(size=f.shape) < 0.2, 0.0, rng.uniform(0.5, 3, f.shape))
    wt[:4, :5] = 0.0
    got = np.empty_like(f)
    SK.local_mean(f, wt, 1, got)
    assert_allclose(got, ref.local_mean(f, wt, 1), equal_nan=True)
    z0 = np.where(np.isfinite(got), got, 0.0)
    z = z0.copy()
    SK.tv_pdhg(f, wt, 0.7, z, 40, *(np.empty_like(f) for _ in range(3)))
    assert_allclose(z, ref.tv_pdhg(f, wt, 0.7, z0, 40), rtol=1e-10, atol=1e-12)
    # it descends: many iterations beat the start and approach a minimum
    z_long = z0.copy()
    SK.tv_pdhg(f, wt, 0.7, z_long, 2000, *(np.empty_like(f) for _ in range(3)))
    assert ref.tv_objective(z_long, f, wt, 0.7) < ref.tv_objective(z0, f, wt, 0.7)
    assert ref.tv_objective(z_long, f, wt, 0.7) <= ref.tv_objective(z, f, wt, 0.7) + 1e-6


def test_tv_of_many_copies_is_tv_of_each():
    # the uncertainty's bootstrap smooths its copies in one parallel call: the same as one by one
    rng = np.random.default_rng(2)
    wt = np.where(rng.uniform(size=(11, 14)) < 0.3, 0.0, rng.uniform(0.5, 3, (11, 14)))
    fs = rng.normal(size=(5, 11, 14))
    zs = rng.normal(size=fs.shape)
    want = zs.copy()
    for j in range(fs.shape[0]):
        SK.tv_pdhg(fs[j], wt, 0.8, want[j], 30, *(np.empty_like(wt) for _ in range(3)))
    SK.tv_pdhg_many(fs, wt, 0.8, zs, 30)
    assert_array_equal(zs, want)


def test_the_uncertainty_is_the_spread_of_the_smoothing_over_noisy_copies():
    # regulariser_variance against its definition: a flat patch of weak data is fused by TV, so its
    # pixels' variance lies far below one pixel's own 1 / wt (the former neighbour rule's 1 / (wt +
    # 4 wt) at best); a lone pixel of strong data among none keeps about its own
    from spdepth.recon.estimators.spatial import _regularise, regulariser_variance

    wt = np.full((20, 20), 1.0)
    f = np.zeros((20, 20))
    z, reach = _regularise(f, wt, SK)
    var = regulariser_variance(f, wt, z, reach, SK, probes=64)
    assert np.all(np.isfinite(var)) and np.median(var) < 0.2 * (1 / (1.0 + 4.0))
    wt1 = np.zeros((9, 9))
    wt1[4, 4] = 400.0
    z1, reach1 = _regularise(np.zeros((9, 9)), wt1, SK)
    var1 = regulariser_variance(np.zeros((9, 9)), wt1, z1, reach1, SK, probes=64)
    assert var1[4, 4] == pytest.approx(1 / 400.0, rel=0.4)


# ------------------------------------------------------------------------------------------------
# accuracy


@pytest.mark.parametrize("sbr", [1.0, 10.0])
def test_beats_the_pixelwise_oracle_at_two_detections(sbr):
    tof = smooth_scene()
    store, oracle = simulate(tof, 2, sbr, seed=int(sbr))
    maps = reconstruct(store, settings("spatial"))
    ml = reconstruct(store, settings("ml"))
    # censoring at the stated false-alarm rate per pixel (--false-alarm, recon.estimators.spatial.
    # censor_alpha) keeps no detection of some pixels; those are filled from the neighbours only
    # where a detection of their own agrees (measured: 73.8% of pixels at SBR 1, 98.7% at SBR 10)
    assert np.isfinite(maps.tof_s).mean() >= (0.7 if sbr < 5 else 0.95)
    # the oracle has no estimate where a pixel got no signal detection: count those as the ML
    # does (it has to guess too), i.e. compare on the pixels the oracle covers
    have = np.isfinite(oracle) & np.isfinite(maps.tof_s)
    err_oracle = float(np.mean(np.abs(oracle - tof)[have]))
    err = float(np.mean(np.abs(maps.tof_s / UNIT_S - tof)[have]))
    assert err <= 0.6 * err_oracle, (err, err_oracle)
    # two detections alone seldom pass ml's test for a return (recon.detect); the neighbours'
    # support adds the pixels whose own ml depth lies on the surface they see: ml reports a depth
    # on part of the frame (about 43% at SBR 1, 89% at SBR 10), spatial on more, and no worse where
    # both do
    ml_has = np.isfinite(ml.tof_s)
    assert 0.2 < ml_has.mean() < 0.95 and ml_has.mean() < np.isfinite(maps.tof_s).mean()
    both = ml_has & np.isfinite(maps.tof_s)
    assert np.mean(np.abs(maps.tof_s / UNIT_S - tof)[both]) <= np.mean(np.abs(ml.tof_s / UNIT_S - tof)[both])


def test_keeps_a_one_cm_step():
    # columns in blocks of 8 alternating between 3.00 m and 3.01 m; 15 detections, SBR 10: the
    # pixelwise ML has no smear at all (it never looks at a neighbour), so the spatial estimate
    # may move at most one pixel's worth of the step across each edge
    h, w, block = 64, 64, 8
    raised = (np.arange(w) // block) % 2 == 1
    tof = 1500 + np.tile(np.where(raised, 1.0, 0.0) * CM_UNITS, (h, 1))
    store, _ = simulate(tof, 15, 10.0, seed=7)
    maps = reconstruct(store, settings("spatial"))
    ml = reconstruct(store, settings("ml"))
    prof = (np.mean(maps.tof_s / UNIT_S, axis=0) - 1500) / CM_UNITS
    aligned = [prof[e - 4:e + 4] if raised[e] else 1 - prof[e - 4:e + 4] for e in range(block, w, block)]
    x = np.mean(aligned, axis=0)            # 0 before the edge (index 4), 1 after
    smear = x[:4].sum() + (1 - x[4:]).sum()
    assert smear <= 1.0, np.round(x, 2)
    assert x[4] - x[3] > 0.5                 # a step, not a ramp
    assert mae(maps, tof) < mae(ml, tof)


# ------------------------------------------------------------------------------------------------
# flags, stability, settings


def test_pixels_without_detections_are_interpolated_and_flagged():
    tof = smooth_scene(24, 24)
    store, _ = simulate(tof, 5, 10.0, seed=3)
    holes = [(5, 5), (12, 7), (20, 20)]
    store = store.without_pixels([r * 24 + c for r, c in holes])
    maps = reconstruct(store, settings("spatial"))
    for r, c in holes:
        assert maps.flags[r, c] == PixelFlag.INTERPOLATED
        assert maps.photons[r, c] == 0 and maps.signal[r, c] == 0
        assert np.isfinite(maps.uncertainty_s[r, c])
        # the value comes from the neighbours: within a few cm of the truth
        assert abs(maps.tof_s[r, c] / UNIT_S - tof[r, c]) < 3 * CM_UNITS
    assert maps.settings["spatial"]["interpolated"] >= len(holes)


def test_every_output_finite_or_flagged():
    tof = smooth_scene(20, 20)
    store, _ = simulate(tof, 3, 0.5, seed=5)
    # a block with no data at all, beyond the fill radius: left NaN and flagged, never a guess
    store = store.without_pixels([r * 20 + c for r in range(0, 8) for c in range(0, 8)])
    maps = reconstruct(store, settings("spatial"))
    ok = maps.flags == PixelFlag.OK
    for a in (maps.tof_s, maps.depth_m, maps.uncertainty_s, maps.background, maps.signal):
        assert np.all(np.isfinite(a[ok]))
    assert np.all(np.isfinite(maps.background)) and np.all(maps.background >= 0)
    nan = ~np.isfinite(maps.tof_s)
    assert nan[2, 2] and maps.flags[2, 2] == PixelFlag.NO_PHOTONS
    assert np.all(np.isin(maps.flags[nan], [PixelFlag.NO_PHOTONS, PixelFlag.NO_SIGNAL]))
    assert np.all(np.isfinite(maps.uncertainty_s[~nan]))
    assert np.all(maps.uncertainty_s[~nan] > 0)


def test_empty_store_and_bad_settings():
    store = PhotonStore(np.zeros(0), np.zeros(17, np.int64), (4, 4), UNIT_S)
    maps = reconstruct(store, settings("spatial"))
    assert np.all(np.isnan(maps.tof_s)) and np.all(maps.flags == PixelFlag.NO_PHOTONS)
    with pytest.raises(InputError, match="reflectors"):
        ReconSettings(method="spatial", reflectors=0)
    assert maps.settings["method"] == "spatial" and "spatial" in maps.settings


def test_uncertainty_roughly_calibrated():
    tof = smooth_scene()
    store, _ = simulate(tof, 5, 10.0, seed=9)
    maps = reconstruct(store, settings("spatial"))
    z = (maps.tof_s / UNIT_S - tof) / (maps.uncertainty_s / UNIT_S)
    iqr = np.subtract(*np.nanpercentile(z, [75, 25]))
    assert 1.349 * 0.6 <= iqr <= 1.349 * 1.5, iqr


def _row(lists):
    return PhotonStore.from_lists([np.asarray(x, dtype=float) for x in lists], (1, len(lists)), UNIT_S)


def test_window_about_the_pulse_width_censors_nothing():
    # tests/test_recon_hard_cases.py's one-bin case: a window of a few bins, pulse far wider
    maps = reconstruct(_row([[100.0, 100.0, 101.0], [100.0], [102.0, 100.5]]),
                       ReconSettings(method="spatial", pulse_rms_s=360e-12))
    assert np.all(maps.flags == PixelFlag.OK)
    assert np.all(np.abs(maps.tof_s / UNIT_S - 101) <= 5)
    assert np.all(np.isfinite(maps.uncertainty_s))


def test_sub_bin_pulse_and_a_lone_pixel():
    # a pulse of 0.05 bins: the pixels with a tight cluster are fitted; the one whose two
    # detections are 1.2 bins apart (24 pulse widths: no support) keeps none, and neither lies
    # near the neighbours' surface (each 0.6 bins, 12 pulse widths, off it): no return, not filled
    b = Binning(UNIT_S, 0.0, 1000.0, 5.0)
    maps = reconstruct(_row([[499.9] * 5 + [500.1] * 5, [502.0] * 3, [497.0, 503.0]]),
                       ReconSettings(method="spatial", binning=b, pulse_rms_s=0.05 * 40e-12))
    assert_array_equal(maps.flags[0], [PixelFlag.OK, PixelFlag.OK, PixelFlag.NO_RETURN])
    assert maps.signal[0, 0] == pytest.approx(10, rel=0.01) and maps.signal[0, 1] == pytest.approx(3, rel=0.01)
    assert np.all(np.abs(maps.tof_s[0, :2] / UNIT_S - 501) < 3) and np.isnan(maps.tof_s[0, 2])
    # a detection of its own on the first neighbour's surface: the neighbour supports it
    maps = reconstruct(_row([[499.9] * 5 + [500.1] * 5, [502.0] * 3, [497.0, 500.0]]),
                       ReconSettings(method="spatial", binning=b, pulse_rms_s=0.05 * 40e-12))
    assert maps.flags[0, 2] == PixelFlag.OK and abs(maps.tof_s[0, 2] / UNIT_S - 500.0) < 0.5


# ------------------------------------------------------------------------------------------------
# the CLI


def test_cli_recon_spatial_on_simulated_ptu_and_mat(tmp_path, capsys, shared_data):
    import json

    import scipy.io

    from spdepth.acq.cli import main

    ptu = tmp_path / "steps.ptu"
    assert main(["simulate", "--scene", "steps", "--size", "24x16", "--ppp", "5", "--sbr", "1",
                 "--seed", "1", "--ptu", str(ptu)]) == 0
    # no pulse option: the response is measured from the data, as for the pixelwise methods
    out = tmp_path / "maps.npz"
    assert main(["recon", str(ptu), "--method", "spatial", "--npz", str(out), "--json"]) == 0
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    # 5 detections at SBR 1: censoring at the stated false-alarm rate keeps none of a few pixels'
    # (362 of 384 reported when this was written), which are then no return, never a guess
    assert summary["method"] == "spatial" and summary["pixels_with_estimate"] >= 0.9 * 24 * 16
    with np.load(out) as z:
        depth, flags = z["depth_m"], z["flags"]
    with np.load(tmp_path / "steps.truth.npz") as z:
        err = np.abs(depth - z["depth_m"])[np.isfinite(depth)]
    assert np.median(err) < 0.02 and np.mean(err > 0.1) < 0.02
    assert set(np.unique(flags)) <= {PixelFlag.OK, PixelFlag.INTERPOLATED, PixelFlag.NO_RETURN}
    assert np.all(np.isnan(depth[flags == PixelFlag.NO_RETURN]))
    # the seed paper's mannequin at 2 detections per pixel (a crop, to stay fast)
    cells = scipy.io.loadmat(shared_data / "fpi/mannequin_face_8ppp.mat")["Ts"][120:160, 140:180]
    mat = tmp_path / "crop.mat"
    scipy.io.savemat(mat, {"Ts": cells})
    assert main(["recon", str(mat), "--method", "spatial", "--time-unit-ps", "8", "--window-ps",
                 "16000:48000", "--bin-ps", "40", "--pulse-rms-ps", "360", "--max-photons", "2",
                 "--json"]) == 0
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    # 1586 of 1600 when this was written: a pixel without a return is no longer filled by its neighbours
    assert summary["pixels_with_estimate"] >= 0.97 * 40 * 40 and 4.2 < summary["depth_m_median"] < 4.5


@pytest.mark.parametrize("sbr", [0.1, 1.0, 10.0])
def test_background_share_measures_the_frame_without_a_model(sbr):
    # what picks the censoring bounds' coarse bins: about the true background share
    from spdepth.recon.estimators.spatial import background_share

    store, _ = simulate(smooth_scene(40, 40), 40, sbr, seed=3)
    x, off = _shifts(store)
    share = background_share(x, np.ones(x.size, np.int32), off, RMS_UNITS / BIN_UNITS)
    true = 1.0 / (1.0 + sbr)
    # the densest 5-RMS span of a pixel holds its signal and the background that falls there
    assert true - 0.12 <= share <= true + 0.02, (share, true)
    assert background_share(x, np.ones(x.size, np.int32), off, RMS_UNITS / BIN_UNITS, sample=50) == pytest.approx(share, abs=0.08)


def test_censoring_holds_the_stated_false_alarm_rate_on_background_alone():
    # 64 x 64 pixels of 50 background detections each (art_top.mat's density) and no return: a
    # pixel keeps a detection (and so reports a return, OK) at most at the stated rate per pixel
    # (--false-alarm; censor_alpha over its 50 tests). A fixed 0.02 per detection, as before,
    # let about 1 - 0.98^50 = 64% of them through.
    rng = np.random.default_rng(3)
    h = w = 64
    n = 50
    times = np.sort(rng.uniform(0, M * BIN_UNITS, (h * w, n)), axis=1)
    store = PhotonStore(times.ravel(), np.arange(0, h * w * n + 1, n), (h, w), UNIT_S)
    seen = {}
    for rate in (1e-3, 1e-2, 1e-1):
        maps = reconstruct(store, dataclasses.replace(settings("spatial"), false_alarm=rate))
        seen[rate] = float(np.mean(maps.flags == PixelFlag.OK))
        assert seen[rate] <= 1.5 * rate, (rate, seen[rate])
        assert "censoring_false_alarm" in maps.settings["spatial"]
    assert seen[1e-3] < seen[1e-2] < seen[1e-1]
    # a pixel filled from a false one's neighbours is flagged, never OK; at the default rate few are
    maps = reconstruct(store, settings("spatial"))
    assert np.mean(np.isfinite(maps.tof_s)) < 0.02
    assert set(np.unique(maps.flags[np.isfinite(maps.tof_s)])) <= {PixelFlag.OK, PixelFlag.INTERPOLATED}


def test_censor_alpha_is_the_sidak_level_of_the_pixel_rate():
    from spdepth.recon.estimators.spatial import censor_alpha

    n = np.array([1, 2, 50, 1000])
    a = censor_alpha(1e-3, n)
    assert_allclose(1 - (1 - a) ** n, 1e-3, rtol=1e-9)
    assert a[0] == pytest.approx(1e-3) and np.all(np.diff(a) < 0)


def _flat_returns(rng, n_signal=6, n_background=2, side=30):
    """A gently tilted surface of Gaussian returns (RMS_UNITS) over a little background."""
    lists = []
    for i in range(side * side):
        d = 2000 + 200 * (i % side) / side
        x = np.concatenate([d + RMS_UNITS * rng.standard_normal(n_signal), rng.uniform(0, 4000, n_background)])
        lists.append(np.floor(x[(x >= 0) & (x < 4000)]))
    return PhotonStore.from_lists(lists, (side, side), UNIT_S)


def test_the_uncertainty_follows_the_detections_spread_not_the_stated_pulse(monkeypatch):
    # the fits' dispersion (pairs of a pixel's detections about one another): 1 with the true
    # width, below with a wider model, above with a narrower one; the noise of the uncertainty's
    # probes follows it, so a pulse stated twice too wide no longer doubles the uncertainty
    from spdepth.recon.estimators import spatial as S

    store = _flat_returns(np.random.default_rng(7))
    b = Binning(UNIT_S, 0, 4000, 5)
    got = {}
    for rms in (RMS_UNITS, 2 * RMS_UNITS, RMS_UNITS / 1.5):
        m = reconstruct(store, ReconSettings(method="spatial", binning=b, pulse_rms_s=rms * UNIT_S))
        got[rms] = (m.settings["spatial"]["fit_dispersion"], float(np.nanmedian(m.uncertainty_s)))
    assert 0.9 < got[RMS_UNITS][0] < 1.1
    assert got[2 * RMS_UNITS][0] < 0.5
    assert got[RMS_UNITS / 1.5][0] > 1.4
    assert got[2 * RMS_UNITS][1] < 1.2 * got[RMS_UNITS][1]
    # the model's width alone (dispersion 1) made it about twice as large
    monkeypatch.setattr(S, "fit_dispersion", lambda *a, **k: 1.0)
    wide = reconstruct(store, ReconSettings(method="spatial", binning=b, pulse_rms_s=2 * RMS_UNITS * UNIT_S))
    assert np.nanmedian(wide.uncertainty_s) > 1.6 * got[RMS_UNITS][1]


def _edge_and_tail_returns(rng, side=40, n_signal=8, n_background=1, edge=8.0, tau=30.0):
    """A gently tilted surface whose returns have a sharp edge (Gaussian of ``edge`` units) and a
    long exponential tail (``tau``), as many single-photon detectors respond, over a little background."""
    lists = []
    for i in range(side * side):
        d = 2000 + 200 * (i % side) / side
        x = np.concatenate([d + edge * rng.standard_normal(n_signal) + rng.exponential(tau, n_signal),
                            rng.uniform(0, 4000, n_background)])
        lists.append(np.floor(x[(x >= 0) & (x < 4000)]))
    return PhotonStore.from_lists(lists, (side, side), UNIT_S)


def test_a_tailed_response_is_fitted_with_the_gaussian_of_its_fwhm():
    # a Gaussian of the sharp edge's width alone fits a different few of a return's detections in
    # each draw: the halves of the mannequin's pixelwise fits differed by 1.78 times their stated
    # sigma; with the FWHM's Gaussian the estimator's own uncertainties are honest (checked
    # without truth: two halves of every pixel's detections, each reconstructed alone)
    from spdepth.acq.commands.bench.honesty import split_halves
    from spdepth.recon.irf import emg_response
    from spdepth.recon.model import Irf, irf_core_rms_s, irf_fwhm_rms_s

    t = np.arange(-48.0, 300.0, 1.0)
    irf = Irf(tuple(t * UNIT_S), tuple(emg_response(t, 8.0, 1.0, 30.0)), source="test")
    assert irf_fwhm_rms_s(irf) > 2.0 * irf_core_rms_s(irf)
    store = _edge_and_tail_returns(np.random.default_rng(11))
    s = ReconSettings(method="spatial", binning=Binning(UNIT_S, 0, 4000, 4), irf=irf)
    halves = [reconstruct(h, s, spreads=False) for h in split_halves(store)]
    assert halves[0].settings["spatial"]["pulse_width_rms_s"] == pytest.approx(irf_fwhm_rms_s(irf))
    da, db = (np.asarray(m.depth_m) for m in halves)
    sa, sb = (np.asarray(m.uncertainty_s) * C_M_PER_S / 2 for m in halves)
    both = np.isfinite(da) & np.isfinite(db)
    assert both.mean() > 0.9
    z = np.abs(da - db)[both] / np.hypot(sa, sb)[both]
    assert 0.6 < np.mean(z <= 1.0) < 0.8
    assert np.mean(z <= 3.0) > 0.97


def test_the_fwhm_gaussian_of_a_response():
    from spdepth.recon.irf import emg_response
    from spdepth.recon.model import Irf, gaussian_irf, irf_fwhm_rms_s

    assert irf_fwhm_rms_s(gaussian_irf(300e-12)) == pytest.approx(300e-12, rel=1e-3)
    t = np.arange(-60.0, 400.0, 0.5)
    c = emg_response(t, 8.0, 1.0, 30.0)
    above = t[c >= 0.5 * c.max()]
    want = (above[-1] - above[0]) / 2.3548 * UNIT_S
    assert irf_fwhm_rms_s(Irf(tuple(t * UNIT_S), tuple(c), source="test")) == pytest.approx(want, rel=0.02)
