"""Does the window slow the scan? Detections/s of the same simulated scan (and of a replay of its
recording at full speed) headless and with the window open, alternated, medians and their ratio.

:func:`measure` takes plain arguments; the command line that calls it lives with the CLI
(``acq/commands/gui.py``'s ``bench``).

Headless runs the session alone (as ``spdepth scan`` does, without its progress bar); windowed
starts the same request from ``MainWindow.start_run`` and lets the window paint at its timer's
rate.
"""

from __future__ import annotations

import statistics
import sys
import tempfile
from pathlib import Path


def _headless(request, out_dir=None) -> float:
    from spdepth.gui.sources import open_run

    run = open_run(request, out_dir)
    try:
        run.session.start()
        run.session.wait()
    finally:
        run.close()
    snap = run.session.snapshot()
    if snap.state != "done":
        raise RuntimeError(f"headless run ended {snap.state}: {snap.error}")
    return snap.detections_per_s


def _windowed(request, view: str = "maps") -> tuple[float, int]:
    from PySide6 import QtCore

    from spdepth.gui.app import application
    from spdepth.gui.window import MainWindow

    app = application()
    settings = QtCore.QSettings(str(Path(tempfile.mkdtemp()) / "bench.ini"),
                                QtCore.QSettings.IniFormat)
    win = MainWindow(settings=settings)
    win.resize(1480, 900)
    win.show_view(view)
    win.show()
    app.processEvents()            # the window is on screen before Start, as at the bench
    paints = {"n": 0}
    orig = win.refresh

    def counted(maps: bool = True) -> bool:
        painted = orig(maps)
        paints["n"] += bool(painted)
        return painted

    win.refresh = counted          # the timer's _tick calls it (and decides when maps repaint)
    loop = QtCore.QEventLoop()
    win.scan_ended.connect(lambda _s: loop.quit())
    if not win.start_run(request, out_dir=None):
        raise RuntimeError(win.banner_text.text())
    loop.exec()
    snap = win.session.snapshot()
    win.close()
    win.deleteLater()
    app.processEvents()
    if snap.state != "done":
        raise RuntimeError(f"windowed run ended {snap.state}: {snap.error}")
    return snap.detections_per_s, paints["n"]


def measure(*, scene: str = "bust", size: tuple[int, int] = (48, 48), target: int = 10,
            repeats: int = 3, replay: bool = True, out=None, view: str = "maps") -> dict:
    """Alternate headless and windowed runs of a simulated scan of ``scene`` (size (H, W),
    ``target`` detections per pixel) ``repeats`` times, and with ``replay`` of a replay of its
    recording at full speed, the window showing ``view`` ("maps" or "3d"); print the medians to ``out`` (each run to stderr as it ends).
    Returns ``{name: (headless det/s list, windowed det/s list)}``."""
    from spdepth.acq.requests import ReplayRequest, ScanRequest, SimBench
    from spdepth.gui.app import application

    out = out if out is not None else sys.stdout
    application()
    scan = ScanRequest(instruments=SimBench(scene=scene), size=tuple(size), target=target)
    _headless(ScanRequest(size=(8, 8), target=2))        # warm the numba caches
    results = {"scan": ([], [])}
    rec = Path(tempfile.mkdtemp(prefix="spdepth-bench-")) / "rec"
    _headless(scan, rec)
    replayed = ReplayRequest(recording=str(rec), method="uos")
    if replay:
        results["replay (max speed)"] = ([], [])
    for i in range(repeats):
        for name, (head, win) in results.items():
            request = scan if name == "scan" else replayed
            h = _headless(request)
            w, n = _windowed(request, view)
            head.append(h)
            win.append(w)
            print(f"  {name:20s} run {i + 1}: headless {h:12,.0f} det/s   window {w:12,.0f} "
                  f"det/s   ({n} map repaints)", file=sys.stderr, flush=True)
    h, w = size
    print(f"{scene} {w}x{h}, target {target}, window showing {view}, {repeats} alternated runs "
          f"each (medians):", file=out)
    for name, (head, win) in results.items():
        mh, mw = statistics.median(head), statistics.median(win)
        print(f"  {name:20s} headless {mh:12,.0f} det/s   window {mw:12,.0f} det/s   "
              f"window/headless {mw / mh:.3f}", file=out)
    return results


__all__ = ["measure"]
