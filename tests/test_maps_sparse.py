"""The sparse layout of a maps file (``recon.maps.sparse_arrays`` / ``npz_arrays``): frame-sized
arrays stored at the kept pixels with the one value elsewhere, read back whole bit for bit."""

from __future__ import annotations

import io

import numpy as np

from spdepth.recon.maps import FILL_SUFFIX, npz_arrays, sparse_arrays


def _round_trip(arrays: dict) -> dict:
    buf = io.BytesIO()
    np.savez_compressed(buf, **arrays)
    buf.seek(0)
    with np.load(buf) as z:
        return npz_arrays(z)


def test_the_sparse_layout_gives_every_array_back_whole():
    rng = np.random.default_rng(0)
    h, w = 50, 40
    keep = rng.random(h * w) < 0.3
    tof = np.full((h, w), np.nan)
    tof.reshape(-1)[keep] = rng.random(np.count_nonzero(keep))
    surfaces = np.full((2, h, w), np.nan)
    surfaces[1] = 3.0                                  # a different value per surface outside
    surfaces.reshape(2, -1)[:, keep] = 2.0
    uneven = rng.random((h, w))                        # no one value outside: kept whole
    flags = np.ones((h, w), np.uint8)
    flags.reshape(-1)[keep] = 0
    arrays = {"tof_s": tof, "signal": surfaces, "noise": uneven, "flags": flags,
              "acq_flags": flags.copy(), "row_deg": np.arange(h, dtype=float), "settings": np.array("{}")}
    sparse = sparse_arrays(arrays, (h, w), keep, dense=("acq_flags",))
    assert str(sparse["layout"]) == "pixels" and sparse["pixels"].size == np.count_nonzero(keep)
    assert sparse["tof_s"].shape == (np.count_nonzero(keep),)
    assert sparse["signal"].shape == (2, np.count_nonzero(keep))
    np.testing.assert_array_equal(sparse["signal" + FILL_SUFFIX], [np.nan, 3.0])
    assert sparse["noise"].shape == (h, w) and "noise" + FILL_SUFFIX not in sparse
    assert sparse["acq_flags"].shape == (h, w)
    back = _round_trip(sparse)
    assert sorted(back) == sorted(arrays)
    for name, a in arrays.items():
        assert back[name].dtype == a.dtype, name
        np.testing.assert_array_equal(back[name], a, err_msg=name)


def test_a_dense_file_reads_as_it_is():
    a = {"depth_m": np.arange(12.0).reshape(3, 4), "flags": np.zeros((3, 4), np.uint8)}
    back = _round_trip(a)
    assert sorted(back) == sorted(a)
    np.testing.assert_array_equal(back["depth_m"], a["depth_m"])
