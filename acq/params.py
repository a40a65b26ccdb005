"""Every option a user can give spdepth, declared once: the command line, the requests' single-field
checks, the window's controls and tooltips, and the README's option tables are generated from here.

The model is pymeasure's ``Parameter``/``Procedure`` (parameters as data; a window builds its inputs
from them). One :class:`Param` per option name, so an option means one thing in every command:

- ``option``/``field``: the CLI spelling and the request field it fills (``--pulse-rms-ps`` ->
  ``pulse_rms_s``), with ``unit`` and ``scale`` (the option's unit in SI: ps -> 1e-12): the option
  is in its unit, the request in SI, and only :func:`to_si`/:func:`from_si` convert.
- ``kind`` (``float``, ``int``, ``str``, ``flag``, ``size`` WxH, ``window`` START:STOP,
  ``surfaces`` K|auto, ``speed`` max|factor, ``xy`` X,Y), ``low``/``high`` (in the option's unit)
  and ``choices`` (a tuple, or a function read lazily: the estimator registry, the scenes).
- ``default`` (in the option's unit; None: ``default_text`` says what happens instead), ``help``,
  ``group`` (the --help section), ``label`` (the window's control; "" for none).
- ``sources``: the source kinds it belongs to (``sim`` the simulated bench, ``real`` devices,
  ``replay`` a recording, ``file`` a file reconstruction), which give its ``commands``
  (:data:`SOURCE_COMMANDS`) unless it names its own; ``per_source`` replaces attributes for one
  source (a replay's "as recorded" defaults, a file's ``max_photons`` field behind ``--target``).

Options that are no request field (``--out``, ``--json``, ``--screenshot`` ...) are declared here
too (``field=""``), so the option table covers every command.

``--out`` has one meaning everywhere: the folder a command writes its files into (a session's run
folder for scan, replay, demo and the window; the report's folder for ``bench report``). A single
output file is named by its format: ``--npz``, ``--png``, ``--ply``, ``--las``, ``--ptu``.

This module imports no numerical or Qt module: building the parser stays fast (``spdepth
--help``). Lists owned elsewhere (the estimator registry ``recon.estimators``, the scenes, the
fault kinds, the tagger models) are read when a help text or a check needs them.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
from dataclasses import dataclass, field
from typing import Any, Callable, Mapping

from spdepth.acq.errors import RequestError

SOURCES = ("sim", "real", "replay", "file")
"""Where photons come from: the simulated bench, real devices, a recording replayed through the
session pipeline, a file reconstructed as a whole."""
SCAN_SOURCES = ("sim", "real")
SOURCE_COMMANDS = {"sim": ("scan", "demo", "gui"), "real": ("scan", "gui"),
                   "replay": ("replay", "gui"), "file": ("recon", "gui")}
"""The commands that run each source kind (an option of a source is an option of each)."""
COMMANDS = ("scan", "replay", "demo", "gui", "recon", "simulate", "array", "bench report")
"""The commands whose options are declared here, in the option table's column order."""

# ---- limits and defaults owned here (the requests, the window and recon's checks read them) ------
DEFAULT_SIZE = (64, 64)
"""(H, W) of a scan unless the user picks another (scan, demo and the window alike)."""
DEFAULT_TARGET = 15
"""In-window detections per pixel: the seed paper's first 15 (``recon.model.SEED_PAPER``)."""
DEFAULT_BIN_PS = 40.0
"""Histogram bin of a scan: the seed paper's 40 ps."""
DEFAULT_N_BINS = 801
"""Bins of a scan's default detection window (the seed paper's window length)."""
DEFAULT_METHOD = "ml"
"""The estimator of every command and the window unless the user picks another: exact Poisson ML,
the most accurate pixelwise estimator (within a few percent of the oracle bound), fast enough since
issue 18 to keep up with a live scan (``spdepth bench session`` prints the live backlog)."""
DEFAULT_REFLECTORS = 1
DEFAULT_MAX_REFLECTORS = 3
DEFAULT_FALSE_ALARM = 1e-3
DEFAULT_NEIGHBOUR_FALSE_ALARM = 0.05
MAX_SURFACES = 8
"""Most surfaces per pixel any estimator fits (``--reflectors``, ``--max-reflectors``)."""
PULSE_RMS_PS = (1.0, 1e6)
"""A pulse (response) RMS width in physical sense, ps: no single-photon detector's timing is finer
than 1 ps, and a response wider than 1 us RMS is no pulse (1e9 put every pixel at 8,328 m)."""
MAX_PIXELS_PER_AXIS = 4096
"""The galvo controller's largest raster side (``drivers.galvo.protocol``; a test ties the two)."""
MIN_DWELL_MS, MAX_DWELL_MS = 100e-6, 10_000_000.0 / 1e3
"""The galvo controller's dwell range per pixel (100 ns .. 10 s)."""
MODES = ("gated", "raster")
"""gated: hold each pixel until the target or the dwell limit; raster: fixed dwell, frames repeated."""
ARRAY_MODES = ("frame", "accumulate")
"""spdepth array: the maps of each frame alone, or of all frames so far."""
PATTERNS = ("raster", "serp")
VIEWS = ("maps", "3d")

def estimators() -> tuple[tuple[str, str], ...]:
    """(name, one-line summary) of every estimator ``--method`` takes, in the registry's order:
    the one place the CLI, the requests' checks, the window and the docs read them from. Read
    from the estimator registry (``recon.estimators``) when asked, never at import: reading it
    loads no kernel and no numba, so ``--help`` can list them."""
    from spdepth.recon import estimators as registry

    return tuple((n, registry.get(n).summary) for n in registry.names())


def method_names() -> tuple[str, ...]:
    return tuple(name for name, _ in estimators())


def pixelwise_methods() -> tuple[str, ...]:
    """The estimators that fit each pixel on its own (the demo compares those)."""
    from spdepth.recon import estimators as registry

    return registry.names(pixelwise=True)


def _methods_help() -> str:
    from spdepth.recon import estimators as registry

    note = registry.live_note()
    return registry.summaries() + (f"; {note}" if note else "")


def scene_names() -> tuple[str, ...]:
    """The built-in scenes (``drivers.sim.builtin_scenes``, the names ``drivers.sim.scenes.BUILTIN``
    maps), sorted as ``drivers.sim.scene_names()`` gives them; read when asked."""
    from spdepth.drivers.sim.builtin_scenes import BUILTIN_SCENES

    return tuple(sorted(BUILTIN_SCENES))


def fault_kinds() -> str:
    """Every fault kind the simulated devices inject, by device (``drivers.sim.faults.FaultKind``)."""
    from spdepth.drivers.sim.faults import FaultKind

    by = {}
    for k in FaultKind:
        where = "NI-DAQ galvo" if k.value.startswith("daq-") else k.device
        by.setdefault(where, []).append(k.value)
    return "; ".join(f"{', '.join(v)} ({where})" for where, v in by.items())


def tagger_forms() -> str:
    from spdepth.drivers.picoquant.protocol import FAMILIES

    return (f"picoquant:MODEL[:SERIAL] ({', '.join(FAMILIES)}), swabian[:SERIAL] or "
            "usb:VID:PID (ours)")


GALVO_FORMS = "nidaq:DEV[/aoN:M] (e.g. nidaq:Dev1/ao0:1) or a serial PORT"
_LAZY_TEXT: dict[str, Callable[[], str]] = {
    "methods": _methods_help,
    "method_names": lambda: "{" + ",".join(method_names()) + "}",
    "pixelwise": lambda: ",".join(pixelwise_methods()),
    "scenes": lambda: ", ".join(scene_names()),
    "faults": fault_kinds,
    "taggers": tagger_forms,
}


def expand(text: str) -> str:
    """A help text (or metavar) with its ``{methods}``, ``{method_names}``, ``{pixelwise}``,
    ``{scenes}``, ``{faults}``, ``{taggers}`` filled in (read only when a help is shown)."""
    for key, fill in _LAZY_TEXT.items():
        if "{" + key + "}" in text:
            text = text.replace("{" + key + "}", fill())
    return text


# ---- the declaration ----------------------------------------------------------------------------
@dataclass(frozen=True)
class Param:
    """One option, as the CLI, the requests and the window see it (see the module docstring)."""

    option: str
    field: str
    kind: str
    help: str
    group: str
    sources: tuple[str, ...] = ()
    commands: tuple[str, ...] = ()
    unit: str = ""
    scale: float = 1.0
    default: Any = None
    default_text: str = ""
    low: float | None = None
    low_open: bool = False
    high: float | None = None
    high_open: bool = False
    range_text: str = ""
    choices: tuple | Callable[[], tuple] | None = None
    free: bool = False
    metavar: str | None = None
    label: str = ""
    none_label: str = ""
    remembered: bool = True
    positional: tuple[str, ...] = ()
    required: bool = False
    nargs: str | None = None
    aliases: tuple[str, ...] = ()
    exclusive: str = ""
    example: str = ""
    summary: str = ""
    per_source: Mapping[str, Mapping[str, Any]] = field(default_factory=dict)
    per_command: Mapping[str, Mapping[str, Any]] = field(default_factory=dict)

    @property
    def dest(self) -> str:
        return self.option.lstrip("-").replace("-", "_")

    def for_source(self, source: str) -> "Param":
        """This option as it applies to one source kind (its ``per_source`` changes made)."""
        over = self.per_source.get(source)
        return dataclasses.replace(self, per_source={}, **over) if over else self

    def for_command(self, command: str) -> "Param":
        over = self.per_command.get(command)
        return dataclasses.replace(self, per_command={}, **over) if over else self

    def in_command(self, command: str) -> bool:
        if self.commands:
            return command in self.commands
        return any(command in SOURCE_COMMANDS[s] for s in self.sources)

    def sources_of(self, command: str) -> tuple[str, ...]:
        return tuple(s for s in self.sources if command in SOURCE_COMMANDS[s])

    def choice_list(self) -> tuple:
        return tuple(self.choices()) if callable(self.choices) else tuple(self.choices or ())

    # ---- values ---------------------------------------------------------------------------------
    def parse(self, text: str):
        """The option's text as a value in its unit, checked; ``argparse.ArgumentTypeError`` (one
        line, naming the value) otherwise."""
        try:
            value = _PARSERS[self.kind](text)
        except ValueError as exc:
            raise argparse.ArgumentTypeError(str(exc) or f"bad value {text!r}") from None
        try:
            self.check(value)
        except RequestError as exc:
            raise argparse.ArgumentTypeError(str(exc).replace(f"{self.option} ", "", 1)) from None
        return value

    def check(self, value) -> None:
        """A value in the option's unit against the declaration: type, range, choices. Raises
        ``RequestError`` naming the option and the value; None (the default) passes."""
        if value is None:
            return
        opt = self.option
        k = self.kind
        if k == "surfaces":
            if value == "auto":
                return
            if isinstance(value, str) and value.isdigit():
                value = int(value)
            if not _whole(value) or value < 1:
                raise RequestError(f"{opt} must be a whole number >= 1 or auto, got {value!r}")
            if value > MAX_SURFACES:
                raise RequestError(f"{opt} must be at most {MAX_SURFACES} or auto, got {value!r}")
            return
        if k == "speed" and value == "max":
            return
        if k in ("float", "int", "speed"):
            number = isinstance(value, (int, float)) and not isinstance(value, bool) and \
                math.isfinite(value)
            if k == "int" and not (number and _whole(value)):
                raise RequestError(f"{opt} must be {self._range_words()}, got {value!r}")
            if not number:
                raise RequestError(f"{opt} must be a number ({self._range_words()}), got {value!r}")
            too_low = self.low is not None and (value <= self.low if self.low_open else
                                                value < self.low * (1 - 1e-12))
            too_high = self.high is not None and (value >= self.high if self.high_open else
                                                  value > self.high * (1 + 1e-12))
            if too_low or too_high:
                if self.range_text:
                    raise RequestError(f"{opt} {value:g}: {self.range_text}")
                raise RequestError(f"{opt} must be {self._range_words()}, got {value:g}")
            return
        if k == "window":
            start, stop = _two(opt, value, "(start, stop)", float)
            if not (math.isfinite(start) and math.isfinite(stop) and 0 <= start < stop):
                raise RequestError(f"{opt} needs 0 <= START < STOP, got {start:g}:{stop:g} {self.unit}")
            return
        if k == "size":
            h, w = _two(opt, value, "WxH", _exact_int)
            if not (1 <= h <= MAX_PIXELS_PER_AXIS and 1 <= w <= MAX_PIXELS_PER_AXIS):
                raise RequestError(f"{opt} {w}x{h}: each side must be 1..{MAX_PIXELS_PER_AXIS} pixels "
                                   f"(the galvo controller's limit)")
            return
        if k == "xy":
            _two(opt, value, f"X,Y {self.unit}", float)
            return
        if k in ("str", "path"):
            if not isinstance(value, str):
                raise RequestError(f"{opt} must be text, got {value!r}")
        if self.choices is not None and not self.free:
            names = self.choice_list()
            if value not in names:
                raise RequestError(f"{opt} must be one of {', '.join(names)}, got {value!r}")

    def _range_words(self) -> str:
        whole = self.kind == "int"
        lo, hi = self.low, self.high
        if not whole and self.low_open and self.high_open and lo == 0 and hi == 1:
            return "a probability between 0 and 1"
        if whole:
            words = f"a whole number >= {lo + 1 if self.low_open else lo:g}" if lo is not None \
                else "a whole number"
        elif lo == 0 and self.low_open:
            words = "a positive number"
        elif lo is not None:
            words = f"a number {'>' if self.low_open else '>='} {lo:g}"
        else:
            words = "a number"
        if hi is not None:
            words += f" and {'below' if self.high_open else 'at most'} {hi:g}"
        return words

    def to_si(self, value):
        """The option's value (its unit) as the request holds it (SI)."""
        if value is None or self.scale == 1.0 or self.kind not in ("float", "window", "int"):
            return value
        if self.kind == "window":
            return tuple(v * self.scale for v in value)
        return value * self.scale

    def from_si(self, value):
        """The request's value (SI) in the option's unit (to 12 digits: 8e-12 s is 8 ps)."""
        if value is None or self.scale == 1.0 or self.kind not in ("float", "window", "int"):
            return value
        if self.kind == "window":
            return tuple(float(f"{v / self.scale:.12g}") for v in value)
        return float(f"{value / self.scale:.12g}")

    def default_words(self) -> str:
        if self.default is None:
            return self.default_text
        return _show(self.default, self.kind)


def _two(opt: str, value, form: str, kind) -> tuple:
    """A pair of ``kind`` (a window, a size, X,Y), or RequestError naming ``form``."""
    try:
        a, b = (kind(v) for v in value)
    except (TypeError, ValueError):
        raise RequestError(f"{opt} must be {form}, got {value!r}") from None
    return a, b


def _exact_int(v) -> int:
    if isinstance(v, bool) or int(v) != v:
        raise ValueError(v)
    return int(v)


def _whole(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and int(v) == v


def _show(value, kind: str) -> str:
    if kind == "size":
        return f"{value[1]}x{value[0]}"
    if kind == "window":
        return f"{value[0]:g}:{value[1]:g}"
    if kind == "xy":
        return f"{value[0]:g},{value[1]:g}"
    if isinstance(value, float):
        return f"{value:g}"
    return str(value)


def _parser(convert: Callable[[str], Any], words: str, keep: tuple[str, ...] = ()):
    """An option's text -> value: ``convert``, the words in ``keep`` as they are, and a
    ValueError saying ``words`` otherwise."""
    def parse(text: str):
        if text in keep:
            return text
        try:
            return convert(text)
        except ValueError:
            raise ValueError(f"{words}, got {text!r}") from None
    return parse


def _pair(sep: str, kind: type):
    def convert(text: str):
        a, b = (kind(v) for v in text.lower().split(sep))
        return a, b
    return convert


def _wxh(text: str) -> tuple[int, int]:
    """'WxH' (width first, as image sizes are written) -> (H, W), rows first as arrays are."""
    w, h = _pair("x", int)(text)
    return h, w


_PARSERS: dict[str, Callable[[str], Any]] = {
    "float": _parser(float, "expected a number"), "int": _parser(int, "expected a whole number"),
    "str": str, "path": str, "size": _parser(_wxh, "size must be WxH (e.g. 64x64)"),
    "window": _parser(_pair(":", float), "expected START:STOP"),
    "surfaces": _parser(int, "expected a whole number or auto", keep=("auto",)),
    "speed": _parser(float, "expected max or a positive factor", keep=("max",)),
    "xy": _parser(_pair(",", float), "expected X,Y"),
}
def parse_size(text: str) -> tuple[int, int]:
    """``--size`` WxH -> (H, W) checked, as an argparse ``type`` (the benchmarks use it too)."""
    return PARAMS["--size"].parse(text)


# ---- the declarations -----------------------------------------------------------------------------
_AS_RECORDED = dict(default=None, default_text="as recorded")
_SURFACES = "surfaces"
_SCAN_DWELL = (f"the galvo controller holds a pixel {MIN_DWELL_MS:g}..{MAX_DWELL_MS:g} ms")

_DECLARED = (
    # -- source ------------------------------------------------------------------------------------
    Param("--sim", "", "flag", group="source", commands=("scan", "gui", "array"),
          per_command={"array": dict(kind="str", metavar="SCENE", choices=scene_names, free=True,
                                     exclusive="array source", required=True,
                                     help="simulate the array looking at this scene ({scenes})")},
          help="the simulated bench: a scene behind the real drivers (galvo emulator over a pyserial "
               "URL, tagger over pyusb); with --tagger/--galvo naming a vendor device, reached "
               "through that vendor's driver and a stand-in of its library"),
    Param("--galvo", "galvo", "str", group="source", sources=SCAN_SOURCES, default="",
          summary="the galvo: nidaq:DEV or our controller's serial port",
          default_text="", metavar="GALVO", label="Galvo", example="/dev/ttyACM0",
          help="galvo: nidaq:DEV[/aoN:M] (NI-DAQ analog outputs) or our controller's serial PORT "
               "or URL; with --sim only nidaq:DEV (the NI-DAQ driver on a stand-in)"),
    Param("--tagger", "tagger", "str", group="source", sources=SCAN_SOURCES, default="",
          summary="the time tagger: picoquant:MODEL, swabian or usb:VID:PID",
          metavar="TAGGER", label="Tagger", example="usb:VID:PID",
          help="time tagger: {taggers}; with --sim only a vendor tagger (its driver on a stand-in)"),
    Param("--replay", "recording", "path",
          summary="the recording replayed: a run folder or a PTU",
          group="source", sources=("replay",), metavar="RECORDING",
          positional=("replay",), label="Recording", example="run folder or recording.ptu",
          commands=("replay", "gui", "array"),
          per_command={"array": dict(metavar="FRAMES.h5", exclusive="array source", required=True,
                                     help="replay an array recording (frames.h5)")},
          help="a session folder or its recording.ptu, or a Generic T3 PTU with pixel markers, "
               "replayed through the session pipeline"),
    Param("--file", "input", "path",
          summary="the file reconstructed: .mat or PTU/HT3/PT3",
          group="source", sources=("file",), metavar="INPUT",
          positional=("recon",), label="File", example="scan.ptu or data.mat",
          per_command={"recon": dict(nargs="+", help=".mat (first-photon imaging) or PTU/HT3/PT3 "
                                     "T3 file, or a count cube (H x W x T, or frames) in .mat/.npy/"
                                     ".npz/HDF5; with several, --npz and --png name folders "
                                     "(NPZ/<name>.npz)")},
          help="a .mat (first-photon imaging) or PicoQuant PTU/HT3/PT3 T3 file, reconstructed as "
               "spdepth recon does"),
    # -- simulated bench -------------------------------------------------------------------------
    Param("--scene", "scene", "str",
          summary="the simulated scene: a built-in one or file:DEPTH",
          group="simulated bench", sources=("sim",), default="bust",
          choices=scene_names, free=True, label="Scene",
          per_command={"simulate": dict(default=None, required=True)},
          commands=("scan", "demo", "gui", "simulate"),
          help="a built-in scene ({scenes}) or file:PATH[,reflectivity=PATH][,scale=M_PER_UNIT]"
               "[,offset=M] for a depth image (.npy/.png/.tif; float images in metres, integer "
               "images in millimetres unless scale)"),
    Param("--ppp", "ppp", "float",
          summary="mean detections per pixel per scene dwell",
          group="simulated bench", sources=("sim",), low=0, low_open=True,
          default_text="the target", commands=("scan", "demo", "gui", "simulate"),
          per_command={"simulate": dict(default=15.0)},
          help="mean detections (signal + background) per pixel per scene dwell"),
    # one definition per scene: every command takes the scene's own SBR unless given (daylight's
    # 0.05 was 10 in scan --sim, demo and the window)
    Param("--sbr", "sbr", "float", group="simulated bench", sources=("sim",), default=None, low=0,
          low_open=True, label="SBR", commands=("scan", "demo", "gui", "simulate", "array"),
          default_text="the scene's: 10, daylight 0.05", none_label="the scene's",
          per_command={"array": dict(default=1.0, group="array",
                                     help="signal to background in range (--sim)")},
          help="signal-to-background ratio in the detection window"),
    Param("--seed", "seed", "int", group="simulated bench", sources=("sim",), default=0, low=0,
          high=2**31 - 1, label="Seed", commands=("scan", "demo", "gui", "simulate", "array"),
          per_command={"array": dict(group="array", help="random seed (--sim)")},
          help="random seed"),
    Param("--faults", "faults", "str", group="simulated bench", sources=("sim",), default="",
          metavar="SPEC", label="Faults", example="e.g. device-vanish@40%", remembered=False,
          help="faults to inject, KIND@WHEN items (WHEN in virtual seconds '2s' or share of the scan "
               "'40%'), e.g. fifo-overflow@40%,device-vanish@2s; kinds: {faults}"),
    # -- real devices ----------------------------------------------------------------------------
    Param("--sync-rate-hz", "sync_rate_hz", "float", group="real devices", sources=("real",),
          unit="Hz", low=0, low_open=True, default_text="required", label="Sync rate",
          none_label="required",
          help="the laser repetition rate (recorded in the PTU header)"),
    Param("--fov-deg", "fov_deg", "float",
          summary="square field of view in optical degrees, centred",
          group="real devices", sources=("real", "file"), unit="deg",
          default=20.0, low=0, low_open=True, high=90.0, metavar="DEG",
          range_text="wider than a galvo mirror turns (90)", label="Field of view",
          per_source={"file": dict(default=None, high=180, high_open=True,
                                   range_text="a field of view must be under 180",
                                   default_text="none", group="points",
                                   help="field of view (square, centred) of a file without scan "
                                        "geometry (.mat): the pixels' angles for --ply/--las and "
                                        "the picture's axes")},
          help="square field of view in optical degrees, centred on the mirror's zero"),
    Param("--deg-per-volt", "deg_per_volt", "float", group="real devices", sources=("real",),
          default=1.0, low=0, low_open=True, help="NI-DAQ galvo: optical degrees per volt"),
    Param("--v-limit", "v_limit", "float", group="real devices", sources=("real",), unit="V",
          default=10.0, low=0, low_open=True, high=10.0, metavar="V",
          help="NI-DAQ galvo: keep the outputs within +-V volts"),
    Param("--park-deg", "park_deg", "xy", group="real devices", sources=("real",), unit="deg",
          default=(0.0, 0.0), metavar="X,Y",
          help="NI-DAQ galvo: where the mirror rests between scans"),
    Param("--picoquant-lib", "picoquant_lib", "path", group="real devices", sources=("real",),
          metavar="PATH", default_text="search the install places, the snapi package "
          "and SPDEPTH_PICOQUANT_LIB", help="PicoQuant: the device library file"),
    Param("--event-divider", "event_divider", "int", group="real devices", sources=("real",),
          default=1, low=1, high=65535, metavar="N",
          help="Swabian: tag every N-th laser sync only (high laser rates)"),
    # -- scan --------------------------------------------------------------------------------------
    Param("--size", "size", "size", group="scan", sources=SCAN_SOURCES, default=DEFAULT_SIZE,
          metavar="WxH", label="Size", commands=("scan", "demo", "gui", "simulate", "array"),
          per_command={"simulate": dict(default=None, default_text="64x64; a depth image's own "
                                        "size for file:"),
                       "array": dict(group="array", help="the array's pixels, width x height (--sim)")},
          help="pixels, width x height"),
    Param("--target", "target", "int",
          summary="in-window detections kept per pixel",
          group="scan", sources=SCAN_SOURCES + ("replay", "file"),
          default=DEFAULT_TARGET, low=1, metavar="N", label="Target",
          per_source={"replay": dict(default=None, none_label="as recorded",
                                     default_text="the recorded target; required for files that "
                                                  "record none",
                                     help="detections per pixel to keep (fewer shows what a "
                                          "shorter scan would have given)"),
                      "file": dict(field="max_photons", default=None, none_label="all",
                                   default_text="every in-window detection; a session's recording: "
                                                "its target",
                                   help="keep the first N in-window detections per pixel (the seed "
                                        "paper: 15)")},
          per_command={"recon": dict(aliases=("--max-photons",))},
          help="in-window detections per pixel"),
    Param("--mode", "mode", "str",
          summary="gated (each pixel until the target) or raster (fixed dwell); array: frame or accumulate",
          group="scan", sources=SCAN_SOURCES, default="gated",
          choices=MODES, label="Mode", commands=("scan", "demo", "gui", "array"),
          per_command={"array": dict(choices=ARRAY_MODES, default="accumulate", group="array",
                                     help="maps of each frame alone, or of all frames so far")},
          help="gated: hold each pixel until N detections or the dwell limit; raster: fixed "
               "dwell, frames repeated until every pixel has N"),
    Param("--dwell-limit-ms", "dwell_limit_s", "float", group="scan", sources=SCAN_SOURCES,
          unit="ms", scale=1e-3, low=MIN_DWELL_MS, high=MAX_DWELL_MS, range_text=_SCAN_DWELL,
          metavar="T", default_text="20 scene dwells / 10 ms", none_label="default",
          help="gated only: dwell limit per pixel"),
    Param("--dwell-ms", "dwell_s", "float", group="scan", sources=SCAN_SOURCES, unit="ms",
          scale=1e-3, low=MIN_DWELL_MS, high=MAX_DWELL_MS, range_text=_SCAN_DWELL, metavar="T",
          default_text="the scene's dwell / 1 ms", none_label="default",
          help="raster only: dwell per pixel and frame"),
    Param("--pattern", "pattern", "str", group="scan", sources=SCAN_SOURCES, default="raster",
          choices=PATTERNS, help="line order: raster or serpentine"),
    Param("--settle-us", "settle_s", "float", group="scan", sources=SCAN_SOURCES, unit="us",
          scale=1e-6, default=0.0, low=0, high=1e6, metavar="US",
          help="wait after each step before the pixel opens"),
    Param("--max-passes", "max_passes", "int",
          summary="re-acquisition passes (gated) or frames (raster)",
          group="scan", sources=SCAN_SOURCES, low=1,
          metavar="N", default_text="gated 10 re-acquisition passes, raster 100 frames",
          help="gated: re-acquisition passes; raster: frames"),
    Param("--time-limit-s", "time_limit_s", "float", group="scan", sources=SCAN_SOURCES, unit="s",
          low=0, low_open=True, metavar="S", default_text="none",
          help="end the scan after S seconds; short pixels are flagged"),
    Param("--window-ps", "window_s", "window", group="scan", sources=SCAN_SOURCES + ("file",),
          unit="ps", scale=1e-12, metavar="START:STOP",
          default_text=f"0:{DEFAULT_N_BINS * DEFAULT_BIN_PS:g}, {DEFAULT_N_BINS} bins of "
                       f"{DEFAULT_BIN_PS:g} ps",
          per_source={"file": dict(group="estimator", default_text="as recorded, else the span of "
                                   "the detections present",
                                   help="keep detections with START <= t < STOP (ps after the "
                                        "laser sync)")},
          help="detection window after the sync"),
    Param("--bin-ps", "bin_s", "float", group="scan", sources=SCAN_SOURCES + ("replay", "file"),
          unit="ps", scale=1e-12, default=DEFAULT_BIN_PS, low=0, low_open=True, metavar="PS",
          per_source={"replay": dict(group="estimator",
                                     help="histogram bin width for files without recorded settings"),
                      "file": dict(group="estimator", default=None, default_text="as recorded, else "
                                   "a ninth of the pulse RMS",
                                   help="histogram bin width (a whole number of raw units)")},
          help="histogram bin width"),
    # -- estimator ---------------------------------------------------------------------------------
    Param("--method", "method", "str",
          summary="the estimator",
          group="estimator", sources=SOURCES, default=DEFAULT_METHOD,
          choices=method_names, label="Estimator", metavar="{method_names}",
          commands=("scan", "replay", "demo", "gui", "recon", "array"),
          per_command={"array": dict(help="estimator of every frame's maps. {methods}")},
          per_source={"replay": dict(default=None, default_text=f"as recorded, else {DEFAULT_METHOD}")},
          help="estimator. {methods}"),
    Param("--pulse-rms-ps", "pulse_rms_s", "float", group="estimator", sources=SOURCES, unit="ps",
          scale=1e-12, low=PULSE_RMS_PS[0], high=PULSE_RMS_PS[1], metavar="PS", exclusive="pulse",
          label="Pulse RMS",
          range_text=(f"outside {PULSE_RMS_PS[0]:g} to {PULSE_RMS_PS[1]:g} ps: no single-photon "
                      f"detector's response is narrower than 1 ps or wider than 1 us RMS (a width in ns "
                      f"typed as ps? 0.36 ns is 360 ps)"),
          none_label="estimate",
          default_text="the simulated scene's, or estimated from the first pixels to complete; with "
                       "several surfaces the response measured on their surfaces",
          per_source={"sim": dict(none_label="the scene's"),
                      "replay": dict(default_text="as recorded", none_label="as recorded"),
                      "file": dict(default_text="as recorded, else estimated from the data")},
          help="Gaussian pulse RMS width (the seed paper: 360)"),
    Param("--irf", "irf", "path",
          summary="a measured instrument response instead of a Gaussian",
          group="estimator", sources=("file",), metavar="FILE",
          exclusive="pulse", help="a measured instrument response (CSV time_ps,counts or .npy) "
          "instead of a Gaussian"),
    Param("--reflectors", "reflectors", _SURFACES, group="estimator", sources=SOURCES,
          default=DEFAULT_REFLECTORS, metavar="K|auto", label="Surfaces",
          per_source={"replay": dict(_AS_RECORDED, none_label="as recorded")},
          help=f"surfaces per pixel to look for: up to K (1 to {MAX_SURFACES}), or auto (decided per "
               "pixel by a likelihood-ratio test, up to --max-reflectors)"),
    Param("--max-reflectors", "max_reflectors", "int", group="estimator", sources=SOURCES,
          default=DEFAULT_MAX_REFLECTORS, low=1, high=MAX_SURFACES, metavar="K",
          per_source={"replay": _AS_RECORDED},
          help="--reflectors auto: most surfaces per pixel"),
    Param("--false-alarm", "false_alarm", "float", group="estimator", sources=SOURCES,
          default=DEFAULT_FALSE_ALARM, low=0, low_open=True, high=1, high_open=True, metavar="P",
          per_source={"replay": _AS_RECORDED},
          help="chance per pixel that background alone passes for a return (every estimator's "
               "test for a return, recon.detect), and with --reflectors auto per added surface"),
    Param("--neighbour-false-alarm", "neighbour_false_alarm", "float", group="estimator", sources=("file",),
          default=DEFAULT_NEIGHBOUR_FALSE_ALARM, low=0, high=1, high_open=True, metavar="P",
          help="a pixel that fails the test, and its neighbours' support at its own estimate, is "
               "tested where its neighbours see returns: the chance that a pixel at a surface's "
               "edge without a return of its own there is given one (0: never; recon.detect)"),
    Param("--speed", "speed", "speed",
          summary="replay speed: max, or a factor of recorded time",
          group="replay", sources=("replay",), default="max",
          help="'max' (as fast as it decodes) or a factor of recorded time (1: real time)"),
    # -- files -------------------------------------------------------------------------------------
    Param("--time-unit-ps", "time_unit_s", "float", group="file", sources=("file",), unit="ps",
          scale=1e-12, low=0, low_open=True, metavar="PS", label="Time unit",
          none_label="from the file",
          default_text="PicoQuant files: the header's resolution; required for .mat (8 for the "
                       "first-photon-imaging files, 1 for ps)",
          help="size of one raw time unit"),
    Param("--mat-var", "mat_var", "str", group="file", sources=("file",), metavar="NAME",
          help="the variable to read when the file holds several: a .mat file's cell array or "
               "count cube, a .npz file's array, an HDF5 file's dataset"),
    Param("--channel", "channel", "int", group="file", sources=("file",), low=0, metavar="N",
          default_text="all", help="PicoQuant files: keep only detector channel N (0-based)"),
    Param("--threads", "threads", "int", group="file", sources=("file",), commands=("recon",),
          low=1, metavar="N", default_text="all cores", help="worker threads for the estimator"),
    Param("--dask", "", "str",
          summary="reconstruct on a dask.distributed cluster",
          group="file", commands=("recon",), metavar="ADDRESS|local:N",
          default_text="this process",
          help="reconstruct on a dask.distributed cluster: a scheduler address, or local:N for N "
               "worker processes on 127.0.0.1 (docs/dask.md); same maps (needs the dask extra: "
               "pip install 'spdepth[dask]')"),
    # -- pile-up (high flux; recon.pileup) -----------------------------------------------------------
    Param("--periods", "periods", "float", group="pile-up", sources=("file",), commands=("recon",),
          low=0, low_open=True, metavar="N",
          default_text="from the file (fixed-dwell PTU, session recordings, array recordings)",
          help="laser periods each pixel integrated over (per frame of a cube), for files that do "
               "not record them"),
    Param("--pileup", "pileup", "str", group="pile-up", sources=("file",), commands=("recon",),
          default="auto", choices=("auto", "on", "off"),
          help="Coates' pile-up correction of each pixel's histogram: auto where some pixel saw more "
               "than 0.05 detections per laser period and the periods are known; on; off"),
    Param("--dead-time-ns", "dead_time_s", "float", group="pile-up", sources=("file",),
          commands=("recon",), unit="ns", scale=1e-9, low=0, low_open=True, metavar="NS",
          default_text="the detector re-arms at each laser sync",
          help="the detector's dead time, when shorter than the laser period"),
    Param("--range-offset-m", "range_offset_m", "float", group="points", sources=("file",),
          unit="m", metavar="M", exclusive="offset",
          help="add M metres to every depth (gated long-range data whose times start at a range "
               "gate)"),
    Param("--gate-delay-ns", "gate_delay_s", "float", group="points", sources=("file",), unit="ns",
          scale=1e-9, metavar="NS", exclusive="offset",
          help="the range gate's delay after the laser pulse: adds c*delay/2 to every depth"),
    # -- outputs -------------------------------------------------------------------------------------
    Param("--out", "", "path", summary="the folder the command writes into: a session's run folder, "
          "bench report's report", group="output", commands=("scan", "replay", "demo", "gui",
                                                           "array", "bench report"), metavar="DIR",
          per_command={
              "array": dict(required=True, help="the run folder: frames.h5 (live), maps.npz, run.json"),
              "scan": dict(required=True, help="the run folder: recording.ptu, "
                           "events.jsonl, maps.npz, maps.png, points.ply, run.json"),
              "replay": dict(required=True, help="the run folder: recording.ptu, "
                             "events.jsonl, maps.npz, maps.png, points.ply, run.json"),
              "demo": dict(default_text="a temporary folder, removed", help="the run folder: "
                           "recording.ptu, events.jsonl, maps.npz, run.json"),
              "gui": dict(default_text="a new folder under --runs-dir", help="the run folder of "
                          "the run started from the command line"),
              "bench report": dict(required=True,
                                   help="the report's folder: report.md, results.csv, PNGs")},
          help="the folder the command writes its files into"),
    Param("--overwrite", "", "flag", group="output",
          summary="replace outputs that exist (without it an existing output is refused before "
                  "any work)",
          commands=("scan", "replay", "demo", "gui", "recon", "simulate"),
          per_command={
              "recon": dict(help="replace output files that exist (--npz, --png, --ply, --las, "
                                 "--save-irf); without it an existing one is refused before any "
                                 "work"),
              "simulate": dict(help="replace --ptu and its .truth.npz if they exist"),
              "demo": dict(help="write into --out even if it is not empty, and replace --png"),
              "gui": dict(help="write into --out even if it is not empty, and replace "
                               "--screenshot")},
          help="write into --out even if it is not empty (never into one a running session holds)"),
    Param("--runs-dir", "", "path", group="output", commands=("gui",), metavar="DIR",
          label="Runs folder", default_text="the window's setting, ~/spdepth-runs",
          help="the window's runs folder: each run started in the window writes its own folder here"),
    Param("--npz", "out", "path", group="output", sources=("file",), commands=("recon",),
          metavar="MAPS.npz", help="write the maps and the settings used"),
    Param("--png", "png", "path",
          summary="a picture (PNG) of the maps",
          group="output", sources=("file",), commands=("recon", "demo"),
          metavar="FILE.png",
          per_command={"demo": dict(default="spdepth-demo.png", help="the PNG sheet: truth and "
                                    "each --compare estimator's depth")},
          help="a picture of the depth, background and photon-count maps (a time histogram for a "
               "point measurement)"),
    Param("--ply", "ply", "path", group="output", sources=("file",), commands=("recon",),
          metavar="POINTS.ply", help="the maps as points (x, y, z in metres in the scanner frame, "
          "intensity, uncertainty, surface, flags; README 'Points')"),
    Param("--las", "las", "path", group="output", sources=("file",), commands=("recon",),
          metavar="POINTS.las", help="the same points as LAS 1.4"),
    Param("--save-irf", "save_irf", "path", group="output", sources=("file",), commands=("recon",),
          metavar="FILE", help="write the pulse shape used (estimated from the data when neither "
          "--pulse-rms-ps nor --irf is given) in the format --irf reads (CSV time_ps,counts; .npy "
          "for an (n, 2) array), so it is measured once"),
    Param("--ptu", "", "path", group="output", commands=("simulate",), metavar="FILE.ptu",
          required=True, help="the T3 image PTU to write (FILE.truth.npz beside it)"),
    Param("--compare", "", "str", group="demo", commands=("demo",), metavar="M,M,...",
          default_text="the pixelwise ones, {pixelwise}",
          help="estimators reconstructing the final photons against the truth, comma-separated"),
    Param("--no-window", "", "flag", group="demo", commands=("demo",),
          help="stay headless (the PNG sheet) even when a display exists; without a display (CI, "
               "ssh, QT_QPA_PLATFORM=offscreen) it always is"),
    Param("--screenshot", "", "path", group="window", commands=("gui", "array"), metavar="PNG",
          per_command={"array": dict(help="with --gui: save the window into PNG at the end and close it")},
          help="grab the whole window into PNG when the scan ends"),
    Param("--exit-after-scan", "", "flag", group="window", commands=("gui",),
          help="close the window when the scan ends (exit 0 when done, 1 otherwise)"),
    Param("--view", "", "str", group="window", commands=("gui",), choices=VIEWS, default="maps",
          help="what the window shows: the maps, or the 3-D point cloud (needs OpenGL: xvfb-run "
               "without a display)"),
    Param("--window-size", "", "size", group="window", commands=("gui",), metavar="WxH",
          default_text="the remembered size; 1480x900 with --screenshot",
          help="the window's size in screen pixels"),
    Param("--json", "", "flag", group="output", commands=("scan", "replay", "demo", "recon"),
          help="print one JSON summary object as the last stdout line"),
    # -- the SPAD array (spdepth array; no request carries them: the command's own, as simulate's)
    Param("--frames", "", "int", group="array", commands=("array",), default=30, low=1, metavar="N",
          help="frames to acquire (--sim)"),
    Param("--counts", "", "float", group="array", commands=("array",), default=20.0, low=0, low_open=True,
          metavar="X", help="mean counts per pixel and frame in range, ideal detector (--sim)"),
    Param("--frame-rate-hz", "", "float", group="array", commands=("array",), default=30.0, low=0,
          low_open=True, unit="Hz", metavar="HZ", help="frames per second of the simulated array (--sim)"),
    Param("--hot-share", "", "float", group="array", commands=("array",), default=0.0, low=0, high=1,
          metavar="X", help="share of hot pixels (--sim)"),
    Param("--crosstalk", "", "float", group="array", commands=("array",), default=0.0, low=0, high=1,
          metavar="P", help="probability a detection fires a neighbour (--sim)"),
    Param("--free-run", "", "flag", group="array", commands=("array",),
          help="do not pace frames at the frame rate (a replay runs free unless --realtime)"),
    Param("--realtime", "", "flag", group="array", commands=("array",),
          help="replay at the recorded frame rate"),
    Param("--gui", "", "flag", group="window", commands=("array",),
          help="show the session live in a window (maps and 3D)"),
    Param("--every-frame", "", "flag", group="array", commands=("array",),
          help="reconstruct every frame (the acquisition waits for the estimator)"),
)

PARAMS: dict[str, Param] = {p.option: p for p in _DECLARED}
"""Every declared option by its name."""
if len(PARAMS) != len(_DECLARED):
    raise ImportError("acq.params: an option is declared twice")

# ---- the benchmarks' options (``spdepth bench TARGET``): declared here like the others (help, default,
# range), kept apart from PARAMS: a benchmark's --sbr or --size is its own workload's, not a scan's
_BENCH_SIDE = dict(kind="int", low=4, high=MAX_PIXELS_PER_AXIS, metavar="N")
BENCH_PARAMS: dict[str, tuple[Param, ...]] = {
    "spatial": (
        Param("--side", "", help="the frame's side in pixels (a side x side frame)",
              group="workload", default=256, **_BENCH_SIDE),
        Param("--detections", "", "str", group="workload", default="2,5,10,15,30,60",
              metavar="N,N,...", help="in-window detections per pixel, comma-separated; one row "
                                      "per value and method"),
        Param("--sbr", "", "float", group="workload", default=10.0, low=0, low_open=True,
              help="signal-to-background ratio of the simulated frame"),
        Param("--methods", "", "str", group="workload", default="spatial,ml", metavar="M,M,...",
              help="estimators to time, comma-separated"),
        Param("--repeats", "", "int", group="timing", default=3, low=1, high=1000, metavar="N",
              help="timed runs per row after an untimed one that compiles; the best is kept"),
    ),
    "gui": (
        Param("--size", "", "size", group="workload", default=(48, 48), metavar="WxH",
              help="the simulated scan's size"),
        Param("--target", "", "int", group="workload", default=10, low=1,
              metavar="N", help="in-window detections per pixel of the scan"),
        Param("--scene", "", "str", group="workload", default="bust", choices=scene_names,
              help="the simulated scene: {scenes}"),
        Param("--repeats", "", "int", group="timing", default=3, low=1, high=100, metavar="N",
              help="headless and windowed runs, alternated; each figure is the best of N"),
        Param("--no-replay", "", "flag", group="workload",
              help="skip the replay comparison (the same scan's recording replayed with and "
                   "without the window)"),
        Param("--view", "", "str", group="workload", choices=VIEWS, default="maps",
              help="the window's tab during the runs (3d needs OpenGL: xvfb-run)"),
    ),
}
"""The options of the benchmarks that declare theirs here (``add_bench_options``)."""


def add_bench_options(parser: argparse.ArgumentParser, target: str) -> None:
    """``spdepth bench TARGET``'s declared options, each with its help, default and checked
    range (a --side of -3 is one line at parsing, not a NumPy traceback)."""
    groups: dict[str, Any] = {}
    for p in BENCH_PARAMS[target]:
        group = groups.get(p.group) or groups.setdefault(p.group, parser.add_argument_group(p.group))
        text = p.help.replace("{scenes}", ", ".join(p.choice_list()) if p.choices else "")
        words = p.default_words()
        text = (text + (f" (default {words})" if words and p.kind != "flag" else "")).replace("%", "%%")
        if p.kind == "flag":
            group.add_argument(p.option, dest=p.dest, action="store_true", help=text)
        else:
            group.add_argument(p.option, dest=p.dest, type=p.parse, default=p.default,
                               metavar=p.metavar or _metavar(p), help=text)


RENAMED = {
    "demo": {"--record": "--record is now --out DIR (the run folder, as in spdepth scan); the PNG "
                         "sheet is --png FILE"},
    "recon": {"--out": "--out names a folder in every command; the maps file is --npz FILE.npz"},
    "simulate": {"--out": "--out names a folder in every command; the PTU file is --ptu FILE.ptu"},
}
"""Spellings an earlier version took with another meaning: refused with one line saying what to
write now (recon's --max-photons, which meant --target, stays its alias)."""


def params_of(source: str) -> list[Param]:
    """The request options of one source kind, as they apply to it."""
    return [p.for_source(source) for p in _DECLARED if source in p.sources and p.field]


def default(option: str, source: str = "sim"):
    """The declared default of ``option`` for ``source``, as the request holds it (SI): the
    requests' field defaults are these."""
    p = PARAMS[option].for_source(source)
    return p.to_si(p.default)


def params_for(command: str) -> list[Param]:
    """The options of a command, in declaration order."""
    return [p.for_command(command) for p in _DECLARED if p.in_command(command)]


# ---- checks of a request's fields ---------------------------------------------------------------
def check_request(request, source: str) -> None:
    """Check every declared field of ``request`` (a request dataclass of ``source``'s kind, or its
    SimBench/Devices part) against its declaration; RequestError names the first bad one. The
    requests call this first, then their cross-field rules."""
    from dataclasses import fields

    names = {f.name for f in fields(request)}
    for p in params_of(source):
        if p.field in names:
            value = getattr(request, p.field)
            if p.kind == "surfaces" and isinstance(value, str) and value.isdigit():
                value = int(value)
                object.__setattr__(request, p.field, value)
            p.check(p.from_si(value))


# ---- the command line ---------------------------------------------------------------------------
class _Renamed(argparse.Action):
    def __init__(self, option_strings, dest, message="", **kw):
        self.message = message
        super().__init__(option_strings, dest=argparse.SUPPRESS, nargs="?", help=argparse.SUPPRESS)

    def __call__(self, parser, namespace, values, option_string=None):
        parser.error(self.message)


def add_options(parser: argparse.ArgumentParser, command: str, *, skip: tuple[str, ...] = ()) -> None:
    """Every declared option of ``command``, in its --help groups, each with its declared help,
    default and checked type. Defaults stay None in the namespace (the request's own default
    applies); the help says what the default is."""
    groups: dict[str, Any] = {}
    for p in params_for(command):
        if p.option in skip:
            continue
        srcs = p.sources_of(command)
        group = p.for_source(srcs[0]).group if len(srcs) == 1 else p.group
        target = groups.get(group)
        if target is None:
            target = groups[group] = parser.add_argument_group(group)
        _add(target, p, command, groups)
    for old, message in RENAMED.get(command, {}).items():
        parser.add_argument(old, action=_Renamed, message=message)


def _add(group, p: Param, command: str, groups: dict) -> None:
    help_text = _help(p, command)
    if command in p.positional:
        group.add_argument(p.dest, metavar=p.metavar or p.dest.upper(), nargs=p.nargs,
                           help=help_text)
        return
    names = (p.option, *p.aliases)
    if p.kind == "flag":
        group.add_argument(*names, dest=p.dest, action="store_true", help=help_text)
        return
    required = p.required
    if p.exclusive:
        key = ("exclusive", p.exclusive)
        if key not in groups:
            # required (one of them must be given) is the group's: argparse takes no required
            # member of an exclusive group
            groups[key] = group.add_mutually_exclusive_group(required=p.required)
        group = groups[key]
        required = False
    # a request option's default is the request's (None here: not given); a command's own
    # option carries its declared default
    own = None if p.sources_of(command) else p.default
    group.add_argument(*names, dest=p.dest, type=p.parse, default=own, metavar=p.metavar or
                       _metavar(p), help=help_text, required=required)


def _metavar(p: Param) -> str:
    if p.choices is not None and not p.free and not callable(p.choices):
        return "|".join(p.choice_list())
    return {"float": p.unit.upper() or "X", "int": "N", "speed": "max|F"}.get(p.kind, p.dest.upper())


def _help(p: Param, command: str) -> str:
    """The help of ``p`` in ``command`` with its default(s): one per source when they differ."""
    sources = p.sources_of(command) if p.field else ()
    parts = []
    if len(sources) > 1:
        said = {}
        for s in sources:
            q = p.for_source(s)
            said.setdefault(q.default_words(), []).append(s)
        base = p.for_source(sources[0]).help
        if len(said) == 1:
            words = next(iter(said))
            parts = [f"default {words}"] if words else []
        else:
            parts = [f"{'/'.join(ss)}: default {w}" for w, ss in said.items() if w]
    else:
        q = p.for_source(sources[0]) if sources else p
        base = q.help
        words = q.default_words()
        if words:
            parts = [f"default {words}"]
    parts = [w.replace("default required", "required") for w in parts]
    text = base + (f" ({'; '.join(parts)})" if parts else "")
    if p.unit and p.kind in ("float", "window") and p.unit not in text:
        text += f" [{p.unit}]"
    return text.replace("%", "%%")


def given(args: argparse.Namespace, command: str) -> dict[str, Any]:
    """The declared options the user gave (dest -> value in the option's unit); None ones (not
    given) are left out, so the request's defaults apply."""
    return {p.dest: getattr(args, p.dest) for p in params_for(command)
            if p.field and p.sources_of(command) and getattr(args, p.dest, None) is not None}


WHERE = {"sim": "the simulated bench (--sim)", "real": "real devices (--galvo/--tagger)",
         "replay": "a replay", "file": "a file reconstruction"}


# ---- docs -----------------------------------------------------------------------------------------
def option_table() -> str:
    """The README's table of option names by command (markdown): a mark where a command takes
    the option."""
    cols = COMMANDS
    head = "| option | " + " | ".join(cols) + " | meaning |"
    rule = "|---|" + "---|" * len(cols) + "---|"
    rows = [head, rule]
    for p in _DECLARED:
        marks = []
        for c in cols:
            if not p.in_command(c):
                marks.append("")
            elif c in p.positional:
                marks.append(p.metavar or "arg")
            else:
                marks.append("x")
        if not any(marks):
            continue
        meaning = p.summary or expand(p.help).split(";")[0].split(" (")[0]
        if p.unit and p.kind in ("float", "window", "int") and p.scale != 1.0:
            meaning += f" [{p.unit}]"
        name = p.option + "".join(f", {a}" for c in cols for a in p.per_command.get(c, {})
                                  .get("aliases", ()))
        rows.append(f"| `{name}` | " + " | ".join(marks) + f" | {meaning} |")
    return "\n".join(rows) + "\n"


__all__ = ["Param", "PARAMS", "SOURCES", "COMMANDS", "estimators", "method_names", "scene_names",
           "fault_kinds", "params_of", "params_for", "add_options", "given",
           "check_request", "option_table", "WHERE", "expand", "DEFAULT_SIZE", "DEFAULT_TARGET",
           "DEFAULT_METHOD", "MODES", "PATTERNS"]
