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
    assert main(["demo", "--no-window", "--size", "24x20", "--method", "ml", "--out", str(png)]) == 0
    out = capsys.readouterr().out
    assert "scanned bust 24x20 through the drivers" in out
    assert "live ml maps equal the batch reconstruction of the final store" in out
    assert png.stat().st_size > 20_000
    # the paper's ordering holds even on a small image: ml <= uos < lmf
    assert _mae(out, "ml") <= _mae(out, "uos") * 1.05 < _mae(out, "lmf")


def test_demo_with_faults_reports_them_and_reacquires(tmp_path, capsys):
    png = tmp_path / "demo.png"
    code = main(["demo", "--no-window", "--size", "16x16", "--compare", DEFAULT_METHOD,
                 "--faults", "serial-unplug@0.2s,fifo-overflow@50%", "--out", str(png)])
    assert code == 0
    out = capsys.readouterr().out
    assert "galvo reconnects: 1" in out
    assert "lost spans in the tag stream: 1, re-acquired in later passes" in out
    assert "in 2 passes" in out                       # the pixels after the hole were scanned again
    assert "flagged" not in out                       # ... and all of them completed
    assert f"live {DEFAULT_METHOD} maps equal the batch reconstruction" in out   # the default live estimator


def test_demo_refuses_bad_options(tmp_path, capsys):
    assert main(["demo", "--no-window", "--faults", "bogus@1s", "--out", str(tmp_path / "x.png")]) == 2
    assert "unknown kind 'bogus'" in capsys.readouterr().err
    # argparse-level: same one line, exit 2; the target has one name in every command
    assert main(["demo", "--no-window", "--target", "0", "--out", str(tmp_path / "x.png")]) == 2
    err = capsys.readouterr().err
    assert "--target: must be at least 1" in err and err.count("\n") == 1
    assert main(["demo", "--no-window", "--compare", "uos,magic", "--out", str(tmp_path / "x.png")]) == 2
    assert "--compare: unknown magic" in capsys.readouterr().err
    assert main(["demo", "--no-window", "--out", "/nonexistent/x.png"]) == 2
    assert "folder /nonexistent does not exist" in capsys.readouterr().err


def test_without_pixels_empties_exactly_those_pixels():
    store = PhotonStore.from_lists([[1, 2], [3], [], [4, 5, 6]], (2, 2), 1e-12)
    cut = store.without_pixels([0, 3])
    np.testing.assert_array_equal(cut.counts(), [[0, 1], [0, 0]])
    np.testing.assert_array_equal(cut.times, [3])
