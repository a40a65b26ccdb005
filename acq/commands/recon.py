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

A histogram cube (counts in time bins per pixel; frames summed) is read as counts: ``--time-unit-ps``
is its bin width, and bin k is raw time k, so the window and bins mean what they mean for photon
times. Pile-up (``--pileup``) is corrected where detections per laser period are not small.
"""

from __future__ import annotations

import argparse
import json
import sys

from spdepth.acq.params import add_options

HELP = ("reconstruct depth/background maps from a .mat or PicoQuant PTU/HT3/PT3 T3 file, or a "
        "histogram cube (.mat, .npy, .npz, HDF5)")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_options(parser, "recon")


def request_from_args(args: argparse.Namespace, path: str, out: str | None = None,
                      png: str | None = None):
    """The :class:`~acq.requests.FileReconRequest` of one input file, its maps to ``out`` (.npz)
    and its picture to ``png``."""
    from spdepth.acq.params import given
    from spdepth.acq.requests import build_request

    values = dict(given(args, "recon"), file=path, npz=out, png=png)
    return build_request("file", values)


def run(args: argparse.Namespace) -> int:
    if args.dask or len(args.file) > 1:
        return _run_many(args)
    from spdepth.acq.api import reconstruct_file
    from spdepth.acq.commands._session import CompileNotice
    from spdepth.acq.report import ProgressBar

    from spdepth.acq.outputs import refuse_existing

    request = request_from_args(args, args.file[0], args.npz, args.png)
    # before any work: an existing output (a session's own maps.npz) is kept unless --overwrite
    refuse_existing(_outputs(request), overwrite=args.overwrite, inputs=(request.input,))
    bar = ProgressBar(f"recon {request.method}")
    # without an output file only the summary is seen, which holds no uncertainty: the return
    # test's spreads are not computed (half of a 512x512 PTU's estimation time); on a cold cache
    # a line as each kernel starts compiling says how far the first run is
    try:
        with CompileNotice("spdepth recon"):
            result = reconstruct_file(request, progress=bar, spreads=request.writes_files(),
                                      notice=lambda text: print(f"spdepth recon: {text}", file=sys.stderr, flush=True))
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


def _outputs(request) -> list[tuple[str, str | None]]:
    """(option, path) of every file a reconstruction writes."""
    return [("--npz", request.out), ("--png", request.png), ("--ply", request.ply),
            ("--las", request.las), ("--save-irf", request.save_irf)]


def _print_result(result) -> None:
    import numpy as np

    from spdepth.acq.report import window_text

    s, maps = result.summary, result.maps
    print(f"{s['input']}: {s['shape'][0]} x {s['shape'][1]} pixels, {s['photons']} photons used "
          f"(of {s['photons_in_file']}), window {window_text(*s['window_ps'])}; read {s['read_s']:.2f} s, "
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
    from spdepth.acq.commands import EXIT_USAGE
    from spdepth.acq.errors import RequestError

    several = len(args.file) > 1
    if args.ply or args.las:
        raise RequestError("--ply/--las write one file's points: give one input (without --dask)")
    names = [Path(p).name for p in args.file]
    if several and (args.npz or args.png) and len(set(names)) < len(names):
        raise RequestError("inputs share a file name, so their outputs would overwrite each other")
    from spdepth.acq.outputs import check_output_folder, refuse_existing

    for option, folder in (("--npz", args.npz), ("--png", args.png)) if several else ():
        if folder:
            check_output_folder(option, folder)
    for folder in (args.npz, args.png) if several else ():
        if folder:
            Path(folder).mkdir(parents=True, exist_ok=True)
    requests, unread = [], []
    for path in args.file:
        stem = Path(path).stem
        out = str(Path(args.npz) / f"{stem}.npz") if several and args.npz else args.npz
        png = str(Path(args.png) / f"{stem}.png") if several and args.png else args.png
        try:
            requests.append(request_from_args(args, path, out, png))
        except RequestError as exc:
            if not several:
                raise
            unread.append({"input": path, "error": str(exc)})   # a missing file: go on
    if several and not requests and len({u["error"].replace(u["input"], "") for u in unread}) == 1:
        raise RequestError(unread[0]["error"])       # the same for every file: an option's fault
    # before any work: every output that exists is kept unless --overwrite
    refuse_existing([o for r in requests for o in _outputs(r)], overwrite=args.overwrite,
                    inputs=tuple(r.input for r in requests))
    t0 = time.perf_counter()
    # a batch goes on past a file it cannot read: one line each, a count and exit 2 at the end
    summaries = distributed.reconstruct_files(requests, args.dask, keep_going=several) \
        if requests else []
    by_input = {s["input"]: s for s in summaries + unread}
    summaries = [by_input[str(p)] for p in args.file if str(p) in by_input]
    wall = time.perf_counter() - t0
    failed = [s for s in summaries if "error" in s]
    for s in summaries:
        if "error" in s:
            print(f"spdepth recon: error: {s['error']}", file=sys.stderr)
            if args.json:
                print(json.dumps(s))
            continue
        for note in s.get("notes", ()):
            print(f"spdepth recon: {note}", file=sys.stderr)
        if args.json:
            print(json.dumps(s))
        else:
            where = ", ".join(f"{k} {s[k]}" for k in ("out", "png") if s.get(k))
            print(f"{s['input']}: {s['shape'][0]} x {s['shape'][1]} pixels, {s['photons']} photons, "
                  f"{s['pixels_with_estimate']} estimated, {s['method']} {s['recon_s']:.2f} s"
                  + (f"; {where}" if where else ""))
    where = f" on dask {args.dask}" if args.dask else " in this process"
    if failed:
        print(f"spdepth recon: {len(summaries) - len(failed)} of {len(summaries)} inputs "
              f"reconstructed; {len(failed)} could not be: "
              f"{', '.join(Path(s['input']).name for s in failed)}", file=sys.stderr)
    if not args.json:
        print(f"{len(summaries) - len(failed)} of {len(summaries)} input(s) in {wall:.2f} s{where}"
              if failed else f"{len(summaries)} input(s) in {wall:.2f} s{where}")
    return EXIT_USAGE if failed else 0
