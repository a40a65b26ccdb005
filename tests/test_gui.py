"""The live window, offscreen: scans started from the controls fill the maps; pause, resume, abort;
replay; the pixel inspector; device health through a simulated tagger dropping off the bus; close
during a scan; errors shown in the window; settings remembered; ``spdepth gui`` from the shell."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("pytestqt")
from PySide6 import QtCore  # noqa: E402

from spdepth.acq.requests import DEFAULT_METHOD  # noqa: E402
from spdepth.gui.sources import SourceSpec, open_run  # noqa: E402
from spdepth.recon.maps import DepthMaps  # noqa: E402
from spdepth.gui.window import MainWindow  # noqa: E402

SMALL = dict(kind="sim", scene="bust", size=(16, 16), target=5)


def _spec(tmp_path, **kw) -> SourceSpec:
    return SourceSpec(**{**SMALL, "out_root": str(tmp_path / "runs"), **kw})


def _state(w) -> str | None:
    return w.snap.state if w.snap is not None else None


def test_the_accuracy_plot_counts_a_miss_as_acq_evaluate_does(qtbot):
    """A reconstructed pixel without an estimate costs the outlier threshold, as in
    ``acq.evaluate.evaluate_depth`` (the plot averaged only the finite estimates before); pixels
    not yet reconstructed are left out."""
    from types import SimpleNamespace

    from spdepth.acq.evaluate import evaluate_depth
    from spdepth.gui.window import AccuracyPlot

    plot = AccuracyPlot()
    qtbot.addWidget(plot)
    truth = np.full((4, 4), 3.0)
    depth = truth + 0.01
    depth[0, :2] = np.nan                         # two misses among the reconstructed pixels
    depth[3] = np.nan                             # the last row: not reconstructed yet
    done = np.ones((4, 4), bool)
    done[3] = False
    snap = SimpleNamespace(elapsed_s=1.0, uncertainty_s=np.full((4, 4), 1e-10), depth_m=depth,
                           reconstructed=done, detections=100, pixels_total=16)
    plot.add(snap, truth, 360e-12, force=True)
    want = evaluate_depth(depth[:3], truth[:3], 1.0, 360e-12)
    assert plot.history[-1][3] == pytest.approx(100 * want.mae_m)
    assert plot.history[-1][3] == pytest.approx(100 * (10 * 0.01 + 2 * want.outlier_m) / 12)


def test_sim_scan_from_the_controls_fills_the_maps(qtbot, win, tmp_path):
    win.controls.set_spec(_spec(tmp_path, size=(24, 24)))
    c = win.controls
    ended = []
    win.scan_ended.connect(ended.append)
    qtbot.mouseClick(c.start, QtCore.Qt.LeftButton)
    # pause part-way (a deterministic look at a half-filled map), then let it finish; on a quiet
    # machine the scan may end before the window has seen a pixel, which is fine too
    qtbot.waitUntil(lambda: bool(ended) or (c.pause.isEnabled() and win.snap is not None
                                            and win.snap.pixels_final > 0), timeout=60_000)
    if not ended:
        qtbot.mouseClick(c.pause, QtCore.Qt.LeftButton)
        qtbot.waitUntil(lambda: _state(win) in ("paused", "done"), timeout=60_000)
    if _state(win) == "paused":
        win.refresh()
        painted = int(np.isfinite(win.panel("counts").data).sum())
        assert painted > 0
        # progress counts complete pixels
        assert win.progress.value() == int(np.count_nonzero(win.snap.acq_flags == 0))
        assert int(np.isfinite(win.panel("depth").data).sum()) <= win.snap.pixels_final
        qtbot.mouseClick(c.resume, QtCore.Qt.LeftButton)
    qtbot.waitUntil(lambda: bool(ended), timeout=60_000)
    assert ended == ["done"]
    depth, counts = win.panel("depth").data, win.panel("counts").data
    assert np.isfinite(depth).mean() > 0.9
    assert np.all(counts == 5)
    assert win.panel("counts").levels == (0.0, 5.0)
    lo, hi = win.panel("depth").levels
    assert 2.0 < lo < hi < 5.0                                # metres, the bust's range
    assert "depth (m)" in win.panel("depth").bar.getAxis("left").labelText.lower()
    assert win.state_label.text() == "done"
    assert win.progress.value() == 576
    assert "ok" in win.health_label.text()
    assert win.accuracy.history and np.isfinite(win.accuracy.history[-1][3])   # error vs truth
    # the files of the run, and the maps saved three ways
    out = win.run.out_dir
    assert json.loads((out / "run.json").read_text())["state"] == "done"
    for name in ("maps.png", "maps.tif", "maps.npz"):
        assert win.save_maps(tmp_path / name).stat().st_size > 0
    import tifffile

    stack = tifffile.imread(tmp_path / "maps.tif")
    assert stack.shape == (4, 24, 24)
    np.testing.assert_allclose(stack[0], win.session.maps().depth_m.astype(np.float32))


def test_inspector_shows_histogram_and_fitted_model(qtbot, win, tmp_path):
    assert win.start_run(_spec(tmp_path), out_dir=None)
    qtbot.waitUntil(lambda: _state(win) == "done", timeout=60_000)
    win.inspect((8, 3), pin=True)
    x, y = win.inspector.hist.getData()
    assert y.sum() == 5                                       # the pixel's kept detections
    mx, my = win.inspector.model.getData()
    assert my is not None and my.size == y.size
    assert abs(np.argmax(my) - np.argmax(y)) <= 1             # the pulse sits on the photons
    m = win.session.maps()
    assert my.sum() == pytest.approx(m.signal[8, 3] + m.background[8, 3] * 801, rel=1e-6)
    text = win.inspector.last_text
    assert "row 8, col 3" in win.inspector.title.text() and "depth: 3." in text
    assert "5 of 5" in text
    # the background as a rate over the laser time the pixel was observed
    t = win.session.exposure_s(8 * win.session.plan.shape[1] + 3)
    assert t > 0
    # to a hundredth of a detection over that time (not 2.08e-08 kcps)
    places = max(0, math.ceil(-math.log10(0.01 / t / 1e3)))
    assert f"{m.background[8, 3] * 801 / t / 1e3:.{places}f} kcps" in text and "e-" not in text
    assert f"{t * 1e3:.3g} ms of laser time" in text
    # hovering does not move a pinned pixel
    depth = win.panel("depth")
    win._mouse_moved(depth.plot.vb.mapViewToScene(depth.pixel_rect(1, 1).center()))
    assert win.inspector.pixel == (8, 3)
    win._pinned = False
    win._mouse_moved(depth.plot.vb.mapViewToScene(depth.pixel_rect(2, 1).center()))
    assert win.inspector.pixel == (2, 1)


def test_a_two_surface_scan_shows_each_surface_live_and_in_the_inspector(qtbot, win, tmp_path):
    spec = _spec(tmp_path, scene="two-layer", size=(16, 16), target=20, reflectors=2)
    assert spec.to_request().reflectors == 2
    assert win.start_run(spec, out_dir=None)
    c = win.controls
    assert c.surface_row.isVisibleTo(win) and c.surface.count() == 2     # picker from the start
    qtbot.waitUntil(lambda: _state(win) == "done", timeout=120_000)
    win.refresh()
    m = win.session.maps()
    assert m.depth_m.shape == (2, 16, 16)
    np.testing.assert_array_equal(win.panel("surfaces").data, m.surfaces.astype(np.float64))
    np.testing.assert_array_equal(win.panel("depth").data, m.depth_m[0])
    c.surface.setCurrentIndex(1)                              # the farther surface
    win._paint_maps(win.snap, 20, refit=True)
    np.testing.assert_array_equal(win.panel("depth").data, m.depth_m[1])
    # its weak pixels are faded (the overlay covers exactly them), the others drawn plainly
    faded = win.panel("depth").faded.image
    assert m.weak[1].any() and faded is not None
    np.testing.assert_array_equal(faded[..., 3] > 0, m.weak[1] & np.isfinite(m.depth_m[1]))
    # a pane pixel: both surfaces drawn, the model holds both returns
    win.inspect((8, 8), pin=True)
    assert m.surfaces[8, 8] == 2 and len(win.inspector.surface_lines) == 2
    assert [ln.value() for ln in win.inspector.surface_lines] == list(m.tof_s[:, 8, 8])
    _, my = win.inspector.model.getData()
    assert my.sum() == pytest.approx(m.signal[:, 8, 8].sum() + m.background[8, 8] * 801, rel=1e-6)
    assert "surface 2: 3.4" in win.inspector.last_text or "surface 2: 3.5" in win.inspector.last_text
    # a surface background alone could have made says so (K=2 adds them off the pane)
    r, c = np.argwhere(m.weak.any(axis=0))[0]
    win.inspect((int(r), int(c)), pin=True)
    assert "(weak: background could make it)" in win.inspector.last_text
    # saved: the npz as spdepth recon writes it, a TIFF channel per surface
    import tifffile

    assert win.save_maps(tmp_path / "k2.tif").stat().st_size > 0
    stack = tifffile.imread(tmp_path / "k2.tif")
    assert stack.shape == (6, 16, 16)
    np.testing.assert_array_equal(stack[1], m.depth_m[1].astype(np.float32))
    assert win.save_maps(tmp_path / "k2.npz").stat().st_size > 0
    np.testing.assert_array_equal(DepthMaps.load_npz(tmp_path / "k2.npz").surfaces, m.surfaces)


def test_pause_resume_abort(qtbot, win, tmp_path):
    c = win.controls
    win.controls.set_spec(_spec(tmp_path, size=(48, 48)))
    ended = []
    win.scan_ended.connect(ended.append)
    qtbot.mouseClick(c.start, QtCore.Qt.LeftButton)
    qtbot.waitUntil(lambda: c.pause.isEnabled() or bool(ended), timeout=30_000)
    if not ended:
        qtbot.mouseClick(c.pause, QtCore.Qt.LeftButton)
    # a quiet machine may finish the scan before the click lands: then there is nothing to pause
    qtbot.waitUntil(lambda: _state(win) == "paused" or bool(ended), timeout=30_000)
    if _state(win) == "paused":
        assert c.resume.isEnabled() and not c.pause.isEnabled() and not c.start.isEnabled()
        qtbot.mouseClick(c.resume, QtCore.Qt.LeftButton)
        qtbot.waitUntil(lambda: _state(win) in ("running", "done"), timeout=30_000)
    if _state(win) == "running":
        qtbot.mouseClick(c.abort, QtCore.Qt.LeftButton)
    qtbot.waitUntil(lambda: bool(ended), timeout=30_000)
    assert ended[0] in ("aborted", "done")
    run = json.loads((win.run.out_dir / "run.json").read_text())
    assert run["state"] == ended[0]
    assert (win.run.out_dir / "recording.ptu").stat().st_size > 0
    assert c.start.isEnabled() and not c.abort.isEnabled()


def test_replay_of_a_recording_matches_the_live_maps(qtbot, win, tmp_path):
    rec_dir = tmp_path / "rec"
    live = open_run(_spec(tmp_path).to_request(), rec_dir)
    live.session.start()
    assert live.session.wait(60).value == "done"
    live.close()
    # the live scan ran the default estimator; the replay runs it too, so the maps must be equal
    spec = SourceSpec(kind="replay", recording=str(rec_dir), target=0, method=DEFAULT_METHOD,
                      out_root=str(tmp_path / "runs"))
    assert win.start_run(spec), win.banner_text.text()
    qtbot.waitUntil(lambda: _state(win) == "done", timeout=60_000)
    np.testing.assert_array_equal(win.session.maps().depth_m, live.session.maps().depth_m)
    assert "recording ok" in win.health_label.text()
    c = win.controls                                  # the recorded plan, not the last scan's
    assert (c.width_px.value(), c.height_px.value(), c.mode.currentText()) == (16, 16, "gated")
    assert win.run_label.text().startswith(f"replay of rec, {DEFAULT_METHOD}")


# The session records a reconnect once the device is back (the galvo controller even scans on
# while its serial link is away, about 0.8 s here): the scans are big enough to go on after that,
# so the indicator can show "recovering" while running (a 16x16 scan often ended first). A window
# that could not look for a while (paints stalled seconds on a loaded machine) still shows it: the
# snapshot counts faults since the window's last look. On a loaded 2-core machine the 64x64 scan
# (with its estimator's warm-up) can run over a minute, hence the longer wait.
@pytest.mark.slow
@pytest.mark.parametrize("faults, size, target, device, kind", [
    ("device-vanish@15%", (64, 64), 10, "tagger", "tagger-reconnect"),
    ("serial-unplug@3%", (64, 64), 10, "galvo", "galvo-reconnect"),
])
def test_health_shows_a_lost_device_and_its_recovery(qtbot, win, tmp_path, faults, size, target,
                                                     device, kind, real_time_sim):
    seen = []

    def watch():
        h = win.health.health
        seen.append((h.level, dict(h.devices).get(device), win.health_label.text()))
        return _state(win) in ("done", "failed")

    assert win.start_run(_spec(tmp_path, faults=faults, size=size, target=target), out_dir=None)
    qtbot.waitUntil(watch, timeout=180_000)
    assert _state(win) == "done"
    # the session's own verdict, per device, reached the indicator while the scan went on
    assert any(lv == "recovering" and dev == "recovering" and f"{device} recovering" in text
               for lv, dev, text in seen), seen
    assert win.health.health.level == "recovered"
    assert f"{device} ok" in win.health_label.text() and "fault" in win.health_label.text()
    assert any(f["kind"] == kind for f in win.snap.faults)


def test_the_health_indicator_shows_a_recovery_it_saw_late_for_as_long():
    """The window stalled from 1 s to 4 s (a slow paint on a busy machine): the session reports
    the fault recorded meanwhile once (``faults_since_s``), and the indicator keeps it shown."""
    from types import SimpleNamespace

    from spdepth.acq.sources import HEALTH_RECENT_S
    from spdepth.gui.health import HealthTracker

    fault = ({"t_s": 1.5, "kind": "galvo-reconnect", "what": "serial link", "action": "re-opened"},)

    def snap(t, galvo, faults=fault):
        return SimpleNamespace(elapsed_s=t, detections=int(t * 100), faults=faults,
                               state="running", health={"galvo": galvo, "tagger": "ok"},
                               pixels_final=1, pixels_total=10, error=None)

    h = HealthTracker()
    assert h.update(snap(1.0, "ok", ())).level == "ok"
    assert h.update(snap(4.0, "recovering")).level == "recovering"
    assert h.last_elapsed_s == 4.0
    held = h.update(snap(4.1, "ok"))
    assert held.level == "recovering" and dict(held.devices)["galvo"] == "recovering"
    after = h.update(snap(4.0 + HEALTH_RECENT_S + 0.1, "ok"))
    assert after.level == "recovered" and dict(after.devices) == {"galvo": "ok", "tagger": "ok"}


def test_close_during_a_scan_aborts_and_keeps_the_recording(qtbot, settings, tmp_path,
                                                           real_time_sim):
    w = MainWindow(settings=settings)
    qtbot.addWidget(w)
    w.show()
    # big enough to be running still when the first pixels show (48x48 could end first)
    assert w.start_run(_spec(tmp_path, size=(128, 128)))
    qtbot.waitUntil(lambda: w.snap is not None and w.snap.pixels_final > 0, timeout=60_000)
    session, out = w.session, w.run.out_dir
    w.close()
    assert session.state.value == "aborted"
    assert w.run.instruments is None
    assert w.run.folder is None and not (out / ".spdepth.lock").exists()    # the lock released
    assert json.loads((out / "run.json").read_text())["state"] == "aborted"
    assert (out / "recording.ptu").stat().st_size > 0


def test_errors_appear_in_the_window_and_it_stays_usable(qtbot, win, tmp_path):
    assert not win.start_run(SourceSpec(kind="replay", recording=str(tmp_path / "nope.ptu")))
    assert win.banner.isVisible() and "does not exist" in win.banner_text.text()
    bad = tmp_path / "broken.ptu"
    bad.write_bytes(b"not a PTU file at all" * 10)
    assert not win.start_run(SourceSpec(kind="replay", recording=str(bad),
                                        out_root=str(tmp_path / "runs")))
    assert "broken.ptu" in win.banner_text.text()
    assert not win.start_run(_spec(tmp_path, scene="no-such-scene"))
    assert "no-such-scene" in win.banner_text.text()
    assert not win.start_run(SourceSpec(kind="real", galvo_port="/dev/nope",
                                        tagger_url="usb:1:2"))
    assert "sync rate" in win.banner_text.text()
    assert not any((tmp_path / "runs").glob("*")), "failed starts leave no empty run folders"
    assert win.controls.start.isEnabled()
    assert win.start_run(_spec(tmp_path), out_dir=None)
    assert not win.banner.isVisible()
    qtbot.waitUntil(lambda: _state(win) == "done", timeout=60_000)


def test_the_controls_make_the_librarys_requests(tmp_path):
    """The window only translates its controls (ms, ps, 0 for "default") into acq requests (SI,
    None); the request validates itself and the banner names the controls."""
    from spdepth.acq.errors import RequestError
    from spdepth.acq.requests import (Devices, FileReconRequest, ReplayRequest, ScanRequest,
                                      SimBench)
    from spdepth.gui.sources import in_window_words

    gated = _spec(tmp_path, dwell_limit_ms=2.5, sbr=3.0, seed=9,
                  faults="usb-timeout@50%").to_request()
    assert isinstance(gated, ScanRequest) and gated.size == (16, 16) and gated.target == 5
    assert gated.dwell_limit_s == pytest.approx(2.5e-3) and gated.dwell_s is None
    assert gated.instruments == SimBench(scene="bust", sbr=3.0, seed=9, faults="usb-timeout@50%")
    raster = _spec(tmp_path, mode="raster", dwell_limit_ms=1.5).to_request()
    assert raster.dwell_s == pytest.approx(1.5e-3) and raster.dwell_limit_s is None
    assert _spec(tmp_path).to_request().dwell_limit_s is None              # 0: the default
    real = SourceSpec(kind="real", galvo_port="loop://", tagger_url="usb:1:2",
                      sync_rate_hz=20e6, fov_deg=12.5).to_request()
    assert real.instruments == Devices(galvo="loop://", tagger="usb:1:2", sync_rate_hz=20e6,
                                       fov_deg=12.5)
    rec = tmp_path / "rec"
    rec.mkdir()
    (rec / "recording.ptu").write_bytes(b"")
    replay = SourceSpec(kind="replay", recording=str(rec), target=0, method="ml").to_request()
    assert replay == ReplayRequest(recording=str(rec), target=None, method="ml")
    data = tmp_path / "x.mat"
    data.write_bytes(b"MATLAB 5.0")
    f = SourceSpec(kind="file", file=str(data), time_unit_ps=8.0, pulse_rms_ps=360.0,
                   target=15).to_request()
    assert isinstance(f, FileReconRequest) and f.max_photons == 15
    assert f.time_unit_s == pytest.approx(8e-12) and f.pulse_rms_s == pytest.approx(360e-12)
    # the controls show a request as it was asked (the round trip keeps every control)
    for spec in (_spec(tmp_path, dwell_limit_ms=2.5, sbr=3.0, seed=9),
                 _spec(tmp_path, mode="raster", dwell_limit_ms=1.5, method="ml"),
                 SourceSpec(kind="real", galvo_port="loop://", tagger_url="usb:1:2",
                            sync_rate_hz=20e6, fov_deg=12.5),
                 SourceSpec(kind="replay", recording=str(rec), target=7, method="ml"),
                 SourceSpec(kind="file", file=str(data), time_unit_ps=8.0, target=15)):
        back = SourceSpec.from_request(spec.to_request(), spec)
        assert back == spec
    with pytest.raises(RequestError, match="--target must be a whole number >= 1, got 0"):
        _spec(tmp_path, target=0).to_request()
    with pytest.raises(RequestError) as e:
        SourceSpec(kind="real", galvo_port="loop://", tagger_url="usb:1:2").to_request()
    assert in_window_words(str(e.value)) == "real devices need sync rate (the laser repetition rate)"


def test_a_run_folder_is_locked_while_its_session_runs(qtbot, win, tmp_path):
    from spdepth.acq.api import LOCK_NAME, OutputDir
    from spdepth.acq.errors import OutputError

    ended = []
    win.scan_ended.connect(ended.append)
    assert win.start_run(_spec(tmp_path, size=(24, 24)))
    out = win.run.out_dir
    assert out.parent == tmp_path / "runs" and out.name.endswith("-sim")
    assert (out / LOCK_NAME).is_file()
    with pytest.raises(OutputError, match="in use by a running session"):
        OutputDir(out, overwrite=True)
    qtbot.waitUntil(lambda: bool(ended), timeout=60_000)
    assert ended == ["done"] and not (out / LOCK_NAME).exists()     # released with the run
    OutputDir(out, overwrite=True).close()


def test_settings_are_remembered_per_source_kind_once_they_ran(qtbot, settings, tmp_path):
    """Each source kind keeps its own controls, and only those of a run that started (before:
    one dict for every kind, saved at close, so a replay's "target: as recorded" (0), a file's
    surfaces or a seed typed and never run changed the next simulated scan)."""
    import dataclasses

    from spdepth.gui.window import DEFAULT_OUT_ROOT

    w = MainWindow(settings=settings)
    qtbot.addWidget(w)
    replay = SourceSpec(kind="replay", target=0, method="uos", reflectors=0,
                        recording=str(tmp_path / "rec"), out_root="runs-here")
    w.controls.set_spec(replay)
    w.save_settings(worked=True)                    # as when a replay started
    w.controls.set_spec(SourceSpec(kind="file", file=str(tmp_path / "x.ptu"), reflectors=2,
                                   target=0, method="ml"))
    w.save_settings(worked=True)                    # as when a file was read
    w.controls.set_spec(SourceSpec(kind="sim", seed=42, size=(24, 40),
                                   out_root="/nonexistent/typo"))    # typed, never run
    w.close()
    w2 = MainWindow(settings=settings)
    qtbot.addWidget(w2)
    shown = w2.controls.spec()                      # the kind that ran last, as it ran
    assert (shown.kind, shown.file, shown.reflectors, shown.target) == \
        ("file", str(tmp_path / "x.ptu"), 2, 0)
    assert shown.out_root == str(Path("runs-here").resolve())       # absolute, the one that worked
    sim = w2.remembered.spec("sim").to_request()    # nothing ran as sim: the declared defaults
    assert (sim.target, sim.reflectors, sim.instruments.seed, sim.size) == (15, 1, 0, (64, 64))
    back = w2.remembered.spec("replay")
    assert (back.target, back.method, back.reflectors) == (0, "uos", 0)
    # switching the source shows that kind's own values, not the last kind's
    c = w2.controls
    c.kind.setCurrentIndex(c.kind.findData("sim"))
    assert (c.target.value(), c.reflectors.currentData(), c.seed.value()) == (15, 1, 0)
    c.kind.setCurrentIndex(c.kind.findData("replay"))
    assert (c.target.value(), c.reflectors.currentText(), c.method.currentText()) == \
        (0, "as recorded", "uos")
    assert c.spec() == dataclasses.replace(c.spec(), **{k: getattr(back, k) for k in
                                                         ("target", "method", "reflectors")})
    assert DEFAULT_OUT_ROOT


def test_a_stored_value_that_no_longer_validates_gives_way_to_its_default(qtbot, settings):
    from spdepth.gui.sources import SETTINGS_KEY

    settings.setValue(SETTINGS_KEY, json.dumps({
        "kind": "sim", "sim": {"target": 0, "method": "retired", "size": [5000, 2], "seed": 3,
                               "reflectors": "auto", "colour": "red"}}))
    w = MainWindow(settings=settings)
    qtbot.addWidget(w)
    spec = w.controls.spec()
    assert (spec.target, spec.method, spec.size, spec.seed, spec.reflectors) == \
        (15, DEFAULT_METHOD, (64, 64), 3, "auto")
    line = w.statusBar().currentMessage()
    assert line.count("ignored") == 3 and "\n" not in line, line
    assert "target 0" in line and "'retired'" in line
    assert spec.to_request().reflectors == "auto"


def test_spdepth_gui_starts_from_its_source_kinds_settings_under_the_command_line(tmp_path):
    """The issue's reproduction: the settings an earlier version stored after a replay (one dict,
    target 0 "as recorded") made ``spdepth gui --sim --size 32x32 --exit-after-scan`` fail with
    "--target must be a whole number >= 1, got 0". Now it starts with the default target; a
    remembered sim run's values are used under the command line, which wins; --reflectors auto
    works in the window too."""
    cfg = tmp_path / "cfg"
    old = QtCore.QSettings(str(cfg / "spdepth" / "spdepth.conf"), QtCore.QSettings.IniFormat)
    old.setValue("source", json.dumps({**SourceSpec(kind="replay", target=0, reflectors=0,
                                                    seed=42).to_dict()}))
    old.sync()
    env = {**os.environ, "QT_QPA_PLATFORM": "offscreen", "XDG_CONFIG_HOME": str(cfg),
           "HOME": str(tmp_path)}

    def gui(*args):
        return subprocess.run([sys.executable, "-m", "spdepth.acq.cli", "gui", "--sim", "--size",
                               "12x10", "--exit-after-scan", *args], env=env, capture_output=True,
                              text=True, timeout=180, cwd=Path(__file__).resolve().parents[1])

    runs = tmp_path / "runs"
    p = gui("--runs-dir", str(runs))
    assert p.returncode == 0, p.stderr
    (first,) = runs.iterdir()
    req = json.loads((first / "run.json").read_text())["info"]["request"]
    assert (req["target"], req["reflectors"], req["instruments"]["seed"]) == (15, 1, 0)
    # that sim run is now remembered (its seed, target); the command line still wins
    p = gui("--target", "4", "--reflectors", "auto", "--seed", "5", "--out", str(tmp_path / "r2"))
    assert p.returncode == 0, p.stderr
    req = json.loads((tmp_path / "r2" / "run.json").read_text())["info"]["request"]
    assert (req["target"], req["reflectors"], req["instruments"]["seed"]) == (4, "auto", 5)
    assert not (runs / "r2").exists() and len(list(runs.iterdir())) == 1


@pytest.mark.slow
def test_spdepth_gui_screenshot_offscreen(tmp_path):
    env = {**os.environ, "QT_QPA_PLATFORM": "offscreen", "XDG_CONFIG_HOME": str(tmp_path / "cfg"),
           "HOME": str(tmp_path)}
    shot = tmp_path / "shot.png"
    p = subprocess.run([sys.executable, "-m", "spdepth.acq.cli", "gui", "--sim", "--size", "16x12",
                        "--target", "5", "--screenshot", str(shot), "--exit-after-scan",
                        "--runs-dir", str(tmp_path / "runs")],
                       env=env, capture_output=True, text=True, timeout=120,
                       cwd=Path(__file__).resolve().parents[1])
    assert p.returncode == 0, p.stderr
    from PIL import Image

    assert Image.open(shot).size == (1480, 900)
    (run,) = (tmp_path / "runs").iterdir()
    assert json.loads((run / "run.json").read_text())["plan"]["nx"] == 16
    bad = subprocess.run([sys.executable, "-m", "spdepth.acq.cli", "gui", "--replay",
                          str(tmp_path / "missing"), "--exit-after-scan"],
                         env=env, capture_output=True, text=True, timeout=120,
                         cwd=Path(__file__).resolve().parents[1])
    assert bad.returncode == 2 and "does not exist" in bad.stderr
    # the command line's request is checked before a window opens, in the CLI's words, and run
    # as given (not as the controls would clamp it)
    for args, said in ((["--size", "5000x2"], "argument --size: 5000x2: each side must be 1..4096"),
                       (["--mode", "raster", "--dwell-limit-ms", "0.5"],
                        "--dwell-limit-ms is the gated dwell limit")):
        bad = subprocess.run([sys.executable, "-m", "spdepth.acq.cli", "gui", "--sim", *args,
                              "--exit-after-scan", "--runs-dir", str(tmp_path / "runs")],
                             env=env, capture_output=True, text=True, timeout=120,
                             cwd=Path(__file__).resolve().parents[1])
        assert bad.returncode == 2 and said in bad.stderr, bad.stderr
        assert len(bad.stderr.strip().splitlines()) == 1, bad.stderr
    assert [run] == list((tmp_path / "runs").iterdir())          # no window, no folder


def test_demo_opens_the_window_only_where_a_display_exists():
    from spdepth.gui.app import display_available

    assert display_available({"DISPLAY": ":0"}, "linux")
    assert display_available({"WAYLAND_DISPLAY": "wayland-0"}, "linux")
    assert not display_available({}, "linux")
    assert not display_available({"DISPLAY": ":0", "QT_QPA_PLATFORM": "offscreen"}, "linux")
    assert not display_available({"DISPLAY": ":0", "QT_QPA_PLATFORM": "minimal"}, "linux")
    assert display_available({}, "darwin") and display_available({}, "win32")
    assert not display_available({"QT_QPA_PLATFORM": "offscreen"}, "win32")


def test_demo_window_runs_the_demo_scan(tmp_path):
    """What ``spdepth demo`` opens with a display: the demo's scene scanned in the window."""
    env = {**os.environ, "QT_QPA_PLATFORM": "offscreen", "XDG_CONFIG_HOME": str(tmp_path / "cfg"),
           "HOME": str(tmp_path)}
    shot = tmp_path / "demo.png"
    code = ("import sys; from spdepth.acq.requests import ScanRequest, SimBench; "
            "from spdepth.gui.app import run_demo_window; sys.exit(run_demo_window(ScanRequest("
            "instruments=SimBench(scene='steps', sbr=10.0, seed=1), size=(12, 16), target=4, "
            f"method='uos'), exit_after_scan=True, screenshot={str(shot)!r}))")
    p = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                       timeout=120, cwd=Path(__file__).resolve().parents[1])
    assert p.returncode == 0, p.stderr
    assert shot.stat().st_size > 0


FPI = Path("/work/shared/data/fpi/mannequin_face_8ppp.mat")


def _reconstruct_in_window(qtbot, win, spec) -> str:
    ended = []
    win.scan_ended.connect(ended.append)
    assert win.start_run(spec), win.banner_text.text()
    assert win.state_label.text() == "reconstructing"
    qtbot.waitUntil(lambda: bool(ended), timeout=90_000)
    return ended[0]


def test_a_ptu_file_is_reconstructed_off_the_gui_thread(qtbot, win, tmp_path, small_ptu):
    from spdepth.acq.readers import read_photons
    from spdepth.recon.estimate import reconstruct
    from spdepth.recon.model import ReconSettings

    spec = SourceSpec(kind="file", file=str(small_ptu), method="ml", target=0)
    win.controls.set_spec(spec)
    assert not win.controls.width_px.isEnabled() and win.controls.target.specialValueText() == "all"
    assert _reconstruct_in_window(qtbot, win, spec) == "done"
    want = reconstruct(read_photons(small_ptu).store, ReconSettings(method="ml"))
    np.testing.assert_array_equal(win.panel("depth").data, want.depth_m)     # spdepth recon's maps
    assert win.state_label.text() == "done" and win.controls.start.isEnabled()
    assert "steps.ptu" in win.run_label.text()
    win.inspect((6, 8), pin=True)
    _, y = win.inspector.hist.getData()
    assert y.sum() == want.photons[6, 8] > 0
    assert "depth: " in win.inspector.last_text and "from steps.ptu" in win.inspector.last_text
    assert win.save_maps(tmp_path / "maps.npz").stat().st_size > 0


def test_a_file_s_notes_are_kept_whole_in_the_title_s_tooltip(qtbot, win, small_ptu):
    # the status bar shows them a while and cuts them at its width; the tooltip keeps every one
    spec = SourceSpec(kind="file", file=str(small_ptu), method="ml", target=5)
    assert _reconstruct_in_window(qtbot, win, spec) == "done"
    tip = win.run_label.toolTip()
    assert str(small_ptu) in tip and "beyond the first 5 per pixel (--target)" in tip
    assert "whole in the title's tooltip: " in win.statusBar().currentMessage()


def test_maps_an_estimator_does_not_estimate_say_so_in_their_titles(qtbot, win, small_ptu):
    # lmf estimates no background: its background and signal/background maps hold no value
    for method, said in (("lmf", True), ("ml", False)):
        spec = SourceSpec(kind="file", file=str(small_ptu), method=method, target=0)
        assert _reconstruct_in_window(qtbot, win, spec) == "done"
        for key in ("background", "sbr"):
            assert ("not estimated by lmf" in win.panel(key).plot.titleLabel.text) is said, (method, key)
        assert "not estimated" not in win.panel("depth").plot.titleLabel.text


def test_a_bad_file_shows_in_the_banner(qtbot, win, tmp_path):
    bad = tmp_path / "broken.ptu"
    bad.write_bytes(b"PQTTTR\0\0" + b"\0" * 40)
    spec = SourceSpec(kind="file", file=str(bad))
    assert _reconstruct_in_window(qtbot, win, spec) == "failed"
    assert win.banner.isVisible() and "broken.ptu" in win.banner_text.text()
    assert win.controls.start.isEnabled()
    mat = tmp_path / "x.mat"
    mat.write_bytes(b"MATLAB 5.0")
    assert not win.start_run(SourceSpec(kind="file", file=str(mat)))
    assert "time unit" in win.banner_text.text()


@pytest.mark.skipif(not FPI.exists(), reason=f"{FPI} not present")
def test_a_first_photon_imaging_mat_file(qtbot, win):
    # compile the .mat reader's kernels here, not on the window's worker thread: on a fresh
    # checkout (CI) that first compile inside the running event loop hung the test (noted in the
    # session note as a defect of the window to find)
    from spdepth.acq.readers import read_photons

    assert read_photons(FPI, time_unit_s=8e-12).store.n_photons > 0
    spec = SourceSpec(kind="file", file=str(FPI), time_unit_ps=8.0, pulse_rms_ps=360.0,
                      method="uos", target=15)
    assert _reconstruct_in_window(qtbot, win, spec) == "done", win.banner_text.text()
    depth = win.panel("depth").data
    assert np.isfinite(depth).mean() > 0.5
    h, w = depth.shape
    win.inspect((h // 2, w // 2), pin=True)
    assert "(first 15)" in win.inspector.last_text and "from mannequin_face_8ppp.mat" in \
        win.inspector.last_text
    assert 0 < win.inspector.hist.getData()[1].sum() <= 15


def test_the_window_benchmark_runs_from_the_cli_side(qtbot, capsys):
    """``gui.benchmark.measure`` takes plain arguments; its command line lives with the CLI."""
    from spdepth.acq.commands.bench.gui import bench

    assert bench(["--size", "8x6", "--target", "2", "--repeats", "1", "--no-replay"]) == 0
    out = capsys.readouterr().out
    assert out.startswith("bust 8x6, target 2, window showing maps, 1 alternated runs each (medians):")
    assert "scan" in out and "window/headless" in out and "replay" not in out


def test_a_headless_run_leaves_no_window_geometry_behind(qtbot, settings):
    # offscreen Qt invents an 800x800 screen: a geometry saved there squeezed the window (its
    # right column clipped) when restored on a real screen
    w = MainWindow(settings=settings)
    qtbot.addWidget(w)
    w.resize(700, 500)
    w.close()
    assert not settings.contains("geometry")
    assert settings.contains("splitter")       # the rest is kept; the controls only once they ran
    assert not settings.contains("sources")


def test_a_new_estimator_after_a_scan_reconstructs_its_recording(qtbot, win, tmp_path):
    ended = []
    win.scan_ended.connect(ended.append)
    assert win.start_run(_spec(tmp_path, size=(10, 12), method="uos"), out_dir=tmp_path / "run")
    qtbot.waitUntil(lambda: ended == ["done"], timeout=60_000)
    assert "uos" in win.run_label.text()
    win.controls.method.setCurrentText("ml")          # as a user picks it
    qtbot.waitUntil(lambda: len(ended) == 2, timeout=60_000)
    assert ended[1] == "done"
    assert "ml" in win.run_label.text() and "recording.ptu" in win.run_label.text()
    assert win.view.maps().settings["method"] == "ml"
    assert win.view.shape == (10, 12)
    # a run kept in memory has nothing to read again: said, not done
    assert win.start_run(_spec(tmp_path, size=(6, 6), method="uos"), out_dir=None)
    qtbot.waitUntil(lambda: len(ended) == 3, timeout=60_000)
    win.controls.method.setCurrentText("lmf")
    assert "next run" in win.statusBar().currentMessage()
