"""``spdepth demo`` end to end (simulated instruments through the real drivers), and its errors."""

from __future__ import annotations

import re

import numpy as np
import pytest

from spdepth.acq.cli import main
from spdepth.acq.requests import DEFAULT_METHOD
from spdepth.recon.photons import PhotonStore


def _mae(out: str, method: str) -> float:
    return float(re.search(rf"^{method}\s+([0-9.]+)", out, re.M).group(1))


def test_demo_scans_reconstructs_and_writes_png(tmp_path, capsys):
    png = tmp_path / "demo.png"
    assert main(["demo", "--no-window", "--size", "24x20", "--method", "ml", "--png", str(png)]) == 0
    out = capsys.readouterr().out
    assert "scanned bust 24x20 through the drivers" in out
    assert "live ml maps equal the batch reconstruction of the final store" in out
    assert png.stat().st_size > 20_000
    # the paper's ordering holds even on a small image: ml <= uos < lmf
    assert _mae(out, "ml") <= _mae(out, "uos") * 1.05 < _mae(out, "lmf")


def test_demo_with_faults_reports_them_and_reacquires(tmp_path, capsys):
    png = tmp_path / "demo.png"
    code = main(["demo", "--no-window", "--size", "16x16", "--compare", DEFAULT_METHOD,
                 "--faults", "serial-unplug@0.2s,fifo-overflow@50%", "--png", str(png)])
    assert code == 0
    out = capsys.readouterr().out
    assert "galvo reconnects: 1" in out
    assert "lost spans in the tag stream: 1, re-acquired in later passes" in out
    assert "in 2 passes" in out                       # the pixels after the hole were scanned again
    assert "flagged" not in out                       # ... and all of them completed
    assert f"live {DEFAULT_METHOD} maps equal the batch reconstruction" in out   # the default live estimator


def test_demo_refuses_bad_options(tmp_path, capsys):
    png = str(tmp_path / "x.png")
    assert main(["demo", "--no-window", "--faults", "bogus@1s", "--png", png]) == 2
    assert "unknown kind 'bogus'" in capsys.readouterr().err
    # argparse-level: same one line, exit 2; the target has one name and one rule in every command
    assert main(["demo", "--no-window", "--target", "0", "--png", png]) == 2
    err = capsys.readouterr().err
    assert "--target: must be a whole number >= 1, got 0" in err and err.count("\n") == 1
    assert main(["demo", "--no-window", "--compare", "uos,magic", "--png", png]) == 2
    assert "--compare: unknown magic" in capsys.readouterr().err
    assert main(["demo", "--no-window", "--png", "/nonexistent/x.png"]) == 2
    assert "folder /nonexistent does not exist" in capsys.readouterr().err
    # --out is the run folder in every command; the old spellings say what to write now
    assert main(["demo", "--no-window", "--out", png]) == 2
    assert "the PNG sheet is --png FILE" in capsys.readouterr().err
    assert main(["demo", "--no-window", "--record", str(tmp_path / "run")]) == 2
    assert "--record is now --out DIR" in capsys.readouterr().err


def test_demo_takes_every_option_of_the_scan_it_runs(tmp_path, capsys):
    """The demo's scan is spdepth scan --sim's: surfaces, pulse, a vendor tagger's driver and
    --json included (the README says so), and --out keeps the run folder."""
    import json

    run = tmp_path / "run"
    assert main(["demo", "--no-window", "--size", "12x10", "--target", "8", "--reflectors", "2",
                 "--pulse-rms-ps", "360", "--tagger", "picoquant:mh150", "--compare", "ml",
                 "--json", "--out", str(run), "--png", str(tmp_path / "d.png")]) == 0
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert summary["state"] == "done" and summary["pixels"] == 120
    assert summary["out"] == str(run) and "ml" in summary["compare"]
    # scored on each pixel's strongest surface: a weak background "surface" before the bust
    # must not count as its depth (the nearest one did: 38x the oracle)
    assert summary["compare"]["ml"]["mae_cm"] < 3 * summary["oracle_mae_cm"]
    saved = json.loads((run / "run.json").read_text())["info"]["request"]
    assert saved["reflectors"] == 2 and saved["pulse_rms_s"] == pytest.approx(360e-12)
    assert saved["instruments"]["tagger"] == "picoquant:mh150"


def test_without_pixels_empties_exactly_those_pixels():
    store = PhotonStore.from_lists([[1, 2], [3], [], [4, 5, 6]], (2, 2), 1e-12)
    cut = store.without_pixels([0, 3])
    np.testing.assert_array_equal(cut.counts(), [[0, 1], [0, 0]])
    np.testing.assert_array_equal(cut.times, [3])


def test_demo_scores_each_surface_against_its_own_truth(tmp_path, capsys):
    # two-layer: a pane at 2 m over the centre before a wall at ~3.5 m; scored against "every pixel
    # 2 m" the table said 73 cm and 46x the oracle
    png = tmp_path / "demo.png"
    assert main(["demo", "--no-window", "--scene", "two-layer", "--size", "16x16", "--compare", "ml",
                 "--png", str(png)]) == 0
    rows = [line.split() for line in capsys.readouterr().out.splitlines() if line.startswith("ml ")]
    assert [r[1] for r in rows] == ["1", "2"]
    for r in rows:
        assert float(r[2]) < 5.0 and float(r[3]) < 2.0          # MAE cm, x oracle
