"""The CLI maps every error family spdepth raises on purpose to one line and a documented exit status;
bad command lines get one line too, before any device is opened or folder made."""

from __future__ import annotations

from types import SimpleNamespace

import pytest

from spdepth.acq import cli
from spdepth.acq.errors import OutputError, RecordingError, RequestError, SessionStateError
from spdepth.drivers.errors import DeviceTimeoutError, ProtocolError, SettingError
from spdepth.drivers.galvo import HardwareFaultError
from spdepth.drivers.galvo.errors import ErrorCode
from spdepth.recon.errors import InputError


def _fake_command(monkeypatch, exc):
    def run(args):
        raise exc
    fake = SimpleNamespace(HELP="raises", add_arguments=lambda parser: None, run=run)
    monkeypatch.setattr(cli, "_command_modules", lambda: iter([("fail", fake)]))


@pytest.mark.parametrize("exc, code", [
    (InputError("maps.mat: field 'x' is missing"), 2),
    (RequestError("--target 0 must be a whole number >= 1"), 2),
    (RecordingError("rec.ptu: header tag SPDepth_Plan is damaged"), 2),
    (OutputError("--out x is in use by a running session"), 2),
    (SessionStateError("cannot pause a session that is done"), 2),
    (SettingError("scene 'nope': unknown scene"), 2),
    (DeviceTimeoutError("galvo: no reply"), 3),
    (ProtocolError("record 3: channel=70"), 3),
    (HardwareFaultError(ErrorCode.HARDWARE_FAULT, "servo fault"), 3),
])
def test_every_error_family_is_one_line_with_its_exit_status(monkeypatch, capsys, exc, code):
    _fake_command(monkeypatch, exc)
    assert cli.main(["fail"]) == code
    assert capsys.readouterr().err == f"spdepth fail: error: {exc}\n"


def test_other_exceptions_are_bugs_and_keep_their_traceback(monkeypatch):
    _fake_command(monkeypatch, RuntimeError("a bug"))
    with pytest.raises(RuntimeError, match="a bug"):
        cli.main(["fail"])


def test_sigterm_and_ctrl_c_are_interrupted(monkeypatch, capsys):
    _fake_command(monkeypatch, cli.Terminated())
    assert cli.main(["fail"]) == cli.EXIT_INTERRUPTED == 130
    assert capsys.readouterr().err == "spdepth fail: terminated\n"
    _fake_command(monkeypatch, KeyboardInterrupt())
    assert cli.main(["fail"]) == 130


BAD_COMMAND_LINES = [
    (["scan", "--sim", "--target", "100000000"], "--target 100000000: the galvo controller gates on at most 65535"),
    (["scan", "--sim", "--dwell-ms", "1", "--dwell-limit-ms", "5"], "give --dwell-limit-ms (gated) or --dwell-ms"),
    (["scan", "--sim", "--mode", "raster", "--dwell-limit-ms", "5"], "a raster scan takes --dwell-ms"),
    (["scan", "--sim", "--dwell-ms", "5"], "a gated scan takes --dwell-limit-ms"),
    (["scan", "--sim", "--bin-ps", "1e9"], "--bin-ps 1e+09 is wider than the window"),
    (["scan", "--sim", "--size", "10"], "argument --size: size must be WxH"),
    (["scan", "--sim", "--faults", "bogus@3s"], "unknown kind 'bogus'"),
    (["scan", "--galvo", "loop://"], "real devices need both --galvo"),
    (["scan", "--galvo", "loop://", "--tagger", "usb:1:2"], "--sync-rate-hz"),
    (["scan", "--sim", "--size", "4096x4096", "--target", "200", "--mode", "raster"], "more than the store holds"),
    (["replay", "/nonexistent/rec"], "recording /nonexistent/rec does not exist"),
    (["recon", "/nonexistent.ptu"], "/nonexistent.ptu: no such file"),
]


@pytest.mark.parametrize("argv, message", BAD_COMMAND_LINES)
def test_bad_command_lines_are_one_line_before_anything_is_made(tmp_path, capsys, argv, message):
    out = tmp_path / "out"
    extra = [] if argv[0] == "recon" else ["--out", str(out)]
    assert cli.main([*argv, *extra]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and message in err, err
    assert not out.exists()            # refused before any folder was made


def test_an_unwritable_output_is_refused_before_the_work(tmp_path, capsys, shared_data):
    mat = shared_data / "fpi" / "chart_depth.mat"
    assert cli.main(["recon", str(mat), "--time-unit-ps", "8", "--png", "/nonexistent/x.png"]) == 2
    err = capsys.readouterr().err
    assert err == "spdepth recon: error: --png /nonexistent/x.png: folder /nonexistent does not exist\n"


def test_version(capsys):
    assert cli.main(["--version"]) == 0
    assert capsys.readouterr().out.startswith("spdepth ")
