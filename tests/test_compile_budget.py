"""What a first run after an install compiles: each kernel once, and kernels compiled in a second
process (recon.estimate.compile_apart) loaded here from numba's cache, not compiled again. Each
test runs a new interpreter with an empty numba cache (NUMBA_CACHE_DIR), as a fresh install has."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

pytestmark = pytest.mark.slow

#: every dispatcher of ours that compiled, with how many signatures, as one JSON line
_SIGNATURES = """
import gc, json
from numba.core.registry import CPUDispatcher
print(json.dumps({f"{o.py_func.__module__}.{o.py_func.__name__}": len(o.overloads) for o in gc.get_objects()
                  if isinstance(o, CPUDispatcher) and o.py_func.__module__.startswith("spdepth.")
                  and len(o.overloads)}))
"""


#: from here on, each compile that starts in the process: "module.name" into ``compiled``
_COUNTING = """
from numba.core import event
compiled = []

class Count(event.Listener):
    def on_start(self, ev):
        f = ev.data["dispatcher"].py_func
        compiled.append(f.__module__ + "." + f.__name__)

    def on_end(self, ev):
        return None     # numba's Listener needs it; only the starts are counted

event.register("numba:compile", Count())
"""


def _cold(code: str, tmp_path) -> dict:
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path / "numba-cache"))
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr[-2000:]
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_estimator_kernels_compile_one_signature_each(tmp_path):
    # a literal argument (a 0 passed, a loop variable before numba unifies its type) compiles a
    # callee and all it calls a second time for Literal[int](0): seconds each on a cold cache
    sigs = _cold("from spdepth.recon.estimate import warm_up\n"
                 "from spdepth.recon.model import ReconSettings\n"
                 "for m in ('lmf', 'uos'):\n"
                 "    warm_up(ReconSettings(method=m, max_photons=15), decide=False)\n" + _SIGNATURES, tmp_path)
    ours = {k: n for k, n in sigs.items() if k.startswith(("spdepth.recon.kernels", "spdepth.recon.estimators"))}
    assert "spdepth.recon.estimators.uos_kernels._iterate" in ours      # the nested helpers compiled here
    assert {k: n for k, n in ours.items() if n != 1} == {}


def test_kernels_compiled_apart_load_from_the_cache(tmp_path):
    got = _cold("""
import json
from spdepth.recon.estimate import compile_apart, warm_up
from spdepth.recon.model import ReconSettings

settings = [ReconSettings(method="lmf", max_photons=15)]
child = compile_apart(settings)
started = child is not None
code = child.wait() if started else None
again = compile_apart(settings)          # cached now: nothing to start
""" + _COUNTING + """warm_up(settings[0], decide=False)
print(json.dumps({"started": started, "code": code, "again": again is None, "compiled": compiled}))
""", tmp_path)
    assert got["started"] and got["code"] == 0 and got["again"]
    assert got["compiled"] == []                  # every lmf kernel came from the child's cache


def test_the_return_test_compiled_apart_loads_here_while_the_estimator_compiles_here(tmp_path):
    # spdepth recon's first run: the return test's kernels (most of its compile) in a second
    # process, the estimator's here, then those of the test the child has not claimed; the
    # reconstruction waits for the child, then loads the rest
    got = _cold("""
import json
from spdepth.recon.estimate import compile_apart, kernels_cached, warm_up
from spdepth.recon.model import ReconSettings

s = ReconSettings(method="lmf", max_photons=15)
cold = not kernels_cached(s, decide=True)
child = compile_apart([s], decide=True, estimator=False)
""" + _COUNTING + """warm_up(s)
print(json.dumps({"cold": cold, "started": child is not None, "code": child.wait() if child else None,
                  "compiled": compiled, "cached": kernels_cached(s, decide=True)}))
""", tmp_path)
    assert got["cold"] and got["started"] and got["code"] == 0 and got["cached"]
    ours = [c for c in got["compiled"] if c.startswith("spdepth.")]
    assert "spdepth.recon.estimators.lmf_kernels._lmf_pixels" in ours          # the estimator compiled here
    # the child takes the test's kernels in order and this process, its estimator's done, the test
    # itself first (claimed while the child compiles ml's search, the largest: lmf's own compile
    # is a third of it), then the rest from the end: of those, what it compiled is a tail of the
    # order, and ml's search (the child's first) is not among them
    order = ["search_kernel", "detect_kernel", "dispersion_kernel", "neighbour_gain_kernel", "neighbour_region_kernel",
             "region_ml_kernel"]
    here = [k for k in order if "spdepth.recon.detect." + k in ours]
    assert "detect_kernel" in here
    rest = [k for k in here if k != "detect_kernel"]
    assert rest == order[len(order) - len(rest):]
    assert "search_kernel" not in here and "spdepth.recon.estimators.ml_kernels.integer_optimum" not in ours


def test_a_first_run_without_spreads_compiles_no_kernel_of_theirs(tmp_path):
    # spdepth recon without an output file (its summary holds no uncertainty) reconstructs without
    # the test's spreads: neither process compiles their kernel (most of the test's compile beside
    # ml's search), the decision compiles the rest, and a later run that needs them sees them cold
    got = _cold("""
import json
import numpy as np
from spdepth.recon.estimate import compile_apart, kernels_cached, reconstruct, warm_up
from spdepth.recon.model import Binning, ReconSettings
from spdepth.recon.photons import PhotonStore

s = ReconSettings(method="lmf", max_photons=15)
child = compile_apart([s], decide=True, estimator=False, spreads=False)
""" + _COUNTING + """warm_up(s, spreads=False)
rng = np.random.default_rng(0)
lists = [np.floor(np.concatenate([30 + 2 * rng.standard_normal(8), rng.uniform(0, 64, 4)])) for _ in range(16)]
b = Binning(1e-12, 0.0, 64.0, 1.0)
maps = reconstruct(PhotonStore.from_lists(lists, (4, 4), 1e-12), ReconSettings(method="lmf", binning=b,
                   pulse_rms_s=2e-12, max_photons=15), spreads=False)
print(json.dumps({"code": child.wait() if child else None, "compiled": compiled,
                  "depths": int(np.isfinite(maps.depth_m).sum()),
                  "lean": kernels_cached(s, decide=True, spreads=False),
                  "full": kernels_cached(s, decide=True)}))
""", tmp_path)
    assert got["code"] == 0 and got["depths"] > 0
    assert "spdepth.recon.detect.detect_kernel" not in got["compiled"]
    assert "spdepth.recon.estimators.lmf_kernels._lmf_pixels" in got["compiled"]
    assert got["lean"] and not got["full"]          # nor did the child: its kernel is still cold


def test_a_first_run_compiles_the_tests_search_only_for_estimators_that_do_not_give_its_gains():
    # ml's maps carry the test's statistic (gain_nats), which the test takes: its search never runs
    # after ml, so a first run of ml does not compile it; uos gives none, and the test searches
    import numpy as np

    from spdepth.recon.estimate import _test_steps
    from spdepth.recon.model import Binning, ReconSettings
    from spdepth.recon.photons import PhotonStore

    b = Binning(1e-12, 0.0, 64.0, 1.0)
    one = PhotonStore(np.array([30.0, 31.0, 32.0, 33.0]), np.array([0, 4]), (1, 1), b.time_unit_s)
    names = {m: [n for n, _ in _test_steps(one, ReconSettings(method=m, binning=b, pulse_rms_s=3e-12))]
             for m in ("ml", "uos")}
    assert names["uos"] == ["search", "test", "support", "regions", "region fit"]
    # ml's maps with the test's spreads measure the pulse model's dispersion from the likelihood's
    # terms (uos's from its matched filter's, with its own kernel)
    assert names["ml"] == ["test", "dispersion", "support", "regions", "region fit"]
    lean = [n for n, _ in _test_steps(one, ReconSettings(method="uos", binning=b, pulse_rms_s=3e-12), spreads=False)]
    assert lean == ["search", "support", "regions", "region fit"]
