"""``spdepth bench gui``: does the window slow the scan? Detections/s of the same simulated scan
(and a replay of it) headless and with the window open, alternated (``gui.benchmark.measure``)."""

from __future__ import annotations

import sys


def bench(argv=None) -> int:
    from spdepth.gui.benchmark import measure

    from spdepth.acq.commands.bench import parser
    from spdepth.acq.params import add_bench_options

    ap = parser("gui", __doc__)
    add_bench_options(ap, "gui")
    args = ap.parse_args(argv)
    measure(scene=args.scene, size=args.size, target=args.target, repeats=args.repeats,
            replay=not args.no_replay, view=args.view)
    return 0


if __name__ == "__main__":
    sys.exit(bench(sys.argv[1:]))
