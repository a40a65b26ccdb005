"""Errors of the galvo scan controller driver, inside the drivers' hierarchy (``drivers.errors``):
numbered error replies become :class:`GalvoReplyError` subclasses that keep the controller's code
and message; a vanished port becomes :class:`ConnectionLostError`."""

from __future__ import annotations

from enum import IntEnum

from spdepth.drivers.errors import DeviceError


class ErrorCode(IntEnum):
    """Numbered error replies of the controller (``ERR <code> <message>``)."""

    NO_ERROR = 0
    """Only in ``ERR?`` replies: the error queue is empty."""
    UNKNOWN_COMMAND = 1
    """The mnemonic is not a command of this controller."""
    BAD_ARGUMENT = 2
    """Wrong number of arguments, not a decimal integer, unknown keyword, or line too long."""
    OUT_OF_RANGE = 3
    """A well-formed argument outside its range or outside the soft limits."""
    BUSY = 4
    """The command is refused while a scan runs (stop it first)."""
    HARDWARE_FAULT = 5
    """The mirror servo is in FAULT; clear it with ``*CLS`` before moving or scanning."""


class GalvoReplyError(DeviceError):
    """Raised when the controller answers a command with a numbered error reply.

    ``code`` is the :class:`ErrorCode`, ``message`` the controller's text."""

    def __init__(self, code: ErrorCode, message: str, command: str = ""):
        self.code = ErrorCode(code)
        self.message = message
        self.command = command
        where = f" to {command!r}" if command else ""
        super().__init__(f"galvo error {int(code)} ({self.code.name}){where}: {message}")


class UnknownCommandError(GalvoReplyError):
    """Raised for ``ERR 1``: the controller does not know the command."""


class BadArgumentError(GalvoReplyError):
    """Raised for ``ERR 2``: malformed arguments."""


class OutOfRangeError(GalvoReplyError):
    """Raised for ``ERR 3``: an argument outside its range or the soft limits."""


class BusyError(GalvoReplyError):
    """Raised for ``ERR 4``: the command is not allowed while scanning."""


class HardwareFaultError(GalvoReplyError):
    """Raised for ``ERR 5``: the servo is in FAULT."""


_BY_CODE = {
    ErrorCode.UNKNOWN_COMMAND: UnknownCommandError,
    ErrorCode.BAD_ARGUMENT: BadArgumentError,
    ErrorCode.OUT_OF_RANGE: OutOfRangeError,
    ErrorCode.BUSY: BusyError,
    ErrorCode.HARDWARE_FAULT: HardwareFaultError,
}


def reply_error(code: ErrorCode, message: str, command: str = "") -> GalvoReplyError:
    """The exception class that matches a numbered error reply."""
    return _BY_CODE[ErrorCode(code)](code, message, command)


class ConnectionLostError(DeviceError):
    """Raised when the serial port vanishes (USB unplug, pty closed) and could not be re-opened
    within the reconnect budget, or when a transport is used after it was closed."""
