"""Histogram cubes as counts: the count store, the readers of .mat / .npy / .npz / HDF5 cubes, and
``spdepth recon`` on a cube."""

from __future__ import annotations

import json

import numpy as np
import pytest

from spdepth.acq.readers import read_photons, sniff_kind
from spdepth.recon.counts import CountStore
from spdepth.recon.errors import InputError
from spdepth.recon.photons import PhotonStore


def small_cube(seed=0, shape=(6, 7, 120), bg=0.04, signal=12.0, dtype=np.uint8):
    """A cube with a Gaussian return (RMS 2 bins) at a per-pixel bin on a flat background."""
    rng = np.random.default_rng(seed)
    h, w, t = shape
    centre = rng.uniform(30, 90, (h, w))
    k = np.arange(t)
    rate = bg + signal * np.exp(-0.5 * ((k - centre[..., None]) / 2.0) ** 2) / (2.0 * np.sqrt(2 * np.pi))
    return rng.poisson(rate).astype(dtype), centre


def test_count_store_round_trip_and_split():
    cube, _ = small_cube()
    c = CountStore.from_cube(cube, 80e-12)
    assert c.n_occupied == np.count_nonzero(cube)
    assert c.n_detections == cube.sum()
    np.testing.assert_array_equal(c.detections(), cube.sum(axis=2))
    photons = c.to_photons()
    assert photons.n_photons == cube.sum()
    again = CountStore.from_photons(photons)
    np.testing.assert_array_equal(again.times, c.times)
    np.testing.assert_array_equal(again.counts, c.counts)
    np.testing.assert_array_equal(again.offsets, c.offsets)
    # the photon list's histogram at its own resolution is the cube
    hist = np.zeros_like(cube, dtype=np.int64)
    pix = again.pixel_index()
    hist.reshape(-1, cube.shape[2])[pix, again.times.astype(int)] += again.counts.astype(int)
    np.testing.assert_array_equal(hist, cube)
    a, b = c.split(seed=3)
    np.testing.assert_array_equal(a.detections() + b.detections(), c.detections())
    assert 0.4 < a.n_detections / c.n_detections < 0.6
    w = c.in_window(40, 80)
    assert w.n_detections == cube[..., 40:80].sum()


def test_count_store_refuses_bad_counts():
    with pytest.raises(InputError, match="negative"):
        CountStore.from_cube(-np.ones((2, 2, 3), np.int16), 1e-12)
    with pytest.raises(InputError, match="whole"):
        CountStore.from_cube(np.full((2, 2, 3), 0.5), 1e-12)
    with pytest.raises(InputError, match="H x W x T"):
        CountStore.from_cube(np.ones((2, 3)), 1e-12)
    corrected = CountStore(np.array([1.0]), np.array([1.5]), np.array([0, 1]), (1, 1), 1e-12)
    with pytest.raises(InputError, match="whole counts"):
        corrected.to_photons()


def test_from_photons_merges_equal_times():
    store = PhotonStore.from_lists([np.array([5.0, 3.0, 5.0, 5.0]), np.array([]), np.array([2.5])],
                                   (1, 3), 1e-12)
    c = CountStore.from_photons(store)
    np.testing.assert_array_equal(c.times, [3.0, 5.0, 2.5])
    np.testing.assert_array_equal(c.counts, [1.0, 3.0, 1.0])
    np.testing.assert_array_equal(c.offsets, [0, 2, 2, 3])


def _write_v73(path, name, array):
    """A MATLAB v7.3 file as MATLAB writes it: HDF5 behind a 512-byte user block whose first
    bytes are the MAT-file text header, arrays stored with their axes reversed."""
    import h5py

    with h5py.File(path, "w", userblock_size=512) as f:
        f.create_dataset(name, data=np.ascontiguousarray(array.T))
    with open(path, "r+b") as f:
        # text, subsystem offset, version 0x0200, endian indicator
        f.write(b"MATLAB 7.3 MAT-file, Platform: GLNXA64, Created on: test HDF5 schema 1.00 .".ljust(116)
                + bytes(8) + b"\x00\x02IM")


@pytest.mark.parametrize("kind", ["mat", "mat73", "npy", "npz", "hdf5"])
def test_readers_give_the_cube(tmp_path, kind):
    import scipy.io

    cube, _ = small_cube(dtype=np.uint16)
    path = tmp_path / {"mat": "c.mat", "mat73": "c.mat", "npy": "c.npy", "npz": "c.npz", "hdf5": "c.h5"}[kind]
    if kind == "mat":
        scipy.io.savemat(path, {"hst": cube, "intensity": cube.sum(axis=2).astype(float)})
    elif kind == "mat73":
        _write_v73(path, "hst", cube)
    elif kind == "npy":
        np.save(path, cube)
    elif kind == "npz":
        np.savez(path, hst=cube, other=np.zeros(3))
    else:
        import h5py

        with h5py.File(path, "w") as f:
            f.create_dataset("frames/hst", data=cube[None])      # one frame, F x H x W x T
            f.attrs["time_unit_s"] = 80e-12
            f.attrs["fov_deg"] = 12.0
    r = read_photons(path, time_unit_s=None if kind == "hdf5" else 80e-12)
    assert r.store is None and r.counts is not None
    assert r.counts.shape == cube.shape[:2]
    np.testing.assert_array_equal(r.counts.detections(), cube.sum(axis=2))
    np.testing.assert_array_equal(r.counts.to_photons().times,
                                  CountStore.from_cube(cube, 80e-12).to_photons().times)
    assert r.counts.time_unit_s == 80e-12
    if kind == "hdf5":
        assert r.meta["fov_deg"] == 12.0 and r.meta["frames"] == 1


def test_frames_are_summed_and_several_arrays_need_a_name(tmp_path):
    import scipy.io

    a, _ = small_cube(seed=1)
    b, _ = small_cube(seed=2)
    np.save(tmp_path / "f.npy", np.stack([a, b]))
    r = read_photons(tmp_path / "f.npy", time_unit_s=1e-10)
    assert r.meta["frames"] == 2
    np.testing.assert_array_equal(r.counts.detections(), a.sum(2) + b.sum(2))
    # MATLAB's 4-D arrays hold the frames last
    scipy.io.savemat(tmp_path / "f.mat", {"x": np.stack([a, b], axis=-1)})
    r = read_photons(tmp_path / "f.mat", time_unit_s=1e-10)
    np.testing.assert_array_equal(r.counts.detections(), a.sum(2) + b.sum(2))
    np.savez(tmp_path / "two.npz", p=a, q=b)
    with pytest.raises(InputError, match="several count arrays .*--mat-var"):
        read_photons(tmp_path / "two.npz", time_unit_s=1e-10)
    r = read_photons(tmp_path / "two.npz", time_unit_s=1e-10, mat_var="q")
    np.testing.assert_array_equal(r.counts.detections(), b.sum(2))
    with pytest.raises(InputError, match="does not record its bin width"):
        read_photons(tmp_path / "f.npy")
    np.save(tmp_path / "flat.npy", np.zeros((3, 4)))
    with pytest.raises(InputError, match="not an H x W x T"):
        read_photons(tmp_path / "flat.npy", time_unit_s=1e-10)
    assert sniff_kind(tmp_path / "two.npz") == "npz"


def test_recon_of_a_cube_equals_recon_of_its_photon_list(tmp_path):
    """The cube read as counts and the same detections as a photon list give the same maps."""
    from spdepth.acq.api import reconstruct_file
    from spdepth.acq.requests import FileReconRequest
    from spdepth.recon.estimate import reconstruct
    from spdepth.recon.model import Binning, ReconSettings

    cube, centre = small_cube(shape=(8, 9, 160), signal=30.0)
    np.save(tmp_path / "c.npy", cube)
    res = reconstruct_file(FileReconRequest(input=str(tmp_path / "c.npy"), method="ml",
                                            time_unit_s=80e-12, pulse_rms_s=160e-12,
                                            window_s=(0.0, 160 * 80e-12), bin_s=80e-12))
    photons = CountStore.from_cube(cube, 80e-12).to_photons()
    direct = reconstruct(photons, ReconSettings(method="ml", pulse_rms_s=160e-12,
                                                binning=Binning.from_window(80e-12, (0.0, 160 * 80e-12), 80e-12)))
    np.testing.assert_array_equal(res.maps.tof_s, direct.tof_s)
    # and the depths are where the returns are (bin k is time k units; the centroid at k + 0.5)
    got = res.maps.tof_s / 80e-12 - 0.5
    assert np.nanmedian(np.abs(got - centre)) < 0.5
    assert res.summary["kind"] == "npy" and res.summary["photons"] == int(cube.sum())


def test_cli_reads_a_mat_cube(tmp_path, capsys):
    import scipy.io

    from spdepth.acq.cli import main

    cube, _ = small_cube(shape=(5, 6, 150), signal=25.0)
    scipy.io.savemat(tmp_path / "c.mat", {"hst_map_set": cube, "i_map_set": cube.sum(2) * 1.0})
    rc = main(["recon", str(tmp_path / "c.mat"), "--time-unit-ps", "80", "--pulse-rms-ps", "170",
               "--json", "--npz", str(tmp_path / "m.npz"), "--fov-deg", "10"])
    assert rc == 0
    s = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert s["shape"] == [5, 6] and s["source"]["cube_var"] == "hst_map_set"
    assert s["pixels_with_estimate"] >= 25
    assert main(["recon", str(tmp_path / "c.mat"), "--time-unit-ps", "80", "--max-photons", "3"]) != 0
    assert "keeps no detection order" in capsys.readouterr().err


@pytest.mark.parametrize("method,reflectors", [("lmf", 1), ("uos", 1), ("ml", 1), ("spatial", 1), ("uos", 2),
                                               ("ml", "auto"), ("spatial", 2), ("spatial", "auto")])
def test_every_estimator_gives_the_same_maps_from_a_cube_as_from_its_photon_list(method, reflectors):
    """(bin, count) pairs in, the maps of the equivalent photon list out: exactly, but for
    spatial's fit, whose EM sums a count times a responsibility where the photon list adds it count
    times (a few ulp; its censoring and every decision are exact), and uos's uncertainties, scaled
    by its matched filter's dispersion, whose terms are summed so too."""
    from spdepth.recon.estimate import reconstruct
    from spdepth.recon.model import Binning, ReconSettings

    cube, _ = small_cube(seed=5, shape=(9, 11, 200), signal=20.0, bg=0.05)
    counts = CountStore.from_cube(cube, 80e-12)
    photons = counts.to_photons()
    for binning in (Binning.from_window(80e-12, (0.0, 200 * 80e-12), 80e-12),
                    Binning.from_window(80e-12, (10 * 80e-12, 190 * 80e-12), 160e-12)):
        s = ReconSettings(method=method, pulse_rms_s=170e-12, binning=binning, reflectors=reflectors)
        a, b = reconstruct(counts, s), reconstruct(photons, s)
        for key in ("flags", "photons", "surfaces"):
            np.testing.assert_array_equal(getattr(a, key), getattr(b, key), err_msg=f"{method} {key}")
        for key in ("tof_s", "signal", "background", "uncertainty_s"):
            if (method == "spatial" and reflectors == 1) or (method == "uos" and key == "uncertainty_s"):
                np.testing.assert_allclose(getattr(a, key), getattr(b, key), rtol=1e-12, atol=0,
                                           err_msg=f"{method} {key}")
            else:
                np.testing.assert_array_equal(getattr(a, key), getattr(b, key), err_msg=f"{method} {key}")
        assert np.isfinite(a.tof_s).any()
        assert np.array_equal(np.isnan(a.tof_s), np.isnan(b.tof_s))


@pytest.mark.parametrize("method", ["ml", "spatial"])
def test_the_k_surface_fit_measures_its_response_on_counts_as_on_photons(method):
    """No pulse given: the K-surface fit re-measures the response pooled on its surfaces, from the
    (bin, count) pairs as from the photon list, with the same maps."""
    from spdepth.recon.estimate import reconstruct
    from spdepth.recon.model import Binning, ReconSettings

    cube, _ = small_cube(seed=5, shape=(24, 24, 200), signal=40.0, bg=0.05)
    counts = CountStore.from_cube(cube, 80e-12)
    s = ReconSettings(method=method, binning=Binning.from_window(80e-12, (0.0, 200 * 80e-12), 80e-12),
                      reflectors=2)
    a, b = reconstruct(counts, s), reconstruct(counts.to_photons(), s)
    assert a.settings["pulse_source"] == "estimated, then measured on the surfaces"
    assert a.settings["irf"] == b.settings["irf"]
    for key in ("tof_s", "signal", "background", "uncertainty_s", "flags", "photons", "surfaces"):
        np.testing.assert_array_equal(getattr(a, key), getattr(b, key), err_msg=f"{method} {key}")


@pytest.mark.parametrize("method,reflectors", [("spatial", 1), ("ml", 2), ("spatial", 2)])
def test_spatial_and_several_surfaces_round_corrected_counts_as_their_photon_list(method, reflectors):
    """A pile-up-corrected store's counts are not whole: spatial's censoring and the K-surface fit
    count whole detections, so its pairs are rounded (CountStore.rounded) as its photon list is
    (to_photons(round_counts=True)), and the maps are that list's."""
    import dataclasses

    from spdepth.recon.estimate import reconstruct
    from spdepth.recon.model import Binning, ReconSettings

    cube, _ = small_cube(seed=7, shape=(9, 10, 160), signal=25.0)
    whole = CountStore.from_cube(cube, 80e-12)
    corrected = dataclasses.replace(whole, counts=whole.counts * 1.37)
    assert not corrected.is_whole() and corrected.rounded().is_whole()
    assert abs(corrected.rounded().n_detections - corrected.n_detections) <= corrected.n_pixels
    s = ReconSettings(method=method, pulse_rms_s=170e-12, reflectors=reflectors,
                      binning=Binning.from_window(80e-12, (0.0, 160 * 80e-12), 80e-12))
    a, b = reconstruct(corrected, s), reconstruct(corrected.to_photons(round_counts=True), s)
    for key in ("flags", "photons", "surfaces"):
        np.testing.assert_array_equal(getattr(a, key), getattr(b, key), err_msg=key)
    for key in ("tof_s", "signal", "background", "uncertainty_s"):
        np.testing.assert_allclose(getattr(a, key), getattr(b, key), rtol=1e-12, atol=0, err_msg=key)
    assert np.isfinite(a.tof_s).any()


@pytest.mark.parametrize("method", ["lmf", "uos", "ml"])
def test_counts_need_not_be_whole(method):
    """Pile-up-corrected counts are not whole numbers: a count a hair above a whole one gives the
    same maps to within that hair (ml once raised such a count to the next power), and doubled
    counts are the photons taken twice."""
    import dataclasses

    from spdepth.recon.estimate import reconstruct
    from spdepth.recon.model import Binning, ReconSettings

    cube, _ = small_cube(seed=6, shape=(6, 8, 150), signal=15.0)
    counts = CountStore.from_cube(cube, 80e-12)
    s = ReconSettings(method=method, pulse_rms_s=170e-12,
                      binning=Binning.from_window(80e-12, (0.0, 150 * 80e-12), 80e-12))
    base = reconstruct(counts, s)
    hair = reconstruct(dataclasses.replace(counts, counts=counts.counts * (1 + 1e-9)), s)
    np.testing.assert_allclose(hair.tof_s, base.tof_s, rtol=1e-6, atol=1e-15)
    np.testing.assert_allclose(hair.signal, base.signal * (1 + 1e-9), rtol=1e-6)
    doubled = reconstruct(dataclasses.replace(counts, counts=counts.counts * 2), s)
    twice = reconstruct(dataclasses.replace(counts, counts=counts.counts * 2).to_photons(), s)
    np.testing.assert_array_equal(doubled.tof_s, twice.tof_s)
