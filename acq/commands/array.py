"""``spdepth array``: a SPAD-array session: frames of per-pixel histograms from the simulated array
(``--sim SCENE``, live at its frame rate) or a recording (``--replay frames.h5``), reconstructed frame
by frame or accumulated (``--mode``), recorded (live: ``OUT/frames.h5``), last maps in ``OUT/maps.npz``,
``OUT/run.json``. The maps take the newest frame whenever the estimator is free (every frame with
``--every-frame``); one line per new maps on stderr. The replay of a recording gives the same frames
and the same final maps bit for bit (``run.json``'s map digests: every frame's with ``--every-frame``).
"""

from __future__ import annotations

import argparse
import sys

from spdepth.acq.params import add_options

HELP = "SPAD-array session: simulated array frames (or a recording's) reconstructed live, recorded (HDF5)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    # declared in acq.params like every command's options (no request carries them: the
    # command's own, as simulate's physics are)
    add_options(parser, "array")


def run(args: argparse.Namespace) -> int:
    from spdepth.acq.api import OutputDir
    from spdepth.acq.array_session import ArraySession, ArrayState, H5ReplaySource, SimArraySource
    from spdepth.acq.commands import EXIT_FAILED, EXIT_OK
    from spdepth.recon.model import ReconSettings

    if args.sim:
        from spdepth.acq.commands.bench.array import make_sensor

        sensor = make_sensor(args.sim, tuple(args.size), args.counts, args.sbr, args.seed,
                             frame_rate_hz=args.frame_rate_hz, hot_share=args.hot_share,
                             crosstalk=args.crosstalk)
        source = SimArraySource(sensor, args.frames, realtime=not args.free_run)
        pulse = sensor.scene.pulse_rms_s
    else:
        source = H5ReplaySource(args.replay, realtime=args.realtime)
        pulse = source.info.get("scene", {}).get("pulse_rms_s")
    with OutputDir(args.out) as out:
        session = ArraySession(source, ReconSettings(method=args.method, pulse_rms_s=pulse), mode=args.mode,
                               out_dir=out.path, every_frame=args.every_frame)
        if args.gui:
            _run_window(session, source, args.screenshot)
        else:
            session.start()
        shown = 0
        while session.wait(0.2) in (ArrayState.IDLE, ArrayState.RUNNING, ArrayState.PAUSED):
            snap = session.snapshot()
            if session.reconstructed > shown and snap.maps is not None:
                import numpy as np

                shown = session.reconstructed
                d = snap.maps.depth_m
                print(f"frame {snap.frames}/{snap.n_frames}, maps of frame {shown}: {np.isfinite(d).sum()} "
                      f"depths, median "
                      f"{np.nanmedian(d):.3f} m; acquired {snap.acquired_fps:.1f} frames/s, recon "
                      f"{snap.recon_fps:.1f} frames/s", file=sys.stderr)
        snap = session.snapshot()
    print(f"{source.name}: {session.state.value}, {snap.frames} frames ({args.mode}), acquired "
          f"{snap.acquired_fps:.1f} frames/s; {session.recon_runs} reconstructions at {snap.recon_fps:.1f}/s, "
          f"the last of frame {session.reconstructed}; {args.out}")
    if session.error is not None:
        print(f"spdepth array: {type(session.error).__name__}: {session.error}", file=sys.stderr)
    return EXIT_OK if session.state == ArrayState.DONE else EXIT_FAILED


def _run_window(session, source, screenshot: str | None) -> None:
    """The session in its window until the window is closed (with ``screenshot``: until the
    session ends, then the window is saved and closed)."""
    from PySide6 import QtCore, QtWidgets

    from spdepth.acq.api import sensor_fov_deg
    from spdepth.acq.array_session import ArrayState
    from spdepth.acq.points import ScanGeometry
    from spdepth.gui.array_window import ArrayWindow

    app = QtWidgets.QApplication.instance() or QtWidgets.QApplication([])
    fov = sensor_fov_deg(source.shape, source.geometry)
    win = ArrayWindow(session, None if fov is None else ScanGeometry.from_fov(source.shape, fov))
    win.show()
    session.start()
    if screenshot:
        def check():
            if session.state not in (ArrayState.IDLE, ArrayState.RUNNING, ArrayState.PAUSED):
                session.wait()
                win.refresh()
                win.grab().save(screenshot)
                win.close()
        timer = QtCore.QTimer()
        timer.timeout.connect(check)
        timer.start(100)
    app.exec()
