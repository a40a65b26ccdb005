"""Output paths checked before any work: every file and folder a command will write is refused up
front, in one line naming the option and the path, when it cannot be written (its folder missing,
not writable, not a real file system such as ``/proc``), and an existing output is refused unless
the command was told to overwrite it (one rule for every command that writes).

Writability is tried, not inferred from permission bits: ``os.access`` says yes to root for any
folder, ``/proc`` included, where creating a file then fails. A probe file is created and removed
in the folder (``.spdepth-probe-<pid>``); an existing file is opened for appending, which changes
nothing in it.
"""

from __future__ import annotations

import errno
import os
from pathlib import Path

from spdepth.acq.errors import OutputError

PROBE_PREFIX = ".spdepth-probe-"


def _why(exc: OSError) -> str:
    """The reason in a person's words (``/proc`` answers "No such file or directory" to a file
    created in it, which reads as if the folder were missing)."""
    return {errno.ENOENT: "files cannot be created there", errno.EACCES: "permission denied",
            errno.EPERM: "permission denied", errno.EROFS: "read-only file system",
            errno.ENOSPC: "no space left on the device"}.get(exc.errno,
                                                             exc.strerror or type(exc).__name__)


def probe_folder(option: str, folder: str | Path, *, shown: str | Path | None = None) -> None:
    """Refuse unless a file can be created in the existing ``folder`` (``shown``: the path to name
    in the message, the option's own value)."""
    folder = Path(folder)
    shown = folder if shown is None else shown
    probe = folder / f"{PROBE_PREFIX}{os.getpid()}"
    try:
        fd = os.open(probe, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o600)
    except FileExistsError:
        return                               # a probe of ours, left by a killed run: writable
    except OSError as exc:
        raise OutputError(f"{option} {shown}: cannot be written ({_why(exc)})") from None
    os.close(fd)
    probe.unlink(missing_ok=True)


def check_output_file(option: str, path: str | Path | None, *, overwrite: bool = False,
                      inputs: tuple = ()) -> None:
    """Refuse an output file before any work: a folder, a missing folder, one that cannot be
    written, one of the command's ``inputs``, or an existing file without ``overwrite`` (the
    refusal names the file and the option that allows it)."""
    if path is None:
        return
    p = Path(path)
    if p.is_dir():
        raise OutputError(f"{option} {path}: is a folder; give a file name")
    parent = p.parent if str(p.parent) else Path(".")
    if not parent.is_dir():
        raise OutputError(f"{option} {path}: folder {parent} does not exist")
    for i in inputs:
        if i is not None and p.exists() and Path(i).exists() and os.path.samefile(p, i):
            raise OutputError(f"{option} {path} is the input {i}: pick another file")
    if p.exists():
        if not overwrite:
            raise OutputError(f"{option} {path} exists (pass --overwrite to replace it)")
        try:
            # opened for appending and closed at once: writable without touching its contents
            os.close(os.open(p, os.O_WRONLY | os.O_APPEND))
        except OSError as exc:
            raise OutputError(f"{option} {path}: cannot be written ({_why(exc)})") from None
        return
    probe_folder(option, parent, shown=path)


def check_output_folder(option: str, path: str | Path | None) -> None:
    """Refuse an output folder before any work when it is a file, or when it (or, missing, the
    nearest folder above it that exists, where it would be made) cannot be written. Whether an
    existing folder may be written into is the caller's rule (``acq.api.OutputDir``: not empty
    without ``--overwrite``; ``recon``'s batch: each file it would replace)."""
    if path is None:
        return
    p = Path(path)
    if p.exists() and not p.is_dir():
        raise OutputError(f"{option} {path} exists and is not a folder")
    existing = p
    while not existing.is_dir():
        if existing.parent == existing:
            break
        existing = existing.parent
    probe_folder(option, existing, shown=path)


def refuse_existing(outputs, *, overwrite: bool, inputs: tuple = ()) -> None:
    """The overwrite rule of every command that writes files: each ``(option, path)`` of
    ``outputs`` that exists is refused unless ``overwrite`` (one line naming the first and how
    many more), and one that is an input is refused even then."""
    existing = []
    for option, path in outputs:
        if path is None:
            continue
        check_output_file(option, path, overwrite=True, inputs=inputs)
        if Path(path).exists():
            existing.append((option, path))
    if existing and not overwrite:
        (option, path), more = existing[0], [str(p) for _, p in existing[1:]]
        also = "" if not more else (f", and so does {more[0]}" if len(more) == 1 else
                                    f", and so do {more[0]} and {len(more) - 1} more")
        raise OutputError(f"{option} {path} exists{also} (pass --overwrite to replace "
                          f"{'them' if more else 'it'})")


__all__ = ["check_output_file", "check_output_folder", "probe_folder", "refuse_existing"]
