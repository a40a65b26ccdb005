"""``spdepth simulate``: the PTU file ptufile reads back holds the expected photons per pixel, the
truth sits beside it, and bad options exit with status 2."""

from __future__ import annotations

import json

import numpy as np
import pytest

from spdepth.acq.cli import main
from spdepth.drivers.events import EventKind
from spdepth.drivers.sim import PhotonWorld, load_scene


def _simulate(tmp_path, *extra, name="scan.ptu"):
    out = tmp_path / name
    rc = main(["simulate", "--ptu", str(out), *extra])
    return rc, out


@pytest.mark.parametrize("scene, size", [("bust", "24x16"), ("two-layer", "16x16")])
def test_simulate_writes_ptu_that_ptufile_reads(tmp_path, scene, size):
    import ptufile

    rc, out = _simulate(tmp_path, "--scene", scene, "--size", size, "--ppp", "12", "--seed", "5")
    assert rc == 0
    w, h = (int(v) for v in size.split("x"))
    with ptufile.PtuFile(out) as ptu:
        assert ptu.is_image and ptu.is_t3
        assert ptu.global_resolution == pytest.approx(100e-9)
        assert ptu.tcspc_resolution == pytest.approx(8e-12)
        image = ptu.decode_image(dtime=-1)        # (T, Y, X, C, 1)
        assert image.shape[1:3] == (h, w)
        counts = image.sum(axis=(0, 3, 4)).astype(np.int64)
        n_photons_file = ptu.number_photons
        hist = ptu.decode_image(channel=0, frame=0).sum(axis=(0, 1, 2, 3))  # dtime histogram
    truth = np.load(out.with_name("scan.truth.npz"))
    settings = json.loads(str(truth["settings"]))
    assert settings["seed"] == 5 and settings["shape"] == [h, w]
    # the same seed regenerates the same events: the file holds exactly them, pixel by pixel
    sc = load_scene(scene, (h, w), ppp=12)
    ev = PhotonWorld(sc, seed=5).raster()
    ph = ev[ev["kind"] == EventKind.PHOTON]
    n_dwell = sc.settings.syncs_per_dwell
    ref = np.bincount(ph["sync"] // n_dwell, minlength=h * w).reshape(h, w)
    assert np.array_equal(counts, ref)
    assert n_photons_file == ph.size == settings["n_photons"]
    ref_hist = np.bincount(ph["dtime"], minlength=hist.size)[:hist.size]
    assert np.array_equal(hist, ref_hist)
    # and the counts agree with the truth's mean detections per pixel (Poisson chi-square)
    mean = truth["signal"] + truth["background"]
    assert mean.mean() == pytest.approx(12)
    chi2 = float(((counts - mean) ** 2 / mean).sum())
    assert chi2 / counts.size == pytest.approx(1.0, abs=0.35)
    depth = truth["depth_m"]
    assert depth.shape == ((h, w) if scene == "bust" else (2, h, w))


def test_simulate_file_scene(tmp_path):
    import ptufile

    depth = np.full((16, 20), 2.5)
    depth[:, 10:] = 3.0
    np.save(tmp_path / "depth.npy", depth)
    rc, out = _simulate(tmp_path, "--scene", f"file:{tmp_path / 'depth.npy'}", "--ppp", "8",
                        "--effects", "jitter")
    assert rc == 0
    truth = np.load(out.with_name("scan.truth.npz"))
    assert np.array_equal(truth["depth_m"], depth)
    assert "jitter" in json.loads(str(truth["settings"]))["active_effects"]
    with ptufile.PtuFile(out) as ptu:
        counts = ptu.decode_image(dtime=-1).sum(axis=(0, 3, 4)).astype(np.int64)
    assert counts.shape == (16, 20)
    assert counts.sum() == pytest.approx(8 * 320, rel=0.1)


@pytest.mark.parametrize("args", [
    ["--scene", "nosuch"],
    ["--scene", "bust", "--size", "0x16"],
    ["--scene", "bust", "--size", "16"],
    ["--scene", "bust", "--ppp", "0"],
    ["--scene", "bust", "--ppp", "-5"],
    ["--scene", "bust", "--sbr", "-1"],
    ["--scene", "bust", "--dark-rate-hz", "-10"],
    ["--scene", "bust", "--effects", "glare"],
    ["--scene", "bust", "--resolution-ps", "1"],          # 100,000 bins: no T3 record holds it
    ["--scene", "file:/no/such/depth.npy"],
])
def test_bad_options_exit_2(tmp_path, capsys, args):
    rc = None
    try:
        rc, out = _simulate(tmp_path, "--size", "16x16", *args)
    except SystemExit as exc:      # argparse-level errors
        rc = exc.code
    assert rc == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err and "error" in err[-1]
    assert not (tmp_path / "scan.ptu").exists()


def test_bad_output_name_exits_2(tmp_path):
    rc = main(["simulate", "--scene", "bust", "--size", "16x16", "--ptu", str(tmp_path / "x.bin")])
    assert rc == 2
