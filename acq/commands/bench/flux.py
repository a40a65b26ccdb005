"""``spdepth bench flux``: depth bias and signal error against detections per laser pulse, with and
without Coates' pile-up correction (``recon.pileup``), on `spdepth simulate`'s files.

Each level is a fixed-dwell scan of the tilted plane written by ``spdepth simulate`` (its dead time
switches itself on above 0.05 detections per pulse) and reconstructed by ``spdepth recon``'s library
call with ``--pileup off`` and ``--pileup on`` (the periods come from the file's header). Bias is the
mean depth error over the pixels with an estimate; the signal error compares the estimated signal
with the truth's (detections an ideal detector would have made), summed over the same pixels.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

#: detections per pixel at a 100 us dwell of a 10 MHz laser (1,000 periods): 0.01 to 1 per pulse
LEVELS = (10, 30, 100, 300, 600, 900, 1000)
QUICK_LEVELS = (10, 300, 900)
DWELL_US = 100.0
PERIODS = 1000


def flux_rows(levels=LEVELS, size: int = 32, seed: int = 0, method: str = "ml",
              pulse_rms_ps: float = 360.0, sbr: float = 10.0) -> list[dict]:
    """One row per level: detections per pulse, and per correction (off/on) the depth bias (cm),
    MAE (cm), signal error (share) and reconstruction seconds; also what ``auto`` decided."""
    import numpy as np

    from spdepth.acq.api import reconstruct_file
    from spdepth.acq.cli import main
    from spdepth.acq.requests import FileReconRequest

    rows = []
    with tempfile.TemporaryDirectory(prefix="spdepth-flux-") as tmp:
        for ppp in levels:
            ptu = Path(tmp) / f"flux{ppp}.ptu"
            rc = main(["simulate", "--scene", "tilted-plane", "--size", f"{size}x{size}", "--ppp", str(ppp),
                       "--sbr", str(sbr), "--dwell-us", str(DWELL_US), "--seed", str(seed), "--ptu", str(ptu)])
            if rc != 0:
                raise RuntimeError(f"spdepth simulate failed at ppp {ppp}")
            truth = np.load(ptu.with_name(ptu.stem + ".truth.npz"))
            row = {"ppp": ppp, "per_pulse": ppp / PERIODS}
            for mode in ("off", "on", "auto"):
                t0 = time.perf_counter()
                res = reconstruct_file(FileReconRequest(input=str(ptu), method=method,
                                                        pulse_rms_s=pulse_rms_ps * 1e-12, pileup=mode))
                dt = time.perf_counter() - t0
                if mode == "auto":
                    row["auto_applied"] = bool(res.pileup and res.pileup["applied"])
                    continue
                d = res.maps.depth_m - truth["depth_m"]
                ok = np.isfinite(d)
                row[f"bias_cm_{mode}"] = 100 * float(np.mean(d[ok]))
                row[f"mae_cm_{mode}"] = 100 * float(np.mean(np.abs(d[ok])))
                row[f"signal_err_{mode}"] = float(np.sum(res.maps.signal[ok]) / np.sum(truth["signal"][ok]) - 1)
                row[f"recon_s_{mode}"] = dt
                row["detected_per_pulse"] = float(np.mean(res.maps.photons)) / PERIODS
            rows.append(row)
    return rows


def flux_table(rows: list[dict]) -> list[str]:
    """The rows as a Markdown table."""
    out = ["| detections/pulse (ideal) | detected/pulse | depth bias cm: raw | corrected | MAE cm: raw | "
           "corrected | signal error: raw | corrected | auto corrects |",
           "|---:|---:|---:|---:|---:|---:|---:|---:|:---:|"]
    for r in rows:
        out.append(f"| {r['per_pulse']:.2f} | {r['detected_per_pulse']:.3f} | {r['bias_cm_off']:+.2f} | "
                   f"{r['bias_cm_on']:+.2f} | {r['mae_cm_off']:.2f} | {r['mae_cm_on']:.2f} | "
                   f"{100 * r['signal_err_off']:+.1f}% | {100 * r['signal_err_on']:+.1f}% | "
                   f"{'yes' if r['auto_applied'] else 'no'} |")
    return out


def bench(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="spdepth bench flux", description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help=f"levels {QUICK_LEVELS} only")
    parser.add_argument("--size", type=int, default=32, help="image side (default 32)")
    parser.add_argument("--method", default="ml", help="estimator (default ml)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--censored", type=int, metavar="PIXELS", default=0,
                        help="also compare Coates + ml with the censored likelihood on this many "
                             "pixels at 0.9 detections per pulse")
    args = parser.parse_args(argv)
    t0 = time.perf_counter()
    rows = flux_rows(QUICK_LEVELS if args.quick else LEVELS, args.size, args.seed, args.method)
    print(f"tilted-plane {args.size}x{args.size}, SBR 10, {DWELL_US:g} us dwell = {PERIODS} laser periods, "
          f"dead time 50 ns (on by itself above 0.05 per pulse), {args.method}, pulse 360 ps given")
    print("\n".join(flux_table(rows)))
    if args.censored:
        c = censored_rows(900, args.size, args.censored, args.seed)
        print(f"0.9 detections per pulse, the same {c['pixels']} pixels: depth bias / MAE cm, signal error, "
              f"ms per pixel")
        for name in ("coates", "censored"):
            r = c[name]
            print(f"  {'Coates + ml' if name == 'coates' else 'censored likelihood (Nelder-Mead)':34s} "
                  f"{r['bias_cm']:+.2f} / {r['mae_cm']:.2f}  {100 * r['signal_err']:+.1f}%  "
                  f"{1e3 * r['s_per_pixel']:.2f}")
    print(f"{time.perf_counter() - t0:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(bench(sys.argv[1:]))


def censored_ml(hist: np.ndarray, n_periods: float, bin_units: float, unit_s: float, rms_s: float,
                start_bin: float) -> tuple[float, float]:
    """The censored (first-detection) likelihood's estimate for one pixel, by direct search: the
    alternative to Coates' correction the flux bench measures it against. A detector that re-arms at
    each sync sees bin i live in N - D_i periods (D_i the detections before it) and detects there
    with probability 1 - exp(-lambda_i), lambda_i = a G_i(t) + b (Gaussian pulse of ``rms_s``
    integrated over the bin, a signal photons and b background per bin, per period), so
    log L = sum_i y_i log(1 - e^-lambda_i) - (N - D_i - y_i) lambda_i. Returns (time of the pulse
    centroid in s, expected signal photons over the N periods)."""
    import numpy as np
    from scipy.optimize import minimize
    from scipy.special import ndtr

    y = hist.astype(np.float64)
    live = n_periods - np.concatenate(([0.0], np.cumsum(y)[:-1])) - y
    edges = np.arange(y.size + 1, dtype=np.float64)
    sig = rms_s / (bin_units * unit_s)
    near = np.abs(np.arange(y.size) - start_bin) < 4 * sig + 2

    def nll(p):
        t, la, lb = p
        g = ndtr((edges[1:] - t) / sig) - ndtr((edges[:-1] - t) / sig)
        lam = np.exp(la) * g + np.exp(lb)
        return -(np.sum(y * np.log(-np.expm1(-lam))) - np.sum(live * lam))

    a0 = max(y[near].sum() / n_periods, 1e-6)
    b0 = max(y[~near].sum() / n_periods / max(1, (~near).sum()), 1e-9)
    best = minimize(nll, [start_bin, np.log(a0), np.log(b0)], method="Nelder-Mead",
                    options={"xatol": 1e-4, "fatol": 1e-6, "maxiter": 4000})
    t, la, _ = best.x
    return (t * bin_units) * unit_s, float(np.exp(la) * n_periods)


def censored_rows(ppp: int = 900, size: int = 32, pixels: int = 256, seed: int = 0,
                  pulse_rms_ps: float = 360.0, sbr: float = 10.0) -> dict:
    """Coates' correction + ml beside the censored likelihood (:func:`censored_ml`) on the same
    pixels of one simulated scan: depth bias and MAE (cm), signal error, seconds per pixel each."""
    import numpy as np

    from spdepth.acq.api import reconstruct_file
    from spdepth.acq.cli import main
    from spdepth.acq.readers import read_photons
    from spdepth.acq.requests import FileReconRequest

    bin_units = 5.0
    with tempfile.TemporaryDirectory(prefix="spdepth-flux-") as tmp:
        ptu = Path(tmp) / "c.ptu"
        main(["simulate", "--scene", "tilted-plane", "--size", f"{size}x{size}", "--ppp", str(ppp),
              "--sbr", str(sbr), "--dwell-us", str(DWELL_US), "--seed", str(seed), "--ptu", str(ptu)])
        truth = np.load(ptu.with_name("c.truth.npz"))
        t0 = time.perf_counter()
        res = reconstruct_file(FileReconRequest(input=str(ptu), method="ml", pulse_rms_s=pulse_rms_ps * 1e-12,
                                                pileup="on"))
        coates_s = (time.perf_counter() - t0) / (size * size)
        read = read_photons(ptu)
    store = read.store
    unit_s = store.time_unit_s
    n_bins = int(np.ceil(12500 / bin_units))
    pick = np.random.default_rng(seed).choice(size * size, size=min(pixels, size * size), replace=False)
    depth_c, sig_c = [], []
    t0 = time.perf_counter()
    for p in pick:
        t = store.times[store.offsets[p]:store.offsets[p + 1]]
        hist = np.bincount(np.floor(t / bin_units).astype(np.int64), minlength=n_bins)[:n_bins]
        start = float(res.maps.tof_s.ravel()[p] / (bin_units * unit_s))
        tof, a = censored_ml(hist, float(read.periods[p]), bin_units, unit_s, pulse_rms_ps * 1e-12, start)
        depth_c.append(tof * 299792458.0 / 2)
        sig_c.append(a)
    cens_s = (time.perf_counter() - t0) / pick.size
    td, ts = truth["depth_m"].ravel()[pick], truth["signal"].ravel()[pick]
    dc = np.asarray(depth_c) - td
    dk = res.maps.depth_m.ravel()[pick] - td
    return {"pixels": int(pick.size), "ppp": ppp,
            "coates": {"bias_cm": 100 * float(np.mean(dk)), "mae_cm": 100 * float(np.mean(np.abs(dk))),
                       "signal_err": float(res.maps.signal.ravel()[pick].sum() / ts.sum() - 1),
                       "s_per_pixel": coates_s},
            "censored": {"bias_cm": 100 * float(np.mean(dc)), "mae_cm": 100 * float(np.mean(np.abs(dc))),
                         "signal_err": float(np.sum(sig_c) / ts.sum() - 1), "s_per_pixel": cens_s}}
