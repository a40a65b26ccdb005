"""What instruments this computer can reach: our serial ports and USB tagger, PicoQuant devices
through their libraries, Swabian taggers, NI devices; and which vendor libraries are missing.
Nothing is opened that another program could be using, except PicoQuant devices, whose library
can only read a serial number by opening (and closing) the device.

:func:`find_instruments` returns one :class:`Found` per instrument and one per missing library;
``spdepth devices`` prints them. Every probe is injectable so tests run without hardware."""

from __future__ import annotations

import importlib
import logging
from dataclasses import asdict, dataclass

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Found:
    """One line of ``spdepth devices``.

    kind:    "serial", "usb", "picoquant", "swabian", "nidaq".
    device:  the device string to scan with (``picoquant:mh150:1000042``, ``nidaq:Dev1``), or ""
             for a line about a missing library.
    what:    what it is, in words.
    install: for a missing library: how to install it ("" when found).
    """

    kind: str
    device: str
    what: str
    install: str = ""

    @property
    def missing(self) -> bool:
        return bool(self.install)

    def line(self) -> str:
        if self.missing:
            return f"{self.kind:9s} not installed: {self.what}; {self.install}"
        return f"{self.kind:9s} {self.device:32s} {self.what}"

    def to_dict(self) -> dict:
        return {**asdict(self), "missing": self.missing}


def _serial_ports() -> list[Found]:
    try:
        from serial.tools import list_ports
    except ImportError:
        return [Found("serial", "", "pyserial's port list", "`pip install pyserial`")]
    out = []
    for p in sorted(list_ports.comports(), key=lambda p: p.device):
        desc = p.description if p.description and p.description != "n/a" else "serial port"
        out.append(Found("serial", p.device, f"{desc} (our galvo controller if one is attached)"))
    return out


def _our_usb(backend=None) -> list[Found]:
    import usb.core

    from spdepth.drivers.tagger.protocol import PRODUCT_ID, VENDOR_ID

    try:
        devs = list(usb.core.find(find_all=True, idVendor=VENDOR_ID, idProduct=PRODUCT_ID,
                                  backend=backend))
    except usb.core.NoBackendError:
        return [Found("usb", "", "libusb (pyusb's backend, for our tagger)",
                      "install libusb-1.0 (e.g. `apt install libusb-1.0-0`)")]
    except usb.core.USBError as exc:
        log.warning("USB scan failed: %s", exc)
        return []
    return [Found("usb", f"usb:{VENDOR_ID:04x}:{PRODUCT_ID:04x}",
                  f"spdepth time tagger (bus {d.bus}, address {d.address})") for d in devs]


def _picoquant(libs: dict | None = None) -> list[Found]:
    """libs: family key -> a loaded library or its path (tests); None searches as the driver does."""
    from spdepth.drivers.picoquant import FAMILIES, LibraryMissingError, LibTransport, list_devices
    from spdepth.drivers.picoquant.transport import install_hint

    out, seen = [], set()
    for key, fam in FAMILIES.items():
        if fam.libraries[0] in seen:
            continue             # MultiHarp 150 and 160 share one library
        seen.add(fam.libraries[0])
        try:
            t = LibTransport(fam, None if libs is None else libs.get(key))
        except LibraryMissingError:
            out.append(Found("picoquant", "", f"PicoQuant {fam.libraries[0]} ({fam.model})",
                             install_hint(fam)))
            continue
        except TypeError:
            continue
        try:
            devices = list_devices(t)
        except LibraryMissingError as exc:      # a library of another family given by path
            out.append(Found("picoquant", "", f"PicoQuant {fam.libraries[0]} ({exc})",
                             install_hint(fam)))
            continue
        for d in devices:
            out.append(Found("picoquant", f"picoquant:{key}:{d['serial']}",
                             f"{fam.model} serial {d['serial']} (library {t.path})"))
    return out


def _swabian(module=None) -> list[Found]:
    hint = "`pip install Swabian-TimeTagger` (and Swabian's USB driver)"
    try:
        tt = module or importlib.import_module("Swabian.TimeTagger")
    except ImportError:
        return [Found("swabian", "", "Swabian Time Tagger software", hint)]
    try:
        serials = list(tt.scanTimeTagger())
    except Exception as exc:  # noqa: BLE001 - the package raises its own errors without its driver
        return [Found("swabian", "", f"Swabian Time Tagger driver ({exc})", hint)]
    return [Found("swabian", f"swabian:{s}", f"Swabian Time Tagger serial {s}")
            for s in serials]


def _nidaq(module=None) -> list[Found]:
    from spdepth.drivers.daq.transport import INSTALL_HINT

    try:
        m = module or importlib.import_module("nidaqmx")
    except ImportError:
        return [Found("nidaq", "", "NI-DAQmx Python package (nidaqmx)", INSTALL_HINT)]
    try:
        devs = list(m.system.System.local().devices)
    except Exception as exc:  # noqa: BLE001 - DaqNotFoundError when NI's driver is missing
        return [Found("nidaq", "", f"NI-DAQmx driver ({exc})", INSTALL_HINT)]
    return [Found("nidaq", f"nidaq:{d.name}", f"{d.product_type} serial {int(d.serial_num):X}")
            for d in devs]


def find_instruments(*, usb_backend=None, picoquant_libs: dict | None = None, swabian=None,
                     nidaqmx=None, serial: bool = True) -> list[Found]:
    """Every instrument found and every vendor library missing, in a fixed order (serial, usb,
    picoquant, swabian, nidaq). The keyword arguments replace the probes' libraries (tests)."""
    out: list[Found] = []
    if serial:
        out += _serial_ports()
    out += _our_usb(usb_backend)
    out += _picoquant(picoquant_libs)
    out += _swabian(swabian)
    out += _nidaq(nidaqmx)
    return out


__all__ = ["Found", "find_instruments"]
