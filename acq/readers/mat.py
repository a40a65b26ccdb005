"""First-photon-imaging .mat files: a 2-D MATLAB cell array, one cell per pixel, each cell a vector
of detection times in detection order.

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


def _cell_variables(contents: dict) -> dict[str, np.ndarray]:
    return {name: value for name, value in contents.items()
            if not name.startswith("__") and isinstance(value, np.ndarray)
            and value.dtype == object and value.ndim == 2}


def load_cells(path: str | Path, var: str | None = None) -> tuple[str, np.ndarray]:
    """Load the file's cell-array variable (or ``var``) as a 2-D object array ``cells[row, col]``."""
    import scipy.io

    path = Path(path)
    try:
        contents = scipy.io.loadmat(path, squeeze_me=False, struct_as_record=True)
    except NotImplementedError:
        raise InputError(f"{path}: MATLAB v7.3 (HDF5) file; save it with -v7 to read it here") from None
    except FileNotFoundError:
        raise InputError(f"{path}: no such file") from None
    except Exception as exc:  # scipy raises many kinds for damaged files (ValueError, TypeError, zlib.error, ...)
        raise InputError(f"{path}: not a readable .mat file ({type(exc).__name__}: {exc})") from None
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


#: byte size of each numeric element type (miINT8=1 ... miUINT64=13); 0: not numeric
_MI_ITEMSIZE = np.array([0, 1, 1, 2, 2, 4, 4, 4, 0, 8, 0, 0, 8, 8], np.int64)
#: mxClass codes of numeric arrays (mxDOUBLE_CLASS=6 ... mxUINT64_CLASS=15), mxSINGLE_CLASS
_MX_NUMERIC_LO, _MX_NUMERIC_HI, _MX_SINGLE = 6, 15, 7


def cell_index(d: bytes, start: int, n_cells: int) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """Walk the ``n_cells`` consecutive miMATRIX elements of ``d`` (the decompressed variable) from
    byte ``start``: (byte offset of each cell's real data, its element count (0: empty), its data
    element type), or None where a cell is not a real numeric vector this walk reads (the caller
    then reads the file with scipy, which names the problem).

    Level-5 layout (MATLAB's "MAT-File Format", little endian): a data element is an 8-byte tag
    (``type: u32 | nbytes: u32``), its data, padding to 8 bytes; a "small" element packs
    ``nbytes: u16 | type: u16`` into the first 4 bytes and up to 4 data bytes into the next 4. A
    cell is a miMATRIX (14) element: array flags (miUINT32, class in the low byte, complex bit
    0x800), dimensions (miINT32), a name (miINT8, empty) and the real part, whose element type may
    be narrower than its class (MATLAB stores integer-valued doubles as miUINT16 and the like).

    Only the chain of element sizes is walked in Python (one word per cell); every field is then
    read for all cells at once with NumPy. No numba here on purpose: the read then needs no
    compiled code, so in a new process it runs while another thread loads the estimator's kernels
    (NumPy releases the GIL in its loops; numba's loading holds it)."""
    if start % 8 or len(d) < start + 8 or sys.byteorder != "little":
        return None
    n_words = len(d) // 4
    w = np.frombuffer(d, "<u4", count=n_words)            # every element starts 8-byte aligned
    words = memoryview(d)[:4 * n_words].cast("I")         # the same words, fast one at a time
    size = len(d)
    starts = [0] * n_cells
    o = start
    for c in range(n_cells):
        if o + 8 > size:
            return None
        starts[c] = o
        o += 8 + words[(o >> 2) + 1]
    if o > size:
        return None
    s = np.array(starts, np.int64) >> 2                   # word index of each cell's tag
    end = (s << 2) + 8 + w[s + 1]                         # byte after each cell
    last = w.size - 1

    def u32(word_index):                                  # past the buffer (an empty last cell): 0
        return np.where(word_index <= last, w[np.minimum(word_index, last)], 0).astype(np.int64)

    if np.any(w[s] != 14):                                # miMATRIX
        return None
    full = w[s + 1] > 0                                   # an empty cell may be a bare tag
    flags = u32(s + 4)
    cls = flags & 0xFF
    ndb = u32(s + 7)
    dims = np.stack([u32(s + 8), u32(s + 9)]).astype(np.uint32).view(np.int32).astype(np.int64)
    ok = ((u32(s + 2) == 6) & (u32(s + 3) == 8)       # array flags: miUINT32, 8 bytes
          & (cls >= _MX_NUMERIC_LO) & (cls <= _MX_NUMERIC_HI) & ((flags & 0x800) == 0)
          & (u32(s + 6) == 5) & (ndb == 8)            # dimensions: miINT32, two of them
          & np.all(dims >= 0, axis=0) & (np.sum(dims > 1, axis=0) <= 1))     # a vector
    numel = dims[0] * dims[1]
    # the name: a small element (8 bytes) or a tagged one; then the real part, if any
    p = (s << 2) + 40
    name_tag = u32(p >> 2)
    p = np.where(name_tag >> 16, p + 8, p + 8 + (u32((p >> 2) + 1) + 7) // 8 * 8)
    no_data = full & (p == end)
    if np.any(full & ~ok) or np.any(full & (p > end)) or np.any(no_data & (numel != 0)):
        return None
    has = full & (p < end)
    t = u32(p >> 2)
    small = (t >> 16) != 0
    typ = np.where(small, t & 0xFFFF, t)
    dnb = np.where(small, t >> 16, u32((p >> 2) + 1))
    doff = np.where(small, p + 4, p + 8)
    typ = np.where(has, typ, 0)
    isz = _MI_ITEMSIZE[np.clip(typ, 0, _MI_ITEMSIZE.size - 1)] * (typ < _MI_ITEMSIZE.size)
    bad = has & ((isz == 0)
                 # single class from wide integers: scipy rounds to float32
                 | ((cls == _MX_SINGLE) & ((typ == 5) | (typ == 6) | (typ >= 12)))
                 | (dnb != numel * isz) | (doff + dnb > end) | (doff % np.maximum(isz, 1) != 0))
    if np.any(bad):
        return None
    return np.where(has, doff, 0), np.where(has, numel, 0), typ


def read_cells_fast(path: Path, var: str | None, time_unit_s: float) -> tuple[str, PhotonStore] | None:
    """The cell-array variable of a level-5 .mat file as a PhotonStore, by one walk over its
    elements (:func:`cell_index`) and one NumPy gather of the times; the same store
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
    index = cell_index(d, start, n_cells)
    if index is None:
        return None
    off, cnt, typ = index
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
        return ReadResult(store=store, path=str(path), kind="mat", is_image=True,
                          meta={"mat_var": name, "time_unit_s": time_unit_s})
    name, cells = load_cells(path, var)
    if cells.size == 0:
        raise InputError(f"{path}: variable {name!r} is an empty cell array")
    store = cells_to_store(cells, time_unit_s, source=f"{path}: variable {name!r}")
    if store.n_photons == 0:
        raise InputError(f"{path}: variable {name!r} holds no detections")
    return ReadResult(store=store, path=str(path), kind="mat", is_image=True,
                      meta={"mat_var": name, "time_unit_s": time_unit_s})
