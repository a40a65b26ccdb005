"""``spdepth bench sim``: does the simulated bench keep up with the pipeline?

Prints, after a warm-up scan (kernels compiled or loaded, nothing timed): the wall time of the
``spdepth demo`` command at its 96x96 size (scan session, then each estimator against the truth and
the PNG sheet) with its scan session's share, and the wall time of a count-gated 512x512 session at
30 detections per pixel through the real drivers (the simulated galvo on its pyserial URL, the
simulated tagger on pyusb, live reconstruction, recording), from start to done.

The module only uses ``spdepth`` imports, so the same file also measures another checkout
(``python acq/commands/bench/sim.py`` with that checkout's package on the path).
"""

from __future__ import annotations

import argparse
import io
import re
import sys
import tempfile
import time
from contextlib import redirect_stdout
from pathlib import Path


def demo_wall(size: str) -> tuple[float, float]:
    """(whole ``spdepth demo --no-window`` command, its scan session) wall seconds."""
    from spdepth.acq.cli import main

    with tempfile.TemporaryDirectory(prefix="spdepth-bench-") as tmp:
        out = io.StringIO()
        t0 = time.perf_counter()
        with redirect_stdout(out):
            code = main(["demo", "--no-window", "--size", size, "--out", str(Path(tmp) / "d.png")])
        wall = time.perf_counter() - t0
    if code != 0:
        raise SystemExit(f"spdepth demo exited {code}")
    # "... s of scan time in <elapsed> s (..." is the demo's own report of its session
    m = re.search(r"of scan time in ([0-9.]+) s", out.getvalue())
    return wall, float(m.group(1)) if m else float("nan")


def bench(argv: list[str]) -> int:
    from spdepth.acq.commands.bench.session import scan_and_replay

    p = argparse.ArgumentParser(prog="spdepth bench sim", description=__doc__)
    p.add_argument("--size", default="512x512", help="WxH of the gated session (default 512x512)")
    p.add_argument("--target", type=int, default=30, help="detections per pixel (default 30)")
    p.add_argument("--method", default="ml", help="live estimator of the session (default ml)")
    p.add_argument("--demo-size", default="96x96", help="WxH of the demo (default 96x96)")
    a = p.parse_args(argv)
    w, h = (int(v) for v in a.size.lower().split("x"))
    scan_and_replay((32, 32), a.target, a.method, 0, replay=False)          # warm-up
    demo_wall("16x16")                                                      # warm-up
    demo, demo_scan = demo_wall(a.demo_size)
    print(f"demo {a.demo_size} (spdepth demo --no-window, warm): {demo:.2f} s wall, of which "
          f"its scan session {demo_scan:.2f} s", flush=True)
    res = scan_and_replay((h, w), a.target, a.method, 0, replay=False)
    print(f"gated session {w}x{h}, target {a.target}, live {a.method}, simulated devices through "
          f"the real drivers: {res['scan_wall_s']:.2f} s wall, {res['detections']:,} detections "
          f"({res['detections'] / res['scan_wall_s'] / 1e6:.2f} M/s), {res['passes']} "
          f"pass{'es' if res['passes'] != 1 else ''}, state {res['state']}, live recon busy "
          f"{res['recon_busy_s']:.2f} s")
    return 0


if __name__ == "__main__":
    sys.exit(bench(sys.argv[1:]))
