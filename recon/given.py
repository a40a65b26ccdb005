"""The model the settings give: the binning as given, the pulse (a width or an IRF) and its kernel,
and :func:`reconstruct_given`, which runs an estimator on it with nothing estimated but the depths
(the IRF estimate's pilot fits: :mod:`recon.irf`). :mod:`recon.resolve` completes the model from
the data where the settings leave a part out.
"""

from __future__ import annotations

import math
from typing import Callable

from spdepth.recon import estimators
from spdepth.recon.errors import InputError
from spdepth.recon.model import Binning, Irf, PulseKernel, ReconSettings, build_kernel, irf_core_rms_s
from spdepth.recon.photons import PhotonStore


def check_time_unit(store: PhotonStore, binning: Binning | None) -> None:
    """InputError when ``binning`` counts in another raw unit than ``store``."""
    if binning is not None and not math.isclose(binning.time_unit_s, store.time_unit_s, rel_tol=1e-9):
        raise InputError(f"binning time unit {binning.time_unit_s} s differs from the data's "
                         f"{store.time_unit_s} s")


def given_pulse(settings: ReconSettings) -> tuple[Irf | None, float, float, str] | None:
    """The pulse ``settings`` give: (irf or None for a Gaussian, RMS s, core RMS s, source), the
    core being the width of the response's sharp part (:func:`recon.model.irf_core_rms_s`). None
    when they give neither a width nor an IRF (then the pulse is measured: ``recon.resolve.resolve_model``)."""
    if settings.irf is not None:
        return settings.irf, settings.irf.rms_s, irf_core_rms_s(settings.irf), "irf"
    if settings.pulse_rms_s is not None:
        return None, settings.pulse_rms_s, settings.pulse_rms_s, "given"
    return None


def pulse_kernel(binning: Binning, irf: Irf | None, rms_s: float, core_s: float, notes: dict) -> PulseKernel:
    """The kernel of the pulse (``irf``, else a Gaussian of ``rms_s``) on ``binning``; records the
    widths used in ``notes`` (``pulse_rms_s``, ``pulse_core_rms_s``)."""
    kern = build_kernel(binning, irf=irf) if irf is not None else build_kernel(binning, pulse_rms_s=rms_s)
    notes["pulse_rms_s"] = float(rms_s)
    notes["pulse_core_rms_s"] = float(min(core_s, rms_s))
    return kern


def reconstruct_given(store: PhotonStore, settings: ReconSettings,
                      progress: Callable[[int, int], None] | None = None):
    """The one-surface fit of ``settings.method`` on settings that give the binning and the pulse
    (a width or an IRF): nothing is estimated from the data but the depths. InputError otherwise."""
    b = settings.binning
    pulse = given_pulse(settings)
    if b is None or pulse is None:
        raise InputError("reconstruct_given needs settings with a binning and a pulse width or IRF")
    check_time_unit(store, b)
    irf, rms_s, core_s, source = pulse
    notes = {"pulse_source": source, "binning_source": "given"}
    kern = pulse_kernel(b, irf, rms_s, core_s, notes)
    return estimators.get(settings.method).run(store, settings, b, kern, notes, progress)
