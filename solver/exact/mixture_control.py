"""The Yau–Jia filter's error control compiled by numba (the second half of solver/exact/mixture_kernels.py).

After a step: σ's components normalised and pruned, and their principal axes (:func:`normalise_axes`);
the rates (:func:`rates`), the split choice, Runnalls' merges and the splits (:func:`control`,
:func:`merge_to`), the exponents, the normalisation and the moments (:func:`finish_control`) — the
numpy path's YauJiaFilter._normalise, _control and _rates, and mixtures.merge_to, to rounding.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from .mixture_kernels import (
    CACHE_DIR,
    FALLBACK,
    LOG_2PI,
    OK,
    cholesky,
    eigh,
    kernel,
    log_sum_exp,
    spd_inverse,
    terms_to_moments,
)

_previous_cache_dir = numba.config.CACHE_DIR
if CACHE_DIR is not None:
    numba.config.CACHE_DIR = str(CACHE_DIR)


@kernel
def normalise_axes(A, B, C, prune, means, covs, logw, C_out, kept, lam, U, points, ws, sigma):
    """σ's components (φ = 0: v's) normalised to ∫σ = 1 (C_out, logw), the components kept by the
    pruning (their indices in ``kept``) and, for those, the principal axes and the sensor's check
    points m ± σ·√λ_k u_k (YauJiaFilter._normalise and the start of _control / _rates).  Returns
    (code, log ∫σ before, number kept)."""
    J, n = B.shape
    if not terms_to_moments(A, B, C, means, covs, logw):
        return FALLBACK, 0.0, 0
    log_mass = log_sum_exp(logw, J)
    if not math.isfinite(log_mass):
        return FALLBACK, 0.0, 0
    top = -np.inf
    for j in range(J):
        C_out[j] = C[j] + log_mass
        logw[j] -= log_mass
        top = max(top, logw[j])
    count = 0
    for j in range(J):
        if logw[j] >= top + prune:
            kept[count] = j
            count += 1
    for i in range(count):
        j = kept[i]
        if eigh(covs[j], lam[i], U[i], ws) != 0:
            return FALLBACK, 0.0, 0
        for k in range(n):
            s = sigma * math.sqrt(max(lam[i, k], 0.0))
            for a in range(n):
                points[i, k, 0, a] = means[j, a] - s * U[i, a, k]
                points[i, k, 1, a] = means[j, a] + s * U[i, a, k]
    return OK, log_mass, count


@kernel
def rates(means, F, h_at, lam, U, whiten, sigma, out):
    """Per component and principal axis, the sensor's departure from its quadratic model at ±σ√λ
    (whitened) times (|h(m)|_R + 1) (YauJiaFilter._rates); inf where not finite."""
    J, n = means.shape
    m = whiten.shape[0]
    axis, diff = np.empty(n), np.empty(m)
    for j in range(J):
        size = 0.0
        for i in range(m):
            t = 0.0
            for l in range(m):
                t += whiten[i, l] * F[j, l]
            size += t * t
        size = math.sqrt(size) + 1.0
        for k in range(n):
            s = sigma * math.sqrt(max(lam[j, k], 0.0))
            for a in range(n):
                axis[a] = s * U[j, a, k]
            err = 0.0
            finite = True
            for side in range(2):
                sign = -1.0 if side == 0 else 1.0
                for i in range(m):
                    lin, quad = 0.0, 0.0
                    for a in range(n):
                        lin += F[j, m + i * n + a] * axis[a]
                        for b in range(n):
                            quad += F[j, m + m * n + (i * n + a) * n + b] * axis[a] * axis[b]
                    diff[i] = h_at[(j * n + k) * 2 + side, i] - (F[j, i] + sign * lin + 0.5 * quad)
                e = 0.0
                for i in range(m):
                    t = 0.0
                    for l in range(m):
                        t += whiten[i, l] * diff[l]
                    e += t * t
                e = math.sqrt(e)
                if not math.isfinite(e):
                    finite = False
                err = max(err, e)
            rate = err * size
            out[j, k] = rate if finite and math.isfinite(rate) else np.inf


@kernel
def lu_log_det(M, work):
    """log |det M| by Gaussian elimination with partial pivoting (numpy's slogdet, to rounding)."""
    n = M.shape[0]
    for i in range(n):
        for j in range(n):
            work[i, j] = M[i, j]
    log_det = 0.0
    for c in range(n):
        p, best = c, abs(work[c, c])
        for r in range(c + 1, n):
            if abs(work[r, c]) > best:
                p, best = r, abs(work[r, c])
        if not best > 0.0:
            return -np.inf
        if p != c:
            for j in range(n):
                t = work[c, j]
                work[c, j] = work[p, j]
                work[p, j] = t
        log_det += math.log(best)
        for r in range(c + 1, n):
            f = work[r, c] / work[c, c]
            for j in range(c, n):
                work[r, j] -= f * work[c, j]
    return log_det


@kernel
def pair_cost(means, covs, w, ld, i, j, P, work):
    """Runnalls' bound of merging components i and j (mixtures.pair_costs), P: the merged covariance."""
    n = means.shape[1]
    wi, wj = w[i], w[j]
    tot = wi + wj
    f = wi * wj / tot**2
    for a in range(n):
        for b in range(n):
            P[a, b] = (wi * covs[i, a, b] + wj * covs[j, a, b]) / tot \
                + f * (means[i, a] - means[j, a]) * (means[i, b] - means[j, b])
    return 0.5 * (tot * lu_log_det(P, work) - wi * ld[i] - wj * ld[j])


@kernel
def merge_to(means, covs, logw, cap):
    """Merge the cheapest pair until at most ``cap`` components are left (mixtures.merge_to); the
    arrays are changed in place, returns the indices of the components left."""
    J, n = means.shape
    if J <= max(cap, 1):
        return np.arange(J)
    top = logw.max()
    w = np.exp(logw - top)
    P, work = np.empty((n, n)), np.empty((n, n))
    ld = np.empty(J)
    for i in range(J):
        ld[i] = lu_log_det(covs[i], work)
    cost = np.full((J, J), np.inf)
    for i in range(J):
        for j in range(i + 1, J):
            cost[i, j] = pair_cost(means, covs, w, ld, i, j, P, work)
    alive = np.ones(J, np.bool_)
    for _ in range(J - max(cap, 1)):
        best, a, b = np.inf, -1, -1
        for i in range(J):
            for j in range(J):
                if a < 0 or cost[i, j] < best:  # the first minimum, as np.argmin
                    best, a, b = cost[i, j], i, j
        tot = w[a] + w[b]
        f = w[a] * w[b] / tot**2
        for x in range(n):
            for y in range(n):
                covs[a, x, y] = (w[a] * covs[a, x, y] + w[b] * covs[b, x, y]) / tot \
                    + f * (means[a, x] - means[b, x]) * (means[a, y] - means[b, y])
        for x in range(n):
            means[a, x] = (w[a] * means[a, x] + w[b] * means[b, x]) / tot
        w[a] = tot
        ld[a] = lu_log_det(covs[a], work)
        alive[b] = False
        for i in range(J):
            cost[b, i] = np.inf
            cost[i, b] = np.inf
        for o in range(J):
            if alive[o] and o != a:
                cost[min(o, a), max(o, a)] = pair_cost(means, covs, w, ld, o, a, P, work)
    left = np.flatnonzero(alive)
    for i in left:
        logw[i] = math.log(w[i]) + top
    return left


@kernel
def exponent_terms(means, covs, logw, A, B, C):
    """Exponent (A, B, C) of w·N(m, P) (mixtures.exponent_terms); False where P is not positive definite."""
    J, n = means.shape
    L, tmp, P_inv = np.empty((n, n)), np.empty((n, n)), np.empty((n, n))
    for j in range(J):
        if not cholesky(covs[j], L):
            return False
        log_det = spd_inverse(L, P_inv, tmp) + n * LOG_2PI
        quad = 0.0
        for a in range(n):
            Pm = 0.0
            for b in range(n):
                A[j, a, b] = 0.5 * P_inv[a, b]
                Pm += P_inv[a, b] * means[j, b]
            B[j, a] = -Pm
            quad += means[j, a] * Pm
        C[j] = 0.5 * quad + 0.5 * log_det - logw[j]
    return True


@kernel
def control(means, covs, logw, rate, lam, U, split_weights, split_offsets, split_width,
            tolerance, budget, max_components):
    """The split choice, the merges that make room and the splits (YauJiaFilter._control after the
    rates) on the kept components; returns (means, covs, logw, splits)."""
    J, n = means.shape
    worst = np.empty(J)
    for j in range(J):
        top = rate[j, 0]
        for k in range(1, n):
            top = max(top, rate[j, k])
        worst[j] = top
    order = np.argsort(-worst)[:budget]
    chosen = order[worst[order] > tolerance]
    k = min(len(chosen), max_components // 3)
    if k and J > k and 3 * k + 1 > max_components:
        k -= 1
    chosen = chosen[:k]
    if k == 0:
        if J > max_components:
            m2, c2, w2 = means.copy(), covs.copy(), logw.copy()
            left = merge_to(m2, c2, w2, max_components)
            return m2[left], c2[left], w2[left], 0
        return means, covs, logw, 0
    split = np.zeros(J, np.bool_)
    split[chosen] = True
    rest = np.flatnonzero(~split)
    m2, c2, w2 = means[rest], covs[rest], logw[rest]
    left = merge_to(m2, c2, w2, max_components - 3 * k)
    R = len(left)
    out_m, out_c, out_w = np.empty((R + 3 * k, n)), np.empty((R + 3 * k, n, n)), np.empty(R + 3 * k)
    for i in range(R):
        out_m[i], out_c[i], out_w[i] = m2[left[i]], c2[left[i]], w2[left[i]]
    u = np.empty(n)
    shrink = 1.0 - split_width**2
    for i in range(k):
        j = chosen[i]
        axis = 0
        for x in range(1, n):
            if rate[j, x] > rate[j, axis]:
                axis = x
        s = math.sqrt(lam[j, axis])
        for x in range(n):
            u[x] = U[j, x, axis] * s
        for t in range(3):
            o = R + 3 * i + t
            out_w[o] = logw[j] + math.log(split_weights[t])
            for x in range(n):
                out_m[o, x] = means[j, x] + split_offsets[t] * u[x]
                for y in range(n):
                    out_c[o, x, y] = covs[j, x, y] - shrink * u[x] * u[y]
    return out_m, out_c, out_w, k


@kernel
def finish_control(means, covs, logw, changed, A, B, C, A_out, B_out, C_out, mean, cov):
    """New exponents where the mixture changed (covariances symmetrised first), the normalisation
    to ∫σ = 1 and σ's mean and covariance.  Returns (code, number of components)."""
    J, n = means.shape
    if changed:
        for j in range(J):
            for x in range(n):
                for y in range(x + 1):
                    t = 0.5 * (covs[j, x, y] + covs[j, y, x])
                    covs[j, x, y] = t
                    covs[j, y, x] = t
        if not exponent_terms(means, covs, logw, A_out, B_out, C_out):
            return FALLBACK, 0
    else:
        A_out[:J] = A
        B_out[:J] = B
        C_out[:J] = C
    log_mass = log_sum_exp(logw, J)
    if not math.isfinite(log_mass):
        return FALLBACK, 0
    for j in range(J):
        C_out[j] += log_mass
        logw[j] -= log_mass
    norm = log_sum_exp(logw, J)
    w = np.empty(J)
    for j in range(J):
        w[j] = math.exp(logw[j] - norm)
    for x in range(n):
        t = 0.0
        for j in range(J):
            t += w[j] * means[j, x]
        mean[x] = t
    for x in range(n):
        for y in range(n):
            t, s = 0.0, 0.0
            for j in range(J):
                t += w[j] * covs[j, x, y]
                s += w[j] * (means[j, x] - mean[x]) * (means[j, y] - mean[y])
            cov[x, y] = t + s
    for x in range(n):
        for y in range(x + 1):
            t = 0.5 * (cov[x, y] + cov[y, x])
            cov[x, y] = t
            cov[y, x] = t
    return OK, J


numba.config.CACHE_DIR = _previous_cache_dir
