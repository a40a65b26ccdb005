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

    def close(self) -> None:
        for dev in (self.galvo, self.tagger, self._link):
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


def open_sim(scene_name: str = "bust", shape: tuple[int, int] = (64, 64), *, ppp: float = 15.0,
             sbr: float | None = 10.0, seed: int = 0, faults: str = "",
             window_s: tuple[float, float] = DEFAULT_WINDOW_S, keep_truth: bool = False,
             galvo_link: str = "url", tagger_options: dict | None = None,
             galvo_options: dict | None = None,
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
           second of dwell, so a scan takes wall time as a real one would)."""
    from spdepth.drivers.galvo import Galvo
    from spdepth.drivers.sim import PhotonWorld, galvo_fw, load_scene
    from spdepth.drivers.sim.faults import GALVO_FAULTS, TAGGER_FAULTS, parse_faults
    from spdepth.drivers.sim.rig import SimRig
    from spdepth.drivers.sim.tagger_usb import SimTaggerBackend
    from spdepth.drivers.tagger import Tagger, TaggerSettings

    h, w = shape
    scene = load_scene(scene_name, (h, w), ppp=float(ppp), sbr=sbr, tagger_range_s=window_s[1],
                       **scene_settings)
    rig = SimRig(PhotonWorld(scene, seed=seed), keep_truth=keep_truth)
    parsed = parse_faults(faults)
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


__all__ = ["Instruments", "open_sim", "open_real", "sim_plan"]
