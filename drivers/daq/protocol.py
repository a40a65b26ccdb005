"""A galvo raster as NI-DAQ samples, with no I/O: the two mirror voltages and the marker lines,
sample by sample, from a scan pattern, a dwell and the mirror's calibration.

Each pixel is two samples of half the dwell: in the first the marker lines of that pixel are
high (PIXEL; LINE_START on a line's first pixel; FRAME on the frame's first), in the second they
are low, so every marker is one rising edge the tagger time-stamps. After a line's last pixel
one more pair of samples holds the mirror still and raises LINE_STOP. The digital lines share
the analog output's sample clock, so markers and steps cannot drift apart.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import IntEnum

import numpy as np

from spdepth.drivers.errors import SettingError

SAMPLES_PER_PIXEL = 2
MAX_RATE_HZ = 1_000_000
"""Highest sample clock we ask for (typical of NI multifunction cards' analog outputs)."""


class MarkerLine(IntEnum):
    """Digital output lines (``port0/line0:3``), each wired to the tagger marker input of the same
    number plus one; the value is the marker bit (``drivers.events.Marker``)."""

    PIXEL = 1
    """line0 -> marker input 1: the mirror stepped to the next pixel."""
    LINE_START = 2
    """line1 -> marker input 2: a line's first pixel."""
    LINE_STOP = 4
    """line2 -> marker input 3: after a line's last pixel."""
    FRAME = 8
    """line3 -> marker input 4: a frame starts."""


@dataclass(frozen=True)
class DaqCalibration:
    """The mirror's analog interface; saved with every recording.

    deg_per_volt_x/y: optical degrees per volt of each axis.
    v_min, v_max:     voltage limits of the outputs (the servo driver's input range).
    park_deg:         where the mirror rests between scans (x, y optical degrees).
    """

    deg_per_volt_x: float = 1.0
    deg_per_volt_y: float = 1.0
    v_min: float = -10.0
    v_max: float = 10.0
    park_deg: tuple[float, float] = (0.0, 0.0)

    def __post_init__(self):
        for n in ("deg_per_volt_x", "deg_per_volt_y"):
            v = getattr(self, n)
            if not (isinstance(v, (int, float)) and v != 0 and np.isfinite(v)):
                raise SettingError(f"galvo calibration {n}={v!r} must be a non-zero number")
        if not (-10.0 <= self.v_min < self.v_max <= 10.0):
            raise SettingError(f"galvo voltage limits {self.v_min}..{self.v_max} V must lie in "
                               f"-10..10 V with min < max")
        object.__setattr__(self, "park_deg", tuple(float(v) for v in self.park_deg))
        self.volts(*self.park_deg, what="park position")

    def volts(self, x_deg, y_deg, what: str = "scan") -> tuple[np.ndarray, np.ndarray]:
        x = np.asarray(x_deg, float) / self.deg_per_volt_x
        y = np.asarray(y_deg, float) / self.deg_per_volt_y
        for axis, v in (("x", x), ("y", y)):
            if v.size and (v.min() < self.v_min or v.max() > self.v_max):
                raise SettingError(f"galvo {what} needs {axis} {v.min():.3g}..{v.max():.3g} V, "
                                   f"outside the limits {self.v_min:g}..{self.v_max:g} V "
                                   f"(check the field of view and deg_per_volt)")
        return x, y

    def to_dict(self) -> dict:
        return {"deg_per_volt_x": self.deg_per_volt_x, "deg_per_volt_y": self.deg_per_volt_y,
                "v_min": self.v_min, "v_max": self.v_max, "park_deg": list(self.park_deg)}


@dataclass(frozen=True)
class Waveform:
    """One scan as samples.

    ao:          float64 (2, N): x and y volts.
    do:          bool (4, N): marker lines (``MarkerLine`` order: line0..line3).
    rate_hz:     sample clock.
    pixels_done: int64 (N + 1,): pixels completed once k samples were generated.
    order:       int64 (P, 2): (row, col) of the pattern's pixels in scan order.
    """

    ao: np.ndarray
    do: np.ndarray
    rate_hz: float
    pixels_done: np.ndarray
    order: np.ndarray = field(repr=False)

    @property
    def n_samples(self) -> int:
        return self.ao.shape[1]


def raster_waveform(nx: int, ny: int, x_deg: np.ndarray, y_deg: np.ndarray, dwell_s: float,
                    cal: DaqCalibration, *, serpentine: bool = False) -> Waveform:
    """The samples of one frame of ``ny`` lines of ``nx`` pixels at column angles ``x_deg``
    (nx,) and row angles ``y_deg`` (ny,), each pixel held ``dwell_s``."""
    if nx < 1 or ny < 1:
        raise SettingError(f"galvo pattern {nx}x{ny} must have at least one pixel")
    rate = SAMPLES_PER_PIXEL / float(dwell_s)
    if rate > MAX_RATE_HZ:
        raise SettingError(f"dwell {dwell_s * 1e6:g} us needs a {rate:g} Hz sample clock, above "
                           f"{MAX_RATE_HZ:g} Hz: use a longer dwell")
    per_line = (nx + 1) * SAMPLES_PER_PIXEL
    n = ny * per_line
    xs = np.empty(n)
    ys = np.empty(n)
    do = np.zeros((4, n), bool)
    done = np.zeros(n + 1, np.int64)
    order = np.empty((nx * ny, 2), np.int64)
    k = 0
    p = 0
    for row in range(ny):
        cols = range(nx - 1, -1, -1) if serpentine and row % 2 else range(nx)
        for j, col in enumerate(cols):
            xs[k:k + 2] = x_deg[col]
            ys[k:k + 2] = y_deg[row]
            do[0, k] = True
            if j == 0:
                do[1, k] = True
                do[3, k] = row == 0
            order[p] = (row, col)
            p += 1
            done[k + 2:] = p          # completed once both samples were generated
            k += 2
        xs[k:k + 2] = xs[k - 1]
        ys[k:k + 2] = ys[k - 1]
        do[2, k] = True
        k += 2
    vx, vy = cal.volts(xs, ys)
    return Waveform(np.vstack([vx, vy]), do, rate, done, order)


def parse_channels(spec: str) -> tuple[str, str]:
    """``Dev1`` or ``Dev1/ao0:1`` -> (device, ao channels); SettingError otherwise."""
    dev, _, ao = spec.partition("/")
    ao = ao or "ao0:1"
    if not dev or not ao.startswith("ao"):
        raise SettingError(f"nidaq:{spec}: expected DEVICE[/aoN:M], e.g. nidaq:Dev1/ao0:1")
    return dev, ao


__all__ = ["DaqCalibration", "Waveform", "raster_waveform", "MarkerLine", "parse_channels",
           "SAMPLES_PER_PIXEL", "MAX_RATE_HZ"]
