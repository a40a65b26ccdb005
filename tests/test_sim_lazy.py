"""Issue 33: a large simulated frame is built a band of rows at a time as the galvo reaches it
(``drivers.sim.scene.LazyScene``), never whole before the scan; smaller frames are built as
before."""

from __future__ import annotations

import numpy as np
import pytest

from spdepth.drivers.sim import PhotonWorld, load_scene
from spdepth.drivers.sim import scene as scene_mod
from spdepth.drivers.sim import world as world_mod
from spdepth.drivers.sim.scene import LazyScene, Scene

SCENES = ["bust", "daylight", "steps", "tilted-plane", "two-layer"]


@pytest.fixture
def lazy_from_10_pixels(monkeypatch):
    monkeypatch.setattr(scene_mod, "LAZY_PIXELS", 10)


@pytest.mark.parametrize("name", SCENES)
def test_a_lazy_scenes_bands_are_its_whole_frames_rows(name, lazy_from_10_pixels):
    # 67 rows, fewer than SAMPLE_ROWS: every row is sampled, so the light levels are exact
    lazy = load_scene(name, (67, 45), ppp=3.0)
    eager = scene_mod._build(scene_mod._scenes.BUILTIN[name]((67, 45)), lazy.settings, None)
    assert isinstance(lazy, LazyScene) and isinstance(eager, Scene)
    bands = [lazy.band(r0, min(67, r0 + 10)) for r0 in range(0, 67, 10)]
    np.testing.assert_array_equal(np.concatenate([b[0] for b in bands], axis=1), eager.signal_pp)
    np.testing.assert_array_equal(np.concatenate([b[1] for b in bands], axis=1), eager.tof_s)
    np.testing.assert_array_equal(np.concatenate([b[2] for b in bands], axis=0), eager.background_pp)
    assert lazy.active_effects == eager.active_effects and lazy.n_surfaces == eager.n_surfaces
    # the whole-frame truth, built on first use, is the eager scene's
    for key, value in eager.truth().items():
        if isinstance(value, np.ndarray):
            np.testing.assert_array_equal(lazy.truth()[key], value, err_msg=key)


def test_a_lazy_world_simulates_what_the_eager_world_does(lazy_from_10_pixels):
    lazy = load_scene("two-layer", (40, 30), ppp=4.0, effects="dead_time,afterpulsing")
    scene_mod.LAZY_PIXELS = 1 << 21
    eager = load_scene("two-layer", (40, 30), ppp=4.0, effects="dead_time,afterpulsing")
    assert isinstance(lazy, LazyScene) and isinstance(eager, Scene)
    pixels = np.arange(40 * 30)[::-1].copy()
    a, b = PhotonWorld(eager, seed=5), PhotonWorld(lazy, seed=5)
    np.testing.assert_array_equal(a.dwell_run(pixels, 0, 1e-4, n_target=4).events,
                                  b.dwell_run(pixels, 0, 1e-4, n_target=4).events)
    np.testing.assert_array_equal(PhotonWorld(eager, seed=5).raster(), PhotonWorld(lazy, seed=5).raster())


def test_a_lazy_world_builds_only_the_rows_its_dwells_reach(lazy_from_10_pixels):
    scene = load_scene("bust", (200, 64), ppp=5.0)
    world = PhotonWorld(scene, seed=1)
    assert not world._rows_built.any()
    world.dwell_run(np.array([-1, 70 * 64 + 3, 70 * 64 + 4]), 0, 1e-4, n_target=2)
    band = world_mod.BAND_ROWS
    built = np.flatnonzero(world._rows_built)
    np.testing.assert_array_equal(built, np.arange(70 // band * band, 70 // band * band + band))
    # rows never reached hold no rates (their memory is never touched)
    assert not world._lam.reshape(200, 64)[~world._rows_built].any()
    assert world._lam.reshape(200, 64)[world._rows_built].all()


def test_a_large_frame_is_lazy_and_its_light_levels_hold():
    scene = load_scene("bust", (2048, 2048), ppp=15.0, sbr=10.0)
    assert isinstance(scene, LazyScene) and scene.shape == (2048, 2048)
    assert load_scene("bust", (1024, 1024)).__class__ is Scene       # normal frames: built whole
    # scaled by SAMPLE_ROWS rows, the image means over every pixel (band by band) are what ppp
    # and sbr ask for, to the sampling's precision
    n = scene.settings.syncs_per_dwell
    sig = bg = 0.0
    for r0 in range(0, 2048, 256):
        s, _, b = scene.band(r0, r0 + 256)
        sig, bg = sig + float(s.sum()), bg + float(b.sum())
    assert sig * n / 2048 ** 2 == pytest.approx(15.0 * 10 / 11, rel=1e-3)
    assert bg * n / 2048 ** 2 == pytest.approx(15.0 / 11, rel=1e-9)      # a flat background
