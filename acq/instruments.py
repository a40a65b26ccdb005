"""Opening the instruments a session drives: the simulated bench (a scene behind the real drivers)
or real devices, each giving a galvo, a tagger and the facts a plan and a recording need."""

from __future__ import annotations

import itertools
import logging
from dataclasses import dataclass, field

from spdepth.acq.errors import RequestError
from spdepth.acq.plan import ScanPlan
from spdepth.acq.requests import DEFAULT_WINDOW_S

log = logging.getLogger(__name__)

SIM_TAGGER_URL = "usb:1209:7a64"
SIM_EVENT_DIVIDER = 64
"""Simulated Swabian tagger: sync event divider (exercises the divider path; fewer sync tags)."""
DWELL_LIMIT_FACTOR = 20
"""Simulated gated scans: dwell limit in units of the dwell that gives the scene's mean ppp."""

_names = itertools.count()


@dataclass
class Instruments:
    """A galvo and a tagger, opened; ``close()`` releases both (and a simulated bench).

    sync_period_s: the laser period (for the recording header; real devices: from the caller).
    scene:         the simulated scene (None for real devices), with its truth.
    """

    galvo: object
    tagger: object
    sync_period_s: float | None
    scene: object = None
    rig: object = None
    info: dict = field(default_factory=dict)
    _name: str | None = None
    _link: object = None
    _standins: tuple = ()

    def close(self) -> None:
        for dev in (self.galvo, self.tagger, self._link, *self._standins):
            if dev is None:
                continue
            try:
                dev.close()
            except Exception as exc:  # noqa: BLE001 - closing one must not keep the other open
                log.warning("closing %s failed: %s", type(dev).__name__, exc)
        if self._name is not None:
            from spdepth.drivers.sim import galvo_fw

            galvo_fw.unregister(self._name)
            self._name = None

    def __enter__(self) -> "Instruments":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def full_plan(self, shape: tuple[int, int], **kwargs) -> ScanPlan:
        """A plan over the whole simulated field of view (pixel centres of an H x W grid)."""
        h, w = shape
        if self.rig is None:
            raise RequestError("full_plan needs the simulated bench; give angles for real devices")
        x0, y0 = self.rig.fov.centre_deg(0, 0, (h, w))
        x1, y1 = self.rig.fov.centre_deg(h - 1, w - 1, (h, w))
        return ScanPlan(w, h, x0, x1, y0, y1, **kwargs)


def _sim_rig(scene_name: str, shape: tuple[int, int], *, ppp: float, sbr: float | None, seed: int,
             window_s: tuple[float, float], keep_truth: bool, **scene_settings):
    """The scene and the rig of a simulated bench, its world's kernels loaded (compiled on a fresh
    install) before any scan can start."""
    from spdepth.drivers.sim import PhotonWorld, load_scene, warm_up
    from spdepth.drivers.sim.rig import SimRig

    scene = load_scene(scene_name, shape, ppp=float(ppp), sbr=sbr, tagger_range_s=window_s[1],
                       **scene_settings)
    warm_up()
    return scene, SimRig(PhotonWorld(scene, seed=seed), keep_truth=keep_truth)


def open_sim(scene_name: str = "bust", shape: tuple[int, int] = (64, 64), *, ppp: float = 15.0,
             sbr: float | None = 10.0, seed: int = 0, faults: str = "",
             window_s: tuple[float, float] = DEFAULT_WINDOW_S, keep_truth: bool = False,
             galvo_link: str = "url", tagger_options: dict | None = None,
             galvo_options: dict | None = None, tagger: str = "", galvo: str = "",
             **scene_settings) -> Instruments:
    """The simulated bench: a scene, its photon world and rig, the galvo emulator on a
    ``galvosim://`` URL and the tagger on the simulated pyusb backend, opened through the real
    drivers. ``faults`` as in ``drivers.sim.faults`` (galvo and tagger kinds mixed). The tagger
    records ``window_s`` after each sync (default the scan's default window), so ``sbr`` is what
    the estimators see.
    keep_truth: the rig keeps every dwell's photons (``rig.truth``) for tests.
    galvo_link: "url" (pyserial URL handler) or "pty" (a real tty from a pty pair, POSIX).
    tagger_options: more arguments of ``SimTaggerBackend`` (e.g. ``vanish_s``).
    galvo_options: more arguments of ``GalvoFirmware`` (e.g. ``pace``: real seconds per virtual
           second of dwell, so a scan takes wall time as a real one would).
    tagger, galvo: vendor device strings (``picoquant:mh150``, ``nidaq:Dev1``): the bench is then
           reached through that vendor's driver and a stand-in of its library or package
           (:func:`_open_sim_vendor`); "" keeps our own devices."""
    if tagger or galvo:
        return _open_sim_vendor(scene_name, shape, ppp=ppp, sbr=sbr, seed=seed, faults=faults,
                                window_s=window_s, keep_truth=keep_truth, tagger=tagger,
                                galvo=galvo, galvo_link=galvo_link, tagger_options=tagger_options,
                                galvo_options=galvo_options, **scene_settings)
    from spdepth.drivers.galvo import Galvo
    from spdepth.drivers.sim import galvo_fw
    from spdepth.drivers.sim.faults import GALVO_FAULTS, TAGGER_FAULTS, parse_faults
    from spdepth.drivers.sim.tagger_usb import SimTaggerBackend
    from spdepth.drivers.tagger import Tagger, TaggerSettings

    h, w = shape
    parsed = parse_faults(faults)
    if any(f.kind.value == "daq-underflow" for f in parsed):
        from spdepth.drivers.errors import SettingError

        raise SettingError("daq-underflow needs --galvo nidaq:DEV")
    scene, rig = _sim_rig(scene_name, shape, ppp=ppp, sbr=sbr, seed=seed, window_s=window_s,
                          keep_truth=keep_truth, **scene_settings)
    name = f"spdepth-sim-{next(_names)}"
    fw = galvo_fw.GalvoFirmware(rig, faults=[f for f in parsed if f.kind in GALVO_FAULTS],
                                **(galvo_options or {}))
    galvo_fw.register_device(name, fw)
    galvo = tagger = link = None
    try:
        if galvo_link == "pty":
            from spdepth.drivers.sim.pty_link import PtyLink

            link = PtyLink(fw)
            galvo = Galvo.open(link.start())
        else:
            galvo = Galvo.open(f"galvosim://{name}")
        backend = SimTaggerBackend(rig, faults=[f for f in parsed if f.kind in TAGGER_FAULTS],
                                   scan_pixels=h * w, **(tagger_options or {}))
        tagger = Tagger.open(SIM_TAGGER_URL, backend=backend)
        tagger.configure(TaggerSettings())
    except BaseException:
        if galvo is not None:
            galvo.close()
        if link is not None:
            link.close()
        galvo_fw.unregister(name)
        raise
    info = {"scene": scene_name, "shape": [h, w], "ppp": ppp, "sbr": scene.settings.sbr,
            "seed": seed, "faults": faults, "pulse_rms_s": scene.pulse_rms_s}
    return Instruments(galvo, tagger, scene.settings.sync_period_s, scene, rig, info, name, link)


def _open_sim_vendor(scene_name, shape, *, ppp, sbr, seed, faults, window_s, keep_truth, tagger,
                     galvo, galvo_link, tagger_options, galvo_options, **scene_settings) -> Instruments:
    """The simulated bench behind vendor drivers: a PicoQuant stand-in library (compiled from C,
    fed by the photon world) and/or a stand-in ``nidaqmx`` module moving the rig's mirror. The
    side not named uses our own simulated device. Faults: tagger kinds go to the tagger side,
    ``daq-underflow`` to the NI-DAQ galvo, the other galvo kinds to our galvo emulator."""
    from spdepth.acq.requests import parse_galvo, parse_tagger
    from spdepth.drivers.errors import SettingError
    from spdepth.drivers.sim import galvo_fw
    from spdepth.drivers.sim.faults import GALVO_FAULTS, TAGGER_FAULTS, FaultKind, parse_faults

    h, w = shape
    scene, rig = _sim_rig(scene_name, shape, ppp=ppp, sbr=sbr, seed=seed, window_s=window_s,
                          keep_truth=keep_truth, **scene_settings)
    parsed = parse_faults(faults)
    t_faults = [f for f in parsed if f.kind in TAGGER_FAULTS]
    daq_faults = [f for f in parsed if f.kind == FaultKind.DAQ_UNDERFLOW]
    g_faults = [f for f in parsed if f.kind in GALVO_FAULTS and f.kind != FaultKind.DAQ_UNDERFLOW]
    if galvo and g_faults:
        raise SettingError(f"faults {', '.join(str(f) for f in g_faults)} are our serial galvo's; "
                           "the NI-DAQ galvo injects daq-underflow")
    if not galvo and daq_faults:
        raise SettingError("daq-underflow needs --galvo nidaq:DEV")
    standins: list = []
    name = None
    g = t = link = None
    try:
        if galvo:
            from spdepth.drivers.daq import DaqCalibration, DaqGalvo
            from spdepth.drivers.sim.nidaqmx_standin import NiDaqmxStandIn

            addr = parse_galvo(galvo)
            cal = DaqCalibration()
            module = NiDaqmxStandIn(rig, addr.device, deg_per_volt=cal.deg_per_volt_x,
                                    faults=daq_faults, scan_pixels=h * w)
            g = DaqGalvo.open(f"{addr.device}/{addr.ao}", nidaqmx=module, calibration=cal)
        else:
            from spdepth.drivers.galvo import Galvo

            name = f"spdepth-sim-{next(_names)}"
            fw = galvo_fw.GalvoFirmware(rig, faults=g_faults, **(galvo_options or {}))
            galvo_fw.register_device(name, fw)
            g = Galvo.open(f"galvosim://{name}")
        addr = parse_tagger(tagger) if tagger else None
        if addr is not None and addr.kind == "swabian":
            from spdepth.drivers.sim.swabian_standin import SwabianStandIn
            from spdepth.drivers.swabian import SwabianSettings, SwabianTagger

            module = SwabianStandIn(rig, addr.serial or "2138000ABC", faults=t_faults,
                                    scan_pixels=h * w, **(tagger_options or {}))
            t = SwabianTagger.open(addr.serial or None, SwabianSettings(
                sync_period_s=scene.settings.sync_period_s, event_divider=SIM_EVENT_DIVIDER,
                resolution_ps=int(round(scene.settings.resolution_s * 1e12))), module=module)
        elif addr is not None:
            from spdepth.drivers.picoquant import PicoQuantSettings, PicoQuantTagger
            from spdepth.drivers.sim.picoquant_standin import PicoQuantStandIn

            sim = PicoQuantStandIn(rig, addr.model, serial=addr.serial or "1000042",
                                   faults=t_faults, scan_pixels=h * w, **(tagger_options or {}))
            standins.append(sim)
            t = PicoQuantTagger.open(addr.model, addr.serial or None, lib=sim.path)
            t.configure(PicoQuantSettings())
        else:
            from spdepth.drivers.sim.tagger_usb import SimTaggerBackend
            from spdepth.drivers.tagger import Tagger, TaggerSettings

            backend = SimTaggerBackend(rig, faults=t_faults, scan_pixels=h * w,
                                       **(tagger_options or {}))
            t = Tagger.open(SIM_TAGGER_URL, backend=backend)
            t.configure(TaggerSettings())
    except BaseException:
        for dev in (g, t, *standins):
            if dev is not None:
                try:
                    dev.close()
                except Exception as exc:  # noqa: BLE001 - the first error is the one to report
                    log.warning("closing %s failed: %s", type(dev).__name__, exc)
        if name is not None:
            galvo_fw.unregister(name)
        raise
    info = {"scene": scene_name, "shape": [h, w], "ppp": ppp, "sbr": scene.settings.sbr,
            "seed": seed, "faults": faults, "pulse_rms_s": scene.pulse_rms_s,
            "tagger": tagger or SIM_TAGGER_URL, "galvo": galvo or "galvosim"}
    return Instruments(g, t, scene.settings.sync_period_s, scene, rig, info, name, link,
                       tuple(standins))


def open_devices(devices) -> Instruments:
    """Real devices named by an ``acq.requests.Devices``: our serial galvo or an NI-DAQ galvo, our
    USB tagger or a PicoQuant device. A missing library or device raises ``DeviceError`` (one line
    naming it and how to install it)."""
    from spdepth.acq.requests import parse_galvo, parse_tagger

    t_addr, g_addr = parse_tagger(devices.tagger), parse_galvo(devices.galvo)
    sync_period_s = 1.0 / devices.sync_rate_hz
    if t_addr.kind == "usb" and g_addr.kind == "serial":
        return open_real(devices.galvo, devices.tagger, sync_period_s)
    galvo = tagger = None
    try:
        # the tagger first: its vendor library is the likelier thing to be missing
        if t_addr.kind == "swabian":
            from spdepth.drivers.swabian import SwabianSettings, SwabianTagger

            tagger = SwabianTagger.open(t_addr.serial or None, SwabianSettings(
                sync_period_s=sync_period_s, event_divider=devices.event_divider))
        elif t_addr.kind == "picoquant":
            from spdepth.drivers.picoquant import PicoQuantSettings, PicoQuantTagger

            tagger = PicoQuantTagger.open(t_addr.model, t_addr.serial or None,
                                          lib_path=devices.picoquant_lib or None)
            tagger.configure(PicoQuantSettings())
        else:
            from spdepth.drivers.tagger import Tagger, TaggerSettings

            tagger = Tagger.open(devices.tagger)
            tagger.stop()
            tagger.configure(TaggerSettings())
        if g_addr.kind == "nidaq":
            from spdepth.drivers.daq import DaqCalibration, DaqGalvo

            cal = DaqCalibration(devices.deg_per_volt, devices.deg_per_volt, -devices.v_limit,
                                 devices.v_limit, tuple(devices.park_deg))
            galvo = DaqGalvo.open(f"{g_addr.device}/{g_addr.ao}", calibration=cal)
        else:
            from spdepth.drivers.galvo import Galvo

            galvo = Galvo.open(g_addr.port)
    except BaseException:
        for dev in (galvo, tagger):
            if dev is not None:
                try:
                    dev.close()
                except Exception as exc:  # noqa: BLE001
                    log.warning("closing %s failed: %s", type(dev).__name__, exc)
        raise
    return Instruments(galvo, tagger, sync_period_s,
                       info={"galvo": devices.galvo, "tagger": devices.tagger})


def open_real(galvo_port: str, tagger_url: str, sync_period_s: float,
              tagger_settings=None) -> Instruments:
    """Real devices: a galvo on a serial port and a tagger at ``usb:VID:PID``, configured with
    ``tagger_settings`` (default ``TaggerSettings()``: 8 ps units, every marker input enabled on
    the rising edge, so the galvo's pixel, line and frame markers reach the stream)."""
    from spdepth.drivers.galvo import Galvo
    from spdepth.drivers.tagger import Tagger, TaggerSettings

    galvo = Galvo.open(galvo_port)
    try:
        tagger = Tagger.open(tagger_url)
        try:
            tagger.stop()            # a previous run may have left it measuring
            tagger.configure(tagger_settings or TaggerSettings())
        except BaseException:
            tagger.close()
            raise
    except BaseException:
        galvo.close()
        raise
    return Instruments(galvo, tagger, sync_period_s, info={"galvo": galvo_port, "tagger": tagger_url})


def sim_plan(inst: Instruments, shape, *, mode: str = "gated", target: int = 15,
             dwell_s: float | None = None, **kwargs) -> ScanPlan:
    """A plan for the simulated bench: gated scans get a dwell limit of DWELL_LIMIT_FACTOR times
    the scene's pixel dwell (dark pixels must not hold the scan), raster scans the scene's dwell
    (about ``ppp`` detections a frame)."""
    if dwell_s is None:
        dwell_s = inst.scene.dwell_s * (DWELL_LIMIT_FACTOR if mode == "gated" else 1)
    return inst.full_plan(shape, mode=mode, target=target, dwell_s=dwell_s, **kwargs)


__all__ = ["Instruments", "open_sim", "open_real", "open_devices", "sim_plan"]
