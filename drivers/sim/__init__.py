"""Simulated photon world and simulated devices.

``load_scene`` builds a scene (built-in or from a depth image) with its truth; ``PhotonWorld``
produces the detections the devices would deliver; ``VirtualClock`` keeps simulated time.
"""

from drivers.sim.scene import EFFECTS, Scene, SceneSettings, load_scene, scene_names
from drivers.sim.world import PhotonWorld, VirtualClock

__all__ = ["EFFECTS", "PhotonWorld", "Scene", "SceneSettings", "VirtualClock", "load_scene",
           "scene_names"]
