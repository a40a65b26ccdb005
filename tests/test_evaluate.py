"""spdepth.acq.evaluate: hand-computable cases, and ML against the per-pixel oracle on a simulated scene."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from spdepth.acq.evaluate import (OUTLIER_PULSE_WIDTHS, DepthErrors, evaluate_depth, oracle_mae_m,
                          signal_detections)
from spdepth.drivers.sim import load_scene
from spdepth.recon.errors import InputError
from spdepth.recon.estimate import reconstruct
from spdepth.recon.maps import C_M_PER_S
from spdepth.recon.model import Binning, ReconSettings

from sim_frames import count_gated_store

SIGMA_S = 2 / C_M_PER_S      # a pulse whose RMS width is exactly 1 m of depth


def test_oracle_formula():
    # c/2 * sigma = 1 m: the bound is sqrt(2/pi)/sqrt(k) metres
    got = oracle_mae_m([1.0, 4.0, 0.0, -1.0], SIGMA_S)
    assert got[:2] == pytest.approx([math.sqrt(2 / math.pi), math.sqrt(2 / math.pi) / 2])
    assert np.all(np.isnan(got[2:]))        # no signal: nothing to find
    # the paper's yardstick: 15 detections at SBR 10, 360 ps -> about 1.2 cm
    assert float(oracle_mae_m(15 * 10 / 11, 360e-12)) == pytest.approx(0.0117, abs=2e-4)
    with pytest.raises(InputError):
        oracle_mae_m(1.0, 0.0)


def test_errors_with_one_denominator_and_misses_as_outliers():
    true = np.array([[1.0, 2.0], [3.0, np.nan]])     # the NaN pixel has no truth: not evaluated
    est = np.array([[1.1, np.nan], [2.7, 5.0]])
    s = evaluate_depth(est, true, 4.0, SIGMA_S, outlier_m=0.25)
    assert isinstance(s, DepthErrors) and s.n_pixels == 3 and s.outlier_m == 0.25
    # errors 0.1, miss -> 0.25 (the threshold), 0.3
    assert s.mae_m == pytest.approx((0.1 + 0.25 + 0.3) / 3)
    assert s.rmse_m == pytest.approx(math.sqrt((0.01 + 0.0625 + 0.09) / 3))
    assert s.miss_share == pytest.approx(1 / 3)
    assert s.outlier_share == pytest.approx(2 / 3)     # the miss and the 0.3 m error
    oracle = math.sqrt(2 / math.pi) / 2
    assert s.oracle_mae_m == pytest.approx(oracle)
    assert s.ratio_to_oracle == pytest.approx(s.mae_m / oracle)
    with pytest.raises(dataclasses.FrozenInstanceError):
        s.mae_m = 0.0


def test_per_pixel_oracle_and_pixels_without_signal():
    true = np.zeros(3)
    est = np.array([0.5, 0.5, 0.5])
    k = np.array([1.0, 4.0, 0.0])                     # the third pixel expects no signal
    s = evaluate_depth(est, true, k, SIGMA_S)
    assert s.n_pixels == 2 and s.mae_m == pytest.approx(0.5)
    assert s.oracle_mae_m == pytest.approx(math.sqrt(2 / math.pi) * (1 + 0.5) / 2)
    assert s.outlier_m == pytest.approx(OUTLIER_PULSE_WIDTHS * 1.0)
    assert s.outlier_share == 0 and s.miss_share == 0


def test_missing_everything_costs_the_threshold():
    s = evaluate_depth(np.full(4, np.nan), np.ones(4), 9.0, SIGMA_S, outlier_m=0.2)
    assert s.mae_m == pytest.approx(0.2) and s.rmse_m == pytest.approx(0.2)
    assert s.miss_share == 1 and s.outlier_share == 1


def test_bad_calls():
    with pytest.raises(InputError, match="shape"):
        evaluate_depth(np.zeros(3), np.zeros(4), 1.0, SIGMA_S)
    with pytest.raises(InputError, match="no pixel"):
        evaluate_depth(np.zeros(2), np.full(2, np.nan), 1.0, SIGMA_S)
    with pytest.raises(InputError, match="outlier_m"):
        evaluate_depth(np.zeros(2), np.zeros(2), 1.0, SIGMA_S, outlier_m=-1)


def test_signal_detections_from_truth():
    # per pulse: signal 0.3 and 0.1 (surface 1), background 0.4 over a 100 ns period
    truth = {"signal_pp": np.array([[[0.3]], [[0.1]]]), "background_pp": np.array([[0.4]]),
             "settings": {"sync_period_s": 100e-9, "tagger_range_s": 25e-9}}
    # recorded window 25 ns: a quarter of the background is among the detections
    assert signal_detections(truth, 10)[0, 0] == pytest.approx(10 * 0.3 / (0.3 + 0.1 + 0.1))
    assert signal_detections(truth, 10, surface=1)[0, 0] == pytest.approx(10 * 0.1 / 0.5)
    assert signal_detections(truth, 10, window_s=100e-9)[0, 0] == pytest.approx(10 * 0.3 / 0.8)
    with pytest.raises(InputError):
        signal_detections(truth, 10, surface=2)
    # one surface: detections * SBR / (1 + SBR)
    one = {"signal_pp": np.array([[1.0, 2.0]]), "background_pp": np.array([[0.1, 0.1]]),
           "settings": {"sync_period_s": 100e-9, "tagger_range_s": None}}
    np.testing.assert_allclose(signal_detections(one, np.array([[11, 21]])), [[10, 20]])


def test_ml_lands_near_the_per_pixel_oracle_on_a_simulated_scene():
    # the demo's settings: a count-gated scan of 15 in-window detections per pixel, the paper's
    # 801 bins of 40 ps; the bust's reflectivity makes the SBR vary from pixel to pixel
    h = w = 32
    n, bins, bin_s = 15, 801, 40e-12
    scene = load_scene("bust", (h, w), ppp=n, sbr=10, tagger_range_s=bins * bin_s)
    store = count_gated_store(scene, n, seed=11)
    unit = round(bin_s / scene.resolution_s)
    binning = Binning(scene.resolution_s, 0, bins * unit, unit)
    maps = reconstruct(store, ReconSettings(method="ml", binning=binning,
                                            pulse_rms_s=scene.pulse_rms_s, max_photons=n))
    truth = scene.truth()
    k = signal_detections(truth, maps.photons)
    assert np.all(maps.photons == n) and 13 < k.mean() < 15   # in-window SBR well above 10
    s = evaluate_depth(maps.depth_m, truth["depth_m"], k, scene.pulse_rms_s)
    assert s.n_pixels == h * w and s.miss_share == 0
    assert 0.011 < s.oracle_mae_m < 0.012
    assert 0.85 <= s.ratio_to_oracle <= 1.15, s     # about 1.0 over seeds and scenes
