"""``spdepth demo``: an acquisition session on a built-in scene through the real drivers talking to
the simulated instruments (galvo over a pyserial URL, time tagger over pyusb), recorded, then the
final photons reconstructed with each estimator, compared with the truth and the per-pixel oracle
bound, written as a PNG sheet. The session is the one ``spdepth scan --sim`` runs for the same
options (one request, one library call)."""

from __future__ import annotations

import argparse
import sys
import tempfile
import time

from spdepth.acq.commands.scan import add_scan_arguments, add_sim_arguments, request_from_args
from spdepth.acq.requests import DEFAULT_METHOD
from spdepth.recon import estimators
from spdepth.recon.model import METHODS

HELP = "simulate a recorded count-gated scan session of a built-in scene, reconstruct it, write a PNG"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_sim_arguments(parser)
    add_scan_arguments(parser)
    parser.add_argument("--method", choices=METHODS, default=DEFAULT_METHOD,
                        help=f"estimator of the live maps during the scan (default {DEFAULT_METHOD})")
    pixelwise = ",".join(estimators.names(pixelwise=True))
    parser.add_argument("--compare", default=pixelwise,
                        help="estimators reconstructing the final photons against the truth, "
                             f"comma-separated (default the pixelwise ones, {pixelwise})")
    parser.add_argument("--record", metavar="DIR",
                        help="keep the session's files (recording.ptu, events.jsonl, maps.npz, "
                             "run.json) in DIR (default: a temporary directory, removed)")
    parser.add_argument("--out", default="spdepth-demo.png", help="PNG sheet to write")
    parser.add_argument("--no-window", action="store_true",
                        help="stay headless (the PNG sheet) even when a display exists; without "
                             "a display (CI, ssh, QT_QPA_PLATFORM=offscreen) it always is")


def run(args: argparse.Namespace) -> int:
    from spdepth.acq.api import OutputDir
    from spdepth.acq.errors import RequestError
    from spdepth.acq.requests import check_writable

    args.sim, args.galvo, args.tagger = True, None, None
    request = request_from_args(argparse.Namespace(**vars(args), pulse_rms_ps=None))
    methods = [m.strip() for m in args.compare.split(",") if m.strip()]
    unknown = [m for m in methods if m not in METHODS]
    if not methods or unknown:
        raise RequestError(f"--compare: unknown {', '.join(unknown) or '(none given)'}; "
                           f"choose from {', '.join(METHODS)}")
    check_writable("--out", args.out)
    if not args.no_window:
        from spdepth.gui.app import display_available, platform_problem

        if display_available():
            problem = platform_problem()
            if problem is None:
                return _window(args, request)
            print(f"spdepth demo: {problem}; writing the PNG sheet instead", file=sys.stderr)
    if args.record:
        with OutputDir(args.record, name="--record") as out:
            return _demo(args, request, methods, out.path)
    with tempfile.TemporaryDirectory(prefix="spdepth-demo-") as tmp:
        return _demo(args, request, methods, tmp)


def _window(args, request) -> int:
    """With a display: the same simulated scan in the live window (spdepth gui)."""
    from spdepth.gui.app import run_demo_window

    print("spdepth demo: opening the window (--no-window for the headless PNG sheet)",
          file=sys.stderr)
    if args.record:
        from spdepth.acq.api import OutputDir

        with OutputDir(args.record, name="--record") as out:
            return run_demo_window(request, out_dir=out.path)
    return run_demo_window(request, out_dir=None)


def _demo(args, request, methods, out_dir) -> int:
    import numpy as np

    from spdepth.acq.api import build_session, open_instruments
    from spdepth.acq.commands._session import PreparingNotice, exit_status, run_session
    from spdepth.acq.evaluate import evaluate_depth, signal_detections
    from spdepth.acq.report import render_maps_png
    from spdepth.recon.estimate import reconstruct

    h, w = request.size
    scene_name = request.instruments.scene
    with PreparingNotice("demo") as notice, open_instruments(request) as inst:
        scene = inst.scene
        session = notice.session = build_session(request, out_dir, inst)
        interrupted = run_session(session, "demo")
        galvo_reconnects = inst.galvo.reconnects
        scan_s = inst.rig.now_s
    snap = session.snapshot()
    store = session.store
    if session.error is not None:
        print(f"session {session.state.value}: {session.error}", file=sys.stderr)
    print(f"scanned {scene_name} {w}x{h} through the drivers: {snap.detections} detections in "
          f"{snap.passes} pass{'es' if snap.passes != 1 else ''}, {scan_s:.2f} s of scan time in "
          f"{snap.running_s:.2f} s after {snap.elapsed_s - snap.running_s:.2f} s preparing "
          f"({snap.detections_per_s / 1e3:,.0f} k detections/s, live "
          f"{request.method} lagged at most {session.live_recon.max_lag} pixels)")
    if request.instruments.faults:
        print(f"faults injected: {request.instruments.faults}; galvo reconnects: {galvo_reconnects}; "
              f"lost spans in the tag stream: {len(session.lost)}, re-acquired in later passes")
        for f in session.run_record()["faults_seen"]:
            print(f"  {f['kind']}: {f['what']} -> {f['action']}")
    reasons = session.run_record()["flag_reasons"]
    if sum(reasons.values()):
        print(f"{sum(reasons.values())} pixels flagged short of {request.target} detections "
              f"({reasons}); they keep what they have")

    truth = scene.truth()
    true_depth = np.asarray(truth["depth_m"], dtype=np.float64)
    if true_depth.ndim == 3:
        true_depth = true_depth[0]
    photons = store.photons()
    binning = session.live_recon.requested.binning
    k_signal = signal_detections(truth, store.count.reshape(h, w), window_s=binning.window_stop_s)
    results = {}
    print(f"{'method':<8}{'MAE (cm)':>10}{'x oracle':>10}{'missed':>8}{'recon (s)':>11}{'pixels/s':>12}")
    oracle_cm = None
    live = session.live_recon.requested
    for method in methods:
        settings = live.__class__(method=method, binning=binning, pulse_rms_s=scene.pulse_rms_s,
                                  max_photons=request.target)
        reconstruct(store.photons(np.arange(1)), settings)   # compile outside the timing
        t1 = time.perf_counter()
        maps = reconstruct(photons, settings)
        dt = time.perf_counter() - t1
        e = evaluate_depth(maps.depth_m, true_depth, k_signal, scene.pulse_rms_s)
        if oracle_cm is None:
            oracle_cm = 100 * e.oracle_mae_m
            print(f"{'oracle':<8}{oracle_cm:>10.2f}{1.0:>10.2f}{'':>8}   (per pixel, same pixels)")
        results[method] = (maps, 100 * e.mae_m)
        print(f"{method:<8}{100 * e.mae_m:>10.2f}{e.ratio_to_oracle:>10.2f}"
              f"{100 * e.miss_share:>7.1f}%{dt:>11.3f}{h * w / dt:>12,.0f}")
    if request.method in results:
        same = np.array_equal(session.maps().tof_s, results[request.method][0].tof_s, equal_nan=True)
        print(f"live {request.method} maps {'equal' if same else 'DIFFER FROM'} the batch "
              f"reconstruction of the final store")

    sheet = argparse.Namespace(truth_m=true_depth)
    panels = [("truth_m", "true depth", "m", "turbo", "percentile")]
    for method, (maps, mae_cm) in results.items():
        setattr(sheet, f"{method}_m", maps.depth_m)
        panels.append((f"{method}_m", f"{method}: MAE {mae_cm:.1f} cm, depth", "m", "turbo", "percentile"))
    # the background panel: the default estimator's, else the first that estimates background
    best = results.get(DEFAULT_METHOD) or next(
        (r for m, r in results.items() if estimators.get(m).background), next(iter(results.values())))
    sheet.background = best[0].background
    panels.append(("background", "background", "detections per bin", "magma", "percentile"))
    render_maps_png(args.out, sheet, panels=panels,
                    title=f"{scene_name} {w}x{h}, {request.target} detections per pixel, "
                          f"SBR {request.instruments.sbr:g}")
    print(f"wrote {args.out}" + (f"; session files in {out_dir}" if args.record else ""))
    return exit_status(session, interrupted)
