"""Requests: validated as a whole when made (each bad value named with its CLI option), saved with
every result and read back typed."""

from __future__ import annotations

import json

import pytest

from spdepth.acq.api import build_session, open_instruments, recorded_request
from spdepth.acq.errors import RequestError
from spdepth.acq.requests import (DEFAULT_METHOD, DEFAULT_SIZE, DEFAULT_TARGET, Devices, FileReconRequest,
                                  ReplayRequest, ScanRequest, SimBench, request_from_dict)


def test_every_request_round_trips_through_json(tmp_path):
    f = tmp_path / "x.ptu"
    f.write_bytes(b"x")
    (tmp_path / "rec").mkdir()
    (tmp_path / "rec" / "recording.ptu").write_bytes(b"x")
    for req in (ScanRequest(),
                ScanRequest(instruments=SimBench(scene="steps", ppp=3.0, faults="usb-timeout@50%"),
                            size=(12, 34), mode="raster", dwell_s=2e-3, window_s=(1e-9, 20e-9),
                            method="ml", pulse_rms_s=300e-12, time_limit_s=5.0),
                ScanRequest(instruments=Devices(galvo="/dev/ttyUSB0", tagger="usb:1209:7a64",
                                                sync_rate_hz=1e7, fov_deg=10.0)),
                ReplayRequest(recording=str(tmp_path / "rec"), target=5, speed=1.0),
                FileReconRequest(input=str(f), window_s=(0.0, 32e-9), bin_s=40e-12, max_photons=15)):
        back = request_from_dict(json.loads(json.dumps(req.to_dict())))
        assert back == req and type(back) is type(req)


def test_one_vocabulary_of_defaults():
    r = ScanRequest()
    assert (r.size, r.target, r.method) == (DEFAULT_SIZE, DEFAULT_TARGET, DEFAULT_METHOD)


@pytest.mark.parametrize("kw, message", [
    (dict(target=0), "--target must be a whole number >= 1"),
    (dict(target=2.5), "--target must be a whole number >= 1"),
    (dict(size=(0, 4)), "--size 4x0"),
    (dict(mode="spiral"), "--mode must be one of gated, raster"),
    (dict(method="magic"), "--method must be one of"),
    (dict(window_s=(5e-9, 1e-9)), "--window-ps needs 0 <= START < STOP"),
    (dict(bin_s=-1.0), "--bin-ps must be a positive number"),
    (dict(window_s=(0, 1e-9), bin_s=2e-9), "--bin-ps 2000 is wider than the window"),
    (dict(settle_s=-1e-6), "--settle-us"),
    (dict(time_limit_s=0), "--time-limit-s"),
    (dict(dwell_limit_s=20.0), "the galvo controller holds a pixel"),
    (dict(instruments="nope"), "instruments must be SimBench or Devices"),
])
def test_a_bad_scan_request_names_the_option_and_value(kw, message):
    with pytest.raises(RequestError, match=message.replace("(", r"\(").replace(")", r"\)")):
        ScanRequest(**kw)


def test_real_devices_need_their_ports_and_rate():
    with pytest.raises(RequestError, match="--sync-rate-hz"):
        Devices(galvo="/dev/ttyUSB0", tagger="usb:1:2")
    with pytest.raises(RequestError, match="--fov-deg 120"):
        Devices(galvo="/dev/ttyUSB0", tagger="usb:1:2", sync_rate_hz=1e7, fov_deg=120)


def test_a_damaged_saved_request_is_refused():
    with pytest.raises(RequestError, match="unknown field"):
        ScanRequest.from_dict({"kind": "scan", "colour": "red"})
    with pytest.raises(RequestError, match="not a saved request"):
        request_from_dict({"kind": "lunch"})
    with pytest.raises(RequestError, match="not a replay request"):
        ReplayRequest.from_dict(ScanRequest().to_dict())


def test_a_session_saves_its_request_in_run_json_and_the_recording(tmp_path):
    req = ScanRequest(size=(6, 5), target=4, instruments=SimBench(seed=3))
    out = tmp_path / "run"
    with open_instruments(req) as inst:
        session = build_session(req, out, inst)
        # the recording's header holds it from the first record on (a killed run keeps it)
        assert session.run() == session.state and session.state.value == "done"
    assert recorded_request(out) == req
    (out / "run.json").unlink()
    assert recorded_request(out / "recording.ptu") == req
    replay = ReplayRequest(recording=str(out), target=2)
    r = build_session(replay, tmp_path / "again")
    r.run()
    assert recorded_request(tmp_path / "again" / "run.json") == replay


def test_run_json_is_read_in_one_place(tmp_path):
    """``read_run_record``: None without run.json, the record with one, and a damaged one named."""
    from spdepth.acq.api import read_run_record
    from spdepth.acq.errors import RecordingError

    assert read_run_record(tmp_path) is None
    (tmp_path / "run.json").write_text(json.dumps({"state": "done", "plan": {}}))
    assert read_run_record(tmp_path)["state"] == "done"
    assert read_run_record(tmp_path / "recording.ptu")["state"] == "done"   # a file in the folder
    for damaged in ("{", "[1, 2]"):
        (tmp_path / "run.json").write_text(damaged)
        with pytest.raises(RecordingError, match="run.json"):
            read_run_record(tmp_path)
        with pytest.raises(RecordingError, match="run.json"):
            recorded_request(tmp_path)
