"""The stand-ins of the vendors' boundaries have the vendors' names and signatures, so a renamed or
re-shaped call fails here in CI instead of in a lab's scan.

* ``nidaqmx``: the stand-in module's classes and methods against the real package (PyPI
  ``nidaqmx``, imports without NI's driver).
* PicoQuant: the stand-in library's exported C functions against the declarations in
  ``drivers.picoquant.transport.SIGNATURES`` (which were written from mhlib.h/hhlib.h of
  PicoQuant's demo repositories), and against the argument counts ``tttrmode.py`` uses.
"""

from __future__ import annotations

import ctypes as ct
import inspect

import pytest

from spdepth.drivers.picoquant import FAMILIES
from spdepth.drivers.picoquant.transport import SIGNATURES
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


@pytest.mark.parametrize("key", ["mh150", "hh400"])
def test_picoquant_standin_exports_every_declared_function(key):
    fam = FAMILIES[key]
    lib = ct.CDLL(str(build_library(key)))
    for name in SIGNATURES:
        full = f"{fam.prefix}_{name}"
        if name in ("SetSyncEdgeTrg", "SetInputEdgeTrg") and fam.readfifo_count:
            assert not hasattr(lib, full), f"{full}: HydraHarp 400 uses CFDs"
            continue
        if name in ("SetSyncCFD", "SetInputCFD") and not fam.readfifo_count:
            assert not hasattr(lib, full), f"{full}: MultiHarp uses edge triggers"
            continue
        assert hasattr(lib, full), full


# calls and argument counts of PicoQuant's MH150-Demos Linux/Python/tttrmode.py and mhlib.h (v3.0)
TTTRMODE_CALLS = {
    "GetLibraryVersion": 1, "GetErrorString": 2, "OpenDevice": 2, "CloseDevice": 1,
    "Initialize": 3, "GetHardwareInfo": 4, "GetNumOfInputChannels": 2, "SetSyncDiv": 2,
    "SetSyncEdgeTrg": 3, "SetSyncChannelOffset": 2, "SetInputEdgeTrg": 4,
    "SetInputChannelOffset": 3, "SetBinning": 2, "SetOffset": 2, "GetResolution": 2,
    "GetSyncRate": 2, "GetCountRate": 3, "StartMeas": 2, "GetFlags": 2, "ReadFiFo": 3,
    "CTCStatus": 2, "StopMeas": 1, "SetMarkerEdges": 5, "SetMarkerEnable": 5,
}


def test_declared_signatures_match_the_vendor_demo():
    for name, n in TTTRMODE_CALLS.items():
        assert len(SIGNATURES[name]) == n, name


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
