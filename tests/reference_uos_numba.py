"""A plain numba port of Algorithm 1 (the published COSAMP_UOS.m loop, as tests/reference.py's
``uos``): per pixel a dense histogram, the dense proxy A^T v, pinv on the support, T_0, the stop
test; pixels under prange. The yardstick for the speed of ``spdepth recon`` (what a careful
first port would run at), not a reference for its outputs: tests/reference.py is that.

    python tests/reference_uos_numba.py ../shared/data/fpi/mannequin_face_8ppp.mat

prints the whole reconstruct (window, first 15, binning, kernel, maps) against the port on the
same photons, both compiled and warm, best of three, at the seed paper's settings.
"""

from __future__ import annotations

import sys
import time

import numpy as np
from numba import njit, prange

#: the port is timed on every STRIDE-th pixel
STRIDE = 40


@njit(parallel=True, cache=True)
def uos_plain(bins, offsets, a_mat, delta, ite_max, out_shift, out_bg):
    """bins/offsets: CSR bin indices per pixel; a_mat: dense M x (M + 1) matrix [S / max, 1]."""
    m = a_mat.shape[0]
    n = a_mat.shape[1]
    s_t = np.ascontiguousarray(a_mat[:, :n - 1].T)
    for p in prange(offsets.size - 1):
        y = np.zeros(m)
        for q in range(offsets[p], offsets[p + 1]):
            y[bins[q]] += 1.0
        a = np.zeros(n)
        v = y.copy()
        for _ in range(ite_max):
            a_prev = a.copy()
            proxy = s_t @ v
            supp_now = int(np.argmax(proxy))
            supp = [supp_now]
            for j in range(n - 1):
                if a[j] != 0.0 and j != supp_now:
                    supp.append(j)
            supp.sort()
            supp.append(n - 1)
            sub = np.empty((m, len(supp)))
            for c in range(len(supp)):
                sub[:, c] = a_mat[:, supp[c]]
            b0 = np.linalg.pinv(sub) @ y
            best = -np.inf
            prune = -1
            for c in range(len(supp) - 1):
                if b0[c] > best:
                    best = b0[c]
                    prune = supp[c]
            a = np.zeros(n)
            if prune >= 0 and best > 0.0:
                a[prune] = best
            a[n - 1] = max(b0[len(supp) - 1], 0.0)
            diff = np.sum((a_prev - a) ** 2)
            v = y - a_mat @ a
            if diff < delta * max(1.0, np.sum(a ** 2)):
                break
        out_bg[p] = a[n - 1]
        out_shift[p] = np.nan
        for j in range(n - 1):
            if a[j] > 0.0:
                out_shift[p] = j


def main(path: str) -> None:
    sys.path.insert(0, str(__import__("pathlib").Path(__file__).resolve().parent))
    import numba
    import reference as ref

    from spdepth.acq.readers import read_photons
    from spdepth.recon.estimate import reconstruct
    from spdepth.recon.model import Binning, ReconSettings, build_kernel

    store = read_photons(path, time_unit_s=8e-12).store
    b = Binning.from_ps(8, (16000, 48000), 40)
    settings = ReconSettings(method="uos", binning=b, pulse_rms_s=360e-12, max_photons=15)
    kept = store.first_in_window(b.window_start, b.window_stop, 15)
    bins = b.bin_index(kept.times)
    kern = build_kernel(b, pulse_rms_s=360e-12)
    a_mat = np.hstack([ref.dense_s(kern) / kern.gmax, np.ones((b.n_bins, 1))])
    # the port takes minutes on the whole image: time it on every STRIDE-th pixel (same photons)
    sub = np.arange(0, store.n_pixels, STRIDE)
    lists = [bins[kept.offsets[p]:kept.offsets[p + 1]] for p in sub]
    sub_off = np.zeros(sub.size + 1, np.int64)
    np.cumsum([len(x) for x in lists], out=sub_off[1:])
    sub_bins = np.concatenate(lists)
    shift = np.empty(sub.size)
    bg = np.empty(sub.size)
    print(f"{path}: {store.shape[0]} x {store.shape[1]} pixels, {kept.n_photons} photons "
          f"(first 15 in 16-48 ns, 801 bins of 40 ps), {numba.get_num_threads()} threads")
    uos_plain(sub_bins, sub_off[:65], a_mat, 1e-4, 10, shift[:64], bg[:64])      # compile
    reconstruct(store, settings)                                                  # compile
    t0 = time.perf_counter()
    uos_plain(sub_bins, sub_off, a_mat, 1e-4, 10, shift, bg)
    port_px = (time.perf_counter() - t0) / sub.size
    t_rec = []
    for _ in range(3):
        t0 = time.perf_counter()
        maps = reconstruct(store, settings)
        t_rec.append(time.perf_counter() - t0)
    rec_px = min(t_rec) / store.n_pixels
    same = np.mean(np.isclose(maps.tof_s.ravel()[sub], b.shift_to_time_s(shift), equal_nan=True,
                              rtol=0, atol=1e-15))
    print(f"plain numba port of Algorithm 1, binned photons in ({sub.size} pixels): "
          f"{1 / port_px:,.0f} pixels/s ({port_px * store.n_pixels:.0f} s for the image)")
    print(f"reconstruct, raw photons in, maps out (whole image, best of 3): {1 / rec_px:,.0f} pixels/s "
          f"({min(t_rec):.3f} s)")
    print(f"ratio {port_px / rec_px:.0f}x; same tof on {same:.1%} of the compared pixels")


if __name__ == "__main__":
    main(sys.argv[1])
