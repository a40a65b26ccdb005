"""spdepth.acq.ptu: the recording header ptufile and tttrlib read, the record-count patch, one marker kind
per record (same pixels as the device's combined records), and simulate's files as images in
tttrlib with every photon placed."""

from __future__ import annotations

import io
import json
import logging

import numpy as np
import pytest
from numpy.testing import assert_array_equal

from spdepth.acq.assign import PixelAssigner
from spdepth.acq.ptu import (MARKER_INPUT, PIXEL_MARKER_TAG, encode_events, marker_map, patch_record_count,
                     ptu_header, read_layout, split_marker_records, write_ptu)
from spdepth.drivers.events import EVENT_DTYPE, EventKind, Marker
from spdepth.drivers.sim import PhotonWorld, load_scene
from spdepth.drivers.tagger.t3 import decode_t3, encode_t3
from spdepth.recon.errors import InputError

ORDER = (8, 2, 1, 4)  # FRAME, LINE_START, PIXEL, LINE_STOP


def split_reference(records: np.ndarray) -> np.ndarray:
    """Plain Python: each marker record (special=1, channel 1..15) -> one record per bit."""
    out = []
    for r in records.tolist():
        ch = (r >> 25) & 63
        if r >> 31 and 1 <= ch <= 15:
            rest = r & ~(63 << 25)
            out += [rest | (b << 25) for b in ORDER if ch & b]
        else:
            out.append(r)
    return np.array(out, np.uint32)


def _scan(h=6, w=5, ppp=20, seed=1, frames=1, **kw):
    sc = load_scene("bust", (h, w), ppp=ppp)
    world = PhotonWorld(sc, seed=seed)
    if frames == 1:
        return sc, world.raster(**kw)
    frame_len = h * w * sc.settings.syncs_per_dwell + 50
    return sc, np.concatenate([world.raster(start_sync=f * frame_len) for f in range(frames)])


def _quiet():
    logging.getLogger("ptufile").setLevel(logging.CRITICAL)


def test_marker_numbering_is_the_devices():
    assert {m: 1 << (n - 1) for m, n in MARKER_INPUT.items()} == {m: int(m) for m in Marker}
    lut = marker_map({"ImgHdr_LineStart": 2, "ImgHdr_LineStop": 3, "ImgHdr_Frame": 4,
                      PIXEL_MARKER_TAG: 1})
    assert_array_equal(lut, np.arange(16))
    # ptufile's own writer numbering: line start 1, stop 2, frame 3, no pixel marker
    lut = marker_map({"ImgHdr_LineStart": 1, "ImgHdr_LineStop": 2, "ImgHdr_Frame": 3})
    assert lut[1] == Marker.LINE_START and lut[2] == Marker.LINE_STOP and lut[4] == Marker.FRAME
    assert lut[8] == 0 and lut[3] == Marker.LINE_START | Marker.LINE_STOP
    assert marker_map({"ImgHdr_PixX": 4}) is None
    with pytest.raises(InputError, match="one marker input for several"):
        marker_map({"ImgHdr_LineStart": 1, "ImgHdr_LineStop": 1})


def test_split_matches_reference(rng):
    n = 20_000
    nsync = rng.integers(0, 1024, n, dtype=np.uint32)
    dtime = rng.integers(0, 2 ** 15, n, dtype=np.uint32)
    kind = rng.integers(0, 4, n)
    channel = np.where(kind == 0, rng.integers(0, 64, n), np.where(kind == 1, 63, rng.integers(1, 16, n)))
    special = (kind != 0).astype(np.uint32)
    records = (special << 31) | (channel.astype(np.uint32) << 25) | (dtime << 10) | nsync
    out = split_marker_records(records)
    assert_array_equal(out, split_reference(records))
    assert out.size > records.size
    photons_only = records[special == 0]
    same = split_marker_records(photons_only)           # nothing to split: no copy
    assert np.shares_memory(same, photons_only) and np.array_equal(same, photons_only)


@pytest.mark.slow
def test_encode_split_keeps_assignment():
    """The device's combined FRAME|LINE_START|PIXEL records and the split file records give every
    photon the same pixel (acq.assign applies combined bits in the split order)."""
    sc, ev = _scan(h=5, w=7, ppp=6, n_target=6)       # count-gated: dwell varies per pixel
    combined = encode_t3(ev)
    split = encode_events(ev)
    assert_array_equal(split, split_marker_records(combined))
    assert split.size > combined.size
    a = decode_t3(combined)
    b = decode_t3(split)
    assert np.all(np.isin(b["marker"][b["kind"] == EventKind.MARKER], [1, 2, 4, 8]))
    pa = PixelAssigner((5, 7)).assign(a)
    pb = PixelAssigner((5, 7)).assign(b)
    assert_array_equal(pa[a["kind"] == EventKind.PHOTON], pb[b["kind"] == EventKind.PHOTON])
    assert np.all(pa[a["kind"] == EventKind.PHOTON] >= 0)


def test_header_reads_in_ptufile_and_count_patch(tmp_path):
    import ptufile

    _quiet()
    sc, ev = _scan()
    s = sc.settings
    head = ptu_header((6, 5), s.sync_period_s, s.resolution_s, s.dwell_s, s.range_bins,
                      comment="test", tags={"SPDepth_Plan": {"mode": "raster", "target": 15},
                                            "SPDepth_Target": 15})
    records = encode_events(ev)
    path = tmp_path / "rec.ptu"
    with open(path, "w+b") as fh:
        fh.write(head)
        fh.write(records.tobytes())
        fh.write(b"\x01\x02")                  # a torn last record, as after kill -9
        fh.flush()
        with ptufile.PtuFile(path) as ptu:     # crash-safe: count 0 -> every whole record
            assert ptu.number_records == records.size
            assert ptu.tags["TTResult_NumberOfRecords"] == 0
            assert ptu.tags["TTResultFormat_TTTRRecType"] == 0x01010304
            assert (ptu.tags["ImgHdr_LineStart"], ptu.tags["ImgHdr_LineStop"],
                    ptu.tags["ImgHdr_Frame"], ptu.tags[PIXEL_MARKER_TAG]) == (2, 3, 4, 1)
            assert json.loads(ptu.tags["SPDepth_Plan"]) == {"mode": "raster", "target": 15}
            assert ptu.tags["SPDepth_Target"] == 15
            assert ptu.is_image and ptu.shape[1:3] == (6, 5)
            assert ptu.decode_image(dtime=-1).sum() == np.count_nonzero(ev["kind"] == 0)
        fh.seek(7)
        patch_record_count(fh, records.size)
        assert fh.tell() == 7                   # position restored
    layout = read_layout(path)
    assert layout.record_offset == len(head) and layout.n_records == records.size
    with ptufile.PtuFile(path) as ptu:
        assert ptu.tags["TTResult_NumberOfRecords"] == records.size
    with pytest.raises(InputError, match="opened for reading"):
        patch_record_count(io.BufferedWriter(io.BytesIO()), 3)
    with pytest.raises(InputError, match="cannot be given"):
        ptu_header((2, 2), 1e-7, 8e-12, 1e-6, 100, tags={"ImgHdr_Frame": 1})
    with pytest.raises(InputError, match="do not fit T3"):
        ptu_header((2, 2), 1e-7, 8e-12, 1e-6, 40_000)


@pytest.mark.parametrize("frames", [1, 3])
def test_tttrlib_and_ptufile_place_every_photon(tmp_path, frames):
    """Split records with FRAME at the start of each frame (as the device streams it): tttrlib
    and ptufile with default settings both find the frames and place every photon where the
    simulator put it."""
    import ptufile
    import tttrlib

    _quiet()
    h, w = 6, 5
    sc, ev = _scan(h, w, frames=frames)
    s = sc.settings
    frame_len = h * w * s.syncs_per_dwell + 50
    ph = ev[ev["kind"] == EventKind.PHOTON]
    ref = np.zeros((frames, h, w), np.int64)
    np.add.at(ref, (ph["sync"] // frame_len, *np.divmod((ph["sync"] % frame_len) // s.syncs_per_dwell, w)), 1)
    path = tmp_path / "scan.ptu"
    write_ptu(path, ev, (h, w), s.sync_period_s, s.resolution_s, s.dwell_s, s.range_bins)
    with ptufile.PtuFile(path) as ptu:
        counts = ptu.decode_image(dtime=-1).sum(axis=(3, 4)).astype(np.int64)
    assert_array_equal(counts, ref)
    tttr = tttrlib.TTTR(str(path))
    image = tttrlib.CLSMImage(tttr)
    assert (image.n_frames, image.n_lines, image.n_pixel) == (frames, h, w)
    image.fill(tttr, channels=[0])
    assert_array_equal(np.asarray(image.intensity, np.int64), ref)


def test_simulate_file_reads_in_tttrlib(tmp_path):
    """``spdepth simulate``'s file: tttrlib's default CLSMImage places every photon, pixel for pixel
    as ptufile does."""
    import ptufile
    import tttrlib

    from spdepth.acq.cli import main

    _quiet()
    out = tmp_path / "sim.ptu"
    assert main(["simulate", "--scene", "steps", "--size", "12x8", "--ppp", "10", "--seed", "2",
                 "--ptu", str(out)]) == 0
    with ptufile.PtuFile(out) as ptu:
        counts = ptu.decode_image(dtime=-1).sum(axis=(0, 3, 4)).astype(np.int64)
        n_photons = ptu.number_photons
    tttr = tttrlib.TTTR(str(out))
    image = tttrlib.CLSMImage(tttr)
    assert (image.n_frames, image.n_lines, image.n_pixel) == (1, 8, 12)
    image.fill(tttr, channels=[0])
    intensity = np.asarray(image.intensity, np.int64)[0]
    assert intensity.sum() == n_photons == counts.sum()
    assert_array_equal(intensity, counts)


def test_write_ptu_chunks_like_one_go(tmp_path):
    sc, ev = _scan(frames=2)
    s = sc.settings
    args = ((6, 5), s.sync_period_s, s.resolution_s, s.dwell_s, s.range_bins)
    write_ptu(tmp_path / "a.ptu", ev, *args)
    n = write_ptu(tmp_path / "b.ptu", ev, *args, chunk_events=37)
    la, lb = read_layout(tmp_path / "a.ptu"), read_layout(tmp_path / "b.ptu")
    ra = np.fromfile(la.path, "<u4", offset=la.record_offset)
    rb = np.fromfile(lb.path, "<u4", offset=lb.record_offset)
    assert n == lb.n_records == rb.size
    assert_array_equal(ra, rb)
    ev2 = decode_t3(rb)
    ev1 = ev.copy()
    ev1["_pad"] = 0
    # split markers decode to one bit each; photons come back exactly
    assert_array_equal(ev2[ev2["kind"] == 0], ev1[ev1["kind"] == 0])
    assert EVENT_DTYPE == ev2.dtype
