"""Galvo scan controller driver (serial, line protocol of docs/protocols.md).

Three layers: ``transport`` (pyserial port, lock, timeouts, TX/RX logging), ``protocol`` (pure
bytes <-> typed values), ``device`` (``Galvo``: units, limits, retries, reconnect)."""

from spdepth.drivers.lazy import lazy_attributes

_LAZY = {"Galvo": "device", "Gate": "device", "ScanPattern": "device", "SerialTransport": "transport",
         **{name: "errors" for name in ("BadArgumentError", "BusyError", "ConnectionLostError", "ErrorCode",
                                        "GalvoReplyError", "HardwareFaultError", "OutOfRangeError",
                                        "UnknownCommandError")},
         **{name: "protocol" for name in ("Calibration", "GalvoState", "GateMode", "GateSetting", "Identity",
                                          "Limits", "PatternCodes", "PixelFlag", "PixelPage", "PixelRecord",
                                          "ScanMode", "Status")}}
"""Loaded on first use: a request's limits (``acq.requests`` reads ``protocol.MAX_N_TARGET``) need
the protocol's tables alone, not the device, its serial transport and pyserial (14 ms of every
``spdepth recon``'s start, on the GIL while the kernels load)."""

__getattr__ = lazy_attributes(__name__, _LAZY)

__all__ = [
    "Galvo", "Gate", "ScanPattern", "SerialTransport", "ErrorCode", "GalvoReplyError",
    "UnknownCommandError", "BadArgumentError", "OutOfRangeError", "BusyError",
    "HardwareFaultError", "ConnectionLostError", "Calibration", "GalvoState", "GateMode",
    "GateSetting", "Identity", "Limits", "PatternCodes", "PixelFlag", "PixelPage", "PixelRecord",
    "ScanMode", "Status",
]
