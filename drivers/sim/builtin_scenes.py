"""The built-in scenes' names (``drivers.sim.scenes.BUILTIN`` maps each to its geometry). Apart
from the scenes so that listing them (``spdepth --help``, the window's scene picker) loads no
numpy."""

BUILTIN_SCENES = ("bust", "steps", "tilted-plane", "two-layer", "daylight")
"""Every built-in scene, in the order the docs list them; ``file:PATH`` loads a depth image."""
