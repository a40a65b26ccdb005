"""``spdepth bench compile``: what a first run after an install waits for. Each kernel group is
compiled cold in a fresh process with its own empty numba cache (a fresh NUMBA_CACHE_DIR), then
the cold ``spdepth demo --no-window`` and the cold ``spdepth recon`` of the seed paper's mannequin
(its README command, ``--method uos``) end to end, each in a new process with an empty cache too.

    spdepth bench compile [--before PKGDIR] [--only NAME,...] [--skip-commands]

Printed per checkout: each group's first call in seconds, wall and CPU (user + system of that
process's threads while it ran: the work done, which other load on the machine moves less than
the wall), and each command's whole wall and CPU from interpreter start to exit. ``--before
PKGDIR``: a directory holding another checkout as ``spdepth`` (put first on PYTHONPATH for its
runs, as ``spdepth bench startup --before`` takes it); the two are alternated, group by group, so a
burst of other work lands on both. The groups call only library entry points (the simulated
bench's and the reader's warm-ups, ``recon.estimate.warm_up``), so any two checkouts compare.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time

from spdepth.acq.commands.bench.startup import FACE, SEED_SETTINGS

def recon_group(method: str, extra: str = "", decide: bool = True) -> str:
    """A group's code: ``method``'s kernels (``extra``: more ReconSettings arguments), and with
    ``decide`` the return test's, through ``recon.estimate.warm_up``. A checkout whose warm-up
    compiled the estimator's alone (no ``decide``: before the return test was compiled apart) compiles the
    test's in a reconstruction of four pixels instead, where every reconstruction ran it."""
    return ("import inspect\n"
            "import numpy as np\n"
            "from spdepth.recon.model import Binning, ReconSettings\n"
            "from spdepth.recon.estimate import reconstruct, warm_up\n"
            f"s = ReconSettings(method={method!r}, binning=Binning(8e-12, 2000.0, 6000.0, 5.0), "
            f"pulse_rms_s=360e-12, max_photons=15{extra})\n"
            "if 'decide' in inspect.signature(warm_up).parameters:\n"
            f"    warm_up(s, decide={decide})\n"
            "else:\n"
            "    warm_up(s)\n"
            + ("    from spdepth.recon.photons import PhotonStore\n"
               "    times = [np.array([3990.0, 4000.0, 4010.0, 2500.0, 5500.0])] * 4\n"
               "    reconstruct(PhotonStore.from_lists(times, (2, 2), 8e-12), s)\n" if decide else ""))


# What each group runs: library entry points with tiny inputs, as a command's first call would.
GROUPS = {
    "sim dwell_run": ("the simulated bench's dwells: gated and fixed (drivers.sim.warm_up)",
                      "from spdepth.drivers.sim import warm_up\nwarm_up()\n"),
    "sim raster": ("a whole fixed-dwell frame, as spdepth simulate writes (PhotonWorld.raster)",
                   "from spdepth.drivers.sim import PhotonWorld, load_scene\n"
                   "PhotonWorld(load_scene('bust', (2, 2), ppp=2.0), seed=0).raster()\n"),
    "t3 decode/encode": ("Generic T3 records both ways (drivers.tagger.t3.warm_up)",
                         "from spdepth.drivers.tagger.t3 import warm_up\nwarm_up()\n"),
    "store feed": ("assignment of events to pixels and the store (acq.store.PixelStore.feed)",
                   "import numpy as np\nfrom spdepth.drivers.events import EVENT_DTYPE\n"
                   "from spdepth.acq.store import PixelStore\n"
                   "ev = np.zeros(2, dtype=EVENT_DTYPE)\nev['kind'] = 255\n"
                   "PixelStore((2, 2), 4, (0, 100), 1e-12).feed(ev)\n"),
    "recon lmf": ("log-matched filter", recon_group("lmf")),
    "recon uos": ("union of subspaces (Algorithm 1)", recon_group("uos")),
    "recon ml": ("exact Poisson ML", recon_group("ml")),
    "recon ml K=2": ("ml with --reflectors 2 (recon.multi)",
                     recon_group("ml", ", reflectors=2")),
    "recon spatial": ("the spatial estimator", recon_group("spatial")),
}
# one group's first call, timed inside its process (imports excluded), as one JSON line
_RUNNER = ("import json, sys, time\nt0 = time.perf_counter()\nc0 = time.process_time()\n"
           "exec(compile(sys.argv[1], 'group', 'exec'))\n"
           "print(json.dumps({'wall_s': time.perf_counter() - t0, 'cpu_s': time.process_time() - c0}))\n")


def _env(pkgdir: str | None, cache_dir: str) -> dict:
    env = dict(os.environ, NUMBA_CACHE_DIR=cache_dir)
    if pkgdir:
        env["PYTHONPATH"] = os.pathsep.join([pkgdir] + [p for p in [env.get("PYTHONPATH")] if p])
    return env


def _children_cpu_s() -> float:
    ru = resource.getrusage(resource.RUSAGE_CHILDREN)
    return ru.ru_utime + ru.ru_stime


def _group(pkgdir: str | None, code: str) -> dict:
    """One group cold: the first call's wall and CPU, in a new process with an empty cache."""
    with tempfile.TemporaryDirectory(prefix="spdepth-cold-cache-") as cache:
        # the imports the group needs first, untimed: the group times its calls alone
        imports = "\n".join(line for line in code.splitlines() if line.startswith(("import", "from")))
        calls = "\n".join(line for line in code.splitlines() if not line.startswith(("import", "from")))
        out = subprocess.run([sys.executable, "-c", imports + "\n" + _RUNNER, calls],
                             env=_env(pkgdir, cache), capture_output=True, text=True)
    if out.returncode != 0:
        return {"error": out.stderr.strip().splitlines()[-1] if out.stderr.strip() else "failed"}
    return json.loads(out.stdout.strip().splitlines()[-1])


def _command(pkgdir: str | None, argv: list[str], cwd: str) -> dict:
    """One ``spdepth`` command cold, interpreter start to exit."""
    with tempfile.TemporaryDirectory(prefix="spdepth-cold-cache-") as cache:
        t0, c0 = time.perf_counter(), _children_cpu_s()
        out = subprocess.run([sys.executable, "-m", "spdepth.acq.cli", *argv], env=_env(pkgdir, cache),
                             capture_output=True, text=True, cwd=cwd)
        wall, cpu = time.perf_counter() - t0, _children_cpu_s() - c0
    if out.returncode != 0:
        return {"error": f"exit {out.returncode}: {out.stderr.strip()[-300:]}"}
    return {"wall_s": wall, "cpu_s": cpu}


def _in_temp(pkgdir: str | None, argv: list[str]) -> dict:
    with tempfile.TemporaryDirectory(prefix="spdepth-bench-compile-") as tmp:
        return _command(pkgdir, argv, tmp)


def _cell(r: dict | None) -> str:
    if r is None:
        return f"{'-':>15}"
    if "error" in r:
        return f"{'failed':>15}"
    return f"{r['wall_s']:6.1f} / {r['cpu_s']:5.1f}"


def bench(argv: list[str]) -> int:
    p = argparse.ArgumentParser(prog="spdepth bench compile", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--before", metavar="PKGDIR", help="also run the checkout found as spdepth in PKGDIR")
    p.add_argument("--only", help=f"comma-separated groups (default all: {', '.join(GROUPS)})")
    p.add_argument("--skip-commands", action="store_true", help="only the kernel groups, not the "
                   "cold demo and recon")
    a = p.parse_args(argv)
    groups = list(GROUPS) if not a.only else [g.strip() for g in a.only.split(",") if g.strip()]
    unknown = [g for g in groups if g not in GROUPS]
    if unknown:
        p.error(f"--only: unknown {', '.join(unknown)}; groups: {', '.join(GROUPS)}")
    sides = {"this checkout": None} if not a.before else {"before": a.before, "after": None}
    print("spdepth bench compile: each row cold, in a new process with an empty numba cache; "
          "wall / cpu seconds")
    print(f"load average before: {' '.join(f'{v:.2f}' for v in os.getloadavg())}")
    rows: dict[str, dict[str, dict]] = {}
    for g in groups:
        rows[g] = {label: _group(pkg, GROUPS[g][1]) for label, pkg in sides.items()}
    if not a.skip_commands:
        # each side in a folder of its own: the demo writes its sheet (spdepth-demo.png) there
        rows["spdepth demo --no-window"] = {label: _in_temp(pkg, ["demo", "--no-window"])
                                            for label, pkg in sides.items()}
        if FACE.is_file():
            recon = ["recon", str(FACE), *SEED_SETTINGS]
            rows["spdepth recon mannequin"] = {label: _in_temp(pkg, recon) for label, pkg in sides.items()}
        else:
            print(f"(no {FACE}: the cold recon of the mannequin is left out)")
    print(f"{'':26}" + "".join(f"{label:>16}" for label in sides))
    for name, by_side in rows.items():
        line = f"{name:26}" + "".join(f" {_cell(by_side.get(label))}" for label in sides)
        errors = [f"{label}: {r['error']}" for label, r in by_side.items() if "error" in r]
        print(line + (f"   ({'; '.join(errors)})" if errors else ""))
    print(f"load average after: {' '.join(f'{v:.2f}' for v in os.getloadavg())}")
    return 0


if __name__ == "__main__":
    sys.exit(bench(sys.argv[1:]))
