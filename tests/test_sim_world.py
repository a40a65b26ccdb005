"""PhotonWorld: count-gated and fixed-dwell calls, rasters with markers, seeded reproducibility,
built-in and depth-image scenes, the virtual clock."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from spdepth.acq.assign import PixelAssigner

from spdepth.drivers.errors import SettingError
from spdepth.drivers.events import EVENT_DTYPE, EventKind, Marker
from spdepth.drivers.sim import PhotonWorld, VirtualClock, load_scene, scene_names
from spdepth.drivers.sim.scene import C_M_PER_S

SCENES = ["bust", "daylight", "steps", "tilted-plane", "two-layer"]


def _sorted_in_time(ev):
    s = ev["sync"].astype(np.int64)
    d = ev["dtime"].astype(np.int64)
    return np.all((np.diff(s) > 0) | ((np.diff(s) == 0) & (np.diff(d) >= 0)))


def test_fixed_dwell_covers_exactly_the_dwell():
    scene = load_scene("bust", (16, 16), ppp=50)
    world = PhotonWorld(scene, seed=1)
    ev, n = world.fixed_dwell(8, 8, 1e-3, 5_000)
    assert n == 10_000
    assert ev.dtype == EVENT_DTYPE
    assert np.all(ev["kind"] == EventKind.PHOTON)
    assert np.all((ev["sync"] >= 5_000) & (ev["sync"] < 15_000))
    assert np.all(ev["dtime"] < scene.settings.range_bins)
    assert _sorted_in_time(ev)
    # mean count over many dwells matches the truth of this pixel
    truth = scene.truth()
    counts = [world.fixed_dwell(8, 8, 1e-3, 20_000 * k)[0].size for k in range(1, 201)]
    expect = truth["signal"][8, 8] + truth["background"][8, 8]
    assert np.mean(counts) == pytest.approx(expect, rel=5 * np.sqrt(expect / 200) / expect)


def test_count_gated_stops_at_the_target_detection():
    scene = load_scene("bust", (16, 16), ppp=15)
    world = PhotonWorld(scene, seed=2)
    ev, n = world.count_gated(5, 7, 15, 1.0, 1_000)
    assert ev.size == 15
    assert ev["sync"][0] >= 1_000
    assert n == int(ev["sync"][-1]) - 1_000 + 1
    assert _sorted_in_time(ev)


def test_count_gated_window_counts_only_in_window():
    scene = load_scene("daylight", (16, 16), ppp=15)  # mostly background: many out of window
    world = PhotonWorld(scene, seed=3)
    lo, hi = 2000, 6000
    ev, n = world.count_gated(3, 3, 15, 1.0, 0, window=(lo, hi))
    inside = (ev["dtime"] >= lo) & (ev["dtime"] < hi)
    assert inside.sum() == 15
    assert inside[-1]                  # the last event is the one that reached the target
    assert (~inside).sum() > 15        # out-of-window detections are returned too
    assert n == int(ev["sync"][-1]) + 1


def test_count_gated_dwell_limit():
    scene = load_scene("bust", (16, 16), ppp=15)  # 15 per 1 ms: 100 us gives ~1.5
    world = PhotonWorld(scene, seed=4)
    ev, n = world.count_gated(8, 8, 1000, 100e-6, 0)
    assert n == 1000
    assert ev.size < 1000
    assert np.all(ev["sync"] < 1000)


def test_count_gated_with_dead_time_counts_registered_detections():
    scene = load_scene("bust", (8, 8), ppp=15, dwell_s=20e-6)  # 0.75 per pulse: pile-up on
    assert "dead_time" in scene.active_effects
    world = PhotonWorld(scene, seed=5)
    for k in range(5):
        ev, n = world.count_gated(4, 4, 40, 1.0, 10_000 * k, window=(2000, 6000))
        inside = (ev["dtime"] >= 2000) & (ev["dtime"] < 6000)
        assert inside.sum() == 40 and inside[-1]
        assert n == int(ev["sync"][-1]) - 10_000 * k + 1


def test_count_gated_matches_fixed_dwell_statistics():
    """Counting to N in a Poisson stream: the syncs needed follow Gamma(N, rate)."""
    scene = load_scene("tilted-plane", (1, 1), ppp=15)
    world = PhotonWorld(scene, seed=6)
    rate = float(scene.rate_per_pulse()[0, 0])
    ns = [world.count_gated(0, 0, 10, 1.0, 0)[1] for _ in range(400)]
    assert np.mean(ns) == pytest.approx(10 / rate, rel=0.05)


def test_bad_calls_raise_input_error():
    world = PhotonWorld(load_scene("bust", (4, 4)), seed=0)
    with pytest.raises(SettingError):
        world.count_gated(4, 0, 10, 1e-3, 0)
    with pytest.raises(SettingError):
        world.count_gated(0, 0, 0, 1e-3, 0)
    with pytest.raises(SettingError):
        world.count_gated(0, 0, 5, -1.0, 0)
    with pytest.raises(SettingError):
        world.count_gated(0, 0, 5, 1e-3, 0, window=(10, 5))
    with pytest.raises(SettingError):
        world.fixed_dwell(0, 0, 0.0, 0)


def test_seeded_reproducibility():
    scene = load_scene("two-layer", (16, 16), ppp=10, effects=("jitter", "afterpulsing"))
    a = PhotonWorld(scene, seed=42).raster()
    b = PhotonWorld(scene, seed=42).raster()
    c = PhotonWorld(scene, seed=43).raster()
    assert np.array_equal(a, b)
    assert not np.array_equal(a["dtime"][:50], c["dtime"][:50])
    ga = [PhotonWorld(scene, seed=7).count_gated(1, 2, 10, 1e-2, 0)[0] for _ in range(2)]
    assert np.array_equal(ga[0], ga[1])


@pytest.mark.parametrize("n_target", [None, 12])
def test_raster_markers(n_target):
    h, w = 6, 5
    scene = load_scene("steps", (h, w), ppp=20)
    ev, origin = PhotonWorld(scene, seed=9).raster(n_target=n_target, with_origin=True)
    mk = ev[ev["kind"] == EventKind.MARKER]
    # the galvo's order (docs/protocols.md): [FRAME|]LINE_START|PIXEL, PIXEL..., LINE_STOP
    first_pixel = Marker.LINE_START | Marker.PIXEL
    assert mk[0]["marker"] == Marker.FRAME | first_pixel
    assert (mk["marker"] & Marker.FRAME != 0).sum() == 1
    assert (mk["marker"] & Marker.LINE_START != 0).sum() == h
    assert (mk["marker"] == Marker.LINE_STOP).sum() == h
    assert (mk["marker"] & Marker.PIXEL != 0).sum() == h * w
    assert np.all(np.diff(ev["sync"].astype(np.int64)) >= 0)
    assert origin.size == ev.size
    pix = PixelAssigner((h, w)).assign(ev)
    photons = ev["kind"] == EventKind.PHOTON
    assert np.all(pix[photons] >= 0)
    counts = np.bincount(pix[photons], minlength=h * w)
    if n_target is None:
        n = scene.settings.syncs_per_dwell
        # fixed dwell: the sync alone also says the pixel
        assert np.array_equal(pix[photons], ev["sync"][photons] // n)
        assert counts.sum() == pytest.approx(20 * h * w, rel=0.15)
    else:
        assert np.all(counts == n_target)


@pytest.mark.parametrize("name", SCENES)
def test_builtin_scene_16x16(name):
    assert name in scene_names()
    scene = load_scene(name, (16, 16), ppp=15)
    t = scene.truth()
    k = scene.n_surfaces
    dshape = (16, 16) if k == 1 else (k, 16, 16)
    assert t["depth_m"].shape == dshape and t["tof_s"].shape == dshape
    assert t["occupancy"].shape == (k, 16, 16)
    assert np.allclose(t["tof_s"], 2 * t["depth_m"] / C_M_PER_S)
    assert np.all((t["depth_m"] > 1.0) & (t["depth_m"] < 5.0))
    assert t["signal"].mean() + t["background"].mean() == pytest.approx(15)
    assert t["signal"].mean() / t["background"].mean() == pytest.approx(scene.settings.sbr)
    ev, origin = PhotonWorld(scene, seed=0).raster(with_origin=True)
    ph = ev["kind"] == EventKind.PHOTON
    assert ph.sum() == pytest.approx(15 * 256, rel=0.08)
    # signal photons sit near their surface's time of flight
    n = scene.settings.syncs_per_dwell
    p = (ev["sync"][ph] // n).astype(np.int64)
    sig = origin[ph] >= 1
    surf = origin[ph][sig].astype(np.int64) - 1
    tof = scene.tof_s.reshape(k, -1)[surf, p[sig]]
    dt = ev["dtime"][ph][sig] * scene.resolution_s - tof
    assert np.abs(dt).max() < 8 * scene.pulse_rms_s


def test_scene_specifics():
    two = load_scene("two-layer", (16, 16), ppp=30)
    assert two.n_surfaces == 2
    ev, origin = PhotonWorld(two, seed=1).raster(with_origin=True)
    assert (origin == 1).sum() > 0 and (origin == 2).sum() > 0
    day = load_scene("daylight", (16, 16))
    t = day.truth()
    assert day.settings.sbr < 0.1
    assert t["background"].max() > 5 * t["background"].min()
    steps = load_scene("steps", (32, 32)).truth()["depth_m"]
    rises = np.unique(np.round(steps.max(axis=1) - steps.min(axis=1), 4))
    assert set([0.001, 0.01, 0.1]).issubset(set(rises.tolist()))


def test_bad_scene_options():
    with pytest.raises(SettingError, match="unknown scene"):
        load_scene("nope")
    with pytest.raises(SettingError):
        load_scene("bust", (0, 16))
    with pytest.raises(SettingError):
        load_scene("bust", ppp=0)
    with pytest.raises(SettingError):
        load_scene("bust", ppp=-3)
    with pytest.raises(SettingError):
        load_scene("bust", dark_rate_hz=-1.0)
    with pytest.raises(SettingError, match="effect"):
        load_scene("bust", effects=("glare",))
    with pytest.raises(SettingError, match="dark-count"):
        load_scene("bust", ppp=1, dark_rate_hz=1e6)


def _write_depth(tmp_path, kind, depth_m):
    if kind == "npy":
        path = tmp_path / "d.npy"
        np.save(path, depth_m)
        return f"file:{path}", depth_m
    if kind == "png":
        from PIL import Image
        mm = np.round(depth_m * 1000).astype(np.uint16)
        path = tmp_path / "d.png"
        Image.fromarray(mm).save(path)
        return f"file:{path}", mm / 1000.0
    import tifffile
    path = tmp_path / "d.tiff"
    tifffile.imwrite(path, depth_m.astype(np.float32))
    return f"file:{path}", depth_m.astype(np.float32).astype(np.float64)


@pytest.mark.parametrize("kind", ["npy", "png", "tiff"])
def test_depth_image_scene(tmp_path, kind):
    y, x = np.mgrid[0:20, 0:24]
    depth = 2.0 + 0.05 * x + 0.02 * y
    spec, expect = _write_depth(tmp_path, kind, depth)
    scene = load_scene(spec, ppp=10)
    assert scene.shape == (20, 24)
    assert np.allclose(scene.truth()["depth_m"], expect)
    ev = PhotonWorld(scene, seed=0).raster()
    assert (ev["kind"] == 0).sum() == pytest.approx(10 * 480, rel=0.1)


def test_depth_image_with_reflectivity_resampled_and_holes(tmp_path):
    from PIL import Image
    depth = np.full((10, 10), 3.0)
    depth[0, 0] = np.nan                       # a hole: no surface there
    np.save(tmp_path / "d.npy", depth)
    refl = np.zeros((10, 10), np.uint8)
    refl[:, 5:] = 255
    Image.fromarray(refl).save(tmp_path / "r.png")
    scene = load_scene(f"file:{tmp_path / 'd.npy'},reflectivity={tmp_path / 'r.png'}", (20, 20))
    t = scene.truth()
    assert scene.shape == (20, 20)
    assert t["occupancy"][0, :2, :2].sum() == 0 and t["signal"][:2, :2].sum() == 0
    assert t["signal"][:, :10].sum() == 0 and t["signal"][:, 10:].min() > 0
    with pytest.raises(SettingError, match="unknown option"):
        load_scene(f"file:{tmp_path / 'd.npy'},gamma=2")
    with pytest.raises(SettingError, match="not found"):
        load_scene(f"file:{tmp_path / 'missing.npy'}")
    (tmp_path / "bad.png").write_bytes(b"not a png")
    with pytest.raises(SettingError, match="cannot read"):
        load_scene(f"file:{tmp_path / 'bad.png'}")


def test_world_can_be_driven_from_another_thread():
    scene = load_scene("bust", (8, 8), ppp=15)
    world = PhotonWorld(scene, seed=0)
    results, errors = [], []

    def drive():
        try:
            s = 0
            for r in range(8):
                for c in range(8):
                    ev, n = world.count_gated(r, c, 15, 1e-2, s)
                    results.append(ev)
                    s += n
        except Exception as exc:  # reaches the test thread
            errors.append(exc)

    th = threading.Thread(target=drive, daemon=True)
    th.start()
    deadline = time.monotonic() + 60
    while th.is_alive() and time.monotonic() < deadline:   # read while the other thread writes
        _ = sum(e.size for e in list(results))
    th.join(1)
    assert not th.is_alive(), "the world never finished its 64 pixels"
    assert not errors
    assert len(results) == 64 and all(e.size == 15 for e in results)


def test_virtual_clock():
    clock = VirtualClock()
    assert clock.now_s == 0.0
    # unpaced: no waiting. Paced at all, 1000 simulated seconds would take >= 1000 s; the join's
    # 60 s leaves a loaded CI machine its slowness and still catches that.
    advanced = []
    th = threading.Thread(target=lambda: advanced.append(clock.advance(1000.0)), daemon=True)
    th.start()
    th.join(60)
    assert advanced == [1000.0]
    paced = VirtualClock(speed=2.0)
    t0 = time.monotonic()
    paced.advance(0.1)
    paced.advance(0.1)
    assert time.monotonic() - t0 >= 0.095             # 0.2 s simulated at 2x -> 0.1 s
    assert paced.now_s == pytest.approx(0.2)
    with pytest.raises(SettingError):
        clock.advance(-1.0)
    with pytest.raises(SettingError):
        VirtualClock(speed=0)


def test_warm_up_loads_the_dwell_kernel_and_leaves_worlds_as_seeded():
    from spdepth.drivers.sim import kernels as K
    from spdepth.drivers.sim import warm_up

    scene = load_scene("bust", (4, 4), ppp=5.0, sbr=1.0)
    before = PhotonWorld(scene, seed=3).dwell_run(np.arange(16), 0, 1e-3, n_target=5).events
    warm_up()
    assert K.dwell_run.signatures                    # what a scan's first dwell would compile
    after = PhotonWorld(scene, seed=3).dwell_run(np.arange(16), 0, 1e-3, n_target=5).events
    assert np.array_equal(before, after)
