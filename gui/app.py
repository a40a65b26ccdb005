"""Running the window as an application (``spdepth gui``): the QApplication, an optional source
started at once, a screenshot at the end of the scan, and exit after it."""

from __future__ import annotations

import logging
import os
import signal
import sys
from pathlib import Path

log = logging.getLogger(__name__)

WINDOW_SIZE = (1480, 900)
"""Default window size (width, height): four maps, the controls and the inspector all legible."""


HEADLESS_PLATFORMS = ("offscreen", "minimal")


def display_available(environ=None, platform: str | None = None) -> bool:
    """Whether a window can be shown: on Linux (and other X11/Wayland systems) DISPLAY or
    WAYLAND_DISPLAY set and QT_QPA_PLATFORM not offscreen/minimal; on macOS and Windows always
    (unless QT_QPA_PLATFORM says offscreen/minimal)."""
    env = os.environ if environ is None else environ
    platform = sys.platform if platform is None else platform
    qpa = env.get("QT_QPA_PLATFORM", "").split(":")[0].strip().lower()
    if qpa in HEADLESS_PLATFORMS:
        return False
    if platform == "darwin" or platform.startswith("win"):
        return True
    return bool(env.get("DISPLAY") or env.get("WAYLAND_DISPLAY"))


XCB_PACKAGES = {
    "libxcb-cursor.so.0": "libxcb-cursor0", "libxcb-icccm.so.4": "libxcb-icccm4",
    "libxcb-keysyms.so.1": "libxcb-keysyms1", "libxcb-image.so.0": "libxcb-image0",
    "libxcb-render-util.so.0": "libxcb-render-util0", "libxkbcommon-x11.so.0": "libxkbcommon-x11-0",
    "libxcb-shape.so.0": "libxcb-shape0", "libxcb-xkb.so.1": "libxcb-xkb1",
    "libxcb-randr.so.0": "libxcb-randr0", "libxcb-xinerama.so.0": "libxcb-xinerama0",
}
"""Debian/Ubuntu package of each X library Qt's xcb plugin links (DESIGN.md, "Qt on X11")."""


def missing_libraries(ldd_output: str) -> list[str]:
    """The libraries ``ldd`` reports as "not found", in order, once each."""
    out = []
    for line in ldd_output.splitlines():
        if "not found" in line:
            name = line.split("=>")[0].strip()
            if name and name not in out:
                out.append(name)
    return out


def platform_problem(environ=None, ldd=None) -> str | None:
    """One line saying why Qt could not open a window here (its xcb platform plugin needs system
    libraries that are missing), or None when it can, or when no window is asked for. Qt itself
    aborts the process (exit 134) in that case, with a message naming another library, so this is
    checked before the QApplication is made. ``ldd(path) -> str`` replaces running ``ldd``
    (tests)."""
    env = os.environ if environ is None else environ
    if not sys.platform.startswith("linux") or not display_available(env, "linux"):
        return None
    qpa = env.get("QT_QPA_PLATFORM", "").split(":")[0].strip().lower()
    if qpa not in ("", "xcb") or (not env.get("DISPLAY") and not qpa):
        return None                          # Wayland or another plugin: not checked here
    import PySide6

    qt = Path(PySide6.__file__).parent / "Qt"
    plugin = qt / "plugins" / "platforms" / "libqxcb.so"
    if not plugin.is_file():
        return None
    if ldd is None:
        import subprocess

        def ldd(path):
            run_env = dict(os.environ)
            run_env["LD_LIBRARY_PATH"] = os.pathsep.join(
                [str(qt / "lib"), run_env.get("LD_LIBRARY_PATH", "")])
            try:
                return subprocess.run(["ldd", str(path)], capture_output=True, text=True,
                                      env=run_env, timeout=20).stdout
            except (OSError, subprocess.SubprocessError):
                return ""
    missing = missing_libraries(ldd(plugin))
    if not missing:
        return None
    packages = [XCB_PACKAGES[m] for m in missing if m in XCB_PACKAGES]
    hint = f" (Debian/Ubuntu: apt-get install {' '.join(packages)})" if packages else ""
    return (f"Qt cannot open a window: its X11 plugin needs {', '.join(missing)}, missing "
            f"here{hint}")


def application():
    """The QApplication (created once)."""
    from PySide6 import QtWidgets

    from PySide6 import QtCore

    app = QtWidgets.QApplication.instance()
    if app is None:
        # one GL resource space for every 3-D view of the process (gui.view3d)
        QtCore.QCoreApplication.setAttribute(QtCore.Qt.AA_ShareOpenGLContexts)
        app = QtWidgets.QApplication(sys.argv[:1])
        app.setOrganizationName("spdepth")
        app.setApplicationName("spdepth")
    return app


def remembered(settings=None):
    """The window's stored settings (``gui.sources.Remembered``: per source kind, each value
    checked against the declarations)."""
    from PySide6 import QtCore

    from spdepth.gui.sources import SETTINGS_KEY, Remembered

    settings = settings if settings is not None else QtCore.QSettings("spdepth", "spdepth")
    return Remembered.load(settings.value(SETTINGS_KEY), settings.value("source"))


def run_window(what=None, *, start: bool = True, screenshot: str | Path | None = None,
               exit_after_scan: bool = False, out_dir="auto",
               window_size: tuple[int, int] | None = None, settings=None, controls=None,
               view: str = "maps", notes: list[str] | None = None, on_started=None) -> int:
    """Show the window with ``what`` in its controls (a ``gui.sources.SourceSpec``, or an
    ``acq.requests`` scan/replay/file request, which is run as given), started at once when
    ``start``, and run the Qt loop. ``controls``: a ``SourceSpec`` shown in the controls first
    (e.g. the remembered settings with the command line's runs folder), under a request.
    ``out_dir`` as ``MainWindow.start_run`` takes it. With ``screenshot``, the whole window is
    grabbed into that PNG when the scan ends; with ``exit_after_scan`` the loop ends then.
    ``window_size`` (width, height) overrides the remembered geometry. ``view``: "maps" or "3d",
    the tab shown. ``notes``: lines for the status bar (stored settings that no longer
    validated). ``on_started(run)``: called with the window's ``gui.sources.Run`` once the
    source started (the demo keeps its session and scene for its table). Returns 0 (scan done, or
    window closed), 1 (scan aborted or failed), 2 (the source could not be started and the window
    is not kept)."""
    from PySide6 import QtCore

    from spdepth.gui.sources import SourceSpec
    from spdepth.gui.window import MainWindow

    app = application()
    win = MainWindow(settings=settings)
    if window_size is not None:
        win.resize(*window_size)
    elif not win.settings.contains("geometry"):
        win.resize(*WINDOW_SIZE)
    if controls is not None:
        win.controls.set_spec(controls)
    if isinstance(what, SourceSpec):
        win.controls.set_spec(what)
    elif what is not None:
        win.controls.set_spec(SourceSpec.from_request(what, win.controls.spec()))
    win.show_view(view)
    if notes:
        win.show_notes(notes)
    win.show()
    result = {"code": 0, "interrupted": False}

    def ended(state: str) -> None:
        result["code"] = 0 if state == "done" else 1
        if screenshot is not None:
            app.processEvents()          # one more paint after the end-of-scan level fit
            try:
                win.screenshot(screenshot)
                print(f"spdepth gui: screenshot {screenshot}", file=sys.stderr)
            except OSError as exc:       # an exception here would leave the window open for good
                print(f"spdepth gui: error: {exc}", file=sys.stderr)
                result["code"] = 2
        if exit_after_scan:
            QtCore.QTimer.singleShot(0, win.close)

    win.scan_ended.connect(ended)
    _close_on_signals(win, result)
    if what is not None and start:
        if not win.start_run(what, out_dir=out_dir) and exit_after_scan:
            print(f"spdepth gui: {win.banner_text.text()}", file=sys.stderr)
            win.close()
            win.deleteLater()
            app.processEvents()
            return 2
        if on_started is not None and win.run is not None:
            on_started(win.run)
    elif exit_after_scan:
        log.warning("--exit-after-scan without a source: the window stays until closed")
    app.exec()
    win.deleteLater()
    app.processEvents()
    # closed by Ctrl-C or SIGTERM: the shell's status for a command Ctrl-C ended (128 + SIGINT),
    # as the other commands give (the aborted scan's recording is kept all the same)
    return 128 + int(signal.SIGINT) if result["interrupted"] else result["code"]


def _close_on_signals(win, result: dict) -> None:
    """Ctrl-C (SIGINT) and SIGTERM in the terminal close the window as Ctrl+Q does (a running scan
    is aborted, its recording kept). Python runs signal handlers only between bytecodes, and Qt's
    loop keeps it in C++: a timer hands control back to Python a few times a second. Sets
    ``result["interrupted"]`` when a signal came."""
    from PySide6 import QtCore

    def close(_signum, _frame) -> None:
        result["interrupted"] = True
        # only a run with a folder keeps a recording (the demo's runs in memory)
        run = win.run
        if run is None:
            kept = ""
        elif run.out_dir is not None:
            kept = f" (its recording is kept in {run.out_dir})"
        else:
            kept = " (the run was kept in memory only: no recording)"
        print(f"spdepth gui: interrupted; closing the window{kept}", file=sys.stderr)
        QtCore.QTimer.singleShot(0, win.close)

    try:
        signal.signal(signal.SIGINT, close)
        signal.signal(signal.SIGTERM, close)
    except ValueError:                 # not the main thread (tests): leave the handlers alone
        return
    win._signal_timer = QtCore.QTimer(win)
    win._signal_timer.timeout.connect(lambda: None)
    win._signal_timer.start(200)


def run_demo_window(request, out_dir=None, *, exit_after_scan: bool = False,
                    screenshot: str | Path | None = None, on_started=None) -> int:
    """``spdepth demo`` with a display: the demo's scan (an ``acq.requests.ScanRequest``) started
    in the window as given. ``out_dir``: the caller's session folder (the caller holds its lock),
    None keeps the run in memory. Returns ``run_window``'s code."""
    application()
    return run_window(request, start=True, out_dir=out_dir, exit_after_scan=exit_after_scan,
                      screenshot=screenshot, window_size=WINDOW_SIZE, on_started=on_started)


__all__ = ["application", "run_window", "run_demo_window", "display_available",
           "remembered", "WINDOW_SIZE", "platform_problem", "missing_libraries"]
