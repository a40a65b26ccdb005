"""Galvo scan controller driver (serial, line protocol of docs/protocols.md).

Three layers: ``transport`` (pyserial port, lock, timeouts, TX/RX logging), ``protocol`` (pure
bytes <-> typed values), ``device`` (``Galvo``: units, limits, retries, reconnect)."""

from .device import Galvo, Gate, ScanPattern
from .errors import (BadArgumentError, BusyError, ConnectionLostError, ErrorCode,
                     GalvoReplyError, HardwareFaultError, OutOfRangeError, UnknownCommandError)
from .protocol import (Calibration, GalvoState, GateMode, GateSetting, Identity, Limits,
                       PatternCodes, PixelFlag, PixelPage, PixelRecord, ScanMode, Status)
from .transport import SerialTransport

__all__ = [
    "Galvo", "Gate", "ScanPattern", "SerialTransport", "ErrorCode", "GalvoReplyError",
    "UnknownCommandError", "BadArgumentError", "OutOfRangeError", "BusyError",
    "HardwareFaultError", "ConnectionLostError", "Calibration", "GalvoState", "GateMode",
    "GateSetting", "Identity", "Limits", "PatternCodes", "PixelFlag", "PixelPage", "PixelRecord",
    "ScanMode", "Status",
]
