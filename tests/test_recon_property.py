"""Every output finite or flagged over the whole input space (issue 9), and an honest uncertainty."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings as hsettings, strategies as st

from spdepth.recon.errors import InputError
from spdepth.recon.estimate import reconstruct
from spdepth.recon.maps import PixelFlag
from spdepth.recon.model import Binning, ReconSettings
from spdepth.recon.photons import PhotonStore

UNIT_S = 8e-12
BIN_UNITS = 5.0


def log_uniform(lo, hi):
    return st.floats(np.log10(lo), np.log10(hi)).map(lambda e: float(10.0 ** e))


detections = st.one_of(st.integers(0, 30), st.integers(0, 1000), st.integers(0, 1_000_000))


@hsettings(max_examples=30, deadline=None, derandomize=True)
@given(n_det=st.lists(detections, min_size=1, max_size=3), sbr=log_uniform(0.01, 100),
       rms_bins=log_uniform(0.05, 50), n_bins=st.one_of(st.integers(1, 8), st.integers(1, 4096)),
       k=st.integers(1, 3), method=st.sampled_from(("lmf", "uos", "ml")), seed=st.integers(0, 2**32 - 1),
       pulse_given=st.booleans())
def test_outputs_finite_or_flagged_over_the_whole_space(n_det, sbr, rms_bins, n_bins, k, method, seed,
                                                        pulse_given):
    if k > 1:
        method = "uos"          # the K-sparse pursuit is uos's
    rng = np.random.default_rng(seed)
    b = Binning(UNIT_S, 0.0, n_bins * BIN_UNITS, BIN_UNITS)
    span = n_bins * BIN_UNITS
    lists = []
    for n in n_det:
        n_sig = rng.binomial(n, sbr / (1 + sbr))
        centres = rng.uniform(0, span, k)
        t = np.concatenate([rng.choice(centres, n_sig) + rms_bins * BIN_UNITS * rng.standard_normal(n_sig),
                            rng.uniform(0, span, n - n_sig)])
        lists.append(np.floor(t))           # a tagger's integer units; some fall outside the window
    store = PhotonStore.from_lists(lists, (1, len(lists)), UNIT_S)
    settings = ReconSettings(method=method, binning=b, reflectors=k,
                             pulse_rms_s=rms_bins * b.bin_width_s if pulse_given else None)
    try:
        maps = reconstruct(store, settings)
    except InputError as exc:
        # without a pulse, data that hold no usable peak are refused, naming the options to give
        assert not pulse_given and "--pulse-rms-ps" in str(exc) and "--irf" in str(exc), str(exc)
        return
    tof = maps.tof_s.reshape(k, -1)
    unc = maps.uncertainty_s.reshape(k, -1)
    sig = maps.signal.reshape(k, -1)
    used = maps.photons.ravel()
    flags = maps.flags.ravel()
    has = np.isfinite(tof)
    # no infinities anywhere; NaN only where no return is reported
    for a in (tof, unc, sig, maps.depth_m, maps.background):
        assert not np.any(np.isinf(a))
    assert np.all(np.isfinite(unc[has])) and np.all(unc[has] > 0)
    assert np.all(np.isnan(unc[~has]))
    # a return lies in the window and its uncertainty is at most the window's uniform spread (+ a bin)
    assert np.all((tof[has] >= b.window_start_s) & (tof[has] <= b.window_stop_s))
    assert np.all(unc[has] <= (n_bins / np.sqrt(12) + 1) * b.bin_width_s)
    # counts are non-negative and not absurd against the detections used
    assert np.all(np.isfinite(sig)) and np.all(sig >= 0)
    assert np.all(sig.sum(axis=0) <= 2 * used + 1)
    if method == "lmf":
        assert np.all(np.isnan(maps.background))
    else:
        bg = maps.background.ravel()
        assert np.all(np.isfinite(bg)) and np.all(bg >= 0)
        assert np.all(bg * n_bins <= 2 * used + 1)
    # every pixel without a first return says why
    assert np.all(has[0] | (flags != PixelFlag.OK))
    assert np.all((used > 0) | (flags == PixelFlag.NO_PHOTONS))


def _simulate(rng, n_pix, k, sbr, m, rms_units):
    """n_pix pixels of k detections (signal share sbr / (1 + sbr)), one surface each; integer times."""
    span = m * BIN_UNITS
    centre = rng.uniform(0.15 * span, 0.85 * span, n_pix)
    n_sig = rng.binomial(k, sbr / (1 + sbr), n_pix)
    sig = np.repeat(centre, n_sig) + rms_units * rng.standard_normal(n_sig.sum())
    per = np.split(sig, np.cumsum(n_sig)[:-1])
    lists = [np.floor(np.concatenate([s, rng.uniform(0, span, k - s.size)])) for s in per]
    # floor() moves each time down by half a unit on average
    return PhotonStore.from_lists(lists, (1, n_pix), UNIT_S), centre - 0.5


@pytest.mark.parametrize("method", ("uos", "ml"))
def test_uncertainty_is_honest(method):
    # the seed paper's pulse-to-bin ratio (360 ps RMS, 40 ps bins) at its SBR of 10: the share of
    # pixels whose error is within one reported sigma must be 68% +- 5% at 5, 15 and 60 detections
    rng = np.random.default_rng(2024)
    m, rms_units = 401, 45.0
    b = Binning(UNIT_S, 0.0, m * BIN_UNITS, BIN_UNITS)
    shares = {}
    for k in (5, 15, 60):
        store, truth = _simulate(rng, 3000, k, 10.0, m, rms_units)
        maps = reconstruct(store, ReconSettings(method=method, binning=b, pulse_rms_s=rms_units * UNIT_S))
        err = maps.tof_s.ravel() / UNIT_S - truth
        sd = maps.uncertainty_s.ravel() / UNIT_S
        ok = np.isfinite(err)
        # 5 detections (4.5 of them signal): the test finds no return in a pixel of ~3 signal
        # (77% report one at the look-elsewhere threshold, 9.2 nats; 85% at the 8.2 before it;
        # 72% with half the rate to the own test, the other half the neighbours' support's)
        assert ok.mean() > (0.70 if k == 5 else 0.99)
        shares[k] = float(np.mean(np.abs(err[ok]) < sd[ok]))
    print(f"{method}: share within one sigma " + ", ".join(f"{k} det {v:.3f}" for k, v in shares.items()))
    for k, v in shares.items():
        # at 5 detections only the pixels whose return passes the test report a depth (~77%): the
        # stronger ones, a little more often within their sigma
        hi = 0.76 if k == 5 else 0.73
        assert 0.63 < v < hi, f"{method} at {k} detections: {v:.3f} within one sigma"
