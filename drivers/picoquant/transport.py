"""The PicoQuant library as a transport: find and load it with ctypes, declare the argument types
of every function we call (so a wrong pointer or integer fails in ctypes, not in the device), call
it under one lock, turn return codes into errors with the library's own text, and log the calls.

Where the library is looked for, first hit wins:

1. the path given (``lib_path``, or the ``SPDEPTH_PICOQUANT_LIB`` environment variable);
2. the ``snapi`` package (PicoQuant's Python package ships the Linux libraries, licensed to device
   owners);
3. the places PicoQuant's installers use (``/usr/local/lib64/<lib>``, ``/opt/picoquant``), then the
   system's library path (``LD_LIBRARY_PATH``, ``ldconfig``).
"""

from __future__ import annotations

import ctypes as ct
import ctypes.util
import importlib.util
import logging
import os
import threading
from pathlib import Path

from spdepth.drivers.errors import DeviceError
from spdepth.drivers.picoquant.protocol import DEVICE_GONE_ERRORS, Family, LibError

log = logging.getLogger("spdepth.picoquant")

LIB_ENV = "SPDEPTH_PICOQUANT_LIB"
"""Environment variable naming the library file (overrides the search)."""
INSTALL_DIRS = ("/usr/local/lib64", "/usr/local/lib", "/usr/lib64", "/usr/lib", "/opt/picoquant")

_I, _PI, _PC, _PD, _PU = ct.c_int, ct.POINTER(ct.c_int), ct.c_char_p, ct.POINTER(ct.c_double), \
    ct.POINTER(ct.c_uint)

# name (without prefix) -> argument types; every function returns int (0 or a negative LibError)
SIGNATURES: dict[str, tuple] = {
    "GetLibraryVersion": (_PC,),
    "GetErrorString": (_PC, _I),
    "OpenDevice": (_I, _PC),
    "CloseDevice": (_I,),
    "Initialize": (_I, _I, _I),
    "GetHardwareInfo": (_I, _PC, _PC, _PC),
    "GetSerialNumber": (_I, _PC),
    "GetFeatures": (_I, _PI),
    "GetBaseResolution": (_I, _PD, _PI),
    "GetNumOfInputChannels": (_I, _PI),
    "SetSyncDiv": (_I, _I),
    "SetSyncTrgMode": (_I, _I),              # PicoHarp 330 only: ETR or CFD, per input
    "SetInputTrgMode": (_I, _I, _I),
    "SetSyncEdgeTrg": (_I, _I, _I),          # MultiHarp (HydraHarp 400: SetSyncCFD)
    "SetSyncCFD": (_I, _I, _I),
    "SetSyncChannelOffset": (_I, _I),
    "SetInputEdgeTrg": (_I, _I, _I, _I),
    "SetInputCFD": (_I, _I, _I, _I),
    "SetInputChannelOffset": (_I, _I, _I),
    "SetBinning": (_I, _I),
    "SetOffset": (_I, _I),
    "GetResolution": (_I, _PD),
    "GetSyncRate": (_I, _PI),
    "GetCountRate": (_I, _I, _PI),
    "GetFlags": (_I, _PI),
    "SetMarkerEdges": (_I, _I, _I, _I, _I),
    "SetMarkerEnable": (_I, _I, _I, _I, _I),
    "StartMeas": (_I, _I),
    "StopMeas": (_I,),
    "CTCStatus": (_I, _PI),
    "ReadFiFo": (_I, _PU, _PI),              # MultiHarp; HydraHarp 400 adds a count (below)
}
READFIFO_WITH_COUNT = (_I, _PU, _I, _PI)
INITIALIZE_NO_REFSOURCE = (_I, _I)
"""``TH260_Initialize(devidx, mode)``: the TimeHarp 260 has no reference clock input."""


def signature(fam: Family, name: str) -> tuple:
    """Argument types of ``<prefix>_<name>`` in the library of ``fam``."""
    if name == "ReadFiFo" and fam.readfifo_count:
        return READFIFO_WITH_COUNT
    if name == "Initialize" and not fam.init_refsource:
        return INITIALIZE_NO_REFSOURCE
    return SIGNATURES[name]


class LibraryMissingError(DeviceError):
    """Raised when the vendor library for a device family is not found or does not load; the
    message names the library and how to install it."""


class PicoQuantError(DeviceError):
    """Raised when a library call returns an error code; ``code`` is the code, the message holds
    the library's own error string."""

    def __init__(self, code: int, message: str):
        self.code = int(code)
        super().__init__(message)

    @property
    def device_gone(self) -> bool:
        return self.code in DEVICE_GONE_ERRORS


def install_hint(fam: Family) -> str:
    return (f"install PicoQuant's {fam.model} software (it ships {fam.libraries[0]}), or "
            f"`pip install snapi` if you own a PicoQuant device, or set {LIB_ENV}=/path/to/"
            f"{fam.libraries[0]}")


def candidate_paths(fam: Family, lib_path: str | os.PathLike | None = None) -> list[Path]:
    """Where the library of ``fam`` may be, in search order (existing files only, except a path
    given explicitly, which is returned even when missing so the error can name it)."""
    given = lib_path or os.environ.get(LIB_ENV)
    if given:
        return [Path(given)]
    out: list[Path] = []
    try:
        spec = importlib.util.find_spec("snapi")
    except (ImportError, ValueError):
        spec = None
    if spec is not None and spec.submodule_search_locations:
        for d in spec.submodule_search_locations:
            for name in dict.fromkeys((fam.snapi_name or fam.libraries[0], *fam.libraries)):
                out += sorted(Path(d).rglob(name))
    for d in INSTALL_DIRS:
        for name in fam.libraries:
            p = Path(d) / name
            if p.is_file():
                out.append(p)
            out += sorted(Path(d).glob(f"*/{name}")) if Path(d).is_dir() else []
    found = ctypes.util.find_library(fam.libraries[0].removeprefix("lib").removesuffix(".so"))
    if found:
        out.append(Path(found))
    return out


def load_library(fam: Family, lib_path: str | os.PathLike | None = None):
    """The loaded ``ctypes.CDLL`` of ``fam`` and its path; LibraryMissingError otherwise."""
    paths = candidate_paths(fam, lib_path)
    if not paths:
        raise LibraryMissingError(f"PicoQuant library {fam.libraries[0]} not found: "
                                  f"{install_hint(fam)}")
    errors = []
    for p in paths:
        try:
            return ct.CDLL(str(p)), p
        except OSError as exc:
            errors.append(f"{p}: {exc}")
    raise LibraryMissingError(f"PicoQuant library {fam.libraries[0]} does not load "
                              f"({'; '.join(errors)}): {install_hint(fam)}")


class LibTransport:
    """One loaded PicoQuant library (``lib``: a ``ctypes.CDLL`` or a path) for a family; ``call``
    runs ``<prefix>_<name>`` under a lock and raises :class:`PicoQuantError` on a negative code."""

    def __init__(self, fam: Family, lib=None, *, lib_path=None):
        self.family = fam
        if lib is None:
            lib, lib_path = load_library(fam, lib_path)
        elif isinstance(lib, (str, os.PathLike)):
            lib, lib_path = load_library(fam, lib)
        self.lib = lib
        self.path = Path(lib_path) if lib_path else None
        self._lock = threading.RLock()
        self._funcs: dict[str, object] = {}

    def _func(self, name: str):
        f = self._funcs.get(name)
        if f is None:
            full = f"{self.family.prefix}_{name}"
            try:
                f = getattr(self.lib, full)
            except AttributeError:
                raise LibraryMissingError(f"PicoQuant library {self.path or self.lib} has no "
                                          f"{full}: is it the {self.family.model} library?") from None
            f.argtypes = list(signature(self.family, name))
            f.restype = ct.c_int
            self._funcs[name] = f
        return f

    def call(self, name: str, *args, quiet: bool = False) -> int:
        """Call ``<prefix>_<name>(*args)``; returns the (non-negative) code."""
        f = self._func(name)
        with self._lock:
            rc = f(*args)
        if not quiet:
            log.debug("%s_%s%s -> %d", self.family.prefix, name, args[:1], rc)
        if rc < 0:
            raise PicoQuantError(rc, f"{self.family.prefix}_{name}: {self.error_string(rc)}")
        return rc

    def error_string(self, code: int) -> str:
        """The library's text for ``code`` (with our name for it when we know it)."""
        buf = ct.create_string_buffer(64)
        try:
            self._func("GetErrorString")(buf, int(code))
            text = buf.value.decode("ascii", "replace").strip()
        except Exception:  # noqa: BLE001 - the code is still worth reporting
            text = ""
        try:
            name = LibError(code).name
        except ValueError:
            name = str(code)
        return f"{text or 'error'} ({name})"

    def library_version(self) -> str:
        buf = ct.create_string_buffer(16)
        self.call("GetLibraryVersion", buf)
        return buf.value.decode("ascii", "replace")


__all__ = ["LibTransport", "LibraryMissingError", "PicoQuantError", "load_library",
           "candidate_paths", "install_hint", "LIB_ENV", "SIGNATURES", "signature"]
