"""PicoQuant T3 files: PTU (tagged header, via ``ptufile``), and the legacy HT3 (HydraHarp) and PT3
(PicoHarp 300) formats, whose fixed binary headers are parsed here and whose records go through
the same ``ptufile`` decoder.

Pixels come from pixel markers when the file has them (DESIGN.md section 5): a PTU whose header
names a pixel-clock marker (``SPDepth_PixelMarker``, written by ``acq.ptu``) and whose records hold
such markers is decoded in chunks into ``drivers.events`` events, its marker bits renumbered to our
``Marker`` bits from the header, and assigned by ``acq.assign.PixelAssigner``, the one assignment
path of live scans and replays: exact for count-gated scans, whose dwell varies per pixel.

Only files with line markers and no pixel markers fall back to interpolation (DESIGN.md section 3),
as ptufile and PicoQuant's tools do, which is right for fixed dwell only: a photon between the
line-start marker at sync ``t0`` and the line-stop marker at sync ``t1`` lands in column
``floor((t - t0) / (t1 - t0) * PixX)``; the row is the line's index within its frame (the frame
marker resets it). ``ImgHdr_PixY`` is not trusted there: the height is the number of lines
actually found. A file without line markers is a point measurement and comes back as a 1 x 1 store.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import math
import struct
from pathlib import Path

import numpy as np
from numba import njit

from spdepth.acq.assign import PixelAssigner, _assign_kernel
from spdepth.acq.ptu import (PIXEL_MARKER_TAG, PLAN_TAG, PtuLayout, iter_records, marker_map,
                             truncation_note)
from spdepth.acq.readers.common import ReadResult
from spdepth.drivers.events import EVENT_DTYPE, GENERIC_T3_RECORD_TYPES, EventKind, Marker, RecordType
from spdepth.drivers.tagger.t3 import T3DecoderState, _decode_kernel, invalid_record
from spdepth.recon.errors import InputError
from spdepth.recon.photons import PhotonStore

CHUNK_RECORDS = 1 << 18
"""Records decoded at a time on the pixel-marker path (4 MiB of events, 2 MiB of their pixels):
buffers a new process writes for the first time cost it a page fault every 4 kB, and these stay
in the caches between the passes over a chunk (at 1 << 22, 96 MiB: a fresh process read the
512x512 PTU in 0.26 s against 0.21 s, medians of 6 alternated)."""
_MARKER_KIND, _PHOTON_KIND, _PIXEL_BIT = int(EventKind.MARKER), int(EventKind.PHOTON), int(Marker.PIXEL)


@contextlib.contextmanager
def _quiet_ptufile():
    """ptufile logs header quirks (e.g. out-of-order indexed tags) that readers cannot act on."""
    log = logging.getLogger("ptufile")
    level = log.level
    log.setLevel(logging.CRITICAL)
    try:
        yield
    finally:
        log.setLevel(level)


# ---------------------------------------------------------------------------------------------
# pixel assignment from markers


@njit(cache=True, nogil=True)
def _assign_pixels_kernel(sync, channel, marker, pix_x, start_mask, stop_mask, frame_mask,
                          bidirectional, keep_channel, row_out, col_out):
    """Fill row_out/col_out (pre-set to -1) for photons inside a line; return (lines_total,
    max_lines_in_a_frame, frames). Within one record the stop bit is handled before the frame bit
    and the frame bit before the start bit, since a controller may fire them together at a line
    boundary."""
    n = sync.size
    in_line = False
    t_start = np.uint64(0)
    first = 0
    lines_in_frame = 0
    max_lines = 0
    lines_total = 0
    frames = 0
    for i in range(n):
        if channel[i] >= 0:
            continue
        m = marker[i]
        if m == 0:
            continue  # overflow record
        if (m & stop_mask) != 0 and in_line:
            span = np.int64(sync[i] - t_start)
            if span > 0:
                y = lines_in_frame
                for j in range(first, i):
                    ch = channel[j]
                    if ch < 0 or (keep_channel >= 0 and ch != keep_channel):
                        continue
                    x = np.int64(sync[j] - t_start) * pix_x // span
                    if x >= pix_x:
                        x = pix_x - 1
                    if bidirectional and (y % 2) == 1:
                        x = pix_x - 1 - x
                    row_out[j] = y
                    col_out[j] = x
            lines_in_frame += 1
            lines_total += 1
            if lines_in_frame > max_lines:
                max_lines = lines_in_frame
            in_line = False
        if frame_mask != 0 and (m & frame_mask) != 0:
            frames += 1
            lines_in_frame = 0
            in_line = False  # a line left open at a frame marker is abandoned
        if (m & start_mask) != 0:
            in_line = True
            t_start = sync[i]
            first = i + 1
    return lines_total, max_lines, frames


def assign_pixels(sync: np.ndarray, channel: np.ndarray, marker: np.ndarray, *, pix_x: int,
                  line_start: int, line_stop: int, frame: int = 0, bidirectional: bool = False,
                  keep_channel: int = -1) -> tuple[np.ndarray, np.ndarray, int, int, int]:
    """Row and column of each record from the scanner's markers.

    sync:     uint64 (n,), sync count of each record (overflows resolved).
    channel:  int8 (n,), detector channel, negative for marker/overflow records.
    marker:   uint8 (n,), marker bit mask of marker records.
    pix_x:    pixels per line.
    line_start, line_stop, frame: marker numbers (1-based, as in ImgHdr_LineStart...; frame 0 =
              the file has no frame marker).
    keep_channel: only photons of this channel get a pixel (-1: all).
    Returns ``(row, col, lines_total, max_lines_per_frame, frames)``; row and col are int64 (n,),
    -1 for records that are not photons inside a line.
    """
    if pix_x < 1:
        raise InputError(f"pixels per line must be at least 1, got {pix_x}")
    masks = []
    for name, number in (("line start", line_start), ("line stop", line_stop), ("frame", frame)):
        if not 0 <= number <= 8 or (number == 0 and name != "frame"):
            raise InputError(f"{name} marker number must be 1..8, got {number}")
        masks.append(0 if number == 0 else 1 << (number - 1))
    n = sync.size
    row = np.full(n, -1, dtype=np.int64)
    col = np.full(n, -1, dtype=np.int64)
    lines_total, max_lines, frames = _assign_pixels_kernel(
        np.ascontiguousarray(sync, dtype=np.uint64), np.ascontiguousarray(channel, dtype=np.int8),
        np.ascontiguousarray(marker, dtype=np.uint8), np.int64(pix_x), np.uint8(masks[0]),
        np.uint8(masks[1]), np.uint8(masks[2]), bool(bidirectional), np.int64(keep_channel), row, col)
    return row, col, int(lines_total), int(max_lines), int(frames)


# ---------------------------------------------------------------------------------------------
# records -> store


def _decode(records: np.ndarray, rectype: int) -> np.ndarray:
    import ptufile
    from ptufile._ptufile import decode_t3_records  # the decoder ptufile itself uses

    out = np.zeros(records.size, dtype=ptufile.T3_RECORD_DTYPE)
    decode_t3_records(out, np.ascontiguousarray(records, dtype=np.uint32), int(rectype))
    return out


def _records_to_result(path: Path, kind: str, decoded: np.ndarray, time_unit_s: float,
                       image: dict | None, keep_channel: int | None, meta: dict) -> ReadResult:
    """Shared tail of all PicoQuant readers: pixel assignment (or point measurement) -> store."""
    is_photon = decoded["channel"] >= 0
    channels, per_channel = np.unique(decoded["channel"][is_photon], return_counts=True)
    meta = dict(meta, time_unit_s=time_unit_s,
                photons_per_channel={int(c): int(k) for c, k in zip(channels, per_channel)})
    if keep_channel is not None:
        if keep_channel not in meta["photons_per_channel"]:
            raise InputError(f"{path}: no photons on channel {keep_channel}; channels with photons: "
                             f"{sorted(meta['photons_per_channel']) or 'none'}")
        is_photon &= decoded["channel"] == keep_channel
    notes = []
    marker_bits = int(np.bitwise_or.reduce(decoded["marker"][~is_photon])) if decoded.size else 0
    if image is not None:
        start_bit = 1 << (image["line_start"] - 1)
        if not marker_bits & start_bit:
            raise InputError(f"{path}: header describes a {image['pix_x']}-pixel-wide image with line "
                             f"start marker {image['line_start']}, but no such marker is in the records")
        row, col, lines, max_lines, frames = assign_pixels(
            decoded["time"], decoded["channel"], decoded["marker"], pix_x=image["pix_x"],
            line_start=image["line_start"], line_stop=image["line_stop"], frame=image["frame"],
            bidirectional=image["bidirectional"],
            keep_channel=-1 if keep_channel is None else keep_channel)
        if lines == 0:
            raise InputError(f"{path}: no complete scan line (line start {image['line_start']} "
                             f"followed by line stop {image['line_stop']}) in the records")
        height = max_lines
        pix_y = image.get("pix_y") or 0
        if image["frame"] == 0 and pix_y and lines > pix_y and lines % pix_y == 0:
            # no frame marker: frames are inferred from ImgHdr_PixY only when it divides evenly
            row = np.where(row >= 0, row % pix_y, -1)
            height = pix_y
            frames = lines // pix_y
        elif image["frame"] == 0:
            frames = 1
        sel = row >= 0
        store = PhotonStore.from_pixel_indices(row[sel] * image["pix_x"] + col[sel],
                                               decoded["dtime"][sel], (height, image["pix_x"]),
                                               time_unit_s)
        dropped = int(np.sum(is_photon)) - int(np.sum(sel))
        meta.update(assignment="line interpolation", lines=lines, frames=max(frames, 1),
                    pix_x=image["pix_x"], height=height, photons_outside_lines=dropped)
        return ReadResult(store=store, path=str(path), kind=kind, is_image=True, notes=tuple(notes),
                          meta=meta)
    times = decoded["dtime"][is_photon]
    store = PhotonStore(times, np.array([0, times.size]), (1, 1), time_unit_s)
    notes.append(f"{path.name}: point measurement (no image line markers): all "
                 f"{times.size} photons go to one 1 x 1 pixel")
    return ReadResult(store=store, path=str(path), kind=kind, is_image=False, notes=tuple(notes),
                      meta=meta)


# ---------------------------------------------------------------------------------------------
# PTU


def header_unit(path, time_unit_s: float | None, resolution_s: float, field: str) -> float:
    """The time unit of a PicoQuant file: its header's resolution. A ``time_unit_s`` given that
    differs from it is refused, naming both (it would silently rescale every time: a bust at 3.59 m
    read with 1 ps units sat at 0.45 m); the same value is accepted."""
    if time_unit_s is not None and not math.isclose(time_unit_s, resolution_s, rel_tol=1e-9):
        raise InputError(f"{path}: the time unit given ({time_unit_s * 1e12:g} ps) differs from the header's "
                         f"resolution ({field} = {resolution_s * 1e12:g} ps); PicoQuant files carry their own "
                         f"time unit: drop --time-unit-ps")
    return resolution_s


def read_ptu(path: str | Path, *, time_unit_s: float | None = None,
             channel: int | None = None, keep: int | None = None) -> ReadResult:
    """Read a PicoQuant PTU T3 file. Times are in units of the file's TCSPC resolution
    (``MeasDesc_Resolution``); a ``time_unit_s`` that differs from it is refused
    (:func:`header_unit`). ``keep``: a session recording's detections kept per pixel (default its
    target; :func:`acq.recording.session_photons`)."""
    import ptufile

    path = Path(path)
    try:
        with _quiet_ptufile(), ptufile.PtuFile(path) as ptu:
            tags = dict(ptu.tags)
            is_t3 = ptu.is_t3
            record_offset = ptu.record_offset
            n_records = ptu.number_records
    except InputError:
        raise
    except FileNotFoundError:
        raise InputError(f"{path}: no such file") from None
    except Exception as exc:  # ptufile raises various kinds on damaged headers
        raise InputError(f"{path}: not a readable PTU file ({type(exc).__name__}: {exc})") from None
    mode = tags.get("Measurement_Mode")
    if not is_t3:
        raise InputError(f"{path}: a T2 file (Measurement_Mode={mode}): it has no TCSPC times after "
                         f"a laser sync, so there is no depth to reconstruct; record in T3 mode")
    for field in ("MeasDesc_Resolution", "TTResultFormat_TTTRRecType"):
        if field not in tags:
            raise InputError(f"{path}: header field {field} is missing")
    size = path.stat().st_size
    # a file cut short (an acquisition stopped by another program) is read up to its last whole
    # record, as replay, ptufile and tttrlib do, with one note saying what is missing
    layout = PtuLayout(str(path), tags, record_offset, int(n_records),
                       max(size - record_offset, 0) // 4)
    resolution_s = float(tags["MeasDesc_Resolution"])
    if not resolution_s > 0:
        raise InputError(f"{path}: header field MeasDesc_Resolution is {resolution_s}, not a positive time")
    time_unit_s = header_unit(path, time_unit_s, resolution_s, "MeasDesc_Resolution")
    rectype = int(tags["TTResultFormat_TTTRRecType"])
    image = ptu_image(path, tags)
    meta = ptu_meta(tags, n_records)
    notes = ()
    if tags.get(PLAN_TAG) and rectype in GENERIC_T3_RECORD_TYPES:   # its reader says when it is cut
        # a session's recording: its passes and lost spans are in events.jsonl beside it
        from spdepth.acq.recording import session_photons

        store, notes, extra, periods = session_photons(path, keep)
        # a count-gated pixel's periods: up to the detection that filled it; its store holds the
        # in-window detections only, so earlier ones outside the window shadow unseen
        known = periods > 0
        return ReadResult(store=store, path=str(path), kind="ptu", is_image=True, notes=notes,
                          meta=dict(meta, **extra, time_unit_s=store.time_unit_s,
                                    periods_source="session store (periods of the kept detections; "
                                                   "in-window detections only)"),
                          periods=np.where(known, periods, 1.0) if known.any() else None)
    if layout.truncation:
        notes = (layout.truncation,)
        meta["records"] = layout.records_in_file
        meta["records_in_header"] = layout.n_records
    if image is not None and int(tags.get(PIXEL_MARKER_TAG, 0) or 0):
        result = _read_by_pixel_markers(path, layout, rectype, image, time_unit_s or resolution_s,
                                        channel, meta)
        if result is not None:
            return _with_fixed_dwell_periods(dataclasses.replace(result, notes=notes + result.notes), tags)
        notes += (f"{path.name}: the header names pixel marker {tags[PIXEL_MARKER_TAG]} but the "
                  f"records hold none: pixels interpolated between line markers",)
    records = np.fromfile(path, dtype="<u4", count=min(layout.n_records, layout.records_in_file),
                          offset=record_offset)
    result = _records_to_result(path, "ptu", _decode(records, rectype), time_unit_s or resolution_s,
                                image, channel, meta)
    if notes:
        result = dataclasses.replace(result, notes=notes + result.notes)
    return _with_fixed_dwell_periods(result, tags) if image is not None else result


def fixed_dwell_periods(tags: dict) -> tuple[float | None, dict]:
    """The laser periods each pixel of an image of fixed dwell saw (not a session's count-gated
    recording, read elsewhere): ``ImgHdr_TimePerPixel`` (ms) times ``TTResult_SyncRate``, the same
    for every pixel, and the meta that says so; (None, {}) when the header lacks either."""
    dwell_ms = float(tags.get("ImgHdr_TimePerPixel", 0) or 0)
    rate = float(tags.get("TTResult_SyncRate", 0) or 0)
    if not (dwell_ms > 0 and rate > 0):
        return None, {}
    n = max(1.0, round(dwell_ms * 1e-3 * rate))
    return n, {"periods_per_pixel": n,
               "periods_source": "header ImgHdr_TimePerPixel x TTResult_SyncRate (fixed dwell)"}


def _with_fixed_dwell_periods(result: ReadResult, tags: dict) -> ReadResult:
    """``result`` with :func:`fixed_dwell_periods` (unchanged when the header tells none)."""
    n, meta = fixed_dwell_periods(tags)
    if n is None:
        return result
    return dataclasses.replace(result, periods=np.full(result.store.n_pixels, n),
                               meta=dict(result.meta, **meta))


def ptu_image(path, tags: dict) -> dict | None:
    """The scan a PTU header describes (``ImgHdr_*``): pixels per line, marker numbers, lines
    (``pix_y``, 0 when not given), serpentine or not; None without line markers (a point
    measurement). Sinusoidal scanning is an ``InputError``."""
    if not all(k in tags for k in ("ImgHdr_LineStart", "ImgHdr_LineStop", "ImgHdr_PixX")):
        return None
    if tags.get("ImgHdr_SinCorrection"):
        raise InputError(f"{path}: sinusoidal (resonant) scanning is not supported: pixels "
                         f"would be unevenly spaced in time")
    return {"pix_x": int(tags["ImgHdr_PixX"]), "line_start": int(tags["ImgHdr_LineStart"]),
            "line_stop": int(tags["ImgHdr_LineStop"]), "frame": int(tags.get("ImgHdr_Frame", 0) or 0),
            "pix_y": int(tags.get("ImgHdr_PixY", 0) or 0),
            "bidirectional": bool(tags.get("ImgHdr_BiDirect", False))}


def ptu_meta(tags: dict, n_records: int) -> dict:
    """What a PTU reader reports of the header (``ReadResult.meta``)."""
    return {"record_type": int(tags["TTResultFormat_TTTRRecType"]),
            "resolution_s": float(tags["MeasDesc_Resolution"]), "records": int(n_records),
            "sync_rate_hz": float(tags.get("TTResult_SyncRate", 0) or 0)}


class PixelMarkerDecoder:
    """A PTU's records with pixel markers, decoded chunk by chunk in stream order: Generic T3
    records into events (``drivers.tagger.t3``'s decoding kernel; the state carries the overflow
    count), the file's marker bits renumbered to ``Marker`` bits, photons assigned by
    ``acq.assign.PixelAssigner``'s kernel and state (the one assignment path of live scans and
    replays), and those in a pixel (of ``keep_channel`` only, when given) appended to the
    caller's arrays. ``read_ptu`` runs one over the whole file;
    ``acq.distributed`` copies one at chunk boundaries and resumes the copies on its workers."""

    def __init__(self, path, tags: dict, shape: tuple[int, int], pattern: str,
                 keep_channel: int | None = None):
        self.path = str(path)
        self.lut = marker_map(tags)
        self.state = T3DecoderState()
        self.assigner = PixelAssigner(shape, pattern)
        self.keep_channel = keep_channel
        self.per_channel = np.zeros(64, np.int64)
        self.pixel_markers = 0
        self.outside = 0

    def decode(self, records: np.ndarray, pixel_out: np.ndarray, time_out: np.ndarray, n: int = 0,
               *, buf: np.ndarray | None = None, pixel_buf: np.ndarray | None = None) -> int:
        """Decode ``records`` (uint32, after the previous ones) and append their photons' flat
        pixels (int32 or int64, :func:`pixel_dtype`) and dtimes (uint32) to
        ``pixel_out``/``time_out`` from index ``n`` (room for ``records.size`` more); returns the
        new ``n``. ``buf`` (EVENT_DTYPE) and ``pixel_buf`` (int64, as long): the events of one
        piece at a time (default: all of ``records`` at once).

        One kernel call (:func:`_decode_pixel_markers`) runs the four stages over every piece:
        called stage by stage, the reading thread took the GIL back after each of them, and while
        the warm-up thread held it (loading the estimator's kernels during a file's read) each
        return waited up to the switch interval: 0.30 s against 0.19 s for the 512x512 PTU's
        read in pieces of 1 << 18 records."""
        records = np.asarray(records).reshape(-1)
        if records.dtype != np.uint32:
            raise InputError(f"{self.path}: records must be uint32, not {records.dtype}")
        if buf is None:
            buf = np.empty(max(records.size, 1), EVENT_DTYPE)
        if pixel_buf is None:
            pixel_buf = np.empty(buf.size, np.int64)
        geom, state, lost = self.assigner.kernel_arguments(buf.size)
        channel = -1 if self.keep_channel is None else int(self.keep_channel)
        n, n_pixel, outside, base, last, bad = _decode_pixel_markers(
            records, buf.size, buf.view(np.uint64).reshape(-1, 2), buf["kind"], buf["marker"],
            buf["channel"], buf["dtime"], self.lut, geom, state, pixel_buf, lost, channel,
            pixel_out, time_out, n, self.per_channel, np.int64(self.state.sync_base))
        if bad >= 0:
            raise InputError(f"{self.path}: {invalid_record(self.state.records + bad, records[bad])}")
        self.state.sync_base = int(base)
        if last >= 0:
            self.state.last_sync = int(last)
        self.state.records += records.size
        self.pixel_markers += n_pixel
        self.outside += outside
        return n

    def meta(self, meta: dict, time_unit_s: float) -> dict:
        """``meta`` with what decoding found (``ReadResult.meta``); an ``InputError`` when the
        channel asked for has no photons."""
        h, w = self.assigner.shape
        meta = dict(meta, time_unit_s=time_unit_s,
                    photons_per_channel={int(c): int(k) for c, k in enumerate(self.per_channel) if k})
        if self.keep_channel is not None and self.keep_channel not in meta["photons_per_channel"]:
            raise InputError(f"{self.path}: no photons on channel {self.keep_channel}; channels "
                             f"with photons: {sorted(meta['photons_per_channel']) or 'none'}")
        meta.update(assignment="pixel markers", lines=self.assigner.lines_closed,
                    frames=max(self.assigner.frame + 1, 1), pix_x=w, height=h,
                    pixel_markers=self.pixel_markers, photons_outside_pixels=self.outside)
        return meta


def _read_by_pixel_markers(path: Path, layout: PtuLayout, rectype: int, image: dict,
                           time_unit_s: float, keep_channel: int | None,
                           meta: dict) -> ReadResult | None:
    """Decode the records chunk by chunk into events, renumber their marker bits to ``Marker``
    bits, and assign photons with ``PixelAssigner`` (a ``ImgHdr_PixY`` x ``ImgHdr_PixX`` scan,
    serpentine when ``ImgHdr_BiDirect``). Returns None when the records hold no pixel marker
    (the caller then interpolates between line markers)."""
    if rectype not in GENERIC_T3_RECORD_TYPES:
        raise InputError(f"{path}: pixel markers in record type 0x{rectype:08x} are not supported "
                         f"(Generic T3 record types only)")
    h, w = image["pix_y"], image["pix_x"]
    if h < 1 or w < 1:
        raise InputError(f"{path}: header field ImgHdr_PixY/ImgHdr_PixX is {h}/{w}: a file with "
                         f"pixel markers needs the scan's size")
    decoder = PixelMarkerDecoder(path, layout.tags, (h, w),
                                 "serp" if image["bidirectional"] else "raster", keep_channel)
    n_read = min(layout.n_records, layout.records_in_file)   # fewer than promised when cut short
    buf = np.empty(min(CHUNK_RECORDS, max(n_read, 1)), EVENT_DTYPE)
    pixel_buf = np.empty(buf.size, np.int64)
    # every photon of the file lands here in stream order, then one counting sort groups them
    cap = n_read
    pixel_all, time_all = np.empty(cap, pixel_dtype(h * w)), np.empty(cap, np.uint32)
    n_kept = 0
    for records in iter_records(layout, max(n_read, 1)):      # the whole map: pieces of buf's size
        n_kept = decoder.decode(records, pixel_all, time_all, n_kept, buf=buf, pixel_buf=pixel_buf)
    if decoder.pixel_markers == 0:
        return None
    meta = decoder.meta(meta, time_unit_s)
    store = PhotonStore.from_pixel_indices(pixel_all[:n_kept], time_all[:n_kept], (h, w),
                                           time_unit_s)
    return ReadResult(store=store, path=str(path), kind="ptu", is_image=True, meta=meta)


def pixel_dtype(n_pixels: int) -> np.dtype:
    """The flat pixel index type of a frame of ``n_pixels`` as the reader collects it: int32 where
    it fits (half the memory a fresh process faults in: 31 of 63 MB for the 7.9 M detections of a
    512x512 PTU), else int64; ``PhotonStore.from_pixel_indices`` groups either as it is."""
    return np.dtype(np.int32) if n_pixels <= np.iinfo(np.int32).max else np.dtype(np.int64)


def warm_up() -> None:
    """Load (on a cold numba cache: compile) the kernels that reading a PTU with pixel markers
    runs, on a made-up chunk of three records (a pixel marker, a photon, a line stop), read-only as
    the memory map's chunks are: ``spdepth recon`` runs it on a thread while it opens the file, so
    that the read does not pay for a new process's first kernel calls."""
    from spdepth.drivers.tagger.t3 import T3_CHANNEL_SHIFT, T3_SPECIAL_SHIFT

    special = 1 << T3_SPECIAL_SHIFT
    # inputs 1 and 3 (line start, pixel) at nsync 1, a photon at nsync 2, input 2 (line stop) at 3
    chunk = np.array([special | (0b101 << T3_CHANNEL_SHIFT) | 1, 2,
                      special | (0b010 << T3_CHANNEL_SHIFT) | 3], np.uint32)
    chunk.setflags(write=False)
    tags = {"ImgHdr_LineStart": 1, "ImgHdr_LineStop": 2, PIXEL_MARKER_TAG: 3}
    decoder = PixelMarkerDecoder("warm-up", tags, (1, 1), "raster")
    pixel_all, time_all = np.empty(chunk.size, pixel_dtype(1)), np.empty(chunk.size, np.uint32)
    n = decoder.decode(chunk, pixel_all, time_all, 0, buf=np.empty(chunk.size, EVENT_DTYPE),
                       pixel_buf=np.empty(chunk.size, np.int64))
    PhotonStore.from_pixel_indices(pixel_all[:n], time_all[:n], (1, 1), 1e-12)


# ---------------------------------------------------------------------------------------------
# legacy HT3 / PT3: fixed little-endian headers (PicoQuant's file format demos)

_TEXT_HEAD = [("Ident", "16s"), ("FormatVersion", "6s"), ("CreatorName", "18s"),
              ("CreatorVersion", "12s"), ("FileTime", "18s"), ("CRLF", "2s"), ("Comment", "256s")]
_HT3_HEAD = _TEXT_HEAD + [
    ("NumberOfCurves", "i"), ("BitsPerRecord", "i"), ("ActiveCurve", "i"), ("MeasurementMode", "i"),
    ("SubMode", "i"), ("Binning", "i"), ("Resolution_ps", "d"), ("Offset", "i"), ("Tacq_ms", "i"),
    ("StopAt", "I"), ("StopOnOvfl", "i"), ("Restart", "i"), ("DispLinLog", "i"),
    ("DispTimeFrom", "i"), ("DispTimeTo", "i"), ("DispCountFrom", "i"), ("DispCountTo", "i"),
    ("DispCurves", "16i"), ("Params", "9f"), ("RepeatMode", "i"), ("RepeatsPerCurve", "i"),
    ("RepeatTime", "i"), ("RepeatWaitTime", "i"), ("ScriptName", "20s"),
    ("HardwareIdent", "16s"), ("HardwarePartNo", "8s"), ("HardwareSerial", "i"),
    ("NumberOfModules", "i"), ("ModuleInfo", "20i"), ("BaseResolution", "d"), ("InputsEnabled", "Q"),
    ("InpChansPresent", "i"), ("RefClockSource", "i"), ("ExtDevices", "i"), ("MarkerSettings", "i"),
    ("SyncDivider", "i"), ("SyncCFDLevel", "i"), ("SyncCFDZeroCross", "i"), ("SyncOffset", "i")]
# then per input channel 4 x int32 (module, CFD level, CFD zero cross, offset), then one int32 rate
# per channel, then this T3 block, then ImgHdrSize int32 words of image header, then the records
_HT3_TTMODE = [("SyncRate", "i"), ("StopAfter", "i"), ("StopReason", "i"), ("ImgHdrSize", "i"),
               ("nRecords", "q")]
_PT3_HEAD = _TEXT_HEAD + [
    ("NumberOfCurves", "i"), ("BitsPerRecord", "i"), ("RoutingChannels", "i"), ("NumberOfBoards", "i"),
    ("ActiveCurve", "i"), ("MeasurementMode", "i"), ("SubMode", "i"), ("RangeNo", "i"), ("Offset", "i"),
    ("Tacq_ms", "i"), ("StopAt", "i"), ("StopOnOvfl", "i"), ("Restart", "i"), ("DispLinLog", "i"),
    ("DispTimeFrom", "i"), ("DispTimeTo", "i"), ("DispCountFrom", "i"), ("DispCountTo", "i"),
    ("DispCurves", "16i"), ("Params", "9f"), ("RepeatMode", "i"), ("RepeatsPerCurve", "i"),
    ("RepeatTime", "i"), ("RepeatWaitTime", "i"), ("ScriptName", "20s"),
    ("HardwareIdent", "16s"), ("HardwarePartNo", "8s"), ("HardwareSerial", "i"), ("SyncDivider", "i"),
    ("CFDZeroCross0", "i"), ("CFDLevel0", "i"), ("CFDZeroCross1", "i"), ("CFDLevel1", "i"),
    ("Resolution_ns", "f"), ("RouterModelCode", "i"), ("RouterEnabled", "i"), ("Router", "24i"),
    ("ExtDevices", "i"), ("Reserved1", "i"), ("Reserved2", "i"), ("SyncRate", "i"), ("CountRate", "i"),
    ("StopAfter", "i"), ("StopReason", "i"), ("nRecords", "i"), ("ImgHdrSize", "i")]


def _unpack(path: Path, data: bytes, offset: int, fields: list[tuple[str, str]]) -> tuple[dict, int]:
    fmt = "<" + "".join(f for _, f in fields)
    size = struct.calcsize(fmt)
    if len(data) < offset + size:
        raise InputError(f"{path}: truncated header ({len(data)} bytes, the header needs more than "
                         f"{offset + size})")
    values = list(struct.unpack_from(fmt, data, offset))
    out = {}
    for name, f in fields:
        count = int(f[:-1]) if f[:-1].isdigit() and f[-1] != "s" else 1
        if count == 1:
            v = values.pop(0)
            out[name] = v.rstrip(b"\0").decode("latin-1").strip() if isinstance(v, bytes) else v
        else:
            out[name] = values[:count]
            del values[:count]
    return out, offset + size


def _legacy_records(path: Path, data: bytes, offset: int, head: dict) -> np.ndarray:
    mode = head["MeasurementMode"]
    if mode == 0:          # PicoHarp .phd, HydraHarp .hhd: the same header, then histograms
        raise InputError(f"{path}: a PicoQuant histogram file (.phd/.hhd, MeasurementMode 0): it "
                         f"holds summed histograms, not the time-tagged detections per pixel "
                         f"that depth needs; record in T3 mode (.ptu, .ht3, .pt3)")
    if mode != 3:
        kind = "T2" if mode == 2 else f"MeasurementMode={mode}"
        raise InputError(f"{path}: a {kind} file, not T3: it has no TCSPC times after a laser sync, "
                         f"so there is no depth to reconstruct")
    if head["BitsPerRecord"] != 32:
        raise InputError(f"{path}: header field BitsPerRecord is {head['BitsPerRecord']}, expected 32")
    n_records = int(head["nRecords"])
    offset += 4 * max(int(head["ImgHdrSize"]), 0)
    if n_records < 0:
        raise InputError(f"{path}: corrupt header: nRecords is {n_records}")
    held = max(len(data) - offset, 0) // 4
    notes = ()
    if held < n_records:   # cut short: its whole records are read, as for a PTU
        notes = (truncation_note(path.name, n_records, held),)
        n_records = held
    return np.frombuffer(data, dtype="<u4", count=n_records, offset=offset), notes


def _read_bytes(path: Path) -> bytes:
    try:
        return path.read_bytes()
    except FileNotFoundError:
        raise InputError(f"{path}: no such file") from None
    except OSError as exc:
        raise InputError(f"{path}: cannot read: {exc.strerror or exc}") from None


def read_ht3(path: str | Path, *, time_unit_s: float | None = None,
             channel: int | None = None) -> ReadResult:
    """Read a legacy HydraHarp .ht3 T3 file (format 1.0 or 2.0). Legacy image headers are not
    decoded, so these files always read as point measurements."""
    path = Path(path)
    data = _read_bytes(path)
    head, off = _unpack(path, data, 0, _HT3_HEAD)
    if not head["Ident"].startswith("HydraHarp"):
        raise InputError(f"{path}: not an HT3 file (ident {head['Ident']!r})")
    n_inputs = head["InpChansPresent"]
    if not 0 < n_inputs <= 64:
        raise InputError(f"{path}: corrupt header: InpChansPresent is {n_inputs}")
    _, off = _unpack(path, data, off, [("Inputs", f"{5 * n_inputs}i")])
    tt, off = _unpack(path, data, off, _HT3_TTMODE)
    head.update(tt)
    version = head["FormatVersion"]
    rectype = {"1.0": RecordType.HYDRAHARP_T3, "2.0": RecordType.HYDRAHARP2_T3}.get(version)
    if rectype is None:
        raise InputError(f"{path}: HT3 format version {version!r} is not 1.0 or 2.0")
    return _legacy_result(path, "ht3", data, off, head, rectype, head["Resolution_ps"] * 1e-12,
                          time_unit_s, channel)


def read_pt3(path: str | Path, *, time_unit_s: float | None = None,
             channel: int | None = None) -> ReadResult:
    """Read a legacy PicoHarp 300 .pt3 T3 file (format 2.0); a point measurement, as for HT3."""
    path = Path(path)
    data = _read_bytes(path)
    head, off = _unpack(path, data, 0, _PT3_HEAD)
    if not head["Ident"].startswith("PicoHarp"):
        raise InputError(f"{path}: not a PT3 file (ident {head['Ident']!r})")
    if head["FormatVersion"] != "2.0":
        raise InputError(f"{path}: PT3 format version {head['FormatVersion']!r} is not 2.0")
    return _legacy_result(path, "pt3", data, off, head, RecordType.PICOHARP_T3,
                          head["Resolution_ns"] * 1e-9, time_unit_s, channel)


def _legacy_result(path, kind, data, off, head, rectype, resolution_s, time_unit_s, channel):
    """Records of a legacy HT3/PT3 file after its header, decoded into a point measurement."""
    records, notes = _legacy_records(path, data, off, head)
    if not resolution_s > 0:
        raise InputError(f"{path}: header field Resolution is {resolution_s * 1e12:g} ps, not positive")
    time_unit_s = header_unit(path, time_unit_s, resolution_s, "Resolution")
    meta = {"record_type": int(rectype), "resolution_s": resolution_s, "records": int(records.size),
            "sync_rate_hz": float(head["SyncRate"]), "format_version": head["FormatVersion"]}
    if notes:
        meta["records_in_header"] = int(head["nRecords"])
    result = _records_to_result(path, kind, _decode(records, rectype), time_unit_s or resolution_s,
                                None, channel, meta)
    return dataclasses.replace(result, notes=notes + result.notes)


@njit(cache=True, nogil=True)
def _renumber_markers(kind, marker, lut):
    """Marker bits of the file's inputs -> ``Marker`` bits (``lut``), in place; returns the number
    of pixel markers."""
    n_pixel = 0
    for i in range(kind.size):
        if kind[i] == _MARKER_KIND:
            m = lut[marker[i]]
            marker[i] = m
            if m & _PIXEL_BIT:
                n_pixel += 1
    return n_pixel


@njit(cache=True, nogil=True)
def _collect_photons(kind, channel, dtime, pixel, keep_channel, pixel_out, time_out, n, per_channel):
    """Append the photons that land in a pixel (of ``keep_channel`` only, when >= 0) to
    ``pixel_out``/``time_out`` from index ``n``; count photons per channel. Returns (new n,
    photons outside any pixel)."""
    outside = 0
    for i in range(kind.size):
        if kind[i] != _PHOTON_KIND:
            continue
        c = channel[i]
        per_channel[c] += 1
        if keep_channel >= 0 and c != keep_channel:
            continue
        if pixel[i] < 0:
            outside += 1
            continue
        pixel_out[n] = pixel[i]
        time_out[n] = dtime[i]
        n += 1
    return n, outside


@njit(cache=True, nogil=True)
def _decode_pixel_markers(records, piece, words, kind, marker, channel, dtime, lut, geom, state, pixel_buf,
                          lost_buf, keep_channel, pixel_out, time_out, n, per_channel, sync_base):
    """:meth:`PixelMarkerDecoder.decode`'s stages over ``records`` in pieces of ``piece``: each
    decoded into ``words`` (the EVENT_DTYPE buffer as uint64 pairs; ``kind``, ``marker``,
    ``channel`` and ``dtime`` its field views) by drivers.tagger.t3's kernel, its marker bits
    renumbered (``lut``), its photons assigned by acq.assign's kernel (``geom``, ``state``: the
    PixelAssigner's) into ``pixel_buf``, and those in a pixel appended to ``pixel_out``/``time_out``
    from ``n``. Decoded records hold photons and markers only (no LOST events), so no span is
    lost here. Returns (n, pixel markers, photons outside pixels, sync_base, the last event's sync
    or -1, the index of the first invalid record or -1: nothing of its piece is kept)."""
    n_pixel = 0
    outside = 0
    last_sync = -1
    for p0 in range(0, records.size, piece):
        ne, sync_base, last, bad = _decode_kernel(records[p0:p0 + piece], words, sync_base)
        if bad >= 0:
            return n, n_pixel, outside, sync_base, last_sync, p0 + bad
        if last >= 0:
            last_sync = last
        n_pixel += _renumber_markers(kind[:ne], marker[:ne], lut)
        _assign_kernel(kind[:ne], marker[:ne], geom, state, pixel_buf[:ne], lost_buf[:ne])
        n, out = _collect_photons(kind[:ne], channel[:ne], dtime[:ne], pixel_buf[:ne], keep_channel,
                                  pixel_out, time_out, n, per_channel)
        outside += out
    return n, n_pixel, outside, sync_base, last_sync, -1
