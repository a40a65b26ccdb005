"""``spdepth bench report --quick``: the files it writes, and figures that agree with the
reconstruction tests (tests/test_recon_accuracy.py, tests/test_evaluate.py) at the paper's point."""

from __future__ import annotations

import pytest

from spdepth.acq.commands.bench.report import CSV_FIELDS, QUICK_DETECTIONS, QUICK_SBRS
from spdepth.recon.model import METHODS


@pytest.mark.slow
def test_writes_report_csv_and_figures(quick_report):
    out, rows = quick_report
    for name in ("error_vs_detections.png", "error_vs_compute.png", "error_vs_sbr.png"):
        assert (out / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n", name
        assert (out / name).stat().st_size > 10_000
    text = (out / "report.md").read_text()
    for needle in ("spdepth bench report --quick", "Machine:", "Versions:", "numba",
                   "detections/s", "a miss", "error_vs_compute.png", "| bust | ml |"):
        assert needle in text, needle
    assert tuple(rows[0]) == CSV_FIELDS
    bust = [r for r in rows if r["scene"] == "bust"]
    assert len(bust) == len(QUICK_DETECTIONS) * len(QUICK_SBRS) * len(METHODS)
    k2 = [r for r in rows if r["scene"] == "two-layer"]
    assert {r["surface"] for r in k2} == {"0", "1"} and all(r["reflectors"] == "2" for r in k2)
    for r in rows:
        assert float(r["compute_us_per_pixel"]) > 0
        assert float(r["scan_us_per_pixel"]) == pytest.approx(2.0 * float(r["detections"]))  # 500k/s


def test_figures_agree_with_the_reconstruction_tests(quick_report):
    _, rows = quick_report
    at = {r["method"]: r for r in rows
          if r["scene"] == "bust" and r["detections"] == "15" and float(r["sbr"]) == 10}
    oracle = float(at["ml"]["oracle_mae_cm"])
    assert 1.1 < oracle < 1.25                         # DESIGN.md: about 1.2 cm
    ratio = {m: float(r["ratio_to_oracle"]) for m, r in at.items()}
    assert 0.85 <= ratio["ml"] <= 1.15                 # exact ML: about the oracle
    assert ratio["ml"] <= ratio["uos"] <= 1.45         # uos: about 25% above it
    assert 3.0 <= ratio["lmf"] / ratio["uos"] <= 12.0  # lmf: several times uos
    # more detections never hurt ml, and the one denominator keeps every pixel in
    ml = sorted((int(r["detections"]), float(r["mae_cm"])) for r in rows
                if r["scene"] == "bust" and r["method"] == "ml" and float(r["sbr"]) == 10)
    assert [m for _, m in ml] == sorted((m for _, m in ml), reverse=True)
    assert len({r["pixels"] for r in rows if r["scene"] == "bust"}) == 1
