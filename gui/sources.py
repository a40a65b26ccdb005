"""What the window runs: a source described by the controls (no Qt here) turned into an
``acq`` session, plus the instruments it must close afterwards and, for simulated scenes, the truth.

The window never touches a device: it asks ``acq`` to open the instruments and to build the
session, and hands both back to ``Run.close`` once the session has ended.
"""

from __future__ import annotations

import time
from argparse import Namespace
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from spdepth.acq.commands._session import METHODS  # one estimator list for the CLI and the window
from spdepth.recon.errors import InputError

SOURCES = ("sim", "real", "replay", "file")
"""Simulated bench, real devices, a recording replayed through the same pipeline, or a PTU/.mat
file reconstructed as a whole (``spdepth recon``'s path, on a worker thread)."""
MODES = ("gated", "raster")


@dataclass
class SourceSpec:
    """Everything the control panel holds (also what QSettings remembers).

    size:           (H, W) pixels, rows first.
    dwell_limit_ms: gated dwell limit / raster dwell; 0 means the default for the source.
    sync_rate_hz:   real devices: the laser repetition rate.
    file:           a PTU/HT3/PT3 or .mat file to reconstruct (kind "file"); target is then the
                    detections kept per pixel (0: all).
    time_unit_ps:   file: size of one raw time unit (required for .mat, 0: the PTU header's).
    pulse_rms_ps:   file: Gaussian pulse RMS (0: estimated from the data).
    out_root:       a folder under which each run gets its own directory (recording, maps, run.json).
    """

    kind: str = "sim"
    scene: str = "bust"
    size: tuple[int, int] = (32, 32)
    target: int = 15
    mode: str = "gated"
    method: str = "uos"
    dwell_limit_ms: float = 0.0
    sbr: float = 10.0
    seed: int = 0
    faults: str = ""
    galvo_port: str = ""
    tagger_url: str = ""
    sync_rate_hz: float = 0.0
    recording: str = ""
    file: str = ""
    time_unit_ps: float = 0.0
    pulse_rms_ps: float = 0.0
    out_root: str = ""

    def to_dict(self) -> dict:
        d = asdict(self)
        d["size"] = list(self.size)
        return d

    @classmethod
    def from_dict(cls, d: dict) -> "SourceSpec":
        known = {k: v for k, v in d.items() if k in cls.__dataclass_fields__}
        if "size" in known:
            known["size"] = tuple(int(v) for v in known["size"])
        return cls(**known)

    def label(self) -> str:
        h, w = self.size
        if self.kind == "sim":
            return f"simulated {self.scene} {w}x{h}, {self.target} per pixel, {self.method}"
        if self.kind == "real":
            return f"devices {w}x{h}, {self.target} per pixel, {self.method}"
        if self.kind == "file":
            return f"{Path(self.file).name}, {self.method}"
        return f"replay of {Path(self.recording).name}, {self.method}"


@dataclass
class Run:
    """A session being shown, with what it needs closed afterwards.

    truth_depth_m: (H, W) true depth of a simulated one-surface scene, else None.
    """

    session: object
    spec: SourceSpec
    out_dir: Path | None
    instruments: object = None
    truth_depth_m: np.ndarray | None = None
    label: str = ""
    started_at: float = field(default_factory=time.time)

    def close(self) -> None:
        """Release the instruments; call once the session has ended."""
        if self.instruments is not None:
            self.instruments.close()
            self.instruments = None


def run_dir(out_root: str | Path, kind: str) -> Path:
    """A fresh directory ``out_root/YYYYmmdd-HHMMSS-kind`` (suffixed when taken)."""
    root = Path(out_root).expanduser()
    stem = time.strftime("%Y%m%d-%H%M%S") + f"-{kind}"
    path = root / stem
    n = 1
    while path.exists():
        n += 1
        path = root / f"{stem}-{n}"
    path.mkdir(parents=True)
    return path


def _scan_args(spec: SourceSpec) -> Namespace:
    """The ``spdepth scan`` arguments this spec stands for (``acq.commands.scan.build_session``)."""
    gated = spec.mode == "gated"
    limit = spec.dwell_limit_ms or None
    return Namespace(size=tuple(spec.size), target=int(spec.target), mode=spec.mode,
                     pattern="raster", settle_us=0.0, max_passes=None, time_limit_s=None,
                     dwell_limit_ms=limit if gated else None, dwell_ms=None if gated else limit,
                     window_ps=None, bin_ps=40.0, pulse_rms_ps=None, method=spec.method,
                     fov_deg=20.0)


def validate(spec: SourceSpec) -> None:
    """InputError naming the field for a setting the session would refuse later, or worse."""
    if spec.kind not in SOURCES:
        raise InputError(f"source must be one of {', '.join(SOURCES)}, got {spec.kind!r}")
    h, w = spec.size
    if h < 1 or w < 1:
        raise InputError(f"size must be at least 1x1, got {w}x{h}")
    if spec.target < 1 and spec.kind not in ("replay", "file"):   # 0: as recorded / all
        raise InputError(f"target detections must be at least 1, got {spec.target}")
    if spec.mode not in MODES:
        raise InputError(f"mode must be gated or raster, got {spec.mode!r}")
    if spec.method not in METHODS:
        raise InputError(f"estimator must be one of {', '.join(METHODS)}, got {spec.method!r}")
    if spec.kind == "real":
        if not spec.galvo_port or not spec.tagger_url:
            raise InputError("real devices need a galvo port and a tagger USB id (usb:VID:PID)")
        if not spec.sync_rate_hz > 0:
            raise InputError("real devices need the laser repetition rate (sync rate)")
    if spec.kind == "replay":
        if not spec.recording:
            raise InputError("choose a recording to replay")
        if not Path(spec.recording).exists():
            raise InputError(f"recording {spec.recording} does not exist")
    if spec.kind == "file":
        if not spec.file:
            raise InputError("choose a PTU or .mat file to reconstruct")
        if not Path(spec.file).is_file():
            raise InputError(f"file {spec.file} does not exist")
        if Path(spec.file).suffix.lower() == ".mat" and not spec.time_unit_ps > 0:
            raise InputError(f"{Path(spec.file).name}: a .mat file does not record its time unit; "
                             "set the time unit (8 ps for first-photon-imaging files, 1 ps for "
                             "times in ps)")


def open_run(spec: SourceSpec, out_dir: str | Path | None) -> Run:
    """Open the source and build its session (not started). Raises the ``acq``/``drivers``
    errors as they come (the window shows them); nothing stays open when it fails."""
    from spdepth.acq.commands import replay as replay_cmd
    from spdepth.acq.commands import scan as scan_cmd
    from spdepth.acq.instruments import open_real, open_sim

    validate(spec)
    out = Path(out_dir) if out_dir is not None else None
    if spec.kind == "replay":
        rec = Path(spec.recording)
        rec_dir = rec if rec.is_dir() else rec.parent
        if out is not None and out.resolve() == rec_dir.resolve():
            raise InputError(f"output folder {out} is the recording's own directory")
        session = replay_cmd.build_session(str(rec), target=spec.target or None,
                                           method=spec.method, out=out)
        return Run(session, spec, out, label=spec.label())
    if spec.kind == "sim":
        inst = open_sim(spec.scene, tuple(spec.size), ppp=float(spec.target), sbr=spec.sbr,
                        seed=spec.seed, faults=spec.faults)
    else:
        inst = open_real(spec.galvo_port, spec.tagger_url, 1.0 / spec.sync_rate_hz)
    try:
        session = scan_cmd.build_session(_scan_args(spec), inst, out)
    except BaseException:
        inst.close()
        raise
    truth = None
    if inst.scene is not None:
        depth = np.asarray(inst.scene.truth()["depth_m"], dtype=np.float64)
        truth = depth if depth.ndim == 2 else None
    return Run(session, spec, out, instruments=inst, truth_depth_m=truth, label=spec.label())


@dataclass(frozen=True)
class PixelInfo:
    """One pixel as the inspector shows it: its kept detection times (tagger units of
    ``binning.time_unit_s``), the estimate, the model used, and words for its counts and state."""

    times: np.ndarray
    binning: object
    pulse_rms_s: float | None
    irf: object
    tof_s: float
    depth_m: float
    background: float
    signal: float
    uncertainty_s: float
    estimated: bool
    flag: int
    kept: str
    acquisition: str


class SessionView:
    """What the inspector and the saving need from a live or replayed session."""

    def __init__(self, session):
        self.session = session

    @property
    def shape(self) -> tuple[int, int]:
        return self.session.plan.shape

    @property
    def target(self) -> int:
        return self.session.plan.target

    def maps(self):
        return self.session.maps()

    def key(self, r: int, c: int):
        """Changes whenever what ``pixel(r, c)`` shows may have changed."""
        s = self.session
        flat = r * self.shape[1] + c
        return (int(s.store.count[flat]), int(s.acq_flags[flat]), bool(s.recon.done[r, c]),
                s.recon.settings.pulse_rms_s)

    def pixel(self, r: int, c: int) -> PixelInfo:
        from spdepth.acq.session import AcqFlag

        s = self.session
        rc = s.recon
        flat = r * self.shape[1] + c
        acq = int(s.acq_flags[flat])
        return PixelInfo(
            times=s.store.photons([flat]).times, binning=rc.settings.binning,
            pulse_rms_s=rc.settings.pulse_rms_s, irf=rc.settings.irf,
            tof_s=float(rc.tof_s[r, c]), depth_m=float(rc.depth_m[r, c]),
            background=float(rc.background[r, c]), signal=float(rc.signal[r, c]),
            uncertainty_s=float(rc.uncertainty_s[r, c]), estimated=bool(rc.done[r, c]),
            flag=int(rc.flags[r, c]), kept=f"{int(s.store.count[flat])} of {s.plan.target}",
            acquisition="acquiring" if acq == 255 else AcqFlag(acq).name.lower().replace("_", " "))


@dataclass
class FileResult:
    """A file reconstructed as a whole: the maps, the kept photons and the model used."""

    path: Path
    maps: object
    store: object
    binning: object
    pulse_rms_s: float | None
    irf: object
    target: int
    notes: tuple = ()
    read_s: float = 0.0
    recon_s: float = 0.0

    @property
    def shape(self) -> tuple[int, int]:
        return tuple(self.maps.flags.shape)

    def snapshot(self):
        """The maps as an ``acq.session.Snapshot`` (state done), for the map panels."""
        from spdepth.acq.session import Snapshot

        m = self.maps
        h, w = self.shape
        return Snapshot(state="done", elapsed_s=self.read_s + self.recon_s, pixels_total=h * w,
                        pixels_final=h * w, detections=int(m.photons.sum()), detections_per_s=0.0,
                        lost_spans=0, lost_records=0, eta_s=None, recon_lag=0, passes=0,
                        depth_m=m.depth_m, background=m.background, signal=m.signal,
                        uncertainty_s=m.uncertainty_s, counts=m.photons,
                        acq_flags=np.zeros((h, w), np.uint8))


class ResultView:
    """``SessionView``'s interface over a :class:`FileResult`."""

    def __init__(self, result: FileResult):
        self.result = result

    @property
    def shape(self) -> tuple[int, int]:
        return self.result.shape

    @property
    def target(self) -> int:
        return self.result.target

    def maps(self):
        return self.result.maps

    def key(self, r: int, c: int):
        return ()

    def pixel(self, r: int, c: int) -> PixelInfo:
        res, m = self.result, self.result.maps
        b = res.binning
        t = res.store.pixel(r, c)
        t = t[(t >= b.window_start) & (t < b.window_stop)]
        if res.target:
            t = t[:res.target]
        n = int(m.photons[r, c])
        return PixelInfo(
            times=t, binning=b, pulse_rms_s=res.pulse_rms_s, irf=res.irf,
            tof_s=float(m.tof_s[r, c]), depth_m=float(m.depth_m[r, c]),
            background=float(m.background[r, c]), signal=float(m.signal[r, c]),
            uncertainty_s=float(m.uncertainty_s[r, c]), estimated=n > 0, flag=int(m.flags[r, c]),
            kept=f"{n} in the window" + (f" (first {res.target})" if res.target else ""),
            acquisition=f"from {res.path.name}")


def reconstruct_file(spec: SourceSpec, progress=None) -> FileResult:
    """Read ``spec.file`` and reconstruct it as ``spdepth recon`` does with no window or bin
    option (both derived from the data; the pulse estimated unless ``spec.pulse_rms_ps``).
    Raises ``InputError`` (naming the file) for what cannot be read."""
    from spdepth.acq.readers import read_photons
    from spdepth.recon.estimate import reconstruct
    from spdepth.recon.model import Binning, Irf, ReconSettings

    validate(spec)
    path = Path(spec.file)
    t0 = time.perf_counter()
    result = read_photons(path, time_unit_s=spec.time_unit_ps * 1e-12 if spec.time_unit_ps else None)
    store = result.store
    if store.n_photons == 0:
        raise InputError(f"{path.name}: holds no photons")
    settings = ReconSettings(method=spec.method, binning=None,
                             pulse_rms_s=spec.pulse_rms_ps * 1e-12 if spec.pulse_rms_ps else None,
                             max_photons=spec.target or None)
    t1 = time.perf_counter()
    maps = reconstruct(store, settings, progress=progress)
    t2 = time.perf_counter()
    used = maps.settings
    b = used["binning"]
    binning = Binning(b["time_unit_s"], b["window_start"], b["window_stop"], b["bin_width"])
    irf = None
    if used.get("irf"):
        irf = Irf(used["irf"]["times_s"], used["irf"]["counts"], used["irf"].get("source", ""))
    return FileResult(path, maps, store, binning, used.get("pulse_rms_s"), irf, int(spec.target),
                      tuple(result.notes), t1 - t0, t2 - t1)


class FileJob:
    """``reconstruct_file`` on a worker thread; the window polls ``done``/``result``/``error`` and
    ``progress`` (pixels done, total) from its timer, so it never blocks."""

    def __init__(self, spec: SourceSpec):
        import threading

        self.spec = spec
        self.result: FileResult | None = None
        self.error: BaseException | None = None
        self.progress = (0, 0)
        self.started_at = time.monotonic()
        self._done = threading.Event()
        self._thread = threading.Thread(target=self._run, name="gui-file-recon", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        try:
            self.result = reconstruct_file(self.spec, progress=self._progress)
        except BaseException as exc:  # noqa: BLE001 - handed to the window, shown in its banner
            self.error = exc
        finally:
            self._done.set()

    def _progress(self, done: int, total: int) -> None:
        self.progress = (int(done), int(total))

    @property
    def done(self) -> bool:
        return self._done.is_set()

    def wait(self, timeout_s: float | None = None) -> bool:
        return self._done.wait(timeout_s)


__all__ = ["SourceSpec", "Run", "open_run", "run_dir", "validate", "SOURCES", "MODES", "METHODS",
           "PixelInfo", "SessionView", "ResultView", "FileResult", "FileJob", "reconstruct_file"]
