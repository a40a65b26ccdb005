"""What a scan is asked to do (:class:`ScanPlan`), and how the pixels still needing detections are
grouped into galvo passes."""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields

import numpy as np

from spdepth.acq.assign import PassGeometry
from spdepth.acq.params import MODES
from spdepth.recon.errors import InputError

DEFAULT_MAX_PASSES = {"gated": 10, "raster": 100}


@dataclass(frozen=True)
class ScanPlan:
    """What to scan and how long to hold each pixel; saved with every recording and result.

    nx, ny:       pixels per line and lines.
    x/y_*_deg:    mirror angles (optical degrees) of the first and last pixel centres.
    pattern:      "raster" (every line left to right) or "serp" (odd lines right to left).
    mode:         "gated": the controller holds each pixel until it counted ``target`` detector
                  pulses or ``dwell_s`` passed (the dwell limit); "raster": every pixel for
                  ``dwell_s``, frames repeated until every pixel holds ``target`` in-window
                  detections.
    target:       in-window detections wanted per pixel.
    dwell_s:      gated: the dwell limit per pixel; raster: the dwell per pixel and frame.
    settle_s:     wait after each step before the pixel opens.
    max_passes:   gated: passes over pixels still short (re-acquisition after lost data) before
                  they are flagged; raster: frames before short pixels are flagged. None: 10 / 100.
    time_limit_s: wall-clock limit of the whole scan (None: none); pixels short then are flagged.
    """

    nx: int
    ny: int
    x_first_deg: float
    x_last_deg: float
    y_first_deg: float
    y_last_deg: float
    pattern: str = "raster"
    mode: str = "gated"
    target: int = 15
    dwell_s: float = 10e-3
    settle_s: float = 0.0
    max_passes: int | None = None
    time_limit_s: float | None = None

    def __post_init__(self) -> None:
        if self.nx < 1 or self.ny < 1:
            raise InputError(f"scan size must be at least 1 x 1, got {self.nx} x {self.ny}")
        if self.pattern not in ("raster", "serp"):
            raise InputError(f"pattern must be 'raster' or 'serp', got {self.pattern!r}")
        if self.mode not in MODES:
            raise InputError(f"mode must be 'gated' or 'raster', got {self.mode!r}")
        if self.target < 1:
            raise InputError(f"target must be at least 1 detection per pixel, got {self.target}")
        if not self.dwell_s > 0:
            raise InputError(f"dwell_s must be positive, got {self.dwell_s}")
        if self.settle_s < 0:
            raise InputError(f"settle_s must not be negative, got {self.settle_s}")
        if self.max_passes is not None and self.max_passes < 1:
            raise InputError(f"max_passes must be at least 1, got {self.max_passes}")
        if self.time_limit_s is not None and not self.time_limit_s > 0:
            raise InputError(f"time_limit_s must be positive, got {self.time_limit_s}")

    @property
    def shape(self) -> tuple[int, int]:
        return self.ny, self.nx

    @property
    def passes_allowed(self) -> int:
        return self.max_passes if self.max_passes is not None else DEFAULT_MAX_PASSES[self.mode]

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "ScanPlan":
        names = {f.name for f in fields(cls)}
        return cls(**{k: v for k, v in d.items() if k in names})

    def col_deg(self, col: int) -> float:
        return _lerp(self.x_first_deg, self.x_last_deg, col, self.nx)

    def row_deg(self, row: int) -> float:
        return _lerp(self.y_first_deg, self.y_last_deg, row, self.ny)


def _lerp(first: float, last: float, i: int, n: int) -> float:
    return first if n == 1 else first + (last - first) * i / (n - 1)


def pass_regions(needy: np.ndarray, pattern: str = "raster") -> list[PassGeometry]:
    """Rectangles covering the pixels of the ``(H, W)`` mask ``needy``: one per run of consecutive
    lines with needy pixels, spanning their leftmost to rightmost needy column. A full image gives
    one full-frame pass; a hole after lost data gives the affected lines only."""
    h, w = needy.shape
    rows = np.flatnonzero(needy.any(axis=1))
    out: list[PassGeometry] = []
    if rows.size == 0:
        return out
    breaks = np.flatnonzero(np.diff(rows) > 1) + 1
    for run in np.split(rows, breaks):
        r0, r1 = int(run[0]), int(run[-1])
        cols = np.flatnonzero(needy[r0:r1 + 1].any(axis=0))
        c0, c1 = int(cols[0]), int(cols[-1])
        out.append(PassGeometry(r0, c0, r1 - r0 + 1, c1 - c0 + 1, w, pattern))
    return out
