"""A simulated flood-illuminated SPAD-array sensor: every pixel has its own detector and its own
time-to-digital converter, and the sensor delivers frames of per-pixel histograms (H x W x T counts)
at a frame rate, as 32x32 to 192x128 lidar arrays do.

Physics per pixel and laser period (each pixel's converter takes the first detection after the
sync and re-arms at the next one, so its dead time spans the rest of the period):

- photons in bin i arrive as Poisson with mean lambda_i = signal (the scene's pulse, equation 3 of
  the seed paper) + ambient + dark, per period; the pixel records bin i when it is the first bin
  with a photon: probability ``exp(-sum_{j<i} lambda_j) (1 - exp(-lambda_i))``, which is pile-up;
- a frame integrates ``periods_per_frame`` periods; its counts are drawn as independent Poisson per
  bin with those means (a pixel's total first, then its bins; exact in distribution for Poisson
  counts, the multinomial's small anti-correlation between bins left out);
- only where the settings call for them: ``hot_share`` of the pixels (drawn once, seeded) with a
  dark rate of ``hot_rate_hz``, and crosstalk: each detection fires one of the four neighbours in
  the same bin with probability ``crosstalk``.

Bin k of a frame covers ``[k, k + 1) * bin_s`` after the sync, as a cube's bins do for
``spdepth recon`` (``acq.readers.cube``).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from spdepth.drivers.errors import DeviceError


@dataclass(frozen=True)
class ArraySettings:
    """How the sensor runs. SI units.

    n_bins, bin_s:      histogram bins per pixel and their width (the range is n_bins * bin_s).
    frame_rate_hz:      frames per second.
    laser_rate_hz:      laser repetition rate; ``periods_per_frame`` = laser_rate / frame_rate.
    dark_rate_hz:       every pixel's dark-count rate.
    hot_share, hot_rate_hz: share of hot pixels (0: none) and their dark rate.
    crosstalk:          probability a detection fires a neighbour (0: none).
    pixel_pitch_m, focal_length_m: the sensor's geometry (the field of view of each pixel).
    """

    n_bins: int = 1024
    bin_s: float = 80e-12
    frame_rate_hz: float = 30.0
    laser_rate_hz: float = 1e6
    dark_rate_hz: float = 0.0
    hot_share: float = 0.0
    hot_rate_hz: float = 50e3
    crosstalk: float = 0.0
    pixel_pitch_m: float = 50e-6
    focal_length_m: float = 8e-3

    def __post_init__(self):
        if not (self.n_bins >= 1 and self.bin_s > 0 and self.frame_rate_hz > 0 and self.laser_rate_hz > 0):
            raise DeviceError("SPAD array: n_bins, bin_s, frame_rate_hz and laser_rate_hz must be positive")
        if self.n_bins * self.bin_s > 1.0 / self.laser_rate_hz * (1 + 1e-9):
            raise DeviceError(f"SPAD array: {self.n_bins} bins of {self.bin_s * 1e12:g} ps outlast the "
                              f"laser period {1e9 / self.laser_rate_hz:g} ns")
        for name in ("dark_rate_hz", "hot_share", "hot_rate_hz", "crosstalk"):
            if not getattr(self, name) >= 0:
                raise DeviceError(f"SPAD array: {name} must be >= 0")
        if self.hot_share > 1 or self.crosstalk >= 0.25:
            raise DeviceError("SPAD array: hot_share must be <= 1 and crosstalk < 0.25")

    @property
    def periods_per_frame(self) -> int:
        return max(1, int(round(self.laser_rate_hz / self.frame_rate_hz)))

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


class SimSpadArray:
    """The sensor looking at ``scene`` (a ``drivers.sim.scene.Scene``; its light levels are per
    laser pulse, its shape the array's). ``frame(i)`` is frame i's histograms, the same for the
    same seed and index whatever was asked before (each frame has its own random stream), so a
    recording can be checked against a regeneration."""

    def __init__(self, scene, settings: ArraySettings = ArraySettings(), seed: int = 0):
        self.scene = scene
        self.settings = settings
        self.seed = int(seed)
        h, w = scene.shape
        s = settings
        rng = np.random.default_rng([self.seed, 0xA55A])
        dark_pp = np.full((h, w), s.dark_rate_hz / s.laser_rate_hz)
        self.hot = np.zeros((h, w), bool)
        if s.hot_share > 0:
            self.hot.ravel()[rng.choice(h * w, int(round(s.hot_share * h * w)), replace=False)] = True
            dark_pp[self.hot] += s.hot_rate_hz / s.laser_rate_hz
        self.lam = self._bin_flux(dark_pp)                      # (P, T) photons per period
        # first-photon probability of each bin: the pile-up of a converter that stops once a period
        before = np.cumsum(self.lam, axis=1) - self.lam
        p = np.exp(-before) * -np.expm1(-self.lam)
        self.mean = p * s.periods_per_frame                     # (P, T) counts per frame
        self.total = self.mean.sum(axis=1)
        cdf = np.cumsum(self.mean, axis=1)
        with np.errstate(invalid="ignore", divide="ignore"):
            cdf = np.where(self.total[:, None] > 0, cdf / self.total[:, None], 1.0)
        # one increasing array over all pixels: pixel p's CDF lies in [p, p + 1]
        self._cdf = (cdf + np.arange(h * w)[:, None]).ravel()

    def _bin_flux(self, dark_pp: np.ndarray) -> np.ndarray:
        """Photons per period in each bin of every pixel: the scene's returns (Gaussian pulse,
        integrated over each bin), its ambient light spread over the period, and dark counts."""
        from scipy.special import ndtr

        sc, s = self.scene, self.settings
        h, w = sc.shape
        period = 1.0 / s.laser_rate_hz
        edges = np.arange(s.n_bins + 1) * s.bin_s
        lam = np.repeat(((sc.background_pp - sc.settings.dark_rate_hz * sc.sync_period_s).clip(0)
                         + dark_pp).reshape(-1, 1) * (s.bin_s / period), s.n_bins, axis=1)
        rms = math.hypot(sc.pulse_rms_s, 0.0)
        tof = sc.tof_s.reshape(sc.n_surfaces, -1)
        amp = sc.signal_pp.reshape(sc.n_surfaces, -1)
        for k in range(sc.n_surfaces):
            x = (edges[None, :] - tof[k][:, None]) / rms
            lam += amp[k][:, None] * np.diff(ndtr(x), axis=1)
        return lam

    @property
    def shape(self) -> tuple[int, int]:
        return self.scene.shape

    def frame_pairs(self, index: int) -> tuple[np.ndarray, np.ndarray]:
        """Frame ``index`` as (flat pixel * n_bins + bin, count) pairs, ascending: what memory and
        time of a sparse frame grow with."""
        s = self.settings
        h, w = self.shape
        rng = np.random.default_rng([self.seed, int(index)])
        n = rng.poisson(self.total)
        pix = np.repeat(np.arange(h * w), n)
        at = np.searchsorted(self._cdf, pix + rng.random(pix.size), side="right")
        tbin = np.minimum(at - pix * s.n_bins, s.n_bins - 1)
        flat = pix * s.n_bins + tbin
        if s.crosstalk > 0 and flat.size:
            fire = rng.random(flat.size) < s.crosstalk
            src = pix[fire]
            r, c = src // w, src % w
            d = rng.integers(0, 4, src.size)
            r2 = r + np.array([-1, 1, 0, 0])[d]
            c2 = c + np.array([0, 0, -1, 1])[d]
            inside = (r2 >= 0) & (r2 < h) & (c2 >= 0) & (c2 < w)
            flat = np.concatenate([flat, (r2 * w + c2)[inside] * s.n_bins + tbin[fire][inside]])
        keys, counts = np.unique(flat, return_counts=True)
        return keys, counts

    def frame(self, index: int) -> np.ndarray:
        """Frame ``index``: (H, W, n_bins) uint16 counts."""
        h, w = self.shape
        keys, counts = self.frame_pairs(index)
        out = np.zeros(h * w * self.settings.n_bins, np.uint16)
        out[keys] = counts
        return out.reshape(h, w, self.settings.n_bins)

    def truth(self) -> dict:
        """The scene's truth with the array's per-frame levels: signal and background counts per
        pixel in one frame with an ideal detector (no pile-up), hot pixels."""
        t = self.scene.truth()
        n = self.settings.periods_per_frame
        t["signal"] = self.scene.signal_pp.sum(axis=0) * n
        t["background"] = self.lam.sum(axis=1).reshape(self.shape) * n - t["signal"]
        t["hot"] = self.hot
        return t

    def info(self) -> dict:
        """JSON-able description (a recording's attributes)."""
        return {"device": "simulated SPAD array", "shape": list(self.shape), "seed": self.seed,
                "array": self.settings.to_dict(), "scene": self.scene.settings.to_dict()}


__all__ = ["ArraySettings", "SimSpadArray"]
