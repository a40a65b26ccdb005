"""Shared pytest setup: hardware options, seeded randomness, the shared-data folder."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

# Qt must never look for a display in tests.
os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")

SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"


def pytest_addoption(parser):
    parser.addoption("--galvo-port", default=None,
                     help="serial port or pyserial URL of a real galvo controller (enables hardware tests)")
    parser.addoption("--tagger", default=None,
                     help="real time tagger as usb:VID:PID (enables hardware tests)")
    parser.addoption("--picoquant", default=None, metavar="MODEL[:SERIAL]",
                     help="real PicoQuant device, e.g. mh150 or mh150:1234567 (enables its "
                          "hardware tests)")
    parser.addoption("--picoquant-lib", default=None, metavar="PATH",
                     help="the PicoQuant library file (default: the driver's search)")
    parser.addoption("--nidaq", default=None, metavar="DEV[/aoN:M]",
                     help="real NI-DAQ device driving a galvo, e.g. Dev1/ao0:1 (moves the mirror; "
                          "enables its hardware tests)")
    parser.addoption("--swabian", default=None, metavar="SERIAL|any",
                     help="real Swabian Time Tagger (enables its hardware tests)")


HARDWARE_OPTIONS = ("--galvo-port", "--tagger", "--picoquant", "--nidaq", "--swabian")


def pytest_collection_modifyitems(config, items):
    have_hw = any(config.getoption(o) for o in HARDWARE_OPTIONS)
    if have_hw:
        return
    skip = pytest.mark.skip(reason="hardware test: name a device with --galvo-port, --tagger, "
                                   "--picoquant, --nidaq or --swabian")
    for item in items:
        if "hardware" in item.keywords:
            item.add_marker(skip)


@pytest.fixture
def rng(request):
    """A generator seeded from the test's name, so every failure reproduces."""
    seed = int.from_bytes(request.node.nodeid.encode()[-8:].rjust(8, b"\0"), "little") % 2**32
    return np.random.default_rng(seed)


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """The folder of real measurements from other labs; tests using it skip when it is absent."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"shared data folder not found at {SHARED_DATA}")
    return SHARED_DATA
