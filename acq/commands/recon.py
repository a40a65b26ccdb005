"""``spdepth recon``: reconstruct depth and background maps from a recorded file.

Reads a first-photon-imaging .mat file or a PicoQuant PTU/HT3/PT3 T3 file, keeps the detections in
the time window (the first ``--max-photons`` of them per pixel), runs the chosen estimator and
writes the maps (.npz), a picture (.png) and, with ``--json``, one JSON summary line on stdout.

Time units: PicoQuant files carry theirs (the TCSPC resolution); .mat files do not, so
``--time-unit-ps`` is required for them (8 for the first-photon-imaging files, 1 for times in ps).
With neither ``--window-ps`` nor ``--bin-ps`` the estimator derives both from the data (window: the
span of the detections; bins: a ninth of the pulse RMS). With only one given: the window defaults
to the span of the detections, the bin width by recon's one default rule
(``recon.model.default_bin_width``: a ninth of ``--pulse-rms-ps`` in whole raw units, at most 4096
bins). Without ``--pulse-rms-ps`` or ``--irf`` the estimator estimates the pulse width.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time

from spdepth.acq.commands._args import positive_float, positive_int
from spdepth.recon.errors import InputError

HELP = "reconstruct depth/background maps from a .mat or PicoQuant PTU/HT3/PT3 T3 file"


def _window(text: str) -> tuple[float, float]:
    parts = text.split(":")
    if len(parts) != 2:
        raise argparse.ArgumentTypeError(f"expected START:STOP in ps, got {text!r}")
    try:
        start, stop = float(parts[0]), float(parts[1])
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected START:STOP in ps, got {text!r}") from None
    if not (math.isfinite(start) and math.isfinite(stop) and stop > start >= 0):
        raise argparse.ArgumentTypeError(f"window needs 0 <= START < STOP, got {text!r}")
    return start, stop


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("input", metavar="INPUT", nargs="+",
                        help=".mat (first-photon imaging) or PTU/HT3/PT3 T3 file; with several, "
                             "--out and --png name folders (OUT/<name>.npz)")
    parser.add_argument("--method", choices=("uos", "lmf", "ml", "spatial"), default="uos",
                        help="estimator: uos (the seed paper's union of subspaces, default), "
                             "lmf (log-matched filter, ignores background), ml (Poisson maximum likelihood), "
                             "spatial (uses the neighbours: censoring, fit, TV; recon/spatial.py)")
    parser.add_argument("--out", metavar="MAPS.npz", help="write the maps and the settings used here")
    parser.add_argument("--png", metavar="MAPS.png", help="write a picture of the depth, background and "
                        "photon-count maps (a time histogram for a point measurement)")
    parser.add_argument("--json", action="store_true",
                        help="print one JSON summary object as the last stdout line")
    parser.add_argument("--time-unit-ps", type=positive_float, metavar="PS",
                        help="size of one raw time unit in ps; required for .mat files (8 for the "
                             "first-photon-imaging files, 1 for ps); PicoQuant files: the header's resolution")
    parser.add_argument("--window-ps", type=_window, metavar="START:STOP",
                        help="keep detections with START <= t < STOP (ps after the laser sync); "
                             "default: the span of the detections present")
    parser.add_argument("--bin-ps", type=positive_float, metavar="PS",
                        help="histogram bin width in ps (a whole number of raw units); default: a "
                             "ninth of the pulse RMS")
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
    parser.add_argument("--reflectors", type=positive_int, default=1, metavar="K",
                        help="surfaces per pixel to look for (default 1)")
    parser.add_argument("--mat-var", metavar="NAME", help=".mat files: the cell-array variable to read "
                        "when the file holds several")
    parser.add_argument("--channel", type=int, metavar="N",
                        help="PicoQuant files: keep only detector channel N (0-based); default all")
    parser.add_argument("--threads", type=positive_int, metavar="N",
                        help="worker threads for the estimator (default: all cores)")
    parser.add_argument("--dask", metavar="ADDRESS|local:N",
                        help="reconstruct on a dask.distributed cluster: a scheduler address, or "
                             "local:N for N worker processes on 127.0.0.1 (docs/dask.md); same maps")


def run(args: argparse.Namespace) -> int:
    if args.dask or len(args.input) > 1:
        from spdepth.acq import distributed

        return distributed.run(args)
    return run_one(argparse.Namespace(**dict(vars(args), input=args.input[0])))


def run_one(args: argparse.Namespace) -> int:
    """One input file (``args.input`` a path)."""
    import numpy as np

    from spdepth.acq.readers import read_photons
    from spdepth.acq.report import ProgressBar
    from spdepth.recon.estimate import reconstruct
    from spdepth.recon.model import Binning, ReconSettings, default_bin_width, load_irf, save_irf

    t0 = time.perf_counter()
    time_unit_s = args.time_unit_ps * 1e-12 if args.time_unit_ps else None
    result = read_photons(args.input, time_unit_s=time_unit_s, mat_var=args.mat_var,
                          channel=args.channel)
    store = result.store
    for note in result.notes:
        print(f"spdepth recon: {note}", file=sys.stderr)
    unit_ps = store.time_unit_s * 1e12
    if store.n_photons == 0:
        raise InputError(f"{args.input}: holds no photons")

    # window and bins in raw units; with neither given the estimator derives both from the data
    if args.window_ps is None and args.bin_ps is None:
        binning = None
        kept = store
    else:
        if args.window_ps is not None:
            start_u, stop_u = args.window_ps[0] / unit_ps, args.window_ps[1] / unit_ps
        else:
            start_u = math.floor(float(store.times.min()))
            stop_u = math.floor(float(store.times.max())) + 1
        if args.bin_ps is not None:
            bin_u = args.bin_ps / unit_ps
            if abs(bin_u - round(bin_u)) > 1e-6 * max(1.0, bin_u) or round(bin_u) < 1:
                raise InputError(f"--bin-ps {args.bin_ps:g} is not a whole number of {unit_ps:g} ps "
                                 f"raw units")
        else:
            bin_u = default_bin_width(stop_u - start_u,
                                      args.pulse_rms_ps / unit_ps if args.pulse_rms_ps else None)
        binning = Binning.from_ps(unit_ps, window_ps=(start_u * unit_ps, stop_u * unit_ps),
                                  bin_ps=round(bin_u) * unit_ps)
        kept = store.first_in_window(binning.window_start, binning.window_stop, args.max_photons)
        if kept.n_photons == 0:
            raise InputError(f"{args.input}: no detections in the window {start_u * unit_ps:g}:"
                             f"{stop_u * unit_ps:g} ps (the file's detections span "
                             f"{store.times.min() * unit_ps:g} to {store.times.max() * unit_ps:g} ps)")
    irf = load_irf(args.irf) if args.irf else None
    settings = ReconSettings(
        method=args.method, binning=binning,
        pulse_rms_s=args.pulse_rms_ps * 1e-12 if args.pulse_rms_ps else None, irf=irf,
        max_photons=args.max_photons, reflectors=args.reflectors)
    read_s = time.perf_counter() - t0

    if args.threads is not None:
        import numba

        if args.threads > numba.config.NUMBA_NUM_THREADS:
            raise InputError(f"--threads {args.threads}: this machine allows at most "
                             f"{numba.config.NUMBA_NUM_THREADS}")
        numba.set_num_threads(args.threads)
    bar = ProgressBar(f"recon {args.method}")
    t1 = time.perf_counter()
    try:
        maps = reconstruct(kept, settings, progress=bar)
    finally:
        bar.close()
    recon_s = time.perf_counter() - t1

    # what was actually used (the estimator fills in what was left to it)
    used = maps.settings["binning"]
    win_u = (used["window_start"], used["window_stop"])
    photons = int(np.sum(maps.photons))
    if args.out:
        maps.save_npz(args.out)
    irf_used = _irf_used(maps.settings)
    if args.save_irf:
        save_irf(irf_used, args.save_irf)
    if args.png:
        from spdepth.acq.report import render_maps_png, render_point_png

        title = (f"{result.path.rsplit('/', 1)[-1]}: {args.method}, {photons} photons, "
                 f"window {win_u[0] * unit_ps:g}-{win_u[1] * unit_ps:g} ps")
        t_irf, c_irf = irf_used.arrays()
        drawn = (t_irf, c_irf, f"{maps.settings['pulse_source']}: RMS "
                 f"{irf_used.rms_s * 1e12:.0f} ps")
        if result.is_image:
            render_maps_png(args.png, maps, title=title, irf=drawn)
        else:
            shown = store.first_in_window(win_u[0], win_u[1], args.max_photons)
            render_point_png(args.png, shown.times * store.time_unit_s,
                             tof_s=float(np.ravel(maps.tof_s)[0]), title=title, irf=drawn)

    depth = np.asarray(maps.depth_m, dtype=float)
    finite = depth[np.isfinite(depth)]
    summary = {
        "input": str(args.input), "kind": result.kind, "is_image": result.is_image,
        "shape": list(store.shape), "pixels": store.n_pixels,
        "pixels_with_estimate": int(finite.size),
        "photons": photons, "photons_in_file": store.n_photons,
        "method": args.method, "read_s": round(read_s, 4), "recon_s": round(recon_s, 4),
        "time_unit_ps": unit_ps, "window_ps": [win_u[0] * unit_ps, win_u[1] * unit_ps],
        "bin_ps": used["bin_width"] * unit_ps, "n_bins": used["n_bins"],
        "pulse_rms_ps": (maps.settings["pulse_rms_s"] * 1e12
                         if maps.settings.get("pulse_rms_s") is not None else None),
        "max_photons": args.max_photons, "settings": maps.settings,
        "depth_m_median": float(np.median(finite)) if finite.size else None,
        "out": args.out, "png": args.png, "source": result.meta,
    }
    if args.json:
        print(json.dumps(summary, default=_json_default))
    else:
        print(f"{result.path}: {store.shape[0]} x {store.shape[1]} pixels, {photons} photons used "
              f"(of {store.n_photons}), window {win_u[0] * unit_ps:g}:{win_u[1] * unit_ps:g} ps; "
              f"read {read_s:.2f} s, {args.method} {recon_s:.2f} s")
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
        for what, where in (("maps", args.out), ("picture", args.png), ("pulse shape", args.save_irf)):
            if where:
                print(f"{what}: {where}")
    return 0


def _irf_used(settings: dict):
    """The pulse shape a reconstruction used, as an Irf (a sampled Gaussian for a Gaussian pulse)."""
    from spdepth.recon.model import Irf, gaussian_irf

    irf = settings.get("irf")
    if irf:
        return Irf(tuple(irf["times_s"]), tuple(irf["counts"]), source=irf.get("source", ""))
    return gaussian_irf(settings["pulse_rms_s"], source=f"Gaussian, {settings['pulse_source']}")


def _json_default(value):
    """numpy scalars/arrays and other odd values in settings dicts, made JSON-able."""
    import numpy as np

    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    return str(value)
