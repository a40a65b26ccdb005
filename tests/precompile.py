"""The suite's first run on a cold numba cache (a clean clone, a CI run): the kernels the tests call
compiled in two processes at once before the first test, instead of one at a time in the tests'
process as each test first calls them. Numba compiles one function at a time in a process, so a
second process is what puts the second core to compiling; the tests then load every kernel from
the cache (a kernel another process put there loads on its first call here). Each group runs
library entry points on tiny inputs, as ``spdepth bench compile``'s groups do; the return test's
kernels (most of every estimator's compile) are compiled once, in the first group. A warm cache
starts nothing. Only a run of many tests pays the wait: a single file compiles what it calls."""

from __future__ import annotations

import subprocess
import sys
import time

from spdepth.acq.commands.bench.compile import GROUPS as BENCH_GROUPS, recon_group

#: Fewer tests than this selected: no precompiling (a test file or two compiles what it needs).
MIN_TESTS = 300

#: (modules whose kernels the group compiles, its code), from ``spdepth bench compile``'s groups,
#: split so the two take about as long (there, cold: the return test about 15 s, ml 4, K=2 8; lmf
#: 5, uos 7, spatial 12, the simulator 9); the return test only in the first
GROUPS = (
    (("spdepth.recon.detect", "spdepth.recon.estimators.ml_kernels", "spdepth.recon.estimators.surfaces_kernels",
      "spdepth.drivers.tagger.t3", "spdepth.acq.assign"),
     recon_group("ml") + recon_group("ml", ", reflectors=2", decide=False)
     + BENCH_GROUPS["t3 decode/encode"][1] + BENCH_GROUPS["store feed"][1]),
    (("spdepth.recon.estimators.lmf_kernels", "spdepth.recon.estimators.uos_kernels",
      "spdepth.recon.estimators.spatial_kernels", "spdepth.drivers.sim.kernels", "spdepth.acq.readers.picoquant",
      "spdepth.recon.pair_kernels"),
     "".join(recon_group(m, decide=False) for m in ("lmf", "uos", "spatial"))
     + BENCH_GROUPS["sim dwell_run"][1] + BENCH_GROUPS["sim raster"][1]
     + "from spdepth.acq.readers.picoquant import warm_up\nwarm_up()\n"
     "from spdepth.recon.irf import warm_up\nwarm_up()\n"),
)


def cold_groups() -> list[str]:
    """The code of each group some of whose kernels are not in numba's cache."""
    from spdepth.recon.estimate import module_cached

    return [code for modules, code in GROUPS if not all(module_cached(m) for m in modules)]


def precompile(n_tests: int, say=print) -> None:
    """Compile the cold groups in a process each and wait for them (``say``: one line each way)."""
    todo = cold_groups() if n_tests >= MIN_TESTS else []
    if not todo:
        return
    say(f"numba's cache is cold: compiling the kernels in {len(todo)} processes at once first")
    t0 = time.perf_counter()
    children = [subprocess.Popen([sys.executable, "-c", code], stdin=subprocess.DEVNULL,
                                 stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True) for code in todo]
    failed = []
    for child in children:
        _, err = child.communicate()
        if child.returncode:
            failed.append(err.strip().splitlines()[-1] if err.strip() else f"exit {child.returncode}")
    # a group that failed only leaves its kernels to the tests that call them (and fail, if broken)
    say(f"compiled in {time.perf_counter() - t0:.0f} s" + (f"; failed: {'; '.join(failed)}" if failed else ""))
