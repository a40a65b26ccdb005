"""PicoQuant "Generic T3" records (HydraHarp v2, TimeHarp 260, MultiHarp): decoding into
``drivers.events.EVENT_DTYPE`` rows and encoding events back into records.

One record is a little-endian ``uint32``, fields from MSB to LSB::

    special:1 | channel:6 | dtime:15 | nsync:10

* special=0: a photon on detector ``channel`` (0-based), ``dtime`` resolution units after sync
  ``sync_base + nsync``.
* special=1, channel=63: sync counter overflow; ``sync_base`` grows by ``1024 * nsync`` (an
  ``nsync`` of 0 counts as 1, as in PicoQuant's demo code and HydraHarp v1 files).
* special=1, channel=1..15: external markers, bit-coded (bit n-1 = marker input n; several can fire
  at once) at sync ``sync_base + nsync``; ``dtime`` carries no meaning.
* special=1 with any other channel (0, 16..62) is not defined by PicoQuant: decoding raises
  ``ProtocolError`` instead of guessing.

The numba kernels (``_decode_kernel``, ``_count_encoded``, ``_encode_kernel``) take plain arrays;
``decode_t3``/``encode_t3`` validate, allocate and carry the overflow state between chunks.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass

import numpy as np
from numba import njit

from drivers.errors import ProtocolError, SettingError
from drivers.events import EVENT_DTYPE, EventKind

T3_WRAP_SYNCS = 1024
"""Syncs per overflow period (the 10-bit ``nsync`` field wraps here)."""
T3_DTIME_MAX = 2 ** 15 - 1
"""Largest ``dtime`` a record can carry (15 bits)."""
T3_OVERFLOW_CHANNEL = 63
"""``channel`` of an overflow record (with special=1)."""
T3_MAX_OVERFLOW_COUNT = 1023
"""Largest overflow count one record carries (10-bit ``nsync``)."""
T3_MARKER_MASK_MAX = 15
"""Markers use channels 1..15: four marker inputs, bit-coded."""

T3_RECORD_DTYPE = np.dtype("<u4")
"""One raw Generic T3 record: ``special:1 | channel:6 | dtime:15 | nsync:10`` (MSB to LSB),
little endian. See the module docstring for the meaning of each kind."""

if sys.byteorder != "little":  # the kernels write EVENT_DTYPE rows as two native uint64 words
    raise ImportError("drivers.tagger.t3 assumes a little-endian host")

# EVENT_DTYPE row as two little-endian 64-bit words: word 0 = sync; word 1 = dtime (bits 0-31) |
# channel (32-39) | kind (40-47) | marker (48-55) | _pad (56-63). Checked here so a change of
# drivers/events.py cannot silently scramble decoded events.
assert EVENT_DTYPE.itemsize == 16
assert [EVENT_DTYPE.fields[f][1] for f in ("sync", "dtime", "channel", "kind", "marker")] == [0, 8, 12, 13, 14]

assert int(EventKind.PHOTON) == 0 and int(EventKind.MARKER) == 1


@dataclass
class T3DecoderState:
    """What decoding must remember from one chunk of records to the next.

    sync_base: syncs accumulated by overflow records so far, plus any offset the owner adds
               (e.g. to keep syncs increasing across a device restart).
    last_sync: sync of the last photon or marker decoded (-1 before the first); a lost-data event
               raised between chunks starts here.
    records:   records decoded so far (position in the stream).
    """

    sync_base: int = 0
    last_sync: int = -1
    records: int = 0


@dataclass
class T3EncoderState:
    """What encoding must remember between chunks: the overflow periods already emitted.

    sync_base: sync at the start of the current overflow period (a multiple of 1024 since the
               stream start).
    """

    sync_base: int = 0


# ---- decoding ------------------------------------------------------------------------------------

@njit(cache=True, nogil=True)
def _decode_kernel(records, out_words, sync_base):
    """Decode ``records`` (uint32[n]) into ``out_words`` (uint64[n, 2], EVENT_DTYPE rows).

    Returns (events written, new sync_base, sync of last event or -1, index of the first invalid
    record or -1). Stops at the first invalid record."""
    n_out = 0
    last_sync = -1
    for i in range(records.size):
        r = np.int64(records[i])      # uint32 fits: all arithmetic stays in int64
        nsync = r & 0x3FF             # nsync: 10 bits
        dtime = (r >> 10) & 0x7FFF    # dtime: 15 bits
        channel = (r >> 25) & 0x3F    # channel: 6 bits
        special = r >> 31             # special: 1 bit
        if special == 0:
            s = sync_base + nsync
            out_words[n_out, 0] = s
            out_words[n_out, 1] = dtime | (channel << 32)          # kind PHOTON = 0
            n_out += 1
            last_sync = s
        elif channel == 63:
            sync_base += 1024 * (nsync if nsync != 0 else 1)
        elif channel <= 15 and channel >= 1:
            s = sync_base + nsync
            out_words[n_out, 0] = s
            out_words[n_out, 1] = (1 << 40) | (channel << 48)     # kind MARKER, marker bits
            n_out += 1
            last_sync = s
        else:
            return n_out, sync_base, last_sync, i
    return n_out, sync_base, last_sync, -1


def describe_record(record: int) -> str:
    """Human-readable fields of one raw record, for error messages."""
    r = int(record)
    return (f"0x{r:08x} (special={r >> 31}, channel={(r >> 25) & 0x3F}, "
            f"dtime={(r >> 10) & 0x7FFF}, nsync={r & 0x3FF})")


def decode_t3(records: np.ndarray, state: T3DecoderState | None = None,
              out: np.ndarray | None = None) -> np.ndarray:
    """Decode Generic T3 records into events.

    records: uint32[n] raw records (or bytes-like of length 4n, little endian).
    state:   carried between consecutive chunks of one stream (overflows, position); a fresh
             state when None. Updated in place.
    out:     optional EVENT_DTYPE array of at least n rows to decode into (no allocation).
    Returns the EVENT_DTYPE events (a view of ``out`` when given), one per photon/marker record;
    overflow records only move the sync base. Syncs are ``state.sync_base`` plus laser syncs.
    Raises ProtocolError for a byte count that is not a multiple of 4 or an undefined record.
    """
    if state is None:
        state = T3DecoderState()
    if not isinstance(records, np.ndarray):
        raw = memoryview(records).cast("B")
        if raw.nbytes % 4:
            raise ProtocolError(f"T3 stream of {raw.nbytes} bytes is not a whole number of "
                                f"4-byte records ({raw.nbytes % 4} bytes left over)")
        records = np.frombuffer(raw, dtype=T3_RECORD_DTYPE)
    elif records.dtype != np.uint32:
        if records.dtype == np.uint8:
            if records.size % 4:
                raise ProtocolError(f"T3 stream of {records.size} bytes is not a whole number of "
                                    f"4-byte records ({records.size % 4} bytes left over)")
            records = np.ascontiguousarray(records).view(T3_RECORD_DTYPE)
        else:
            raise SettingError(f"T3 records must be uint32 or bytes, not {records.dtype}")
    records = records.reshape(-1)
    if out is None:
        out = np.empty(records.size, dtype=EVENT_DTYPE)
    elif out.dtype != EVENT_DTYPE or out.size < records.size or not out.flags.c_contiguous:
        raise SettingError(f"out must be a C-contiguous EVENT_DTYPE array of >= {records.size} rows")
    words = out.view(np.uint64).reshape(-1, 2)
    n, base, last, bad = _decode_kernel(records, words, np.int64(state.sync_base))
    if bad >= 0:
        raise ProtocolError(f"T3 record {state.records + bad} is not a photon, marker or overflow: "
                            f"{describe_record(records[bad])}")
    state.sync_base = int(base)
    if last >= 0:
        state.last_sync = int(last)
    state.records += records.size
    return out[:n]


# ---- encoding ------------------------------------------------------------------------------------

@njit(cache=True, nogil=True)
def _count_encoded(sync, kind, sync_base):
    """Records needed for events with these syncs (overflows included), or -(i+1) when event i
    goes back in time."""
    n = 0
    base = sync_base
    prev = sync_base
    for i in range(sync.size):
        s = np.int64(sync[i])
        if s < prev:
            return -(i + 1)
        prev = s
        wraps = (s - base) // 1024
        if wraps > 0:
            n += (wraps + 1022) // 1023
            base += wraps * 1024
        n += 1
    return n


@njit(cache=True, nogil=True)
def _encode_kernel(sync, dtime, channel, kind, marker, sync_base, out):
    """Write records for the events into ``out``; returns (records written, new sync_base,
    index of the first event that cannot be encoded or -1)."""
    n = 0
    base = sync_base
    for i in range(sync.size):
        s = np.int64(sync[i])
        wraps = (s - base) // 1024
        while wraps > 0:
            c = min(wraps, 1023)
            # special:1=1 | channel:6=63 | dtime:15=0 | nsync:10=count
            out[n] = np.uint32((1 << 31) | (63 << 25) | c)
            n += 1
            base += c * 1024
            wraps -= c
        nsync = np.uint32(s - base)
        k = kind[i]
        if k == 0:  # PHOTON
            if dtime[i] > 32767 or channel[i] > 63:
                return n, base, i
            out[n] = (np.uint32(channel[i]) << np.uint32(25)) | (np.uint32(dtime[i]) << np.uint32(10)) | nsync
        elif k == 1:  # MARKER
            m = marker[i]
            if m < 1 or m > 15:
                return n, base, i
            out[n] = np.uint32(1 << 31) | (np.uint32(m) << np.uint32(25)) | nsync
        else:
            return n, base, i
        n += 1
    return n, base, -1


def encode_t3(events: np.ndarray, state: T3EncoderState | None = None) -> np.ndarray:
    """Encode photon and marker events into Generic T3 records, inserting overflow records.

    events: EVENT_DTYPE[n] with non-decreasing ``sync`` >= ``state.sync_base`` (syncs since the
            stream start), photons with dtime <= 32767 and channel <= 63, markers with mask 1..15.
    state:  carried between chunks of one stream; updated in place.
    Returns uint32 records. Raises SettingError for events a T3 stream cannot carry (LOST events,
    syncs going backwards, fields out of range).
    """
    if state is None:
        state = T3EncoderState()
    if events.dtype != EVENT_DTYPE:
        raise SettingError(f"events must have EVENT_DTYPE, not {events.dtype}")
    events = events.reshape(-1)
    sync = events["sync"]
    kind = events["kind"]
    if sync.size and int(sync[0]) < state.sync_base:
        raise SettingError(f"event 0 at sync {int(sync[0])} precedes the encoder's overflow "
                         f"period starting at sync {state.sync_base}")
    count = _count_encoded(sync, kind, np.int64(state.sync_base))
    if count < 0:
        i = -count - 1
        raise SettingError(f"event {i} at sync {int(sync[i])} goes back in time "
                         f"(previous event at sync {int(sync[i - 1]) if i else state.sync_base})")
    out = np.empty(count, dtype=T3_RECORD_DTYPE)
    n, base, bad = _encode_kernel(sync, events["dtime"], events["channel"], kind,
                                  events["marker"], np.int64(state.sync_base), out)
    if bad >= 0:
        e = events[bad]
        raise SettingError(f"event {bad} cannot be a T3 record: kind={int(e['kind'])}, "
                         f"dtime={int(e['dtime'])}, channel={int(e['channel'])}, "
                         f"marker={int(e['marker'])} (photons: dtime <= {T3_DTIME_MAX}, "
                         f"channel <= 63; markers: mask 1..15; LOST has no record)")
    state.sync_base = int(base)
    return out[:n]
