"""The model a reconstruction uses: the binning and the pulse kernel, from the settings where they
give them (:mod:`recon.given`), else from the data (the window from the detections' span, the pulse
measured by :mod:`recon.irf`), and notes saying which. Every estimator runs on a model resolved
here (:func:`resolve_model`), so a method never sees settings with a part left to guess.
"""

from __future__ import annotations

from spdepth.recon.given import check_time_unit, given_pulse, pulse_kernel
from spdepth.recon.irf import estimate_irf
from spdepth.recon.model import Binning, PulseKernel, ReconSettings, default_binning
from spdepth.recon.photons import PhotonStore


def resolve_model(store: PhotonStore, settings: ReconSettings) -> tuple[Binning, PulseKernel, dict]:
    """The binning and pulse kernel a reconstruction of ``store`` uses, and notes for the record."""
    notes: dict = {}
    b = settings.binning
    check_time_unit(store, b)
    pulse = given_pulse(settings)
    if pulse is not None:
        irf, rms_s, core_s, notes["pulse_source"] = pulse
    else:
        # measured from the data: a Gaussian when no tail shows, else the measured shape
        est = estimate_irf(store, b, settings.max_photons)
        notes["pulse_source"] = "estimated"
        notes["irf_estimate"] = est.to_dict()
        core_s = est.core_rms_s
        if est.method == "emg-pairs" and est.tail_share == 0.0:
            irf, rms_s = None, est.core_rms_s
        else:
            irf = est.irf
            rms_s = irf.rms_s
            notes["irf"] = dict(irf.to_dict(), rms_s=rms_s)
    if b is None:
        # bins from the sharp part of the response (a ninth of its RMS): a long tail must not
        # blur the leading edge
        b = default_binning(store.times, store.time_unit_s, core_s)
        notes["binning_source"] = "derived from the data's time range"
    else:
        notes["binning_source"] = "given"
    kern = pulse_kernel(b, irf, rms_s, core_s, notes)
    return b, kern, notes
