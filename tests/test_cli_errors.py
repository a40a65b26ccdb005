"""The CLI maps every error family spdepth raises on purpose to one line and an exit status."""

from __future__ import annotations

from types import SimpleNamespace

import pytest

from spdepth.acq import cli
from spdepth.drivers.errors import DeviceTimeoutError, ProtocolError, SettingError
from spdepth.drivers.galvo import HardwareFaultError
from spdepth.drivers.galvo.errors import ErrorCode
from spdepth.recon.errors import InputError


@pytest.mark.parametrize("exc", [
    InputError("maps.mat: field 'x' is missing"),
    SettingError("scene 'nope': unknown scene"),
    DeviceTimeoutError("galvo: no reply"),
    ProtocolError("record 3: channel=70"),
    HardwareFaultError(ErrorCode.HARDWARE_FAULT, "servo fault"),
])
def test_every_error_family_is_one_line_and_exit_2(monkeypatch, capsys, exc):
    def run(args):
        raise exc
    fake = SimpleNamespace(HELP="raises", add_arguments=lambda parser: None, run=run)
    monkeypatch.setattr(cli, "_command_modules", lambda: iter([("fail", fake)]))
    assert cli.main(["fail"]) == cli.EXIT_USAGE == 2
    assert capsys.readouterr().err == f"spdepth fail: error: {exc}\n"


def test_other_exceptions_are_bugs_and_keep_their_traceback():
    assert cli.exit_code(RuntimeError("bug")) is None
    assert cli.exit_code(KeyError("x")) is None
