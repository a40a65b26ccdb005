"""The time tagger as an instrument: settings in SI units, start/stop, status, reconnect.

``Tagger(transport)`` takes any object with ``control(Setup) -> bytes``, ``read_into(buffer,
timeout_s) -> int``, ``clear_halt()``, ``reopen()`` and ``close()`` (``UsbTransport`` for real and
simulated devices); ``Tagger.open("usb:VID:PID", backend=None)`` builds the USB transport.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass

from spdepth.drivers.errors import DeviceError, SettingError
from spdepth.drivers.tagger import protocol as proto
from spdepth.drivers.tagger.protocol import Binning, Gap, MarkerConfig, TaggerIdentity, TaggerStatus
from spdepth.drivers.tagger.transport import DeviceGoneError, UsbTransport

log = logging.getLogger(__name__)

DEFAULT_URL = f"usb:{proto.VENDOR_ID:04x}:{proto.PRODUCT_ID:04x}"
"""Address of the spdepth tagger (and of the simulated one)."""


@dataclass(frozen=True)
class TaggerSettings:
    """How the tagger measures; saved with every recording.

    binning:             dtime unit = base resolution * 2**binning (0..15).
    sync_divider:        the tagger counts every n-th laser sync (1, 2, 4, 8, 16).
    marker_enabled_mask: marker inputs that produce marker records (bit n-1 = input n).
    marker_rising_mask:  inputs that trigger on the rising edge (others on the falling edge).
    """

    binning: int = 3
    sync_divider: int = 1
    marker_enabled_mask: int = 0b1111
    marker_rising_mask: int = 0b1111

    def __post_init__(self):
        # Building the requests validates every field with a message naming it.
        proto.set_binning(self.binning)
        proto.set_sync_divider(self.sync_divider)
        proto.set_markers(self.marker_enabled_mask, self.marker_rising_mask)


class Tagger:
    """A TCSPC time tagger streaming Generic T3 records over USB."""

    def __init__(self, transport):
        self.transport = transport
        self.identity: TaggerIdentity = self.identify()
        self._settings: TaggerSettings | None = None
        self._running = False

    @classmethod
    def open(cls, url: str = DEFAULT_URL, backend=None, timeout_s: float = 1.0) -> "Tagger":
        """Open ``usb:VID:PID`` (hex ids) with pyusb; ``backend`` None uses libusb, a
        ``drivers.sim.tagger_usb.SimTaggerBackend`` the simulated tagger."""
        vid, pid = proto.parse_url(url)
        return cls(UsbTransport.find(vid, pid, backend=backend, timeout_s=timeout_s))

    # ---- identity and settings -----------------------------------------------------------------
    def identify(self) -> TaggerIdentity:
        """Ask the device who it is (GET_IDENTITY)."""
        return proto.decode_identity(self.transport.control(proto.get_identity()))

    def binning(self) -> Binning:
        """Current binning code and dtime unit (GET_BINNING)."""
        return proto.decode_binning(self.transport.control(proto.get_binning()))

    @property
    def resolution_s(self) -> float:
        """The dtime unit of records, seconds (read from the device)."""
        return self.binning().resolution_s

    def set_binning(self, code: int) -> Binning:
        """Set the binning code (0..15) and return what the device then reports."""
        self.transport.control(proto.set_binning(code))
        got = self.binning()
        if got.code != code:
            raise DeviceError(f"tagger kept binning {got.code} after SET_BINNING {code}")
        return got

    def sync_divider(self) -> int:
        return proto.decode_sync_divider(self.transport.control(proto.get_sync_divider()))

    def set_sync_divider(self, divider: int) -> None:
        self.transport.control(proto.set_sync_divider(divider))
        got = self.sync_divider()
        if got != divider:
            raise DeviceError(f"tagger kept sync divider {got} after SET_SYNC_DIVIDER {divider}")

    def markers(self) -> MarkerConfig:
        return proto.decode_markers(self.transport.control(proto.get_markers()))

    def set_markers(self, enabled_mask: int, rising_mask: int) -> None:
        """Enable marker inputs (bit n-1 = input n) and pick their edges (bit set = rising)."""
        self.transport.control(proto.set_markers(enabled_mask, rising_mask))
        got = self.markers()
        if got != MarkerConfig(enabled_mask, rising_mask):
            raise DeviceError(f"tagger kept markers {got} after SET_MARKERS "
                              f"{enabled_mask:#x}/{rising_mask:#x}")

    def configure(self, settings: TaggerSettings) -> None:
        """Apply all settings (while stopped); they are re-applied after a reconnect."""
        if not isinstance(settings, TaggerSettings):
            raise SettingError(f"tagger settings must be TaggerSettings, not {type(settings).__name__}")
        self.set_binning(settings.binning)
        self.set_sync_divider(settings.sync_divider)
        self.set_markers(settings.marker_enabled_mask, settings.marker_rising_mask)
        self._settings = settings

    @property
    def settings(self) -> TaggerSettings | None:
        """The settings last applied with ``configure`` (None before)."""
        return self._settings

    # ---- measuring -----------------------------------------------------------------------------
    def start(self) -> None:
        """Clear the FIFO and counters and start streaming records (sync counter restarts at 0)."""
        self.transport.control(proto.start())
        self._running = True

    def stop(self) -> None:
        self.transport.control(proto.stop())
        self._running = False

    @property
    def running(self) -> bool:
        """Whether the host started a measurement it has not stopped."""
        return self._running

    def status(self) -> TaggerStatus:
        """FIFO fill, loss counters and the pending gap (GET_STATUS)."""
        return proto.decode_status(self.transport.control(proto.get_status()))

    def ack_gap(self) -> Gap:
        """Take the pending gap (ACK_GAP): the device clears OVERRUN and releases the records it
        held back after the gap."""
        return proto.decode_gap(self.transport.control(proto.ack_gap()))

    def read_into(self, buffer, timeout_s: float) -> int:
        """Bulk-read raw record bytes into ``buffer`` (an ``array.array``); returns the byte count
        (possibly ending mid-record). Raises DeviceTimeoutError when nothing arrived."""
        return self.transport.read_into(buffer, timeout_s)

    def reader(self, **kwargs):
        """A ``TaggerReader`` on this tagger (not started); see its docstring for options."""
        from spdepth.drivers.tagger.reader import TaggerReader

        return TaggerReader(self, **kwargs)

    # ---- connection ----------------------------------------------------------------------------
    def reconnect(self, timeout_s: float = 5.0, interval_s: float = 0.02) -> None:
        """Reopen the device after it vanished: wait up to ``timeout_s`` for it to come back,
        check it is the same unit, re-apply the settings and restart a running measurement.
        Raises DeviceGoneError when it does not come back."""
        deadline = time.monotonic() + timeout_s
        while True:
            try:
                self.transport.reopen()
                break
            except DeviceGoneError:
                if time.monotonic() >= deadline:
                    raise DeviceGoneError(f"tagger did not come back within {timeout_s:g} s") from None
                time.sleep(interval_s)
        ident = self.identify()
        if ident.serial != self.identity.serial:
            raise DeviceError(f"a different tagger came back (serial {ident.serial!r}, "
                              f"expected {self.identity.serial!r})")
        log.warning("tagger %s reconnected", ident.serial)
        if self._settings is not None:
            self.configure(self._settings)
        if self._running:
            self.start()

    def close(self) -> None:
        if self._running and not self.transport.closed:
            try:
                self.stop()
            except DeviceError as exc:  # closing a vanished device must still release it
                log.debug("stop on close failed: %s", exc)
        self._running = False
        self.transport.close()

    def __enter__(self) -> "Tagger":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
