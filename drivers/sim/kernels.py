"""Numba kernels of the photon simulator.

Each kernel takes a NumPy ``Generator`` and a few plain arrays; the orchestration in
``drivers.sim.world`` and ``drivers.sim.effects`` validates, allocates and calls them. Times
inside one laser period are float64 seconds in ``[0, period_s)``; a detection is the pair
(absolute sync index, time after that sync). Plain NumPy references live in
``tests/test_sim_kernels.py``.

Origin codes (``origin`` arrays, uint8): 0 = background or dark count, ``1 + k`` = signal from
surface ``k``, ``ORIGIN_AFTERPULSE`` = an afterpulse, ``ORIGIN_MARKER`` = a marker row.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numba import njit

ORIGIN_BACKGROUND = 0
ORIGIN_AFTERPULSE = 250
ORIGIN_MARKER = 251

PULSE_GAUSSIAN = 0
PULSE_TABLE = 1

KIND_PHOTON = 0
KIND_MARKER = 1

# an int64 zero for kernel calls: a literal 0 argument compiles one more variant of the callee
ZERO = np.int64(0)


@njit(cache=True, nogil=True)
def sample_pulse_s(rng, pulse_kind, rms_s, irf_cdf, irf_t0_s, irf_bin_s):
    """One draw of the emission-to-detection delay of the pulse shape, zero-mean, seconds."""
    if pulse_kind == PULSE_GAUSSIAN:
        return rms_s * rng.standard_normal()
    # A measured instrument response: pick its bin by the cumulative table, uniform inside.
    j = np.searchsorted(irf_cdf, rng.random(), side="right")
    if j >= irf_cdf.size:
        j = irf_cdf.size - 1
    return irf_t0_s + (j + rng.random()) * irf_bin_s


@njit(cache=True, nogil=True)
def generate_chain(rng, pix, start_sync, n_sync, i_begin, u_begin,
                   sig_pp, tof_s, bg_pp, period_s,
                   pulse_kind, rms_s, irf_cdf, irf_t0_s, irf_bin_s,
                   out_sync, out_t, out_origin, out_item):
    """Ideal detections (equation (3) of the paper) for a list of pixels, one after another.

    Detections of one pixel form a Poisson process in the continuous pulse coordinate ``u``
    (pulses since the pixel's first sync) with rate ``sum(sig_pp[p]) + bg_pp[p]`` per pulse;
    drawing exponential gaps skips the empty pulses instead of visiting each one, and the count
    in each pulse comes out Poisson exactly. Each detection is then background (uniform over the
    period) or signal of surface k (tof + pulse shape, folded into the period) in proportion to
    the rates.

    pix (n,) int64 pixel indices into the rate tables; start_sync, n_sync (n,) int64 first sync
    and number of syncs of each; sig_pp (P, K), tof_s (P, K), bg_pp (P,) mean detections per pulse
    and times of flight. Writes (absolute sync, time in period s, origin, list index) into the out
    arrays. Starts at list item ``i_begin`` at pulse coordinate ``u_begin`` (for resuming).

    Returns (n_written, i_next, u_next): when the output is full it stops before drawing the next
    gap; since gaps are memoryless, resuming at (i_next, u_next) continues the same process.
    """
    cap = out_sync.size
    n = 0
    u = u_begin
    n_surf = sig_pp.shape[1]
    for i in range(i_begin, pix.size):
        p = pix[i]
        lam_bg = bg_pp[p]
        lam = lam_bg
        for k in range(n_surf):
            lam += sig_pp[p, k]
        end = float(n_sync[i])
        if lam > 0.0:
            inv = 1.0 / lam
            while True:
                if n >= cap:
                    return n, i, u
                u += rng.standard_exponential() * inv
                if u >= end:
                    break
                pulse = np.int64(u)
                x = rng.random() * lam
                if x < lam_bg:
                    t = rng.random() * period_s
                    origin = ORIGIN_BACKGROUND
                else:
                    x -= lam_bg
                    k = 0
                    while k < n_surf - 1 and x >= sig_pp[p, k]:
                        x -= sig_pp[p, k]
                        k += 1
                    t = tof_s[p, k] + sample_pulse_s(rng, pulse_kind, rms_s, irf_cdf,
                                                     irf_t0_s, irf_bin_s)
                    # Fold into the period: the pulse train is periodic, so a return later than
                    # one period is statistically the same as one in this period.
                    t -= np.floor(t / period_s) * period_s
                    if t >= period_s:
                        t = 0.0
                    origin = 1 + k
                out_sync[n] = start_sync[i] + pulse
                out_t[n] = t
                out_origin[n] = origin
                out_item[n] = i
                n += 1
        u = 0.0
    return n, pix.size, 0.0


@njit(cache=True, nogil=True)
def sort_within_sync(sync, t, origin, item):
    """Order detections by (sync, t) in place. Input is already sorted by sync, and runs of equal
    sync are short at any sensible flux, so insertion sort is linear in practice."""
    n = sync.size
    for i in range(1, n):
        s = sync[i]
        ti = t[i]
        j = i - 1
        if sync[j] < s or (sync[j] == s and t[j] <= ti):
            continue
        o = origin[i]
        it = item[i]
        while j >= 0 and (sync[j] > s or (sync[j] == s and t[j] > ti)):
            sync[j + 1] = sync[j]
            t[j + 1] = t[j]
            origin[j + 1] = origin[j]
            item[j + 1] = item[j]
            j -= 1
        sync[j + 1] = s
        t[j + 1] = ti
        origin[j + 1] = o
        item[j + 1] = it


@njit(cache=True, nogil=True)
def jitter_kernel(rng, t, rms_s, period_s):
    """Add Gaussian timing jitter (RMS ``rms_s``) to every time in place, folded into the period."""
    for i in range(t.size):
        x = t[i] + rms_s * rng.standard_normal()
        x -= np.floor(x / period_s) * period_s
        if x >= period_s:
            x = 0.0
        t[i] = x


@njit(cache=True, nogil=True)
def _counted(t, res_s, range_bins, win_lo, win_hi):
    """Whether a detection at time t counts towards a count-gated target: recorded at all
    (dtime below the tagger range) and inside [win_lo, win_hi) tagger units."""
    d = np.int64(t / res_s)
    return d < range_bins and d >= win_lo and d < win_hi


@njit(cache=True, nogil=True)
def detector_kernel(rng, sync, t, origin, item, period_s, dead_s, ap_prob, ap_tau_s, det, sync_end,
                    stop_count, res_s, range_bins, win_lo, win_hi,
                    out_sync, out_t, out_origin, out_item):
    """The detector as a sequential machine: non-paralysable dead time and afterpulsing.

    Inputs are ideal detections sorted by (sync, t). The detector is blind for ``dead_s`` after
    every detection it registers (0 disables); with probability ``ap_prob`` a registered
    detection releases an afterpulse ``dead_s + Exponential(ap_tau_s)`` later (0 disables), which
    may itself be blocked or afterpulse again.

    State carried between calls (the detector does not know about pixels), ``det``, a
    :class:`DetState`: state_i = [has_last, last_sync, n_pending], state_t = [last_t]; pending
    afterpulses in pend_sync/pend_t/pend_item[:n_pending], sorted. Pending afterpulses at or after ``sync_end``
    stay pending. When ``stop_count`` > 0 the kernel stops right after the registered detection
    that makes ``stop_count`` counted ones (see ``_counted``), so the carried state is exactly the
    state at that detection.

    Returns (n_out, n_counted), or (-1, 0) when the output arrays are too small.
    """
    state_i, state_t, pend_sync, pend_t, pend_item = det
    n_in = sync.size
    cap = out_sync.size
    pcap = pend_sync.size
    has_last = state_i[0]
    last_sync = state_i[1]
    npend = state_i[2]
    last_t = state_t[0]
    i = 0
    n = 0
    counted = 0
    while True:
        use_pend = False
        if npend > 0 and pend_sync[0] < sync_end:
            if i >= n_in:
                use_pend = True
            elif pend_sync[0] < sync[i] or (pend_sync[0] == sync[i] and pend_t[0] < t[i]):
                use_pend = True
        if use_pend:
            s = pend_sync[0]
            ti = pend_t[0]
            o = ORIGIN_AFTERPULSE
            it = pend_item[0]
            for q in range(1, npend):
                pend_sync[q - 1] = pend_sync[q]
                pend_t[q - 1] = pend_t[q]
                pend_item[q - 1] = pend_item[q]
            npend -= 1
        elif i < n_in:
            s = sync[i]
            ti = t[i]
            o = origin[i]
            it = item[i]
            i += 1
        else:
            break
        if has_last == 1 and dead_s > 0.0:
            gap = (s - last_sync) * period_s + (ti - last_t)
            if gap < dead_s:
                continue
        if n >= cap:
            return -1, 0
        out_sync[n] = s
        out_t[n] = ti
        out_origin[n] = o
        out_item[n] = it
        n += 1
        has_last = 1
        last_sync = s
        last_t = ti
        if ap_prob > 0.0 and rng.random() < ap_prob:
            ta = ti + dead_s + ap_tau_s * rng.standard_exponential()
            sa = s + np.int64(np.floor(ta / period_s))
            ta -= np.floor(ta / period_s) * period_s
            if ta >= period_s:
                ta = 0.0
            if npend < pcap:
                q = npend
                while q > 0 and (pend_sync[q - 1] > sa or (pend_sync[q - 1] == sa and pend_t[q - 1] > ta)):
                    pend_sync[q] = pend_sync[q - 1]
                    pend_t[q] = pend_t[q - 1]
                    pend_item[q] = pend_item[q - 1]
                    q -= 1
                pend_sync[q] = sa
                pend_t[q] = ta
                pend_item[q] = it
                npend += 1
        if stop_count > 0 and _counted(ti, res_s, range_bins, win_lo, win_hi):
            counted += 1
            if counted >= stop_count:
                break
    state_i[0] = has_last
    state_i[1] = last_sync
    state_i[2] = npend
    state_t[0] = last_t
    return n, counted


@njit(cache=True, nogil=True, inline="always")
def _put_marker(n, sync, bits, ev_sync, ev_dtime, ev_channel, ev_kind, ev_marker, ev_origin):
    ev_sync[n] = sync
    ev_dtime[n] = 0
    ev_channel[n] = 0
    ev_kind[n] = KIND_MARKER
    ev_marker[n] = bits
    ev_origin[n] = ORIGIN_MARKER


@njit(cache=True, nogil=True)
def pack_events(sync, t, origin, res_s, range_bins, channel, m_sync, m_bits,
                ev_sync, ev_dtime, ev_channel, ev_kind, ev_marker, ev_origin):
    """Quantise detection times to tagger units, drop those beyond the tagger range, and merge
    marker rows in (a marker goes before the photons of its sync). Writes into event field views;
    returns the number of rows written (capacity must be len(sync) + len(m_sync))."""
    n = 0
    j = 0
    nm = m_sync.size
    for i in range(sync.size):
        s = sync[i]
        while j < nm and m_sync[j] <= s:
            _put_marker(n, m_sync[j], m_bits[j], ev_sync, ev_dtime, ev_channel, ev_kind,
                        ev_marker, ev_origin)
            n += 1
            j += 1
        d = np.int64(t[i] / res_s)
        if d >= range_bins:
            continue
        ev_sync[n] = s
        ev_dtime[n] = d
        ev_channel[n] = channel
        ev_kind[n] = KIND_PHOTON
        ev_marker[n] = 0
        ev_origin[n] = origin[i]
        n += 1
    while j < nm:
        _put_marker(n, m_sync[j], m_bits[j], ev_sync, ev_dtime, ev_channel, ev_kind,
                    ev_marker, ev_origin)
        n += 1
        j += 1
    return n



@njit(cache=True, nogil=True)
def start_at_kernel(state_i, pend_sync, pend_t, pend_item, sync):
    """The detector forgets what cannot affect detections from ``sync`` on: pending afterpulses
    that would have fired before it (nobody was listening), and everything when time went
    backwards. State arrays as in ``detector_kernel``."""
    if state_i[0] != 0 and state_i[1] > sync:
        state_i[0] = 0
        state_i[1] = 0
        state_i[2] = 0
        return
    m = 0
    for q in range(state_i[2]):
        if pend_sync[q] >= sync:
            pend_sync[m] = pend_sync[q]
            pend_t[m] = pend_t[q]
            pend_item[m] = pend_item[q]
            m += 1
    state_i[2] = m


class Dwell(NamedTuple):
    """How ``dwell_run`` dwells (all int64 but ``stop_s``): ``n_target`` counted detections per pixel
    (0: fixed dwell), ``limit`` syncs per pixel (the fixed dwell, or the count gate's limit),
    ``settle`` syncs before every pixel but the first, ``off_syncs`` syncs of a pixel off the
    scene, ``start_sync`` of the first pixel, ``stop_s`` virtual time and ``max_records`` rows
    after which the run stops, ``capacity`` a first guess of the detections (arrays grow)."""

    n_target: int
    limit: int
    settle: int
    off_syncs: int
    start_sync: int
    stop_s: float
    max_records: int
    capacity: int


class Rates(NamedTuple):
    """The scene as rate tables over flat pixels P and surfaces K: ``sig_pp`` (P, K) and ``bg_pp``
    (P,) mean detections per pulse, ``tof_s`` (P, K) times of flight, ``lam`` (P,) their sum per
    pixel, ``period_s`` the laser period."""

    sig_pp: np.ndarray
    tof_s: np.ndarray
    bg_pp: np.ndarray
    lam: np.ndarray
    period_s: float


class Pulse(NamedTuple):
    """The pulse shape ``sample_pulse_s`` draws from: ``kind`` PULSE_GAUSSIAN (``rms_s``) or
    PULSE_TABLE (cumulative ``irf_cdf`` over bins of ``irf_bin_s`` from ``irf_t0_s``)."""

    kind: int
    rms_s: float
    irf_cdf: np.ndarray
    irf_t0_s: float
    irf_bin_s: float


class Effects(NamedTuple):
    """The effects of a dwell: ``jitter_rms_s`` > 0 jitters every time; ``sequential`` runs
    ``detector_kernel`` with dead time ``dead_s`` and afterpulses (``ap_prob``, ``ap_tau_s``)."""

    jitter_rms_s: float
    sequential: bool
    dead_s: float
    ap_prob: float
    ap_tau_s: float


class DetState(NamedTuple):
    """The detector state arrays of ``detector_kernel`` (carried from call to call):
    ``state_i`` [has_last, last_sync, n_pending], ``state_t`` [last_t], pending afterpulses."""

    state_i: np.ndarray
    state_t: np.ndarray
    pend_sync: np.ndarray
    pend_t: np.ndarray
    pend_item: np.ndarray


class Gate(NamedTuple):
    """What a count gate counts (``_counted``): dtime = t / ``res_s`` below ``range_bins`` and in
    [``win_lo``, ``win_hi``) tagger units."""

    res_s: float
    range_bins: int
    win_lo: int
    win_hi: int


class Rows(NamedTuple):
    """Detections in flight: sync (int64), t (float64 s), origin (uint8), item (int32)."""

    sync: np.ndarray
    t: np.ndarray
    origin: np.ndarray
    item: np.ndarray


@njit(cache=True, nogil=True)
def _no_rows():
    return Rows(np.empty(0, np.int64), np.empty(0, np.float64), np.empty(0, np.uint8),
                np.empty(0, np.int32))


@njit(cache=True, nogil=True)
def _grow(rows, n_keep, need):
    """Rows with room for ``need``: the same ones when they have it, else new ones at least twice
    as long holding the first ``n_keep``."""
    if rows.sync.size >= need:
        return rows
    cap = max(need, 2 * rows.sync.size)
    new = Rows(np.empty(cap, np.int64), np.empty(cap, np.float64), np.empty(cap, np.uint8),
               np.empty(cap, np.int32))
    for q in range(n_keep):
        new.sync[q] = rows.sync[q]
        new.t[q] = rows.t[q]
        new.origin[q] = rows.origin[q]
        new.item[q] = rows.item[q]
    return new


@njit(cache=True, nogil=True)
def _take(rows, n):
    return Rows(rows.sync[:n], rows.t[:n], rows.origin[:n], rows.item[:n])


@njit(cache=True, nogil=True)
def _copy_state(dst, src):
    """dst = src for detector states, as loops: numba compiles a slice assignment for tens of
    seconds."""
    for i in range(src.state_i.size):
        dst.state_i[i] = src.state_i[i]
    dst.state_t[0] = src.state_t[0]
    for i in range(src.pend_sync.size):
        dst.pend_sync[i] = src.pend_sync[i]
        dst.pend_t[i] = src.pend_t[i]
        dst.pend_item[i] = src.pend_item[i]


@njit(cache=True, nogil=True, inline="always")
def _chunk_syncs(gated, need, rate, left, limit):
    """Syncs to generate next for a pixel: the whole dwell when not gated, else enough for the
    ``need`` counts still missing at ``rate`` counted detections per sync (25% more, at least 16),
    never more than the ``left`` syncs of its limit."""
    if not gated:
        chunk = limit
    elif rate > 0.0:
        f = need / rate * 1.25 + 16
        chunk = left if f >= left else max(np.int64(f), 16)
    else:
        chunk = limit
    return min(max(chunk, 16) if gated else chunk, left)


@njit(cache=True, nogil=True, inline="always")
def _generate(rng, p, s0, chunk, gen, rates, pulse):
    """Ideal detections of pixel ``p`` over ``chunk`` syncs from ``s0`` into ``gen`` (grown as
    needed; ``generate_chain`` resumes where the buffer filled); returns (gen, rows written)."""
    expected = rates.lam[p] * chunk
    gen = _grow(gen, ZERO, np.int64(expected + 6.0 * np.sqrt(expected) + 64))
    one_pix = np.full(1, p, np.int64)
    one_start = np.full(1, s0, np.int64)
    one_n = np.full(1, chunk, np.int64)
    n_g = ZERO
    i_next = ZERO
    u_next = 0.0
    while True:
        n_new, i_next, u_next = generate_chain(
            rng, one_pix, one_start, one_n, i_next, u_next, rates.sig_pp, rates.tof_s, rates.bg_pp,
            rates.period_s, pulse.kind, pulse.rms_s, pulse.irf_cdf, pulse.irf_t0_s, pulse.irf_bin_s,
            gen.sync[n_g:], gen.t[n_g:], gen.origin[n_g:], gen.item[n_g:])
        n_g += n_new
        if i_next >= 1:
            return gen, n_g
        gen = _grow(gen, n_g, 2 * gen.sync.size)


@njit(cache=True, nogil=True, inline="always")
def _detect(rng, b, sync_end, stop_count, dbuf, saved, fx, det, gate, period_s):
    """``detector_kernel`` over the rows ``b`` into ``dbuf``; when an afterpulse cascade overflows
    the first guess of room, the state is put back and it runs again with twice the room. Returns
    (dbuf, rows out, counted)."""
    n_g = b.sync.size
    # the capacity effects._Sequential starts with
    d_need = n_g + np.int64(n_g * 3 * fx.ap_prob / (1.0 - fx.ap_prob)) + det.pend_sync.size + 64
    _copy_state(saved, det)
    while True:
        dbuf = _grow(dbuf, ZERO, d_need)
        n_d, got = detector_kernel(
            rng, b.sync, b.t, b.origin, b.item, period_s, fx.dead_s, fx.ap_prob, fx.ap_tau_s, det,
            sync_end, stop_count, gate.res_s, gate.range_bins, gate.win_lo, gate.win_hi,
            dbuf.sync, dbuf.t, dbuf.origin, dbuf.item)
        if n_d >= 0:
            return dbuf, n_d, got
        _copy_state(det, saved)
        d_need = 2 * dbuf.sync.size


@njit(cache=True, nogil=True, inline="always")
def _gate_cut(b, need, gate):
    """(rows up to and including the one that brings the count to ``need``, or all; count)."""
    got = 0
    for q in range(b.t.size):
        if _counted(b.t[q], gate.res_s, gate.range_bins, gate.win_lo, gate.win_hi):
            got += 1
            if got >= need:
                return q + 1, got
    return b.t.size, got


@njit(cache=True, nogil=True, inline="always")
def _append(out, n_out, b, n_b, gate):
    """Append the first ``n_b`` rows of ``b`` to ``out``; returns (out, n_out, rows recorded)."""
    out = _grow(out, n_out, n_out + n_b)
    recorded = 0
    for q in range(n_b):
        out.sync[n_out] = b.sync[q]
        out.t[n_out] = b.t[q]
        out.origin[n_out] = b.origin[q]
        if np.int64(b.t[q] / gate.res_s) < gate.range_bins:
            recorded += 1
        n_out += 1
    return out, n_out, recorded


@njit(cache=True, nogil=True, inline="always")
def _dwell_pixel(rng, p, s, out, n_out, bufs, dwell, rates, pulse, fx, det, gate):
    """One pixel of ``dwell_run`` from sync ``s``, appended to ``out``: generation in chunks sized
    from the rate seen so far (an exponential gap running past a chunk's end is dropped and the
    process resumes at the chunk's end: exact, since gaps are memoryless), jitter, detector, count
    gate. ``bufs`` (generation rows, detector rows, saved detector state) are scratch reused from
    pixel to pixel. Returns (syncs taken, rows recorded, out, n_out, bufs)."""
    gen, dbuf, saved = bufs
    gated = dwell.n_target > 0
    done = 0          # syncs generated so far
    counted = 0
    reached = -1
    rate = rates.lam[p]     # counted detections per sync, refined as we go
    recorded = 0
    while done < dwell.limit and (not gated or counted < dwell.n_target):
        need = dwell.n_target - counted
        chunk = _chunk_syncs(gated, need, rate, dwell.limit - done, dwell.limit)
        s0 = s + done
        gen, n_g = _generate(rng, p, s0, chunk, gen, rates, pulse)
        b = _take(gen, n_g)
        sort_within_sync(b.sync, b.t, b.origin, b.item)
        if fx.jitter_rms_s > 0.0:
            jitter_kernel(rng, b.t, fx.jitter_rms_s, rates.period_s)
            sort_within_sync(b.sync, b.t, b.origin, b.item)
        if fx.sequential:
            dbuf, n_b, got = _detect(rng, b, s0 + chunk, need if gated else 0, dbuf, saved, fx, det,
                                     gate, rates.period_s)
            b = _take(dbuf, n_b)
        elif gated:
            n_b, got = _gate_cut(b, need, gate)
        else:
            n_b, got = n_g, 0
        if gated and got >= need:
            reached = b.sync[n_b - 1]
        out, n_out, rec = _append(out, n_out, b, n_b, gate)
        recorded += rec
        counted += got
        done += chunk
        if gated and counted < dwell.n_target:
            rate = max(counted / done, 0.5 * rate) if counted else rate / 4
    n = reached - s + 1 if reached >= 0 else dwell.limit
    return n, recorded, out, n_out, (gen, dbuf, saved)


@njit(cache=True, nogil=True)
def dwell_run(rng, pix, dwell, rates, pulse, fx, det, gate, starts, n_syncs, counts):
    """Dwells on a list of pixels one after another, as a scanner holding the mirror on each: the
    whole per-pixel pipeline (generation, jitter, detector, count gate) in one call, so a scan
    line costs one call instead of one per pixel. Each pixel gets exactly the random draws a call
    for that pixel alone would take, in the same order, so a run equals its pixels one by one.

    pix (n,) int64 pixel indices into the ``rates`` tables, -1 for a pixel off the scene (nothing
    returns; it takes ``dwell.off_syncs``). ``dwell`` (:class:`Dwell`): ``settle`` syncs pass
    before every pixel but the first (which starts at ``start_sync``). Fixed dwell (``n_target``
    0): each pixel takes ``limit`` syncs. Count-gated: each pixel runs until the detection that
    brings its count (detections recorded inside the ``gate``, :class:`Gate`) to ``n_target``, or
    ``limit`` syncs; the next pixel starts at the sync after.

    Effects (:class:`Effects`): jitter, and the sequential detector on the ``det`` state arrays
    (:class:`DetState`), which carry over from call to call. The run stops early after the first
    pixel that ends (plus the settle after it) at or after virtual time ``stop_s``, so a fault due
    then fires at that pixel, and after the pixel that brings its detections plus one marker per
    pixel to ``max_records``.

    Writes per pixel ``starts`` (first sync), ``n_syncs`` and ``counts`` (detections the tagger
    records); returns (pixels done, sync, t, origin) of the detections, sorted by (sync, t).
    """
    out = _grow(_no_rows(), ZERO, dwell.capacity)
    # scratch reused from pixel to pixel: generated rows, detector rows, the saved detector state
    bufs = (_grow(_no_rows(), ZERO, np.int64(4096)), _no_rows(),
            DetState(np.empty(3, np.int64), np.empty(1, np.float64),
                     np.empty(det.pend_sync.size, np.int64), np.empty(det.pend_sync.size, np.float64),
                     np.empty(det.pend_sync.size, np.int32)))
    n_out = ZERO
    s = dwell.start_sync
    done_pixels = 0
    for j in range(pix.size):
        if j > 0:
            s += dwell.settle
        starts[j] = s
        p = pix[j]
        if p < 0:
            n_syncs[j] = dwell.off_syncs
            counts[j] = 0
        else:
            start_at_kernel(det.state_i, det.pend_sync, det.pend_t, det.pend_item, s)
            n_syncs[j], counts[j], out, n_out, bufs = _dwell_pixel(
                rng, p, s, out, n_out, bufs, dwell, rates, pulse, fx, det, gate)
        s += n_syncs[j]
        done_pixels = j + 1
        if (s + dwell.settle) * rates.period_s >= dwell.stop_s or n_out + done_pixels >= dwell.max_records:
            break
    return done_pixels, out.sync[:n_out], out.t[:n_out], out.origin[:n_out]
