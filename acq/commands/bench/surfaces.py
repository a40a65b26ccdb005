"""Speed of several surfaces per pixel: ``--reflectors 2`` and ``auto`` beside ``--reflectors 1``
(uos), at 50 detections per pixel (two surfaces of 20, SBR 4), the model given (window 4000 units
of 8 ps, 5-unit bins, Gaussian pulse RMS 40 units), warm, one thread, best of ``--rounds``.

Run as ``spdepth bench surfaces``. Times the whole ``recon.estimate.reconstruct`` call (binning,
kernel, maps), so the figures are what a user gets per thread. ``--before REV``: the same command
of another revision (a git revision or a folder holding spdepth) and of this checkout, in turn in
new processes ``--rounds`` times, with the ratios (``acq.commands.bench.before``).
"""

from __future__ import annotations

import argparse
import time

# numpy, numba and the estimators are imported where used: ``spdepth bench surfaces --help``
# loads none of them

UNIT_S = 8e-12
RMS_U = 40.0


def scene(n_pix: int, seed: int) -> PhotonStore:
    import numpy as np

    from spdepth.recon.photons import PhotonStore

    rng = np.random.default_rng(seed)
    lists = []
    for _ in range(n_pix):
        c = np.sort(rng.uniform(300, 3700, 2))
        x = np.concatenate([c[0] + RMS_U * rng.standard_normal(20), c[1] + RMS_U * rng.standard_normal(20),
                            rng.uniform(0, 4000, 10)])
        lists.append(np.floor(x))
    side = int(np.sqrt(n_pix))
    return PhotonStore.from_lists(lists[:side * side], (side, side), UNIT_S)


def bench(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="spdepth bench surfaces", description=__doc__.split("\n\n")[0])
    parser.add_argument("--pixels", type=int, default=40_000)
    parser.add_argument("--rounds", type=int, default=3, help="timed runs (best kept); with --before, runs of each side")
    parser.add_argument("--before", metavar="REV", help="also run this command of another revision, in turn")
    args = parser.parse_args(argv)
    if args.before:
        from spdepth.acq.commands.bench.before import side_by_side, table_rows

        inner = ["--pixels", str(args.pixels), "--rounds", "1"]
        side_by_side("spdepth.acq.commands.bench.surfaces", inner, args.before, args.rounds,
                     table_rows(["1", "2", "auto"], [0], pattern=r"^--reflectors\s+(\S+):"), ["pixels/s"])
        return 0
    import numba
    import numpy as np

    from spdepth.recon.estimate import reconstruct
    from spdepth.recon.model import Binning, ReconSettings

    store = scene(args.pixels, 0)
    b = Binning(UNIT_S, 0, 4000, 5)
    numba.set_num_threads(1)
    print(f"{store.n_pixels} pixels, {store.n_photons / store.n_pixels:.0f} detections per pixel, 1 thread, warm")
    for refl in (1, 2, "auto"):
        settings = ReconSettings(method="uos", binning=b, pulse_rms_s=RMS_U * UNIT_S, reflectors=refl)
        reconstruct(store, settings)        # warm (compiles on the first run)
        best = np.inf
        for _ in range(args.rounds):
            t0 = time.perf_counter()
            maps = reconstruct(store, settings)
            best = min(best, time.perf_counter() - t0)
        n = np.bincount(np.ravel(maps.surfaces), minlength=3)
        print(f"--reflectors {refl!s:>4}: {store.n_pixels / best:10,.0f} pixels/s   "
              f"(pixels with 0/1/2 surfaces: {n[0]}/{n[1]}/{n[2]})")
    return 0


if __name__ == "__main__":
    raise SystemExit(bench(__import__("sys").argv[1:]))
