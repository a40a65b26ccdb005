"""The ``spdepth`` command: finds the subcommands in ``acq.commands`` and turns every spdepth
error into a one-line message with exit status 2."""

from __future__ import annotations

import argparse
import importlib
import logging
import pkgutil
import sys

import acq.commands
from recon.errors import SpdError

EXIT_USAGE = 2


def _command_modules():
    for info in sorted(pkgutil.iter_modules(acq.commands.__path__), key=lambda i: i.name):
        if not info.name.startswith("_"):
            yield info.name, importlib.import_module(f"acq.commands.{info.name}")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="spdepth",
        description="Single-photon depth imaging: drive the scan, record tags, reconstruct depth.",
    )
    parser.add_argument("-v", "--verbose", action="count", default=0,
                        help="more logging on stderr (-vv for device traffic)")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name, module in _command_modules():
        cmd = sub.add_parser(name, help=module.HELP, description=module.HELP)
        module.add_arguments(cmd)
        cmd.set_defaults(_run=module.run)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    level = {0: logging.WARNING, 1: logging.INFO}.get(args.verbose, logging.DEBUG)
    logging.basicConfig(level=level, format="%(levelname)s %(name)s: %(message)s")
    try:
        return int(args._run(args) or 0)
    except SpdError as exc:
        print(f"spdepth {args.command}: error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt:
        print(f"spdepth {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
