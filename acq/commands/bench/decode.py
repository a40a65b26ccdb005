"""Decode speed of Generic T3 records, side by side on the same records: the numba decoder, a plain
vectorised NumPy decoder, and ptufile's compiled decoder.

    spdepth bench decode [--records N] [--repeat R] [--seed S]
    python -m spdepth.acq.commands.bench.decode [...]

Prints records/s (best of R runs, one core, output arrays preallocated for every decoder).
"""

from __future__ import annotations

import sys
import time

# numpy and the numba decoder are imported where used: ``spdepth bench decode --help`` loads neither


def make_records(n_records: int, seed: int = 0) -> np.ndarray:
    """A lidar-like stream: photons on 2 channels at about 0.05 per sync (so an overflow record
    every ~50 records), with pixel markers every ~100 records."""
    import numpy as np

    from spdepth.drivers.events import EVENT_DTYPE, EventKind
    from spdepth.drivers.tagger.t3 import encode_t3

    rng = np.random.default_rng(seed)
    n_events = int(n_records * 0.98)
    ev = np.zeros(n_events, dtype=EVENT_DTYPE)
    ev["sync"] = np.cumsum(rng.geometric(0.05, n_events))
    marker = rng.random(n_events) < 0.01
    ev["kind"] = np.where(marker, EventKind.MARKER, EventKind.PHOTON)
    ev["dtime"] = np.where(marker, 0, rng.integers(0, 12500, n_events))
    ev["channel"] = np.where(marker, 0, rng.integers(0, 2, n_events))
    ev["marker"] = np.where(marker, 1, 0)
    return encode_t3(ev)


def decode_numpy(records: np.ndarray, out: np.ndarray, sync_base: int = 0) -> int:
    """Vectorised NumPy decoder (the baseline): same output as ``decode_t3``; returns events."""
    import numpy as np

    r = records.astype(np.int64)
    nsync = r & 0x3FF                 # nsync: 10 bits
    dtime = (r >> 10) & 0x7FFF        # dtime: 15 bits
    channel = (r >> 25) & 0x3F        # channel: 6 bits
    special = (r >> 31).astype(bool)  # special: 1 bit
    overflow = special & (channel == 63)
    wraps = np.where(overflow, np.where(nsync == 0, 1, nsync), 0)
    base = sync_base + 1024 * (np.cumsum(wraps) - wraps)
    keep = ~overflow
    if np.any(special & ~overflow & ((channel < 1) | (channel > 15))):
        raise ValueError("undefined special record")
    n = int(np.count_nonzero(keep))
    o = out[:n]
    o["sync"] = (base + nsync)[keep]
    marker = special[keep]
    o["dtime"] = np.where(marker, 0, dtime[keep])
    o["channel"] = np.where(marker, 0, channel[keep])
    o["kind"] = marker
    o["marker"] = np.where(marker, channel[keep], 0)
    return n


def _best(fn, repeat: int) -> float:
    best = float("inf")
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def bench(argv: list[str]) -> int:
    from spdepth.acq.commands.bench import parser as bench_parser

    parser = bench_parser("decode", __doc__)
    parser.add_argument("--records", type=int, default=10_000_000, help="records to decode (10e6)")
    parser.add_argument("--repeat", type=int, default=5, help="runs per decoder, best kept (5)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the random records (0)")
    args = parser.parse_args(argv)
    if args.records < 1000 or args.repeat < 1:
        parser.error("--records must be >= 1000 and --repeat >= 1")
    import numpy as np

    from spdepth.drivers.events import EVENT_DTYPE
    from spdepth.drivers.tagger.t3 import T3DecoderState, decode_t3

    records = make_records(args.records, args.seed)
    n = records.size
    # zeroed, not empty: the rows' padding byte takes part in the equality checks below
    out = np.zeros(n, dtype=EVENT_DTYPE)
    decode_t3(records[:1000])                       # compile/load the kernel outside the timing
    rows = []

    t = _best(lambda: decode_t3(records, T3DecoderState(), out), args.repeat)
    ours = decode_t3(records, T3DecoderState(), out).copy()
    rows.append(("numba decode_t3 (drivers.tagger.t3)", t))

    ref = np.zeros(n, dtype=EVENT_DTYPE)
    t = _best(lambda: decode_numpy(records, ref), max(1, min(args.repeat, 2)))
    m = decode_numpy(records, ref)
    if m != ours.size or not np.array_equal(ref[:m], ours):
        print("NumPy and numba decoders disagree", file=sys.stderr)
        return 1
    rows.append(("NumPy vectorised", t))

    try:
        from ptufile import T3_RECORD_DTYPE, PtuRecordType
        from ptufile._ptufile import decode_t3_records   # what PtuFile.decode_records calls
    except ImportError as exc:
        print(f"ptufile decoder unavailable: {exc}", file=sys.stderr)
    else:
        pq = np.zeros(n, dtype=T3_RECORD_DTYPE)
        rectype = int(PtuRecordType.GenericT3)
        t = _best(lambda: decode_t3_records(pq, records, rectype), args.repeat)
        keep = (pq["channel"] >= 0) | (pq["marker"] > 0)
        if not np.array_equal(pq["time"][keep], ours["sync"]):
            print("ptufile and numba decoders disagree", file=sys.stderr)
            return 1
        rows.append(("ptufile decode_t3_records (compiled)", t))

    print(f"T3 decode, {n:,} records ({ours.size:,} events), best of {args.repeat}, one thread")
    print(f"{'decoder':40s} {'seconds':>9s} {'Mrecords/s':>11s}")
    for name, t in rows:
        print(f"{name:40s} {t:9.4f} {n / t / 1e6:11.1f}")
    return 0


if __name__ == "__main__":
    sys.exit(bench(sys.argv[1:]))
