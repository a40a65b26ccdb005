"""Subcommands of ``spdepth``. Each module here is one subcommand named after the module and
defines ``HELP`` (one line), ``add_arguments(parser)`` and ``run(args) -> int``.

Modules keep heavy imports (numba kernels, Qt) inside ``run`` so ``spdepth --help`` stays fast.
"""

EXIT_OK = 0
"""Done."""
EXIT_FAILED = 1
"""The session failed or was aborted (the files so far are kept; the error is in run.json)."""
EXIT_USAGE = 2
"""Bad input or usage: a file, field, value or option (argparse's own status too)."""
EXIT_DEVICE = 3
"""A device that is missing or failed."""
EXIT_INTERRUPTED = 130
"""Ctrl-C or SIGTERM (128 + SIGINT, as shells report it): the session was aborted cleanly."""


class Terminated(KeyboardInterrupt):
    """SIGTERM, raised in the main thread so it unwinds exactly as Ctrl-C does (the session is
    aborted cleanly and its files are written)."""
