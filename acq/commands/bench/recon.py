"""Speed of the recon estimators, printed side by side with the plain NumPy references
(tests/reference.py) in one run, at the paper's settings (``recon.model.SEED_PAPER``: 801 bins of
40 ps, Gaussian pulse RMS 360 ps, 15 detections per pixel), SBR 10 (``--sbr``).

Run as ``spdepth bench recon`` or ``python -m spdepth.acq.commands.bench.recon``. The references live in the source
checkout's tests/ folder (not installed); without it only the kernels are timed, and it says so.
Ratios are what to read: other work on the machine moves absolute figures, not the side-by-side
comparison made within one run.

``--before REV``: the same command of another revision of this checkout (a git revision, exported
to a temporary folder, or a folder holding another checkout as ``spdepth``) and of this one, run
in turn in new processes ``--rounds`` times, both outputs printed and the best of each side's
kernel and reconstruct figures with their ratio (``acq.commands.bench.before``).

Like for like: kernel and reference get the same pixels (the first ``--ref-pixels``), both are
warm (one untimed run first) and timed best-of, on one thread, and the references' dense matrices
are built once, outside the timed region. Each reference is the same estimator as its kernel,
written densely in NumPy one pixel at a time (REFERENCES says which), and the bench prints the share
of pixels where the two agree.
"""

from __future__ import annotations

import argparse
import importlib.util
import os
import sys
import time
from pathlib import Path
from typing import Callable


def _import_heavy() -> None:
    """Bind numpy, numba, the estimators' kernels and the seed paper's grid (M bins of BIN_UNITS
    raw units of UNIT_S, pulse RMS_S, DETECTIONS per pixel) as this module's globals, which its
    functions use; once, by :func:`bench` after its arguments are parsed and by the functions
    other benchmarks call, so that ``spdepth bench recon --help`` loads none of them."""
    if "np" in globals():
        return
    import numba
    import numpy as np

    from spdepth.acq.live_recon import MIN_BATCH_PIXELS
    from spdepth.recon.estimate import reconstruct
    from spdepth.recon.estimators import lmf_kernels, ml_kernels, uos_kernels
    from spdepth.recon.estimators.ml import ml_tables
    from spdepth.recon.kernels import BLOCK, Photons
    from spdepth.recon.model import FINE_STEPS, SEED_PAPER, Binning, ReconSettings, build_kernel
    from spdepth.recon.photons import PhotonStore
    from spdepth.recon.threadpool import on_slices

    globals().update(
        numba=numba, np=np, MIN_BATCH_PIXELS=MIN_BATCH_PIXELS, reconstruct=reconstruct,
        lmf_kernels=lmf_kernels, ml_kernels=ml_kernels, uos_kernels=uos_kernels, ml_tables=ml_tables,
        Photons=Photons, FINE_STEPS=FINE_STEPS, SEED_PAPER=SEED_PAPER, Binning=Binning,
        ReconSettings=ReconSettings, build_kernel=build_kernel, PhotonStore=PhotonStore,
        on_slices=on_slices, BLOCK=BLOCK, M=SEED_PAPER.n_bins, UNIT_S=SEED_PAPER.time_unit_s,
        BIN_UNITS=float(SEED_PAPER.bin_units), RMS_S=SEED_PAPER.pulse_rms_s,
        DETECTIONS=SEED_PAPER.max_photons)


def _load_reference():
    path = Path(__file__).resolve().parents[3] / "tests" / "reference.py"
    if not path.is_file():
        return None, path
    spec = importlib.util.spec_from_file_location("spdepth_tests_reference", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod, path


def simulate(n_pix: int, seed: int, k: int | None = None, sbr: float = 10.0):
    """Per-pixel bin lists (CSR) of the paper's model: Gaussian return + uniform background; ``k``
    detections per pixel (default the paper's)."""
    _import_heavy()
    k = DETECTIONS if k is None else k
    rng = np.random.default_rng(seed)
    sig_bins = RMS_S / (UNIT_S * BIN_UNITS)
    ns = rng.binomial(k, sbr / (1 + sbr), n_pix)
    centre = rng.uniform(0.2 * M, 0.8 * M, n_pix)
    sig = np.repeat(centre, ns) + sig_bins * rng.standard_normal(ns.sum())
    is_sig = np.arange(k)[None, :] < ns[:, None]
    t = rng.uniform(0, M, (n_pix, k))
    t[is_sig] = sig
    bins = np.clip(np.floor(t), 0, M - 1).astype(np.int64).ravel()
    offsets = np.arange(n_pix + 1, dtype=np.int64) * k
    return bins, offsets


REFERENCES = {
    "lmf": "eq. 11 as one dense product log(S)^T y per pixel (tests/reference.py lmf)",
    "uos": "Algorithm 1 as published: dense A = [S/max, 1], pinv least squares each iteration "
           "(tests/reference.py uos)",
    "ml": "exact Poisson ML, every shift's profile likelihood solved by the kernel's safeguarded "
          "Newton in the signal share, vectorised over all shifts, no pruning; then the same "
          "1/8-bin refinement and parabola (ml_dense here)",
}
"""What each reference is: the same estimator as the kernel, dense, in plain NumPy."""


def _share_profile(y: np.ndarray, cols: np.ndarray, iters: int = 60) -> np.ndarray:
    """For every column j of ``cols`` (unnormalised pulse columns, M x J): max over s in [0, 1] of
    sum_k y_k log((1 - s)/M + s cols[k, j]/C_j), C_j the column sum: the Poisson likelihood with
    amplitude and background profiled out, as the ml kernel's ``mix_ml`` solves it (safeguarded
    Newton), for all columns at once. Returns the log-likelihood per column."""
    m = cols.shape[0]
    nz = np.flatnonzero(y)
    w = y[nz][:, None]
    uni = 1.0 / m
    e = cols[nz, :] / cols.sum(axis=0) - uni
    s = np.full(cols.shape[1], 0.5)
    lo, hi = np.zeros_like(s), np.ones_like(s)
    for _ in range(iters):
        q = e / (uni + s * e)
        f1 = (w * q).sum(axis=0)
        f2 = (w * q * q).sum(axis=0)
        up = f1 > 0
        lo, hi = np.where(up, s, lo), np.where(up, hi, s)
        with np.errstate(divide="ignore", invalid="ignore"):
            sn = np.where(f2 > 0, s + f1 / f2, 0.5 * (lo + hi))
        s = np.where((sn > lo) & (sn < hi), sn, 0.5 * (lo + hi))
    # the end points, where Newton only creeps towards them
    ll = [(w * np.log(uni + t * e)).sum(axis=0) for t in (s, 0.0)]
    with np.errstate(divide="ignore"):
        ll.append((w * np.log(uni + e)).sum(axis=0))
    return np.max(ll, axis=0)


def ml_dense(y: np.ndarray, kern, s_mat: np.ndarray, ref) -> float:
    """Shift (bins) of exact Poisson ML: global search over every integer shift, then the best of
    the 1/8-bin shifts within one bin of it, then a parabola through its neighbours."""
    i = int(np.argmax(_share_profile(y, s_mat)))
    fine = i + np.arange(-FINE_STEPS, FINE_STEPS + 1) / FINE_STEPS
    fine = fine[(fine >= 0) & (fine <= kern.n_bins - 1)]
    ll = _share_profile(y, np.stack([ref.s_at(kern, t) for t in fine], axis=1))
    j = int(np.argmax(ll))
    if not 0 < j < fine.size - 1:
        return float(fine[j])
    # vertex of the parabola through the best fine shift and its neighbours, within half a step
    c2, c1, _ = np.polyfit(np.arange(-1.0, 2.0), ll[j - 1:j + 2], 2)
    return float(fine[j] + (np.clip(-c1 / (2 * c2), -0.5, 0.5) if c2 < 0 else 0.0) / FINE_STEPS)


BIG_PHOTONS = 50_000
BIG_BINS = 4096
BIG_RMS_UNITS = 25.0


def huge_pixel(seed: int) -> np.ndarray:
    """Raw times of one point-measurement pixel: 80% of BIG_PHOTONS in a Gaussian return at unit
    1500.3 (RMS BIG_RMS_UNITS), the rest uniform over [0, BIG_BINS); one raw unit per bin."""
    rng = np.random.default_rng(seed)
    n_sig = int(0.8 * BIG_PHOTONS)
    t = np.concatenate([1500.3 + BIG_RMS_UNITS * rng.standard_normal(n_sig),
                        rng.uniform(0, BIG_BINS, BIG_PHOTONS - n_sig)])
    return t[(t >= 0) & (t < BIG_BINS)]


def _time(fn, min_s: float = 0.3) -> float:
    """Seconds per call (best of repeated runs lasting at least min_s in total)."""
    fn()
    best = np.inf
    total = 0.0
    while total < min_s:
        t0 = time.perf_counter()
        fn()
        dt = time.perf_counter() - t0
        total += dt
        best = min(best, dt)
    return best


def uos_port_rate(n_pix: int = 200) -> float:
    """Pixels/s of the plain port of Algorithm 1 (tests/reference.py ``uos``: dense A, pinv each
    iteration) on :func:`simulate`'s pixels at the paper's settings, warm, best-of, one pixel at a
    time as ``spdepth bench recon``'s reference column; NaN without the source checkout's tests/."""
    _import_heavy()
    ref, _ = _load_reference()
    if ref is None:
        return np.nan
    kern = build_kernel(SEED_PAPER.binning, pulse_rms_s=RMS_S)
    a_mat = np.hstack([ref.dense_s(kern) / kern.gmax, np.ones((M, 1))])
    bins, offsets = simulate(n_pix, seed=1)

    def run():
        for p in range(n_pix):
            ref.uos(ref.histogram(bins[offsets[p]:offsets[p + 1]], M), a_mat)

    return n_pix / _time(run, 0.2)


def live_batch(bins: np.ndarray, offsets: np.ndarray, binning: Binning, methods: list[str]) -> None:
    """A live scan's unit of work: ``reconstruct`` of a batch of MIN_BATCH_PIXELS (the live worker's
    smallest, what it takes while it keeps up), one thread, with the pulse kernel kept from the
    batch before (as ``recon.model.build_kernel`` keeps it) and, beside it, the same call that
    first builds the kernel anew (what each batch cost before it was kept)."""
    n = min(MIN_BATCH_PIXELS, offsets.size - 1)
    times = BIN_UNITS * (bins[:offsets[n]] + 0.5) + binning.window_start
    store = PhotonStore(times, offsets[:n + 1].copy(), (1, n), UNIT_S)
    line = []
    for method in methods:
        if method not in ("lmf", "uos", "ml"):
            continue
        s = ReconSettings(method=method, binning=binning, pulse_rms_s=RMS_S)

        def anew():
            build_kernel.cache_clear()
            reconstruct(store, s)

        kept = _time(lambda: reconstruct(store, s), min_s=0.2)
        line.append(f"{method} {kept * 1e3:.2f} ms ({n / kept:,.0f} px/s; kernel built anew "
                    f"{_time(anew, min_s=0.2) * 1e3:.2f} ms)")
    print(f"a live batch of {n:,} pixels (reconstruct, 1 thr, pulse kernel kept): " + ", ".join(line),
          flush=True)


def kernel_runner(kern) -> Callable[[str, np.ndarray, np.ndarray], np.ndarray]:
    """``run(method, bins, offsets)``: the method's kernel alone on those pixels (the tables built
    here, once), its shift per pixel (bins, NaN: none)."""
    lmf_tabs = lmf_kernels.LmfTables(M, kern.logg, kern.log_concave)
    uos_tabs = uos_kernels.uos_tables(kern.g, kern.off, kern.gmax, kern.colsum, kern.pp, M, SEED_PAPER.delta,
                                      SEED_PAPER.max_iterations)
    ml_tabs = ml_tables(kern, M)

    def run_slice(method, b, o, shift):
        p = o.size - 1
        ph = Photons(b, o)
        if method == "lmf":
            si = np.empty(p, np.int64)
            lmf_kernels.lmf_kernel(ph, lmf_tabs, DETECTIONS, si, np.empty(p), np.empty(p, np.int64))
            shift[:] = np.where(si >= 0, si, np.nan)
        elif method == "uos":
            uos_kernels.uos_kernel(ph, uos_tabs, DETECTIONS, shift, np.empty(p), np.empty(p), np.empty(p, np.int32),
                                   np.empty(p, np.bool_), np.empty(p, np.int64))
        else:
            ml_kernels.ml_kernel(ph, ml_tabs, DETECTIONS, shift, np.empty(p), np.empty(p), np.empty(p),
                                 np.empty(p, np.int64), np.empty(p))

    def run(method, b, o):
        # the kernel's blocks shared among numba's threads, as a reconstruction runs them
        shift = np.full(o.size - 1, np.nan)
        on_slices(lambda a, c: run_slice(method, b[o[a]:o[c]], o[a:c + 1] - o[a], shift[a:c]), o.size - 1, BLOCK)
        return shift

    return run


def reference_runner(kern, ref) -> Callable[[str, np.ndarray, np.ndarray], np.ndarray]:
    """``run(method, bins, offsets)``: the method's plain NumPy reference, one pixel at a time, its
    shift per pixel (bins); the dense matrices built here, outside every timed region."""
    s_mat = ref.dense_s(kern)
    log_s = ref.dense_logs(kern)
    a_mat = np.hstack([s_mat / kern.gmax, np.ones((M, 1))])

    def run(method, b, o):
        out = np.full(o.size - 1, np.nan)
        for p in range(o.size - 1):
            y = ref.histogram(b[o[p]:o[p + 1]], M)
            if method == "lmf":
                out[p] = ref.lmf(y, log_s)
            elif method == "uos":
                a, _ = ref.uos(y, a_mat)
                if np.any(a[:M] > 0):
                    out[p] = np.argmax(a[:M])
            else:
                out[p] = ml_dense(y, kern, s_mat, ref)
        return out

    return run


def thread_rates(fn, n: int, rounds: int) -> dict[int, float]:
    """Pixels/s of ``fn`` (n pixels) on 1 and 2 threads, the two alternated over ``rounds`` and the best
    of each kept, so a burst of other work on the machine does not land on one of them only."""
    rates = {1: 0.0, 2: 0.0}
    for _round in range(rounds):
        for nt in (1, 2):
            if nt > numba.config.NUMBA_NUM_THREADS:
                rates[nt] = np.nan
                continue
            numba.set_num_threads(nt)
            rates[nt] = max(rates[nt], n / _time(fn, 0.15))
    numba.set_num_threads(1)
    return rates


def method_row(method, run_kernel, run_ref, store, bins, offsets, args) -> str:
    """The table's row of one method: kernel 1/2 threads, the whole reconstruct, and beside its
    reference on the same pixels (when the references are there) with the share that agrees."""
    n = offsets.size - 1
    rates = thread_rates(lambda: run_kernel(method, bins, offsets), n, args.rounds)
    settings = ReconSettings(method=method, binning=SEED_PAPER.binning, pulse_rms_s=RMS_S)
    full = n / _time(lambda: reconstruct(store, settings), min_s=0.1)
    ref_rate = same_rate = agree = np.nan
    if run_ref is not None:
        npr = min(n, args.ml_ref_pixels if method == "ml" else args.ref_pixels)
        o = offsets[:npr + 1]
        same_rate = npr / _time(lambda: run_kernel(method, bins, o), 0.1)
        ref_rate = npr / _time(lambda: run_ref(method, bins, o), 1e-9 if method == "ml" else 0.2)
        # agreement: same shift to 1/8 bin (both NaN counts as agreeing)
        a, b = run_kernel(method, bins, o), run_ref(method, bins, o)
        agree = np.mean((np.abs(a - b) <= 1 / 8 + 1e-9) | (np.isnan(a) & np.isnan(b)))
    return (f"{method:<10} {rates[1]:13,.0f} {rates[2]:13,.0f} {rates[2] / rates[1]:8.2f}x "
            f"{full:18,.0f} {same_rate:15,.0f} {ref_rate:11,.1f} {same_rate / ref_rate:10,.0f}x "
            f"{100 * agree:5.0f}%")


def big_pixel_line(methods: list[str]) -> str:
    """One pathological pixel: a point measurement of 50,000 detections over 4096 bins."""
    big_b = Binning(UNIT_S, 0.0, float(BIG_BINS), 1.0)
    big_store = PhotonStore.from_lists([huge_pixel(seed=2)], (1, 1), UNIT_S)
    line = []
    for method in methods:
        s = ReconSettings(method=method, binning=big_b, pulse_rms_s=BIG_RMS_UNITS * UNIT_S)
        line.append(f"{method} {_time(lambda: reconstruct(big_store, s), min_s=0.1):.4f} s")
    return (f"one pixel of {BIG_PHOTONS:,} detections over {BIG_BINS} bins (reconstruct, 1 thr, pulse kernel "
            f"kept): " + ", ".join(line))


def _parse(argv: list[str]) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="spdepth bench recon", description=__doc__.splitlines()[0])
    parser.add_argument("--pixels", type=int, default=100_000, help="pixels per kernel run")
    parser.add_argument("--ref-pixels", type=int, default=200,
                        help="pixels of the side-by-side kernel/reference comparison (lmf, uos)")
    parser.add_argument("--ml-ref-pixels", type=int, default=40, help="the same for ml")
    parser.add_argument("--methods", default="lmf,uos,ml", help="kernels to time (of lmf, uos, ml)")
    parser.add_argument("--rounds", type=int, default=3,
                        help="alternating 1/2-thread rounds (best kept); with --before, runs of each side")
    parser.add_argument("--sbr", type=float, default=10.0,
                        help="signal-to-background ratio of the simulated pixels (ml's search prunes less "
                             "at low SBR)")
    parser.add_argument("--before", metavar="REV",
                        help="also run this command of another revision (git revision or a folder holding "
                             "spdepth), in turn with this checkout's, and print the ratios")
    args = parser.parse_args(argv)
    if not args.sbr > 0:
        parser.error(f"--sbr must be positive, got {args.sbr}")
    unknown = set(args.methods.split(",")) - set(REFERENCES)
    if unknown:
        parser.error(f"--methods: unknown {', '.join(sorted(unknown))} (of {', '.join(REFERENCES)})")
    return args


def bench(argv: list[str]) -> int:
    args = _parse(argv)
    _import_heavy()
    methods = args.methods.split(",")
    if args.before:
        from spdepth.acq.commands.bench.before import side_by_side, table_rows

        inner = [a for i, a in enumerate(argv) if a != "--before" and (i == 0 or argv[i - 1] != "--before")
                 and not a.startswith("--before=")]
        side_by_side("spdepth.acq.commands.bench.recon", inner + ["--rounds", "1"], args.before, args.rounds,
                     table_rows(methods, [0, 3]), ["kernel 1 thr", "reconstruct 1 thr"])
        return 0
    kern = build_kernel(SEED_PAPER.binning, pulse_rms_s=RMS_S)
    bins, offsets = simulate(args.pixels, seed=1, sbr=args.sbr)
    n = args.pixels
    ref, ref_path = _load_reference()
    run_kernel = kernel_runner(kern)
    run_ref = reference_runner(kern, ref) if ref is not None else None
    store = PhotonStore((bins + 0.5) * BIN_UNITS + SEED_PAPER.binning.window_start, offsets, (1, n), UNIT_S)

    print(f"recon estimators, {M} bins of {BIN_UNITS * UNIT_S * 1e12:.0f} ps, pulse RMS {RMS_S * 1e12:.0f} ps, "
          f"{DETECTIONS} detections/pixel, SBR {args.sbr:g}; pixels per second")
    if ref is None:
        print(f"(plain NumPy references not found at {ref_path}: run from a source checkout to compare)")
    else:
        print(f"references ({ref_path}): the same estimator, dense NumPy, one pixel at a time; same "
              "pixels as the kernel, both warm, best-of, 1 thread, matrices built before timing:")
        for method in methods:
            print(f"  {method}: {REFERENCES[method]}")
    print(f"load average before: {' '.join(f'{v:.2f}' for v in os.getloadavg())}")
    print(f"{'method':<10} {'kernel 1 thr':>13} {'kernel 2 thr':>13} {'speed-up':>9} "
          f"{'reconstruct 1 thr':>18} {'kernel, ref px':>15} {'reference':>11} {'kernel/ref':>11} "
          f"{'agree':>6}")
    old_threads = numba.get_num_threads()
    try:
        for method in methods:
            print(method_row(method, run_kernel, run_ref, store, bins, offsets, args), flush=True)
        numba.set_num_threads(1)
        print(big_pixel_line(methods), flush=True)
        live_batch(bins, offsets, SEED_PAPER.binning, methods)
    finally:
        numba.set_num_threads(old_threads)
    return 0

if __name__ == "__main__":
    sys.exit(bench(sys.argv[1:]))
