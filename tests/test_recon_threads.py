"""recon.pixelwise's thread pools: kept for the process, and never waited on from inside."""

import threading

from spdepth.recon.pixelwise import over_threads, shared_pool


def test_the_pool_is_kept_between_fits():
    assert shared_pool(2) is shared_pool(2)
    assert shared_pool(3) is not shared_pool(2)


def test_a_fit_started_from_a_pool_thread_runs_there_instead_of_waiting_on_the_pool():
    # a pool of 2 whose two threads each wait on a nested fit would wait for themselves forever;
    # nested, the inner fit runs on the calling thread, and every pixel is still covered once
    seen = []
    lock = threading.Lock()

    def inner(a, b):
        with lock:
            seen.extend(range(a, b))

    def outer(a, b):
        over_threads(lambda c, d: inner(a * 1000 + c, a * 1000 + d), 300, 100)

    done = threading.Event()
    t = threading.Thread(target=lambda: (over_threads(outer, 4096, 4096), done.set()), daemon=True)
    t.start()
    assert done.wait(60), "a nested fit waited on its own pool"
    starts = sorted({v // 1000 for v in seen})
    assert len(seen) == 300 * len(starts) and len(set(seen)) == len(seen)


def test_every_pixel_is_fitted_once_and_progress_comes_in_order():
    seen, told = [], []
    lock = threading.Lock()

    def fit(a, b):
        with lock:
            seen.extend(range(a, b))

    over_threads(fit, 5000, 1024, lambda done, total: told.append((done, total, len(seen))))
    assert sorted(seen) == list(range(5000))
    assert [t[:2] for t in told] == [(1024, 5000), (2048, 5000), (3072, 5000), (4096, 5000), (5000, 5000)]
    # each chunk is complete when it is reported: its pixels and all before it were fitted
    assert all(n >= done for done, _, n in told)


def test_a_failing_slice_stops_the_fit_and_nothing_runs_after_it_returns():
    import pytest

    started, running = [], []
    lock = threading.Lock()

    def fit(a, b):
        with lock:
            started.append(a)
            running.append(a)
        try:
            if a == 0:
                raise ValueError("bad pixel")
            threading.Event().wait(0.01)
        finally:
            with lock:
                running.remove(a)

    with pytest.raises(ValueError, match="bad pixel"):
        over_threads(fit, 64 * 400, 64 * 8)
    assert running == []                      # the slices still running were waited for
    assert len(started) < 400                 # and the queued ones cancelled
