"""``spdepth scan`` and ``spdepth replay`` from the command line: files, exit codes, the JSON
summary, refusing to overwrite, and a recording left by ``kill -9`` that still replays."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from spdepth.acq.cli import main
from spdepth.acq.requests import DEFAULT_METHOD
from spdepth.recon.maps import DepthMaps

FILES = ("recording.ptu", "events.jsonl", "maps.npz", "maps.png", "run.json")


def _last_json(out: str) -> dict:
    return json.loads(out.strip().splitlines()[-1])


def test_scan_writes_every_file_and_a_json_summary(tmp_path, capsys):
    out = tmp_path / "run"
    assert main(["scan", "--sim", "--size", "12x10", "--target", "8", "--method", "uos",
                 "--faults", "fifo-overflow@50%", "--out", str(out), "--json"]) == 0
    summary = _last_json(capsys.readouterr().out)
    assert summary["state"] == "done" and summary["pixels"] == 120 and summary["flagged"] == 0
    assert summary["lost_spans"] == 1 and summary["passes"] >= 2
    for name in FILES:
        assert (out / name).stat().st_size > 0, name
    run = json.loads((out / "run.json").read_text())
    assert run["plan"]["target"] == 8 and run["recon"]["method"] == "uos"
    assert run["devices"]["tagger"]["serial"] == "SIMTAG000001"
    assert [f["kind"] for f in run["faults_seen"]] == ["lost-data"]
    maps = DepthMaps.load_npz(out / "maps.npz")
    assert maps.depth_m.shape == (10, 12) and np.all(maps.photons == 8)


def test_scan_refuses_a_non_empty_directory_and_bad_sources(tmp_path, capsys):
    out = tmp_path / "busy"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    assert main(["scan", "--sim", "--size", "4x4", "--out", str(out)]) == 2
    assert "not empty" in capsys.readouterr().err
    assert (out / "notes.txt").read_text() == "mine"
    assert main(["scan", "--size", "4x4", "--out", str(tmp_path / "x")]) == 2
    assert "either --sim or both --galvo" in capsys.readouterr().err
    assert main(["scan", "--sim", "--faults", "bogus@1s", "--out", str(tmp_path / "y")]) == 2
    assert "bogus" in capsys.readouterr().err
    assert main(["scan", "--sim", "--size", "4x4", "--target", "3", "--out", str(out),
                 "--overwrite"]) == 0
    assert (out / "recording.ptu").is_file()


def test_replay_reproduces_the_live_maps_and_reports_its_stream_rate(tmp_path, capsys):
    live = tmp_path / "live"
    assert main(["scan", "--sim", "--size", "10x10", "--target", "10", "--method", "ml",
                 "--out", str(live)]) == 0
    capsys.readouterr()
    again = tmp_path / "again"
    assert main(["replay", str(live / "recording.ptu"), "--out", str(again), "--json"]) == 0
    summary = _last_json(capsys.readouterr().out)
    assert summary["detections"] > 0 and summary["stream_s"] > 0
    a, b = DepthMaps.load_npz(live / "maps.npz"), DepthMaps.load_npz(again / "maps.npz")
    for key in ("tof_s", "background", "signal", "photons", "uncertainty_s", "flags"):
        np.testing.assert_array_equal(getattr(a, key), getattr(b, key), err_msg=key)
    fewer = tmp_path / "fewer"
    assert main(["replay", str(live), "--target", "4", "--method", "lmf", "--out", str(fewer),
                 "--json"]) == 0
    assert np.all(DepthMaps.load_npz(fewer / "maps.npz").photons == 4)
    assert main(["replay", str(live), "--out", str(live), "--overwrite"]) == 2
    assert "own folder" in capsys.readouterr().err


def test_replay_takes_a_simulated_ptu(tmp_path, capsys):
    ptu = tmp_path / "sim.ptu"
    assert main(["simulate", "--scene", "steps", "--size", "16x8", "--ppp", "20",
                 "--ptu", str(ptu)]) == 0
    out = tmp_path / "rep"
    assert main(["replay", str(ptu), "--target", "5", "--pulse-rms-ps", "360", "--out", str(out),
                 "--json"]) == 0
    summary = _last_json(capsys.readouterr().out)
    assert summary["pixels"] == 128 and summary["detections"] > 128 * 10
    assert summary["flagged"] < 10          # a fixed-dwell frame of 20 per pixel: few below 5
    # the file records no estimator of ours: the default method, as scan and recon use
    assert json.loads((out / "run.json").read_text())["recon"]["method"] == DEFAULT_METHOD


def test_replay_refuses_what_is_not_a_recording(tmp_path, capsys):
    bad = tmp_path / "bad.ptu"
    bad.write_bytes(b"not a ptu file at all")
    assert main(["replay", str(bad), "--out", str(tmp_path / "o")]) == 2
    assert "bad.ptu" in capsys.readouterr().err
    assert main(["replay", str(tmp_path / "missing"), "--out", str(tmp_path / "o2")]) == 2
    assert not (tmp_path / "o").exists() and not (tmp_path / "o2").exists()


@pytest.mark.parametrize("kill_after_bytes", [60_000, 300_000])
def test_kill_9_mid_scan_leaves_a_recording_that_replays(tmp_path, kill_after_bytes):
    import ptufile

    rec = tmp_path / "rec"
    # 128x128 x 15 records about 1.1 MB: both kill points fall mid-scan on a quiet machine too
    proc = _scan_until_recording(rec, "128x128", kill_after_bytes)
    ptu = rec / "recording.ptu"
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait(10)
    assert not (rec / "run.json").exists()       # it really died mid-scan
    with ptufile.PtuFile(ptu) as pf:              # count 0: ptufile reads what is there
        n = pf.number_records
        assert n > 0
        assert pf.decode_records().size == n
    out = tmp_path / "replayed"
    proc2 = subprocess.run([sys.executable, "-m", "spdepth.acq.cli", "replay", str(rec), "--out", str(out),
                            "--json"], capture_output=True, text=True, timeout=120)
    assert proc2.returncode == 0, proc2.stderr
    summary = _last_json(proc2.stdout)
    assert summary["state"] == "done" and summary["detections"] > 0
    # the scan was cut: pixels it never finished are flagged, the others are complete
    run = json.loads((out / "run.json").read_text())
    assert 0 < sum(run["flag_reasons"].values()) < 128 * 128
    assert set(run["flag_reasons"]) == {"INCOMPLETE"}


def test_recon_of_a_recording_gives_the_sessions_maps(tmp_path, capsys):
    """`spdepth recon DIR/recording.ptu` reads the photons the session kept (passes from the event
    log, re-acquired pixels included), so the same method gives the live maps."""
    live = tmp_path / "live"
    assert main(["scan", "--sim", "--size", "10x8", "--target", "8", "--method", "lmf",
                 "--faults", "fifo-overflow@30%", "--out", str(live)]) == 0
    out = tmp_path / "maps.npz"
    assert main(["recon", str(live / "recording.ptu"), "--method", "lmf", "--pulse-rms-ps", "360",
                 "--window-ps", "0:32040", "--bin-ps", "40", "--max-photons", "8",
                 "--npz", str(out)]) == 0
    a, b = DepthMaps.load_npz(live / "maps.npz"), DepthMaps.load_npz(out)
    np.testing.assert_array_equal(a.photons, b.photons)
    np.testing.assert_array_equal(a.tof_s, b.tof_s)


def _default_sigint() -> None:
    """In the child before it starts: Ctrl-C's default, as in a terminal. A suite started in the
    background of a script has SIGINT ignored (``(.ci/run &)``), which children inherit and Python
    keeps (the CLI, as shells expect, does not undo it): the scans ran to "done" through it on a
    clean clone's suite, in an xdist worker."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def _scan_until_recording(rec, size="512x512", min_bytes=100_000, extra=()):
    """A scan in a child process, returned once its recording holds ``min_bytes`` (big enough to
    be still running after two more CLI processes: the simulator scans 128x128 in a few s)."""
    proc = subprocess.Popen([sys.executable, "-m", "spdepth.acq.cli", "scan", "--sim", "--size", size,
                             "--target", "15", "--out", str(rec), *extra],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, preexec_fn=_default_sigint)
    ptu = rec / "recording.ptu"
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and proc.poll() is None:
        if ptu.exists() and ptu.stat().st_size > min_bytes:
            break
        time.sleep(0.01)
    assert proc.poll() is None, "the scan ended before it could be interrupted"
    return proc


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_ctrl_c_and_sigterm_abort_cleanly_keep_the_files_and_the_json_summary(tmp_path, sig):
    rec = tmp_path / "rec"
    proc = _scan_until_recording(rec, extra=["--json"])
    proc.send_signal(sig)
    out, err = proc.communicate(timeout=60)
    assert proc.returncode == 130, err
    assert ("interrupted" if sig == signal.SIGINT else "terminated") in err
    assert "Traceback" not in err
    summary = _last_json(out)                  # the summary is still the last stdout line
    assert summary["state"] == "aborted" and summary["out"] == str(rec)
    run = json.loads((rec / "run.json").read_text())
    assert run["state"] == "aborted"
    import ptufile

    with ptufile.PtuFile(rec / "recording.ptu") as pf:   # closed cleanly: record count patched in
        assert pf.number_records == run["statistics"]["records_recorded"] > 0
    assert (rec / "maps.npz").is_file()


def test_a_folder_in_use_by_a_running_session_is_refused(tmp_path):
    rec = tmp_path / "rec"
    proc = _scan_until_recording(rec, min_bytes=1000)
    try:
        for extra in ([], ["--overwrite"]):
            second = subprocess.run([sys.executable, "-m", "spdepth.acq.cli", "scan", "--sim",
                                     "--size", "4x4", "--out", str(rec), *extra],
                                    capture_output=True, text=True, timeout=120)
            assert second.returncode == 2, second.stderr
            assert "in use by a running session" in second.stderr
            assert len(second.stderr.strip().splitlines()) == 1
    finally:
        proc.send_signal(signal.SIGINT)
        proc.communicate(timeout=60)
    assert json.loads((rec / "run.json").read_text())["state"] == "aborted"   # untouched by the second


def test_scan_on_a_missing_device_is_one_line_and_leaves_no_directory(tmp_path, capsys):
    out = tmp_path / "never"
    assert main(["scan", "--galvo", str(tmp_path / "ttyNOPE"), "--tagger", "usb:1209:7a64",
                 "--sync-rate-hz", "1e7", "--out", str(out)]) == 3
    err = capsys.readouterr().err
    assert "ttyNOPE" in err and "Traceback" not in err and len(err.strip().splitlines()) == 1
    assert not out.exists()
    # a URL scheme pyserial has no handler for is the caller's mistake, said in one line too
    assert main(["scan", "--galvo", "nosuchscheme://x", "--tagger", "usb:1209:7a64",
                 "--sync-rate-hz", "1e7", "--out", str(out)]) == 2
    assert "nosuchscheme" in capsys.readouterr().err


def test_ctrl_c_closes_the_window_aborts_its_scan_and_exits_130(tmp_path):
    runs = tmp_path / "runs"                   # the window's runs folder: one folder per run
    env = {**os.environ, "QT_QPA_PLATFORM": "offscreen", "XDG_CONFIG_HOME": str(tmp_path / "cfg")}
    proc = subprocess.Popen([sys.executable, "-m", "spdepth.acq.cli", "gui", "--sim", "--size",
                             "128x128", "--target", "15", "--runs-dir", str(runs)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and proc.poll() is None:
        if any(p.stat().st_size > 100_000 for p in runs.glob("*/recording.ptu")):
            break
        time.sleep(0.01)
    assert proc.poll() is None, "the scan ended before it could be interrupted"
    proc.send_signal(signal.SIGINT)
    _out, err = proc.communicate(timeout=90)
    assert proc.returncode == 130, err
    assert "interrupted; closing the window" in err and "Traceback" not in err
    (run,) = runs.glob("*/run.json")
    assert json.loads(run.read_text())["state"] == "aborted"
    assert (run.parent / "maps.npz").is_file()


@pytest.mark.parametrize("state, said", [(None, True), ("armed", True), ("running", False)])
def test_a_command_still_preparing_says_why(capsys, state, said):
    # a fresh install compiles every kernel on first use: a minute of silence without this line
    from types import SimpleNamespace

    from spdepth.acq.commands._session import PreparingNotice

    with PreparingNotice("scan", after_s=0.05) as notice:
        if state is not None:
            notice.session = SimpleNamespace(state=SimpleNamespace(value=state))
        notice._timer.join(30)             # the notice is due and has been given, or not
        assert not notice._timer.is_alive()
    assert ("spdepth scan: preparing" in capsys.readouterr().err) == said


def test_a_quick_command_says_nothing_about_preparing(capsys):
    from spdepth.acq.commands._session import PreparingNotice

    with PreparingNotice("scan", after_s=30.0) as notice:
        pass                         # a command done before the notice is due: it is cancelled
    notice._timer.join(30)           # a cancelled timer ends at once, without a word
    assert not notice._timer.is_alive()
    assert capsys.readouterr().err == ""


def test_a_first_run_says_which_kernel_it_compiles():
    import io

    from numba import njit

    from spdepth.acq.commands._session import CompileNotice

    def inner(x):
        return x + 1

    def outer(x):
        return k_inner(x) * 2

    inner.__module__ = outer.__module__ = "spdepth.acq.made_up"
    k_inner = njit(inner)
    k_outer = njit(outer)
    out = io.StringIO()
    with CompileNotice("spdepth test", stream=out) as notice:
        assert k_outer(1) == 4        # compiles outer and, inside it, inner: one line
        assert k_outer(2) == 6        # compiled already: nothing more
    assert notice.count == 1
    assert out.getvalue().startswith("spdepth test: compiling kernel 1, acq.made_up.outer (first run")
    k_other = njit(lambda x: x)       # not ours (module of this test): not listed
    with CompileNotice("spdepth test", stream=out) as notice:
        k_other(1)
    assert notice.count == 0
