"""``replay --speed S`` paces to the recorded laser time within a chunk, not only between chunks."""

from __future__ import annotations

import time

import numpy as np

from spdepth.acq.api import scan_settings
from spdepth.acq.instruments import open_sim, sim_plan
from spdepth.acq.recording import ReplaySource
from spdepth.acq.requests import ScanRequest
from spdepth.acq.scan_source import ScanSource
from spdepth.acq.session import Session, SessionState


def test_a_paced_replay_follows_the_recorded_laser_time(tmp_path):
    with open_sim("bust", (10, 10), ppp=10, seed=3) as inst:
        plan = sim_plan(inst, (10, 10), target=10)
        settings = scan_settings(ScanRequest(size=(10, 10), target=10, method="lmf"),
                                 inst.tagger.resolution_s, inst.scene)
        s = Session(plan, settings, ScanSource(inst.galvo, inst.tagger,
                                               sync_period_s=inst.sync_period_s), out_dir=tmp_path)
        assert s.run() == SessionState.DONE
    fast = ReplaySource(tmp_path)
    period = fast.info.sync_period_s
    chunks = [c for _, it in fast.segments() for c in it]
    syncs = np.concatenate([c["sync"] for c in chunks])
    recorded_s = float(syncs.max() - syncs.min()) * period
    assert len(chunks) <= 2                      # the whole scan fits in a chunk or two
    speed = recorded_s / 1.5                     # replayed over about 1.5 s
    paced = ReplaySource(tmp_path, speed=speed)
    arrivals = []
    t0 = time.monotonic()
    for _, it in paced.segments():
        for c in it:
            if c.size:
                arrivals.append((time.monotonic() - t0, float(c["sync"].max()) * period / speed))
    a = np.array(arrivals)
    assert len(a) >= 20                          # let out in slices, not as one chunk
    assert 1.2 < a[-1, 0] < 3.0                  # took the replayed time, not zero
    # each slice arrives when its recorded time has passed (relative to the first), not before
    rel = a[:, 1] - a[0, 1]
    assert np.all(a[:, 0] >= rel - 0.02)
    assert np.median(a[:, 0] - rel) < 0.2
