"""A Swabian Time Tagger (20, Ultra, X) through the ``Swabian-TimeTagger`` package: the package as
the transport (injected module, errors turned into ours), the tagger as a device (inputs,
trigger levels, event divider, a ``TimeTagStream``), and its reader thread, which turns the tags
into our event stream (``protocol.tags_to_events``) and hands the recorder Generic T3 records of
those events, so a Swabian session records the same PTU layout as ours (HydraHarp V2 T3) with the
channel mapping in the header.

A stream that fails (the package raises from ``getData``: a USB error, the tagger unplugged) does
not end the session: the reader puts a LOST event (count unknown) into the stream at the last sync
it placed, starts a new stream on the same tagger or, if that fails, frees it and opens the same
serial again (``SwabianTagger.reconnect``), and the session re-acquires what the hole touched, as
on the PicoQuant path. A tagger that does not come back within ``reconnect_timeout_s`` fails the
session."""

from __future__ import annotations

import importlib
import logging
import time

import numpy as np

from spdepth.drivers.errors import DeviceError, SettingError
from spdepth.drivers.events import EventKind
from spdepth.drivers.swabian.protocol import ConverterState, SwabianSettings, tags_to_events
from spdepth.drivers.tagger.reader import TaggerReader, lost_event
from spdepth.drivers.tagger.t3 import T3EncoderState, encode_t3

log = logging.getLogger("spdepth.swabian")

STREAM_EVENTS = 1 << 22
"""Tags the ``TimeTagStream`` buffers between two reads."""
POLL_S = 0.005
INSTALL_HINT = "`pip install Swabian-TimeTagger` (and Swabian's software for the USB driver)"


class SwabianLibraryMissingError(DeviceError):
    """Raised when the ``Swabian-TimeTagger`` package is not installed."""


def import_timetagger(module=None):
    if module is not None:
        return module
    try:
        return importlib.import_module("Swabian.TimeTagger")
    except ImportError as exc:
        raise SwabianLibraryMissingError(f"Swabian Time Tagger package not installed ({exc}): "
                                         f"{INSTALL_HINT}") from None


class SwabianTagger:
    """One Swabian tagger (``tt``: the package module, ``device``: its TimeTagger object)."""

    record_type = None      # the recorder's default: our HydraHarp V2 T3 layout

    def __init__(self, tt, device, settings: SwabianSettings):
        self.tt = tt
        self.device = device
        self._settings = None
        self.stream = None
        self.identity = {"kind": "swabian", "serial": str(device.getSerial()),
                         "model": str(device.getModel())}
        self.configure(settings)

    @classmethod
    def open(cls, serial: str | None = None, settings: SwabianSettings | None = None, *,
             module=None) -> "SwabianTagger":
        tt = import_timetagger(module)
        try:
            dev = tt.createTimeTagger(serial or "")
        except Exception as exc:  # noqa: BLE001 - the package raises RuntimeError without a device
            which = f"Swabian Time Tagger {serial} not" if serial else "no Swabian Time Tagger"
            raise DeviceError(f"{which} found ({exc}); check USB and that no other program holds "
                              f"it") from None
        return cls(tt, dev, settings or SwabianSettings())

    def configure(self, settings: SwabianSettings) -> None:
        if not isinstance(settings, SwabianSettings):
            raise SettingError(f"Swabian settings must be SwabianSettings, not "
                               f"{type(settings).__name__}")
        try:
            for c in settings.channels():
                self.device.setTriggerLevel(abs(c), float(settings.trigger_level_v))
            self.device.setEventDivider(settings.sync_channel, int(settings.event_divider))
        except Exception as exc:  # noqa: BLE001
            raise DeviceError(f"Swabian Time Tagger {self.identity['serial']}: {exc}") from None
        self._settings = settings

    @property
    def settings(self) -> dict:
        return self._settings.to_dict()

    @property
    def header_info(self) -> dict:
        """What the recording's header carries about this tagger (the channel mapping)."""
        return {"tagger_channels": self._settings.channel_map(), "tagger": self.identity}

    @property
    def resolution_s(self) -> float:
        return self._settings.resolution_ps * 1e-12

    def start(self) -> None:
        self.stop()
        self.stream = self.tt.TimeTagStream(self.device, STREAM_EVENTS, self._settings.channels())
        self.stream.start()

    def stop(self) -> None:
        if self.stream is not None:
            try:
                self.stream.stop()
            finally:
                self.stream = None

    def restart(self) -> None:
        """A new stream on the same tagger after a failed one (whose stop may fail too)."""
        try:
            self.stop()
        except Exception as exc:  # noqa: BLE001 - the failed stream's own error; start decides
            log.debug("stopping the failed Swabian stream: %s", exc)
        try:
            self.start()
        except Exception as exc:  # noqa: BLE001 - the package's errors: the tagger is not usable
            raise DeviceError(f"Swabian Time Tagger {self.identity['serial']}: a new stream "
                              f"did not start ({exc})") from None

    def reconnect(self, timeout_s: float = 5.0) -> None:
        """Free the tagger, open the same serial again, re-apply the settings and start a stream;
        DeviceError if it is not back within ``timeout_s``."""
        self.stream = None
        try:
            self.tt.freeTimeTagger(self.device)
        except Exception as exc:  # noqa: BLE001 - it is gone: freeing can fail
            log.debug("freeing the vanished Swabian tagger: %s", exc)
        serial = self.identity["serial"]
        deadline = time.monotonic() + timeout_s
        while True:
            try:
                self.device = self.tt.createTimeTagger(serial)
                self.configure(self._settings)
                self.start()
                return
            except Exception as exc:  # noqa: BLE001 - not back yet
                last = exc
            if time.monotonic() > deadline:
                raise DeviceError(f"Swabian Time Tagger {serial} did not come back within "
                                  f"{timeout_s:g} s ({last})")
            time.sleep(0.05)

    def read(self):
        """The tags since the last read: (timestamps ps, channels, types)."""
        buf = self.stream.getData()
        return (np.asarray(buf.getTimestamps(), np.int64), np.asarray(buf.getChannels(), np.int32),
                np.asarray(buf.getEventTypes(), np.uint8))

    def reader(self, **options) -> "SwabianReader":
        return SwabianReader(self, **options)

    def close(self) -> None:
        try:
            self.stop()
        finally:
            self.tt.freeTimeTagger(self.device)


class SwabianReader(TaggerReader):
    """Reads a Swabian tagger's ``TimeTagStream`` in a thread (the ``TaggerReader`` contract: a
    bounded queue of event chunks, the tap sees records and holes in stream order, a thread error
    reaches the owner). Overflows are LOST events where they begin; the stream goes on. A failed
    stream is a LOST event at the last sync placed, then a new stream (or a reopened tagger): the
    new stream's tags are placed from its first sync tag on, counted on after the last sync seen
    (``_sync_offset``), so syncs keep increasing across the hole."""

    def __init__(self, tagger: SwabianTagger, **options):
        options.pop("buffer_bytes", None)
        super().__init__(tagger, buffer_bytes=512, **options)
        self.conv = ConverterState()
        self.enc = T3EncoderState()
        self.stats.update({"overflows": 0, "unplaced": 0, "stream_errors": 0})
        self._sync_offset = 0      # our sync of the current stream's first sync tag
        self._last_sync = -1       # the last sync placed (-1: none yet)

    def step(self) -> None:
        t = self.tagger
        try:
            ts, ch, ty = t.read()
        except Exception as exc:  # noqa: BLE001 - the package's own errors: a device problem
            self._stream_failed(exc)
            return
        if ts.size == 0:
            self._stop.wait(POLL_S)
            return
        ev = tags_to_events(ts, ch, ty, t._settings, self.conv)
        ev["sync"] += self._sync_offset
        if ev.size:
            self._last_sync = int(ev["sync"][-1])
        self.stats["overflows"] = self.conv.overflows
        self.stats["unplaced"] = self.conv.unplaced
        self.stats["records"] += int(ts.size)
        lost = np.flatnonzero(ev["kind"] == EventKind.LOST)
        start = 0
        for i in [*lost.tolist(), ev.size]:
            part = ev[start:i]
            if part.size:
                if self.tap is not None:
                    self.tap.on_records(encode_t3(part, self.enc))
            if i < ev.size:
                log.warning("Swabian overflow: tags lost from sync %d", int(ev["sync"][i]))
                if self.tap is not None:
                    self.tap.on_lost(int(ev["sync"][i]), 0, False)
            start = i + 1
        self._push(ev)

    def _stream_failed(self, exc: Exception) -> None:
        """LOST at the last sync placed, a new stream (or the tagger reopened), syncs counted on
        after the hole; DeviceError (to the owner) if the tagger does not come back."""
        t = self.tagger
        sync = max(self._last_sync, self._sync_offset)
        self.stats["stream_errors"] += 1
        log.warning("Swabian Time Tagger stream failed (%s): tags lost from sync %d; restarting",
                    exc, sync)
        if self.tap is not None:
            # our records carry our sync count, which goes on across the hole: no restart for
            # the recorder
            self.tap.on_lost(sync, 0, False)
        self._push(lost_event(sync, 0))
        try:
            t.restart()
            self.stats["restarts"] += 1
        except DeviceError as why:
            log.warning("%s: reopening the tagger", why)
            t.reconnect(timeout_s=self.reconnect_timeout_s)
            self.stats["reconnects"] += 1
        # the new stream's first sync tag starts the count again (its time base may be new)
        self.conv = ConverterState(unplaced=self.conv.unplaced, overflows=self.conv.overflows)
        self._sync_offset = sync + 1
        self._last_sync = sync


__all__ = ["SwabianTagger", "SwabianReader", "SwabianLibraryMissingError", "import_timetagger"]
