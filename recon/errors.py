"""The one error hierarchy of spdepth.

It lives in ``recon`` because ``recon`` is the bottom layer (it imports nothing from ``acq``,
``drivers`` or ``gui``) and every other package may import from it.
"""

from __future__ import annotations


class SpdError(Exception):
    """Base of every error spdepth raises on purpose; the CLI turns it into a one-line message."""


class InputError(SpdError, ValueError):
    """Raised for bad user input: a file that is missing, truncated, corrupt or of the wrong kind,
    a setting out of range, a scene name that does not exist. The message names the file, field
    and value."""


class DeviceError(SpdError):
    """Raised when an instrument reports a fault, answers with an error reply, or vanishes."""


class DeviceTimeoutError(DeviceError, TimeoutError):
    """Raised when an instrument does not answer within the transport's timeout."""


class ProtocolError(DeviceError):
    """Raised when bytes from an instrument or a recording do not decode: garbled, truncated or
    unexpected replies and records."""
