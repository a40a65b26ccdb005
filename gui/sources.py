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

from recon.errors import InputError

SOURCES = ("sim", "real", "replay")
"""Simulated bench, real devices, or a recording replayed through the same pipeline."""
MODES = ("gated", "raster")
METHODS = ("uos", "ml", "lmf")


@dataclass
class SourceSpec:
    """Everything the control panel holds (also what QSettings remembers).

    size:           (H, W) pixels, rows first.
    dwell_limit_ms: gated dwell limit / raster dwell; 0 means the default for the source.
    sync_rate_hz:   real devices: the laser repetition rate.
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
    if spec.target < 1 and spec.kind != "replay":   # a replay may keep the recorded target (0)
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


def open_run(spec: SourceSpec, out_dir: str | Path | None) -> Run:
    """Open the source and build its session (not started). Raises the ``acq``/``drivers``
    errors as they come (the window shows them); nothing stays open when it fails."""
    from acq.commands import replay as replay_cmd
    from acq.commands import scan as scan_cmd
    from acq.instruments import open_real, open_sim

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


__all__ = ["SourceSpec", "Run", "open_run", "run_dir", "validate", "SOURCES", "MODES", "METHODS"]
