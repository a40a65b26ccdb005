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


@pytest.hookimpl(optionalhook=True)
def pytest_xdist_auto_num_workers(config):
    """``-n auto`` (the default, pyproject.toml): two processes where there are two cores or more
    (the count measured: 414 s warm against 627 s in one process here; a few 4096 x 4096 frames
    cost a gigabyte each per process), one process on one core and for hardware tests (a real
    device opens in one process at a time)."""
    if any(config.getoption(o) for o in HARDWARE_OPTIONS):
        return 0
    return 2 if (os.cpu_count() or 1) >= 2 else 0


def _precompile(config, n_tests: int) -> None:
    """A cold numba cache (a clean clone): the kernels compiled in two processes at once before the
    first test (tests/precompile.py)."""
    if config.option.collectonly:
        return
    from tests.precompile import precompile

    reporter = config.pluginmanager.get_plugin("terminalreporter")
    precompile(n_tests, say=reporter.write_line if reporter else print)


def pytest_collection_finish(session):
    # in the suite's processes (pytest-xdist's workers) the controller does it, once
    if not hasattr(session.config, "workerinput"):
        _precompile(session.config, len(session.items))


_precompiled = False


@pytest.hookimpl(optionalhook=True)
def pytest_xdist_node_collection_finished(node, ids):
    """The controller, when the first worker has collected: no test is handed out before every
    worker has, so they all wait for the kernels, and its lines show (a worker's do not)."""
    global _precompiled
    if not _precompiled:
        _precompiled = True
        _precompile(node.config, len(ids))


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
def user_settings_untouched(tmp_path_factory):
    """The whole run leaves the user's ``~/.config/spdepth`` as it found it (a test that wrote
    there once left a pytest folder as the window's runs folder, where pytest deletes the runs).
    A change naming this run's temporary folders is this run's doing and fails it; any other
    change (another process on the machine) is only a warning."""
    before = _fingerprint(USER_SETTINGS)
    yield
    after = _fingerprint(USER_SETTINGS)
    if after == before:
        return
    ours = str(tmp_path_factory.getbasetemp())
    changed = sorted(k for k in set(before) | set(after) if before.get(k) != after.get(k))
    texts = [(USER_SETTINGS / k).read_text(errors="replace") for k in changed
             if (USER_SETTINGS / k).is_file()]
    assert not any(ours in t for t in texts), \
        f"the tests wrote their temporary folder {ours} into {USER_SETTINGS}: {changed}"
    import warnings

    warnings.warn(f"{USER_SETTINGS} changed during the run ({changed}), not by these tests "
                  f"(it names none of their folders)")


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


# ---- fixtures the test modules share -----------------------------------------------------------

@pytest.fixture
def settings(tmp_path):
    """The window's QSettings for one test, an ini file in its own folder."""
    from PySide6 import QtCore

    return QtCore.QSettings(str(tmp_path / "spdepth.ini"), QtCore.QSettings.IniFormat)


@pytest.fixture
def win(qtbot, settings, tmp_path):
    """The window, shown (1200 x 800) with ``settings`` and its runs folder in ``tmp_path``; shut
    down after the test (its session, if any, aborted)."""
    from spdepth.gui.window import MainWindow

    w = MainWindow(settings=settings)
    w.controls.out_root.setText(str(tmp_path / "runs"))
    qtbot.addWidget(w)
    w.resize(1200, 800)
    w.show()
    yield w
    w.shutdown(timeout_s=10)


@pytest.fixture
def real_time_sim(monkeypatch):
    """The simulated galvo dwells in real time (``pace``), as a lab scan does: the simulator
    otherwise scans a 64x64 image faster than the window repaints, and a test of what the window
    shows *during* a scan would see only its start and end."""
    from spdepth.acq import instruments

    open_sim = instruments.open_sim

    def paced(*args, galvo_options=None, **kw):
        return open_sim(*args, galvo_options={"pace": 1.0, **(galvo_options or {})}, **kw)

    monkeypatch.setattr(instruments, "open_sim", paced)


def _simulate(out: Path, *args: str) -> Path:
    """``spdepth simulate ARGS --ptu OUT`` (in this process)."""
    from spdepth.acq.cli import main

    assert main(["simulate", *args, "--ptu", str(out)]) == 0
    return out


@pytest.fixture(scope="module")
def small_ptu(tmp_path_factory) -> Path:
    """A 16 x 12 simulated PTU of the "steps" scene (20 detections per pixel)."""
    return _simulate(tmp_path_factory.mktemp("ptu") / "steps.ptu", "--scene", "steps",
                     "--size", "16x12", "--ppp", "20")


@pytest.fixture(scope="module")
def simulated_ptus(tmp_path_factory) -> tuple[Path, list[str]]:
    """(folder, paths) of three 40 x 30 simulated PTUs with pixel markers: bust, steps, two-layer."""
    d = tmp_path_factory.mktemp("dask")
    paths = [str(_simulate(d / f"{scene}.ptu", "--scene", scene, "--size", "40x30", "--ppp", "12",
                           "--seed", str(i)))
             for i, scene in enumerate(("bust", "steps", "two-layer"))]
    return d, paths


@pytest.fixture(scope="module")
def client():
    """A ``dask.distributed`` client of a local cluster of 2 worker processes (127.0.0.1 only)."""
    from spdepth.acq import distributed

    with distributed.connect("local:2") as c:
        yield c


@pytest.fixture(scope="module")
def recording(tmp_path_factory) -> Path:
    """A finished 16 x 16 session's folder (kept read-only by the tests: they copy it)."""
    from spdepth.acq.instruments import open_sim
    from spdepth.acq.session import SessionState
    from tests.sessions import sim_session

    out = tmp_path_factory.mktemp("rec") / "live"
    with open_sim("bust", (16, 16), ppp=10, seed=21) as inst:
        s = sim_session(inst, (16, 16), out, method="uos")
        assert s.run() == SessionState.DONE, s.error
    return out


@pytest.fixture(scope="module")
def quick_report(tmp_path_factory):
    """(folder, rows of results.csv) of ``spdepth bench report --quick`` (about a minute)."""
    import csv

    from spdepth.acq.cli import main

    out = tmp_path_factory.mktemp("bench_report")
    assert main(["bench", "report", "--quick", "--out", str(out)]) == 0
    with open(out / "results.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    return out, rows
