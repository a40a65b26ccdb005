"""The simulated TCSPC time tagger as a pyusb backend.

``usb.core.find(backend=SimTaggerBackend(rig), idVendor=0x1209, idProduct=0x7a64)`` finds a device
that speaks exactly the protocol of ``docs/protocols.md`` ("TCSPC time tagger"), so the driver runs
the same code path as with libusb:

    from spdepth.drivers.sim.tagger_usb import SimTaggerBackend
    from spdepth.drivers.tagger import Tagger
    backend = SimTaggerBackend(rig, faults="fifo-overflow@2s", scan_pixels=64 * 64)
    tagger = Tagger.open("usb:1209:7a64", backend=backend)

The firmware drains the rig's FIFO (``SimRig.read_events``), turns rig syncs into tagger syncs
(since START, divided by the sync divider), rig dtimes into its own resolution, filters the enabled
marker inputs, and encodes Generic T3 records with ``drivers.tagger.t3.encode_t3``. A loss in the
rig's FIFO is latched as a gap (position, sync, count) and the records after it are held back
until the host sends ACK_GAP.

Faults (``drivers.sim.faults``; WHEN in the rig's virtual seconds or a fraction of ``scan_pixels``
counted by PIXEL markers): ``usb-timeout`` (one bulk read times out with data waiting),
``partial-read`` (one bulk read ends in the middle of a record), ``fifo-overflow``
(``rig.schedule_overflow``: the rig drops ``overflow_records`` when the scan reaches WHEN),
``device-vanish`` (the device leaves the bus for
``vanish_s`` wall-clock seconds and comes back powered up afresh).
"""

from __future__ import annotations

import errno
import threading
import time
from dataclasses import dataclass

import numpy as np
import usb.backend
import usb.core

from spdepth.drivers.errors import SettingError
from spdepth.drivers.events import EVENT_DTYPE, EventKind, Marker
from spdepth.drivers.sim.faults import Fault, FaultKind, FaultSchedule, TAGGER_FAULTS, parse_faults
from spdepth.drivers.tagger import protocol as proto
from spdepth.drivers.tagger.protocol import Gap, Request, StatusFlag, TaggerIdentity, TaggerStatus
from spdepth.drivers.tagger.t3 import T3_DTIME_MAX, T3EncoderState, encode_t3

SIM_IDENTITY = TaggerIdentity(
    protocol_version=proto.PROTOCOL_VERSION,
    firmware_version=(1, 2, 0),
    n_channels=4,
    n_marker_inputs=proto.MARKER_INPUTS,
    base_resolution_s=1e-12,
    fifo_capacity_records=2 ** 21,
    serial="SIMTAG000001",
)
"""What the simulated tagger reports (the FIFO depth is replaced by the rig's)."""

DEFAULT_BINNING = 3
"""Binning after power-up: 8 ps, the seed paper's raw unit."""


def world_resolution_s(world) -> float:
    """The dtime unit (seconds) of the events a photon world produces."""
    for holder in (world, getattr(world, "scene", None), getattr(world, "settings", None)):
        value = getattr(holder, "resolution_s", None) if holder is not None else None
        if value is not None:
            return float(value)
    raise SettingError(f"photon world {type(world).__name__} does not say its dtime unit "
                     f"(resolution_s)")


# ---- descriptors -----------------------------------------------------------------------------------

@dataclass
class _DeviceDescriptor:
    bLength: int = 18
    bDescriptorType: int = 1
    bcdUSB: int = 0x0200
    bDeviceClass: int = 0xFF
    bDeviceSubClass: int = 0
    bDeviceProtocol: int = 0
    bMaxPacketSize0: int = 64
    idVendor: int = proto.VENDOR_ID
    idProduct: int = proto.PRODUCT_ID
    bcdDevice: int = 0x0120
    iManufacturer: int = 0
    iProduct: int = 0
    iSerialNumber: int = 0
    bNumConfigurations: int = 1
    address: int = 7
    bus: int = 1
    port_number: int = 2
    port_numbers: tuple = (2,)
    speed: int = 3   # usb.util.SPEED_HIGH


@dataclass
class _ConfigDescriptor:
    bLength: int = 9
    bDescriptorType: int = 2
    wTotalLength: int = 9 + 9 + 7
    bNumInterfaces: int = 1
    bConfigurationValue: int = 1
    iConfiguration: int = 0
    bmAttributes: int = 0x80
    bMaxPower: int = 250
    extra_descriptors: bytes = b""


@dataclass
class _InterfaceDescriptor:
    bLength: int = 9
    bDescriptorType: int = 4
    bInterfaceNumber: int = proto.INTERFACE
    bAlternateSetting: int = 0
    bNumEndpoints: int = 1
    bInterfaceClass: int = 0xFF
    bInterfaceSubClass: int = 0
    bInterfaceProtocol: int = 0
    iInterface: int = 0
    extra_descriptors: bytes = b""


@dataclass
class _EndpointDescriptor:
    bLength: int = 7
    bDescriptorType: int = 5
    bEndpointAddress: int = proto.BULK_IN_EP
    bmAttributes: int = 0x02   # bulk
    wMaxPacketSize: int = proto.BULK_MAX_PACKET
    bInterval: int = 0
    bRefresh: int = 0
    bSynchAddress: int = 0
    extra_descriptors: bytes = b""


def _stall(what: str) -> usb.core.USBError:
    return usb.core.USBError(f"Pipe error ({what})", -9, errno.EPIPE)


def _gone() -> usb.core.USBError:
    return usb.core.USBError("No such device (it may have been disconnected)", -4, errno.ENODEV)


# ---- firmware --------------------------------------------------------------------------------------

class TaggerFirmware:
    """State and behaviour of the simulated tagger, independent of pyusb."""

    def __init__(self, rig, identity: TaggerIdentity = SIM_IDENTITY):
        self.rig = rig
        self.identity = TaggerIdentity(**{**identity.__dict__,
                                          "fifo_capacity_records": rig.fifo_capacity_records})
        self.power_up()

    def power_up(self) -> None:
        """State after power-on or re-plug."""
        self.binning = DEFAULT_BINNING
        self.sync_divider = 1
        self.marker_enabled = (1 << proto.MARKER_INPUTS) - 1
        self.marker_rising = (1 << proto.MARKER_INPUTS) - 1
        self.running = False
        self._reset_stream()

    def _reset_stream(self) -> None:
        self._out = bytearray()            # encoded records waiting for the bulk endpoint
        self._records_out = 0              # records encoded since START (stream position)
        self._encoder = T3EncoderState()
        self._held = np.zeros(0, dtype=EVENT_DTYPE)   # rig events after a pending gap
        self._gap: Gap | None = None
        self._sync0 = self.rig.sync
        self._lost0 = self.rig.fifo_status().lost_records
        self.pixels_seen = 0

    @property
    def resolution_s(self) -> float:
        return self.identity.base_resolution_s * 2 ** self.binning

    @property
    def start_sync(self) -> int:
        """Rig sync at the last START (the tagger's sync 0)."""
        return self._sync0

    @property
    def records_out(self) -> int:
        """Records encoded since START (handed to the bulk endpoint or waiting for it)."""
        return self._records_out

    @property
    def gap_pending(self) -> bool:
        return self._gap is not None

    # ---- control requests ------------------------------------------------------------------------
    def control_in(self, request: int, value: int, index: int, length: int) -> bytes:
        if request == Request.GET_IDENTITY:
            reply = proto.encode_identity(self.identity)
        elif request == Request.GET_BINNING:
            reply = proto.encode_binning(self.binning, self.resolution_s)
        elif request == Request.GET_SYNC_DIVIDER:
            reply = proto.encode_sync_divider(self.sync_divider)
        elif request == Request.GET_MARKERS:
            reply = proto.encode_markers(proto.MarkerConfig(self.marker_enabled, self.marker_rising))
        elif request == Request.GET_STATUS:
            reply = proto.encode_status(self.status())
        elif request == Request.ACK_GAP:
            if self._gap is None:
                raise _stall("ACK_GAP without a pending gap")
            reply = proto.encode_gap(self._gap)
            self._gap = None
            self.rig.clear_fifo_flags()
            held, self._held = self._held, np.zeros(0, dtype=EVENT_DTYPE)
            self._ingest(held)
        else:
            raise _stall(f"unknown IN request {request:#04x}")
        # A real device sends at most wLength bytes; a host asking for fewer gets a short reply.
        return reply[:length]

    def control_out(self, request: int, value: int, index: int, data: bytes) -> None:
        if data:
            raise _stall(f"request {request:#04x} takes no data")
        if request == Request.SET_BINNING:
            if self.running or value > proto.MAX_BINNING:
                raise _stall(f"SET_BINNING {value}")
            self.binning = value
        elif request == Request.SET_SYNC_DIVIDER:
            if self.running or value not in proto.SYNC_DIVIDERS:
                raise _stall(f"SET_SYNC_DIVIDER {value}")
            self.sync_divider = value
        elif request == Request.SET_MARKERS:
            full = (1 << proto.MARKER_INPUTS) - 1
            if value & ~full or index & ~full:
                raise _stall(f"SET_MARKERS {value:#x}/{index:#x}")
            self.marker_enabled, self.marker_rising = value, index
        elif request == Request.START:
            self.rig.stop_tagger()
            self.rig.clear_fifo()                        # START clears the FIFO
            self.rig.clear_fifo_flags()
            self._reset_stream()
            self.running = True
            self.rig.start_tagger()
        elif request == Request.STOP:
            self.running = False
            self.rig.stop_tagger()
        else:
            raise _stall(f"unknown OUT request {request:#04x}")

    def status(self) -> TaggerStatus:
        fifo = self.rig.fifo_status()
        flags = StatusFlag(0)
        if self.running:
            flags |= StatusFlag.RUNNING
        if self._gap is not None:
            flags |= StatusFlag.OVERRUN
        if fifo.fill_records >= fifo.capacity_records:
            flags |= StatusFlag.FIFO_FULL
        gap = self._gap or Gap(0, 0, 0)
        # the fill counts what the host has not read yet: the FIFO and the records already
        # packed for the bulk endpoint
        fill = fifo.fill_records + len(self._out) // 4
        return TaggerStatus(flags, fill, fifo.lost_records - self._lost0,
                            gap.lost_records, gap.position)

    # ---- the record stream -----------------------------------------------------------------------
    def pending_bytes(self) -> int:
        return len(self._out)

    def pump(self, want_bytes: int) -> None:
        """Move events from the rig FIFO into the outgoing records until ``want_bytes`` wait or the
        FIFO is empty; nothing moves while a gap is pending."""
        while len(self._out) < want_bytes and self._gap is None:
            events = self.rig.read_events(max(1024, (want_bytes - len(self._out)) // 4))
            if events.size == 0:
                return
            self._ingest(events)

    def _ingest(self, events: np.ndarray) -> None:
        if events.size == 0:
            return
        if self._gap is not None:
            self._held = np.concatenate([self._held, events])
            return
        lost = np.flatnonzero(events["kind"] == EventKind.LOST)
        if lost.size:
            i = int(lost[0])
            self._emit(events[:i])
            self._gap = Gap(self._records_out, self._device_sync(int(events["sync"][i])),
                            int(events["dtime"][i]))
            self._held = events[i + 1:].copy()
            return
        self._emit(events)

    def _device_sync(self, rig_sync: int) -> int:
        return max(0, rig_sync - self._sync0) // self.sync_divider

    def _emit(self, events: np.ndarray) -> None:
        if events.size == 0:
            return
        ev = events.copy()
        self.pixels_seen += int(np.count_nonzero((ev["kind"] == EventKind.MARKER)
                                                 & (ev["marker"] & Marker.PIXEL != 0)))
        rel = ev["sync"].astype(np.int64) - self._sync0
        if np.any(rel < 0):
            raise RuntimeError("rig delivered an event from before the tagger's START")
        ev["sync"] = rel // self.sync_divider
        photon = ev["kind"] == EventKind.PHOTON
        # dtime: world units -> tagger units, plus the laser periods skipped by the divider.
        period_units = self.rig.world.sync_period_s / self.resolution_s
        scale = world_resolution_s(self.rig.world) / self.resolution_s
        dt = np.floor(ev["dtime"] * scale + (rel % self.sync_divider) * period_units)
        keep = ~photon | (dt <= T3_DTIME_MAX)           # the TDC range ends at 2**15 units
        ev["dtime"] = np.where(photon, np.minimum(dt, T3_DTIME_MAX), 0).astype(np.uint32)
        ev["marker"] &= np.where(photon, 0, self.marker_enabled).astype(np.uint8)
        keep &= photon | (ev["marker"] != 0)             # disabled marker inputs record nothing
        ev["channel"] = np.where(photon, ev["channel"], 0)
        ev = ev[keep]
        records = encode_t3(ev, self._encoder)
        self._out += records.tobytes()
        self._records_out += records.size

    def take(self, n_bytes: int) -> bytes:
        data = bytes(self._out[:n_bytes])
        del self._out[:n_bytes]
        return data


# ---- the pyusb backend -------------------------------------------------------------------------------

class TaggerUsbDescriptors(usb.backend.IBackend):
    """pyusb backend plumbing of one tagger-shaped USB device (ids, descriptors, handles): what
    ``usb.core.find`` and ``Device`` need. Subclasses provide the transfers and may override
    ``present`` (a device that left the bus)."""

    def __init__(self):
        self._lock = threading.RLock()
        self._handles = 0
        self.dev = _DeviceDescriptor()
        self.cfg = _ConfigDescriptor()
        self.intf = _InterfaceDescriptor()
        self.ep = _EndpointDescriptor()

    @property
    def present(self) -> bool:
        return True

    def _check_present(self) -> None:
        if not self.present:
            raise _gone()

    # ---- enumeration and descriptors ---------------------------------------------------------------
    def enumerate_devices(self):
        if self.present:
            yield self.dev

    def get_device_descriptor(self, dev):
        return self.dev

    def get_configuration_descriptor(self, dev, config):
        if config != 0:
            raise IndexError(f"configuration {config}")
        return self.cfg

    def get_interface_descriptor(self, dev, intf, alt, config):
        # pyusb walks alternate settings until IndexError: there is exactly one.
        if config != 0 or intf != 0 or alt != 0:
            raise IndexError(f"interface {intf} alt {alt}")
        return self.intf

    def get_endpoint_descriptor(self, dev, ep, intf, alt, config):
        if config != 0 or intf != 0 or alt != 0 or ep != 0:
            raise IndexError(f"endpoint {ep}")
        return self.ep

    def open_device(self, dev):
        self._check_present()
        with self._lock:
            self._handles += 1
            return self._handles

    # A simulated device holds no OS resources and no kernel driver binds to it, so closing,
    # releasing and (de)attaching have nothing to undo.
    def close_device(self, dev_handle):
        return None

    def set_configuration(self, dev_handle, config_value):
        self._check_present()
        if config_value != self.cfg.bConfigurationValue:
            raise _stall(f"configuration {config_value}")

    def get_configuration(self, dev_handle):
        self._check_present()
        return self.cfg.bConfigurationValue

    def set_interface_altsetting(self, dev_handle, intf, altsetting):
        self._check_present()
        if intf != 0 or altsetting != 0:
            raise _stall(f"interface {intf} alt {altsetting}")

    def claim_interface(self, dev_handle, intf):
        self._check_present()

    def release_interface(self, dev_handle, intf):
        return None

    def clear_halt(self, dev_handle, ep):
        self._check_present()

    def reset_device(self, dev_handle):
        self._check_present()

    def is_kernel_driver_active(self, dev_handle, intf):
        return False

    def detach_kernel_driver(self, dev_handle, intf):
        return None

    def attach_kernel_driver(self, dev_handle, intf):
        return None


class SimTaggerBackend(TaggerUsbDescriptors):
    """pyusb backend with one simulated tagger on a shared ``SimRig``.

    rig:              the shared ``drivers.sim.rig.SimRig``.
    faults:           a ``KIND@WHEN`` spec string, or a list of ``drivers.sim.faults.Fault``.
    scan_pixels:      pixels of the scan, for faults given as a fraction (``40%``).
    overflow_records: records a ``fifo-overflow`` fault loses.
    vanish_s:         wall-clock seconds a vanished device stays away.
    poll_s:           longest an idle bulk read sleeps before it looks again (it wakes at once
                      when the rig has events).
    """

    def __init__(self, rig, faults: str | list[Fault] | None = None, scan_pixels: int | None = None,
                 overflow_records: int = 1000, vanish_s: float = 0.1, poll_s: float = 0.02):
        super().__init__()
        self.rig = rig
        self.firmware = TaggerFirmware(rig)
        if isinstance(faults, str) or faults is None:
            faults = parse_faults(faults, TAGGER_FAULTS)
        if any(f.at_fraction is not None for f in faults) and not scan_pixels:
            raise SettingError("tagger faults given as a fraction of the scan need scan_pixels")
        self.scan_pixels = scan_pixels
        self.overflow_records = int(overflow_records)
        # A FIFO overflow belongs to the moment the scan reaches WHEN, not to when the host
        # happens to read that far (the galvo can run far ahead of the reader in virtual time),
        # so the rig fires it as the scan passes that point.
        for f in faults:
            if f.kind == FaultKind.FIFO_OVERFLOW:
                if f.at_fraction is not None:
                    # "50%" = once half the pixels are complete: as the next one opens
                    at_pixel = rig.pixels_pulsed + round(f.at_fraction * scan_pixels) + 1
                    rig.schedule_overflow(self.overflow_records, at_pixel=at_pixel)
                else:
                    rig.schedule_overflow(self.overflow_records, at_s=f.at_s)
        self.schedule = FaultSchedule([f for f in faults if f.kind != FaultKind.FIFO_OVERFLOW])
        self.vanish_s = float(vanish_s)
        self.poll_s = float(poll_s)
        self._gone_until: float | None = None
        self._timeouts_due = 0
        self._partials_due = 0

    # ---- presence and faults -----------------------------------------------------------------------
    @property
    def present(self) -> bool:
        with self._lock:
            if self._gone_until is not None and time.monotonic() >= self._gone_until:
                self._gone_until = None
                self.firmware.power_up()     # it comes back as after power-on
            return self._gone_until is None

    def _fire_due_faults(self) -> None:
        fraction = (self.firmware.pixels_seen / self.scan_pixels) if self.scan_pixels else None
        for fault in self.schedule.take_due(self.rig.now_s, fraction):
            if fault.kind == FaultKind.USB_TIMEOUT:
                self._timeouts_due += 1
            elif fault.kind == FaultKind.PARTIAL_READ:
                self._partials_due += 1
            elif fault.kind == FaultKind.DEVICE_VANISH:
                self.rig.stop_tagger()
                self.firmware.running = False
                self._gone_until = time.monotonic() + self.vanish_s

    # ---- transfers ---------------------------------------------------------------------------------
    def ctrl_transfer(self, dev_handle, bmRequestType, bRequest, wValue, wIndex, data, timeout):
        with self._lock:
            self._check_present()
            if bmRequestType == proto.REQUEST_TYPE_IN:
                reply = self.firmware.control_in(bRequest, wValue, wIndex, len(data))
                memoryview(data).cast("B")[:len(reply)] = reply
                return len(reply)
            if bmRequestType == proto.REQUEST_TYPE_OUT:
                payload = bytes(data)
                self.firmware.control_out(bRequest, wValue, wIndex, payload)
                return len(payload)
            raise _stall(f"bmRequestType {bmRequestType:#04x}")

    def bulk_write(self, dev_handle, ep, intf, data, timeout):
        raise _stall(f"no bulk OUT endpoint {ep:#04x}")

    def bulk_read(self, dev_handle, ep, intf, buff, timeout):
        if ep != proto.BULK_IN_EP:
            raise _stall(f"no endpoint {ep:#04x}")
        view = memoryview(buff).cast("B")
        deadline = time.monotonic() + (timeout or 1000) / 1000.0
        while True:
            with self._lock:
                self._check_present()
                self._fire_due_faults()
                self._check_present()
                fw = self.firmware
                fw.pump(len(view))
                if self._timeouts_due and fw.pending_bytes():
                    # "times out with data waiting": the records stay in the device for the
                    # next read (a due timeout waits for records to hold back)
                    self._timeouts_due -= 1
                    raise usb.core.USBTimeoutError("Operation timed out (injected)", -7,
                                                   errno.ETIMEDOUT)
                n = min(fw.pending_bytes(), len(view))
                if n and self._partials_due and n > 4:
                    self._partials_due -= 1
                    n = n // 2 if (n // 2) % 4 else n // 2 - 1     # ends mid-record
                if n:
                    view[:n] = fw.take(n)
                    return n
            left = deadline - time.monotonic()
            if left <= 0:
                raise usb.core.USBTimeoutError("Operation timed out", -7, errno.ETIMEDOUT)
            # Sleep until the rig has events; wake at least every poll_s for faults due in
            # wall-clock time (a vanished device coming back).
            self.rig.wait_for_events(min(left, self.poll_s))
