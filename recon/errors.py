"""The errors of the ``recon`` room (math only). Device and protocol errors belong to the drivers
(``drivers.errors``); ``recon`` imports nothing from the other rooms, and ``acq`` (above both)
raises :class:`InputError` for bad files and settings too.
"""

from __future__ import annotations


class InputError(ValueError):
    """Raised for bad user input: a file that is missing, truncated, corrupt or of the wrong kind,
    a reconstruction or scan setting out of range. The message names the file, field and value."""
