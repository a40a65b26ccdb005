"""The vendor drivers' layers on their own: the exact library calls ``PicoQuantTagger`` makes
(a transcript against a recording stand-in of the C library), its error and FIFO-full paths
through the compiled stand-in, and the NI-DAQ raster as samples and marker edges."""

from __future__ import annotations

import ctypes as ct

import numpy as np
import pytest

from spdepth.drivers.daq import DaqCalibration, MarkerLine, raster_waveform
from spdepth.drivers.errors import DeviceError, SettingError
from spdepth.drivers.picoquant import (FAMILIES, LibraryMissingError, LibTransport,
                                       PicoQuantError, PicoQuantSettings, PicoQuantTagger)


class TranscriptLib:
    """A library object that answers from a transcript: ``[(name, args, rc, outputs)]``; every
    call must come in order with these arguments, and every entry must be used."""

    def __init__(self, prefix, transcript):
        self.prefix = prefix
        self.expected = list(transcript)
        self.i = 0

    def __getattr__(self, full):
        if not full.startswith(self.prefix + "_"):
            raise AttributeError(full)
        name = full[len(self.prefix) + 1:]

        def call(*args):
            assert self.i < len(self.expected), f"unexpected call {name}{args}"
            want, want_args, rc, outputs = self.expected[self.i]
            self.i += 1
            assert name == want, f"call {self.i}: {name} instead of {want}"
            plain = [a for a in args if isinstance(a, int)]
            assert plain == list(want_args), f"{name}: arguments {plain} != {list(want_args)}"
            ptrs = [a for a in args if not isinstance(a, int)]
            for ptr, value in zip(ptrs, outputs):
                target = ptr._obj if hasattr(ptr, "_obj") else ptr
                if isinstance(value, bytes):
                    target.value = value
                else:
                    target.value = value
            return rc
        call.__name__ = full
        return call

    def done(self):
        assert self.i == len(self.expected), f"unused: {self.expected[self.i:]}"


OPEN = [
    ("OpenDevice", [0], 0, [b"1000042"]),
    ("Initialize", [0, 3, 0], 0, []),
    ("GetHardwareInfo", [0], 0, [b"MultiHarp 150 4N", b"930099", b"1.0"]),
    ("GetSerialNumber", [0], 0, [b"1000042"]),
    ("GetLibraryVersion", [], 0, [b"3.0"]),
]


def test_open_and_configure_make_exactly_the_vendor_calls():
    s = PicoQuantSettings(binning=1, sync_divider=2, sync_level_mv=-70, input_level_mv=-40,
                          sync_offset_ps=-5000, input_offset_ps=10, marker_enabled=0b0111,
                          marker_rising=0b0101)
    lib = TranscriptLib("MH", OPEN + [
        ("SetSyncDiv", [0, 2], 0, []),
        ("SetSyncEdgeTrg", [0, -70, 0], 0, []),
        ("SetSyncChannelOffset", [0, -5000], 0, []),
        ("GetNumOfInputChannels", [0], 0, [2]),
        ("SetInputEdgeTrg", [0, 0, -40, 0], 0, []),
        ("SetInputChannelOffset", [0, 0, 10], 0, []),
        ("SetInputEdgeTrg", [0, 1, -40, 0], 0, []),
        ("SetInputChannelOffset", [0, 1, 10], 0, []),
        ("SetBinning", [0, 1], 0, []),
        ("SetOffset", [0, 0], 0, []),
        ("SetMarkerEdges", [0, 1, 0, 1, 0], 0, []),
        ("SetMarkerEnable", [0, 1, 1, 1, 0], 0, []),
        ("GetResolution", [0], 0, [10.0]),
        ("StartMeas", [0, 360_000_000], 0, []),
        ("StopMeas", [0], 0, []),
        ("CloseDevice", [0], 0, []),
    ])
    t = PicoQuantTagger.open("mh150", lib=lib)
    assert t.identity["serial"] == "1000042" and t.identity["model"] == "MultiHarp 150 4N"
    t.configure(s)
    assert t.resolution_s == pytest.approx(10e-12)
    t.start()
    t.close()
    lib.done()


def test_a_device_with_another_serial_is_closed_and_the_error_names_both():
    lib = TranscriptLib("MH", [("OpenDevice", [0], 0, [b"1111111"]), ("CloseDevice", [0], 0, [])]
                        + [c for i in range(1, 8) for c in (
                            ("OpenDevice", [i], -1, []),
                            ("GetErrorString", [-1], 0, [b"ERROR_DEVICE_OPEN_FAIL"]))])
    with pytest.raises(DeviceError, match="serial 2222222 .found: 1111111"):
        PicoQuantTagger.open("mh150", "2222222", lib=lib)
    lib.done()


def test_library_errors_carry_the_librarys_text(tmp_path):
    from spdepth.drivers.sim.picoquant_standin import build_library

    lib = ct.CDLL(str(build_library("mh150")))
    lib.SIM_RemoveAll()
    t = LibTransport(FAMILIES["mh150"], lib)
    with pytest.raises(PicoQuantError, match="ERROR_DEVICE_OPEN_FAIL") as err:
        t.call("OpenDevice", 0, ct.create_string_buffer(16))
    assert err.value.code == -1 and err.value.device_gone
    with pytest.raises(LibraryMissingError, match="has no HH_CloseDevice"):
        LibTransport(FAMILIES["hh400"], lib).call("CloseDevice", 0)


def test_a_library_path_that_is_not_a_library_says_how_to_install(tmp_path):
    bad = tmp_path / "libmhlib.so"
    bad.write_text("not a library")
    with pytest.raises(LibraryMissingError, match="does not load.*snapi"):
        PicoQuantTagger.open("mh150", lib_path=bad)


def test_settings_are_checked_before_anything_is_sent():
    for kw in ({"binning": 25}, {"sync_divider": 3}, {"sync_level_mv": 5000},
               {"marker_enabled": 16}):
        with pytest.raises(SettingError):
            PicoQuantSettings(**kw)


def test_fifo_full_drains_then_reports_an_in_band_loss_and_restarts():
    """Through the compiled stand-in: records before the overrun arrive, then one LOST event,
    then the stream continues with syncs still increasing."""
    import time

    from spdepth.drivers.events import EventKind
    from spdepth.drivers.sim import PhotonWorld, load_scene
    from spdepth.drivers.sim.picoquant_standin import PicoQuantStandIn
    from spdepth.drivers.sim.rig import SimRig

    scene = load_scene("steps", (4, 4), ppp=20.0)
    rig = SimRig(PhotonWorld(scene, seed=1))
    sim = PicoQuantStandIn(rig, fifo_records=200)    # a small FIFO: overruns for real
    t = PicoQuantTagger.open("mh150", lib=sim.path)
    t.configure(PicoQuantSettings())
    r = t.reader().start()
    try:
        deadline = time.monotonic() + 60
        while not rig.tagger_running and time.monotonic() < deadline:
            time.sleep(0.01)
        # hold the reader off: the pump overfills the stand-in's FIFO
        with t.transport._lock:
            for k in range(16):
                rig.set_mirror(*rig.fov.centre_deg(k // 4, k % 4, (4, 4)))
                rig.pulse_markers(1)
                rig.fixed_dwell(scene.dwell_s * 5)
            time.sleep(0.3)
        chunks = []
        while time.monotonic() < deadline:
            c = r.get(timeout_s=0.5)
            if c is not None and c.size:
                chunks.append(c)
            elif r.stats["restarts"]:
                break
        ev = np.concatenate(chunks)
    finally:
        r.stop()
        t.close()
        sim.close()
    assert r.stats["fifo_full"] == 1 and r.stats["restarts"] == 1
    lost = np.flatnonzero(ev["kind"] == EventKind.LOST)
    assert lost.size == 1 and lost[0] > 0
    assert np.all(np.diff(ev["sync"].astype(np.int64)) >= 0)
    assert sim.dropped_records > 0


def test_raster_samples_hold_each_pixel_and_raise_one_edge_per_marker():
    cal = DaqCalibration(deg_per_volt_x=2.0, deg_per_volt_y=0.5)
    xs, ys = np.array([-1.0, 0.0, 1.0]), np.array([-0.5, 0.5])
    w = raster_waveform(3, 2, xs, ys, 1e-3, cal)
    assert w.rate_hz == 2000.0 and w.n_samples == 2 * (3 + 1) * 2
    np.testing.assert_allclose(w.ao[0, :8], [-0.5, -0.5, 0, 0, 0.5, 0.5, 0.5, 0.5])
    np.testing.assert_allclose(w.ao[1, :8], -1.0)
    edges = w.do & ~np.concatenate([np.zeros((4, 1), bool), w.do[:, :-1]], axis=1)
    assert edges[0].sum() == 6 and edges[1].sum() == 2 and edges[2].sum() == 2 and edges[3].sum() == 1
    assert [int(b) for b in MarkerLine] == [1, 2, 4, 8]
    assert w.pixels_done[-1] == 6 and list(w.pixels_done[:5]) == [0, 0, 1, 1, 2]
    sw = raster_waveform(3, 2, xs, ys, 1e-3, cal, serpentine=True)
    assert [tuple(p) for p in sw.order] == [(0, 0), (0, 1), (0, 2), (1, 2), (1, 1), (1, 0)]


def test_raster_outside_the_voltage_limits_is_refused():
    cal = DaqCalibration(deg_per_volt_x=1.0, v_min=-5, v_max=5)
    with pytest.raises(SettingError, match="outside the limits"):
        raster_waveform(2, 1, np.array([-6.0, 6.0]), np.array([0.0]), 1e-3, cal)
    with pytest.raises(SettingError, match="sample clock"):
        raster_waveform(2, 1, np.array([0.0, 1.0]), np.array([0.0]), 1e-7, cal)
