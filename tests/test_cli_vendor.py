"""The vendor backends from the command line: ``spdepth scan --sim --tagger picoquant:mh150 --galvo
nidaq:Dev1`` on the stand-ins records a PTU that ptufile opens and replays identically; real
vendor devices that are not there are one line and exit 3 with no folder left; ``spdepth devices``
with nothing attached exits 0; device strings are parsed in one place."""

from __future__ import annotations

import json

import numpy as np
import ptufile
import pytest

from spdepth.acq.cli import main
from spdepth.acq.errors import RequestError
from spdepth.acq.requests import Devices, ScanRequest, SimBench, parse_galvo, parse_tagger
from spdepth.recon.maps import DepthMaps


def _last_json(out: str) -> dict:
    return json.loads(out.strip().splitlines()[-1])


def test_scan_on_picoquant_and_nidaq_standins_records_a_ptu_that_replays_identically(tmp_path, capsys):
    out = tmp_path / "scan"
    argv = ["scan", "--sim", "--tagger", "picoquant:mh150", "--galvo", "nidaq:Dev1",
            "--mode", "raster", "--size", "12x10", "--target", "8", "--faults",
            "fifo-overflow@40%", "--out", str(out), "--json"]
    assert main(argv) == 0
    live = _last_json(capsys.readouterr().out)
    assert live["state"] == "done" and live["flagged"] == 0 and live["lost_spans"] == 1
    with ptufile.PtuFile(out / "recording.ptu") as f:
        assert f.tags["TTResultFormat_TTTRRecType"] == ptufile.PtuRecordType.GenericT3
        assert f.shape[1:3] == (10, 12)
    assert main(["replay", str(out), "--out", str(tmp_path / "rep"), "--json"]) == 0
    rep = _last_json(capsys.readouterr().out)
    assert rep["state"] == "done" and rep["lost_spans"] == live["lost_spans"]
    a, b = DepthMaps.load_npz(out / "maps.npz"), DepthMaps.load_npz(tmp_path / "rep" / "maps.npz")
    for k in ("depth_m", "photons", "background", "signal"):
        np.testing.assert_array_equal(getattr(a, k), getattr(b, k), err_msg=k)
    run = json.loads((out / "run.json").read_text())
    assert run["info"]["request"]["instruments"]["tagger"] == "picoquant:mh150"


@pytest.mark.parametrize("tagger,galvo,words", [
    ("picoquant:mh150", "nidaq:Dev1", "libmh150.so"),
    ("picoquant:hh400:1234", "/dev/ttyDOESNOTEXIST", None),
    ("picoquant:mh160", "nidaq:Dev1/ao0:1", "libmh150.so"),
    ("swabian", "nidaq:Dev1", "Swabian"),
])
def test_missing_vendor_library_or_device_is_one_line_exit_3_and_no_folder(
        tmp_path, capsys, monkeypatch, tagger, galvo, words):
    monkeypatch.delenv("SPDEPTH_PICOQUANT_LIB", raising=False)
    out = tmp_path / "never"
    code = main(["scan", "--tagger", tagger, "--galvo", galvo, "--sync-rate-hz", "20e6",
                 "--mode", "raster", "--size", "4x4", "--out", str(out)])
    err = capsys.readouterr().err.strip()
    assert code == 3, err
    assert len(err.splitlines()) == 1 and err.startswith("spdepth scan: error:")
    if words:
        assert words in err
    assert not out.exists()


def test_picoquant_library_given_by_path_that_does_not_exist_names_it(tmp_path, capsys):
    code = main(["scan", "--tagger", "picoquant:mh150", "--galvo", "nidaq:Dev1", "--sync-rate-hz",
                 "20e6", "--mode", "raster", "--picoquant-lib", str(tmp_path / "libmh150.so"),
                 "--out", str(tmp_path / "x")])
    err = capsys.readouterr().err
    assert code == 3 and str(tmp_path / "libmh150.so") in err and "snapi" in err


def test_devices_with_nothing_attached_exits_0(capsys):
    assert main(["devices"]) == 0
    text = capsys.readouterr().out
    assert text.strip()
    assert main(["devices", "--json"]) == 0
    d = json.loads(capsys.readouterr().out)
    assert set(d) == {"instruments", "missing"}
    for f in d["missing"]:
        assert f["install"] and f["missing"]


def test_devices_lists_standin_instruments():
    from spdepth.acq.discovery import find_instruments
    from spdepth.drivers.sim import PhotonWorld, load_scene
    from spdepth.drivers.sim.nidaqmx_standin import NiDaqmxStandIn
    from spdepth.drivers.sim.picoquant_standin import PicoQuantStandIn, build_library
    from spdepth.drivers.sim.rig import SimRig

    rig = SimRig(PhotonWorld(load_scene("steps", (4, 4)), seed=0))
    sim = PicoQuantStandIn(rig, serial="7654321")
    try:
        libs = {"mh150": sim.path, **{k: build_library(k) for k in ("hh400", "th260", "ph330")}}
        found = find_instruments(serial=False, picoquant_libs=libs,
                                 nidaqmx=NiDaqmxStandIn(rig, "Dev3"), swabian=_NoTaggers())
    finally:
        sim.close()
    devices = [f.device for f in found if not f.missing]
    assert "picoquant:mh150:7654321" in devices and "nidaq:Dev3" in devices
    # every family's library was found (no device on the others): none is reported missing
    assert not [f for f in found if f.kind == "picoquant" and f.missing]


class _NoTaggers:
    @staticmethod
    def scanTimeTagger():
        return ()


@pytest.mark.parametrize("parse,text,kind,fields", [
    (parse_tagger, "picoquant:mh150", "picoquant", {"model": "mh150", "serial": ""}),
    (parse_tagger, "picoquant:MH150:01234567", "picoquant", {"model": "mh150", "serial": "01234567"}),
    (parse_tagger, "swabian", "swabian", {"serial": ""}),
    (parse_tagger, "swabian:1910000ABC", "swabian", {"serial": "1910000ABC"}),
    (parse_tagger, "usb:1209:7a64", "usb", {"vid": 0x1209, "pid": 0x7A64}),
    (parse_galvo, "nidaq:Dev1", "nidaq", {"device": "Dev1", "ao": "ao0:1"}),
    (parse_galvo, "nidaq:PXI1Slot2/ao2:3", "nidaq", {"device": "PXI1Slot2", "ao": "ao2:3"}),
    (parse_galvo, "/dev/ttyACM0", "serial", {"port": "/dev/ttyACM0"}),
    (parse_galvo, "galvosim://x", "serial", {"port": "galvosim://x"}),
])
def test_device_strings(parse, text, kind, fields):
    d = parse(text)
    assert d.kind == kind
    for k, v in fields.items():
        assert getattr(d, k) == v


@pytest.mark.parametrize("tagger,galvo,message", [
    ("picoquant:hh500", "nidaq:Dev1", "not supported yet"),
    ("picoquant:xx9", "nidaq:Dev1", "unknown PicoQuant device"),
    ("picoquant:mh150:bad serial!", "nidaq:Dev1", "serial"),
    ("picoquant", "nidaq:Dev1", "picoquant:MODEL"),
    ("usb:zz:1", "nidaq:Dev1", "VID:PID"),
    ("hydra", "nidaq:Dev1", "--tagger must be"),
    ("picoquant:mh150", "nidaq:Dev1/ao0:2", "adjacent"),
    ("picoquant:mh150", "nidaq:/ao0:1", "nidaq:DEV"),
    ("picoquant:mh150", "usb:1209:7a64", "names a time tagger"),
])
def test_bad_device_strings_are_request_errors(tagger, galvo, message):
    with pytest.raises(RequestError, match=message):
        Devices(galvo=galvo, tagger=tagger, sync_rate_hz=20e6)


def test_nidaq_galvo_requests_within_its_voltage_limits():
    assert ScanRequest(instruments=SimBench(galvo="nidaq:Dev1")).mode == "gated"
    with pytest.raises(RequestError, match="--settle-us"):
        ScanRequest(instruments=SimBench(galvo="nidaq:Dev1"), settle_s=1e-5)
    with pytest.raises(RequestError, match="--v-limit"):
        Devices(galvo="nidaq:Dev1", tagger="picoquant:mh150", sync_rate_hz=20e6, fov_deg=30,
                deg_per_volt=1.0, v_limit=5)
    d = Devices(galvo="nidaq:Dev1", tagger="picoquant:mh150", sync_rate_hz=20e6, park_deg=[1, 2])
    assert Devices.from_dict(d.to_dict()) == d


def test_bad_command_line_device_string_is_exit_2(tmp_path, capsys):
    assert main(["scan", "--tagger", "picoquant:zz", "--galvo", "nidaq:Dev1", "--sync-rate-hz",
                 "1e7", "--out", str(tmp_path / "o")]) == 2
    assert "unknown PicoQuant device" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_a_swabian_tagger_not_there_is_a_device_error_naming_it():
    from spdepth.drivers.errors import DeviceError
    from spdepth.drivers.sim import PhotonWorld, load_scene
    from spdepth.drivers.sim.rig import SimRig
    from spdepth.drivers.sim.swabian_standin import SwabianStandIn
    from spdepth.drivers.swabian import SwabianTagger

    module = SwabianStandIn(SimRig(PhotonWorld(load_scene("steps", (2, 2)), seed=0)), "111")
    with pytest.raises(DeviceError, match="Swabian Time Tagger 222 not found"):
        SwabianTagger.open("222", module=module)


def test_nidaq_without_ni_driver_is_a_device_error_naming_it():
    from spdepth.drivers.daq import DaqGalvo
    from spdepth.drivers.errors import DeviceError

    with pytest.raises(DeviceError, match="NI-DAQmx"):
        DaqGalvo.open("Dev1")
