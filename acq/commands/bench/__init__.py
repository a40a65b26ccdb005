"""``spdepth bench TARGET``: print speed (and accuracy-for-time) figures measured side by side in
one run, never in timed unit tests.

Every benchmark lives in this package, one module per target exposing ``bench(argv) -> int``; each
builds what it measures from the same library calls the commands use (requests and ``acq.api``
for sessions and files, ``recon.estimate.reconstruct`` for estimators).
"""

from __future__ import annotations

import argparse
import importlib
import sys

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
    "halves": ("spdepth.acq.commands.bench.halves", "a histogram cube split into two halves at random, "
               "each reconstructed: the shares of pixels whose depths agree within 3 and 1 combined sigma"),
    "array": ("spdepth.acq.commands.bench.array", "SPAD-array frames (64x64x1024, ~20 counts per pixel) "
              "per second: pixelwise and spatial estimators on counts, one thread and all"),
    "flux": ("spdepth.acq.commands.bench.flux", "depth bias and signal error against detections per laser "
             "pulse (0.01 to 1), with and without the pile-up correction"),
    "honesty": ("spdepth.acq.commands.bench.honesty", "split-half check of depths and uncertainties without truth: "
                "each pixel's alternate detections reconstructed apart, agreement within 1 and 3 sigma (FILE)"),
    "compile": ("spdepth.acq.commands.bench.compile", "first run after an install: each kernel group's cold "
                "compile in a new process with an empty numba cache, and the cold demo and recon "
                "of the mannequin end to end (--before: another checkout)"),
    "spatial": ("spdepth.acq.commands.bench.spatial", "spatial estimator on a 256x256 frame beside ml, warm, 1 thread "
                "(pixels/s per core)"),
}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("target", choices=sorted(TARGETS), nargs="?", metavar="TARGET",
                        help="; ".join(f"{k}: {v[1]}" for k, v in TARGETS.items()))
    parser.add_argument("rest", nargs=argparse.REMAINDER, metavar="...",
                        help="options passed to the target's benchmark (see spdepth bench "
                             "TARGET --help)")


def parser(target: str, doc: str) -> argparse.ArgumentParser:
    """A benchmark's own parser: ``spdepth bench TARGET`` as its name, the module docstring's
    first paragraph whole as its description, and one-line errors as every spdepth command's."""
    from spdepth.acq.cli import OneLineParser

    first = " ".join(doc.strip().split("\n\n")[0].split())
    return OneLineParser(prog=f"spdepth bench {target}", description=first)


def run(args: argparse.Namespace) -> int:
    if args.target is None:
        from spdepth.acq.errors import RequestError

        raise RequestError(f"give a benchmark: {', '.join(sorted(TARGETS))} (spdepth bench --help "
                           f"says what each measures)")
    module = importlib.import_module(TARGETS[args.target][0])
    try:
        return int(module.bench(list(args.rest)) or 0)
    except SystemExit as exc:     # the benchmark's --help, or its one-line usage error
        if isinstance(exc.code, str):           # SystemExit("message"): said in one line, status 2
            print(f"spdepth bench {args.target}: error: {' '.join(exc.code.split())}", file=sys.stderr)
            return 2
        return int(exc.code or 0)
