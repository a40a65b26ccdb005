"""No silent override or loss: what a summary says about the file, what was used and why."""

from __future__ import annotations

import numpy as np
import pytest

from spdepth.acq.api import reconstruct_file
from spdepth.acq.cli import main
from spdepth.acq.readers import read_photons
from spdepth.acq.requests import FileReconRequest


@pytest.fixture(scope="module")
def raster_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("raster") / "run"
    assert main(["scan", "--sim", "--mode", "raster", "--size", "16x16", "--out", str(out)]) == 0
    return out


def test_a_header_resolution_is_never_overridden_silently(tmp_path):
    path = tmp_path / "b.ptu"
    assert main(["simulate", "--scene", "bust", "--size", "8x8", "--ptu", str(path)]) == 0
    plain = read_photons(path)
    given = read_photons(path, time_unit_s=1e-12)
    assert given.store.time_unit_s == plain.store.time_unit_s == 8e-12
    assert any("time unit 1 ps given, the header's resolution 8 ps used" in n for n in given.notes)
    a = reconstruct_file(FileReconRequest(input=str(path), time_unit_s=1e-12))
    b = reconstruct_file(FileReconRequest(input=str(path)))
    assert a.summary["depth_m_median"] == pytest.approx(b.summary["depth_m_median"])


def test_a_recording_summary_counts_the_file_and_max_photons_works(raster_run):
    rec = str(raster_run / "recording.ptu")
    res = reconstruct_file(FileReconRequest(input=rec))
    s = res.summary
    # a raster scan runs passes until every pixel holds its target (15): the file holds more
    assert s["photons_in_file"] > s["photons"] == 15 * 16 * 16
    line = next(n for n in s["notes"] if "detections in the file" in n)
    assert f"{s['photons_in_file']} detections in the file, {s['photons']} used" in line
    assert "the session's target" in line
    more = reconstruct_file(FileReconRequest(input=rec, max_photons=25)).summary
    assert more["photons"] > s["photons"]
    assert np.max(reconstruct_file(FileReconRequest(input=rec, max_photons=25)).maps.photons) == 25
    assert any("--target" in n for n in more["notes"])


def test_a_file_summary_says_what_the_window_and_limit_left_out(tmp_path):
    path = tmp_path / "b.ptu"
    assert main(["simulate", "--scene", "bust", "--size", "8x8", "--ptu", str(path)]) == 0
    s = reconstruct_file(FileReconRequest(input=str(path), max_photons=5)).summary
    line = next(n for n in s["notes"] if "detections in the file" in n)
    assert f"{s['photons_in_file']} detections in the file, {s['photons']} used" in line
    assert "outside the window or beyond the first 5 per pixel (--target)" in line


def test_a_run_that_completes_no_pixel_exits_1_naming_the_cause(tmp_path, capsys):
    assert main(["scan", "--sim", "--size", "8x8", "--window-ps", "0:1000", "--out", str(tmp_path / "w")]) == 1
    out = capsys.readouterr().out
    assert "no pixel completed" in out and "--window-ps" in out
    assert main(["scan", "--sim", "--size", "8x8", "--ppp", "0.01", "--out", str(tmp_path / "p")]) == 1
    assert "dwell reached its limit" in capsys.readouterr().out


@pytest.mark.parametrize("state", ["aborted", "failed"])
def test_a_replay_ends_as_the_recorded_session_ended(raster_run, tmp_path, capsys, state):
    import json
    import shutil

    run = tmp_path / "run"
    shutil.copytree(raster_run, run)
    lines = (run / "events.jsonl").read_text().splitlines()
    last = json.loads(lines[-1])
    assert last == {**last, "event": "state", "state": "done"}
    lines[-1] = json.dumps({**last, "state": state})
    (run / "events.jsonl").write_text("\n".join(lines) + "\n")
    rec = json.loads((run / "run.json").read_text())
    rec.update(state=state, error="DeviceError: tagger vanished" if state == "failed" else None)
    (run / "run.json").write_text(json.dumps(rec))
    assert main(["replay", str(run), "--out", str(tmp_path / "r")]) == 1
    out = capsys.readouterr().out
    assert out.startswith(f"replay: {state},")
    if state == "failed":
        assert "tagger vanished" in out


def test_one_definition_per_scene_and_physical_pulse_widths(tmp_path, capsys):
    import json

    out = tmp_path / "d"
    assert main(["scan", "--sim", "--scene", "daylight", "--size", "8x8", "--out", str(out)]) in (0, 1)
    run = json.loads((out / "run.json").read_text())
    assert "0.05" in json.dumps(run["info"])                # the scene's SBR, as simulate uses
    capsys.readouterr()
    for bad in ("1e9", "0.36"):
        assert main(["recon", str(out / "recording.ptu"), "--pulse-rms-ps", bad]) == 2
        err = capsys.readouterr().err
        assert "--pulse-rms-ps" in err and bad.replace("1e9", "1e+09") in err and "1 to 1e+06 ps" in err
