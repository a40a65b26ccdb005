"""``spdepth gui``: the live window (maps filling in during the scan, pixel inspector, controls),
optionally starting a scan, replay or file reconstruction at once, grabbing a screenshot and
exiting at its end.

Its options are every declared option (``acq.params``) of the sources the window runs: those of
``spdepth scan`` (sim and real), ``replay`` and ``recon``'s reading and estimator. A source given
on the command line runs the request ``acq.params.build_request`` makes of the window's remembered
settings for that source kind (each checked when loaded) with the command line on top: the command
line always wins, and a stored value that no longer validates falls back to its default (one line
in the status bar) instead of blocking the start."""

from __future__ import annotations

import argparse

from spdepth.acq.params import add_options

HELP = ("open the live window; with --sim, --galvo/--tagger or --replay start that scan at once, "
        "with --file reconstruct a PTU/.mat file in it")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_options(parser, "gui")


def source_of(args: argparse.Namespace) -> str | None:
    """The source kind the arguments start (None: the window waits for Start)."""
    from spdepth.acq.errors import RequestError

    kinds = [k for k, on in (("sim", args.sim), ("real", bool((args.galvo or args.tagger) and not args.sim)),
                             ("replay", bool(args.replay)), ("file", bool(args.file))) if on]
    if len(kinds) > 1:
        raise RequestError("give one source: --sim, --galvo/--tagger, --replay or --file")
    return kinds[0] if kinds else None


def request_from_args(args: argparse.Namespace, remembered):
    """``(request, spec)``: the request of the source the arguments start (None without one) and
    the controls to show. The stored settings of that kind (``remembered``, a
    ``gui.sources.Remembered``) under the command line's options: what the command line gives
    wins; a dwell or mode given there replaces the stored dwell (one control holds either)."""
    from spdepth.acq.params import given
    from spdepth.acq.requests import build_request

    source = source_of(args)
    runs = {"out_root": args.runs_dir} if args.runs_dir else {}
    if source is None:
        import dataclasses

        return None, dataclasses.replace(remembered.spec(), **runs)
    import dataclasses

    base = dataclasses.replace(remembered.spec(source), **runs)
    cli = given(args, "gui")
    if "mode" in cli:
        base = dataclasses.replace(base, mode=cli["mode"])
    values = base.values()
    if {"mode", "dwell_limit_ms", "dwell_ms"} & set(cli):
        values.pop("dwell_limit_ms", None)
        values.pop("dwell_ms", None)
    values.update(cli)
    request = build_request(source, values)
    from spdepth.gui.sources import SourceSpec

    return request, SourceSpec.from_request(request, base)


def run(args: argparse.Namespace) -> int:
    from spdepth.gui.app import (WINDOW_SIZE, application, platform_problem, remembered,
                                 run_window)

    problem = platform_problem()
    if problem:
        import sys

        from spdepth.acq.commands import EXIT_FAILED

        print(f"spdepth gui: {problem}", file=sys.stderr)
        return EXIT_FAILED
    if args.out is not None and source_of(args) in (None, "file"):
        from spdepth.acq.errors import RequestError

        raise RequestError("--out names the folder of the run started from the command line (a "
                           "scan or a replay; a file reconstructed in the window writes nothing): "
                           "give --sim, --galvo/--tagger or --replay, or --runs-dir")
    from spdepth.acq.outputs import check_output_folder, refuse_existing

    # before a window opens: the screenshot and the folders it would write
    refuse_existing([("--screenshot", args.screenshot)], overwrite=args.overwrite)
    check_output_folder("--out", args.out)
    check_output_folder("--runs-dir", args.runs_dir)
    application()
    stored = remembered()
    # a source to start is checked here: bad arguments are one line and exit 2, no window; the
    # window then runs exactly this request (its controls could clamp a value)
    request, spec = request_from_args(args, stored)
    source = source_of(args)
    # the window shows its restored kind's notes itself; a source of another kind adds its own
    notes = stored.notes.get(source, []) if source not in (None, stored.kind) else []
    size = args.window_size[::-1] if args.window_size else (WINDOW_SIZE if args.screenshot else None)
    kw = dict(controls=spec, start=request is not None, screenshot=args.screenshot,
              exit_after_scan=args.exit_after_scan, window_size=size, view=args.view, notes=notes)
    if args.out is not None:
        from spdepth.acq.api import OutputDir

        with OutputDir(args.out, overwrite=args.overwrite) as out:
            return run_window(request, out_dir=out.path, **kw)
    return run_window(request or spec, **kw)
