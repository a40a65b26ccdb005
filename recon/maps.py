"""Per-pixel results of a reconstruction and their file format."""

from __future__ import annotations

import json
import zipfile
from dataclasses import dataclass
from enum import IntEnum
from pathlib import Path

import numpy as np

from spdepth.recon.errors import InputError

#: Speed of light in vacuum, m/s (depth = c * tof / 2): recon's one copy, exact by the SI's
#: definition of the metre (scipy.constants gives the same; its import, which parses CODATA, took
#: 70 ms of every new process).
C_M_PER_S: float = 299_792_458.0

NPZ_KEYS = ("tof_s", "depth_m", "background", "signal", "photons", "iterations", "uncertainty_s",
            "flags", "surfaces", "weak", "settings")
#: Keys a file written before the several-surface maps may lack (derived on reading).
OPTIONAL_NPZ_KEYS = ("surfaces", "weak")


class PixelFlag(IntEnum):
    """Outcome of the estimate at one pixel (the ``flags`` map, uint8)."""

    OK = 0
    """A return was found; tof, signal, background and uncertainty are set."""
    NO_PHOTONS = 1
    """No detection in the window: tof NaN, signal and background 0."""
    NO_RETURN = 2
    """Detections, but no return among them: the test of :mod:`recon.detect` (a likelihood-ratio
    test at the false-alarm rate in ``settings['detection']``) does not find one, or the fit puts
    every detection in the background: no depth (tof NaN), signal 0."""
    NO_SIGNAL = 2
    """The former name of NO_RETURN (the same value)."""
    NOT_CONVERGED = 3
    """uos stopped at max_iterations before ``||x_k - x_{k-1}||^2 < delta``; the estimate is kept."""
    INTERPOLATED = 4
    """spatial: the pixel had no detection kept as signal; tof comes from its neighbours."""


@dataclass(frozen=True, eq=False)
class DepthMaps:
    """Maps of one reconstruction. H x W pixels; K surfaces per pixel when ``settings['reflectors']``
    is K > 1 or "auto" (then tof_s, depth_m, signal, uncertainty_s and weak are (K, H, W) with K the
    most surfaces looked for (``max_reflectors`` for auto), surfaces sorted by time, NaN / 0 / False
    past the ones the data support; ``surfaces`` says how many per pixel).

    tof_s:         round-trip time of flight from the laser sync to the pulse centroid, s (NaN: none).
    depth_m:       c * tof_s / 2, m.
    background:    expected background detections per bin (the paper's B), >= 0; NaN for lmf, which
                   does not estimate it (``settings['background']`` says so).
    signal:        detections attributed to the return (expected signal count in the window), >= 0.
    photons:       detections used (in the window, after max_photons), int64.
    iterations:    estimator iterations (uos), 1 for lmf and ml, int32.
    uncertainty_s: standard deviation of tof_s, s (from the Poisson likelihood's curvature).
    flags:         :class:`PixelFlag` codes, uint8.
    settings:      every setting used, including the pulse RMS actually used (estimated or given).
    surfaces:      (H, W) int16, surfaces found per pixel (0: none; the finite entries of tof_s).
    weak:          like tof_s, bool: the surface raised the likelihood too little to rule out a
                   chance cluster of background at a false-alarm rate of 1e-6 (``settings
                   ['weak_below_nats']``); all False for one surface per pixel.
    gain_nats:     (H, W) float64 or None: the log-likelihood gain of one return over background
                   alone (nats) where the estimator computed it (ml), for recon.detect's test to
                   use instead of searching again; not saved.
    """

    tof_s: np.ndarray
    depth_m: np.ndarray
    background: np.ndarray
    signal: np.ndarray
    photons: np.ndarray
    iterations: np.ndarray
    uncertainty_s: np.ndarray
    flags: np.ndarray
    settings: dict
    surfaces: np.ndarray | None = None
    weak: np.ndarray | None = None
    gain_nats: np.ndarray | None = None

    def __post_init__(self) -> None:
        tof = np.asarray(self.tof_s)
        if self.surfaces is None:
            n = np.isfinite(tof).astype(np.int16)
            object.__setattr__(self, "surfaces", n.sum(axis=0).astype(np.int16) if tof.ndim == 3 else n)
        if self.weak is None:
            object.__setattr__(self, "weak", np.zeros(tof.shape, np.bool_))

    @property
    def shape(self) -> tuple[int, int]:
        return tuple(self.flags.shape)

    def save_npz(self, path) -> None:
        """Write a compressed .npz with keys exactly NPZ_KEYS; settings as a JSON string."""
        arrays = {k: getattr(self, k) for k in NPZ_KEYS if k != "settings"}
        np.savez_compressed(Path(path), settings=np.array(json.dumps(self.settings)), **arrays)

    @classmethod
    def load_npz(cls, path) -> "DepthMaps":
        """Read a file written by save_npz; InputError naming the file if it is not one."""
        p = Path(path)
        if not p.is_file():
            raise InputError(f"depth maps file {p} not found")
        try:
            with np.load(p, allow_pickle=False) as z:
                missing = [k for k in NPZ_KEYS if k not in z.files and k not in OPTIONAL_NPZ_KEYS]
                if missing:
                    raise InputError(f"depth maps file {p}: missing {', '.join(missing)}")
                data = npz_arrays(z, NPZ_KEYS)
        except (zipfile.BadZipFile, ValueError, OSError, EOFError) as exc:
            raise InputError(f"depth maps file {p}: not a readable .npz ({exc})") from None
        try:
            settings = json.loads(str(data.pop("settings")))
        except json.JSONDecodeError as exc:
            raise InputError(f"depth maps file {p}: settings are not JSON ({exc})") from None
        return cls(settings=settings, **data)


SPARSE_LAYOUT = "pixels"
"""``layout`` of a maps file that holds its frame-sized arrays only at some pixels
(:func:`sparse_arrays`): a large scan that reached few of its pixels (a time limit)."""
FILL_SUFFIX = "__fill"


def sparse_arrays(arrays: dict, shape: tuple[int, int], keep: np.ndarray, dense: tuple = ()) -> dict:
    """``arrays`` for a maps file in the sparse layout: every array whose last two axes are the
    frame's ``shape`` and whose value is one and the same outside the flat mask ``keep``
    (pixels never reached: NaN, 0, NO_PHOTONS) is stored as its values at ``pixels`` (``(...,
    n)``, pixels in ascending flat order) and that value (``NAME__fill``, ``(...)``); other
    arrays, and those named in ``dense``, as they are; plus ``layout`` ("pixels"),
    ``frame_shape`` (H, W) and ``pixels``.
    :func:`npz_arrays` (and ``DepthMaps.load_npz``) give back the full arrays, bit for bit."""
    keep = np.asarray(keep, bool).reshape(-1)
    pixels = np.flatnonzero(keep)
    out = {"layout": np.array(SPARSE_LAYOUT), "frame_shape": np.array(shape, np.int64),
           "pixels": pixels}
    first = int(np.argmin(keep)) if not keep.all() else None    # a pixel left out
    n_out = keep.size - pixels.size
    for name, a in arrays.items():
        a = np.asarray(a)
        if first is None or name in dense or a.ndim < 2 or tuple(a.shape[-2:]) != tuple(shape):
            out[name] = a
            continue
        flat = a.reshape(a.shape[:-2] + (-1,))
        fill = flat[..., first]
        kept = flat[..., pixels]
        # every pixel outside holds the fill when the pixels that do, over the whole frame, are
        # those inside that do plus all n_out outside: counted, not masked (a mask of the pixels
        # outside for each map of a 4096 x 4096 frame took most of this function's 0.3 s)
        if np.count_nonzero(_is_fill(flat, fill)) - np.count_nonzero(_is_fill(kept, fill)) \
                != n_out * int(np.prod(flat.shape[:-1])):
            out[name] = a                   # not one value outside: kept whole
            continue
        out[name] = kept
        out[name + FILL_SUFFIX] = np.asarray(fill)
    return out


def _is_fill(flat: np.ndarray, fill) -> np.ndarray:
    """Where ``flat`` (..., n) holds ``fill`` (...), NaN matching NaN (the fill of each surface)."""
    if flat.dtype.kind not in "fc":
        return flat == np.asarray(fill)[..., None]
    fill = np.asarray(fill)
    if fill.ndim == 0 and np.isnan(fill):
        return np.isnan(flat)
    same = flat == fill[..., None]
    return same | (np.isnan(flat) & np.isnan(fill)[..., None])


def npz_arrays(z, names=None) -> dict:
    """The arrays of an opened maps file (``np.load``), full frame whichever the layout
    (:func:`sparse_arrays`); ``names``: only those present among them."""
    files = [f for f in z.files if not f.endswith(FILL_SUFFIX)]
    if names is not None:
        files = [f for f in files if f in names]
    if "layout" not in z.files:
        return {f: z[f] for f in files}
    if str(z["layout"]) != SPARSE_LAYOUT:
        raise ValueError(f"unknown maps layout {str(z['layout'])!r}")
    h, w = (int(v) for v in z["frame_shape"])
    pixels = z["pixels"]
    out = {}
    for f in files:
        if f in ("layout", "frame_shape", "pixels"):
            continue
        if f + FILL_SUFFIX not in z.files:
            out[f] = z[f]
            continue
        fill, vals = z[f + FILL_SUFFIX], z[f]
        full = np.empty(fill.shape + (h * w,), vals.dtype)
        full[...] = fill[..., None]
        full[..., pixels] = vals
        out[f] = full.reshape(fill.shape + (h, w))
    return out
