"""Serial transport for the galvo controller: one pyserial port (real tty, pty or URL handler),
one lock, line reads with a deadline, and all TX/RX logging in one place.

pyserial errors never leave this module: a vanished port becomes ConnectionLostError, a missing
line DeviceTimeoutError, an over-long line ProtocolError.
"""

from __future__ import annotations

import logging
import threading
import time

import serial

from spdepth.drivers.errors import DeviceTimeoutError, ProtocolError, SettingError

from .errors import ConnectionLostError
from .protocol import MAX_REPLY_BYTES, TERMINATOR

log = logging.getLogger("spdepth.galvo.transport")

WRITE_TIMEOUT_S = 2.0
"""A command line is a few bytes: a write blocked this long means the port is dead. Not the
reply timeout: pyserial reports a write timeout whenever its deadline passed by the end of the
write, so a host stalled for a moment (a loaded machine) would look like a lost port."""

try:
    import termios
    # pyserial lets termios.error (not an OSError) through from flush() on a hung-up tty.
    _PORT_ERRORS: tuple = (serial.SerialException, OSError, termios.error)
except ImportError:   # Windows
    _PORT_ERRORS = (serial.SerialException, OSError)


class SerialTransport:
    """Lines over a pyserial port.

    url_or_port: a device path (``/dev/ttyUSB0``, a pty slave) or any pyserial URL
                 (``galvosim://bench``, ``socket://host:port``, ``loop://``).
    timeout_s:   how long ``read_line`` waits for a complete line.
    port:        an already open pyserial object to use instead (then ``reopen`` re-opens it).
    """

    def __init__(self, url_or_port: str | None = None, *, timeout_s: float = 0.5,
                 baudrate: int = 115200, port: serial.SerialBase | None = None):
        if (url_or_port is None) == (port is None):
            raise ValueError("give exactly one of url_or_port, port")
        self.url = url_or_port if port is None else port.port
        self.timeout_s = float(timeout_s)
        self.baudrate = int(baudrate)
        self.lock = threading.RLock()
        """Held by the device layer around each command/reply exchange."""
        self._rx = bytearray()
        self._port = port
        if self._port is None:
            self._open()

    def _open(self) -> None:
        try:
            # Short port timeout: read_line loops to its own deadline, so a slow trickle of bytes
            # cannot stretch one read past timeout_s.
            self._port = serial.serial_for_url(self.url, baudrate=self.baudrate, timeout=0.02,
                                               write_timeout=max(self.timeout_s, WRITE_TIMEOUT_S))
        except _PORT_ERRORS as e:
            raise ConnectionLostError(f"galvo port {self.url}: cannot open: {e}") from e
        except ValueError as e:
            # pyserial's word for a URL scheme it has no handler for (e.g. galvosim:// before
            # drivers.sim is imported) or a bad port setting: the caller's input, not the device
            raise SettingError(f"galvo port {self.url}: {e}") from None
        self._rx.clear()
        log.debug("open %s", self.url)

    @property
    def is_open(self) -> bool:
        return self._port is not None and self._port.is_open

    def reopen(self) -> None:
        """Close (ignoring errors of a dead port) and open again; ConnectionLostError if the port
        is still gone."""
        with self.lock:
            self._close_quietly()
            self._open()

    def close(self) -> None:
        with self.lock:
            self._close_quietly()
            self._port = None

    def _close_quietly(self) -> None:
        if self._port is not None:
            try:
                self._port.close()
            except _PORT_ERRORS as e:
                log.debug("close %s: %s", self.url, e)
        self._rx.clear()

    def write_line(self, line: bytes) -> None:
        """Send one complete line (terminator included)."""
        if self._port is None:
            raise ConnectionLostError(f"galvo port {self.url} is closed")
        log.debug("TX %s %r", self.url, line)
        try:
            self._port.write(line)
            self._port.flush()
        except _PORT_ERRORS as e:
            raise ConnectionLostError(f"galvo port {self.url}: write failed: {e}") from e

    def read_line(self, timeout_s: float | None = None) -> bytes:
        """The next complete line (terminator included).

        Raises DeviceTimeoutError when no full line arrives within ``timeout_s`` (default: the
        transport's), ConnectionLostError when the port vanishes, ProtocolError for a line longer
        than any reply can be (the excess is dropped up to the next terminator)."""
        if self._port is None:
            raise ConnectionLostError(f"galvo port {self.url} is closed")
        deadline = time.monotonic() + (self.timeout_s if timeout_s is None else timeout_s)
        while True:
            i = self._rx.find(TERMINATOR)
            if i >= 0:
                line = bytes(self._rx[:i + 1])
                del self._rx[:i + 1]
                log.debug("RX %s %r", self.url, line)
                if len(line) > MAX_REPLY_BYTES:
                    raise ProtocolError(f"galvo port {self.url}: line of {len(line)} bytes")
                return line
            if len(self._rx) > MAX_REPLY_BYTES:
                self._rx.clear()
                raise ProtocolError(f"galvo port {self.url}: more than {MAX_REPLY_BYTES} bytes "
                                    f"without a line terminator")
            if time.monotonic() >= deadline:
                log.debug("RX %s timeout, partial %r", self.url, bytes(self._rx))
                raise DeviceTimeoutError(f"galvo port {self.url}: no reply within "
                                         f"{self.timeout_s if timeout_s is None else timeout_s:g} s")
            try:
                chunk = self._port.read(max(1, self._port.in_waiting))
            except _PORT_ERRORS as e:
                raise ConnectionLostError(f"galvo port {self.url}: read failed: {e}") from e
            if chunk:
                self._rx += chunk

    def reset_input(self) -> None:
        """Drop everything received but not read (before re-sending after a bad reply)."""
        if self._port is None:
            raise ConnectionLostError(f"galvo port {self.url} is closed")
        if self._rx:
            log.debug("RX %s dropped %r", self.url, bytes(self._rx))
        self._rx.clear()
        try:
            self._port.reset_input_buffer()
        except _PORT_ERRORS as e:
            raise ConnectionLostError(f"galvo port {self.url}: {e}") from e

    def __repr__(self) -> str:
        return f"SerialTransport({self.url!r}, timeout_s={self.timeout_s:g})"
