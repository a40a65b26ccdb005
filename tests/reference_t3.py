"""Plain-Python reference for the Generic T3 record decoder (``drivers.tagger.t3.decode_t3``),
written record by record straight from the PicoQuant layout so it shares no code with the kernel."""

from __future__ import annotations

import numpy as np

from spdepth.drivers.errors import ProtocolError
from spdepth.drivers.events import EVENT_DTYPE, EventKind


def reference_decode_t3(records: np.ndarray, sync_base: int = 0) -> tuple[np.ndarray, int]:
    """Decode uint32 records; returns (EVENT_DTYPE events, sync_base after the last record).
    Raises ProtocolError at the first record that is not a photon, marker or overflow."""
    rows = []
    for i, r in enumerate(np.asarray(records, dtype=np.uint32).tolist()):
        special = r >> 31                 # 1 bit
        channel = (r >> 25) & 0b111111    # 6 bits
        dtime = (r >> 10) & 0x7FFF        # 15 bits
        nsync = r & 0x3FF                 # 10 bits
        if special == 0:
            rows.append((sync_base + nsync, dtime, channel, EventKind.PHOTON, 0, 0))
        elif channel == 63:
            sync_base += 1024 * max(nsync, 1)
        elif 1 <= channel <= 15:
            rows.append((sync_base + nsync, 0, 0, EventKind.MARKER, channel, 0))
        else:
            raise ProtocolError(f"record {i}: special channel {channel}")
    return np.array(rows, dtype=EVENT_DTYPE), sync_base
