"""A galvo driven by an NI-DAQ card, with the scan interface of our serial galvo controller
(``drivers.galvo.Galvo``) so the live scan source drives either: configure a pattern and a gate,
start, poll the status, stop, park. Fixed-dwell (raster) scans only: the card steps the mirror
from its own sample clock and raises the marker lines with each step."""

from __future__ import annotations

import logging

import numpy as np

from spdepth.drivers.daq.protocol import DaqCalibration, raster_waveform
from spdepth.drivers.daq.transport import DaqError, DaqTransport
from spdepth.drivers.errors import SettingError
from spdepth.drivers.galvo.errors import ErrorCode
from spdepth.drivers.galvo.protocol import GalvoState, GateMode, PixelPage, ScanMode, Status

log = logging.getLogger("spdepth.nidaq")


class DaqGalvo:
    """Two analog outputs (x, y) and four marker lines of one NI device (``DaqTransport``)."""

    def __init__(self, transport: DaqTransport, calibration: DaqCalibration | None = None):
        self.transport = transport
        self.calibration = calibration or DaqCalibration()
        self.reconnects = 0
        self._wave = None
        self._state = GalvoState.IDLE
        self._errors: list[tuple[ErrorCode, str]] = []
        self._scan_id = 0
        self.identity = {"kind": "nidaq", "device": transport.device, "ao": transport.ao,
                         "do": transport.do_lines, "product": transport.product,
                         "serial": transport.serial, "calibration": self.calibration.to_dict()}

    @classmethod
    def open(cls, spec: str, *, nidaqmx=None, calibration: DaqCalibration | None = None) -> "DaqGalvo":
        """``Dev1`` or ``Dev1/ao0:1`` (the ``nidaq:`` device string without its scheme)."""
        from spdepth.drivers.daq.protocol import parse_channels

        dev, ao = parse_channels(spec)
        cal = calibration or DaqCalibration()
        return cls(DaqTransport(dev, ao, nidaqmx=nidaqmx, v_min=cal.v_min, v_max=cal.v_max), cal)

    @property
    def settings(self) -> dict:
        return self.calibration.to_dict()

    # ---- the scan interface of drivers.galvo.Galvo -----------------------------------------------
    def configure_scan(self, pattern, gate, *, settle_s: float = 0.0, frames: int = 1) -> None:
        if gate.mode != GateMode.FIXED:
            raise SettingError("count-gated scans with an NI-DAQ galvo are not supported yet: use "
                               "--mode raster (fixed dwell)")
        if frames != 1:
            raise SettingError("the NI-DAQ galvo scans one frame per start")
        if settle_s:
            raise SettingError("the NI-DAQ galvo has no settle time yet (--settle-us 0)")
        xs = np.linspace(pattern.x_first_deg, pattern.x_last_deg, pattern.nx)
        ys = np.linspace(pattern.y_first_deg, pattern.y_last_deg, pattern.ny)
        self._wave = raster_waveform(pattern.nx, pattern.ny, xs, ys, gate.dwell_s, self.calibration,
                                     serpentine=pattern.mode == ScanMode.SERPENTINE)

    def start(self) -> Status:
        if self._wave is None:
            raise SettingError("configure_scan before start")
        w = self._wave
        self._scan_id += 1
        self.transport.start_waveform(w.ao, w.do, w.rate_hz)
        self._state = GalvoState.SCANNING
        return self.status()

    def status(self) -> Status:
        w = self._wave
        total = 0 if w is None else int(w.pixels_done[-1])
        if self._state == GalvoState.SCANNING:
            try:
                done = self.transport.done()
                gen = self.transport.generated()
            except DaqError as exc:
                log.warning("DAQ scan failed: %s", exc)
                self._errors.append((ErrorCode.HARDWARE_FAULT, str(exc)))
                self._state = GalvoState.FAULT
                self._completed = self._safe_completed()
                self.transport.stop()
            else:
                self._completed = int(w.pixels_done[min(gen, w.n_samples)])
                if done:
                    self._state = GalvoState.PARKED
                    self.transport.stop()
                    self.park()
        completed = getattr(self, "_completed", 0)
        row, col = (-1, -1)
        if w is not None and completed:
            row, col = (int(v) for v in w.order[min(completed, len(w.order)) - 1])
        return Status(self._state, self._scan_id, 0, row, col, completed, total)

    def _safe_completed(self) -> int:
        try:
            gen = self.transport.generated()
        except DaqError:
            return 0
        return int(self._wave.pixels_done[min(gen, self._wave.n_samples)])

    def stop(self) -> None:
        if self._state == GalvoState.SCANNING:
            self._completed = self._safe_completed()
            self._state = GalvoState.PARKED
        self.transport.stop()

    def park(self) -> None:
        x, y = self.calibration.volts(*self.calibration.park_deg, what="park position")
        self.transport.write_static(float(x), float(y))

    def poll_pixels(self, max_records: int = 0) -> PixelPage:
        """The card keeps no pixel log (the markers in the stream are the record)."""
        return PixelPage(0, 0, ())

    def next_error(self) -> tuple[ErrorCode, str]:
        if self._errors:
            return self._errors.pop(0)
        return ErrorCode.NO_ERROR, "no error"

    def clear_errors(self) -> None:
        self._errors.clear()
        if self._state == GalvoState.FAULT:
            self.transport.stop()
            self._state = GalvoState.PARKED
            self.park()

    def close(self) -> None:
        self.transport.close()


__all__ = ["DaqGalvo"]
