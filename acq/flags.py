"""Per-pixel acquisition flags: why a pixel ended with fewer than the target detections (the
``acq_flags`` map of a session, saved in ``maps.npz``)."""

from __future__ import annotations

from enum import IntEnum


class AcqFlag(IntEnum):
    """Why a pixel has fewer than the target detections (``acq_flags`` map, uint8)."""

    COMPLETE = 0
    """The pixel holds the target number of in-window detections."""
    DWELL_LIMIT = 1
    """Gated: a dwell reached the dwell limit before the target count."""
    PASS_LIMIT = 2
    """Still short when the pass budget (gated re-acquisition passes, raster frames) ran out."""
    TIME_LIMIT = 3
    """Still short when the scan's time limit passed."""
    INCOMPLETE = 4
    """The session (abort, failure) or the replayed stream ended before the pixel was complete."""


ACQUIRING = 255
"""``acq_flags`` value of a pixel that is not final yet (still being acquired). Not an
:class:`AcqFlag`: a finished session has none left, and ``maps.npz`` never holds it."""

__all__ = ["AcqFlag", "ACQUIRING"]
