"""The galvo emulator reached the two ways the real driver reaches hardware (pyserial URL handler,
pty tty path): the shared contract, marker semantics against the rig, raw protocol details, and
every injected fault."""

from __future__ import annotations

import itertools
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import serial

from spdepth.drivers.errors import DeviceTimeoutError, SettingError
from spdepth.drivers.events import EventKind, Marker
from spdepth.drivers.galvo import (ConnectionLostError, Galvo, GalvoState, Gate, HardwareFaultError,
                           PatternCodes, PixelFlag, ScanMode, ScanPattern)
from spdepth.drivers.galvo import protocol as P
from spdepth.drivers.sim import galvo_fw
from spdepth.drivers.sim.faults import FaultKind
from spdepth.drivers.sim.galvo_fw import GalvoFirmware
from spdepth.drivers.sim.pty_link import PtyLink
from spdepth.drivers.sim.rig import SimRig
from tests import galvo_contract as C
from tests.galvo_support import poisson_rig
from tests.waiting import wait_until

_names = itertools.count()


class Bench:
    """One emulator behind one link; ``open()`` connects a driver the way an app would."""

    def __init__(self, link: str, rig=None, **fw_kwargs):
        self.rig = rig if rig is not None else poisson_rig((8, 8), 0.05)
        fw_kwargs.setdefault("replug_s", 0.15)
        fw_kwargs.setdefault("slow_reply_s", 0.3)
        self.fw = GalvoFirmware(self.rig, **fw_kwargs)
        self.name = f"test-{next(_names)}"
        galvo_fw.register_device(self.name, self.fw)
        self.link = None
        if link == "url":
            self.target = f"galvosim://{self.name}"
        else:
            self.link = PtyLink(self.fw)
            self.target = self.link.start()
        self.drivers: list[Galvo] = []

    def open(self, **kw) -> Galvo:
        kw.setdefault("timeout_s", 0.15)
        kw.setdefault("backoff_s", 0.02)
        g = Galvo.open(self.target, **kw)
        self.drivers.append(g)
        return g

    def close(self):
        for g in self.drivers:
            g.close()
        if self.link is not None:
            self.link.close()
            assert self.link.error is None
        galvo_fw.unregister(self.name)
        assert self.fw.thread_error is None


@pytest.fixture(params=["url", "pty"])
def make_bench(request):
    benches = []

    def make(**kw):
        b = Bench(request.param, **kw)
        benches.append(b)
        return b

    yield make
    for b in benches:
        b.close()


# ---- the contract, on both transports ---------------------------------------------------------

@pytest.mark.parametrize("check", C.CONTRACT, ids=lambda f: f.__name__)
def test_contract(make_bench, check):
    # pace=1: dwells take real time, so a long scan can be caught running and stopped.
    g = make_bench(pace=1.0).open()
    check(g)


def test_contract_serpentine(make_bench):
    C.check_fixed_dwell_raster(make_bench().open(), ScanMode.SERPENTINE)


# ---- what the scan does to the rig --------------------------------------------------------------

def _markers_and_photons(rig: SimRig):
    ev = rig.read_events(10 ** 7)
    return ev, [int(m) for m in ev["marker"][ev["kind"] == EventKind.MARKER]]


@pytest.mark.parametrize("mode", [ScanMode.RASTER, ScanMode.SERPENTINE])
def test_markers_mirror_and_counts(make_bench, mode):
    b = make_bench()
    rig = b.rig
    g = b.open()
    shape = rig.world.shape
    x0, y0 = rig.fov.centre_deg(0, 0, shape)
    x1, y1 = rig.fov.centre_deg(1, 2, shape)
    g.configure_scan(ScanPattern(3, 2, x0, x1, y0, y1, mode), Gate.count(4, 200e-6), frames=2)
    rig.start_tagger()
    g.start()
    g.wait_until_done(10)
    recs = []
    while (page := g.poll_pixels()).records:
        recs += page.records
    ev, markers = _markers_and_photons(rig)
    F, LS, PX, LE = Marker.FRAME, Marker.LINE_START, Marker.PIXEL, Marker.LINE_STOP
    line = [LS | PX, PX, PX, LE]
    assert markers == [F | line[0]] + line[1:] + line + [F | line[0]] + line[1:] + line
    # The mirror visited the scene pixels in the pattern's order (the rig's pixel under it).
    cols = [0, 1, 2, 2, 1, 0] if mode == ScanMode.SERPENTINE else [0, 1, 2, 0, 1, 2]
    visited = [(c[1], c[2]) for c in rig.world.calls]
    assert visited == list(zip([0, 0, 0, 1, 1, 1], cols)) * 2
    assert [(r.frame, r.row, r.col) for r in recs] == [
        (f, row, c) for f in (0, 1) for row, c in zip([0, 0, 0, 1, 1, 1], cols)]
    # Photons between a PIXEL marker and the next marker belong to that pixel: the counts agree
    # with the pixel log, and a pixel flagged GATED holds exactly n_target photons.
    is_marker = ev["kind"] == EventKind.MARKER
    marker_idx = np.flatnonzero(is_marker)
    per_pixel = []
    for a, bnd in zip(marker_idx[:-1], marker_idx[1:]):
        if ev["marker"][a] & PX:
            per_pixel.append(int(bnd - a - 1))
    assert per_pixel == [r.count for r in recs]
    assert all(r.count == 4 for r in recs if r.flag == PixelFlag.GATED)
    assert any(r.flag == PixelFlag.GATED for r in recs)


def test_settle_time_passes_before_the_pixel_marker():
    rig = poisson_rig((4, 4), rate_per_sync=0.0)
    fw = GalvoFirmware(rig)
    for line in [b"SETTLE 50000\n", b"GATE FIXED 100000\n", b"PAT RASTER 2 1 30000 31000 30000 30000\n"]:
        fw.host_write(line, 0)
    rig.start_tagger()
    fw.host_write(b"START\n", 0)
    assert fw.wait_idle(5)
    ev = rig.read_events(100)
    syncs = ev["sync"][ev["kind"] == EventKind.MARKER].astype(int).tolist()
    # Per pixel 500 syncs settle, then the marker, then 1000 syncs dwell (100 ns syncs);
    # LINE_STOP right after the last dwell.
    assert syncs == [500, 2000, 3000]
    fw.close()


def test_continuous_scan_runs_until_stop(make_bench):
    g = make_bench().open()
    g.configure_scan(PatternCodes(ScanMode.RASTER, 2, 2, 30000, 31000, 30000, 31000),
                     Gate.fixed(1e-6), frames=0)
    g.start()
    deadline = time.monotonic() + 10
    while g.status().completed < 40 and time.monotonic() < deadline:
        time.sleep(0.01)
    st = g.status()
    assert st.state == GalvoState.SCANNING and st.total == 0 and st.frame >= 9
    g.stop()
    assert g.status().state == GalvoState.PARKED


def test_an_unpaced_scan_nobody_reads_keeps_to_real_time(make_bench):
    # With the tagger idle nothing takes the data, so nothing paces an unpaced scan: it must
    # not spin through virtual time (that starved the threads answering the host: replies to
    # STAT? took up to 0.35 s, past the driver's timeout, and a CI run failed on it).
    g = make_bench().open()
    g.configure_scan(PatternCodes(ScanMode.RASTER, 2, 2, 30000, 31000, 30000, 31000),
                     Gate.fixed(2e-3), frames=0)
    t0 = time.monotonic()
    g.start()
    time.sleep(0.3)
    done = g.status().completed
    wall = time.monotonic() - t0
    g.stop()
    assert 0 < done <= wall / 2e-3 + 4


def test_pixel_log_overrun_is_reported(make_bench):
    g = make_bench().open()
    g.configure_scan(PatternCodes(ScanMode.RASTER, 100, 50, 30000, 31000, 30000, 31000),
                     Gate.fixed(1e-6))
    g.start()
    g.wait_until_done(30)
    page = g.poll_pixels()
    assert page.lost == 5000 - P.PIXEL_LOG_DEPTH and page.records[0].seq == page.lost
    assert (page.records[0].row, page.records[0].col) == divmod(page.lost, 100)


def test_end_to_end_with_the_photon_world():
    from spdepth.drivers.sim import PhotonWorld, load_scene

    rig = SimRig(PhotonWorld(load_scene("bust", shape=(6, 6)), seed=1))
    galvo_fw.register_rig("e2e-rig", rig)
    try:
        with Galvo.open("galvosim://e2e?rig=e2e-rig") as g:
            x0, y0 = rig.fov.centre_deg(0, 0, (6, 6))
            x1, y1 = rig.fov.centre_deg(5, 5, (6, 6))
            g.configure_scan(ScanPattern(6, 6, x0, x1, y0, y1), Gate.count(15, 5e-3))
            rig.start_tagger()
            g.start()
            g.wait_until_done(30)
            recs = g.poll_pixels().records
        ev = rig.read_events(10 ** 7)
        photons = int((ev["kind"] == EventKind.PHOTON).sum())
        assert len(recs) == 36 and photons == sum(r.count for r in recs)
        assert sum(r.flag == PixelFlag.GATED for r in recs) > 18
    finally:
        galvo_fw.unregister("e2e")
        galvo_fw.unregister("e2e-rig")


def test_url_builds_a_scene_and_rejects_bad_options():
    with Galvo.open("galvosim://scene-dev?scene=steps&size=4x5&seed=3&serial=SN42") as g:
        assert g.identity.serial == "SN42"
        fw = galvo_fw.device_for_url("galvosim://scene-dev")
        assert fw.rig.world.shape == (5, 4)   # size is width x height
    galvo_fw.unregister("scene-dev")
    for url, words in [("galvosim://x?colour=red", "unknown options"),
                       ("galvosim://x?rig=nope", "no rig registered"),
                       ("galvosim://x?faults=usb-timeout@1s", "cannot be injected"),
                       ("galvosim://x?size=big", "not like 32x32")]:
        with pytest.raises(serial.SerialException, match=words):
            serial.serial_for_url(url)
        galvo_fw.unregister("x")



def test_real_galvo_driver_leaves_pyserial_url_handlers_alone():
    # A fresh interpreter: this one has long since imported the simulator.
    code = ("import sys, serial, spdepth.drivers.galvo\n"
            "print('spdepth.drivers.sim' in serial.protocol_handler_packages, 'spdepth.drivers.sim' in sys.modules)\n"
            "import spdepth.drivers.sim\n"
            "print('spdepth.drivers.sim' in serial.protocol_handler_packages)\n"
            "spdepth.drivers.galvo.Galvo.open('galvosim://fresh').close()\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120,
                         cwd=Path(__file__).resolve().parents[1])
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["False", "False", "True"]

# ---- raw protocol details -------------------------------------------------------------------

def _raw(fw: GalvoFirmware, data: bytes) -> list[bytes]:
    fw.host_write(data, fw.generation)
    out = b""
    while chunk := fw.host_read(65536, 0.05, fw.generation):
        out += chunk
    return out.splitlines(keepends=True)


def test_raw_lines_as_a_terminal_user_types_them():
    fw = GalvoFirmware(poisson_rig())
    assert _raw(fw, b"*idn?\r\n") == [P.encode_reply("OK SPDEPTH,GS-16,SIM0001,1.0", None)]
    assert _raw(fw, b"\r\n\n") == []                              # empty lines: no reply
    assert _raw(fw, b"  pos   10   20 \n12:POS?\n") == [P.encode_reply("OK", None),
                                                          P.encode_reply("OK 10 20", 12)]
    assert _raw(fw, b"POS +11 20\n")[0].startswith(b"OK")
    assert _raw(fw, b"7:POS 10\n") == [P.encode_reply("ERR 2 expected 2 arguments, got 1", 7)]
    assert _raw(fw, b"7:POS x 1\n") == [P.encode_reply("ERR 2 x is not a decimal integer", 7)]
    assert _raw(fw, b"8:" + b"A" * 300 + b"\n") == [
        P.encode_reply("ERR 2 line longer than 256 bytes", None)]
    assert _raw(fw, b"9:POS\xff?\n") == [P.encode_reply("ERR 2 non-ASCII or control bytes in line", None)]
    assert _raw(fw, b"99999:POS?\n") == [P.encode_reply("ERR 2 tag 99999 outside 0..65535", None)]
    assert _raw(fw, b"3:WHAT*\n") == [P.encode_reply("ERR 1 unknown command WHAT?", 3)]
    assert _raw(fw, b"CAL?\n") == [P.encode_reply("OK 32768 610.3515625 32768 610.3515625", None)]
    assert _raw(fw, b"PIX? 0\n") == [P.encode_reply("OK 0 0", None)]
    assert _raw(fw, b"PIX? 0 0\n") == [P.encode_reply("ERR 3 max_records 0 outside 1..256", None)]
    fw.close()


def test_limits_and_start_checks_in_firmware():
    fw = GalvoFirmware(poisson_rig())
    assert _raw(fw, b"LIM 100 200 100 200\n")[0].startswith(b"ERR 3 park position")
    assert _raw(fw, b"LIM 200 100 0 65535\n")[0].startswith(b"ERR 3 min above max")
    assert _raw(fw, b"PAT RASTER 2 2 30000 35000 30000 35000\n")[0].startswith(b"OK")
    assert _raw(fw, b"LIM 30000 34000 30000 40000\n")[0].startswith(b"OK")
    assert _raw(fw, b"START\n")[0].startswith(b"ERR 3 last pixel")
    assert _raw(fw, b"POS 34001 30000\n")[0].startswith(b"ERR 3 position")
    fw.close()


def test_servo_fault_latches_until_cleared(make_bench):
    b = make_bench(faults="servo-fault@30%")
    g = b.open()
    g.configure_scan(PatternCodes(ScanMode.RASTER, 4, 4, 30000, 31000, 30000, 31000),
                     Gate.fixed(1e-6))
    g.start()
    st = g.wait_until_done(10)
    assert st.state == GalvoState.FAULT and st.completed == 5
    with pytest.raises(HardwareFaultError):
        g.move_codes(30000, 30000)
    with pytest.raises(HardwareFaultError):
        g.start()
    code, msg = g.next_error()
    assert code == P.ErrorCode.HARDWARE_FAULT and "servo" in msg
    ev = b.rig.read_events(100)   # tagger never started: nothing recorded, but the line closed
    g.clear_errors()
    assert g.status().state == GalvoState.PARKED
    g.move_codes(30000, 30000)
    assert ev.size == 0


# ---- injected link faults: typed errors, recovery, never wrong data -------------------------------

def test_unplug_during_scan_reconnects_and_loses_nothing(make_bench):
    b = make_bench(faults="serial-unplug@25%", pace=1.0)
    g = b.open(reconnect_timeout_s=3.0)
    g.configure_scan(PatternCodes(ScanMode.RASTER, 4, 4, 30000, 31000, 30000, 31000),
                     Gate.fixed(10e-3), settle_s=0.0, frames=1)
    g.start()
    recs = []
    deadline = time.monotonic() + 30
    while True:
        st = g.status()
        recs += g.poll_pixels().records
        if st.state != GalvoState.SCANNING:
            break
        assert time.monotonic() < deadline, "the scan never ended"
        time.sleep(0.02)
    recs += g.poll_pixels().records
    assert g.reconnects == 1
    assert [r.seq for r in recs] == list(range(16))
    assert [f.kind for f in b.fw.faults.fired] == [FaultKind.SERIAL_UNPLUG]
    # The controller kept the configuration it was given (it was scanning: verified, not re-sent).
    assert g.frames() == 1


def test_power_cycle_when_idle_restores_configuration(make_bench):
    b = make_bench()
    g = b.open(reconnect_timeout_s=3.0)
    g.set_park_position_codes(31000, 32000)
    b.fw.power_cycle()                                  # settings back to power-on values
    assert g.park_position_codes() == (31000, 32000)    # reconnected and re-sent
    assert g.reconnects == 1


def test_unplug_for_too_long_raises_connection_lost(make_bench):
    b = make_bench(replug_s=5.0)
    g = b.open(reconnect_timeout_s=0.2)
    b.fw.unplug()
    with pytest.raises(ConnectionLostError, match="did not come back"):
        g.status()


@pytest.mark.parametrize("kind", ["garbled-reply", "missing-reply", "slow-reply"])
def test_reply_faults_are_retried_and_data_is_right(make_bench, kind):
    b = make_bench(faults=f"{kind}@0s")
    g = b.open()          # the fault hits *IDN? at connect; the retry gets the real answer
    assert g.identity.serial == "SIM0001"
    assert [f.kind.value for f in b.fw.faults.fired] == [kind]
    g.move_codes(12345, 23456)
    for _ in range(5):
        assert g.position_codes() == (12345, 23456)


@pytest.mark.parametrize("kind", ["garbled-reply", "missing-reply", "slow-reply"])
def test_reply_faults_without_retries_raise_typed_errors(make_bench, kind):
    b = make_bench()
    g = b.open(retries=0)
    b.fw.faults = galvo_fw.FaultSchedule.from_spec(f"{kind}@0s")
    expected = P.ProtocolError if kind == "garbled-reply" else DeviceTimeoutError
    with pytest.raises(expected):
        g.position_codes()
    if kind == "slow-reply":
        # the stale reply lands in the host's buffer; the next command must skip it, not take it
        wait_until(lambda: g.transport._port.in_waiting > 0, 10.0, what="the held-back reply")
    assert g.position_codes() == (32768, 32768)


def test_start_reply_lost_starts_exactly_one_scan(make_bench):
    b = make_bench()
    g = b.open()
    g.configure_scan(PatternCodes(ScanMode.RASTER, 2, 2, 30000, 31000, 30000, 31000),
                     Gate.fixed(1e-6))
    before = g.status().scan_id
    b.fw.faults = galvo_fw.FaultSchedule.from_spec("missing-reply@0s")
    g.start()
    assert g.wait_until_done(5).scan_id == before + 1
    assert g.next_error()[0] == P.ErrorCode.NO_ERROR      # no BUSY from a blind re-send


def test_emulator_rejects_bad_settings():
    with pytest.raises(SettingError):
        GalvoFirmware(poisson_rig(), faults="fifo-overflow@1s")
    with pytest.raises(SettingError):
        GalvoFirmware(poisson_rig(), serial_number="bad serial*")
    with pytest.raises(SettingError):
        GalvoFirmware(poisson_rig(), pace=-1)
