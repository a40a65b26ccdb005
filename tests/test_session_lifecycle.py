"""Session lifecycles and the source interface: no thread outlives a session, the time limit ends a
big scan (what follows bounded by what it reached), a failing live-recon worker or subscriber or a
removed output folder ends cleanly with one line, survived faults are listed, damaged recordings
are refused or replayed with a warning, and snapshots never hold half a reconstruction batch."""

from __future__ import annotations

import json
import logging
import shutil
import threading

import numpy as np
import pytest

from spdepth.acq.errors import OutputError, RecordingError
from spdepth.acq.flags import ACQUIRING, AcqFlag
from spdepth.acq.instruments import open_sim
from spdepth.acq.recording import ReplaySource, recon_settings_from_dict
from spdepth.acq.scan_source import ScanSource
from spdepth.acq.session import Session, SessionState
from spdepth.acq.sources import RETRIED, FaultRecord, Source, feed_passes
from spdepth.recon.maps import DepthMaps
from tests.sessions import replay_session as _replay
from tests.sessions import sim_session as _session
from tests.waiting import wait_until


def _copy(recording, tmp_path):
    dst = tmp_path / "rec"
    shutil.copytree(recording, dst)
    return dst


def _own_threads():
    return {t for t in threading.enumerate() if t.name in ("live-recon", "acq-session",
                                                            "tagger-reader", "session-subscriber")}


# ---- sources --------------------------------------------------------------------------------------
def test_both_sources_satisfy_the_source_protocol(recording):
    with open_sim("bust", (4, 4), ppp=10, seed=1) as inst:
        assert isinstance(ScanSource(inst.galvo, inst.tagger), Source)
    assert isinstance(ReplaySource(recording), Source)


class MemorySource:
    """A third kind of source, as a vendor tagger would be: passes of event chunks held in
    memory, faults reported through the host."""

    name = "memory"
    lost_action = "kept as delivered"

    def __init__(self, passes, sync_period_s=None):
        self.passes = passes
        self.sync_period_s = sync_period_s
        self.warnings = []
        self.first_read_t = None
        self.closed = False

    def default_gate_target(self, plan):
        return plan.target if plan.mode == "gated" else None

    def arm(self, host):
        host.fault("memory-note", "armed from memory", "none needed")

    def run(self, host):
        feed_passes(host, self.passes)
        return AcqFlag.INCOMPLETE

    def flush(self):
        """Nothing is buffered: the passes are in memory."""

    def close(self):
        self.closed = True

    def health(self, recent, error):
        return {"tagger": "failed" if error is not None else "ok"}

    def identities(self):
        return {"tagger": {"model": "in memory"}}

    def statistics(self):
        return {"records_recorded": None}


def test_any_source_gives_the_same_maps_as_the_replay_it_was_taken_from(recording):
    from spdepth.acq.plan import ScanPlan

    rep = _replay(recording)
    assert rep.run() == SessionState.DONE
    src = ReplaySource(recording)
    passes = [(g, [c.copy() for c in chunks]) for g, chunks in src.segments()]
    mem = MemorySource(passes, src.sync_period_s)
    assert isinstance(mem, Source)
    plan = ScanPlan.from_dict(src.info.plan)
    s = Session(plan, rep.live_recon.requested, mem)
    assert s.run() == SessionState.DONE and mem.closed
    for k in ("depth_m", "background", "signal", "flags"):
        np.testing.assert_array_equal(getattr(s.maps(), k), getattr(rep.maps(), k), err_msg=k)
    assert np.all(rep.exposure_s() > 0)
    np.testing.assert_array_equal(s.exposure_s(), rep.exposure_s())
    run = s.run_record()
    assert run["source"] == "memory" and run["devices"] == {"tagger": {"model": "in memory"}}
    assert [f["kind"] for f in run["faults_seen"]] == ["memory-note"]
    assert s.snapshot().health == {"tagger": "ok"}


def test_fault_records_are_frozen_and_serialise():
    f = FaultRecord("usb-timeout", 1.5, "a read timed out", RETRIED)
    assert f.to_dict() == {"kind": "usb-timeout", "t_s": 1.5, "what": "a read timed out",
                           "action": RETRIED}
    with pytest.raises(AttributeError):
        f.kind = "x"


# ---- lifecycles -----------------------------------------------------------------------------------
def test_a_session_built_and_never_started_leaves_no_thread(recording):
    before = _own_threads()
    with open_sim("bust", (8, 8), ppp=10, seed=2) as inst:
        s = _session(inst, (8, 8))
        assert _own_threads() == before, "building a session started a thread"
        del s
    rep = _replay(recording)
    assert _own_threads() == before
    # a finished session leaves none either (the worker is joined at the end)
    assert rep.run() == SessionState.DONE
    wait_until(lambda: _own_threads() == before, 10, what="session threads to end")


def test_the_time_limit_ends_a_big_scan_and_what_follows_is_bounded_by_what_it_reached(tmp_path):
    """Issue 33: the time limit stops the scan (the frame's rest is flagged TIME_LIMIT, not scanned
    to its end), only the pixels reached go to the reconstruction, and run.json stays small: what
    bounds the wait after the limit. The wall time itself, start to exit of the command, is
    measured by ``spdepth bench startup --scan`` (a benchmark, not a timed test)."""
    with open_sim("bust", (1024, 1024), ppp=10, seed=3) as inst:
        s = _session(inst, (1024, 1024), tmp_path, time_limit_s=1.0)
        assert s.run() == SessionState.DONE, s.error
    run = json.loads((tmp_path / "run.json").read_text())
    assert run["flag_reasons"].get("TIME_LIMIT", 0) > 1000
    st = s.store
    reached = int(np.count_nonzero((st.count > 0) | (st.dwells > 0)))
    assert 0 < reached < 1024 * 1024 - 1000
    assert s.live_recon.submitted == s.live_recon.processed == reached
    assert "flagged_pixels" not in run
    assert (tmp_path / "run.json").stat().st_size < 50_000
    with np.load(tmp_path / "maps.npz") as z:
        flags = z["acq_flags"]
    assert flags.shape == (1024, 1024) and not np.any(flags == ACQUIRING)
    assert int(np.count_nonzero(flags == AcqFlag.TIME_LIMIT)) == run["flag_reasons"]["TIME_LIMIT"]
    # the progress bar's count: pixels that reached the target, not every final one
    snap = s.snapshot()
    assert snap.pixels_final == 1024 * 1024
    assert snap.pixels_complete == int(np.count_nonzero(flags == AcqFlag.COMPLETE)) < 1024 * 1024 - 1000
    maps = DepthMaps.load_npz(tmp_path / "maps.npz")       # still the recon format
    assert maps.depth_m.shape == (1024, 1024)


def test_a_time_limited_scan_reconstructs_only_what_it_reached_and_writes_those_pixels(
        tmp_path, monkeypatch):
    """Issue 33: pixels the galvo never reached are flagged and not reconstructed (no value is
    made up for them), and a large frame that reached few pixels writes them alone to maps.npz
    (the sparse layout; here from any size), read back whole by DepthMaps.load_npz."""
    from spdepth.acq import session as session_mod
    from spdepth.recon.maps import PixelFlag, npz_arrays

    monkeypatch.setattr(session_mod, "SPARSE_MIN_PIXELS", 0)
    with open_sim("bust", (1024, 1024), ppp=10, seed=4) as inst:
        s = _session(inst, (1024, 1024), tmp_path, time_limit_s=0.5)
        assert s.run() == SessionState.DONE, s.error
    st = s.store
    reached = (st.count > 0) | (st.dwells > 0)
    assert 0 < np.count_nonzero(reached) < 1024 * 1024 // 2
    assert s.live_recon.submitted == np.count_nonzero(reached)      # each reached pixel, once
    live = s.live_recon.maps()
    with np.load(tmp_path / "maps.npz") as z:
        assert str(z["layout"]) == "pixels"
        np.testing.assert_array_equal(z["pixels"], np.flatnonzero(reached))
        assert z["depth_m"].shape == (np.count_nonzero(reached),)
        assert z["acq_flags"].shape == (1024, 1024)                   # whole in either layout
        full = npz_arrays(z)
    maps = DepthMaps.load_npz(tmp_path / "maps.npz")
    for name in ("tof_s", "depth_m", "background", "signal", "photons", "uncertainty_s", "flags"):
        np.testing.assert_array_equal(getattr(maps, name), getattr(live, name), err_msg=name)
    np.testing.assert_array_equal(full["exposure_s"], s.exposure_s())
    never = ~reached.reshape(1024, 1024)
    assert np.all(full["acq_flags"][never] == AcqFlag.TIME_LIMIT)
    assert np.all(maps.flags[never] == PixelFlag.NO_PHOTONS) and np.all(maps.photons[never] == 0)
    assert np.all(np.isnan(maps.background[never]) & np.isnan(maps.depth_m[never]))
    assert (tmp_path / "maps.npz").stat().st_size < 4_000_000


def test_a_live_recon_worker_failure_ends_the_session_failed_with_one_line(recording, tmp_path,
                                                                          caplog):
    import dataclasses

    from spdepth.acq.plan import ScanPlan
    from spdepth.recon.model import Binning

    # no pulse width given, and a window no detection falls in: the worker cannot estimate one
    src = ReplaySource(recording)
    plan = ScanPlan.from_dict(src.info.plan)
    rec = recon_settings_from_dict(src.info.recon, max_photons=plan.target)
    b = rec.binning
    settings = dataclasses.replace(rec, pulse_rms_s=None, irf=None, binning=Binning(
        b.time_unit_s, 30000, 30000 + 100 * b.bin_width, b.bin_width))
    rep = Session(plan, settings, src, out_dir=tmp_path / "out")
    with caplog.at_level(logging.WARNING):
        assert rep.run() == SessionState.FAILED
    assert "pulse" in str(rep.error)
    run = json.loads((tmp_path / "out" / "run.json").read_text())
    assert run["state"] == "failed" and "pulse" in run["error"]
    errors = [r for r in caplog.records if r.levelno >= logging.ERROR]
    assert len(errors) == 1 and errors[0].exc_info is None, [r.getMessage() for r in errors]
    assert not any(t.name == "live-recon" for t in threading.enumerate())


def test_a_failing_subscriber_is_logged_once_and_unsubscribed_alone(recording, caplog):
    rep = _replay(recording)
    calls, good = [], []

    def broken(snap):
        calls.append(snap)
        raise RuntimeError("subscriber bug")

    bad_sub = rep.subscribe(broken, max_hz=100)
    good_sub = rep.subscribe(good.append, max_hz=100)
    with caplog.at_level(logging.ERROR):
        assert rep.run() == SessionState.DONE
        assert good_sub.join(10) and bad_sub.join(10)
    assert len(calls) == 1
    assert [r for r in caplog.records if "subscriber" in r.getMessage()].__len__() == 1
    assert good and good[-1].state == "done" and good[-1].pixels_final == 256


def test_snapshots_never_hold_half_a_batch(recording):
    # uos gives every reconstructed pixel a finite background: a depth without one is half a batch
    rep = _replay(recording)
    bad = []

    def check(snap):
        torn = np.isfinite(snap.depth_m) & ~np.isfinite(snap.background)
        if torn.any():
            bad.append(int(torn.sum()))

    sub = rep.subscribe(check, max_hz=1000)
    assert rep.run() == SessionState.DONE
    assert sub.join(10)
    assert not bad


def test_an_output_folder_removed_mid_scan_fails_the_session_with_one_error(tmp_path, caplog):
    out = tmp_path / "out"
    with open_sim("bust", (16, 16), ppp=10, seed=4, galvo_options={"pace": 1.0}) as inst:
        s = _session(inst, (16, 16), out)
        with caplog.at_level(logging.WARNING):
            s.start()
            wait_until(lambda: s.snapshot().pixels_final > 5, 30, what="a few pixels")
            shutil.rmtree(out)
            assert s.wait(30) == SessionState.FAILED
    assert isinstance(s.error, OutputError) and str(out) in str(s.error)
    errors = [r for r in caplog.records if r.levelno >= logging.ERROR]
    assert len(errors) == 1 and errors[0].exc_info is None, [r.getMessage() for r in errors]
    assert not out.exists()


# ---- faults ---------------------------------------------------------------------------------------
@pytest.mark.parametrize("fault", ["usb-timeout@50%", "partial-read@50%"])
def test_survived_faults_are_listed_with_nothing_lost(tmp_path, fault):
    kind = fault.split("@")[0]
    with open_sim("bust", (10, 10), ppp=10, seed=5, faults=fault,
                  galvo_options={"pace": 1.0}) as inst:
        s = _session(inst, (10, 10), tmp_path)
        assert s.run() == SessionState.DONE, s.error
    run = json.loads((tmp_path / "run.json").read_text())
    seen = [f for f in run["faults_seen"] if f["kind"] == kind]
    assert len(seen) == 1, run["faults_seen"]
    assert seen[0]["action"] == RETRIED and not s.lost and s.flagged_pixels().size == 0
    assert sum(1 for line in (tmp_path / "events.jsonl").open()
               if json.loads(line).get("kind") == kind) == 1


# ---- damaged recordings ---------------------------------------------------------------------------
def _corrupt_tag(ptu, tag: str) -> None:
    """Overwrite the first character of tag ``tag``'s string value (a JSON object) with '#'."""
    data = bytearray(ptu.read_bytes())
    at = data.index(tag.encode())
    value = data.index(b"{", at)
    data[value] = ord("#")
    ptu.write_bytes(bytes(data))


@pytest.mark.parametrize("tag", ["SPDepth_Plan", "SPDepth_Recon"])
def test_a_recording_with_a_damaged_header_is_refused_naming_file_and_tag(recording, tmp_path,
                                                                          tag):
    from spdepth.acq.readers.picoquant import read_ptu

    rec = _copy(recording, tmp_path)
    _corrupt_tag(rec / "recording.ptu", tag)
    with pytest.raises(RecordingError, match=tag) as info:
        ReplaySource(rec)
    assert "recording.ptu" in str(info.value)
    with pytest.raises(RecordingError, match=tag):     # `spdepth recon FILE` reads it too
        read_ptu(rec / "recording.ptu")


def _replay_warnings(rec, tmp_path, caplog):
    with caplog.at_level(logging.WARNING):
        rep = _replay(rec, tmp_path / "out")
        state = rep.run()
    run = json.loads((tmp_path / "out" / "run.json").read_text())
    # each warning is said once, by the caller (the CLI's summary, the window's banner): the
    # source and the session do not log it as well
    logged = [r.getMessage() for r in caplog.records
              if r.levelno == logging.WARNING and any(w in r.getMessage() for w in run["warnings"])]
    assert logged == []
    return state, run, run["warnings"]


def test_replay_of_a_truncated_event_log_warns(recording, tmp_path, caplog):
    rec = _copy(recording, tmp_path)
    lines = (rec / "events.jsonl").read_text().splitlines(keepends=True)
    (rec / "events.jsonl").write_text("".join(lines[:len(lines) // 2]))
    state, run, warned = _replay_warnings(rec, tmp_path, caplog)
    assert state == SessionState.DONE
    assert len(warned) == 1 and "events.jsonl is truncated" in warned[0]
    assert any("events.jsonl is truncated" in w for w in run["warnings"])


def test_replay_without_its_event_log_warns(recording, tmp_path, caplog):
    rec = _copy(recording, tmp_path)
    (rec / "events.jsonl").unlink()
    _, run, warned = _replay_warnings(rec, tmp_path, caplog)
    assert len(warned) == 1 and "events.jsonl is missing" in warned[0]
    assert run["warnings"]


def test_replay_of_a_cut_ptu_warns(recording, tmp_path, caplog):
    rec = _copy(recording, tmp_path)
    ptu = rec / "recording.ptu"
    data = ptu.read_bytes()
    ptu.write_bytes(data[:len(data) * 2 // 3 + 2])       # cut mid-record, count still patched
    state, run, warned = _replay_warnings(rec, tmp_path, caplog)
    assert state == SessionState.DONE
    assert len(warned) == 1 and "recording.ptu is truncated" in warned[0]
    assert any("truncated" in w for w in run["warnings"])
    assert run["flag_reasons"].get("INCOMPLETE", 0) > 0


def test_replay_of_a_killed_sessions_recording_is_no_warning_by_itself(recording, tmp_path,
                                                                      caplog):
    from spdepth.acq.ptu import patch_record_count

    rec = _copy(recording, tmp_path)
    patch_record_count(rec / "recording.ptu", 0)          # as after kill -9: count never patched
    state, run, warned = _replay_warnings(rec, tmp_path, caplog)
    assert state == SessionState.DONE and warned == [] and run["warnings"] == []


def test_finishing_a_session_says_which_file_it_writes(tmp_path):
    """Issue 33: the files written after a session (maps.png, points.ply) report their progress:
    each as it starts, then all written, and each exists once reported done."""
    from spdepth.acq.api import finish_session

    seen = []

    def progress(name, done, total):
        # the files reported done so far exist; the one starting does not yet
        seen.append((name, done, total, [p.name for p in sorted(tmp_path.glob("*.p*"))
                                         if p.name in ("maps.png", "points.ply")]))

    with open_sim("bust", (16, 16), ppp=10, seed=2) as inst:
        s = _session(inst, (16, 16), tmp_path)
        assert s.run() == SessionState.DONE, s.error
    summary = finish_session(s, tmp_path, "t", progress=progress)
    assert seen == [("maps.png", 0, 2, []), ("points.ply", 1, 2, ["maps.png"]),
                    ("", 2, 2, ["maps.png", "points.ply"])]
    assert summary["points"] > 0
