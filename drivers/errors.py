"""The errors of the ``drivers`` room: instruments, their wire protocols and the simulated devices.

``drivers`` sits at the bottom of the data flow next to ``recon`` and imports from neither ``recon``
nor ``acq``; code above it (``acq``, the CLI) catches these. ``recon`` keeps its own
:class:`recon.errors.InputError`.
"""

from __future__ import annotations


class DriverError(Exception):
    """Base of every error the drivers and simulated devices raise on purpose; the CLI turns it
    into a one-line message."""


class SettingError(DriverError, ValueError):
    """Raised for a bad argument to a driver or a simulated device, before anything is sent: a
    value outside its range or the soft limits, a malformed device address or ``galvosim://``
    option, an unknown scene, effect or fault spec, a scene file that cannot be read, events a T3
    stream cannot carry. The message names the setting (or file) and the value.

    Not a :class:`DeviceError`: the instrument is fine, the caller asked for something it cannot
    do, so code that reconnects or re-acquires on device faults must not catch it."""


class DeviceError(DriverError):
    """Raised when an instrument reports a fault, answers with an error reply, or vanishes."""


class DeviceTimeoutError(DeviceError, TimeoutError):
    """Raised when an instrument does not answer within the transport's timeout."""


class ProtocolError(DeviceError):
    """Raised when bytes from an instrument or a recording do not decode: garbled, truncated or
    unexpected replies and records."""
