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
from dataclasses import dataclass, field

import numpy as np

from spdepth.acq.errors import RequestError, UnreachableError
from spdepth.recon.errors import InputError

CHUNK_RECORDS = 1 << 22
"""Records per chunk task (16 MiB of records)."""
BLOCK_PIXELS = 1 << 17
"""About this many pixels per block task (whole rows)."""
CONNECT_TIMEOUT_S = 5.0
"""How long a scheduler address may take to answer before the command gives up in one line."""


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
        try:
            client = Client(value, timeout=f"{CONNECT_TIMEOUT_S:g}s")
        except OSError:      # distributed's "Timed out trying to connect", refused, unknown host
            raise UnreachableError(f"--dask {value}: no dask scheduler answers there within "
                                   f"{CONNECT_TIMEOUT_S:g} s (connect timeout); start one "
                                   f"(`dask scheduler`) or use local:N") from None
        except Exception as exc:  # noqa: BLE001 - something answers, but not as a scheduler
            raise UnreachableError(f"--dask {value}: what answers there is not a dask scheduler "
                                   f"({type(exc).__name__} in the handshake)") from None
        with client:
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


def recon_file(request, keep_going: bool = False) -> dict:
    """One file on a worker (or in this process): the library call ``spdepth recon FILE`` makes;
    returns its JSON summary (the notes travel in it; progress bars stay on the worker). With
    ``keep_going`` a file that cannot be read or reconstructed (an error spdepth raises on
    purpose: ``AcqError``, ``InputError``, ``DriverError``) gives ``{"input", "error"}`` instead,
    so a batch goes on past it; anything else (a bug) still raises."""
    from spdepth.acq.api import reconstruct_file
    from spdepth.acq.errors import AcqError
    from spdepth.drivers.errors import DriverError

    try:
        # the summary alone comes back: without an output file, no spreads (as spdepth recon FILE)
        return reconstruct_file(request, spreads=request.writes_files()).summary
    except (AcqError, InputError, DriverError) as exc:
        if not keep_going:
            raise
        return {"input": str(request.input), "error": str(exc)}


def _per_file(requests: list, client, keep_going: bool = False) -> list[dict]:
    if client is None:
        return [recon_file(r, keep_going) for r in requests]
    return client.gather(client.map(recon_file, requests, [keep_going] * len(requests), pure=False))


# ---------------------------------------------------------------------------------------------
# one big recording in blocks of rows


@dataclass(frozen=True)
class Plan:
    """How a recording splits: ``starts[i]`` is the first record of chunk i and ``states[i]`` the
    decoder (``acq.readers.picoquant.PixelMarkerDecoder``) before it; blocks are row ranges
    ``rows[b]:rows[b + 1]``. ``meta``: what the reader reports of the whole file
    (``ReadResult.meta``); ``photons``: the photons in a pixel (of the channel kept)."""

    path: str
    shape: tuple[int, int]
    rectype: int
    chunk_records: int
    starts: tuple[int, ...]
    states: tuple
    rows: tuple[int, ...]
    meta: dict = field(default_factory=dict)
    photons: int = 0


def _image_and_unit(path: str, time_unit_s: float | None):
    """(layout, shape, pattern, rectype, time unit) of a PTU with pixel markers that the reader
    (``acq.readers.picoquant``) would read by them, or None."""
    from spdepth.acq.ptu import PIXEL_MARKER_TAG, PLAN_TAG, read_layout
    from spdepth.acq.readers import sniff_kind
    from spdepth.acq.readers.picoquant import ptu_image
    from spdepth.drivers.events import GENERIC_T3_RECORD_TYPES

    if sniff_kind(path) != "ptu":
        return None
    layout = read_layout(path)
    tags = layout.tags
    if not int(tags.get(PIXEL_MARKER_TAG, 0) or 0) or tags.get(PLAN_TAG):
        # a session's recording keeps complete dwells only (acq.recording): one task reads it so
        return None
    image = ptu_image(path, tags)
    rectype = int(tags.get("TTResultFormat_TTTRRecType", 0) or 0)
    if image is None or image["pix_y"] < 1 or image["pix_x"] < 1 or \
            rectype not in GENERIC_T3_RECORD_TYPES or "MeasDesc_Resolution" not in tags:
        return None       # one task: the reader says what is wrong with it, or interpolates
    pattern = "serp" if image["bidirectional"] else "raster"
    unit = time_unit_s or float(tags["MeasDesc_Resolution"])
    return layout, (image["pix_y"], image["pix_x"]), pattern, rectype, unit


def _decoded(decoder, chunk: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(flat pixel, dtime) of one chunk's photons that land in a pixel (``decoder.decode``)."""
    pixel, dtime = np.empty(chunk.size, np.int64), np.empty(chunk.size, np.uint32)
    n = decoder.decode(chunk, pixel, dtime)
    return pixel[:n], dtime[:n]


def plan_blocks(path: str, time_unit_s: float | None = None, *, chunk_records: int = CHUNK_RECORDS,
                block_pixels: int = BLOCK_PIXELS, keep_channel: int | None = None) -> Plan | None:
    """Walk the recording once, in chunks, keeping the decoder at each chunk start and what the
    reader would report of the whole file. None when it is not a PTU with pixel markers (then it
    goes whole to one task)."""
    from spdepth.acq.ptu import iter_records
    from spdepth.acq.readers.picoquant import PixelMarkerDecoder, fixed_dwell_periods, ptu_meta

    found = _image_and_unit(path, time_unit_s)
    if found is None:
        return None
    layout, (h, w), pattern, rectype, unit_s = found
    decoder = PixelMarkerDecoder(path, layout.tags, (h, w), pattern, keep_channel)
    starts, states, photons = [], [], 0
    for i, chunk in enumerate(iter_records(layout, chunk_records)):
        starts.append(i * chunk_records)
        states.append(copy.deepcopy(decoder))
        photons += _decoded(decoder, chunk)[0].size
    if decoder.pixel_markers == 0:
        return None
    meta = decoder.meta(ptu_meta(layout.tags, layout.n_records), unit_s)
    meta.update(fixed_dwell_periods(layout.tags)[1])
    from spdepth.recon.detect import NEIGHBOUR_ROWS

    # each block at least as tall as the halo its neighbours read from it (block_task)
    per = max(NEIGHBOUR_ROWS, block_pixels // w)
    rows = tuple(range(0, h, per)) + (h,)
    return Plan(str(path), (h, w), rectype, chunk_records, tuple(starts), tuple(states), rows,
                meta, photons)


def chunk_task(plan: Plan, i: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """Chunk i's photons split by block: ``[(flat pixel, dtime) of block b, ...]``. Reads its own
    records from the file, so dask can recompute it anywhere."""
    from spdepth.acq.ptu import iter_records, read_layout

    layout = read_layout(plan.path)
    decoder = copy.deepcopy(plan.states[i])
    chunk = next(iter_records(layout, plan.chunk_records, start=plan.starts[i]))
    pixel, dtime = _decoded(decoder, chunk)
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


def _block_store(plan: Plan, b: int, time_unit_s: float, shares):
    """(block b's store with its halo rows, the first row of it, its own rows within it)."""
    from spdepth.recon.detect import NEIGHBOUR_ROWS
    from spdepth.recon.photons import PhotonStore

    r0, r1 = plan.rows[b], plan.rows[b + 1]
    h, w = plan.shape
    lo, hi = max(0, r0 - NEIGHBOUR_ROWS), min(h, r1 + NEIGHBOUR_ROWS)
    pixel = np.concatenate([s[0] for s in shares])
    dtime = np.concatenate([s[1] for s in shares])
    # a pixel's detections all come from one block's shares, in chunk order, which the store keeps
    keep = (pixel >= lo * w) & (pixel < hi * w)
    store = PhotonStore.from_pixel_indices(pixel[keep] - lo * w, dtime[keep], (hi - lo, w), time_unit_s)
    return store, lo, (r0 - lo, r1 - lo)


def search_terms_task(plan: Plan, b: int, settings, time_unit_s: float, *shares):
    """Block b's terms of the pulse model's dispersion at ml's search's shifts
    (``recon.detect.search_dispersion_terms``), for an estimator that tempers its test's spreads
    by the frame's before the test (``recon.detect.TEMPERED_METHODS``): pooled over the blocks
    first (:func:`reconstruct_blocks`), as one process measures it on the whole frame."""
    from spdepth.recon.detect import search_dispersion_terms
    from spdepth.recon.estimate import resolve_model

    store, lo, rows = _block_store(plan, b, time_unit_s, shares)
    bb, kern, _ = resolve_model(store, settings)
    h, w = plan.shape
    return search_dispersion_terms(store, settings, bb, kern, first_pixel=lo * w, frame_pixels=h * w, rows=rows)


def block_task(plan: Plan, b: int, settings, time_unit_s: float, *shares, spreads: bool = True,
               tempered: dict | None = None):
    """Reconstruct block b (rows ``plan.rows[b]:plan.rows[b + 1]``) from its share of every chunk,
    in chunk order, and the shares of the blocks above and below it (``shares``: every chunk's
    share of block b, then of b - 1 and of b + 1 where they exist): their NEIGHBOUR_ROWS rows next
    to the block are its halo, so the return test's neighbours' support (recon.detect) sees a block's edge rows
    as the whole frame does. The halo's own maps are cut off. ``spreads`` False: the return test's
    spreads are not computed (no output file: ``recon.estimate.reconstruct``). Returns (the block's
    maps, its rows' terms of the pulse model's dispersion or None): the frame's dispersion is
    pooled from every block's (:func:`reconstruct_blocks`), as the whole frame's reconstruction
    takes it (``recon.detect.dispersion_terms``). ``tempered``: the frame's dispersion for an
    estimator that tempers its test's spreads by it (:func:`search_terms_task`)."""
    from spdepth.recon.detect import dispersion_terms
    from spdepth.recon.estimate import reconstruct
    from spdepth.recon.pixelwise import binned_once

    store, lo, rows = _block_store(plan, b, time_unit_s, shares)
    w = plan.shape[1]
    with binned_once():                 # the dispersion's terms read the detections the estimator binned
        maps = reconstruct(store, settings, spreads=spreads, dispersion=tempered or False)
        terms = dispersion_terms(store, settings, maps, first_pixel=lo * w, frame_pixels=plan.shape[0] * w,
                                 rows=rows) if spreads else None
    return crop_rows(maps, *rows), terms


def crop_rows(maps, a: int, b: int):
    """``maps`` of rows [a, b) only."""
    import dataclasses

    from spdepth.recon.maps import NPZ_KEYS

    cut = {k: np.asarray(getattr(maps, k))[..., a:b, :] for k in NPZ_KEYS if k != "settings"}
    return dataclasses.replace(maps, gain_nats=None, **cut)


def assemble(parts: list) -> object:
    """One DepthMaps from blocks of rows (in order)."""
    from spdepth.recon.maps import NPZ_KEYS, DepthMaps

    arrays = {k: np.concatenate([getattr(p, k) for p in parts], axis=getattr(parts[0], k).ndim - 2)
              for k in NPZ_KEYS if k != "settings"}
    return DepthMaps(settings=parts[0].settings, **arrays)


def reconstruct_blocks(client, plan: Plan, settings, time_unit_s: float, on_submitted=None, spreads: bool = True):
    """Maps of the whole recording, computed as chunk and block tasks on ``client`` (the channel
    kept is the plan's). ``on_submitted(futures)`` is called once everything is submitted (tests
    kill a worker there). ``spreads``: as :func:`block_task`'s; with them, ml's uncertainties are
    scaled by the frame's pulse model's dispersion, pooled from the blocks' terms in frame order (so
    the same as one process's, to the bit: ``recon.detect.with_dispersion``)."""
    from spdepth.recon.detect import TEMPERED_METHODS, dispersion_of, with_dispersion

    n_blocks = len(plan.rows) - 1
    chunks = [client.submit(chunk_task, plan, i, pure=False)
              for i in range(len(plan.starts))]
    shares = [[client.submit(_share, c, b, pure=False) for c in chunks] for b in range(n_blocks)]
    # each block's own shares, then its neighbours' (the halo rows: block_task)
    inputs = [shares[b] + [f for n in (b - 1, b + 1) if 0 <= n < n_blocks for f in shares[n]]
              for b in range(n_blocks)]
    tempered = None
    if spreads and settings.method in TEMPERED_METHODS and settings.irf is None:
        # its test tempers the spreads by the frame's dispersion, measured before the blocks' tests
        found = client.gather([client.submit(search_terms_task, plan, b, settings, time_unit_s, *inputs[b],
                                             pure=False) for b in range(n_blocks)])
        tempered = dispersion_of(tuple(np.concatenate(part) for part in zip(*found)))
    blocks = [client.submit(block_task, plan, b, settings, time_unit_s, *inputs[b], spreads=spreads,
                            tempered=tempered, pure=False)
              for b in range(n_blocks)]
    if on_submitted is not None:
        on_submitted(chunks + blocks)
    del chunks, shares, inputs      # the scheduler keeps what the blocks still need, and how to remake it
    parts = client.gather(blocks)
    maps = assemble([p[0] for p in parts])
    terms = [p[1] for p in parts]
    if any(t is None for t in terms):
        return maps
    return with_dispersion(maps, dispersion_of(tuple(np.concatenate(part) for part in zip(*terms))))


def block_settings(request, unit_s: float):
    """ReconSettings of a fully given model (window, bins and pulse), as
    ``acq.api.reconstruct_file`` resolves them (``acq.api.file_settings``), or None when any is
    left to the data."""
    from spdepth.acq.api import file_settings

    if request.window_s is None or request.bin_s is None or \
            (request.pulse_rms_s is None and request.irf is None):
        return None
    return file_settings(request, unit_s)


def _by_blocks(request, client) -> dict | None:
    """The single-recording block path; None when the input cannot be split (see module doc).
    The maps are finished and written by the library (``acq.api.file_result``), as in-process."""
    from spdepth.acq.api import file_result, pileup_decided
    from spdepth.acq.readers.common import ReadResult

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
    plan = plan_blocks(path, unit_s, keep_channel=request.channel)
    if plan is None:
        return None
    if plan.photons == 0:
        raise InputError(f"{path}: holds no photons")
    decided, pileup = pileup_decided(request, "periods_per_pixel" in plan.meta or request.periods is not None,
                                     cube=False)
    if not decided:
        # Coates' correction needs each pixel's whole histogram (and the decision, all of them)
        print(f"spdepth recon: {path}: the pile-up decision needs every pixel's histogram: "
              f"reconstructing it as one task (--pileup off splits it into blocks)", file=sys.stderr)
        return None
    t1 = time.perf_counter()
    # without an output file only the summary is seen: no spreads (as spdepth recon FILE)
    maps = reconstruct_blocks(client, plan, settings, unit_s, spreads=request.writes_files())
    read = ReadResult(store=None, path=str(path), kind="ptu", is_image=True, meta=plan.meta)
    res = file_result(request, maps, read, read_s=t1 - t0, recon_s=time.perf_counter() - t1,
                      photons_in_file=plan.photons, pileup=pileup)
    return {**res.summary, "chunks": len(plan.starts), "blocks": len(plan.rows) - 1}


def reconstruct_files(requests: list, dask: str | None = None,
                      keep_going: bool = False) -> list[dict]:
    """Summaries of ``requests`` (``FileReconRequest``), in order: on a dask cluster (``dask`` an
    address or ``local:N``; one recording with a fully given model is split into blocks of rows),
    or one after the other in this process when ``dask`` is None. ``keep_going``: a file that
    fails gives ``{"input", "error"}`` in its place (``recon_file``) and the others go on."""
    with (connect(dask) if dask else contextlib.nullcontext()) as client:
        if client is not None and len(requests) == 1:
            summary = _by_blocks(requests[0], client)
            if summary is not None:
                return [summary]
        return _per_file(requests, client, keep_going)
