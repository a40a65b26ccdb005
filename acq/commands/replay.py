"""``spdepth replay``: feed a recording through the same session pipeline as a live tagger."""

from __future__ import annotations

import argparse

from spdepth.acq.commands._args import positive_float, positive_int
from spdepth.acq.commands._session import (add_output_arguments, add_recon_arguments, finish_outputs,
                                   prepare_out_dir, report, run_session)

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
                        help="a session directory or its recording.ptu, or a T3 PTU with pixel markers")
    parser.add_argument("--target", type=positive_int, metavar="N",
                        help="detections per pixel to keep (default: the recorded target; fewer "
                             "shows what a shorter scan would have given)")
    parser.add_argument("--speed", type=_speed, default="max",
                        help="'max' (as fast as it decodes) or a factor of recorded time (1: real time)")
    parser.add_argument("--bin-ps", type=positive_float, default=40.0,
                        help="bin width for files without recorded settings (default 40)")
    add_recon_arguments(parser, default_method=None)
    add_output_arguments(parser)


def build_session(recording, *, target=None, method=None, pulse_rms_s=None, bin_s=40e-12,
                  speed="max", out=None):
    """A replay session of ``recording`` with the recorded plan and estimator settings, any of
    target, method and pulse width replaced."""
    import dataclasses

    from spdepth.acq.instruments import window_binning
    from spdepth.acq.plan import ScanPlan
    from spdepth.acq.recording import ReplaySource, recon_settings_from_dict
    from spdepth.acq.session import Session

    src = ReplaySource(recording, speed=speed)
    info = src.info
    if info.plan is not None:
        plan = ScanPlan.from_dict(info.plan)
    else:   # a foreign file: one raster frame of the header's size
        h, w = info.shape
        plan = ScanPlan(w, h, 0.0, 0.0, 0.0, 0.0, mode="raster", target=target or 15,
                        dwell_s=1e-3)
    gate_target = plan.target if plan.mode == "gated" else None
    if target is not None:
        plan = dataclasses.replace(plan, target=target)
    if info.recon is not None:
        settings = recon_settings_from_dict(info.recon, method=method, pulse_rms_s=pulse_rms_s,
                                            max_photons=plan.target)
    else:
        range_bins = int(src.layout.tags.get("SPDepth_RangeBins", 0)) or \
            int(round(info.sync_period_s / info.resolution_s))
        units = max(1, int(round(bin_s / info.resolution_s)))
        binning = window_binning(info.resolution_s, n_bins=max(1, range_bins // units), bin_s=bin_s)
        from spdepth.recon.model import ReconSettings

        settings = ReconSettings(method=method or "uos", binning=binning, pulse_rms_s=pulse_rms_s,
                                 max_photons=plan.target)
    return Session(plan, settings, replay=src, out_dir=out, gate_target=gate_target,
                   info={"replay_of": str(src.path), **info.info})


def run(args: argparse.Namespace) -> int:
    from pathlib import Path

    from spdepth.recon.errors import InputError

    rec = Path(args.recording)
    rec_dir = rec if rec.is_dir() else rec.parent
    if Path(args.out).resolve() == rec_dir.resolve():
        raise InputError(f"--out {args.out} is the recording's own directory: pick another")
    out = prepare_out_dir(args.out, args.overwrite)
    try:
        session = build_session(args.recording, target=args.target, method=args.method,
                                pulse_rms_s=args.pulse_rms_ps * 1e-12 if args.pulse_rms_ps else None,
                                bin_s=args.bin_ps * 1e-12, speed=args.speed, out=out)
    except BaseException:
        if not any(out.iterdir()):
            out.rmdir()          # nothing replayed: leave no empty directory behind
        raise
    run_session(session, "replay")
    s = session.plan
    summary = finish_outputs(session, out, f"replay {s.nx}x{s.ny}, {s.target} per pixel, "
                                           f"{session.recon.requested.method}")
    return report(summary, args.json, "replay")
