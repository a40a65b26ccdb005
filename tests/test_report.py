"""PNG map sheets and the stderr progress bar."""

from __future__ import annotations

import io
import types

import numpy as np
import pytest
from matplotlib.colors import to_rgb
from matplotlib.image import imread

from spdepth.acq.report import (NAN_COLOUR, ProgressBar, dense_limits, render_maps_png, render_point_png,
                        robust_limits)


def test_robust_limits_ignore_outliers_and_nan(rng):
    values = rng.normal(5.0, 0.1, size=10_000)
    values[:20] = 9000.0  # a few stray pixels far away
    values[20:40] = np.nan
    lo, hi = robust_limits(values)
    assert 4.6 < lo < 5.0 < hi < 5.4


@pytest.mark.parametrize("values", [np.full(5, np.nan), np.full(5, 3.0), np.zeros(0)])
def test_robust_limits_degenerate_maps(values):
    lo, hi = robust_limits(values)
    assert lo < hi and np.isfinite(lo) and np.isfinite(hi)


def _colour_pixels(img: np.ndarray, colour: str, tol: float = 0.02) -> int:
    return int(np.sum(np.all(np.abs(img[..., :3] - np.array(to_rgb(colour))) < tol, axis=-1)))


def _maps(rng, shape=(40, 60), nan=True):
    depth = 4.5 + 0.05 * rng.standard_normal(shape)
    if nan:
        depth[5:15, 10:30] = np.nan
    return types.SimpleNamespace(depth_m=depth, background=rng.random(shape),
                                 signal=rng.uniform(1, 15, shape),
                                 uncertainty_s=np.where(np.isnan(depth), np.nan, 1e-10),
                                 photons=rng.integers(1, 15, shape), settings={})


def test_render_maps_png_draws_nan_in_its_own_colour(tmp_path, rng):
    path = render_maps_png(tmp_path / "maps.png", _maps(rng), title="test sheet")
    img = imread(path)
    assert img.shape[0] > 200 and img.shape[1] > 600
    img2 = imread(render_maps_png(tmp_path / "maps2.png", _maps(rng, nan=False)))
    # the NaN block is 10 x 20 of 40 x 60 map pixels, about 5 x 5 screen pixels each; anti-aliased
    # text adds some grey to both sheets, the block only to the first
    assert _colour_pixels(img, NAN_COLOUR) - _colour_pixels(img2, NAN_COLOUR) > 3000
    assert img.std() > 0.05  # not a blank page


def test_render_maps_png_missing_map_is_an_error(tmp_path):
    with pytest.raises(AttributeError):
        render_maps_png(tmp_path / "x.png", types.SimpleNamespace(depth_m=np.ones((2, 2))))


def test_render_point_png(tmp_path, rng):
    times = np.concatenate([rng.uniform(0, 100e-9, 5000), rng.normal(30e-9, 0.3e-9, 5000)])
    img = imread(render_point_png(tmp_path / "p.png", times, tof_s=30e-9))
    assert img.shape[1] > 600 and img.std() > 0.05
    assert _colour_pixels(img, "#d62728", tol=0.05) > 50  # the time-of-flight marker


def test_progress_bar_silent_when_not_on_a_terminal():
    stream = io.StringIO()
    with ProgressBar("x", 100, stream=stream) as bar:
        assert not bar.enabled
        for i in range(101):
            bar(i, 100)
        bar.update(1, "note")
    assert stream.getvalue() == ""


class _Tty(io.StringIO):
    def isatty(self):
        return True


def test_progress_bar_draws_on_a_terminal():
    stream = _Tty()
    bar = ProgressBar("recon ml", stream=stream, max_rate_hz=1e9)
    assert bar.enabled
    for i in range(0, 11):
        bar(i, 10)                    # the callback form: (done, total), total learnt on the way
    bar.close()
    text = stream.getvalue()
    assert "recon ml" in text and "10/10" in text and text.endswith("\n")


def test_progress_bar_steps_with_notes_when_forced():
    stream = io.StringIO()
    with ProgressBar("bench report", 3, unit="point", stream=stream, force=True) as bar:
        for name in ("a", "b", "c"):
            bar.update(1, f"method {name}")
    last = stream.getvalue().rsplit("\r", 1)[-1]
    assert "bench report" in last and "3/3" in last and "method c" in last


def test_dense_limits_follow_the_scene_not_the_wall(rng):
    # 78% of pixels a face 4.27-4.42 m away, 22% a wall at 4.93 m: the colours go to the face
    face = rng.uniform(4.27, 4.42, 7800)
    wall = rng.normal(4.93, 0.005, 2200)
    lo, hi = dense_limits(np.concatenate([face, wall, [np.nan] * 50]))
    assert 4.26 < lo < 4.31 and 4.38 < hi < 4.43
    assert robust_limits(np.concatenate([face, wall]))[1] > 4.9  # percentiles would take the wall


def test_render_maps_png_fades_weak_surfaces_and_says_how_many(tmp_path, rng):
    import dataclasses

    from spdepth.recon.maps import DepthMaps

    h, w = 30, 40
    depth = np.stack([rng.uniform(1.0, 2.0, (h, w)), rng.uniform(3.0, 4.0, (h, w))])
    maps = DepthMaps(tof_s=depth / 1.5e8, depth_m=depth, background=np.ones((h, w)),
                     signal=np.full((2, h, w), 5.0), photons=np.full((h, w), 20),
                     iterations=np.ones((h, w), np.int32), uncertainty_s=np.full((2, h, w), 1e-10),
                     flags=np.zeros((h, w), np.uint8), settings={})
    weak = np.zeros((2, h, w), bool)
    weak[1, :, : w // 2] = True                 # half of the second surface may be background
    plain = imread(render_maps_png(tmp_path / "plain.png", maps))
    faded = imread(render_maps_png(tmp_path / "faded.png", dataclasses.replace(maps, weak=weak)))
    # faded pixels are lighter: the second depth panel's left half, the second uncertainty panel's
    light = lambda img: int(np.sum(img[..., :3].min(axis=-1) > 0.6))  # noqa: E731
    assert light(faded) - light(plain) > 2000


def test_a_progress_bar_that_waits_says_it_is_preparing(monkeypatch):
    """'0 px' for a minute while numba compiles looked like a hang: the bar says why, and the
    note goes once work is done."""
    import io

    from spdepth.acq.report import ProgressBar
    from tests.waiting import wait_until

    monkeypatch.setattr(ProgressBar, "PREPARING_AFTER_S", 0.05)
    out = io.StringIO()
    bar = ProgressBar("recon ml", 10, stream=out, force=True)
    wait_until(lambda: "preparing" in out.getvalue(), timeout_s=5, what="the preparing line")
    assert "preparing: reading the input; the first run after an install also compiles" in out.getvalue()
    bar(10, 10)
    bar.close()
    assert "preparing" not in out.getvalue().rsplit("\r", 1)[-1]
