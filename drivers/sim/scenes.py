"""Built-in scene geometries, each with its truth, and depth images loaded from files.

Every builder takes the image shape (H, W) and returns a ``Geometry``: per-surface depth,
reflectivity and occupancy, shape (K, H, W), and a relative background map (H, W). Builders are
pure functions of the shape, so the truth of a built-in scene is the same on every machine.
``rows=(r0, r1)`` builds only the rows r0..r1-1 of that image (shape (K, r1 - r0, W)), with each
pixel's values the same as in the whole image's: a large simulated frame is built row band by
row band as the galvo reaches it (``drivers.sim.scene.LazyScene``).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from spdepth.drivers.errors import SettingError
from spdepth.drivers.sim.builtin_scenes import BUILTIN_SCENES


@dataclass(frozen=True, eq=False)
class Geometry:
    """What is there, before any light is scaled.

    depth_m:      (K, H, W) distance of surface k at each pixel, metres.
    reflectivity: (K, H, W) relative reflectivity of surface k (any non-negative scale; the
                  scene's ``ppp`` and ``sbr`` set the absolute flux).
    occupancy:    (K, H, W) fraction of the pixel's footprint covered by surface k (edges,
                  panes); surface k's signal strength is reflectivity * occupancy.
    background:   (H, W) relative ambient background (any positive scale).
    defaults:     scene-specific default settings (e.g. ``sbr`` for daylight).
    """

    depth_m: np.ndarray
    reflectivity: np.ndarray
    occupancy: np.ndarray
    background: np.ndarray
    defaults: dict = field(default_factory=dict)


def _band(shape, rows):
    """(r0, r1, band shape) of the rows a builder makes (``rows`` None: all of them)."""
    h, w = shape
    r0, r1 = (0, h) if rows is None else (int(rows[0]), int(rows[1]))
    if not 0 <= r0 < r1 <= h:
        raise SettingError(f"rows {rows} outside a scene of {h} rows")
    return r0, r1, (r1 - r0, w)


def _grid(shape, rows=None):
    """Normalised coordinates: x in [-1, 1] left to right, y in [-1, 1] top to bottom (of the
    rows ``rows`` only, when given)."""
    h, w = shape
    r0, r1, _ = _band(shape, rows)
    y = (np.arange(r0, r1) + 0.5) / h * 2.0 - 1.0
    x = (np.arange(w) + 0.5) / w * 2.0 - 1.0
    return np.meshgrid(x, y)


def _single(depth, refl, background, **defaults) -> Geometry:
    return Geometry(depth[None].astype(np.float64), refl[None].astype(np.float64),
                    np.ones((1,) + depth.shape), background.astype(np.float64), defaults)


def _bust_depth_refl(shape, rows=None):
    """A head on a neck and shoulders in front of a wall, like the seed paper's mannequin."""
    x, y = _grid(shape, rows)
    shape = x.shape
    wall_m = 3.6
    depth = np.full(shape, wall_m)
    refl = np.full(shape, 0.25)
    # Shoulders: a broad flattened ellipsoid low in the frame.
    rs = (x / 0.95) ** 2 + ((y - 1.05) / 0.55) ** 2
    m = rs < 1.0
    depth[m] = 3.2 - 0.15 * np.sqrt(1.0 - rs[m])
    refl[m] = 0.5 + 0.2 * np.sqrt(1.0 - rs[m])
    # Neck: a vertical cylinder.
    rn = (x / 0.17) ** 2
    m = (rn < 1.0) & (y > 0.2) & (y < 0.7)
    depth[m] = 3.1 - 0.06 * np.sqrt(1.0 - rn[m])
    refl[m] = 0.55 + 0.2 * np.sqrt(1.0 - rn[m])
    # Head: an ellipsoid with a nose, brow and eye sockets; reflectivity falls off at grazing view.
    rh = (x / 0.40) ** 2 + ((y + 0.2) / 0.52) ** 2
    m = rh < 1.0
    cos_view = np.sqrt(np.clip(1.0 - rh, 0.0, 1.0))
    face = (3.0 - 0.16 * cos_view
            - 0.045 * np.exp(-((x / 0.07) ** 2 + ((y + 0.12) / 0.14) ** 2))         # nose
            - 0.015 * np.exp(-((x / 0.25) ** 2 + ((y + 0.38) / 0.05) ** 2))         # brow
            + 0.02 * np.exp(-(((np.abs(x) - 0.15) / 0.07) ** 2 + ((y + 0.28) / 0.05) ** 2))  # eyes
            - 0.012 * np.exp(-((x / 0.12) ** 2 + ((y - 0.12) / 0.03) ** 2)))        # lips
    depth[m] = face[m]
    refl[m] = 0.3 + 0.6 * cos_view[m]
    return depth, refl


def bust(shape, rows=None) -> Geometry:
    """A smooth head-like surface at about 3 m before a wall at 3.6 m (the seed paper's target)."""
    depth, refl = _bust_depth_refl(shape, rows)
    return _single(depth, refl, np.ones(depth.shape))


STEP_HEIGHTS_M = (0.001, 0.002, 0.005, 0.01, 0.02, 0.05, 0.1)


def steps(shape, rows=None) -> Geometry:
    """A resolution target: horizontal bands, each alternating between 3 m and 3 m + h in
    column blocks, with h = 1, 2, 5, 10, 20, 50, 100 mm from top to bottom."""
    h, w = shape
    r0, r1, shape = _band(shape, rows)
    band = np.minimum((np.arange(r0, r1) * len(STEP_HEIGHTS_M)) // h, len(STEP_HEIGHTS_M) - 1)
    block = max(1, w // 8)
    raised = ((np.arange(w) // block) % 2 == 1)
    depth = 3.0 + np.asarray(STEP_HEIGHTS_M)[band][:, None] * raised[None, :]
    return _single(depth, np.full(shape, 0.6), np.ones(shape))


def tilted_plane(shape, rows=None) -> Geometry:
    """A plane from 2.5 m (left) to 3.5 m (right), rising 0.2 m from top to bottom."""
    x, y = _grid(shape, rows)
    depth = 3.0 + 0.5 * x + 0.1 * y
    return _single(depth, np.full(x.shape, 0.5), np.ones(x.shape))


def two_layer(shape, rows=None) -> Geometry:
    """A semi-transparent pane at 2 m over the central half of the image, before a wall at
    3.5 m: K = 2 surfaces. The pane reflects 30%; the wall behind it is seen at transmission^2."""
    x, y = _grid(shape, rows)
    shape = x.shape
    pane = (np.abs(x) < 0.5) & (np.abs(y) < 0.5)
    transmission = 0.7
    depth = np.stack([np.full(shape, 2.0), 3.5 + 0.05 * y])
    refl = np.stack([np.full(shape, 0.3), np.where(pane, 0.6 * transmission**2, 0.6)])
    occ = np.stack([pane.astype(np.float64), np.ones(shape)])
    return Geometry(depth, refl, occ, np.ones(shape))


def daylight(shape, rows=None) -> Geometry:
    """The bust in bright daylight: background far above signal (default SBR 0.05), brightest
    at the top (sky) and ten times dimmer at the bottom, with a sunlit patch on the left."""
    x, y = _grid(shape, rows)
    depth, refl = _bust_depth_refl(shape, rows)
    bg = 1.0 + 9.0 * (1.0 - y) / 2.0 + 4.0 * np.exp(-(((x + 0.6) / 0.3) ** 2 + (y / 0.4) ** 2))
    return _single(depth, refl, bg, sbr=0.05)


BUILTIN = dict(zip(BUILTIN_SCENES, (bust, steps, tilted_plane, two_layer, daylight)))
"""Each built-in scene's geometry, by its name (``drivers.sim.builtin_scenes``)."""


def _read_image(path: Path) -> np.ndarray:
    if not path.is_file():
        raise SettingError(f"scene image {path}: file not found")
    suffix = path.suffix.lower()
    try:
        if suffix == ".npy":
            img = np.load(path, allow_pickle=False)
        elif suffix in (".tif", ".tiff"):
            import tifffile
            img = tifffile.imread(path)
        elif suffix == ".png":
            from PIL import Image
            with Image.open(path) as im:
                img = np.asarray(im)
        else:
            raise SettingError(f"scene image {path}: unknown type {suffix!r} (use .npy, .png, .tif, .tiff)")
    except SettingError:
        raise
    except Exception as exc:  # a corrupt file of a known type
        raise SettingError(f"scene image {path}: cannot read ({exc})") from exc
    img = np.asarray(img)
    if img.ndim != 2:
        raise SettingError(f"scene image {path}: need a single-channel 2-D image, got shape {img.shape}")
    if img.dtype.kind not in "uif":
        raise SettingError(f"scene image {path}: need numbers, got dtype {img.dtype}")
    return img


def _resample(img: np.ndarray, shape) -> np.ndarray:
    """Nearest-neighbour resampling (depth must not be blurred across edges)."""
    h, w = shape
    rows = np.minimum((np.arange(h) + 0.5) * img.shape[0] / h, img.shape[0] - 1).astype(np.int64)
    cols = np.minimum((np.arange(w) + 0.5) * img.shape[1] / w, img.shape[1] - 1).astype(np.int64)
    return img[np.ix_(rows, cols)]


def parse_file_spec(spec: str) -> dict:
    """``file:PATH[,reflectivity=PATH][,scale=M_PER_UNIT][,offset=M]`` -> dict of options."""
    body = spec[len("file:"):]
    parts = body.split(",")
    if not parts[0]:
        raise SettingError(f"scene {spec!r}: no depth image path after 'file:'")
    opts = {"path": parts[0]}
    for part in parts[1:]:
        key, sep, value = part.partition("=")
        if not sep or key not in ("reflectivity", "scale", "offset"):
            raise SettingError(f"scene {spec!r}: unknown option {part!r} "
                             "(allowed: reflectivity=PATH, scale=M_PER_UNIT, offset=M)")
        if key in ("scale", "offset"):
            try:
                opts[key] = float(value)
            except ValueError:
                raise SettingError(f"scene {spec!r}: {key} must be a number, got {value!r}") from None
        else:
            opts[key] = value
    return opts


def from_file(spec: str, shape=None) -> Geometry:
    """A scene from a depth image (see ``parse_file_spec``).

    Float images are metres; integer images are millimetres unless ``scale`` (metres per unit)
    is given; ``offset`` (metres) is added after scaling. Pixels whose depth is not finite or not
    positive have no surface (background only). Reflectivity: float images as they are, integer
    images divided by their type's maximum; default 0.5 everywhere. With ``shape`` the images are
    resampled (nearest neighbour) to (H, W).
    """
    opts = parse_file_spec(spec)
    img = _read_image(Path(opts["path"]))
    scale = opts.get("scale", 1.0 if img.dtype.kind == "f" else 1e-3)
    depth = img.astype(np.float64) * scale + opts.get("offset", 0.0)
    if shape is not None and tuple(shape) != depth.shape:
        depth = _resample(depth, shape)
    valid = np.isfinite(depth) & (depth > 0)
    if not valid.any():
        raise SettingError(f"scene image {opts['path']}: no pixel has a finite positive depth")
    if "reflectivity" in opts:
        rimg = _read_image(Path(opts["reflectivity"]))
        refl = rimg.astype(np.float64)
        if rimg.dtype.kind in "ui":
            refl /= np.iinfo(rimg.dtype).max
        if rimg.shape != img.shape:
            raise SettingError(f"reflectivity image {opts['reflectivity']}: shape {rimg.shape} "
                             f"differs from depth image shape {img.shape}")
        if shape is not None and tuple(shape) != refl.shape:
            refl = _resample(refl, shape)
        if not np.all(np.isfinite(refl)) or np.any(refl < 0):
            raise SettingError(f"reflectivity image {opts['reflectivity']}: values must be finite and >= 0")
    else:
        refl = np.full(depth.shape, 0.5)
    occ = valid.astype(np.float64)
    depth = np.where(valid, depth, 0.0)
    return Geometry(depth[None], refl[None], occ[None], np.ones(depth.shape))
