"""Effects on demand: without an effect the detections follow equation (3) of the paper exactly
and the effect's code never runs; with it, the known distortion appears."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import stats

from spdepth.drivers.sim import PhotonWorld, effects, kernels, load_scene
from spdepth.drivers.sim.scene import PILEUP_THRESHOLD


def _group(counts, expected, min_expected=20.0):
    """Merge neighbouring bins until each expects at least ``min_expected`` detections."""
    obs, exp = [], []
    o = e = 0.0
    for c, x in zip(counts, expected):
        o += c
        e += x
        if e >= min_expected:
            obs.append(o)
            exp.append(e)
            o = e = 0.0
    if e > 0:
        obs[-1] += o
        exp[-1] += e
    return np.asarray(obs), np.asarray(exp)


def _chi2_pvalue(counts, expected):
    """Poisson chi-square of counts against expected means (no normalisation: the total is part
    of what equation (3) predicts)."""
    o, e = _group(counts, expected)
    chi2 = float(((o - e) ** 2 / e).sum())
    return stats.chi2.sf(chi2, df=o.size), o.size


def _pure_scene(**kw):
    # 2 x 2 so each pixel has its own depth; one second of dwell -> 1e7 pulses
    args = dict(ppp=2e5, sbr=2.0, dwell_s=1.0)
    args.update(kw)
    return load_scene("tilted-plane", (2, 2), **args)


@pytest.mark.parametrize("pixel", [(0, 0), (1, 1)])
def test_no_effects_follow_equation_3(pixel):
    scene = _pure_scene()
    assert scene.active_effects == ()
    assert scene.rate_per_pulse().max() < PILEUP_THRESHOLD
    world = PhotonWorld(scene, seed=11)
    ev, n_syncs = world.fixed_dwell(*pixel, 1.0, 0)
    hist = np.bincount(ev["dtime"], minlength=scene.settings.range_bins)
    expected = scene.bin_rates(*pixel, n_pulses=n_syncs)
    p, dof = _chi2_pvalue(hist, expected)
    assert dof > 500
    assert p > 1e-3, f"chi-square p = {p:.2g} over {dof} bins"


def test_equation_3_chi_square_detects_a_wrong_model():
    """The chi-square test above has power: the same histogram against a pulse 10% wider fails."""
    scene = _pure_scene()
    world = PhotonWorld(scene, seed=12)
    ev, n_syncs = world.fixed_dwell(0, 0, 1.0, 0)
    hist = np.bincount(ev["dtime"], minlength=scene.settings.range_bins)
    wrong = scene.with_settings(pulse_rms_s=scene.pulse_rms_s * 1.1).bin_rates(0, 0, n_pulses=n_syncs)
    p, _ = _chi2_pvalue(hist, wrong)
    assert p < 1e-6


def test_measured_irf_follows_equation_3():
    # a skewed instrument response (fast rise, slow tail), 16 ps bins
    t = np.arange(200)
    irf = np.where(t < 20, t / 20.0, np.exp(-(t - 20) / 40.0))
    scene = _pure_scene(irf=irf, irf_bin_s=16e-12)
    world = PhotonWorld(scene, seed=13)
    ev, n_syncs = world.fixed_dwell(1, 0, 1.0, 0)
    hist = np.bincount(ev["dtime"], minlength=scene.settings.range_bins)
    p, _ = _chi2_pvalue(hist, scene.bin_rates(1, 0, n_pulses=n_syncs))
    assert p > 1e-3


def _boom(*args, **kwargs):
    raise AssertionError("effect code ran for a scene that does not call for it")


@pytest.mark.parametrize("name, target", [
    ("jitter", (effects.Jitter, "apply")),
    ("jitter", (kernels, "jitter_kernel")),
    ("dead_time", (effects.DeadTime, "apply")),
    ("dead_time", (kernels, "detector_kernel")),
    ("afterpulsing", (effects.Afterpulsing, "apply")),
    ("afterpulsing", (kernels, "detector_kernel")),
])
def test_effect_code_runs_only_when_called_for(monkeypatch, name, target):
    monkeypatch.setattr(*target, _boom)
    plain = load_scene("bust", (8, 8), ppp=15)
    world = PhotonWorld(plain, seed=0)
    world.raster()
    world.raster(n_target=5)
    world.fixed_dwell(3, 3, 1e-3, 0)
    world.count_gated(3, 3, 10, 1e-2, 0, (2000, 6000))
    # the same hook does fire once the scene names the effect
    named = load_scene("bust", (8, 8), ppp=15, effects=(name,))
    with pytest.raises(AssertionError, match="effect code ran"):
        PhotonWorld(named, seed=0).raster()


def test_pileup_switches_dead_time_on_by_itself():
    low = load_scene("bust", (4, 4), ppp=15)
    assert "dead_time" not in low.active_effects
    high = load_scene("bust", (4, 4), ppp=15, dwell_s=10e-6)  # 100 pulses: 0.15 per pulse
    assert high.rate_per_pulse().max() > PILEUP_THRESHOLD
    assert "dead_time" in high.active_effects
    assert "dead_time" in high.truth()["settings"]["active_effects"]


def test_jitter_widens_the_pulse():
    rms, jit = 360e-12, 250e-12
    widths = {}
    for name, eff in (("plain", ()), ("jitter", ("jitter",))):
        scene = load_scene("tilted-plane", (1, 1), ppp=20000, sbr=float("inf"), dwell_s=1.0,
                           pulse_rms_s=rms, jitter_rms_s=jit, effects=eff)
        ev, _ = PhotonWorld(scene, seed=5).fixed_dwell(0, 0, 1.0, 0)
        t = ev["dtime"] * scene.resolution_s
        widths[name] = float(np.std(t))
    q = scene.resolution_s ** 2 / 12  # quantisation to tagger bins
    assert widths["plain"] == pytest.approx(np.sqrt(rms**2 + q), rel=0.025)
    assert widths["jitter"] == pytest.approx(np.sqrt(rms**2 + jit**2 + q), rel=0.025)


def test_dead_time_pileup_matches_coates():
    """At 1.5 detections per pulse the dead detector registers only the first photon of each
    pulse: the histogram is skewed early exactly as P(k) = exp(-sum_{j<k} l_j) (1 - exp(-l_k))."""
    scene = load_scene("tilted-plane", (1, 1), ppp=1.5 * 20000, sbr=float("inf"), dwell_s=2e-3,
                       dead_time_s=60e-9, effects=("dead_time",))
    world = PhotonWorld(scene, seed=21)
    ev, n = world.fixed_dwell(0, 0, 2e-3, 0)
    assert n == 20000
    assert np.all(np.diff(ev["sync"].astype(np.int64)) >= 1)  # one detection per pulse at most
    lam = scene.bin_rates(0, 0, n_pulses=1.0)
    assert lam.sum() == pytest.approx(1.5, rel=1e-6)
    before = np.concatenate([[0.0], np.cumsum(lam)[:-1]])
    coates = n * np.exp(-before) * (1 - np.exp(-lam))
    hist = np.bincount(ev["dtime"], minlength=lam.size)
    p, _ = _chi2_pvalue(hist, coates)
    assert p > 1e-3
    # against the undistorted shape the same data fail: the pile-up is really there
    p_ideal, _ = _chi2_pvalue(hist, lam / lam.sum() * hist.sum())
    assert p_ideal < 1e-6
    tof = float(scene.tof_s[0, 0, 0])
    mean_t = float((ev["dtime"] + 0.5).mean() * scene.resolution_s)
    assert mean_t < tof - 0.4 * scene.pulse_rms_s
    # the Coates correction recovers the true per-pulse rate
    cum = np.concatenate([[0], np.cumsum(hist)[:-1]])
    live = n - cum
    ok = live > 0
    lam_hat = -np.log1p(-hist[ok] / live[ok])
    assert lam_hat.sum() == pytest.approx(1.5, rel=0.05)


def test_afterpulsing_adds_delayed_correlated_counts():
    p_ap, tau = 0.1, 50e-9
    counts = {}
    for name, eff in (("plain", ()), ("ap", ("afterpulsing",))):
        scene = load_scene("tilted-plane", (1, 1), ppp=20000, sbr=1.0, dwell_s=2.0,
                           afterpulse_prob=p_ap, afterpulse_tau_s=tau, effects=eff)
        ev, n, origin = PhotonWorld(scene, seed=8).fixed_dwell(0, 0, 2.0, 0, with_origin=True)
        t_abs = ev["sync"] * scene.sync_period_s + (ev["dtime"] + 0.5) * scene.resolution_s
        gaps = np.diff(t_abs)
        short = gaps < 10 * tau
        counts[name] = (ev.size, int((origin == kernels.ORIGIN_AFTERPULSE).sum()),
                        float(short.mean()), gaps[short])
    n_plain, ap_plain, frac_plain, _ = counts["plain"]
    n_ap, ap_n, frac_ap, short_gaps = counts["ap"]
    assert ap_plain == 0
    # a cascade: each detection afterpulses with p, so total = primary / (1 - p)
    primary = n_ap - ap_n
    assert ap_n == pytest.approx(primary * p_ap / (1 - p_ap), rel=0.06)
    assert primary == pytest.approx(n_plain, rel=0.03)
    # accidental close pairs: 10 tau = 5 pulses at 1e-3 detections per pulse -> 0.5%
    assert frac_plain < 0.01
    assert frac_ap == pytest.approx(p_ap + frac_plain, abs=0.012)
    # the delays are exponential with mean tau, mixed with the accidental pairs (uniform over
    # the 10 tau span, mean 5 tau)
    expected_mean = (p_ap * tau + frac_plain * 5 * tau) / (p_ap + frac_plain)
    assert float(short_gaps.mean()) == pytest.approx(expected_mean, rel=0.08)


def test_afterpulsing_with_dead_time_waits_for_the_detector():
    dead = 40e-9
    scene = load_scene("tilted-plane", (1, 1), ppp=20000, sbr=1.0, dwell_s=2.0,
                       afterpulse_prob=0.2, afterpulse_tau_s=30e-9, dead_time_s=dead,
                       effects=("dead_time", "afterpulsing"))
    ev, n = PhotonWorld(scene, seed=9).fixed_dwell(0, 0, 2.0, 0)
    t_abs = ev["sync"] * scene.sync_period_s + ev["dtime"] * scene.resolution_s
    gaps = np.diff(t_abs)
    assert gaps.min() >= dead - 2 * scene.resolution_s
    short = gaps[gaps < dead + 10 * 30e-9]
    assert float(short.mean() - dead) == pytest.approx(30e-9, rel=0.1)
