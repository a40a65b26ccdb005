"""Marker-driven pixel assignment against a plain Python reference, in any chunking."""

from __future__ import annotations

import numpy as np
import pytest

from spdepth.acq.assign import PixelAssigner
from spdepth.drivers.events import EVENT_DTYPE, EventKind, Marker
from spdepth.recon.errors import InputError


def reference_assign(events, shape, serpentine):
    """Record by record, as docs/protocols.md describes the marker lines."""
    h, w = shape
    row, visit, is_open, known = -1, -1, False, True
    out = []
    for e in events:
        pix = -1
        if e["kind"] == EventKind.MARKER:
            m = int(e["marker"])
            if m & Marker.FRAME:
                row, is_open, known = -1, False, True
            if m & Marker.LINE_START:
                row, visit = row + 1, -1
            if m & Marker.PIXEL:
                visit, is_open = visit + 1, True
            if m & Marker.LINE_STOP:
                is_open = False
        elif e["kind"] == EventKind.PHOTON and is_open and known and 0 <= row < h and 0 <= visit < w:
            col = w - 1 - visit if serpentine and row % 2 else visit
            pix = row * w + col
        elif e["kind"] == EventKind.LOST:
            known = False
        out.append(pix)
    return np.array(out, dtype=np.int64)


def scan_stream(rng, shape, frames=1, p_lost=0.0):
    """Markers of a scan in the galvo's order with a few photons per pixel and between lines."""
    h, w = shape
    rows = []
    for f in range(frames):
        for r in range(h):
            for c in range(w):
                m = Marker.PIXEL | (Marker.LINE_START if c == 0 else 0) | (
                    Marker.FRAME if (r == 0 and c == 0) else 0)
                rows.append((EventKind.MARKER, m))
                rows += [(EventKind.PHOTON, 0)] * int(rng.integers(0, 4))
                if rng.random() < p_lost:
                    rows.append((EventKind.LOST, 0))
            rows.append((EventKind.MARKER, Marker.LINE_STOP))
            rows += [(EventKind.PHOTON, 0)] * int(rng.integers(0, 2))   # fly-back photons
    ev = np.zeros(len(rows), EVENT_DTYPE)
    ev["kind"] = [k for k, _ in rows]
    ev["marker"] = [m for _, m in rows]
    ev["sync"] = np.arange(len(rows))
    return ev


@pytest.mark.parametrize("pattern", ["raster", "serp"])
@pytest.mark.parametrize("p_lost", [0.0, 0.02])
def test_kernel_matches_reference_in_any_chunking(rng, pattern, p_lost):
    shape = (5, 7)
    ev = scan_stream(rng, shape, frames=3, p_lost=p_lost)
    want = reference_assign(ev, shape, pattern == "serp")
    a = PixelAssigner(shape, pattern)
    cuts = np.sort(rng.integers(0, ev.size, 6))
    got = np.concatenate([a.assign(part) for part in np.split(ev, cuts)])
    np.testing.assert_array_equal(got, want)
    assert a.lines_closed == 3 * 5
    assert len(a.lost) == int((ev["kind"] == EventKind.LOST).sum())


def test_every_pixel_gets_its_photons_and_flyback_gets_none(rng):
    shape = (4, 6)
    ev = scan_stream(rng, shape)
    pix = PixelAssigner(shape, "serp").assign(ev)
    photons = ev["kind"] == EventKind.PHOTON
    # fly-back photons (right after LINE_STOP) are unassigned, everything else is on the grid
    after_stop = np.zeros(ev.size, bool)
    after_stop[1:] = (ev["kind"][:-1] == EventKind.MARKER) & (ev["marker"][:-1] == Marker.LINE_STOP)
    assert np.all(pix[photons & after_stop] == -1)
    assert np.all(pix[photons & ~after_stop] >= 0)


def test_lost_span_names_the_open_pixel_and_stops_assignment_until_the_next_frame():
    kinds = [1, 0, 1, 0, 2, 0, 1, 0, 1, 0]
    marks = [Marker.FRAME | Marker.LINE_START | Marker.PIXEL, 0, Marker.PIXEL, 0, 0, 0,
             Marker.PIXEL, 0, Marker.FRAME | Marker.LINE_START | Marker.PIXEL, 0]
    ev = np.zeros(len(kinds), EVENT_DTYPE)
    ev["kind"], ev["marker"], ev["sync"] = kinds, marks, np.arange(len(kinds))
    ev["dtime"][4] = 123
    a = PixelAssigner((2, 3))
    pix = a.assign(ev)
    np.testing.assert_array_equal(pix, [-1, 0, -1, 1, -1, -1, -1, -1, -1, 0])
    assert len(a.lost) == 1 and a.lost[0].pixel == 1 and a.lost[0].records_lost == 123
    assert a.position_known


def test_bad_arguments_are_refused():
    with pytest.raises(InputError, match="pattern"):
        PixelAssigner((2, 2), "spiral")
    with pytest.raises(InputError, match="shape"):
        PixelAssigner((0, 2))
    with pytest.raises(InputError, match="EVENT_DTYPE"):
        PixelAssigner((2, 2)).assign(np.zeros(3, np.uint32))
