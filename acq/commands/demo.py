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

from spdepth.acq.params import add_options

HELP = "simulate a recorded count-gated scan session of a built-in scene, reconstruct it, write a PNG"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_options(parser, "demo")


def run(args: argparse.Namespace) -> int:
    from spdepth.acq.api import OutputDir
    from spdepth.acq.commands.scan import request_from_args
    from spdepth.acq.errors import RequestError
    from spdepth.acq.params import method_names, pixelwise_methods
    from spdepth.acq.outputs import check_output_folder, refuse_existing

    request = request_from_args(args, "demo")
    methods = [m.strip() for m in (args.compare or ",".join(pixelwise_methods())).split(",") if m.strip()]
    unknown = [m for m in methods if m not in method_names()]
    if not methods or unknown:
        raise RequestError(f"--compare: unknown {', '.join(unknown) or '(none given)'}; "
                           f"choose from {', '.join(method_names())}")
    png = args.png or "spdepth-demo.png"
    refuse_existing([("--png", png)], overwrite=args.overwrite)
    check_output_folder("--out", args.out)
    if args.out is not None and str(args.out).lower().endswith(".png"):
        raise RequestError(f"--out {args.out}: --out is the run folder; the PNG sheet is --png FILE")
    if not args.no_window:
        from spdepth.gui.app import display_available, platform_problem

        if display_available():
            problem = platform_problem()
            if problem is None:
                return _window(args, request, methods)
            print(f"spdepth demo: {problem}; writing the PNG sheet instead", file=sys.stderr)
    if args.out:
        with OutputDir(args.out, overwrite=args.overwrite) as out:
            return _demo(args, request, methods, out.path, png)
    with tempfile.TemporaryDirectory(prefix="spdepth-demo-") as tmp:
        return _demo(args, request, methods, tmp, png)


def _window(args, request, methods) -> int:
    """With a display: the same simulated scan in the live window (spdepth gui), then, once the
    window is closed, the accuracy table of the headless demo for what it scanned."""
    from spdepth.gui.app import run_demo_window

    print("spdepth demo: opening the window (--no-window for the headless PNG sheet)",
          file=sys.stderr)
    ran = {}
    apart = _compile_comparison_apart(request, methods)

    def started(run) -> None:
        ran.update(session=run.session, scene=run.instruments.scene)

    if args.out:
        from spdepth.acq.api import OutputDir

        with OutputDir(args.out, overwrite=args.overwrite) as out:
            code = run_demo_window(request, out_dir=out.path, on_started=started)
    else:
        code = run_demo_window(request, out_dir=None, on_started=started)
    session = ran.get("session")
    if session is not None and session.ended.is_set() and session.store.count.any():
        _accuracy_table(session, ran["scene"], request, methods, apart)
    return code


def _strongest_surface(maps):
    """(H, W) depth of each pixel's strongest surface (most signal): the one-surface scene's
    return when several surfaces were fitted (``--reflectors``); the maps themselves for one."""
    import numpy as np

    depth = np.asarray(maps.depth_m)
    if depth.ndim == 2:
        return depth
    signal = np.where(np.isfinite(depth), np.nan_to_num(np.asarray(maps.signal), nan=-1.0), -np.inf)
    best = np.argmax(signal, axis=0)
    return np.take_along_axis(depth, best[None], axis=0)[0]


def _nearest_surface(maps, truth_m):
    """(H, W) depth of each pixel's estimated surface nearest ``truth_m`` (one truth surface),
    NaN where that surface is absent (its truth NaN)."""
    import numpy as np

    est = np.asarray(maps.depth_m, dtype=np.float64)
    est = est if est.ndim == 3 else est[None]
    gap = np.abs(est - truth_m[None])
    pick = np.argmin(np.where(np.isfinite(gap), gap, np.inf), axis=0)
    got = np.take_along_axis(est, pick[None], axis=0)[0]
    return np.where(np.isfinite(truth_m), got, np.nan)


def _demo(args, request, methods, out_dir, png) -> int:
    import json

    from spdepth.acq.api import build_session, finish_session, open_instruments
    from spdepth.acq.commands._session import PreparingNotice, exit_status, run_session
    from spdepth.acq.params import DEFAULT_METHOD
    from spdepth.acq.report import render_maps_png
    from spdepth.recon import estimators

    h, w = request.size
    scene_name = request.instruments.scene
    apart = _compile_comparison_apart(request, methods)
    with PreparingNotice("demo") as notice, open_instruments(request) as inst:
        scene = inst.scene
        session = notice.session = build_session(request, out_dir, inst)
        interrupted = run_session(session, "demo")
        galvo_reconnects = inst.galvo.reconnects
        scan_s = inst.rig.now_s
    snap = session.snapshot()
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

    results, true_depth, oracle_cm, same = _accuracy_table(session, scene, request, methods, apart)

    n_surf = true_depth.shape[0]
    sheet = argparse.Namespace()
    panels = []
    for r in range(n_surf):
        name = f", surface {r + 1}" if n_surf > 1 else ""
        setattr(sheet, f"truth_{r}", true_depth[r])
        panels.append((f"truth_{r}", f"true depth{name}", "m", "turbo", "percentile"))
        for method, (maps, per_surface) in results.items():
            got, mae_cm = per_surface[r]
            setattr(sheet, f"{method}_{r}", got)
            panels.append((f"{method}_{r}", f"{method}: MAE {mae_cm:.1f} cm, depth{name}", "m", "turbo",
                           "percentile"))
    # the background panel: the default estimator's, else the first that estimates background, in
    # the one background quantity and unit of every sheet and the window (acq.mapdefs "background")
    from spdepth.acq.mapdefs import MAPS_BY_KEY, map_input_from_maps

    best = results.get(DEFAULT_METHOD) or next(
        (r for m, r in results.items() if estimators.get(m).background), next(iter(results.values())))
    bg = MAPS_BY_KEY["background"]
    sheet.background = bg.extract(map_input_from_maps(best[0]))
    panels.append(("background", bg.title, bg.unit, bg.cmap, "percentile"))
    render_maps_png(png, sheet, panels=panels,
                    title=f"{scene_name} {w}x{h}, {request.target} detections per pixel, "
                          f"SBR {scene.settings.sbr:g}")
    print(f"wrote {png}" + (f"; session files in {out_dir}" if args.out else ""))
    if args.json:
        summary = finish_session(session, None)
        summary.update(out=str(out_dir) if args.out else None, png=str(png),
                       oracle_mae_cm=oracle_cm[0], live_equals_batch=same,
                       compare={m: {"mae_cm": r[1][0][1], "mae_cm_per_surface": [x[1] for x in r[1]]}
                                for m, r in results.items()})
        print(json.dumps(summary))
    return exit_status(session, interrupted)


class _CompiledApart:
    """The first run's compiles begun by :func:`_compile_comparison_apart`: ``wait()`` for all."""

    def __init__(self, child, thread):
        self._child, self._thread = child, thread

    def wait(self) -> None:
        if self._thread is not None:
            self._thread.join()
        if self._child is not None:
            self._child.wait()


def _compile_comparison_apart(request, methods):
    """On a cold numba cache, split the first run's compiles over both cores: the live estimator's
    kernels and the return test's in a second process (``recon.estimate.compile_apart``, which the
    session's warm-up waits for and then loads), and here on a thread the simulator's, the other
    compared methods' and the test's kernels the second process has not claimed, while the scan is
    prepared and runs; a line says so. None when they are all cached."""
    import threading

    from spdepth.recon.estimate import compile_apart, kernels_cached, warm_up
    from spdepth.recon.model import ReconSettings

    def settings(method):
        return ReconSettings(method=method, max_photons=request.target, reflectors=request.reflectors)

    child = compile_apart([settings(request.method)], decide=True)
    others = [m for m in methods if m != request.method and not kernels_cached(settings(m))]
    thread = None
    if others:
        def compile_here() -> None:
            try:
                # the simulator's first: the scan waits for them, the rest only after it (numba
                # compiles one function at a time in a process, whichever thread asks)
                from spdepth.drivers.sim.world import warm_up as warm_sim

                warm_sim()
                for m in others:
                    warm_up(settings(m), decide=False)
                # then the return test's kernels the second process has not claimed yet, from its
                # last (recon.estimate's claims), with the search the compared methods need
                warm_up(settings(others[-1]), estimator=False)
            except Exception:  # noqa: BLE001 - the comparison's own call then says what is wrong
                return

        thread = threading.Thread(target=compile_here, name="compile-compared", daemon=True)
        thread.start()
    if child is None and thread is None:
        return None
    theirs = ", ".join(f"{m}'s" for m in others)
    parts = ([f"{request.method}'s and the return test's kernels in a second process"] if child else []) + (
        [f"the simulator's, {theirs} and the test's last here"] if others else [])
    print(f"spdepth demo: compiling {' and '.join(parts)} while the scan is prepared (first run; later runs "
          f"load them from numba's cache)", file=sys.stderr)
    return _CompiledApart(child, thread)


def _accuracy_table(session, scene, request, methods, apart=None):
    """Reconstruct the session's final photons with each of ``methods`` and print the table
    against the truth and the per-pixel oracle (the headless demo, and the window's once it is
    closed); ``apart``: the process compiling their kernels (:func:`_compile_comparison_apart`),
    waited for first. Returns ({method: (maps, MAE cm, strongest-surface depth)}, the true depth, the
    oracle's MAE in cm, whether the live maps equal the batch ones (None: not compared))."""
    import dataclasses

    import numpy as np

    from spdepth.acq.commands._session import CompileNotice
    from spdepth.acq.evaluate import evaluate_depth, signal_detections
    from spdepth.recon.estimate import reconstruct

    h, w = request.size
    store = session.store
    truth = scene.truth()
    # every surface the scene has, each scored against its own truth (NaN where it is absent: the
    # pane of two-layer covers only the centre); one surface: the strongest estimated one
    true_depth = np.asarray(truth["depth_m"], dtype=np.float64)
    if true_depth.ndim == 2:
        true_depth = true_depth[None]
    occ = np.asarray(truth.get("occupancy", np.ones_like(true_depth)), dtype=np.float64)
    occ = occ if occ.ndim == 3 else occ[None]
    true_depth = np.where(occ > 0, true_depth, np.nan)
    n_surf = true_depth.shape[0]
    photons = store.photons()
    binning = session.live_recon.requested.binning
    counts = store.count.reshape(h, w)
    k_signal = [signal_detections(truth, counts, window_s=binning.window_stop_s, surface=r) for r in range(n_surf)]
    results = {}
    print(f"{'method':<8}" + ("surface " if n_surf > 1 else "")
          + f"{'MAE (cm)':>10}{'x oracle':>10}{'missed':>8}{'recon (s)':>11}{'pixels/s':>12}")
    oracle_cm = [None] * n_surf
    live = session.live_recon.requested
    pulse_rms_s = request.pulse_rms_s or scene.pulse_rms_s
    if apart is not None:
        apart.wait()
    for method in methods:
        # the live estimator's settings (pulse, target) with another method, a surface per layer
        settings = dataclasses.replace(live, method=method, max_photons=request.target,
                                       pulse_rms_s=live.pulse_rms_s or pulse_rms_s,
                                       reflectors=n_surf if n_surf > 1 else live.reflectors)
        with CompileNotice("spdepth demo"):
            reconstruct(store.photons(np.arange(1)), settings)   # compile outside the timing
        t1 = time.perf_counter()
        maps = reconstruct(photons, settings)
        dt = time.perf_counter() - t1
        per_surface = []
        for r in range(n_surf):
            got = _strongest_surface(maps) if n_surf == 1 else _nearest_surface(maps, true_depth[r])
            e = evaluate_depth(got, true_depth[r], k_signal[r], pulse_rms_s)
            if oracle_cm[r] is None:
                oracle_cm[r] = 100 * e.oracle_mae_m
                print(f"{'oracle':<8}" + (f"{r + 1:<8}" if n_surf > 1 else "")
                      + f"{oracle_cm[r]:>10.2f}{1.0:>10.2f}{'':>8}   (per pixel, same pixels)")
            per_surface.append((got, 100 * e.mae_m))
            print(f"{method:<8}" + (f"{r + 1:<8}" if n_surf > 1 else "")
                  + f"{100 * e.mae_m:>10.2f}{e.ratio_to_oracle:>10.2f}"
                  f"{100 * e.miss_share:>7.1f}%{dt:>11.3f}{h * w / dt:>12,.0f}")
        results[method] = (maps, per_surface)
    same = None
    if request.method in results:
        batch = results[request.method][0] if n_surf == 1 else reconstruct(photons, live)
        same = np.array_equal(session.maps().tof_s, batch.tof_s, equal_nan=True)
        print(f"live {request.method} maps {'equal' if same else 'DIFFER FROM'} the batch "
              f"reconstruction of the final store")
    return results, true_depth, oracle_cm, same
