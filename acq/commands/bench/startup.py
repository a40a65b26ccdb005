"""``spdepth bench startup``: what a user waits for in a NEW process: ``spdepth recon`` of one
file run as a fresh subprocess each time, with a warm numba cache (the cache an earlier run left,
the user's case), alternated with the same command of another checkout (``--before``) when given.

    spdepth bench startup [--file MAT] [--runs 5] [--before PKGDIR] [--cold] [-- RECON OPTIONS]

Printed per checkout, best and median over the runs: the command's whole wall time (interpreter
start to exit, timed here) and CPU time (user + system, all its threads: the work done, which other
load on the machine moves less than the wall), ``read_s`` and ``recon_s`` as the command reports them (its
``--json`` summary), the reconstruction's pixels/s and their ratio to the plain port of
Algorithm 1 (``spdepth bench recon``'s uos reference, timed in this process in the same run, one
thread; it is BLAS-bound and slows far more than the kernels when other work shares the cores,
so the ratio is only comparable between quiet runs, while before/after in one run always is).
``--before PKGDIR|REV``: a directory holding another checkout as ``spdepth`` (put first on
PYTHONPATH for its runs; e.g. a ``git worktree add`` of an older commit and a symlink to it), or a
git revision of this checkout, exported to such a directory (``acq.commands.bench.before``).
``--cold``: also one run each with an empty numba cache (a fresh NUMBA_CACHE_DIR: every kernel
compiled), the first run after an install.
Defaults: the seed paper's mannequin and settings (README), ``--method uos``.

``--scan``: instead, the time-limited scan of issue 33, ``spdepth scan --sim --size 4096x4096
--target 1 --time-limit-s 5 --out DIR`` (``--size``, ``--time-limit-s``), run the same way: per
checkout its wall time from the interpreter's start to its exit against the limit + 5 s, its CPU
time, its peak resident memory (the child's own, from ``wait4``) against 2 GB, the size of its
run.json and the pixels it completed.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

#: the seed paper's mannequin, where the tests find the shared data: beside the source checkout
FACE = Path(__file__).resolve().parents[4] / "shared" / "data" / "fpi" / "mannequin_face_8ppp.mat"
SEED_SETTINGS = ["--time-unit-ps", "8", "--window-ps", "16000:48000", "--bin-ps", "40",
                 "--pulse-rms-ps", "360", "--max-photons", "15", "--method", "uos"]


def _run(pkgdir: str | None, argv: list[str], cache_dir: str | None) -> dict:
    """One ``spdepth recon ... --json`` in a new interpreter: its summary plus ``wall_s``."""
    env = dict(os.environ)
    if pkgdir:
        env["PYTHONPATH"] = os.pathsep.join([pkgdir] + [p for p in [env.get("PYTHONPATH")] if p])
    if cache_dir:
        env["NUMBA_CACHE_DIR"] = cache_dir
    t0, c0 = time.perf_counter(), _children_cpu_s()
    out = subprocess.run([sys.executable, "-m", "spdepth.acq.cli", "recon", *argv, "--json"], env=env,
                         capture_output=True, text=True)
    wall, cpu = time.perf_counter() - t0, _children_cpu_s() - c0
    if out.returncode != 0:
        raise RuntimeError(f"spdepth recon exited {out.returncode}: {out.stderr.strip()[-500:]}")
    summary = json.loads(out.stdout.strip().splitlines()[-1])
    summary["wall_s"], summary["cpu_s"] = wall, cpu
    return summary


def _run_scan(pkgdir: str | None, argv: list[str], out_dir: Path) -> dict:
    """One ``spdepth scan ... --out out_dir --json`` in a new interpreter: its summary plus
    ``wall_s``, ``cpu_s``, ``peak_rss_mb`` (the child's own) and ``run_json_bytes``."""
    import shutil

    env = dict(os.environ)
    if pkgdir:
        env["PYTHONPATH"] = os.pathsep.join([pkgdir] + [p for p in [env.get("PYTHONPATH")] if p])
    shutil.rmtree(out_dir, ignore_errors=True)
    with tempfile.TemporaryFile("w+") as out, tempfile.TemporaryFile("w+") as err:
        t0 = time.perf_counter()
        proc = subprocess.Popen([sys.executable, "-m", "spdepth.acq.cli", "scan", *argv, "--out",
                                 str(out_dir), "--json"], env=env, stdout=out, stderr=err,
                                stdin=subprocess.DEVNULL)
        # wait4, not wait: the rusage of this child alone (RUSAGE_CHILDREN's peak is the largest
        # of every child so far)
        _, status, usage = os.wait4(proc.pid, 0)
        wall = time.perf_counter() - t0
        proc.returncode = os.waitstatus_to_exitcode(status)
        out.seek(0)
        err.seek(0)
        stdout, stderr = out.read(), err.read()
    if proc.returncode != 0:
        raise RuntimeError(f"spdepth scan exited {proc.returncode}: {stderr.strip()[-500:]}")
    summary = json.loads(stdout.strip().splitlines()[-1])
    summary.update(wall_s=wall, cpu_s=usage.ru_utime + usage.ru_stime,
                   peak_rss_mb=usage.ru_maxrss / 1024,
                   run_json_bytes=(out_dir / "run.json").stat().st_size)
    return summary


def bench_scan(sides: dict, size: tuple[int, int], limit_s: float, runs: int) -> None:
    """``--scan`` (module docstring): ``runs`` runs of each side in turn, after one untimed run
    each (which leaves, or finds, each checkout's numba cache warm)."""
    h, w = size
    argv = ["--sim", "--size", f"{w}x{h}", "--target", "1", "--time-limit-s", f"{limit_s:g}"]
    print(f"spdepth bench startup --scan: spdepth scan {' '.join(argv)} --out DIR")
    print(f"load average before: {' '.join(f'{v:.2f}' for v in os.getloadavg())}")
    with tempfile.TemporaryDirectory(prefix="spdepth-bench-scan-") as tmp:
        for i, pkg in enumerate(sides.values()):
            _run_scan(pkg, argv, Path(tmp) / f"warm-{i}")
        results: dict[str, list[dict]] = {label: [] for label in sides}
        for _ in range(runs):
            for i, (label, pkg) in enumerate(sides.items()):
                results[label].append(_run_scan(pkg, argv, Path(tmp) / f"run-{i}"))
    print(f"{runs} runs each, in turn; best / median; targets: wall <= {limit_s + 5:g} s "
          f"(the limit + 5 s), peak RSS <= 2048 MB")
    print(f"{'':22} {'wall s':>13} {'cpu s':>13} {'peak RSS MB':>13} {'run.json B':>13} "
          f"{'pixels complete':>17}")
    for label, rs in results.items():
        def col(key, fmt="{:.2f}"):
            v = [r[key] for r in rs]
            return f"{fmt.format(min(v))} / {fmt.format(statistics.median(v))}"

        complete = [r["pixels"] - r["flagged"] for r in rs]
        print(f"{label:22} {col('wall_s'):>13} {col('cpu_s'):>13} {col('peak_rss_mb', '{:.0f}'):>13} "
              f"{col('run_json_bytes', '{:.0f}'):>13} {min(complete):>8,} / {max(complete):,}")
    print(f"load average after: {' '.join(f'{v:.2f}' for v in os.getloadavg())}")


def _children_cpu_s() -> float:
    """CPU seconds (user + system) of this process's finished children."""
    ru = resource.getrusage(resource.RUSAGE_CHILDREN)
    return ru.ru_utime + ru.ru_stime


def bench(argv: list[str]) -> int:
    p = argparse.ArgumentParser(prog="spdepth bench startup", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--file", default=FACE, help=f"the file to reconstruct (default {FACE})")
    p.add_argument("--runs", type=int, default=None,
                   help="warm runs per checkout, alternated (default 5; --scan: 3)")
    p.add_argument("--before", metavar="PKGDIR|REV",
                   help="also run the checkout found as spdepth in PKGDIR, or this checkout's revision REV")
    p.add_argument("--cold", action="store_true", help="also one run each with an empty numba cache")
    p.add_argument("--scan", action="store_true",
                   help="time the time-limited scan instead (module docstring; --runs default 3)")
    p.add_argument("--size", default="4096x4096", metavar="WxH",
                   help="--scan: the frame (default 4096x4096)")
    p.add_argument("--time-limit-s", type=float, default=5.0,
                   help="--scan: the time limit (default 5)")
    p.add_argument("recon", nargs=argparse.REMAINDER,
                   help="spdepth recon options after '--' (default: the seed paper's, --method uos)")
    a = p.parse_args(argv)
    if a.scan:
        from spdepth.acq.params import parse_size

        sides = {"this checkout": None}
        if a.before:
            from spdepth.acq.commands.bench.before import package_dir

            sides = {"before": package_dir(a.before), "after (this checkout)": None}
        bench_scan(sides, parse_size(a.size), a.time_limit_s, a.runs or 3)
        return 0
    a.runs = a.runs or 5
    if not Path(a.file).is_file():
        p.error(f"no file {a.file} (give one with --file)")
    settings = [v for v in a.recon if v != "--"] or SEED_SETTINGS
    recon_argv = [str(a.file), *settings]
    from spdepth.acq.commands.bench.recon import uos_port_rate

    sides = {"this checkout": None}
    if a.before:
        from spdepth.acq.commands.bench.before import package_dir

        sides = {"before": package_dir(a.before), "after (this checkout)": None}
    print(f"spdepth bench startup: spdepth recon {' '.join(recon_argv)}")
    print(f"load average before: {' '.join(f'{v:.2f}' for v in os.getloadavg())}")
    cold = {}
    if a.cold:
        for label, pkg in sides.items():
            with tempfile.TemporaryDirectory(prefix="spdepth-cold-cache-") as cache:
                cold[label] = _run(pkg, recon_argv, cache)
    for pkg in sides.values():
        _run(pkg, recon_argv, None)          # leaves (or finds) the warm cache of this checkout
    runs: dict[str, list[dict]] = {label: [] for label in sides}
    port = 0.0
    for _ in range(a.runs):
        # alternated, and the port timed between them: a burst of other work lands on all
        for label, pkg in sides.items():
            runs[label].append(_run(pkg, recon_argv, None))
        port = max(port, uos_port_rate(50))
    pixels = runs[next(iter(sides))][0]["pixels"]
    print(f"{pixels:,} pixels; the plain port of Algorithm 1: {port:,.0f} pixels/s (1 thread, best of "
          f"{a.runs}); {a.runs} warm runs each, in turn; best / median")
    print(f"{'':22} {'wall s':>13} {'cpu s':>13} {'read_s':>13} {'recon_s':>13} {'recon px/s':>19} {'x port':>11}")
    for label, rs in runs.items():
        def col(key, fmt="{:.2f}"):
            v = [r[key] for r in rs]
            return f"{fmt.format(min(v))} / {fmt.format(statistics.median(v))}"

        rates = [pixels / r["recon_s"] for r in rs]
        print(f"{label:22} {col('wall_s'):>13} {col('cpu_s'):>13} {col('read_s'):>13} {col('recon_s'):>13} "
              f"{max(rates):>9,.0f} / {statistics.median(rates):>7,.0f} "
              f"{max(rates) / port:>5.0f} / {statistics.median(rates) / port:>3.0f}")
    for label, r in cold.items():
        print(f"cold numba cache, {label}: wall {r['wall_s']:.1f} s (read_s {r['read_s']:.2f}, "
              f"recon_s {r['recon_s']:.2f})")
    return 0


if __name__ == "__main__":
    sys.exit(bench(sys.argv[1:]))
