"""A PicoQuant TCSPC device in T3 mode: open by family and serial, settings in SI units, start and
stop, the FIFO read, flags, reconnect; and its reader thread (the same queue, tap and in-band loss
contract as our own tagger's ``TaggerReader``).

``PicoQuantTagger(transport, index)`` takes a ``LibTransport`` (the loaded library);
``PicoQuantTagger.open("mh150", serial=None)`` finds the library and the device. Tests load a
stand-in library compiled from ``drivers/sim/picoquant_standin.c`` through the same path.
"""

from __future__ import annotations

import ctypes as ct
import logging
import time

import numpy as np

from spdepth.drivers.errors import DeviceError, SettingError
from spdepth.drivers.picoquant.protocol import (CFD_ZEROCROSS_MV, TRGMODE_ETR, Family, Feature,
                                                Flag, LibError, MeasMode, PicoQuantIdentity,
                                                PicoQuantSettings, Trigger, family)
from spdepth.drivers.picoquant.transport import LibTransport, PicoQuantError
from spdepth.drivers.tagger.reader import TaggerReader
from spdepth.drivers.tagger.t3 import decode_t3

log = logging.getLogger("spdepth.picoquant")

ACQ_TIME_MS = 360_000_000
"""``*_StartMeas`` acquisition time: the longest the libraries take (100 h); we stop it ourselves."""
IDLE_SLEEP_S = 0.002
"""Pause after an empty ``*_ReadFiFo`` (the call does not block)."""


def _text(buf) -> str:
    return buf.value.decode("ascii", "replace").strip()


def _open_each(transport: LibTransport):
    """(index, serial) of each device the library opens, in index order, left open for the caller
    to close or keep; one another program holds is skipped (it cannot be opened to ask)."""
    for i in range(transport.family.max_devices):
        buf = ct.create_string_buffer(16)
        try:
            transport.call("OpenDevice", i, buf, quiet=True)
        except PicoQuantError:
            continue
        yield i, _text(buf)


def list_devices(transport: LibTransport) -> list[dict]:
    """Devices the library can open: ``[{"index", "serial"}]``. Devices held by another program
    are skipped (they cannot be opened to ask)."""
    found = []
    for i, serial in _open_each(transport):
        found.append({"index": i, "serial": serial})
        try:
            transport.call("CloseDevice", i, quiet=True)
        except PicoQuantError as exc:
            log.warning("closing PicoQuant device %d after the scan failed: %s", i, exc)
    return found


class PicoQuantTagger:
    """One opened PicoQuant device (``index`` in its library), initialised in T3 mode."""

    def __init__(self, transport: LibTransport, index: int, *, serial: str = ""):
        self.transport = transport
        self.family: Family = transport.family
        self.index = int(index)
        self.serial = serial
        self._settings: PicoQuantSettings | None = None
        self._resolution_s: float | None = None
        self._running = False
        self.hw_model = ""
        self.features = Feature(0)
        self.identity: dict = {}
        self.initialize()

    # ---- opening ---------------------------------------------------------------------------------
    @classmethod
    def open(cls, model: str, serial: str | None = None, *, lib=None, lib_path=None) -> "PicoQuantTagger":
        """Open the first device of family ``model`` (``mh150``), or the one with ``serial``.
        ``lib``: a loaded ``ctypes.CDLL`` or its path (default: the search in ``transport``)."""
        fam = family(model)
        transport = LibTransport(fam, lib, lib_path=lib_path)
        index, got = cls._find(transport, serial)
        return cls(transport, index, serial=got)

    @staticmethod
    def _find(transport: LibTransport, serial: str | None) -> tuple[int, str]:
        seen = []
        for i, got in _open_each(transport):
            if not serial or got == serial:
                return i, got
            seen.append(got)
            transport.call("CloseDevice", i, quiet=True)
        fam = transport.family
        if serial:
            raise DeviceError(f"no {fam.model} with serial {serial} (found: "
                              f"{', '.join(seen) or 'none'}); check USB and power")
        raise DeviceError(f"no {fam.model} found through {transport.path or 'its library'}; "
                          "check USB and power (and that no other program holds it)")

    def initialize(self) -> None:
        """``*_Initialize`` in T3 mode and read who the device is."""
        if self.family.init_refsource:
            ref = int(self._settings.ref_source) if self._settings else 0
            self.transport.call("Initialize", self.index, int(MeasMode.T3), ref)
        else:       # TimeHarp 260: no reference input, Initialize(devidx, mode)
            self.transport.call("Initialize", self.index, int(MeasMode.T3))
        model, part, ver = (ct.create_string_buffer(32) for _ in range(3))
        self.transport.call("GetHardwareInfo", self.index, model, part, ver)
        self.hw_model = _text(model)
        sn = ct.create_string_buffer(16)
        self.transport.call("GetSerialNumber", self.index, sn)
        self.serial = _text(sn)
        features = ct.c_int()
        self.transport.call("GetFeatures", self.index, ct.byref(features))
        self.features = Feature(features.value & int(Feature.TTTR | Feature.MARKERS))
        if Feature.TTTR not in self.features:
            # T3 mode is a licensed option: without it Initialize worked but nothing streams
            raise DeviceError(f"{self.family.model} {self.serial} has no time-tagging (TTTR) "
                              "option; spdepth records in T3 mode")
        self.identity = PicoQuantIdentity(self.family.key, _text(model), _text(part), _text(ver),
                                          self.serial, self.transport.library_version(),
                                          self.index).to_dict()

    @property
    def n_inputs(self) -> int:
        n = ct.c_int()
        self.transport.call("GetNumOfInputChannels", self.index, ct.byref(n))
        return n.value

    # ---- settings --------------------------------------------------------------------------------
    def configure(self, settings: PicoQuantSettings) -> None:
        """Apply every setting (while stopped); re-applied after a reconnect."""
        if not isinstance(settings, PicoQuantSettings):
            raise SettingError(f"PicoQuant settings must be PicoQuantSettings, not "
                               f"{type(settings).__name__}")
        fam, t, i = self.family, self.transport, self.index
        if settings.marker_enabled and Feature.MARKERS not in self.features:
            # the pixel clock arrives on the marker inputs: without them no photon finds its pixel
            raise DeviceError(f"{fam.model} {self.serial} has no marker inputs (a licensed "
                              "option); the galvo's pixel, line and frame markers need them")
        if settings.sync_divider > fam.sync_div_max:
            raise SettingError(f"PicoQuant sync_divider={settings.sync_divider}: the {fam.model} "
                               f"divides by 1..{fam.sync_div_max}")
        cfd = fam.uses_cfd(self.hw_model)
        if cfd and max(abs(settings.sync_level_mv), abs(settings.input_level_mv)) > \
                fam.cfd_level_max_mv:
            raise SettingError(f"PicoQuant trigger levels {settings.sync_level_mv}/"
                               f"{settings.input_level_mv} mV: the {self.hw_model or fam.model} "
                               f"CFD takes at most {fam.cfd_level_max_mv} mV")
        t.call("SetSyncDiv", i, settings.sync_divider)
        # Edge triggers take (level mV, edge); CFDs take (level mV, zero cross mV) with the sign
        # the family's library wants (HydraHarp 400: magnitudes; TimeHarp 260 PICO: negative)
        # for the same negative detector pulses.
        if fam.trigger == Trigger.SELECTABLE:
            t.call("SetSyncTrgMode", i, TRGMODE_ETR)
        if cfd:
            t.call("SetSyncCFD", i, fam.cfd_sign * abs(settings.sync_level_mv),
                   fam.cfd_sign * CFD_ZEROCROSS_MV)
        else:
            t.call("SetSyncEdgeTrg", i, settings.sync_level_mv, 0)
        t.call("SetSyncChannelOffset", i, settings.sync_offset_ps)
        for ch in range(self.n_inputs):
            if fam.trigger == Trigger.SELECTABLE:
                t.call("SetInputTrgMode", i, ch, TRGMODE_ETR)
            if cfd:
                t.call("SetInputCFD", i, ch, fam.cfd_sign * abs(settings.input_level_mv),
                       fam.cfd_sign * CFD_ZEROCROSS_MV)
            else:
                t.call("SetInputEdgeTrg", i, ch, settings.input_level_mv, 0)
            t.call("SetInputChannelOffset", i, ch, settings.input_offset_ps)
        t.call("SetBinning", i, settings.binning)
        t.call("SetOffset", i, 0)
        edges, enables = settings.marker_args()
        t.call("SetMarkerEdges", i, *edges)
        t.call("SetMarkerEnable", i, *enables)
        res = ct.c_double()
        t.call("GetResolution", i, ct.byref(res))
        self._resolution_s = res.value * 1e-12
        self._settings = settings

    @property
    def settings(self) -> dict | None:
        """The settings last applied (as a dict, for ``run.json``), None before ``configure``."""
        return None if self._settings is None else self._settings.to_dict()

    @property
    def resolution_s(self) -> float:
        """The dtime unit of the records, seconds (read from the device at ``configure``)."""
        if self._resolution_s is None:
            res = ct.c_double()
            self.transport.call("GetResolution", self.index, ct.byref(res))
            self._resolution_s = res.value * 1e-12
        return self._resolution_s

    @property
    def record_type(self) -> int:
        """PTU record type of this device's T3 records (TimeHarp 260: PICO and NANO differ)."""
        return self.family.record_type_of(self.hw_model)

    def sync_rate_hz(self) -> int:
        r = ct.c_int()
        self.transport.call("GetSyncRate", self.index, ct.byref(r))
        return r.value

    # ---- measuring -------------------------------------------------------------------------------
    def start(self) -> None:
        self.transport.call("StartMeas", self.index, ACQ_TIME_MS)
        self._running = True

    def stop(self) -> None:
        self.transport.call("StopMeas", self.index)
        self._running = False

    def flags(self) -> Flag:
        f = ct.c_int()
        self.transport.call("GetFlags", self.index, ct.byref(f), quiet=True)
        return Flag(f.value & 0x7F)

    def read_into(self, buffer) -> int:
        """``*_ReadFiFo`` into ``buffer`` (a ctypes ``c_uint`` array of at least ``ttreadmax``
        records); returns the records read (0 when none waited)."""
        n = ct.c_int()
        if self.family.readfifo_count:
            self.transport.call("ReadFiFo", self.index, buffer, len(buffer), ct.byref(n), quiet=True)
        else:
            self.transport.call("ReadFiFo", self.index, buffer, ct.byref(n), quiet=True)
        if not 0 <= n.value <= len(buffer):
            raise DeviceError(f"{self.family.prefix}_ReadFiFo returned {n.value} records into a "
                              f"buffer of {len(buffer)}")
        return n.value

    def reconnect(self, timeout_s: float = 5.0) -> None:
        """Close and reopen the same device (by serial), re-initialise and re-apply the settings;
        DeviceError if it is not back within ``timeout_s``."""
        try:
            self.transport.call("CloseDevice", self.index, quiet=True)
        except PicoQuantError:
            pass           # it is gone: closing can fail
        deadline = time.monotonic() + timeout_s
        last = None
        while True:
            try:
                self.index, _ = self._find(self.transport, self.serial or None)
                self.initialize()
                if self._settings is not None:
                    self.configure(self._settings)
                return
            except DeviceError as exc:
                last = exc
            if time.monotonic() > deadline:
                raise DeviceError(f"{self.family.model} {self.serial} did not come back within "
                                  f"{timeout_s:g} s ({last})")
            time.sleep(0.05)

    def reader(self, **options) -> "PicoQuantReader":
        return PicoQuantReader(self, **options)

    def close(self) -> None:
        try:
            if self._running:
                self.stop()
        finally:
            self.transport.call("CloseDevice", self.index, quiet=True)


class PicoQuantReader(TaggerReader):
    """Reads a PicoQuant device in a thread: the ``*_ReadFiFo`` loop, decoding, in-band loss.

    FIFO full (``Flag.FIFOFULL``) halts a PicoQuant measurement: the records still in the FIFO are
    read, then a LOST event (count unknown) goes into the stream at the last decoded sync, the
    measurement is stopped and started again (the sync counter restarts; syncs are offset so they
    keep increasing) and the session re-acquires what the hole touched. A failed USB bulk read
    does the same; a device that went away is reopened (same serial) first. Arguments as
    ``TaggerReader`` (``buffer_bytes`` is ignored: the buffer holds the family's ``ttreadmax``).
    """

    def __init__(self, tagger: PicoQuantTagger, **options):
        options.pop("buffer_bytes", None)
        super().__init__(tagger, buffer_bytes=512, **options)
        self._cbuf = (ct.c_uint * tagger.family.ttreadmax)()
        self._view = np.ctypeslib.as_array(self._cbuf)
        self.stats.update({"fifo_full": 0, "usb_errors": 0})

    def step(self) -> None:
        t = self.tagger
        try:
            n = t.read_into(self._cbuf)
            if n:
                self._deliver(self._view[:n])
                return
            if Flag.FIFOFULL in t.flags():
                # the FIFO can have filled up after the empty read above (a host busy elsewhere
                # between the two calls): what it holds is read before the restart clears it
                n = t.read_into(self._cbuf)
                if n:
                    self._deliver(self._view[:n])
                    return
                self.stats["fifo_full"] += 1
                log.warning("%s FIFO full: records lost; restarting the measurement", t.family.model)
                self._restart("fifo")
                return
        except PicoQuantError as exc:
            if exc.device_gone:
                log.warning("%s went away (%s): reopening", t.family.model, exc)
                self._lost(self._gap_sync(), 0, restart=True)
                t.reconnect(timeout_s=self.reconnect_timeout_s)
                t.start()
                self.stats["reconnects"] += 1
                self._restart_session()
                return
            if exc.code == LibError.USB_BULKRD_FAIL:
                self.stats["usb_errors"] += 1
                log.warning("%s: %s; restarting the measurement", t.family.model, exc)
                self._restart("usb")
                return
            raise
        self._stop.wait(IDLE_SLEEP_S)

    def _deliver(self, records: np.ndarray) -> None:
        if self.tap is not None:
            self.tap.on_records(records)
        self._push(decode_t3(records, self.state))
        self.stats["records"] += int(records.size)

    def _restart(self, why: str) -> None:
        """Loss of unknown size at the last decoded sync; stop, start, continue syncs after it."""
        self._lost(self._gap_sync(), 0, restart=True)
        try:
            self.tagger.stop()
        except PicoQuantError as exc:
            log.debug("StopMeas after %s failed: %s", why, exc)
        self.tagger.start()
        self.stats["restarts"] += 1
        self._restart_session()


__all__ = ["PicoQuantTagger", "PicoQuantReader", "list_devices", "ACQ_TIME_MS"]
