"""Every option declared once (``acq.params``): the parser, the requests' checks, the window's
controls and the README's table come from the declarations, and ``spdepth --help`` starts at once
(no numba, scipy, matplotlib or Qt imported to build the parser)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from spdepth.acq import params
from spdepth.acq.cli import build_parser, main
from spdepth.acq.errors import RequestError
from spdepth.acq.requests import (DEFAULT_BIN_S, DEFAULT_WINDOW_S, Devices, FileReconRequest,
                                  ReplayRequest, ScanRequest, SimBench, build_request)

ROOT = Path(__file__).resolve().parents[1]
HEAVY = ("numba", "numpy", "scipy", "matplotlib", "PySide6", "pyqtgraph", "shiboken6")


def _subcommands():
    parser = build_parser()
    sub = next(a for a in parser._actions if a.__class__.__name__ == "_SubParsersAction")
    return parser, sub.choices


def test_building_the_parser_imports_nothing_heavy():
    """Issue 33: ``spdepth --help`` took 0.7-1.1 s because building the parser imported numba
    (acq.requests -> drivers.picoquant -> drivers.tagger.t3). A fresh process builds every
    subcommand's parser and formats every --help (the estimator registry's names and summaries,
    the PicoQuant models) without loading numpy, numba, scipy or Qt."""
    code = ("import sys; from spdepth.acq.cli import build_parser; p = build_parser(); "
            f"built = [m for m in {HEAVY!r} if m in sys.modules]; "
            "sub = [a for a in p._actions if a.__class__.__name__ == '_SubParsersAction'][0]; "
            "[c.format_help() for c in sub.choices.values()]; p.format_help(); "
            f"print(built, [m for m in {HEAVY!r} if m in sys.modules])")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                         cwd=ROOT).stdout
    assert out.strip() == "[] []", out


def test_every_commands_help_and_the_version_import_nothing_heavy():
    """Issue 33: ``spdepth --help``, ``--version``, every subcommand's ``--help`` and every
    ``spdepth bench TARGET --help``, run through ``main`` as the console script runs them, in one
    fresh process: none loads numpy, numba, scipy, matplotlib or Qt (which take the start from
    about 0.1 s to most of a second; the benchmarks' took 0.4-0.8 s)."""
    from spdepth.acq.commands.bench import TARGETS

    names = sorted(_subcommands()[1])
    # every benchmark's own --help too (it imports the benchmark's module to build its parser)
    argvs = [["--help"], ["--version"]] + [[n, "--help"] for n in names] + \
        [["bench", t, "--help"] for t in sorted(TARGETS)]
    code = ("import contextlib, io, sys; from spdepth.acq.cli import main; out = io.StringIO(); "
            "rc = []\nwith contextlib.redirect_stdout(out):\n"
            f"    for argv in {argvs!r}:\n"
            "        rc.append(main(argv))\n"
            f"print(rc, [m for m in {HEAVY!r} if m in sys.modules], out.getvalue().count('usage: spdepth'))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                         cwd=ROOT).stdout
    assert out.strip() == f"{[0] * len(argvs)} [] {len(argvs) - 1}", out
    assert {"scan", "recon", "replay", "demo", "gui", "bench", "simulate"} <= set(names)
    assert {"recon", "startup", "compile", "halves"} <= set(TARGETS)


@pytest.mark.parametrize("given, after", [(None, "0"), ("1", "1")])
def test_the_command_runs_numpy_without_huge_pages_unless_told(given, after):
    """Issue 33: ``spdepth`` sets NUMPY_MADVISE_HUGEPAGE=0 before numpy loads (first touches of
    huge pages cost a fresh recon of a 512x512 PTU 0.35-0.6 s of system time here), and leaves a
    value the user set; numpy, loaded after, follows it."""
    import os

    code = ("import os; from spdepth.acq.cli import main; main(['--version']); import numpy; "
            "from numpy._core import multiarray as m; on = m._set_madvise_hugepage(False); "
            "print(os.environ['NUMPY_MADVISE_HUGEPAGE'], int(on))")
    env = {k: v for k, v in os.environ.items() if k != "NUMPY_MADVISE_HUGEPAGE"}
    if given is not None:
        env["NUMPY_MADVISE_HUGEPAGE"] = given
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                         cwd=ROOT, env=env).stdout.splitlines()[-1].split()
    assert out == [after, after], out


@pytest.mark.parametrize("inner, status, said", [
    ("return orig(['recon', '/no/such/file.ptu'])", 2, "/no/such/file.ptu: no such file"),
    ("raise RuntimeError('a bug')", 1, "RuntimeError: a bug")])
def test_the_console_script_keeps_the_status_and_the_exit_handlers(inner, status, said):
    """Issue 33: the console script ends without the interpreter's teardown (which unloads the
    numba kernels: 0.7-1.3 s), and only that is skipped: main's exit status (1 for a bug, with
    its traceback), and the atexit handlers registered while the command ran, are kept."""
    code = ("import atexit\nfrom spdepth.acq import cli\norig = cli.main\n"
            "def main(argv=None):\n"
            "    atexit.register(lambda: print('handler ran', flush=True))\n"
            f"    {inner}\n"
            "cli.main = main\ncli.console_main()\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT)
    assert out.returncode == status, out.stderr
    assert out.stdout.strip() == "handler ran" and said in out.stderr


def test_every_command_option_is_declared_once():
    parser, commands = _subcommands()
    declared = {n for p in params.PARAMS.values() for n in (p.option, *p.aliases)} | \
        {a for c in params.COMMANDS for p in params.params_for(c) for a in p.aliases}
    own = {"simulate": {"--dwell-us", "--effects", "--jitter-ps", "--dead-time-ns",
                        "--afterpulse-prob", "--dark-rate-hz", "--pulse-rms-ps",
                        "--resolution-ps", "--period-ns"}}
    for name in ("scan", "replay", "demo", "gui", "recon", "simulate", "array"):
        for action in commands[name]._actions:
            for opt in action.option_strings:
                if opt in ("-h", "--help") or action.help == "==SUPPRESS==":
                    continue
                assert opt in declared or opt in own.get(name, ()), (name, opt)


def test_the_demo_and_the_window_take_every_option_of_the_scan_they_run():
    scan = {p.option for p in params.params_for("scan")}
    demo = {p.option for p in params.params_for("demo")}
    gui = {p.option for p in params.params_for("gui")}
    real_only = {p.option for p in params.params_for("scan")
                 if p.sources_of("scan") and set(p.sources_of("scan")) <= {"real"}}
    assert scan - {"--sim"} - real_only <= demo       # the demo is always the simulated bench
    assert scan - {"--json"} <= gui                  # the window prints no summary
    assert {p.option for p in params.params_for("replay")} - {"--json"} <= gui


def test_the_declared_lists_are_the_owners():
    """Names listed for --help (which must not load numba) are the registries' own."""
    from spdepth.drivers.galvo import protocol
    from spdepth.drivers.sim import scene_names
    from spdepth.drivers.sim.faults import FaultKind
    from spdepth.recon.model import MAX_REFLECTORS, METHODS, SEED_PAPER, ReconSettings

    assert params.method_names() == METHODS
    assert params.scene_names() == tuple(scene_names())
    help_text = params.expand(params.PARAMS["--faults"].help)
    assert all(k.value in help_text for k in FaultKind)      # the window's tooltip lacked one
    assert params.MAX_SURFACES == MAX_REFLECTORS
    assert params.MAX_PIXELS_PER_AXIS == protocol.MAX_PIXELS_PER_AXIS
    assert params.MIN_DWELL_MS == pytest.approx(protocol.MIN_DWELL_NS * 1e-6)
    assert params.MAX_DWELL_MS == pytest.approx(protocol.MAX_DWELL_NS * 1e-6)
    assert params.DEFAULT_TARGET == SEED_PAPER.max_photons
    assert DEFAULT_BIN_S == SEED_PAPER.binning.bin_width_s
    assert DEFAULT_WINDOW_S[1] == pytest.approx(SEED_PAPER.n_bins * SEED_PAPER.binning.bin_width_s)
    r = ReconSettings()
    assert (params.default("--max-reflectors"), params.default("--false-alarm")) == \
        (r.max_reflectors, r.false_alarm)


@pytest.mark.parametrize("source, cls", [("sim", SimBench), ("real", Devices), ("sim", ScanRequest),
                                         ("replay", ReplayRequest), ("file", FileReconRequest)])
def test_the_requests_defaults_are_the_declared_ones(source, cls):
    fields = cls.__dataclass_fields__
    for p in params.params_of(source):
        if p.field in fields and p.default is not None:
            assert fields[p.field].default == p.to_si(p.default), (cls.__name__, p.option)


def test_options_become_the_request_in_si():
    req = build_request("sim", {"pulse_rms_ps": 360.0, "dwell_limit_ms": 2.5, "window_ps": (0, 32000),
                                "settle_us": 5.0, "bin_ps": 20.0, "scene": "steps", "size": (8, 12)})
    assert req.pulse_rms_s == pytest.approx(360e-12) and req.dwell_limit_s == pytest.approx(2.5e-3)
    assert req.window_s == pytest.approx((0.0, 32e-9)) and req.settle_s == pytest.approx(5e-6)
    assert req.bin_s == pytest.approx(20e-12) and req.instruments.scene == "steps"
    assert req.size == (8, 12)
    with pytest.raises(RequestError, match="--scene is an option of the simulated bench"):
        build_request("real", {"scene": "steps", "galvo": "loop://", "tagger": "usb:1:2"})


@pytest.mark.parametrize("argv, message", [
    (["scan", "--sim", "--reflectors", "9"], "--reflectors: must be at most 8 or auto, got 9"),
    (["scan", "--sim", "--false-alarm", "1"], "--false-alarm: must be a probability between 0 and 1"),
    (["scan", "--sim", "--settle-us", "2e6"], "--settle-us: must be a number >= 0 and at most 1e+06"),
    (["gui", "--sim", "--size", "32"], "--size: size must be WxH"),
    (["simulate", "--scene", "bust", "--size", "0x3", "--ptu", "x.ptu"], "--size: 0x3: each side"),
    (["recon", "x.ptu", "--out", "m.npz"], "the maps file is --npz FILE.npz"),
    (["simulate", "--scene", "bust", "--out", "x.ptu"], "the PTU file is --ptu FILE.ptu"),
    (["demo", "--record", "d"], "--record is now --out DIR"),
    (["gui", "--file", "x.ptu", "--out", "d"], "a file reconstructed in the window writes nothing"),
])
def test_one_rule_per_option_in_every_command(argv, message, capsys):
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1, err


def test_gui_takes_surfaces_auto_as_scan_does():
    """``spdepth gui --sim --reflectors auto`` was refused ("not a whole number")."""
    from spdepth.acq.commands.gui import request_from_args
    from spdepth.gui.sources import Remembered

    _, commands = _subcommands()
    args = commands["gui"].parse_args(["--sim", "--reflectors", "auto", "--size", "8x6",
                                       "--time-limit-s", "5", "--pattern", "serp"])
    request, spec = request_from_args(args, Remembered())
    assert (request.reflectors, request.size, request.time_limit_s, request.pattern) == \
        ("auto", (6, 8), 5.0, "serp")
    assert spec.reflectors == "auto" and spec.size == (6, 8)


def test_a_saved_request_of_the_previous_version_still_loads():
    """run.json files written before the declarations (main at 6e2de66) read back typed."""
    from spdepth.acq.requests import request_from_dict

    old = [
        {"kind": "scan", "instruments": {"kind": "sim", "scene": "steps", "ppp": None, "sbr": 10.0,
                                         "seed": 0, "faults": "usb-timeout@50%", "tagger": "", "galvo": ""},
         "size": [12, 34], "target": 15, "mode": "gated", "dwell_limit_s": 0.002, "dwell_s": None,
         "pattern": "raster", "settle_s": 0.0, "max_passes": None, "time_limit_s": None,
         "window_s": None, "bin_s": 4e-11, "method": "ml", "pulse_rms_s": None,
         "reflectors": "auto", "max_reflectors": 3, "false_alarm": 0.001},
        {"kind": "scan", "instruments": {"kind": "devices", "galvo": "nidaq:Dev1",
                                         "tagger": "picoquant:mh150", "sync_rate_hz": 20000000.0,
                                         "fov_deg": 20.0, "deg_per_volt": 1.0, "v_limit": 10.0,
                                         "park_deg": [1.0, -2.0], "picoquant_lib": "", "event_divider": 1},
         "size": [64, 64], "target": 15, "mode": "gated", "dwell_limit_s": None, "dwell_s": None,
         "pattern": "raster", "settle_s": 0.0, "max_passes": None, "time_limit_s": None,
         "window_s": None, "bin_s": 4e-11, "method": "ml", "pulse_rms_s": None, "reflectors": 1,
         "max_reflectors": 3, "false_alarm": 0.001},
    ]
    a, b = (request_from_dict(json.loads(json.dumps(d))) for d in old)
    assert a.instruments.faults == "usb-timeout@50%" and a.size == (12, 34) and a.reflectors == "auto"
    assert b.instruments.park_deg == (1.0, -2.0) and b.instruments.tagger == "picoquant:mh150"
    assert a.to_dict() == old[0] and b.to_dict() == old[1]


def test_the_readme_option_table_is_the_generated_one():
    readme = (ROOT / "README.md").read_text()
    start, end = "<!-- option-table -->\n", "<!-- /option-table -->"
    table = readme[readme.index(start) + len(start):readme.index(end)].strip("\n") + "\n"
    assert table == params.option_table(), "README option table is stale: regenerate it with " \
        "acq.params.option_table()"


def test_the_window_controls_carry_their_declarations(qtbot):
    pytest.importorskip("pytestqt")
    from spdepth.gui.window import ControlPanel

    c = ControlPanel()
    qtbot.addWidget(c)
    assert c.fov.maximum() == params.PARAMS["--fov-deg"].high
    assert c.faults.toolTip() == params.expand(params.PARAMS["--faults"].help)
    assert "daq-underflow" in c.faults.toolTip()
    assert [c.method.itemText(i) for i in range(c.method.count())] == list(params.method_names())
    assert [c.scene.itemText(i) for i in range(c.scene.count())] == list(params.scene_names())
    assert [c.mode.itemText(i) for i in range(c.mode.count())] == list(params.MODES)
    assert c.reflectors.findData("auto") >= 0 and c.reflectors.findData(params.MAX_SURFACES) >= 0
    assert c.width_px.maximum() == params.MAX_PIXELS_PER_AXIS


def test_the_array_command_takes_its_options_from_the_declarations(capsys):
    """spdepth array's options are declared (acq.params): their ranges and choices are checked at
    parsing, one of --sim/--replay is required, and the defaults are the declared ones."""
    from spdepth.acq.cli import main

    parser, commands = _subcommands()
    args = commands["array"].parse_args(["--sim", "tilted-plane", "--out", "x"])
    assert (args.frames, args.counts, args.mode, args.method, args.size, args.sbr) == \
        (30, 20.0, "accumulate", "ml", (64, 64), 1.0)
    for argv, words in ((["--out", "x"], "one of the arguments --sim --replay is required"),
                        (["--sim", "bust", "--replay", "f.h5", "--out", "x"], "not allowed with"),
                        (["--sim", "bust", "--hot-share", "2", "--out", "x"], "--hot-share"),
                        (["--sim", "bust", "--mode", "gated", "--out", "x"], "frame, accumulate")):
        assert main(["array", *argv]) == 2
        assert words in capsys.readouterr().err


@pytest.mark.parametrize("before, after", [(700, 50_000), (200_000, 200_000), (0, 0)])
def test_the_console_script_collects_cycles_less_often_unless_told_otherwise(before, after):
    """Issue 33: the console script raises the collector's first threshold (a warm 512x512 recon ran
    321 collections as its kernels loaded); one set higher, or 0 (collection off), stands, and
    the other two thresholds are kept."""
    code = ("import gc\nfrom spdepth.acq import cli\n"
            f"gc.set_threshold({before}, 7, 9)\n"
            "cli.main = lambda argv=None: print(*gc.get_threshold(), flush=True) or 0\n"
            "cli.console_main()\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, check=True)
    assert out.stdout.split() == [str(after), "7", "9"], out.stderr


def test_reading_a_file_loads_no_device_driver():
    """Issue 33: every spdepth recon imported the galvo's and the tagger's devices, their serial
    and USB transports and pyserial (acq.requests reads the galvo protocol's MAX_N_TARGET, the PTU
    reader the tagger's t3): their packages now load those on first use."""
    code = ("import sys\nimport spdepth.acq.api, spdepth.acq.readers.picoquant, spdepth.acq.commands.recon\n"
            "print([m for m in sys.modules if m.split('.')[0] in ('serial', 'usb') or "
            "m.startswith(('spdepth.drivers.galvo.', 'spdepth.drivers.tagger.')) and m.rsplit('.', 1)[1] in "
            "('device', 'transport', 'reader')])\n"
            "from spdepth.drivers.galvo import Galvo, SerialTransport\nfrom spdepth.drivers.tagger import Tagger\n"
            "print(Galvo.__module__, SerialTransport.__module__, Tagger.__module__)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                         cwd=ROOT).stdout.splitlines()
    assert out == ["[]", "spdepth.drivers.galvo.device spdepth.drivers.galvo.transport spdepth.drivers.tagger.device"]
