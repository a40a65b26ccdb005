"""``spdepth bench TARGET``: print speed (and accuracy-for-time) figures measured side by side in
one run, never in timed unit tests.

Every benchmark lives in this package, one module per target exposing ``bench(argv) -> int``; each
builds what it measures from the same library calls the commands use (requests and ``acq.api``
for sessions and files, ``recon.estimate.reconstruct`` for estimators).
"""

from __future__ import annotations

import argparse
import importlib

HELP = "measure speed (generation, reconstruction, T3 decoding) and accuracy for time (report)"

TARGETS = {
    "generate": ("spdepth.acq.commands.bench.generate", "photon generation of the scene simulator (detections/s)"),
    "recon": ("spdepth.acq.commands.bench.recon", "estimators vs plain NumPy references, 1 and 2 threads (pixels/s)"),
    "decode": ("spdepth.acq.commands.bench.decode", "T3 record decoding: numba vs NumPy vs ptufile (records/s)"),
    "gui": ("spdepth.acq.commands.bench.gui", "the window's cost: scan/replay detections/s headless "
            "vs with the window open"),
    "read": ("spdepth.acq.commands.bench.read", "reading a PTU: spdepth recon's reader beside replay's "
             "stream on the same file (detections/s)"),
    "sim": ("spdepth.acq.commands.bench.sim", "the simulated bench: the demo's session (96x96) and a gated "
            "512x512 session at 30 per pixel through the real drivers, warm (wall s)"),
    "session": ("spdepth.acq.commands.bench.session", "acquisition session end to end: scan det/s, live-recon "
                "backlog, replay det/s, peak memory"),
    "report": ("spdepth.acq.commands.bench.report", "accuracy vs detections per pixel, SBR and estimator, with scan and "
               "compute time: report.md, results.csv, PNGs (--out DIR [--quick])"),
    "surfaces": ("spdepth.acq.commands.bench.surfaces", "several surfaces per pixel: --reflectors 2 and auto beside "
                 "1 at 50 detections per pixel, warm, 1 thread (pixels/s)"),
    "startup": ("spdepth.acq.commands.bench.startup", "spdepth recon in a new process, warm numba cache: "
                "wall, read_s, recon_s, ratio to the plain port of Algorithm 1 (--before: another checkout)"),
    "honesty": ("spdepth.acq.commands.bench.honesty", "split-half check of depths and uncertainties without truth: "
                "each pixel's alternate detections reconstructed apart, agreement within 1 and 3 sigma (FILE)"),
    "spatial": ("spdepth.acq.commands.bench.spatial", "spatial estimator on a 256x256 frame beside ml, warm, 1 thread "
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
