"""PicoQuant reader, pixel markers first: a count-gated recording (dwell varies per pixel) is
assigned by its pixel markers through acq.assign, photon for photon as the simulator placed them,
where interpolating between line markers misplaces photons. Files with line markers and no pixel
markers still interpolate."""

from __future__ import annotations

import logging

import numpy as np
import pytest
from numpy.testing import assert_array_equal

import spdepth.acq.readers.picoquant as pq
from spdepth.acq.ptu import read_layout, write_ptu
from spdepth.acq.readers import read_photons
from spdepth.drivers.events import EventKind, Marker, RecordType
from spdepth.drivers.sim import PhotonWorld, load_scene

H, W, TARGET = 7, 9, 12


@pytest.fixture(scope="module")
def gated(tmp_path_factory):
    """A count-gated scan written as a recording, with each photon's true pixel from the
    simulator: pixel k owns the syncs from its PIXEL marker up to the next one (count-gated
    pixels never share a sync), and the row/column follow the scan order."""
    logging.getLogger("ptufile").setLevel(logging.CRITICAL)
    sc = load_scene("bust", (H, W), ppp=TARGET)
    s = sc.settings
    ev = PhotonWorld(sc, seed=3).raster(n_target=TARGET, dwell_limit_s=1.0)
    starts = ev["sync"][(ev["kind"] == EventKind.MARKER) & (ev["marker"] & Marker.PIXEL != 0)]
    assert starts.size == H * W
    ph = ev[ev["kind"] == EventKind.PHOTON]
    truth_pixel = np.searchsorted(starts, ph["sync"], side="right") - 1
    path = tmp_path_factory.mktemp("gated") / "gated.ptu"
    write_ptu(path, ev, (H, W), s.sync_period_s, s.resolution_s, s.dwell_s, s.range_bins)
    return path, ev, ph, truth_pixel


def _per_pixel(pixel, dtime):
    """Sorted detection times of each pixel, for an order-free comparison."""
    order = np.lexsort((dtime, pixel))
    return pixel[order], dtime[order]


def test_count_gated_dwell_varies(gated):
    _, ev, _, _ = gated
    starts = ev["sync"][(ev["kind"] == EventKind.MARKER) & (ev["marker"] & Marker.PIXEL != 0)]
    dwell = np.diff(starts.reshape(H, W), axis=1)
    assert dwell.min() * 3 < dwell.max()      # far from fixed dwell: interpolation must fail


def test_pixel_markers_place_every_photon(gated, monkeypatch):
    path, _, ph, truth_pixel = gated
    monkeypatch.setattr(pq, "CHUNK_RECORDS", 97)   # many chunks: state carried across them
    res = read_photons(path)
    assert res.is_image and res.meta["assignment"] == "pixel markers"
    assert res.store.shape == (H, W)
    assert res.store.n_photons == ph.size and res.meta["photons_outside_pixels"] == 0
    assert res.meta["lines"] == H and res.meta["frames"] == 1
    assert_array_equal(res.store.counts().ravel(), np.bincount(truth_pixel, minlength=H * W))
    assert np.all(res.store.counts() == TARGET)
    got_pixel = np.repeat(np.arange(H * W), res.store.counts().ravel())
    ref = _per_pixel(truth_pixel, ph["dtime"].astype(np.float64))
    assert_array_equal(_per_pixel(got_pixel, res.store.times), ref)


def test_interpolation_would_misplace_them(gated):
    """The same records through the line-marker interpolation (what ptufile and PicoQuant's
    tools do): many photons land in the wrong column."""
    path, _, ph, truth_pixel = gated
    records = np.fromfile(path, "<u4", offset=read_layout(path).record_offset)
    decoded = pq._decode(records, int(RecordType.HYDRAHARP2_T3))
    row, col, lines, _, _ = pq.assign_pixels(decoded["time"], decoded["channel"], decoded["marker"],
                                             pix_x=W, line_start=2, line_stop=3, frame=4)
    is_photon = decoded["channel"] >= 0
    interp = (row * W + col)[is_photon]
    assert lines == H
    wrong = np.count_nonzero(interp != truth_pixel)
    assert wrong > ph.size // 10


def test_tttrlib_with_pixel_markers_matches(gated):
    """tttrlib reads our pixel clock too (its ``marker_pixel`` default is our input 1)."""
    import tttrlib

    path, _, _, truth_pixel = gated
    tttr = tttrlib.TTTR(str(path))
    image = tttrlib.CLSMImage(tttr, use_pixel_markers=True)
    image.fill(tttr, channels=[0])
    counts = np.asarray(image.intensity, np.int64).sum(axis=0)
    assert_array_equal(counts.ravel(), np.bincount(truth_pixel, minlength=H * W))


def test_pixel_tag_without_pixel_markers_interpolates(tmp_path):
    """Fixed dwell with the pixel markers stripped: the reader notes it and interpolates, which
    for fixed dwell puts every photon where the simulator did."""
    logging.getLogger("ptufile").setLevel(logging.CRITICAL)
    sc = load_scene("bust", (5, 6), ppp=10)
    s = sc.settings
    ev = PhotonWorld(sc, seed=4).raster()
    ev["marker"] &= ~np.uint8(Marker.PIXEL)
    ev = ev[(ev["kind"] != EventKind.MARKER) | (ev["marker"] != 0)]
    path = tmp_path / "fixed.ptu"
    write_ptu(path, ev, (5, 6), s.sync_period_s, s.resolution_s, s.dwell_s, s.range_bins)
    res = read_photons(path)
    assert res.meta["assignment"] == "line interpolation"
    assert any("pixel marker 1" in n for n in res.notes)
    ph = ev[ev["kind"] == EventKind.PHOTON]
    ref = np.bincount(ph["sync"] // s.syncs_per_dwell, minlength=30).reshape(5, 6)
    assert_array_equal(res.store.counts(), ref)


def test_fixed_dwell_simulate_file_by_pixel_markers(tmp_path):
    """``spdepth simulate``'s files carry pixel markers: read by them, the counts equal ptufile's
    interpolated image (fixed dwell: both are exact)."""
    import ptufile

    from spdepth.acq.cli import main

    out = tmp_path / "sim.ptu"
    assert main(["simulate", "--scene", "two-layer", "--size", "10x6", "--ppp", "9",
                 "--ptu", str(out)]) == 0
    res = read_photons(out)
    assert res.meta["assignment"] == "pixel markers"
    with ptufile.PtuFile(out) as ptu:
        counts = ptu.decode_image(dtime=-1).sum(axis=(0, 3, 4)).astype(np.int64)
    assert_array_equal(res.store.counts(), counts)


def test_gated_recording_header_holds_the_typical_dwell(tmp_path):
    """A count-gated session's recording closes with ``ImgHdr_TimePerPixel`` = the mean logged
    pixel time (not the dwell limit), so ptufile's decode_image, which places photons by it from each
    line start, puts most photons in their pixel (with the 20 ms limit there: about 8%)."""
    import json
    import ptufile

    from spdepth.acq.cli import main

    out = tmp_path / "run"
    assert main(["scan", "--sim", "--mode", "gated", "--size", "16x16", "--out", str(out)]) == 0
    dwells = [r[4] for line in (out / "events.jsonl").read_text().splitlines()
              for r in (json.loads(line).get("records") or []) if json.loads(line).get("event") == "pixels"]
    ours = read_photons(out / "recording.ptu").store.counts()
    with ptufile.PtuFile(out / "recording.ptu") as ptu:
        assert ptu.tags["ImgHdr_TimePerPixel"] == pytest.approx(np.mean(dwells) * 1e-6, rel=1e-6)   # ms
        theirs = ptu.decode_image(dtime=-1).sum(axis=(0, 3, 4)).astype(np.int64)[:16, :16]
    assert np.minimum(theirs, ours).sum() > 0.5 * ours.sum()


def test_the_reader_warm_up_loads_every_kernel_the_read_runs(gated):
    # spdepth recon runs it on a thread while it opens the file: a kernel it missed would still be
    # loaded (or compiled) inside the read, in the read's time. The read calls two from Python: the
    # stages of decoding in one (their kernels compiled into it) and the grouping by pixel
    from spdepth.recon import photons

    pq.warm_up()
    kernels = (pq._decode_pixel_markers, photons._group_by_pixel)
    before = [len(k.signatures) for k in kernels]
    assert all(before)
    assert read_photons(gated[0]).meta["assignment"] == "pixel markers"
    assert [len(k.signatures) for k in kernels] == before


def test_an_undefined_record_is_refused_naming_the_file_and_its_place(gated, tmp_path, monkeypatch):
    # special=1 on channel 20 is neither a marker (1..15) nor an overflow (63); found in a later
    # piece than the first, its index counts from the stream's start
    from spdepth.drivers.tagger.t3 import T3_CHANNEL_SHIFT, T3_SPECIAL_SHIFT

    path = tmp_path / "bad.ptu"
    data = bytearray(gated[0].read_bytes())
    layout = read_layout(gated[0])
    at = 250
    bad = (1 << T3_SPECIAL_SHIFT) | (20 << T3_CHANNEL_SHIFT) | 5
    data[layout.record_offset + 4 * at:layout.record_offset + 4 * at + 4] = bad.to_bytes(4, "little")
    path.write_bytes(bytes(data))
    monkeypatch.setattr(pq, "CHUNK_RECORDS", 97)
    with pytest.raises(pq.InputError, match=rf"bad\.ptu: T3 record {at} is not a photon, marker or overflow: "
                                            rf"0x{bad:08x} \(special=1, channel=20"):
        read_photons(path)
