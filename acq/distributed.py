"""``spdepth recon INPUT... [--dask ADDRESS|local:N]``: many files, or one big recording, on a
``dask.distributed`` cluster, with the same maps, bit for bit, as the single-process command.

Two kinds of task:

- **one per file** when several inputs are given (or one whose settings need every pixel at
  once): the worker calls the library's ``acq.api.reconstruct_file(request)``, exactly what
  ``spdepth recon FILE`` calls, which writes ``OUT/<name>.npz`` (and ``.png``) itself, so the data
  and the output folder must be at the same path on every worker (a shared file system). A worker
  runs as many files at once as it has task threads.
- **one per block of image rows** for a single PTU recording with pixel markers when the model is
  fully given (``--window-ps``, ``--bin-ps`` and ``--pulse-rms-ps`` or ``--irf``): estimating a
  pulse or a window from the data would need every pixel at once. The client walks the records once
  in chunks of ``CHUNK_RECORDS`` (a memory map; nothing is loaded whole) and keeps only the decoder
  and pixel-assigner state at each chunk boundary; each chunk task re-reads its own records from
  the file, so a task lost with a dead worker is simply recomputed; each block task takes its
  pixels from every chunk and reconstructs them. Pixels are independent given the model, so the
  assembled maps equal the single-process maps exactly.

A local cluster (``local:N``) runs N worker processes listening on 127.0.0.1 only, each with the
machine's cores divided by N as task threads and one numba thread per task. A remote
scheduler is reached with dask's own configuration, TLS included (docs/dask.md).
"""

from __future__ import annotations

import contextlib
import copy
import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from spdepth.acq.errors import RequestError
from spdepth.recon.errors import InputError

CHUNK_RECORDS = 1 << 22
"""Records per chunk task (16 MiB of records)."""
BLOCK_PIXELS = 1 << 17
"""About this many pixels per block task (whole rows)."""


def parse_address(text: str) -> tuple[str, int | str]:
    """``local:N`` -> ("local", N); anything else is a scheduler address ("remote", text)."""
    if text.startswith("local"):
        _, _, n = text.partition(":")
        try:
            workers = int(n) if n else os.cpu_count() or 1
        except ValueError:
            raise RequestError(f"--dask {text!r}: expected local:N with N a whole number of workers") from None
        if workers < 1:
            raise RequestError(f"--dask {text!r}: a local cluster needs at least one worker")
        return "local", workers
    if "://" not in text and ":" not in text:
        raise RequestError(f"--dask {text!r}: expected a scheduler address (tls://host:8786, "
                         f"tcp://host:8786) or local:N")
    return "remote", text


@contextlib.contextmanager
def connect(spec: str):
    """A ``distributed.Client`` for ``--dask SPEC``; a local cluster is closed on exit."""
    # dask logs every scheduler and worker event at INFO; the command's own lines are the report
    os.environ.setdefault("DASK_LOGGING__DISTRIBUTED", "warning")
    import logging

    try:
        from distributed import Client, LocalCluster
    except ImportError:
        raise RequestError("--dask needs the dask extra: pip install 'spdepth[dask]'") from None

    logging.getLogger("distributed").setLevel(logging.WARNING)
    kind, value = parse_address(spec)
    if kind == "remote":
        # Security() from dask's configuration (distributed.comm.tls.*): TLS when it names
        # certificates, as docs/dask.md shows
        host = value.split("://", 1)[-1].rsplit(":", 1)[0]
        if not value.startswith("tls://") and host not in ("127.0.0.1", "localhost", "[::1]"):
            print(f"spdepth recon: {value} is not a tls:// address: the photons and maps cross the "
                  f"network unencrypted (docs/dask.md shows TLS)", file=sys.stderr)
        with Client(value, timeout="30s") as client:
            yield client
        return
    threads = max(1, (os.cpu_count() or 1) // value)
    # 127.0.0.1 for the scheduler, nannies, workers and dashboard alike: no port open to the network;
    # each task thread runs a file (or block) with one numba thread, so the cores are used by tasks
    with LocalCluster(n_workers=value, threads_per_worker=threads, processes=True, host="127.0.0.1",
                      dashboard_address="127.0.0.1:0",
                      env={"NUMBA_NUM_THREADS": "1", "DASK_LOGGING__DISTRIBUTED": "warning"}
                      ) as cluster, \
            Client(cluster) as client:
        yield client


# ---------------------------------------------------------------------------------------------
# one task per file


def recon_file(request) -> dict:
    """One file on a worker (or in this process): the library call ``spdepth recon FILE`` makes;
    returns its JSON summary (the notes travel in it; progress bars stay on the worker)."""
    from spdepth.acq.api import reconstruct_file

    return reconstruct_file(request).summary


def _per_file(requests: list, client) -> list[dict]:
    if client is None:
        return [recon_file(r) for r in requests]
    return client.gather(client.map(recon_file, requests, pure=False))


# ---------------------------------------------------------------------------------------------
# one big recording in blocks of rows


@dataclass(frozen=True)
class Plan:
    """How a recording splits: ``starts[i]`` is the first record of chunk i and ``states[i]`` the
    (decoder, assigner) state before it; blocks are row ranges ``rows[b]:rows[b + 1]``."""

    path: str
    shape: tuple[int, int]
    rectype: int
    chunk_records: int
    starts: tuple[int, ...]
    states: tuple
    rows: tuple[int, ...]


def _image_and_unit(path: str, time_unit_s: float | None):
    """(layout, shape, pattern, rectype, time unit) of a PTU with pixel markers, or None."""
    from spdepth.acq.ptu import PIXEL_MARKER_TAG, PLAN_TAG, read_layout
    from spdepth.acq.readers import sniff_kind

    if sniff_kind(path) != "ptu":
        return None
    layout = read_layout(path)
    tags = layout.tags
    if not int(tags.get(PIXEL_MARKER_TAG, 0) or 0) or tags.get(PLAN_TAG):
        # a session's recording keeps complete dwells only (acq.recording): one task reads it so
        return None
    h, w = int(tags.get("ImgHdr_PixY", 0) or 0), int(tags.get("ImgHdr_PixX", 0) or 0)
    if h < 1 or w < 1:
        return None
    pattern = "serp" if tags.get("ImgHdr_BiDirect") else "raster"
    unit = time_unit_s or float(tags["MeasDesc_Resolution"])
    return layout, (h, w), pattern, int(tags["TTResultFormat_TTTRRecType"]), unit


def _assigned(layout, chunk: np.ndarray, dec, assigner, lut, keep_channel):
    """Decode one chunk of records and assign its photons: (flat pixel, dtime) of the photons that
    land in a pixel (of ``keep_channel`` only, when given)."""
    from spdepth.drivers.errors import DriverError
    from spdepth.drivers.events import EventKind, Marker
    from spdepth.drivers.tagger.t3 import decode_t3

    try:
        ev = decode_t3(chunk, dec)
    except DriverError as exc:
        raise InputError(f"{layout.path}: {exc}") from None
    is_marker = ev["kind"] == EventKind.MARKER
    ev["marker"][is_marker] = lut[ev["marker"][is_marker]]
    pixel = assigner.assign(ev)
    sel = (ev["kind"] == EventKind.PHOTON) & (pixel >= 0)
    if keep_channel is not None:
        sel &= ev["channel"] == keep_channel
    n_pixel_markers = int(np.count_nonzero(ev["marker"][is_marker] & Marker.PIXEL))
    return pixel[sel], ev["dtime"][sel].astype(np.float64), n_pixel_markers


def plan_blocks(path: str, time_unit_s: float | None = None, *, chunk_records: int = CHUNK_RECORDS,
                block_pixels: int = BLOCK_PIXELS) -> Plan | None:
    """Walk the recording once, in chunks, keeping the state at each chunk start. None when it is
    not a PTU with pixel markers (then it goes whole to one task)."""
    from spdepth.acq.assign import PixelAssigner
    from spdepth.acq.ptu import iter_records, marker_map
    from spdepth.drivers.tagger.t3 import T3DecoderState

    found = _image_and_unit(path, time_unit_s)
    if found is None:
        return None
    layout, (h, w), pattern, rectype, _ = found
    lut = marker_map(layout.tags)
    dec, assigner = T3DecoderState(), PixelAssigner((h, w), pattern)
    starts, states, markers = [], [], 0
    for i, chunk in enumerate(iter_records(layout, chunk_records)):
        starts.append(i * chunk_records)
        states.append((copy.deepcopy(dec), copy.deepcopy(assigner)))
        markers += _assigned(layout, chunk, dec, assigner, lut, None)[2]
    if markers == 0:
        return None
    per = max(1, block_pixels // w)
    rows = tuple(range(0, h, per)) + (h,)
    return Plan(str(path), (h, w), rectype, chunk_records, tuple(starts), tuple(states), rows)


def chunk_task(plan: Plan, i: int, keep_channel: int | None) -> list[tuple[np.ndarray, np.ndarray]]:
    """Chunk i's photons split by block: ``[(flat pixel, dtime) of block b, ...]``. Reads its own
    records from the file, so dask can recompute it anywhere."""
    from spdepth.acq.ptu import iter_records, marker_map, read_layout

    layout = read_layout(plan.path)
    dec, assigner = copy.deepcopy(plan.states[i])
    chunk = next(iter_records(layout, plan.chunk_records, start=plan.starts[i]))
    pixel, dtime, _ = _assigned(layout, chunk, dec, assigner, marker_map(layout.tags), keep_channel)
    edges = np.asarray(plan.rows, np.int64) * plan.shape[1]
    block = np.searchsorted(edges, pixel, side="right") - 1
    # stable: detection order within a pixel survives, as in the single-process reader
    order = np.argsort(block, kind="stable")
    pixel, dtime, block = pixel[order], dtime[order], block[order]
    bounds = np.searchsorted(block, np.arange(len(plan.rows)))
    # copies: each block's share is its own object, moved alone to the worker that needs it
    return [(pixel[bounds[b]:bounds[b + 1]].copy(), dtime[bounds[b]:bounds[b + 1]].copy())
            for b in range(len(plan.rows) - 1)]


def _share(chunk: list, b: int):
    """Block b's share of one chunk task's output (a task of its own, so only it moves)."""
    return chunk[b]


def block_task(plan: Plan, b: int, settings, time_unit_s: float, *shares):
    """Reconstruct block b (rows ``plan.rows[b]:plan.rows[b + 1]``) from its share of every chunk,
    in chunk order."""
    from spdepth.recon.estimate import reconstruct
    from spdepth.recon.photons import PhotonStore

    r0, r1 = plan.rows[b], plan.rows[b + 1]
    w = plan.shape[1]
    pixel = np.concatenate([s[0] for s in shares]) - r0 * w
    dtime = np.concatenate([s[1] for s in shares])
    store = PhotonStore.from_pixel_indices(pixel, dtime, (r1 - r0, w), time_unit_s)
    return reconstruct(store, settings)


def assemble(parts: list) -> object:
    """One DepthMaps from blocks of rows (in order)."""
    from spdepth.recon.maps import NPZ_KEYS, DepthMaps

    arrays = {k: np.concatenate([getattr(p, k) for p in parts], axis=getattr(parts[0], k).ndim - 2)
              for k in NPZ_KEYS if k != "settings"}
    return DepthMaps(settings=parts[0].settings, **arrays)


def reconstruct_blocks(client, plan: Plan, settings, time_unit_s: float, keep_channel: int | None,
                       on_submitted=None):
    """Maps of the whole recording, computed as chunk and block tasks on ``client``.
    ``on_submitted(futures)`` is called once everything is submitted (tests kill a worker there)."""
    n_blocks = len(plan.rows) - 1
    chunks = [client.submit(chunk_task, plan, i, keep_channel, pure=False)
              for i in range(len(plan.starts))]
    shares = [[client.submit(_share, c, b, pure=False) for c in chunks] for b in range(n_blocks)]
    blocks = [client.submit(block_task, plan, b, settings, time_unit_s, *shares[b], pure=False)
              for b in range(n_blocks)]
    if on_submitted is not None:
        on_submitted(chunks + blocks)
    del chunks, shares      # the scheduler keeps what the blocks still need, and how to remake it
    return assemble(client.gather(blocks))


def block_settings(request, unit_s: float):
    """ReconSettings of a fully given model (window, bins and pulse), exactly as
    ``acq.api.reconstruct_file`` resolves them, or None when any is left to the data."""
    from spdepth.recon.model import Binning, ReconSettings, load_irf

    if request.window_s is None or request.bin_s is None or \
            (request.pulse_rms_s is None and request.irf is None):
        return None
    return ReconSettings(method=request.method,
                         binning=Binning.from_window(unit_s, request.window_s, request.bin_s),
                         pulse_rms_s=request.pulse_rms_s,
                         irf=load_irf(request.irf) if request.irf else None,
                         max_photons=request.max_photons, reflectors=request.reflectors,
                         max_reflectors=request.max_reflectors, false_alarm=request.false_alarm)


def _by_blocks(request, client) -> dict | None:
    """The single-recording block path; None when the input cannot be split (see module doc)."""
    path = request.input
    from spdepth.recon import estimators

    if not estimators.get(request.method).pixelwise:
        # its pixels are not independent: blocks would cut every neighbourhood at their seams
        print(f"spdepth recon: {path}: the {request.method} method needs each pixel's neighbours: "
              f"reconstructing it as one task", file=sys.stderr)
        return None
    found = _image_and_unit(path, request.time_unit_s)
    if found is None:
        return None
    unit_s = found[4]
    settings = block_settings(request, unit_s)
    if settings is None:
        print(f"spdepth recon: {path}: the window, bins or pulse are left to the data, which needs "
              f"every pixel at once: reconstructing it as one task (give --window-ps, --bin-ps and "
              f"--pulse-rms-ps to split it into blocks)", file=sys.stderr)
        return None
    t0 = time.perf_counter()
    plan = plan_blocks(path, unit_s)
    if plan is None:
        return None
    maps = reconstruct_blocks(client, plan, settings, unit_s, request.channel)
    seconds = time.perf_counter() - t0
    if request.out:
        maps.save_npz(request.out)
    if request.png:
        from spdepth.acq.report import render_maps_png

        render_maps_png(request.png, maps, title=f"{Path(path).name}: {request.method} "
                        f"({len(plan.rows) - 1} blocks on dask)")
    depth = np.asarray(maps.depth_m, dtype=float)
    return {"input": str(path), "shape": list(plan.shape), "pixels": int(np.prod(plan.shape)),
            "pixels_with_estimate": int(np.isfinite(depth).sum() if depth.ndim == 2 else
                                        np.isfinite(depth).any(axis=0).sum()),
            "photons": int(maps.photons.sum()), "method": request.method,
            "recon_s": round(seconds, 4), "chunks": len(plan.starts), "blocks": len(plan.rows) - 1,
            "out": request.out, "png": request.png, "notes": []}


def reconstruct_files(requests: list, dask: str | None = None) -> list[dict]:
    """Summaries of ``requests`` (``FileReconRequest``), in order: on a dask cluster (``dask`` an
    address or ``local:N``; one recording with a fully given model is split into blocks of rows),
    or one after the other in this process when ``dask`` is None."""
    with (connect(dask) if dask else contextlib.nullcontext()) as client:
        if client is not None and len(requests) == 1:
            summary = _by_blocks(requests[0], client)
            if summary is not None:
                return [summary]
        return _per_file(requests, client)
