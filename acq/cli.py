"""The ``spdepth`` command: finds the subcommands in ``acq.commands`` and turns every error family
spdepth raises on purpose (``recon``'s and ``drivers``') into a one-line message and an exit status."""

from __future__ import annotations

import argparse
import importlib
import logging
import pkgutil
import sys

from spdepth.acq import commands as _commands
from spdepth.acq.errors import AcqError
from spdepth.drivers.errors import DeviceError, SettingError
from spdepth.recon.errors import InputError

EXIT_USAGE = 2
"""Exit status for bad input (a file, field or value) and, as always, for device faults."""

EXIT_CODES: tuple[tuple[type[Exception], int], ...] = (
    (AcqError, EXIT_USAGE),      # acq: a bad request, recording or output
    (InputError, EXIT_USAGE),    # recon: a bad file or setting
    (SettingError, EXIT_USAGE),  # drivers: a bad argument to a driver or simulated device
    (DeviceError, EXIT_USAGE),   # drivers: a fault, timeout or undecodable bytes (also recordings)
)
"""Every error family the CLI reports as one line, with its exit status; the first match wins.
Anything else is a bug and keeps its traceback."""


def exit_code(exc: BaseException) -> int | None:
    """The exit status for an error of a known family, None for anything else."""
    return next((code for family, code in EXIT_CODES if isinstance(exc, family)), None)


def _command_modules():
    for info in sorted(pkgutil.iter_modules(_commands.__path__), key=lambda i: i.name):
        if not info.name.startswith("_"):
            yield info.name, importlib.import_module(f"spdepth.acq.commands.{info.name}")


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
    except tuple(family for family, _ in EXIT_CODES) as exc:
        print(f"spdepth {args.command}: error: {exc}", file=sys.stderr)
        return exit_code(exc)
    except KeyboardInterrupt:
        print(f"spdepth {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
