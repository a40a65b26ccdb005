"""``spdepth bench halves FILE [recon options]``: do a reconstruction's error bars hold? Every count of
a histogram cube goes to one of two halves at random (``recon.counts.CountStore.split``: two
independent measurements of the same scene with half the light each); both halves are
reconstructed as ``spdepth recon`` would (the same options), and their depths compared where both
report one: the share within 3 combined sigma (sqrt(s1^2 + s2^2)) should be near 99.7% for honest
Gaussian error bars, and at least 95%; within 1 combined sigma near 68%.
"""

from __future__ import annotations

import sys
import tempfile
import time
from pathlib import Path


def dense(counts, n_bins: int) -> np.ndarray:
    """The H x W x n_bins cube of a store of whole counts."""
    import numpy as np

    cube = np.zeros((counts.n_pixels, n_bins), np.uint16)
    cube[counts.pixel_index(), counts.times.astype(np.int64)] = counts.counts.astype(np.uint16)
    return cube.reshape(*counts.shape, n_bins)


def compare(a, b, k: float = 3.0) -> dict:
    """Agreement of two depth maps within k combined sigma, where both have a depth."""
    import numpy as np

    both = np.isfinite(a.depth_m) & np.isfinite(b.depth_m)
    sa = a.uncertainty_s * 299792458.0 / 2
    sb = b.uncertainty_s * 299792458.0 / 2
    comb = np.sqrt(sa ** 2 + sb ** 2)
    diff = np.abs(a.depth_m - b.depth_m)
    within = both & (diff <= k * comb)
    within_1 = both & (diff <= comb)
    return {"pixels": int(a.depth_m.size), "both": int(both.sum()), "within": int(within.sum()),
            "share": float(within.sum() / max(1, both.sum())),
            "share_1_sigma": float(within_1.sum() / max(1, both.sum())),
            "median_sigma_cm": float(100 * np.median(comb[both])) if both.any() else float("nan"),
            "median_diff_cm": float(100 * np.median(diff[both])) if both.any() else float("nan")}


def bench(argv: list[str]) -> int:
    from spdepth.acq.commands import recon as recon_cmd
    from spdepth.acq.commands.bench import parser as bench_parser

    # the bench's own parser fills the recon options' method list into their help (acq.params.expand)
    parser = bench_parser("halves", __doc__.splitlines()[0])
    recon_cmd.add_arguments(parser)
    parser.add_argument("--seed", type=int, default=0, help="seed of the split (default 0)")
    args = parser.parse_args(argv)
    # after the parse: --help loads none of numpy, numba or the estimators
    import numpy as np

    from spdepth.acq.api import reconstruct_file
    from spdepth.acq.readers import read_photons
    from spdepth.recon.counts import CountStore

    path = args.file[0]
    t0 = time.perf_counter()
    asked = recon_cmd.request_from_args(args, path)
    read = read_photons(path, time_unit_s=asked.time_unit_s, mat_var=asked.mat_var)
    counts = read.counts if read.counts is not None else CountStore.from_photons(read.store)
    if read.counts is None:
        raise SystemExit("spdepth bench halves: give a histogram cube")
    n_bins = int(read.meta["n_bins"])
    halves = counts.split(args.seed)
    maps = []
    with tempfile.TemporaryDirectory(prefix="spdepth-halves-") as tmp:
        for i, half in enumerate(halves):
            f = Path(tmp) / f"half{i}.npy"
            np.save(f, dense(half, n_bins))
            req = recon_cmd.request_from_args(args, str(f))
            maps.append(reconstruct_file(req).maps)
    r = compare(*maps)
    each = " / ".join(f"{100 * np.isfinite(m.depth_m).mean():.1f}%" for m in maps)
    print(f"{path}: halves of {counts.n_detections:.0f} counts (seed {args.seed}), {args.method or 'default'} "
          f"method; a depth on {each} of each half's pixels, {r['both']} of {r['pixels']} pixels "
          f"({100 * r['both'] / r['pixels']:.1f}%) with a depth in both halves; within 3 combined "
          f"sigma: {r['within']} = {100 * r['share']:.1f}%, within 1: {100 * r['share_1_sigma']:.1f}% (median combined sigma {r['median_sigma_cm']:.2f} cm, "
          f"median difference {r['median_diff_cm']:.2f} cm); {time.perf_counter() - t0:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(bench(sys.argv[1:]))
