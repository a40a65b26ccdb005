"""The K-surface fits (``reflectors`` K > 1 or "auto"; orchestration :mod:`.surfaces_fit`, kernels
:mod:`.surfaces_kernels`): "surfaces", the greedy Poisson pursuit that lmf, uos and ml all hand
several surfaces to (the same fit for the three), and "spatial-surfaces", the same pursuit with
each surface supported by its neighbours (spatial's). Neither is a ``--method`` of its own: they
are reached through the methods' ``several``."""

from __future__ import annotations

from spdepth.recon.estimators import Estimator, register

SURFACES = register(Estimator(
    "surfaces", "the same K-surface fit (a greedy Poisson pursuit)",
    "spdepth.recon.estimators.surfaces_fit:reconstruct_multi", pixelwise=True, max_surfaces=8,
    method=False, counts="whole"))
SPATIAL_SURFACES = register(Estimator(
    "spatial-surfaces", "the K-surface fit with the neighbours' proposals and smoothing",
    "spdepth.recon.estimators.surfaces_fit:reconstruct_multi_spatial", pixelwise=False,
    max_surfaces=8, live=False, live_stand_in="surfaces", method=False, counts="whole"))
