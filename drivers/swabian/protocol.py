"""Swabian time tags as our event stream, with no I/O.

A Swabian Time Tagger streams absolute time tags (``TimeTagStream``: timestamp in ps, channel,
tag type) for every input: the laser sync, the detectors and the galvo's marker lines. T3-style
events need, for each detection, the sync it follows and its time after that sync. The laser
period is known (``sync_period_s``), so the tag of sync n lets us place every later tag by time:
``k = floor((t - t_sync) / period)`` syncs later, ``dtime = t - t_sync - k * period``. That keeps
working with an event divider on the sync input (only every n-th sync tagged, for high laser
rates) and across an overflow (tags missing for a while): syncs are counted by time, not by tags.

Marker tags with the same timestamp (the galvo's lines rising together at one step) become one
marker event with their bits OR-ed, as PicoQuant devices record them; the assignment then applies
them in its fixed order (frame, line start, pixel, line stop). Separate pulses keep separate
events.

Overflows (``OverflowBegin``) become LOST events in-band at the sync where they begin (count 0:
unknown); ``Error`` tags likewise. Tags before the first sync tag cannot be placed and are
counted in ``state.unplaced``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import IntEnum

import numpy as np
from numba import njit

from spdepth.drivers.errors import SettingError
from spdepth.drivers.events import EVENT_DTYPE, EventKind, Marker


class TagType(IntEnum):
    """``Swabian.TimeTagger.TagType`` values."""

    TIME_TAG = 0
    """A normal time tag."""
    ERROR = 1
    """The device reported an error; tags around it may be missing."""
    OVERFLOW_BEGIN = 2
    """The USB link fell behind: tags are missing from here ..."""
    OVERFLOW_END = 3
    """... to here."""
    MISSED_EVENTS = 4
    """How many tags of one channel were missed during the overflow."""


@dataclass(frozen=True)
class SwabianSettings:
    """How a Swabian tagger is used; saved with every recording (and in the PTU header as the
    channel mapping).

    sync_channel:      input of the laser sync.
    detector_channels: inputs of the detectors (detector i -> event channel i).
    marker_channels:   inputs of the galvo's pixel, line start, line stop, frame lines (in the
                       ``Marker`` bit order: 1, 2, 4, 8).
    sync_period_s:     the laser period (the events are placed by it).
    event_divider:     tag only every n-th sync (1..65535; high laser rates).
    resolution_ps:     dtime unit of the events and the recording (whole ps; 8 ps keeps 15-bit
                       T3 dtimes up to 262 ns).
    trigger_level_v:   trigger level of every input used.
    """

    sync_channel: int = 1
    detector_channels: tuple[int, ...] = (2,)
    marker_channels: tuple[int, ...] = (3, 4, 5, 6)
    sync_period_s: float = 50e-9
    event_divider: int = 1
    resolution_ps: int = 8
    trigger_level_v: float = 0.5

    def __post_init__(self):
        object.__setattr__(self, "detector_channels", tuple(int(c) for c in self.detector_channels))
        object.__setattr__(self, "marker_channels", tuple(int(c) for c in self.marker_channels))
        chans = [self.sync_channel, *self.detector_channels, *self.marker_channels]
        if any(not (1 <= abs(c) <= 63) for c in chans) or len(set(chans)) != len(chans):
            raise SettingError(f"Swabian channels {chans} must be distinct, 1..63 (negative: "
                               f"falling edge)")
        if len(self.marker_channels) > 4 or not self.detector_channels:
            raise SettingError("Swabian: 1+ detector channels and at most 4 marker channels")
        if not (1 <= self.event_divider <= 65535):
            raise SettingError(f"Swabian event_divider={self.event_divider} outside 1..65535")
        if not (0 < self.sync_period_s < 1e-3):
            raise SettingError(f"Swabian sync_period_s={self.sync_period_s!r} must be 0..1 ms")
        if not (isinstance(self.resolution_ps, int) and 1 <= self.resolution_ps <= 1000):
            raise SettingError(f"Swabian resolution_ps={self.resolution_ps!r} must be 1..1000")
        if self.sync_period_s * 1e12 / self.resolution_ps > 32768:
            raise SettingError(f"a {self.sync_period_s * 1e9:g} ns period in "
                               f"{self.resolution_ps} ps units does not fit 15-bit T3 dtimes: "
                               f"raise resolution_ps")

    def channel_map(self) -> dict:
        return {"sync": self.sync_channel, "detectors": list(self.detector_channels),
                "markers": {m.name: c for m, c in zip(Marker, self.marker_channels)},
                "event_divider": self.event_divider, "resolution_ps": self.resolution_ps,
                "sync_period_s": self.sync_period_s}

    def to_dict(self) -> dict:
        return {**self.channel_map(), "trigger_level_v": self.trigger_level_v}

    def channels(self) -> list[int]:
        return [self.sync_channel, *self.detector_channels, *self.marker_channels]

    def luts(self) -> tuple[np.ndarray, np.ndarray]:
        """(role, value) per channel + 64: role 0 ignore, 1 sync, 2 detector, 3 marker."""
        role = np.zeros(128, np.int8)
        value = np.zeros(128, np.int16)
        role[self.sync_channel + 64] = 1
        for i, c in enumerate(self.detector_channels):
            role[c + 64], value[c + 64] = 2, i
        for m, c in zip(Marker, self.marker_channels):
            role[c + 64], value[c + 64] = 3, int(m)
        return role, value


@dataclass
class ConverterState:
    """Carried between chunks of one stream."""

    last_sync_t: int = -1       # ps timestamp of the last sync tag (-1: none yet)
    last_sync: int = 0          # its sync index
    unplaced: int = 0           # tags before the first sync tag
    overflows: int = 0
    arr: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))


_PHOTON, _MARKER, _LOST = int(EventKind.PHOTON), int(EventKind.MARKER), int(EventKind.LOST)


@njit(cache=True, nogil=True)
def _convert_kernel(ts, ch, types, role, value, period_ps, res_ps, st, out_sync, out_dtime,
                    out_channel, out_kind, out_marker):
    """st: int64[4] = last_sync_t, last_sync, unplaced, overflows (updated)."""
    last_t, last_s, unplaced, overflows = st[0], st[1], st[2], st[3]
    st_prev_t = np.int64(-1)          # timestamp of the last marker event written
    n = 0
    for i in range(ts.size):
        t = ts[i]
        ty = types[i]
        if ty == 2 or ty == 1:                          # OverflowBegin, Error: a hole from here
            overflows += 1
            s = last_s
            if last_t >= 0:
                s = last_s + np.int64(np.floor((t - last_t) / period_ps))
            out_sync[n] = s
            out_dtime[n] = 0
            out_channel[n] = 0
            out_kind[n] = 2
            out_marker[n] = 0
            n += 1
            continue
        if ty != 0:                                      # OverflowEnd, MissedEvents
            continue
        c = ch[i] + 64
        if c < 0 or c >= 128 or role[c] == 0:
            continue
        if role[c] == 1:                                 # laser sync
            if last_t < 0:
                last_s = 0
            else:
                last_s = last_s + np.int64(np.floor((t - last_t) / period_ps + 0.5))
            last_t = t
            continue
        if last_t < 0:
            unplaced += 1
            continue
        k = np.int64(np.floor((t - last_t) / period_ps))
        dt = (t - last_t) - k * period_ps
        out_sync[n] = last_s + k
        out_channel[n] = 0
        out_marker[n] = 0
        if role[c] == 2:
            out_kind[n] = 0
            out_dtime[n] = np.uint32(np.floor(dt / res_ps + 1e-6))
            out_channel[n] = value[c]
        else:
            if n > 0 and out_kind[n - 1] == 1 and st_prev_t == t:
                # marker lines that rose together (one galvo step): one event, bits OR-ed, as a
                # PicoQuant device's bit-coded marker record
                out_marker[n - 1] |= value[c]
                continue
            out_kind[n] = 1
            out_dtime[n] = 0
            out_marker[n] = value[c]
            st_prev_t = t
        n += 1
    st[0], st[1], st[2], st[3] = last_t, last_s, unplaced, overflows
    return n


def tags_to_events(timestamps: np.ndarray, channels: np.ndarray, types: np.ndarray,
                   settings: SwabianSettings, state: ConverterState) -> np.ndarray:
    """Time tags (ps int64, channel int32, TagType uint8) of one stream chunk -> EVENT_DTYPE
    events in the same order; ``state`` carries the last sync across chunks."""
    ts = np.ascontiguousarray(timestamps, np.int64)
    ch = np.ascontiguousarray(channels, np.int32)
    ty = np.ascontiguousarray(types, np.uint8)
    if not (ts.size == ch.size == ty.size):
        raise SettingError("timestamps, channels and types must have one length")
    role, value = settings.luts()
    out = np.zeros(ts.size, EVENT_DTYPE)
    st = np.array([state.last_sync_t, state.last_sync, state.unplaced, state.overflows], np.int64)
    sync = np.zeros(ts.size, np.int64)
    dtime = np.zeros(ts.size, np.uint32)
    chan = np.zeros(ts.size, np.uint8)
    kind = np.zeros(ts.size, np.uint8)
    marker = np.zeros(ts.size, np.uint8)
    n = _convert_kernel(ts, ch, ty, role, value, float(settings.sync_period_s * 1e12),
                        float(settings.resolution_ps), st, sync, dtime, chan, kind, marker)
    state.last_sync_t, state.last_sync, state.unplaced, state.overflows = (int(v) for v in st)
    out = out[:n]
    out["sync"], out["dtime"], out["channel"] = sync[:n], dtime[:n], chan[:n]
    out["kind"], out["marker"] = kind[:n], marker[:n]
    return out


__all__ = ["TagType", "SwabianSettings", "ConverterState", "tags_to_events"]
