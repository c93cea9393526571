"""The Yau–Niu filter's row for independent one-coordinate blocks, compiled by numba (solver/qmc/blocks.py).

Each kernel does for all B blocks what :class:`~solver.qmc.blocks.SingleBlocks`'s numpy path does with
about thirty whole-array passes: the Kolmogorov step with its moment matching (:func:`kolmogorov`), the
observation factors shifted by each block's maximum (:func:`log_factors`), the normalisation and
coverage (:func:`normalise`) and the moments (:func:`moments`).  Arrays are (B, N), one contiguous row
per block, so that one block's passes stay in the cache.  The exponential between the second and third
is numpy's (its SIMD exp is ~8× a scalar loop's here).  Results agree with the numpy path to rounding
(tests/solver/qmc/test_singles_kernels.py).  Importing this module imports numba.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from ..jit import writable_cache_dir

CACHE_DIR = writable_cache_dir()
_previous_cache_dir = numba.config.CACHE_DIR
if CACHE_DIR is not None:
    numba.config.CACHE_DIR = str(CACHE_DIR)
kernel = numba.njit(cache=CACHE_DIR is not None, nogil=True, error_model="numpy")
# sums in any order (SIMD reductions) and fused multiply-adds: rounding only, never NaN/inf assumptions
sums = numba.njit(cache=CACHE_DIR is not None, nogil=True, error_model="numpy",
                  fastmath={"reassoc", "contract"})

CONTINUOUS, GAUSSIAN, STUDENT = 0, 1, 2  # the measurement's kind (solver/measurement.py)


@kernel
def kolmogorov(XT, FT, W, Q, perm, offset, sd, var_add, tau):
    """The Euler kernel N(x + f(x)τ, aτ) of every block b on the row XT[b] (moved in place), the noise of
    point i being Q[(perm[i] + offset[b]) mod N] × sd[b], then each block mapped affinely onto the
    kernel's mean Σ w (x + fτ) and variance Var_w(x + fτ) + var_add[b] under its weights W[b]
    (SingleBlocks.kolmogorov)."""
    B, N = XT.shape
    for b in range(B):
        x, f, w = XT[b], FT[b], W[b]
        mean = 0.0
        for i in range(N):
            d = x[i] + f[i] * tau
            x[i] = d
            mean += w[i] * d
        var = 0.0
        for i in range(N):
            e = x[i] - mean
            var += w[i] * (e * e)
        var += var_add[b]
        here = 0.0
        s, k = sd[b], offset[b]
        for i in range(N):
            j = perm[i] + k
            if j >= N:
                j -= N
            x[i] += s * Q[j]
            here += w[i] * x[i]
        spread = 0.0
        for i in range(N):
            e = x[i] - here
            spread += w[i] * (e * e)
        ratio = math.sqrt(var / spread) if spread > 1e-300 else 1.0  # match_moments' rule: only shifted
        for i in range(N):
            x[i] = (x[i] - here) * ratio + mean


@kernel
def log_factors(logW, HT, comp, scale, y, observed, kind, tau, constant, quadratic, dof, top):
    """logW[b] += log e(h) − top[b] in place for each observed block b, top[b] the maximum of logW[b] +
    log e(h) (not finite: a NaN, or −inf at every point — the caller's zero likelihood, logW[b] then
    left unshifted); h its sensor's values HT[comp[b]] scaled by scale[b] and the unit-noise measurement
    on y[b]: ``kind`` CONTINUOUS y h − ½h²τ, GAUSSIAN y h − ½h² + constant, STUDENT −½(ν + 1)
    log(1 + max(q − 2yh + h², 0)/ν) + constant (solver/measurement.py log_factors)."""
    B, N = logW.shape
    for b in range(B):
        if not observed[b]:
            continue
        h, lw = HT[comp[b]], logW[b]
        s, yb, c = scale[b], y[b], constant[b]
        best, nan = -np.inf, False
        for i in range(N):
            hs = h[i] * s
            if kind == CONTINUOUS:
                v = yb * hs - 0.5 * hs * hs * tau
            elif kind == GAUSSIAN:
                v = yb * hs - 0.5 * hs * hs + c
            else:
                q = max(quadratic[b] - 2.0 * yb * hs + hs * hs, 0.0) / dof
                v = -0.5 * (dof + 1.0) * math.log1p(q) + c
            v += lw[i]
            lw[i] = v
            if v > best:
                best = v
            elif v != v:
                nan = True
        top[b] = np.nan if nan else best
        if -np.inf < best < np.inf and not nan:
            for i in range(N):
                lw[i] -= best


@kernel
def normalise(E, observed, logW, sums, coverage):
    """For each observed block, from E[b] = exp(logW[b]) (logW shifted by its maximum): logW[b] −=
    log Σ E, sums[b] = Σ E and the coverage (Σ E)²/Σ E² (1/Σ w²)."""
    B, N = E.shape
    for b in range(B):
        if not observed[b]:
            continue
        e, lw = E[b], logW[b]
        s, s2 = 0.0, 0.0
        for i in range(N):
            s += e[i]
            s2 += e[i] * e[i]
        log_s = math.log(s)
        for i in range(N):
            lw[i] -= log_s
        sums[b] = s
        coverage[b] = s * s / s2


@kernel
def moments(XT, W, mean, var):
    """The weighted mean and variance of each block's coordinate XT[b] under its weights W[b]."""
    B, N = XT.shape
    for b in range(B):
        w, x = W[b], XT[b]
        m = 0.0
        for i in range(N):
            m += w[i] * x[i]
        v = 0.0
        for i in range(N):
            d = x[i] - m
            v += w[i] * (d * d)
        mean[b], var[b] = m, v


@kernel
def gather(Z, offset, GT):
    """GT = Z[(i + offset) mod N]ᵀ: a bank's set (N, n) from ``offset`` on, as coordinate rows (n, N),
    point by point (Z's rows are the set's points, in a random order)."""
    N, n = Z.shape
    for i in range(N):
        p = i + offset
        if p >= N:
            p -= N
        for m in range(n):
            GT[m, i] = Z[p, m]


@sums
def euler(XT, FT, Z, offset, root, sqrt_tau, tau, GT, DT, MT):
    """The coupled blocks' Euler kernel before its moment matching (solver/qmc/coupled.py), coordinates
    and the drift as rows (n, N): GT = Z[(i + offset) mod N]ᵀ (the noise in the points' order: a bank's
    set taken from ``offset`` on, solver/qmc/bank.py), DT = (X + Fτ)ᵀ and MT = DT + √τ·rootᵀGT."""
    n, N = XT.shape
    gather(Z, offset, GT)
    for m in range(n):
        x, f, d = XT[m], FT[m], DT[m]
        for i in range(N):
            d[i] = x[i] + f[i] * tau
    for j in range(n):
        d, g = DT[j], MT[j]
        for i in range(N):
            g[i] = d[i]
        for m in range(n):
            a = sqrt_tau * root[m, j]
            if a == 0.0:
                continue
            z = GT[m]
            for i in range(N):
                g[i] += z[i] * a


@sums
def block_moments(XT, owner, W, mean, cov):
    """The weighted mean and within-block covariance of the points, coordinates as rows XT (n, N),
    coordinate j under its block's weights W[owner[j]]: two passes, the mean first (as
    cloud.weighted_moments), zero across blocks."""
    n, N = XT.shape
    for j in range(n):
        w, x = W[owner[j]], XT[j]
        m = 0.0
        for i in range(N):
            m += w[i] * x[i]
        mean[j] = m
    for j in range(n):
        w, x, mj = W[owner[j]], XT[j], mean[j]
        for k in range(j + 1):
            if owner[k] != owner[j]:
                cov[j, k] = cov[k, j] = 0.0
                continue
            y, mk = XT[k], mean[k]
            c = 0.0
            for i in range(N):
                c += w[i] * (x[i] - mj) * (y[i] - mk)
            cov[j, k] = cov[k, j] = c


@sums
def affine(MT, here, A, mean, out):
    """outᵀ = mean + (M − here) A, coordinates as rows (n, N): the moment matching's map
    (cloud.match_moments), A block-diagonal over the blocks."""
    n, N = MT.shape
    for j in range(n):
        o = out[j]
        for i in range(N):
            o[i] = mean[j]
        for m in range(n):
            a = A[m, j]
            if a == 0.0:
                continue
            x, h = MT[m], here[m]
            for i in range(N):
                o[i] += (x[i] - h) * a


@kernel
def block_log_factor(HT, cols, R_inv, y, penalty, constant, hr, half, out):
    """A coupled block's Gaussian log factor at each point p (solver/measurement.py ``log_factors`` for
    one row whose points are its own; each element the same operations in the same order): out[p] =
    Σ_j y_j (hR)_j − penalty·½Σ_j (hR)_j h_j + constant, h = HT[cols, p] the observed components of the
    row's sensor values as rows HT (m, P), hR = h R_oo⁻¹ (``penalty``: τ for increments, 1 for
    discrete readings; ``hr`` (|o|, P) and ``half`` (P,) buffers).  Pass by pass over contiguous rows."""
    o, P = cols.shape[0], HT.shape[1]
    for j in range(o):
        r = hr[j]
        h, a = HT[cols[0]], R_inv[0, j]
        for p in range(P):
            r[p] = h[p] * a
        for i in range(1, o):
            h, a = HT[cols[i]], R_inv[i, j]
            for p in range(P):
                r[p] += h[p] * a
    for j in range(o):
        h, r, c = HT[cols[j]], hr[j], y[j]
        if j == 0:
            for p in range(P):
                half[p] = r[p] * h[p]
                out[p] = c * r[p]
        else:
            for p in range(P):
                half[p] += r[p] * h[p]
                out[p] += c * r[p]
    for p in range(P):
        out[p] = out[p] - penalty * (0.5 * half[p]) + constant


@kernel
def systematic(w, u0, picks):
    """Systematic resampling by the weights w: picks[i] the first j with Σ_{l≤j} w_l ≥ (u0 + i)/N · Σw
    (numpy's cumsum and searchsorted of the restart, in one merge pass)."""
    N = w.shape[0]
    cdf = np.empty(N)
    total = 0.0
    for i in range(N):
        total += w[i]
        cdf[i] = total
    j = 0
    for i in range(N):
        u = (u0 + i) / N * total
        while j < N and cdf[j] < u:
            j += 1
        picks[i] = min(j, N - 1)


@sums
def shape_sums(XT, w, mean, B, third, fourth):
    """The weighted third and fourth moments of the whitened cloud z = (x − mean) B along each axis
    (cloud.multiscale_bandwidth's), coordinates as rows XT (d, N): pass by pass over contiguous rows."""
    d, N = XT.shape
    z = np.empty(N)
    for k in range(d):
        for i in range(N):
            z[i] = 0.0
        for j in range(d):
            x, m, b = XT[j], mean[j], B[j, k]
            for i in range(N):
                z[i] += (x[i] - m) * b
        t, f = 0.0, 0.0
        for i in range(N):
            z2 = z[i] * z[i]
            t += w[i] * (z2 * z[i])
            f += w[i] * (z2 * z2)
        third[k], fourth[k] = t, f


@sums
def spread(XT, picks, shrink, mean, Z, offset, M, GT, YT):
    """The restart's points as rows YT (d, N): y_i = shrink·x_{picks[i]} + (1 − shrink)·mean + Σ_m
    Z[(i + offset) mod N, m] M[m] (a bank's set from ``offset`` on, gathered into GT (n, N) as
    :func:`euler` does; M the signed order and the kernel's h·cov^{1/2} folded together, zero rows
    skipped)."""
    d, N = YT.shape
    n = Z.shape[1]
    for j in range(d):
        x, y, b = XT[j], YT[j], (1.0 - shrink) * mean[j]
        for i in range(N):
            y[i] = shrink * x[picks[i]] + b
    used = False
    for m in range(n):
        for j in range(d):
            used = used or M[m, j] != 0.0
    if not used:
        return
    gather(Z, offset, GT)
    for j in range(d):
        y = YT[j]
        for m in range(n):
            a = M[m, j]
            if a == 0.0:
                continue
            g = GT[m]
            for i in range(N):
                y[i] += g[i] * a


numba.config.CACHE_DIR = _previous_cache_dir
