"""``spdepth recon``: reconstruct depth and background maps from a recorded file.

Reads a first-photon-imaging .mat file or a PicoQuant PTU/HT3/PT3 T3 file, keeps the detections in
the time window (the first ``--max-photons`` of them per pixel), runs the chosen estimator and
writes the maps (.npz), a picture (.png) and, with ``--json``, one JSON summary line on stdout.

Time units: PicoQuant files carry theirs (the TCSPC resolution); .mat files do not, so
``--time-unit-ps`` is required for them (8 for the first-photon-imaging files, 1 for times in ps).
A session's own recording is reconstructed with the settings the session used unless options
override them. Otherwise, with neither ``--window-ps`` nor ``--bin-ps`` the estimator derives both
from the data (window: the span of the detections; bins: a ninth of the pulse RMS); with only one
given, the other comes from the data by recon's one rule (``recon.model.Binning.from_data``).
Without ``--pulse-rms-ps`` or ``--irf`` the estimator estimates the pulse shape.
"""

from __future__ import annotations

import argparse
import json
import sys

from spdepth.acq.commands._args import add_reflector_arguments, positive_float, positive_int, window_ps
from spdepth.acq.requests import DEFAULT_METHOD
from spdepth.recon import estimators
from spdepth.recon.model import METHODS

HELP = "reconstruct depth/background maps from a .mat or PicoQuant PTU/HT3/PT3 T3 file"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("input", metavar="INPUT", nargs="+",
                        help=".mat (first-photon imaging) or PTU/HT3/PT3 T3 file; with several, "
                             "--out and --png name folders (OUT/<name>.npz)")
    parser.add_argument("--method", choices=METHODS, default=None,
                        help=f"estimator (default {DEFAULT_METHOD}). {estimators.summaries()}")
    parser.add_argument("--out", metavar="MAPS.npz", help="write the maps and the settings used here")
    parser.add_argument("--png", metavar="MAPS.png", help="write a picture of the depth, background and "
                        "photon-count maps (a time histogram for a point measurement)")
    parser.add_argument("--ply", metavar="POINTS.ply",
                        help="write the maps as points (x, y, z in metres in the scanner frame, "
                             "intensity, uncertainty, surface, flags; README 'Points')")
    parser.add_argument("--las", metavar="POINTS.las", help="the same points as LAS 1.4")
    parser.add_argument("--fov-deg", type=positive_float, metavar="DEG",
                        help="field of view (square, centred) of a file without scan geometry "
                             "(.mat): the pixels' angles for --ply/--las and the picture's axes")
    offset = parser.add_mutually_exclusive_group()
    offset.add_argument("--range-offset-m", type=float, metavar="M",
                        help="add M metres to every depth (gated long-range data whose times "
                             "start at a range gate)")
    offset.add_argument("--gate-delay-ns", type=float, metavar="NS",
                        help="the range gate's delay after the laser pulse: adds c*delay/2 to "
                             "every depth")
    parser.add_argument("--json", action="store_true",
                        help="print one JSON summary object as the last stdout line")
    parser.add_argument("--time-unit-ps", type=positive_float, metavar="PS",
                        help="size of one raw time unit in ps; required for .mat files (8 for the "
                             "first-photon-imaging files, 1 for ps); PicoQuant files: the header's resolution")
    parser.add_argument("--window-ps", type=window_ps, metavar="START:STOP",
                        help="keep detections with START <= t < STOP (ps after the laser sync); "
                             "default: as recorded, else the span of the detections present")
    parser.add_argument("--bin-ps", type=positive_float, metavar="PS",
                        help="histogram bin width in ps (a whole number of raw units); default: as "
                             "recorded, else a ninth of the pulse RMS")
    pulse = parser.add_mutually_exclusive_group()
    pulse.add_argument("--pulse-rms-ps", type=positive_float, metavar="PS",
                       help="Gaussian pulse RMS width in ps (the seed paper: 360)")
    pulse.add_argument("--irf", metavar="FILE", help="measured instrument response to use instead of a Gaussian")
    parser.add_argument("--save-irf", metavar="FILE",
                        help="write the pulse shape used (estimated from the data when neither "
                             "--pulse-rms-ps nor --irf is given) in the format --irf reads "
                             "(CSV time_ps,counts; .npy for an (n, 2) array), so it is measured once")
    parser.add_argument("--max-photons", type=positive_int, metavar="N",
                        help="keep the first N in-window detections per pixel (the seed paper: 15)")
    add_reflector_arguments(parser)
    parser.add_argument("--mat-var", metavar="NAME", help=".mat files: the cell-array variable to read "
                        "when the file holds several")
    parser.add_argument("--channel", type=int, metavar="N",
                        help="PicoQuant files: keep only detector channel N (0-based); default all")
    parser.add_argument("--threads", type=positive_int, metavar="N",
                        help="worker threads for the estimator (default: all cores)")
    parser.add_argument("--dask", metavar="ADDRESS|local:N",
                        help="reconstruct on a dask.distributed cluster: a scheduler address, or "
                             "local:N for N worker processes on 127.0.0.1 (docs/dask.md); same maps "
                             "(needs the dask extra: pip install 'spdepth[dask]')")


def request_from_args(args: argparse.Namespace, path: str, out: str | None = None,
                      png: str | None = None):
    """The :class:`~acq.requests.FileReconRequest` of one input file."""
    from spdepth.acq.requests import FileReconRequest

    ps = lambda v: None if v is None else v * 1e-12          # noqa: E731
    return FileReconRequest(
        input=path, method=args.method or DEFAULT_METHOD,
        time_unit_s=ps(args.time_unit_ps),
        window_s=None if args.window_ps is None else tuple(v * 1e-12 for v in args.window_ps),
        bin_s=ps(args.bin_ps), pulse_rms_s=ps(args.pulse_rms_ps), irf=args.irf,
        max_photons=args.max_photons, reflectors=args.reflectors, max_reflectors=args.max_reflectors,
        false_alarm=args.false_alarm, mat_var=args.mat_var,
        channel=args.channel, threads=args.threads, out=out, png=png, save_irf=args.save_irf,
        ply=getattr(args, "ply", None), las=getattr(args, "las", None),
        fov_deg=getattr(args, "fov_deg", None), range_offset_m=getattr(args, "range_offset_m", None),
        gate_delay_s=None if getattr(args, "gate_delay_ns", None) is None else args.gate_delay_ns * 1e-9)


def run(args: argparse.Namespace) -> int:
    if args.dask or len(args.input) > 1:
        return _run_many(args)
    from spdepth.acq.api import reconstruct_file
    from spdepth.acq.report import ProgressBar

    request = request_from_args(args, args.input[0], args.out, args.png)
    bar = ProgressBar(f"recon {request.method}")
    try:
        result = reconstruct_file(request, progress=bar)
    finally:
        bar.close()
    summary = result.summary
    for note in summary["notes"]:
        print(f"spdepth recon: {note}", file=sys.stderr)
    if args.json:
        print(json.dumps(summary))
    else:
        _print_result(result)
    return 0


def _print_result(result) -> None:
    import numpy as np

    s, maps = result.summary, result.maps
    w0, w1 = s["window_ps"]
    print(f"{s['input']}: {s['shape'][0]} x {s['shape'][1]} pixels, {s['photons']} photons used "
          f"(of {s['photons_in_file']}), window {w0:g}:{w1:g} ps; read {s['read_s']:.2f} s, "
          f"{s['method']} {s['recon_s']:.2f} s")
    depth = np.asarray(maps.depth_m, dtype=float)
    surfaces = depth if depth.ndim == 3 else depth[None]
    for r, surf in enumerate(surfaces):
        got = surf[np.isfinite(surf)]
        if got.size:
            which = f"surface {r + 1} " if depth.ndim == 3 else ""
            print(f"{which}depth: median {np.median(got):.4f} m, 2-98% {np.percentile(got, 2):.4f} "
                  f"to {np.percentile(got, 98):.4f} m; {got.size} of {surf.size} pixels estimated")
    est = maps.settings.get("irf_estimate")
    if est:
        tail = (f", tail {est['tail_share']:.0%} of it" + (f" (mean delay {est['tail_tau_s'] * 1e12:.0f} ps)"
                if est.get("tail_tau_s") else "")) if est["tail_share"] > 0 else ", no tail"
        print(f"pulse estimated from the data ({est['method']}): RMS {est['rms_s'] * 1e12:.0f} ps, "
              f"core {est['core_rms_s'] * 1e12:.0f} ps, FWHM {est['fwhm_s'] * 1e12:.0f} ps{tail}")
    if str(maps.settings.get("pulse_source", "")).endswith("measured on the surfaces"):
        t = np.asarray(maps.settings["irf"]["times_s"])
        print(f"response re-measured on the surfaces: {t[0] * 1e12:.0f} to {t[-1] * 1e12:.0f} ps about its "
              f"centroid (tail and later bumps included), RMS {maps.settings['pulse_rms_s'] * 1e12:.0f} ps")
    if "surfaces_rule" in maps.settings:
        counts = np.bincount(np.ravel(maps.surfaces), minlength=2)
        print(f"surfaces per pixel ({maps.settings['surfaces_rule']}): "
              + ", ".join(f"{k}: {c}" for k, c in enumerate(counts)))
    if s.get("range_offset_m"):
        print(f"range offset {s['range_offset_m']:.3f} m added to every depth")
    for what, where in (("maps", s["out"]), ("picture", s["png"]), ("pulse shape", s["save_irf"]),
                        ("points (PLY)", s.get("ply")), ("points (LAS)", s.get("las"))):
        if where:
            print(f"{what}: {where}")


def _run_many(args: argparse.Namespace) -> int:
    """Several inputs, or ``--dask``: one line (or JSON object) per input."""
    import time
    from pathlib import Path

    from spdepth.acq import distributed
    from spdepth.acq.errors import RequestError

    several = len(args.input) > 1
    if args.ply or args.las:
        raise RequestError("--ply/--las write one file's points: give one input (without --dask)")
    names = [Path(p).name for p in args.input]
    if several and (args.out or args.png) and len(set(names)) < len(names):
        raise RequestError("inputs share a file name, so their outputs would overwrite each other")
    for folder in (args.out, args.png) if several else ():
        if folder:
            Path(folder).mkdir(parents=True, exist_ok=True)
    requests = []
    for path in args.input:
        stem = Path(path).stem
        out = str(Path(args.out) / f"{stem}.npz") if several and args.out else args.out
        png = str(Path(args.png) / f"{stem}.png") if several and args.png else args.png
        requests.append(request_from_args(args, path, out, png))
    t0 = time.perf_counter()
    summaries = distributed.reconstruct_files(requests, args.dask)
    wall = time.perf_counter() - t0
    for s in summaries:
        for note in s.get("notes", ()):
            print(f"spdepth recon: {note}", file=sys.stderr)
        if args.json:
            print(json.dumps(s))
        else:
            where = ", ".join(f"{k} {s[k]}" for k in ("out", "png") if s.get(k))
            print(f"{s['input']}: {s['shape'][0]} x {s['shape'][1]} pixels, {s['photons']} photons, "
                  f"{s['pixels_with_estimate']} estimated, {s['method']} {s['recon_s']:.2f} s"
                  + (f"; {where}" if where else ""))
    if not args.json:
        print(f"{len(summaries)} input(s) in {wall:.2f} s"
              + (f" on dask {args.dask}" if args.dask else " in this process"))
    return 0
