"""Runs of pixels (PhotonWorld.dwell_run, SimRig.scan_run) give exactly what the same pixels give
one call at a time, faults land on the same pixel, and an unpaced scan waits for the tagger's
reader instead of overflowing its FIFO."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from spdepth.drivers.events import EventKind, Marker
from spdepth.drivers.sim import PhotonWorld, galvo_fw, load_scene
from spdepth.drivers.sim.rig import SimRig

EFFECTS = [(), ("jitter",), ("dead_time",), ("jitter", "dead_time", "afterpulsing")]


@pytest.mark.parametrize("effects", EFFECTS)
@pytest.mark.parametrize("n_target, window", [(None, None), (12, None), (9, (1500, 5000))])
def test_a_run_equals_its_pixels_one_by_one(effects, n_target, window):
    scene = load_scene("steps", (5, 7), ppp=10, effects=effects)
    pix = np.array([3, 4, -1, 5, 11, 12, -1, 30, 31, 2], np.int64)
    dwell_s, settle, off, start = 3 * scene.dwell_s, 7, 40, 1000
    run_world, one_world = PhotonWorld(scene, seed=4), PhotonWorld(scene, seed=4)
    run = run_world.dwell_run(pix, start, dwell_s, n_target=n_target, window=window,
                              settle_syncs=settle, off_syncs=off, with_origin=True,
                              marker_bits=np.full(pix.size, Marker.PIXEL, np.uint8))
    s, parts, origins = start, [], []
    for j, p in enumerate(pix):
        s += settle if j else 0
        assert run.starts[j] == s
        if p < 0:
            n, ev, org = off, run.events[:0], run.origin[:0]
        elif n_target is None:
            ev, n, org = one_world.fixed_dwell(p // 7, p % 7, dwell_s, s, with_origin=True)
        else:
            ev, n, org = one_world.count_gated(p // 7, p % 7, n_target, dwell_s, s, window,
                                               with_origin=True)
        assert run.n_syncs[j] == n and run.counts[j] == ev.size
        opens = run.events[run.events["kind"] == EventKind.MARKER][j]
        assert opens["sync"] == s
        parts += [np.array([opens]), ev]
        origins += [np.array([251], np.uint8), org]
        s += n
    assert run.n_done == pix.size and run.counts.sum() > 50
    np.testing.assert_array_equal(run.events, np.concatenate(parts))
    np.testing.assert_array_equal(run.origin, np.concatenate(origins))


def test_a_run_stops_at_a_virtual_time_and_at_a_record_budget():
    scene = load_scene("steps", (4, 4), ppp=10)
    world = PhotonWorld(scene, seed=1)
    pix = np.arange(16, dtype=np.int64)
    full = PhotonWorld(scene, seed=1).dwell_run(pix, 0, scene.dwell_s, n_target=10)
    end = full.starts + full.n_syncs
    stop_s = float(end[5] * scene.settings.sync_period_s)      # pixel 5 ends exactly then
    cut = world.dwell_run(pix, 0, scene.dwell_s, n_target=10, stop_s=stop_s)
    assert cut.n_done == 6
    np.testing.assert_array_equal(cut.n_syncs, full.n_syncs[:6])
    budget = int(full.counts[:3].sum()) + 3                    # detections plus one marker each
    assert PhotonWorld(scene, seed=1).dwell_run(pix, 0, scene.dwell_s, n_target=10,
                                                max_records=budget).n_done <= 3


def _twin_rigs(effects=(), fifo=1 << 20):
    scene = load_scene("bust", (6, 8), ppp=10, effects=effects)
    rigs = [SimRig(PhotonWorld(scene, seed=5), fifo_capacity_records=fifo, keep_truth=True)
            for _ in range(2)]
    for r in rigs:
        r.start_tagger()
    return scene, rigs


def _pixel_by_pixel(rig, xs, ys, bits, n_target, dwell_s, settle_s):
    out = []
    for x, y, b in zip(xs, ys, bits):
        rig.set_mirror(x, y)
        rig.wait(settle_s)
        rig.pulse_markers(int(b))
        out.append(rig.count_gated_dwell(n_target, dwell_s) if n_target else rig.fixed_dwell(dwell_s))
    return out


@pytest.mark.parametrize("n_target", [None, 10])
def test_scan_run_equals_the_rig_driven_pixel_by_pixel(n_target):
    scene, (a, b) = _twin_rigs(("jitter", "afterpulsing"))
    h, w = scene.shape
    # one line across the scene and past its right edge (two pixels off the scene)
    xs = np.array([a.fov.centre_deg(2, c, (h, w))[0] for c in range(w)] + [10.5, 11.0])
    ys = np.full(xs.size, a.fov.centre_deg(2, 0, (h, w))[1])
    bits = np.full(xs.size, Marker.PIXEL, np.uint8)
    bits[0] |= Marker.LINE_START
    a.schedule_overflow(300, at_pixel=4)            # the FIFO loses records at the 4th pixel
    b.schedule_overflow(300, at_pixel=4)
    dwell_s, settle_s = 2 * scene.dwell_s, 3e-7
    done_total, counts, elapsed = 0, [], []
    while done_total < xs.size:
        done, c, e = a.scan_run(xs[done_total:], ys[done_total:], bits[done_total:],
                                dwell_s=dwell_s, n_target=n_target, settle_s=settle_s)
        done_total += done
        counts += c.tolist()
        elapsed += e.tolist()
    want = _pixel_by_pixel(b, xs, ys, bits, n_target, dwell_s, settle_s)
    assert counts == [c for c, _ in want] and elapsed == [e for _, e in want]
    assert a.sync == b.sync and a.pixels_pulsed == b.pixels_pulsed == xs.size
    assert a.mirror_deg == b.mirror_deg
    ev_a, ev_b = a.read_events(1 << 20), b.read_events(1 << 20)
    assert np.count_nonzero(ev_a["kind"] == EventKind.LOST) == 1
    np.testing.assert_array_equal(ev_a, ev_b)
    assert [(r, c) for r, c, _ in a.truth] == [(r, c) for r, c, _ in b.truth]
    for (_, _, x), (_, _, y) in zip(a.truth, b.truth):
        np.testing.assert_array_equal(x, y)


def test_unpaced_scan_waits_for_a_slow_reader_and_overflows_a_silent_one(monkeypatch):
    scene, _ = _twin_rigs()
    rig = SimRig(PhotonWorld(scene, seed=2), fifo_capacity_records=4096)
    fw = galvo_fw.GalvoFirmware(rig)
    lead = galvo_fw.MIN_LEAD           # 6 x 8 pixels: a 64th of the frame is below the minimum
    h, w = scene.shape
    x0, y0 = rig.fov.centre_deg(0, 0, (h, w))
    x1, y1 = rig.fov.centre_deg(h - 1, w - 1, (h, w))
    codes = [int(round(v / galvo_fw.UDEG_PER_CODE * 1e6)) + galvo_fw.ZERO_CODE
             for v in (x0, x1, y0, y1)]
    fw.host_write(f"PAT RASTER {w} {h} {codes[0]} {codes[1]} {codes[2]} {codes[3]}\n".encode(),
                  fw.generation)
    fw.host_write(b"GATE COUNT 10 5000000\n", fw.generation)
    fw.host_write(b"FRAMES 1\n", fw.generation)
    rig.start_tagger()
    most, taken = [0], []

    def slow_reader():
        markers = 0
        while fw.state.name != "PARKED" or rig.fifo_status().fill_records:
            most[0] = max(most[0], rig.pixels_pulsed - markers)   # pixels waiting in the FIFO
            ev = rig.read_events(64)
            taken.append(ev)
            markers += np.count_nonzero(ev["marker"] & Marker.PIXEL)
            time.sleep(0.002)

    t = threading.Thread(target=slow_reader)
    fw.host_write(b"START\n", fw.generation)
    t.start()
    t.join(60)
    assert not t.is_alive()
    ev = np.concatenate(taken)
    assert not np.any(ev["kind"] == EventKind.LOST) and not rig.fifo_status().overflowed
    assert np.count_nonzero(ev["marker"] & Marker.PIXEL) == h * w
    assert most[0] <= 2 * lead                      # never more than a run beyond the lead

    # nobody reads: after FIFO_STALL_S the scan goes on and the FIFO overflows, as it must
    monkeypatch.setattr(galvo_fw, "FIFO_STALL_S", 0.2)
    rig2 = SimRig(PhotonWorld(scene, seed=2), fifo_capacity_records=64)
    fw2 = galvo_fw.GalvoFirmware(rig2)
    for line in (f"PAT RASTER {w} {h} {codes[0]} {codes[1]} {codes[2]} {codes[3]}",
                 "GATE COUNT 10 5000000", "FRAMES 1"):
        fw2.host_write(f"{line}\n".encode(), fw2.generation)
    rig2.start_tagger()
    fw2.host_write(b"START\n", fw2.generation)
    assert fw2.wait_idle(30)
    assert rig2.fifo_status().overflowed
    fw.close()
    fw2.close()
