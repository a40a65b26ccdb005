"""``spdepth scan``: one acquisition session against the simulated bench or real devices, recorded
and reconstructed live, written to a folder."""

from __future__ import annotations

import argparse

from spdepth.acq.commands._args import (non_negative_float, positive_float, positive_int,
                                        size_wxh, window_ps)
from spdepth.acq.commands._session import (PreparingNotice, add_output_arguments,
                                           add_recon_arguments, exit_status, report, run_session)
from spdepth.acq.requests import DEFAULT_SIZE, DEFAULT_TARGET, TAGGER_FORMS

HELP = "scan (simulated or real devices), record the tag stream, reconstruct live, write the maps"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    src = parser.add_argument_group("source (one of)")
    src.add_argument("--sim", action="store_true",
                     help="simulated galvo and tagger (a scene); with --tagger/--galvo naming a "
                          "vendor device, the scene is reached through that vendor's driver and a "
                          "stand-in of its library")
    src.add_argument("--galvo", metavar="GALVO",
                     help="galvo: nidaq:DEV[/aoN:M] (NI-DAQ analog outputs) or our controller's "
                          "serial PORT or URL")
    src.add_argument("--tagger", metavar="TAGGER",
                     help=f"time tagger: {TAGGER_FORMS} (ours)")
    add_sim_arguments(parser)
    real = parser.add_argument_group("real devices")
    real.add_argument("--sync-rate-hz", type=positive_float,
                      help="laser repetition rate (real devices; recorded in the PTU header)")
    real.add_argument("--fov-deg", type=positive_float, default=20.0,
                      help="square field of view in optical degrees, centred (default 20)")
    real.add_argument("--deg-per-volt", type=positive_float, default=1.0,
                      help="NI-DAQ galvo: optical degrees per volt (default 1)")
    real.add_argument("--v-limit", type=positive_float, default=10.0,
                      help="NI-DAQ galvo: keep the outputs within +-V volts (default 10)")
    real.add_argument("--park-deg", default="0,0", metavar="X,Y",
                      help="NI-DAQ galvo: where the mirror rests between scans (default 0,0)")
    real.add_argument("--picoquant-lib", default="", metavar="PATH",
                      help="PicoQuant: the device library file (default: search the install "
                           "places, the snapi package and SPDEPTH_PICOQUANT_LIB)")
    real.add_argument("--event-divider", type=positive_int, default=1, metavar="N",
                      help="Swabian: tag every N-th laser sync only (high laser rates; default 1)")
    add_scan_arguments(parser)
    add_recon_arguments(parser)
    add_output_arguments(parser)


def add_sim_arguments(parser: argparse.ArgumentParser) -> None:
    """The simulated bench's options (scan and demo)."""
    sim = parser.add_argument_group("simulated bench")
    sim.add_argument("--scene", default="bust", help="built-in scene or file:DEPTH (default bust)")
    sim.add_argument("--ppp", type=positive_float, default=None,
                     help="mean detections per pixel per scene dwell (default: the target)")
    sim.add_argument("--sbr", type=positive_float, default=10.0,
                     help="signal-to-background ratio (default 10)")
    sim.add_argument("--faults", default="", metavar="SPEC",
                     help="faults to inject, KIND@WHEN items (WHEN in virtual seconds '2s' or share "
                          "of the scan '40%%'), e.g. fifo-overflow@40%%,device-vanish@2s; kinds: "
                          "serial-unplug, garbled-reply, missing-reply, slow-reply, servo-fault "
                          "(galvo); daq-underflow (NI-DAQ galvo); usb-timeout, partial-read, fifo-overflow, "
                          "device-vanish (tagger)")
    sim.add_argument("--seed", type=int, default=0, help="random seed (default 0)")


def add_scan_arguments(parser: argparse.ArgumentParser) -> None:
    """The plan's options (scan and demo)."""
    scan = parser.add_argument_group("scan")
    scan.add_argument("--size", type=size_wxh, default=DEFAULT_SIZE, metavar="WxH",
                      help=f"pixels (default {DEFAULT_SIZE[1]}x{DEFAULT_SIZE[0]})")
    scan.add_argument("--target", type=positive_int, default=DEFAULT_TARGET, metavar="N",
                      help=f"in-window detections per pixel (default {DEFAULT_TARGET})")
    scan.add_argument("--mode", choices=("gated", "raster"), default="gated",
                      help="gated: hold each pixel until N detections or the dwell limit; "
                           "raster: fixed dwell, frames repeated until every pixel has N")
    scan.add_argument("--dwell-limit-ms", type=positive_float, metavar="T",
                      help="gated only: dwell limit per pixel (default 20 scene dwells / 10 ms)")
    scan.add_argument("--dwell-ms", type=positive_float, metavar="T",
                      help="raster only: dwell per pixel and frame (default the scene's dwell / 1 ms)")
    scan.add_argument("--pattern", choices=("raster", "serp"), default="raster",
                      help="line order: raster or serpentine (default raster)")
    scan.add_argument("--settle-us", type=non_negative_float, default=0.0,
                      help="wait after each step before the pixel opens (default 0)")
    scan.add_argument("--max-passes", type=positive_int, metavar="N",
                      help="gated: re-acquisition passes (default 10); raster: frames (default 100)")
    scan.add_argument("--time-limit-s", type=positive_float, metavar="S",
                      help="end the scan after S seconds; short pixels are flagged")
    scan.add_argument("--window-ps", type=window_ps, metavar="START:STOP",
                      help="detection window after the sync (default 0:32040, 801 bins of 40 ps)")
    scan.add_argument("--bin-ps", type=positive_float, default=40.0,
                      help="histogram bin width (default 40)")


def request_from_args(args: argparse.Namespace):
    """The :class:`~acq.requests.ScanRequest` the arguments stand for (validated as a whole)."""
    from spdepth.acq.errors import RequestError
    from spdepth.acq.requests import Devices, ScanRequest, SimBench

    sim = getattr(args, "sim", True)
    galvo, tagger = getattr(args, "galvo", None), getattr(args, "tagger", None)
    if not sim and not (galvo or tagger):
        raise RequestError("give either --sim or both --galvo and --tagger (real devices)")
    if sim:
        instruments = SimBench(scene=args.scene, ppp=args.ppp, sbr=args.sbr, seed=args.seed,
                               faults=args.faults, tagger=tagger or "", galvo=galvo or "")
    else:
        if args.faults:
            raise RequestError("--faults only applies to the simulated devices (--sim)")
        try:
            park = tuple(float(v) for v in str(args.park_deg).split(","))
            if len(park) != 2:
                raise ValueError
        except ValueError:
            raise RequestError(f"--park-deg must be X,Y degrees, got {args.park_deg!r}") from None
        instruments = Devices(galvo=galvo or "", tagger=tagger or "",
                              sync_rate_hz=args.sync_rate_hz or 0.0, fov_deg=args.fov_deg,
                              deg_per_volt=args.deg_per_volt, v_limit=args.v_limit,
                              park_deg=park, picoquant_lib=args.picoquant_lib,
                              event_divider=args.event_divider)
    # the demo has no surfaces options: the request's defaults
    surfaces = {k: getattr(args, k) for k in ("reflectors", "max_reflectors", "false_alarm")
                if getattr(args, k, None) is not None}
    ms = lambda v: None if v is None else v * 1e-3          # noqa: E731
    ps = lambda v: None if v is None else v * 1e-12         # noqa: E731
    return ScanRequest(
        instruments=instruments, size=tuple(args.size), target=args.target, mode=args.mode,
        dwell_limit_s=ms(args.dwell_limit_ms), dwell_s=ms(args.dwell_ms), pattern=args.pattern,
        settle_s=args.settle_us * 1e-6, max_passes=args.max_passes, time_limit_s=args.time_limit_s,
        window_s=None if args.window_ps is None else tuple(v * 1e-12 for v in args.window_ps),
        bin_s=args.bin_ps * 1e-12, method=args.method, pulse_rms_s=ps(args.pulse_rms_ps),
        **surfaces)


def run(args: argparse.Namespace) -> int:
    from spdepth.acq.api import OutputDir, build_session, finish_session, open_instruments

    request = request_from_args(args)
    with OutputDir(args.out, overwrite=args.overwrite) as out:
        with PreparingNotice("scan") as notice, open_instruments(request) as inst:
            session = notice.session = build_session(request, out, inst)
            interrupted = run_session(session, "scan")
        summary = finish_session(session, out.path, request.label())
    report(summary, args.json, "scan")
    return exit_status(session, interrupted)
