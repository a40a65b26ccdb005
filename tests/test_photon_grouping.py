"""Grouping detections by pixel (``PhotonStore.from_pixel_indices``, a numba counting sort) equals
the stable-argsort reference, and the PTU pixel-marker reader keeps every photon in stream order."""

from __future__ import annotations

import numpy as np
import pytest

from spdepth.recon.errors import InputError
from spdepth.recon.photons import PhotonStore
from tests.reference import photons_by_pixel


@pytest.mark.parametrize("index_type", [np.int64, np.int32])   # int32: the PTU reader's (pixel_dtype)
@pytest.mark.parametrize("n, shape", [(0, (1, 1)), (1, (2, 3)), (5000, (7, 9)), (20000, (1, 1))])
def test_counting_sort_equals_the_stable_argsort(rng, n, shape, index_type):
    pixel = rng.integers(0, shape[0] * shape[1], n).astype(index_type)
    times = rng.integers(0, 4096, n).astype(np.uint32)
    store = PhotonStore.from_pixel_indices(pixel, times, shape, 8e-12)
    want_t, want_o = photons_by_pixel(pixel, times, shape[0] * shape[1])
    np.testing.assert_array_equal(store.offsets, want_o)
    np.testing.assert_array_equal(store.times, want_t)


def test_bad_pixel_indices_are_refused():
    with pytest.raises(InputError, match="out of range"):
        PhotonStore.from_pixel_indices(np.array([0, 6]), np.array([1.0, 2.0]), (2, 3), 8e-12)
    with pytest.raises(InputError, match="out of range"):
        PhotonStore.from_pixel_indices(np.array([0, -1], np.int32), np.array([1.0, 2.0]), (2, 3), 8e-12)
    with pytest.raises(InputError, match="out of range"):
        PhotonStore.from_pixel_indices(np.array([2, -1, 0]), np.array([1.0, 2.0, 3.0]), (2, 3), 8e-12)
    with pytest.raises(InputError, match="differ in length"):
        PhotonStore.from_pixel_indices(np.array([0, 1]), np.array([1.0]), (2, 3), 8e-12)


def test_collect_photons_equals_a_numpy_selection(rng):
    from spdepth.acq.readers.picoquant import _collect_photons
    from spdepth.drivers.events import EventKind

    n = 3000
    kind = rng.choice([int(k) for k in EventKind], n).astype(np.uint8)
    channel = rng.integers(0, 3, n).astype(np.uint8)
    dtime = rng.integers(0, 1000, n).astype(np.uint32)
    pixel = rng.integers(-1, 50, n).astype(np.int64)
    for keep in (-1, 1):
        pix_out, t_out = np.empty(n, np.int64), np.empty(n, np.uint32)
        per_channel = np.zeros(64, np.int64)
        got, outside = _collect_photons(kind, channel, dtime, pixel, keep, pix_out, t_out, 0, per_channel)
        is_ph = kind == EventKind.PHOTON
        sel = is_ph & (pixel >= 0) & ((channel == keep) if keep >= 0 else True)
        assert got == sel.sum()
        np.testing.assert_array_equal(pix_out[:got], pixel[sel])
        np.testing.assert_array_equal(t_out[:got], dtime[sel])
        np.testing.assert_array_equal(per_channel[:3], np.bincount(channel[is_ph], minlength=3))
        in_channel = is_ph & ((channel == keep) if keep >= 0 else True)
        assert outside == int((in_channel & (pixel < 0)).sum())


def test_the_reader_collects_pixels_in_the_smallest_index_type_that_holds_the_frame():
    from spdepth.acq.readers.picoquant import pixel_dtype

    assert pixel_dtype(512 * 512) == np.int32
    assert pixel_dtype(2**31 - 1) == np.int32
    assert pixel_dtype(2**31) == np.int64
