"""``spdepth demo``: an acquisition session on a built-in scene through the real drivers talking to
the simulated instruments (galvo over a pyserial URL, time tagger over pyusb), recorded, then the
final photons reconstructed with each estimator, compared with the truth and the per-pixel oracle
bound, written as a PNG sheet."""

from __future__ import annotations

import argparse
import sys
import tempfile
import time

from spdepth.acq.commands._args import positive_float, positive_int, size_wxh

HELP = "simulate a recorded count-gated scan session of a built-in scene, reconstruct it, write a PNG"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--scene", default="bust", help="built-in scene name (default: bust)")
    parser.add_argument("--size", type=size_wxh, default=(96, 96), metavar="WxH",
                        help="scan size in pixels (default 96x96)")
    parser.add_argument("--photons", type=positive_int, default=15, metavar="N",
                        help="count-gated target: in-window detections per pixel (default 15)")
    parser.add_argument("--sbr", type=positive_float, default=10.0,
                        help="signal-to-background ratio (default 10)")
    parser.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    parser.add_argument("--methods", default="lmf,uos,ml",
                        help="estimators to run, comma-separated (default lmf,uos,ml); the last one "
                             "also runs live during the scan")
    parser.add_argument("--faults", default="", metavar="SPEC",
                        help="inject faults into the simulated instruments, KIND@WHEN items "
                             "(WHEN in virtual seconds '2s' or share of the scan '40%%'), e.g. "
                             "serial-unplug@2s,usb-timeout@50%%,fifo-overflow@70%%; kinds: "
                             "serial-unplug, garbled-reply, missing-reply, slow-reply, servo-fault "
                             "(galvo); usb-timeout, partial-read, fifo-overflow, device-vanish (tagger)")
    parser.add_argument("--record", metavar="DIR",
                        help="keep the session's files (recording.ptu, events.jsonl, maps.npz, "
                             "run.json) in DIR (default: a temporary directory, removed)")
    parser.add_argument("--out", default="spdepth-demo.png", help="PNG sheet to write")
    parser.add_argument("--no-window", action="store_true",
                        help="stay headless (the PNG sheet) even when a display exists; without "
                             "a display (CI, ssh, QT_QPA_PLATFORM=offscreen) it always is")


def run(args: argparse.Namespace) -> int:
    from spdepth.recon.errors import InputError
    from spdepth.recon.model import METHODS

    from spdepth.gui.app import display_available

    methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    unknown = [m for m in methods if m not in METHODS]
    if not methods or unknown:
        raise InputError(f"--methods: unknown {', '.join(unknown) or '(none given)'}; "
                         f"choose from {', '.join(METHODS)}")
    if not args.no_window and display_available():
        return _window(args, methods)
    if args.record:
        from spdepth.acq.commands._session import prepare_out_dir

        return _demo(args, methods, prepare_out_dir(args.record, overwrite=False))
    with tempfile.TemporaryDirectory(prefix="spdepth-demo-") as tmp:
        return _demo(args, methods, tmp)


def _window(args, methods) -> int:
    """With a display: the same simulated scan in the live window (spdepth gui)."""
    from spdepth.gui.app import run_demo_window

    print("spdepth demo: opening the window (--no-window for the headless PNG sheet)",
          file=sys.stderr)
    out = None
    if args.record:
        from spdepth.acq.commands._session import prepare_out_dir

        out = prepare_out_dir(args.record, overwrite=False)
    return run_demo_window(scene=args.scene, size=args.size, target=args.photons, sbr=args.sbr,
                           seed=args.seed, faults=args.faults,
                           method=methods[-1], out_dir=out)


def _demo(args, methods, out_dir) -> int:
    import numpy as np

    from spdepth.acq.commands._session import run_session
    from spdepth.acq.evaluate import evaluate_depth, signal_detections
    from spdepth.acq.instruments import PAPER_BIN_S, PAPER_BINS, open_sim, sim_plan, window_binning
    from spdepth.acq.report import render_maps_png
    from spdepth.acq.session import Session
    from spdepth.recon.estimate import reconstruct
    from spdepth.recon.model import ReconSettings

    h, w = args.size
    with open_sim(args.scene, (h, w), ppp=float(args.photons), sbr=args.sbr, seed=args.seed,
                  faults=args.faults) as inst:
        scene = inst.scene
        plan = sim_plan(inst, (h, w), target=args.photons)
        # The tagger records the seed paper's window (801 bins of 40 ps), so --sbr is the ratio
        # among the detections the estimators see.
        binning = window_binning(inst.tagger.resolution_s)
        live = ReconSettings(method=methods[-1], binning=binning, pulse_rms_s=scene.pulse_rms_s,
                             max_photons=args.photons)
        session = Session(plan, live, galvo=inst.galvo, tagger=inst.tagger, out_dir=out_dir,
                          sync_period_s=inst.sync_period_s, info=inst.info)
        run_session(session, "demo")
        galvo_reconnects = inst.galvo.reconnects
        scan_s = inst.rig.now_s
    snap = session.snapshot()
    store = session.store
    if session.error is not None:
        print(f"session {session.state.value}: {session.error}", file=sys.stderr)
    print(f"scanned {args.scene} {w}x{h} through the drivers: {snap.detections} detections in "
          f"{snap.passes} pass{'es' if snap.passes != 1 else ''}, {scan_s:.2f} s of scan time in {snap.elapsed_s:.2f} s "
          f"({snap.detections_per_s / 1e3:,.0f} k detections/s, live {methods[-1]} lagged at most "
          f"{session.recon.max_lag} pixels)")
    if args.faults:
        print(f"faults injected: {args.faults}; galvo reconnects: {galvo_reconnects}; lost spans "
              f"in the tag stream: {len(session.lost)}, re-acquired in later passes")
        for f in session.faults:
            print(f"  {f['kind']}: {f['what']} -> {f['action']}")
    flagged = session.flagged_pixels()
    if flagged.size:
        reasons = session.run_record()["flag_reasons"]
        print(f"{flagged.size} pixels flagged short of {args.photons} detections ({reasons}); "
              "they keep what they have")

    truth = scene.truth()
    true_depth = np.asarray(truth["depth_m"], dtype=np.float64)
    if true_depth.ndim == 3:
        true_depth = true_depth[0]
    photons = store.photons()
    k_signal = signal_detections(truth, store.count.reshape(h, w),
                                 window_s=PAPER_BINS * PAPER_BIN_S)
    results = {}
    print(f"{'method':<8}{'MAE (cm)':>10}{'x oracle':>10}{'missed':>8}{'recon (s)':>11}{'pixels/s':>12}")
    oracle_cm = None
    for method in methods:
        settings = ReconSettings(method=method, binning=binning, pulse_rms_s=scene.pulse_rms_s,
                                 max_photons=args.photons)
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
    if methods[-1] in results:
        live_maps = session.maps()
        same = np.array_equal(live_maps.tof_s, results[methods[-1]][0].tof_s, equal_nan=True)
        print(f"live {methods[-1]} maps {'equal' if same else 'DIFFER FROM'} the batch "
              f"reconstruction of the final store")

    sheet = argparse.Namespace(truth_m=true_depth)
    panels = [("truth_m", "true depth", "m", "turbo", "percentile")]
    for method, (maps, mae_cm) in results.items():
        setattr(sheet, f"{method}_m", maps.depth_m)
        panels.append((f"{method}_m", f"{method}, MAE {mae_cm:.1f} cm", "m", "turbo", "percentile"))
    best = results.get("ml") or next(iter(results.values()))
    sheet.background = best[0].background
    panels.append(("background", "background", "detections per bin", "magma", "percentile"))
    render_maps_png(args.out, sheet, panels=panels,
                    title=f"{args.scene} {w}x{h}, {args.photons} detections per pixel, SBR {args.sbr:g}")
    print(f"wrote {args.out}" + (f"; session files in {out_dir}" if args.record else ""))
    return 0 if session.state.value == "done" else 1
