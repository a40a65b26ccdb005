"""A simulated scene read as a count-gated scan into a PhotonStore (shared by the tests that score
estimators on simulated frames)."""

from __future__ import annotations

import numpy as np

from spdepth.drivers.events import EventKind
from spdepth.drivers.sim import PhotonWorld
from spdepth.recon.photons import PhotonStore


def count_gated_store(scene, n: int, seed: int) -> PhotonStore:
    """Every pixel of ``scene`` row by row until ``n`` detections (or 100 dwells), as a store of
    the detections' times in the scene's resolution."""
    h, w = scene.shape
    world = PhotonWorld(scene, seed=seed)
    lists, sync = [], 0
    for r in range(h):
        for c in range(w):
            ev, n_syncs = world.count_gated(r, c, n, 100 * scene.dwell_s, sync)
            sync += n_syncs
            lists.append(ev["dtime"][ev["kind"] == EventKind.PHOTON].astype(np.float64))
    return PhotonStore.from_lists(lists, (h, w), scene.resolution_s)
