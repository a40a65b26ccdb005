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


def _children_cpu_s() -> float:
    """CPU seconds (user + system) of this process's finished children."""
    ru = resource.getrusage(resource.RUSAGE_CHILDREN)
    return ru.ru_utime + ru.ru_stime


def bench(argv: list[str]) -> int:
    p = argparse.ArgumentParser(prog="spdepth bench startup", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--file", default=FACE, help=f"the file to reconstruct (default {FACE})")
    p.add_argument("--runs", type=int, default=5, help="warm runs per checkout, alternated (default 5)")
    p.add_argument("--before", metavar="PKGDIR|REV",
                   help="also run the checkout found as spdepth in PKGDIR, or this checkout's revision REV")
    p.add_argument("--cold", action="store_true", help="also one run each with an empty numba cache")
    p.add_argument("recon", nargs=argparse.REMAINDER,
                   help="spdepth recon options after '--' (default: the seed paper's, --method uos)")
    a = p.parse_args(argv)
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
