"""spatial: depth from a pixel's detections and its neighbours' (censoring, a pixelwise fit, edge-
preserving TV: :mod:`recon.spatial`); with several surfaces, each surface supported by its
neighbours (:mod:`recon.multi`, registered as "spatial-surfaces" by :mod:`.surfaces`). Not
pixelwise, so a live scan shows ml's maps and runs it once on the final frame."""

from __future__ import annotations

from spdepth.recon.estimators import Estimator, register

ESTIMATOR = register(Estimator(
    "spatial", "uses the neighbours: censoring, a pixelwise fit and edge-preserving TV",
    "spdepth.recon.spatial:fit", pixelwise=False, several="spatial-surfaces", live=False,
    live_stand_in="ml"))
