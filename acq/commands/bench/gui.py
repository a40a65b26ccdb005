"""``spdepth bench gui``: does the window slow the scan? Detections/s of the same simulated scan
(and a replay of it) headless and with the window open, alternated (``gui.benchmark.measure``)."""

from __future__ import annotations

import argparse
import sys

from spdepth.acq.commands._args import positive_int
from spdepth.acq.params import parse_size


def bench(argv=None) -> int:
    from spdepth.gui.benchmark import measure

    ap = argparse.ArgumentParser(prog="spdepth bench gui", description=__doc__)
    ap.add_argument("--size", type=parse_size, default=(48, 48), metavar="WxH")
    ap.add_argument("--target", type=positive_int, default=10)
    ap.add_argument("--scene", default="bust")
    ap.add_argument("--repeats", type=positive_int, default=3)
    ap.add_argument("--no-replay", action="store_true", help="skip the replay comparison")
    ap.add_argument("--view", choices=("maps", "3d"), default="maps",
                    help="the window's tab during the runs (3d needs OpenGL: xvfb-run)")
    args = ap.parse_args(argv)
    measure(scene=args.scene, size=args.size, target=args.target, repeats=args.repeats,
            replay=not args.no_replay, view=args.view)
    return 0


if __name__ == "__main__":
    sys.exit(bench(sys.argv[1:]))
