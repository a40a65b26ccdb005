"""``spdepth replay``: feed a recording through the same session pipeline as a live tagger. Its
options are ``acq.params``' of the "replay" source."""

from __future__ import annotations

import argparse

from spdepth.acq.params import add_options

HELP = "replay a recording (or a PTU with pixel markers) through the session pipeline"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_options(parser, "replay")


def request_from_args(args: argparse.Namespace):
    from spdepth.acq.params import given
    from spdepth.acq.requests import build_request

    return build_request("replay", given(args, "replay"))


def run(args: argparse.Namespace) -> int:
    from pathlib import Path

    from spdepth.acq.api import OutputDir, build_session, finish_session
    from spdepth.acq.commands._session import (OutputsProgress, PreparingNotice, exit_status, report,
                                               run_session)
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
                                                    f"{asked.method}{surfaces}",
                                 progress=OutputsProgress("replay"))
    report(summary, args.json, "replay")
    return exit_status(session, interrupted)
