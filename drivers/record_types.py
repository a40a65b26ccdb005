"""PTU record-type codes (``TTResultFormat_TTTRRecType``), apart from :mod:`drivers.events` so that
naming them (the PicoQuant driver's model list, read by ``spdepth --help``) imports no numpy."""

from __future__ import annotations

from enum import IntEnum


class RecordType(IntEnum):
    """PTU ``TTResultFormat_TTTRRecType`` codes of the T3 records we read and write (ptufile's
    ``PtuRecordType``); the one list of them (drivers, recordings and readers all use it)."""

    PICOHARP_T3 = 0x00010303
    """PicoHarp 300: ``channel:4 | dtime:12 | nsync:16``, channel 15 special."""
    HYDRAHARP_T3 = 0x00010304
    """HydraHarp v1: the Generic T3 bit layout, but each overflow record counts one."""
    HYDRAHARP2_T3 = 0x01010304
    """HydraHarp 400 with library v3 (HydraHarp V2 T3), what our tagger writes: Generic T3 layout."""
    TIMEHARP260N_T3 = 0x00010305
    """TimeHarp 260 NANO T3: Generic T3 layout."""
    TIMEHARP260P_T3 = 0x00010306
    """TimeHarp 260 PICO T3: Generic T3 layout."""
    GENERIC_T3 = 0x00010307
    """MultiHarp, PicoHarp 330, HydraHarp 500: Generic T3 records."""


GENERIC_T3_RECORD_TYPES = frozenset({RecordType.HYDRAHARP2_T3, RecordType.TIMEHARP260N_T3,
                                     RecordType.TIMEHARP260P_T3, RecordType.GENERIC_T3})
"""Record types whose 32-bit records are ``special:1 | channel:6 | dtime:15 | nsync:10`` with
overflow counts in nsync, which ``drivers.tagger.t3`` decodes (PicoQuant's file demos decode
the TimeHarp 260 and HydraHarp V2 types with the Generic T3 routine; ptufile likewise)."""
