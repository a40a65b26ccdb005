"""``spdepth gui``: the live window (maps filling in during the scan, pixel inspector, controls),
optionally starting a scan or replay at once, grabbing a screenshot and exiting at its end.

The arguments become the window's control settings (``gui.sources.SourceSpec``, on top of the ones
it remembers), which the window turns into an ``acq.requests`` request. Also the command line of
the window's benchmark lives with the others (``spdepth bench gui``)."""

from __future__ import annotations

import argparse

from spdepth.acq.commands._args import non_negative_float, positive_float, positive_int, size_wxh
from spdepth.recon import estimators
from spdepth.recon.model import METHODS

HELP = ("open the live window; with --sim, --galvo/--tagger or --replay start that scan at once, "
        "with --file reconstruct a PTU/.mat file in it")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    src = parser.add_argument_group("source (optional: without one the window waits for Start)")
    src.add_argument("--sim", action="store_true", help="simulated galvo and tagger (a scene)")
    src.add_argument("--galvo", metavar="GALVO",
                     help="real galvo: nidaq:DEV[/aoN:M] or our controller's serial PORT or URL")
    src.add_argument("--tagger", metavar="TAGGER",
                     help="real time tagger: picoquant:MODEL[:SERIAL], swabian[:SERIAL] or "
                          "usb:VID:PID")
    src.add_argument("--sync-rate-hz", type=positive_float,
                     help="laser repetition rate (real devices)")
    src.add_argument("--fov-deg", type=positive_float,
                     help="real devices: square field of view in optical degrees, centred "
                          "(default 20)")
    src.add_argument("--replay", metavar="RECORDING",
                     help="replay a run folder or its recording.ptu through the session pipeline")
    src.add_argument("--file", metavar="PTU|MAT",
                     help="reconstruct a PTU/HT3/PT3 or .mat file (spdepth recon's reading) and "
                          "show its maps")
    src.add_argument("--time-unit-ps", type=positive_float, metavar="PS",
                     help="--file: raw time unit (required for .mat: 8 for first-photon imaging)")
    src.add_argument("--pulse-rms-ps", type=positive_float, metavar="PS",
                     help="--file: Gaussian pulse RMS (default: estimated from the data)")
    sim = parser.add_argument_group("simulated bench")
    sim.add_argument("--scene", help="built-in scene or file:DEPTH (default bust)")
    sim.add_argument("--sbr", type=positive_float, help="signal-to-background ratio (default 10)")
    sim.add_argument("--seed", type=int, help="random seed (default 0)")
    sim.add_argument("--faults", metavar="SPEC",
                     help="faults to inject, KIND@WHEN items, e.g. device-vanish@40%%")
    scan = parser.add_argument_group("scan (defaults: the window's remembered settings)")
    scan.add_argument("--size", type=size_wxh, metavar="WxH", help="pixels (e.g. 32x32)")
    scan.add_argument("--target", type=positive_int, metavar="N",
                      help="in-window detections per pixel (replay: default as recorded)")
    scan.add_argument("--mode", choices=("gated", "raster"))
    scan.add_argument("--dwell-limit-ms", type=non_negative_float, metavar="T",
                      help="gated only: dwell limit per pixel (0: default)")
    scan.add_argument("--dwell-ms", type=non_negative_float, metavar="T",
                      help="raster only: dwell per pixel and frame (0: default)")
    scan.add_argument("--method", choices=METHODS,
                      help=f"estimator for the maps. {estimators.live_note()}")
    scan.add_argument("--reflectors", type=positive_int, metavar="K",
                      help="surfaces per pixel to look for (default 1; replay: as recorded)")
    out = parser.add_argument_group("output")
    out.add_argument("--out", metavar="DIR",
                     help="runs folder: each run writes its own subfolder here "
                          "(default: the window's setting, ~/spdepth-runs)")
    out.add_argument("--screenshot", metavar="PNG",
                     help="grab the whole window into PNG when the scan ends")
    out.add_argument("--exit-after-scan", action="store_true",
                     help="close the window when the scan ends (exit 0 when done, 1 otherwise)")
    out.add_argument("--view", choices=("maps", "3d"), default="maps",
                     help="what the window shows: the maps, or the 3-D point cloud (needs OpenGL: "
                          "a display, or xvfb-run with Mesa)")
    out.add_argument("--window-size", type=size_wxh, metavar="WxH",
                     help="window size in screen pixels (default 1480x900)")


def spec_from_args(args: argparse.Namespace, base=None):
    """``(spec, start)``: the ``gui.sources.SourceSpec`` of the arguments on top of ``base`` (the
    window's remembered settings), and whether they name a source to start at once."""
    import dataclasses

    from spdepth.acq.errors import RequestError
    from spdepth.gui.sources import SourceSpec

    kinds = [k for k, on in (("sim", args.sim), ("real", bool(args.galvo or args.tagger)),
                             ("replay", bool(args.replay)), ("file", bool(args.file))) if on]
    if len(kinds) > 1:
        raise RequestError("give one source: --sim, --galvo/--tagger, --replay or --file")
    changes = {"kind": kinds[0]} if kinds else {}
    for name, field in (("scene", "scene"), ("sbr", "sbr"), ("seed", "seed"), ("faults", "faults"),
                        ("size", "size"), ("target", "target"), ("mode", "mode"),
                        ("dwell_limit_ms", "dwell_limit_ms"), ("method", "method"),
                        ("galvo", "galvo_port"), ("tagger", "tagger_url"),
                        ("sync_rate_hz", "sync_rate_hz"), ("fov_deg", "fov_deg"),
                        ("replay", "recording"),
                        ("file", "file"), ("time_unit_ps", "time_unit_ps"),
                        ("pulse_rms_ps", "pulse_rms_ps"), ("reflectors", "reflectors"),
                        ("out", "out_root")):
        value = getattr(args, name)
        if value is not None:
            changes[field] = value
    if args.dwell_ms is not None:        # one control holds the gated limit or the raster dwell
        changes["dwell_limit_ms"] = args.dwell_ms
    if kinds in (["replay"], ["file"]) and args.target is None:
        changes["target"] = 0            # as recorded / every detection
    if kinds == ["replay"] and args.reflectors is None:
        changes["reflectors"] = 0        # as recorded
    if kinds == ["file"]:
        changes.setdefault("time_unit_ps", 0.0)      # not a remembered one: the file's own
        changes.setdefault("pulse_rms_ps", 0.0)      # estimated
    if kinds == ["sim"] and args.faults is None:
        changes["faults"] = ""           # a remembered fault spec must not sneak into a CLI run
    return dataclasses.replace(base or SourceSpec(), **changes), bool(kinds)


def run(args: argparse.Namespace) -> int:
    import dataclasses

    from spdepth.acq.requests import ScanRequest
    from spdepth.gui.app import (WINDOW_SIZE, application, platform_problem, remembered_spec,
                                 run_window)

    problem = platform_problem()
    if problem:
        import sys

        from spdepth.acq.commands import EXIT_FAILED

        print(f"spdepth gui: {problem}", file=sys.stderr)
        return EXIT_FAILED
    application()
    spec, start = spec_from_args(args, remembered_spec())
    # a source to start is checked here: bad arguments are one line and exit 2, no window; the
    # window then runs exactly this request (its controls could clamp a value)
    request = spec.to_request() if start else None
    if isinstance(request, ScanRequest) and \
            (args.dwell_limit_ms is not None or args.dwell_ms is not None):
        # the dwell as the options said it (the control holds either): the request refuses a
        # raster --dwell-limit-ms, a gated --dwell-ms or both, as spdepth scan does
        ms = lambda v: v * 1e-3 if v else None          # noqa: E731 - 0: the default
        request = dataclasses.replace(request, dwell_limit_s=ms(args.dwell_limit_ms),
                                      dwell_s=ms(args.dwell_ms))
    size = args.window_size[::-1] if args.window_size else (WINDOW_SIZE if args.screenshot else None)
    return run_window(request or spec, controls=spec, start=start, screenshot=args.screenshot,
                      exit_after_scan=args.exit_after_scan, window_size=size, view=args.view)
