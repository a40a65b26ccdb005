"""File readers: orientation and layout of .mat cell arrays, PicoQuant T3 files with and without
image markers, and one clear InputError for every kind of bad file."""

from __future__ import annotations

import struct

import numpy as np
import pytest
import scipy.io
from numpy.testing import assert_allclose, assert_array_equal

import reference as ref
from spdepth.acq.readers import read_photons, sniff_kind
from spdepth.acq.readers.picoquant import _PT3_HEAD, assign_pixels
from spdepth.recon.errors import InputError

MANNEQUIN = "fpi/mannequin_face_8ppp.mat"
TOWER = "longrange/tower_9km.mat"
PTU_V2 = "ptu/hydraharp_v20_t3.ptu"


# --------------------------------------------------------------------------------- .mat files

def _cell(rows):
    """A 2-D object array as scipy builds MATLAB cells, from nested lists of arrays."""
    out = np.empty((len(rows), len(rows[0])), dtype=object)
    for i, row in enumerate(rows):
        for j, v in enumerate(row):
            out[i, j] = v
    return out


def test_mat_orientation_rows_columns_and_empty_cells(tmp_path):
    # 2 x 3 so a transposed read cannot pass; column vectors, row vectors and empty cells mixed
    cells = _cell([
        [np.array([[10.0], [11.0], [12.0]]), np.zeros((0, 0)), np.array([[20.0, 21.0]])],
        [np.array([[30.0]]), np.array([[40.0, 41.0, 42.0, 43.0]]), np.array([[50.0], [51.0]])],
    ])
    path = tmp_path / "small.mat"
    scipy.io.savemat(path, {"Ts": cells})
    res = read_photons(path, time_unit_s=8e-12)
    store = res.store
    assert store.shape == (2, 3)
    assert res.meta["mat_var"] == "Ts" and res.is_image
    assert_array_equal(store.counts(), [[3, 0, 2], [1, 4, 2]])
    assert_array_equal(store.pixel(0, 0), [10, 11, 12])
    assert store.pixel(0, 1).size == 0
    assert_array_equal(store.pixel(0, 2), [20, 21])
    assert_array_equal(store.pixel(1, 1), [40, 41, 42, 43])  # detection order kept
    assert store.time_unit_s == 8e-12


@pytest.mark.parametrize("compress", [False, True])
def test_mat_fast_path_equals_scipy_for_every_element_type(tmp_path, compress):
    # the NumPy cell walk (read_cells_fast) against scipy's loadmat + cells_to_store: every numeric
    # element type, empty cells, rows and columns, on a 3 x 4 array (MATLAB's column-major cell
    # order against row-major pixels), compressed or not
    from spdepth.acq.readers.mat import cells_to_store, load_cells, read_cells_fast

    rng = np.random.default_rng(3)
    kinds = [np.float64, np.float32, np.uint16, np.int16, np.uint8, np.int8, np.int32, np.uint32,
             np.int64, np.uint64]
    rows = []
    for i in range(3):
        row = []
        for j in range(4):
            t = kinds[(4 * i + j) % len(kinds)]
            n = int(rng.integers(0, 6))
            v = rng.integers(0, 100, n).astype(t)
            row.append(np.zeros((0, 0)) if n == 0 else (v[:, None] if (i + j) % 2 else v[None, :]))
        rows.append(row)
    path = tmp_path / "types.mat"
    scipy.io.savemat(path, {"Ts": _cell(rows), "other": np.arange(3.0)}, do_compression=compress)
    fast = read_cells_fast(path, None, 8e-12)
    assert fast is not None, "the fast path declined a plain cell array of numeric vectors"
    name, store = fast
    _, cells = load_cells(path)
    slow = cells_to_store(cells, 8e-12)
    assert name == "Ts" and store.shape == slow.shape == (3, 4)
    assert_array_equal(store.offsets, slow.offsets)
    assert_array_equal(store.times, slow.times)
    assert store.times.dtype == np.float64
    times, offsets = ref.mat_cells(path, "Ts")
    assert_array_equal(store.offsets, offsets)
    assert_allclose(store.times, times, rtol=0, atol=0)


def test_mat_fast_path_declines_what_it_does_not_read(tmp_path):
    # a matrix cell, complex times and two cell arrays: the fast path says no, the scipy path
    # gives the message
    from spdepth.acq.readers.mat import read_cells_fast

    for i, cells in enumerate([_cell([[np.ones((2, 2)), np.ones((3, 1))]]),
                               _cell([[np.array([1 + 2j]), np.ones((3, 1))]])]):
        path = tmp_path / f"bad{i}.mat"
        scipy.io.savemat(path, {"Ts": cells})
        assert read_cells_fast(path, None, 8e-12) is None
    path = tmp_path / "two.mat"
    scipy.io.savemat(path, {"A": _cell([[np.ones(2)]]), "B": _cell([[np.ones(3)]])})
    assert read_cells_fast(path, None, 8e-12) is None
    assert read_cells_fast(path, "B", 8e-12)[1].n_photons == 3


@pytest.mark.parametrize("nbytes", [0x7FFFFFF8, 8, 12])
def test_mat_fast_path_declines_a_broken_cell_chain(tmp_path, nbytes):
    # a cell whose length runs past the variable, is too short for its own header, or is not padded
    # to 8 bytes: the walk says no instead of reading beside the cells, and the file is read by scipy
    # (which walks each cell's sub-elements by their own tags)
    from spdepth.acq.readers.mat import _top_level, cells_to_store, load_cells, read_cells_fast

    path = tmp_path / "chain.mat"
    scipy.io.savemat(path, {"Ts": _cell([[np.arange(3.0), np.arange(2.0)], [np.arange(4.0), np.ones(1)]])},
                     do_compression=False)
    raw = bytearray(path.read_bytes())
    (_name, _cls, _dims, _d, start), = _top_level(bytes(raw))
    first_cell = 128 + start                # uncompressed: the variable's element starts at byte 128
    assert raw[first_cell:first_cell + 4] == (14).to_bytes(4, "little")
    raw[first_cell + 4:first_cell + 8] = nbytes.to_bytes(4, "little")
    path.write_bytes(bytes(raw))
    assert read_cells_fast(path, None, 8e-12) is None
    store = read_photons(path, time_unit_s=8e-12).store
    assert_array_equal(store.times, cells_to_store(load_cells(path)[1], 8e-12).times)


def test_mannequin_matches_loadmat_cell_by_cell(shared_data):
    path = shared_data / MANNEQUIN
    res = read_photons(path, time_unit_s=8e-12)
    cells = scipy.io.loadmat(path)["Ts"]
    assert res.store.shape == cells.shape == (340, 340)
    counts = np.array([[c.size for c in row] for row in cells])
    assert_array_equal(res.store.counts(), counts)
    for r, c in [(0, 0), (3, 7), (170, 20), (339, 338), (100, 250)]:
        assert_array_equal(res.store.pixel(r, c), cells[r, c].ravel().astype(float))


def test_tower_row_vectors_in_ps(shared_data):
    path = shared_data / TOWER
    res = read_photons(path, time_unit_s=1e-12)
    cells = scipy.io.loadmat(path)["data_processed"]
    assert res.store.shape == (160, 160)
    assert res.meta["mat_var"] == "data_processed"  # mm, MM, sbr... are numeric, not cells
    r, c = next((i, j) for i in range(160) for j in range(160) if cells[i, j].shape[1] > 2)
    assert_array_equal(res.store.pixel(r, c), cells[r, c].ravel())
    assert 5.18e6 <= res.store.times.min() and res.store.times.max() <= 5.38e6


def test_mat_needs_time_unit(shared_data):
    with pytest.raises(InputError, match="time unit"):
        read_photons(shared_data / MANNEQUIN)


def test_mat_without_cell_variable(tmp_path):
    path = tmp_path / "numbers.mat"
    scipy.io.savemat(path, {"depth": np.ones((4, 4)), "sbr": 3.0})
    with pytest.raises(InputError, match=r"numbers\.mat.*no 2-D cell-array.*depth"):
        read_photons(path, time_unit_s=1e-12)


def test_mat_two_cell_variables_need_mat_var(tmp_path):
    a = _cell([[np.array([[1.0]]), np.array([[2.0]])]])
    b = _cell([[np.array([[5.0, 6.0]])]])
    path = tmp_path / "two.mat"
    scipy.io.savemat(path, {"first": a, "second": b})
    with pytest.raises(InputError, match=r"two\.mat.*several.*first, second.*--mat-var"):
        read_photons(path, time_unit_s=1e-12)
    res = read_photons(path, time_unit_s=1e-12, mat_var="second")
    assert res.store.shape == (1, 1)
    assert_array_equal(res.store.pixel(0, 0), [5, 6])
    with pytest.raises(InputError, match="no variable 'third'"):
        read_photons(path, time_unit_s=1e-12, mat_var="third")


def test_mat_cell_holding_matrix_or_text(tmp_path):
    path = tmp_path / "matrix.mat"
    scipy.io.savemat(path, {"Ts": _cell([[np.ones((2, 3))]])})
    with pytest.raises(InputError, match=r"cell \(1,1\).*matrix"):
        read_photons(path, time_unit_s=1e-12)
    path = tmp_path / "text.mat"
    scipy.io.savemat(path, {"Ts": _cell([[np.array(["abc"])]])})
    with pytest.raises(InputError, match=r"cell \(1,1\) holds text, not detection times"):
        read_photons(path, time_unit_s=1e-12)


def test_mat_all_cells_empty(tmp_path):
    path = tmp_path / "empty_cells.mat"
    scipy.io.savemat(path, {"Ts": _cell([[np.zeros((0, 0)), np.zeros((0, 0))]])})
    with pytest.raises(InputError, match="no detections"):
        read_photons(path, time_unit_s=1e-12)


def test_truncated_mat(shared_data, tmp_path):
    data = (shared_data / MANNEQUIN).read_bytes()
    path = tmp_path / "cut.mat"
    path.write_bytes(data[: len(data) // 3])
    with pytest.raises(InputError, match=r"cut\.mat: not a readable \.mat file"):
        read_photons(path, time_unit_s=8e-12)


# --------------------------------------------------------------------------- bad files of any kind

@pytest.mark.parametrize("name,content,message", [
    ("empty.ptu", b"", "file is empty"),
    ("empty.mat", b"", "file is empty"),
    ("notes.ptu", b"just some text, not a measurement\n" * 5, "not a .mat, PTU, HT3, PT3, .npy, .npz or HDF5"),
    ("magic_only.ptu", b"PQTTTR\0\0", "not a readable PTU file"),
])
def test_bad_files_are_named_in_one_line(tmp_path, name, content, message):
    path = tmp_path / name
    path.write_bytes(content)
    with pytest.raises(InputError) as info:
        read_photons(path, time_unit_s=1e-12)
    text = str(info.value)
    assert message in text and name in text and "\n" not in text


def test_missing_file_and_directory(tmp_path):
    with pytest.raises(InputError, match="no such file"):
        read_photons(tmp_path / "nope.ptu")
    with pytest.raises(InputError, match="is a directory"):
        sniff_kind(tmp_path)


# -------------------------------------------------------------------------------- PicoQuant files

def test_ptu_point_measurement(shared_data):
    res = read_photons(shared_data / PTU_V2)
    assert not res.is_image
    assert res.store.shape == (1, 1)
    assert res.store.n_photons == 77883  # as the data README and ptufile's header say
    assert_allclose(res.store.time_unit_s, 64e-12, rtol=1e-6)
    assert res.meta["photons_per_channel"] == {0: 45012, 1: 32871}
    assert any("point measurement" in n for n in res.notes)
    assert res.store.times.min() >= 0 and res.store.times.max() < 2**15


def test_ptu_channel_filter(shared_data):
    res = read_photons(shared_data / PTU_V2, channel=1)
    assert res.store.n_photons == 32871
    with pytest.raises(InputError, match="no photons on channel 5"):
        read_photons(shared_data / PTU_V2, channel=5)


def test_ptu_v1_records(shared_data):
    res = read_photons(shared_data / "ptu/hydraharp_v10_t3.ptu")
    assert res.store.n_photons == 94560
    assert_allclose(res.store.time_unit_s, 128e-12, rtol=1e-6)


def test_t2_file_is_refused(shared_data):
    with pytest.raises(InputError, match=r"picoharp_v30_t2\.ptu: a T2 file"):
        read_photons(shared_data / "ptu/picoharp_v30_t2.ptu")


def test_ht3_legacy_file(shared_data):
    res = read_photons(shared_data / "ptu/hydraharp_v20.ht3")
    assert res.kind == "ht3" and not res.is_image
    assert res.store.n_photons == 44141
    assert_allclose(res.store.time_unit_s, 16e-12)
    assert res.meta["sync_rate_hz"] == 998898


@pytest.mark.parametrize("keep", [3000, 5799])
def test_ptu_cut_inside_its_header_is_refused(shared_data, tmp_path, keep):
    path = tmp_path / "cut.ptu"
    path.write_bytes((shared_data / PTU_V2).read_bytes()[:keep])
    with pytest.raises(InputError, match=r"cut\.ptu"):
        read_photons(path)


@pytest.mark.parametrize("keep", [5801, 5800 + 4 * 1000, 5800 + 4 * 1000 + 3, 431196 - 4])
def test_truncated_ptu_reads_its_whole_records_with_one_note(shared_data, tmp_path, keep):
    # an acquisition cut short by another program: every whole record is read, as replay,
    # ptufile and tttrlib do, and one note says what the header promised and what was there
    import ptufile

    with ptufile.PtuFile(shared_data / PTU_V2) as full:
        decoded = full.decode_records()
    held = (keep - 5800) // 4
    path = tmp_path / "cut.ptu"
    path.write_bytes((shared_data / PTU_V2).read_bytes()[:keep])
    res = read_photons(path)
    truncated = [n for n in res.notes if "truncated" in n]
    assert len(truncated) == 1
    assert truncated[0].startswith("cut.ptu is truncated: its header promises 106,349 records, "
                                   f"the file holds {held:,} whole records")
    assert res.meta["records"] == held and res.meta["records_in_header"] == 106349
    assert res.store.n_photons == int(np.count_nonzero(decoded["channel"][:held] >= 0))
    assert_array_equal(np.sort(res.store.pixel(0, 0)),
                       np.sort(decoded["dtime"][:held][decoded["channel"][:held] >= 0]))


@pytest.mark.parametrize("keep", [100, 790])
def test_ht3_cut_inside_its_header_is_refused(shared_data, tmp_path, keep):
    path = tmp_path / "cut.ht3"
    path.write_bytes((shared_data / "ptu/hydraharp_v20.ht3").read_bytes()[:keep])
    with pytest.raises(InputError, match=r"cut\.ht3: truncated"):
        read_photons(path)


def test_truncated_ht3_reads_its_whole_records_with_one_note(shared_data, tmp_path):
    data = (shared_data / "ptu/hydraharp_v20.ht3").read_bytes()
    full = read_photons(shared_data / "ptu/hydraharp_v20.ht3")
    path = tmp_path / "cut.ht3"
    path.write_bytes(data[:-4 * 1000 - 2])      # 1,000 records and half of one gone
    res = read_photons(path)
    assert res.notes[0].startswith("cut.ht3 is truncated: its header promises 53,606 records, the "
                                   "file holds 52,605 whole records")
    assert res.meta["records"] == 52605 and res.meta["records_in_header"] == 53606
    assert 0 < full.store.n_photons - res.store.n_photons <= 1001


def test_ptu_image_from_ptufile_writer(tmp_path, rng):
    import ptufile

    hist = rng.poisson(0.4, size=(3, 5, 7, 1, 16)).astype(np.uint8)  # T Y X C H
    path = tmp_path / "image.ptu"
    ptufile.imwrite(path, hist, global_resolution=1e-7, tcspc_resolution=4e-11)
    res = read_photons(path)
    store = res.store
    assert res.is_image and store.shape == (5, 7)
    assert res.meta["frames"] == 3 and res.meta["lines"] == 15
    assert_array_equal(store.counts(), hist.sum(axis=(0, 3, 4)))
    assert_allclose(store.time_unit_s, 4e-11)
    for r in range(5):
        for c in range(7):
            assert_array_equal(np.bincount(store.pixel(r, c).astype(int), minlength=16),
                               hist[:, r, c, 0, :].sum(axis=0))


def test_image_header_without_markers_is_an_error(tmp_path, rng):
    import ptufile

    hist = rng.poisson(0.4, size=(2, 3, 1, 8)).astype(np.uint8)
    path = tmp_path / "image.ptu"
    ptufile.imwrite(path, hist, global_resolution=1e-7, tcspc_resolution=4e-11)
    with ptufile.PtuFile(path) as f:
        start = f.tags["ImgHdr_LineStart"]
    # rewrite the header so it names a marker that never fires: tag values are int64 after the
    # 32-byte tag identifier, 4-byte index and 4-byte type of the ImgHdr_LineStart entry
    data = bytearray(path.read_bytes())
    pos = data.find(b"ImgHdr_LineStart")
    struct.pack_into("<q", data, pos + 40, 4 if start != 4 else 5)
    path.write_bytes(bytes(data))
    with pytest.raises(InputError, match="no such marker"):
        read_photons(path)


# ------------------------------------------------------------------ marker kernel vs reference

def assign_reference(sync, channel, marker, pix_x, start_mask, stop_mask, frame_mask, bidir, keep):
    """Plain NumPy: walk the (few) marker records in Python, place each line's photons at once."""
    row = np.full(sync.size, -1, np.int64)
    col = np.full(sync.size, -1, np.int64)
    y, open_at, lines = 0, None, 0
    photon = (channel >= 0) & ((channel == keep) if keep >= 0 else True)
    for i in np.flatnonzero((channel < 0) & (marker != 0)):
        m = int(marker[i])
        if m & stop_mask and open_at is not None:
            t0 = int(sync[open_at])
            span = int(sync[i]) - t0
            if span > 0:
                idx = np.arange(open_at + 1, i)
                idx = idx[photon[idx]]
                x = np.minimum((sync[idx].astype(np.int64) - t0) * pix_x // span, pix_x - 1)
                if bidir and y % 2:
                    x = pix_x - 1 - x
                row[idx], col[idx] = y, x
            y += 1
            lines += 1
            open_at = None
        if frame_mask and m & frame_mask:
            y, open_at = 0, None
        if m & start_mask:
            open_at = i
    return row, col, lines


@pytest.mark.parametrize("frame,bidir,keep", [(0, False, -1), (4, False, -1), (4, True, -1),
                                              (0, True, 1)])
def test_assign_pixels_matches_reference(rng, frame, bidir, keep):
    # a synthetic stream: frames of lines, photons everywhere (also between lines), some markers
    # firing together (stop of one line with start of the next), overflow records sprinkled in
    rows_per_frame, pix_x, n_frames = 6, 9, 3
    recs = []
    t = 0
    for f in range(n_frames):
        for y in range(rows_per_frame):
            m = 1  # line start is marker 1
            if y == 0 and frame:
                m |= 1 << (frame - 1)
            recs.append((t, -1, m))
            line_len = int(rng.integers(50, 80))
            for tt in np.sort(rng.integers(t, t + line_len, size=int(rng.integers(0, 30)))):
                recs.append((int(tt), int(rng.integers(0, 3)), 0))
            t += line_len
            recs.append((t, -1, 2))  # line stop is marker 2
            if rng.random() < 0.3:
                recs.append((t + 1, -1, 0))  # overflow record
            for tt in range(int(rng.integers(0, 3))):
                recs.append((t + 2, int(rng.integers(0, 3)), 0))  # flyback photons: no pixel
            t += 5
    sync = np.array([r[0] for r in recs], dtype=np.uint64)
    channel = np.array([r[1] for r in recs], dtype=np.int8)
    marker = np.array([r[2] for r in recs], dtype=np.uint8)
    row, col, lines, max_lines, frames = assign_pixels(
        sync, channel, marker, pix_x=pix_x, line_start=1, line_stop=2, frame=frame,
        bidirectional=bidir, keep_channel=keep)
    ref_row, ref_col, ref_lines = assign_reference(sync, channel, marker, pix_x, 1, 2,
                                                   (1 << (frame - 1)) if frame else 0, bidir, keep)
    assert_array_equal(row, ref_row)
    assert_array_equal(col, ref_col)
    assert lines == ref_lines == rows_per_frame * n_frames
    assert max_lines == (rows_per_frame if frame else rows_per_frame * n_frames)
    assert frames == (n_frames if frame else 0)
    assert col.max() == pix_x - 1 and row[channel < 0].max() == -1


def test_assign_pixels_rejects_bad_marker_numbers():
    z = np.zeros(1, np.uint64)
    with pytest.raises(InputError, match="line start marker number"):
        assign_pixels(z, np.zeros(1, np.int8), np.zeros(1, np.uint8), pix_x=4, line_start=0, line_stop=2)


# ----------------------------------------------------------------------------------- PT3 files

def _pt3_bytes(records: np.ndarray, resolution_ns: float, n_records: int | None = None) -> bytes:
    values = []
    for name, fmt in _PT3_HEAD:
        count = int(fmt[:-1]) if fmt[:-1].isdigit() and fmt[-1] != "s" else 1
        default = {"Ident": b"PicoHarp 300", "FormatVersion": b"2.0", "BitsPerRecord": 32,
                   "MeasurementMode": 3, "Resolution_ns": resolution_ns, "SyncRate": 40_000_000,
                   "nRecords": records.size if n_records is None else n_records,
                   "ImgHdrSize": 0}.get(name, b"" if fmt.endswith("s") else 0)
        values.extend([default] * count if count > 1 else [default])
    head = struct.pack("<" + "".join(f for _, f in _PT3_HEAD), *values)
    return head + records.astype("<u4").tobytes()


def test_pt3_point_measurement(tmp_path):
    # PicoHarp T3 records: channel:4 | dtime:12 | nsync:16; channel 15 with dtime 0 = overflow
    dtimes = np.array([100, 2000, 4095, 7])
    recs = np.array([(1 << 28) | (d << 16) | (5 + i) for i, d in enumerate(dtimes)]
                    + [15 << 28], dtype=np.uint32)
    path = tmp_path / "point.pt3"
    path.write_bytes(_pt3_bytes(recs, 0.004))
    res = read_photons(path)
    assert res.kind == "pt3" and res.store.shape == (1, 1)
    assert_array_equal(res.store.pixel(0, 0), dtimes)
    assert_allclose(res.store.time_unit_s, 4e-12)
    path.write_bytes(_pt3_bytes(recs, 0.004, n_records=10))       # 5 records there of 10
    res = read_photons(path)
    assert res.notes[0].startswith("point.pt3 is truncated: its header promises 10 records, the "
                                   "file holds 5 whole records")
    assert_array_equal(res.store.pixel(0, 0), dtimes)


def test_picoquant_histogram_files_are_named_as_such(tmp_path):
    # a .phd shares the PT3 header with MeasurementMode 0; a .phu starts with PQHISTO
    fields = [f for _, f in _PT3_HEAD]
    at = struct.calcsize("<" + "".join(fields[:[n for n, _ in _PT3_HEAD].index("MeasurementMode")]))
    data = bytearray(_pt3_bytes(np.zeros(4, np.uint32), 0.004))
    data[at:at + 4] = struct.pack("<i", 0)
    phd = tmp_path / "hist.phd"
    phd.write_bytes(bytes(data))
    with pytest.raises(InputError, match=r"hist\.phd: a PicoQuant histogram file \(\.phd/\.hhd"):
        read_photons(phd)
    phu = tmp_path / "hist.phu"
    phu.write_bytes(b"PQHISTO\0" + b"\0" * 200)
    with pytest.raises(InputError, match=r"hist\.phu: a PicoQuant histogram file \(\.phu\)"):
        read_photons(phu)
