"""Binning.from_window / from_data: THE binning rule from SI seconds, and the seed paper's settings."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings as hsettings, strategies as st

from spdepth.recon.errors import InputError
from spdepth.recon.maps import C_M_PER_S
from spdepth.recon.model import BINS_PER_PULSE_RMS, SEED_PAPER, Binning, ReconSettings, default_bin_width


def bits(b: Binning) -> tuple[str, ...]:
    return tuple(float(v).hex() for v in (b.time_unit_s, b.window_start, b.window_stop, b.bin_width))


def old_from_ps(time_unit_ps, window_ps, bin_ps) -> Binning:
    """Binning.from_ps as it was before from_window (the arithmetic only)."""
    start_ps, stop_ps = window_ps
    return Binning(time_unit_ps * 1e-12, start_ps / time_unit_ps, stop_ps / time_unit_ps, bin_ps / time_unit_ps)


def old_run_one(times, unit_s, window_ps, bin_ps, pulse_rms_ps) -> Binning:
    """What ``spdepth recon`` (acq/commands/recon.py run_one) did with one of window/bin given."""
    unit_ps = unit_s * 1e12
    if window_ps is not None:
        start_u, stop_u = window_ps[0] / unit_ps, window_ps[1] / unit_ps
    else:
        start_u = math.floor(float(times.min()))
        stop_u = math.floor(float(times.max())) + 1
    if bin_ps is not None:
        bin_u = bin_ps / unit_ps
    else:
        bin_u = default_bin_width(stop_u - start_u, pulse_rms_ps / unit_ps if pulse_rms_ps else None)
    return old_from_ps(unit_ps, (start_u * unit_ps, stop_u * unit_ps), round(bin_u) * unit_ps)


WINDOWS = [(8, (16000, 48000), 40), (8, (0, 32040), 8), (8, (16000, 48000), 360), (1, (123, 4567), 3),
           (4, (100, 50000), 12), (25, (0, 100000), 25), (12, (16000, 48000), 36), (5, (2.5, 1e6), 5),
           (16, (0, 65536 * 16), 16 * 16), (8, (100, 200), 8)]


@pytest.mark.parametrize("unit_ps, window_ps, bin_ps", WINDOWS)
def test_from_window_is_from_ps_bit_for_bit(unit_ps, window_ps, bin_ps):
    ps = Binning.from_ps(unit_ps, window_ps, bin_ps)
    si = Binning.from_window(unit_ps * 1e-12, (window_ps[0] * 1e-12, window_ps[1] * 1e-12), bin_ps * 1e-12)
    assert bits(si) == bits(ps) == bits(old_from_ps(unit_ps, window_ps, bin_ps))


def test_from_window_takes_whole_units_where_plain_division_would_not():
    # 16000e-12 / 8e-12 is 2000.0000000000002 in floating point; the rule gives unit 2000
    assert 16000e-12 / 8e-12 != 2000.0
    b = Binning.from_window(8e-12, (16000e-12, 48000e-12), 40e-12)
    assert (b.window_start, b.window_stop, b.bin_width, b.n_bins) == (2000.0, 6000.0, 5.0, 800)


@pytest.mark.parametrize("args, message", [
    ((8e-12, (0.0, 32040e-12), 1e-3), "bin 1e+09 ps is wider than the window 0-32040 ps"),
    ((8e-12, (0.0, 32040e-12), 44e-12), "bin 44 ps is not a whole number of 8 ps raw units"),
    ((8e-12, (0.0, 32040e-12), 4e-12), "bin 4 ps is not a whole number of 8 ps raw units"),
    ((8e-12, (0.0, 32040e-12), 0.0), "bin 0 ps must be positive"),
    ((8e-12, (0.0, 32040e-12), -40e-12), "bin -40 ps must be positive"),
    ((8e-12, (0.0, 32040e-12), math.nan), "bin nan ps is not finite"),
    ((8e-12, (48000e-12, 16000e-12), 40e-12), "window 48000-16000 ps is empty: stop must exceed start"),
    ((8e-12, (16000e-12, 16000e-12), 40e-12), "window 16000-16000 ps is empty: stop must exceed start"),
    ((8e-12, (-80e-12, 16000e-12), 40e-12), "window start -80 ps is negative"),
    ((8e-12, (0.0, math.inf), 40e-12), "window stop inf ps is not finite"),
    ((8e-12, (math.nan, 1e-9), 40e-12), "window start nan ps is not finite"),
    ((0.0, (0.0, 1e-9), 40e-12), "time unit 0 ps must be positive"),
    ((-8e-12, (0.0, 1e-9), 40e-12), "time unit -8 ps must be positive"),
    ((math.inf, (0.0, 1e-9), 40e-12), "time unit inf ps is not finite"),
    ((8e-12, (0.0,), 40e-12), "window must be (start_s, stop_s)"),
    ((8e-12, (0.0, "x"), 40e-12), "window stop must be a number of seconds, got 'x'"),
])
def test_from_window_refuses_with_the_value_in_ps(args, message):
    with pytest.raises(InputError) as exc:
        Binning.from_window(*args)
    assert str(exc.value).startswith(message)


def test_a_bin_as_wide_as_the_window_is_one_bin():
    b = Binning.from_window(8e-12, (0.0, 32000e-12), 32000e-12)
    assert b.n_bins == 1


def test_from_ps_refuses_what_from_window_refuses():
    with pytest.raises(InputError, match="bin 1e\\+09 ps is wider than the window 0-32040 ps"):
        Binning.from_ps(8, (0, 32040), 1e9)


@hsettings(max_examples=300, deadline=None)
@given(unit_ps=st.sampled_from([1, 2, 4, 5, 8, 12, 16, 25, 0.5]),
       start=st.integers(0, 10**6), length=st.integers(1, 10**6), k=st.integers(1, 50))
def test_from_window_matches_from_ps_on_whole_ps(unit_ps, start, length, k):
    bin_ps = k * unit_ps
    # at most Binning's 1,000,000 bins (0.5 ps units over 10**6 ps would give 2,000,000)
    stop = start + min(max(length, bin_ps), 10**6 * bin_ps)
    ps = Binning.from_ps(unit_ps, (start, stop), bin_ps)
    si = Binning.from_window(unit_ps * 1e-12, (start * 1e-12, stop * 1e-12), bin_ps * 1e-12)
    assert bits(si) == bits(ps) == bits(old_from_ps(unit_ps, (start, stop), bin_ps))


@hsettings(max_examples=300, deadline=None)
@given(unit_ps=st.sampled_from([1, 4, 5, 8, 12, 16, 25]), seed=st.integers(0, 2**32 - 1),
       which=st.sampled_from(["window", "bin", "both", "neither"]),
       pulse_ps=st.sampled_from([None, 30.0, 360.0, 1000.0]))
def test_from_data_is_what_spdepth_recon_did(unit_ps, seed, which, pulse_ps):
    rng = np.random.default_rng(seed)
    lo = int(rng.integers(0, 5000))
    times = np.floor(rng.uniform(lo, lo + rng.integers(50, 20000), 200))
    unit_s = unit_ps * 1e-12
    window_ps = bin_ps = None
    if which in ("window", "both"):
        a = int(rng.integers(0, 1000)) * unit_ps
        window_ps = (a, a + int(rng.integers(200, 40000)) * unit_ps)
    if which in ("bin", "both"):
        bin_ps = int(rng.integers(1, 20)) * unit_ps
    got = Binning.from_data(times, unit_s, window_s=None if window_ps is None else
                            (window_ps[0] * 1e-12, window_ps[1] * 1e-12),
                            bin_s=None if bin_ps is None else bin_ps * 1e-12,
                            pulse_rms_s=None if pulse_ps is None else pulse_ps * 1e-12)
    want = old_run_one(times, unit_s, window_ps, bin_ps, pulse_ps)
    assert bits(got) == bits(want)


def test_from_data_window_is_the_span_of_the_detections():
    times = np.array([2001.7, 2500.0, 5998.2])
    b = Binning.from_data(times, 8e-12, bin_s=40e-12)
    assert (b.window_start, b.window_stop, b.bin_width) == (2001.0, 5999.0, 5.0)
    b = Binning.from_data(times, 8e-12, pulse_rms_s=360e-12)
    assert b.bin_width == 5.0                               # a ninth of the pulse RMS, in whole units
    b = Binning.from_data(times, 8e-12, window_s=(0.0, 80000e-12))
    assert (b.window_start, b.window_stop, b.bin_width) == (0.0, 10000.0, 3.0)   # at most 4096 bins


def test_from_data_refuses():
    with pytest.raises(InputError, match="without detections"):
        Binning.from_data(np.array([]), 8e-12, bin_s=40e-12)
    with pytest.raises(InputError, match="bin 1e\\+09 ps is wider than the window 16000-32008 ps"):
        Binning.from_data(np.array([2000.0, 4000.0]), 8e-12, bin_s=1e-3)
    with pytest.raises(InputError, match="bin 44 ps is not a whole number of 8 ps raw units"):
        Binning.from_data(np.array([2000.0, 4000.0]), 8e-12, bin_s=44e-12)


def test_seed_paper():
    b = SEED_PAPER.binning
    assert (b.time_unit_s, b.window_start, b.bin_width, b.n_bins) == (8e-12, 2000.0, 5.0, 801)
    assert b.bin_width_s == pytest.approx(40e-12, rel=1e-12)
    assert SEED_PAPER.pulse_rms_s == 360e-12
    s = SEED_PAPER.settings("lmf")
    assert (s.method, s.max_photons, s.binning, s.pulse_rms_s) == ("lmf", 15, b, 360e-12)
    default = ReconSettings()
    assert (default.delta, default.max_iterations) == (SEED_PAPER.delta, SEED_PAPER.max_iterations) == (1e-4, 10)
    assert BINS_PER_PULSE_RMS == 9.0 and default_bin_width(4000, SEED_PAPER.pulse_rms_units) == SEED_PAPER.bin_units
    assert C_M_PER_S == 299_792_458.0


def test_a_default_bin_wider_than_the_detections_makes_one_bin():
    # detections within 3 units and a 360 ps pulse: the default bin (5 units) is wider than the
    # span, and the detections say no more than one bin (as spdepth recon did)
    times = np.array([4000.0, 4001.0, 4002.0])
    b = Binning.from_data(times, 8e-12, pulse_rms_s=360e-12)
    assert (b.window_start, b.window_stop, b.bin_width, b.n_bins) == (4000.0, 4003.0, 5.0, 1)
    assert bits(b) == bits(old_run_one(times, 8e-12, None, None, 360.0))
