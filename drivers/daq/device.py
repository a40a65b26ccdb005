"""A galvo driven by an NI-DAQ card, with the scan interface of our serial galvo controller
(``drivers.galvo.Galvo``) so the live scan source drives either: configure a pattern and a gate,
start, poll the status, stop, park.

Fixed dwell (raster): the card steps the mirror from its own sample clock and raises the marker
lines with each step (hardware-timed). Count-gated: the card cannot count photons, so the host
steps the mirror itself (on-demand writes) and moves on when ``counter(row, col)`` (the session's
count of the pixel's in-window detections, from the decoded stream) reaches the target or the
dwell limit passes. Its latency (detection -> step) is the stream's: the tagger's read interval,
the reader's queue and the session's processing, a few ms to tens of ms (README); each pixel then
dwells that much longer than needed, which costs time, never data (the session keeps the first N
detections of each pixel)."""

from __future__ import annotations

import logging
import threading
import time

import numpy as np

from spdepth.drivers.daq.protocol import DaqCalibration, raster_waveform
from spdepth.drivers.daq.transport import DaqError, DaqTransport
from spdepth.drivers.errors import SettingError
from spdepth.drivers.galvo.errors import ErrorCode
from spdepth.drivers.galvo.protocol import (GalvoState, GateMode, PixelFlag, PixelPage, PixelRecord,
                                            ScanMode, Status)

GATE_POLL_S = 0.0002
"""How often a count-gated pixel's count is looked at."""

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
        self._gated = None          # (order (P, 2), volts (2, P), n_target, limit_s) of a gated scan
        self._thread = None
        self._halt = threading.Event()
        self._log: list[PixelRecord] = []
        self._log_read = 0
        self._completed = 0
        self.counter = None
        """Count-gated scans: ``counter(row, col)`` -> in-window detections the pixel holds
        (pattern coordinates); the scan source sets it."""
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
        if frames != 1:
            raise SettingError("the NI-DAQ galvo scans one frame per start")
        if settle_s:
            raise SettingError("the NI-DAQ galvo has no settle time yet (--settle-us 0)")
        xs = np.linspace(pattern.x_first_deg, pattern.x_last_deg, pattern.nx)
        ys = np.linspace(pattern.y_first_deg, pattern.y_last_deg, pattern.ny)
        # the raster's samples give the order and the volts (checked against the limits) either way
        wave = raster_waveform(pattern.nx, pattern.ny, xs, ys, max(gate.dwell_s, 2e-6),
                               self.calibration, serpentine=pattern.mode == ScanMode.SERPENTINE)
        self._wave = wave
        self._gated = None
        if gate.mode == GateMode.COUNT:
            if self.counter is None:
                raise SettingError("a count-gated NI-DAQ scan needs a counter (the session's "
                                   "per-pixel counts)")
            volts = wave.ao[:, wave.do[0]]            # the sample that opens each pixel
            self._gated = (wave.order, volts, int(gate.n_target), float(gate.dwell_s))

    def start(self) -> Status:
        if self._wave is None:
            raise SettingError("configure_scan before start")
        w = self._wave
        self._scan_id += 1
        self._completed = 0
        if self._gated is not None:
            self.transport.open_static()
            self._halt.clear()
            self._state = GalvoState.SCANNING
            self._thread = threading.Thread(target=self._gated_main, name="daq-gated", daemon=True)
            self._thread.start()
            return self.status()
        self.transport.start_waveform(w.ao, w.do, w.rate_hz)
        self._state = GalvoState.SCANNING
        return self.status()

    def _gated_main(self) -> None:
        """Step pixel by pixel; each pixel ends at the target count or the dwell limit."""
        order, volts, n_target, limit_s = self._gated
        step = self.transport.step
        try:
            prev_row = None
            for i, (row, col) in enumerate(order.tolist()):
                if self._halt.is_set():
                    break
                if prev_row is not None and row != prev_row:
                    step(None, None, [False, False, True, False])          # LINE_STOP
                lines = [True, row != prev_row, False, i == 0]             # PIXEL, LINE_START, FRAME
                step(float(volts[0, i]), float(volts[1, i]), lines)
                t0 = time.monotonic()
                got = self.counter(row, col)
                while got < n_target and time.monotonic() - t0 < limit_s \
                        and not self._halt.is_set():
                    self._halt.wait(GATE_POLL_S)
                    got = self.counter(row, col)
                if self._halt.is_set() and got < n_target:
                    break                  # stopped mid-dwell: this pixel did not complete
                dwell_ns = int((time.monotonic() - t0) * 1e9)
                flag = PixelFlag.GATED if got >= n_target else PixelFlag.LIMIT
                self._log.append(PixelRecord(len(self._log), 0, row, col, int(got), dwell_ns, flag))
                self._completed = i + 1
                prev_row = row
            if prev_row is not None:
                step(None, None, [False, False, True, False])
        except DaqError as exc:
            log.warning("DAQ gated scan failed: %s", exc)
            self._errors.append((ErrorCode.HARDWARE_FAULT, str(exc)))
            self._state = GalvoState.FAULT
            return
        if self._state == GalvoState.SCANNING:
            self._state = GalvoState.PARKED

    def status(self) -> Status:
        w = self._wave
        total = 0 if w is None else int(w.pixels_done[-1])
        if self._gated is not None:
            if self._state != GalvoState.SCANNING and self._thread is not None:
                self._end_gated()
        elif self._state == GalvoState.SCANNING:
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

    def _end_gated(self) -> None:
        self._halt.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(5.0)
        self._thread = None
        self.transport.close_static()
        if self._state != GalvoState.FAULT:
            self.park()

    def _safe_completed(self) -> int:
        if self._gated is not None:
            return self._completed
        try:
            gen = self.transport.generated()
        except DaqError:
            return 0
        return int(self._wave.pixels_done[min(gen, self._wave.n_samples)])

    def stop(self) -> None:
        if self._gated is not None and self._thread is not None:
            self._halt.set()
            self._end_gated()
            if self._state == GalvoState.SCANNING:
                self._state = GalvoState.PARKED
            return
        if self._state == GalvoState.SCANNING:
            self._completed = self._safe_completed()
            self._state = GalvoState.PARKED
        self.transport.stop()

    def park(self) -> None:
        x, y = self.calibration.volts(*self.calibration.park_deg, what="park position")
        self.transport.write_static(float(x), float(y))

    def poll_pixels(self, max_records: int = 0) -> PixelPage:
        """Count-gated scans: the pixels stepped since the last call (count seen, dwell, G/L);
        raster scans keep no log (the markers in the stream are the record)."""
        first = self._log_read
        recs = tuple(self._log[first:])
        self._log_read += len(recs)
        return PixelPage(first, first, recs)

    def next_error(self) -> tuple[ErrorCode, str]:
        if self._errors:
            return self._errors.pop(0)
        return ErrorCode.NO_ERROR, "no error"

    def clear_errors(self) -> None:
        self._errors.clear()
        if self._state == GalvoState.FAULT:
            self.transport.stop()
            if self._thread is not None:
                self._end_gated()
            self._state = GalvoState.PARKED
            self.park()

    def close(self) -> None:
        self.transport.close()


__all__ = ["DaqGalvo"]
