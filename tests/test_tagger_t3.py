"""T3 records: numba decoder vs the plain reference, encoder round trips, chunking, fuzzing, and a
real HydraHarp v2 PTU file against ptufile's own decoder."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from spdepth.drivers.errors import ProtocolError, SettingError
from spdepth.drivers.events import EVENT_DTYPE, EventKind
from spdepth.drivers.tagger.t3 import (T3DecoderState, T3EncoderState, decode_t3, encode_t3)
from reference_t3 import reference_decode_t3


def random_events(rng, n: int, max_gap_syncs: int = 5000, marker_share: float = 0.05) -> np.ndarray:
    """A valid event stream: non-decreasing syncs with gaps up to ``max_gap_syncs`` (so several
    overflow periods and multi-count overflow records occur), photons and markers."""
    ev = np.zeros(n, dtype=EVENT_DTYPE)
    ev["sync"] = np.cumsum(rng.integers(0, max_gap_syncs, n))
    marker = rng.random(n) < marker_share
    ev["kind"] = np.where(marker, EventKind.MARKER, EventKind.PHOTON)
    ev["dtime"] = np.where(marker, 0, rng.integers(0, 2 ** 15, n))
    ev["channel"] = np.where(marker, 0, rng.integers(0, 64, n))
    ev["marker"] = np.where(marker, rng.integers(1, 16, n), 0)
    return ev


def random_valid_records(rng, n: int) -> np.ndarray:
    """Random records of every defined kind (photons, markers, overflows with any count)."""
    nsync = rng.integers(0, 1024, n, dtype=np.uint32)
    dtime = rng.integers(0, 2 ** 15, n, dtype=np.uint32)
    kind = rng.integers(0, 3, n)
    channel = np.where(kind == 0, rng.integers(0, 64, n),
                       np.where(kind == 1, rng.integers(1, 16, n), 63)).astype(np.uint32)
    special = (kind > 0).astype(np.uint32)
    return (special << 31) | (channel << 25) | (dtime << 10) | nsync


def test_decoder_matches_reference_on_random_records(rng):
    records = random_valid_records(rng, 20000)
    got = decode_t3(records, T3DecoderState(sync_base=7))
    want, base = reference_decode_t3(records, sync_base=7)
    np.testing.assert_array_equal(got, want)


def test_decoder_carries_overflow_state_across_chunks(rng):
    records = random_valid_records(rng, 10000)
    whole_state = T3DecoderState()
    whole = decode_t3(records, whole_state)
    state = T3DecoderState()
    cuts = np.sort(rng.integers(0, records.size, 12))
    parts = [decode_t3(part, state) for part in np.split(records, cuts)]
    np.testing.assert_array_equal(np.concatenate(parts), whole)
    assert state.sync_base == whole_state.sync_base
    assert state.records == records.size
    assert state.last_sync == int(whole["sync"][-1])


def test_encode_decode_round_trip_in_chunks(rng):
    events = random_events(rng, 30000)
    enc = T3EncoderState()
    cuts = np.sort(rng.integers(0, events.size, 9))
    records = np.concatenate([encode_t3(part, enc) for part in np.split(events, cuts)])
    n_overflow = np.count_nonzero(records >> 25 == 0x7F)
    assert n_overflow >= events["sync"][-1] // (1024 * 1023)  # long gaps need many overflows
    np.testing.assert_array_equal(decode_t3(records), events)
    np.testing.assert_array_equal(reference_decode_t3(records)[0], events)


def test_encoder_splits_long_gaps_into_full_overflow_records():
    ev = np.zeros(1, dtype=EVENT_DTYPE)
    ev["sync"] = 1024 * 1023 * 2 + 1024 * 5 + 17
    records = encode_t3(ev)
    overflow = 0xFE000000
    assert records.tolist() == [overflow | 1023, overflow | 1023, overflow | 5, 17]


def test_overflow_count_zero_means_one_period():
    records = np.array([0xFE000000, 0x00000003], dtype=np.uint32)
    ev = decode_t3(records)
    assert ev["sync"].tolist() == [1024 + 3]


def test_decode_exact_bit_layout():
    # special=0 channel=5 dtime=0x1234 nsync=0x155; then marker bits 0b1010 at nsync 9
    photon = (5 << 25) | (0x1234 << 10) | 0x155
    marker = (1 << 31) | (0b1010 << 25) | 9
    ev = decode_t3(np.array([photon, marker], dtype=np.uint32))
    assert ev[0].tolist() == (0x155, 0x1234, 5, EventKind.PHOTON, 0, 0)
    assert ev[1].tolist() == (9, 0, 0, EventKind.MARKER, 0b1010, 0)


@pytest.mark.parametrize("channel", [0, 16, 40, 62])
def test_undefined_special_records_raise(channel):
    records = np.array([5, (1 << 31) | (channel << 25) | 3], dtype=np.uint32)
    with pytest.raises(ProtocolError, match=r"record 1 .*channel=%d" % channel):
        decode_t3(records)


def test_truncated_bytes_raise():
    with pytest.raises(ProtocolError, match="4-byte records"):
        decode_t3(b"\x01\x02\x03\x04\x05")
    with pytest.raises(ProtocolError, match="4-byte records"):
        decode_t3(np.zeros(6, dtype=np.uint8))


def test_decode_into_preallocated_out(rng):
    records = random_valid_records(rng, 500)
    out = np.zeros(1000, dtype=EVENT_DTYPE)
    ev = decode_t3(records, out=out)
    assert np.shares_memory(ev, out)
    np.testing.assert_array_equal(ev, reference_decode_t3(records)[0])
    with pytest.raises(SettingError):
        decode_t3(records, out=np.zeros(10, dtype=EVENT_DTYPE))


@pytest.mark.parametrize("field,value", [("dtime", 2 ** 15), ("channel", 64), ("marker", 0),
                                         ("marker", 16), ("kind", EventKind.LOST)])
def test_encoder_rejects_what_t3_cannot_carry(field, value):
    ev = np.zeros(3, dtype=EVENT_DTYPE)
    ev["sync"] = [1, 2, 3]
    ev["kind"][1] = EventKind.MARKER if field == "marker" else EventKind.PHOTON
    ev["marker"][1] = 1 if field != "marker" else 0
    ev[field][1] = value
    with pytest.raises(SettingError, match="event 1"):
        encode_t3(ev)


def test_encoder_rejects_time_going_backwards():
    ev = np.zeros(3, dtype=EVENT_DTYPE)
    ev["sync"] = [10, 5000, 4999]
    with pytest.raises(SettingError, match="event 2 .* back in time"):
        encode_t3(ev)
    state = T3EncoderState()
    encode_t3(ev[:2], state)
    with pytest.raises(SettingError, match="precedes"):
        encode_t3(ev[:1], state)


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=64))
def test_fuzz_bytes_decode_or_protocol_error(data):
    # Raising is right only where the reference raises too (a ragged tail, an undefined record).
    if len(data) % 4:
        with pytest.raises(ProtocolError, match="4-byte records"):
            decode_t3(data)
        return
    try:
        want, _ = reference_decode_t3(np.frombuffer(data, dtype="<u4"))
    except ProtocolError:
        with pytest.raises(ProtocolError):
            decode_t3(data)
        return
    ev = decode_t3(data)
    assert ev.dtype == EVENT_DTYPE and ev.size <= len(data) // 4
    np.testing.assert_array_equal(ev, want)


@settings(max_examples=200, deadline=None)
@given(st.lists(st.integers(0, 2 ** 32 - 1), max_size=40), st.integers(0, 2 ** 40))
def test_fuzz_records_match_reference(values, base):
    records = np.array(values, dtype=np.uint32)
    try:
        want, want_base = reference_decode_t3(records, base)
    except ProtocolError:
        with pytest.raises(ProtocolError):
            decode_t3(records, T3DecoderState(sync_base=base))
        return
    state = T3DecoderState(sync_base=base)
    np.testing.assert_array_equal(decode_t3(records, state), want)
    assert state.sync_base == want_base


def test_real_hydraharp_v2_ptu_matches_ptufile(shared_data):
    ptufile = pytest.importorskip("ptufile")
    path = shared_data / "ptu" / "hydraharp_v20_t3.ptu"
    if not path.exists():
        pytest.skip(f"{path} not found")
    with ptufile.PtuFile(path) as f:
        assert f.record_type == ptufile.PtuRecordType.HydraHarp2T3
        records = f.read_records()
        theirs = f.decode_records(records)
    ours = decode_t3(records)
    keep = (theirs["channel"] >= 0) | (theirs["marker"] > 0)   # ptufile keeps overflow rows
    theirs = theirs[keep]
    assert ours.size == theirs.size == 77883
    photon = theirs["channel"] >= 0
    np.testing.assert_array_equal(ours["sync"], theirs["time"])
    np.testing.assert_array_equal(ours["kind"], np.where(photon, EventKind.PHOTON, EventKind.MARKER))
    np.testing.assert_array_equal(ours["dtime"][photon], theirs["dtime"][photon])
    np.testing.assert_array_equal(ours["channel"][photon], theirs["channel"][photon])
    # and our encoder writes the same stream back (overflow records may be grouped differently)
    again = decode_t3(encode_t3(ours))
    np.testing.assert_array_equal(again, ours)


def test_bench_times_three_decoders_on_the_same_records(capsys):
    from spdepth.acq.commands.bench.decode import bench, make_records

    assert bench(["--records", "200000", "--repeat", "1", "--seed", "3"]) == 0
    out = capsys.readouterr().out.splitlines()
    n = make_records(200000, 3).size
    assert out[0].startswith(f"T3 decode, {n:,} records")
    rows = {line[:40].strip(): line[40:].split() for line in out[2:]}
    assert [name.split()[0] for name in rows] == ["numba", "NumPy", "ptufile"]
    for name, (seconds, mrec_per_s) in rows.items():
        t, rate = float(seconds), float(mrec_per_s)
        assert t > 0 and rate > 0, name
        # the rate is the records over the time (both printed rounded), not a made-up number
        assert n / (t + 5e-5) / 1e6 - 0.05 <= rate <= n / max(t - 5e-5, 1e-9) / 1e6 + 0.05, name


def test_bench_numpy_baseline_decodes_like_the_kernel(rng):
    from spdepth.acq.commands.bench.decode import decode_numpy, make_records

    records = make_records(5000, 1)
    want = decode_t3(records, T3DecoderState(sync_base=11))
    out = np.zeros(records.size, dtype=EVENT_DTYPE)
    n = decode_numpy(records, out, sync_base=11)
    np.testing.assert_array_equal(out[:n], want)
    bad = np.append(records, np.uint32((1 << 31) | (40 << 25)))    # undefined special record
    with pytest.raises(ValueError, match="undefined special"):
        decode_numpy(bad, np.zeros(bad.size, dtype=EVENT_DTYPE))


@pytest.mark.parametrize("argv", [["--records", "999"], ["--repeat", "0"]])
def test_bench_refuses_too_few_records_or_runs(argv, capsys):
    from spdepth.acq.commands.bench.decode import bench

    with pytest.raises(SystemExit) as exc:
        bench(argv)
    assert exc.value.code == 2 and "--records must be >= 1000" in capsys.readouterr().err


def test_warm_up_loads_every_kernel_a_reader_runs_with_the_types_a_reader_passes():
    # a reader hands decode_t3 uint32 views of its read buffer; warm_up must have loaded the
    # kernels for exactly those types, or the first real chunk still compiles in the reader thread
    from spdepth.drivers.tagger import t3

    t3.warm_up()
    kernels = (t3._decode_kernel, t3._count_split_extra, t3._split_kernel)
    before = [len(k.signatures) for k in kernels]
    assert all(before)
    buf = bytearray(t3.encode_t3(_warm_events()).tobytes())
    records = np.frombuffer(buf, np.uint8).view(np.uint32)
    t3.decode_t3(t3.split_marker_records(records))
    assert [len(k.signatures) for k in kernels] == before


def test_warm_up_loads_the_encoder_for_chunks_of_any_length():
    # a simulated tagger encodes in the reader's thread; a chunk of one event gives contiguous field
    # views, another specialisation than longer chunks: compiled there, it stalled a first scan
    from spdepth.drivers.tagger import t3

    t3.warm_up()
    kernels = (t3._count_encoded, t3._encode_kernel)
    before = [len(k.signatures) for k in kernels]
    for n in (1, 2):
        ev = _warm_events()[:n]
        t3.encode_t3(ev, t3.T3EncoderState())
    assert [len(k.signatures) for k in kernels] == before


def _warm_events():
    ev = np.zeros(2, dtype=EVENT_DTYPE)
    ev["sync"] = (5, 9)
    ev["kind"] = (EventKind.MARKER, EventKind.PHOTON)
    ev["marker"][0] = 0b101
    return ev
