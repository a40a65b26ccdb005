"""Sessions of a SPAD-array sensor: frames of per-pixel histograms from a frame source (the simulated
array live, or a recording replayed), recorded as they come (HDF5), reconstructed frame by frame or
accumulated, with snapshots for a window.

The source side mirrors :mod:`acq.sources`' contract (``arm(host) -> run(host) -> close()``, the
host's ``checkpoint()`` honouring pause and abort), but what a frame source delivers is a frame of
counts (``host.frame(index, keys, counts)``: flat pixel * n_bins + bin, ascending, and their counts),
not events: an array has no galvo, passes or pixel markers, and its counts stay counts from the
sensor to the estimator (``recon.counts.CountStore``).

Recording (``frames.h5``, :class:`FrameRecorder`): each frame's occupied bins as (key, count) pairs,
appended and flushed per frame (a killed session keeps every whole frame; a dense 64x64x1024 frame
compressed cost 130 ms to write on the loaded 2-core machine, its pairs about 1), with attributes
``layout`` ("sparse-frames"), ``shape`` (H, W, T), ``time_unit_s`` (the bin width), ``periods``
(laser periods per pixel and frame), ``frame_rate_hz``, ``period_s``, ``pixel_pitch_m`` /
``focal_length_m`` and the source's JSON ``info``: ``spdepth recon frames.h5`` reads it as a cube
(frames summed, ``acq.readers.cube``) with its geometry and periods, and a replay hands the session
the same frames bit for bit.
"""

from __future__ import annotations

import dataclasses
import json
import threading
import time
from dataclasses import dataclass
from enum import Enum
from pathlib import Path

import numpy as np

from spdepth.acq.errors import OutputError, RequestError, SessionStateError
from spdepth.recon.counts import CountStore
from spdepth.recon.model import Binning, ReconSettings

MODES = ("frame", "accumulate")
"""``frame``: each frame's maps from that frame alone; ``accumulate``: from all frames so far."""


class ArrayState(str, Enum):
    IDLE = "idle"
    RUNNING = "running"
    PAUSED = "paused"
    DONE = "done"
    ABORTED = "aborted"
    FAILED = "failed"


@dataclass(frozen=True)
class ArraySnapshot:
    """What a window shows: the state, frames done, the latest maps (``recon.maps.DepthMaps``, None
    before the first frame), the latest frame's counts per pixel and the frame rates achieved."""

    state: ArrayState
    frames: int
    n_frames: int | None
    maps: object
    counts: np.ndarray | None
    acquired_fps: float
    recon_fps: float


class _Aborted(Exception):
    """Raised on the source's thread at its next checkpoint after ``abort()``; ends the run."""


# ---- sources -------------------------------------------------------------------------------------
def deliver(host, n_frames: int, frame_rate_hz: float | None, frame_pairs) -> None:
    """Hand ``host`` frames 0 .. n_frames - 1 (``frame_pairs(i)`` -> keys, counts), each at the end
    of its exposure when ``frame_rate_hz`` is given (a live sensor), else as fast as they come."""
    t0 = time.monotonic()
    for i in range(n_frames):
        host.checkpoint()
        keys, counts = frame_pairs(i)
        if frame_rate_hz:
            wait = t0 + (i + 1) / frame_rate_hz - time.monotonic()
            if wait > 0:
                time.sleep(wait)
        host.frame(i, keys, counts)


class SimArraySource:
    """The simulated array (``drivers.sim.spad_array.SimSpadArray``), paced at its frame rate when
    ``realtime`` (a live sensor), else as fast as frames are made."""

    name = "live"

    def __init__(self, sensor, n_frames: int, realtime: bool = True):
        self.sensor = sensor
        self.n_frames = int(n_frames)
        self.realtime = realtime
        s = sensor.settings
        self.shape, self.n_bins, self.bin_s = sensor.shape, s.n_bins, s.bin_s
        self.periods_per_frame = s.periods_per_frame
        self.frame_rate_hz = s.frame_rate_hz
        self.period_s = 1.0 / s.laser_rate_hz
        self.geometry = {"pixel_pitch_m": s.pixel_pitch_m, "focal_length_m": s.focal_length_m}
        self.info = sensor.info()

    def arm(self, host) -> None:
        self.sensor.frame_pairs(0)          # anything slow (first calls) before the clock runs

    def run(self, host) -> None:
        deliver(host, self.n_frames, self.frame_rate_hz if self.realtime else None, self.sensor.frame_pairs)

    def close(self) -> None:
        """Nothing to release: the simulated sensor holds no device or file."""


class H5ReplaySource:
    """A recording's frames (``frames.h5``, :class:`FrameRecorder`), in order (optionally at the
    recorded frame rate)."""

    name = "replay"

    def __init__(self, path: str | Path, realtime: bool = False):
        import h5py

        self.path = Path(path)
        try:
            self._f = h5py.File(self.path, "r")
            a = dict(self._f.attrs)
            if a.get("layout") != SPARSE_LAYOUT:
                raise KeyError("no frames of an array session")
            self._offsets = self._f["frame_offsets"][()]
        except (OSError, KeyError) as exc:
            raise RequestError(f"{self.path}: not an array recording ({exc})") from None
        self.n_frames = int(self._offsets.size - 1)
        h, w, t = (int(v) for v in a["shape"])
        self.shape, self.n_bins = (h, w), t
        self.bin_s = float(a["time_unit_s"])
        self.periods_per_frame = float(np.ravel(a["periods"])[0])
        self.frame_rate_hz = float(a["frame_rate_hz"])
        self.period_s = float(a["period_s"])
        self.geometry = {k: float(a[k]) for k in ("pixel_pitch_m", "focal_length_m", "fov_deg") if k in a}
        self.info = json.loads(a.get("info", "{}"))
        self.realtime = realtime

    def arm(self, host) -> None:
        """Nothing to prepare: the file was opened and checked when the source was made."""

    def run(self, host) -> None:
        deliver(host, self.n_frames, self.frame_rate_hz if self.realtime else None, self.frame_pairs)

    def frame_pairs(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        """Recorded frame ``i`` as (key, count) pairs."""
        lo, hi = int(self._offsets[i]), int(self._offsets[i + 1])
        return self._f["keys"][lo:hi].astype(np.int64), self._f["counts"][lo:hi].astype(np.int64)

    def close(self) -> None:
        self._f.close()


# ---- recording -----------------------------------------------------------------------------------
SPARSE_LAYOUT = "sparse-frames"
"""``frames.h5``'s layout attribute: frames as (key, count) pairs (module docstring)."""


class FrameRecorder:
    """``frames.h5``: each frame's occupied bins appended and flushed at once (module docstring):
    ``keys`` (uint64: flat pixel * n_bins + bin, ascending within a frame), ``counts`` (uint16) and
    ``frame_offsets`` (int64, F + 1: frame f is ``[frame_offsets[f], frame_offsets[f + 1])``), so
    writing a frame costs its occupied bins, not H x W x T."""

    def __init__(self, path: Path, source):
        import h5py

        self._f = h5py.File(path, "w")
        grow = dict(maxshape=(None,), chunks=(1 << 16,))
        self._keys = self._f.create_dataset("keys", shape=(0,), dtype=np.uint64, **grow)
        self._counts = self._f.create_dataset("counts", shape=(0,), dtype=np.uint16, **grow)
        self._offsets = self._f.create_dataset("frame_offsets", data=np.zeros(1, np.int64),
                                               maxshape=(None,), chunks=(1024,))
        a = self._f.attrs
        a["layout"] = SPARSE_LAYOUT
        a["shape"] = np.array([*source.shape, source.n_bins], np.int64)
        a["time_unit_s"] = source.bin_s
        a["periods"] = float(source.periods_per_frame)
        a["frame_rate_hz"] = source.frame_rate_hz
        a["period_s"] = source.period_s
        for k, v in source.geometry.items():
            a[k] = v
        a["info"] = json.dumps(source.info)
        self.frames = 0
        self._n = 0

    def append(self, keys: np.ndarray, counts: np.ndarray) -> None:
        n = self._n + keys.size
        for ds, v in ((self._keys, keys), (self._counts, counts)):
            ds.resize(n, axis=0)
            ds[self._n:n] = v
        self._offsets.resize(self.frames + 2, axis=0)
        self._offsets[self.frames + 1] = n
        self._n = n
        self.frames += 1
        self._f.flush()

    def close(self) -> None:
        self._f.close()


# ---- the session ---------------------------------------------------------------------------------
class ArraySession:
    """Frames from ``source`` reconstructed with ``recon`` (its binning in the source's bins, a
    pulse given) by ``mode`` (MODES); ``out_dir``: ``frames.h5`` (a live source's), ``maps.npz``
    (the last maps) and ``run.json``; None keeps everything in memory.

    The source's thread records each frame and adds it to the total; a reconstruction worker takes
    the newest state (the newest frame, or the total) whenever it is free, so a slow estimator
    never holds the sensor back: the maps skip frames instead. The last state is always
    reconstructed, so the final maps are those of the last frame (``frame``) or of every frame
    (``accumulate``: equal to ``spdepth recon frames.h5``). ``every_frame``: reconstruct every
    frame in turn (the acquisition then waits for it): each frame's map digest lands in
    ``frame_digests``, the same in a replay."""

    def __init__(self, source, recon: ReconSettings, *, mode: str = "accumulate",
                 out_dir: str | Path | None = None, record: bool | None = None, every_frame: bool = False):
        if mode not in MODES:
            raise RequestError(f"array mode must be one of {', '.join(MODES)}, got {mode!r}")
        if recon.pulse_rms_s is None and recon.irf is None:
            raise RequestError("an array session needs the pulse (a width or an IRF)")
        self.source = source
        self.mode = mode
        self.every_frame = every_frame
        b = recon.binning or Binning.from_window(source.bin_s, (0.0, source.n_bins * source.bin_s), source.bin_s)
        self.recon_settings = dataclasses.replace(recon, binning=b)
        self.out_dir = Path(out_dir) if out_dir is not None else None
        self.record = (source.name == "live") if record is None else record
        h, w = source.shape
        self.total = np.zeros(h * w * source.n_bins, np.int64) if mode == "accumulate" else None
        self.frames = 0                     # acquired
        self.reconstructed = 0              # frames whose state the maps show (the newest one's index + 1)
        self.recon_runs = 0
        self.maps = None
        self.last_counts = None
        self.frame_digests: list = []       # (frame, digest of its maps) for every reconstruction
        self.state = ArrayState.IDLE
        self.error: BaseException | None = None
        self._go = threading.Event()        # cleared while paused: the source's thread waits on it
        self._go.set()
        self._abort = False
        self._thread = None
        self._lock = threading.Lock()
        self._wake = threading.Condition(self._lock)
        self._pending = None                # (frame index, CountStore) not reconstructed yet
        self._acquiring = False
        self._t_run = None
        self._recon_s = 0.0
        self._recorder = None

    # commands
    def start(self) -> "ArraySession":
        if self._thread is not None:
            raise SessionStateError("the array session was started already")
        self._thread = threading.Thread(target=self._main, name="array-session", daemon=True)
        self._thread.start()
        return self

    def run(self) -> ArrayState:
        self.start()
        return self.wait()

    def wait(self, timeout_s: float | None = None) -> ArrayState:
        self._thread.join(timeout_s)
        return self.state

    def pause(self) -> None:
        self._go.clear()

    def resume(self) -> None:
        self._go.set()

    def abort(self) -> None:
        self._abort = True
        self._go.set()

    def snapshot(self) -> ArraySnapshot:
        with self._lock:
            el = (time.monotonic() - self._t_run) if self._t_run else 0.0
            return ArraySnapshot(self.state, self.frames, getattr(self.source, "n_frames", None), self.maps,
                                 self.last_counts, self.frames / el if el > 0 else 0.0,
                                 self.recon_runs / self._recon_s if self._recon_s > 0 else 0.0)

    # the host's side (the source's thread)
    def checkpoint(self) -> None:
        if self.error is not None:
            raise self.error
        if not self._go.is_set() and not self._abort:
            # held here, between frames, until resume() or abort() sets the event: no polling
            self.state = ArrayState.PAUSED
            self._go.wait()
        if self._abort:
            raise _Aborted
        self.state = ArrayState.RUNNING

    def frame(self, index: int, keys: np.ndarray, counts: np.ndarray) -> None:
        src = self.source
        h, w = src.shape
        if self._recorder is not None:
            self._recorder.append(keys, counts)
        if self.total is not None:
            self.total[keys] += counts
            keys = np.flatnonzero(self.total)
            counts = self.total[keys]
            periods = src.periods_per_frame * (index + 1)
        else:
            periods = src.periods_per_frame
        store = CountStore.from_pairs(keys, counts, (h, w), src.n_bins, src.bin_s,
                                      periods=np.full(h * w, float(periods)))
        with self._wake:
            self.frames = index + 1
            self._pending = (index, store)
            self._wake.notify_all()
            if self.every_frame:
                while self._pending is not None and self.error is None:
                    self._wake.wait(0.1)

    # the reconstruction worker
    def _reconstruct_loop(self) -> None:
        from spdepth.recon.estimate import reconstruct

        while True:
            with self._wake:
                while self._pending is None and self._acquiring:
                    self._wake.wait(0.1)
                if self._pending is None:
                    return
                index, store = self._pending
                self._pending = None
            try:
                t0 = time.perf_counter()
                maps = reconstruct(store, self.recon_settings)
                dt = time.perf_counter() - t0
            except BaseException as exc:  # noqa: BLE001 - the session fails with it
                with self._wake:
                    self.error = self.error or exc
                    self._wake.notify_all()
                return
            with self._wake:
                self.maps = maps
                self.last_counts = store.detections()
                self.reconstructed = index + 1
                self.recon_runs += 1
                self._recon_s += dt
                self.frame_digests.append((index, _digest(maps)))
                self._wake.notify_all()

    def _main(self) -> None:
        worker = threading.Thread(target=self._reconstruct_loop, name="array-recon", daemon=True)
        try:
            if self.out_dir is not None:
                try:
                    self.out_dir.mkdir(parents=True, exist_ok=True)
                except OSError as exc:
                    raise OutputError(f"output folder {self.out_dir}: {exc.strerror or exc}") from None
                if self.record:
                    self._recorder = FrameRecorder(self.out_dir / "frames.h5", self.source)
            self.source.arm(self)
            self.state = ArrayState.RUNNING
            self._t_run = time.monotonic()
            self._acquiring = True
            worker.start()
            self.source.run(self)
            final = ArrayState.DONE
        except _Aborted:
            final = ArrayState.ABORTED
        except BaseException as exc:  # noqa: BLE001 - kept in .error, shown to the caller
            self.error = self.error or exc
            final = ArrayState.FAILED
        finally:
            with self._wake:
                self._acquiring = False
                self._wake.notify_all()
            if worker.is_alive():
                worker.join()       # the newest state is reconstructed before the files
            if self.error is not None:
                final = ArrayState.FAILED
            for closing in (self.source.close, self._recorder.close if self._recorder else None):
                if closing is not None:
                    try:
                        closing()
                    except BaseException as exc:  # noqa: BLE001
                        self.error = self.error or exc
                        final = ArrayState.FAILED
        if self.out_dir is not None:
            try:
                self._write(final)
            except BaseException as exc:  # noqa: BLE001
                self.error = self.error or exc
                final = ArrayState.FAILED
        self.state = final

    def _write(self, final: ArrayState) -> None:
        from spdepth.acq.api import sensor_fov_deg
        from spdepth.acq.points import GEOMETRY_KEY, ScanGeometry

        if self.maps is not None:
            settings = dict(self.maps.settings)
            fov = sensor_fov_deg(self.source.shape, self.source.geometry)
            if fov is not None:
                settings[GEOMETRY_KEY] = ScanGeometry.from_fov(self.source.shape, fov).to_dict()
                settings["sensor"] = dict(self.source.geometry)
            self.maps = dataclasses.replace(self.maps, settings=settings)
            self.maps.save_npz(self.out_dir / "maps.npz")
        snap = self.snapshot()
        run = {"state": final.value, "source": self.source.name, "mode": self.mode, "frames": self.frames,
               "recorded": self._recorder.frames if self._recorder else 0,
               "frames_reconstructed": self.recon_runs, "maps_of_frame": self.reconstructed,
               "acquired_fps": snap.acquired_fps, "recon_fps": snap.recon_fps,
               "final_maps_digest": self.frame_digests[-1][1] if self.frame_digests else None,
               "frame_digests": self.frame_digests, "info": self.source.info,
               "error": None if self.error is None else f"{type(self.error).__name__}: {self.error}"}
        tmp = self.out_dir / "run.json.tmp"
        tmp.write_text(json.dumps(run, indent=1))
        tmp.replace(self.out_dir / "run.json")


def _digest(maps) -> str:
    """A checksum of the maps a frame gave (tof, signal, background, flags): a replay must give the
    same for every frame."""
    import hashlib

    h = hashlib.sha256()
    for a in (maps.tof_s, maps.signal, maps.background, maps.flags):
        h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()[:16]


__all__ = ["ArraySession", "ArraySnapshot", "ArrayState", "FrameRecorder", "H5ReplaySource", "MODES",
           "SimArraySource"]
