"""Does the window slow the scan? Detections/s of the same simulated scan (and of a replay of its
recording at full speed) headless and with the window open, alternated, medians and their ratio.

    QT_QPA_PLATFORM=offscreen python -m gui.benchmark [--size 48x48] [--target 10] [--repeats 3]

Headless runs the session alone (as ``spdepth scan`` does, without its progress bar); windowed
starts the same source from ``MainWindow.start_run`` and lets the window paint at its timer's rate.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path


def _headless(spec, out_dir=None) -> float:
    from spdepth.gui.sources import open_run

    run = open_run(spec, out_dir)
    try:
        run.session.start()
        run.session.wait()
    finally:
        run.close()
    snap = run.session.snapshot()
    if snap.state != "done":
        raise RuntimeError(f"headless run ended {snap.state}: {snap.error}")
    return snap.detections_per_s


def _windowed(spec) -> tuple[float, int]:
    from PySide6 import QtCore

    from spdepth.gui.app import application
    from spdepth.gui.window import MainWindow

    app = application()
    settings = QtCore.QSettings(str(Path(tempfile.mkdtemp()) / "bench.ini"),
                                QtCore.QSettings.IniFormat)
    win = MainWindow(settings=settings)
    win.resize(1480, 900)
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
    if not win.start_run(spec, out_dir=None):
        raise RuntimeError(win.banner_text.text())
    loop.exec()
    snap = win.session.snapshot()
    win.close()
    win.deleteLater()
    app.processEvents()
    if snap.state != "done":
        raise RuntimeError(f"windowed run ended {snap.state}: {snap.error}")
    return snap.detections_per_s, paints["n"]


def main(argv=None) -> int:
    from spdepth.acq.commands._args import positive_int, size_wxh
    from spdepth.gui.app import application
    from spdepth.gui.sources import SourceSpec

    ap = argparse.ArgumentParser(prog="python -m gui.benchmark", description=__doc__.split("\n")[0])
    ap.add_argument("--size", type=size_wxh, default=(48, 48), metavar="WxH")
    ap.add_argument("--target", type=positive_int, default=10)
    ap.add_argument("--scene", default="bust")
    ap.add_argument("--repeats", type=positive_int, default=3)
    ap.add_argument("--no-replay", action="store_true", help="skip the replay comparison")
    args = ap.parse_args(argv)
    application()
    spec = SourceSpec(kind="sim", scene=args.scene, size=args.size, target=args.target)
    _headless(SourceSpec(kind="sim", size=(8, 8), target=2))        # warm the numba caches
    rows = []
    results = {"scan": ([], [])}
    tmp = Path(tempfile.mkdtemp(prefix="spdepth-bench-"))
    rec = tmp / "rec"
    _headless(spec, rec)
    replay = SourceSpec(kind="replay", recording=str(rec), target=0, method="uos")
    if not args.no_replay:
        results["replay (max speed)"] = ([], [])
    for i in range(args.repeats):
        for name, (head, win) in results.items():
            s = spec if name == "scan" else replay
            h = _headless(s)
            w, n = _windowed(s)
            head.append(h)
            win.append(w)
            rows.append(f"  {name:20s} run {i + 1}: headless {h:12,.0f} det/s   window {w:12,.0f} "
                        f"det/s   ({n} map repaints)")
            print(rows[-1], file=sys.stderr, flush=True)
    h, w = args.size
    print(f"{args.scene} {w}x{h}, target {args.target}, {args.repeats} alternated runs each "
          f"(medians):")
    for name, (head, win) in results.items():
        mh, mw = statistics.median(head), statistics.median(win)
        print(f"  {name:20s} headless {mh:12,.0f} det/s   window {mw:12,.0f} det/s   "
              f"window/headless {mw / mh:.3f}")
    return 0


if __name__ == "__main__":
    t0 = time.monotonic()
    code = main()
    print(f"({time.monotonic() - t0:.0f} s)", file=sys.stderr)
    sys.exit(code)
