"""pyserial URL handler ``galvosim://NAME?options``: a serial port wired to a GalvoFirmware.

Enabled by ``drivers.sim.register_url_handlers()`` (importing ``drivers.sim`` does it; the real
``drivers.galvo`` does not), after which ``serial.serial_for_url("galvosim://bench")`` opens the
emulator registered (or created) under that name; see ``drivers.sim.galvo_fw.device_for_url`` for
the options. An unplugged emulator makes every call raise SerialException, and ``open()`` fails
until it is plugged back in, like a USB-serial adapter that vanished from /dev.
"""

from __future__ import annotations

import time

from serial.serialutil import PortNotOpenError, SerialBase, SerialException

from spdepth.drivers.errors import SettingError
from spdepth.drivers.sim import galvo_fw


class Serial(SerialBase):
    """Serial port implementation backed by an in-process galvo firmware emulator."""

    BAUDRATES = (9600, 19200, 38400, 57600, 115200, 230400, 460800, 921600)

    def __init__(self, *args, **kwargs):
        self._fw: galvo_fw.GalvoFirmware | None = None
        self._gen = -1
        super().__init__(*args, **kwargs)

    def open(self):
        if self.is_open:
            raise SerialException("Port is already open.")
        if self._port is None:
            raise SerialException("Port must be configured before it can be used.")
        try:
            fw = galvo_fw.device_for_url(self._port)
        except SettingError as e:
            raise SerialException(f"could not open port {self._port}: {e}") from e
        if not fw.is_plugged:
            raise SerialException(f"could not open port {self._port}: no such device "
                                  f"(unplugged)")
        self._fw = fw
        self._gen = fw.generation
        self.is_open = True

    def close(self):
        self.is_open = False
        self._fw = None

    def _reconfigure_port(self):
        """Baud rate, parity and the like mean nothing to an in-process emulator."""

    def _live(self) -> galvo_fw.GalvoFirmware:
        if not self.is_open or self._fw is None:
            raise PortNotOpenError()
        return self._fw

    def _gone(self, e: OSError):
        return SerialException(f"{self._port}: device reports readiness to read but returned no "
                               f"data (device disconnected?): {e}")

    @property
    def in_waiting(self) -> int:
        fw = self._live()
        try:
            return fw.out_waiting(self._gen)
        except galvo_fw.PortUnplugged as e:
            raise self._gone(e) from e

    def read(self, size: int = 1) -> bytes:
        fw = self._live()
        timeout = self._timeout
        deadline = None if timeout is None else time.monotonic() + timeout
        out = bytearray()
        try:
            while len(out) < size:
                wait = 3600.0 if deadline is None else max(0.0, deadline - time.monotonic())
                chunk = fw.host_read(size - len(out), wait, self._gen)
                out += chunk
                if deadline is not None and time.monotonic() >= deadline:
                    break
        except galvo_fw.PortUnplugged as e:
            raise self._gone(e) from e
        return bytes(out)

    def write(self, data) -> int:
        fw = self._live()
        data = bytes(data)
        try:
            fw.host_write(data, self._gen)
        except galvo_fw.PortUnplugged as e:
            raise SerialException(f"{self._port}: write failed: {e}") from e
        return len(data)

    def flush(self):
        self._live()

    def reset_input_buffer(self):
        fw = self._live()
        try:
            fw.discard_output(self._gen)
        except galvo_fw.PortUnplugged as e:
            raise self._gone(e) from e

    def reset_output_buffer(self):
        self._live()

    @property
    def cts(self):
        return True

    @property
    def dsr(self):
        return True

    @property
    def ri(self):
        return False

    @property
    def cd(self):
        return True

    # The emulated controller has no modem lines and no break detection: SerialBase calls these
    # when the host sets RTS, DTR or break, and there is nothing to drive.
    def _update_rts_state(self):
        return None

    def _update_dtr_state(self):
        return None

    def _update_break_state(self):
        return None
