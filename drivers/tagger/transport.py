"""USB transport of the time tagger: one pyusb device, endpoint 0 for control requests and the bulk
IN endpoint for records. Locks, timeouts, error mapping and TX/RX logging live here and nowhere
else; the protocol module says what the bytes mean."""

from __future__ import annotations

import array
import errno
import logging
import threading

import usb.core
import usb.util

from spdepth.drivers.errors import DeviceError, DeviceTimeoutError, ProtocolError
from spdepth.drivers.tagger import protocol as proto

log = logging.getLogger(__name__)

_LIBUSB_ERROR_NO_DEVICE = -4
_LIBUSB_ERROR_PIPE = -9


class DeviceGoneError(DeviceError):
    """Raised when the tagger vanished from the bus (unplugged, reset, powered off)."""


class EndpointStallError(DeviceError):
    """Raised when the device stalls an endpoint (pipe error): a refused control request, or a
    bulk transfer that failed; the transfer's data is gone."""


def _map_usb_error(exc: usb.core.USBError, what: str) -> DeviceError:
    if isinstance(exc, usb.core.USBTimeoutError):
        return DeviceTimeoutError(f"tagger {what}: timed out ({exc})")
    if exc.errno == errno.ENODEV or exc.backend_error_code == _LIBUSB_ERROR_NO_DEVICE:
        return DeviceGoneError(f"tagger {what}: device vanished ({exc})")
    if exc.errno == errno.EPIPE or exc.backend_error_code == _LIBUSB_ERROR_PIPE:
        return EndpointStallError(f"tagger {what}: endpoint stalled ({exc})")
    return DeviceError(f"tagger {what}: USB error ({exc})")


class UsbTransport:
    """A claimed pyusb device with the tagger's endpoints.

    device:    a ``usb.core.Device`` (configured here).
    timeout_s: control transfer timeout.
    backend:   the pyusb backend the device was found with; ``reopen`` searches it again.
    """

    def __init__(self, device: usb.core.Device, timeout_s: float = 1.0, backend=None):
        self.timeout_s = float(timeout_s)
        self.vid = device.idVendor
        self.pid = device.idProduct
        self.backend = backend
        # Control and bulk transfers may run concurrently on USB (reader thread + owner), so each
        # kind has its own lock; reopen takes both.
        self._ctrl_lock = threading.RLock()
        self._bulk_lock = threading.RLock()
        self._device = None
        self._attach(device)

    @classmethod
    def find(cls, vid: int, pid: int, backend=None, timeout_s: float = 1.0) -> "UsbTransport":
        """Open the first device with these ids. Raises DeviceGoneError when none is attached."""
        device = cls._find_device(vid, pid, backend)
        return cls(device, timeout_s=timeout_s, backend=backend)

    @staticmethod
    def _find_device(vid: int, pid: int, backend) -> usb.core.Device:
        try:
            device = usb.core.find(idVendor=vid, idProduct=pid, backend=backend)
        except usb.core.NoBackendError as exc:
            raise DeviceError(f"no USB backend (libusb) available: {exc}") from exc
        if device is None:
            raise DeviceGoneError(f"no tagger with USB id {vid:04x}:{pid:04x} attached")
        return device

    def _attach(self, device: usb.core.Device) -> None:
        try:
            device.set_configuration()
            usb.util.claim_interface(device, proto.INTERFACE)
            cfg = device.get_active_configuration()
            intf = cfg[(proto.INTERFACE, 0)]
            ep = usb.util.find_descriptor(intf, bEndpointAddress=proto.BULK_IN_EP)
        except usb.core.USBError as exc:
            raise _map_usb_error(exc, "configure") from exc
        if ep is None:
            raise ProtocolError(f"tagger {self.vid:04x}:{self.pid:04x} has no bulk IN endpoint "
                                f"{proto.BULK_IN_EP:#04x}")
        self._device = device
        self._ep = ep
        log.info("tagger %04x:%04x opened (bus %s address %s)", self.vid, self.pid,
                 device.bus, device.address)

    def control(self, setup: proto.Setup) -> bytes:
        """Run one control transfer; returns the IN data (b"" for OUT requests)."""
        timeout_ms = max(1, int(self.timeout_s * 1000))
        is_in = bool(setup.bmRequestType & 0x80)
        name = proto.Request(setup.bRequest).name if setup.bRequest in proto.Request._value2member_map_ else hex(setup.bRequest)
        with self._ctrl_lock:
            if self._device is None:
                raise DeviceGoneError("tagger transport is closed")
            log.debug("TX %s wValue=%#06x wIndex=%#06x %s", name, setup.wValue, setup.wIndex,
                      f"wLength={setup.wLength}" if is_in else setup.data.hex())
            try:
                if is_in:
                    reply = self._device.ctrl_transfer(setup.bmRequestType, setup.bRequest,
                                                       setup.wValue, setup.wIndex, setup.wLength,
                                                       timeout_ms)
                    data = bytes(reply)
                else:
                    n = self._device.ctrl_transfer(setup.bmRequestType, setup.bRequest,
                                                   setup.wValue, setup.wIndex,
                                                   setup.data or None, timeout_ms)
                    if n != len(setup.data):
                        raise ProtocolError(f"tagger {name}: device took {n} of "
                                            f"{len(setup.data)} bytes")
                    data = b""
            except usb.core.USBError as exc:
                err = _map_usb_error(exc, name)
                log.debug("RX %s error: %s", name, err)
                raise err from exc
            if is_in:
                log.debug("RX %s %s", name, data.hex())
            return data

    def read_into(self, buffer: array.array, timeout_s: float) -> int:
        """One bulk IN transfer into ``buffer`` (an ``array.array``, filled from its start without
        allocating). Returns the byte count, which may end mid-record (libusb delivers what arrived
        before the timeout). Raises DeviceTimeoutError when nothing arrived in ``timeout_s``."""
        timeout_ms = max(1, int(timeout_s * 1000))
        with self._bulk_lock:
            if self._device is None:
                raise DeviceGoneError("tagger transport is closed")
            try:
                return self._device.read(self._ep.bEndpointAddress, buffer, timeout_ms)
            except usb.core.USBError as exc:
                err = _map_usb_error(exc, "bulk read")
                if not isinstance(err, DeviceTimeoutError):
                    log.warning("bulk read failed: %s", err)
                raise err from exc

    def clear_halt(self) -> None:
        """Clear a stall of the bulk endpoint after a pipe error."""
        with self._bulk_lock:
            try:
                self._device.clear_halt(self._ep.bEndpointAddress)
            except usb.core.USBError as exc:
                raise _map_usb_error(exc, "clear halt") from exc

    def reopen(self) -> None:
        """Find the device again (after it vanished and came back) and claim it. Raises
        DeviceGoneError while it is still absent."""
        with self._ctrl_lock, self._bulk_lock:
            self._release()
            self._attach(self._find_device(self.vid, self.pid, self.backend))

    def _release(self) -> None:
        device, self._device = self._device, None
        if device is None:
            return
        try:
            usb.util.dispose_resources(device)
        except usb.core.USBError as exc:  # a vanished device cannot be released cleanly
            log.debug("dispose after loss: %s", exc)

    def close(self) -> None:
        with self._ctrl_lock, self._bulk_lock:
            self._release()

    @property
    def closed(self) -> bool:
        return self._device is None
