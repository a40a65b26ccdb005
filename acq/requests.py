"""What a user asks spdepth to do, as frozen, validated data: a scan, a replay, a file reconstruction.

Every front end (the CLI, the window, Dask workers, the demo, the benchmarks) only translates its own
input into one of these requests and hands it to :mod:`acq.api`. A request is checked as a whole when
it is made (``__post_init__``), before any device is opened or folder made; a bad or conflicting
value raises :class:`~acq.errors.RequestError` naming the field (in the CLI's words, e.g.
``--dwell-limit-ms``) and the value. Requests are saved with every result (``run.json``, the PTU
header, ``maps.npz`` settings) through ``to_dict`` and read back typed with ``from_dict``.

Units are SI inside (``bin_s``, ``dwell_s``, ``window_s``); the front ends convert at their edges.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field, fields
from pathlib import Path

from spdepth.acq.errors import RequestError
from spdepth.acq.params import (DEFAULT_BIN_PS, DEFAULT_METHOD, DEFAULT_N_BINS,  # noqa: F401
                                DEFAULT_SIZE, DEFAULT_TARGET, GALVO_FORMS, MODES, check_request,
                                default, tagger_forms)
from spdepth.drivers.galvo.protocol import MAX_N_TARGET
from spdepth.recon.model import METHODS

DEFAULT_BIN_S = DEFAULT_BIN_PS * 1e-12
"""Histogram bin of a scan: the seed paper's 40 ps."""
DEFAULT_WINDOW_S = (0.0, DEFAULT_N_BINS * DEFAULT_BIN_S)
"""Detection window of a scan after each sync: 801 bins of 40 ps, the seed paper's window length."""
MAX_TARGET = MAX_N_TARGET
"""Largest count the galvo controller can gate a pixel on."""
MAX_STORE_DETECTIONS = 2_000_000_000
"""Pixels x target above this would not fit the per-pixel store (8 bytes a detection: 16 GB)."""
DEFAULT_DWELL_S = {"gated": 10e-3, "raster": 1e-3}
"""Real devices: the gated dwell limit and the raster dwell unless given."""


def _method(value) -> None:
    """--method against the estimator registry itself (the declarations list its names for --help)."""
    if value is not None and value not in METHODS:
        raise RequestError(f"--method must be one of {', '.join(METHODS)}, got {value!r}")


def _window(window) -> tuple[float, float] | None:
    """A checked window (``check_request`` ran) as a tuple of floats."""
    return None if window is None else tuple(float(v) for v in window)


def check_bin_fits(bin_s: float | None, window_s: tuple[float, float] | None, *,
                   bin_name: str = "--bin-ps", window_name: str = "--window-ps") -> None:
    """A bin wider than the window would give every pixel the same depth: refuse it."""
    if bin_s is None or window_s is None:
        return
    span = window_s[1] - window_s[0]
    if bin_s > span * (1 + 1e-9):
        raise RequestError(f"{bin_name} {bin_s * 1e12:g} is wider than the window {window_name} "
                           f"{window_s[0] * 1e12:g}:{window_s[1] * 1e12:g} ({span * 1e12:g} ps)")


def check_writable(name: str, path: str | None) -> None:
    """An output file whose folder does not exist or cannot be written is refused before any work
    (not after the whole computation); tried, not inferred from permission bits
    (``acq.outputs``). Whether an existing one may be replaced is the command's rule
    (``--overwrite``)."""
    from spdepth.acq.outputs import check_output_file

    check_output_file(name, path, overwrite=True)


# ---- device strings (one style for scan and gui; parsed here only) ----------------------------------
@dataclass(frozen=True)
class TaggerAddress:
    """A parsed ``--tagger``: ``kind`` "usb" (ours; ``vid``/``pid``), "picoquant" (``model``,
    ``serial``) or "swabian" (``serial``)."""

    kind: str
    model: str = ""
    serial: str = ""
    vid: int = 0
    pid: int = 0
    text: str = ""


@dataclass(frozen=True)
class GalvoAddress:
    """A parsed ``--galvo``: ``kind`` "serial" (ours; ``port``: a serial port or pyserial URL) or
    "nidaq" (``device`` e.g. Dev1, ``ao`` e.g. ao0:1)."""

    kind: str
    port: str = ""
    device: str = ""
    ao: str = "ao0:1"
    text: str = ""


TAGGER_FORMS = tagger_forms()


def parse_tagger(text: str) -> TaggerAddress:
    """``picoquant:mh150[:SERIAL]``, ``swabian[:SERIAL]``, ``usb:VID:PID``; RequestError naming
    the forms otherwise."""
    if not isinstance(text, str) or not text.strip():
        raise RequestError(f"--tagger must be {TAGGER_FORMS}, got {text!r}")
    parts = text.strip().split(":")
    head = parts[0].lower()
    if head == "picoquant":
        if len(parts) not in (2, 3) or not parts[1]:
            raise RequestError(f"--tagger {text}: expected picoquant:MODEL[:SERIAL], e.g. "
                               f"picoquant:mh150")
        from spdepth.drivers.errors import SettingError
        from spdepth.drivers.picoquant.protocol import family

        try:
            fam = family(parts[1])
        except SettingError as exc:
            raise RequestError(f"--tagger {text}: {exc}") from None
        serial = parts[2] if len(parts) == 3 else ""
        if serial and not (serial.isalnum() and len(serial) <= 8):
            raise RequestError(f"--tagger {text}: a PicoQuant serial number is up to 8 letters "
                               f"or digits, got {serial!r}")
        return TaggerAddress("picoquant", model=fam.key, serial=serial, text=text)
    if head == "swabian":
        if len(parts) > 2 or (len(parts) == 2 and not parts[1]):
            raise RequestError(f"--tagger {text}: expected swabian[:SERIAL]")
        return TaggerAddress("swabian", serial=parts[1] if len(parts) == 2 else "", text=text)
    if head == "usb":
        try:
            if len(parts) != 3:
                raise ValueError
            vid, pid = int(parts[1], 16), int(parts[2], 16)
            if not (0 <= vid <= 0xFFFF and 0 <= pid <= 0xFFFF):
                raise ValueError
        except ValueError:
            raise RequestError(f"--tagger {text}: expected usb:VID:PID in hex, e.g. "
                               f"usb:1209:7a64") from None
        return TaggerAddress("usb", vid=vid, pid=pid, text=text)
    raise RequestError(f"--tagger must be {TAGGER_FORMS}, got {text!r}")


def parse_galvo(text: str) -> GalvoAddress:
    """``nidaq:Dev1[/ao0:1]`` or a serial port / pyserial URL; RequestError otherwise."""
    if not isinstance(text, str) or not text.strip():
        raise RequestError(f"--galvo must be {GALVO_FORMS}, got {text!r}")
    text = text.strip()
    if text.lower().startswith("nidaq:"):
        spec = text[len("nidaq:"):]
        dev, _, ao = spec.partition("/")
        ao = ao or "ao0:1"
        import re

        if not re.fullmatch(r"[A-Za-z][A-Za-z0-9_]*", dev or "") or \
                not re.fullmatch(r"ao\d+:\d+", ao):
            raise RequestError(f"--galvo {text}: expected nidaq:DEV[/aoN:M] with two analog "
                               f"outputs, e.g. nidaq:Dev1/ao0:1")
        a, b = (int(v) for v in ao[2:].split(":"))
        if b != a + 1:
            raise RequestError(f"--galvo {text}: {ao} must name two adjacent outputs (x, y), "
                               f"e.g. ao0:1")
        return GalvoAddress("nidaq", device=dev, ao=ao, text=text)
    if text.lower().startswith(("usb:", "picoquant:", "swabian")):
        raise RequestError(f"--galvo {text} names a time tagger; --galvo must be {GALVO_FORMS}")
    return GalvoAddress("serial", port=text, text=text)


class _Request:
    """``to_dict``/``from_dict`` for the frozen request dataclasses (nested ones included)."""

    KIND = ""
    _NESTED: dict = {}

    def to_dict(self) -> dict:
        d = {}
        for f in fields(self):
            v = getattr(self, f.name)
            d[f.name] = v.to_dict() if isinstance(v, _Request) else list(v) if isinstance(v, tuple) else v
        return {"kind": self.KIND, **d}

    @classmethod
    def from_dict(cls, d: dict):
        if not isinstance(d, dict):
            raise RequestError(f"a saved {cls.KIND} request must be a JSON object, got {type(d).__name__}")
        if d.get("kind", cls.KIND) != cls.KIND:
            raise RequestError(f"a saved request of kind {d.get('kind')!r} is not a {cls.KIND} request")
        names = {f.name: f for f in fields(cls)}
        unknown = sorted(set(d) - set(names) - {"kind"})
        if unknown:
            raise RequestError(f"saved {cls.KIND} request: unknown field(s) {', '.join(unknown)}")
        kw = {}
        for k, v in d.items():
            if k == "kind":
                continue
            if k in cls._NESTED and isinstance(v, dict):
                v = _instruments_from_dict(v) if k == "instruments" else cls._NESTED[k].from_dict(v)
            elif isinstance(v, list):
                v = tuple(v)
            kw[k] = v
        try:
            return cls(**kw)
        except TypeError as exc:
            raise RequestError(f"saved {cls.KIND} request: {exc}") from None


@dataclass(frozen=True)
class SimBench(_Request):
    """The simulated bench: a scene behind the real drivers (galvo emulator, simulated USB tagger).

    scene:  a built-in scene name or ``file:DEPTH`` (``drivers.sim.load_scene``).
    ppp:    mean detections per pixel per scene dwell (None: the scan's target).
    sbr:    signal-to-background ratio in the detection window.
    faults: instrument faults to inject, ``KIND@WHEN`` items (``drivers.sim.faults``).
    tagger: "" (our USB tagger) or a vendor device string (``picoquant:mh150``): the bench is then
            reached through that vendor's driver and a stand-in of its library.
    galvo:  "" (our serial galvo) or ``nidaq:Dev1[/ao0:1]`` (the NI-DAQ driver on a stand-in
            ``nidaqmx``).
    """

    KIND = "sim"
    scene: str = default("--scene")
    ppp: float | None = None
    sbr: float = default("--sbr")
    seed: int = default("--seed")
    faults: str = default("--faults")
    tagger: str = ""
    galvo: str = ""

    def __post_init__(self) -> None:
        if not isinstance(self.scene, str) or not self.scene:
            raise RequestError(f"--scene must name a scene, got {self.scene!r}")
        check_request(self, "sim")
        if self.faults:
            from spdepth.drivers.errors import SettingError
            from spdepth.drivers.sim.faults import parse_faults

            try:
                parse_faults(self.faults)
            except SettingError as exc:
                raise RequestError(f"--faults {self.faults!r}: {exc}") from None
        if self.tagger:
            t = parse_tagger(self.tagger)
            if t.kind == "usb":
                raise RequestError(f"--sim --tagger {self.tagger}: the simulated bench's own "
                                   f"tagger is the default; name a vendor tagger or leave it out")
        if self.galvo:
            g = parse_galvo(self.galvo)
            if g.kind != "nidaq":
                raise RequestError(f"--sim --galvo {self.galvo}: the simulated bench's own galvo "
                                   f"is the default; name nidaq:DEV or leave it out")

    @property
    def vendor(self) -> bool:
        """Whether the bench is reached through a vendor backend."""
        return bool(self.tagger or self.galvo)

    def label(self) -> str:
        via = " via " + " + ".join(x for x in (self.tagger, self.galvo) if x) if self.vendor else ""
        return f"simulated {self.scene}{via}"


@dataclass(frozen=True)
class Devices(_Request):
    """Real instruments: a galvo (``--galvo``: our controller on a serial port, or ``nidaq:Dev1``)
    and a tagger (``--tagger``: ``usb:VID:PID`` ours, ``picoquant:mh150[:SERIAL]``,
    ``swabian[:SERIAL]``); device strings are parsed by :func:`parse_tagger`/:func:`parse_galvo`.

    sync_rate_hz:  the laser repetition rate (recorded in the PTU header).
    fov_deg:       square field of view in optical degrees, centred on the mirror's zero.
    deg_per_volt:  NI-DAQ galvo: optical degrees per volt (both axes).
    v_limit:       NI-DAQ galvo: outputs stay within +-v_limit volts.
    park_deg:      NI-DAQ galvo: (x, y) where the mirror rests between scans.
    picoquant_lib: PicoQuant: the library file to load ("" searches; see drivers.picoquant).
    event_divider: Swabian: tag every n-th laser sync only (high laser rates).
    """

    KIND = "devices"
    galvo: str = ""
    tagger: str = ""
    sync_rate_hz: float = 0.0
    fov_deg: float = default("--fov-deg", "real")
    deg_per_volt: float = default("--deg-per-volt", "real")
    v_limit: float = default("--v-limit", "real")
    park_deg: tuple[float, float] = default("--park-deg", "real")
    picoquant_lib: str = ""
    event_divider: int = default("--event-divider", "real")

    def __post_init__(self) -> None:
        if not self.galvo or not self.tagger:
            raise RequestError(f"real devices need both --galvo ({GALVO_FORMS}) and --tagger "
                               f"({TAGGER_FORMS})")
        t, g = parse_tagger(self.tagger), parse_galvo(self.galvo)
        if not self.sync_rate_hz:
            raise RequestError("real devices need --sync-rate-hz (the laser repetition rate)")
        check_request(self, "real")
        object.__setattr__(self, "park_deg", tuple(float(v) for v in self.park_deg))
        if g.kind == "nidaq" and self.fov_deg / 2 / self.deg_per_volt > self.v_limit:
            raise RequestError(f"--fov-deg {self.fov_deg:g} needs +-{self.fov_deg / 2 / self.deg_per_volt:g} V "
                               f"at --deg-per-volt {self.deg_per_volt:g}, beyond --v-limit "
                               f"{self.v_limit:g}")

    def label(self) -> str:
        return f"devices {self.galvo} + {self.tagger}"


def _instruments_from_dict(d: dict):
    kinds = {SimBench.KIND: SimBench, Devices.KIND: Devices}
    if d.get("kind") not in kinds:
        raise RequestError(f"saved instruments of unknown kind {d.get('kind')!r}")
    return kinds[d["kind"]].from_dict(d)


@dataclass(frozen=True)
class ScanRequest(_Request):
    """A scan: instruments, plan and reconstruction settings.

    size:          (H, W) pixels, rows first.
    target:        in-window detections wanted per pixel.
    mode:          "gated" (the controller holds each pixel until ``target`` detections or the dwell
                   limit) or "raster" (fixed dwell, frames repeated until every pixel holds target).
    dwell_limit_s: gated only: the dwell limit per pixel (None: 20 scene dwells / 10 ms).
    dwell_s:       raster only: the dwell per pixel and frame (None: the scene's dwell / 1 ms).
    window_s:      detection window after the sync (None: 801 bins of 40 ps from 0).
    bin_s:         histogram bin width.
    pulse_rms_s:   Gaussian pulse RMS (None: the simulated scene's, or estimated from the first
                   pixels to complete; with several surfaces the response is then measured on them,
                   ``acq.live_recon``).
    reflectors, max_reflectors, false_alarm: surfaces per pixel, as for a file
                   (:class:`FileReconRequest`), mapped live.
    """

    KIND = "scan"
    _NESTED = {"instruments": SimBench}
    instruments: SimBench | Devices = field(default_factory=SimBench)
    size: tuple[int, int] = default("--size")
    target: int = default("--target")
    mode: str = default("--mode")
    dwell_limit_s: float | None = None
    dwell_s: float | None = None
    pattern: str = default("--pattern")
    settle_s: float = default("--settle-us")
    max_passes: int | None = None
    time_limit_s: float | None = None
    window_s: tuple[float, float] | None = None
    bin_s: float = default("--bin-ps")
    method: str = default("--method")
    pulse_rms_s: float | None = None
    reflectors: int | str = default("--reflectors")
    max_reflectors: int = default("--max-reflectors")
    false_alarm: float = default("--false-alarm")

    def __post_init__(self) -> None:
        if not isinstance(self.instruments, (SimBench, Devices)):
            raise RequestError(f"instruments must be SimBench or Devices, got {self.instruments!r}")
        object.__setattr__(self, "size", tuple(self.size) if isinstance(self.size, list) else self.size)
        check_request(self, "sim")
        h, w = (int(v) for v in self.size)
        object.__setattr__(self, "size", (h, w))
        _method(self.method)
        if self.mode == "gated" and self.target > MAX_TARGET:
            raise RequestError(f"--target {self.target}: the galvo controller gates on at most "
                               f"{MAX_TARGET} detections per pixel")
        if h * w * self.target > MAX_STORE_DETECTIONS:
            raise RequestError(f"--target {self.target} on {w}x{h} pixels is {h * w * self.target:,} "
                               f"detections to keep, more than the store holds "
                               f"({MAX_STORE_DETECTIONS:,}); lower --target or --size")
        if self.dwell_limit_s is not None and self.dwell_s is not None:
            raise RequestError("give --dwell-limit-ms (gated) or --dwell-ms (raster), not both")
        if self.mode == "raster" and self.dwell_limit_s is not None:
            raise RequestError("--dwell-limit-ms is the gated dwell limit; a raster scan takes "
                               "--dwell-ms (the fixed dwell per pixel and frame)")
        if self.mode == "gated" and self.dwell_s is not None:
            raise RequestError("--dwell-ms is the raster dwell; a gated scan takes --dwell-limit-ms "
                               "(the longest wait for the target)")
        object.__setattr__(self, "window_s", _window(self.window_s))
        check_bin_fits(self.bin_s, self.window_s or DEFAULT_WINDOW_S)
        galvo = self.instruments.galvo
        if galvo and parse_galvo(galvo).kind == "nidaq":
            if self.settle_s:
                raise RequestError("--galvo nidaq: --settle-us is not supported yet (the raster "
                                   "steps on the card's sample clock)")

    @property
    def window(self) -> tuple[float, float]:
        return self.window_s or DEFAULT_WINDOW_S

    def label(self) -> str:
        h, w = self.size
        what = self.instruments.scene if isinstance(self.instruments, SimBench) else "devices"
        surfaces = "" if self.reflectors == 1 else f", surfaces {self.reflectors}"
        return f"scan {what} {w}x{h}, {self.target} per pixel, {self.method}{surfaces}"


@dataclass(frozen=True)
class ReplayRequest(_Request):
    """A recording fed through the session pipeline as if it came from the tagger.

    recording:   a session folder or its ``recording.ptu``, or a Generic T3 PTU with pixel markers.
    target:      detections per pixel to keep (None: the recorded target; fewer shows what a shorter
                 scan would have given).
    method, pulse_rms_s, reflectors, max_reflectors, false_alarm: replace the recorded estimator
                 settings (None: as recorded; a file that records none is reconstructed with
                 DEFAULT_METHOD).
    speed:       "max" (as fast as it decodes) or a factor of recorded time (1: real time).
    bin_s:       bin width for files that record no settings of ours.
    """

    KIND = "replay"
    recording: str = ""
    target: int | None = None
    method: str | None = None
    pulse_rms_s: float | None = None
    speed: str | float = default("--speed", "replay")
    bin_s: float = default("--bin-ps", "replay")
    reflectors: int | str | None = None
    max_reflectors: int | None = None
    false_alarm: float | None = None

    def __post_init__(self) -> None:
        if not self.recording:
            raise RequestError("choose a recording to replay (a session folder or its recording.ptu)")
        object.__setattr__(self, "recording", str(self.recording))
        p = Path(self.recording)
        if not p.exists():
            raise RequestError(f"recording {p} does not exist")
        if p.is_dir() and not (p / "recording.ptu").is_file():
            raise RequestError(f"recording {p}: the folder holds no recording.ptu")
        check_request(self, "replay")
        _method(self.method)

    @property
    def folder(self) -> Path:
        """The recording's own folder (a replay must not write into it)."""
        p = Path(self.recording)
        return p if p.is_dir() else p.parent

    def label(self) -> str:
        return f"replay of {Path(self.recording).name}"


@dataclass(frozen=True)
class FileReconRequest(_Request):
    """A recorded file (first-photon-imaging .mat, PicoQuant PTU/HT3/PT3) reconstructed as a whole.

    time_unit_s: size of one raw time unit (required for .mat; PicoQuant files: the header's).
    window_s, bin_s, pulse_rms_s, max_photons: None leaves each to the file's recorded session
                 settings when it has them, else to the data (window: the detections' span; bins: a
                 ninth of the pulse RMS; pulse: estimated).
    irf:         a measured response file (CSV time_ps,counts or .npy) instead of a Gaussian.
    reflectors:  surfaces per pixel: K (1 to 8) or "auto" (decided per pixel by a likelihood-ratio test
                 at ``false_alarm`` per pixel and surface, up to ``max_reflectors``); recon.estimators.surfaces_fit.
    out, png, save_irf: where the maps (.npz), the picture and the pulse shape used go (None: not
                 written); checked for writability before any work.
    ply, las:    point clouds of the maps (``acq.points``; None: not written).
    fov_deg:     field of view (degrees, square, centred) for files without scan geometry (.mat):
                 gives the pixels' angles for points and for the pictures' true aspect.
    range_offset_m, gate_delay_s: gated long-range data record times after a range gate: the
                 range added to every depth (or the gate delay, c * delay / 2 added); one or none.
    threads:     estimator threads (None: all cores).
    periods, pileup, dead_time_s: pile-up (``recon.pileup``): the laser periods each pixel (each
                 frame of a cube) integrated over, for files that do not record them; ``auto``
                 corrects where detections per period are not small, ``on``/``off`` force it; the
                 detector's dead time (None: it re-arms at each laser sync).
    """

    KIND = "recon"
    input: str = ""
    method: str = default("--method", "file")
    time_unit_s: float | None = None
    window_s: tuple[float, float] | None = None
    bin_s: float | None = None
    pulse_rms_s: float | None = None
    irf: str | None = None
    max_photons: int | None = None
    reflectors: int | str = default("--reflectors", "file")
    max_reflectors: int = default("--max-reflectors", "file")
    false_alarm: float = default("--false-alarm", "file")
    neighbour_false_alarm: float = default("--neighbour-false-alarm", "file")
    mat_var: str | None = None
    channel: int | None = None
    threads: int | None = None
    out: str | None = None
    png: str | None = None
    save_irf: str | None = None
    ply: str | None = None
    las: str | None = None
    fov_deg: float | None = None
    range_offset_m: float | None = None
    gate_delay_s: float | None = None
    periods: float | None = None
    pileup: str = default("--pileup", "file")
    dead_time_s: float | None = None

    def __post_init__(self) -> None:
        if not self.input:
            raise RequestError("choose a file to reconstruct")
        check_request(self, "file")
        _method(self.method)
        if self.range_offset_m is not None and self.gate_delay_s is not None:
            raise RequestError("give --range-offset-m or --gate-delay-ns, not both")
        if (self.ply or self.las) and self.fov_deg is None and \
                Path(str(self.input)).suffix.lower() == ".mat":
            raise RequestError(f"{self.input}: a .mat file holds no scan geometry: give --fov-deg "
                               f"to write points (--ply/--las)")
        object.__setattr__(self, "input", str(self.input))
        if not Path(self.input).is_file():
            raise RequestError(f"{self.input}: no such file")
        if self.time_unit_s is None and Path(self.input).suffix.lower() == ".mat":
            raise RequestError(f"{self.input}: a .mat file does not record its time unit: give "
                               f"--time-unit-ps (8 for the first-photon-imaging files, 1 for ps)")
        object.__setattr__(self, "window_s", _window(self.window_s))
        check_bin_fits(self.bin_s, self.window_s)
        if self.irf is not None and self.pulse_rms_s is not None:
            raise RequestError("give --pulse-rms-ps or --irf, not both")
        if self.irf is not None and not Path(self.irf).is_file():
            raise RequestError(f"--irf {self.irf}: no such file")
        for name, path in (("--npz", self.out), ("--png", self.png), ("--save-irf", self.save_irf),
                           ("--ply", self.ply), ("--las", self.las)):
            check_writable(name, path)

    def label(self) -> str:
        return f"{Path(self.input).name}, {self.method}"

    def writes_files(self) -> bool:
        """Whether the reconstruction writes a file (maps, picture, pulse shape, points); when not,
        its summary alone is seen, which holds no uncertainty (``acq.api.reconstruct_file``'s
        ``spreads``)."""
        return any((self.out, self.png, self.save_irf, self.ply, self.las))


def build_request(source: str, values: dict):
    """The request of ``source`` ("sim", "real", "replay", "file") for option values in their
    units (dest -> value; what is missing takes the request's default). A value for an option
    of another source is refused, naming it; the request checks itself as a whole."""
    from spdepth.acq.params import _DECLARED, SOURCES, WHERE, params_of

    if source not in SOURCES:
        raise RequestError(f"source must be one of {', '.join(SOURCES)}, got {source!r}")
    inst_cls = {"sim": SimBench, "real": Devices}.get(source)
    req_cls = {"sim": ScanRequest, "real": ScanRequest, "replay": ReplayRequest,
               "file": FileReconRequest}[source]
    inst_fields = {f.name for f in fields(inst_cls)} if inst_cls else set()
    mine = {p.dest: p for p in params_of(source)}
    inst_kw, req_kw = {}, {}
    for dest, value in values.items():
        if value is None:
            continue
        p = mine.get(dest)
        if p is None:
            other = next((q for q in _DECLARED if q.dest == dest), None)
            if other is None or not other.field:
                continue
            where = " or ".join(WHERE[s] for s in other.sources)
            raise RequestError(f"{other.option} is an option of {where}, not of {WHERE[source]}")
        (inst_kw if p.field in inst_fields else req_kw)[p.field] = p.to_si(value)
    if inst_cls is not None:
        req_kw["instruments"] = inst_cls(**inst_kw)
    return req_cls(**req_kw)


REQUEST_KINDS = {cls.KIND: cls for cls in (ScanRequest, ReplayRequest, FileReconRequest)}


def request_from_dict(d: dict):
    """Any saved request, typed by its ``kind``."""
    if not isinstance(d, dict) or d.get("kind") not in REQUEST_KINDS:
        raise RequestError(f"not a saved request (kind {d.get('kind') if isinstance(d, dict) else d!r})")
    return REQUEST_KINDS[d["kind"]].from_dict(d)


__all__ = ["build_request", "SimBench", "Devices", "TaggerAddress", "GalvoAddress", "parse_tagger", "parse_galvo", "ScanRequest", "ReplayRequest", "FileReconRequest",
           "request_from_dict", "DEFAULT_METHOD", "DEFAULT_SIZE", "DEFAULT_TARGET", "DEFAULT_BIN_S",
           "DEFAULT_WINDOW_S", "MAX_TARGET", "check_writable"]
