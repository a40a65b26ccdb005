"""``spdepth bench read``: how fast a recorded PTU is read, by ``spdepth recon``'s reader beside
``spdepth replay``'s stream, on the same file in one run (alternated, best of N each).

    spdepth bench read [--size 512x512] [--ppp 30] [--repeats 3] [--file PTU]

recon: ``acq.readers.read_photons`` (decode, pixel assignment by markers, every detection grouped
by pixel), as ``acq.api.reconstruct_file`` calls it; replay: a replay session at ``--speed max``
with the cheapest estimator (lmf) live, from the first record read to the last photon assigned.
Both in detections/s.
"""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
import time
from pathlib import Path


def bench(argv: list[str]) -> int:
    p = argparse.ArgumentParser(prog="spdepth bench read", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--size", default="512x512", help="WxH of the simulated PTU (default 512x512)")
    p.add_argument("--ppp", type=float, default=30.0, help="mean detections per pixel (default 30)")
    p.add_argument("--repeats", type=int, default=3, help="runs of each, alternated (default 3)")
    p.add_argument("--file", help="read this PTU (with pixel markers) instead of simulating one")
    a = p.parse_args(argv)

    from spdepth.acq.api import build_session
    from spdepth.acq.cli import main
    from spdepth.acq.readers import read_photons
    from spdepth.acq.requests import ReplayRequest
    from spdepth.recon.model import SEED_PAPER

    tmp = Path(tempfile.mkdtemp(prefix="spdepth-bench-read-"))
    try:
        ptu = Path(a.file) if a.file else tmp / "sim.ptu"
        if not a.file:
            w, h = (int(v) for v in a.size.lower().split("x"))
            if main(["simulate", "--scene", "bust", "--size", f"{w}x{h}", "--ppp", f"{a.ppp:g}",
                     "--out", str(ptu)]) != 0:
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


if __name__ == "__main__":
    sys.exit(bench(sys.argv[1:]))
