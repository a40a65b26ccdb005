"""``spdepth bench TARGET``: print speed figures measured side by side in one run.

Targets live next to the code they measure; each module exposes ``bench(argv) -> int``.
"""

from __future__ import annotations

import argparse
import importlib

HELP = "measure speed (generation, reconstruction, T3 decoding) and accuracy for time (report)"

TARGETS = {
    "generate": ("spdepth.drivers.sim.bench", "photon generation of the scene simulator (detections/s)"),
    "recon": ("spdepth.recon.bench", "estimators vs plain NumPy references, 1 and 2 threads (pixels/s)"),
    "decode": ("spdepth.drivers.tagger.bench", "T3 record decoding: numba vs NumPy vs ptufile (records/s)"),
    "session": ("spdepth.acq.bench_session", "acquisition session end to end: scan det/s, live-recon "
                "backlog, replay det/s, peak memory"),
    "report": ("spdepth.acq.bench_report", "accuracy vs detections per pixel, SBR and estimator, with scan and "
               "compute time: report.md, results.csv, PNGs (--out DIR [--quick])"),
    "spatial": ("spdepth.recon.spatial_bench", "spatial estimator on a 256x256 frame beside ml, warm, 1 thread "
                "(pixels/s per core)"),
}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("target", choices=sorted(TARGETS),
                        help="; ".join(f"{k}: {v[1]}" for k, v in TARGETS.items()))
    parser.add_argument("rest", nargs=argparse.REMAINDER,
                        help="options passed to the target's benchmark (see its --help)")


def run(args: argparse.Namespace) -> int:
    module = importlib.import_module(TARGETS[args.target][0])
    return int(module.bench(list(args.rest)) or 0)
