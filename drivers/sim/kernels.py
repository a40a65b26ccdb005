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

