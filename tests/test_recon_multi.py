"""Several surfaces per pixel (recon.estimators.surfaces): kernel vs its NumPy reference, simulated two-surface and
single-surface scenes, --reflectors auto, and the issue-15 scoring on the real two-surface file."""

from __future__ import annotations

import numpy as np
import pytest

from spdepth.recon.estimate import reconstruct
from spdepth.recon.errors import InputError
from spdepth.recon.maps import PixelFlag
from spdepth.recon.model import Binning, ReconSettings, build_kernel
from spdepth.recon.estimators.surfaces_fit import CAND_CORE, _step0, auto_threshold_nats, fit_surfaces, fwhm_bins
from spdepth.recon.photons import PhotonStore

import multidepth as MD
import reference as ref
from sim_frames import count_gated_store

UNIT_S = 8e-12
RMS_U = 40.0


def scene(rng, n_pix, counts, sbr, span=4000.0, min_sep=300.0):
    """Per-pixel lists with surfaces of the given mean detection counts (Poisson), a Gaussian pulse
    of RMS_U units and uniform background of (sum counts)/sbr; truth (n_pix, K) sorted."""
    kk = len(counts)
    truth = np.empty((n_pix, kk))
    lists = []
    for p in range(n_pix):
        while True:
            c = np.sort(rng.uniform(300, span - 300, kk))
            if kk == 1 or np.min(np.diff(c)) >= min_sep:
                break
        truth[p] = c
        parts = [c[r] + RMS_U * rng.standard_normal(rng.poisson(counts[r])) for r in range(kk)]
        parts.append(rng.uniform(0, span, rng.poisson(sum(counts) / sbr)))
        lists.append(np.floor(np.concatenate(parts)))
    return lists, truth


def test_kernel_matches_numpy_reference():
    rng = np.random.default_rng(150)
    b = Binning(UNIT_S, 0.0, 1200.0, 6.0)
    lists, _ = scene(rng, 40, [12, 6], 3.0, span=1200.0, min_sep=150.0)
    store = PhotonStore.from_lists(lists, (4, 10), UNIT_S)
    kern = build_kernel(b, pulse_rms_s=RMS_U * UNIT_S)
    for refl in (2, "auto"):
        settings = ReconSettings(binning=b, pulse_rms_s=RMS_U * UNIT_S, reflectors=refl)
        core_s = RMS_U * UNIT_S
        shift, amp, bg, var, gain, n_used, kmax, gain_min, _ = fit_surfaces(store, settings, b, kern, core_s)
        s_mat = ref.dense_s(kern)
        core_bins = RMS_U / 6.0
        sep = max(1, round(fwhm_bins(kern.g)))
        cand = max(1, round(CAND_CORE * core_bins))
        step0 = _step0(core_bins)
        for p, t in enumerate(lists):
            t = t[(t >= 0) & (t < 1200)]
            y = np.bincount(np.floor(t / 6.0).astype(int), minlength=b.n_bins).astype(float)
            rs, ra, rg, rb = ref.multi_return(y, kern, s_mat, kmax, sep, gain_min, cand, step0)
            n = rs.size
            assert np.sum(np.isfinite(shift[p])) == n
            np.testing.assert_allclose(shift[p, :n], rs)
            np.testing.assert_allclose(amp[p, :n], ra, rtol=1e-7)
            np.testing.assert_allclose(gain[p, :n], rg, rtol=1e-7, atol=1e-9)
            np.testing.assert_allclose(bg[p], rb, rtol=1e-7)


def _both(tof_u, truth, tol):
    found = np.ones(truth.shape[0], bool)
    for r in range(truth.shape[1]):
        found &= np.nanmin(np.abs(tof_u - truth[:, r][None]), axis=0) < tol
    return found


def test_two_surfaces_simulated_found_and_uncertainty_honest():
    rng = np.random.default_rng(151)
    lists, truth = scene(rng, 1500, [25, 25], 5.0)
    store = PhotonStore.from_lists(lists, (30, 50), UNIT_S)
    maps = reconstruct(store, ReconSettings(binning=Binning(UNIT_S, 0, 4000, 5), pulse_rms_s=RMS_U * UNIT_S,
                                            reflectors=2))
    tof = maps.tof_s.reshape(2, -1) / UNIT_S
    both = _both(tof, truth, 3 * RMS_U)
    assert both.mean() >= 0.95, both.mean()
    unc = maps.uncertainty_s.reshape(2, -1) / UNIT_S
    err = np.abs(tof - truth.T)
    ok = both[None] & np.isfinite(err)
    share = np.mean(err[ok] < unc[ok])
    print(f"both found {both.mean():.1%}; |error| < 1 sigma on {share:.1%}")
    assert 0.63 <= share <= 0.73
    assert maps.surfaces.shape == (30, 50) and np.all(maps.surfaces == np.isfinite(maps.tof_s).sum(axis=0))


def test_auto_one_surface_none_and_two():
    rng = np.random.default_rng(152)
    b = Binning(UNIT_S, 0, 4000, 5)
    one, _ = scene(rng, 800, [15], 1.0)
    two, _ = scene(rng, 400, [20, 20], 5.0)
    none = [np.floor(rng.uniform(0, 4000, rng.poisson(5))) for _ in range(400)]
    store = PhotonStore.from_lists(one + two + none, (40, 40), UNIT_S)
    maps = reconstruct(store, ReconSettings(binning=b, pulse_rms_s=RMS_U * UNIT_S, reflectors="auto"))
    n = maps.surfaces.ravel()
    flags = maps.flags.ravel()
    print(f"auto: one-surface pixels with 1: {np.mean(n[:800] == 1):.1%}, two-surface with 2: "
          f"{np.mean(n[800:1200] == 2):.1%}, empty with 0: {np.mean(n[1200:] == 0):.1%}")
    assert np.mean(n[:800] == 1) >= 0.98
    assert np.mean(n[800:1200] == 2) >= 0.95
    assert np.mean(n[1200:] == 0) >= 0.98
    assert np.all(np.isin(flags[1200:][n[1200:] == 0], [PixelFlag.NO_SIGNAL, PixelFlag.NO_PHOTONS]))
    assert maps.tof_s.shape == (3, 40, 40)


def test_auto_threshold_and_settings():
    # stricter false-alarm rates and wider windows need more evidence
    assert auto_threshold_nats(1e-6, 1000, 10) > auto_threshold_nats(1e-3, 1000, 10)
    assert auto_threshold_nats(1e-3, 10000, 10) > auto_threshold_nats(1e-3, 100, 10)
    assert ReconSettings(reflectors="auto").to_dict()["reflectors"] == "auto"
    for bad in ({"reflectors": "many"}, {"reflectors": 0}, {"false_alarm": 1.5}, {"max_reflectors": 9}):
        with pytest.raises(InputError):
            ReconSettings(**bad)


@pytest.mark.skipif(not MD.DATA.is_file(), reason=f"{MD.DATA} absent")
def test_real_two_surface_file_scored_beside_the_naive_baseline():
    from spdepth.acq.api import reconstruct_file
    from spdepth.acq.requests import FileReconRequest

    cell, t1, t2 = MD.load()
    r1, r2, _ = MD.references(cell, t1, t2)
    naive = MD.score(MD.naive_baseline(cell), r1, r2)
    # pixels where both surfaces hold at least 6 detections (within the tolerance of the re-centred
    # maps): there the test of auto can see both; on the rest the first surface has 0-5
    near = [np.array([[np.sum(np.abs(np.ravel(cell[i, j]) - r[i, j]) < MD.TOL_UNITS) for j in range(r.shape[1])]
                      for i in range(r.shape[0])]) for r in (r1, r2)]
    seen = (near[0] >= 6) & (near[1] >= 6)
    scores, seen_scores, units = {}, {}, {}
    for method, refl in (("uos", 2), ("spatial", 2), ("uos", "auto"), ("spatial", "auto")):
        res = reconstruct_file(FileReconRequest(input=str(MD.DATA), method=method, time_unit_s=UNIT_S,
                                                window_s=(24e-9, 56e-9), reflectors=refl))
        units[method, refl] = res.maps.tof_s / UNIT_S
        scores[method, refl] = MD.score(units[method, refl], r1, r2)
        seen_scores[method, refl] = MD.score(units[method, refl], r1, r2, seen)
    print(f"\nnaive baseline: {naive}")
    for key, sc in scores.items():
        print(f"{key[0]} --reflectors {key[1]}: {sc}")
        print(f"   on the {seen.sum()} pixels with >= 6 detections on both: both {seen_scores[key]['both']:.1%}")
    ours, spatial = scores["uos", 2], scores["spatial", 2]
    auto, sp_auto = scores["uos", "auto"], scores["spatial", "auto"]
    assert naive["both"] > 0.85
    # the achieved levels (the calibrated second map lies between two returns behind the object, on
    # ~6% of the pixels, which bounds "second" near 94% for any estimate on a return: see the end).
    # They move by a few tenths of a percent when the kernels' arithmetic changes in the last bits:
    # the response pooled on the first fit moves, and every shift with it, within its uncertainty
    # (spatial K=2 "both" was 0.9144-0.9168 over five such versions of the kernel, pixelwise K=2
    # 0.8998-0.9010 over three), so each floor sits that much below what was measured; beating the
    # naive baseline is asserted as it stands
    assert ours["both"] >= 0.895 and ours["both"] > naive["both"]
    assert ours["first"] >= naive["first"] and ours["second"] >= naive["second"] - 0.005
    assert spatial["both"] >= 0.91 and spatial["first"] >= 0.98
    assert sp_auto["both"] >= 0.93 and sp_auto["first"] >= 0.995
    # auto at a 1e-3 false-alarm rate cannot take a first surface of 2-5 detections on its own
    # (its statistic is 4-9 nats, the test asks 9.3), the neighbours can; where the pixel holds 6
    # or more on both, auto is within a point of fixed K=2 (77.7% and not worse at 8.2 nats, a
    # threshold that let background pass 1.7-2.8 times as often as stated)
    assert auto["both"] >= 0.74 and auto["second"] >= ours["second"] - 0.005
    assert seen_scores["uos", "auto"]["both"] >= seen_scores["uos", 2]["both"] - 0.01
    # what bounds "second": behind the object (the columns ~35-57) the pixels hold three returns (the
    # front layer, the object, the wall behind it) and the calibrated second map, a mean of detection
    # times (its values are ratios of whole numbers), lies between the object and the wall. Where
    # spatial auto misses that map, it found two returns past the first, one on either side of it
    est = units["spatial", "auto"] - sp_auto["offset_units"]
    missed = ~(np.nanmin(np.abs(est - r2[None]), axis=0) < MD.TOL_UNITS)
    before = np.max(np.where(est < r2[None], est, -np.inf), axis=0)
    after = np.min(np.where(est > r2[None], est, np.inf), axis=0)
    flanked = missed & (before > r1 + MD.TOL_UNITS) & np.isfinite(after)
    print(f"spatial auto misses the second map on {missed.sum()} pixels; on {flanked.sum()} of them it lies "
          f"between two returns past the first, {np.median((after - before)[flanked]):.0f} units apart")
    assert missed.sum() > 0 and flanked.sum() >= 0.95 * missed.sum()


def test_auto_no_phantom_from_a_measured_tail():
    # single surfaces with the chart's measured response (Gaussian core 127 ps, 33% delayed by a
    # 250 ps exponential tail) and an afterpulse-like bump 3.6 ns later holding 4% of the return;
    # the pulse left to the program: auto reports exactly one surface on >= 98% of the pixels
    rng = np.random.default_rng(153)
    s, share, tau = 127 / 8, 0.33, 250 / 8
    lists = []
    for _ in range(2500):
        c = rng.uniform(800, 2500)
        ns = rng.binomial(50, 10 / 11)
        nb = rng.binomial(ns, 0.04)
        x = c + s * rng.standard_normal(ns) + np.where(rng.random(ns) < share, rng.exponential(tau, ns), 0.0)
        x[:nb] += 450 + 60 * rng.standard_normal(nb)
        x = np.concatenate([x, rng.uniform(0, 4000, 50 - ns)])
        lists.append(np.floor(x[(x >= 0) & (x < 4000)]))
    store = PhotonStore.from_lists(lists, (50, 50), UNIT_S)
    maps = reconstruct(store, ReconSettings(method="uos", reflectors="auto"))
    one = np.mean(maps.surfaces == 1)
    print(f"auto, one surface with a measured tail and bump: exactly one on {one:.1%}")
    assert one >= 0.98


def weak_far_scene(rng, h=40, w=40, near=20.0, far=2.0, bg=3.0):
    """A near surface with an edge (left half at 1000 units, right half a slope from 1400) over a far
    wall at 2800 units giving Poisson(far) detections per pixel (1-3 mostly), uniform background."""
    lists, truth = [], np.empty((h * w, 2))
    for y in range(h):
        for x in range(w):
            c1 = 1000.0 if x < w // 2 else 1400.0 + 5 * y
            t = np.concatenate([c1 + RMS_U * rng.standard_normal(rng.poisson(near)),
                                2800.0 + RMS_U * rng.standard_normal(rng.poisson(far)),
                                rng.uniform(0, 4000, rng.poisson(bg))])
            lists.append(np.floor(t))
            truth[y * w + x] = (c1, 2800.0)
    return PhotonStore.from_lists(lists, (h, w), UNIT_S), truth


def test_spatial_kernels_match_numpy_reference():
    from spdepth.recon.estimators import surfaces_kernels as MK
    from spdepth.recon.kernels import Photons

    rng = np.random.default_rng(155)
    store, _ = weak_far_scene(rng, 5, 6)
    b = Binning(UNIT_S, 0.0, 4000.0, 10.0)
    kern = build_kernel(b, pulse_rms_s=RMS_U * UNIT_S)
    settings = ReconSettings(binning=b, pulse_rms_s=RMS_U * UNIT_S, reflectors=2)
    shift0, _, _, _, gain0, _, kmax, _, _ = fit_surfaces(store, settings, b, kern, RMS_U * UNIT_S)
    ys = np.stack([np.bincount(np.floor(t[(t >= 0) & (t < 4000)] / 10).astype(int), minlength=b.n_bins)
                   for t in store.to_lists()]).astype(float) if hasattr(store, "to_lists") else None
    if ys is None:
        ys = np.zeros((store.n_pixels, b.n_bins))
        for p in range(store.n_pixels):
            t = store.times[store.offsets[p]:store.offsets[p + 1]]
            t = t[(t >= 0) & (t < 4000)]
            ys[p] = np.bincount(np.floor(t / 10).astype(int), minlength=b.n_bins)
    fw = fwhm_bins(kern.g)
    core = RMS_U / 10
    args = dict(radius=1, strong_nats=14.0, pool_nats=8.0, tau=float(fw), sep=fw, kmax=2, kpool=3,
                cand_step=max(1, round(CAND_CORE * core)), step0=_step0(core))
    bins = np.concatenate([np.floor(ys[p].nonzero()[0]).repeat(ys[p][ys[p] > 0].astype(int))
                           for p in range(store.n_pixels)]).astype(np.int64)
    offsets = np.concatenate(([0], np.cumsum(ys.sum(axis=1)))).astype(np.int64)
    npix = store.n_pixels
    res = MK.SurfOut(np.full((npix, 2), np.nan), np.zeros((npix, 2)), np.zeros(npix), np.full((npix, 2), np.nan),
                     np.zeros((npix, 2)), np.zeros(npix, np.int64))
    src = np.full((npix, 2), -1, np.int64)
    tabs = MK.surf_tables(b.n_bins, kern.g, kern.off, kern.colsum, kern.dg, fw, args["cand_step"], args["step0"])
    nb = MK.Neighbourhood(5, 6, 1, 14.0, 8.0, float(fw), 3)
    # in two slices of pixels, as recon.estimators.surfaces_fit calls it (between progress reports)
    for p0, p1 in ((0, 13), (13, npix)):
        MK.neighbour_surfaces(Photons(bins, offsets), shift0, gain0, nb, tabs, int(np.diff(offsets).max()), res,
                              src, p0, p1)
    out = [res.shift, res.amp, res.bg, res.var, res.gain, src]
    expect = ref.neighbour_surfaces(ys, 5, 6, kern, ref.dense_s(kern), shift_in=shift0, gain_in=gain0, **args)
    for p, (rs, ra, rc) in enumerate(expect):
        n = rs.size
        assert np.sum(np.isfinite(out[0][p])) == n
        # two detections one bin apart put a symmetric pulse's best shift exactly between two bins:
        # the summation order (sparse vs dense) breaks that tie, with the same amplitudes
        np.testing.assert_allclose(out[0][p, :n], rs, atol=1)
        assert np.mean(out[0][p, :n] == rs) >= 0.5
        np.testing.assert_allclose(out[1][p, :n], ra, rtol=1e-6)
        np.testing.assert_array_equal(out[5][p, :n], rc)
    sig = np.where(np.isfinite(out[0]), out[1] * 10.0, 0.0)
    sm, sv = np.empty_like(out[0]), np.empty_like(out[3])
    MK.smooth_surfaces(out[0], sig, out[3], 5, 6, 1, float(fw), sm, sv)
    np.testing.assert_allclose(sm, ref.smooth_surfaces(out[0], sig, 5, 6, 1, float(fw)))


def test_spatial_finds_the_weak_far_surface_where_pixelwise_cannot():
    rng = np.random.default_rng(156)
    store, truth = weak_far_scene(rng)
    b = Binning(UNIT_S, 0, 4000, 5)
    found = {}
    for method in ("uos", "spatial"):
        maps = reconstruct(store, ReconSettings(method=method, binning=b, pulse_rms_s=RMS_U * UNIT_S,
                                                reflectors=2))
        tof = maps.tof_s.reshape(2, -1) / UNIT_S
        found[method] = _both(tof, truth, 3 * RMS_U).mean()
    # the far wall gives at least one detection on 1 - exp(-2) = 86% of the pixels
    print(f"weak far surface, both found: pixelwise {found['uos']:.1%}, spatial {found['spatial']:.1%}")
    assert found["spatial"] >= found["uos"] + 0.2
    assert found["spatial"] >= 0.8


CHART = MD.DATA.parents[1] / "fpi" / "chart_depth.mat"


@pytest.mark.skipif(not CHART.is_file(), reason=f"{CHART} absent")
def test_auto_one_surface_on_the_simulated_bust_with_the_charts_measured_response():
    # the check: the bust simulated with the response measured from the chart (pulse left
    # to the program there and here), 15 detections per pixel: auto reports exactly one surface
    from spdepth.acq.api import reconstruct_file
    from spdepth.acq.requests import FileReconRequest
    from spdepth.drivers.sim import load_scene

    irf = reconstruct_file(FileReconRequest(input=str(CHART), time_unit_s=UNIT_S)).maps.settings["irf"]
    t = np.asarray(irf["times_s"])
    scene = load_scene("bust", (64, 64), ppp=15, irf=np.asarray(irf["counts"]), irf_bin_s=float(t[1] - t[0]))
    store = count_gated_store(scene, 15, seed=3)
    one = {}
    for method in ("uos", "spatial"):
        k = reconstruct(store, ReconSettings(method=method, reflectors="auto")).surfaces
        one[method] = float(np.mean(k == 1))
    print(f"simulated bust, chart's response: exactly one surface: pixelwise {one['uos']:.2%}, "
          f"spatial {one['spatial']:.2%}")
    assert one["uos"] >= 0.995 and one["spatial"] >= 0.98


def test_weak_flags_chance_clusters_not_clean_surfaces_of_a_few_detections():
    # K fixed: two clean surfaces of 7 detections each (1 background detection) are findings; the
    # second surface K=2 puts on a one-surface pixel (a chance pair of background) is weak
    rng = np.random.default_rng(157)
    b = Binning(UNIT_S, 0, 4005, 5)
    two = [np.floor(np.concatenate([1000 + 45 * rng.standard_normal(7), 2000 + 45 * rng.standard_normal(7),
                                    rng.uniform(0, 4005, 1)])) for _ in range(200)]
    one = [np.floor(np.concatenate([1500 + 45 * rng.standard_normal(14), rng.uniform(0, 4005, 4)]))
           for _ in range(200)]
    settings = ReconSettings(binning=b, pulse_rms_s=45 * UNIT_S, reflectors=2)
    m2 = reconstruct(PhotonStore.from_lists(two, (10, 20), UNIT_S), settings)
    m1 = reconstruct(PhotonStore.from_lists(one, (10, 20), UNIT_S), settings)
    assert np.mean(m2.surfaces == 2) > 0.95 and m2.weak.mean() < 0.05
    near = np.abs(m1.tof_s / UNIT_S - 1500) < 3 * 45
    extra = np.isfinite(m1.tof_s) & ~near
    assert extra.sum() > 20 and m1.weak[extra].mean() > 0.9
    assert np.all((near & ~m1.weak).any(axis=0))          # the real surface is never weak


FACE = MD.DATA.parents[1] / "fpi" / "mannequin_face_8ppp.mat"


@pytest.mark.skipif(not FACE.is_file(), reason=f"{FACE} absent")
def test_auto_one_surface_on_the_mannequin():
    # the real one-surface check (pulse left to the program). Pixelwise auto reports one
    # surface wherever it reports any. Spatial auto finds two on the silhouette and the chin over
    # the neck, where a pixel's footprint holds both the face and what is behind it (mixed pixels,
    # real second returns): measured 97.5% one overall, 99.2% where the depth varies by < 30 cm
    from scipy.ndimage import maximum_filter, minimum_filter

    from spdepth.acq.api import reconstruct_file
    from spdepth.acq.requests import FileReconRequest

    share = {}
    for method in ("uos", "spatial"):
        m = reconstruct_file(FileReconRequest(input=str(FACE), method=method, time_unit_s=UNIT_S,
                                              window_s=(16e-9, 48e-9), reflectors="auto")).maps
        found = m.surfaces >= 1
        d = np.nan_to_num(m.depth_m[0])
        flat = (maximum_filter(d, size=5) - minimum_filter(d, size=5) < 0.3) & found
        share[method] = (np.mean(m.surfaces[found] == 1), np.mean(m.surfaces[flat] == 1), found.mean())
    print(f"mannequin, auto: exactly one surface where any (all / away from depth edges / share found): "
          f"pixelwise {share['uos']}, spatial {share['spatial']}")
    assert share["uos"][0] >= 0.995 and share["uos"][2] > 0.7
    assert share["spatial"][0] >= 0.97 and share["spatial"][1] >= 0.985 and share["spatial"][2] > 0.85


def _random_pixel(rng, kern, m):
    """A pixel's distinct bins, counts and a model rate's inverse at them, as the kernel holds them:
    a surface and background, some bins with several detections."""
    t = np.concatenate([rng.normal(rng.uniform(100, m - 100), 8.0, rng.integers(3, 40)),
                        rng.uniform(0, m, rng.integers(1, 30))])
    kb, kw = np.unique(np.clip(np.floor(t), 0, m - 1).astype(np.int64), return_counts=True)
    lam = rng.uniform(0.01, 0.3) + rng.uniform(0, 2.0) * kern.g[np.clip(kb - kb[len(kb) // 2] + kern.off, 0,
                                                                          kern.g.size - 1)]
    return kb, kw.astype(float), 1.0 / lam


def test_screen_bound_is_above_every_exact_gain_it_spares():
    """fit_pixel skips a screened candidate's exact gain when the screen's Jensen bound,
    N (log r - 1 + 1 / r), is below the best: the bound must never be below the exact gain (a wrong
    bound would skip a candidate that wins)."""
    from spdepth.recon.estimators import surfaces_kernels as MK

    rng = np.random.default_rng(152)
    b = Binning(UNIT_S, 0.0, 1600.0, 2.0)
    kern = build_kernel(b, pulse_rms_s=8.0 * 2.0 * UNIT_S)
    m = b.n_bins
    wk = np.empty((2, 200))
    checked = 0
    dpk = int(np.argmax(kern.g))
    for _ in range(300):
        kb, kw, ilam = _random_pixel(rng, kern, m)
        nu = kb.size
        # the shifts the screen looks at: the response's peak on a detection, and some off them
        for j in np.clip(rng.choice(kb, 20) + kern.off - dpk + rng.integers(-20, 21, 20), 0, m - 1):
            u0 = int(np.searchsorted(kb, j - kern.off))
            u1 = int(np.searchsorted(kb, j - kern.off + kern.g.size))
            sc, nin, ratio = MK.screen_score(j, kb, kw, u0, u1, ilam, kern.g, kern.off, kern.colsum)
            gain, _ = MK.add_gain(j, kb, kw, nu, ilam, kern.g, kern.off, kern.colsum, 0.0, 0.0, wk)
            if sc <= 0.0:
                assert gain == 0.0       # no positive slope at 0: nothing to gain
                continue
            bound = nin * (np.log(ratio) - 1.0 + 1.0 / ratio)
            assert gain > 0.0 and bound >= gain - 1e-9 * (1.0 + gain), (j, gain, bound)
            checked += 1
    assert checked > 2000


def test_rate_from_em_table_is_model_irate_bit_for_bit():
    """After EM, the rate's inverse at the detections comes from EM's table of the response there
    (irate_table) instead of looking the response up again (model_irate): the same sums in the
    same order, so the same bits, with or without a return left out (the re-refinement's rate)."""
    from spdepth.recon.estimators import surfaces_kernels as MK

    rng = np.random.default_rng(153)
    b = Binning(UNIT_S, 0.0, 1600.0, 2.0)
    kern = build_kernel(b, pulse_rms_s=8.0 * 2.0 * UNIT_S)
    m = b.n_bins
    for nr in (1, 2, 3):
        kb, kw, _ = _random_pixel(rng, kern, m)
        nu = kb.size
        shifts = np.sort(rng.choice(np.arange(50, m - 50), nr, replace=False)).astype(np.int64)
        amps = rng.uniform(1.0, 20.0, nr)
        ilam, via_table, direct = np.empty(nu), np.empty(nu), np.empty(nu)
        gt, newa = np.empty((nr, nu)), np.empty(nr)
        bg = MK.em_refit(kb, kw, nu, shifts, amps, nr, 0.05, 1e-9, kern.g, kern.off, kern.colsum, m, ilam,
                         MK.EM_SWEEPS, gt, newa)
        MK.model_irate(kb, nu, shifts, amps, nr, bg, kern.g, kern.off, direct)
        assert np.array_equal(ilam, direct)
        without = amps.copy()
        without[0] = 0.0
        MK.irate_table(gt, nu, without, nr, bg, via_table)
        MK.model_irate(kb, nu, shifts, without, nr, bg, kern.g, kern.off, direct)
        assert np.array_equal(via_table, direct)


def test_spatial_surfaces_report_progress_as_they_go():
    """--method spatial --reflectors K fits every pixel's neighbourhood in slices and says how far
    it got after each (a 512 x 512 frame takes tens of seconds on one core), ending at the total."""
    from spdepth.recon.estimators import surfaces_fit as multi

    rng = np.random.default_rng(156)
    lists, _ = scene(rng, 40 * 50, [12, 8], 4.0)
    store = PhotonStore.from_lists(lists, (40, 50), UNIT_S)
    seen = []
    slice_was = multi.SPATIAL_SLICE
    multi.SPATIAL_SLICE = 512
    try:
        reconstruct(store, ReconSettings(method="spatial", binning=Binning(UNIT_S, 0, 4000, 5),
                                         pulse_rms_s=RMS_U * UNIT_S, reflectors=2),
                    progress=lambda done, total: seen.append((done, total)))
    finally:
        multi.SPATIAL_SLICE = slice_was
    assert [d for d, _ in seen] == [512, 1024, 1536, 2000] and {t for _, t in seen} == {2000}
