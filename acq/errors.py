"""The errors ``acq`` raises on purpose. Each front end maps them (with ``recon``'s ``InputError`` and
``drivers``' ``DeviceError``/``SettingError``) to one line and an exit status (``acq.cli``)."""

from __future__ import annotations


class AcqError(Exception):
    """Base of every error the acquisition library raises on purpose."""


class RequestError(AcqError):
    """Raised when a request (scan, replay, file reconstruction) holds a bad or conflicting value;
    the message names the field and the value. Raised before any device is opened or folder made."""


class RecordingError(AcqError):
    """Raised when a recording or data file cannot be read as one: a damaged header, a missing
    record-type tag, settings that do not parse. The message names the file and the field."""


class OutputError(AcqError):
    """Raised when an output cannot be written: a folder that is not empty (without overwrite),
    in use by another running session, not writable, or removed while a session writes into it."""


class UnreachableError(AcqError):
    """Raised when a service a command needs does not answer at its address (a Dask scheduler)
    within a short connect timeout; the message names the option, the address and the timeout.
    The CLI exits 3 for it, as for a missing device."""


class SessionStateError(AcqError):
    """Raised when a command does not fit the session's state (pause when not running, start
    twice, resume when not paused, abort after the end)."""


__all__ = ["AcqError", "RequestError", "RecordingError", "OutputError", "SessionStateError",
           "UnreachableError"]
