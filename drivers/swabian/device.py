"""A Swabian Time Tagger (20, Ultra, X) through the ``Swabian-TimeTagger`` package: the package as
the transport (injected module, errors turned into ours), the tagger as a device (inputs,
trigger levels, event divider, a ``TimeTagStream``), and its reader thread, which turns the tags
into our event stream (``protocol.tags_to_events``) and hands the recorder Generic T3 records of
those events, so a Swabian session records the same PTU layout as ours (HydraHarp V2 T3) with the
channel mapping in the header."""

from __future__ import annotations

import importlib
import logging

import numpy as np

from spdepth.drivers.errors import DeviceError, SettingError
from spdepth.drivers.events import EventKind
from spdepth.drivers.swabian.protocol import ConverterState, SwabianSettings, tags_to_events
from spdepth.drivers.tagger.reader import TaggerReader
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
    reaches the owner). Overflows are LOST events where they begin; the stream goes on."""

    def __init__(self, tagger: SwabianTagger, **options):
        options.pop("buffer_bytes", None)
        super().__init__(tagger, buffer_bytes=512, **options)
        self.conv = ConverterState()
        self.enc = T3EncoderState()
        self.stats.update({"overflows": 0, "unplaced": 0})

    def step(self) -> None:
        t = self.tagger
        try:
            ts, ch, ty = t.read()
        except Exception as exc:  # noqa: BLE001 - the package's own errors: a device problem
            raise DeviceError(f"Swabian Time Tagger stream failed: {exc}") from None
        if ts.size == 0:
            self._stop.wait(POLL_S)
            return
        ev = tags_to_events(ts, ch, ty, t._settings, self.conv)
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


__all__ = ["SwabianTagger", "SwabianReader", "SwabianLibraryMissingError", "import_timetagger"]
