"""One scan through the instruments: configure the galvo and the tagger, stream tags while the
galvo steps, assign photons to pixels by the markers, cross-check with the galvo's pixel log.

The same code drives real devices and the simulated ones (``galvosim://`` or a pty for the galvo,
the simulated pyusb backend for the tagger): it only sees ``drivers.galvo.Galvo`` and
``drivers.tagger.Tagger``.
"""

from __future__ import annotations

import logging
import time
from dataclasses import asdict, dataclass, field
from typing import Callable

import numpy as np

from acq.assign import LostSpan, PixelAssigner
from drivers.errors import DeviceError, DeviceTimeoutError
from recon.errors import InputError
from recon.photons import PhotonStore

log = logging.getLogger(__name__)

PIXEL_LOG_POLL_S = 0.1
"""How often the galvo's pixel log is read during a scan (it holds 4096 pixels; far inside that)."""


@dataclass(frozen=True)
class ScanPlan:
    """What to scan and how long to hold each pixel; saved with every result.

    nx, ny:        pixels per line and lines.
    x/y_*_deg:     mirror angles (optical degrees) of the first and last pixel centres.
    pattern:       "raster" (every line left to right) or "serp" (odd lines right to left).
    n_target:      count-gated: hold each pixel until this many detector pulses; None: fixed dwell.
    dwell_s:       count-gated: the dwell limit per pixel; fixed dwell: the dwell per pixel.
    settle_s:      wait after each step before the pixel opens.
    """

    nx: int
    ny: int
    x_first_deg: float
    x_last_deg: float
    y_first_deg: float
    y_last_deg: float
    pattern: str = "raster"
    n_target: int | None = 15
    dwell_s: float = 10e-3
    settle_s: float = 0.0

    def __post_init__(self) -> None:
        if self.nx < 1 or self.ny < 1:
            raise InputError(f"scan size must be at least 1 x 1, got {self.nx} x {self.ny}")
        if self.pattern not in ("raster", "serp"):
            raise InputError(f"pattern must be 'raster' or 'serp', got {self.pattern!r}")
        if self.n_target is not None and self.n_target < 1:
            raise InputError(f"n_target must be at least 1, got {self.n_target}")
        if not self.dwell_s > 0:
            raise InputError(f"dwell_s must be positive, got {self.dwell_s}")
        if self.settle_s < 0:
            raise InputError(f"settle_s must not be negative, got {self.settle_s}")

    @property
    def shape(self) -> tuple[int, int]:
        return self.ny, self.nx

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass
class ScanResult:
    """What a scan produced.

    store:         the assigned photons, pixel by pixel (dtime in tagger resolution units).
    pixel_log:     the galvo's record of every completed pixel (count, dwell, gated/limit flag).
    lost:          holes the tagger reported in its stream; pixels from each hole's pixel on are
                   unknown until the next frame.
    short_pixels:  flat indices of pixels with fewer assigned photons than the galvo counted:
                   to be re-acquired or flagged, never taken as complete.
    """

    plan: ScanPlan
    store: PhotonStore
    pixel_log: list = field(default_factory=list)
    lost: list[LostSpan] = field(default_factory=list)
    short_pixels: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    events: int = 0
    unassigned_photons: int = 0
    wall_s: float = 0.0


def galvo_pattern(plan: ScanPlan):
    """The galvo driver's pattern and gate for ``plan``."""
    from drivers.galvo import Gate, ScanMode, ScanPattern

    mode = ScanMode.RASTER if plan.pattern == "raster" else ScanMode.SERPENTINE
    pattern = ScanPattern(plan.nx, plan.ny, plan.x_first_deg, plan.x_last_deg,
                          plan.y_first_deg, plan.y_last_deg, mode=mode)
    gate = Gate.fixed(plan.dwell_s) if plan.n_target is None else Gate.count(plan.n_target, plan.dwell_s)
    return pattern, gate


def run_scan(galvo, tagger, plan: ScanPlan, *,
             on_chunk: Callable[[np.ndarray, np.ndarray], None] | None = None,
             timeout_s: float = 600.0) -> ScanResult:
    """Run one frame of ``plan`` and return the assigned photons.

    on_chunk(flat_pixel, dtime) is called from this thread with each chunk of assigned photons,
    so a live view can update while the scan runs. The scan ends when the stream shows the last
    line closed (LINE_STOP) and the galvo reports it finished; DeviceTimeoutError after
    ``timeout_s`` of real time, with the tagger stopped.
    """
    from drivers.galvo import GalvoState

    t0 = time.monotonic()
    assigner = PixelAssigner(plan.shape, plan.pattern)
    pattern, gate = galvo_pattern(plan)
    galvo.configure_scan(pattern, gate, settle_s=plan.settle_s, frames=1)
    pixels: list[np.ndarray] = []
    dtimes: list[np.ndarray] = []
    log_records: list = []
    n_events = 0
    unassigned = 0
    reader = tagger.reader().start()
    try:
        galvo.start()
        next_poll = 0.0
        galvo_done = False
        while True:
            chunk = reader.get(timeout_s=0.05)
            if chunk is None:
                raise DeviceError("the time tagger's stream ended before the scan finished")
            if chunk.size:
                n_events += chunk.size
                pix = assigner.assign(chunk)
                ok = pix >= 0
                unassigned += int(np.count_nonzero(chunk["kind"][~ok] == 0))
                if ok.any():
                    pixels.append(pix[ok])
                    dtimes.append(chunk["dtime"][ok])
                    if on_chunk is not None:
                        on_chunk(pixels[-1], dtimes[-1])
            now = time.monotonic()
            if now >= next_poll or galvo_done:
                next_poll = now + PIXEL_LOG_POLL_S
                _read_pixel_log(galvo, log_records)
                if not galvo_done:
                    st = galvo.status()
                    if st.state == GalvoState.FAULT:
                        raise DeviceError(f"galvo fault during the scan at row {st.row}, col {st.col}")
                    galvo_done = st.state != GalvoState.SCANNING
            if galvo_done and (assigner.lines_closed >= plan.ny or assigner.lost):
                # Everything the galvo did is in the stream once its last LINE_STOP arrived.
                # After a loss the last LINE_STOP may be gone with it; drain what is there.
                if assigner.lost:
                    _drain(reader, assigner, pixels, dtimes, on_chunk)
                break
            if now - t0 > timeout_s:
                raise DeviceTimeoutError(f"scan not finished after {timeout_s:.0f} s")
    finally:
        reader.stop()
        try:
            galvo.stop()
        except DeviceError as exc:
            log.warning("could not stop the galvo after the scan: %s", exc)
    _read_pixel_log(galvo, log_records)

    pix = np.concatenate(pixels) if pixels else np.zeros(0, np.int64)
    dt = np.concatenate(dtimes).astype(np.float64) if dtimes else np.zeros(0)
    store = PhotonStore.from_pixel_indices(pix, dt, plan.shape, tagger.resolution_s)
    return ScanResult(plan, store, log_records, list(assigner.lost),
                      _short_pixels(store, log_records, plan), n_events, unassigned,
                      time.monotonic() - t0)


def _read_pixel_log(galvo, out: list) -> None:
    """Append every pixel-log record the galvo has that we have not read (pages of <= 256)."""
    while True:
        page = galvo.poll_pixels()
        if page.lost:
            log.warning("galvo pixel log overran: %d pixel records lost", page.lost)
        out.extend(page.records)
        if not page.records:
            return


def _drain(reader, assigner, pixels, dtimes, on_chunk) -> None:
    """Take what the reader still has (it is not producing more: the galvo has stopped)."""
    while True:
        chunk = reader.get(timeout_s=0.2)
        if chunk is None or chunk.size == 0:
            return
        pix = assigner.assign(chunk)
        ok = pix >= 0
        if ok.any():
            pixels.append(pix[ok])
            dtimes.append(chunk["dtime"][ok])
            if on_chunk is not None:
                on_chunk(pixels[-1], dtimes[-1])


def _short_pixels(store: PhotonStore, records, plan: ScanPlan) -> np.ndarray:
    """Pixels whose assigned photons fall short of what the galvo's counter saw, and pixels the
    galvo never reported (log overrun, aborted scan)."""
    counted = np.full(plan.ny * plan.nx, -1, dtype=np.int64)
    for r in records:
        if r.frame == 0:
            counted[r.row * plan.nx + r.col] = r.count
    got = store.counts().ravel()
    return np.flatnonzero((counted < 0) | (got < counted))
