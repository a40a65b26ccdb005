"""Write a simulated scan as a PicoQuant T3 image PTU file that PicoQuant's and others' tools open.

ptufile's ``imwrite``/``PtuWriter`` encode a dense (Y, X, bins) histogram with one photon per
sync, which cannot hold a 1024 x 1024 scan at 8 ps (12,500 bins a pixel) nor keep the simulated
sync of each detection. So the header comes from ``ptufile.PtuWriter`` (all the image tags
PicoQuant's readers expect, same marker numbering: line start = marker 1, line stop = marker 2,
frame = marker 3), and the records are our events encoded as Generic T3 records, with the
record count patched into the header's ``TTResult_NumberOfRecords`` tag.

Markers in the file: LINE_START -> input 1, LINE_STOP -> input 2, FRAME -> input 3 (written at
the end of the frame, where ptufile and PicoQuant scanners put the frame change), PIXEL -> input
4 (readers that do not use pixel markers ignore it).
"""

from __future__ import annotations

import io
import struct

import numpy as np

from drivers.errors import SettingError
from drivers.events import Marker

from drivers.sim import kernels as K

MARKER_INPUT = {Marker.LINE_START: 1, Marker.LINE_STOP: 2, Marker.FRAME: 4, Marker.PIXEL: 8}
"""Our marker bit -> the file's marker bit mask (input n has mask 1 << (n - 1))."""


def _marker_map() -> np.ndarray:
    m = np.zeros(256, np.uint8)
    for bits in range(256):
        v = 0
        for flag, mask in MARKER_INPUT.items():
            if bits & int(flag):
                v |= mask
        m[bits] = v
    return m


def _frame_at_end(events: np.ndarray) -> np.ndarray:
    """Move the FRAME marker from the start of the frame to its end (after the last LINE_STOP)."""
    is_frame = (events["kind"] == K.KIND_MARKER) & ((events["marker"] & Marker.FRAME) != 0)
    if not is_frame.any():
        return events
    frames = events[is_frame].copy()
    rest = events.copy()
    rest["marker"][is_frame] &= ~np.uint8(Marker.FRAME)
    rest = rest[~(is_frame & (rest["marker"] == 0))]
    frames["sync"] = rest["sync"][-1] if rest.size else frames["sync"]
    return np.concatenate([rest, frames[-1:]])


def write_ptu(path, events: np.ndarray, shape: tuple[int, int], sync_period_s: float,
              resolution_s: float, pixel_time_s: float, range_bins: int, *, comment: str = "",
              tags: dict | None = None) -> int:
    """Write ``events`` (EVENT_DTYPE, one fixed-dwell frame with markers) as a T3 image PTU.

    shape (H, W); range_bins is the number of dtime bins (<= 32768 for Generic T3 records).
    Returns the number of records written. Raises SettingError when the settings cannot be
    expressed in Generic T3 records.
    """
    import ptufile

    if range_bins > 32768:
        raise SettingError(f"{range_bins} tagger bins per period do not fit T3 records (max 32768): "
                         "use a coarser resolution or a shorter tagger range")
    if events.size and int(events["channel"].max()) > 62:
        raise SettingError("detector channel above 62 does not fit T3 records")
    h, w = shape
    ev = _frame_at_end(events)
    # overflow records: at most one per 1023 x 1024 syncs of gap, plus one per event
    span = int(ev["sync"][-1]) if ev.size else 0
    cap = ev.size + span // (1023 * K.T3_OVERFLOW_PERIOD) + ev.size + 16
    out = np.empty(cap, np.uint32)
    n = K.encode_t3_generic(ev["sync"], ev["dtime"], ev["channel"], ev["kind"], ev["marker"],
                            _marker_map(), out)
    if n < 0:  # cannot happen with the bound above; kept as a guard against a silent short file
        raise SettingError("T3 record buffer too small")
    head = io.BytesIO()
    writer = ptufile.PtuWriter(head, (h, w, range_bins), sync_period_s, resolution_s,
                               max(pixel_time_s, sync_period_s),
                               record_type=ptufile.PtuRecordType.GenericT3, comment=comment,
                               tags=tags)
    writer.close()
    header = bytearray(head.getvalue())
    # A tag is 32 bytes of name, 4 of index, 4 of type, then its 8-byte value.
    for name, value in ((b"TTResult_NumberOfRecords", n), (b"ImgHdr_MaxFrames", 1)):
        at = header.find(name)
        if at < 0:
            raise SettingError(f"ptufile header lacks {name.decode()}")
        header[at + 40:at + 48] = struct.pack("<q", value)
    with open(path, "wb") as fh:
        fh.write(header)
        fh.write(out[:n].tobytes())
    return n
