"""Reconstruction: forward model, photon store, estimators behind one registry
(``recon.estimators``, entry point ``recon.estimate.reconstruct``) and maps. Math only.

``recon`` imports nothing from ``acq``, ``drivers`` or ``gui``.
"""

# the built-in estimators declare themselves in the registry (their kernels, and numba, load when
# one runs): before any other module of recon is used, as Python runs this package first
from spdepth.recon.estimators import lmf, uos, ml, spatial, surfaces  # noqa: E402,F401
