"""Waiting in tests on a condition, never on a guessed sleep: a loaded 2-core CI machine can be
ten times slower than a laptop, and a sleep that is long enough there is a waste everywhere else."""

from __future__ import annotations

import time
from typing import Callable, TypeVar

T = TypeVar("T")


def wait_until(predicate: Callable[[], T], timeout_s: float = 30.0, poll_s: float = 0.005,
               what: str = "") -> T:
    """Poll ``predicate()`` until it returns something truthy and return that; fail the test
    with an AssertionError naming ``what`` after ``timeout_s`` seconds. Keep the timeout generous:
    it only costs time when the test is failing anyway."""
    deadline = time.monotonic() + timeout_s
    while True:
        value = predicate()
        if value:
            return value
        if time.monotonic() >= deadline:
            raise AssertionError(f"timed out after {timeout_s:g} s waiting for "
                                 f"{what or getattr(predicate, '__name__', 'a condition')}")
        time.sleep(poll_s)
