"""``spdepth bench array``: frames per second of the estimators on SPAD-array frames, 64x64 pixels of
1,024 bins at about 20 counts per pixel (simulated: ``drivers.sim.spad_array``), each frame handed to
``recon.estimate.reconstruct`` as counts, pixelwise (lmf, uos, ml) and spatial, one thread and all.

Frames are made before the clock starts; each estimator runs once untimed (kernels load or
compile), then over ``--frames`` frames, wall time per frame (the machine is shared: compare the
rows of one run).
"""

from __future__ import annotations

import argparse
import sys
import time

SIZE = 64
N_BINS = 1024
BIN_S = 80e-12
COUNTS = 20.0
SBR = 1.0
LASER_HZ = 1e6
FRAME_HZ = 30.0


def make_sensor(scene_name: str, shape: tuple[int, int], counts: float = COUNTS, sbr: float = SBR,
                seed: int = 0, **settings):
    """The simulated array (``drivers.sim.spad_array``, 1,024 bins of 80 ps, 1 MHz laser) looking at
    a scene lit for ``counts`` per pixel and frame in range (ideal detector) at ``sbr`` in range."""
    from spdepth.drivers.sim import load_scene
    from spdepth.drivers.sim.spad_array import ArraySettings, SimSpadArray

    s = ArraySettings(**{"n_bins": N_BINS, "bin_s": BIN_S, "frame_rate_hz": FRAME_HZ,
                         "laser_rate_hz": LASER_HZ, **settings})
    n = s.periods_per_frame
    in_range = s.n_bins * s.bin_s * s.laser_rate_hz          # share of the period the bins see
    # a scene's ppp counts background over the whole period; the array sees in_range of it
    bg = counts / (1 + sbr)
    ppp = counts - bg + bg / in_range
    scene = load_scene(scene_name, shape, ppp=ppp, sbr=(counts - bg) / (bg / in_range),
                       dwell_s=n / s.laser_rate_hz, sync_period_s=1 / s.laser_rate_hz)
    return SimSpadArray(scene, s, seed=seed)


def array_frames(n_frames: int, size: int = SIZE, counts: float = COUNTS, sbr: float = SBR, seed: int = 0):
    """(sensor, [CountStore per frame]) of the tilted plane at ``counts`` per pixel and frame
    (in range, ideal detector) and ``sbr`` in range."""
    import numpy as np

    from spdepth.recon.counts import CountStore

    sensor = make_sensor("tilted-plane", (size, size), counts, sbr, seed)
    n = sensor.settings.periods_per_frame
    frames = [CountStore.from_pairs(*sensor.frame_pairs(i), sensor.shape, N_BINS, BIN_S,
                                    periods=np.full(size * size, float(n))) for i in range(n_frames)]
    return sensor, frames


def bench(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="spdepth bench array", description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=30, help="timed frames per row (default 30)")
    parser.add_argument("--methods", default="lmf,uos,ml,spatial")
    args = parser.parse_args(argv)
    # after the parse: --help loads none of numpy, numba or the estimators
    import numba
    import numpy as np

    from spdepth.recon.estimate import reconstruct
    from spdepth.recon.model import Binning, ReconSettings

    t0 = time.perf_counter()
    sensor, frames = array_frames(args.frames)
    made = time.perf_counter() - t0
    per_pixel = np.mean([f.n_detections for f in frames]) / (SIZE * SIZE)
    occupied = np.mean([f.n_occupied for f in frames]) / (SIZE * SIZE)
    binning = Binning.from_window(BIN_S, (0.0, N_BINS * BIN_S), BIN_S)
    rms = sensor.scene.pulse_rms_s
    print(f"{SIZE}x{SIZE} pixels x {N_BINS} bins of {BIN_S * 1e12:g} ps, {per_pixel:.1f} counts per pixel "
          f"({occupied:.1f} occupied bins), pulse {rms * 1e12:.0f} ps RMS given; {args.frames} frames made in "
          f"{made:.1f} s ({made / args.frames * 1e3:.0f} ms a frame, not timed below)")
    all_threads = numba.config.NUMBA_NUM_THREADS
    print(f"{'method':8s} {'threads':>7s} {'frames/s':>9s} {'ms/frame':>9s}")
    for method in args.methods.split(","):
        settings = ReconSettings(method=method, binning=binning, pulse_rms_s=rms)
        for threads in sorted({1, all_threads}):
            numba.set_num_threads(threads)
            reconstruct(frames[0], settings)
            t = time.perf_counter()
            for f in frames:
                reconstruct(f, settings)
            dt = (time.perf_counter() - t) / len(frames)
            print(f"{method:8s} {threads:7d} {1 / dt:9.1f} {dt * 1e3:9.1f}")
    numba.set_num_threads(all_threads)
    return 0


if __name__ == "__main__":
    sys.exit(bench(sys.argv[1:]))
