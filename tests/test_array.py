"""The simulated SPAD array (drivers.sim.spad_array) and its sessions (acq.array_session): frames,
pile-up, hot pixels and crosstalk only where asked, recording to HDF5 and replay bit for bit."""

from __future__ import annotations

import json

import numpy as np
import pytest

from spdepth.acq.commands.bench.array import make_sensor


def test_frames_are_seeded_and_hold_the_asked_counts():
    s = make_sensor("tilted-plane", (12, 10), counts=20.0, sbr=1.0, seed=4)
    f3 = s.frame(3)
    assert f3.shape == (12, 10, 1024) and f3.dtype == np.uint16
    np.testing.assert_array_equal(f3, make_sensor("tilted-plane", (12, 10), seed=4).frame(3))
    assert not np.array_equal(f3, s.frame(4))
    mean = np.mean([s.frame(i).sum() for i in range(20)]) / 120
    assert mean == pytest.approx(20.0, rel=0.03)
    # the return sits where the scene puts it: bin of the truth's time of flight
    t = s.truth()
    peak = np.argmax(sum(s.frame(i) for i in range(20)).astype(float), axis=2)
    tof_bins = t["tof_s"] / s.settings.bin_s
    assert np.median(np.abs(peak - tof_bins)) < 2
    assert not s.hot.any()


def test_pileup_hot_pixels_and_crosstalk_only_when_asked():
    low = make_sensor("tilted-plane", (8, 8), counts=20.0, sbr=10.0)
    # 20 counts in 33,333 periods is no pile-up; 3 per period is a lot
    high = make_sensor("tilted-plane", (8, 8), counts=3.0 * 33333, sbr=10.0)
    lo_frac = low.mean.sum() / (low.lam.sum() * low.settings.periods_per_frame)
    hi_frac = high.mean.sum() / (high.lam.sum() * high.settings.periods_per_frame)
    assert lo_frac > 0.999 and hi_frac < 0.4
    # the piled-up histogram leans early; Coates' correction of a frame brings the centroid back
    from spdepth.recon.counts import CountStore
    from spdepth.recon.pileup import coates

    f = CountStore.from_pairs(*high.frame_pairs(0), (8, 8), 1024, 80e-12,
                              periods=np.full(64, float(high.settings.periods_per_frame)))
    ideal = high.lam * high.settings.periods_per_frame          # (pixels, bins) without pile-up
    tof = (high.truth()["tof_s"] / 80e-12).ravel()
    k = np.arange(1024)
    near_ideal = np.abs(k - tof[:, None]) < 15
    want = (ideal * k * near_ideal).sum(1) / (ideal * near_ideal).sum(1)

    def centroid(store):
        pix = store.pixel_index()
        near = np.abs(store.times - tof[pix]) < 15
        return np.bincount(pix[near], weights=(store.counts * store.times)[near], minlength=64) / \
            np.bincount(pix[near], weights=store.counts[near], minlength=64)

    assert np.median(centroid(f) - want) < -1.0                 # a bin early and more
    assert abs(np.median(centroid(coates(f)) - want)) < 0.3
    hot = make_sensor("tilted-plane", (10, 10), hot_share=0.05, hot_rate_hz=2e6)
    assert hot.hot.sum() == 5
    counts = hot.frame(0).sum(axis=2)
    assert counts[hot.hot].min() > 3 * np.median(counts[~hot.hot])
    xt = make_sensor("tilted-plane", (10, 10), crosstalk=0.1)
    assert xt.frame(0).sum() > 1.05 * make_sensor("tilted-plane", (10, 10)).frame(0).sum()


def test_session_records_frames_and_replays_them_bit_for_bit(tmp_path):
    import h5py

    from spdepth.acq.api import reconstruct_file
    from spdepth.acq.array_session import ArraySession, ArrayState, H5ReplaySource, SimArraySource
    from spdepth.acq.requests import FileReconRequest
    from spdepth.recon.maps import DepthMaps
    from spdepth.recon.model import ReconSettings

    sensor = make_sensor("tilted-plane", (16, 12), counts=30.0, seed=2)
    settings = ReconSettings(method="ml", pulse_rms_s=sensor.scene.pulse_rms_s)
    for mode in ("frame", "accumulate"):
        live = ArraySession(SimArraySource(sensor, 6, realtime=False), settings, mode=mode,
                            out_dir=tmp_path / f"live-{mode}", every_frame=True)
        assert live.run() == ArrayState.DONE, live.error
        with h5py.File(tmp_path / f"live-{mode}" / "frames.h5") as f:
            off = f["frame_offsets"][()]
            keys, counts = f["keys"][()], f["counts"][()]
        assert off.size == 7
        for i in range(6):
            frame = np.zeros(16 * 12 * 1024, np.uint16)
            frame[keys[off[i]:off[i + 1]].astype(np.int64)] = counts[off[i]:off[i + 1]]
            np.testing.assert_array_equal(frame.reshape(16, 12, 1024), sensor.frame(i))
        replay = ArraySession(H5ReplaySource(tmp_path / f"live-{mode}" / "frames.h5"), settings, mode=mode,
                              out_dir=tmp_path / f"replay-{mode}", every_frame=True)
        assert replay.run() == ArrayState.DONE, replay.error
        assert not (tmp_path / f"replay-{mode}" / "frames.h5").exists()
        assert replay.frame_digests == live.frame_digests and len(set(live.frame_digests)) == 6
        a = DepthMaps.load_npz(tmp_path / f"live-{mode}" / "maps.npz")
        b = DepthMaps.load_npz(tmp_path / f"replay-{mode}" / "maps.npz")
        np.testing.assert_array_equal(a.tof_s, b.tof_s)
        run = json.loads((tmp_path / f"live-{mode}" / "run.json").read_text())
        assert run["state"] == "done" and run["recorded"] == 6
    # accumulated maps are the maps of the recording read as one cube (frames summed)
    res = reconstruct_file(FileReconRequest(input=str(tmp_path / "live-accumulate" / "frames.h5"), method="ml",
                                            pulse_rms_s=sensor.scene.pulse_rms_s))
    np.testing.assert_array_equal(res.maps.tof_s, a.tof_s)
    assert res.maps.settings["sensor"]["pixel_pitch_m"] == sensor.settings.pixel_pitch_m
    assert "geometry" in res.maps.settings
    truth = sensor.truth()
    assert np.nanmedian(np.abs(a.depth_m - truth["depth_m"])) < 0.02


def test_a_live_session_keeps_every_frame_while_its_maps_skip(tmp_path):
    """Free-running, the reconstruction takes the newest state when free: every frame is recorded
    and counted, the last state is always reconstructed, and the final maps of an accumulating
    session are the recording's, replayed or not."""
    from spdepth.acq.array_session import ArraySession, ArrayState, H5ReplaySource, SimArraySource
    from spdepth.recon.model import ReconSettings

    sensor = make_sensor("tilted-plane", (24, 24), counts=20.0, seed=3)
    settings = ReconSettings(method="uos", pulse_rms_s=sensor.scene.pulse_rms_s)
    live = ArraySession(SimArraySource(sensor, 12, realtime=False), settings, out_dir=tmp_path / "live")
    assert live.run() == ArrayState.DONE, live.error
    assert live.frames == 12 and live.reconstructed == 12 and 1 <= live.recon_runs <= 12
    replay = ArraySession(H5ReplaySource(tmp_path / "live" / "frames.h5"), settings, out_dir=tmp_path / "replay")
    assert replay.run() == ArrayState.DONE
    assert replay.frame_digests[-1] == live.frame_digests[-1]
    run = json.loads((tmp_path / "live" / "run.json").read_text())
    assert run["recorded"] == 12 and run["final_maps_digest"] == live.frame_digests[-1][1]


def test_a_session_can_be_paused_and_aborted(tmp_path):
    from spdepth.acq.array_session import ArraySession, ArrayState, SimArraySource
    from spdepth.recon.model import ReconSettings
    from tests.waiting import wait_until

    sensor = make_sensor("tilted-plane", (8, 8), frame_rate_hz=50.0)
    s = ArraySession(SimArraySource(sensor, 10_000, realtime=True),
                     ReconSettings(method="lmf", pulse_rms_s=360e-12), mode="frame")
    s.start()
    wait_until(lambda: s.snapshot().frames >= 2, what="two frames")
    s.pause()
    # paused, the source's thread is held between frames until resume or abort: no frame comes
    wait_until(lambda: s.snapshot().state == ArrayState.PAUSED, what="the session paused")
    held = s.snapshot().frames
    assert s.snapshot().frames <= held + 1 and s.snapshot().state == ArrayState.PAUSED
    s.resume()
    wait_until(lambda: s.snapshot().frames > held + 1, what="frames again after resume")
    s.pause()
    wait_until(lambda: s.snapshot().state == ArrayState.PAUSED, what="paused again")
    s.abort()                       # an abort ends a paused session too
    assert s.wait(60) == ArrayState.ABORTED     # generous: only a failing test waits it out


def test_the_window_shows_the_session_live(qtbot, tmp_path):
    import time

    from spdepth.acq.array_session import ArraySession, ArrayState, SimArraySource
    from spdepth.acq.points import ScanGeometry
    from spdepth.gui.array_window import ArrayWindow
    from spdepth.recon.model import ReconSettings

    from spdepth.recon.estimate import reconstruct

    sensor = make_sensor("tilted-plane", (16, 16), frame_rate_hz=10.0)
    session = ArraySession(SimArraySource(sensor, 8, realtime=True),
                           ReconSettings(method="ml", pulse_rms_s=sensor.scene.pulse_rms_s), mode="frame")
    from spdepth.recon.counts import CountStore

    # the kernels loaded before the clock runs (a cold first call would outlast the session)
    reconstruct(CountStore.from_pairs(*sensor.frame_pairs(0), (16, 16), 1024, 80e-12), session.recon_settings)
    win = ArrayWindow(session, ScanGeometry.from_fov((16, 16), 5.0))
    qtbot.addWidget(win)
    win.show()
    session.start()
    seen = set()
    deadline = time.monotonic() + 30
    while session.state not in (ArrayState.DONE, ArrayState.FAILED) and time.monotonic() < deadline:
        qtbot.wait(30)
        if win.refresh():
            seen.add(win.shown_frame)
    session.wait()
    win.refresh()
    assert session.state == ArrayState.DONE and win.shown_frame == 8
    assert len(seen) >= 2            # the maps changed while the session ran
    depth = win.images["depth"].image
    # a pixel whose frame holds no return by the detection test (recon.detect) shows none (NaN,
    # drawn grey); the tilted plane is everywhere, so nearly every pixel shows its depth
    assert depth.shape == (16, 16) and np.isfinite(depth).mean() > 0.9
    assert "done: frame 8/8" in win.status.text()
    assert not win.grab().isNull()
