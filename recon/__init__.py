"""Reconstruction: forward model, photon store, per-pixel estimators and maps. Math only.

``recon`` imports nothing from ``acq``, ``drivers`` or ``gui``.
"""
