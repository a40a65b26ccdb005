"""What every reader returns."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from spdepth.recon.counts import CountStore
from spdepth.recon.photons import PhotonStore


@dataclass(frozen=True)
class ReadResult:
    """A file read into a photon store (or a count store), with what the reader learned on the way.

    store:  the per-pixel detection times (raw units of ``store.time_unit_s``); None for a
            histogram cube, which comes as ``counts``.
    counts: a histogram cube's per-pixel counts (``recon.counts.CountStore``, time bins as raw
            units), else None.
    path:   the file read, as given.
    kind:   ``"mat"``, ``"ptu"``, ``"ht3"``, ``"pt3"``, ``"npy"``, ``"npz"`` or ``"hdf5"``.
    is_image: False for a point measurement (no line markers), which comes back as a 1 x 1 store.
    notes:  one-line remarks a person should see (e.g. "point measurement: no line markers"),
            printed on stderr by the CLI.
    meta:   JSON-able facts from the file: variable name, record type, resolution, sync rate,
            channel counts, frames and lines found.
    periods: laser periods each pixel integrated over (float64, H * W), when the file tells
            (Coates' pile-up correction needs them: ``recon.pileup``), else None.
    """

    store: PhotonStore | None
    path: str
    kind: str
    is_image: bool = True
    notes: tuple[str, ...] = ()
    meta: dict = field(default_factory=dict)
    counts: CountStore | None = None
    periods: np.ndarray | None = None

    @property
    def shape(self) -> tuple[int, int]:
        return (self.store if self.store is not None else self.counts).shape
