"""The stand-in PicoQuant library, built and driven by the simulated bench.

``build_library("mh150")`` compiles ``picoquant_standin.c`` with the system C compiler into a
cache folder (once per source and flags) and returns the path of the family's library file
(``libmh150.so``, ``libhh400.so``, ``th260lib.so``, ``libph330.so``);
``PicoQuantStandIn(rig)`` loads it, adds a device and runs a pump thread that turns the photon
world's events (``SimRig``: the galvo's markers and every dwell's photons) into T3 records and
pushes them into the library's FIFO while a measurement runs. The driver
(``drivers.picoquant.PicoQuantTagger``) then opens the same library file through ctypes exactly as
it opens the vendor's.

Faults (``drivers.sim.faults`` kinds, WHEN as there): ``fifo-overflow`` (the FIFO overruns: FIFO
full flag, measurement halted), ``device-vanish`` (the device leaves for ``vanish_s`` wall-clock
seconds; calls fail with DEVICE_NOT_OPEN, opening fails until it is back), ``usb-timeout`` (one
``ReadFiFo`` fails with USB_BULKRD_FAIL: the library's view of a USB error). ``partial-read`` cannot
happen through the library (it hands over whole records) and is refused.

The library keeps its devices in process-wide state (one ``dlopen`` handle per path): one
stand-in at a time per process; a new one resets the previous.
"""

from __future__ import annotations

import ctypes as ct
import hashlib
import os
import shutil
import subprocess
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from spdepth.drivers.errors import DeviceError, SettingError
from spdepth.drivers.events import EventKind
from spdepth.drivers.picoquant.protocol import FAMILIES
from spdepth.drivers.sim.faults import FaultKind, FaultSchedule, TAGGER_FAULTS, parse_faults
from spdepth.drivers.tagger.t3 import T3EncoderState, encode_t3

SOURCE = Path(__file__).with_name("picoquant_standin.c")
CACHE_ENV = "SPDEPTH_STANDIN_CACHE"
"""Folder the compiled stand-ins are cached in (default: the system temp folder)."""
_BUILD = {
    "mh150": ["-DPFX=MH", "-DTRG_EDGE"],
    "mh160": ["-DPFX=MH", "-DTRG_EDGE"],
    "hh400": ["-DPFX=HH", "-DREADFIFO_COUNT", "-DTRG_CFD"],
    "th260": ["-DPFX=TH260", "-DREADFIFO_COUNT", "-DTRG_BY_MODEL", "-DINIT_NO_REFSOURCE",
              "-DMAXDEVNUM=4", "-DSYNCDIVMAX=8"],
    "ph330": ["-DPFX=PH330", "-DTRG_SELECTABLE", "-DSYNCDIVMAX=8"],
}
"""Compiler flags of each family's build (what each flag means: the C source's head)."""
MODELS = {"mh150": "MultiHarp 150 4N", "mh160": "MultiHarp 160", "hh400": "HydraHarp 400",
          "th260": "TimeHarp 260 P", "ph330": "PicoHarp 330"}
"""``*_GetHardwareInfo`` model of the simulated device, per family (TimeHarp 260: the PICO unless
``hw_model`` says ``TimeHarp 260 N``)."""
_HOOK = ct.CFUNCTYPE(None, ct.c_int)
_build_lock = threading.Lock()
_active: "PicoQuantStandIn | None" = None


def build_library(family_key: str = "mh150", cache_dir: str | os.PathLike | None = None) -> Path:
    """Compile the stand-in for ``family_key`` (cached by the source's hash and the flags)."""
    if family_key not in _BUILD:
        raise SettingError(f"no PicoQuant stand-in for {family_key!r} (have: {', '.join(_BUILD)})")
    name, flags = FAMILIES[family_key].libraries[0], _BUILD[family_key]
    src = SOURCE.read_bytes()
    key = hashlib.sha256(src + " ".join(flags).encode()).hexdigest()[:16]
    root = Path(cache_dir or os.environ.get(CACHE_ENV) or tempfile.gettempdir())
    out_dir = root / f"spdepth-pq-standin-{key}"
    out = out_dir / name
    with _build_lock:
        if out.is_file():
            return out
        cc = os.environ.get("CC") or shutil.which("cc") or shutil.which("gcc")
        if cc is None:
            raise DeviceError("no C compiler (cc/gcc) to build the PicoQuant stand-in library")
        out_dir.mkdir(parents=True, exist_ok=True)
        tmp = out_dir / f".{name}.{os.getpid()}"
        proc = subprocess.run([cc, "-shared", "-fPIC", "-O2", "-Wall", "-Werror", *flags,
                               "-o", str(tmp), str(SOURCE)], capture_output=True, text=True)
        if proc.returncode:
            raise DeviceError(f"building the PicoQuant stand-in failed: {proc.stderr.strip()}")
        os.replace(tmp, out)
    return out


class PicoQuantStandIn:
    """A simulated PicoQuant device behind the stand-in library, fed by ``rig``.

    rig:          a ``drivers.sim.rig.SimRig`` (the galvo side pulses markers and dwells on it).
    family_key:   ``mh150``, ``mh160``, ``hh400``, ``th260`` or ``ph330``.
    hw_model:     the model the device reports (default ``MODELS[family_key]``).
    serial:       the device's serial number (8 characters at most).
    fifo_records: the device FIFO's depth.
    faults:       a ``KIND@WHEN`` spec or a list of ``Fault`` (tagger kinds, see the module).
    scan_pixels:  pixels of the scan, for faults given as a share of it.
    overflow_records, vanish_s: the size of an injected overrun and how long a vanish lasts.
    """

    def __init__(self, rig, family_key: str = "mh150", *, serial: str = "1000042",
                 hw_model: str | None = None,
                 fifo_records: int = 1 << 22, faults=None, scan_pixels: int | None = None,
                 overflow_records: int = 1000, vanish_s: float = 0.2, cache_dir=None):
        global _active
        self.rig = rig
        self.family_key = family_key
        self.path = build_library(family_key, cache_dir)
        self.lib = ct.CDLL(str(self.path))
        self._sig()
        if _active is not None:
            _active.close()
        _active = self
        self.lib.SIM_RemoveAll()
        res_ps = rig.world.scene.settings.resolution_s * 1e12
        model = hw_model or MODELS[family_key]
        self.dev = self.lib.SIM_AddDevice(serial.encode(), model.encode(), res_ps, 1, fifo_records)
        if self.dev < 0:
            raise DeviceError("the PicoQuant stand-in could not add a device")
        self._lock = threading.RLock()
        self._enc = T3EncoderState()
        self._hooks = (_HOOK(self._on_start), _HOOK(self._on_stop))   # kept: C holds pointers
        self.lib.SIM_SetHooks(*self._hooks)
        faults = parse_faults(faults, TAGGER_FAULTS) if isinstance(faults, str) or faults is None \
            else list(faults)
        if any(f.kind == FaultKind.PARTIAL_READ for f in faults):
            raise SettingError("partial-read cannot happen through the PicoQuant library (its "
                               "ReadFiFo hands over whole records)")
        if any(f.at_fraction is not None for f in faults) and not scan_pixels:
            raise SettingError("faults given as a share of the scan need scan_pixels")
        for f in faults:
            if f.kind == FaultKind.FIFO_OVERFLOW:
                if f.at_fraction is not None:
                    rig.schedule_overflow(overflow_records,
                                          at_pixel=max(1, int(f.at_fraction * scan_pixels)))
                else:
                    rig.schedule_overflow(overflow_records, at_s=f.at_s)
        self.schedule = FaultSchedule([f for f in faults if f.kind != FaultKind.FIFO_OVERFLOW])
        self.scan_pixels = scan_pixels
        self.vanish_s = float(vanish_s)
        self._back_at: float | None = None
        self.fired: list[str] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._pump, name="pq-standin-pump", daemon=True)
        self._thread.start()

    def _sig(self) -> None:
        L = self.lib
        L.SIM_AddDevice.argtypes = [ct.c_char_p, ct.c_char_p, ct.c_double, ct.c_int, ct.c_long]
        L.SIM_AddDevice.restype = ct.c_int
        L.SIM_Push.argtypes = [ct.c_int, ct.POINTER(ct.c_uint), ct.c_int]
        L.SIM_Push.restype = ct.c_int
        L.SIM_SetHooks.argtypes = [_HOOK, _HOOK]
        L.SIM_SetHooks.restype = None
        for name in ("SIM_Binning", "SIM_Measuring"):
            getattr(L, name).argtypes = [ct.c_int]
            getattr(L, name).restype = ct.c_int
        L.SIM_Dropped.argtypes = [ct.c_int]
        L.SIM_Dropped.restype = ct.c_longlong
        for name in ("SIM_Plug", "SIM_FailReads", "SIM_SetFeatures"):
            getattr(L, name).argtypes = [ct.c_int, ct.c_int]
            getattr(L, name).restype = None
        L.SIM_FifoFull.argtypes = [ct.c_int]
        L.SIM_FifoFull.restype = None
        L.SIM_RemoveAll.restype = None

    # ---- called from the library (the caller's thread, inside StartMeas/StopMeas) -------------
    def _on_start(self, dev: int) -> None:
        with self._lock:
            self.rig.clear_fifo()
            self.rig.start_tagger()
            self._enc = T3EncoderState(sync_base=self.rig.sync)   # the device counts syncs from 0

    def _on_stop(self, dev: int) -> None:
        with self._lock:
            self.rig.stop_tagger()

    # ---- the device's acquisition ----------------------------------------------------------------
    def _pump(self) -> None:
        while not self._stop.is_set():
            self._faults()
            if not self.rig.wait_for_events(0.01):
                continue
            with self._lock:
                ev = self.rig.read_events(1 << 16)
                if ev.size == 0 or not self.lib.SIM_Measuring(self.dev):
                    continue
                lost = np.flatnonzero(ev["kind"] == EventKind.LOST)
                if lost.size:
                    self._push(ev[:lost[0]])
                    self.lib.SIM_FifoFull(self.dev)     # the hardware FIFO overran: halted
                    self.fired.append("fifo-overflow")
                    continue
                self._push(ev)

    def _push(self, ev: np.ndarray) -> None:
        if ev.size == 0:
            return
        shift = self.lib.SIM_Binning(self.dev)
        if shift:
            ev = ev.copy()
            photons = ev["kind"] == EventKind.PHOTON
            ev["dtime"][photons] >>= shift
        recs = np.ascontiguousarray(encode_t3(ev, self._enc), dtype=np.uint32)
        self.lib.SIM_Push(self.dev, recs.ctypes.data_as(ct.POINTER(ct.c_uint)), int(recs.size))

    def _faults(self) -> None:
        if self._back_at is not None and time.monotonic() >= self._back_at:
            self._back_at = None
            self.lib.SIM_Plug(self.dev, 1)
        frac = self.rig.pixels_pulsed / self.scan_pixels if self.scan_pixels else None
        for f in self.schedule.take_due(self.rig.now_s, frac):
            self.fired.append(f.kind.value)
            if f.kind == FaultKind.DEVICE_VANISH:
                with self._lock:
                    self.lib.SIM_Plug(self.dev, 0)
                self._back_at = time.monotonic() + self.vanish_s
            elif f.kind == FaultKind.USB_TIMEOUT:
                self.lib.SIM_FailReads(self.dev, 1)

    @property
    def dropped_records(self) -> int:
        return int(self.lib.SIM_Dropped(self.dev))

    def close(self) -> None:
        global _active
        self._stop.set()
        if self._thread.is_alive() and self._thread is not threading.current_thread():
            self._thread.join(2.0)
        if _active is self:
            _active = None
            self.lib.SIM_SetHooks(_HOOK(), _HOOK())


__all__ = ["PicoQuantStandIn", "build_library", "SOURCE", "CACHE_ENV", "MODELS"]
