"""File readers: recorded measurements enter here, at the same point a live device does, and leave
as one :class:`recon.photons.PhotonStore` (photon lists) or :class:`recon.counts.CountStore`
(histogram cubes: :mod:`acq.readers.cube`).

``read_photons(path)`` picks the reader from the file's first bytes (not its name), so a text file
called ``x.ptu`` gets a clear "not a PTU file" error instead of a decoder traceback.

Every reader raises :class:`recon.errors.InputError` with a one-line message naming the file and
what is wrong (missing, empty, truncated, corrupt, wrong kind, missing field).
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

from spdepth.acq.readers.common import ReadResult
from spdepth.recon.errors import InputError

__all__ = ["ReadResult", "read_photons", "sniff_kind"]

_MAT_MAGIC = b"MATLAB"
_PTU_MAGICS = (b"PQTTTR\0\0",)
_HT3_IDENT = b"HydraHarp"
_PT3_IDENT = b"PicoHarp 300"


def sniff_kind(path: str | Path) -> str:
    """The file's kind from its first bytes: ``"mat"``, ``"ptu"``, ``"ht3"``, ``"pt3"``, ``"npy"``,
    ``"npz"`` or ``"hdf5"``.

    Raises InputError when the file is missing, empty or of none of these kinds."""
    path = Path(path)
    try:
        with open(path, "rb") as f:
            head = f.read(128)
    except FileNotFoundError:
        raise InputError(f"{path}: no such file") from None
    except IsADirectoryError:
        raise InputError(f"{path}: is a directory, not a measurement file") from None
    except OSError as exc:
        raise InputError(f"{path}: cannot read: {exc.strerror or exc}") from None
    if not head:
        raise InputError(f"{path}: file is empty")
    if head.startswith(_MAT_MAGIC):
        return "mat"
    if head[:8] in _PTU_MAGICS:
        return "ptu"
    if head.startswith(_HT3_IDENT):
        return "ht3"
    if head.startswith(_PT3_IDENT):
        return "pt3"
    if head.startswith(b"PQHISTO"):
        raise InputError(f"{path}: a PicoQuant histogram file (.phu): it holds summed histograms, "
                         f"not the time-tagged detections per pixel that depth needs; record in "
                         f"T3 mode (.ptu)")
    if head.startswith(b"\x89HDF"):
        return "hdf5"
    if head.startswith(b"\x93NUMPY"):
        return "npy"
    if head.startswith(b"PK\x03\x04") and path.suffix.lower() == ".npz":
        return "npz"
    raise InputError(f"{path}: not a .mat, PTU, HT3, PT3, .npy, .npz or HDF5 file (unrecognised "
                     f"first bytes {head[:8]!r})")


def read_photons(path: str | Path, *, time_unit_s: float | None = None, mat_var: str | None = None,
                 channel: int | None = None, keep: int | None = None) -> ReadResult:
    """Read any supported file into a PhotonStore (a histogram cube: into a CountStore, ``counts``).

    path:        a .mat file (first-photon-imaging cells, or a count cube), a PicoQuant PTU / HT3 /
                 PT3 T3 file, or a count cube in .npy / .npz / HDF5.
    time_unit_s: size of one raw time unit in seconds. Required for .mat files (they carry none);
                 PicoQuant files use their header's TCSPC resolution, and a different value given
                 here is noted (in the result's notes, naming both), never applied.
    mat_var:     the cell-array or cube variable of a .mat file (the array of a .npz, the dataset
                 of an HDF5 file) when it holds more than one.
    channel:     PicoQuant files: keep only this detector channel (0-based); default all channels.
    keep:        a session's recording: detections kept per pixel (default the session's target).
    """
    kind = sniff_kind(path)
    if kind == "mat":
        from spdepth.acq.readers.mat import read_mat

        if channel is not None:
            raise InputError(f"{path}: a .mat file has no detector channels; drop the channel option")
        return read_mat(path, time_unit_s=time_unit_s, var=mat_var)
    if kind in ("npy", "npz", "hdf5"):
        from spdepth.acq.readers import cube

        if channel is not None:
            raise InputError(f"{path}: a count cube has no detector channels; drop the channel option")
        if kind == "hdf5":
            return cube.read_hdf5(path, time_unit_s=time_unit_s, var=mat_var)
        return cube.read_numpy(path, kind, time_unit_s=time_unit_s, var=mat_var)
    if mat_var is not None:
        raise InputError(f"{path}: a {kind.upper()} file has no variables; drop the mat-var option")
    from spdepth.acq.readers import picoquant

    reader = {"ptu": picoquant.read_ptu, "ht3": picoquant.read_ht3, "pt3": picoquant.read_pt3}[kind]
    result = reader(path, channel=channel, **({"keep": keep} if kind == "ptu" else {}))
    unit_s = result.store.time_unit_s
    if time_unit_s is not None and not math.isclose(time_unit_s, unit_s, rel_tol=1e-9):
        # never a silent override: the header's resolution is the file's unit (several inputs may
        # mix .mat files, which need the option, with PicoQuant files, which carry their own)
        note = (f"{Path(path).name}: time unit {time_unit_s * 1e12:g} ps given, the header's resolution "
                f"{unit_s * 1e12:g} ps used (PicoQuant files carry their own time unit)")
        result = dataclasses.replace(result, notes=(note,) + tuple(result.notes))
    return result
