"""First-photon-imaging .mat files: a 2-D MATLAB cell array, one cell per pixel, each cell a vector
of detection times in detection order. A .mat file holding a numeric 3-D / 4-D array instead (a
histogram cube) is read by :mod:`acq.readers.cube`.

MATLAB cell ``(i, j)`` is image row ``i``, column ``j``; scipy's ``loadmat`` keeps that as
``cells[i, j]``, so the row-major flat pixel index is simply ``cells.ravel(order="C")``. Cells can
be empty (``0 x 0``), columns (``n x 1``, the fpi files) or rows (``1 x n``, the long-range file).
"""

from __future__ import annotations

import struct
import sys
import zlib
from pathlib import Path

import numpy as np

from spdepth.acq.readers.common import ReadResult
from spdepth.recon.errors import InputError
from spdepth.recon.photons import PhotonStore


def _describe(value) -> str:
    shape = "x".join(str(n) for n in np.shape(value)) or "scalar"
    dtype = "cell" if getattr(value, "dtype", None) == object else getattr(value, "dtype", type(value).__name__)
    return f"{shape} {dtype}"


def _kind_words(a: np.ndarray) -> str:
    """What a cell holds, in MATLAB's words."""
    return {"V": "a struct", "U": "text", "S": "text", "c": "complex numbers", "b": "logicals",
            "O": "a cell array"}.get(a.dtype.kind, f"{a.dtype} values")


def _cell_variables(contents: dict) -> dict[str, np.ndarray]:
    return {name: value for name, value in contents.items()
            if not name.startswith("__") and isinstance(value, np.ndarray)
            and value.dtype == object and value.ndim == 2}


class MatlabHdf5(Exception):
    """The file is MATLAB v7.3, which is HDF5 (scipy's ``loadmat`` reads level 5 only): its numeric
    arrays are read by :func:`acq.readers.cube.read_hdf5`."""


def load_contents(path: Path) -> dict:
    """Every variable of a level-5 .mat file (scipy's ``loadmat``); :class:`MatlabHdf5` for a v7.3
    file."""
    import scipy.io

    try:
        return scipy.io.loadmat(path, squeeze_me=False, struct_as_record=True)
    except NotImplementedError:       # scipy's word for "v7.3: use HDF5 reader"
        raise MatlabHdf5(str(path)) from None
    except FileNotFoundError:
        raise InputError(f"{path}: no such file") from None
    except Exception as exc:  # scipy raises many kinds for damaged files (ValueError, TypeError, zlib.error, ...)
        raise InputError(f"{path}: not a readable .mat file ({type(exc).__name__}: {exc})") from None


def load_cells(path: str | Path, var: str | None = None, contents: dict | None = None) -> tuple[str, np.ndarray]:
    """Load the file's cell-array variable (or ``var``) as a 2-D object array ``cells[row, col]``."""
    path = Path(path)
    if contents is None:
        try:
            contents = load_contents(path)
        except MatlabHdf5:
            raise InputError(f"{path}: MATLAB v7.3 (HDF5) file; save it with -v7 to read it here") from None
    cells = _cell_variables(contents)
    others = ", ".join(f"{k} ({_describe(v)})" for k, v in contents.items() if not k.startswith("__"))
    if var is not None:
        if var not in contents or var.startswith("__"):
            raise InputError(f"{path}: no variable {var!r}; the file holds: {others or 'nothing'}")
        if var not in cells:
            raise InputError(f"{path}: variable {var!r} is {_describe(contents[var])}, not a 2-D cell "
                             f"array of detection times")
        return var, cells[var]
    if not cells:
        raise InputError(f"{path}: no 2-D cell-array variable of detection times; the file holds: "
                         f"{others or 'nothing'}")
    if len(cells) > 1:
        raise InputError(f"{path}: several cell-array variables ({', '.join(sorted(cells))}); "
                         f"choose one with --mat-var")
    (name, value), = cells.items()
    return name, value


def cells_to_store(cells: np.ndarray, time_unit_s: float, *, source: str = "cell array") -> PhotonStore:
    """Flatten a 2-D object array of per-pixel time vectors into a PhotonStore (row-major pixels,
    detection order kept within each pixel).

    One pass over the cells collects sizes and checks they are numeric vectors; then a single
    ``np.concatenate`` builds the times (a 340 x 340 file takes tens of milliseconds)."""
    h, w = cells.shape
    flat = cells.ravel(order="C")
    counts = np.empty(flat.size, dtype=np.int64)
    for p, cell in enumerate(flat):
        if not isinstance(cell, np.ndarray):
            raise InputError(f"{source}: cell ({p // w + 1},{p % w + 1}) holds a {type(cell).__name__}, "
                             f"not a vector of times")
        if cell.ndim > 2 or (cell.ndim == 2 and min(cell.shape) > 1):
            raise InputError(f"{source}: cell ({p // w + 1},{p % w + 1}) is a {_describe(cell)} matrix, "
                             f"not a vector of detection times")
        if cell.size and cell.dtype.kind not in "uif":     # a struct, text, complex, logical, cell
            raise InputError(f"{source}: cell ({p // w + 1},{p % w + 1}) holds {_kind_words(cell)}, "
                             f"not detection times")
        counts[p] = cell.size
    offsets = np.zeros(flat.size + 1, dtype=np.int64)
    np.cumsum(counts, out=offsets[1:])
    nonempty = [c.ravel() for c in flat if c.size]
    if nonempty:
        times = np.concatenate(nonempty)
        if times.dtype.kind not in "uif":
            raise InputError(f"{source}: cells hold {times.dtype} values, not numbers")
        times = times.astype(np.float64, copy=False)
        if not np.all(np.isfinite(times)):
            raise InputError(f"{source}: {int(np.sum(~np.isfinite(times)))} detection times are NaN or infinite")
    else:
        times = np.zeros(0)
    return PhotonStore(times, offsets, (h, w), time_unit_s)


#: numpy dtype of each level-5 numeric element type (little endian)
_MI_DTYPE = {1: "<i1", 2: "<u1", 3: "<i2", 4: "<u2", 5: "<i4", 6: "<u4", 7: "<f4", 9: "<f8", 12: "<i8",
             13: "<u8"}
#: byte size of each numeric element type (miINT8=1 ... miUINT64=13); 0: not numeric
_MI_ITEMSIZE = np.array([0, 1, 1, 2, 2, 4, 4, 4, 0, 8, 0, 0, 8, 8], np.int64)
#: miMATRIX, miINT32, miUINT32: the element types of a cell, its dimensions and its array flags
_MI_MATRIX, _MI_INT32, _MI_UINT32 = 14, 5, 6
#: mxClass codes of numeric arrays (mxDOUBLE_CLASS=6 ... mxUINT64_CLASS=15) and mxSINGLE_CLASS
_MX_NUMERIC_LO, _MX_NUMERIC_HI, _MX_SINGLE = 6, 15, 7


def _top_level(raw: bytes):
    """The variables of a little-endian level-5 file: (name, mxClass, dims, element bytes, offset of
    the first byte after the name) each; None when the file is not one this fast path reads."""
    if len(raw) < 128 or raw[124:128] != b"\x00\x01IM":
        return None
    out = []
    o = 128
    while o + 8 <= len(raw):
        t, n = struct.unpack_from("<II", raw, o)
        if t == 15:                         # miCOMPRESSED: one zlib-compressed element
            d = zlib.decompress(raw[o + 8:o + 8 + n])
            o += 8 + n
        elif t == 14:
            d = raw[o:o + 8 + n]
            o += 8 + n + (-n) % 8
        else:
            return None
        if len(d) < 40 or struct.unpack_from("<I", d, 0)[0] != 14:
            return None
        if struct.unpack_from("<II", d, 8) != (6, 8):
            return None
        cls = struct.unpack_from("<I", d, 16)[0] & 0xFF
        p = 24
        t, ndb = struct.unpack_from("<II", d, p)
        if t != 5:
            return None
        dims = struct.unpack_from(f"<{ndb // 4}i", d, p + 8)
        p += 8 + ndb + (-ndb) % 8
        t = struct.unpack_from("<I", d, p)[0]
        if t >> 16:
            nn = t >> 16
            name = d[p + 4:p + 4 + nn].decode("ascii", "replace")
            p += 8
        else:
            nn = struct.unpack_from("<I", d, p + 4)[0]
            name = d[p + 8:p + 8 + nn].decode("ascii", "replace")
            p += 8 + nn + (-nn) % 8
        out.append((name, cls, dims, d, p))
    return out


def _cell_elements(d: bytes, start: int, n_cells: int):
    """Where the data of each of ``n_cells`` consecutive cells of the decompressed variable ``d``
    lie, from byte ``start``: (byte offset, element count, element type) per cell in MATLAB's
    order (count and type 0 for an empty cell), or None where a cell is not a real numeric vector
    this walk reads (the caller then reads the file with scipy, which names the problem).

    Level-5 layout (MATLAB's "MAT-File Format", little endian): a data element is an 8-byte tag
    (``type: u32 | nbytes: u32``), its data, padding to 8 bytes; a "small" element packs
    ``nbytes: u16 | type: u16`` into the first 4 bytes and up to 4 data bytes into the next 4. A
    cell is a ``miMATRIX`` element holding array flags (``miUINT32``: class in the low byte,
    complex bit 0x800), two dimensions (``miINT32``), a name (``miINT8``, empty here) and the real
    part, whose element type may be narrower than its class (MATLAB stores integer-valued doubles
    as ``miUINT16`` and the like).

    Only the chain of cells is walked in Python (each cell's start is the previous one's end: 0.03 s
    for the 115,600 cells of a 340 x 340 file); every field is then read and checked for all cells
    at once. Plain NumPy, no compiled kernel: reading a file in a new process does not pay numba's
    once-per-process set-up (its first compiled call costs over half a second); the estimator's
    first kernel does."""
    if start % 8 or sys.byteorder != "little":
        return None
    # the chain, in 4-byte words (elements are padded to 8 bytes; checked below)
    words = memoryview(d)[:len(d) // 4 * 4].cast("I")
    at = [0] * n_cells
    o = start >> 2
    try:
        for c in range(n_cells):
            at[c] = o
            o += 2 + (words[o + 1] >> 2)
    except IndexError:
        return None
    u32 = np.frombuffer(d, "<u4", count=len(d) // 4)
    i32 = u32.view("<i4")

    def word(byte_at, signed=False):
        return (i32 if signed else u32)[byte_at >> 2].astype(np.int64)

    o = np.array(at, np.int64) << 2
    if o[-1] + 8 > len(d):
        return None
    nb = word(o + 4)
    end = o + 8 + nb
    if np.any(word(o) != _MI_MATRIX) or np.any(nb % 8) or end[-1] > len(d):
        return None
    # cells with content (an empty cell may be a bare tag): flags, dimensions and a name take 40 bytes
    cell = np.flatnonzero(nb > 0)
    p = o[cell] + 8
    if np.any(nb[cell] < 40) or np.any(word(p) != _MI_UINT32) or np.any(word(p + 4) != 8):
        return None
    flags = word(p + 8)
    cls = flags & 0xFF
    if np.any((cls < _MX_NUMERIC_LO) | (cls > _MX_NUMERIC_HI) | (flags & 0x800 != 0)):
        return None
    p += 16
    if np.any(word(p) != _MI_INT32) or np.any(word(p + 4) != 8):
        return None
    rows, cols = word(p + 8, signed=True), word(p + 12, signed=True)
    if np.any((rows < 0) | (cols < 0) | ((rows > 1) & (cols > 1))):
        return None
    numel = rows * cols
    p += 16
    tag = word(p)
    small = (tag >> 16) != 0
    p += np.where(small, 8, 8 + (word(p + 4) + 7) // 8 * 8)
    e = end[cell]
    # no data element: an empty array
    bare = p == e
    if np.any(p > e) or np.any(bare & (numel != 0)) or np.any(~bare & (p + 8 > e)):
        return None
    data = ~bare
    cell, p, e, numel, cls = cell[data], p[data], e[data], numel[data], cls[data]
    tag = word(p)
    small = (tag >> 16) != 0
    typ = np.where(small, tag & 0xFFFF, tag)
    nbytes = np.where(small, tag >> 16, word(p + 4))
    at = p + np.where(small, 4, 8)
    if np.any((typ <= 0) | (typ >= _MI_ITEMSIZE.size)):
        return None
    size = _MI_ITEMSIZE[typ]
    # single class from wide integers: scipy rounds them to float32, so leave those to it
    wide = (typ == 5) | (typ == 6) | (typ >= 12)
    if (np.any(size == 0) or np.any((cls == _MX_SINGLE) & wide) or np.any(nbytes != numel * size)
            or np.any(at + nbytes > e) or np.any(at % size)):
        return None
    off = np.zeros(n_cells, np.int64)
    cnt = np.zeros(n_cells, np.int64)
    types = np.zeros(n_cells, np.int64)
    off[cell], cnt[cell], types[cell] = at, numel, typ
    return off, cnt, types


def read_cells_fast(path: Path, var: str | None, time_unit_s: float) -> tuple[str, PhotonStore] | None:
    """The cell-array variable of a level-5 .mat file as a PhotonStore, by one walk over its
    elements (:func:`_cell_elements`) and one NumPy gather of the times; the same store
    :func:`load_cells` + :func:`cells_to_store` make (row-major pixels, detection order kept).
    None whenever the file holds anything this path does not read (big endian, v7.3, several or
    no cell arrays without ``var``, a cell that is not a real numeric vector, NaN times ...): the
    caller then reads it with scipy, which names the problem."""
    try:
        raw = path.read_bytes()
        top = _top_level(raw)
    except (OSError, zlib.error, struct.error, ValueError):
        return None
    if not top:
        return None
    cells = {name: v for name, *v in top if v[0] == 1 and len(v[1]) == 2}
    if var is not None:
        if var not in cells:
            return None
        name = var
    elif len(cells) == 1:
        (name,) = cells
    else:
        return None
    _cls, (h, w), d, start = cells[name]
    n_cells = h * w
    if n_cells == 0:
        return None
    walked = _cell_elements(d, start, n_cells)
    if walked is None:
        return None
    off, cnt, typ = walked
    # MATLAB's cells run down the columns; pixels run along the rows
    c = np.arange(n_cells)
    pix = (c % h) * w + c // h
    counts = np.empty(n_cells, np.int64)
    counts[pix] = cnt
    offsets = np.zeros(n_cells + 1, np.int64)
    np.cumsum(counts, out=offsets[1:])
    times = np.empty(int(offsets[-1]), np.float64)
    dst = offsets[pix]
    for t in np.unique(typ[cnt > 0]):
        sel = (typ == t) & (cnt > 0)
        n = cnt[sel]
        isz = int(_MI_ITEMSIZE[t])
        view = np.frombuffer(d, dtype=_MI_DTYPE[int(t)], count=len(d) // isz)
        k = np.arange(int(n.sum())) - np.repeat(np.cumsum(n) - n, n)
        times[np.repeat(dst[sel], n) + k] = view[np.repeat(off[sel] // isz, n) + k]
    if times.size == 0 or not np.all(np.isfinite(times)):
        return None
    return name, PhotonStore(times, offsets, (h, w), time_unit_s)


MAX_TIME_S = 1.0
"""Latest detection time after the laser pulse a file may hold: TCSPC times lie within a laser
period (a 150 km range is 1 ms). Later ones are not times after a pulse (absolute timestamps,
or a wrong time unit), and would become a window of 1e300 bins or a depth of 1e300 m."""


def _check_times(path: Path, name: str, store: PhotonStore) -> None:
    """Refuse times more than MAX_TIME_S from the laser pulse, either side (a time before it
    is an offset a calibration may leave; a second is none)."""
    if not store.n_photons:
        return
    lo, hi = float(np.min(store.times)), float(np.max(store.times))
    t = hi if abs(hi) >= abs(lo) else lo
    if abs(t) * store.time_unit_s > MAX_TIME_S:
        raise InputError(f"{path}: variable {name!r}: detection times reach {t:.4g} units "
                         f"({t * store.time_unit_s:.3g} s at {store.time_unit_s * 1e12:g} ps each), "
                         f"more than {MAX_TIME_S:g} s from the laser pulse: not TCSPC times, or "
                         f"the wrong --time-unit-ps")


def read_mat(path: str | Path, *, time_unit_s: float | None, var: str | None = None) -> ReadResult:
    """Read a first-photon-imaging .mat file.

    time_unit_s: the size of one unit of the stored times (8e-12 for the fpi files, 1e-12 for the
                 long-range file); .mat files do not record it, so it is required.
    var:         the cell-array variable, needed only when the file holds several.
    """
    path = Path(path)
    if time_unit_s is None:
        raise InputError(f"{path}: a .mat file does not record its time unit; give it "
                         f"(--time-unit-ps 8 for first-photon-imaging files, 1 for times in ps)")
    fast = read_cells_fast(path, var, time_unit_s)
    if fast is not None:
        name, store = fast
        _check_times(path, name, store)
        return ReadResult(store=store, path=str(path), kind="mat", is_image=True,
                          meta={"mat_var": name, "time_unit_s": time_unit_s})
    try:
        contents = load_contents(path)
    except MatlabHdf5:
        # v7.3 is HDF5: only its numeric arrays (a cube) are read (cell arrays there are references)
        from spdepth.acq.readers.cube import read_hdf5

        return read_hdf5(path, time_unit_s=time_unit_s, var=var, matlab=True)
    from spdepth.acq.readers.cube import is_cube, read_mat_cube

    wanted = contents.get(var) if var is not None else None
    if (wanted is not None and is_cube(wanted)) or (
            var is None and not _cell_variables(contents)
            and any(is_cube(v) for k, v in contents.items() if not k.startswith("__"))):
        return read_mat_cube(path, contents, var, time_unit_s)
    name, cells = load_cells(path, var, contents)
    if cells.size == 0:
        raise InputError(f"{path}: variable {name!r} is an empty cell array")
    store = cells_to_store(cells, time_unit_s, source=f"{path}: variable {name!r}")
    if store.n_photons == 0:
        raise InputError(f"{path}: variable {name!r} holds no detections")
    _check_times(path, name, store)
    return ReadResult(store=store, path=str(path), kind="mat", is_image=True,
                      meta={"mat_var": name, "time_unit_s": time_unit_s})
