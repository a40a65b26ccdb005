"""``spdepth scan``: one acquisition session against the simulated bench or real devices, recorded
and reconstructed live, written to a directory."""

from __future__ import annotations

import argparse

from spdepth.acq.commands._args import non_negative_float, positive_float, positive_int, size_wxh
from spdepth.acq.commands._session import (add_output_arguments, add_recon_arguments, finish_outputs,
                                   prepare_out_dir, report, run_session)

HELP = "scan (simulated or real devices), record the tag stream, reconstruct live, write the maps"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    src = parser.add_argument_group("source (one of)")
    src.add_argument("--sim", action="store_true", help="simulated galvo and tagger (a scene)")
    src.add_argument("--galvo", metavar="PORT", help="real galvo controller: serial port or URL")
    src.add_argument("--tagger", metavar="usb:VID:PID", help="real time tagger")
    sim = parser.add_argument_group("simulated bench")
    sim.add_argument("--scene", default="bust", help="built-in scene or file:DEPTH (default bust)")
    sim.add_argument("--ppp", type=positive_float, default=None,
                     help="mean detections per pixel per scene dwell (default: the target)")
    sim.add_argument("--sbr", type=positive_float, default=10.0,
                     help="signal-to-background ratio (default 10)")
    sim.add_argument("--faults", default="", metavar="SPEC",
                     help="faults to inject, KIND@WHEN items, e.g. fifo-overflow@40%%,"
                          "device-vanish@2s (see `spdepth demo --help`)")
    sim.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    real = parser.add_argument_group("real devices")
    real.add_argument("--sync-rate-hz", type=positive_float,
                      help="laser repetition rate (real devices; recorded in the PTU header)")
    real.add_argument("--fov-deg", type=positive_float, default=20.0,
                      help="square field of view in optical degrees, centred (default 20)")
    scan = parser.add_argument_group("scan")
    scan.add_argument("--size", type=size_wxh, default=(64, 64), metavar="WxH",
                      help="pixels (default 64x64)")
    scan.add_argument("--target", type=positive_int, default=15, metavar="N",
                      help="in-window detections per pixel (default 15)")
    scan.add_argument("--mode", choices=("gated", "raster"), default="gated",
                      help="gated: hold each pixel until N detections or the dwell limit; "
                           "raster: fixed dwell, frames repeated until every pixel has N")
    scan.add_argument("--dwell-limit-ms", type=positive_float, metavar="T",
                      help="gated: dwell limit per pixel (default 20 scene dwells / 10 ms)")
    scan.add_argument("--dwell-ms", type=positive_float, metavar="T",
                      help="raster: dwell per pixel and frame (default the scene's dwell / 1 ms)")
    scan.add_argument("--pattern", choices=("raster", "serp"), default="raster",
                      help="line order: raster or serpentine (default raster)")
    scan.add_argument("--settle-us", type=non_negative_float, default=0.0,
                      help="wait after each step before the pixel opens (default 0)")
    scan.add_argument("--max-passes", type=positive_int, metavar="N",
                      help="gated: re-acquisition passes (default 10); raster: frames (default 100)")
    scan.add_argument("--time-limit-s", type=positive_float, metavar="S",
                      help="end the scan after S seconds; short pixels are flagged")
    scan.add_argument("--window-ps", metavar="START:STOP",
                      help="detection window after the sync (default 0:32040, 801 bins of 40 ps)")
    scan.add_argument("--bin-ps", type=positive_float, default=40.0,
                      help="histogram bin width (default 40)")
    add_recon_arguments(parser)
    add_output_arguments(parser)


def _window(args):
    from spdepth.recon.errors import InputError

    if args.window_ps is None:
        return None
    try:
        a, b = (float(v) for v in args.window_ps.split(":"))
    except ValueError:
        raise InputError(f"--window-ps must be START:STOP in ps, got {args.window_ps!r}") from None
    if not 0 <= a < b:
        raise InputError(f"--window-ps {args.window_ps}: need 0 <= START < STOP")
    return a * 1e-12, b * 1e-12


def open_instruments(args):
    """The instruments the arguments name (simulated or real)."""
    from spdepth.acq.instruments import open_real, open_sim
    from spdepth.recon.errors import InputError

    if args.sim == bool(args.galvo or args.tagger):
        raise InputError("give either --sim or both --galvo PORT and --tagger usb:VID:PID")
    if args.sim:
        h, w = args.size
        return open_sim(args.scene, (h, w), ppp=args.ppp or float(args.target), sbr=args.sbr,
                        seed=args.seed, faults=args.faults)
    if not (args.galvo and args.tagger):
        raise InputError("real devices need both --galvo PORT and --tagger usb:VID:PID")
    if args.sync_rate_hz is None:
        raise InputError("real devices need --sync-rate-hz (the laser repetition rate)")
    if args.faults:
        raise InputError("--faults only applies to the simulated devices (--sim)")
    return open_real(args.galvo, args.tagger, 1.0 / args.sync_rate_hz)


def build_session(args, inst, out):
    """The plan, estimator settings and session for ``args`` on opened instruments."""
    from spdepth.acq.instruments import recon_settings, sim_plan, window_binning
    from spdepth.acq.plan import ScanPlan
    from spdepth.acq.session import Session

    h, w = args.size
    dwell_ms = args.dwell_limit_ms if args.mode == "gated" else args.dwell_ms
    common = dict(mode=args.mode, target=args.target, pattern=args.pattern,
                  settle_s=args.settle_us * 1e-6, max_passes=args.max_passes,
                  time_limit_s=args.time_limit_s)
    if inst.scene is not None:
        plan = sim_plan(inst, (h, w), dwell_s=None if dwell_ms is None else dwell_ms * 1e-3, **common)
    else:
        half = args.fov_deg / 2
        x = [-half + (c + 0.5) * args.fov_deg / w for c in (0, w - 1)]
        y = [-half + (r + 0.5) * args.fov_deg / h for r in (0, h - 1)]
        default_ms = 10.0 if args.mode == "gated" else 1.0
        plan = ScanPlan(w, h, x[0], x[1], y[0], y[1],
                        dwell_s=(dwell_ms or default_ms) * 1e-3, **common)
    res_s = inst.tagger.resolution_s
    window = _window(args)
    bin_s = args.bin_ps * 1e-12
    if window is None:
        binning = window_binning(res_s, bin_s=bin_s)
    else:
        n_bins = max(1, int(round((window[1] - window[0]) / bin_s)))
        binning = window_binning(res_s, n_bins=n_bins, bin_s=bin_s, start_s=window[0])
    pulse = args.pulse_rms_ps * 1e-12 if args.pulse_rms_ps else (
        inst.scene.pulse_rms_s if inst.scene is not None else None)
    settings = recon_settings(args.method, binning, args.target, pulse)
    return Session(plan, settings, galvo=inst.galvo, tagger=inst.tagger, out_dir=out,
                   sync_period_s=inst.sync_period_s, info=inst.info)


def run(args: argparse.Namespace) -> int:
    out = prepare_out_dir(args.out, args.overwrite)
    try:
        inst = open_instruments(args)
    except BaseException:
        if not any(out.iterdir()):
            out.rmdir()          # nothing was recorded: leave no empty directory behind
        raise
    with inst:
        session = build_session(args, inst, out)
        run_session(session, "scan")
    h, w = args.size
    summary = finish_outputs(session, out, f"scan {args.scene if args.sim else 'devices'} "
                                           f"{w}x{h}, {args.target} per pixel, {args.method}")
    return report(summary, args.json, "scan")
