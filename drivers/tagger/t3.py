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

The numba kernels (``_decode_kernel``, ``_count_encoded``, ``_encode_kernel``, ``_split_kernel``)
take plain arrays; ``decode_t3``/``encode_t3``/``split_marker_records`` validate, allocate and carry
the overflow state between chunks. This is the one Generic T3 encoder: the simulated tagger and
``acq.ptu`` (files) both use it.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass

import numpy as np
from numba import njit

from spdepth.drivers.errors import ProtocolError, SettingError
from spdepth.drivers.events import EVENT_DTYPE, EventKind, Marker
from spdepth.drivers.jit import call_strided

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
T3_CHANNEL_MAX = 2 ** 6 - 1
"""Largest ``channel`` field (6 bits): the highest detector channel a photon record carries."""

T3_DTIME_SHIFT = 10
"""Bit position of ``dtime`` (above the 10 bits of ``nsync``)."""
T3_CHANNEL_SHIFT = 25
"""Bit position of ``channel`` (above ``dtime``)."""
T3_SPECIAL_SHIFT = 31
"""Bit position of ``special`` (the top bit)."""
# The numba kernels read these module-level ints as compile-time constants (numba freezes global
# ints when it compiles), so naming them costs nothing at run time.

KIND_PHOTON = int(EventKind.PHOTON)
KIND_MARKER = int(EventKind.MARKER)

MARKER_SPLIT_ORDER = (Marker.FRAME, Marker.LINE_START, Marker.PIXEL, Marker.LINE_STOP)
"""The order in which one marker record with several bits becomes several records
(``split_marker_records``): the order ``acq.assign`` applies the bits of a combined record, so
the split stream assigns every photon exactly as the combined one. The device's marker inputs
are the ``Marker`` bits (input n = mask ``1 << (n - 1)``)."""

T3_RECORD_DTYPE = np.dtype("<u4")
"""One raw Generic T3 record: ``special:1 | channel:6 | dtime:15 | nsync:10`` (MSB to LSB),
little endian. See the module docstring for the meaning of each kind."""

if sys.byteorder != "little":  # the kernels write EVENT_DTYPE rows as two native uint64 words
    raise ImportError("spdepth.drivers.tagger.t3 assumes a little-endian host")

# EVENT_DTYPE row as two little-endian 64-bit words: word 0 = sync; word 1 = dtime (bits 0-31) |
# channel (32-39) | kind (40-47) | marker (48-55) | _pad (56-63). Checked here so a change of
# drivers/events.py cannot silently scramble decoded events.
assert EVENT_DTYPE.itemsize == 16
assert [EVENT_DTYPE.fields[f][1] for f in ("sync", "dtime", "channel", "kind", "marker")] == [0, 8, 12, 13, 14]

assert sorted(int(m) for m in MARKER_SPLIT_ORDER) == [1, 2, 4, 8]  # every marker input once


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
        nsync = r & (T3_WRAP_SYNCS - 1)                         # nsync: 10 bits
        dtime = (r >> T3_DTIME_SHIFT) & T3_DTIME_MAX            # dtime: 15 bits
        channel = (r >> T3_CHANNEL_SHIFT) & T3_CHANNEL_MAX      # channel: 6 bits
        special = r >> T3_SPECIAL_SHIFT                         # special: 1 bit
        if special == 0:
            s = sync_base + nsync
            out_words[n_out, 0] = s
            out_words[n_out, 1] = dtime | (channel << 32) | (KIND_PHOTON << 40)
            n_out += 1
            last_sync = s
        elif channel == T3_OVERFLOW_CHANNEL:
            sync_base += T3_WRAP_SYNCS * (nsync if nsync != 0 else 1)
        elif channel <= T3_MARKER_MASK_MAX and channel >= 1:
            s = sync_base + nsync
            out_words[n_out, 0] = s
            out_words[n_out, 1] = (KIND_MARKER << 40) | (channel << 48)    # marker bits
            n_out += 1
            last_sync = s
        else:
            return n_out, sync_base, last_sync, i
    return n_out, sync_base, last_sync, -1


def describe_record(record: int) -> str:
    """Human-readable fields of one raw record, for error messages."""
    r = int(record)
    return (f"0x{r:08x} (special={r >> T3_SPECIAL_SHIFT}, "
            f"channel={(r >> T3_CHANNEL_SHIFT) & T3_CHANNEL_MAX}, "
            f"dtime={(r >> T3_DTIME_SHIFT) & T3_DTIME_MAX}, nsync={r & (T3_WRAP_SYNCS - 1)})")


def invalid_record(index: int, record: int) -> ProtocolError:
    """The error for stream record ``index`` (from the stream's start), which :func:`_decode_kernel`
    stopped at."""
    return ProtocolError(f"T3 record {index} is not a photon, marker or overflow: {describe_record(record)}")


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
        raise invalid_record(state.records + bad, records[bad])
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
        wraps = (s - base) // T3_WRAP_SYNCS
        if wraps > 0:
            n += (wraps + T3_MAX_OVERFLOW_COUNT - 1) // T3_MAX_OVERFLOW_COUNT
            base += wraps * T3_WRAP_SYNCS
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
        wraps = (s - base) // T3_WRAP_SYNCS
        while wraps > 0:
            c = min(wraps, T3_MAX_OVERFLOW_COUNT)
            # special:1=1 | channel:6=63 | dtime:15=0 | nsync:10=count
            out[n] = np.uint32((1 << T3_SPECIAL_SHIFT) | (T3_OVERFLOW_CHANNEL << T3_CHANNEL_SHIFT) | c)
            n += 1
            base += c * T3_WRAP_SYNCS
            wraps -= c
        nsync = np.uint32(s - base)
        k = kind[i]
        if k == KIND_PHOTON:
            if dtime[i] > T3_DTIME_MAX or channel[i] > T3_CHANNEL_MAX:
                return n, base, i
            # special:1=0 | channel:6 | dtime:15 | nsync:10
            out[n] = ((np.uint32(channel[i]) << np.uint32(T3_CHANNEL_SHIFT))
                      | (np.uint32(dtime[i]) << np.uint32(T3_DTIME_SHIFT)) | nsync)
        elif k == KIND_MARKER:
            m = marker[i]
            if m < 1 or m > T3_MARKER_MASK_MAX:
                return n, base, i
            # special:1=1 | channel:6=marker bits | dtime:15=0 | nsync:10
            out[n] = (np.uint32(1 << T3_SPECIAL_SHIFT) | (np.uint32(m) << np.uint32(T3_CHANNEL_SHIFT))
                      | nsync)
        else:
            return n, base, i
        n += 1
    return n, base, -1


def encode_t3(events: np.ndarray, state: T3EncoderState | None = None, *,
              split_markers: bool = False) -> np.ndarray:
    """Encode photon and marker events into Generic T3 records, inserting overflow records.

    events: EVENT_DTYPE[n] with non-decreasing ``sync`` >= ``state.sync_base`` (syncs since the
            stream start), photons with dtime <= 32767 and channel <= 63, markers with mask 1..15.
    state:  carried between chunks of one stream; updated in place.
    split_markers: False writes a marker event with several bits as one record, as the device
            does; True writes one record per bit (``split_marker_records``), as files for other
            tools need.
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
    count = call_strided(_count_encoded, (0, 1), sync, kind, np.int64(state.sync_base))
    if count < 0:
        i = -count - 1
        raise SettingError(f"event {i} at sync {int(sync[i])} goes back in time "
                         f"(previous event at sync {int(sync[i - 1]) if i else state.sync_base})")
    out = np.empty(count, dtype=T3_RECORD_DTYPE)
    n, base, bad = call_strided(_encode_kernel, (0, 1, 2, 3, 4), sync, events["dtime"],
                                events["channel"], kind, events["marker"],
                                np.int64(state.sync_base), out)
    if bad >= 0:
        e = events[bad]
        raise SettingError(f"event {bad} cannot be a T3 record: kind={int(e['kind'])}, "
                         f"dtime={int(e['dtime'])}, channel={int(e['channel'])}, "
                         f"marker={int(e['marker'])} (photons: dtime <= {T3_DTIME_MAX}, "
                         f"channel <= {T3_CHANNEL_MAX}; markers: mask 1..{T3_MARKER_MASK_MAX}; "
                         f"LOST has no record)")
    state.sync_base = int(base)
    return split_marker_records(out[:n]) if split_markers else out[:n]


# ---- one marker kind per record ----------------------------------------------------------------

def _split_tables() -> tuple[np.ndarray, np.ndarray]:
    """For each marker channel value 0..15: its bits in ``MARKER_SPLIT_ORDER`` and their count."""
    bits = np.zeros((T3_MARKER_MASK_MAX + 1, len(MARKER_SPLIT_ORDER)), np.uint32)
    count = np.zeros(T3_MARKER_MASK_MAX + 1, np.int64)
    for m in range(1, T3_MARKER_MASK_MAX + 1):
        for b in MARKER_SPLIT_ORDER:
            if m & int(b):
                bits[m, count[m]] = int(b)
                count[m] += 1
    return bits, count


_SPLIT_BITS, _SPLIT_COUNT = _split_tables()


@njit(cache=True, nogil=True)
def _count_split_extra(records, count):
    """Records that splitting adds: for each marker record, its number of bits minus one."""
    extra = 0
    for i in range(records.size):
        r = records[i]
        if (r >> T3_SPECIAL_SHIFT) != 0:
            ch = (r >> T3_CHANNEL_SHIFT) & T3_CHANNEL_MAX       # channel: 6 bits
            if ch >= 1 and ch <= T3_MARKER_MASK_MAX:
                extra += count[ch] - 1
    return extra


@njit(cache=True, nogil=True)
def _split_kernel(records, bits, count, out):
    """Copy ``records`` into ``out``, each marker record as ``count[ch]`` records carrying one bit
    each (``bits[ch, :count[ch]]``), same nsync; returns records written."""
    keep = np.uint32(~(T3_CHANNEL_MAX << T3_CHANNEL_SHIFT) & 0xFFFFFFFF)   # all but channel:6
    n = 0
    for i in range(records.size):
        r = records[i]
        if (r >> T3_SPECIAL_SHIFT) != 0:
            ch = (r >> T3_CHANNEL_SHIFT) & T3_CHANNEL_MAX
            if ch >= 1 and ch <= T3_MARKER_MASK_MAX and count[ch] > 1:
                rest = r & keep
                for k in range(count[ch]):
                    out[n] = rest | (bits[ch, k] << np.uint32(T3_CHANNEL_SHIFT))
                    n += 1
                continue
        out[n] = r
        n += 1
    return n


def split_marker_records(records: np.ndarray) -> np.ndarray:
    """One record per marker bit: every marker record whose channel field has several bits set
    becomes one record per bit, same nsync (and dtime), in ``MARKER_SPLIT_ORDER`` (FRAME,
    LINE_START, PIXEL, LINE_STOP). Photons, overflows and single-bit markers are copied unchanged,
    in order.

    Tools that match marker values whole (tttrlib) see the device's ``FRAME|LINE_START|PIXEL``
    record as none of them; after splitting they see each. ``acq.assign`` gives the split stream
    the same pixels as the combined one, since it applies combined bits in this same order.

    records: uint32[n] Generic T3 records. Returns a new uint32 array, or a view of ``records``
    when there is nothing to split (no copy). Runs at hundreds of millions of records per second.
    """
    records = np.ascontiguousarray(records)
    if records.dtype != np.uint32:
        raise SettingError(f"T3 records must be uint32, not {records.dtype}")
    records = records.reshape(-1)
    extra = _count_split_extra(records, _SPLIT_COUNT)
    if extra == 0:
        return records
    out = np.empty(records.size + extra, dtype=T3_RECORD_DTYPE)
    n = _split_kernel(records, _SPLIT_BITS, _SPLIT_COUNT, out)
    assert n == out.size
    return out


def warm_up() -> None:
    """Load (on a cold cache: compile) the decoding and encoding kernels a reader thread runs, on
    three made-up events. A reader calls it before START: compiling them on the first real chunk,
    in the reader thread, takes seconds on a fresh install while the device's FIFO fills."""
    ev = np.zeros(3, dtype=EVENT_DTYPE)
    ev["sync"] = (1, 2, 1 << 20)                  # the last needs overflow records
    ev["kind"] = (EventKind.PHOTON, EventKind.MARKER, EventKind.PHOTON)
    ev["marker"][1] = 0b11                        # two bits: the split kernel runs
    records = encode_t3(ev)
    decode_t3(records)
    decode_t3(split_marker_records(records))
    # a chunk of one event has contiguous field views: the encoder's one strided specialisation
    # (drivers.jit.call_strided) serves it too, so nothing more compiles in the reader's thread
