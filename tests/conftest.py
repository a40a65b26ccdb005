"""Shared pytest setup: hardware options, seeded randomness, the shared-data folder, and a
settings folder of its own for every test (the user's ``~/.config`` is never written)."""

from __future__ import annotations

import hashlib
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


USER_SETTINGS = Path.home() / ".config" / "spdepth"
"""Where the window keeps a user's settings (QSettings "spdepth"/"spdepth" on Linux)."""


def _fingerprint(folder: Path) -> dict:
    """Each file under ``folder`` with a hash of its bytes ({} when there is no folder)."""
    if not folder.is_dir():
        return {}
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.fixture(scope="session", autouse=True)
def user_settings_untouched():
    """The whole run leaves the user's ``~/.config/spdepth`` as it found it (a test that wrote
    there once left a pytest folder as the window's runs folder, where pytest deletes the runs)."""
    before = _fingerprint(USER_SETTINGS)
    yield
    after = _fingerprint(USER_SETTINGS)
    assert after == before, f"the tests changed {USER_SETTINGS}: {sorted(set(after) | set(before))}"


@pytest.fixture(autouse=True)
def own_settings_folder(tmp_path_factory, monkeypatch) -> Path:
    """Every test its own settings folder: ``XDG_CONFIG_HOME`` (children, e.g. ``spdepth gui``,
    inherit it) and Qt's user-scope QSettings path (Qt reads the environment only once per
    process), both set before the test makes any QSettings."""
    folder = tmp_path_factory.mktemp("config", numbered=True)
    monkeypatch.setenv("XDG_CONFIG_HOME", str(folder))
    try:
        from PySide6 import QtCore
    except ImportError:        # no Qt: nothing in this run can make a QSettings
        return folder
    for fmt in (QtCore.QSettings.NativeFormat, QtCore.QSettings.IniFormat):
        QtCore.QSettings.setPath(fmt, QtCore.QSettings.UserScope, str(folder))
    return folder
