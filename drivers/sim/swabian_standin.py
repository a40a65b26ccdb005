"""A stand-in for the ``Swabian.TimeTagger`` package, fed by the simulated bench: a module-like
object with the package's names (``createTimeTagger``, ``freeTimeTagger``, ``scanTimeTagger``,
``TimeTagStream``, ``TagType``) whose stream turns the photon world's events into absolute time
tags, as a Swabian tagger wired to the laser sync, a detector and the galvo's marker lines would
produce them: a sync tag on every ``divider``-th laser pulse (the event divider), a detector tag
``dtime`` after its sync, a marker tag per marker line that rose. ``tests/test_vendor_standins.py``
checks the names and parameters against the real package.

Faults (WHEN as ``drivers.sim.faults``): ``fifo-overflow``: the rig drops records and the stream
reports ``OverflowBegin``/``OverflowEnd`` (and ``MissedEvents``) where they went missing, as the
tagger does when USB falls behind; ``usb-timeout``: one ``getData`` raises (a failed USB transfer)
and the stream is stopped, the tagger stays usable; ``device-vanish``: ``getData`` raises, the
tagger object is dead (its calls raise) and ``createTimeTagger`` fails for ``vanish_s`` wall-clock
seconds. Other faults are refused.
"""

from __future__ import annotations

import threading
import time
import types
from enum import IntEnum

import numpy as np

from spdepth.drivers.errors import SettingError
from spdepth.drivers.events import EventKind
from spdepth.drivers.sim.faults import FaultKind, FaultSchedule, TAGGER_FAULTS, parse_faults


class TagType(IntEnum):
    TimeTag = 0
    Error = 1
    OverflowBegin = 2
    OverflowEnd = 3
    MissedEvents = 4


class _Buffer:
    """As ``TimeTagStreamBuffer``."""

    def __init__(self, ts, ch, ty, missed):
        self._ts, self._ch, self._ty, self._missed = ts, ch, ty, missed
        self.size = int(ts.size)

    def getTimestamps(self):
        return self._ts

    def getChannels(self):
        return self._ch

    def getEventTypes(self):
        return self._ty

    def getMissedEvents(self):
        return self._missed

    def hasOverflows(self):
        return bool(np.any(self._ty == TagType.OverflowBegin))


class StandInTimeTagger:
    """As ``Swabian.TimeTagger.TimeTagger`` (the calls ``drivers.swabian`` makes)."""

    def __init__(self, card, serial):
        self._card, self._serial = card, serial
        self._generation = card.generation      # a vanish makes this object dead
        self.levels: dict[int, float] = {}
        self.dividers: dict[int, int] = {}
        self.freed = False

    def _alive(self):
        if self._generation != self._card.generation:
            raise RuntimeError(f"Time Tagger {self._serial} was disconnected")

    def getSerial(self):
        return self._serial

    def getModel(self):
        return "Time Tagger Ultra"

    def setTriggerLevel(self, channel, voltage):
        self._alive()
        if not 1 <= channel <= 18:
            raise RuntimeError(f"channel {channel} does not exist")
        self.levels[channel] = float(voltage)

    def setEventDivider(self, channel, divider):
        self._alive()
        if not 1 <= divider <= 65535:
            raise RuntimeError("divider out of range")
        self.dividers[channel] = int(divider)

    def getEventDivider(self, channel):
        return self.dividers.get(channel, 1)


class StandInTimeTagStream:
    """As ``TimeTagStream(tagger, n_max_events, channels)``: tags of the rig's stream."""

    def __init__(self, tagger, n_max_events, channels):
        self._tagger = tagger
        self._card = tagger._card
        self._n_max = int(n_max_events)
        self._channels = [int(c) for c in channels]
        self._running = False
        self._lock = threading.Lock()

    def start(self):
        card, rig = self._card, self._card.rig
        self._tagger._alive()
        with self._lock:
            rig.clear_fifo()
            rig.start_tagger()
            self._s0 = rig.sync                 # the tagger's time 0
            self._next_sync = rig.sync
            self._carry = np.zeros(0, rig.read_events(0).dtype)
            self._running = True
        card.stream = self

    def stop(self):
        with self._lock:
            self._running = False
            self._card.rig.stop_tagger()

    def isRunning(self):
        return self._running

    def clear(self):
        self._card.rig.clear_fifo()

    def _faults(self):
        """Inject the stream faults that are due (called by ``getData``)."""
        card, rig = self._card, self._card.rig
        frac = rig.pixels_pulsed / card.scan_pixels if card.scan_pixels else None
        for f in card.schedule.take_due(rig.now_s, frac):
            card.fired.append(f.kind.value)
            self.stop()
            if f.kind == FaultKind.DEVICE_VANISH:
                card.generation += 1
                card.back_at = time.monotonic() + card.vanish_s
                raise RuntimeError(f"Time Tagger {self._tagger._serial} disconnected")
            raise RuntimeError("Time Tagger: USB transfer failed")

    def getData(self):
        card, rig = self._card, self._card.rig
        self._tagger._alive()
        self._faults()
        sync_ch = self._channels[0]
        det_ch = card.detector_channel
        marker_ch = card.marker_channels
        period_ps, res_ps = card.period_ps, card.res_ps
        with self._lock:
            if not self._running:
                return _Buffer(*(np.zeros(0, t) for t in (np.int64, np.int32, np.uint8, np.uint16)))
            # the laser pulse now has been tagged; a dwell that pushed events after this read of
            # the clock starts at s_now or later, and its photons come after s_now's sync tag
            s_now = rig.sync
            ev = np.concatenate([self._carry, rig.read_events(1 << 20)])
            keep = ev["sync"] <= s_now
            keep &= np.cumsum(~keep) == 0               # stop at the first not yet complete
            self._carry = ev[~keep]
            ev = ev[keep]
            div = self._tagger.getEventDivider(abs(sync_ch))
            first = self._next_sync + (-(self._next_sync - self._s0)) % div
            syncs = np.arange(first, s_now + 1, div, dtype=np.int64)
            self._next_sync = max(self._next_sync, s_now + 1)
            rel = ev["sync"].astype(np.int64) - self._s0
            t_ev = rel * period_ps + ev["dtime"].astype(np.int64) * res_ps
            kind = ev["kind"]
            parts_t, parts_c, parts_y, parts_o = [(syncs - self._s0) * period_ps], \
                [np.full(syncs.size, sync_ch, np.int32)], [np.zeros(syncs.size, np.uint8)], \
                [np.zeros(syncs.size, np.int8)]
            ph = kind == EventKind.PHOTON
            parts_t.append(t_ev[ph])
            parts_c.append(np.full(int(ph.sum()), det_ch, np.int32))
            parts_y.append(np.zeros(int(ph.sum()), np.uint8))
            parts_o.append(np.full(int(ph.sum()), 2, np.int8))
            # the lines of one marker pulse rise together (one timestamp); separate pulses at
            # the same laser sync (a line's stop, the next line's first pixel) 1 ps apart, in
            # the order the galvo sent them
            is_m = kind == EventKind.MARKER
            t_m = t_ev.copy()
            m_sync = ev["sync"][is_m]
            t_m[is_m] += np.arange(m_sync.size) - np.searchsorted(m_sync, m_sync, "left")
            for bit, c in zip((1, 2, 4, 8), marker_ch):
                m = is_m & ((ev["marker"] & bit) != 0)
                parts_t.append(t_m[m])
                parts_c.append(np.full(int(m.sum()), c, np.int32))
                parts_y.append(np.zeros(int(m.sum()), np.uint8))
                parts_o.append(np.full(int(m.sum()), 1, np.int8))
            lost = kind == EventKind.LOST
            if lost.any():
                card.fired.append("fifo-overflow")
                t_lost = rel[lost] * period_ps          # a LOST event's dtime is its count
                for y in (TagType.OverflowBegin, TagType.OverflowEnd):
                    parts_t.append(t_lost)
                    parts_c.append(np.zeros(int(lost.sum()), np.int32))
                    parts_y.append(np.full(int(lost.sum()), int(y), np.uint8))
                    parts_o.append(np.full(int(lost.sum()), 0 if y == 2 else 3, np.int8))
            t = np.concatenate(parts_t)
            c = np.concatenate(parts_c)
            y = np.concatenate(parts_y)
            o = np.concatenate(parts_o)
            # time order; at one time: overflow begin, markers, the sync, detectors, overflow end
            order = np.lexsort((o, t))
            return _Buffer(t[order], c[order], y[order], np.zeros(t.size, np.uint16))


class SwabianStandIn(types.SimpleNamespace):
    """The stand-in module. rig: a ``SimRig``; serial: the tagger's serial; detector_channel and
    marker_channels: where the simulated cables go (match the driver's settings); faults:
    ``fifo-overflow``, ``usb-timeout``, ``device-vanish`` (see the module); scan_pixels for faults
    given as a share of the scan; vanish_s: how long a vanished tagger stays away."""

    _KINDS = (FaultKind.FIFO_OVERFLOW, FaultKind.USB_TIMEOUT, FaultKind.DEVICE_VANISH)

    def __init__(self, rig, serial: str = "2138000ABC", *, detector_channel: int = 2,
                 marker_channels=(3, 4, 5, 6), faults=None, scan_pixels: int | None = None,
                 overflow_records: int = 1000, vanish_s: float = 0.2):
        faults = parse_faults(faults, TAGGER_FAULTS) if isinstance(faults, str) or faults is None \
            else list(faults)
        bad = [f for f in faults if f.kind not in self._KINDS]
        if bad:
            raise SettingError(f"the Swabian stand-in injects "
                               f"{', '.join(k.value for k in self._KINDS)}, not "
                               f"{', '.join(f.kind.value for f in bad)}")
        if any(f.at_fraction is not None for f in faults) and not scan_pixels:
            raise SettingError("faults given as a share of the scan need scan_pixels")
        for f in faults:
            if f.kind != FaultKind.FIFO_OVERFLOW:
                continue
            if f.at_fraction is not None:
                rig.schedule_overflow(overflow_records,
                                      at_pixel=max(1, int(f.at_fraction * scan_pixels)))
            else:
                rig.schedule_overflow(overflow_records, at_s=f.at_s)
        s = rig.world.scene.settings
        card = types.SimpleNamespace(rig=rig, detector_channel=detector_channel,
                                     marker_channels=tuple(marker_channels), stream=None,
                                     period_ps=int(round(s.sync_period_s * 1e12)),
                                     res_ps=int(round(s.resolution_s * 1e12)), fired=[],
                                     schedule=FaultSchedule([f for f in faults
                                                             if f.kind != FaultKind.FIFO_OVERFLOW]),
                                     scan_pixels=scan_pixels, vanish_s=float(vanish_s),
                                     generation=0, back_at=0.0)
        taggers = {serial}

        def createTimeTagger(serial_="", resolution=0):
            if serial_ and serial_ not in taggers:
                raise RuntimeError(f"no Time Tagger with serial {serial_}")
            if time.monotonic() < card.back_at:
                raise RuntimeError("no Time Tagger found")
            return StandInTimeTagger(card, serial)

        def freeTimeTagger(tagger):
            tagger.freed = True

        def scanTimeTagger(include_model_name=False):
            return (f"{serial},Time Tagger Ultra",) if include_model_name else (serial,)

        super().__init__(__name__="Swabian.TimeTagger", createTimeTagger=createTimeTagger,
                         freeTimeTagger=freeTimeTagger, scanTimeTagger=scanTimeTagger,
                         TimeTagStream=StandInTimeTagStream, TagType=TagType, card=card)


__all__ = ["SwabianStandIn", "StandInTimeTagger", "StandInTimeTagStream", "TagType"]
