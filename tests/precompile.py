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

#: Fewer tests than this selected: no precompiling (a test file or two compiles what it needs).
MIN_TESTS = 300

_RECON = ("warm_up(ReconSettings(method={method!r}, binning=Binning(8e-12, 2000.0, 6000.0, 5.0), "
          "pulse_rms_s=360e-12, max_photons=15{extra}), decide={decide})\n")
_HEAD = ("from spdepth.recon.model import Binning, ReconSettings\n"
         "from spdepth.recon.estimate import warm_up\n")
#: (modules whose kernels the group compiles, its code); split so the two take about as long
#: (spdepth bench compile: the return test about 15 s, ml 4, K=2 8; lmf 5, uos 7, spatial 12,
#: the simulator 9)
GROUPS = (
    (("spdepth.recon.detect", "spdepth.recon.estimators.ml_kernels", "spdepth.recon.estimators.surfaces_kernels",
      "spdepth.drivers.tagger.t3", "spdepth.acq.assign"),
     _HEAD + _RECON.format(method="ml", extra="", decide=True)
     + _RECON.format(method="ml", extra=", reflectors=2", decide=False)
     + "from spdepth.drivers.tagger.t3 import warm_up as t3\nt3()\n"
     "import numpy as np\nfrom spdepth.drivers.events import EVENT_DTYPE\nfrom spdepth.acq.store import PixelStore\n"
     "ev = np.zeros(2, dtype=EVENT_DTYPE)\nev['kind'] = 255\nPixelStore((2, 2), 4, (0, 100), 1e-12).feed(ev)\n"),
    (("spdepth.recon.estimators.lmf_kernels", "spdepth.recon.estimators.uos_kernels",
      "spdepth.recon.estimators.spatial_kernels", "spdepth.drivers.sim.kernels", "spdepth.acq.readers.picoquant",
      "spdepth.recon.pair_kernels"),
     _HEAD + "".join(_RECON.format(method=m, extra="", decide=False) for m in ("lmf", "uos", "spatial"))
     + "from spdepth.drivers.sim import PhotonWorld, load_scene, warm_up as sim\nsim()\n"
     "PhotonWorld(load_scene('bust', (2, 2), ppp=2.0), seed=0).raster()\n"
     "from spdepth.acq.readers.picoquant import warm_up as reader\nreader()\n"
     "from spdepth.recon.irf import warm_up as pulse\npulse()\n"),
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
