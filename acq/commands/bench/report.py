"""``spdepth bench report``: what accuracy costs in detections, scan time and compute.

Sweeps detections per pixel, signal-to-background ratio and estimator over simulated scenes with
truth, and writes ``report.md`` (tables, machine, versions, the command), ``results.csv`` and three
PNGs: error vs detections per pixel (with the oracle bound), error vs compute time per pixel (the
accuracy-for-time trade-off) and error vs SBR.

How a point is made:

- Scene: the built-in ``bust`` (one surface; reflectivity, hence SBR, varies over the image) and,
  for the K = 2 estimator, ``two-layer`` (a pane at 2 m before a wall at 3.5 m), simulated by
  ``drivers.sim.PhotonWorld`` as a count-gated scan: every pixel is kept until it has exactly N
  detections in the recorded window (the seed paper's 801 bins of 40 ps after each sync; 8 ps
  tagger units; Gaussian pulse of 360 ps RMS; 10 MHz laser).
- SBR is the image-mean ratio inside the recorded window (the scene's SBR over the laser period is
  set to ``SBR * window / period`` so the estimators see the stated ratio).
- Errors: ``acq.evaluate.evaluate_depth`` over every pixel with truth, one denominator: a pixel
  without an estimate is a miss, counts as an outlier and costs the outlier threshold (3 pulse
  RMS of depth, 16.2 cm) in MAE and RMSE. The oracle is per pixel (``signal_detections``:
  N * SBR_p / (1 + SBR_p) expected signal detections at that pixel), averaged over the same pixels.
  Below about one expected signal detection the bound is not a bound (the oracle itself has
  nothing to average most of the time); such points are marked in the tables.
- Scan time: count-gated at a stated detection rate (default 500,000 detections/s: 5% of the
  pulses of a 10 MHz laser, where pile-up is still small), so a pixel of N detections takes
  N / rate seconds.
- Compute time: warm (kernels compiled by an untimed first run), one numba thread, best of a few
  runs of ``recon.estimate.reconstruct`` over the whole image, in CPU time of this process (other
  work on a shared machine inflates wall time, not this), divided by its pixels.
"""

from __future__ import annotations

import argparse
import csv
import math
import os
import platform
import shlex
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

# numpy and the estimators (recon.model.METHODS: the report covers every one) are imported where
# used: ``spdepth bench report --help`` loads neither

DETECTIONS = (2, 5, 10, 15, 30, 60)
SBRS = (0.1, 1.0, 10.0)
QUICK_DETECTIONS = (5, 15, 60)
QUICK_SBRS = (1.0, 10.0)
SIZE = 128
QUICK_SIZE = 32
RATE_HZ = 500_000.0
FRAME_SIDE = 256
"""Scan times are also given for a FRAME_SIDE x FRAME_SIDE frame."""

# the seed paper's recording: 8 ps units, 801 bins of 40 ps, 360 ps pulse
UNIT_S = 8e-12
BIN_UNITS = 5
N_BINS = 801
PULSE_RMS_S = 360e-12
SYNC_PERIOD_S = 100e-9
WINDOW_S = N_BINS * BIN_UNITS * UNIT_S

CSV_FIELDS = ("scene", "method", "reflectors", "surface", "detections", "sbr", "pixels", "mae_cm",
              "rmse_cm", "outlier_share", "miss_share", "oracle_mae_cm", "ratio_to_oracle",
              "signal_per_pixel", "scan_us_per_pixel", "scan_s_per_frame", "compute_us_per_pixel")


@dataclass(frozen=True)
class Point:
    """One simulated acquisition: scene, detections per pixel N, in-window SBR."""

    scene: str
    detections: int
    sbr: float


def simulate(point: Point, size: tuple[int, int], seed: int):
    """(store, scene) of a count-gated scan of ``point``: every pixel until N recorded detections."""
    import numpy as np

    from spdepth.drivers.events import EventKind
    from spdepth.drivers.sim import PhotonWorld, load_scene
    from spdepth.recon.photons import PhotonStore

    h, w = size
    scene = load_scene(point.scene, (h, w), ppp=point.detections,
                       sbr=point.sbr * WINDOW_S / SYNC_PERIOD_S, tagger_range_s=WINDOW_S,
                       sync_period_s=SYNC_PERIOD_S, pulse_rms_s=PULSE_RMS_S, resolution_s=UNIT_S)
    world = PhotonWorld(scene, seed=seed)
    lists, sync = [], 0
    # generous dwell limit: a dark pixel at low N must still reach its count
    limit_s = 1000 * scene.dwell_s
    for r in range(h):
        for c in range(w):
            ev, n_syncs = world.count_gated(r, c, point.detections, limit_s, sync)
            sync += n_syncs
            lists.append(ev["dtime"][ev["kind"] == EventKind.PHOTON].astype(np.float64))
    return PhotonStore.from_lists(lists, (h, w), UNIT_S), scene


def settings_for(method: str, reflectors: int = 1):
    from spdepth.recon.model import Binning, ReconSettings

    binning = Binning(UNIT_S, 0, N_BINS * BIN_UNITS, BIN_UNITS)
    return ReconSettings(method=method, binning=binning, pulse_rms_s=PULSE_RMS_S,
                         reflectors=reflectors)


def warm_time_s(store, settings, repeats: int) -> tuple[object, float]:
    """(maps, best CPU seconds of ``repeats`` timed runs) after one untimed run that compiles.

    CPU time of this process, not wall time: on a machine shared with other work, wall time
    measures the neighbours too (seen here: the same point 2-3x apart between runs); with one
    numba thread the CPU time is the estimator's own cost."""
    from spdepth.recon.estimate import reconstruct

    maps = reconstruct(store, settings)
    best = math.inf
    for _ in range(repeats):
        t0 = time.process_time()
        reconstruct(store, settings)
        best = min(best, time.process_time() - t0)
    return maps, best


def errors_rows(point: Point, method: str, reflectors: int, maps, truth, compute_s: float,
                rate_hz: float) -> list[dict]:
    """CSV rows of one reconstruction: one per surface evaluated."""
    import numpy as np

    from spdepth.acq.evaluate import evaluate_depth, signal_detections

    n_pix = maps.photons.size
    common = {"scene": point.scene, "method": method, "reflectors": reflectors,
              "detections": point.detections, "sbr": point.sbr,
              "scan_us_per_pixel": 1e6 * point.detections / rate_hz,
              "scan_s_per_frame": FRAME_SIDE * FRAME_SIDE * point.detections / rate_hz,
              "compute_us_per_pixel": 1e6 * compute_s / n_pix}
    rows = []
    if reflectors == 1:
        surfaces = [(0, maps.depth_m, truth["depth_m"])]
    else:
        # K returns sorted by time against the surfaces sorted by depth, on the pixels that see
        # all K of them (the pane's pixels for two-layer)
        seen = np.all(truth["occupancy"] > 0, axis=0)
        surfaces = [(s, maps.depth_m[s], np.where(seen, truth["depth_m"][s], np.nan))
                    for s in range(reflectors)]
    for surface, est, true in surfaces:
        k = signal_detections(truth, maps.photons, surface=surface)
        e = evaluate_depth(est, true, k, PULSE_RMS_S)
        valid = np.isfinite(true) & (k > 0)
        rows.append(dict(common, surface=surface, pixels=e.n_pixels, mae_cm=100 * e.mae_m,
                         rmse_cm=100 * e.rmse_m, outlier_share=e.outlier_share,
                         miss_share=e.miss_share, oracle_mae_cm=100 * e.oracle_mae_m,
                         ratio_to_oracle=e.ratio_to_oracle,
                         signal_per_pixel=float(k[valid].mean())))
    return rows


def run_sweep(detections, sbrs, methods, size: tuple[int, int], rate_hz: float, repeats: int, seed: int,
              two_layer: bool = True) -> list[dict]:
    """Every point of the sweep, as CSV rows (see CSV_FIELDS)."""
    import numba

    from spdepth.acq.report import ProgressBar

    jobs = [(Point("bust", n, s), m, 1) for s in sbrs for n in detections for m in methods]
    if two_layer:
        top = max(sbrs)
        jobs += [(Point("two-layer", n, top), "uos", 2) for n in detections]
    rows: list[dict] = []
    cache: dict[Point, tuple] = {}
    old_threads = numba.get_num_threads()
    numba.set_num_threads(1)
    try:
        with ProgressBar("bench report", len(jobs), unit="point") as bar:
            for i, (point, method, k) in enumerate(jobs):
                if point not in cache:
                    cache.clear()       # jobs are grouped by point: keep only the current one
                    store, scene = simulate(point, size, seed + 1000 * i)
                    cache[point] = (store, scene.truth())
                store, truth = cache[point]
                maps, secs = warm_time_s(store, settings_for(method, k), repeats)
                rows += errors_rows(point, method, k, maps, truth, secs, rate_hz)
                bar.update(1, f"{point.scene} N={point.detections} SBR={point.sbr:g} {method}")
    finally:
        numba.set_num_threads(old_threads)
    return rows


# ---------------------------------------------------------------------------------------------
# outputs


def write_csv(path: Path, rows: list[dict]) -> None:
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=CSV_FIELDS)
        w.writeheader()
        for r in rows:
            w.writerow({k: (f"{r[k]:.6g}" if isinstance(r[k], float) else r[k]) for k in CSV_FIELDS})


def _label(r: dict) -> str:
    return r["method"] if r["reflectors"] == 1 else f"{r['method']} K={r['reflectors']}"


def _outlier_cm() -> float:
    """The outlier threshold (and a miss's cost) of ``evaluate_depth``'s default, cm."""
    from spdepth.acq.evaluate import OUTLIER_PULSE_WIDTHS
    from spdepth.recon.maps import C_M_PER_S

    return 100 * OUTLIER_PULSE_WIDTHS * C_M_PER_S / 2 * PULSE_RMS_S


def _series(rows, **match):
    return [r for r in rows if all(r[k] == v for k, v in match.items())]


def _plain_log_ticks(ax, xticks=None) -> None:
    """Log axes labelled 5, 15, 60 rather than 5x10^0, 1.5x10^1, 6x10^1."""
    from matplotlib.ticker import NullFormatter, ScalarFormatter

    if xticks is not None:
        ax.set_xticks(list(xticks))
    for axis in (ax.xaxis, ax.yaxis):
        fmt = ScalarFormatter()
        fmt.set_scientific(False)
        axis.set_major_formatter(fmt)
        axis.set_minor_formatter(NullFormatter())


def _figure(ncols: int, width: float = 4.2, height: float = 3.6):
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width * ncols, height), dpi=110, layout="constrained")
    FigureCanvasAgg(fig)
    return fig, [fig.add_subplot(1, ncols, i + 1) for i in range(ncols)]


COLOURS = {"lmf": "tab:red", "uos": "tab:blue", "ml": "tab:green", "spatial": "tab:purple", "oracle": "black"}


def _error_panel(ax, pts: list[dict], x_key: str, xlabel: str, title: str) -> None:
    """One panel: MAE of each estimator and the oracle bound against ``x_key``."""
    from spdepth.recon.model import METHODS

    for method in sorted({r["method"] for r in pts}, key=METHODS.index):
        s = sorted(_series(pts, method=method), key=lambda r: r[x_key])
        ax.plot([r[x_key] for r in s], [r["mae_cm"] for r in s], "o-", color=COLOURS.get(method),
                label=method)
    s = sorted(_series(pts, method=pts[0]["method"]), key=lambda r: r[x_key])
    ax.plot([r[x_key] for r in s], [r["oracle_mae_cm"] for r in s], "k--", label="oracle bound")
    ax.axhline(_outlier_cm(), color="grey", lw=0.8, ls=":", label="miss / outlier cost")
    ax.set(xscale="log", yscale="log", xlabel=xlabel, title=title)
    _plain_log_ticks(ax, sorted({r[x_key] for r in pts}))
    ax.grid(True, which="both", alpha=0.3)


def _finish(fig, axes, path: Path, title: str) -> None:
    axes[0].set_ylabel("mean absolute depth error (cm)")
    axes[0].legend(fontsize=8)
    fig.suptitle(title)
    fig.savefig(path)


def plot_error_vs_detections(path: Path, rows: list[dict]) -> None:
    bust = _series(rows, scene="bust")
    sbrs = sorted({r["sbr"] for r in bust})
    fig, axes = _figure(len(sbrs))
    for ax, sbr in zip(axes, sbrs):
        _error_panel(ax, _series(bust, sbr=sbr), "detections", "detections per pixel",
                     f"bust, SBR {sbr:g} in the window")
    _finish(fig, axes, path, "Depth error vs detections per pixel (count-gated; one denominator, "
            "misses count)")


def plot_error_vs_compute(path: Path, rows: list[dict], rate_hz: float) -> None:
    """Left: MAE vs compute per pixel; right: MAE vs scan + compute per pixel. Each line is one
    estimator through its detection counts (labelled); the lower-left envelope is the Pareto front."""
    from spdepth.recon.model import METHODS

    bust = _series(rows, scene="bust")
    sbr = max(r["sbr"] for r in bust)
    pts = _series(bust, sbr=sbr)
    fig, axes = _figure(2, width=5.0)
    for ax, total in zip(axes, (False, True)):
        cloud = []
        for method in sorted({r["method"] for r in pts}, key=METHODS.index):
            s = sorted(_series(pts, method=method), key=lambda r: r["detections"])
            x = [r["compute_us_per_pixel"] + (r["scan_us_per_pixel"] if total else 0.0) for r in s]
            y = [r["mae_cm"] for r in s]
            cloud += list(zip(x, y))
            ax.plot(x, y, "o-", color=COLOURS.get(method), label=method)
            for xi, yi, r in zip(x, y, s):
                ax.annotate(str(r["detections"]), (xi, yi), fontsize=7, xytext=(3, 3),
                            textcoords="offset points")
        front, best = [], math.inf
        for xi, yi in sorted(cloud):
            if yi < best:
                front.append((xi, yi))
                best = yi
        ax.step([p[0] for p in front], [p[1] for p in front], where="post", color="grey", lw=3,
                alpha=0.35, label="Pareto front")
        ax.set(xscale="log", yscale="log",
               xlabel=("scan + compute" if total else "compute") + " time per pixel (µs)",
               title=(f"scan at {rate_hz:,.0f} detections/s + 1-thread compute" if total
                      else "compute only (warm, 1 thread)"))
        _plain_log_ticks(ax)
        ax.grid(True, which="both", alpha=0.3)
    _finish(fig, axes, path, f"Accuracy for time, bust at SBR {sbr:g} (labels: detections per pixel)")


def plot_error_vs_sbr(path: Path, rows: list[dict]) -> None:
    bust = _series(rows, scene="bust")
    ns = sorted({r["detections"] for r in bust})
    shown = [n for n in (15, 60) if n in ns] or ns[-1:]
    fig, axes = _figure(len(shown))
    for ax, n in zip(axes, shown):
        _error_panel(ax, _series(bust, detections=n), "sbr",
                     "signal-to-background ratio (in the window)", f"bust, {n} detections per pixel")
    _finish(fig, axes, path, "Depth error vs SBR")


def _versions() -> str:
    import matplotlib
    import numba
    import numpy as np

    try:
        rev = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                             cwd=Path(__file__).resolve().parent, timeout=5).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        rev = ""
    from importlib.metadata import PackageNotFoundError, version

    try:
        ours = version("spdepth")
    except PackageNotFoundError:
        ours = "source"
    return (f"spdepth {ours}{' (git ' + rev + ')' if rev else ''}, Python {platform.python_version()}, "
            f"NumPy {np.__version__}, numba {numba.__version__}, matplotlib {matplotlib.__version__}")


def _machine() -> str:
    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as f:
            names = [ln.split(":", 1)[1].strip() for ln in f if ln.startswith("model name")]
        cpu = names[0] if names else cpu
    except OSError:
        pass   # no /proc/cpuinfo (not Linux): keep platform's own CPU name
    load = " ".join(f"{v:.2f}" for v in os.getloadavg()) if hasattr(os, "getloadavg") else "n/a"
    return f"{platform.system()} {platform.release()}, {cpu}, {os.cpu_count()} logical CPUs, load {load}"


def _fmt_ratio(r: dict) -> str:
    flag = "†" if r["signal_per_pixel"] < 1 else ""
    return f"{r['mae_cm']:.2f} ({r['ratio_to_oracle']:.2f}x{flag})"


def headline_table(rows: list[dict]) -> list[str]:
    """MAE (x oracle) per estimator and detections per pixel at the highest SBR, with scan time."""
    from spdepth.recon.model import METHODS

    bust = _series(rows, scene="bust")
    sbr = max(r["sbr"] for r in bust)
    pts = _series(bust, sbr=sbr)
    ns = sorted({r["detections"] for r in pts})
    methods = sorted({r["method"] for r in pts}, key=METHODS.index)
    out = [f"| bust, SBR {sbr:g} | " + " | ".join(f"N = {n}" for n in ns) + " |",
           "|---|" + "---:|" * len(ns)]
    first = {r["detections"]: r for r in _series(pts, method=methods[0])}
    out.append(f"| scan of a {FRAME_SIDE}x{FRAME_SIDE} frame | "
               + " | ".join(f"{first[n]['scan_s_per_frame']:.2f} s" for n in ns) + " |")
    out.append("| oracle bound (cm) | " + " | ".join(f"{first[n]['oracle_mae_cm']:.2f}" for n in ns)
               + " |")
    for m in methods:
        by = {r["detections"]: r for r in _series(pts, method=m)}
        out.append(f"| {m}: MAE cm (x oracle) | " + " | ".join(_fmt_ratio(by[n]) for n in ns) + " |")
    for m in methods:
        by = {r["detections"]: r for r in _series(pts, method=m)}
        out.append(f"| {m}: compute µs/pixel | "
                   + " | ".join(f"{by[n]['compute_us_per_pixel']:.2f}" for n in ns) + " |")
    return out


def full_table(rows: list[dict]) -> list[str]:
    out = ["| scene | estimator | surface | N | SBR | signal/px | MAE cm | RMSE cm | outliers | misses "
           "| oracle cm | x oracle | scan µs/px | compute µs/px |",
           "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        flag = " †" if r["signal_per_pixel"] < 1 else ""
        out.append(f"| {r['scene']} | {_label(r)} | {r['surface']} | {r['detections']} | {r['sbr']:g} "
                   f"| {r['signal_per_pixel']:.2f} | {r['mae_cm']:.2f} | {r['rmse_cm']:.2f} "
                   f"| {100 * r['outlier_share']:.1f}% | {100 * r['miss_share']:.1f}% "
                   f"| {r['oracle_mae_cm']:.2f} | {r['ratio_to_oracle']:.2f}{flag} "
                   f"| {r['scan_us_per_pixel']:.0f} | {r['compute_us_per_pixel']:.2f} |")
    return out


def write_report(path: Path, rows: list[dict], *, command: str, size: tuple[int, int], rate_hz: float,
                 repeats: int, seed: int, elapsed_s: float, quick: bool, flux: list[str] = ()) -> None:
    lines = [
        "# spdepth bench report: what accuracy costs in time",
        "",
        f"Command: `{command}`{' (quick: a subset of points, small images)' if quick else ''}  ",
        f"Machine: {_machine()}  ",
        f"Versions: {_versions()}  ",
        f"Run: {time.strftime('%Y-%m-%d %H:%M:%S')}, {elapsed_s:.0f} s, seed {seed}",
        "",
        "## How each point is made",
        "",
        f"- Simulated count-gated scans of {size[1]}x{size[0]} pixels (`drivers.sim.PhotonWorld`): every "
        "pixel is kept until it has exactly N detections in the recorded window, the seed paper's "
        f"{N_BINS} bins of {BIN_UNITS * UNIT_S * 1e12:.0f} ps ({UNIT_S * 1e12:.0f} ps tagger units), "
        f"Gaussian pulse of {PULSE_RMS_S * 1e12:.0f} ps RMS, {1e-6 / SYNC_PERIOD_S:.0f} MHz laser. "
        "Scenes `bust` (one surface) and `two-layer` (a pane at 2 m before a wall at 3.5 m, for "
        "the K = 2 estimator, evaluated on the pane's pixels, per surface).",
        "- SBR: image-mean signal to background inside the recorded window. The bust's "
        "reflectivity varies, so per-pixel SBR varies around it.",
        "- Errors over every pixel with truth, one denominator (`acq.evaluate.evaluate_depth`): a "
        "pixel without an estimate is a miss; it counts as an outlier and costs the outlier "
        f"threshold ({_outlier_cm():.1f} cm, 3 pulse RMS of depth) in "
        "MAE and RMSE. Outliers: error above that threshold, misses included.",
        "- Oracle bound: per pixel, c/2 σ √(2/π) / √k with k = N · SBR_p / (1 + SBR_p) the pixel's "
        "expected signal detections, averaged over the same pixels. † marks points with under one "
        "expected signal detection per pixel, where the formula is no longer a bound (the oracle "
        "itself usually has no signal detection to average).",
        "- `spatial` (recon/estimators/spatial.py) also uses each pixel's neighbours, so the pixelwise bound "
        "does not bind it: below 1.00x oracle is what the neighbours buy on a piecewise-smooth scene.",
        f"- Scan time: count-gated at {rate_hz:,.0f} detections/s (5% of the pulses of a 10 MHz "
        f"laser, where pile-up is still small): N / rate per pixel; also given for a {FRAME_SIDE}x"
        f"{FRAME_SIDE} frame.",
        f"- Compute time: warm (an untimed first run compiles the kernels), one numba thread, best of "
        f"{repeats} runs of `recon.estimate.reconstruct` over the whole image, per pixel, in CPU "
        "time of the process (wall time on a shared machine also measures the neighbours). It "
        "includes the per-call set-up, which matters for lmf on small images. Compare methods "
        "within one run; absolute figures move with the machine.",
        "",
        "## Headline",
        "",
        "![error vs detections](error_vs_detections.png)",
        "",
        *headline_table(rows),
        "",
        "![accuracy for time](error_vs_compute.png)",
        "",
        "![error vs SBR](error_vs_sbr.png)",
        "",
        "## Every point",
        "",
        *full_table(rows),
        "",
        "Raw numbers: `results.csv` (one row per point and surface).",
        "",
        *flux,
    ]
    path.write_text("\n".join(lines))


def flux_section(quick: bool, seed: int) -> list[str]:
    """The report's high-flux section: ``spdepth bench flux``'s table (pile-up corrected and not)."""
    from spdepth.acq.commands.bench import flux

    rows = flux.flux_rows(flux.QUICK_LEVELS if quick else flux.LEVELS, seed=seed)
    return ["## High flux: pile-up corrected and not", "",
            f"`spdepth simulate --scene tilted-plane --size 32x32 --sbr 10 --dwell-us {flux.DWELL_US:g}` "
            f"({flux.PERIODS} laser periods per pixel; the simulator's 50 ns dead time switches itself on above "
            "0.05 detections per pulse) at each level, reconstructed by ml with the pulse given, `--pileup off` "
            "and `on` (`recon/pileup.py`, Coates' correction); bias: mean depth error over the pixels with an "
            "estimate; signal error: estimated against ideal-detector signal, summed.", "",
            *flux.flux_table(rows), ""]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from spdepth.acq.params import add_options, parse_size

    add_options(parser, "bench report")         # --out: the report's folder
    parser.add_argument("--quick", action="store_true",
                        help=f"a subset (N {QUICK_DETECTIONS}, SBR {QUICK_SBRS}, {QUICK_SIZE}x{QUICK_SIZE}): "
                             "about a minute")
    parser.add_argument("--size", type=parse_size, metavar="WxH",
                        help=f"pixels (default {SIZE}x{SIZE}, quick {QUICK_SIZE}x{QUICK_SIZE})")
    parser.add_argument("--rate-hz", type=float, default=RATE_HZ,
                        help=f"detection rate the scan times assume (default {RATE_HZ:,.0f}/s)")
    parser.add_argument("--repeats", type=int, help="timed runs per point, best kept (default 5, quick 2)")
    parser.add_argument("--seed", type=int, default=0)


def bench(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="spdepth bench report", description=__doc__.splitlines()[0])
    add_arguments(parser)
    args = parser.parse_args(argv)
    from spdepth.recon.errors import InputError
    from spdepth.recon.model import METHODS
    side = QUICK_SIZE if args.quick else SIZE
    size = args.size or (side, side)
    repeats = args.repeats or (2 if args.quick else 5)
    if min(size) < 4 or repeats < 1 or not (args.rate_hz > 0 and math.isfinite(args.rate_hz)):
        raise InputError(f"bench report: need --size of at least 4x4, --repeats >= 1 and a positive --rate-hz "
                         f"(got {size}, {repeats}, {args.rate_hz})")
    from spdepth.acq.outputs import check_output_folder, probe_folder

    out = Path(args.out)
    check_output_folder("--out", out)          # before the minutes of the sweep, not after
    out.mkdir(parents=True, exist_ok=True)
    probe_folder("--out", out)
    t0 = time.perf_counter()
    rows = run_sweep(QUICK_DETECTIONS if args.quick else DETECTIONS, QUICK_SBRS if args.quick else SBRS,
                     METHODS, size, args.rate_hz, repeats, args.seed)
    flux = flux_section(args.quick, args.seed)
    elapsed = time.perf_counter() - t0
    write_csv(out / "results.csv", rows)
    plot_error_vs_detections(out / "error_vs_detections.png", rows)
    plot_error_vs_compute(out / "error_vs_compute.png", rows, args.rate_hz)
    plot_error_vs_sbr(out / "error_vs_sbr.png", rows)
    command = "spdepth bench report " + " ".join(shlex.quote(a) for a in argv)
    write_report(out / "report.md", rows, command=command, size=size, rate_hz=args.rate_hz,
                 repeats=repeats, seed=args.seed, elapsed_s=elapsed, quick=args.quick, flux=flux)
    print("\n".join(headline_table(rows)))
    print(f"wrote {out / 'report.md'}, results.csv and 3 PNGs in {elapsed:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(bench(sys.argv[1:]))
