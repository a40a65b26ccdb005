"""What the hardware-in-loop tests share: the device a command-line option names (else the test
is skipped), opened PicoQuant devices, and a reader's chunks over a few seconds."""

from __future__ import annotations

import time

import numpy as np
import pytest


def named(request, option: str, hint: str) -> str:
    """The value of ``option`` (the device to test), or skip the test saying ``hint``."""
    spec = request.config.getoption(option)
    if not spec:
        pytest.skip(hint)
    return spec


def open_picoquant(request, spec: str):
    """The PicoQuant device ``spec`` names (``model[:SERIAL]``), through ``--picoquant-lib``."""
    from spdepth.drivers.picoquant import PicoQuantTagger

    model, _, serial = spec.partition(":")
    return PicoQuantTagger.open(model, serial or None, lib_path=request.config.getoption("--picoquant-lib"))


def chunks_for(reader, seconds: float = 2.0) -> list[np.ndarray]:
    """The non-empty chunks a started ``reader`` gives over ``seconds``; it is stopped after."""
    chunks = []
    try:
        t_end = time.monotonic() + seconds
        while time.monotonic() < t_end:
            c = reader.get(timeout_s=0.1)
            if c is not None and c.size:
                chunks.append(c)
    finally:
        reader.stop()
    return chunks
