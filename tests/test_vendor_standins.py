"""The stand-ins of the vendors' boundaries have the vendors' names and signatures, so a renamed or
re-shaped call fails here in CI instead of in a lab's scan.

* ``nidaqmx``: the stand-in module's classes and methods against the real package (PyPI
  ``nidaqmx``, imports without NI's driver).
* PicoQuant: per family, the stand-in library's exported C functions and our ctypes declarations
  (``drivers.picoquant.transport.signature``) against the functions and argument counts of the
  vendor's header (mhlib.h, hhlib.h, th260lib.h, ph330lib.h).
"""

from __future__ import annotations

import ctypes as ct
import inspect

import pytest

from spdepth.drivers.picoquant import FAMILIES
from spdepth.drivers.picoquant.transport import SIGNATURES, signature
from spdepth.drivers.sim import nidaqmx_standin as fake
from spdepth.drivers.sim.picoquant_standin import build_library


def _params(fn) -> list[tuple[str, object]]:
    sig = inspect.signature(fn)
    return [(p.name, p.kind) for p in sig.parameters.values()]


def _real_nidaqmx():
    try:
        import nidaqmx
        from nidaqmx.task._out_stream import OutStream
        from nidaqmx.task._timing import Timing
        from nidaqmx.task.collections._ao_channel_collection import AOChannelCollection
        from nidaqmx.task.collections._do_channel_collection import DOChannelCollection
    except ImportError as exc:
        pytest.skip(f"the real nidaqmx package does not import here ({exc})")
    return nidaqmx, AOChannelCollection, DOChannelCollection, Timing, OutStream


def test_nidaqmx_standin_has_the_packages_names_and_signatures():
    nidaqmx, AO, DO, Timing, OutStream = _real_nidaqmx()
    pairs = [
        (nidaqmx.Task.__init__, fake.StandInTask.__init__, ["_card"]),
        (nidaqmx.Task.write, fake.StandInTask.write, []),
        (nidaqmx.Task.start, fake.StandInTask.start, []),
        (nidaqmx.Task.stop, fake.StandInTask.stop, []),
        (nidaqmx.Task.close, fake.StandInTask.close, []),
        (nidaqmx.Task.is_task_done, fake.StandInTask.is_task_done, []),
        (nidaqmx.Task.wait_until_done, fake.StandInTask.wait_until_done, []),
        (AO.add_ao_voltage_chan, fake._Channels.add_ao_voltage_chan, []),
        (DO.add_do_chan, fake._Channels.add_do_chan, []),
        (Timing.cfg_samp_clk_timing, fake._Timing.cfg_samp_clk_timing, []),
        (nidaqmx.errors.DaqError.__init__, fake.DaqError.__init__, []),
    ]
    for real, ours, extra in pairs:
        got = [p for p in _params(ours) if p[0] not in extra]
        assert got == _params(real), f"{real.__qualname__}: {got} != {_params(real)}"
    for name in ("ao_channels", "do_channels", "timing", "out_stream"):
        assert isinstance(getattr(nidaqmx.Task, name), property)
    assert isinstance(OutStream.total_samp_per_chan_generated, property)
    for enum_name, members in (("AcquisitionType", fake.AcquisitionType),
                               ("LineGrouping", fake.LineGrouping), ("Edge", fake.Edge)):
        real = getattr(nidaqmx.constants, enum_name)
        for m in members:
            assert real[m.name].value == m.value, f"{enum_name}.{m.name}"
    dev = nidaqmx.system.Device
    for attr in ("name", "product_type", "serial_num", "ao_physical_chans", "do_lines"):
        assert hasattr(dev, attr), attr
    assert hasattr(nidaqmx.system.System, "local") and hasattr(nidaqmx.system.System, "devices")
    codes = nidaqmx.error_codes.DAQmxErrors
    assert codes.OUTPUT_FIFO_UNDERFLOW_2.value == fake.OUTPUT_FIFO_UNDERFLOW


def test_nidaqmx_real_package_without_driver_is_a_missing_library_line():
    _real_nidaqmx()
    from spdepth.drivers.daq import DaqGalvo, DaqLibraryMissingError

    try:
        import nidaqmx
        list(nidaqmx.system.System.local().devices)
    except Exception:   # noqa: BLE001 - no NI driver: what CI has
        with pytest.raises(DaqLibraryMissingError, match="installdriver"):
            DaqGalvo.open("Dev1")
    else:
        pytest.skip("NI-DAQmx is installed here")


# For each family, the functions of ``SIGNATURES`` its vendor header declares and their argument
# counts (None: the header has no such function), read from mhlib.h v3.0 (MH150-Demos), hhlib.h
# v3.0 (HH400-v3.x-Demos), th260lib.h v3.2 (TH260-Demos; TimeHarp260-Linux library/th260lib.h is
# the same) and ph330lib.h v2.0 (the MultiHarp and TimeHarp 260 demos' tttrmode.py call them with
# these counts). The families differ in the trigger calls, Initialize and ReadFiFo.
_COMMON_CALLS = {
    "GetLibraryVersion": 1, "GetErrorString": 2, "OpenDevice": 2, "CloseDevice": 1,
    "GetHardwareInfo": 4, "GetSerialNumber": 2, "GetFeatures": 2, "GetBaseResolution": 3,
    "GetNumOfInputChannels": 2, "SetSyncDiv": 2, "SetSyncChannelOffset": 2,
    "SetInputChannelOffset": 3, "SetBinning": 2, "SetOffset": 2, "GetResolution": 2,
    "GetSyncRate": 2, "GetCountRate": 3, "GetFlags": 2, "SetMarkerEdges": 5, "SetMarkerEnable": 5,
    "StartMeas": 2, "StopMeas": 1, "CTCStatus": 2,
    "SetSyncTrgMode": None, "SetInputTrgMode": None, "SetSyncEdgeTrg": None,
    "SetInputEdgeTrg": None, "SetSyncCFD": None, "SetInputCFD": None,
}
_EDGE = {"SetSyncEdgeTrg": 3, "SetInputEdgeTrg": 4}
_CFD = {"SetSyncCFD": 3, "SetInputCFD": 4}
_MH = {**_COMMON_CALLS, **_EDGE, "Initialize": 3, "ReadFiFo": 3}
HEADER_CALLS = {
    "mh150": _MH,
    "mh160": _MH,
    "hh400": {**_COMMON_CALLS, **_CFD, "Initialize": 3, "ReadFiFo": 4},
    "th260": {**_COMMON_CALLS, **_EDGE, **_CFD, "Initialize": 2, "ReadFiFo": 4},
    "ph330": {**_COMMON_CALLS, **_EDGE, **_CFD, "SetSyncTrgMode": 2, "SetInputTrgMode": 3,
              "Initialize": 3, "ReadFiFo": 3},
}


def test_every_supported_family_has_its_header_checked():
    assert set(HEADER_CALLS) == set(FAMILIES)
    for calls in HEADER_CALLS.values():
        assert set(calls) == set(SIGNATURES)


@pytest.mark.parametrize("key", sorted(FAMILIES))
def test_picoquant_standin_and_declarations_match_the_vendor_header(key):
    """The stand-in of ``key`` exports exactly the header's functions (of those we call), and our
    ctypes declaration of each has the header's argument count."""
    fam = FAMILIES[key]
    lib = ct.CDLL(str(build_library(key)))
    for name, n_args in HEADER_CALLS[key].items():
        full = f"{fam.prefix}_{name}"
        assert hasattr(lib, full) == (n_args is not None), full
        if n_args is not None:
            assert len(signature(fam, name)) == n_args, full


def _real_timetagger():
    try:
        import Swabian.TimeTagger as tt
    except ImportError as exc:
        pytest.skip(f"the real Swabian-TimeTagger package does not import here ({exc})")
    return tt


def _doc_params(fn) -> list[str]:
    """Parameter names a SWIG function documents (``:param name:``), in order."""
    import re

    return re.findall(r":param (\w+):", fn.__doc__ or "")


def test_swabian_standin_has_the_packages_names_and_parameters():
    from spdepth.drivers.sim import swabian_standin as sw

    tt = _real_timetagger()
    for name in ("createTimeTagger", "freeTimeTagger", "scanTimeTagger", "TimeTagStream", "TagType"):
        assert hasattr(tt, name), name
    assert _doc_params(tt.createTimeTagger)[:1] == ["serial"]
    assert _doc_params(tt.scanTimeTagger) == ["include_model_name"]
    assert _doc_params(tt.TimeTagStream.__init__) == ["tagger", "n_max_events", "channels"]
    ours = list(inspect.signature(sw.StandInTimeTagStream.__init__).parameters)[1:]
    assert ours == ["tagger", "n_max_events", "channels"]
    for method, params in (("setTriggerLevel", ["channel", "voltage"]),
                           ("setEventDivider", ["channel", "divider"]),
                           ("getSerial", []), ("getModel", [])):
        real = getattr(tt.TimeTagger, method)
        assert _doc_params(real)[:len(params)] == params, method
        mine = list(inspect.signature(getattr(sw.StandInTimeTagger, method)).parameters)[1:]
        assert mine == params, method
    for method in ("start", "stop", "getData", "isRunning", "clear"):
        assert hasattr(tt.TimeTagStream, method) and hasattr(sw.StandInTimeTagStream, method)
    for method in ("getTimestamps", "getChannels", "getEventTypes", "getMissedEvents",
                   "hasOverflows"):
        assert hasattr(tt.TimeTagStreamBuffer, method) and hasattr(sw._Buffer, method), method
    assert {m.name: int(m) for m in tt.TagType} == {m.name: int(m) for m in sw.TagType}
    from spdepth.drivers.swabian import TagType as Ours

    assert [int(m) for m in Ours] == [int(m) for m in tt.TagType]
