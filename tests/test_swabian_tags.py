"""Swabian time tags -> our events (``drivers.swabian.protocol.tags_to_events``, a numba kernel)
against a plain Python reference, with an event divider, overflows, markers that rose together,
and chunk boundaries anywhere."""

from __future__ import annotations

import numpy as np
import pytest

from spdepth.drivers.events import EventKind
from spdepth.drivers.swabian.protocol import ConverterState, SwabianSettings, tags_to_events


def reference(ts, ch, ty, s: SwabianSettings):
    period, res = s.sync_period_s * 1e12, s.resolution_ps
    roles = {s.sync_channel: ("sync", 0)}
    roles.update({c: ("det", i) for i, c in enumerate(s.detector_channels)})
    roles.update({c: ("mark", 1 << i) for i, c in enumerate(s.marker_channels)})
    out, last_t, last_s, prev_mark_t = [], None, 0, None
    for t, c, y in zip(ts.tolist(), ch.tolist(), ty.tolist()):
        if y in (1, 2):
            k = 0 if last_t is None else int(np.floor((t - last_t) / period))
            out.append((last_s + k, 0, 0, int(EventKind.LOST), 0))
            continue
        if y != 0 or c not in roles:
            continue
        role, v = roles[c]
        if role == "sync":
            last_s = 0 if last_t is None else last_s + int(np.floor((t - last_t) / period + 0.5))
            last_t = t
            continue
        if last_t is None:
            continue
        k = int(np.floor((t - last_t) / period))
        dt = (t - last_t) - k * period
        if role == "det":
            out.append((last_s + k, int(np.floor(dt / res + 1e-6)), v, 0, 0))
        elif out and out[-1][3] == 1 and prev_mark_t == t:
            s_, d_, c_, k_, m_ = out[-1]
            out[-1] = (s_, d_, c_, k_, m_ | v)
        else:
            out.append((last_s + k, 0, 0, 1, v))
            prev_mark_t = t
    return out


def _stream(rng, settings, n_sync=400):
    period = int(settings.sync_period_s * 1e12)
    ts, ch, ty = [], [], []
    for s in range(n_sync):
        t0 = s * period
        if s % settings.event_divider == 0:
            ts.append(t0), ch.append(settings.sync_channel), ty.append(0)
        if rng.random() < 0.1:
            for c in rng.choice(settings.marker_channels, rng.integers(1, 3), replace=False):
                ts.append(t0), ch.append(int(c)), ty.append(0)
        for _ in range(rng.poisson(0.3)):
            ts.append(t0 + int(rng.integers(0, period // 8)) * 8), ch.append(2), ty.append(0)
        if rng.random() < 0.01:
            ts += [t0 + 1, t0 + 1]
            ch += [0, 0]
            ty += [2, 3]
    order = np.argsort(ts, kind="stable")
    return (np.array(ts)[order].astype(np.int64), np.array(ch)[order].astype(np.int32),
            np.array(ty)[order].astype(np.uint8))


@pytest.mark.parametrize("divider", [1, 7, 64])
def test_kernel_equals_reference_across_chunks(rng, divider):
    settings = SwabianSettings(sync_period_s=100e-9, event_divider=divider, resolution_ps=8)
    ts, ch, ty = _stream(rng, settings)
    ref = reference(ts, ch, ty, settings)
    cuts = np.sort(rng.choice(np.arange(1, ts.size), 5, replace=False))
    state = ConverterState()
    parts = [tags_to_events(a, b, c, settings, state)
             for a, b, c in zip(np.split(ts, cuts), np.split(ch, cuts), np.split(ty, cuts))]
    got = np.concatenate(parts)
    # a chunk boundary between two simultaneous marker tags leaves them as two events; the
    # reference sees one: compare with the cuts' marker pairs merged back
    rows = [tuple(int(v) for v in (e["sync"], e["dtime"], e["channel"], e["kind"], e["marker"]))
            for e in got]
    merged = []
    for r in rows:
        if merged and r[3] == 1 and merged[-1][3] == 1 and merged[-1][0] == r[0] \
                and not (merged[-1][4] & r[4]):
            m = merged[-1]
            merged[-1] = (m[0], m[1], m[2], m[3], m[4] | r[4])
        else:
            merged.append(r)
    ref_merged = []
    for r in ref:
        if ref_merged and r[3] == 1 and ref_merged[-1][3] == 1 and ref_merged[-1][0] == r[0] \
                and not (ref_merged[-1][4] & r[4]):
            m = ref_merged[-1]
            ref_merged[-1] = (m[0], m[1], m[2], m[3], m[4] | r[4])
        else:
            ref_merged.append(r)
    assert merged == ref_merged
    assert np.all(np.diff(got["sync"].astype(np.int64)) >= 0)
    assert np.count_nonzero(got["kind"] == EventKind.LOST) == np.count_nonzero(ty == 2)


def test_tags_before_the_first_sync_cannot_be_placed():
    s = SwabianSettings(sync_period_s=100e-9)
    st = ConverterState()
    ev = tags_to_events(np.array([5, 10, 100_050]), np.array([2, 1, 2]), np.zeros(3, np.uint8), s, st)
    assert st.unplaced == 1 and ev.size == 1
    assert int(ev["sync"][0]) == 1 and int(ev["dtime"][0]) == (100_050 - 10 - 100_000) // 8


def test_settings_refuse_what_t3_records_cannot_carry():
    from spdepth.drivers.errors import SettingError

    with pytest.raises(SettingError, match="15-bit"):
        SwabianSettings(sync_period_s=1e-6, resolution_ps=1)
    with pytest.raises(SettingError, match="distinct"):
        SwabianSettings(sync_channel=2, detector_channels=(2,))
