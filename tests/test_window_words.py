"""What the window says, offscreen: numbers to their precision with units a person reads, captions
true in every state (running, paused, aborted, done), labels that fit at the default size."""

from __future__ import annotations

import math

import numpy as np
import pytest

pytest.importorskip("pytestqt")
from PySide6 import QtCore  # noqa: E402

from spdepth.acq.mapdefs import MAPS_BY_KEY, constant_caption, not_estimated  # noqa: E402
from spdepth.gui.window import MainWindow, fmt_depth, fmt_kcps, readable_span  # noqa: E402


def test_a_depth_is_given_to_the_precision_of_its_uncertainty():
    assert fmt_depth(2.850612, 0.0139) == "2.851 m ± 1.4 cm"
    assert fmt_depth(2.849412, 0.0092) == "2.8494 m ± 0.92 cm"
    assert fmt_depth(1234.5678, 0.23) == "1234.57 m ± 23 cm"
    assert fmt_depth(3.0, math.nan) == "3.0000 m"
    assert fmt_depth(math.nan, 0.01) == "–"


def test_a_background_rate_is_in_kcps_to_a_hundredth_of_a_detection():
    # the case: 2.08e-08 kcps over half a millisecond is nothing a person reads
    assert fmt_kcps(2.08e-08 * 1e3 * 0.509e-3, 0.509e-3) == "0.00 kcps"
    assert fmt_kcps(3.05, 0.509e-3) == "5.99 kcps"
    assert fmt_kcps(3.05, 2.0) == "0.001525 kcps"
    assert "e" not in fmt_kcps(1e-9, 1e-6)


def test_a_flat_accuracy_line_gets_a_span_worth_reading():
    assert readable_span(np.array([1.453297857435]), 0.05) == pytest.approx((1.308, 1.599), abs=1e-3)
    assert readable_span(np.array([1.4532978, 1.4532979]), 0.05) is not None
    assert readable_span(np.array([1.0, 2.0]), 0.05) is None
    assert readable_span(np.array([np.nan]), 0.05) is None


def test_a_constant_map_says_where_it_holds_its_value():
    counts = MAPS_BY_KEY["counts"]
    every = np.full((4, 4), 15.0)
    assert constant_caption(counts, every) == "15 in every pixel"
    paused = every.copy()
    paused[1:] = np.nan                      # rows not measured yet (paused or aborted there)
    assert constant_caption(counts, paused) == "15 in 4 of 16 pixels"
    assert constant_caption(MAPS_BY_KEY["depth"], every) == "15 m in every pixel"
    every[0, 0] = 14
    assert constant_caption(counts, every) is None


def test_a_map_the_estimator_does_not_estimate_says_so():
    # the window's titles and the PNG's notes (acq.report) take it from one place
    for key in ("background", "background_rate", "sbr"):
        assert not_estimated(MAPS_BY_KEY[key], "lmf") == "not estimated by lmf"
        assert not_estimated(MAPS_BY_KEY[key], "ml") is None
    assert not_estimated(MAPS_BY_KEY["depth"], "lmf") is None
    assert not_estimated(MAPS_BY_KEY["background"], None) is None


@pytest.fixture
def win(win):
    """conftest's window at the default size of ``spdepth gui``."""
    from spdepth.gui.app import WINDOW_SIZE

    win.resize(*WINDOW_SIZE)
    return win


def _spec(tmp_path, **kw):
    from spdepth.gui.sources import SourceSpec

    return SourceSpec(**{"kind": "sim", "scene": "bust", "size": (48, 48), "target": 5,
                         "out_root": str(tmp_path / "runs"), **kw})


def _bar_ticks_inside(win) -> list[str]:
    """Map panels whose colour bar (with its tick labels) reaches past the maps' view."""
    view = win.maps_view
    right = view.viewport().width()
    out = []
    for p in win.panels:
        if not p.plot.isVisible():
            continue
        edge = p.bar.axis.mapRectToScene(p.bar.axis.boundingRect()).right()
        if view.mapFromScene(QtCore.QPointF(edge, 0)).x() > right:
            out.append(p.spec.key)
    return out


def test_paused_and_aborted_captions_are_true(qtbot, win, tmp_path, real_time_sim):
    assert win.start_run(_spec(tmp_path))
    qtbot.waitUntil(lambda: win.snap is not None and win.snap.pixels_final > 20, timeout=60_000)
    win.pause()
    qtbot.waitUntil(lambda: win.snap.state == "paused", timeout=30_000)
    win.refresh()
    title = win.panel("counts").plot.titleLabel.text
    assert "every pixel" not in title
    assert win.eta_label.text() == "ETA – (paused)"
    assert "det/s" not in win.rate_label.text()
    win.abort()
    qtbot.waitUntil(lambda: win.snap.state == "aborted", timeout=30_000)
    win.refresh()
    snap = win.snap
    from spdepth.acq.flags import AcqFlag

    assert np.count_nonzero(snap.acq_flags == AcqFlag.COMPLETE) < snap.pixels_total
    title = win.panel("counts").plot.titleLabel.text
    assert "every pixel" not in title
    if "Detections kept: " + "5 in " in title:        # constant: it says where
        assert f"of {snap.pixels_total:,} pixels" in title
    assert win.eta_label.text().startswith("aborted after ")
    assert win.rate_label.text() == f"{snap.detections:,} det"
    assert _bar_ticks_inside(win) == []


def test_at_the_default_size_every_colour_bar_keeps_its_ticks(qtbot, win, tmp_path):
    ended = []
    win.scan_ended.connect(ended.append)
    assert win.start_run(_spec(tmp_path, size=(32, 32), target=15), out_dir=None)
    qtbot.waitUntil(lambda: bool(ended), timeout=60_000)
    qtbot.wait(200)
    assert win.panel("counts").plot.titleLabel.text == "Detections kept: 15 in every pixel"
    ci = win.maps_view.ci
    assert ci.minimumWidth() <= win.maps_view.viewport().width()
    assert _bar_ticks_inside(win) == []
    assert win.eta_label.text().startswith("done after ")
    assert "e-" not in win.inspector.last_text and "e+" not in win.inspector.last_text


def _demo_request():
    from spdepth.acq.requests import ScanRequest, SimBench

    return ScanRequest(instruments=SimBench(scene="steps", sbr=10.0, seed=1), size=(12, 16),
                       target=4, method="uos")


def test_the_demo_with_a_window_prints_its_accuracy_table(qtbot, tmp_path, capsys, monkeypatch):
    import argparse

    from spdepth.acq.commands import demo
    from spdepth.gui import app

    monkeypatch.setenv("XDG_CONFIG_HOME", str(tmp_path / "cfg"))
    real = app.run_demo_window
    monkeypatch.setattr(app, "run_demo_window",
                        lambda *a, **kw: real(*a, exit_after_scan=True, **kw))
    args = argparse.Namespace(out=None, overwrite=False)
    assert demo._window(args, _demo_request(), ["lmf", "ml"]) == 0
    out = capsys.readouterr().out
    assert "method    MAE (cm)" in out and "\noracle " in out
    assert "\nlmf " in out and "\nml " in out


def test_a_terminated_window_says_whether_its_run_kept_a_recording(qtbot, tmp_path, capsys,
                                                                   monkeypatch):
    import os
    import signal

    from spdepth.gui import app

    monkeypatch.setenv("XDG_CONFIG_HOME", str(tmp_path / "cfg"))
    before = signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)
    settings = QtCore.QSettings(str(tmp_path / "s.ini"), QtCore.QSettings.IniFormat)

    def terminate_when_done(run):
        def check():
            if run.session.ended.is_set():
                os.kill(os.getpid(), signal.SIGTERM)
            else:
                QtCore.QTimer.singleShot(100, check)
        QtCore.QTimer.singleShot(100, check)

    try:
        for out_dir, said in ((None, "the run was kept in memory only: no recording"),
                              (tmp_path / "kept", f"its recording is kept in {tmp_path / 'kept'}")):
            if out_dir is not None:
                out_dir.mkdir()
            code = app.run_window(_demo_request(), out_dir=out_dir, settings=settings,
                                  on_started=terminate_when_done)
            assert code == 130
            err = capsys.readouterr().err
            assert f"spdepth gui: interrupted; closing the window ({said})" in err, err
    finally:
        signal.signal(signal.SIGINT, before[0])
        signal.signal(signal.SIGTERM, before[1])


def test_a_cut_recording_replayed_in_the_window_says_so_once(qtbot, win, recording, tmp_path):
    import shutil

    from spdepth.gui.sources import SourceSpec

    rec = tmp_path / "cut"
    shutil.copytree(recording, rec)
    data = (rec / "recording.ptu").read_bytes()
    (rec / "recording.ptu").write_bytes(data[:len(data) * 2 // 3])
    ended = []
    win.scan_ended.connect(ended.append)
    assert win.start_run(SourceSpec(kind="replay", recording=str(rec), target=0,
                                    out_root=str(tmp_path / "runs")))
    assert "recording.ptu is truncated: its header promises" in win.statusBar().currentMessage()
    qtbot.waitUntil(lambda: bool(ended), timeout=60_000)
