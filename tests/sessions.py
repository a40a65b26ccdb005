"""Sessions for tests, and what the session tests check of them. Sessions are built the way every
front end builds them, a request through ``acq.api.build_session``, so a test fails when the
library's wiring drifts; only the simulated bench is opened by the test itself
(``acq.instruments.open_sim``), for its test hooks (the rig's truth, pacing, faults)."""

from __future__ import annotations

import numpy as np

from spdepth.acq.api import build_session
from spdepth.acq.flags import ACQUIRING, AcqFlag
from spdepth.acq.requests import ReplayRequest, ScanRequest, SimBench
from spdepth.recon.maps import DepthMaps


def sim_session(inst, shape, out=None, *, target=10, method="lmf", mode="gated", dwell_s=None,
                reader_options=None, **request_fields):
    """A scan session on the opened simulated bench ``inst``: ``shape`` (H, W), ``dwell_s`` the
    gated dwell limit or the raster dwell (None: the bench's default), other ``ScanRequest``
    fields as given (``pattern``, ``max_passes``, ``time_limit_s``, ...). The pulse is the
    scene's, as ``build_session`` gives a simulated bench. ``reader_options``: more arguments of
    the tagger's reader (``ScanSource.reader_options``), a test hook no request carries."""
    dwell = {"dwell_limit_s" if mode == "gated" else "dwell_s": dwell_s}
    bench = SimBench(scene=inst.info["scene"], ppp=inst.info["ppp"], seed=inst.info["seed"])
    request = ScanRequest(instruments=bench, size=tuple(shape),
                          target=target, method=method, mode=mode, **dwell, **request_fields)
    session = build_session(request, out, inst)
    session.source.reader_options.update(reader_options or {})
    return session


def replay_session(recording, out=None, **request_fields):
    """A replay of ``recording`` (a session folder) with its recorded plan and settings unless
    ``request_fields`` (``ReplayRequest``: ``target``, ``method``, ...) replace them."""
    return build_session(ReplayRequest(recording=str(recording), **request_fields), out)


def _dwells_by_pixel(rig, width):
    out: dict[int, list[np.ndarray]] = {}
    for row, col, ev in rig.truth:
        out.setdefault(row * width + col, []).append(ev["dtime"][ev["kind"] == 0])
    return out


def assert_from_complete_dwells(session, rig):
    """Every pixel's kept times are the first in-window detections of a subsequence of the dwells
    the world produced for that pixel, in order: right pixel, no detection twice, none invented."""
    store = session.store
    lo, hi = store.window
    dwells = _dwells_by_pixel(rig, store.shape[1])
    for p in range(store.n_pixels):
        kept = store.times[p, :store.count[p]]
        # every way through the dwells, not the first match only: a dwell lost in an overflow
        # (the world made it, the stream never had it) can start with the same time as the next
        # dwell kept, and taking it would leave the kept times misaligned
        reach = {0}
        for d in dwells.get(p, []):
            w = d[(d >= lo) & (d < hi)]
            for k in list(reach):
                take = min(w.size, kept.size - k)
                if take and np.array_equal(kept[k:k + take], w[:take]):
                    reach.add(k + take)
        assert kept.size in reach, f"pixel {divmod(p, store.shape[1])}: kept times not from its dwells"


def assert_complete_or_flagged(session):
    """Every pixel final: complete with the target, or flagged short."""
    target = session.plan.target
    counts = session.store.count
    flags = session.acq_flags
    assert np.all(flags != ACQUIRING), "every pixel ends final"
    short = counts < target
    assert np.all(flags[short] != AcqFlag.COMPLETE), "a short pixel passed as complete"
    assert np.all(counts[flags == AcqFlag.COMPLETE] == target)


def assert_same_maps(a: DepthMaps, b: DepthMaps, skip_flags=False):
    """The same maps, bit for bit (``skip_flags``: but the estimator flags)."""
    for k in ("tof_s", "depth_m", "background", "signal", "photons", "uncertainty_s", "flags"):
        if skip_flags and k == "flags":
            continue
        np.testing.assert_array_equal(getattr(a, k), getattr(b, k), err_msg=k)


class StoreView:
    """What ``LiveRecon`` reads of ``acq.store.PixelStore``, over a ``PhotonStore``."""

    def __init__(self, store):
        self.whole, self.shape, self.time_unit_s = store, store.shape, store.time_unit_s
        self.count = np.diff(store.offsets)

    def photons(self, pixels=None):
        from spdepth.recon.photons import PhotonStore

        if pixels is None:
            return self.whole
        idx = np.asarray(pixels, np.int64)
        parts = [self.whole.times[self.whole.offsets[p]:self.whole.offsets[p + 1]] for p in idx]
        offsets = np.concatenate(([0], np.cumsum([x.size for x in parts]))).astype(np.int64)
        return PhotonStore(np.concatenate(parts) if parts else np.zeros(0), offsets, (1, idx.size),
                           self.time_unit_s)


__all__ = ["sim_session", "replay_session", "assert_complete_or_flagged", "assert_from_complete_dwells",
           "assert_same_maps", "StoreView"]
