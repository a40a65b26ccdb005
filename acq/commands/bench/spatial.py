"""``spdepth bench spatial``: the spatial estimator's speed on a whole frame, beside pixelwise ml.

A 256 x 256 piecewise-smooth frame (a tilted plane with a 30 cm step) is simulated with NumPy as a
count-gated scan (N in-window detections per pixel, the seed paper's 801 bins of 40 ps, 360 ps
pulse: ``recon.model.SEED_PAPER``, its window moved to start at 0), then reconstructed warm (an untimed first run compiles), best of ``--repeats`` runs of
``recon.estimate.reconstruct`` in CPU time of this process with one numba thread, so the figure is
per core and the neighbours on a shared machine do not inflate it.
"""

from __future__ import annotations

import math
import time

# numpy, numba and the estimators are imported where used (the seed paper's grid with them):
# ``spdepth bench spatial --help`` loads none of them


def simulate(side: int, n: int, sbr: float, seed: int = 0):
    """(store, true tof in s) of a side x side count-gated frame, N detections per pixel, on the
    seed paper's grid."""
    import numpy as np

    from spdepth.recon.maps import C_M_PER_S
    from spdepth.recon.model import SEED_PAPER
    from spdepth.recon.photons import PhotonStore

    UNIT_S, BIN_UNITS = SEED_PAPER.time_unit_s, SEED_PAPER.bin_units
    N_BINS, RMS_UNITS = SEED_PAPER.n_bins, SEED_PAPER.pulse_rms_units
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:side, 0:side]
    cm = 0.02 / C_M_PER_S / UNIT_S
    tof = 1500 + (0.2 * xx + 0.1 * yy + np.where(xx > side // 2, 30.0, 0.0)) * cm
    npx = side * side
    ns = rng.binomial(n, sbr / (1 + sbr), npx)
    sig = np.arange(n)[None, :] < ns[:, None]
    t = np.where(sig, tof.ravel()[:, None] + RMS_UNITS * rng.standard_normal((npx, n)),
                 rng.uniform(0, N_BINS * BIN_UNITS, (npx, n)))
    t = np.clip(t, 0, N_BINS * BIN_UNITS - 1)
    return PhotonStore(t.ravel(), np.arange(npx + 1) * n, (side, side), UNIT_S), tof * UNIT_S


def bench(argv: list[str]) -> int:
    from spdepth.acq.commands.bench import parser as bench_parser
    from spdepth.acq.params import add_bench_options

    parser = bench_parser("spatial", __doc__)
    add_bench_options(parser, "spatial")
    args = parser.parse_args(argv)
    import numba
    import numpy as np

    from spdepth.recon import estimators
    from spdepth.recon.estimate import reconstruct
    from spdepth.recon.model import SEED_PAPER, Binning, ReconSettings

    UNIT_S, BIN_UNITS = SEED_PAPER.time_unit_s, SEED_PAPER.bin_units
    N_BINS, RMS_UNITS = SEED_PAPER.n_bins, SEED_PAPER.pulse_rms_units
    try:
        counts = [int(v) for v in args.detections.split(",")]
    except ValueError:
        counts = []
    if not counts or min(counts) < 1:
        parser.error(f"--detections must be whole numbers >= 1, comma-separated, got {args.detections!r}")
    unknown = [m for m in args.methods.split(",") if m not in estimators.names()]
    if unknown:
        parser.error(f"--methods: unknown {', '.join(unknown)}; choose from {', '.join(estimators.names())}")
    binning = Binning(UNIT_S, 0, N_BINS * BIN_UNITS, BIN_UNITS)
    old = numba.get_num_threads()
    numba.set_num_threads(1)
    print(f"{args.side}x{args.side} frame, SBR {args.sbr:g}, warm, 1 numba thread, best of "
          f"{args.repeats} in process CPU time")
    print(f"{'method':<8} {'N':>3} {'CPU s':>7} {'pixels/s':>11} {'MAE ps':>7}")
    try:
        for n in counts:
            store, tof = simulate(args.side, n, args.sbr)
            for method in args.methods.split(","):
                settings = ReconSettings(method=method, binning=binning, pulse_rms_s=RMS_UNITS * UNIT_S)
                maps = reconstruct(store, settings)
                best = math.inf
                for _ in range(args.repeats):
                    t0 = time.process_time()
                    reconstruct(store, settings)
                    best = min(best, time.process_time() - t0)
                mae = 1e12 * float(np.nanmean(np.abs(maps.tof_s - tof)))
                print(f"{method:<8} {n:>3} {best:7.3f} {store.n_pixels / best:11,.0f} {mae:7.1f}")
    finally:
        numba.set_num_threads(old)
    return 0
