"""The tests never write the user's settings: each test has its own settings folder
(``conftest.own_settings_folder``), and the whole run leaves ``~/.config/spdepth`` as it was
(``conftest.user_settings_untouched``)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def test_a_window_with_default_settings_writes_into_the_tests_own_folder(qtbot, own_settings_folder):
    pytest.importorskip("pytestqt")
    from spdepth.gui.window import MainWindow

    w = MainWindow()                       # QSettings("spdepth", "spdepth"), as `spdepth gui` makes
    qtbot.addWidget(w)
    w.save_settings()
    w.settings.sync()
    assert Path(w.settings.fileName()) == own_settings_folder / "spdepth" / "spdepth.conf"
    assert Path(w.settings.fileName()).is_file()
    assert os.environ["XDG_CONFIG_HOME"] == str(own_settings_folder)


@pytest.mark.slow
def test_the_window_from_the_shell_leaves_home_untouched(tmp_path):
    """A test that runs ``spdepth gui`` in a child process (the one that wrote a pytest folder
    into ``~/.config/spdepth/spdepth.conf`` as the window's runs folder), run by pytest with HOME
    an empty folder and no XDG_CONFIG_HOME: HOME/.config is never made."""
    home = tmp_path / "home"
    home.mkdir()
    env = {k: v for k, v in os.environ.items() if k != "XDG_CONFIG_HOME"}
    env.update(HOME=str(home), QT_QPA_PLATFORM="offscreen")
    test = "tests/test_cli_session.py::test_ctrl_c_closes_the_window_aborts_its_scan_and_exits_130"
    done = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider",
                           "--basetemp", str(tmp_path / "basetemp"), test],
                          cwd=ROOT, env=env, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-2000:]
    assert "1 passed" in done.stdout
    assert not (home / ".config").exists()       # nor matplotlib's, or anyone's
