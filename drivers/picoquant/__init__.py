"""PicoQuant TCSPC devices (MultiHarp 150/160, HydraHarp 400) through the vendor's C library.

Three layers: ``transport`` (find and load the library with ctypes, typed calls under a lock,
error codes to errors), ``protocol`` (families, codes, settings: no I/O), ``device``
(``PicoQuantTagger``: T3 measurement, FIFO reads, reconnect; ``PicoQuantReader``: the reader
thread with in-band loss)."""

from spdepth.drivers.lazy import lazy_attributes

from .protocol import FAMILIES, Flag, LibError, PicoQuantSettings, family

_LAZY = {"PicoQuantReader": "device", "PicoQuantTagger": "device", "list_devices": "device",
         "LibraryMissingError": "transport", "LibTransport": "transport", "PicoQuantError": "transport"}
"""Loaded on first use: the device decodes with numba, which the protocol's tables (the tagger
models ``--help`` lists) do not need."""

__getattr__ = lazy_attributes(__name__, _LAZY)

__all__ = ["PicoQuantTagger", "PicoQuantReader", "PicoQuantSettings", "LibTransport",
           "LibraryMissingError", "PicoQuantError", "FAMILIES", "Flag", "LibError", "family",
           "list_devices"]
