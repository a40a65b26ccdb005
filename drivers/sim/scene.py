"""A scene: what is there, how the laser, detector and tagger behave, and which physical effects
the simulator must compute. ``load_scene`` builds one from a name the way a user thinks of it
(``ppp`` detections per pixel, ``sbr`` signal-to-background ratio)."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import numpy as np

from spdepth.drivers.errors import SettingError
from spdepth.drivers.sim import scenes as _scenes

#: Speed of light in vacuum, m/s: exact by the SI's definition of the metre, the value recon.maps uses.
C_M_PER_S = 299_792_458.0

EFFECTS = ("jitter", "dead_time", "afterpulsing")
"""Effects a scene may name. Anything else of equation (3) (pulse shape, background, dark counts,
efficiency, tagger resolution and range) is always part of the base model."""

PILEUP_THRESHOLD = 0.05
"""Mean detections per pulse above which dead-time pile-up is no longer negligible, so the
scene switches the ``dead_time`` effect on even when not asked (Coates: the bias of the first
bins is of order the detections per pulse)."""

MAX_SIDE = 4096


@dataclass(frozen=True)
class SceneSettings:
    """How a scene is lit and observed. SI units; saved with every truth file.

    name:            scene name (built-in name or ``file:...`` spec).
    shape:           (H, W) pixels.
    ppp:             mean detections (signal + background + dark) per pixel in one dwell,
                     averaged over the image, with no dead time.
    sbr:             image-mean signal detections / image-mean background+dark detections
                     (``inf`` for no background).
    dwell_s:         the dwell the ``ppp`` refers to (fixed-dwell raster pixel time).
    sync_period_s:   laser repetition period (100 ns = 10 MHz).
    pulse_rms_s:     RMS width of the Gaussian pulse (ignored when a measured IRF is given).
    resolution_s:    tagger bin width (dtime unit).
    tagger_range_s:  detections later than this after their sync are not recorded (None: the
                     whole period).
    efficiency:      detection efficiency eta; ppp counts detections, so eta only converts them
                     to incident photons in the truth.
    dark_rate_hz:    detector dark-count rate (part of the background ppp/sbr imply).
    jitter_rms_s:    detector+tagger timing jitter, applied when ``jitter`` is in ``effects``.
    dead_time_s:     non-paralysable dead time, applied when ``dead_time`` is in ``effects`` or
                     pile-up requires it.
    afterpulse_prob: probability a registered detection releases an afterpulse.
    afterpulse_tau_s: mean delay of an afterpulse after the dead time ends.
    effects:         named effects (subset of ``EFFECTS``), as requested.
    channel:         detector channel the photons carry (0-based).
    irf_bin_s:       bin width of the measured instrument response, when the scene has one.
    """

    name: str
    shape: tuple[int, int]
    ppp: float = 15.0
    sbr: float = 10.0
    dwell_s: float = 1e-3
    sync_period_s: float = 100e-9
    pulse_rms_s: float = 360e-12
    resolution_s: float = 8e-12
    tagger_range_s: float | None = None
    efficiency: float = 0.35
    dark_rate_hz: float = 0.0
    jitter_rms_s: float = 50e-12
    dead_time_s: float = 50e-9
    afterpulse_prob: float = 0.01
    afterpulse_tau_s: float = 50e-9
    effects: tuple[str, ...] = ()
    channel: int = 0
    irf_bin_s: float | None = None

    def __post_init__(self):
        h, w = self.shape
        if not (1 <= h <= MAX_SIDE and 1 <= w <= MAX_SIDE):
            raise SettingError(f"scene size must be 1..{MAX_SIDE} pixels a side, got {w}x{h} (WxH)")
        positive = ("ppp", "sbr", "dwell_s", "sync_period_s", "resolution_s", "efficiency")
        for name in positive:
            v = getattr(self, name)
            if not (v > 0) or math.isnan(v) or (math.isinf(v) and name != "sbr"):
                raise SettingError(f"scene setting {name} must be positive and finite, got {v}")
        for name in ("pulse_rms_s", "dark_rate_hz", "jitter_rms_s", "dead_time_s",
                     "afterpulse_prob", "afterpulse_tau_s"):
            v = getattr(self, name)
            if not (v >= 0) or math.isinf(v):
                raise SettingError(f"scene setting {name} must be >= 0 and finite, got {v}")
        if self.efficiency > 1:
            raise SettingError(f"scene setting efficiency must be in (0, 1], got {self.efficiency}")
        if self.afterpulse_prob >= 0.5:
            raise SettingError(f"scene setting afterpulse_prob must be below 0.5, got {self.afterpulse_prob}")
        if self.resolution_s > self.sync_period_s:
            raise SettingError(f"tagger resolution {self.resolution_s} s exceeds the sync period "
                             f"{self.sync_period_s} s")
        if self.tagger_range_s is not None and not (0 < self.tagger_range_s):
            raise SettingError(f"scene setting tagger_range_s must be positive, got {self.tagger_range_s}")
        bad = [e for e in self.effects if e not in EFFECTS]
        if bad:
            raise SettingError(f"unknown effect(s) {', '.join(bad)}; known: {', '.join(EFFECTS)}")
        if not 0 <= self.channel < 63:
            raise SettingError(f"scene setting channel must be 0..62, got {self.channel}")

    @property
    def syncs_per_dwell(self) -> int:
        """Laser pulses in one dwell (at least 1)."""
        return max(1, int(round(self.dwell_s / self.sync_period_s)))

    @property
    def range_bins(self) -> int:
        """Tagger units a recorded dtime can take: dtime < range_bins."""
        span = self.sync_period_s if self.tagger_range_s is None else min(self.tagger_range_s,
                                                                          self.sync_period_s)
        return max(1, int(math.ceil(span / self.resolution_s - 1e-9)))

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        d["shape"] = list(self.shape)
        d["effects"] = list(self.effects)
        d["sbr"] = None if math.isinf(self.sbr) else self.sbr
        return d


@dataclass(frozen=True, eq=False)
class Scene:
    """A scene ready to simulate: geometry, light levels and the effects to compute.

    ``background_rel`` (H, W) is the geometry's relative ambient map.
    Per-pixel rates are mean *detections per laser pulse* with an ideal (dead-time-free)
    detector: ``signal_pp`` (K, H, W) per surface, ``background_pp`` (H, W) ambient + dark.
    ``active_effects`` is what the simulator runs: the named effects plus ``dead_time`` when the
    detections per pulse are not small (see ``PILEUP_THRESHOLD``).
    """

    settings: SceneSettings
    depth_m: np.ndarray
    reflectivity: np.ndarray
    occupancy: np.ndarray
    background_rel: np.ndarray
    signal_pp: np.ndarray
    background_pp: np.ndarray
    active_effects: tuple[str, ...]
    irf: np.ndarray | None = field(default=None)

    @property
    def shape(self) -> tuple[int, int]:
        return self.settings.shape

    @property
    def n_surfaces(self) -> int:
        return int(self.depth_m.shape[0])

    @property
    def sync_period_s(self) -> float:
        return self.settings.sync_period_s

    @property
    def resolution_s(self) -> float:
        return self.settings.resolution_s

    @property
    def pulse_rms_s(self) -> float:
        """RMS width of the pulse shape (of the measured IRF when there is one), seconds."""
        if self.irf is None:
            return self.settings.pulse_rms_s
        b = self.settings.irf_bin_s
        t = (np.arange(self.irf.size) + 0.5) * b
        w = self.irf / self.irf.sum()
        mean = float((w * t).sum())
        # + b^2/12: the simulator spreads each IRF bin uniformly
        return float(np.sqrt((w * (t - mean) ** 2).sum() + b * b / 12.0))

    @property
    def tof_s(self) -> np.ndarray:
        """(K, H, W) round-trip time of flight 2 d / c, seconds."""
        return 2.0 * self.depth_m / C_M_PER_S

    @property
    def dwell_s(self) -> float:
        return self.settings.dwell_s

    def rate_per_pulse(self) -> np.ndarray:
        """(H, W) mean detections per pulse (signal + background) with an ideal detector."""
        return self.signal_pp.sum(axis=0) + self.background_pp

    def bin_rates(self, row: int, col: int, n_pulses: float = 1.0) -> np.ndarray:
        """Equation (3): expected detections per tagger bin of pixel (row, col) over ``n_pulses``
        pulses with an ideal detector and no effects, shape (range_bins,). Gaussian pulses only
        (a measured IRF is integrated by its table)."""
        from scipy.special import ndtr

        s = self.settings
        nb = s.range_bins
        edges = np.arange(nb + 1) * s.resolution_s
        T = s.sync_period_s
        out = np.full(nb, self.background_pp[row, col] * s.resolution_s / T)
        out[-1] = self.background_pp[row, col] * (min(edges[-1], T) - edges[-2]) / T
        for k in range(self.n_surfaces):
            a = self.signal_pp[k, row, col]
            if a == 0:
                continue
            tof = float(self.tof_s[k, row, col])
            cdf = np.zeros(nb + 1)
            # the folded (periodic) pulse: sum the copies a period apart that reach the window
            for m in range(-2, 3):
                x = edges - tof + m * T
                if self.irf is None:
                    if s.pulse_rms_s == 0:
                        cdf += (x >= 0).astype(float)
                    else:
                        cdf += ndtr(x / s.pulse_rms_s)
                else:
                    cdf += _table_cdf(self.irf, s.irf_bin_s, x)
            out += a * np.diff(cdf)
        return out * n_pulses

    def truth(self) -> dict:
        """The truth of the scene.

        depth_m, tof_s, reflectivity: (H, W) for one surface, (K, H, W) for several.
        occupancy: (K, H, W). signal, background: (H, W) mean signal and background+dark
        detections per pixel in one dwell (ideal detector). signal_pp, background_pp: the same per
        laser pulse. settings: dict of the ``SceneSettings`` plus the active effects.
        """
        one = self.n_surfaces == 1
        squeeze = (lambda a: a[0]) if one else (lambda a: a)
        n = self.settings.syncs_per_dwell
        settings = self.settings.to_dict()
        settings["active_effects"] = list(self.active_effects)
        settings["measured_irf"] = None if self.irf is None else self.irf.tolist()
        return {
            "depth_m": squeeze(self.depth_m).copy(),
            "tof_s": squeeze(self.tof_s),
            "reflectivity": squeeze(self.reflectivity).copy(),
            "occupancy": self.occupancy.copy(),
            "signal": self.signal_pp.sum(axis=0) * n,
            "background": self.background_pp * n,
            "signal_pp": squeeze(self.signal_pp).copy(),
            "background_pp": self.background_pp.copy(),
            "settings": settings,
        }

    def with_settings(self, **changes) -> "Scene":
        """The same geometry with some settings changed (light levels rescaled)."""
        geom = _scenes.Geometry(self.depth_m, self.reflectivity, self.occupancy,
                                self.background_rel, {})
        return _build(geom, dataclasses.replace(self.settings, **changes), self.irf)


def _table_cdf(irf, bin_s, x):
    """CDF of the measured IRF (mean shifted to 0, uniform within bins) at times x."""
    w = np.asarray(irf, float) / np.sum(irf)
    t0 = -float((w * (np.arange(w.size) + 0.5) * bin_s).sum())
    c = np.concatenate([[0.0], np.cumsum(w)])
    pos = (x - t0) / bin_s
    j = np.clip(np.floor(pos).astype(np.int64), 0, w.size - 1)
    frac = np.clip(pos - j, 0, 1)
    out = c[j] + frac * w[j]
    out = np.where(pos < 0, 0.0, out)
    return np.where(pos >= w.size, 1.0, out)


@dataclass(frozen=True)
class _Light:
    """How a scene's geometry becomes rates: signal_pp = amp * signal_per_amp, background_pp =
    background_rel * background_per_rel + dark_pp (per laser pulse); ``active`` its effects."""

    signal_per_amp: float
    background_per_rel: float
    dark_pp: float
    active: tuple[str, ...]


def _light(s: SceneSettings, mean_amp: float, bg_rel_mean: float, max_rate) -> _Light:
    """The scale factors of ``s``'s light levels for a geometry whose signal strength
    (reflectivity x occupancy, summed over surfaces) averages ``mean_amp`` and whose relative
    background averages ``bg_rel_mean``; ``max_rate(light)`` the largest detections per pulse
    those factors give a pixel (it decides the dead time's pile-up)."""
    n = s.syncs_per_dwell
    if not mean_amp > 0:
        raise SettingError(f"scene {s.name}: nothing reflects (all reflectivity x occupancy is 0)")
    if math.isinf(s.sbr):
        sig_mean, bg_mean = s.ppp / n, 0.0
    else:
        sig_mean = s.ppp * s.sbr / (1.0 + s.sbr) / n
        bg_mean = s.ppp / (1.0 + s.sbr) / n
    dark_pp = s.dark_rate_hz * s.sync_period_s
    ambient_mean = bg_mean - dark_pp
    if ambient_mean < -1e-12 * max(bg_mean, 1e-300):
        raise SettingError(
            f"dark-count rate {s.dark_rate_hz} Hz alone gives {dark_pp * n:.3g} detections per "
            f"pixel, more than the {bg_mean * n:.3g} background detections ppp={s.ppp} and "
            f"sbr={s.sbr} allow")
    ambient_mean = max(ambient_mean, 0.0)
    light = _Light(sig_mean / mean_amp, ambient_mean / bg_rel_mean, dark_pp, ())
    active = list(e for e in EFFECTS if e in s.effects)
    if "dead_time" not in active and s.dead_time_s > 0:
        if max_rate(light) > PILEUP_THRESHOLD:
            active.insert(1 if "jitter" in active else 0, "dead_time")
    return dataclasses.replace(light, active=tuple(active))


def _rates(geom: _scenes.Geometry, light: _Light) -> tuple[np.ndarray, np.ndarray]:
    """(signal_pp (K, H, W), background_pp (H, W)) of a geometry (or a band of its rows)."""
    amp = geom.reflectivity * geom.occupancy
    bg_rel = np.asarray(geom.background, np.float64)
    return amp * light.signal_per_amp, bg_rel * light.background_per_rel + light.dark_pp


def _check_background(name: str, bg_rel: np.ndarray) -> None:
    if np.any(bg_rel < 0) or not np.all(np.isfinite(bg_rel)) or bg_rel.mean() <= 0:
        raise SettingError(f"scene {name}: background map must be finite, >= 0 and not all 0")


def _check_irf(s: SceneSettings, irf):
    if irf is None:
        return None
    irf = np.asarray(irf, np.float64).ravel()
    if irf.size < 1 or np.any(irf < 0) or not np.all(np.isfinite(irf)) or irf.sum() <= 0:
        raise SettingError("measured IRF must be a non-empty array of finite values >= 0, not all 0")
    if s.irf_bin_s is None or not s.irf_bin_s > 0:
        raise SettingError("a measured IRF needs its bin width irf_bin_s > 0")
    return irf


def _build(geom: _scenes.Geometry, settings: SceneSettings, irf, light: _Light | None = None) -> Scene:
    """The scene of a whole geometry; ``light`` the scale factors to use (a lazy scene's, taken
    from its sampled rows), else those of this geometry's own means."""
    s = settings
    amp = geom.reflectivity * geom.occupancy
    bg_rel = np.asarray(geom.background, np.float64)
    if light is None:
        mean_amp = float(amp.sum(axis=0).mean())
        if mean_amp > 0:
            _check_background(s.name, bg_rel)
        light = _light(s, mean_amp, float(bg_rel.mean()), lambda lt: float(
            ((amp * lt.signal_per_amp).sum(axis=0) + (bg_rel * lt.background_per_rel + lt.dark_pp)).max()))
    signal_pp, background_pp = _rates(geom, light)
    if geom.depth_m.shape[1:] != s.shape:
        raise SettingError(f"scene {s.name}: geometry shape {geom.depth_m.shape[1:]} != {s.shape}")
    return Scene(s, np.asarray(geom.depth_m, np.float64), np.asarray(geom.reflectivity, np.float64),
                 np.asarray(geom.occupancy, np.float64), bg_rel, signal_pp, background_pp, light.active,
                 _check_irf(s, irf))


LAZY_PIXELS = 1 << 21
"""Built-in scenes of more pixels than this (above 2048 x 1024) are built lazily
(:class:`LazyScene`): a band of rows when the galvo first reaches it, never the whole frame up
front (a 4096 x 4096 frame's maps are gigabytes and took seconds to build)."""
SAMPLE_ROWS = 256
"""Rows of a lazy scene its light levels are scaled by (evenly spread over the frame)."""


class LazyScene:
    """A built-in scene too large to build whole before a scan: the same interface as
    :class:`Scene`, its rates computed a band of rows at a time (:meth:`band`) as the simulated
    galvo reaches them.

    Its light levels (``ppp`` and ``sbr`` are image means) and the pile-up decision are taken
    from ``SAMPLE_ROWS`` rows spread evenly over the frame instead of every pixel, so the image
    means hold to the sampling's precision (within 4e-4 on the built-in scenes) instead of
    exactly. The whole-frame maps (``depth_m``, ``signal_pp``, ``truth()``, ...) are built on
    first use, with the same scale factors, so they are the truth of the detections simulated.
    """

    lazy = True

    def __init__(self, builder, settings: SceneSettings, irf=None):
        self.settings = settings
        self._builder = builder
        h, w = settings.shape
        rows = np.unique(np.linspace(0, h - 1, min(h, SAMPLE_ROWS)).round().astype(np.int64))
        parts = [builder(settings.shape, rows=(int(r), int(r) + 1)) for r in rows]
        amp = np.concatenate([(g.reflectivity * g.occupancy).sum(axis=0) for g in parts])
        bg_rel = np.concatenate([np.asarray(g.background, np.float64) for g in parts])
        self._n_surfaces = int(parts[0].depth_m.shape[0])
        mean_amp = float(amp.mean())
        if mean_amp > 0:
            _check_background(settings.name, bg_rel)
        self._light = _light(settings, mean_amp, float(bg_rel.mean()), lambda lt: float(
            (amp * lt.signal_per_amp + (bg_rel * lt.background_per_rel + lt.dark_pp)).max()))
        self.active_effects = self._light.active
        self.irf = _check_irf(settings, irf)
        self._full: Scene | None = None

    def band(self, r0: int, r1: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(signal_pp (K, n, W), tof_s (K, n, W), background_pp (n, W)) of rows r0..r1-1."""
        geom = self._builder(self.settings.shape, rows=(r0, r1))
        signal_pp, background_pp = _rates(geom, self._light)
        return signal_pp, 2.0 * np.asarray(geom.depth_m, np.float64) / C_M_PER_S, background_pp

    def full(self) -> Scene:
        """The whole frame as a :class:`Scene` (built once, on first use), with this scene's
        scale factors."""
        if self._full is None:
            self._full = _build(self._builder(self.settings.shape), self.settings, self.irf, self._light)
        return self._full

    shape = Scene.shape
    sync_period_s = Scene.sync_period_s
    resolution_s = Scene.resolution_s
    pulse_rms_s = Scene.pulse_rms_s
    dwell_s = Scene.dwell_s

    @property
    def n_surfaces(self) -> int:
        return self._n_surfaces

    _FULL = frozenset({"depth_m", "reflectivity", "occupancy", "background_rel", "signal_pp",
                       "background_pp", "tof_s", "truth", "rate_per_pulse", "bin_rates", "with_settings"})
    """What only the whole frame answers: asked for, it is built (gigabytes at 4096 x 4096)."""

    def __getattr__(self, name: str):
        # only the names of the whole frame build it: a probe for anything else (getattr with a
        # default) must not build 4096 x 4096 maps as a side effect
        if name not in LazyScene._FULL:
            raise AttributeError(f"{type(self).__name__!r} object has no attribute {name!r}")
        return getattr(self.full(), name)


def scene_names() -> list[str]:
    """Names of the built-in scenes (``file:PATH`` loads a depth image)."""
    return sorted(_scenes.BUILTIN)


def load_scene(name: str, shape: tuple[int, int] | None = None, *, ppp: float = 15.0,
               sbr: float | None = None, irf: np.ndarray | None = None,
               **settings) -> "Scene | LazyScene":
    """Build a scene.

    name:  a built-in scene (``scene_names()``: bust, daylight, steps, tilted-plane, two-layer)
           or ``file:PATH[,reflectivity=PATH][,scale=M_PER_UNIT][,offset=M]`` for a depth image
           (.npy, .png, .tif/.tiff; float images in metres, integer images in mm unless scale).
    shape: (H, W) pixels, rows first like NumPy. Default 64 x 64 for built-in scenes, the
           image's own shape for files.
    ppp:   mean detections per pixel per dwell; sbr: signal-to-background ratio (default the
           scene's, 10 for most, 0.05 for daylight).
    irf:   a measured instrument response (histogram, any scale) replacing the Gaussian pulse;
           give ``irf_bin_s`` too.
    settings: any other ``SceneSettings`` field (dwell_s, sync_period_s, effects, ...).
    A built-in scene of more than ``LAZY_PIXELS`` pixels is a :class:`LazyScene` (built a band of
    rows at a time as it is scanned).
    Raises SettingError for an unknown scene or a bad setting.
    """
    if shape is not None:
        try:
            shape = (int(shape[0]), int(shape[1]))
        except (TypeError, ValueError, IndexError):
            raise SettingError(f"scene shape must be (H, W), got {shape!r}") from None
        if not (1 <= shape[0] <= MAX_SIDE and 1 <= shape[1] <= MAX_SIDE):
            raise SettingError(f"scene size must be 1..{MAX_SIDE} pixels a side, got {shape} (H, W)")
    if name.startswith("file:"):
        geom = _scenes.from_file(name, shape)
        shape = geom.depth_m.shape[1:]
    elif name in _scenes.BUILTIN:
        shape = shape or (64, 64)
        geom = None if shape[0] * shape[1] > LAZY_PIXELS else _scenes.BUILTIN[name](shape)
    else:
        raise SettingError(f"unknown scene {name!r}; built-in scenes: {', '.join(scene_names())}, "
                         "or file:PATH for a depth image")
    if sbr is None:
        sbr = (geom.defaults if geom is not None else _scenes.BUILTIN[name]((1, 1)).defaults).get("sbr", 10.0)
    if "effects" in settings:
        eff = settings["effects"]
        settings["effects"] = tuple(eff.split(",")) if isinstance(eff, str) else tuple(eff)
    try:
        s = SceneSettings(name=name, shape=tuple(shape), ppp=float(ppp), sbr=float(sbr), **settings)
    except TypeError as exc:
        raise SettingError(f"bad scene setting: {exc}") from None
    if geom is None:
        return LazyScene(_scenes.BUILTIN[name], s, irf)
    return _build(geom, s, irf)
