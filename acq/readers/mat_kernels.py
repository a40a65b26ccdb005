"""Numba kernel of the .mat reader (:mod:`acq.readers.mat`): the walk over a MATLAB level-5 cell
array's elements, which scipy's ``loadmat`` does cell by cell in Python objects (over a second for a
340 x 340 file). Plain arrays in, one output row per cell; validation, decompression and the
gathering of the times happen in :mod:`acq.readers.mat`.

Level-5 layout (MATLAB's "MAT-File Format", little endian): a data element is an 8-byte tag
(``type: u32 | nbytes: u32``), its data, padding to 8 bytes; a "small" element packs
``nbytes: u16 | type: u16`` into the first 4 bytes and up to 4 data bytes into the next 4. A cell
of a cell array is a ``miMATRIX`` (type 14) element holding array flags (``miUINT32``, class in the
low byte, complex bit 0x800), dimensions (``miINT32``), a name (``miINT8``, empty here) and the real
part, whose element type may be narrower than its class (MATLAB stores integer-valued doubles as
``miUINT16`` and the like).
"""

from __future__ import annotations

import numpy as np
from numba import njit

#: miMATRIX data element type
MI_MATRIX = 14
#: byte size of each numeric element type (miINT8=1 ... miUINT64=13); 0: not numeric
MI_ITEMSIZE = np.array([0, 1, 1, 2, 2, 4, 4, 4, 0, 8, 0, 0, 8, 8], np.int64)
#: mxClass codes of numeric arrays (mxDOUBLE_CLASS=6 ... mxUINT64_CLASS=15)
MX_NUMERIC_LO, MX_NUMERIC_HI = 6, 15


@njit(cache=True, nogil=True, inline="always")
def _u32(buf, o):
    return (np.int64(buf[o]) | (np.int64(buf[o + 1]) << 8) | (np.int64(buf[o + 2]) << 16)
            | (np.int64(buf[o + 3]) << 24))


@njit(cache=True, nogil=True, inline="always")
def _i32(buf, o):
    v = _u32(buf, o)
    return v - (np.int64(1) << 32) if v >= (np.int64(1) << 31) else v


@njit(cache=True, nogil=True)
def cell_index(buf, start, n_cells, itemsize, out_off, out_n, out_type):
    """Walk ``n_cells`` consecutive miMATRIX elements of ``buf`` (uint8, the decompressed variable)
    from byte ``start``; for cell c write the byte offset of its real data (out_off), its element
    count (out_n, 0 for an empty cell) and its data type (out_type). ``itemsize``: MI_ITEMSIZE.

    Returns the byte offset after the last cell, or a negative code where a cell is not a real
    numeric vector this walk reads (-1 - its index): the caller then reads the file the slow way,
    which names the problem."""
    o = start
    size = buf.size
    for c in range(n_cells):
        if o + 8 > size:
            return -1 - c
        if _u32(buf, o) != MI_MATRIX:
            return -1 - c
        nb = _u32(buf, o + 4)
        end = o + 8 + nb
        if end > size:
            return -1 - c
        if nb == 0:                         # an empty cell may be a bare tag
            out_off[c] = 0
            out_n[c] = 0
            out_type[c] = 0
            o = end
            continue
        p = o + 8
        # array flags: miUINT32 (6), 8 bytes
        if _u32(buf, p) != 6 or _u32(buf, p + 4) != 8:
            return -1 - c
        flags = _u32(buf, p + 8)
        cls = flags & 0xFF
        if cls < MX_NUMERIC_LO or cls > MX_NUMERIC_HI or (flags & 0x800) != 0:
            return -1 - c
        p += 16
        # dimensions: miINT32 (5); a vector has at most one dimension above 1
        if _u32(buf, p) != 5:
            return -1 - c
        ndb = _u32(buf, p + 4)
        nd = ndb // 4
        numel = 1
        big = 0
        for k in range(nd):
            dk = _i32(buf, p + 8 + 4 * k)
            if dk < 0:
                return -1 - c
            numel *= dk
            if dk > 1:
                big += 1
        if nd > 2 or big > 1:
            return -1 - c
        p += 8 + ((ndb + 7) // 8) * 8
        # name: a small element or a tagged one (empty for a cell)
        t = _u32(buf, p)
        if (t >> 16) != 0:
            p += 8
        else:
            nn = _u32(buf, p + 4)
            p += 8 + ((nn + 7) // 8) * 8
        if p > end:
            return -1 - c
        if p == end:                        # no data element: an empty array
            if numel != 0:
                return -1 - c
            out_off[c] = 0
            out_n[c] = 0
            out_type[c] = 0
            o = end
            continue
        t = _u32(buf, p)
        if (t >> 16) != 0:
            typ = t & 0xFFFF
            dnb = t >> 16
            doff = p + 4
        else:
            typ = t
            dnb = _u32(buf, p + 4)
            doff = p + 8
        if typ <= 0 or typ >= itemsize.size or itemsize[typ] == 0:
            return -1 - c
        if cls == 7 and (typ == 5 or typ == 6 or typ >= 12):
            return -1 - c                   # single class from wide integers: scipy rounds to float32
        isz = itemsize[typ]
        if dnb != numel * isz or doff + dnb > end or doff % isz != 0:
            return -1 - c
        out_off[c] = doff
        out_n[c] = numel
        out_type[c] = typ
        o = end
    return o
