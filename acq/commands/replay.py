"""``spdepth replay``: feed a recording through the same session pipeline as a live tagger."""

from __future__ import annotations

import argparse

from spdepth.acq.commands._args import positive_float, positive_int
from spdepth.acq.commands._session import (PreparingNotice, add_output_arguments,
                                           add_recon_arguments, exit_status, report, run_session)

HELP = "replay a recording (or a PTU with pixel markers) through the session pipeline"


def _speed(text: str):
    if text == "max":
        return "max"
    try:
        return positive_float(text)
    except argparse.ArgumentTypeError:
        raise argparse.ArgumentTypeError(f"--speed must be 'max' or a positive factor, got {text!r}") from None


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("recording", metavar="RECORDING",
                        help="a session folder or its recording.ptu, or a T3 PTU with pixel markers")
    parser.add_argument("--target", type=positive_int, metavar="N",
                        help="detections per pixel to keep (default: the recorded target; fewer "
                             "shows what a shorter scan would have given; required for files "
                             "that record none)")
    parser.add_argument("--speed", type=_speed, default="max",
                        help="'max' (as fast as it decodes) or a factor of recorded time (1: real time)")
    parser.add_argument("--bin-ps", type=positive_float, default=40.0,
                        help="bin width for files without recorded settings (default 40)")
    add_recon_arguments(parser, default_method=None)
    add_output_arguments(parser)


def request_from_args(args: argparse.Namespace):
    from spdepth.acq.requests import ReplayRequest

    return ReplayRequest(recording=args.recording, target=args.target, method=args.method,
                         pulse_rms_s=None if args.pulse_rms_ps is None else args.pulse_rms_ps * 1e-12,
                         speed=args.speed, bin_s=args.bin_ps * 1e-12, reflectors=args.reflectors,
                         max_reflectors=args.max_reflectors, false_alarm=args.false_alarm)


def run(args: argparse.Namespace) -> int:
    from pathlib import Path

    from spdepth.acq.api import OutputDir, build_session, finish_session
    from spdepth.acq.errors import OutputError

    request = request_from_args(args)
    if Path(args.out).resolve() == request.folder.resolve():
        raise OutputError(f"--out {args.out} is the recording's own folder: pick another")
    with OutputDir(args.out, overwrite=args.overwrite) as out:
        with PreparingNotice("replay") as notice:
            session = notice.session = build_session(request, out)
            interrupted = run_session(session, "replay")
        p = session.plan
        asked = session.live_recon.requested
        surfaces = "" if asked.reflectors == 1 else f", surfaces {asked.reflectors}"
        summary = finish_session(session, out.path, f"replay {p.nx}x{p.ny}, {p.target} per pixel, "
                                                    f"{asked.method}{surfaces}")
    report(summary, args.json, "replay")
    return exit_status(session, interrupted)
