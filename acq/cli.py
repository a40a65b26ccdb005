"""The ``spdepth`` command: finds the subcommands in ``acq.commands``, and turns every error family
spdepth raises on purpose into a one-line message and a documented exit status.

Exit status:

==== =====================================================================================
0    done
1    the session failed or was aborted (the files so far are kept; the error is in run.json)
2    bad input or usage: a file, field, value or option (one line naming it)
3    a device that is missing or failed (one line naming it)
130  interrupted (Ctrl-C or SIGTERM): the session was aborted cleanly, its files kept
==== =====================================================================================
"""

from __future__ import annotations

import argparse
import atexit
import contextlib
import gc
import importlib
import logging
import os
import pkgutil
import signal
import sys
import threading

from spdepth.acq import commands as _commands
from spdepth.acq.commands import (EXIT_DEVICE, EXIT_FAILED, EXIT_INTERRUPTED, EXIT_OK,  # noqa: F401
                                  EXIT_USAGE, Terminated)
from spdepth.acq.errors import AcqError, UnreachableError
from spdepth.drivers.errors import DeviceError, SettingError


def exit_codes() -> tuple[tuple[type[Exception], int], ...]:
    """Every error family the CLI reports as one line, with its exit status; the first match
    wins. Anything else is a bug and keeps its traceback. (recon's family is imported here, not
    with the module: importing ``spdepth.recon`` registers its estimators, which loads numpy, and
    ``spdepth --help`` needs none of it.)"""
    from spdepth.recon.errors import InputError

    return (
        (UnreachableError, EXIT_DEVICE),  # acq: a service (Dask scheduler) that does not answer
        (AcqError, EXIT_USAGE),      # acq: a bad request, recording or output folder
        (InputError, EXIT_USAGE),    # recon: a bad file or setting
        (SettingError, EXIT_USAGE),  # drivers: a bad argument to a driver or simulated device
        (DeviceError, EXIT_DEVICE),  # drivers: a device missing, faulted, timed out or undecodable
    )


def __getattr__(name: str):
    if name == "EXIT_CODES":         # the table as it was named before exit_codes()
        return exit_codes()
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def exit_code(exc: BaseException) -> int | None:
    """The exit status for an error of a known family, None for anything else (a bug)."""
    return next((code for family, code in exit_codes() if isinstance(exc, family)), None)


class OneLineParser(argparse.ArgumentParser):
    """argparse with one-line errors: ``spdepth scan: error: ... (see spdepth scan --help)``
    instead of the usage block first."""

    def error(self, message: str):
        self.exit(EXIT_USAGE, f"{self.prog}: error: {message} (see {self.prog} --help)\n")

    def format_help(self) -> str:
        self._expand()
        return super().format_help()

    def format_usage(self) -> str:
        self._expand()
        return super().format_usage()

    def _expand(self) -> None:
        # lists owned elsewhere (estimators, scenes, fault kinds) fill the declared help texts and
        # metavars only when a help or usage is shown (acq.params.expand)
        from spdepth.acq.params import expand

        for action in self._actions:
            if action.help and "{" in action.help:
                action.help = expand(action.help)
            if isinstance(action.metavar, str) and "{" in action.metavar:
                action.metavar = expand(action.metavar)


def _command_modules():
    for info in sorted(pkgutil.iter_modules(_commands.__path__), key=lambda i: i.name):
        if not info.name.startswith("_"):
            yield info.name, importlib.import_module(f"spdepth.acq.commands.{info.name}")


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("spdepth")
    except PackageNotFoundError:
        return "unknown (not installed)"


class _VersionAction(argparse.Action):
    """``--version``: the installed version, looked up only when asked (importlib.metadata's
    lookup costs tens of milliseconds, which every command paid at start as argparse's
    ``version=`` string)."""

    def __init__(self, option_strings, dest=argparse.SUPPRESS, default=argparse.SUPPRESS,
                 help="show the version and exit"):
        super().__init__(option_strings, dest=dest, default=default, nargs=0, help=help)

    def __call__(self, parser, namespace, values, option_string=None):
        print(f"spdepth {_version()}")
        parser.exit()


def build_parser() -> argparse.ArgumentParser:
    parser = OneLineParser(
        prog="spdepth",
        description="Single-photon depth imaging: drive the scan, record tags, reconstruct depth.",
        epilog="exit status: 0 done; 1 session failed or aborted; 2 bad input or usage; "
               "3 device missing or failed; 130 interrupted (Ctrl-C, SIGTERM)")
    parser.add_argument("--version", action=_VersionAction)
    parser.add_argument("-v", "--verbose", action="count", default=0,
                        help="more logging on stderr (-vv for device traffic)")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name, module in _command_modules():
        cmd = sub.add_parser(name, help=module.HELP, description=module.HELP)
        module.add_arguments(cmd)
        cmd.set_defaults(_run=module.run, _parser=cmd)
    return parser


def _raise_terminated(signum, frame):
    raise Terminated()


def small_pages() -> None:
    """Numpy's large arrays without transparent huge pages in this process (and its children),
    unless ``NUMPY_MADVISE_HUGEPAGE`` is set already or numpy is loaded (then its own choice
    stands). Kernels that set huge pages to ``madvise`` with ``defrag`` ``madvise`` (this
    machine's, and a common default) compact memory on the first touch of every 2 MB page numpy
    asks them for, in the faulting thread: a fresh process reading a 512x512 PTU spent 0.35-0.6 s
    of system time there against about 0.1 s with 4 kB pages, and the commands' arrays are
    written once and read a few times, which gains little from fewer TLB misses."""
    if "numpy" not in sys.modules:
        os.environ.setdefault("NUMPY_MADVISE_HUGEPAGE", "0")


#: The cycle collector's first threshold in a ``spdepth`` process (:func:`fewer_collections`).
COLLECT_AFTER = 50_000


def fewer_collections() -> None:
    """The cycle collector's first threshold raised to :data:`COLLECT_AFTER` allocations in this
    process (the console script's; a threshold already higher, or 0, stands). A command builds
    most of its objects as it starts (its modules; numba's typing and lowering registries when the
    first kernel loads, about 140,000 objects) and keeps them until it exits: at the default 700,
    a warm 512x512 recon ran 321 collections, two of them full, 0.085-0.12 s, all holding the GIL
    while the kernels load; at 50,000, 8 collections, 0.04 s. Garbage cycles are still collected,
    in fewer, larger passes (about 5 ms each)."""
    first, second, third = gc.get_threshold()
    if 0 < first < COLLECT_AFTER:
        gc.set_threshold(COLLECT_AFTER, second, third)


def main(argv: list[str] | None = None) -> int:
    small_pages()
    parser = build_parser()
    try:
        args, extra = parser.parse_known_args(argv)
        if extra:     # named by the subcommand that was given them, not by the top level
            args._parser.error(f"unrecognized arguments: {' '.join(extra)}")
    except SystemExit as exc:       # --help, --version and usage errors: their status, returned
        return int(exc.code or 0)
    level = {0: logging.WARNING, 1: logging.INFO}.get(args.verbose, logging.DEBUG)
    logging.basicConfig(level=level, format="%(levelname)s %(name)s: %(message)s")
    # SIGTERM unwinds as Ctrl-C does (a signal handler can only be set from the main thread)
    main_thread = threading.current_thread() is threading.main_thread()
    previous = signal.signal(signal.SIGTERM, _raise_terminated) if main_thread else None
    try:
        return int(args._run(args) or 0)
    except tuple(family for family, _ in exit_codes()) as exc:
        print(f"spdepth {args.command}: error: {exc}", file=sys.stderr)
        return exit_code(exc)
    except KeyboardInterrupt as exc:
        what = "terminated" if isinstance(exc, Terminated) else "interrupted"
        print(f"spdepth {args.command}: {what}", file=sys.stderr)
        return EXIT_INTERRUPTED
    finally:
        if main_thread:
            signal.signal(signal.SIGTERM, previous)


_status: list[int] = []
"""The exit status :func:`console_main` got from :func:`main` (empty: main did not return)."""


def console_main() -> None:
    """The ``spdepth`` console script (and ``python -m spdepth.acq.cli``): :func:`main`, then an
    exit that skips the interpreter's teardown of its modules. That teardown frees numba's compiled
    kernels one by one: 0.7-1.3 s here after a recon or a scan had returned, a third of a warm
    512x512 recon's whole time (mypy ends its runs this way for the same reason). The cycle
    collector runs less often in it (:func:`fewer_collections`).

    Everything a normal exit does before the teardown still runs: the non-daemon threads are
    joined and every atexit handler registered from here on runs before :func:`_hard_exit`,
    which was registered first and so runs last; it flushes the streams and logging and ends the
    process with main's status (1 when main raised: the traceback is printed by then)."""
    atexit.register(_hard_exit)
    fewer_collections()
    _status.append(main())
    sys.exit(_status[0])


def _hard_exit() -> None:
    logging.shutdown()       # registered before console_main's handler: it would not run
    for stream in (sys.stdout, sys.stderr):
        # a stream closed or replaced has nothing to flush
        with contextlib.suppress(OSError, ValueError, AttributeError):
            stream.flush()
    os._exit(_status[0] if _status else 1)


if __name__ == "__main__":
    console_main()
