"""``spdepth scan``: one acquisition session against the simulated bench or real devices, recorded
and reconstructed live, written to a folder. Its options are ``acq.params``' of the "sim" and
"real" sources."""

from __future__ import annotations

import argparse

from spdepth.acq.params import add_options

HELP = "scan (simulated or real devices), record the tag stream, reconstruct live, write the maps"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_options(parser, "scan")


def request_from_args(args: argparse.Namespace, command: str = "scan"):
    """The :class:`~acq.requests.ScanRequest` the arguments of ``command`` (scan, demo, gui)
    stand for, validated as a whole: the simulated bench with ``--sim`` (always for the demo),
    else real devices."""
    from spdepth.acq.errors import RequestError
    from spdepth.acq.params import given
    from spdepth.acq.requests import build_request

    values = given(args, command)
    sim = command == "demo" or bool(getattr(args, "sim", False))
    if not sim and not (values.get("galvo") or values.get("tagger")):
        raise RequestError("give either --sim or both --galvo and --tagger (real devices)")
    return build_request("sim" if sim else "real", values)


def run(args: argparse.Namespace) -> int:
    from spdepth.acq.api import OutputDir, build_session, finish_session, open_instruments
    from spdepth.acq.commands._session import (OutputsProgress, PreparingNotice, compile_live_apart, exit_status,
                                               report, run_session)

    request = request_from_args(args)
    compile_live_apart(request, "scan")
    with OutputDir(args.out, overwrite=args.overwrite) as out:
        with PreparingNotice("scan") as notice, open_instruments(request) as inst:
            session = notice.session = build_session(request, out, inst)
            interrupted = run_session(session, "scan")
        summary = finish_session(session, out.path, request.label(), progress=OutputsProgress("scan"))
    report(summary, args.json, "scan")
    return exit_status(session, interrupted)
