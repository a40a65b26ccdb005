"""``spdepth bench sim``: does the simulated bench keep up with the pipeline?

Prints, after a warm-up session (kernels compiled or loaded, nothing timed), the wall time from
start to done of two count-gated sessions through the real drivers (the simulated galvo on its
pyserial URL, the simulated tagger on pyusb, live reconstruction, recording): the one ``spdepth
demo`` runs at 96x96 with its defaults, and a 512x512 one at 30 detections per pixel.

The module only uses ``spdepth`` imports, so the same file also measures another checkout
(``python acq/commands/bench/sim.py`` with that checkout's package on the path).
"""

from __future__ import annotations

import argparse
import sys


def bench(argv: list[str]) -> int:
    from spdepth.acq.params import DEFAULT_METHOD, DEFAULT_TARGET, parse_size

    p = argparse.ArgumentParser(prog="spdepth bench sim", description=__doc__)
    p.add_argument("--size", type=parse_size, default=(512, 512), metavar="WxH",
                   help="pixels of the big session (default 512x512)")
    p.add_argument("--target", type=int, default=30, help="its detections per pixel (default 30)")
    p.add_argument("--method", default=DEFAULT_METHOD,
                   help=f"live estimator of both sessions (default {DEFAULT_METHOD})")
    p.add_argument("--demo-size", type=parse_size, default=(96, 96), metavar="WxH",
                   help="pixels of the demo's session (default 96x96)")
    a = p.parse_args(argv)
    from spdepth.acq.commands.bench.session import scan_and_replay

    for label, size, target in (("demo", a.demo_size, DEFAULT_TARGET),
                                ("gated session", a.size, a.target)):
        h, w = size
        scan_and_replay((32, 32), target, a.method, 0, replay=False)          # warm-up
        res = scan_and_replay((h, w), target, a.method, 0, replay=False)
        print(f"{label} {w}x{h}, target {target}, live {a.method}: {res['scan_wall_s']:.2f} s "
              f"wall, {res['detections']:,} detections "
              f"({res['detections'] / res['scan_wall_s'] / 1e6:.2f} M/s), {res['passes']} "
              f"pass{'es' if res['passes'] != 1 else ''}, {res['state']}, live recon busy "
              f"{res['recon_busy_s']:.2f} s", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(bench(sys.argv[1:]))
