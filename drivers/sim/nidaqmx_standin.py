"""A stand-in for the ``nidaqmx`` package, driving the simulated bench: a module-like object with
the package's names (``Task``, ``constants``, ``errors``, ``system``) whose analog output task
moves the rig's mirror and whose digital lines pulse the rig's marker inputs, sample by sample on
the analog task's sample clock. ``tests/test_vendor_standins.py`` checks these names and
signatures against the real package.

``NiDaqmxStandIn(rig)`` is the module; pass it as ``nidaqmx=`` to ``drivers.daq``. The card runs
the waveform in a thread as fast as the photon world computes it (virtual time), and holds the
mirror and marker lines exactly as the samples say: volts -> degrees with ``deg_per_volt``, a
rising edge on line n -> marker bit n.

Faults (``drivers.sim.faults`` kind ``daq-underflow`` at a share of the scan or a virtual time):
the card stops generating and the task reports NI's output underflow error (-200621) from
``is_task_done``, as a card does when its output buffer runs dry.
"""

from __future__ import annotations

import threading
import types
from enum import Enum

import numpy as np

from spdepth.drivers.errors import SettingError
from spdepth.drivers.sim.faults import FaultKind, FaultSchedule, parse_faults

OUTPUT_FIFO_UNDERFLOW = -200621
"""NI's code for an output buffer that ran dry during generation."""


class AcquisitionType(Enum):
    FINITE = 10178
    CONTINUOUS = 10123
    HW_TIMED_SINGLE_POINT = 12522


class LineGrouping(Enum):
    CHAN_PER_LINE = 0
    CHAN_FOR_ALL_LINES = 1


class Edge(Enum):
    RISING = 10280
    FALLING = 10171


class VoltageUnits(Enum):
    VOLTS = 10348
    FROM_CUSTOM_SCALE = 10065


class DaqError(Exception):
    """As ``nidaqmx.errors.DaqError``: ``error_code`` NI's code."""

    def __init__(self, message, error_code, task_name=""):
        super().__init__(message)
        self.error_code = error_code
        self.task_name = task_name


def _expand(spec: str) -> list[str]:
    """``Dev1/ao0:1`` -> [``Dev1/ao0``, ``Dev1/ao1``]; ``Dev1/port0/line0:3`` likewise."""
    head, _, last = spec.rpartition("/")
    stem = last.rstrip("0123456789:")
    rng = last[len(stem):]
    if ":" in rng:
        a, b = (int(v) for v in rng.split(":"))
        return [f"{head}/{stem}{i}" for i in range(a, b + 1)]
    return [spec]


class _Card:
    """The simulated device: owns the rig, runs armed waveforms; while on-demand (static) tasks
    are open, a clock thread lets the laser and detector run in real time (``pace`` virtual
    seconds per second) with the mirror where the last write put it, as a held mirror does while
    the host decides when to step it."""

    def __init__(self, rig, name, deg_per_volt, faults, scan_pixels, pace=1.0):
        self.rig, self.name, self.deg_per_volt = rig, name, deg_per_volt
        self.schedule = FaultSchedule(faults)
        self.scan_pixels = scan_pixels
        self.armed_do = None        # a DO task waiting for the AO sample clock
        self.fired: list[str] = []
        self.pace = float(pace)
        self.lines = None           # on-demand DO state
        self.static_tasks = 0
        self.hold = threading.Lock()   # held by a step (lines high .. low): the world waits
        self._clock = None
        self._clock_stop = threading.Event()

    def static_opened(self):
        self.static_tasks += 1
        if self._clock is None:
            self._clock_stop.clear()
            self._clock = threading.Thread(target=self._run_clock, name="daq-standin-clock",
                                           daemon=True)
            self._clock.start()

    def static_closed(self):
        self.static_tasks = max(0, self.static_tasks - 1)
        if self.static_tasks == 0 and self._clock is not None:
            self._clock_stop.set()
            if self._clock is not threading.current_thread():
                self._clock.join(2.0)
            self._clock = None

    def _run_clock(self):
        import time

        last = time.monotonic()
        period = self.rig.world.sync_period_s
        while not self._clock_stop.wait(0.0005):
            with self.hold:
                now = time.monotonic()
                dt = (now - last) * self.pace
                if dt >= period:
                    self.rig.fixed_dwell(dt)
                    last = now
                    if self.fault_due():
                        self.underflow = True

    underflow = False

    def fault_due(self) -> bool:
        frac = self.rig.pixels_pulsed / self.scan_pixels if self.scan_pixels else None
        due = self.schedule.take_due(self.rig.now_s, frac)
        self.fired += [f.kind.value for f in due]
        return bool(due)


class _Channels:
    def __init__(self, task, kind):
        self._task, self._kind = task, kind

    def add_ao_voltage_chan(self, physical_channel, name_to_assign_to_channel="", min_val=-10.0,
                            max_val=10.0, units=VoltageUnits.VOLTS, custom_scale_name=""):
        if self._kind != "ao":
            raise AttributeError("add_ao_voltage_chan")
        chans = _expand(physical_channel)
        self._task._check_device(chans)
        self._task.channels += chans
        self._task.limits = (float(min_val), float(max_val))
        return chans

    def add_do_chan(self, lines, name_to_assign_to_lines="", line_grouping=LineGrouping.CHAN_FOR_ALL_LINES):
        if self._kind != "do":
            raise AttributeError("add_do_chan")
        chans = _expand(lines)
        self._task._check_device(chans)
        if line_grouping != LineGrouping.CHAN_PER_LINE:
            raise DaqError("the stand-in takes one channel per line", -200000)
        self._task.channels += chans
        return chans


class _Timing:
    def __init__(self, task):
        self._task = task

    def cfg_samp_clk_timing(self, rate, source="", active_edge=Edge.RISING,
                            sample_mode=AcquisitionType.FINITE, samps_per_chan=1000):
        if not rate > 0:
            raise DaqError(f"sample clock rate {rate} must be > 0", -200077)
        if sample_mode != AcquisitionType.FINITE:
            raise DaqError("the stand-in generates finite waveforms only", -200077)
        self._task.clock = (float(rate), source, int(samps_per_chan))


class _OutStream:
    def __init__(self, task):
        self._task = task

    @property
    def total_samp_per_chan_generated(self):
        return self._task.generated


class StandInTask:
    """As ``nidaqmx.Task`` (the calls ``drivers.daq`` makes)."""

    def __init__(self, new_task_name="", *, grpc_options=None, _card=None):
        self._card = _card
        self.name = new_task_name
        self.channels: list[str] = []
        self.limits = (-10.0, 10.0)
        self.clock = None
        self.data = None
        self.generated = 0
        self.error: DaqError | None = None
        self._opened_static = False
        self._thread = None
        self._stop = threading.Event()
        self.ao_channels = _Channels(self, "ao")
        self.do_channels = _Channels(self, "do")
        self.timing = _Timing(self)
        self.out_stream = _OutStream(self)

    def _check_device(self, chans):
        for c in chans:
            if c.split("/")[0] != self._card.name:
                raise DaqError(f"device {c.split('/')[0]} not found", -200220)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def write(self, data, auto_start=None, timeout=10.0):
        arr = np.asarray(data)
        if arr.ndim == 1:
            arr = arr[:, None] if len(self.channels) > 1 else arr[None, :]
        if arr.shape[0] != len(self.channels):
            raise DaqError(f"write: {arr.shape[0]} rows for {len(self.channels)} channels", -200524)
        if self.channels[0].split("/")[1].startswith("ao"):
            lo, hi = self.limits
            if arr.size and (arr.min() < lo - 1e-9 or arr.max() > hi + 1e-9):
                raise DaqError("write: value outside the channel's limits", -200561)
        self.data = arr
        if self.clock is None:        # on-demand: applied at once; the world runs meanwhile
            card = self._card
            if not self._opened_static:
                self._opened_static = True
                card.static_opened()
            if card.underflow:
                card.underflow = False         # reported once, as the task's error
                raise DaqError("the stand-in's held output faulted", OUTPUT_FIFO_UNDERFLOW,
                               self.name)
            if self.channels[0].split("/")[1].startswith("ao"):
                card.rig.set_mirror(*(arr[:, -1] * card.deg_per_volt))
            else:
                now = arr[:, -1].astype(bool)
                prev = card.lines if card.lines is not None else np.zeros_like(now)
                rising = now & ~prev
                if now.any() and not prev.any():
                    card.hold.acquire()      # a step: the world waits until the lines fall
                mask = int(np.dot(rising, 1 << np.arange(rising.size)))
                if mask:
                    card.rig.pulse_markers(mask)
                if prev.any() and not now.any():
                    card.hold.release()
                card.lines = now
            return arr.shape[1]
        if auto_start:
            self.start()
        return arr.shape[1]

    def start(self):
        if self.clock is None or self.data is None:
            return
        rate, source, n = self.clock
        if source:                    # clocked by another task: waits for it
            self._card.armed_do = self
            return
        self._stop.clear()
        self._thread = threading.Thread(target=self._generate, name="daq-standin", daemon=True)
        self._thread.start()

    def _generate(self):
        card, rig = self._card, self._card.rig
        rate, _, n = self.clock
        do = card.armed_do.data.astype(bool) if card.armed_do is not None else None
        ao = self.data
        dt = 1.0 / rate
        prev = np.zeros(do.shape[0], bool) if do is not None else None
        for k in range(min(n, ao.shape[1])):
            if self._stop.is_set():
                return
            if card.fault_due():
                self.error = DaqError("Onboard device memory underflow. Because of system and/or "
                                      "bus-bandwidth limitations, the driver could not write data "
                                      "to the device fast enough to keep up with the device "
                                      "output rate.", OUTPUT_FIFO_UNDERFLOW, self.name)
                return
            rig.set_mirror(float(ao[0, k]) * card.deg_per_volt, float(ao[1, k]) * card.deg_per_volt)
            if do is not None:
                rising = do[:, k] & ~prev
                prev = do[:, k]
                mask = int(np.dot(rising, 1 << np.arange(rising.size)))
                if mask:
                    rig.pulse_markers(mask)
            rig.fixed_dwell(dt)
            self.generated = k + 1
            if card.armed_do is not None:
                card.armed_do.generated = k + 1

    def is_task_done(self):
        if self.error is not None:
            raise self.error
        return self._thread is None or not self._thread.is_alive()

    def wait_until_done(self, timeout=10.0):
        if self._thread is not None:
            self._thread.join(timeout)
        return self.is_task_done()

    def stop(self):
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(5.0)
        if self._card.armed_do is self:
            self._card.armed_do = None

    def close(self):
        self.stop()
        if self._opened_static:
            self._opened_static = False
            self._card.static_closed()


class _PhysChan:
    def __init__(self, name):
        self.name = name


class _Device:
    def __init__(self, name, product_type, serial_num):
        self.name, self.product_type, self.serial_num = name, product_type, serial_num
        self.ao_physical_chans = [_PhysChan(f"{name}/ao{i}") for i in range(2)]
        self.do_lines = [_PhysChan(f"{name}/port0/line{i}") for i in range(8)]


class NiDaqmxStandIn(types.SimpleNamespace):
    """The stand-in module. rig: a ``SimRig``; device: the card's name; deg_per_volt: optical
    degrees per volt of the simulated servo (match the driver's calibration); faults: a spec or
    list (kind ``daq-underflow``); scan_pixels: for faults given as a share of the scan."""

    def __init__(self, rig, device: str = "Dev1", *, deg_per_volt: float = 1.0, faults=None,
                 scan_pixels: int | None = None, product: str = "USB-6343", serial: int = 0x1A2B3C4,
                 pace: float = 1.0):
        faults = parse_faults(faults) if isinstance(faults, str) or faults is None else list(faults)
        bad = [f for f in faults if f.kind != FaultKind.DAQ_UNDERFLOW]
        if bad:
            raise SettingError(f"the NI-DAQ stand-in injects daq-underflow only, not "
                               f"{', '.join(f.kind.value for f in bad)}")
        if any(f.at_fraction is not None for f in faults) and not scan_pixels:
            raise SettingError("faults given as a share of the scan need scan_pixels")
        card = _Card(rig, device, float(deg_per_volt), faults, scan_pixels, pace)
        devices = [_Device(device, product, serial)]

        class System:
            @staticmethod
            def local():
                return types.SimpleNamespace(devices=devices)

        def task(new_task_name="", *, grpc_options=None):
            return StandInTask(new_task_name, grpc_options=grpc_options, _card=card)

        super().__init__(
            __name__="nidaqmx", Task=task, card=card,
            constants=types.SimpleNamespace(AcquisitionType=AcquisitionType,
                                            LineGrouping=LineGrouping, Edge=Edge,
                                            VoltageUnits=VoltageUnits),
            errors=types.SimpleNamespace(DaqError=DaqError),
            system=types.SimpleNamespace(System=System))


__all__ = ["NiDaqmxStandIn", "StandInTask", "DaqError", "OUTPUT_FIFO_UNDERFLOW"]
