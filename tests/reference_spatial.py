"""Plain NumPy references of the spatial estimator's kernels (recon.estimators.spatial_kernels), one pixel or one
whole-array step at a time, written to be read. Compared in tests/test_recon_spatial.py."""

from __future__ import annotations

import math

import numpy as np


def window_shifts(times, offsets, start, stop, width, max_photons):
    """Per pixel: the first max_photons in-window detections as sorted shifts (bins)."""
    out = []
    for p in range(offsets.size - 1):
        t = times[offsets[p]:offsets[p + 1]]
        t = t[(t >= start) & (t < stop)]
        if max_photons >= 0:
            t = t[:max_photons]
        out.append(np.sort((t - start) / width - 0.5))
    return out


def window_counts(lists, h, w, radius, width, n_coarse):
    """(h w) x n_coarse: the window's detections in coarse bins 0..k, as recon.estimators.spatial_kernels.window_counts."""
    out = np.zeros((h * w, n_coarse), np.int64)
    for p in range(h * w):
        r0, c0 = divmod(p, w)
        for r in range(max(0, r0 - radius), min(h, r0 + radius + 1)):
            for c in range(max(0, c0 - radius), min(w, c0 + radius + 1)):
                k = np.clip(((lists[r * w + c] + 0.5) * (1.0 / width)).astype(np.int64), 0, n_coarse - 1)
                out[p] += np.cumsum(np.bincount(k, minlength=n_coarse))
    return out


def censor_fit(lists, h, w, radius, tau, s_min, sigma, n_bins, em_iters):
    """(mu, k, bg, n, kept) per pixel, as recon.estimators.spatial_kernels.censor_fit."""
    npix = h * w
    mu = np.full(npix, np.nan)
    k = np.zeros(npix)
    bg = np.zeros(npix)
    n_used = np.zeros(npix, np.int64)
    n_kept = np.zeros(npix, np.int64)
    for p in range(npix):
        x = lists[p]
        n = x.size
        n_used[p] = n
        bg[p] = n / n_bins
        if n == 0:
            continue
        r0, c0 = divmod(p, w)
        others = np.concatenate([lists[r * w + c] for r in range(max(0, r0 - radius), min(h, r0 + radius + 1))
                                 for c in range(max(0, c0 - radius), min(w, c0 + radius + 1))])
        support = np.array([np.sum(np.abs(others - t) <= tau) - 1 for t in x])
        kept = x[support >= s_min[p]]
        n_kept[p] = kept.size
        if kept.size == 0:
            continue
        reach = 2.5 * sigma
        dens = np.array([np.sum(np.abs(kept - t) <= reach) for t in kept])
        seed = kept[int(np.argmax(dens))]
        cluster = kept[np.abs(kept - seed) <= reach]
        m = cluster.mean()
        pi = min(0.999, max(cluster.size / n, 1e-3))
        ks = float(cluster.size)
        for _ in range(em_iters):
            a = pi * np.exp(-0.5 * ((x - m) / sigma) ** 2) / (math.sqrt(2 * math.pi) * sigma)
            r = a / (a + (1 - pi) / n_bins)
            if r.sum() <= 1e-9:
                break
            m = float(np.sum(r * x) / r.sum())
            pi = min(0.999, max(r.sum() / n, 1e-3))
            ks = float(r.sum())
        mu[p] = m
        k[p] = ks
        bg[p] = max(0.0, n - ks) / n_bins
    return mu, k, bg, n_used, n_kept


def local_mean(f, wt, radius):
    h, w = f.shape
    out = np.full((h, w), np.nan)
    for r in range(h):
        for c in range(w):
            ww = wt[max(0, r - radius):r + radius + 1, max(0, c - radius):c + radius + 1]
            ff = f[max(0, r - radius):r + radius + 1, max(0, c - radius):c + radius + 1]
            ww = np.where(ww > 0, ww, 0.0)
            if ww.sum() > 0:
                out[r, c] = np.sum(ww * ff) / ww.sum()
    return out


def _grad(z):
    gx = np.zeros_like(z)
    gy = np.zeros_like(z)
    gx[:, :-1] = z[:, 1:] - z[:, :-1]
    gy[:-1, :] = z[1:, :] - z[:-1, :]
    return gx, gy


def _div(px, py):
    """Minus the adjoint of _grad."""
    d = np.zeros_like(px)
    d[:, :-1] += px[:, :-1]
    d[:, 1:] -= px[:, :-1]
    d[:-1, :] += py[:-1, :]
    d[1:, :] -= py[:-1, :]
    return d


def tv_pdhg(f, wt, lam, z0, iters):
    """Chambolle-Pock for min sum wt (z - f)^2 / 2 + lam TV(z), whole arrays per step."""
    step = 1 / math.sqrt(8)
    z = z0.copy()
    zbar = z.copy()
    px = np.zeros_like(z)
    py = np.zeros_like(z)
    for _ in range(iters):
        gx, gy = _grad(zbar)
        ax, ay = px + step * gx, py + step * gy
        nrm = np.sqrt(ax ** 2 + ay ** 2)
        sc = np.where(nrm <= lam, 1.0, lam / np.maximum(nrm, 1e-300))
        px, py = ax * sc, ay * sc
        old = z
        a = step * wt
        z = (old + step * _div(px, py) + a * f) / (1 + a)
        zbar = 2 * z - old
    return z


def tv_objective(z, f, wt, lam):
    gx, gy = _grad(z)
    return float(np.sum(wt * (z - f) ** 2) / 2 + lam * np.sum(np.sqrt(gx ** 2 + gy ** 2)))
