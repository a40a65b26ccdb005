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

import numpy as np
from numba import njit

ORIGIN_BACKGROUND = 0
ORIGIN_AFTERPULSE = 250
ORIGIN_MARKER = 251

PULSE_GAUSSIAN = 0
PULSE_TABLE = 1

KIND_PHOTON = 0
KIND_MARKER = 1


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
def detector_kernel(rng, sync, t, origin, item, period_s, dead_s, ap_prob, ap_tau_s,
                    state_i, state_t, pend_sync, pend_t, pend_item, sync_end,
                    stop_count, res_s, range_bins, win_lo, win_hi,
                    out_sync, out_t, out_origin, out_item):
    """The detector as a sequential machine: non-paralysable dead time and afterpulsing.

    Inputs are ideal detections sorted by (sync, t). The detector is blind for ``dead_s`` after
    every detection it registers (0 disables); with probability ``ap_prob`` a registered
    detection releases an afterpulse ``dead_s + Exponential(ap_tau_s)`` later (0 disables), which
    may itself be blocked or afterpulse again.

    State carried between calls (the detector does not know about pixels):
    state_i = [has_last, last_sync, n_pending], state_t = [last_t]; pending afterpulses in
    pend_sync/pend_t/pend_item[:n_pending], sorted. Pending afterpulses at or after ``sync_end``
    stay pending. When ``stop_count`` > 0 the kernel stops right after the registered detection
    that makes ``stop_count`` counted ones (see ``_counted``), so the carried state is exactly the
    state at that detection.

    Returns (n_out, n_counted), or (-1, 0) when the output arrays are too small.
    """
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


@njit(cache=True, nogil=True)
def _copy(dst, src):
    """dst[:src.size] = src as a loop: numba compiles a slice assignment for tens of seconds."""
    for i in range(src.size):
        dst[i] = src[i]


@njit(cache=True, nogil=True)
def _grow(sync, t, origin, item, n_keep, need):
    """Detection arrays (sync, t, origin, item) with room for ``need``: the same ones when they
    have it, else new ones at least twice as long holding the first ``n_keep`` rows."""
    if sync.size >= need:
        return sync, t, origin, item
    cap = max(need, 2 * sync.size)
    s2, t2 = np.empty(cap, np.int64), np.empty(cap, np.float64)
    o2, i2 = np.empty(cap, np.uint8), np.empty(cap, np.int32)
    for q in range(n_keep):
        s2[q] = sync[q]
        t2[q] = t[q]
        o2[q] = origin[q]
        i2[q] = item[q]
    return s2, t2, o2, i2


@njit(cache=True, nogil=True)
def dwell_run(rng, pix, n_target, limit, settle, off_syncs, start_sync, stop_s, max_records,
              sig_pp, tof_s, bg_pp, lam, period_s,
              pulse_kind, rms_s, irf_cdf, irf_t0_s, irf_bin_s,
              jitter_rms_s, sequential, dead_s, ap_prob, ap_tau_s,
              state_i, state_t, pend_sync, pend_t, pend_item,
              res_s, range_bins, win_lo, win_hi, capacity,
              starts, n_syncs, counts):
    """Dwells on a list of pixels one after another, as a scanner holding the mirror on each: the
    whole per-pixel pipeline (generation, jitter, detector, count gate) in one call, so a scan
    line costs one call instead of one per pixel. Each pixel gets exactly the random draws a call
    for that pixel alone would take, in the same order, so a run equals its pixels one by one.

    pix (n,) int64 pixel indices into the rate tables, -1 for a pixel off the scene (nothing
    returns; it takes ``off_syncs``). ``settle`` syncs pass before every pixel but the first
    (which starts at ``start_sync``). Fixed dwell (``n_target`` 0): each pixel takes ``limit``
    syncs. Count-gated: each pixel runs until the detection that brings its count (detections
    recorded, dtime < range_bins, inside [win_lo, win_hi) tagger units) to ``n_target``, or
    ``limit`` syncs; the next pixel starts at the sync after. Generation goes in chunks sized from
    the rate seen so far (an exponential gap running past a chunk's end is dropped, and the
    process resumes at the chunk's end: exact, since gaps are memoryless).

    Effects: ``jitter_rms_s`` > 0 jitters every time; ``sequential`` runs ``detector_kernel``
    (``dead_s``, ``ap_prob``, ``ap_tau_s``) on the detector state arrays, which carry over from
    call to call. The run stops early after the first pixel that ends (plus the settle after it)
    at or after virtual time ``stop_s``, so a fault due then fires at that pixel, and after the
    pixel that brings its detections plus one marker per pixel to ``max_records``.

    Writes per pixel ``starts`` (first sync), ``n_syncs`` and ``counts`` (detections the tagger
    records); returns (pixels done, sync, t, origin) of the detections, sorted by (sync, t).
    ``capacity`` is a first guess of the number of detections (the arrays grow as needed).
    """
    n_pix = pix.size
    # (np.int64(...) around constants: a literal argument would compile one more variant)
    zero = np.int64(0)
    out_sync, out_t, out_origin, out_item = _grow(np.empty(0, np.int64), np.empty(0, np.float64),
                                                  np.empty(0, np.uint8), np.empty(0, np.int32),
                                                  zero, np.int64(capacity))
    n_out = 0
    # one pixel's chunk of ideal detections, and the detector's output
    g_sync, g_t, g_origin, g_item = _grow(np.empty(0, np.int64), np.empty(0, np.float64),
                                          np.empty(0, np.uint8), np.empty(0, np.int32), zero,
                                          np.int64(4096))
    d_sync, d_t, d_origin, d_item = _grow(np.empty(0, np.int64), np.empty(0, np.float64),
                                          np.empty(0, np.uint8), np.empty(0, np.int32), zero, zero)
    saved_i = np.empty(3, np.int64)
    saved_t = np.empty(1, np.float64)
    saved_ps = np.empty(pend_sync.size, np.int64)
    saved_pt = np.empty(pend_sync.size, np.float64)
    saved_pi = np.empty(pend_sync.size, np.int32)
    one_pix = np.zeros(1, np.int64)
    one_start = np.zeros(1, np.int64)
    one_n = np.zeros(1, np.int64)
    s = start_sync
    done_pixels = 0
    for j in range(n_pix):
        if j > 0:
            s += settle
        starts[j] = s
        p = pix[j]
        if p < 0:
            n_syncs[j] = off_syncs
            counts[j] = 0
            s += off_syncs
        else:
            start_at_kernel(state_i, pend_sync, pend_t, pend_item, s)
            one_pix[0] = p
            gated = n_target > 0
            done = 0          # syncs generated so far
            counted = 0
            reached = -1
            rate = lam[p]     # counted detections per sync, refined as we go
            recorded = 0
            while done < limit and (not gated or counted < n_target):
                need = n_target - counted
                if not gated:
                    chunk = limit
                elif rate > 0.0:
                    f = need / rate * 1.25 + 16
                    chunk = limit - done if f >= limit - done else max(np.int64(f), 16)
                else:
                    chunk = limit
                chunk = min(max(chunk, 16) if gated else chunk, limit - done)
                s0 = s + done
                # ideal detections of the chunk (generate_chain resumes where the buffer filled)
                expected = lam[p] * chunk
                g_sync, g_t, g_origin, g_item = _grow(
                    g_sync, g_t, g_origin, g_item, zero,
                    np.int64(expected + 6.0 * np.sqrt(expected) + 64))
                one_start[0] = s0
                one_n[0] = chunk
                n_g = 0
                i_next = zero
                u_next = 0.0
                while True:
                    n_new, i_next, u_next = generate_chain(
                        rng, one_pix, one_start, one_n, i_next, u_next, sig_pp, tof_s, bg_pp,
                        period_s, pulse_kind, rms_s, irf_cdf, irf_t0_s, irf_bin_s,
                        g_sync[n_g:], g_t[n_g:], g_origin[n_g:], g_item[n_g:])
                    n_g += n_new
                    if i_next >= 1:
                        break
                    g_sync, g_t, g_origin, g_item = _grow(g_sync, g_t, g_origin, g_item, n_g,
                                                          2 * g_sync.size)
                b_sync = g_sync[:n_g]
                b_t = g_t[:n_g]
                b_origin = g_origin[:n_g]
                b_item = g_item[:n_g]
                sort_within_sync(b_sync, b_t, b_origin, b_item)
                if jitter_rms_s > 0.0:
                    jitter_kernel(rng, b_t, jitter_rms_s, period_s)
                    sort_within_sync(b_sync, b_t, b_origin, b_item)
                if sequential:
                    # the capacity effects._Sequential starts with
                    d_need = n_g + np.int64(n_g * 3 * ap_prob / (1.0 - ap_prob)) + pend_sync.size + 64
                    _copy(saved_i, state_i)
                    _copy(saved_t, state_t)
                    _copy(saved_ps, pend_sync)
                    _copy(saved_pt, pend_t)
                    _copy(saved_pi, pend_item)
                    while True:
                        d_sync, d_t, d_origin, d_item = _grow(d_sync, d_t, d_origin, d_item, zero,
                                                              d_need)
                        n_d, got = detector_kernel(
                            rng, b_sync, b_t, b_origin, b_item, period_s, dead_s, ap_prob,
                            ap_tau_s, state_i, state_t, pend_sync, pend_t, pend_item, s0 + chunk,
                            need if gated else 0, res_s, range_bins, win_lo, win_hi,
                            d_sync, d_t, d_origin, d_item)
                        if n_d >= 0:
                            break
                        # an afterpulse cascade overflowed the guess: again with room to spare
                        _copy(state_i, saved_i)
                        _copy(state_t, saved_t)
                        _copy(pend_sync, saved_ps)
                        _copy(pend_t, saved_pt)
                        _copy(pend_item, saved_pi)
                        d_need = 2 * d_sync.size
                    b_sync = d_sync[:n_d]
                    b_t = d_t[:n_d]
                    b_origin = d_origin[:n_d]
                    if gated and got >= need:
                        reached = b_sync[n_d - 1]
                    n_b = n_d
                else:
                    n_b = n_g
                    got = 0
                    if gated:
                        for q in range(n_g):
                            if _counted(b_t[q], res_s, range_bins, win_lo, win_hi):
                                got += 1
                                if got >= need:
                                    n_b = q + 1
                                    reached = b_sync[q]
                                    break
                out_sync, out_t, out_origin, out_item = _grow(out_sync, out_t, out_origin,
                                                              out_item, n_out, n_out + n_b)
                for q in range(n_b):
                    out_sync[n_out] = b_sync[q]
                    out_t[n_out] = b_t[q]
                    out_origin[n_out] = b_origin[q]
                    if np.int64(b_t[q] / res_s) < range_bins:
                        recorded += 1
                    n_out += 1
                counted += got
                done += chunk
                if gated and counted < n_target:
                    rate = max(counted / done, 0.5 * rate) if counted else rate / 4
            n_syncs[j] = reached - s + 1 if reached >= 0 else limit
            counts[j] = recorded
            s += n_syncs[j]
        done_pixels = j + 1
        if (s + settle) * period_s >= stop_s or n_out + done_pixels >= max_records:
            break
    return done_pixels, out_sync[:n_out], out_t[:n_out], out_origin[:n_out]
