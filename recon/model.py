"""Forward model of the seed paper (Shin, Shapiro, Goyal 2015, eqs. 1-7): binning, pulse kernel, and
the settings of a reconstruction.

The paper's matrix ``A = [S, 1]`` is never built. ``S`` is shift-invariant: column ``i`` (a return
whose pulse centroid sits at the centre of bin ``i``) holds ``g[k - i]`` in row ``k``, where ``g`` is
the pulse integrated over one bin (eq. 5 with ``epsilon = Delta``, so N = M as in the paper's
experiments). :class:`PulseKernel` keeps ``g`` as a short 1-D table plus the few precomputed
quantities the estimators need (column sums ``S_i^T 1``, column inner products ``S_i^T S_j`` via
prefix sums, a finely sampled copy for sub-bin shifts, and ``log g`` for the log-matched filter).

Times: raw units are multiples of ``time_unit_s`` (the time tagger's resolution); a pixel's detection
times are in raw units after the laser sync. SI seconds everywhere else.
"""

from __future__ import annotations

import functools
import json
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from spdepth.recon.errors import InputError

#: Relative level below which the pulse is treated as zero (kernel truncation for uos/ml). The
#: truncated tail carries less than ~1e-10 of the pulse energy for a Gaussian.
KERNEL_TAIL_REL = 1e-10
#: Sub-bin steps per bin of the fine kernel table used for the ml estimator's sub-bin refinement.
FINE_STEPS = 8
#: Pulse kernels kept by :func:`build_kernel` (the most recently used): a live scan reconstructs
#: batch after batch with one pulse, and the tables took half of a 1,024-pixel batch of ml. Few,
#: since a kernel's pair table grows as the square of the pulse's length in bins (~1 MB for the
#: paper's pulse, up to ~270 MB for a measured response spanning 4,096 bins).
KERNEL_CACHE = 2
#: The most bins a default binning makes (``default_bin_width``). 4096, not fewer: it keeps the
#: pulse-RMS/9 bins (the paper's 40 ps for a 360 ps pulse) over windows up to 164 ns, a whole
#: 10 MHz laser period or a 24 m range gate, where 1024 would coarsen the bins of any window past
#: 41 ns (and the lmf estimate is a whole bin).
#: The estimators hold no pixels x bins arrays, so the price of more bins is time linear in bins per
#: pixel; the cap only stops absurd counts (a ps-unit file with a 200 ns gate would get 200,000).
DEFAULT_MAX_BINS = 4096
#: The Fisher table (:func:`fisher_table`, read by ``recon.kernels.fisher_tab``): rows at log(a / bg)
#: from FISHER_RHO0, FISHER_STEPS per unit, FISHER_SPAN units (a / bg from 2e-9 to 8e23; a pixel off
#: it takes the loop)
FISHER_RHO0 = -20.0
FISHER_STEPS = 16
FISHER_SPAN = 75


def _ps(value_s, what: str) -> float:
    """``value_s`` seconds in ps, rounded to 14 significant digits: a value written in ps and
    converted (``16000 * 1e-12``) comes back as that ps value exactly (16000.000000000002 would
    not), so windows in seconds and in ps give bit-identical bins. 14 digits keep 0.01 fs at 100
    us, far below any tagger's resolution. InputError naming ``what`` when it is not finite."""
    try:
        v = float(value_s) * 1e12
    except (TypeError, ValueError):
        raise InputError(f"{what} must be a number of seconds, got {value_s!r}") from None
    if not math.isfinite(v):
        raise InputError(f"{what} {v:g} ps is not finite")
    return float(f"{v:.14g}")


def _unit_ps(time_unit_s) -> float:
    """The raw time unit in ps (:func:`_ps`); InputError unless positive."""
    unit_ps = _ps(time_unit_s, "time unit")
    if not unit_ps > 0:
        raise InputError(f"time unit {unit_ps:g} ps must be positive")
    return unit_ps


def _window_units(window_s, unit_ps: float) -> tuple[float, float]:
    """A (start_s, stop_s) window in raw units of ``unit_ps`` (:func:`_ps` first)."""
    try:
        start_s, stop_s = window_s
    except (TypeError, ValueError):
        raise InputError(f"window must be (start_s, stop_s), got {window_s!r}") from None
    return _ps(start_s, "window start") / unit_ps, _ps(stop_s, "window stop") / unit_ps


@dataclass(frozen=True)
class Binning:
    """How detection times become histogram bins.

    time_unit_s:  size of one raw time unit in seconds (e.g. 8e-12).
    window_start: first time kept, raw units, inclusive.
    window_stop:  end of the window, raw units, exclusive.
    bin_width:    bin width, raw units. Bin ``k`` covers
                  ``[window_start + k*bin_width, window_start + (k+1)*bin_width)``; there are
                  ``ceil((window_stop - window_start) / bin_width)`` bins (a last partial bin counts
                  as a full one, so the paper's [2000, 6005) window of 5-unit bins gives 801 bins).

    Detections outside ``[window_start, window_stop)`` are dropped (``bin_index`` gives -1), never
    clamped into the edge bins.
    """

    time_unit_s: float
    window_start: float
    window_stop: float
    bin_width: float

    def __post_init__(self) -> None:
        for name in ("time_unit_s", "window_start", "window_stop", "bin_width"):
            v = getattr(self, name)
            if not isinstance(v, (int, float, np.integer, np.floating)) or not math.isfinite(v):
                raise InputError(f"binning {name} must be a finite number, got {v!r}")
            object.__setattr__(self, name, float(v))
        if self.time_unit_s <= 0:
            raise InputError(f"binning time_unit_s must be positive, got {self.time_unit_s}")
        if self.bin_width <= 0:
            raise InputError(f"binning bin_width must be positive, got {self.bin_width}")
        if not self.window_stop > self.window_start:
            raise InputError(f"binning window [{self.window_start}, {self.window_stop}) holds no bin: "
                             "stop must exceed start")
        if self.n_bins > 1_000_000:
            raise InputError(f"binning gives {self.n_bins} bins (more than 1,000,000): widen bin_width")

    @classmethod
    def from_window(cls, time_unit_s: float, window_s: tuple[float, float], bin_s: float) -> "Binning":
        """THE binning rule from SI seconds: raw unit, ``(start_s, stop_s)`` window and bin width.

        The window becomes ``start/unit, stop/unit`` raw units (fractions allowed); the bin must be a
        whole number of raw units (relative tolerance 1e-6) and becomes exactly that number. Values
        are taken to 14 significant digits in ps first (:func:`_ps`), so ``16000e-12`` over
        ``8e-12`` is unit 2000 as ``16000 / 8`` is, not 2000.0000000000002: a window written in ps
        and one written in seconds give the same bins (and :meth:`from_ps` the same Binning).
        Raises InputError naming the value in ps: a non-finite or negative value, a unit or bin
        that is not positive, an empty window, a bin that is not a whole number of raw units or
        is wider than the window."""
        unit_ps = _unit_ps(time_unit_s)
        start_u, stop_u = _window_units(window_s, unit_ps)
        return cls._from_raw(time_unit_s, unit_ps, start_u, stop_u, _ps(bin_s, "bin") / unit_ps)

    @classmethod
    def from_data(cls, times, time_unit_s: float, *, window_s: tuple[float, float] | None = None,
                  bin_s: float | None = None, pulse_rms_s: float | None = None) -> "Binning":
        """Binning for detection ``times`` (raw units) with the window and/or bin width left out.

        window_s: (start_s, stop_s); default the span of the detections, whole raw units
                  ``[floor(min), floor(max) + 1)``.
        bin_s:    bin width, a whole number of raw units; default :func:`default_bin_width` of the
                  window's span (a ninth of ``pulse_rms_s`` in whole raw units, else one unit; at
                  most DEFAULT_MAX_BINS bins).
        Given values are checked as :meth:`from_window` checks them; a default bin wider than
        the window (detections spanning less than a ninth of the pulse) makes one bin, as the
        detections say no more. (With both left out and no pulse width this is not what
        ``ReconSettings(binning=None)`` does: that derives the bins from the pulse measured in the
        data.)"""
        unit_ps = _unit_ps(time_unit_s)
        if window_s is not None:
            start_u, stop_u = _window_units(window_s, unit_ps)
        else:
            t = np.asarray(times, dtype=np.float64)
            if t.size == 0:
                raise InputError("cannot take the window from data without detections; give a window")
            start_u = float(math.floor(float(t.min())))
            stop_u = float(math.floor(float(t.max())) + 1)
        if bin_s is not None:
            bin_u = _ps(bin_s, "bin") / unit_ps
        else:
            rms_u = None if pulse_rms_s is None else _ps(pulse_rms_s, "pulse RMS") / unit_ps
            bin_u = default_bin_width(stop_u - start_u, rms_u)
        return cls._from_raw(time_unit_s, unit_ps, start_u, stop_u, bin_u, bin_given=bin_s is not None)

    @classmethod
    def _from_raw(cls, time_unit_s: float, unit_ps: float, start_u: float, stop_u: float,
                  bin_u: float, bin_given: bool = True) -> "Binning":
        """Checks of :meth:`from_window` on a window and bin already in raw units (a bin that is
        not ``bin_given`` may be wider than the window)."""
        start_ps, stop_ps = start_u * unit_ps, stop_u * unit_ps
        if start_u < 0:
            raise InputError(f"window start {start_ps:g} ps is negative")
        if not stop_u > start_u:
            raise InputError(f"window {start_ps:g}-{stop_ps:g} ps is empty: stop must exceed start")
        bin_ps = bin_u * unit_ps
        if not bin_u > 0:
            raise InputError(f"bin {bin_ps:g} ps must be positive")
        whole = round(bin_u)
        if abs(bin_u - whole) > 1e-6 * max(1.0, bin_u) or whole < 1:
            raise InputError(f"bin {bin_ps:g} ps is not a whole number of {unit_ps:g} ps raw units")
        if bin_given and whole > (stop_u - start_u) * (1.0 + 1e-9):
            raise InputError(f"bin {bin_ps:g} ps is wider than the window {start_ps:g}-{stop_ps:g} ps")
        return cls(time_unit_s, start_u, stop_u, float(whole))

    @classmethod
    def from_ps(cls, time_unit_ps: float, window_ps: tuple[float, float], bin_ps: float) -> "Binning":
        """:meth:`from_window` with the raw unit, (start, stop) window and bin width in ps."""
        try:
            start_ps, stop_ps = (float(v) for v in window_ps)
        except (TypeError, ValueError):
            raise InputError(f"window must be (start_ps, stop_ps), got {window_ps!r}") from None
        return cls.from_window(time_unit_ps * 1e-12, (start_ps * 1e-12, stop_ps * 1e-12), bin_ps * 1e-12)

    @property
    def n_bins(self) -> int:
        # tolerance so a window that is a whole number of bins in ps does not gain a sliver bin
        return max(1, int(math.ceil((self.window_stop - self.window_start) / self.bin_width - 1e-9)))

    @property
    def bin_width_s(self) -> float:
        return self.bin_width * self.time_unit_s

    @property
    def window_start_s(self) -> float:
        return self.window_start * self.time_unit_s

    @property
    def window_stop_s(self) -> float:
        return self.window_stop * self.time_unit_s

    def bin_index(self, times) -> np.ndarray:
        """Bin of each time (raw units), int64, -1 outside ``[window_start, window_stop)``."""
        t = np.asarray(times, dtype=np.float64)
        inside = (t >= self.window_start) & (t < self.window_stop)
        k = np.floor((t - self.window_start) / self.bin_width)
        # floating rounding at the stop edge must not create bin n_bins
        k = np.minimum(k, self.n_bins - 1)
        return np.where(inside, k, -1).astype(np.int64)

    def shift_to_time_s(self, shift) -> np.ndarray:
        """Time (s) of the pulse centroid for a (fractional) shift in bins: centre of bin ``shift``."""
        return (self.window_start + (np.asarray(shift, dtype=np.float64) + 0.5) * self.bin_width) \
            * self.time_unit_s

    def to_dict(self) -> dict:
        return {"time_unit_s": self.time_unit_s, "window_start": self.window_start,
                "window_stop": self.window_stop, "bin_width": self.bin_width, "n_bins": self.n_bins}

    @classmethod
    def from_dict(cls, d: dict) -> "Binning":
        """Back from :meth:`to_dict` (``n_bins`` is derived, not read)."""
        try:
            return cls(d["time_unit_s"], d["window_start"], d["window_stop"], d["bin_width"])
        except (KeyError, TypeError):
            raise InputError(f"a saved binning needs time_unit_s, window_start, window_stop and "
                             f"bin_width, got {d!r}") from None


@dataclass(frozen=True)
class Irf:
    """A measured instrument response: the pulse shape as detected (laser, detector jitter, tagger).

    times_s: sample times, seconds, strictly increasing, evenly or unevenly spaced.
    counts:  counts (or any non-negative weights) per sample; only the shape matters.
    source:  where it came from (file name), for the record.

    The pulse's reference point is its centroid: a return reported at ``tof_s`` has its detected
    pulse centroid at ``tof_s`` (the IRF's own time origin does not matter).
    """

    times_s: tuple
    counts: tuple
    source: str = ""

    def __post_init__(self) -> None:
        t = np.asarray(self.times_s, dtype=np.float64).ravel()
        c = np.asarray(self.counts, dtype=np.float64).ravel()
        where = f"IRF {self.source}" if self.source else "IRF"
        if t.size != c.size:
            raise InputError(f"{where}: {t.size} times but {c.size} counts")
        if t.size < 2:
            raise InputError(f"{where}: needs at least 2 samples, got {t.size}")
        if not np.all(np.isfinite(t)) or not np.all(np.isfinite(c)):
            raise InputError(f"{where}: contains NaN or infinite values")
        if np.any(c < 0):
            raise InputError(f"{where}: negative counts (first at sample {int(np.argmax(c < 0))})")
        if np.any(np.diff(t) <= 0):
            raise InputError(f"{where}: times must be strictly increasing")
        if not c.sum() > 0:
            raise InputError(f"{where}: all counts are zero")
        object.__setattr__(self, "times_s", tuple(float(v) for v in t))
        object.__setattr__(self, "counts", tuple(float(v) for v in c))

    def arrays(self) -> tuple[np.ndarray, np.ndarray]:
        return np.asarray(self.times_s), np.asarray(self.counts)

    @property
    def rms_s(self) -> float:
        t, c = self.arrays()
        mean = np.sum(t * c) / c.sum()
        return float(np.sqrt(np.sum(c * (t - mean) ** 2) / c.sum()))

    def to_dict(self) -> dict:
        return {"times_s": list(self.times_s), "counts": list(self.counts), "source": self.source}

    @classmethod
    def from_dict(cls, d: dict) -> "Irf":
        """Back from :meth:`to_dict` (other keys, such as a recorded ``rms_s``, are ignored)."""
        try:
            return cls(tuple(d["times_s"]), tuple(d["counts"]), d.get("source", ""))
        except (KeyError, TypeError):
            raise InputError("a saved pulse shape needs times_s and counts") from None


def load_irf(path) -> Irf:
    """Read a measured instrument response.

    Accepted: a text/CSV file with two columns, time in ps and counts (comma, tab or space separated;
    lines starting with ``#`` and one header line of non-numbers are skipped), or a ``.npy`` array of
    shape (n, 2) with the same columns. Raises InputError naming the file for anything else, NaN,
    negative counts, non-increasing times or an all-zero response.
    """
    p = Path(path)
    if not p.is_file():
        raise InputError(f"IRF file {p} not found")
    if p.suffix.lower() == ".npy":
        try:
            arr = np.load(p, allow_pickle=False)
        except (ValueError, OSError, EOFError) as exc:
            raise InputError(f"IRF file {p}: not a readable .npy array ({exc})") from None
        arr = np.asarray(arr)
        if arr.ndim != 2 or arr.shape[1] != 2 or not np.issubdtype(arr.dtype, np.number):
            raise InputError(f"IRF file {p}: expected a numeric (n, 2) array of time ps, counts; "
                             f"got shape {arr.shape} dtype {arr.dtype}")
    else:
        try:
            text = p.read_text(encoding="utf-8")
        except (UnicodeDecodeError, OSError) as exc:
            raise InputError(f"IRF file {p}: not a text file ({exc})") from None
        rows = []
        header_seen = False
        for lineno, line in enumerate(text.splitlines(), 1):
            s = line.strip()
            if not s or s.startswith("#"):
                continue
            parts = [q for q in s.replace(",", " ").replace(";", " ").replace("\t", " ").split() if q]
            try:
                vals = [float(q) for q in parts]
            except ValueError:
                if not rows and not header_seen:
                    header_seen = True   # one header line such as "time_ps,counts"
                    continue
                raise InputError(f"IRF file {p}, line {lineno}: not numbers: {s[:60]!r}") from None
            if len(vals) != 2:
                raise InputError(f"IRF file {p}, line {lineno}: expected 2 columns (time ps, counts), "
                                 f"got {len(vals)}")
            rows.append(vals)
        if not rows:
            raise InputError(f"IRF file {p}: no data rows")
        arr = np.asarray(rows, dtype=np.float64)
    arr = arr.astype(np.float64)
    if not np.all(np.isfinite(arr)):
        raise InputError(f"IRF file {p}: contains NaN or infinite values")
    return Irf(tuple(arr[:, 0] * 1e-12), tuple(arr[:, 1]), source=str(p))


def save_irf(irf: Irf, path) -> Path:
    """Write ``irf`` in the format :func:`load_irf` reads: ``.npy`` (n, 2) array of time ps and
    counts for a ``.npy`` name, else CSV text with a ``time_ps,counts`` header and a comment line
    saying where it came from. Returns the path."""
    p = Path(path)
    t, c = irf.arrays()
    table = np.stack([t * 1e12, c], axis=1)
    try:
        if p.suffix.lower() == ".npy":
            np.save(p, table)
        else:
            with open(p, "w", encoding="utf-8") as f:
                f.write(f"# instrument response, {irf.source or 'spdepth'}; RMS {irf.rms_s * 1e12:.4g} ps\n")
                f.write("time_ps,counts\n")
                for a, b in table:
                    f.write(f"{a:.6f},{b:.9g}\n")
    except OSError as exc:
        raise InputError(f"IRF file {p}: cannot write ({exc.strerror or exc})") from None
    return p


def gaussian_irf(rms_s: float, source: str = "Gaussian") -> Irf:
    """A Gaussian response of RMS ``rms_s`` sampled at a twentieth of it over +-6 RMS."""
    t = np.linspace(-6.0, 6.0, 241) * rms_s
    return Irf(tuple(t), tuple(np.exp(-0.5 * (t / rms_s) ** 2)), source=source)


def irf_core_rms_s(irf: Irf) -> float:
    """Width (s) of a response's sharp part: its leading edge read as a Gaussian's (10% to 90% of
    the peak over 2.563), never more than its RMS. For a Gaussian, its RMS."""
    t, c = irf.arrays()
    if t.size < 3 or not np.allclose(np.diff(t), t[1] - t[0], rtol=1e-6):
        return irf.rms_s
    return float(min(edge_core_rms(c, t[1] - t[0]), irf.rms_s))


#: FWHM of a Gaussian over its RMS, 2 sqrt(2 ln 2)
FWHM_PER_RMS = 2.0 * math.sqrt(2.0 * math.log(2.0))


def irf_fwhm_rms_s(irf: Irf) -> float:
    """RMS (s) of the Gaussian with a response's FWHM: the width of where most of a return's
    detections lie, which a sharp edge and a long tail make far wider than the edge and far
    narrower than the RMS. For a Gaussian, its RMS."""
    t, c = irf.arrays()
    c = np.asarray(c, np.float64)
    if t.size < 3:
        return irf.rms_s
    pk = int(np.argmax(c))
    half = 0.5 * c[pk]

    def at(x: float) -> float:          # the time at a fractional sample index
        j = min(int(x), t.size - 2)
        return float(t[j] + (x - j) * (t[j + 1] - t[j]))

    width = at(level_crossing(c, pk, half, 1)) - at(level_crossing(c, pk, half, -1))
    return float(min(width / FWHM_PER_RMS, irf.rms_s))


def level_crossing(shape: np.ndarray, pk: int, level: float, side: int) -> float:
    """Where a sampled response ``shape`` falls below ``level`` walking from its peak sample ``pk``
    towards ``side`` (-1: earlier, 1: later), as a fractional sample index (linear between
    samples; the end sample if it never does)."""
    j = pk
    while 0 <= j + side < shape.size and shape[j + side] >= level:
        j += side
    if not 0 <= j + side < shape.size:
        return float(j)
    near, far = shape[j], shape[j + side]
    return (j + side) - side * (level - far) / (near - far) if near > far else float(j)


def edge_core_rms(shape: np.ndarray, step: float) -> float:
    """Core RMS (units of ``step``) of a sampled response from its leading edge: 10% to 90% of the
    peak spans 2.563 RMS of a Gaussian (linear interpolation between samples)."""
    pk = int(np.argmax(shape))
    peak = shape[pk]
    rise = level_crossing(shape, pk, 0.9 * peak, -1) - level_crossing(shape, pk, 0.1 * peak, -1)
    return float(max(rise * step / 2.563, 0.5 * step))


class MethodNames(Sequence):
    """The ``--method`` names the registry (:mod:`recon.estimators`) holds, read afresh at every use
    (an estimator registered later is in it), like a tuple: ``in``, iteration, ``index``, ``==``.
    The registry is imported on first use, not with this module."""

    def __init__(self, pixelwise: bool | None = None):
        self._pixelwise = pixelwise

    def _names(self) -> tuple[str, ...]:
        from spdepth.recon import estimators

        return estimators.names(self._pixelwise)

    def __getitem__(self, i):
        return self._names()[i]

    def __len__(self) -> int:
        return len(self._names())

    def __eq__(self, other) -> bool:
        return tuple(self) == tuple(other) if isinstance(other, (tuple, list, Sequence)) else NotImplemented

    def __hash__(self):
        return hash(self._names())

    def __add__(self, other):
        return self._names() + tuple(other)

    def __repr__(self) -> str:
        return repr(self._names())


#: Every estimator's name (``recon.estimators.names()``), in registration order: lmf, uos, ml,
#: spatial, then any plugin's.
METHODS = MethodNames()
#: The estimators that fit each pixel on its own (``recon.estimators.get(name).pixelwise``).
PIXELWISE_METHODS = MethodNames(pixelwise=True)
#: Most surfaces per pixel any estimator fits (``reflectors`` K, ``max_reflectors``); acq.params
#: declares the options with this limit (a test ties the two).
MAX_REFLECTORS = 8


@dataclass(frozen=True)
class SeedPaper:
    """The settings of the seed paper's experiment: Shin, Shapiro and Goyal, "Single-Photon Depth
    Imaging Using a Union-of-Subspaces Model", IEEE SPL 2015 (``paper/``): 15 detections per
    pixel, M = N = 801 bins, delta = 1e-4 (its experiments section); the raw unit, window, bin
    width, pulse width and iteration cap are those of its published code and data (its ref. [14]).

    time_unit_s:      the time tagger's raw unit (8 ps).
    window_start:     first raw unit kept (2000, 16 ns after the sync).
    window_stop:      end of the window, exclusive: [2000, 6000] with a last bin starting at 6000,
                      so 801 bins of 5 units (6005).
    bin_units:        bin width in raw units (5: 40 ps).
    pulse_rms_units:  Gaussian pulse RMS width in raw units (45: 360 ps).
    delta:            uos stopping threshold.
    max_iterations:   uos iteration cap.
    max_photons:      detections used per pixel (the first 15).
    """

    time_unit_s: float = 8e-12
    window_start: int = 2000
    window_stop: int = 6005
    bin_units: int = 5
    pulse_rms_units: float = 45.0
    delta: float = 1e-4
    max_iterations: int = 10
    max_photons: int = 15

    @property
    def n_bins(self) -> int:
        return self.binning.n_bins

    @property
    def pulse_rms_s(self) -> float:
        return self.pulse_rms_units * self.time_unit_s

    @property
    def binning(self) -> Binning:
        return Binning(self.time_unit_s, self.window_start, self.window_stop, self.bin_units)

    def settings(self, method: str = "uos", **changes) -> "ReconSettings":
        """The paper's reconstruction settings for ``method``; ``changes`` override fields."""
        base = dict(method=method, binning=self.binning, pulse_rms_s=self.pulse_rms_s,
                    max_photons=self.max_photons, delta=self.delta, max_iterations=self.max_iterations)
        base.update(changes)
        return ReconSettings(**base)


#: The seed paper's settings (see :class:`SeedPaper`); its delta and iteration cap are
#: ReconSettings' defaults.
SEED_PAPER = SeedPaper()
#: The default bin is the pulse RMS over this (:func:`default_bin_width`): the seed paper's ratio,
#: 360 ps / 40 ps = 9.
BINS_PER_PULSE_RMS = SEED_PAPER.pulse_rms_units / SEED_PAPER.bin_units


@dataclass(frozen=True)
class ReconSettings:
    """Everything a reconstruction depends on; saved with every result (``to_dict``).

    method:         a name the registry holds (:mod:`recon.estimators`): "lmf" (log-matched filter,
                    eq. 11), "uos" (Algorithm 1), "ml" (exact pixelwise Poisson ML of eq. 9),
                    "spatial" (censoring, pixelwise fit and TV over neighbours) or a plugin's.
    binning:        None derives it from the data: window = [min, max] of all detection times
                    (stop just past the max), bin width = pulse RMS / 9 rounded to whole raw units
                    (the paper's 360 ps / 40 ps ratio), widened if needed to keep at most
                    ``DEFAULT_MAX_BINS`` (4096) bins; see :func:`default_bin_width`.
    pulse_rms_s:    Gaussian pulse RMS width, seconds. With ``irf`` also None the instrument response
                    is measured from the data (:func:`recon.irf.estimate_irf`: an exponentially
                    modified Gaussian fitted to within-pixel time differences, or for pixels of
                    hundreds of detections their pooled aligned histogram) and recorded in the
                    result's settings (``irf_estimate``, and ``irf`` when it has a tail).
    irf:            a measured instrument response (:class:`Irf`, see :func:`load_irf`) instead of a
                    Gaussian.
    max_photons:    use only the first N in-window detections of each pixel (None: all).
    reflectors:     surfaces per pixel: 1, K > 1 (up to K, each kept when it raises the Poisson
                    likelihood by more than recon.estimators.surfaces_fit.LLR_MIN = 2 nats, Akaike's criterion, and
                    flagged weak when doubtful) or "auto" (decided per pixel
                    by a likelihood-ratio test at ``false_alarm``, up to ``max_reflectors``); K > 1
                    and auto fit every pixel by recon.estimators.surfaces' greedy Poisson pursuit (lmf, uos, ml)
                    or recon.estimators.surfaces' K-surface fit with the neighbours' help (spatial).
    max_reflectors: most surfaces per pixel for reflectors="auto" (default 3).
    false_alarm:    chance per pixel that background alone passes the return test (:mod:`recon.detect`:
                    its own test and the neighbours' support together, half each) and, with
                    reflectors="auto", per added surface that background (or the response's own
                    tail) passes for a surface (default 1e-3).
    neighbour_false_alarm: the return test's rule for a pixel that fails on its own and by its
                    neighbours' support at its own estimate (:mod:`recon.detect`): its detections are
                    tested where its neighbours see returns at this false-alarm rate for that
                    region's span of shifts, the chance that a pixel at a surface's edge without a
                    return of its own at those shifts is given one (default 0.05; 0: never).
    delta:          uos stopping threshold on ``||x_k - x_{k-1}||^2`` (paper: 1e-4, with the pulse
                    columns scaled to peak 1 as in the published code).
    max_iterations: uos iteration cap (paper: 10).
    """

    method: str = "uos"
    binning: Binning | None = None
    pulse_rms_s: float | None = None
    irf: Irf | None = None
    max_photons: int | None = None
    reflectors: int | str = 1
    delta: float = SEED_PAPER.delta
    max_iterations: int = SEED_PAPER.max_iterations
    max_reflectors: int = 3
    false_alarm: float = 1e-3
    neighbour_false_alarm: float = 0.05

    def __post_init__(self) -> None:
        from spdepth.recon import estimators

        estimators.get(self.method)     # InputError naming the methods for another name
        if self.pulse_rms_s is not None:
            if not (isinstance(self.pulse_rms_s, (int, float, np.floating)) and math.isfinite(self.pulse_rms_s)
                    and self.pulse_rms_s > 0):
                raise InputError(f"pulse_rms_s must be a positive number of seconds, got {self.pulse_rms_s!r}")
            object.__setattr__(self, "pulse_rms_s", float(self.pulse_rms_s))
        if self.irf is not None and not isinstance(self.irf, Irf):
            try:
                t, c = self.irf
            except (TypeError, ValueError):
                raise InputError("irf must be an Irf or a (times_s, counts) pair") from None
            object.__setattr__(self, "irf", Irf(tuple(np.ravel(t)), tuple(np.ravel(c))))
        if self.irf is not None and self.pulse_rms_s is not None:
            raise InputError("give either pulse_rms_s or irf, not both")
        if self.max_photons is not None and (int(self.max_photons) != self.max_photons or self.max_photons < 1):
            raise InputError(f"max_photons must be a positive integer, got {self.max_photons!r}")
        if self.reflectors != "auto":
            if isinstance(self.reflectors, str) or int(self.reflectors) != self.reflectors \
                    or not 1 <= self.reflectors <= MAX_REFLECTORS:
                raise InputError(f"reflectors must be an integer from 1 to {MAX_REFLECTORS} or 'auto', "
                                 f"got {self.reflectors!r}")
            object.__setattr__(self, "reflectors", int(self.reflectors))
        if isinstance(self.max_reflectors, str) or int(self.max_reflectors) != self.max_reflectors \
                or not 1 <= self.max_reflectors <= MAX_REFLECTORS:
            raise InputError(f"max_reflectors must be an integer from 1 to {MAX_REFLECTORS}, "
                             f"got {self.max_reflectors!r}")
        object.__setattr__(self, "max_reflectors", int(self.max_reflectors))
        if not (isinstance(self.false_alarm, (int, float, np.floating)) and 0 < self.false_alarm < 1):
            raise InputError(f"false_alarm must be a probability in (0, 1), got {self.false_alarm!r}")
        object.__setattr__(self, "false_alarm", float(self.false_alarm))
        if not (isinstance(self.neighbour_false_alarm, (int, float, np.floating)) and 0 <= self.neighbour_false_alarm < 1):
            raise InputError(f"neighbour_false_alarm must be a probability in [0, 1), got {self.neighbour_false_alarm!r}")
        object.__setattr__(self, "neighbour_false_alarm", float(self.neighbour_false_alarm))
        if not (math.isfinite(self.delta) and self.delta > 0):
            raise InputError(f"delta must be positive, got {self.delta!r}")
        if int(self.max_iterations) != self.max_iterations or self.max_iterations < 1:
            raise InputError(f"max_iterations must be a positive integer, got {self.max_iterations!r}")

    def to_dict(self) -> dict:
        """JSON-serialisable copy (nested dicts and lists)."""
        d = {"method": self.method,
             "binning": None if self.binning is None else self.binning.to_dict(),
             "pulse_rms_s": self.pulse_rms_s,
             "irf": None if self.irf is None else self.irf.to_dict(),
             "max_photons": self.max_photons, "reflectors": self.reflectors,
             "delta": self.delta, "max_iterations": int(self.max_iterations),
             "max_reflectors": self.max_reflectors, "false_alarm": self.false_alarm,
             "neighbour_false_alarm": self.neighbour_false_alarm}
        json.dumps(d)   # fail here, not when saving, if something is not serialisable
        return d

    @property
    def several(self) -> bool:
        """True when more than one surface per pixel is looked for (K > 1 or auto)."""
        return self.reflectors == "auto" or self.reflectors > 1

    @classmethod
    def from_dict(cls, d: dict, **override) -> "ReconSettings":
        """Back from :meth:`to_dict` (or a result's settings record, whose extra keys are
        ignored), typed, with any field replaced by ``override`` (None values are ignored). A
        pulse width given in ``override`` replaces a recorded pulse shape."""
        if not isinstance(d, dict):
            raise InputError(f"saved settings must be a dict, got {type(d).__name__}")
        d = {**d, **{k: v for k, v in override.items() if v is not None}}
        b = d.get("binning")
        binning = Binning.from_dict(b) if isinstance(b, dict) else b
        irf = d.get("irf")
        irf = Irf.from_dict(irf) if isinstance(irf, dict) else irf
        if override.get("pulse_rms_s") is not None:
            irf = None
        return cls(method=d.get("method", "uos"), binning=binning,
                   pulse_rms_s=None if irf is not None else d.get("pulse_rms_s"), irf=irf,
                   max_photons=d.get("max_photons"), reflectors=d.get("reflectors", 1),
                   max_reflectors=int(d.get("max_reflectors", cls.max_reflectors)),
                   false_alarm=float(d.get("false_alarm", cls.false_alarm)),
                   neighbour_false_alarm=float(d.get("neighbour_false_alarm", cls.neighbour_false_alarm)),
                   delta=float(d.get("delta", SEED_PAPER.delta)),
                   max_iterations=int(d.get("max_iterations", SEED_PAPER.max_iterations)))


# ------------------------------------------------------------------------------------------------
# Pulse kernel


@dataclass(frozen=True, eq=False)
class PulseKernel:
    """The pulse integrated over bins, with the tables the estimators need. Shapes: M = n_bins.

    g:          float64 (L0 + L1 + 1,): unit-area pulse integrated over a bin, ``g[d + L0]`` for a
                photon ``d`` bins after the shift (d in [-L0, L1]); zero outside (truncated where the
                pulse is below KERNEL_TAIL_REL of its peak, and to |d| < M).
    off:        L0.
    gmax:       max(g); the uos columns are ``g / gmax`` (peak 1, as in the published code).
    colsum:     float64 (M,): ``S_i^T 1 = sum_k g[k - i]`` over the window's bins.
    pp:         float64 (2M-1, len(g)+1): prefix sums of ``g[m] g[m - d]`` over m, row ``d + M - 1``,
                so ``S_i^T S_j`` is a difference of two entries (see kernels.col_dot).
    dg:         float64 like g: d g(x)/dx at integer x (for the Fisher information), per bin.
    ddg:        float64 like g: d^2 g(x)/dx^2 at integer x (one-bin differences), per bin^2.
    fine:       float64: g at offsets ``x = j / FINE_STEPS - L0`` (fractional shifts).
    fine_colsum:float64 ((M-1)*FINE_STEPS + 1,): column sums at fractional shifts q / FINE_STEPS.
    fisher:     float64 (rows, 6): the shift's Fisher sums tabulated over log(a / B), and in the last
                row their values for B = 0, for ml's uncertainty (:func:`fisher_table`).
    logg:       float64 (2M-1,): log(g / gmax) at offsets d in [-(M-1), M-1] (index d + M - 1), for
                the log-matched filter; exact tails for a Gaussian, floored at the smallest finite
                value for a measured IRF (the published code's convention).
    log_concave:True when ``logg`` is concave (its argmax can be found by hill climbing).
    rms_bins:   the pulse RMS width in bins.
    """

    g: np.ndarray
    off: int
    gmax: float
    colsum: np.ndarray
    pp: np.ndarray
    dg: np.ndarray
    ddg: np.ndarray
    fine: np.ndarray
    fine_colsum: np.ndarray
    fisher: np.ndarray
    logg: np.ndarray
    log_concave: bool
    rms_bins: float
    n_bins: int
    info: dict = field(default_factory=dict)


def _gaussian_cdf(sigma_bins: float):
    # scipy.special where used, not at import: it costs a new process 0.17 s (its array-API layer
    # loads numpy.f2py), which a file's reconstruction pays on the warm-up thread during the read
    from scipy.special import ndtr

    return lambda x: ndtr(np.asarray(x, dtype=np.float64) / sigma_bins)


def _irf_cdf(irf: Irf, bin_width_s: float):
    """CDF of the IRF (unit area, centred on its centroid) as a function of time in bins. Each sample
    spreads its counts evenly over the half-way points to its neighbours."""
    t, c = irf.arrays()
    edges = np.empty(t.size + 1)
    edges[1:-1] = 0.5 * (t[1:] + t[:-1])
    edges[0] = t[0] - 0.5 * (t[1] - t[0])
    edges[-1] = t[-1] + 0.5 * (t[-1] - t[-2])
    p = c / c.sum()
    centroid = np.sum(p * 0.5 * (edges[1:] + edges[:-1]))
    e_bins = (edges - centroid) / bin_width_s
    cdf = np.concatenate(([0.0], np.cumsum(p)))
    cdf[-1] = 1.0
    return lambda x: np.interp(np.asarray(x, dtype=np.float64), e_bins, cdf, left=0.0, right=1.0), \
        (float(e_bins[0]), float(e_bins[-1]))


def fisher_table(g: np.ndarray, dg: np.ndarray) -> np.ndarray:
    """The sums of :func:`recon.kernels.fisher_var` for a pulse inside the window, per unit of 1 / bg, tabulated
    for :func:`recon.kernels.fisher_tab`: row i holds ``sum_t h_t / (1 + r g_t)`` at
    ``r = a / bg = exp(FISHER_RHO0 + i / FISHER_STEPS)`` for h = (dg^2, dg g, dg, g^2, g, 1). The
    last row is for bg = 0, where the rate is a g_t alone: ``sum over g_t > 0 of h_t / g_t`` (the
    loop's bins with g_t = 0 then have no rate and add nothing)."""
    rho = FISHER_RHO0 + np.arange(FISHER_SPAN * FISHER_STEPS) / FISHER_STEPS
    inv = 1.0 / (1.0 + np.exp(rho)[:, None] * g[None, :])
    h = np.stack([dg * dg, dg * g, dg, g * g, g, np.ones_like(g)], axis=1)
    pos = g > 0.0
    limit = (h[pos] / g[pos, None]).sum(axis=0)
    return np.ascontiguousarray(np.vstack([inv @ h, limit]))


@functools.lru_cache(maxsize=KERNEL_CACHE)
def build_kernel(binning: Binning, pulse_rms_s: float | None = None, irf: Irf | None = None) -> PulseKernel:
    """Tables of the bin-integrated pulse for this binning (see :class:`PulseKernel`). The same
    arguments give the same object, kept from an earlier call (:data:`KERNEL_CACHE`): its arrays are
    shared and must be treated as read-only."""
    m = binning.n_bins
    w_s = binning.bin_width_s
    if (pulse_rms_s is None) == (irf is None):
        raise InputError("build_kernel needs exactly one of pulse_rms_s and irf")
    if irf is None:
        if not (pulse_rms_s > 0 and math.isfinite(pulse_rms_s)):
            raise InputError(f"pulse RMS width must be positive, got {pulse_rms_s}")
        sig = pulse_rms_s / w_s
        cdf = _gaussian_cdf(sig)
        reach = sig * math.sqrt(2 * math.log(1 / KERNEL_TAIL_REL)) + 1.0
        lo_x, hi_x = -reach, reach
        rms_bins = sig
        irf_step = 0.0
    else:
        cdf, (lo_x, hi_x) = _irf_cdf(irf, w_s)
        rms_bins = irf.rms_s / w_s
        lo_x, hi_x = lo_x - 1.0, hi_x + 1.0
        t_irf = irf.arrays()[0]
        irf_step = float(np.median(np.diff(t_irf))) / w_s if t_irf.size > 1 else 0.0
    l0 = int(min(m - 1, math.ceil(-lo_x)))
    l1 = int(min(m - 1, math.ceil(hi_x)))
    d = np.arange(-l0, l1 + 1, dtype=np.float64)
    g = cdf(d + 0.5) - cdf(d - 0.5)
    gmax = float(g.max())
    if not gmax > 0:
        raise InputError("pulse kernel is zero on this binning")
    g = np.where(g >= KERNEL_TAIL_REL * gmax, g, 0.0)
    # trim zero ends so loops stay short, keeping the offset bookkeeping right
    nz = np.flatnonzero(g)
    # keep one (zero) bin beyond the support on each side: the fine table then covers sub-bin shifts
    # of a pulse narrower than a bin (trimmed to one bin, a half-bin shift read as zero signal)
    a, b = max(0, int(nz[0]) - 1), min(g.size - 1, int(nz[-1]) + 1)
    g = np.ascontiguousarray(g[a:b + 1])
    l0 = l0 - a
    d = d[a:b + 1]
    nk = g.size

    # fine table for sub-bin shifts: g(x) at x = j/FINE_STEPS - l0, j in [0, (nk-1)*FINE_STEPS]
    xf = np.arange((nk - 1) * FINE_STEPS + 1) / FINE_STEPS - l0
    fine = cdf(xf + 0.5) - cdf(xf - 0.5)
    fine = np.where(fine >= KERNEL_TAIL_REL * gmax, fine, 0.0)
    # derivative at integer offsets by central differences on the fine grid, and no finer than a
    # sampled response's own step: its CDF is piecewise linear between samples, so differences
    # over less than a sample read a step function, whose jumps doubled the Fisher information
    # of a response measured in 88 ps steps on 40 ps bins (K-surface halves within 1 sigma 51%)
    h = max(1.0 / FINE_STEPS, irf_step)
    dg = (cdf(d + h + 0.5) - cdf(d + h - 0.5) - cdf(d - h + 0.5) + cdf(d - h - 0.5)) / (2 * h)
    # second derivative (uos's matched-filter variance); one-bin steps keep a sampled IRF's
    # piecewise-linear CDF from turning it into noise
    ddg = (cdf(d + 1.5) - cdf(d + 0.5)) - 2 * (cdf(d + 0.5) - cdf(d - 0.5)) + (cdf(d - 0.5) - cdf(d - 1.5))

    # column sums S_i^T 1 = sum_{m=-i}^{M-1-i} g[m]
    csum = np.concatenate(([0.0], np.cumsum(g)))
    i = np.arange(m)
    lo_t = np.clip(-i + l0, 0, nk)
    hi_t = np.clip(m - i + l0, 0, nk)
    colsum = csum[hi_t] - csum[lo_t]
    # fine column sums at shift tau = q / FINE_STEPS: sum_k g(k - tau) over k in the window
    nq = (m - 1) * FINE_STEPS + 1
    fine_colsum = np.empty(nq)
    q = np.arange(nq)
    for r in range(FINE_STEPS):
        # shift tau = i + r/F: photon offset k - tau = (k - i) - r/F -> fine index (k-i+l0)*F - r
        sel = q % FINE_STEPS == r
        ii = q[sel] // FINE_STEPS
        col = np.zeros(nk + 1)
        # entries g((m') - r/F) for m' in [-l0, l1]: fine index (m'+l0)*F - r
        idx = np.arange(nk) * FINE_STEPS - r
        vals = np.where(idx >= 0, fine[np.clip(idx, 0, fine.size - 1)], 0.0)
        # the value at m' = l1 + 1 (idx beyond) is ~0 by truncation
        col[1:] = np.cumsum(vals)
        lo_r = np.clip(-ii + l0, 0, nk)
        hi_r = np.clip(m - ii + l0, 0, nk)
        fine_colsum[sel] = col[hi_r] - col[lo_r]

    # prefix sums of g[m] g[m-d] for d in [-(M-1), M-1]; only |d| < nk overlap
    dmax = min(m - 1, nk - 1)
    pp = np.zeros((2 * dmax + 1, nk + 1))
    for dd in range(-dmax, dmax + 1):
        prod = np.zeros(nk)
        if dd >= 0:
            prod[dd:] = g[dd:] * g[:nk - dd]
        else:
            prod[:nk + dd] = g[:nk + dd] * g[-dd:]
        pp[dd + dmax, 1:] = np.cumsum(prod)

    # log table for the log-matched filter over every offset a window can hold
    dl = np.arange(-(m - 1), m, dtype=np.float64)
    if irf is None:
        from scipy.special import log_ndtr

        sig = rms_bins
        aa = (np.abs(dl) - 0.5) / sig
        bb = (np.abs(dl) + 0.5) / sig
        # log(Q(a) - Q(b)) with Q the upper tail, stable far out (no -inf for a Gaussian)
        la = log_ndtr(-aa)
        lb = log_ndtr(-bb)
        with np.errstate(divide="ignore"):
            logg = la + np.log1p(-np.exp(lb - la))
        logg -= logg.max()
    else:
        gl = cdf(dl + 0.5) - cdf(dl - 0.5)
        # zero far out, or a rounding below zero where the sampled CDF is flat: floored just below
        with np.errstate(divide="ignore", invalid="ignore"):
            logg = np.log(gl / gl.max())
        finite = np.isfinite(logg)
        logg[~finite] = logg[finite].min()
    d2 = logg[2:] - 2 * logg[1:-1] + logg[:-2]
    log_concave = bool(np.all(d2 <= 1e-9 * np.maximum(1.0, np.abs(logg[1:-1]))))

    return PulseKernel(g=g, off=int(l0), gmax=gmax, colsum=np.ascontiguousarray(colsum), pp=pp,
                       dg=np.ascontiguousarray(dg), ddg=np.ascontiguousarray(ddg), fine=np.ascontiguousarray(fine),
                       fine_colsum=fine_colsum, fisher=fisher_table(g, dg), logg=np.ascontiguousarray(logg),
                       log_concave=log_concave, rms_bins=float(rms_bins), n_bins=m,
                       info={"pulse": "gaussian" if irf is None else "irf",
                             "pulse_rms_s": float(rms_bins * w_s)})


# ------------------------------------------------------------------------------------------------
# Pulse width from the data


def pair_difference_histogram(times: np.ndarray, offsets: np.ndarray, max_per_pixel: int = 32,
                              nh: int = 4096, step: float | None = None) -> tuple[np.ndarray, float]:
    """Histogram (nh bins from 0, int64) of ``|t_i - t_j|`` over the pairs among the first
    ``max_per_pixel`` detections of each pixel (raw units), and its bin width. The pulse shape's
    autocorrelation plus a floor from pairs with a background detection; scene depth cancels.
    ``step`` fixes the bin width instead (bins ``[j, j + 1) * step``); integer times get a whole
    number of units per bin. Raises InputError when no pixel's detections differ."""
    times = np.asarray(times, dtype=np.float64)
    offsets = np.asarray(offsets, dtype=np.int64)
    # |dt| of every pair among the first max_per_pixel times of each pixel, histogrammed a block of
    # pixels at a time: memory stays bounded (keeping every difference of 1 Mpx at 32 detections
    # took about 4 GB). The range is the largest within-pixel spread, found first.
    from spdepth.recon.pair_kernels import pair_histogram, pair_span

    # |dt| of every pair among the first max_per_pixel times of each pixel, binned as each pair is
    # formed (recon.pair_kernels): no pair is kept (keeping every difference of 1 Mpx at 32
    # detections took about 4 GB). The range is the largest within-pixel spread, found first.
    counts = np.minimum(np.diff(offsets), max_per_pixel)
    starts = np.ascontiguousarray(offsets[:-1])
    multi = np.flatnonzero(counts > 1).astype(np.int64)
    span = float(pair_span(times, starts, counts, multi))
    if not span > 0:
        raise InputError("cannot estimate the pulse width: all detections of each pixel coincide")
    # fine histogram of |dt| (raw units); step small against any plausible pulse
    if step is None and np.all(np.mod(times, 1) == 0):
        # integer times: whole units per bin (a fractional width combs the histogram: some bins
        # hold two integer differences, their neighbours none)
        step = float(max(1, math.ceil(span / nh)))
    if step is None:
        step = span / nh
        edges_hi = span + step
    else:
        nh = int(span // step) + 1
        edges_hi = nh * step
    from spdepth.recon.threadpool import shared_pool, threads

    # np.histogram(|dt|, bins=nh, range=(0, edges_hi)), bin for bin: its edges and scale. One
    # slice of the pixels per thread of numba's (--threads), each counting into its own histogram
    # (counts: their sum is exact), on the process's pool (inline when called from one of its threads)
    edges = np.linspace(0.0, edges_hi, nh + 1, endpoint=True)
    workers = max(1, min(threads(), multi.size))
    cuts = np.linspace(0, multi.size, workers + 1).astype(np.int64)
    parts = np.zeros((workers, nh), np.int64)

    def count(k: int) -> None:
        pair_histogram(times, starts, counts, multi[cuts[k]:cuts[k + 1]], edges, nh / edges_hi, parts[k])

    pool = shared_pool(workers)
    if pool is None:
        for k in range(workers):
            count(k)
    else:
        list(pool.map(count, range(workers)))
    return parts.sum(axis=0), step


def estimate_pulse_rms_s(times: np.ndarray, offsets: np.ndarray, time_unit_s: float,
                         max_per_pixel: int = 32) -> float:
    """Estimate the Gaussian pulse RMS width (s) from the data alone.

    Depth differs from pixel to pixel, so the aggregate histogram of detection times is broadened by
    the scene; the differences between two detections of the *same* pixel are not. Signal-signal
    pairs give a peak at 0 of RMS ``sqrt(2) * sigma``; pairs involving background give a broad,
    slowly varying floor. We histogram within-pixel differences (first ``max_per_pixel`` detections
    of each pixel), subtract a floor fitted (linear in |dt|) on a band outside the peak, take the
    second moment of the peak within +-4 of its RMS widths (iterated, truncation-corrected) and
    divide by sqrt(2). Raises InputError when the data hold no clear peak.
    """
    times = np.asarray(times, dtype=np.float64)
    offsets = np.asarray(offsets, dtype=np.int64)
    counts = np.minimum(np.diff(offsets), max_per_pixel)
    if times.size == 0 or np.sum(counts * (counts - 1)) < 20:
        raise InputError("cannot estimate the pulse width: too few pixels with two or more detections; "
                         "give the pulse RMS width or an IRF")
    hist, step = pair_difference_histogram(times, offsets, max_per_pixel)
    nh = hist.size
    centers = (np.arange(nh) + 0.5) * step
    # initial width: half-width where the smoothed histogram falls to half its peak above the floor
    smooth = np.convolve(hist, np.ones(5) / 5, mode="same")
    floor0 = np.median(smooth[nh // 4:])
    peak = smooth[:8].max()
    if not peak > 3 * max(floor0, 1.0):
        raise InputError("cannot estimate the pulse width: no peak of coincident detections in the data; "
                         "give the pulse RMS width or an IRF")
    half = np.flatnonzero(smooth < floor0 + 0.5 * (peak - floor0))
    hw = centers[half[0]] if half.size else centers[nh // 8]
    s_d = max(hw / 1.1774, 2 * step)       # RMS of the difference distribution (HWHM / 1.1774)
    for _ in range(20):
        core = centers < 4 * s_d
        band = (centers >= 5 * s_d) & (centers < 10 * s_d)
        if band.sum() < 3:
            band = centers >= 4 * s_d
        if band.sum() < 3:
            raise InputError("cannot estimate the pulse width: peak spans the whole window")
        coef = np.polyfit(centers[band], hist[band], 1)
        net = hist[core] - np.polyval(coef, centers[core])
        if not net.sum() > 0:
            raise InputError("cannot estimate the pulse width: no signal above the background floor")
        var = np.sum(net * centers[core] ** 2) / net.sum() - step ** 2 / 12
        # a Gaussian truncated at 4 sigma keeps 0.9989 of its variance
        new = math.sqrt(max(var, step ** 2) / 0.99893)
        if abs(new - s_d) < 1e-4 * s_d:
            s_d = new
            break
        s_d = new
    # raw-unit quantization adds 1/12 unit^2 to each time, 2/12 to a difference
    sigma_units = math.sqrt(max(s_d ** 2 / 2 - 1 / 12, (s_d ** 2 / 2) * 1e-4))
    return float(sigma_units * time_unit_s)


def default_bin_width(span: float, pulse_rms: float | None = None,
                      max_bins: int = DEFAULT_MAX_BINS) -> float:
    """The one default bin rule (``default_binning`` and ``spdepth recon`` use it): bin width in
    whole raw units for a window ``span`` raw units long. A ninth of the pulse RMS (raw units) when
    it is known (the seed paper's 40 ps bins for a 360 ps pulse), else one unit; at least one unit;
    widened to whole units so that the window holds at most ``max_bins`` bins
    (``ceil(span / width) <= max_bins``)."""
    width = max(1.0, float(round(pulse_rms / BINS_PER_PULSE_RMS))) if pulse_rms else 1.0
    if span / width > max_bins:
        width = float(math.ceil(span / max_bins))
    return width


def default_binning(times: np.ndarray, time_unit_s: float, pulse_rms_s: float) -> Binning:
    """Binning derived from the data (see ReconSettings.binning)."""
    if times.size == 0:
        raise InputError("cannot derive a binning from data without detections; give a binning")
    lo = float(np.floor(times.min()))
    hi = float(times.max())
    # the window below has floor((hi - lo) / width) + 1 bins, never more than ceil((hi - lo + 1) / width)
    width = default_bin_width(hi - lo + 1.0, pulse_rms_s / time_unit_s)
    # stop one bin past the bin holding the latest detection, so it is inside [start, stop)
    n = int(math.floor((hi - lo) / width)) + 1
    if n < 3:
        # all detections within a bin or two: one empty bin each side, so signal and background are
        # told apart (in a one-bin window they are the same column)
        lo -= width
        n += 2
    return Binning(time_unit_s, lo, lo + n * width, width)
