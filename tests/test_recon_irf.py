"""The instrument response measured from the data (issue 9): simulated responses with a diffusion
tail, every real file with a return peak, --save-irf round trip, pictures."""

from __future__ import annotations

import json

import numpy as np
import pytest
from matplotlib.image import imread

from spdepth.acq.cli import main
from spdepth.acq.readers import read_photons
from spdepth.recon.errors import InputError
from spdepth.recon.estimate import reconstruct
from spdepth.recon.irf import emg_response, estimate_irf
from spdepth.recon.model import Binning, ReconSettings, load_irf
from spdepth.recon.photons import PhotonStore

UNIT_S = 8e-12


def emg_times(rng, n, sigma, share, tau):
    return sigma * rng.standard_normal(n) + np.where(rng.random(n) < share, rng.exponential(tau, n), 0.0)


def raster(rng, n_pix, k, sigma, share, tau, sbr=10.0):
    lists = []
    for _ in range(n_pix):
        c = rng.uniform(1000, 3000)
        ns = rng.binomial(k, sbr / (1 + sbr))
        lists.append(np.floor(np.concatenate([c + emg_times(rng, ns, sigma, share, tau),
                                              rng.uniform(0, 4500, k - ns)])))
    return PhotonStore.from_lists(lists, (1, n_pix), UNIT_S)


@pytest.mark.parametrize("share,tau", [(0.0, 1.0), (0.3, 150.0)])
def test_raster_response_fitted_from_pair_differences(share, tau):
    rng = np.random.default_rng(11)
    est = estimate_irf(raster(rng, 8000, 12, 30.0, share, tau))
    assert est.method == "emg-pairs"
    assert est.core_rms_s / UNIT_S == pytest.approx(30.0, rel=0.1)
    assert est.tail_share == pytest.approx(share, abs=0.08)
    truth_rms = np.sqrt(30.0 ** 2 + share * tau ** 2 * (2 - share))
    assert est.irf.rms_s / UNIT_S == pytest.approx(truth_rms, rel=0.15)


def test_point_measurement_response_pooled():
    # one pixel, 60,000 detections of a response with a long tail: the pooled histogram is the shape
    rng = np.random.default_rng(12)
    t = np.floor(np.concatenate([2000 + emg_times(rng, 60_000, 6.0, 0.6, 400.0), rng.uniform(0, 8000, 6000)]))
    est = estimate_irf(PhotonStore.from_lists([t], (1, 1), UNIT_S))
    assert est.method == "aligned"
    # the core is read off the leading edge (10% to 90% of the peak), which the tail steepens
    assert 3.0 < est.core_rms_s / UNIT_S < 9.0
    tt, c = est.irf.arrays()
    x = tt / UNIT_S
    want = emg_response(x - x[np.argmax(c)], 6.0, 0.6, 400.0)
    # the measured shape follows the true one over two decades of its tail
    late = (x - x[np.argmax(c)] > 100) & (x - x[np.argmax(c)] < 1500)
    ratio = (c[late] / c.max()) / (want[late] / want.max())
    assert np.median(ratio) == pytest.approx(1.0, abs=0.2)


def test_tail_model_beats_gaussian_on_a_tailed_raster():
    # detections with a diffusion tail: a Gaussian of the same RMS puts the return late (it reads
    # the tail as part of the pulse's bulk); the estimated shape keeps the error near the
    # Gaussian-data figure
    rng = np.random.default_rng(13)
    n_pix, k = 3000, 30
    lists, truth = [], []
    for _ in range(n_pix):
        c = rng.uniform(1000, 3000)
        ns = rng.binomial(k, 10 / 11)
        lists.append(np.floor(np.concatenate([c + emg_times(rng, ns, 20.0, 0.4, 150.0),
                                              rng.uniform(0, 4500, k - ns)])))
        truth.append(c)
    store = PhotonStore.from_lists(lists, (1, n_pix), UNIT_S)
    maps = reconstruct(store, ReconSettings(method="ml"))
    assert maps.settings["pulse_source"] == "estimated" and maps.settings["irf"] is not None
    # tof is the response's centroid; the truth's centroid is c + share * tau
    err = maps.tof_s.ravel() / UNIT_S - (np.array(truth) + 0.4 * 150.0 - 0.5)
    gauss = reconstruct(store, ReconSettings(method="ml", pulse_rms_s=maps.settings["pulse_rms_s"]))
    err_g = gauss.tof_s.ravel() / UNIT_S - (np.array(truth) + 0.4 * 150.0 - 0.5)
    mad = np.nanmedian(np.abs(err - np.nanmedian(err)))
    mad_g = np.nanmedian(np.abs(err_g - np.nanmedian(err_g)))
    assert abs(np.nanmedian(err)) < 15
    assert mad < 0.8 * mad_g


REAL = [("fpi/chart_depth.mat", 8e-12), ("longrange/tower_9km.mat", 1e-12),
        ("ptu/hydraharp_v20_t3.ptu", None), ("ptu/hydraharp_v10_t3.ptu", None)]


@pytest.mark.slow
@pytest.mark.parametrize("name,unit_s", REAL)
def test_real_files_reconstruct_with_no_pulse_given(shared_data, name, unit_s):
    store = read_photons(shared_data / name, time_unit_s=unit_s).store
    maps = reconstruct(store, ReconSettings(method="uos"))
    assert maps.settings["pulse_source"] == "estimated"
    est = maps.settings["irf_estimate"]
    assert 20e-12 < est["core_rms_s"] < 2e-9
    assert np.isfinite(maps.tof_s).sum() >= min(store.n_pixels, 1000)


def test_real_file_without_a_peak_names_the_options(shared_data):
    store = read_photons(shared_data / "ptu/hydraharp_v20.ht3").store
    with pytest.raises(InputError, match="--pulse-rms-ps.*--irf"):
        reconstruct(store, ReconSettings(method="uos"))


@pytest.mark.slow
def test_save_irf_round_trip_and_picture(shared_data, tmp_path, capsys):
    src = shared_data / "ptu/hydraharp_v10_t3.ptu"
    irf_csv, png = tmp_path / "irf.csv", tmp_path / "point.png"
    assert main(["recon", str(src), "--save-irf", str(irf_csv), "--png", str(png), "--json"]) == 0
    first = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    irf = load_irf(irf_csv)
    assert irf.rms_s == pytest.approx(first["settings"]["irf"]["rms_s"], rel=1e-6)
    assert main(["recon", str(src), "--irf", str(irf_csv), "--json"]) == 0
    second = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert second["settings"]["pulse_source"] == "irf"
    assert second["depth_m_median"] == pytest.approx(first["depth_m_median"], abs=0.01)
    # the picture holds the histogram and the pulse shape side by side
    img = imread(png)
    assert img.shape[1] > 1.4 * img.shape[0]
    # .npy too
    assert main(["recon", str(src), "--pulse-rms-ps", "300", "--save-irf", str(tmp_path / "g.npy")]) == 0
    assert load_irf(tmp_path / "g.npy").rms_s == pytest.approx(300e-12, rel=1e-3)


#: the response measured from fpi/chart_depth.mat by fit_emg_pairs (spdepth recon ... --time-unit-ps 8
#: prints it): Gaussian core 127 ps RMS, 33% of it delayed by an exponential tail of mean 250 ps
CHART_RESPONSE_PS = (127.0, 0.33, 250.0)


def two_layer(rng, n_pix, k, sbr, sep_m, resp_ps=CHART_RESPONSE_PS, span=4500):
    """A pane at 2 m before a wall sep_m behind it, half the signal each, k detections per pixel of
    8 ps units; returns the store and the two true centroids (units)."""
    s, share, tau = (v / 8.0 if i != 1 else v for i, v in enumerate(resp_ps))
    t1, t2 = 2 * 2.0 / 299792458.0 / UNIT_S, 2 * (2.0 + sep_m) / 299792458.0 / UNIT_S
    lists = []
    for _ in range(n_pix):
        ns = rng.binomial(k, sbr / (1 + sbr))
        n1 = rng.binomial(ns, 0.5)
        x = np.concatenate([t1 + emg_times(rng, n1, s, share, tau), t2 + emg_times(rng, ns - n1, s, share, tau),
                            rng.uniform(0, span, k - ns)])
        lists.append(np.floor(x[(x >= 0) & (x < span)]))
    rms = np.sqrt(s ** 2 + share * tau ** 2 * (2 - share))
    return PhotonStore.from_lists(lists, (1, n_pix), UNIT_S), (t1 + share * tau, t2 + share * tau), rms


@pytest.mark.parametrize("sep_m", [1.5, 0.3])
def test_two_surfaces_found_with_the_measured_response(sep_m):
    # 50 detections per pixel, SBR 10, the chart's measured response; no pulse given: both surfaces
    # within 3 response RMS on at least 80% of pixels (the pair differences across the two surfaces
    # must not be read as a tail, nor the tail as a surface)
    rng = np.random.default_rng(14)
    store, truth, rms = two_layer(rng, 1500, 50, 10.0, sep_m)
    maps = reconstruct(store, ReconSettings(method="uos", reflectors=2,
                                            binning=Binning(UNIT_S, 0, 4500, 5)))
    tof = maps.tof_s.reshape(2, -1) / UNIT_S
    both = np.ones(tof.shape[1], bool)
    for t in truth:
        both &= np.any(np.abs(tof - t) < 3 * rms, axis=0)
    print(f"two surfaces {sep_m} m apart: both found on {both.mean():.1%} of pixels")
    assert both.mean() >= 0.8


@pytest.mark.slow
def test_png_draws_a_depth_map_per_surface(tmp_path, capsys):
    # a 20 x 20 two-layer .mat file: --reflectors 2 --png draws depth for surface 1 and surface 2
    import scipy.io

    rng = np.random.default_rng(15)
    store, _, _ = two_layer(rng, 400, 50, 10.0, 1.5)
    cells = np.empty((20, 20), dtype=object)
    for p in range(400):
        cells[p // 20, p % 20] = store.times[store.offsets[p]:store.offsets[p + 1]].reshape(-1, 1)
    src = tmp_path / "two_layer.mat"
    scipy.io.savemat(src, {"Ts": cells})
    one, two = tmp_path / "k1.png", tmp_path / "k2.png"
    assert main(["recon", str(src), "--time-unit-ps", "8", "--png", str(one)]) == 0
    assert main(["recon", str(src), "--time-unit-ps", "8", "--reflectors", "2", "--png", str(two),
                 "--npz", str(tmp_path / "k2.npz")]) == 0
    out = capsys.readouterr().out
    assert "pulse estimated from the data" in out
    # the single-surface sheet: 5 maps + the pulse, 2 rows of 3 panels; with two surfaces depth and
    # uncertainty per surface and the surfaces-found map: 9 panels, 3 rows (acq.report)
    (h1, w1), (h2, w2) = imread(one).shape[:2], imread(two).shape[:2]
    assert w2 == w1
    panel_h = 4.4 * 0.85 + 0.8
    assert h2 / h1 == pytest.approx((3 * panel_h + 0.5) / (2 * panel_h + 0.5), rel=0.05)
    with np.load(tmp_path / "k2.npz") as z:
        depth = z["depth_m"]
    assert depth.shape == (2, 20, 20)
    assert np.nanmedian(depth[0]) == pytest.approx(2.0 + 0.33 * 250e-12 * 299792458.0 / 2, abs=0.03)
    assert np.nanmedian(depth[1]) == pytest.approx(3.5 + 0.33 * 250e-12 * 299792458.0 / 2, abs=0.03)


@pytest.mark.parametrize("k", [5, 15, 60])
def test_uncertainty_is_honest_with_the_measured_response(k):
    # a response with a tail, measured from the data (no pulse given): about 68% of pixels within
    # one reported sigma for uos and ml (at 60 detections a combed pair histogram once made the fit
    # read the whole response as tail: every pixel 35 units off)
    rng = np.random.default_rng(16)
    n_pix = 2000
    centre = rng.uniform(800, 3200, n_pix)
    lists = []
    for c in centre:
        ns = rng.binomial(k, 10 / 11)
        lists.append(np.floor(np.concatenate([c + emg_times(rng, ns, 20.0, 0.4, 100.0),
                                              rng.uniform(0, 4500, k - ns)])))
    store = PhotonStore.from_lists(lists, (1, n_pix), UNIT_S)
    truth = centre + 0.4 * 100.0 - 0.5           # the response's centroid; floor() takes half a unit
    for method in ("uos", "ml"):
        maps = reconstruct(store, ReconSettings(method=method, binning=Binning(UNIT_S, 0, 4500, 5)))
        err = maps.tof_s.ravel() / UNIT_S - truth
        sd = maps.uncertainty_s.ravel() / UNIT_S
        ok = np.isfinite(err)
        share = np.mean(np.abs(err[ok]) < sd[ok])
        print(f"{method} at {k} detections, measured response: {share:.3f} within one sigma")
        # honest means neither too narrow nor much too wide: issue 31's band for a split-half check
        # (55-80% within one sigma). Since recon.detect the reported sigma is the larger of the
        # estimator's and a 40-sample bootstrap's, which over-covers a little at 5-15 detections
        # (0.75-0.76 within one sigma here; 0.68 with the estimator's own sigma before)
        assert 0.55 <= share <= 0.80


def test_bright_background_is_not_read_as_a_tail(tmp_path):
    # simulated daylight (SBR 0.05, a Gaussian pulse of 360 ps with 50 ps jitter): a return's pairs
    # with the background fall off in |dt| once they pass the window's start, which a long "tail"
    # mimics; read as the response, it put every depth late by its mean delay (4.4 m)
    from tests.conftest import _simulate

    ptu = _simulate(tmp_path / "day.ptu", "--scene", "daylight", "--size", "64x64", "--ppp", "100", "--seed", "1")
    store = read_photons(ptu).store
    est = estimate_irf(store)
    assert est.tail_share < 0.05
    assert est.irf.rms_s == pytest.approx(np.hypot(360e-12, 50e-12), rel=0.1)
    maps = reconstruct(store, ReconSettings(method="ml", irf=est.irf))
    truth = np.load(tmp_path / "day.truth.npz")["depth_m"]
    err = np.abs(maps.depth_m - truth)[np.isfinite(maps.depth_m)]
    assert np.median(err) < 0.05


@pytest.mark.parametrize("kind,step", [("float", None), ("int", None), ("int", 3.0), ("float", 0.7)])
def test_the_pair_histogram_bins_as_numpy_does(kind, step):
    # recon.pair_kernels bins each pair as it is formed: the counts of np.histogram over every
    # pair's |dt| among each pixel's first detections, bin for bin (integer times put many
    # differences on the edges themselves), and the same bin width
    from spdepth.recon.model import pair_difference_histogram

    rng = np.random.default_rng(16)
    n = rng.integers(0, 40, 3000)
    offsets = np.concatenate([[0], np.cumsum(n)])
    times = rng.uniform(0, 2500.0, offsets[-1])
    if kind == "int":
        times = np.floor(times)
    hist, got_step = pair_difference_histogram(times, offsets, max_per_pixel=32, step=step)
    first = [times[offsets[p]:offsets[p] + min(n[p], 32)] for p in range(n.size)]
    diffs = np.concatenate([np.abs(t[j] - t[:j]) for t in first for j in range(1, t.size)])
    span = max(float(t.max() - t.min()) for t in first if t.size > 1)
    if step is None and kind == "float":       # 4096 bins over the spread and one bin more
        step, hi = span / 4096, span + span / 4096
    else:                                       # whole bins of the width given (or whole units)
        step = float(max(1, np.ceil(span / 4096))) if step is None else step
        hi = (int(span // step) + 1) * step
    assert got_step == step
    assert np.array_equal(hist, np.histogram(diffs, bins=hist.size, range=(0.0, hi))[0])


def test_the_pulse_is_measured_on_pixels_that_are_the_scene_s_mix():
    # half the pixels are sunlit background without a return and hold the most detections: a
    # sample of the busiest pixels was mostly those (a 256 x 256 daylight scan: its pair peak 2.8
    # times the floor there, 4.3 over the frame, and refused); evenly spaced pixels are the mix
    from spdepth.recon.irf import MAX_PIXELS, estimate_irf

    rng = np.random.default_rng(3)
    lists = []
    for i in range(30000):
        if i % 2:
            x = rng.uniform(0, 4000, 40)
        else:
            x = np.concatenate([1000 + rng.uniform(0, 2000) + 45 * rng.standard_normal(6), rng.uniform(0, 4000, 10)])
        lists.append(np.floor(x))
    assert len(lists) > MAX_PIXELS
    est = estimate_irf(PhotonStore.from_lists(lists, (150, 200), 8e-12))
    assert est.irf.rms_s == pytest.approx(360e-12, rel=0.05)         # busiest pixels: 394 ps
