"""``spdepth recon`` end to end: real files in, maps/PNG/JSON out, exit status 0 or 2."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
import scipy.io
from matplotlib.image import imread

from spdepth.acq.cli import main
from spdepth.recon.maps import NPZ_KEYS

FACE = "fpi/mannequin_face_8ppp.mat"
PAPER = ["--time-unit-ps", "8", "--window-ps", "16000:48000", "--bin-ps", "40",
         "--pulse-rms-ps", "360"]


def _last_json(text: str) -> dict:
    return json.loads(text.strip().splitlines()[-1])


@pytest.fixture
def face_crop(shared_data, tmp_path):
    """A 60 x 50 crop of the mannequin (nose and cheek) as its own .mat file, to keep tests fast."""
    cells = scipy.io.loadmat(shared_data / FACE)["Ts"][120:180, 140:190]
    path = tmp_path / "crop.mat"
    scipy.io.savemat(path, {"Ts": cells})
    return path


@pytest.mark.parametrize("method", ["uos", "lmf", "ml"])
def test_recon_crop_writes_maps_png_and_json(face_crop, tmp_path, capsys, method):
    out, png = tmp_path / "maps.npz", tmp_path / "maps.png"
    code = main(["recon", str(face_crop), "--method", method, *PAPER, "--max-photons", "15",
                 "--npz", str(out), "--png", str(png), "--json"])
    captured = capsys.readouterr()
    assert code == 0, captured.err
    summary = _last_json(captured.out)
    assert summary["pixels"] == 60 * 50 and summary["shape"] == [60, 50]
    assert summary["method"] == method and summary["read_s"] >= 0 and summary["recon_s"] >= 0
    assert summary["window_ps"] == [16000, 48000] and summary["n_bins"] == 800  # 40 ps bins
    assert summary["pulse_rms_ps"] == pytest.approx(360)
    with np.load(out) as z:
        assert set(NPZ_KEYS) <= set(z.files)
        photons = z["photons"]
        depth = z["depth_m"]
        settings = json.loads(str(z["settings"]))
    assert photons.shape == (60, 50) and photons.max() <= 15
    assert summary["photons"] == int(photons.sum()) > 60 * 50 * 5
    assert settings["method"] == method and settings["max_photons"] == 15
    # the face is about 4.3-4.5 m away (window 16-48 ns covers 2.4-7.2 m)
    assert 4.0 < np.nanmedian(depth) < 4.8
    img = imread(png)
    assert img.shape[0] > 200 and img.std() > 0.05


def test_recon_human_output_and_defaults(face_crop, capsys):
    # no window or bin: the estimator derives them (and the pulse width) from the data
    code = main(["recon", str(face_crop), "--time-unit-ps", "8", "--max-photons", "10", "--method", "lmf"])
    captured = capsys.readouterr()
    assert code == 0, captured.err
    assert "60 x 50 pixels" in captured.out and "depth: median" in captured.out


def test_recon_without_outputs_decides_alike_and_skips_the_spreads(face_crop, tmp_path, capsys):
    # no output file: the summary (which holds no uncertainty) is that of the run writing maps,
    # and its record says the test's spreads were not computed
    opts = [str(face_crop), "--method", "ml", *PAPER, "--max-photons", "15", "--json"]
    assert main(["recon", *opts]) == 0
    bare = _last_json(capsys.readouterr().out)
    assert main(["recon", *opts, "--npz", str(tmp_path / "m.npz")]) == 0
    full = _last_json(capsys.readouterr().out)
    for key in ("pixels_with_estimate", "depth_m_median", "photons"):
        assert bare[key] == full[key]
    assert "not computed" in bare["settings"]["detection"]["uncertainty"]
    assert "not computed" not in full["settings"]["detection"]["uncertainty"]
    # several inputs (one summary line each) as one: the same record
    assert main(["recon", str(face_crop), *opts]) == 0
    both = [json.loads(line) for line in capsys.readouterr().out.strip().splitlines()]
    assert len(both) == 2 and all(s["settings"]["detection"] == bare["settings"]["detection"] for s in both)


def test_recon_point_measurement_ptu(shared_data, tmp_path, capsys):
    png = tmp_path / "point.png"
    code = main(["recon", str(shared_data / "ptu/hydraharp_v20_t3.ptu"), "--channel", "0", "--pulse-rms-ps", "200",
                 "--method", "ml", "--png", str(png), "--json"])
    captured = capsys.readouterr()
    assert code == 0, captured.err
    assert "point measurement" in captured.err
    summary = _last_json(captured.out)
    assert summary["pixels"] == 1 and summary["is_image"] is False
    assert summary["photons"] == 45012
    assert summary["time_unit_ps"] == pytest.approx(64, rel=1e-6)
    assert png.stat().st_size > 10_000



def test_recon_window_without_bins_uses_recons_default_rule(face_crop, capsys):
    # a 64 ns window at a ninth of 360 ps (5 units of 8 ps) is 1600 bins: inside recon's one cap
    # (4096); the CLI's old cap of 1024 bins widened them to 8 units (1000 bins)
    code = main(["recon", str(face_crop), "--time-unit-ps", "8", "--window-ps", "16000:80000",
                 "--pulse-rms-ps", "360", "--max-photons", "5", "--method", "lmf", "--json"])
    captured = capsys.readouterr()
    assert code == 0, captured.err
    assert _last_json(captured.out)["n_bins"] == 1600

@pytest.mark.parametrize("args,message", [
    (["ptu/picoharp_v30_t2.ptu"], "T2 file"),
    ([FACE], "time unit"),
    ([FACE, "--time-unit-ps", "8", "--window-ps", "90000:95000"], "no detections in the window"),
    ([FACE, "--time-unit-ps", "8", "--bin-ps", "13"], "not a whole number"),
    ([FACE, "--time-unit-ps", "8", "--mat-var", "nope"], "no variable 'nope'"),
])
def test_recon_bad_input_exits_2_with_one_line(shared_data, capsys, args, message):
    code = main(["recon", str(shared_data / args[0]), *args[1:]])
    err = capsys.readouterr().err
    assert code == 2
    assert message in err and err.count("\n") == 1 and err.startswith("spdepth recon: error:")


@pytest.mark.parametrize("args", [["--window-ps", "5:2"], ["--max-photons", "0"],
                                  ["--method", "magic"], ["--pulse-rms-ps", "360", "--irf", "x.txt"]])
def test_recon_bad_options_exit_2(face_crop, args, capsys):
    assert main(["recon", str(face_crop), "--time-unit-ps", "8", *args]) == 2
    err = capsys.readouterr().err
    assert err.startswith("spdepth recon: error: ") and err.count("\n") == 1, err


def test_recon_text_file_named_ptu(tmp_path, capsys):
    path = tmp_path / "notes.ptu"
    path.write_text("not a measurement\n")
    assert main(["recon", str(path)]) == 2
    assert "notes.ptu: not a .mat, PTU, HT3, PT3, .npy, .npz or HDF5 file" in capsys.readouterr().err


def test_recon_subprocess(face_crop, tmp_path):
    out = tmp_path / "m.npz"
    proc = subprocess.run(
        [sys.executable, "-m", "spdepth.acq.cli", "recon", str(face_crop), *PAPER, "--max-photons", "15",
         "--method", "uos", "--npz", str(out), "--json"],
        capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert _last_json(proc.stdout)["pixels"] == 3000 and out.stat().st_size > 1000
    bad = subprocess.run(["spdepth", "recon", str(tmp_path / "missing.mat")],
                         capture_output=True, text=True, timeout=300)
    assert bad.returncode == 2 and "missing.mat: no such file" in bad.stderr


def test_a_batch_goes_on_past_a_file_it_cannot_read(small_ptu, tmp_path, capsys):
    import shutil

    a, b, bad = tmp_path / "a.ptu", tmp_path / "b.ptu", tmp_path / "bad.ptu"
    shutil.copy(small_ptu, a)
    shutil.copy(small_ptu, b)
    bad.write_text("not a measurement\n")
    out = tmp_path / "maps"
    assert main(["recon", str(a), str(bad), str(b), "--npz", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[0].startswith(f"spdepth recon: error: {bad}: not a .mat, PTU, HT3, PT3, .npy, .npz or HDF5 file")
    assert err[-1] == "spdepth recon: 2 of 3 inputs reconstructed; 1 could not be: bad.ptu"
    assert len(err) == 2
    assert sorted(p.name for p in out.iterdir()) == ["a.npz", "b.npz"]    # both good ones written


def test_a_stated_pulse_wider_than_the_returns_is_said_with_what_it_does_to_the_uncertainties(
        simulated_ptus, tmp_path, capsys):
    # the simulator's pulse is 362 ps RMS: stated as 720 ps, the model's uncertainties are too large
    bust = simulated_ptus[1][0]
    assert main(["recon", bust, "--pulse-rms-ps", "720", "--npz", str(tmp_path / "wide.npz"), "--json"]) == 0
    captured = capsys.readouterr()
    summary = _last_json(captured.out)
    assert summary["pulse_dispersion"]["dispersion"] < 0.5
    assert "closer to their depths than the pulse model" in captured.err
    assert "--pulse-rms-ps may be too wide" in captured.err
    assert main(["recon", bust, "--pulse-rms-ps", "362", "--npz", str(tmp_path / "right.npz"), "--json"]) == 0
    captured = capsys.readouterr()
    summary = _last_json(captured.out)
    assert 0.8 < summary["pulse_dispersion"]["dispersion"] < 1.25
    assert "pulse model" not in captured.err
    # without an output the summary holds no uncertainty, so the check is not made
    assert main(["recon", bust, "--pulse-rms-ps", "720", "--json"]) == 0
    captured = capsys.readouterr()
    assert _last_json(captured.out)["pulse_dispersion"] is None


@pytest.mark.parametrize("reader_cached, order", [(True, ["reader", "apart", "estimator"]),
                                                  (False, ["apart", "reader", "estimator"])])
def test_the_warm_up_loads_a_cached_reader_before_it_looks_for_a_cold_return_test(monkeypatch, tmp_path,
                                                                                 reader_cached, order):
    # issue 33: a warm install's read waits only for the reader's kernels; on a cold cache the
    # second process compiling the return test starts first, to compile beside them
    import spdepth.acq.readers.picoquant as pq
    import spdepth.recon.estimate as E
    from spdepth.acq.api import KernelWarmUp
    from spdepth.acq.requests import FileReconRequest

    seen = []
    monkeypatch.setattr(E, "module_cached", lambda module: reader_cached)
    monkeypatch.setattr(pq, "warm_up", lambda: seen.append("reader"))
    monkeypatch.setattr(E, "compile_apart", lambda *a, **k: seen.append("apart"))
    monkeypatch.setattr(E, "warm_up", lambda *a, **k: seen.append("estimator"))
    (tmp_path / "scan.ptu").write_bytes(b"")         # the request checks that the file is there
    warm = KernelWarmUp(FileReconRequest(input=str(tmp_path / "scan.ptu"), method="ml"))
    warm.wait_reader()
    assert seen[:order.index("reader") + 1] == order[:order.index("reader") + 1]
    warm.wait()
    assert seen == order
