"""The process's thread pools for the nogil kernels (``recon.pixelwise.over_threads``, the pulse
estimate's pair histogram in ``recon.model``): a module of its own, below both, since pixelwise
imports model."""

from __future__ import annotations

import threading
from concurrent.futures import ThreadPoolExecutor, wait
from typing import Callable

#: The thread pools, one per thread count, kept for the process: a pool made and shut down per call
#: cost about 0.4 ms (an array frame's estimator and return test make five calls: 2 ms of its 33).
_POOLS: dict[int, ThreadPoolExecutor] = {}
_POOLS_LOCK = threading.Lock()
_POOL_PREFIX = "spdepth-fit"


def shared_pool(workers: int) -> ThreadPoolExecutor | None:
    """The process's pool of ``workers`` threads, or None when the caller is one of its threads (a
    fit waiting on the pool from inside it could wait for itself)."""
    if threading.current_thread().name.startswith(_POOL_PREFIX):
        return None
    with _POOLS_LOCK:
        pool = _POOLS.get(workers)
        if pool is None:
            pool = _POOLS[workers] = ThreadPoolExecutor(workers, thread_name_prefix=f"{_POOL_PREFIX}-{workers}")
        return pool


def threads() -> int:
    """The threads a fit runs on: numba's (``numba.set_num_threads``, ``--threads``)."""
    import numba

    return max(1, numba.get_num_threads())


def slices(p0: int, p1: int, workers: int, unit: int = 1) -> list[tuple[int, int]]:
    """[p0, p1) in slices of whole ``unit``s (a kernel's block), about four per one of ``workers``
    threads: a thread that ends its slice early takes another instead of waiting for the slowest."""
    step = max(unit, -(-(p1 - p0) // (4 * workers)) // unit * unit)
    return [(a, min(p1, a + step)) for a in range(p0, p1, step)]


def on_slices(work: Callable[[int, int], None], n: int, unit: int = 1) -> None:
    """``work(a, b)`` over the :func:`slices` of [0, n) on :func:`on_threads`."""
    parts = slices(0, n, threads(), unit)
    on_threads(lambda i: work(*parts[i]), len(parts))


def on_threads(work: Callable[[int], None], n: int) -> None:
    """``work(i)`` for i in range(n) on the process's pool of :func:`threads` threads (in this
    thread when called from one of its own, or for one item): for nogil kernels over independent
    parts, which numba's ``prange`` would compile several times slower. On an error the parts not
    started are cancelled and those running are waited for, so no part writes after this returns."""
    pool = shared_pool(threads()) if n > 1 else None
    if pool is None:
        for i in range(n):
            work(i)
        return
    futures = [pool.submit(work, i) for i in range(n)]
    try:
        for f in futures:
            f.result()
    except BaseException:
        wait([f for f in futures if not f.cancel()])
        raise
