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
    assert main(["simulate", "--scene", "bust", "--size", "8x8", "--out", str(path)]) == 0
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
    assert any("--max-photons" in n for n in more["notes"])


def test_a_file_summary_says_what_the_window_and_limit_left_out(tmp_path):
    path = tmp_path / "b.ptu"
    assert main(["simulate", "--scene", "bust", "--size", "8x8", "--out", str(path)]) == 0
    s = reconstruct_file(FileReconRequest(input=str(path), max_photons=5)).summary
    line = next(n for n in s["notes"] if "detections in the file" in n)
    assert f"{s['photons_in_file']} detections in the file, {s['photons']} used" in line
    assert "beyond the first 5 per pixel (--max-photons)" in line
