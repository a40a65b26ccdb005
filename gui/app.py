"""Running the window as an application (``spdepth gui``): the QApplication, an optional source
started at once, a screenshot at the end of the scan, and exit after it."""

from __future__ import annotations

import logging
import os
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


def remembered_spec(settings=None):
    """The source settings the window stored last time (None when there are none)."""
    import json

    from PySide6 import QtCore

    from spdepth.gui.sources import SourceSpec

    settings = settings if settings is not None else QtCore.QSettings("spdepth", "spdepth")
    raw = settings.value("source")
    if not raw:
        return None
    try:
        return SourceSpec.from_dict(json.loads(raw))
    except (ValueError, TypeError):
        return None


def run_window(what=None, *, start: bool = True, screenshot: str | Path | None = None,
               exit_after_scan: bool = False, out_dir="auto",
               window_size: tuple[int, int] | None = None, settings=None, controls=None,
               view: str = "maps") -> int:
    """Show the window with ``what`` in its controls (a ``gui.sources.SourceSpec``, or an
    ``acq.requests`` scan/replay/file request, which is run as given), started at once when
    ``start``, and run the Qt loop. ``controls``: a ``SourceSpec`` shown in the controls first
    (e.g. the remembered settings with the command line's runs folder), under a request.
    ``out_dir`` as ``MainWindow.start_run`` takes it. With ``screenshot``, the whole window is
    grabbed into that PNG when the scan ends; with ``exit_after_scan`` the loop ends then.
    ``window_size`` (width, height) overrides the remembered geometry. ``view``: "maps" or "3d",
    the tab shown. Returns 0 (scan done, or
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
    win.show()
    result = {"code": 0}

    def ended(state: str) -> None:
        result["code"] = 0 if state == "done" else 1
        if screenshot is not None:
            app.processEvents()          # one more paint after the end-of-scan level fit
            win.screenshot(screenshot)
            print(f"spdepth gui: screenshot {screenshot}", file=sys.stderr)
        if exit_after_scan:
            QtCore.QTimer.singleShot(0, win.close)

    win.scan_ended.connect(ended)
    if what is not None and start:
        if not win.start_run(what, out_dir=out_dir) and exit_after_scan:
            print(f"spdepth gui: {win.banner_text.text()}", file=sys.stderr)
            win.close()
            win.deleteLater()
            app.processEvents()
            return 2
    elif exit_after_scan:
        log.warning("--exit-after-scan without a source: the window stays until closed")
    app.exec()
    win.deleteLater()
    app.processEvents()
    return result["code"]


def run_demo_window(request, out_dir=None, *, exit_after_scan: bool = False,
                    screenshot: str | Path | None = None) -> int:
    """``spdepth demo`` with a display: the demo's scan (an ``acq.requests.ScanRequest``) started
    in the window as given. ``out_dir``: the caller's session folder (the caller holds its lock),
    None keeps the run in memory. Returns ``run_window``'s code."""
    application()
    return run_window(request, start=True, out_dir=out_dir, exit_after_scan=exit_after_scan,
                      screenshot=screenshot, window_size=WINDOW_SIZE)


__all__ = ["application", "run_window", "run_demo_window", "display_available",
           "remembered_spec", "WINDOW_SIZE"]
