"""Histogram cubes: per-pixel counts in time bins, as SPAD-array sensors, histogramming TCSPC cards and
most public single-photon lidar data sets deliver them.

An H x W x T numeric array is one frame (time the last axis), F x H x W x T several frames (summed
here: ``spdepth recon`` reconstructs the accumulated frame; MATLAB files hold frames last, H x W x
T x F, as MATLAB code builds them). Where they come from:

- .mat (MATLAB level 5): any 3-D or 4-D numeric variable, found as the photon-time variables are (the
  only one, or ``var``); MATLAB v7.3 files are HDF5 and are read with h5py, whose axes are MATLAB's
  reversed (so they are turned back).
- .npy, .npz (``var`` names the array when there are several), HDF5 (.h5/.hdf5: ``var`` names the
  dataset; attributes ``time_unit_s``, ``periods`` (laser periods per pixel and frame),
  ``fov_deg`` / ``pixel_pitch_m`` + ``focal_length_m`` are used when present, as the array
  sessions write them, ``acq.array_session``).

A cube records no bin width (HDF5 attributes aside), so ``time_unit_s`` (the bin width) is needed
as for .mat photon times; bin k of the last axis is raw time k, so ``--window-ps`` and ``--bin-ps``
mean what they mean for photon times.
"""

from __future__ import annotations

import zipfile
from pathlib import Path

import numpy as np

from spdepth.acq.readers.common import ReadResult
from spdepth.recon.counts import CountStore
from spdepth.recon.errors import InputError


def _describe(name: str, shape, dtype) -> str:
    return f"{name} ({'x'.join(str(n) for n in shape) or 'scalar'} {dtype})"


def is_cube(value) -> bool:
    """A 3-D or 4-D array of numbers (counts)."""
    return (isinstance(value, np.ndarray) or hasattr(value, "shape")) and len(value.shape) in (3, 4) \
        and np.dtype(value.dtype).kind in "uifb"


def pick_cube(path: Path, arrays: dict, var: str | None, what: str = "variable"):
    """The cube among ``arrays`` (name -> array-like with shape and dtype): ``var``, else the only
    3-D/4-D numeric one. InputError naming the file and what it holds otherwise."""
    held = ", ".join(_describe(k, v.shape, v.dtype) for k, v in arrays.items()) or "nothing"
    if var is not None:
        if var not in arrays:
            raise InputError(f"{path}: no {what} {var!r}; the file holds: {held}")
        if not is_cube(arrays[var]):
            raise InputError(f"{path}: {what} {var!r} is {_describe(var, arrays[var].shape, arrays[var].dtype)}, "
                             f"not an H x W x T (or F x H x W x T) count array")
        return var, arrays[var]
    cubes = [k for k, v in arrays.items() if is_cube(v)]
    if not cubes:
        raise InputError(f"{path}: no 3-D (H x W x T) or 4-D (frames) count array; the file holds: {held}")
    if len(cubes) > 1:
        raise InputError(f"{path}: several count arrays ({', '.join(sorted(cubes))}); choose one with --mat-var")
    return cubes[0], arrays[cubes[0]]


MAX_BIN_COUNT = float(2 ** 48)
"""Most detections one bin of a cube may hold (a detector at 1 GHz for three days)."""


def cube_counts(path: Path, name: str, cube, time_unit_s: float, *, periods=None,
                frames_last: bool = False) -> tuple[CountStore, dict]:
    """The CountStore of a cube (frames summed) and what was learned: frames, shape, bins.
    ``frames_last``: a 4-D array is H x W x T x F (MATLAB's order), else F x H x W x T."""
    shape = tuple(int(n) for n in cube.shape)
    if 0 in shape:
        raise InputError(f"{path}: {name} is empty ({'x'.join(map(str, shape))})")
    source = f"{path}: {name}"
    if len(shape) == 3:
        frames, arr = 1, np.asarray(cube)
    else:
        frames = shape[-1] if frames_last else shape[0]
        # summed a frame at a time: a recording of many frames need not fit in memory twice
        arr = None
        for f in range(frames):
            fr = np.asarray(cube[..., f] if frames_last else cube[f])
            if fr.dtype.kind == "f" and not np.all(np.isfinite(fr)):
                raise InputError(f"{source}: frame {f} holds NaN or infinite counts")
            arr = fr.astype(np.float64 if fr.dtype.kind == "f" else np.int64) if arr is None else arr + fr
    if arr.dtype.kind in "uif" and arr.size and float(np.nanmax(arr)) > MAX_BIN_COUNT:
        # not detections (no detector counts 2**60 in a bin): and they would overflow as floats
        raise InputError(f"{source}: holds counts up to {float(np.nanmax(arr)):.3g} in one bin, "
                         f"more than {MAX_BIN_COUNT:.3g}: not detection counts")
    if periods is not None:
        periods = np.ravel(np.asarray(periods, np.float64)) * frames
    counts = CountStore.from_cube(arr, time_unit_s, periods=periods, source=source)
    if counts.n_occupied == 0:
        raise InputError(f"{source}: holds no counts")
    meta = {"cube_var": name, "frames": frames, "cube_shape": list(shape), "n_bins": int(arr.shape[-1]),
            "occupied_bins": counts.n_occupied, "time_unit_s": time_unit_s}
    return counts, meta


def _h5_datasets(f) -> dict:
    import h5py

    out = {}

    def visit(name, obj):
        if isinstance(obj, h5py.Dataset):
            out[name] = obj
    f.visititems(visit)
    return out


def _attr(ds, f, key):
    for holder in (ds.attrs, f.attrs):
        if key in holder:
            v = holder[key]
            return v.item() if np.ndim(v) == 0 else np.asarray(v)
    return None


def read_hdf5(path: str | Path, *, time_unit_s: float | None, var: str | None = None,
              matlab: bool = False) -> ReadResult:
    """An HDF5 file's cube (a MATLAB v7.3 .mat when ``matlab``: axes reversed, MATLAB's own
    ``#refs#`` group skipped). Attributes (module docstring) fill in what options leave out."""
    import h5py

    path = Path(path)
    try:
        f = h5py.File(path, "r")
    except OSError as exc:
        raise InputError(f"{path}: not a readable HDF5 file ({exc})") from None
    with f:
        if f.attrs.get("layout") == "sparse-frames":
            return _read_sparse_frames(path, f, time_unit_s)
        arrays = {k: v for k, v in _h5_datasets(f).items() if not k.startswith("#")}
        name, ds = pick_cube(path, arrays, var, "dataset")
        unit = time_unit_s if time_unit_s is not None else _attr(ds, f, "time_unit_s")
        if unit is None:
            raise InputError(f"{path}: the file does not record its bin width; give it "
                             f"(--time-unit-ps, the width of one time bin)")
        periods = _attr(ds, f, "periods")
        # h5py sees a v7.3 file's arrays with MATLAB's axes reversed
        cube = np.asarray(ds).T if matlab else ds
        counts, meta = cube_counts(path, name, cube, float(unit), periods=periods, frames_last=matlab)
        for key in ("fov_deg", "pixel_pitch_m", "focal_length_m", "frame_rate_hz", "period_s"):
            v = _attr(ds, f, key)
            if v is not None:
                meta[key] = v.tolist() if isinstance(v, np.ndarray) else v
    if periods is not None:
        meta["periods_source"] = "file attribute periods"
    return ReadResult(store=None, counts=counts, path=str(path), kind="mat" if matlab else "hdf5",
                      is_image=True, meta=meta)


def _read_sparse_frames(path: Path, f, time_unit_s: float | None) -> ReadResult:
    """An array session's recording (``acq.array_session.FrameRecorder``): its frames' (key, count)
    pairs summed into one CountStore, without a dense cube."""
    a = f.attrs
    h, w, t = (int(v) for v in a["shape"])
    offsets = f["frame_offsets"][()]
    frames = int(offsets.size - 1)
    keys = f["keys"][()].astype(np.int64)
    counts = f["counts"][()].astype(np.int64)
    if frames < 1 or keys.size == 0:
        raise InputError(f"{path}: the recording holds no counts")
    uniq, inverse = np.unique(keys, return_inverse=True)
    summed = np.bincount(inverse, weights=counts)
    unit = time_unit_s if time_unit_s is not None else float(a["time_unit_s"])
    periods = np.full(h * w, float(np.ravel(a["periods"])[0]) * frames)
    store = CountStore.from_pairs(uniq, summed, (h, w), t, unit, periods=periods)
    meta = {"cube_var": "keys/counts (array session frames)", "frames": frames, "cube_shape": [frames, h, w, t],
            "n_bins": t, "occupied_bins": store.n_occupied, "time_unit_s": unit,
            "periods_source": "file attribute periods"}
    for key in ("fov_deg", "pixel_pitch_m", "focal_length_m", "frame_rate_hz", "period_s"):
        if key in a:
            meta[key] = float(a[key])
    return ReadResult(store=None, counts=store, path=str(path), kind="hdf5", is_image=True, meta=meta)


def read_numpy(path: str | Path, kind: str, *, time_unit_s: float | None,
               var: str | None = None) -> ReadResult:
    """A .npy array or a .npz archive's array as a cube."""
    path = Path(path)
    if time_unit_s is None:
        raise InputError(f"{path}: a {kind} file does not record its bin width; give it "
                         f"(--time-unit-ps, the width of one time bin)")
    try:
        if kind == "npy":
            arrays = {path.stem: np.load(path, mmap_mode="r", allow_pickle=False)}
            if var is not None and var != path.stem:
                raise InputError(f"{path}: a .npy file holds one array; drop --mat-var")
            var = path.stem
        else:
            z = np.load(path, allow_pickle=False)
            arrays = {k: z[k] for k in z.files}
    except (ValueError, OSError, zipfile.BadZipFile, EOFError) as exc:
        raise InputError(f"{path}: not a readable {kind} file ({exc})") from None
    name, cube = pick_cube(path, arrays, var, "array")
    counts, meta = cube_counts(path, name, cube, time_unit_s)
    return ReadResult(store=None, counts=counts, path=str(path), kind=kind, is_image=True, meta=meta)


def read_mat_cube(path: Path, contents: dict, var: str | None, time_unit_s: float) -> ReadResult:
    """A level-5 .mat file's cube, from the variables scipy read (``contents``)."""
    arrays = {k: v for k, v in contents.items() if not k.startswith("__") and isinstance(v, np.ndarray)
              and v.dtype != object}
    name, cube = pick_cube(path, arrays, var)
    counts, meta = cube_counts(path, name, cube, time_unit_s, frames_last=True)
    return ReadResult(store=None, counts=counts, path=str(path), kind="mat", is_image=True, meta=meta)


__all__ = ["cube_counts", "is_cube", "pick_cube", "read_hdf5", "read_mat_cube", "read_numpy"]
