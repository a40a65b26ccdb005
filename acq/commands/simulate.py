"""``spdepth simulate``: scan a simulated scene and write what the tagger would have recorded as
a PicoQuant T3 image PTU file, with the truth beside it (FILE.truth.npz)."""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from spdepth.acq.commands._args import non_negative_float, positive_float
from spdepth.acq.params import add_options

HELP = "simulate a scan of a built-in or depth-image scene; write a T3 image PTU and its truth"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    # --scene, --size, --ppp, --sbr, --seed, --ptu: the declared options (acq.params), as in
    # spdepth scan --sim; the rest are the simulator's physics, this command's own
    add_options(parser, "simulate")
    parser.add_argument("--dwell-us", type=positive_float, default=1000.0,
                        help="pixel dwell in microseconds the ppp refers to (default 1000)")
    parser.add_argument("--effects", default="",
                        help="comma list of effects to simulate: jitter, dead_time, afterpulsing "
                             "(dead_time is added by itself when detections per pulse are not small)")
    parser.add_argument("--jitter-ps", type=non_negative_float, default=50.0,
                        help="timing jitter RMS in ps, with --effects jitter (default 50)")
    parser.add_argument("--dead-time-ns", type=non_negative_float, default=50.0,
                        help="detector dead time in ns, with --effects dead_time (default 50)")
    parser.add_argument("--afterpulse-prob", type=non_negative_float, default=0.01,
                        help="afterpulse probability, with --effects afterpulsing (default 0.01)")
    parser.add_argument("--dark-rate-hz", type=non_negative_float, default=0.0,
                        help="dark-count rate in Hz, part of the background (default 0)")
    parser.add_argument("--pulse-rms-ps", type=non_negative_float, default=360.0,
                        help="Gaussian laser pulse RMS in ps (default 360)")
    parser.add_argument("--resolution-ps", type=positive_float, default=8.0,
                        help="tagger bin width in ps (default 8)")
    parser.add_argument("--period-ns", type=positive_float, default=100.0,
                        help="laser repetition period in ns (default 100 = 10 MHz)")


def run(args: argparse.Namespace) -> int:
    import numpy as np

    from spdepth.acq.ptu import MARKER_INPUT, write_ptu
    from spdepth.acq.report import ProgressBar
    from spdepth.drivers.sim import PhotonWorld, load_scene
    from spdepth.recon.errors import InputError

    out = Path(args.ptu)
    if out.suffix.lower() != ".ptu":
        raise InputError(f"--ptu {out}: the file name must end in .ptu")
    from spdepth.acq.outputs import refuse_existing

    # before any work: writable, and an existing PTU (or its truth) kept unless --overwrite
    refuse_existing([("--ptu", out), ("--ptu", out.with_name(out.stem + ".truth.npz"))],
                    overwrite=args.overwrite)
    effects = tuple(e for e in args.effects.split(",") if e)
    scene = load_scene(args.scene, args.size, ppp=args.ppp if args.ppp is not None else 15.0, sbr=args.sbr, effects=effects,
                       dwell_s=args.dwell_us * 1e-6, jitter_rms_s=args.jitter_ps * 1e-12,
                       dead_time_s=args.dead_time_ns * 1e-9, afterpulse_prob=args.afterpulse_prob,
                       dark_rate_hz=args.dark_rate_hz, pulse_rms_s=args.pulse_rms_ps * 1e-12,
                       resolution_s=args.resolution_ps * 1e-12, sync_period_s=args.period_ns * 1e-9)
    s = scene.settings
    if s.range_bins > 32768:
        raise InputError(f"{s.range_bins} tagger bins per period do not fit T3 records "
                         "(max 32768): raise --resolution-ps or lower --period-ns")
    h, w = scene.shape
    t0 = time.monotonic()
    world = PhotonWorld(scene, seed=args.seed or 0)
    with ProgressBar("simulate", h * w, unit="px") as bar:
        events = world.raster(progress=bar if bar.enabled else None)
    n_photons = int(np.count_nonzero(events["kind"] == 0))
    truth = scene.truth()
    settings = dict(truth["settings"], seed=args.seed or 0, n_photons=n_photons,
                    pixel_order="row-major, left to right, fixed dwell",
                    ptu_markers=", ".join(f"{m.name.lower()}={n}" for m, n in MARKER_INPUT.items())
                    + " (frame at the start of the frame; one marker kind per record)")
    n_rec = write_ptu(out, events, (h, w), s.sync_period_s, s.resolution_s, s.dwell_s, s.range_bins,
                      comment=f"spdepth simulate: scene {s.name}, {w}x{h}, ppp {s.ppp}, "
                              f"sbr {s.sbr}, seed {args.seed or 0}")
    truth_path = out.with_name(out.stem + ".truth.npz")
    np.savez_compressed(truth_path, depth_m=truth["depth_m"], tof_s=truth["tof_s"],
                        reflectivity=truth["reflectivity"], occupancy=truth["occupancy"],
                        signal=truth["signal"], background=truth["background"],
                        settings=np.array(json.dumps(settings)))
    print(f"simulate: {n_photons} detections, {n_rec} records -> {out}; truth -> {truth_path} "
          f"({time.monotonic() - t0:.1f} s)", file=sys.stderr)
    return 0
