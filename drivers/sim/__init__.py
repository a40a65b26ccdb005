"""Simulated photon world and simulated devices.

``load_scene`` builds a scene (built-in or from a depth image) with its truth; ``PhotonWorld``
produces the detections the devices would deliver; ``VirtualClock`` keeps simulated time.

Importing this package registers the simulated devices' pyserial URL handlers (``galvosim://``),
so ``serial.serial_for_url`` and ``Galvo.open`` reach them by the same path as a real port; the real
drivers never import the simulator, so a process that only drives hardware keeps pyserial as it is.
"""

import serial

from spdepth.drivers.lazy import lazy_attributes

_LAZY = {"EFFECTS": "scene", "Scene": "scene", "SceneSettings": "scene", "load_scene": "scene",
         "scene_names": "scene", "PhotonWorld": "world", "VirtualClock": "world", "warm_up": "world"}
"""Names loaded on first use: the scene and the photon world need numpy, scipy and numba, which a
process that only reads the fault kinds or the scene list (``spdepth --help``) does not."""

__getattr__ = lazy_attributes(__name__, _LAZY)

__all__ = ["EFFECTS", "PhotonWorld", "Scene", "SceneSettings", "VirtualClock", "load_scene",
           "register_url_handlers", "scene_names", "warm_up"]


def register_url_handlers() -> None:
    """Let pyserial open ``galvosim://`` URLs (module ``drivers.sim.protocol_galvosim``).
    Idempotent; runs when ``drivers.sim`` (or any of its modules) is first imported."""
    if __name__ not in serial.protocol_handler_packages:
        serial.protocol_handler_packages.append(__name__)


register_url_handlers()
