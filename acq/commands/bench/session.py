"""``spdepth bench session``: the acquisition session end to end on the simulated bench.

Prints, from one run: a count-gated scan through the real drivers (wall time, detections/s, the
live reconstruction's backlog sampled through the scan and how long after the last pixel the
maps were complete), the replay of its recording at full speed (detections/s from the first record
read to the last photon assigned), and the peak memory of the process. ``--memory`` runs only a
scan (no replay) in a fresh process and reports its peak RSS, for the 1024 x 1024 figure.
"""

from __future__ import annotations

import argparse
import resource
import shutil
import sys
import tempfile
import time
from pathlib import Path


def _peak_rss_mb() -> float:
    kb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss   # kilobytes on Linux
    return kb / 1024


def scan_and_replay(size, target, method, seed, keep_dir=None, replay=True):
    import numpy as np

    from spdepth.acq.api import build_session, open_instruments
    from spdepth.acq.requests import ReplayRequest, ScanRequest, SimBench

    tmp = Path(keep_dir or tempfile.mkdtemp(prefix="spdepth-bench-"))
    lag = []
    request = ScanRequest(instruments=SimBench(scene="bust", seed=seed), size=tuple(size),
                          target=target, method=method)
    try:
        with open_instruments(request) as inst:
            s = build_session(request, tmp / "live", inst)
            s.subscribe(lambda snap: lag.append((snap.pixels_final / snap.pixels_total,
                                                 snap.recon_lag, snap.state)), max_hz=10)
            t0 = time.perf_counter()
            s.start()
            s.wait()
            wall = time.perf_counter() - t0
        st = s.snapshot()
        out = {"scan_wall_s": wall, "scan_running_s": st.detections / max(st.detections_per_s, 1e-9),
               "detections": st.detections, "scan_det_per_s": st.detections_per_s,
               "passes": st.passes, "state": s.state.value, "max_lag": s.live_recon.max_lag,
               "recon_busy_s": s.live_recon.busy_s, "lag_samples": lag,
               "rss_after_scan_mb": _peak_rss_mb()}
        if replay:
            r = build_session(ReplayRequest(recording=str(tmp / "live")), tmp / "replay")
            r.start()
            r.wait()
            out.update(replay_detections=r.detections, replay_stream_s=r.stream_s,
                       replay_det_per_s=r.detections / r.stream_s if r.stream_s else float("nan"),
                       replay_equal=bool(np.array_equal(r.maps().tof_s, s.maps().tof_s,
                                                        equal_nan=True)))
        return out
    finally:
        if keep_dir is None:
            shutil.rmtree(tmp, ignore_errors=True)


def replay_simulated(size, ppp, method="lmf", repeats=3):
    """Replay rate on a bigger stream than a bench scan makes: a fixed-dwell ``spdepth simulate``
    PTU (pixel markers, one frame), replayed ``repeats`` times; returns (detections, best
    stream_s)."""
    from spdepth.acq.api import build_session
    from spdepth.acq.cli import main
    from spdepth.acq.requests import ReplayRequest
    from spdepth.recon.model import SEED_PAPER

    w, h = size
    tmp = Path(tempfile.mkdtemp(prefix="spdepth-bench-"))
    try:
        ptu = tmp / "sim.ptu"
        main(["simulate", "--scene", "bust", "--size", f"{w}x{h}", "--ppp", str(ppp),
              "--ptu", str(ptu)])
        best = None
        for i in range(repeats):
            r = build_session(ReplayRequest(recording=str(ptu), target=int(ppp), method=method,
                                            pulse_rms_s=SEED_PAPER.pulse_rms_s), tmp / f"r{i}")
            r.start()
            r.wait()
            best = r.stream_s if best is None else min(best, r.stream_s)
        return r.detections, best
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def bench(argv: list[str]) -> int:
    from spdepth.acq.params import parse_size

    p = argparse.ArgumentParser(prog="spdepth bench session", description=__doc__)
    p.add_argument("--size", type=parse_size, default=(256, 256), metavar="WxH",
                   help="pixels (default 256x256)")
    p.add_argument("--target", type=int, default=15, help="detections per pixel (default 15)")
    p.add_argument("--method", default="ml", help="live estimator (default ml)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--replay-size", default="512x512",
                   help="WxH of the simulated PTU for the big replay figure (default 512x512, 30 per "
                        "pixel; 'none' skips it)")
    p.add_argument("--memory", action="store_true",
                   help="scan only and report the peak RSS (run e.g. --size 1024x1024 --target 30)")
    a = p.parse_args(argv)
    h, w = a.size
    print(f"spdepth bench session: bust {w}x{h}, target {a.target}, live {a.method}, gated, "
          f"simulated devices through the real drivers", flush=True)
    from spdepth.acq.report import plural

    res = scan_and_replay((h, w), a.target, a.method, a.seed, replay=not a.memory)
    print(f"scan    {res['state']}: {res['detections']:,} detections, {plural(res['passes'], 'pass')}, "
          f"wall {res['scan_wall_s']:.2f} s, {res['scan_det_per_s'] / 1e6:.3f} M detections/s "
          f"while running")
    samples = res["lag_samples"]
    marks = []
    for q in (0.25, 0.5, 0.75, 1.0):
        at = [lag for frac, lag, state in samples if frac >= q - 1e-9]
        marks.append(f"{int(q * 100)}%: {at[0] if at else '-'}")
    print(f"live recon backlog (pixels waiting, sampled at 10 Hz) at scan progress "
          f"{', '.join(marks)}; max {res['max_lag']}; recon busy {res['recon_busy_s']:.2f} s of "
          f"{res['scan_wall_s']:.2f} s")
    if "replay_det_per_s" in res:
        print(f"replay  --speed max: {res['replay_detections']:,} detections in "
              f"{res['replay_stream_s']:.3f} s = {res['replay_det_per_s'] / 1e6:.1f} M detections/s "
              f"(first record read to last photon assigned); maps equal live: {res['replay_equal']}")
    if not a.memory and a.replay_size != "none":
        rw, rh = (int(v) for v in a.replay_size.lower().split("x"))
        n, best = replay_simulated((rw, rh), 30)
        print(f"replay  --speed max of a simulated {rw}x{rh} PTU (30 per pixel, fixed dwell): "
              f"{n:,} detections in {best:.3f} s = {n / best / 1e6:.1f} M detections/s (best of 3)")
    print(f"peak RSS {_peak_rss_mb():.0f} MB (whole process, Python and libraries included)")
    return 0


if __name__ == "__main__":
    sys.exit(bench(sys.argv[1:]))
