"""The process's thread pools for the nogil kernels (``recon.pixelwise.over_threads``, the pulse
estimate's pair histogram in ``recon.model``): a module of its own, below both, since pixelwise
imports model."""

from __future__ import annotations

import threading
from concurrent.futures import ThreadPoolExecutor

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
