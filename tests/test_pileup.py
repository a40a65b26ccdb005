"""Pile-up: Coates' correction (recon.pileup) against detectors simulated here period by period, and
spdepth recon on a simulated high-flux scan (the flux table's point at ~0.9 detections per pulse is
in ``spdepth bench flux``)."""

from __future__ import annotations

import numpy as np
import pytest

from spdepth.recon.counts import CountStore
from spdepth.recon.errors import InputError
from spdepth.recon.pileup import Detector, coates, correct_pileup, detections_per_period


def rates(n_bins=200, signal=0.8, bg=0.2, centre=60.0, rms=3.0):
    """Mean photons per period in each bin: a Gaussian return on a flat background."""
    k = np.arange(n_bins)
    pulse = np.exp(-0.5 * ((k - centre) / rms) ** 2)
    return bg / n_bins + signal * pulse / pulse.sum()


def first_photon_histogram(lam, n_periods, rng):
    """A detector that re-arms at each sync: per period, the first bin with a photon (if any)."""
    hits = rng.poisson(lam, size=(n_periods, lam.size)) > 0
    any_hit = hits.any(axis=1)
    first = np.argmax(hits, axis=1)[any_hit]
    return np.bincount(first, minlength=lam.size)


def dead_time_histogram(lam, n_periods, dead_bins, rng):
    """A non-paralysable detector with a dead time shorter than the period, running across periods."""
    hits = rng.poisson(lam, size=(n_periods, lam.size)) > 0
    t = np.flatnonzero(hits.ravel())          # absolute bin of every photon, in time order
    out = np.zeros(lam.size, np.int64)
    last = -10 ** 12
    for v in t:
        if v - last >= dead_bins:
            out[v % lam.size] += 1
            last = v
    return out


def as_store(hist, n_periods):
    return CountStore.from_cube(hist[None, None, :], 1e-12, periods=[n_periods])


@pytest.mark.parametrize("flux", [0.05, 0.5, 1.5])
def test_coates_recovers_the_flux_of_a_detector_that_rearms_at_each_sync(flux):
    rng = np.random.default_rng(1)
    lam = rates(signal=flux * 0.8, bg=flux * 0.2)
    n = 40_000
    hist = first_photon_histogram(lam, n, rng)
    corrected = coates(as_store(hist, n))
    got = np.zeros(lam.size)
    got[corrected.times.astype(int)] = corrected.counts
    ideal = n * lam
    # the return's detections and its centroid, as an ideal detector would have had them
    k = np.arange(lam.size)
    near = np.abs(k - 60) < 12
    # within 4 Poisson sigma of the ideal count (the correction's own variance is larger, not smaller)
    assert got[near].sum() == pytest.approx(ideal[near].sum(), abs=4 * np.sqrt(ideal[near].sum()))
    assert np.average(k[near], weights=got[near]) == pytest.approx(60.0, abs=4 * 3.0 / np.sqrt(hist[near].sum()))
    # the raw histogram leans early and loses detections once flux is not small
    if flux >= 0.5:
        assert hist[near].sum() < 0.85 * ideal[near].sum()
        assert np.average(k[near], weights=hist[near]) < 59.7


def test_coates_with_a_dead_time_shorter_than_the_period():
    """Detections late in a period shadow the start of the next: the classic formula misses
    that, the dead-time one does not."""
    rng = np.random.default_rng(2)
    n_bins, dead = 200, 100
    lam = rates(n_bins, signal=0.6, bg=1.0, centre=30.0)
    n = 20_000
    hist = dead_time_histogram(lam, n, dead, rng)
    store = as_store(hist, n)
    ideal = n * lam
    k = np.arange(n_bins)
    near = np.abs(k - 30) < 12
    with_dead = coates(store, Detector(period_units=n_bins, dead_units=dead))
    classic = coates(store)

    def near_sum(c):
        got = np.zeros(n_bins)
        got[c.times.astype(int)] = c.counts
        return got[near].sum()

    assert near_sum(with_dead) == pytest.approx(ideal[near].sum(), abs=4 * np.sqrt(ideal[near].sum()))
    assert abs(near_sum(classic) / ideal[near].sum() - 1) > 2 * abs(near_sum(with_dead) / ideal[near].sum() - 1)


def test_auto_switches_on_where_detections_per_period_are_not_small():
    rng = np.random.default_rng(3)
    n = 5_000
    low = as_store(first_photon_histogram(rates(signal=0.02, bg=0.005), n, rng), n)
    high = as_store(first_photon_histogram(rates(signal=0.6, bg=0.2), n, rng), n)
    assert detections_per_period(low)[0, 0] < 0.05 < detections_per_period(high)[0, 0]
    same, rec = correct_pileup(low)
    assert same is low and not rec["applied"] and "negligible" in rec["reason"]
    fixed, rec = correct_pileup(high)
    assert rec["applied"] and fixed.n_detections > high.n_detections
    off, rec = correct_pileup(high, "off")
    assert off is high and not rec["applied"]
    unknown = CountStore(high.times, high.counts, high.offsets, high.shape, high.time_unit_s)
    assert not correct_pileup(unknown)[1]["applied"]
    with pytest.raises(InputError, match="periods"):
        correct_pileup(unknown, "on")


def test_a_photon_list_is_decided_as_its_histogram_and_histogrammed_only_when_corrected():
    """A file's photon list goes to the decision as it is (its histogram is built only when the
    correction applies): the same record, and the same corrected counts, as from its histogram."""
    from spdepth.recon.photons import PhotonStore

    rng = np.random.default_rng(4)
    n = 2_000
    for signal, applied in ((0.02, False), (0.6, True)):
        hist = [first_photon_histogram(rates(signal=signal, bg=0.005), n, rng) for _ in range(6)]
        photons = PhotonStore.from_lists([np.repeat(np.arange(h.size), h).astype(np.float64)
                                          for h in hist], (2, 3), 1e-12)
        periods = np.full(6, float(n))
        counts = CountStore.from_photons(photons, periods)
        got, rec = correct_pileup(photons, periods=periods)
        want, rec_counts = correct_pileup(counts)
        assert rec == rec_counts and rec["applied"] is applied
        if applied:
            assert isinstance(got, CountStore)
            np.testing.assert_array_equal(got.counts, want.counts)
            np.testing.assert_array_equal(got.times, want.times)
        else:
            assert got is photons
    with pytest.raises(InputError, match="periods"):
        correct_pileup(photons, "on")


@pytest.mark.slow
def test_recon_of_a_high_flux_scan_is_corrected_by_itself(tmp_path, capsys):
    """At ~0.6 detections per pulse the uncorrected depth leans early by about a centimetre and the
    signal is a quarter short; corrected (by itself: the PTU tells its periods) both come back."""
    import json

    from spdepth.acq.cli import main

    ptu = tmp_path / "hf.ptu"
    assert main(["simulate", "--scene", "tilted-plane", "--size", "12x12", "--ppp", "600", "--sbr", "10",
                 "--dwell-us", "100", "--ptu", str(ptu)]) == 0
    truth = np.load(tmp_path / "hf.truth.npz")
    out = {}
    for mode in ("auto", "off"):
        assert main(["recon", str(ptu), "--pulse-rms-ps", "360", "--pileup", mode, "--json",
                     "--npz", str(tmp_path / f"{mode}.npz")]) == 0
        s = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
        from spdepth.recon.maps import DepthMaps

        m = DepthMaps.load_npz(tmp_path / f"{mode}.npz")
        out[mode] = (100 * np.nanmean(m.depth_m - truth["depth_m"]),
                     np.nansum(m.signal) / truth["signal"].sum() - 1, s)
    bias, sig, s = out["auto"]
    assert s["settings"]["pileup"]["applied"] and s["pileup"]["applied"]
    assert any("pile-up" in n for n in s["notes"])
    assert abs(bias) < 0.3 and abs(sig) < 0.1
    bias_off, sig_off, _ = out["off"]
    assert bias_off < -0.5 and sig_off < -0.15


@pytest.mark.slow
def test_a_session_recording_knows_its_periods(tmp_path, capsys):
    """A count-gated scan at ~0.6 detections per pulse: its recording tells each pixel's periods
    (the session's store), so spdepth recon corrects it by itself."""
    from spdepth.acq.cli import main
    from spdepth.drivers.sim import load_scene
    from spdepth.recon.maps import DepthMaps

    out = tmp_path / "scan"
    assert main(["scan", "--sim", "--scene", "tilted-plane", "--size", "8x8", "--ppp", "9000",
                 "--target", "400", "--out", str(out)]) == 0
    truth = load_scene("tilted-plane", (8, 8), ppp=9000).truth()["depth_m"]
    bias = {}
    for mode in ("auto", "off"):
        assert main(["recon", str(out / "recording.ptu"), "--pileup", mode, "--npz",
                     str(tmp_path / f"{mode}.npz")]) == 0
        m = DepthMaps.load_npz(tmp_path / f"{mode}.npz")
        bias[mode] = 100 * np.nanmean(m.depth_m - truth)
        assert ("pileup" in m.settings) == (mode == "auto")
    assert "pile-up" in capsys.readouterr().err
    assert abs(bias["auto"]) < 0.3 < -bias["off"]


def test_a_live_scan_at_high_flux_is_corrected_as_recon_corrects_its_recording(tmp_path, capsys):
    """The live maps of a count-gated scan at ~0.9 detections per pulse come from Coates-corrected
    histograms (acq.live_recon, per pixel), as spdepth recon of the recording does: depth and signal
    per laser period near the truth, the summary says so, and the live maps equal recon's."""
    import json

    from spdepth.acq.cli import main
    from spdepth.drivers.sim import load_scene
    from spdepth.recon.maps import DepthMaps

    out = tmp_path / "scan"
    assert main(["scan", "--sim", "--scene", "tilted-plane", "--size", "8x8", "--ppp", "9000",
                 "--target", "200", "--out", str(out), "--json"]) == 0
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert summary["pileup"]["applied"] and summary["pileup"]["pixels"] == 64
    truth = load_scene("tilted-plane", (8, 8), ppp=9000).truth()
    live = DepthMaps.load_npz(out / "maps.npz")
    assert live.settings["pileup"]["applied"]
    with np.load(out / "maps.npz", allow_pickle=True) as z:
        periods = z["exposure_s"] / 100e-9            # the simulated laser's 10 MHz
    assert abs(100 * np.mean(live.depth_m - truth["depth_m"])) < 0.3
    # the truth's signal is per scene dwell of 10,000 periods
    signal_error = np.sum(live.signal / periods) / np.sum(truth["signal"] / 10_000) - 1
    assert abs(signal_error) < 0.1, signal_error
    assert main(["recon", str(out / "recording.ptu"), "--npz", str(tmp_path / "recon.npz")]) == 0
    again = DepthMaps.load_npz(tmp_path / "recon.npz")
    np.testing.assert_allclose(again.depth_m, live.depth_m, rtol=0, atol=1e-6)
    np.testing.assert_allclose(again.signal, live.signal, rtol=1e-6)
    # uncorrected (what the live maps were before): early and short
    assert main(["recon", str(out / "recording.ptu"), "--pileup", "off", "--npz", str(tmp_path / "off.npz")]) == 0
    plain = DepthMaps.load_npz(tmp_path / "off.npz")
    assert 100 * np.mean(plain.depth_m - truth["depth_m"]) < -0.5
    assert np.sum(plain.signal / periods) / np.sum(truth["signal"] / 10_000) - 1 < -0.2
