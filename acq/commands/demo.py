"""``spdepth demo``: a count-gated scan of a built-in scene through the real drivers talking to
the simulated instruments (galvo over a pyserial URL, time tagger over pyusb), reconstructed with
each estimator, compared with the truth and the oracle bound, written as a PNG sheet."""

from __future__ import annotations

import argparse
import sys
import time

from acq.commands._args import positive_int, size_wxh

HELP = "simulate a count-gated scan of a built-in scene, reconstruct it, write a PNG of the maps"

C_M_PER_S = 299_792_458.0


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--scene", default="bust", help="built-in scene name (default: bust)")
    parser.add_argument("--size", type=size_wxh, default=(96, 96), metavar="WxH",
                        help="scan size in pixels (default 96x96)")
    parser.add_argument("--photons", type=positive_int, default=15, metavar="N",
                        help="count-gated target: in-window detections per pixel (default 15)")
    parser.add_argument("--sbr", type=float, default=10.0, help="signal-to-background ratio (default 10)")
    parser.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    parser.add_argument("--methods", default="lmf,uos,ml",
                        help="estimators to run, comma-separated (default lmf,uos,ml)")
    parser.add_argument("--faults", default="", metavar="SPEC",
                        help="inject faults into the simulated instruments, KIND@WHEN items "
                             "(WHEN in virtual seconds '2s' or share of the scan '40%%'), e.g. "
                             "serial-unplug@2s,usb-timeout@50%%,fifo-overflow@70%%; kinds: "
                             "serial-unplug, garbled-reply, missing-reply, slow-reply, servo-fault "
                             "(galvo); usb-timeout, partial-read, fifo-overflow, device-vanish (tagger)")
    parser.add_argument("--out", default="spdepth-demo.png", help="PNG sheet to write")


def run(args: argparse.Namespace) -> int:
    import numpy as np

    from acq.report import ProgressBar, render_maps_png
    from acq.scan import ScanPlan, run_scan
    from drivers.galvo import Galvo
    from drivers.sim import PhotonWorld, galvo_fw, load_scene
    from drivers.sim.faults import GALVO_FAULTS, TAGGER_FAULTS, parse_faults
    from drivers.sim.rig import SimRig
    from drivers.sim.tagger_usb import SimTaggerBackend
    from drivers.tagger import Tagger
    from recon.estimate import reconstruct
    from recon.model import Binning, ReconSettings

    methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    h, w = args.size
    # The tagger records the seed paper's window: 801 bins of 40 ps (32 ns) after each sync,
    # so --sbr is the ratio among the detections the estimators see.
    n_bins, bin_s = 801, 40e-12
    scene = load_scene(args.scene, (h, w), ppp=float(args.photons), sbr=args.sbr,
                       tagger_range_s=n_bins * bin_s)
    rig = SimRig(PhotonWorld(scene, seed=args.seed))
    x0, y0 = rig.fov.centre_deg(0, 0, (h, w))
    x1, y1 = rig.fov.centre_deg(h - 1, w - 1, (h, w))
    # The galvo counts every detector pulse; the dwell limit stops dark pixels from holding the scan.
    plan = ScanPlan(w, h, x0, x1, y0, y1, n_target=args.photons, dwell_s=20 * scene.dwell_s)

    faults = parse_faults(args.faults)
    galvo_faults = [f for f in faults if f.kind in GALVO_FAULTS]
    tagger_faults = [f for f in faults if f.kind in TAGGER_FAULTS]
    galvo_fw.register_device("demo-galvo", galvo_fw.GalvoFirmware(rig, faults=galvo_faults))
    bar = ProgressBar("scan", stream=sys.stderr)
    got = [0]

    def on_chunk(pixel, dtime):
        got[0] += pixel.size
        bar(min(got[0], h * w * args.photons), h * w * args.photons)

    try:
        backend = SimTaggerBackend(rig, faults=tagger_faults, scan_pixels=h * w)
        with Galvo.open("galvosim://demo-galvo") as galvo, \
                Tagger.open("usb:1209:7a64", backend=backend) as tagger:
            result = run_scan(galvo, tagger, plan, on_chunk=on_chunk)
            galvo_reconnects = galvo.reconnects
    finally:
        bar.close()
        galvo_fw.unregister("demo-galvo")
    store = result.store
    print(f"scanned {args.scene} {w}x{h} through the drivers: {store.n_photons} detections, "
          f"{result.events} events, {rig.now_s:.2f} s of scan time in {result.wall_s:.2f} s"
          + (f", {result.short_pixels.size} pixels short" if result.short_pixels.size else ""))
    if faults:
        print(f"faults injected: {', '.join(str(f) for f in faults)}; galvo reconnects: "
              f"{galvo_reconnects}; lost spans in the tag stream: {len(result.lost)}"
              + "".join(f"\n  lost {span.records_lost or 'unknown'} records from sync {span.sync}, "
                        f"pixel {divmod(span.pixel, w) if span.pixel >= 0 else 'between pixels'}"
                        for span in result.lost))
    if result.short_pixels.size:
        print(f"{result.short_pixels.size} pixels are short of what the galvo counted (lost data): "
              "they show as holes in the maps, to be re-acquired")
        store = store.without_pixels(result.short_pixels)

    res_s = store.time_unit_s
    bin_units = max(1, int(round(bin_s / res_s)))
    binning = Binning(time_unit_s=res_s, window_start=0, window_stop=n_bins * bin_units,
                      bin_width=bin_units)
    true_depth = np.asarray(scene.truth()["depth_m"], dtype=np.float64)
    if true_depth.ndim == 3:
        true_depth = true_depth[0]
    valid = np.isfinite(true_depth)
    # Oracle: knows which detections are signal and averages them (DESIGN.md section 3); here its
    # analytic error for the image-mean SBR, so pixels brighter than the mean can beat it.
    k_signal = args.photons * args.sbr / (1 + args.sbr)
    oracle_cm = 100 * C_M_PER_S / 2 * scene.pulse_rms_s * np.sqrt(2 / np.pi) / np.sqrt(k_signal)
    results = {}
    print(f"{'method':<8}{'MAE (cm)':>10}{'x oracle':>10}{'recon (s)':>11}{'pixels/s':>12}")
    print(f"{'oracle':<8}{oracle_cm:>10.2f}{1.0:>10.2f}   (analytic, at the image-mean SBR)")
    for method in methods:
        settings = ReconSettings(method=method, binning=binning, pulse_rms_s=scene.pulse_rms_s,
                                 max_photons=args.photons)
        # Time the reconstruction, not numba's one-off compilation (cached after the first run).
        t1 = time.perf_counter()
        reconstruct(_first_pixel(store), settings)
        if time.perf_counter() - t1 > 1.0:
            print(f"  ({method}: numba kernels compiled in {time.perf_counter() - t1:.0f} s, "
                  "cached for later runs)", file=sys.stderr)
        t1 = time.perf_counter()
        maps = reconstruct(store, settings)
        dt = time.perf_counter() - t1
        err = np.abs(maps.depth_m - true_depth)
        ok_px = valid & np.isfinite(err)
        mae_cm = 100 * float(np.mean(err[ok_px])) if ok_px.any() else float("nan")
        results[method] = (maps, mae_cm)
        print(f"{method:<8}{mae_cm:>10.2f}{mae_cm / oracle_cm:>10.2f}{dt:>11.3f}{h * w / dt:>12,.0f}")

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
    print(f"wrote {args.out}")
    return 0


def _first_pixel(store):
    """A 1 x 1 store holding the first pixel's photons (enough to compile a method's kernel)."""
    from recon.photons import PhotonStore

    return PhotonStore.from_lists([store.pixel(0, 0)], (1, 1), store.time_unit_s)
