"""The numba kernels against the plain NumPy references of tests/reference.py, pixel by pixel."""

from __future__ import annotations

import numpy as np
import pytest

import reference as ref
from spdepth.recon import kernels as K
from spdepth.recon.estimators import lmf_kernels as LK
from spdepth.recon.estimators import ml_bounds as MB
from spdepth.recon.estimators import ml_kernels as MLK
from spdepth.recon.estimators import uos_kernels as UK
from spdepth.recon.estimate import reconstruct
from spdepth.recon.model import FISHER_RHO0, FISHER_STEPS, Binning, Irf, ReconSettings, build_kernel
from spdepth.recon.photons import PhotonStore

M = 201
BIN = Binning(8e-12, 0.0, M * 5.0, 5.0)
RMS_S = 4 * 40e-12          # 4 bins: short kernel, dense references stay fast


def random_pixels(rng, n_pix, k=15, sbr=5.0, m=M):
    """Bin lists of n_pix pixels: a Gaussian return (RMS 4 bins) plus uniform background."""
    lists = []
    for _ in range(n_pix):
        ns = rng.binomial(k, sbr / (1 + sbr))
        c = rng.uniform(5, m - 5)
        s = np.clip(np.floor(c + 4 * rng.standard_normal(ns) + 0.5), 0, m - 1)
        b = rng.integers(0, m, k - ns)
        lists.append(np.concatenate([s, b]).astype(np.int64))
    return lists


def csr(lists):
    off = np.zeros(len(lists) + 1, np.int64)
    off[1:] = np.cumsum([len(x) for x in lists])
    return np.concatenate(lists).astype(np.int64), off


@pytest.fixture(scope="module")
def kern():
    return build_kernel(BIN, pulse_rms_s=RMS_S)


def test_build_kernel_gives_the_kept_tables_for_the_same_pulse_only():
    # a live scan rebuilds nothing batch after batch; another pulse, binning or IRF gets its own
    irf = Irf(tuple(np.arange(40) * 40e-12), tuple(np.exp(-0.5 * ((np.arange(40) - 12) / 3.0) ** 2)))
    a = build_kernel(BIN, pulse_rms_s=RMS_S)
    assert build_kernel(Binning(8e-12, 0.0, M * 5.0, 5.0), pulse_rms_s=RMS_S) is a
    other = build_kernel(BIN, pulse_rms_s=2 * RMS_S)
    assert other is not a and other.rms_bins == pytest.approx(2 * a.rms_bins)
    wider = build_kernel(Binning(8e-12, 0.0, M * 10.0, 5.0), pulse_rms_s=RMS_S)
    assert wider.colsum.size == 2 * M
    by_irf = build_kernel(BIN, irf=irf)
    assert build_kernel(BIN, irf=Irf(irf.times_s, irf.counts)) is by_irf
    assert by_irf.info["pulse"] == "irf" and a.info["pulse"] == "gaussian"


def test_unique_bins_by_bitmap_equals_the_sort_and_leaves_its_scratch_zero(rng):
    # every kernel reads a pixel's distinct bins and counts through unique_bins: a bitmap of the
    # window when the detections lie close, the sort (unique_counts) when they spread
    m = 3000
    tally = np.zeros(m, np.int64)
    bits = np.zeros(m // 64 + 1, np.uint64)
    paths = set()
    for trial in range(400):
        n = int(rng.integers(1, 80))
        if trial % 4 == 0:      # a cluster on the words' edges: bins 63, 64, 127, 128 ...
            b = rng.choice(np.array([0, 63, 64, 127, 128, 191, m - 1]), n)
        elif trial % 4 == 1:    # spread over the window: the sort
            b = rng.integers(0, m, n)
        else:                   # a return with repeats, some background
            b = np.clip(np.round(rng.normal(rng.uniform(0, m), rng.uniform(0.5, 40), n)), 0, m - 1)
        b = b.astype(np.int64)
        out = [np.empty(n, np.int64), np.empty(n, np.int64), np.empty(n)]
        nu = K.unique_bins(b, 0, n, tally, bits, *out)
        kb, kw = out[1][:nu], out[2][:nu]
        want_b, want_w = np.unique(b, return_counts=True)
        np.testing.assert_array_equal(kb, want_b)
        np.testing.assert_array_equal(kw, want_w)
        assert not tally.any() and not bits.any()
        paths.add(b.max() // 64 - b.min() // 64 < K.BITMAP_WORDS * n)
    assert paths == {True, False}
    # the lowest set bit, compiled (LLVM's cttz) and in plain Python (NUMBA_DISABLE_JIT) alike
    from numba import njit

    lowest = njit(lambda x: K.lowest_set_bit(x))
    for v in (1, 6, 2 ** 40 + 2 ** 63, 2 ** 63, 96):
        assert K.lowest_set_bit(np.uint64(v)) == lowest(np.uint64(v)) == (v & -v).bit_length() - 1


@pytest.mark.parametrize("pulse", ["gaussian", "irf"])
def test_ml_variance_from_the_fisher_table_matches_the_loop(rng, pulse):
    # ml reads its uncertainty's sums from a table over log(a / B) for shifts inside the window;
    # at the edges, without background or off the table it takes the loop itself
    if pulse == "irf":
        t = np.arange(60)
        kern = build_kernel(BIN, irf=Irf(tuple(t * 40e-12), tuple(np.exp(-t / 6.0) * (t >= 3) + 1e-3)))
    else:
        kern = build_kernel(BIN, pulse_rms_s=RMS_S)
    g, dg, off = kern.g, kern.dg, kern.off
    n_table = n_no_bg = 0
    for _ in range(3000):
        a = 10 ** rng.uniform(-4, 6)
        bg = 0.0 if rng.random() < 0.05 else 10 ** rng.uniform(-12, 2)
        shift = int(rng.integers(0, M))
        loop = K.fisher_var(shift, a, bg, M, g, dg, off)
        inside = off <= shift <= M - g.size + off
        row = (np.log(a / bg) - FISHER_RHO0) * FISHER_STEPS if bg > 0 else -1.0
        n_table += inside and 1 <= row < kern.fisher.shape[0] - 3     # its last row is for bg = 0
        # without background the table's last row holds the loop's own sums: equal to rounding
        n_no_bg += inside and bg == 0
        np.testing.assert_allclose(K.fisher_tab(shift, a, bg, M, g, dg, off, kern.fisher), loop,
                                   rtol=1e-12 if bg == 0 else 2e-5, err_msg=f"a {a}, bg {bg}, shift {shift}")
    assert n_table > 1500       # the table, not the loop, gave most of them
    assert n_no_bg > 50
    assert np.isnan(K.fisher_tab(100, 0.0, 1.0, M, g, dg, off, kern.fisher))


def test_dense_s_matches_kernel_tables(kern):
    s = ref.dense_s(kern)
    np.testing.assert_allclose(s.sum(axis=0), kern.colsum, rtol=1e-12, atol=1e-15)
    for i, j in [(0, 0), (3, 5), (100, 97), (200, 199), (200, 200), (0, 30)]:
        np.testing.assert_allclose(K.col_dot(i, j, M, kern.pp, kern.off, kern.g.size), s[:, i] @ s[:, j],
                                   rtol=1e-10, atol=1e-15)


def test_lmf_kernel_matches_reference(kern, rng):
    lists = random_pixels(rng, 60)
    bins, off = csr(lists)
    out = np.empty(60, np.int64)
    var = np.empty(60)
    n = np.empty(60, np.int64)
    log_s = ref.dense_logs(kern)
    assert kern.log_concave
    for concave in (True, False):    # the hill climb and the exhaustive scan agree with argmax
        LK.lmf_kernel(K.Photons(bins, off), LK.LmfTables(M, kern.logg, concave), 15, out, var, n)
        want = [ref.lmf(ref.histogram(b, M), log_s) for b in lists]
        np.testing.assert_array_equal(out, want)
    assert np.all(n == 15) and np.all(var > 0)


def test_uos_kernel_matches_published_loop(kern, rng):
    lists = random_pixels(rng, 80)
    bins, off = csr(lists)
    a_mat = np.hstack([ref.dense_s(kern) / kern.gmax, np.ones((M, 1))])
    shift, amp = np.full(80, np.nan), np.zeros(80)
    bg, it, conv, n = np.zeros(80), np.zeros(80, np.int32), np.zeros(80, bool), np.zeros(80, np.int64)
    tabs = UK.uos_tables(kern.g, kern.off, kern.gmax, kern.colsum, kern.pp, M, 1e-4, 10)
    UK.uos_kernel(K.Photons(bins, off), tabs, 15, shift, amp, bg, it, conv, n)
    for p, b in enumerate(lists):
        x, iters = ref.uos(ref.histogram(b, M), a_mat)
        nz = np.flatnonzero(x[:M])
        assert it[p] == iters
        if nz.size:
            assert shift[p] == nz[0]
            np.testing.assert_allclose(amp[p] * kern.gmax, x[nz[0]], rtol=1e-8)
        else:
            assert np.isnan(shift[p])
        np.testing.assert_allclose(bg[p], x[M], rtol=1e-8, atol=1e-12)


@pytest.mark.slow
@pytest.mark.parametrize("k, sbr", [(15, 2.0), (120, 2.0), (10, 0.05)])
def test_ml_kernel_global_integer_optimum_matches_reference(kern, rng, k, sbr):
    # k = 120: more distinct photon bins than ML_SCAN_ALL, so each solve searches the photons under
    # the pulse (and counts the rest as one rate-0 term) instead of scanning them all; SBR 0.05:
    # so many shifts survive U that their bounds come from share_sweep (on 9 of 10 such pixels)
    assert (k > MB.ML_SCAN_ALL) == (k == 120)
    lists = random_pixels(rng, 10, k=k, sbr=sbr)
    bins, off = csr(lists)
    s_mat = ref.dense_s(kern)
    for p, b in enumerate(lists):
        y = ref.histogram(b, M)
        i_ref, ll_ref, ll_all = ref.ml_integer(y, s_mat)
        tau_ref = ref.ml_refined(y, kern, s_mat)
        st = PhotonStore.from_lists([b * 5.0 + 2.0], (1, 1), 8e-12)
        r = estimator_maps(st, ReconSettings(method="ml", binning=BIN, pulse_rms_s=RMS_S))
        tau = (r.tof_s[0, 0] / 8e-12 / 5.0) - 0.5
        # same global optimum (EM reference converges to 1e-6 nats: allow ties within that)
        near = np.flatnonzero(ll_all >= ll_ref - 1e-5)
        assert np.min(np.abs(near - tau)) <= 1.0
        assert abs(tau - tau_ref) <= 1.0 / 8 + 1e-9
        y_sum = y.sum()
        assert r.signal[0, 0] + r.background[0, 0] * M == pytest.approx(y_sum, rel=1e-6)


@pytest.mark.parametrize("rms_bins", [MLK.ML_CLIMB_RMS_BINS, 4.0])
def test_ml_fine_climb_finds_the_full_searchs_shift(rng, rms_bins):
    # the climb over the fine shifts (a smooth pulse) against the search of all of them, on the
    # narrowest pulse it is used for: few detections (where twin peaks would show), sub-bin returns
    from spdepth.recon.estimators.ml import ml_tables
    kern_w = build_kernel(BIN, pulse_rms_s=rms_bins * 40e-12)
    tabs = ml_tables(kern_w, M)
    assert tabs.fine_climb is True          # what reconstruct passes for this pulse
    for k in (2, 3, 5, 15, 60):
        for sbr in (0.3, 3.0, 30.0):
            n = 400
            lists = []
            for _ in range(n):
                ns = rng.binomial(k, sbr / (1 + sbr))
                t = np.concatenate([rng.uniform(5, M - 5) + rms_bins * rng.standard_normal(ns),
                                    rng.uniform(0, M, k - ns)])
                lists.append(np.clip(np.floor(t), 0, M - 1).astype(np.int64))
            bins, off = csr(lists)
            shifts = []
            for climb in (True, False):
                sh = np.full(n, np.nan)
                MLK.ml_kernel(K.Photons(bins, off), tabs._replace(fine_climb=climb), k, sh, np.empty(n),
                              np.empty(n), np.empty(n), np.empty(n, np.int64), np.empty(n))
                shifts.append(sh)
            np.testing.assert_allclose(shifts[0], shifts[1], rtol=0, atol=1e-9,
                                       err_msg=f"{k} detections, SBR {sbr}")
    # a sub-bin pulse searches every fine shift (its likelihood has flat or twin peaks between them)
    assert ml_tables(build_kernel(BIN, pulse_rms_s=0.05 * 40e-12), M).fine_climb is False


def test_irf_kernel_brute_force_lmf_matches_reference(rng, tmp_path):
    # an asymmetric, not log-concave response (two lobes): the exhaustive LMF path
    t_ps = np.arange(0, 2000, 8.0)
    counts = np.exp(-0.5 * ((t_ps - 400) / 60) ** 2) + 0.3 * np.exp(-0.5 * ((t_ps - 900) / 80) ** 2)
    irf = Irf(tuple(t_ps * 1e-12), tuple(counts))
    kern = build_kernel(BIN, irf=irf)
    assert not kern.log_concave
    lists = random_pixels(rng, 30)
    bins, off = csr(lists)
    out, var, n = np.empty(30, np.int64), np.empty(30), np.empty(30, np.int64)
    LK.lmf_kernel(K.Photons(bins, off), LK.LmfTables(M, kern.logg, kern.log_concave), 15, out, var, n)
    log_s = ref.dense_logs(kern)
    np.testing.assert_array_equal(out, [ref.lmf(ref.histogram(b, M), log_s) for b in lists])


def _dense_proxy(cvec, colsum, bgc, j, aj, kern, m):
    """The proxy of Algorithm 1 for x = (aj on column j, background bgc), every shift, with the same
    floating-point expression as the kernel (cvec - bgc*colsum, minus aj * S_i^T S_j near j)."""
    nk = kern.g.size
    v = cvec - bgc * colsum
    if aj is not None:
        s = ref.dense_s(kern)
        lo, hi = max(0, j - (nk - 1)), min(m - 1, j + (nk - 1))
        i = np.arange(lo, hi + 1)
        v[i] = v[i] - aj * (s[:, i].T @ s[:, j])
    return v


@pytest.mark.parametrize("case", range(40))
def test_pruned_uos_argmax_is_the_dense_argmax(kern, rng, case):
    # photons anywhere (edges included), backgrounds from none to far above the photons' level (the
    # dense fallback), supports inside the window and clipped by its edges
    nk, off, m = kern.g.size, kern.off, M
    n = int(rng.integers(1, 20))
    kb = np.unique(np.concatenate([rng.integers(0, m, n), [0, m - 1][:case % 3]])).astype(np.int64)
    kw = rng.integers(1, 4, kb.size).astype(np.float64)
    cvec = np.zeros(m)
    for k, w in zip(kb, kw):
        i = np.arange(max(0, k - (nk - 1 - off)), min(m - 1, k + off) + 1)
        cvec[i] += w / kern.gmax * kern.g[k - i + off]
    ivlo, ivhi = np.empty(kb.size, np.int64), np.empty(kb.size, np.int64)
    niv = K.photon_intervals(kb, kb.size, nk - 1 - off, off, m, ivlo, ivhi)
    covered = np.zeros(m, bool)
    for t in range(niv):
        covered[ivlo[t]:ivhi[t] + 1] = True
    assert np.all(cvec[~covered] == 0.0) and np.all(ivlo[1:niv] > ivhi[:niv - 1] + 1)
    bgc = [0.0, 1e-3, 0.3, 50.0][case % 4]
    j = int([rng.integers(0, m), 1, m - 2, kb[0]][(case // 4) % 4])
    amp = None if case % 5 == 0 else float(rng.uniform(0.0, 3.0))
    # uos1_argmax takes the peak-1 scaling: aj multiplies S_i^T S_j of the unit-area kernel
    aj_k = 0.0 if amp is None else amp / kern.gmax ** 2
    got = UK.uos1_argmax(cvec, kern.colsum, kern.colsum.min(), bgc, 0 if amp is None else 1, j, aj_k,
                        _acorr(kern), nk, m, kern.pp, off, ivlo, ivhi, niv)
    want = int(np.argmax(_dense_proxy(cvec, kern.colsum, bgc, j, None if amp is None else aj_k, kern, m)))
    assert got == want


def _acorr(kern):
    g = kern.g
    return np.correlate(g, g, mode="full")


def test_huge_pixel_matches_reference_and_methods_agree():
    # one pixel of 50,000 detections over 4096 bins (a point measurement): the uos kernel follows
    # the published loop exactly, the LMF equals its dense reference, and the ML agrees with uos
    rng = np.random.default_rng(50_000)
    m = 4096
    b = Binning(8e-12, 0.0, float(m), 1.0)
    rms_s = 25 * 8e-12
    t = np.concatenate([1500.3 + 25 * rng.standard_normal(40_000), rng.uniform(0, m, 10_000)])
    t = t[(t >= 0) & (t < m)]
    store = PhotonStore.from_lists([t], (1, 1), 8e-12)
    kern = build_kernel(b, pulse_rms_s=rms_s)
    y = ref.histogram(b.bin_index(t), m)
    res = {meth: reconstruct(store, ReconSettings(method=meth, binning=b, pulse_rms_s=rms_s))
           for meth in ("uos", "lmf", "ml")}
    shift = {meth: r.tof_s[0, 0] / 8e-12 - 0.5 for meth, r in res.items()}
    a_mat = np.hstack([ref.dense_s(kern) / kern.gmax, np.ones((m, 1))])
    x, iters = ref.uos(y, a_mat)
    assert res["uos"].photons[0, 0] == t.size
    assert shift["uos"] == pytest.approx(np.flatnonzero(x[:m])[0], abs=1e-6)
    assert res["uos"].iterations[0, 0] == iters
    np.testing.assert_allclose(res["uos"].background[0, 0], x[m], rtol=1e-8)
    assert shift["lmf"] == pytest.approx(ref.lmf(y, ref.dense_logs(kern)), abs=1e-6)
    assert abs(shift["ml"] - shift["uos"]) <= 1.0 and abs(shift["ml"] - 1500.3) <= 1.0


@pytest.mark.parametrize("max_photons", [None, 1, 3, 15])
def test_window_bins_is_first_in_window_then_bin_index(rng, max_photons):
    # times straddling both window edges, exact edge values, empty pixels and a window that is not a
    # whole number of bins (the last partial bin, and rounding at the stop edge)
    b = Binning(8e-12, 1000.0, 1000.0 + 37.5 * 7.0, 7.0)
    lists = [rng.uniform(900.0, 1400.0, int(rng.integers(0, 25))) for _ in range(200)]
    lists[3] = np.array([b.window_start, b.window_stop, np.nextafter(b.window_stop, 0.0), 999.999])
    lists[4] = np.array([])
    store = PhotonStore.from_lists(lists, (10, 20), 8e-12)
    used = store.first_in_window(b.window_start, b.window_stop, max_photons)
    want = b.bin_index(used.times)
    out_b = np.empty(store.times.size, np.int64)
    out_o = np.empty(store.offsets.size, np.int64)
    n = K.window_bins(store.times, store.offsets, b.window_start, b.window_stop, b.bin_width, b.n_bins,
                      -1 if max_photons is None else max_photons, out_b, out_o)
    np.testing.assert_array_equal(out_o, used.offsets)
    np.testing.assert_array_equal(out_b[:n], want)
    assert n == want.size and np.all(want >= 0) and want.max() == b.n_bins - 1


def test_kernel_sorts_match_numpy(rng):
    # sort_run/heap_sort and sort_desc stand in for np.sort / a stable argsort inside the
    # kernels; ties are frequent here, and sort_desc must keep equal keys in index order
    for n in (0, 1, 2, 5, 49, 50, 333):
        a = rng.integers(0, 40, n).astype(np.int64)
        b = a.copy()
        K.heap_sort(b, n)
        np.testing.assert_array_equal(b, np.sort(a))
        x = rng.normal(size=n + 6)
        y = x.copy()
        K.sort_run(y, 3, n + 3)     # only the run, in place
        np.testing.assert_array_equal(y, np.concatenate([x[:3], np.sort(x[3:n + 3]), x[n + 3:]]))
        keys = np.round(rng.normal(size=400), 1)
        keys[::7] = -np.inf
        idx = np.sort(rng.choice(400, n, replace=False)).astype(np.int64)
        got = idx.copy()
        K.sort_desc(keys, got, n)
        np.testing.assert_array_equal(got, idx[np.argsort(-keys[idx], kind="mergesort")])


def test_first_above_matches_searchsorted(rng):
    # the kernels' binary search stands in for np.searchsorted (left: not strict, right: strict)
    a = np.sort(rng.integers(0, 30, 57)).astype(np.int64)
    for v in range(-2, 33):
        for n in (0, 1, 20, 57):
            assert K.first_above(a, n, v, False) == np.searchsorted(a[:n], v, side="left")
            assert K.first_above(a, n, v, True) == np.searchsorted(a[:n], v, side="right")


def test_ml_ties_settle_for_the_latest_shift():
    # lone detections far apart: the pulse on any of them is an exact tie (logliks equal to ~1e-16
    # from different solver starts); the latest one is reported (ML_TIE), whichever bound the
    # search met first
    lists = [[40, 160], [160, 40, 100], [50, 90, 130, 170]]
    st = PhotonStore.from_lists([np.asarray(b) * 5.0 + 2.0 for b in lists], (1, len(lists)), 8e-12)
    r = estimator_maps(st, ReconSettings(method="ml", binning=BIN, pulse_rms_s=RMS_S))
    got = r.tof_s[0] / 8e-12 / 5.0 - 0.5
    np.testing.assert_allclose(got, [max(b) for b in lists], atol=1.0 / 8)


def test_ml_ties_between_two_alike_returns_settle_for_the_latest(kern):
    # two pairs of detections the same distance apart, and one more, all far from the window's
    # edges (where a column's sum differs): the pulse on either pair is an exact tie, and the later
    # pair is reported. The search solves one pair first and starts the other's solve at that
    # share, its own optimum too (see the next test)
    lists = [[40, 43, 120, 123, 180], [30, 33, 150, 153, 90], [100, 104, 150, 154, 60]]
    st = PhotonStore.from_lists([np.asarray(b) * 5.0 + 2.0 for b in lists], (1, len(lists)), 8e-12)
    r = estimator_maps(st, ReconSettings(method="ml", binning=BIN, pulse_rms_s=RMS_S))
    got = r.tof_s[0] / 8e-12 / 5.0 - 0.5
    np.testing.assert_allclose(got, [121.5, 151.5, 152.0], atol=1.0 / 8)


def test_ml_solve_from_its_own_optimum_gives_the_same_loglik(kern):
    # mix_ml started at the maximum (a tie's twin starts there) against a cold start at 1/2: a
    # Newton step below the share's resolution was bisected instead, and the solve then stopped
    # on the model's value after a bisected step, 5e-10 nats low; on the bench's pixels at SBR 3
    # and 5 detections that broke 3 ties in 20,000 the wrong way
    kb = np.array([40, 43, 120, 123, 180], np.int64)
    kw = np.ones(kb.size)
    uni = 1.0 / M
    for i in (41, 42, 121, 122):
        s_cold, ll_cold = MB._ml_at_int(kb, kw, kb.size, 5.0, i, kern.g, kern.off, kern.colsum, uni, 0.5, -np.inf)
        s_warm, ll_warm = MB._ml_at_int(kb, kw, kb.size, 5.0, i, kern.g, kern.off, kern.colsum, uni, s_cold,
                                       -np.inf)
        assert abs(ll_warm - ll_cold) <= 1e-13 * abs(ll_cold)
        assert s_warm == pytest.approx(s_cold, rel=1e-9)


def test_ml_share_tables_bound_every_interior_shift_from_above(kern, rng):
    # share_bound at any tabulated share is an upper bound of the exact profile loglik (the search
    # drops a shift on it), and at the share nearest the optimum it is tight: U overshoots by
    # nats (measured here: median 5e-6 nats, the worst 0.08, at a share near 0)
    uni = 1.0 / M
    stabs = MB.share_tables(kern.g, kern.colsum[kern.off], uni, MB.ML_SHARES)
    nk = kern.g.size
    ia, ib = kern.off, M - nk + kern.off
    tight = []
    for b in random_pixels(rng, 40, k=15, sbr=1.0):
        kb, kw = np.unique(b, return_counts=True)
        kw = kw.astype(float)
        for i in rng.integers(ia, ib + 1, 6):
            s, ll = MB._ml_at_int(kb, kw, kb.size, kw.sum(), i, kern.g, kern.off, kern.colsum, uni, 0.5, -np.inf)
            for j in (0, MB.ML_SHARES // 2, MB.ML_SHARES - 1, min(int(s * MB.ML_SHARES), MB.ML_SHARES - 1)):
                sj = (j + 0.5) / MB.ML_SHARES
                bnd = MB.share_bound(kb, kw, 0, kb.size, 0.0, i, kern.off, stabs, j, sj)
                assert bnd >= ll - 1e-12 * abs(ll)
            tight.append(bnd - ll)
    assert np.median(tight) < 1e-3 and np.max(tight) < 0.5


def test_ml_share_sweep_gives_share_bound_at_every_interior_shift(kern, rng):
    # the sums built for all shifts at once (many survivors) against the per-shift reads
    uni = 1.0 / M
    stabs = MB.share_tables(kern.g, kern.colsum[kern.off], uni, MB.ML_SHARES)
    nk = kern.g.size
    sdiff = MB.share_diffs(stabs)
    ia, ib = kern.off, M - nk + kern.off
    for b in random_pixels(rng, 20, k=12, sbr=0.1):
        kb, kw = np.unique(b, return_counts=True)
        kw = kw.astype(float)
        j = int(rng.integers(MB.ML_SHARES))
        sj = (j + 0.5) / MB.ML_SHARES
        ssum = np.zeros((4, M))
        lo, hi = MB.share_sweep(kb, kw, kb.size, kern.off, ia, ib, sdiff, j, ssum)
        assert np.all(ssum[:, :max(lo, 0)] == 0.0) and np.all(ssum[:, hi + 1:] == 0.0)
        n = kw.sum()
        for i in range(ia, ib + 1):
            swept = MB.swept_bound(ssum, i, n, stabs, j, sj)
            read = MB.share_bound(kb, kw, 0, kb.size, 0.0, i, kern.off, stabs, j, sj)
            assert swept == pytest.approx(read, rel=1e-12, abs=1e-12)


def estimator_maps(store, settings):
    """The estimator's own maps, before recon.detect's test for a return (these tests check the
    kernel's optimum on pixels of a few detections, which that test may call background)."""
    from spdepth.recon import estimators
    from spdepth.recon.resolve import resolve_model

    return estimators.for_settings(settings).run(store, settings, *resolve_model(store, settings))


def test_a_sampled_response_carries_the_fisher_information_of_its_pulse():
    # a Gaussian response sampled every 88 ps (a measured one: the K-surface fit pools its
    # surfaces' detections in steps of a quarter core RMS) on 40 ps bins: its CDF is piecewise
    # linear, and a derivative over less than a sample read its steps (twice the information of the
    # pulse, sigmas 1.4 times too small: K=2 halves within 1 sigma on 51%)
    b = Binning(8e-12, 0, 12500, 5)
    t = np.arange(-3000, 3001, 88) * 1e-12
    irf = Irf(tuple(t), tuple(np.exp(-0.5 * (t / 360e-12) ** 2)))

    def info(k):
        ok = k.g > 0
        return float(np.sum(k.dg[ok] ** 2 / k.g[ok]))

    assert info(build_kernel(b, irf=irf)) == pytest.approx(info(build_kernel(b, pulse_rms_s=360e-12)), rel=0.05)


@pytest.mark.parametrize("parts", [2, 3, 7])
@pytest.mark.parametrize("window, max_photons", [((0.0, 400.0), -1), ((50.0, 300.0), -1), ((50.0, 300.0), 3)])
def test_binning_in_parts_on_threads_gives_the_bins_of_one_call(rng, parts, window, max_photons):
    # recon.pixelwise bins a large frame's detections in runs side by side, each in place, then
    # moves the runs together: the same bins and offsets as one call, with empty pixels, detections
    # outside the window and the first max_photons a pixel left out
    from spdepth.recon.kernels import window_bins
    from spdepth.recon.pixelwise import bin_in_parts, shared_pool

    counts = rng.integers(0, 12, 500)
    counts[rng.random(500) < 0.2] = 0
    offsets = np.concatenate(([0], np.cumsum(counts))).astype(np.int64)
    times = rng.uniform(0, 400, int(offsets[-1]))
    w = (window[0], window[1], 2.5, 100, max_photons)
    one_bins, one_off = np.empty(times.size, np.int64), np.empty(offsets.size, np.int64)
    n_one = window_bins(times, offsets, *w, one_bins, one_off)
    bins, off = np.full(times.size, -7, np.int64), np.full(offsets.size, -7, np.int64)
    n = bin_in_parts(times, offsets, w, bins, off, parts, shared_pool(2))
    assert n == n_one
    np.testing.assert_array_equal(off, one_off)
    np.testing.assert_array_equal(bins[:n], one_bins[:n_one])
