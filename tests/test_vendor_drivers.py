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
    ("GetFeatures", [0], 0, [0x7]),
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


def _open_calls(init_args, model):
    """The calls ``PicoQuantTagger.open`` makes on a device at index 0 (``init_args``: the
    arguments ``Initialize`` takes after the index)."""
    return [("OpenDevice", [0], 0, [b"1000042"]),
            ("Initialize", [0, *init_args], 0, []),
            ("GetHardwareInfo", [0], 0, [model, b"930099", b"1.0"]),
            ("GetSerialNumber", [0], 0, [b"1000042"]),
            ("GetFeatures", [0], 0, [0x7]),
            ("GetLibraryVersion", [], 0, [b"3.2"])]


def _configure_calls(sync_trigger, input_trigger, trgmode=False):
    """The calls ``configure`` makes for one detector input, given the trigger calls."""
    pre = [("SetSyncTrgMode", [0, 0], 0, [])] if trgmode else []
    pre_in = [("SetInputTrgMode", [0, 0, 0], 0, [])] if trgmode else []
    return ([("SetSyncDiv", [0, 2], 0, [])] + pre + [sync_trigger,
            ("SetSyncChannelOffset", [0, -5000], 0, []),
            ("GetNumOfInputChannels", [0], 0, [1])] + pre_in + [input_trigger,
            ("SetInputChannelOffset", [0, 0, 10], 0, []),
            ("SetBinning", [0, 1], 0, []),
            ("SetOffset", [0, 0], 0, []),
            ("SetMarkerEdges", [0, 1, 0, 1, 0], 0, []),
            ("SetMarkerEnable", [0, 1, 1, 1, 0], 0, []),
            ("GetResolution", [0], 0, [25.0])])


@pytest.mark.parametrize("key,prefix,init_args,model,sync_trg,input_trg,trgmode,rectype", [
    # HydraHarp 400 CFD: levels 0..1000 mV and zero cross 0..40 mV (hhdefin.h), so magnitudes
    ("hh400", "HH", [3, 0], b"HydraHarp 400", ("SetSyncCFD", [0, 70, 10], 0, []),
     ("SetInputCFD", [0, 0, 40, 10], 0, []), False, 0x01010304),
    # TimeHarp 260 PICO: Initialize(devidx, mode); CFD levels -1200..0, zero cross -40..0 mV
    ("th260", "TH260", [3], b"TimeHarp 260 P", ("SetSyncCFD", [0, -70, -10], 0, []),
     ("SetInputCFD", [0, 0, -40, -10], 0, []), False, 0x00010306),
    # TimeHarp 260 NANO: edge triggers, its own record type
    ("th260", "TH260", [3], b"TimeHarp 260 N", ("SetSyncEdgeTrg", [0, -70, 0], 0, []),
     ("SetInputEdgeTrg", [0, 0, -40, 0], 0, []), False, 0x00010305),
    # PicoHarp 330: the trigger mode (ETR) first, then the edge trigger levels
    ("ph330", "PH330", [3, 0], b"PicoHarp 330", ("SetSyncEdgeTrg", [0, -70, 0], 0, []),
     ("SetInputEdgeTrg", [0, 0, -40, 0], 0, []), True, 0x00010307),
])
def test_each_family_gets_the_calls_of_its_own_header(key, prefix, init_args, model, sync_trg,
                                                      input_trg, trgmode, rectype):
    s = PicoQuantSettings(binning=1, sync_divider=2, sync_level_mv=-70, input_level_mv=-40,
                          sync_offset_ps=-5000, input_offset_ps=10, marker_enabled=0b0111,
                          marker_rising=0b0101)
    lib = TranscriptLib(prefix, _open_calls(init_args, model)
                        + _configure_calls(sync_trg, input_trg, trgmode)
                        + [("CloseDevice", [0], 0, [])])
    t = PicoQuantTagger.open(key, lib=lib)
    t.configure(s)
    assert t.record_type == rectype and t.resolution_s == pytest.approx(25e-12)
    t.close()
    lib.done()


def test_a_sync_divider_beyond_the_familys_range_is_refused_before_it_is_sent():
    lib = TranscriptLib("TH260", _open_calls([3], b"TimeHarp 260 P"))
    t = PicoQuantTagger.open("th260", lib=lib)
    with pytest.raises(SettingError, match="1..8"):
        t.configure(PicoQuantSettings(sync_divider=16))
    lib.done()


@pytest.mark.parametrize("features,where,words", [(0x3, "configure", "no marker inputs"),
                                                   (0x5, "open", "no time-tagging")])
def test_a_device_without_the_marker_or_tttr_option_is_refused_with_its_name(features, where,
                                                                             words):
    """Markers and T3 mode are licensed options (``*_GetFeatures``): without them a scan would
    stream nothing or assign no photon, so the driver says which option is missing."""
    from spdepth.drivers.sim import PhotonWorld, load_scene
    from spdepth.drivers.sim.picoquant_standin import PicoQuantStandIn
    from spdepth.drivers.sim.rig import SimRig

    sim = PicoQuantStandIn(SimRig(PhotonWorld(load_scene("steps", (4, 4)), seed=1)), "th260",
                           serial="1000077")
    try:
        sim.lib.SIM_SetFeatures(sim.dev, features)
        if where == "open":
            with pytest.raises(DeviceError, match=f"1000077 has {words}"):
                PicoQuantTagger.open("th260", lib=sim.path)
            return
        t = PicoQuantTagger.open("th260", lib=sim.path)
        with pytest.raises(DeviceError, match=f"1000077 has {words}"):
            t.configure(PicoQuantSettings())
        t.configure(PicoQuantSettings(marker_enabled=0))     # no markers asked for: fine
        t.close()
    finally:
        sim.close()


def test_the_standins_refuse_the_trigger_call_the_header_does_not_allow():
    """What the driver's per-family choice is checked against: a TimeHarp 260 PICO has no edge
    trigger, a PicoHarp 330 input takes levels only in the trigger mode set, and the HydraHarp
    400's CFD levels are not negative."""
    from spdepth.drivers.sim.picoquant_standin import build_library

    def opened(key, model):
        lib = ct.CDLL(str(build_library(key)))
        lib.SIM_RemoveAll()
        lib.SIM_AddDevice.argtypes = [ct.c_char_p, ct.c_char_p, ct.c_double, ct.c_int, ct.c_long]
        lib.SIM_AddDevice(b"1000042", model, 25.0, 1, 1024)
        t = LibTransport(FAMILIES[key], lib)
        t.call("OpenDevice", 0, ct.create_string_buffer(16))
        t.call("Initialize", 0, 3, *(() if key == "th260" else (0,)))
        return t

    t = opened("th260", b"TimeHarp 260 P")
    with pytest.raises(PicoQuantError, match="UNSUPPORTED_FUNCTION"):
        t.call("SetSyncEdgeTrg", 0, -50, 0)
    t.call("SetSyncCFD", 0, -50, -10)
    t = opened("th260", b"TimeHarp 260 N")
    with pytest.raises(PicoQuantError, match="UNSUPPORTED_FUNCTION"):
        t.call("SetInputCFD", 0, 0, -50, -10)
    t.call("SetInputEdgeTrg", 0, 0, -50, 0)
    t = opened("ph330", b"PicoHarp 330")
    with pytest.raises(PicoQuantError, match="INVALID_MODE"):
        t.call("SetSyncEdgeTrg", 0, -50, 0)
    t.call("SetSyncTrgMode", 0, 0)
    t.call("SetSyncEdgeTrg", 0, -50, 0)
    t = opened("hh400", b"HydraHarp 400")
    with pytest.raises(PicoQuantError, match="INVALID_ARGUMENT"):
        t.call("SetSyncCFD", 0, -50, 10)
    t.call("SetSyncCFD", 0, 50, 10)


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


@pytest.mark.parametrize("key", sorted(FAMILIES))
def test_fifo_full_drains_then_reports_an_in_band_loss_and_restarts(key):
    """Through the compiled stand-in of each family: records before the overrun arrive, then one
    LOST event, then the stream continues with syncs still increasing."""
    import time

    from spdepth.drivers.events import EventKind
    from spdepth.drivers.sim import PhotonWorld, load_scene
    from spdepth.drivers.sim.picoquant_standin import PicoQuantStandIn
    from spdepth.drivers.sim.rig import SimRig

    scene = load_scene("steps", (4, 4), ppp=20.0)
    rig = SimRig(PhotonWorld(scene, seed=1))
    sim = PicoQuantStandIn(rig, key, fifo_records=200)    # a small FIFO: overruns for real
    t = PicoQuantTagger.open(key, lib=sim.path)
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


@pytest.mark.parametrize("fault,stat", [("usb-timeout@0.002s", "restarts"),
                                        ("device-vanish@0.002s", "reconnects")])
def test_a_failed_swabian_stream_is_a_loss_in_band_then_a_new_stream(fault, stat):
    """A stream error (USB) restarts the stream on the same tagger; a vanished tagger is opened
    again by serial; either way one LOST event sits where the hole is, syncs keep increasing, and
    the stream goes on with the dwells after the hole."""
    import time

    from spdepth.drivers.events import EventKind
    from spdepth.drivers.sim import PhotonWorld, load_scene
    from spdepth.drivers.sim.rig import SimRig
    from spdepth.drivers.sim.swabian_standin import SwabianStandIn
    from spdepth.drivers.swabian import SwabianSettings, SwabianTagger

    scene = load_scene("steps", (4, 4), ppp=20.0)
    rig = SimRig(PhotonWorld(scene, seed=2))
    module = SwabianStandIn(rig, faults=fault, vanish_s=0.1)
    settings = SwabianSettings(sync_period_s=scene.settings.sync_period_s, event_divider=64,
                               resolution_ps=int(round(scene.settings.resolution_s * 1e12)))
    t = SwabianTagger.open(None, settings, module=module)
    first = t.device
    r = t.reader().start()
    chunks = []
    try:
        deadline = time.monotonic() + 60
        while not rig.tagger_running and time.monotonic() < deadline:
            time.sleep(0.01)
        for k in range(16):          # one dwell per pixel; the fault fires early in virtual time
            rig.set_mirror(*rig.fov.centre_deg(k // 4, k % 4, (4, 4)))
            rig.pulse_markers(1)
            rig.fixed_dwell(scene.dwell_s * 5)
            # once the fault is due, let the reader meet it before more dwells are pushed (the
            # new stream starts with what comes after it)
            while rig.now_s >= 0.002 and not r.stats[stat] and time.monotonic() < deadline:
                c = r.get(timeout_s=0.05)
                if c is not None and c.size:
                    chunks.append(c)
        while time.monotonic() < deadline:
            c = r.get(timeout_s=0.3)
            if c is None or not c.size:
                break
            chunks.append(c)
        ev = np.concatenate(chunks)
    finally:
        r.stop()
        t.close()
    assert r.error is None and r.stats[stat] == 1 and r.stats["stream_errors"] == 1
    assert module.card.fired == [fault.split("@")[0]]
    assert (t.device is first) == (stat == "restarts")
    lost = np.flatnonzero(ev["kind"] == EventKind.LOST)
    assert lost.size == 1
    assert np.all(np.diff(ev["sync"].astype(np.int64)) >= 0)
    after = ev[lost[0] + 1:]
    assert np.count_nonzero(after["kind"] == EventKind.MARKER) >= 10, "dwells after the hole"
    assert np.count_nonzero(after["kind"] == EventKind.PHOTON) > 0
