"""Plain NumPy reference implementations of the recon estimators: dense matrices, one pixel at a
time, written to be read rather than to be fast. The kernels in ``recon.kernels`` are compared
against these in tests/test_recon_kernels.py, and ``spdepth bench recon`` (acq/commands/bench/recon.py) times them side by side.

Every function takes one pixel's histogram ``y`` (length M, counts per bin) and the dense matrices
built by ``dense_s`` from a :class:`recon.model.PulseKernel`.
"""

from __future__ import annotations

import numpy as np


def dense_s(kern) -> np.ndarray:
    """S (M x M, unit-area columns): S[k, i] = g[k - i] for the truncated kernel table."""
    m = kern.n_bins
    k = np.arange(m)[:, None]
    i = np.arange(m)[None, :]
    idx = k - i + kern.off
    ok = (idx >= 0) & (idx < kern.g.size)
    return np.where(ok, kern.g[np.clip(idx, 0, kern.g.size - 1)], 0.0)


def dense_logs(kern) -> np.ndarray:
    """log S (M x M) of the log-matched filter, from the kernel's log table."""
    m = kern.n_bins
    d = np.arange(m)[:, None] - np.arange(m)[None, :]
    return kern.logg[d + m - 1]


def histogram(bins: np.ndarray, m: int) -> np.ndarray:
    return np.bincount(np.asarray(bins, dtype=np.int64), minlength=m).astype(np.float64)


def lmf(y: np.ndarray, log_s: np.ndarray) -> int:
    """Eq. (11) as in the published code: argmax over shifts of sum_k y_k log S[k, i]."""
    return int(np.argmax(log_s.T @ y))


def uos(y: np.ndarray, a_mat: np.ndarray, delta: float = 1e-4, ite_max: int = 10):
    """Algorithm 1, a direct port of the published MATLAB loop (COSAMP_UOS.m): A = [S/max, 1],
    proxy A^T v, support = best proxy index + previous support + background column, pinv
    least squares, keep the largest depth coefficient and the background, T_0, stop on
    ||a_prev - a||^2 < delta * max(1, ||a||^2). Returns (x_hat, iterations).

    The stopping test is the published one where ||a|| <= 1 (the paper's photon counts) and
    relative above it, as in our kernel: an absolute test never stops on high-count pixels."""
    n = a_mat.shape[1]
    a = np.zeros(n)
    v = y.copy()
    i = 0
    for i in range(1, ite_max + 1):
        a_prev = a
        x_proxy = a_mat.T @ v
        supp_now = int(np.argmax(x_proxy[:n - 1]))
        supp_prev = np.flatnonzero(a[:n - 1])
        supp_total = np.union1d(np.union1d([supp_now], supp_prev), [n - 1]).astype(int)
        # MATLAB pinv tolerance: max(size(A)) * norm(A) * eps
        sub = a_mat[:, supp_total]
        b0 = np.linalg.pinv(sub, rcond=max(sub.shape) * np.finfo(float).eps) @ y
        b = np.zeros(n)
        b[supp_total] = b0
        clipped = bool(np.any(b0 < 0))
        prune_ind = int(np.argmax(b[:n - 1]))
        a = np.zeros(n)
        a[prune_ind] = b[prune_ind]
        a[n - 1] = b[n - 1]
        a[a < 0] = 0
        diff_norm = float(np.sum((a_prev - a) ** 2))
        v = y - a_mat @ a
        if diff_norm < delta * max(1.0, float(np.sum(a ** 2))):
            break
    return (refit_nonneg(y, a_mat, a) if clipped else a), i


def refit_nonneg(y: np.ndarray, a_mat: np.ndarray, a: np.ndarray) -> np.ndarray:
    """Our one deviation after the loop: when the last least squares had a negative coefficient
    (which T_0 zeroed), refit on the kept columns, dropping the most negative until none is."""
    cols = list(np.flatnonzero(a))
    while cols:
        sub = a_mat[:, cols]
        sol = np.linalg.pinv(sub, rcond=max(sub.shape) * np.finfo(float).eps) @ y
        worst = int(np.argmin(sol))
        if sol[worst] > 0:
            out = np.zeros_like(a)
            out[cols] = sol
            return out
        del cols[worst]
    return np.zeros_like(a)


def poisson_profile(y: np.ndarray, s_mat: np.ndarray, iters: int = 4000):
    """For every column i of S, max over a, B >= 0 of sum_k y_k log(a S_ki + B) - a sum_k S_ki - B M
    (eq. 9 negated, constants dropped), by EM on all columns at once (monotone, slow, independent
    of the kernels' Newton solver). Returns (loglik per column, a, B)."""
    m = s_mat.shape[0]
    nz = np.flatnonzero(y)
    yk = y[nz]
    sk = s_mat[nz, :]                       # (photon bins, shifts)
    c = s_mat.sum(axis=0)
    n = yk.sum()
    a = np.full(s_mat.shape[1], 0.5 * n) / np.maximum(c, 1e-300)
    b = np.full(s_mat.shape[1], 0.5 * n / m)
    for _ in range(iters):
        lam = a * sk + b
        with np.errstate(invalid="ignore", divide="ignore"):
            resp = np.where(lam > 0, a * sk / lam, 0.0)
        sig = (yk[:, None] * resp).sum(axis=0)
        a = sig / np.maximum(c, 1e-300)
        b = (n - sig) / m
    lam = a * sk + b
    with np.errstate(divide="ignore"):
        ll = (yk[:, None] * np.log(lam)).sum(axis=0) - a * c - b * m
    return ll, a, b


def ml_integer(y: np.ndarray, s_mat: np.ndarray):
    """Global ML over integer shifts: (best shift, its log-likelihood, all log-likelihoods)."""
    ll, a, b = poisson_profile(y, s_mat)
    i = int(np.argmax(ll))
    return i, ll[i], ll


def s_at(kern, shift: float) -> np.ndarray:
    """Column of S for a fractional shift (pulse centroid at bin ``shift``), from the fine table."""
    from spdepth.recon.model import FINE_STEPS
    m = kern.n_bins
    x = np.arange(m) - shift + kern.off
    j = np.rint(x * FINE_STEPS).astype(np.int64)
    ok = (j >= 0) & (j < kern.fine.size)
    return np.where(ok, kern.fine[np.clip(j, 0, kern.fine.size - 1)], 0.0)


def ml_refined(y: np.ndarray, kern, s_mat: np.ndarray):
    """Global integer search, then the best of the fine shifts within one bin of it, then a
    parabola through the fine neighbours (what the ml kernel does, in dense form)."""
    from spdepth.recon.model import FINE_STEPS
    i, _, _ = ml_integer(y, s_mat)
    qs = np.arange(-FINE_STEPS, FINE_STEPS + 1)
    qs = qs[(i + qs / FINE_STEPS >= 0) & (i + qs / FINE_STEPS <= kern.n_bins - 1)]
    cols = np.stack([s_at(kern, i + q / FINE_STEPS) for q in qs], axis=1)
    ll, _, _ = poisson_profile(y, cols)
    j = int(np.argmax(ll))
    frac = 0.0
    if 0 < j < len(qs) - 1:
        den = ll[j - 1] - 2 * ll[j] + ll[j + 1]
        if den < 0:
            frac = float(np.clip(0.5 * (ll[j - 1] - ll[j + 1]) / den, -0.5, 0.5))
    return i + (qs[j] + frac) / FINE_STEPS


def photons_by_pixel(pixel, times, n_pix):
    """``PhotonStore.from_pixel_indices``'s grouping by a stable argsort: (times grouped by pixel,
    detection order kept within a pixel; offsets)."""
    pixel = np.asarray(pixel, np.int64)
    order = np.argsort(pixel, kind="stable")
    offsets = np.zeros(n_pix + 1, np.int64)
    np.cumsum(np.bincount(pixel, minlength=n_pix), out=offsets[1:])
    return np.asarray(times, np.float64)[order], offsets


def mat_cells(path, var: str):
    """A level-5 .mat cell array of detection-time vectors as (times, offsets), pixels row-major
    and detection order kept, by scipy's loadmat: the reference of the NumPy cell walk
    (acq.readers.mat.read_cells_fast)."""
    import scipy.io

    cells = scipy.io.loadmat(path)[var]
    flat = [np.asarray(c, dtype=np.float64).ravel() for c in cells.ravel(order="C")]
    offsets = np.zeros(len(flat) + 1, np.int64)
    offsets[1:] = np.cumsum([f.size for f in flat])
    times = np.concatenate(flat) if flat else np.zeros(0)
    return times, offsets


# ------------------------------------------------------------------------------------------------
# several surfaces per pixel (recon.estimators.surfaces_kernels), densely: the whole histogram and S each step

def _multi_gain(y, lam, col, csum, newton=12):
    """(gain, amplitude) of adding the column ``col`` (column sum csum) to the rate lam (dense)."""
    nz = (y > 0) & (col > 0)
    yy, cc, ll = y[nz], col[nz], lam[nz]
    if csum <= 0 or np.sum(yy * cc / ll) - csum <= 0:
        return 0.0, 0.0
    a = max(yy.sum() / csum, 1e-6)
    for _ in range(newton):
        q = cc / (ll + a * cc)
        f1, f2 = np.sum(yy * q) - csum, -np.sum(yy * q * q)
        if f2 >= 0:
            break
        # Newton on 1 / phi(a) = 1 / csum, phi = f' + csum: the same root (see recon.estimators.surfaces_kernels.add_gain)
        na = a - f1 / f2 * (f1 + csum) / csum
        na = 0.5 * a if na <= 0 else na
        done = abs(na - a) <= 1e-7 * a
        a = na
        if done:
            break
    return float(np.sum(yy * np.log1p(a * cc / ll)) - a * csum), float(a)


def _em(y, s_mat, colsum, shifts, amps, b, bg_floor, sweeps, tol=1e-7):
    """EM of the amplitudes (in place) and background at fixed shifts, stopping when nothing changes
    by more than tol (relative); returns the background."""
    m = y.size
    for _ in range(sweeps):
        lam = b + s_mat[:, shifts] @ np.asarray(amps, float)
        r = np.where(y > 0, y / lam, 0.0)
        new = [amps[i] * (s_mat[:, shifts[i]] @ r) / colsum[shifts[i]] for i in range(len(shifts))]
        nb = max(b * r.sum() / m, bg_floor)
        change = max([abs(n - a) / max(n, 1e-300) for n, a in zip(new, amps)] + [abs(nb - b) / nb])
        amps[:] = new
        b = nb
        if change < tol:
            break
    return b


def multi_return(y, kern, s_mat, kmax, sep_bins, gain_min, cand_step, step0, em_sweeps=12, screen=4):
    """The K-surface greedy Poisson pursuit of recon.estimators.surfaces_kernels on one histogram y (length M):
    returns (shifts (sorted), amplitudes, gains, background)."""
    m = y.size
    colsum = s_mat.sum(axis=0)
    ntot = y.sum()
    if ntot == 0:
        return np.array([]), np.array([]), np.array([]), 0.0
    bg_floor = 1e-9 * ntot / m
    bg = ntot / m
    dpk = int(np.argmax(kern.g))
    cands = []
    for k in np.flatnonzero(y):
        j = int(np.clip(k + kern.off - dpk, 0, m - 1))
        if not cands or j - cands[-1] >= cand_step:
            cands.append(j)
    shifts, amps, gains = [], [], []

    def rate(sh, am, b):
        return b + s_mat[:, sh] @ np.asarray(am, float) if sh else np.full(m, b)

    def free(j, skip):
        return all(abs(j - s) >= sep_bins for r, s in enumerate(shifts) if r != skip)

    def refine(j, best, a, lam, step, skip):
        while step >= 1:
            moved = True
            while moved:
                moved = False
                for jj in (j - step, j + step):
                    if 0 <= jj < m and free(jj, skip):
                        gn, an = _multi_gain(y, lam, s_mat[:, jj], colsum[jj])
                        if gn > best:
                            best, a, j, moved = gn, an, jj, True
                            break
            step //= 2
        return j, best, a

    def em(b):
        return _em(y, s_mat, colsum, shifts, amps, b, bg_floor, em_sweeps)

    lam = rate(shifts, amps, bg)
    while len(shifts) < kmax:
        # screen: d0^2 / (2 c2), the gain to second order in the amplitude; the best `screen` exactly
        scored = []
        for j in cands:
            if not free(j, -1):
                continue
            q = np.where(y > 0, s_mat[:, j] / lam, 0.0)
            d0, c2 = np.sum(y * q) - colsum[j], np.sum(y * q * q)
            if d0 > 0 and c2 > 0:
                scored.append((d0 * d0 / (2 * c2), j))
        top = [j for _, j in sorted(scored, key=lambda t: -t[0])[:screen]]
        best, bj, ba = 0.0, -1, 0.0
        for j in top:
            gn, an = _multi_gain(y, lam, s_mat[:, j], colsum[j])
            if gn > best:
                best, bj, ba = gn, j, an
        if bj < 0:
            break
        bj, best, ba = refine(bj, best, ba, lam, step0, -1)
        if not best > gain_min:
            break
        shifts.append(bj)
        amps.append(ba)
        gains.append(best)
        bg = em(bg)
        lam = rate(shifts, amps, bg)
        if len(shifts) > 1:
            for r in range(len(shifts)):
                other = [a if i != r else 0.0 for i, a in enumerate(amps)]
                lam_r = rate(shifts, other, bg)
                g0, a0 = _multi_gain(y, lam_r, s_mat[:, shifts[r]], colsum[shifts[r]])
                shifts[r], _, amps[r] = refine(shifts[r], g0, a0, lam_r, 2, r)
            bg = em(bg)
            lam = rate(shifts, amps, bg)
    order = np.argsort(shifts, kind="stable")
    return np.asarray(shifts, float)[order], np.asarray(amps)[order], np.asarray(gains)[order], float(bg)


def neighbour_surfaces(ys, h, w, kern, s_mat, radius, shift_in, gain_in, strong_nats, pool_nats, tau, sep,
                       kmax, kpool, cand_step, step0):
    """recon.estimators.surfaces_kernels.neighbour_surfaces densely: ys (P, M) histograms; returns per pixel
    (shifts, amplitudes, sources) like the kernel (sorted by shift)."""
    m = ys.shape[1]
    colsum = s_mat.sum(axis=0)
    dpk = int(np.argmax(kern.g))
    out = []
    for p in range(h * w):
        y = ys[p]
        if y.sum() == 0:
            out.append((np.array([]), np.array([]), np.array([], int)))
            continue
        y0, x0 = divmod(p, w)
        pool = sum(ys[yy * w + xx] for yy in range(max(0, y0 - radius), min(h, y0 + radius + 1))
                   for xx in range(max(0, x0 - radius), min(w, x0 + radius + 1)))
        ps, pa, _, _ = multi_return(pool, kern, s_mat, kpool, sep, pool_nats, cand_step, step0)
        cands = [(int(v), 0) for v, gn in zip(shift_in[p], gain_in[p]) if np.isfinite(v) and gn > strong_nats]
        cands += [(int(v), 1) for v in ps[np.argsort(-pa, kind="stable")]]
        live = [True] * len(cands)
        bg_floor = 1e-9 * y.sum() / m
        bg = y.sum() / m
        shifts, amps, srcs = [], [], []
        lam = np.full(m, bg)
        aligned = [k + kern.off - dpk for k in np.flatnonzero(y)]
        while len(shifts) < kmax:
            best, bj, ba, bc = 0.0, -1, 0.0, -1
            for c, (j0, _) in enumerate(cands):
                if not live[c]:
                    continue
                for j in aligned:
                    if 0 <= j < m and abs(j - j0) <= tau and all(abs(j - s) >= sep for s in shifts):
                        gn, an = _multi_gain(y, lam, s_mat[:, j], colsum[j])
                        if gn > best:
                            best, bj, ba, bc = gn, j, an, c
            if bc < 0:
                break
            # pattern search, as refine in multi_return
            step = step0
            while step >= 1:
                moved = True
                while moved:
                    moved = False
                    for jj in (bj - step, bj + step):
                        if 0 <= jj < m and all(abs(jj - s) >= sep for s in shifts):
                            gn, an = _multi_gain(y, lam, s_mat[:, jj], colsum[jj])
                            if gn > best:
                                best, ba, bj, moved = gn, an, jj, True
                                break
                step //= 2
            for d in range(len(cands)):
                if live[d] and d != bc and abs(cands[d][0] - cands[bc][0]) < sep:
                    live[d] = False
            shifts.append(bj)
            amps.append(ba)
            srcs.append(cands[bc][1])
            live[bc] = False
            bg = _em(y, s_mat, colsum, shifts, amps, bg, bg_floor, 12)
            lam = bg + s_mat[:, shifts] @ np.asarray(amps)
        o = np.argsort(shifts, kind="stable")
        out.append((np.asarray(shifts, float)[o], np.asarray(amps)[o], np.asarray(srcs, int)[o]))
    return out


def smooth_surfaces(shift, sig, h, w, radius, tau):
    """recon.estimators.surfaces_kernels.smooth_surfaces' shifts: signal-weighted mean of the surfaces within tau
    in each surface's neighbourhood."""
    out = shift.copy()
    for p in range(h * w):
        y0, x0 = divmod(p, w)
        nb = [yy * w + xx for yy in range(max(0, y0 - radius), min(h, y0 + radius + 1))
              for xx in range(max(0, x0 - radius), min(w, x0 + radius + 1))]
        for r in range(shift.shape[1]):
            s = shift[p, r]
            if np.isnan(s):
                continue
            v, wt = shift[nb].ravel(), sig[nb].ravel()
            ok = np.isfinite(v) & (np.abs(v - s) <= tau) & (wt > 0)
            if ok.any():
                out[p, r] = np.sum(wt[ok] * v[ok]) / wt[ok].sum()
    return out
