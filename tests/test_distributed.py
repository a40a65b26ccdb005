"""``spdepth recon --dask``: a LocalCluster of 2 worker processes gives the single-process maps bit
for bit, per file and per block of rows of one recording, also when a worker dies mid-run."""

from __future__ import annotations

import os
import signal

import numpy as np
import pytest

pytest.importorskip("distributed")

from spdepth.acq import distributed as D  # noqa: E402
from spdepth.acq.cli import main  # noqa: E402
from spdepth.acq.errors import RequestError  # noqa: E402
from spdepth.acq.requests import FileReconRequest  # noqa: E402
from spdepth.recon.maps import NPZ_KEYS, DepthMaps  # noqa: E402

MODEL = ["--window-ps", "0:100000", "--bin-ps", "40", "--pulse-rms-ps", "360", "--max-photons", "12"]


def _request(path, method="uos", **changes):
    """The request `spdepth recon PATH --method M MODEL` makes."""
    model = dict(window_s=(0.0, 100e-9), bin_s=40e-12, pulse_rms_s=360e-12, max_photons=12)
    return FileReconRequest(input=path, method=method, **{**model, **changes})


def _same(a: DepthMaps, b: DepthMaps):
    for k in NPZ_KEYS:
        if k == "settings":
            assert a.settings == b.settings
        else:
            x, y = getattr(a, k), getattr(b, k)
            assert x.dtype == y.dtype and np.array_equal(x, y, equal_nan=True), k


def _single(path, tmp, method="uos", reflectors=1):
    out = tmp / f"single-{os.path.basename(path)}-{method}-{reflectors}.npz"
    # tests share the module's folder: the same single run is made again (--overwrite)
    assert main(["recon", path, "--method", method, *MODEL, "--reflectors", str(reflectors),
                 "--npz", str(out), "--overwrite"]) == 0
    return DepthMaps.load_npz(out)


def _blocks(client, path, method="uos", on_submitted=None, reflectors=1, spreads=True):
    unit_s = D._image_and_unit(path, None)[4]
    settings = D.block_settings(_request(path, method, reflectors=reflectors), unit_s)
    # small chunks and blocks, so that rows, chunks and blocks all cut across each other
    plan = D.plan_blocks(path, unit_s, chunk_records=3001, block_pixels=7 * 40 + 13)
    assert len(plan.starts) > 3 and len(plan.rows) > 3
    return D.reconstruct_blocks(client, plan, settings, unit_s, on_submitted=on_submitted, spreads=spreads)


def test_local_cluster_listens_on_loopback_only(client):
    info = client.scheduler_info()
    assert client.scheduler.address.startswith("tcp://127.0.0.1:")
    assert len(info["workers"]) == 2
    assert all(a.startswith("tcp://127.0.0.1:") for a in info["workers"])


def test_blocks_of_one_recording_give_the_single_process_maps(client, simulated_ptus):
    d, paths = simulated_ptus
    for method in ("uos", "ml", "lmf"):
        single = _single(paths[0], d, method)
        _same(_blocks(client, paths[0], method), single)
        if method == "lmf":
            # its test's spreads tempered by the frame's dispersion, which the blocks pool before their tests
            assert "tempered" in single.settings["pulse_dispersion"]["applied"]


def test_blocks_read_the_rows_the_neighbours_support_needs(client, tmp_path):
    # 2 detections a pixel: most pixels hold a return only by their neighbours' support, which
    # pools the pixels within SUPPORT_RADIUS rows: a block's halo must hold as many rows
    from spdepth.recon.detect import NEIGHBOUR_ROWS, SUPPORT_RADIUS
    from tests.conftest import _simulate

    assert NEIGHBOUR_ROWS >= SUPPORT_RADIUS
    faint = str(_simulate(tmp_path / "faint.ptu", "--scene", "bust", "--size", "80x60", "--ppp", "2",
                          "--seed", "5"))
    single = _single(faint, tmp_path, "ml")
    alone = np.isfinite(np.asarray(single.depth_m)).mean()
    _same(_blocks(client, faint, "ml"), single)
    assert alone > 0.5


def test_blocks_without_spreads_decide_alike_and_compute_no_spread(client, simulated_ptus):
    # no output file: the summary holds no uncertainty, so no block computes the test's spreads
    _, paths = simulated_ptus
    lean = _blocks(client, paths[0], "ml", spreads=False)
    full = _blocks(client, paths[0], "ml")
    np.testing.assert_array_equal(lean.depth_m, full.depth_m)
    np.testing.assert_array_equal(lean.flags, full.flags)
    assert "not computed" in lean.settings["detection"]["uncertainty"]
    assert "not computed" not in full.settings["detection"]["uncertainty"]


def test_blocks_with_several_surfaces_give_the_single_process_maps(client, simulated_ptus):
    d, paths = simulated_ptus
    for reflectors in (2, "auto"):
        blocks = _blocks(client, paths[2], reflectors=reflectors)
        _same(blocks, _single(paths[2], d, reflectors=reflectors))
        assert blocks.surfaces.shape == blocks.shape and blocks.tof_s.ndim == 3


def test_a_worker_killed_mid_run_is_retried_and_the_maps_are_the_same(client, simulated_ptus):
    from distributed import wait

    d, paths = simulated_ptus
    killed = []

    def kill_a_worker_holding_results(futures):
        wait(futures[0])                                   # a chunk's photons now live on a worker
        (addr,) = list(client.who_has(futures[0]).values())[0][:1]
        pid = client.run(os.getpid, workers=[addr])[addr]
        os.kill(pid, signal.SIGKILL)
        killed.append(pid)

    maps = _blocks(client, paths[1], on_submitted=kill_a_worker_holding_results)
    assert killed
    _same(maps, _single(paths[1], d))
    client.wait_for_workers(2, timeout=30)                 # the nanny restarted it


def test_many_files_one_task_each_equal_the_single_runs(client, simulated_ptus, tmp_path):
    d, paths = simulated_ptus
    (tmp_path / "dask").mkdir()
    requests = [_request(p, out=str(tmp_path / "dask" / os.path.basename(p).replace(".ptu", ".npz")))
                for p in paths]
    summaries = D._per_file(requests, client)
    assert [s["input"] for s in summaries] == paths
    # the one note: the file's detections, those used and why (max_photons)
    assert all(s["notes"] in ([], [s["photons_account"]]) and "times_s" not in str(s["settings"])
               for s in summaries)
    # the command without --dask runs the same per-file path in this process
    assert main(["recon", *paths, "--method", "uos", *MODEL, "--npz", str(tmp_path / "here")]) == 0
    for p in paths:
        name = os.path.basename(p).replace(".ptu", ".npz")
        single = _single(p, d)
        _same(DepthMaps.load_npz(tmp_path / "dask" / name), single)
        _same(DepthMaps.load_npz(tmp_path / "here" / name), single)


def test_addresses():
    assert D.parse_address("local:3") == ("local", 3)
    assert D.parse_address("tls://sched.lab:8786") == ("remote", "tls://sched.lab:8786")
    for bad in ("local:x", "local:0", "nonsense"):
        with pytest.raises(RequestError, match=bad):
            D.parse_address(bad)


def test_a_model_left_to_the_data_is_not_split(simulated_ptus):
    _, paths = simulated_ptus
    for left in ("window_s", "bin_s", "pulse_rms_s"):
        assert D.block_settings(_request(paths[0], **{left: None}), 8e-12) is None
    given = D.block_settings(_request(paths[0]), 8e-12)
    assert given.binning.n_bins == 2500 and given.max_photons == 12


@pytest.mark.slow
def test_a_dask_run_writes_what_the_in_process_run_writes(simulated_ptus, tmp_path, capsys):
    """``--dask local:1`` on one recording takes the block path, and the library finishes its
    maps: the same npz (keys, arrays, settings with the geometry of --fov-deg and the range
    offset), the same pulse shape file, a picture, and the same summary but for timings, paths and
    the block counts (the block path dropped --save-irf, the offset and the geometry before)."""
    import json

    _, paths = simulated_ptus
    runs = {}
    for name, dask in (("here", []), ("dask", ["--dask", "local:1"])):
        d = tmp_path / name
        d.mkdir()
        assert main(["recon", paths[0], *MODEL, "--fov-deg", "20", "--range-offset-m", "1.5",
                     "--npz", str(d / "maps.npz"), "--png", str(d / "maps.png"),
                     "--save-irf", str(d / "irf.csv"), "--json", *dask]) == 0
        summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
        runs[name] = (d, summary)
    (here, s_here), (there, s_dask) = runs["here"], runs["dask"]
    assert s_dask["blocks"] >= 1 and "blocks" not in s_here       # the block path was taken
    a, b = DepthMaps.load_npz(here / "maps.npz"), DepthMaps.load_npz(there / "maps.npz")
    _same(a, b)
    assert a.settings["range_offset_m"] == 1.5 and "geometry" in a.settings
    assert (here / "irf.csv").read_text() == (there / "irf.csv").read_text()
    assert (there / "maps.png").stat().st_size > 0
    # the pulse model's dispersion pooled from the blocks' terms is the whole frame's, to the bit
    # (ml with a Gaussian pulse: every uncertainty scaled by it, so _same above checks it too)
    ignore = {"read_s", "recon_s", "load_s", "out", "png", "save_irf", "request", "chunks", "blocks"}
    assert s_here["pulse_dispersion"] is not None and s_dask["pulse_dispersion"] == s_here["pulse_dispersion"]
    assert a.settings["pulse_dispersion"]["applied"]
    assert {k: v for k, v in s_here.items() if k not in ignore} == \
        {k: v for k, v in s_dask.items() if k not in ignore}
    assert s_dask["save_irf"] == str(there / "irf.csv") and s_dask["range_offset_m"] == 1.5


def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_a_scheduler_address_with_nothing_listening_is_one_line_and_exit_3(simulated_ptus, capsys,
                                                                           monkeypatch):
    monkeypatch.setattr(D, "CONNECT_TIMEOUT_S", 1.0)
    address = f"tcp://127.0.0.1:{_free_port()}"
    assert main(["recon", simulated_ptus[1][0], "--dask", address]) == 3
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"spdepth recon: error: --dask {address}: no dask scheduler answers there "
                   f"within 1 s (connect timeout); start one (`dask scheduler`) or use local:N"]


def test_an_address_that_answers_but_is_no_scheduler_is_one_line_and_exit_3(simulated_ptus, capsys,
                                                                            monkeypatch):
    import socket
    import threading

    monkeypatch.setattr(D, "CONNECT_TIMEOUT_S", 2.0)
    server = socket.socket()
    server.bind(("127.0.0.1", 0))
    server.listen()

    def answer_like_a_web_server():
        with server:
            conn, _ = server.accept()
            with conn:
                conn.sendall(b"HTTP/1.1 400 Bad Request\r\nContent-Length: 0\r\n\r\n" * 4)
                conn.recv(1024)

    threading.Thread(target=answer_like_a_web_server, daemon=True).start()
    address = f"tcp://127.0.0.1:{server.getsockname()[1]}"
    assert main(["recon", simulated_ptus[1][0], "--dask", address]) == 3
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"spdepth recon: error: --dask {address}: ")
