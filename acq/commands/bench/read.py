"""``spdepth bench read``: how fast a recorded PTU is read, by ``spdepth recon``'s reader beside
``spdepth replay``'s stream, on the same file in one run (alternated, best of N each).

    spdepth bench read [--size 512x512] [--ppp 30] [--repeats 3] [--file PTU] [--mat MAT --time-unit-ps PS]

recon: ``acq.readers.read_photons`` (decode, pixel assignment by markers, every detection grouped
by pixel), as ``acq.api.reconstruct_file`` calls it; replay: a replay session at ``--speed max``
with the cheapest estimator (lmf) live, from the first record read to the last photon assigned.
Both in detections/s. ``--mat``: a first-photon-imaging .mat file instead, read by ``spdepth recon``'s
reader (the NumPy cell walk, :func:`acq.readers.mat.read_cells_fast`) beside scipy's ``loadmat``
(the reader before issue 18, still the fallback), alternated, best of N each, after one untimed read.
"""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
import time
from pathlib import Path


def bench(argv: list[str]) -> int:
    from spdepth.acq.params import parse_size

    p = argparse.ArgumentParser(prog="spdepth bench read", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--size", type=parse_size, default=(512, 512), metavar="WxH",
                   help="pixels of the simulated PTU (default 512x512)")
    p.add_argument("--ppp", type=float, default=30.0, help="mean detections per pixel (default 30)")
    p.add_argument("--repeats", type=int, default=3, help="runs of each, alternated (default 3)")
    p.add_argument("--file", help="read this PTU (with pixel markers) instead of simulating one")
    p.add_argument("--mat", help="time the .mat reader on this file instead (needs --time-unit-ps)")
    p.add_argument("--time-unit-ps", type=float, default=8.0, help="--mat: raw time unit (default 8)")
    a = p.parse_args(argv)
    if a.mat:
        return _bench_mat(Path(a.mat), a.time_unit_ps * 1e-12, a.repeats)

    from spdepth.acq.api import build_session
    from spdepth.acq.cli import main
    from spdepth.acq.readers import read_photons
    from spdepth.acq.requests import ReplayRequest
    from spdepth.recon.model import SEED_PAPER

    tmp = Path(tempfile.mkdtemp(prefix="spdepth-bench-read-"))
    try:
        ptu = Path(a.file) if a.file else tmp / "sim.ptu"
        if not a.file:
            h, w = a.size
            if main(["simulate", "--scene", "bust", "--size", f"{w}x{h}", "--ppp", f"{a.ppp:g}",
                     "--ptu", str(ptu)]) != 0:
                return 1
        target = max(1, int(round(a.ppp)))
        read_photons(ptu)                      # compile / load the kernels outside the timing
        recon_s, replay_s, n_read, n_replay = [], [], 0, 0
        for i in range(a.repeats):
            t0 = time.perf_counter()
            n_read = read_photons(ptu).store.n_photons
            recon_s.append(time.perf_counter() - t0)
            r = build_session(ReplayRequest(recording=str(ptu), target=target, method="lmf",
                                            pulse_rms_s=SEED_PAPER.pulse_rms_s), tmp / f"replay{i}")
            r.run()
            n_replay = r.detections
            replay_s.append(r.stream_s)
        print(f"spdepth bench read: {ptu.name}, {n_read:,} detections in the file")
        print(f"recon  read (decode + assign + group by pixel): {min(recon_s):.3f} s = "
              f"{n_read / min(recon_s) / 1e6:.1f} M detections/s (best of {a.repeats})")
        print(f"replay --speed max (decode + assign + store + live lmf): {min(replay_s):.3f} s = "
              f"{n_replay / min(replay_s) / 1e6:.1f} M detections/s (best of {a.repeats}; it keeps "
              f"the first {target} per pixel)")
        return 0
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def _bench_mat(path: Path, unit_s: float, repeats: int) -> int:
    import numpy as np

    from spdepth.acq.readers.mat import cells_to_store, load_cells, read_cells_fast

    fast_store = read_cells_fast(path, None, unit_s)      # one untimed read (the file in the page cache)
    if fast_store is None:
        print(f"{path}: the fast path declines this file (scipy reads it)")
        return 1
    fast_s, scipy_s = [], []
    for _ in range(repeats):
        t0 = time.perf_counter()
        _, store = read_cells_fast(path, None, unit_s)
        fast_s.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        _, cells = load_cells(path)
        ref = cells_to_store(cells, unit_s)
        scipy_s.append(time.perf_counter() - t0)
    same = np.array_equal(store.times, ref.times) and np.array_equal(store.offsets, ref.offsets)
    print(f"spdepth bench read --mat {path.name}: {store.shape[0]}x{store.shape[1]} cells, "
          f"{store.n_photons:,} detections")
    print(f"NumPy cell walk: {min(fast_s):.3f} s; scipy loadmat + cells_to_store: {min(scipy_s):.3f} s "
          f"({min(scipy_s) / min(fast_s):.1f}x; best of {repeats}, alternated); same store: {same}")
    return 0


if __name__ == "__main__":
    sys.exit(bench(sys.argv[1:]))
