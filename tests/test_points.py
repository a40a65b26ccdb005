"""Point clouds (acq.points) read back with plyfile and laspy; the map definitions' levels."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from spdepth.acq.mapdefs import MAPS_BY_KEY, MapInput, constant_value, levels_for, widen
from spdepth.acq.points import ScanGeometry, geometry_of, points_from_maps, write_points
from spdepth.recon.maps import DepthMaps


def _maps(rng, h=12, w=16, k=None):
    shape = (h, w) if k is None else (k, h, w)
    depth = 3.0 + rng.normal(0, 0.1, shape)
    depth[..., 2, 3] = np.nan                       # a pixel without an estimate
    depth[..., 5, :4] = np.nan
    return DepthMaps(tof_s=2 * depth / 299792458.0, depth_m=depth,
                     background=rng.uniform(0, 1e-3, (h, w)), signal=rng.uniform(5, 15, shape),
                     photons=np.full((h, w), 15), iterations=np.ones((h, w), np.int32),
                     uncertainty_s=np.full(shape, 1e-10), flags=np.zeros((h, w), np.uint8),
                     settings={})


def test_ply_and_las_read_back(tmp_path, rng):
    plyfile = pytest.importorskip("plyfile")
    laspy = pytest.importorskip("laspy")
    maps = _maps(rng)
    g = ScanGeometry.from_fov((12, 16), 20.0)
    n = write_points(maps, g, ply=tmp_path / "p.ply", las=tmp_path / "p.las")
    ok = np.isfinite(maps.depth_m)
    assert n == ok.sum()                                        # points = estimated pixels
    v = plyfile.PlyData.read(str(tmp_path / "p.ply"))["vertex"]
    assert len(v) == n
    xyz = np.stack([v["x"], v["y"], v["z"]], axis=1)
    rng_m = np.linalg.norm(xyz, axis=1)
    np.testing.assert_allclose(rng_m, maps.depth_m[v["row"], v["col"]], rtol=1e-12)  # range = depth
    np.testing.assert_allclose(v["intensity"], maps.signal[v["row"], v["col"]], rtol=1e-6)
    # the frame: column angle > 0 -> x > 0, row angle > 0 -> y > 0, z forward
    assert np.all(v["z"] > 0)
    right = v["col"] > 7
    assert np.all(v["x"][right] > 0) and np.all(v["x"][~right] < 0)
    las = laspy.read(str(tmp_path / "p.las"))
    assert len(las.points) == n
    xyz_l = np.stack([las.x, las.y, las.z], axis=1)
    np.testing.assert_allclose(np.linalg.norm(xyz_l, axis=1),
                               maps.depth_m[las.row, las.col], atol=2e-4)  # 0.1 mm scale
    assert set(np.unique(las.surface)) == {0}


def test_several_surfaces_give_one_point_each(rng):
    maps = _maps(rng, k=2)
    cloud = points_from_maps(maps, ScanGeometry.from_fov((12, 16), 10.0))
    assert len(cloud) == np.isfinite(maps.depth_m).sum()
    assert set(np.unique(cloud.surface)) == {0, 1}
    np.testing.assert_allclose(cloud.range_m, maps.depth_m[cloud.surface, cloud.row, cloud.col])


def test_geometry_of_a_non_square_scan():
    g = ScanGeometry.from_fov((96, 128), 20.0)
    dx, dy = g.pixel_deg
    assert dx == pytest.approx(20 / 128) and dy == pytest.approx(20 / 96)
    assert g.fov_deg == pytest.approx((20.0, 20.0))
    left, right, top, bottom = g.extent_deg
    assert (left, right, top, bottom) == pytest.approx((-10, 10, -10, 10))
    assert geometry_of(type("M", (), {"settings": {"geometry": g.to_dict()}})()) == g


def test_depth_levels_show_object_and_wall(rng):
    # a head (2.8-3.1 m) in front of a wall at 3.6 m: both inside the levels, as in the bust
    depth = np.full((64, 64), 3.6) + rng.normal(0, 0.01, (64, 64))
    depth[16:40, 20:44] = np.linspace(2.8, 3.1, 24)[None, :]
    lo, hi = levels_for(MAPS_BY_KEY["depth"], depth)
    assert lo < 2.85 and hi > 3.55
    # steps 10 cm apart: every step has its own colour (none saturates)
    steps = np.repeat(np.arange(5) * 0.1 + 2.0, 64 * 64 // 5 + 1)[:64 * 64].reshape(64, 64)
    lo, hi = levels_for(MAPS_BY_KEY["depth"], steps)
    assert lo <= 2.0 and hi >= 2.4


def test_levels_widen_and_constant_maps():
    assert widen((1.0, 2.0), (1.5, 3.0)) == (1.0, 3.0)
    assert widen(None, (0.0, 1.0)) == (0.0, 1.0)
    assert constant_value(np.array([15.0, 15.0, np.nan])) == 15.0
    assert constant_value(np.array([15.0, 14.0])) is None


def test_unmeasured_pixels_have_no_background():
    counts = np.array([[15.0, 0.0], [np.nan, 15.0]])
    mi = MapInput(depth_m=np.array([[3.0, np.nan], [np.nan, 3.0]]), background=np.zeros((2, 2)),
                  signal=np.full((2, 2), 15.0), uncertainty_s=np.zeros((2, 2)), counts=counts,
                  n_bins=801, target=15)
    bg = MAPS_BY_KEY["background"].extract(mi)
    assert np.isnan(bg[0, 1]) and np.isnan(bg[1, 0]) and bg[0, 0] == 0.0


DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
if not DATA.is_dir():
    DATA = Path("/work/shared/data")


def _data(rel):
    p = DATA / rel
    if not p.is_file():
        pytest.skip(f"{p} not here (../shared/data)")
    return str(p)


def test_gated_long_range_data_land_at_their_range(tmp_path):
    from spdepth.acq.api import reconstruct_file
    from spdepth.acq.requests import FileReconRequest

    path = _data("longrange/tower_9km.mat")
    plain = reconstruct_file(FileReconRequest(input=path, time_unit_s=1e-12, method="lmf"))
    assert 700 < plain.summary["depth_m_median"] < 900            # times after the range gate
    res = reconstruct_file(FileReconRequest(
        input=path, time_unit_s=1e-12, method="lmf", range_offset_m=9015.0, fov_deg=1.0,
        las=str(tmp_path / "t.las")))
    assert res.summary["depth_m_median"] == pytest.approx(plain.summary["depth_m_median"] + 9015)
    import laspy

    las = laspy.read(str(tmp_path / "t.las"))
    r = np.sqrt(np.asarray(las.x) ** 2 + np.asarray(las.y) ** 2 + np.asarray(las.z) ** 2)
    assert len(r) == int(np.isfinite(res.maps.depth_m).sum())
    assert 9700 < np.median(r) < 9900                             # the tower at 9.8 km
    delay = reconstruct_file(FileReconRequest(input=path, time_unit_s=1e-12, method="lmf",
                                              gate_delay_s=2 * 9015.0 / 299792458.0))
    np.testing.assert_allclose(delay.maps.depth_m, res.maps.depth_m, rtol=1e-12)


def test_sparse_data_suggest_the_spatial_method():
    from spdepth.acq.api import reconstruct_file
    from spdepth.acq.requests import FileReconRequest

    res = reconstruct_file(FileReconRequest(input=_data("fpi/chart_depth.mat"), time_unit_s=8e-12,
                                            pulse_rms_s=360e-12, method="lmf"))
    assert any("--method spatial" in n for n in res.summary["notes"])


def test_points_of_a_mat_file_need_its_field_of_view(tmp_path):
    from spdepth.acq.errors import RequestError
    from spdepth.acq.requests import FileReconRequest

    path = _data("fpi/chart_depth.mat")
    with pytest.raises(RequestError, match="--fov-deg"):
        FileReconRequest(input=path, time_unit_s=8e-12, ply=str(tmp_path / "p.ply"))
    with pytest.raises(RequestError, match="not both"):
        FileReconRequest(input=path, time_unit_s=8e-12, range_offset_m=1.0, gate_delay_s=1e-6)


def test_a_plan_without_angles_has_no_geometry():
    """One rule (``ScanGeometry.from_plan``) for the session's maps, a file's run.json and the
    window: a foreign recording replayed has all angles 0, which is no geometry, not a point."""
    from spdepth.acq.plan import ScanPlan

    assert ScanGeometry.from_plan(ScanPlan(8, 6, 0.0, 0.0, 0.0, 0.0)) is None
    assert ScanGeometry.from_plan(ScanPlan(8, 6, -2.0, 2.0, 0.0, 0.0)) is None   # rows without angles
    assert ScanGeometry.from_plan(ScanPlan(1, 1, 0.0, 0.0, 0.0, 0.0)) is not None   # a point
    g = ScanGeometry.from_plan(ScanPlan(8, 6, -2.0, 2.0, -1.5, 1.5))
    assert g.shape == (6, 8) and (g.x_first_deg, g.y_last_deg) == (-2.0, 1.5)


def test_las_returns_and_flags_read_back(tmp_path, rng):
    # two surfaces per pixel, the far one stored first in some pixels; a weak surface, a pixel
    # without a return, and session flags: every one survives in the files
    laspy = pytest.importorskip("laspy")
    plyfile = pytest.importorskip("plyfile")
    from spdepth.acq.flags import AcqFlag
    from spdepth.acq.points import PointFlag
    from spdepth.recon.maps import PixelFlag

    maps = _maps(rng, k=2)
    depth = maps.depth_m.copy()
    depth[0, 0, 0], depth[1, 0, 0] = 5.0, 3.0                 # surface 0 farther than surface 1
    depth[:, 7, 7] = np.nan
    flags = maps.flags.copy()
    flags[7, 7] = PixelFlag.NO_RETURN
    weak = np.zeros(depth.shape, bool)
    weak[1, 1, 1] = True
    acq = np.zeros((12, 16), np.uint8)
    acq[0, 0] = AcqFlag.DWELL_LIMIT
    acq[1, 1] = AcqFlag.INCOMPLETE
    from dataclasses import replace

    maps = replace(maps, depth_m=depth, tof_s=2 * depth / 299792458.0, flags=flags, weak=weak, surfaces=None)
    g = ScanGeometry.from_fov((12, 16), 20.0)
    n = write_points(maps, g, ply=tmp_path / "p.ply", las=tmp_path / "p.las", acq_flags=acq)
    assert n == np.isfinite(depth).sum()                      # the no-return pixel is left out
    las = laspy.read(str(tmp_path / "p.las"))
    ret, nret = np.asarray(las.return_number), np.asarray(las.number_of_returns)
    assert ret.min() >= 1 and np.all(ret <= nret)
    r = np.sqrt(np.asarray(las.x) ** 2 + np.asarray(las.y) ** 2 + np.asarray(las.z) ** 2)
    row, col = np.asarray(las.row), np.asarray(las.col)
    for (rr, cc) in [(0, 0), (3, 3), (2, 3)]:
        here = (row == rr) & (col == cc)
        order = np.argsort(ret[here])
        assert np.all(np.diff(r[here][order]) > 0)            # return 1 the nearest
        assert np.all(nret[here] == here.sum())
    ud = np.asarray(las.user_data)
    assert np.all(ud[(row == 0) & (col == 0)] & PointFlag.SHORT)
    assert np.all(ud[(row == 1) & (col == 1)] & PointFlag.INCOMPLETE)
    assert (ud[(row == 1) & (col == 1)] & PointFlag.WEAK).sum() == 1
    assert not np.any(np.asarray(las.withheld))
    # asked for, the no-return pixel is one withheld point at the origin, flagged
    write_points(maps, g, las=tmp_path / "q.las", ply=tmp_path / "q.ply", no_return=True)
    q = laspy.read(str(tmp_path / "q.las"))
    nr = (np.asarray(q.user_data) & PointFlag.NO_RETURN) != 0
    assert nr.sum() == 1 and np.asarray(q.withheld)[nr].all() and np.asarray(q.pixel_flag)[nr][0] == PixelFlag.NO_RETURN
    v = plyfile.PlyData.read(str(tmp_path / "q.ply"))["vertex"]
    assert ((v["flags"] & PointFlag.NO_RETURN) != 0).sum() == 1
    assert {"return_number", "number_of_returns", "pixel_flag", "acq_flag"} <= set(v.data.dtype.names)


def test_weak_surfaces_do_not_set_the_levels(rng):
    # a face at 2.8-3.1 m over a wall at 3.6 m, and weak surfaces scattered over 0.2-14 m: the
    # levels are the confident surfaces' (the face keeps its colours)
    depth = np.full((64, 64), 3.6) + rng.normal(0, 0.01, (64, 64))
    depth[16:40, 20:44] = np.linspace(2.8, 3.1, 24)[None, :]
    weak = rng.random((64, 64)) < 0.25
    depth[weak] = rng.uniform(0.2, 14.0, int(weak.sum()))
    lo, hi = levels_for(MAPS_BY_KEY["depth"], depth, weak=weak)
    assert 2.7 < lo < 2.85 and 3.55 < hi < 3.7
    lo_all, hi_all = levels_for(MAPS_BY_KEY["depth"], depth)
    assert lo_all < 1.0 and hi_all > 10.0                      # what the weak ones did before
    # only weak surfaces: they are all there is to draw
    assert levels_for(MAPS_BY_KEY["depth"], depth, weak=np.ones_like(weak)) == (lo_all, hi_all)


def test_directions_at_pixels_are_the_frame_s_directions_bit_for_bit():
    # points_from_maps takes the rays of the estimated pixels alone (a 4096 x 4096 frame's
    # (H, W, 3) array is 400 MB); they must be the very floats of the whole frame's
    g = ScanGeometry((37, 53), -7.5, 9.25, 4.0, -3.0)
    rr, cc = np.nonzero(np.random.default_rng(5).random((37, 53)) < 0.3)
    assert np.array_equal(g.directions_at(rr, cc), g.directions()[rr, cc])
