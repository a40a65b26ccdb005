"""Subcommands of ``spdepth``. Each module here is one subcommand named after the module and
defines ``HELP`` (one line), ``add_arguments(parser)`` and ``run(args) -> int``.

Modules keep heavy imports (numba kernels, Qt) inside ``run`` so ``spdepth --help`` stays fast.
"""
