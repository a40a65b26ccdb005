"""The NI-DAQmx card as a transport: the ``nidaqmx`` package (or a stand-in module with its
names, injected) behind a lock, its errors turned into ours, task set-up in one place."""

from __future__ import annotations

import importlib
import logging
import threading

import numpy as np

from spdepth.drivers.errors import DeviceError

log = logging.getLogger("spdepth.nidaq")


class DaqLibraryMissingError(DeviceError):
    """Raised when the ``nidaqmx`` package (or NI's driver under it) is not installed."""


class DaqError(DeviceError):
    """Raised when a DAQmx call fails; ``code`` is NI's error code (negative)."""

    def __init__(self, code: int, message: str):
        self.code = int(code)
        super().__init__(message)


INSTALL_HINT = ("`pip install nidaqmx` and NI-DAQmx (the driver: `python -m nidaqmx "
                "installdriver`)")


def import_nidaqmx(module=None):
    """The ``nidaqmx`` module (or ``module`` when given); DaqLibraryMissingError otherwise."""
    if module is not None:
        return module
    try:
        return importlib.import_module("nidaqmx")
    except ImportError as exc:
        raise DaqLibraryMissingError(f"NI-DAQmx Python package not installed ({exc}): "
                                     f"{INSTALL_HINT}") from None


class DaqTransport:
    """One NI device's analog outputs (mirror x, y) and digital lines (markers).

    device: ``Dev1``; ao: ``ao0:1``; do_lines: ``port0/line0:3``; nidaqmx: the module (tests
    pass a stand-in with the package's names).
    """

    def __init__(self, device: str, ao: str = "ao0:1", do_lines: str = "port0/line0:3", *,
                 nidaqmx=None, v_min: float = -10.0, v_max: float = 10.0):
        self.nidaqmx = import_nidaqmx(nidaqmx)
        self.device, self.ao, self.do_lines = device, ao, do_lines
        self.v_min, self.v_max = v_min, v_max
        self._lock = threading.RLock()
        self._ao_task = self._do_task = None
        self.product, self.serial = self._identify()

    def _wrap(self, what: str, fn, *args, **kwargs):
        errors = self.nidaqmx.errors
        try:
            with self._lock:
                return fn(*args, **kwargs)
        except errors.DaqError as exc:
            code = int(getattr(exc, "error_code", -1))
            raise DaqError(code, f"NI-DAQmx {what} on {self.device}: {exc} (error {code})") from None

    def _identify(self) -> tuple[str, str]:
        def find():
            for d in self.nidaqmx.system.System.local().devices:
                if d.name == self.device:
                    return str(d.product_type), f"{int(d.serial_num):X}"
            return None
        try:
            got = self._wrap("device list", find)
        except DaqError as exc:
            raise DaqLibraryMissingError(f"{exc}: is NI-DAQmx installed? {INSTALL_HINT}") from None
        except Exception as exc:  # noqa: BLE001 - nidaqmx without its driver raises its own errors
            raise DaqLibraryMissingError(f"NI-DAQmx driver not usable ({type(exc).__name__}: "
                                         f"{exc}): {INSTALL_HINT}") from None
        if got is None:
            raise DeviceError(f"NI device {self.device} not found (check NI MAX for its name)")
        return got

    def _new_task(self, kind: str):
        return self.nidaqmx.Task(f"spdepth-{kind}")

    def write_static(self, x_v: float, y_v: float) -> None:
        """Set both outputs now (on-demand task), e.g. to park the mirror."""
        def go():
            with self.nidaqmx.Task("spdepth-park") as t:
                t.ao_channels.add_ao_voltage_chan(f"{self.device}/{self.ao}", min_val=self.v_min,
                                                  max_val=self.v_max)
                t.write([float(x_v), float(y_v)], auto_start=True)
        self._wrap("park", go)

    def start_waveform(self, ao: np.ndarray, do: np.ndarray, rate_hz: float) -> None:
        """Load a finite waveform (ao float (2, N) volts, do bool (L, N)) and start it: the digital
        task runs on the analog task's sample clock, so it is started first and waits for it."""
        C = self.nidaqmx.constants
        n = int(ao.shape[1])

        def go():
            self._close_tasks()
            ao_t, do_t = self._new_task("ao"), self._new_task("do")
            self._ao_task, self._do_task = ao_t, do_t
            ao_t.ao_channels.add_ao_voltage_chan(f"{self.device}/{self.ao}", min_val=self.v_min,
                                                 max_val=self.v_max)
            ao_t.timing.cfg_samp_clk_timing(rate_hz, sample_mode=C.AcquisitionType.FINITE,
                                            samps_per_chan=n)
            do_t.do_channels.add_do_chan(f"{self.device}/{self.do_lines}",
                                         line_grouping=C.LineGrouping.CHAN_PER_LINE)
            do_t.timing.cfg_samp_clk_timing(rate_hz, source=f"/{self.device}/ao/SampleClock",
                                            sample_mode=C.AcquisitionType.FINITE,
                                            samps_per_chan=n)
            do_t.write(do.tolist(), auto_start=False)
            ao_t.write(ao.tolist(), auto_start=False)
            do_t.start()
            ao_t.start()
        self._wrap("scan start", go)

    def open_static(self) -> None:
        """Open on-demand (software-timed) tasks for the mirror and the marker lines, for scans
        the host steps itself (count-gated)."""
        def go():
            self._close_static()
            ao_t, do_t = self._new_task("ao-static"), self._new_task("do-static")
            self._static = (ao_t, do_t)
            ao_t.ao_channels.add_ao_voltage_chan(f"{self.device}/{self.ao}", min_val=self.v_min,
                                                 max_val=self.v_max)
            do_t.do_channels.add_do_chan(f"{self.device}/{self.do_lines}",
                                         line_grouping=self.nidaqmx.constants.LineGrouping.CHAN_PER_LINE)
        self._wrap("static tasks", go)

    def step(self, x_v: float | None, y_v: float | None, lines: list[bool]) -> None:
        """Raise ``lines`` (marker lines, line0 first), move the mirror to (x_v, y_v) (None: stay),
        lower the lines: the markers open the next pixel as the mirror leaves for it."""
        ao_t, do_t = self._static

        def go():
            do_t.write([bool(v) for v in lines], auto_start=True)
            try:
                if x_v is not None:
                    ao_t.write([float(x_v), float(y_v)], auto_start=True)
            finally:
                do_t.write([False] * len(lines), auto_start=True)   # never leave a line high
        self._wrap("step", go)

    def _close_static(self) -> None:
        for t in getattr(self, "_static", ()) or ():
            try:
                t.close()
            except Exception as exc:  # noqa: BLE001
                log.debug("DAQ static task close: %s", exc)
        self._static = ()

    def close_static(self) -> None:
        with self._lock:
            self._close_static()

    def generated(self) -> int:
        """Samples generated so far by the running (or last) waveform."""
        if self._ao_task is None:
            return 0
        return int(self._wrap("progress", lambda: self._ao_task.out_stream.total_samp_per_chan_generated))

    def done(self) -> bool:
        """Whether the waveform has ended (raises DaqError for an error it ended with)."""
        if self._ao_task is None:
            return True
        return bool(self._wrap("status", self._ao_task.is_task_done))

    def _close_tasks(self) -> None:
        for t in (self._ao_task, self._do_task):
            if t is not None:
                try:
                    t.stop()
                except Exception as exc:  # noqa: BLE001 - a task that failed still gets closed
                    log.debug("DAQ task stop: %s", exc)
                try:
                    t.close()
                except Exception as exc:  # noqa: BLE001
                    log.debug("DAQ task close: %s", exc)
        self._ao_task = self._do_task = None

    def stop(self) -> None:
        with self._lock:
            self._close_tasks()

    def close(self) -> None:
        self.stop()
        self.close_static()


def list_devices(nidaqmx=None) -> list[dict]:
    """NI devices the driver sees: ``[{"name", "product", "serial", "ao"}]``."""
    m = import_nidaqmx(nidaqmx)
    out = []
    for d in m.system.System.local().devices:
        out.append({"name": d.name, "product": str(d.product_type),
                    "serial": f"{int(d.serial_num):X}",
                    "ao": [c.name for c in d.ao_physical_chans]})
    return out


__all__ = ["DaqTransport", "DaqError", "DaqLibraryMissingError", "import_nidaqmx", "list_devices",
           "INSTALL_HINT"]
