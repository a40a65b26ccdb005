"""PicoQuant TCSPC devices (MultiHarp 150/160, HydraHarp 400) through the vendor's C library.

Three layers: ``transport`` (find and load the library with ctypes, typed calls under a lock,
error codes to errors), ``protocol`` (families, codes, settings: no I/O), ``device``
(``PicoQuantTagger``: T3 measurement, FIFO reads, reconnect; ``PicoQuantReader``: the reader
thread with in-band loss)."""

import importlib

from .protocol import FAMILIES, Flag, LibError, PicoQuantSettings, family

_LAZY = {"PicoQuantReader": "device", "PicoQuantTagger": "device", "list_devices": "device",
         "LibraryMissingError": "transport", "LibTransport": "transport", "PicoQuantError": "transport"}
"""Loaded on first use: the device decodes with numba, which the protocol's tables (the tagger
models ``--help`` lists) do not need."""


def __getattr__(name: str):
    if name in _LAZY:
        value = getattr(importlib.import_module(f"{__name__}.{_LAZY[name]}"), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")

__all__ = ["PicoQuantTagger", "PicoQuantReader", "PicoQuantSettings", "LibTransport",
           "LibraryMissingError", "PicoQuantError", "FAMILIES", "Flag", "LibError", "family",
           "list_devices"]
