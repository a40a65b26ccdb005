"""recon.detect: the per-pixel "is there a return?" test and the honest uncertainty of every depth."""

import dataclasses

import numpy as np
import pytest

from spdepth.acq.commands.bench.honesty import agreement, split_halves
from spdepth.recon.estimate import reconstruct
from spdepth.recon.maps import PixelFlag
from spdepth.recon.model import Binning, ReconSettings
from spdepth.recon.photons import PhotonStore

UNIT_S = 8e-12
RMS_U = 45.0
B = Binning(UNIT_S, 0, 4000, 5)


def _store(rng, n_pix, n_signal, n_background, returns=1.0):
    """n_pix pixels (a square), a share ``returns`` of them with a return of n_signal detections."""
    lists = []
    for i in range(n_pix):
        d = rng.uniform(500, 3500)
        k = n_signal if i < returns * n_pix else 0
        x = np.concatenate([d + RMS_U * rng.standard_normal(k), rng.uniform(0, 4000, n_background)])
        lists.append(np.floor(x[(x >= 0) & (x < 4000)]))
    side = int(np.sqrt(n_pix))
    return PhotonStore.from_lists(lists[:side * side], (side, side), UNIT_S)


@pytest.mark.parametrize("method", ["ml", "uos", "lmf"])
def test_background_alone_is_no_return_at_the_stated_rate(method):
    rng = np.random.default_rng(3)
    store = _store(rng, 1600, 0, 20)
    maps = reconstruct(store, ReconSettings(method=method, binning=B, pulse_rms_s=RMS_U * UNIT_S))
    found = np.isfinite(maps.depth_m)
    # false-alarm 1e-3 per pixel: about 1.6 of 1,600; 10 would be a rate 6x the stated one
    assert found.sum() <= 10
    assert np.all(maps.flags[~found] == PixelFlag.NO_RETURN)
    assert maps.settings["detection"]["false_alarm"] == 1e-3


def test_a_clear_return_is_found_and_its_uncertainty_is_the_fisher_one():
    rng = np.random.default_rng(4)
    store = _store(rng, 400, 15, 2)
    maps = reconstruct(store, ReconSettings(method="ml", binning=B, pulse_rms_s=RMS_U * UNIT_S))
    assert np.isfinite(maps.depth_m).mean() > 0.99
    # 15 signal detections of a 45-unit pulse: about 45 / sqrt(15) = 11.6 units
    sd_u = np.nanmedian(maps.uncertainty_s) / UNIT_S
    assert 9 < sd_u < 16


def test_split_halves_agree_within_three_sigma_at_low_sbr():
    # half the pixels hold a return of 16 detections over 32 of background, half background alone:
    # without the test every pixel had a depth and the halves agreed within 3 sigma on 54%
    rng = np.random.default_rng(5)
    store = _store(rng, 900, 16, 32, returns=0.5)
    s = ReconSettings(method="ml", binning=B, pulse_rms_s=RMS_U * UNIT_S)
    maps = reconstruct(store, s)
    assert 0.45 < np.isfinite(maps.depth_m).mean() < 0.52
    a, b = (reconstruct(h, s) for h in split_halves(store))
    r = agreement(a, b)
    assert r["both"] > 300
    assert r["within_3_sigma"] >= 0.97
    assert 0.55 <= r["within_1_sigma"] <= 0.85


def test_a_second_likely_peak_widens_the_uncertainty():
    # two clusters of 6 detections 2,000 units apart, no background: the depth may be either
    rng = np.random.default_rng(6)
    one = [np.floor(1000 + RMS_U * rng.standard_normal(6)) for _ in range(4)]
    two = [np.concatenate([o, np.floor(3000 + RMS_U * rng.standard_normal(6))]) for o in one]
    s = ReconSettings(method="ml", binning=B, pulse_rms_s=RMS_U * UNIT_S)
    m1 = reconstruct(PhotonStore.from_lists(one, (2, 2), UNIT_S), s)
    m2 = reconstruct(PhotonStore.from_lists(two, (2, 2), UNIT_S), s)
    assert np.all(np.isfinite(m2.depth_m))
    assert np.all(m2.uncertainty_s / UNIT_S > 400)          # the other cluster, ~2,000 units away
    assert np.all(m1.uncertainty_s / UNIT_S < 60)


def test_neighbours_support_a_surface_too_faint_for_one_pixel():
    # a flat wall at 2,000 units seen by every pixel with 2 signal detections over 10 of
    # background: too few for a pixel alone, plain in its 8 neighbours pooled; every 7th pixel
    # sees background alone (a hole in the wall), which its neighbours must not fill
    rng = np.random.default_rng(8)
    side = 30
    hole = (np.arange(side * side) % 7) == 3
    lists = []
    for i in range(side * side):
        k = 0 if hole[i] else 2
        x = np.concatenate([2000 + RMS_U * rng.standard_normal(k), rng.uniform(0, 4000, 10)])
        lists.append(np.floor(x))
    store = PhotonStore.from_lists(lists, (side, side), UNIT_S)
    s = ReconSettings(method="ml", binning=B, pulse_rms_s=RMS_U * UNIT_S)
    maps = reconstruct(store, s)
    found = np.isfinite(maps.depth_m).ravel()
    assert "neighbours" in maps.settings["detection"]
    alone = np.isfinite(reconstruct(store, s, neighbours=False).depth_m).ravel()
    assert found.sum() > alone.sum() + 150         # pixels the test alone drops
    assert np.all(found[alone])
    # ml's own estimate lies on the wall on about 57% of the wall's pixels (elsewhere 2 of its 10
    # background detections happened to coincide): those are supported, the others are not
    assert found[~hole].mean() > 0.5
    t_u = maps.tof_s.ravel() / UNIT_S
    assert (np.abs(t_u[found & ~hole] - 2000) < 150).mean() > 0.95
    # a hole's own best detection lies near the wall's depth on about 10 x 2 x 2.5 x 45 / 4000 of
    # them; the neighbours support nothing elsewhere
    assert found[hole].mean() < 0.2


def test_a_faint_return_beside_a_background_cluster_is_found_where_the_neighbours_see_it():
    # a faint wall (3 signal detections over 60 of background a pixel): on most of its pixels a
    # background cluster beats the return for the pixel's own best shift, so the neighbours'
    # support at that shift fails; tested where the neighbours see returns, the pixel's own
    # detections hold it. A hole (background only) is given a return there at most at the rate
    rng = np.random.default_rng(8)
    side = 40
    hole = (np.arange(side * side) % 7) == 3
    lists = [np.floor(np.concatenate([2000 + RMS_U * rng.standard_normal(0 if hole[i] else 3),
                                      rng.uniform(0, 4000, 60)])) for i in range(side * side)]
    store = PhotonStore.from_lists(lists, (side, side), UNIT_S)
    s = ReconSettings(method="ml", binning=B, pulse_rms_s=RMS_U * UNIT_S)
    maps = reconstruct(store, s)
    rate = s.neighbour_false_alarm
    before = np.isfinite(reconstruct(store, dataclasses.replace(s, neighbour_false_alarm=0.0)).depth_m).ravel()
    found = np.isfinite(maps.depth_m).ravel()
    assert np.all(found[before])
    filled = found & ~before
    assert maps.settings["detection"]["neighbours_region"]["false_alarm"] == rate
    assert found[~hole].mean() > before[~hole].mean() + 0.015         # 0.370 -> 0.390
    assert found[hole].mean() - before[hole].mean() <= rate
    # the filled pixels' depths are the wall's within their uncertainty, and their maps consistent
    t, sig = maps.tof_s.ravel() / UNIT_S, maps.uncertainty_s.ravel() / UNIT_S
    wall = filled & ~hole
    assert np.mean(np.abs(t[wall] - 2000) <= 3 * sig[wall]) >= 0.95
    assert np.all(maps.flags.ravel()[filled] == PixelFlag.OK)
    assert np.all(maps.signal.ravel()[filled] > 0) and np.all(np.isfinite(maps.background.ravel()[filled]))


def test_a_supported_pixel_s_uncertainty_is_that_where_its_neighbours_see_returns():
    # a faint wall (3 signal detections over 30 of background a pixel, in each half): a pixel its
    # neighbours support reports its own estimate, near the wall by the support's rule, so its
    # spread is taken where the neighbours see returns. Over the whole window the likelihood's
    # far background peaks gave sigmas of metres and halves that agreed within 1 sigma on 100%
    rng = np.random.default_rng(9)
    side = 40
    lists = [np.floor(np.concatenate([2000 + RMS_U * rng.standard_normal(6), rng.uniform(0, 4000, 60)]))
             for _ in range(side * side)]
    store = PhotonStore.from_lists(lists, (side, side), UNIT_S)
    s = ReconSettings(method="ml", binning=B, pulse_rms_s=RMS_U * UNIT_S)
    a, b = (reconstruct(h, s) for h in split_halves(store))
    r = agreement(a, b)
    assert r["both"] > 300
    assert r["within_3_sigma"] >= 0.95
    assert 0.55 <= r["within_1_sigma"] <= 0.85
    # and against the truth: the wall within 3 sigma on almost every pixel with a depth
    t, sig = a.tof_s.ravel() / UNIT_S, a.uncertainty_s.ravel() / UNIT_S
    ok = np.isfinite(t)
    assert np.mean(np.abs(t[ok] - 2000) <= 3 * sig[ok]) >= 0.95
    assert np.median(sig[ok]) < 3 * RMS_U


def test_two_real_surfaces_widen_a_one_surface_uncertainty(shared_data):
    # two_layer_top.mat: most pixels see a pane and a wall behind it; a one-surface estimator
    # reports either, and a half of the data may pick the other, so the bootstrap's spread among
    # modes that are returns in their own right takes half its 95.45% quantile too: ml's halves
    # within 3 sigma 92.5% -> 95.8% (a background cluster must not widen it:
    # test_a_supported_pixel_s_uncertainty_is_that_where_its_neighbours_see_returns)
    from spdepth.acq.commands.bench.honesty import split_half
    from spdepth.acq.readers import read_photons

    store = read_photons(shared_data / "multidepth" / "two_layer_top.mat", time_unit_s=UNIT_S).store
    r = split_half(store, ReconSettings(method="ml"))
    assert r["depth_full"] > 0.99
    assert r["within_3_sigma"] >= 0.95
    assert 0.55 <= r["within_1_sigma"] <= 0.80


@pytest.mark.parametrize("method", ["ml", "spatial"])
def test_each_of_two_real_surfaces_has_an_honest_uncertainty(shared_data, method):
    # two_layer_top.mat at --reflectors 2: the pane and the wall, each surface's sigma checked on
    # the halves where both find it (not weak). The fit's Fisher variance read the measured
    # response's sharp edge and missed its flat top (92.8 / 92.5% within 3 sigma); with its own
    # sandwich and bootstrap over its part of the window, as a one-surface estimate is widened.
    # spatial's smoothing averaged those Fisher variances (94.8 / 93.4%, 55.3 / 53.5% within 1):
    # now each surface's own, widened as a pixelwise fit's, before the smoothing
    from spdepth.acq.commands.bench.honesty import resolved_settings, split_halves
    from spdepth.acq.readers import read_photons

    store = read_photons(shared_data / "multidepth" / "two_layer_top.mat", time_unit_s=UNIT_S).store
    # the README's window: with the data's own, wider one spatial's were within the bands before
    window = Binning.from_data(store.times, store.time_unit_s, window_s=(24e-9, 56e-9))
    s = ReconSettings(method=method, reflectors=2, binning=window)
    fixed = resolved_settings(s, reconstruct(store, s).settings)
    a, b = (reconstruct(h, fixed) for h in split_halves(store))
    for r in agreement(a, b)["surfaces"]:       # as spdepth bench honesty --reflectors 2 prints them
        assert r["both"] > 2500
        assert r["within_3_sigma"] >= 0.95
        assert 0.55 <= r["within_1_sigma"] <= 0.80


def test_background_alone_passes_the_test_at_the_stated_rate():
    # 22,500 pixels of 10 background detections each: at --false-alarm 1e-3 about 22 may pass in
    # all, whichever rule passes them. Counting window / FWHM independent shifts let 43 pass the own
    # test alone; the threshold by Rice's formula for the search, 18. Each rule at the whole rate
    # let 39 pass with the support and 46 with the regions too; half of it each to the own test and
    # the support, 12 and 18
    rng = np.random.default_rng(5)
    side = 150
    store = PhotonStore.from_lists([np.floor(rng.uniform(0, 4000, 10)) for _ in range(side * side)],
                                   (side, side), UNIT_S)
    s = ReconSettings(method="ml", binning=B, pulse_rms_s=RMS_U * UNIT_S, neighbour_false_alarm=0.0)
    own = int(np.isfinite(reconstruct(store, s, neighbours=False).depth_m).sum())
    with_support = int(np.isfinite(reconstruct(store, s).depth_m).sum())
    assert own <= 1.4e-3 * side * side and with_support <= 1.4e-3 * side * side
    # the third rule adds few: a region needs the neighbours to pass somewhere first
    filled = int(np.isfinite(reconstruct(store, dataclasses.replace(s, neighbour_false_alarm=0.05)).depth_m).sum())
    assert filled <= 1.4e-3 * side * side


def test_the_tables_are_kept_with_their_pulse_kernel():
    """ml's tables and the test's rate tables are built once per pulse kernel and window (every live
    batch and array frame asked for them anew), and never handed to another kernel."""
    from spdepth.recon.detect import _tables_of
    from spdepth.recon.estimators.ml import ml_tables
    from spdepth.recon.model import Binning, build_kernel

    b = Binning.from_window(80e-12, (0.0, 200 * 80e-12), 80e-12)
    k1, k2 = build_kernel(b, pulse_rms_s=170e-12), build_kernel(b, pulse_rms_s=250e-12)
    t1 = ml_tables(k1, b.n_bins)
    assert ml_tables(k1, b.n_bins) is t1 and ml_tables(k1, b.n_bins, t1.fine_climb) is t1
    assert ml_tables(k2, b.n_bins) is not t1 and ml_tables(k1, b.n_bins, not t1.fine_climb) is not t1
    assert ml_tables(k2, b.n_bins).g is k2.g
    dt, rates = _tables_of(t1)
    assert _tables_of(t1)[1] is rates and _tables_of(ml_tables(k2, b.n_bins))[1] is not rates
    assert dt.m == b.n_bins and rates.shape[1] == t1.nk + 1


@pytest.mark.parametrize("method", ["ml", "uos"])
def test_without_spreads_the_decision_is_the_same_and_the_uncertainty_the_estimator_s(method):
    # spreads=False (a caller that writes no map): the same pixels hold a return, neighbours'
    # support included, the same depths, and each uncertainty is the estimator's own, which the
    # spreads only ever widen; the record says which
    rng = np.random.default_rng(10)
    side = 30
    lists = []
    for i in range(side * side):
        k = 2 if i % 3 else 12         # most pixels too faint alone, beside their neighbours
        x = np.concatenate([2000 + RMS_U * rng.standard_normal(k), rng.uniform(0, 4000, 10)])
        lists.append(np.floor(x))
    store = PhotonStore.from_lists(lists, (side, side), UNIT_S)
    s = ReconSettings(method=method, binning=B, pulse_rms_s=RMS_U * UNIT_S)
    full, bare = reconstruct(store, s), reconstruct(store, s, spreads=False)
    alone = reconstruct(store, s, neighbours=False)
    assert np.isfinite(full.depth_m).sum() > np.isfinite(alone.depth_m).sum()     # support at work
    assert np.array_equal(full.flags, bare.flags)
    assert np.array_equal(full.depth_m, bare.depth_m, equal_nan=True)
    assert np.array_equal(full.gain_nats, bare.gain_nats, equal_nan=True)
    got = np.isfinite(full.depth_m)
    # the spreads before the pulse model's dispersion scales them all (uos's here: 0.8, ml's 1.0)
    spread = full.uncertainty_s / full.settings.get("pulse_dispersion", {}).get("width_ratio", 1.0)
    assert np.all(bare.uncertainty_s[got] <= spread[got] * (1 + 1e-12))
    assert np.any(bare.uncertainty_s[got] < spread[got])          # the spreads widened some
    assert "not computed" in bare.settings["detection"]["uncertainty"]
    assert "not computed" not in full.settings["detection"]["uncertainty"]


@pytest.mark.parametrize("weighted", [False, True])
def test_the_test_alone_decides_as_the_test_with_its_spreads(weighted):
    # detect() without spreads reads the search's gains without running the spreads' kernel: the
    # same gains and decisions, from detections and from a count store's weighted bins, with
    # pixels without any entry among them
    from spdepth.recon.detect import detect
    from spdepth.recon.model import build_kernel

    rng = np.random.default_rng(3)
    kern = build_kernel(B, pulse_rms_s=RMS_U * UNIT_S)
    m = int(kern.n_bins)
    bins, weights, offsets = _frame(rng, 8, 5, 6, m // 2, m, weighted)
    empty = np.arange(0, offsets.size - 1, 5)        # every fifth pixel without an entry
    keep = np.ones(bins.size, bool)
    for p in empty:
        keep[offsets[p]:offsets[p + 1]] = False
    counts = np.array([keep[offsets[p]:offsets[p + 1]].sum() for p in range(offsets.size - 1)])
    offsets = np.concatenate([[0], np.cumsum(counts)])
    bins, weights = bins[keep], weights[keep] if weighted else weights
    est = np.full(offsets.size - 1, m / 2)
    full = detect(bins, offsets, kern, est, 1e-3, weights)
    lean = detect(bins, offsets, kern, est, 1e-3, weights, spreads=False)
    assert np.array_equal(full.gain_nats, lean.gain_nats) and np.array_equal(full.has_return, lean.has_return)
    assert 0 < full.has_return.sum() < full.has_return.size and np.all(lean.gain_nats[empty] == 0)
    assert np.all(np.isnan(lean.sd_bins)) and np.isfinite(full.sd_bins).any()


def test_the_return_test_reads_the_estimator_s_binned_detections():
    # within binned_once (a reconstruction) the second binning of the same store, window and
    # first-N is the first one's arrays; outside it, or for another window, a binning of its own
    from spdepth.recon.pixelwise import binned_once, binned_photons

    store = _store(np.random.default_rng(11), 16, 5, 5)
    other = Binning(UNIT_S, 0, 2000, 5)
    with binned_once():
        first = binned_photons(store, B, None)
        assert binned_photons(store, Binning.from_dict(B.to_dict()), None)[0] is first[0]
        again = binned_photons(store, other, None)
        assert again[0] is not first[0] and again[1].size == first[1].size
        assert binned_photons(store, B, 3)[0] is not first[0]
    assert binned_photons(store, B, None)[0] is not first[0]
    assert np.array_equal(binned_photons(store, B, None)[0], first[0])


@pytest.mark.parametrize("model_rms_u, lo, hi", [(RMS_U, 0.85, 1.15), (2 * RMS_U, 0.2, 0.5), (0.7 * RMS_U, 1.4, 2.5)])
def test_the_pulse_dispersion_measures_the_model_s_width_against_the_detections(model_rms_u, lo, hi):
    # returns of a 45-unit pulse fitted with it, twice as wide, 0.7 as wide: 1.00, 0.39, 1.67 here
    # (without background 0.99, 0.25, 1.85: the width ratio squared), from the detections alone
    from spdepth.recon.detect import pulse_dispersion

    rng = np.random.default_rng(11)
    store = _store(rng, 2500, 8, 4)
    s = ReconSettings(method="ml", binning=B, pulse_rms_s=model_rms_u * UNIT_S)
    d = pulse_dispersion(store, s, reconstruct(store, s))
    assert d["pixels"] >= 2000
    assert lo < d["dispersion"] < hi
    assert d["width_ratio"] == pytest.approx(np.sqrt(d["dispersion"]))


def test_the_pulse_dispersion_is_not_said_where_it_cannot_be():
    from spdepth.recon.detect import pulse_dispersion

    rng = np.random.default_rng(12)
    store = _store(rng, 2500, 8, 4)
    # no score of their own on their maps (uos's: its matched filter's; lmf's is measured before its
    # test, at ml's search's shifts: TEMPERED_METHODS)
    for method in ("lmf", "spatial"):
        s = ReconSettings(method=method, binning=B, pulse_rms_s=RMS_U * UNIT_S)
        assert pulse_dispersion(store, s, reconstruct(store, s)) is None
    s = ReconSettings(method="ml", binning=B, pulse_rms_s=RMS_U * UNIT_S)
    few = _store(rng, 5, 8, 4)                    # too few pixels to pool
    assert pulse_dispersion(few, s, reconstruct(few, s)) is None
    weak = _store(rng, 12, 3, 4)                  # a ratio too uncertain (over 10%) to scale by
    assert pulse_dispersion(weak, s, reconstruct(weak, s)) is None
    # a small frame of well-filled pixels says it, with its error: the model fits (ratio 1)
    small = _store(rng, 100, 8, 4)
    d = pulse_dispersion(small, s, reconstruct(small, s))
    assert d is not None and d["pixels"] == 100 and 0 < d["width_ratio_se"] <= 0.1
    assert abs(d["width_ratio"] - 1) < 3 * d["width_ratio_se"]


def test_the_pulse_dispersion_s_stated_error_is_its_spread_over_frames():
    # the width ratio's standard error (from one frame's pixels) against the ratio's spread over
    # independent frames of the same scene: 0.88 of it here
    from spdepth.recon.detect import pulse_dispersion

    rng = np.random.default_rng(5)
    s = ReconSettings(method="ml", binning=B, pulse_rms_s=RMS_U * UNIT_S)
    got = [pulse_dispersion(st, s, reconstruct(st, s)) for st in (_store(rng, 60, 8, 4) for _ in range(30))]
    assert all(d is not None for d in got)
    spread = np.std([d["width_ratio"] for d in got], ddof=1)
    stated = np.mean([d["width_ratio_se"] for d in got])
    assert 0.6 * stated < spread < 1.4 * stated


@pytest.mark.parametrize("method", ["ml", "uos"])
@pytest.mark.parametrize("model_rms_u", [2 * RMS_U, 0.7 * RMS_U])
def test_the_uncertainties_follow_the_detections_not_a_wrongly_stated_pulse(model_rms_u, method):
    # returns of a 45-unit pulse fitted with a pulse twice as wide or 0.7 as wide: the model's own
    # uncertainties were too large (too small), and with the dispersion's scaling the depths' errors
    # against the truth are about their sigma again (here ml 73% / 72%, uos 70% / 68% within 1
    # sigma; uos's own 96% / 64%, its matched filter's dispersion 0.26 / 1.20)
    store, truth = _returns(np.random.default_rng(13), 4)
    s = ReconSettings(method=method, binning=B, pulse_rms_s=model_rms_u * UNIT_S)
    m = reconstruct(store, s)
    d = m.settings["pulse_dispersion"]
    assert d["applied"] and (d["width_ratio"] < 0.8 if model_rms_u > RMS_U else d["width_ratio"] > 1.05)
    z = _errors_in_sigmas(m, truth)
    assert z.size > 2000
    assert 0.6 < np.mean(z <= 1.0) < 0.78
    # the model's own (here ml 91% / 61%, uos 96% / 64% within 1 sigma): too large (too small)
    raw = np.asarray(m.uncertainty_s).ravel() / d["width_ratio"] / UNIT_S
    z0 = np.abs(np.asarray(m.tof_s).ravel() / UNIT_S - truth) / raw
    z0 = z0[np.isfinite(z0)]
    assert (np.mean(z0 <= 1.0) > 0.85) if model_rms_u > RMS_U else (np.mean(z0 <= 1.0) < 0.65)


@pytest.mark.parametrize("model_rms_u, n_background", [(2 * RMS_U, 0), (2 * RMS_U, 4), (0.7 * RMS_U, 4)])
def test_lmf_s_uncertainties_follow_the_detections_not_a_wrongly_stated_pulse(model_rms_u, n_background):
    # lmf's depth (a Gaussian pulse) is its detections' mean: its error is their spread and the
    # background's pull, which the test's likelihood spreads see as the distance to their modes.
    # Tempered by the pulse model's dispersion at ml's search's shifts (TEMPERED_METHODS), their
    # widths follow the detections and those distances stay: here 69.8% / 72.8% / 72.1% within 1
    # sigma; untempered 95.6% / 80.3% / 70.5%, and with lmf's whole uncertainty scaled instead
    # (as ml's is) 72.8% became 10.6%: the pull's distances shrank with the widths
    store, truth = _returns(np.random.default_rng(13), n_background)
    m = reconstruct(store, ReconSettings(method="lmf", binning=B, pulse_rms_s=model_rms_u * UNIT_S))
    d = m.settings["pulse_dispersion"]
    assert "tempered" in d["applied"]
    assert d["width_ratio"] < 0.8 if model_rms_u > RMS_U else d["width_ratio"] > 1.05
    z = _errors_in_sigmas(m, truth)
    assert z.size > 2000
    assert 0.62 < np.mean(z <= 1.0) < 0.78
    assert np.mean(z <= 3.0) > 0.99


def _returns(rng, n_background: int):
    """(store, true shifts) of 50 x 50 pixels: 8 detections of a 45-unit Gaussian return each at a
    uniform depth, and ``n_background`` uniform over the window."""
    lists, truth = [], []
    for _ in range(50 * 50):
        d = rng.uniform(500, 3500)
        x = np.concatenate([d + RMS_U * rng.standard_normal(8), rng.uniform(0, 4000, n_background)])
        lists.append(np.floor(x[(x >= 0) & (x < 4000)]))
        truth.append(d + 0.5)                       # floor() moves every detection half a unit on average
    return PhotonStore.from_lists(lists, (50, 50), UNIT_S), np.array(truth)


def _errors_in_sigmas(maps, truth):
    """|depth - truth| over the depth's sigma, at the pixels with a depth."""
    z = np.abs(np.asarray(maps.tof_s).ravel() / UNIT_S - truth) / (np.asarray(maps.uncertainty_s).ravel() / UNIT_S)
    return z[np.isfinite(z)]


def test_no_dispersion_scaling_with_a_sampled_response_or_without_spreads():
    from spdepth.recon.model import gaussian_irf

    rng = np.random.default_rng(14)
    store = _store(rng, 2500, 8, 4)
    irf = ReconSettings(method="ml", binning=B, irf=gaussian_irf(2 * RMS_U * UNIT_S))
    assert "pulse_dispersion" not in reconstruct(store, irf).settings
    s = ReconSettings(method="ml", binning=B, pulse_rms_s=2 * RMS_U * UNIT_S)
    lean, full = reconstruct(store, s, spreads=False), reconstruct(store, s)
    assert "pulse_dispersion" not in lean.settings and "pulse_dispersion" in full.settings


def _frame(rng, side, n_signal, n_background, at_bin, m, weighted=False):
    """(bins, weights, offsets) of a frame: each pixel n_signal detections about bin at_bin (the
    pulse's RMS RMS_U / 5 bins) and n_background over the m bins; ``weighted``: as a count store's
    distinct bins, with counts that are not whole."""
    bins, weights, offsets = [], [], [0]
    for _ in range(side * side):
        x = np.concatenate([at_bin + RMS_U / 5 * rng.standard_normal(n_signal), rng.uniform(0, m, n_background)])
        b = np.clip(np.floor(x), 0, m - 1).astype(np.int64)
        if weighted:
            b, c = np.unique(b, return_counts=True)
            weights.append(c * rng.uniform(0.8, 1.3, c.size))
        bins.append(np.sort(b))
        offsets.append(offsets[-1] + b.size)
    w = np.concatenate(weights) if weighted else np.empty(0)
    return np.concatenate(bins), w, np.array(offsets, np.int64)


def _pooled(bins, weights, offsets, side, p, r):
    """The detections of the pixels within r of pixel p pooled, its own left out (distinct bins
    ascending, counts), added in the support kernel's order."""
    y, x = divmod(p, side)
    dense = {}
    for yy in range(max(0, y - r), min(side, y + r + 1)):
        for xx in range(max(0, x - r), min(side, x + r + 1)):
            q = yy * side + xx
            if q != p:
                for a in range(offsets[q], offsets[q + 1]):
                    dense[int(bins[a])] = dense.get(int(bins[a]), 0.0) + (float(weights[a]) if weights.size else 1.0)
    kb = np.array(sorted(dense), np.int64)
    return kb, np.array([dense[k] for k in kb])


@pytest.mark.parametrize("n_signal,n_background,weighted", [(2, 2, False), (1, 10, False), (3, 30, False),
                                                            (0, 4, False), (2, 3, True)])
def test_the_support_decides_as_ml_s_solve_at_every_shift(n_signal, n_background, weighted):
    """neighbour_support's pixels are those whose pooled neighbours' profiled gain (ml's solve at
    each shift of the span, from the share of the shift before) passes the threshold: the fixed
    shares it tries first on the tabulated rates only pass pixels the solve passes too (few and
    many detections pooled, beyond ML_SCAN_ALL distinct bins, counts that are not whole)."""
    from spdepth.recon.detect import SUPPORT_RADIUS, neighbour_support
    from spdepth.recon.estimators.ml import ml_tables
    from spdepth.recon.estimators.ml_bounds import _ml_at_int
    from spdepth.recon.model import build_kernel

    rng = np.random.default_rng(n_signal * 100 + n_background)
    kern = build_kernel(B, pulse_rms_s=RMS_U * UNIT_S)
    m = int(kern.n_bins)
    side = 14
    bins, weights, offsets = _frame(rng, side, n_signal, n_background, 300.0, m, weighted)
    # estimates on the surface, beside it and anywhere (the window's edges too)
    est = np.where(rng.uniform(size=side * side) < 0.5, 300 + rng.normal(0, 15, side * side),
                   rng.uniform(0, m - 1, side * side))
    cand = np.arange(side * side)
    half = 18
    got, thr = neighbour_support(bins, weights, offsets, (side, side), kern, est, cand, 1e-3, half)
    T = ml_tables(kern, m)
    want = []
    for p in cand:
        kb, kw = _pooled(bins, weights, offsets, side, p, SUPPORT_RADIUS)
        best, s0, c = 0.0, 0.5, int(round(est[p]))
        for i in range(max(0, c - half), min(m, c + half + 1)) if kb.size else ():
            s, ll = _ml_at_int(kb, kw, kb.size, kw.sum(), i, T.g, T.off, T.colsum, T.uni, s0, -np.inf)
            s0 = s if 0.0 < s < 1.0 else s0
            best = max(best, ll + kw.sum() * T.logm)
        if best > thr:
            want.append(p)
    assert np.array_equal(got, np.array(want, np.int64))
    if n_signal >= 2:
        assert got.size > cand.size / 4


@pytest.mark.parametrize("at_bin", [15.0, 785.0, 400.0])
def test_the_regions_mark_where_the_pooled_gain_passes_at_the_window_s_edges_too(at_bin):
    """neighbour_regions marks the shifts within ``half`` of one where the 8 neighbours' pooled gain
    at one of REGION_SHARES passes the threshold, computed here from its definition: at the
    window's edges (a surface there, other column sums) the bound that spares most edge shifts'
    logs must not drop one that passes."""
    from spdepth.recon.detect import REGION_RADIUS, REGION_SHARES, neighbour_regions
    from spdepth.recon.estimators.ml import ml_tables
    from spdepth.recon.model import build_kernel

    rng = np.random.default_rng(int(at_bin))
    kern = build_kernel(B, pulse_rms_s=RMS_U * UNIT_S)
    m = int(kern.n_bins)
    side = 8
    bins, weights, offsets = _frame(rng, side, 2, 2, at_bin, m)
    cand = np.arange(side * side)
    half, thr = 18, 7.0
    regions = neighbour_regions(bins, weights, offsets, side, kern, cand, half, thr)
    T = ml_tables(kern, m)
    i = np.arange(m)
    eps = 0.05        # the interior's tabulated rates lie below the exact ones by less
    for c in cand:
        kb, kw = _pooled(bins, weights, offsets, side, c, REGION_RADIUS)
        d = kb[:, None] - i[None, :] + T.off
        g = np.where((d >= 0) & (d < T.nk), T.g[np.clip(d, 0, T.nk - 1)], 0.0) / T.colsum[None, :]
        gain = np.max([(kw[:, None] * np.log(T.uni + s * (g - T.uni))).sum(0) + kw.sum() * T.logm
                       for s in REGION_SHARES], axis=0)
        sure = np.flatnonzero(gain > thr + eps)
        maybe = np.flatnonzero(gain > thr - eps)
        for k in sure:
            assert regions[c, max(0, k - half):k + half + 1].all()
        near = np.zeros(m, bool)
        for k in maybe:
            near[max(0, k - half):k + half + 1] = True
        assert not (regions[c].astype(bool) & ~near).any()
        if at_bin != 400.0:
            assert regions[:, :40].any() if at_bin < 400 else regions[:, -40:].any()


def test_the_dispersion_s_terms_of_blocks_of_rows_are_the_frame_s(monkeypatch):
    # every stride-th pixel of the frame, so blocks of rows (acq.distributed) give, concatenated in
    # order, the frame's terms; here 50 x 50 pixels sampled every 7th
    import spdepth.recon.detect as D

    monkeypatch.setattr(D, "DISPERSION_PIXELS", 2500 // 7)
    rng = np.random.default_rng(15)
    store = _store(rng, 2500, 8, 4)
    s = ReconSettings(method="ml", binning=B, pulse_rms_s=RMS_U * UNIT_S)
    maps = reconstruct(store, s, dispersion=False)
    whole = D.dispersion_terms(store, s, maps)
    assert 250 < whole[0].size <= -(-2500 // 7)
    parts = [D.dispersion_terms(store, s, maps, rows=(r0, r1)) for r0, r1 in ((0, 13), (13, 14), (14, 50))]
    for i in (0, 1):
        assert np.array_equal(np.concatenate([p[i] for p in parts]), whole[i])
    # a block's own maps: its pixels counted from the frame's first_pixel on
    lower = dataclasses.replace(maps, **{k: np.asarray(getattr(maps, k))[20:] for k in
                                         ("tof_s", "background", "signal")})
    sub = PhotonStore.from_pixel_indices(*_rows_from(store, 20), (30, 50), UNIT_S)
    got = D.dispersion_terms(sub, s, lower, first_pixel=20 * 50, frame_pixels=2500)
    ref = D.dispersion_terms(store, s, maps, rows=(20, 50))
    assert np.array_equal(got[0], ref[0]) and np.array_equal(got[1], ref[1])


def _rows_from(store, r0):
    """(pixel indices from row r0 on, renumbered, and their times) of ``store``."""
    counts = np.diff(store.offsets)
    pix = np.repeat(np.arange(store.n_pixels), counts)
    keep = pix >= r0 * store.shape[1]
    return pix[keep] - r0 * store.shape[1], store.times[keep]


def test_a_pixel_s_own_peak_width_is_its_one_peak_s_and_none_where_it_has_others():
    """_own_width, which lets a spatial depth keep its own uncertainty: one cluster of detections
    gives its peak's width (about the pulse's over the square root of its detections), two
    clusters far apart give 0 (other peaks: the pixel's spreads may overrule), none NaN."""
    from spdepth.recon.detect import _own_width, search
    from spdepth.recon.model import build_kernel

    rng = np.random.default_rng(5)
    kern = build_kernel(B, pulse_rms_s=RMS_U * UNIT_S)
    rms_bins = RMS_U / B.bin_width
    one = np.round(300 + rms_bins * rng.standard_normal(8))
    two = np.concatenate([np.round(200 + rms_bins * rng.standard_normal(4)),
                          np.round(600 + rms_bins * rng.standard_normal(4))])
    bins = np.concatenate([np.sort(one), np.sort(two)]).astype(np.int64)
    offsets = np.array([0, 8, 16, 16], np.int64)
    gain, index, share = search(bins, offsets, kern)
    got = _own_width(bins, np.zeros(0), offsets, kern, np.arange(3), gain, index, share, 1e-3)
    assert 0.5 * rms_bins / np.sqrt(8) < got[0] < 2.0 * rms_bins / np.sqrt(8)
    assert got[1] == 0.0
    assert np.isnan(got[2])
