"""PicoQuant TCSPC devices (MultiHarp 150/160, HydraHarp 400) through the vendor's C library.

Three layers: ``transport`` (find and load the library with ctypes, typed calls under a lock,
error codes to errors), ``protocol`` (families, codes, settings: no I/O), ``device``
(``PicoQuantTagger``: T3 measurement, FIFO reads, reconnect; ``PicoQuantReader``: the reader
thread with in-band loss)."""

from .device import PicoQuantReader, PicoQuantTagger, list_devices
from .protocol import FAMILIES, Flag, LibError, PicoQuantSettings, family
from .transport import LibraryMissingError, LibTransport, PicoQuantError

__all__ = ["PicoQuantTagger", "PicoQuantReader", "PicoQuantSettings", "LibTransport",
           "LibraryMissingError", "PicoQuantError", "FAMILIES", "Flag", "LibError", "family",
           "list_devices"]
