"""What every reader returns."""

from __future__ import annotations

from dataclasses import dataclass, field

from spdepth.recon.photons import PhotonStore


@dataclass(frozen=True)
class ReadResult:
    """A file read into a photon store, with what the reader learned on the way.

    store:  the per-pixel detection times (raw units of ``store.time_unit_s``).
    path:   the file read, as given.
    kind:   ``"mat"``, ``"ptu"``, ``"ht3"`` or ``"pt3"``.
    is_image: False for a point measurement (no line markers), which comes back as a 1 x 1 store.
    notes:  one-line remarks a person should see (e.g. "point measurement: no line markers"),
            printed on stderr by the CLI.
    meta:   JSON-able facts from the file: variable name, record type, resolution, sync rate,
            channel counts, frames and lines found.
    """

    store: PhotonStore
    path: str
    kind: str
    is_image: bool = True
    notes: tuple[str, ...] = ()
    meta: dict = field(default_factory=dict)
