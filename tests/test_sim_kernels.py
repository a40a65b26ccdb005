"""Each simulator kernel against a plain NumPy/Python reference. Numba's Generator methods draw
the same streams as NumPy's, so references fed an identically seeded generator agree exactly."""

from __future__ import annotations

import numpy as np
from numpy.testing import assert_allclose, assert_array_equal

from spdepth.drivers.events import EVENT_DTYPE
from spdepth.drivers.sim import kernels as K


def ref_generate_chain(rng, pix, start_sync, n_sync, sig_pp, tof_s, bg_pp, period_s, rms_s,
                       irf_cdf=None, irf_t0_s=0.0, irf_bin_s=1.0):
    out = []
    for i, p in enumerate(pix):
        lam = bg_pp[p] + sig_pp[p].sum()
        u = 0.0
        while lam > 0:
            u += rng.standard_exponential() / lam
            if u >= n_sync[i]:
                break
            x = rng.random() * lam
            if x < bg_pp[p]:
                t, o = rng.random() * period_s, 0
            else:
                x -= bg_pp[p]
                k = 0
                while k < sig_pp.shape[1] - 1 and x >= sig_pp[p, k]:
                    x -= sig_pp[p, k]
                    k += 1
                if irf_cdf is None:
                    d = rms_s * rng.standard_normal()
                else:
                    j = min(np.searchsorted(irf_cdf, rng.random(), side="right"), irf_cdf.size - 1)
                    d = irf_t0_s + (j + rng.random()) * irf_bin_s
                t = np.mod(tof_s[p, k] + d, period_s)
                o = 1 + k
            out.append((start_sync[i] + int(u), t, o, i))
    a = np.array(out, dtype=[("s", "i8"), ("t", "f8"), ("o", "u1"), ("i", "i4")])
    return a["s"], a["t"], a["o"], a["i"]


def _tables(rng, n_pix, k):
    sig = rng.uniform(0, 0.02, (n_pix, k))
    tof = rng.uniform(5e-9, 95e-9, (n_pix, k))
    tof[0, 0] = 99.9e-9          # a pulse that folds over the period end
    bg = rng.uniform(0, 0.01, n_pix)
    bg[1] = 0.0
    return sig, tof, bg


def _run_chain(seed, pix, starts, nsync, sig, tof, bg, kind=K.PULSE_GAUSSIAN, cdf=np.zeros(1),
               t0=0.0, b=1.0, cap=100_000):
    out = [np.empty(cap, np.int64), np.empty(cap), np.empty(cap, np.uint8), np.empty(cap, np.int32)]
    n, i, u = K.generate_chain(np.random.default_rng(seed), pix, starts, nsync, 0, 0.0, sig, tof,
                               bg, 100e-9, kind, 360e-12, cdf, t0, b, *out)
    assert i == pix.size
    return [o[:n] for o in out]


def test_generate_chain_matches_reference(rng):
    sig, tof, bg = _tables(rng, 6, 2)
    pix = np.array([0, 1, 2, 3, 4, 5, 2], np.int64)
    starts = np.arange(7, dtype=np.int64) * 3000 + 17
    nsync = np.full(7, 3000, np.int64)
    got = _run_chain(4, pix, starts, nsync, sig, tof, bg)
    ref = ref_generate_chain(np.random.default_rng(4), pix, starts, nsync, sig, tof, bg,
                             100e-9, 360e-12)
    assert got[0].size > 100
    for g, r in zip(got, ref):
        assert_allclose(g, r, rtol=1e-12, atol=1e-21)


def test_generate_chain_measured_irf_matches_reference(rng):
    sig, tof, bg = _tables(rng, 3, 1)
    irf = rng.uniform(0, 1, 50)
    cdf = np.cumsum(irf) / irf.sum()
    cdf[-1] = 1.0
    pix = np.arange(3, dtype=np.int64)
    starts = np.zeros(3, np.int64)
    nsync = np.full(3, 5000, np.int64)
    got = _run_chain(5, pix, starts, nsync, sig, tof, bg, K.PULSE_TABLE, cdf, -0.4e-9, 16e-12)
    ref = ref_generate_chain(np.random.default_rng(5), pix, starts, nsync, sig, tof, bg, 100e-9,
                             0.0, cdf, -0.4e-9, 16e-12)
    for g, r in zip(got, ref):
        assert_allclose(g, r, rtol=1e-12, atol=1e-21)


def test_generate_chain_resumes_exactly_when_output_is_full(rng):
    sig, tof, bg = _tables(rng, 4, 1)
    pix = np.arange(4, dtype=np.int64)
    starts = np.arange(4, dtype=np.int64) * 10_000
    nsync = np.full(4, 10_000, np.int64)
    whole = _run_chain(6, pix, starts, nsync, sig, tof, bg)
    r = np.random.default_rng(6)
    parts, i, u = [], 0, 0.0
    while i < pix.size:
        out = [np.empty(7, np.int64), np.empty(7), np.empty(7, np.uint8), np.empty(7, np.int32)]
        n, i, u = K.generate_chain(r, pix, starts, nsync, i, u, sig, tof, bg, 100e-9,
                                   K.PULSE_GAUSSIAN, 360e-12, np.zeros(1), 0.0, 1.0, *out)
        parts.append(out[0][:n])
    assert_array_equal(np.concatenate(parts), whole[0])


def test_sort_within_sync_matches_lexsort(rng):
    n = 5000
    sync = np.sort(rng.integers(0, 800, n)).astype(np.int64)
    t = rng.uniform(0, 1e-7, n)
    origin = rng.integers(0, 3, n).astype(np.uint8)
    item = np.arange(n, dtype=np.int32)
    order = np.lexsort((t, sync))
    ref = [a[order] for a in (sync, t, origin, item)]
    K.sort_within_sync(sync, t, origin, item)
    for g, r in zip((sync, t, origin, item), ref):
        assert_array_equal(g, r)


def test_jitter_kernel_matches_numpy():
    t = np.random.default_rng(1).uniform(0, 100e-9, 1000)
    t[:3] = [1e-12, 99.99e-9, 50e-9]
    ref = np.mod(t + 300e-12 * np.random.default_rng(2).standard_normal(t.size), 100e-9)
    K.jitter_kernel(np.random.default_rng(2), t, 300e-12, 100e-9)
    assert_allclose(t, ref, rtol=1e-12, atol=1e-21)


def ref_dead_time(sync, t, period_s, dead_s, last=None):
    keep = []
    for s, x in zip(sync, t):
        a = s * period_s + x
        if last is None or a - last >= dead_s - 1e-18:
            keep.append(True)
            last = a
        else:
            keep.append(False)
    return np.array(keep)


def _det(sync, t, dead_s, ap=0.0, tau=0.0, stop=0, win=(0, 12500), seed=0):
    n = sync.size
    st_i, st_t = np.zeros(3, np.int64), np.zeros(1)
    ps, pt, pi = np.zeros(64, np.int64), np.zeros(64), np.zeros(64, np.int32)
    out = [np.empty(2 * n + 64, np.int64), np.empty(2 * n + 64), np.empty(2 * n + 64, np.uint8),
           np.empty(2 * n + 64, np.int32)]
    m, c = K.detector_kernel(np.random.default_rng(seed), sync, t, np.zeros(n, np.uint8),
                             np.arange(n, dtype=np.int32), 100e-9, dead_s, ap, tau,
                             K.DetState(st_i, st_t, ps, pt, pi), int(sync.max()) + 10, stop, 8e-12, 12500,
                             win[0], win[1], *out)
    return [o[:m] for o in out], c, st_i


def test_detector_kernel_dead_time_matches_reference(rng):
    n = 20_000
    sync = np.sort(rng.integers(0, 30_000, n)).astype(np.int64)
    t = rng.uniform(0, 100e-9, n)
    order = np.lexsort((t, sync))
    sync, t = sync[order], t[order]
    (s_out, t_out, _, item), _, st = _det(sync, t, 70e-9)
    keep = ref_dead_time(sync, t, 100e-9, 70e-9)
    assert_array_equal(item, np.flatnonzero(keep))
    assert st[0] == 1 and st[1] == s_out[-1]


def test_detector_kernel_stops_at_count(rng):
    n = 2000
    sync = np.arange(n, dtype=np.int64) * 3
    t = rng.uniform(0, 100e-9, n)
    (s_out, t_out, _, _), c, _ = _det(sync, t, 0.0, stop=25, win=(2000, 6000))
    d = (t_out / 8e-12).astype(np.int64)
    inside = (d >= 2000) & (d < 6000)
    assert c == 25 and inside.sum() == 25 and inside[-1]


def test_detector_kernel_afterpulse_reference():
    """A single detection with afterpulse probability p: the afterpulse draws match NumPy's."""
    sync = np.array([10], np.int64)
    t = np.array([20e-9])
    (s_out, t_out, o, _), _, _ = _det(sync, t, 30e-9, ap=0.4999, tau=40e-9, seed=3)
    r = np.random.default_rng(3)
    ref_s, ref_t = [10], [20e-9]
    s, x = 10, 20e-9
    while r.random() < 0.4999:
        a = x + 30e-9 + 40e-9 * r.standard_exponential()
        s, x = s + int(np.floor(a / 100e-9)), np.mod(a, 100e-9)
        if s >= 20:   # beyond sync_end: stays pending
            break
        ref_s.append(s)
        ref_t.append(x)
    assert_array_equal(s_out, ref_s)
    assert_allclose(t_out, ref_t, rtol=1e-12)
    assert np.all(o[1:] == K.ORIGIN_AFTERPULSE)


def test_pack_events_matches_numpy(rng):
    n = 3000
    sync = np.sort(rng.integers(0, 5000, n)).astype(np.int64)
    t = rng.uniform(0, 100e-9, n)
    origin = rng.integers(0, 3, n).astype(np.uint8)
    m_sync = np.sort(rng.integers(0, 5200, 40)).astype(np.int64)
    m_bits = rng.integers(1, 16, 40).astype(np.uint8)
    range_bins = 10_000  # drops detections after 80 ns
    ev = np.zeros(n + 40, EVENT_DTYPE)
    org = np.zeros(n + 40, np.uint8)
    m = K.pack_events(sync, t, origin, 8e-12, range_bins, 3, m_sync, m_bits, ev["sync"],
                      ev["dtime"], ev["channel"], ev["kind"], ev["marker"], org)
    d = (t / 8e-12).astype(np.int64)
    keep = d < range_bins
    ref = np.zeros(keep.sum() + 40, EVENT_DTYPE)
    ref_o = np.empty(ref.size, np.uint8)
    # markers first within a sync: sort by (sync, photon-after-marker)
    key_s = np.concatenate([m_sync, sync[keep]])
    key_k = np.concatenate([np.zeros(40), np.ones(keep.sum())])
    order = np.lexsort((key_k, key_s), axis=0)
    ref["sync"] = key_s[order]
    ref["dtime"] = np.concatenate([np.zeros(40, np.int64), d[keep]])[order]
    ref["kind"] = 1 - key_k[order]     # key 0 = marker (kind 1), key 1 = photon (kind 0)
    ref["marker"] = np.concatenate([m_bits, np.zeros(keep.sum(), np.uint8)])[order]
    ref["channel"] = np.where(key_k[order] == 1, 3, 0)
    ref_o[:] = np.concatenate([np.full(40, K.ORIGIN_MARKER, np.uint8), origin[keep]])[order]
    assert m == ref.size
    assert_array_equal(ev[:m], ref)
    assert_array_equal(org[:m], ref_o)

