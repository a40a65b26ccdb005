"""Numba kernels compiled for the one signature they are used with.

A kernel called with the field views of a structured array (``EVENT_DTYPE`` rows, strided: numba
layout 'A') is called with contiguous views now and then too (a chunk of one event), and numba
compiles a second specialisation for those, seconds on a fresh install. :func:`call_strided`
compiles (or loads from numba's cache) the strided one on the first call and no other: a
contiguous array passes where a strided one is declared, at the same speed for these loops.
"""

from __future__ import annotations

import threading

import numba

_lock = threading.Lock()


def call_strided(kernel, strided: tuple[int, ...], *args):
    """``kernel(*args)``, compiled on first use for the types of ``args`` with the arrays at
    positions ``strided`` declared any-layout ('A'), and never again for other layouts.
    ``kernel`` is an ``njit`` dispatcher; its other arguments keep the types they have here."""
    if not kernel.signatures:
        with _lock:
            if not kernel.signatures:
                sig = tuple(numba.typeof(a).copy(layout="A") if i in strided else numba.typeof(a)
                            for i, a in enumerate(args))
                kernel.compile(sig)
                kernel.disable_compile()
    return kernel(*args)


__all__ = ["call_strided"]
