"""Recordings as PicoQuant PTU files: the header, the record body, and reading it back in chunks.

The time tagger streams PicoQuant Generic T3 records, so a recording is a PTU file whose body is
the device's records as they came (DESIGN.md section 5): ``ptu_header`` first with
``TTResult_NumberOfRecords = 0`` (a crash leaves a file ptufile still reads: it then takes the
rest of the file as records), the records appended and flushed, ``patch_record_count`` on a clean
close. ``spdepth simulate`` writes the same layout (``write_ptu``).

Marker numbering (``MARKER_INPUT``) is the device's: marker input n has mask ``1 << (n - 1)`` and
input n is our ``Marker`` bit of that mask, so the device's records need no renumbering (only
splitting, below):

    PIXEL -> input 1, LINE_START -> input 2, LINE_STOP -> input 3, FRAME -> input 4

and the header says so: ``ImgHdr_LineStart = 2``, ``ImgHdr_LineStop = 3``, ``ImgHdr_Frame = 4``
(what ptufile and tttrlib read), ``SPDepth_PixelMarker = 1`` (ours: PicoQuant has no pixel-marker
tag; tttrlib's ``marker_pixel`` default is also 1).

One marker kind per record. The device fires ``FRAME|LINE_START|PIXEL`` (channel bits 0b1011) in
one record at the start of a frame and ``LINE_START|PIXEL`` at each line start. tttrlib compares
marker values whole, so it sees none of them in a combined record (0 frames); ptufile tests bits
and does not mind. ``split_marker_records`` turns each combined record into one record per bit at
the same nsync, in the order FRAME, LINE_START, PIXEL, LINE_STOP (the order ``acq.assign`` applies
combined bits, so our own assignment does not change). Recordings and ``simulate`` write split
records.

Where FRAME goes (checked with ptufile 2026.2.6 and tttrlib 0.26.2, default settings, split
records, one and three frames): at the START of each frame, before its first LINE_START, exactly
as the device streams it. Both tools then find every frame and line and place every photon of a
fixed-dwell scan in the right pixel of the right frame (a FRAME record after each frame's last
LINE_STOP works as well; neither tool needs it there). ptufile's ``number_images`` says 0 for a
one-frame file with FRAME at the start (it counts frame changes), yet ``decode_image`` returns
that frame with every photon. See ``tests/test_acq_ptu.py``.

Count-gated scans (dwell varies per pixel): the pixel markers are exact, and our reader
(``acq.readers.picoquant``) and tttrlib with ``CLSMImage(tttr, use_pixel_markers=True)`` (its
``marker_pixel`` default is our input 1) use them. Interpolating readers cannot be right there:
tttrlib's default spreads each line evenly, and ptufile places pixels by ``ImgHdr_TimePerPixel``
from the line start, dropping photons past ``ImgHdr_PixX`` pixel times. So a count-gated recording
closes with that tag patched to the scan's mean pixel time (the galvo's logged dwells plus the
settle time; the dwell limit until then): on a 32 x 32 simulated bust, ptufile then places 74% of
the photons in their pixel (8% with the 20 ms limit there), the rest one or more pixels off or
past the line's last pixel: as near as a fixed pixel time can come. A raster rescan pass that
starts below row 0 or right of column 0 (only the pixels still short) cannot be placed by readers
that know no pixel markers: PTU frames always start at row 0, column 0.
"""

from __future__ import annotations

import json
import math
import os
import struct
import uuid
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path
from typing import IO, Iterator

import numpy as np

from spdepth.drivers.events import GENERIC_T3_RECORD_TYPES, Marker, RecordType
from spdepth.drivers.tagger.t3 import (T3_DTIME_MAX, T3_MARKER_MASK_MAX, T3EncoderState, encode_t3,
                               split_marker_records)
from spdepth.recon.errors import InputError

MARKER_INPUT = {Marker.PIXEL: 1, Marker.LINE_START: 2, Marker.LINE_STOP: 3, Marker.FRAME: 4}
"""Our marker -> the tagger's marker input number in recordings (mask ``1 << (n - 1)``, which is
the ``Marker`` value itself: the device's numbering)."""

PIXEL_MARKER_TAG = "SPDepth_PixelMarker"
"""Our header tag naming the marker input of the pixel clock (PicoQuant has none)."""
PLAN_TAG = "SPDepth_Plan"
"""A session recording's ``acq.plan.ScanPlan`` (JSON); its presence marks a session recording."""
RECON_TAG = "SPDepth_Recon"
"""The estimator settings the session used (JSON)."""
INFO_TAG = "SPDepth_Info"
"""Facts about the source (scene, seed, devices) (JSON)."""

T3_MAX_BINS = T3_DTIME_MAX + 1
"""dtime bins a Generic T3 record can carry (15 bits)."""

_TAG_HEAD = struct.Struct("<32siI")   # name, index, type code; then an 8-byte value
_TAG_SIZE = _TAG_HEAD.size + 8
_TYPE_INT8 = 0x10000008
_TYPE_FLOAT8 = 0x20000008
_TYPES_WITH_PAYLOAD = (0x2001FFFF, 0x4001FFFF, 0x4002FFFF, 0xFFFFFFFF)  # float array, ansi, wide, blob


def image_tags() -> dict[str, int]:
    """The header's marker numbering: ``ImgHdr_LineStart/LineStop/Frame`` and our pixel tag."""
    return {"ImgHdr_LineStart": MARKER_INPUT[Marker.LINE_START],
            "ImgHdr_LineStop": MARKER_INPUT[Marker.LINE_STOP],
            "ImgHdr_Frame": MARKER_INPUT[Marker.FRAME],
            PIXEL_MARKER_TAG: MARKER_INPUT[Marker.PIXEL]}


def _tag_value(name: str, value):
    """A user tag as something ``encode_tag`` writes: numbers, bools and strings as they are,
    anything else JSON-able as a JSON string."""
    if isinstance(value, (bool, int, float, str)) and not isinstance(value, np.generic):
        return value
    if isinstance(value, np.generic):
        return value.item()
    try:
        return json.dumps(value, sort_keys=True)
    except TypeError:
        raise InputError(f"PTU tag {name}: value {value!r} is not a number, string or JSON-able "
                         f"setting") from None


def ptu_header(shape: tuple[int, int], sync_period_s: float, resolution_s: float,
               pixel_time_s: float, range_bins: int, *, comment: str = "",
               tags: dict | None = None, record_type: int = RecordType.HYDRAHARP2_T3) -> bytes:
    """A complete PTU header for a T3 image recording of HydraHarp v2 / Generic T3 records
    (``TTResultFormat_TTTRRecType = 0x01010304``) with ``TTResult_NumberOfRecords = 0``.

    shape:         (H, W) pixels of one frame (``ImgHdr_PixY``, ``ImgHdr_PixX``).
    sync_period_s: laser period (``MeasDesc_GlobalResolution``); resolution_s: dtime unit
                   (``MeasDesc_Resolution``); pixel_time_s: nominal pixel dwell
                   (``ImgHdr_TimePerPixel``; for count-gated scans the dwell limit or the typical
                   dwell: readers that interpolate use the line markers, not this).
    range_bins:    dtime bins per period the tagger records (at most 32768 in T3 records).
    comment:       ``File_Comment``.
    tags:          extra tags (names up to 31 ASCII characters, e.g. ``SPDepth_Plan``): numbers,
                   bools and strings are written as such, other JSON-able values as JSON strings.
                   They cannot replace the tags this function sets for the format.
    record_type:   ``TTResultFormat_TTTRRecType``: one of ``drivers.events.GENERIC_T3_RECORD_TYPES`` (a
                   PicoQuant device's own type, e.g. MultiHarp Generic T3 0x00010307).
    The records follow the header directly. Raises InputError for settings a T3 image PTU cannot
    express.
    """
    import ptufile
    from ptufile.ptufile import encode_tag  # ptufile exports it from its module, not the package

    h, w = (int(v) for v in shape)
    if h < 1 or w < 1:
        raise InputError(f"PTU image shape must be at least 1 x 1, got {tuple(shape)}")
    if not (0 < resolution_s <= sync_period_s and math.isfinite(sync_period_s)):
        raise InputError(f"PTU resolution {resolution_s!r} s must be > 0 and at most the sync "
                         f"period {sync_period_s!r} s")
    if not 0 < range_bins <= T3_MAX_BINS:
        raise InputError(f"{range_bins} tagger bins per period do not fit T3 records (max "
                         f"{T3_MAX_BINS}): use a coarser resolution or a shorter tagger range")
    if not pixel_time_s > 0:
        raise InputError(f"PTU pixel time must be > 0 s, got {pixel_time_s!r}")
    if record_type not in GENERIC_T3_RECORD_TYPES:
        raise InputError(f"PTU record type 0x{record_type:08x} does not have the Generic T3 layout")
    fixed = {
        "File_GUID": f"{{{uuid.uuid4()}}}",
        "File_Comment": comment,
        "File_CreatingTime": datetime.now(),
        "CreatorSW_Name": "spdepth",
        "CreatorSW_Version": _version(),
        "Measurement_Mode": int(ptufile.PtuMeasurementMode.T3),
        "Measurement_SubMode": int(ptufile.PtuMeasurementSubMode.IMAGE),
        "MeasDesc_GlobalResolution": float(sync_period_s),
        "MeasDesc_Resolution": float(resolution_s),
        "MeasDesc_BinningFactor": 1,
        "TTResult_NumberOfRecords": 0,
        "TTResult_SyncRate": round(1.0 / sync_period_s),
        "TTResultFormat_TTTRRecType": int(record_type),
        "TTResultFormat_BitsPerRecord": 32,
        "HW_InpChannels": 2,
        "ImgHdr_Dimensions": 3,
        "ImgHdr_Ident": int(ptufile.PtuScannerType.LSM),
        **image_tags(),
        "ImgHdr_MaxFrames": 0,
        "ImgHdr_TimePerPixel": float(max(pixel_time_s, sync_period_s)) * 1e3,  # ms
        "ImgHdr_PixX": w,
        "ImgHdr_PixY": h,
        "ImgHdr_PixResol": 1.0,
        "ImgHdr_BiDirect": False,
        "ImgHdr_SinCorrection": 0,
        "SPDepth_RangeBins": int(range_bins),
    }
    parts = [b"PQTTTR\x00\x001.0.00\x00\x00"]  # magic and format version
    parts += [encode_tag(name, value) for name, value in fixed.items()]
    for name, value in (tags or {}).items():
        if not (isinstance(name, str) and name.isascii() and 0 < len(name) <= 31):
            raise InputError(f"PTU tag name {name!r} must be 1 to 31 ASCII characters")
        if name in fixed or name == "Header_End":
            raise InputError(f"PTU tag {name} is set by the recording format and cannot be given")
        parts.append(encode_tag(name, _tag_value(name, value)))
    parts.append(encode_tag("Header_End", None))
    return b"".join(parts)


def _version() -> str:
    try:
        from importlib.metadata import version
        return version("spdepth")
    except Exception:  # not installed (source tree): the header still needs a string
        return "unknown"


def _find_tag(head: bytes, name: str) -> tuple[int, int]:
    """(offset of the tag's 8-byte value, type code) of the first tag ``name`` in a PTU header;
    walks the tags, so a name inside a string value cannot be mistaken for it."""
    if head[:6] != b"PQTTTR":
        raise InputError("not a PTU file (no PQTTTR magic)")
    at = 16
    while at + _TAG_SIZE <= len(head):
        raw, _index, typ = _TAG_HEAD.unpack_from(head, at)
        tag = raw.split(b"\0", 1)[0].decode("latin-1")
        value_at = at + _TAG_HEAD.size
        if tag == name:
            return value_at, typ
        if tag == "Header_End":
            break
        at = value_at + 8
        if typ in _TYPES_WITH_PAYLOAD:
            at += struct.unpack_from("<q", head, value_at)[0]
    raise InputError(f"PTU header has no tag {name}")


def patch_record_count(path_or_file: str | os.PathLike | IO[bytes], n_records: int) -> None:
    """Write ``n_records`` into ``TTResult_NumberOfRecords`` (for a clean close).

    path_or_file: a path, or a binary file opened for update (``r+b``/``w+b``), whose position is
    restored afterwards. Raises InputError when the header has no such integer tag.
    """
    n_records = int(n_records)
    if n_records < 0:
        raise InputError(f"record count must be >= 0, got {n_records}")
    if isinstance(path_or_file, (str, os.PathLike)):
        with open(path_or_file, "r+b") as fh:
            _patch(fh, n_records)
        return
    fh = path_or_file
    if not (fh.readable() and fh.seekable()):
        raise InputError("patch_record_count needs a file opened for reading and writing "
                         "('r+b' or 'w+b')")
    pos = fh.tell()
    try:
        _patch(fh, n_records)
    finally:
        fh.seek(pos)


def patch_pixel_time(path_or_file: str | os.PathLike | IO[bytes], pixel_time_s: float) -> None:
    """Write ``pixel_time_s`` into ``ImgHdr_TimePerPixel`` (ms, Float8): at the close of a count-gated
    scan, the typical dwell, by which interpolating readers (ptufile's ``decode_image``) place
    photons from each line start. Same file handling as :func:`patch_record_count`."""
    if not (pixel_time_s > 0 and math.isfinite(pixel_time_s)):
        raise InputError(f"PTU pixel time must be > 0 s, got {pixel_time_s!r}")
    if isinstance(path_or_file, (str, os.PathLike)):
        with open(path_or_file, "r+b") as fh:
            _patch_value(fh, "ImgHdr_TimePerPixel", _TYPE_FLOAT8, struct.pack("<d", pixel_time_s * 1e3))
        return
    pos = path_or_file.tell()
    try:
        _patch_value(path_or_file, "ImgHdr_TimePerPixel", _TYPE_FLOAT8, struct.pack("<d", pixel_time_s * 1e3))
    finally:
        path_or_file.seek(pos)


def _patch(fh, n_records: int) -> None:
    _patch_value(fh, "TTResult_NumberOfRecords", _TYPE_INT8, struct.pack("<q", n_records))


def _patch_value(fh, name: str, typ_wanted: int, value: bytes) -> None:
    fh.seek(0)
    head = fh.read(1 << 16)
    while b"Header_End" not in head:    # a header with large string tags
        more = fh.read(1 << 16)
        if not more:
            break
        head += more
    at, typ = _find_tag(head, name)
    if typ != typ_wanted:
        raise InputError(f"PTU tag {name} has type 0x{typ:08x}, not 0x{typ_wanted:08x}")
    fh.seek(at)
    fh.write(value)
    fh.flush()


def encode_events(events: np.ndarray, state: T3EncoderState | None = None) -> np.ndarray:
    """Events (``drivers.events.EVENT_DTYPE``, markers as ``Marker`` bits) -> Generic T3 records for
    a file: ``MARKER_INPUT`` numbering, one marker kind per record. ``state`` carries the overflow
    period between chunks. Raises SettingError (drivers) for events T3 cannot carry."""
    return encode_t3(events, state, split_markers=True)


def write_ptu(path: str | os.PathLike, events: np.ndarray, shape: tuple[int, int],
              sync_period_s: float, resolution_s: float, pixel_time_s: float, range_bins: int, *,
              comment: str = "", tags: dict | None = None, chunk_events: int = 1 << 22) -> int:
    """Write ``events`` (EVENT_DTYPE: photons and markers as the galvo drives them, FRAME at the
    start of each frame) as a T3 image PTU in the recording layout; returns the records written.
    Encodes ``chunk_events`` at a time; the record count is patched in at the end."""
    if events.size and int(events["channel"][events["kind"] == 0].max(initial=0)) > 62:
        raise InputError("detector channel above 62 does not fit T3 records")
    header = ptu_header(shape, sync_period_s, resolution_s, pixel_time_s, range_bins,
                        comment=comment, tags=tags)
    state = T3EncoderState()
    n = 0
    with open(path, "w+b") as fh:
        fh.write(header)
        for i in range(0, events.size, chunk_events):
            records = encode_events(events[i:i + chunk_events], state)
            fh.write(records.tobytes())
            n += records.size
        patch_record_count(fh, n)
    return n


# ---- reading ---------------------------------------------------------------------------------

@dataclass(frozen=True)
class PtuLayout:
    """Where a PTU file's records are: ``record_offset`` bytes of header, then ``n_records``
    uint32 records (the header's count, or every whole record in the file when the count is 0,
    as for a recording that did not close cleanly). ``records_in_file``: whole records the file
    holds after the header (fewer than ``n_records`` when the file is truncated)."""

    path: str
    tags: dict
    record_offset: int
    n_records: int
    records_in_file: int

    @property
    def truncation(self) -> str | None:
        """One line saying what the header promised and what the file holds, when it holds
        fewer records (its whole records are read); None otherwise."""
        if self.records_in_file >= self.n_records:
            return None
        return truncation_note(Path(self.path).name, self.n_records, self.records_in_file)


def truncation_note(name: str, promised: int, held: int) -> str:
    """The one warning for a file cut short (an acquisition stopped by another program, a copy
    cut off): the same words for PTU, HT3 and PT3, in ``recon`` and in ``replay``."""
    return (f"{name} is truncated: its header promises {promised:,} records, the file holds "
            f"{held:,} whole records ({held / promised:.0%}); reading those")


def marker_map(tags: dict) -> np.ndarray | None:
    """The file's marker bits -> our ``Marker`` bits, as a lookup table uint8[16] indexed by a
    marker record's channel field, from ``ImgHdr_LineStart/LineStop/Frame`` and
    ``SPDepth_PixelMarker``; None when the header names no line markers. Bits the header does not
    name map to nothing."""
    numbers = {}
    for marker, tag in ((Marker.LINE_START, "ImgHdr_LineStart"), (Marker.LINE_STOP, "ImgHdr_LineStop"),
                        (Marker.FRAME, "ImgHdr_Frame"), (Marker.PIXEL, PIXEL_MARKER_TAG)):
        value = int(tags.get(tag, 0) or 0)
        if value:
            if not 1 <= value <= 4:
                raise InputError(f"header field {tag} is {value}: marker inputs are 1..4")
            numbers[marker] = value
    if Marker.LINE_START not in numbers or Marker.LINE_STOP not in numbers:
        return None
    if len(set(numbers.values())) != len(numbers):
        raise InputError(f"header names one marker input for several markers: "
                         f"{ {m.name: n for m, n in numbers.items()} }")
    lut = np.zeros(T3_MARKER_MASK_MAX + 1, np.uint8)
    for bits in range(lut.size):
        for marker, n in numbers.items():
            if bits & (1 << (n - 1)):
                lut[bits] |= int(marker)
    return lut


def iter_records(layout: PtuLayout, chunk_records: int = 1 << 22,
                 start: int = 0) -> Iterator[np.ndarray]:
    """The file's records from record ``start`` on, ``chunk_records`` at a time, as read-only
    uint32 views of a memory map (nothing is read before it is used)."""
    n = min(layout.n_records, layout.records_in_file) - start
    if n <= 0:
        return
    mm = np.memmap(layout.path, dtype="<u4", mode="r", offset=layout.record_offset + 4 * start,
                   shape=(n,))
    for i in range(0, n, chunk_records):
        yield mm[i:i + chunk_records]


def read_layout(path: str | os.PathLike) -> PtuLayout:
    """The header tags and record span of a PTU file (ptufile parses the header). A count of 0
    (a recording that did not close cleanly) means every whole record after the header."""
    import logging

    import ptufile

    path = Path(path)
    log = logging.getLogger("ptufile")
    level = log.level
    log.setLevel(logging.CRITICAL)  # the 0-count warning is expected for recordings in progress
    try:
        with ptufile.PtuFile(path) as ptu:
            tags = dict(ptu.tags)
            offset = int(ptu.record_offset)
            n = int(ptu.number_records)
    finally:
        log.setLevel(level)
    whole = max(path.stat().st_size - offset, 0) // 4
    return PtuLayout(str(path), tags, offset, n if n > 0 else whole, whole)


__all__ = ["MARKER_INPUT", "PIXEL_MARKER_TAG", "PLAN_TAG", "RECON_TAG", "INFO_TAG",
           "PtuLayout", "truncation_note",
           "encode_events", "image_tags", "iter_records", "marker_map", "patch_pixel_time", "patch_record_count",
           "ptu_header", "read_layout", "split_marker_records", "write_ptu"]
