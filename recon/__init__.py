"""Reconstruction: forward model, photon store, estimators behind one registry
(``recon.estimate.ESTIMATORS``, entry point ``recon.estimate.reconstruct``) and maps. Math only.

``recon`` imports nothing from ``acq``, ``drivers`` or ``gui``.
"""
