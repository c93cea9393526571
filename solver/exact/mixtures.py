"""Gaussian mixtures in exponent form, Σ_j exp(−xᵀA_jx − B_jᵀx − C_j), as the exact filters hold them.

Moments and normalisers (:func:`mixture_moments`, :func:`log_sum_exp`, and in plain floats for
n = 1 :func:`scalar_mixture`, Yau–Hu's chunk of one row), a prior's exponents
(:func:`mixture_terms`, :func:`exponent_terms`), and the Yau–Jia filter's error control: the
cubature points, the product with exp(quadratic), splitting a component in three along its widest
axis, and merging the cheapest pair by Runnalls' bound (:func:`merge_to`).
"""

from __future__ import annotations

import math

import numpy as np

from ..spec_tables import GaussianPrior, mixture_weights
from .riccati import gaussian_to_terms

# the three-component split of N(0, 1) (weights and offsets of DeMars, Bishop & Jah (2013), width
# chosen so that mean and variance are kept exactly)
SPLIT_WEIGHTS = np.array([0.2252246249, 0.5495507502, 0.2252246249])
SPLIT_OFFSETS = np.array([-1.0575154615, 0.0, 1.0575154615])
SPLIT_WIDTH = math.sqrt(1.0 - float(SPLIT_WEIGHTS @ SPLIT_OFFSETS**2))


def log_sum_exp(values, axis=-1):
    """log Σ exp along ``axis`` (finite values; scipy's logsumexp costs ~10x more per call)."""
    top = np.max(values, axis=axis, keepdims=True)
    return (top + np.log(np.exp(values - top).sum(axis=axis, keepdims=True))).squeeze(axis)


def mixture_moments(logw, means, covs):
    """Mean and covariance of Σ w_i N(means_i, covs_i), w ∝ e^{logw}; leading axes batched."""
    w = np.exp(logw - log_sum_exp(logw)[..., None])
    mean = np.einsum("...i,...ij->...j", w, means)
    dev = means - mean[..., None, :]
    cov = np.einsum("...i,...ijk->...jk", w, covs) + np.einsum("...i,...ij,...ik->...jk", w, dev, dev)
    return mean, 0.5 * (cov + np.swapaxes(cov, -1, -2))


def mixture_terms(prior):
    """Exponents (A, B, C) of a Gaussian or mixture prior's components (zero weights dropped)."""
    if isinstance(prior, GaussianPrior):
        weights, means, covs = [1.0], [prior.mean], [prior.cov]
    else:
        weights, means, covs = prior.weights, prior.means, prior.covs
    scaled = mixture_weights(weights)  # the largest first: [1e308, 1e308] -> [0.5, 0.5], as the engine
    terms = [gaussian_to_terms(mu, P, w)
             for w, mu, P in zip(scaled, means, covs, strict=True) if w > 0]
    return (np.stack([t.A for t in terms]), np.stack([t.B for t in terms]), np.array([t.C for t in terms]))


def scalar_mixture(covs, half_log_dets, Bs, Cs, slopes, logc):
    """(log mass, mean, variance) of σ = e^{F}Σ_j exp(−A_jx² − B_jx − C_j), n = 1, in plain floats.

    Component j, term t: log mass ½log(2πp_j) + ½p_j(B_j − s_t)² − C_j + log c_t, mean −p_j(B_j − s_t).
    """
    if half_log_dets is None:
        half_log_dets = [0.5 * math.log(2 * math.pi * p) for p in covs]
    logs, means, variances = [], [], []
    for p, hl, b, c in zip(covs, half_log_dets, Bs, Cs, strict=True):
        for s, lc in zip(slopes, logc, strict=True):
            dev = b - s
            logs.append(hl + 0.5 * p * dev * dev - c + lc)
            means.append(-p * dev)
            variances.append(p)
    if len(logs) == 1:
        return logs[0], means[0], variances[0]
    top = max(logs)
    weights = [math.exp(v - top) for v in logs]
    total = math.fsum(weights)
    mean = math.fsum(w * m for w, m in zip(weights, means, strict=True)) / total
    var = math.fsum(w * (p + (m - mean) ** 2)
                    for w, p, m in zip(weights, variances, means, strict=True)) / total
    return top + math.log(total), mean, var


def exponent_terms(means, covs, logw):
    """Exponent (A, B, C) of w·N(m, P) for stacks: A = ½P⁻¹, B = −P⁻¹m, C = ½mᵀP⁻¹m + ½log det 2πP − log w."""
    n = means.shape[-1]
    chol = np.linalg.cholesky(covs)
    P_inv = np.linalg.inv(covs)
    P_inv = 0.5 * (P_inv + np.swapaxes(P_inv, -1, -2))
    log_det = 2.0 * np.log(np.diagonal(chol, axis1=-2, axis2=-1)).sum(-1) + n * math.log(2 * math.pi)
    Pm = (P_inv @ means[..., None])[..., 0]
    return 0.5 * P_inv, -Pm, 0.5 * (means * Pm).sum(-1) + 0.5 * log_det - logw


def cubature_points(means, covs) -> np.ndarray:
    """The 2n points m ± √n·√λ_k u_k of each component N(m, P) (P = U diag(λ) Uᵀ), equally weighted:
    the third-degree cubature of the Yau–Jia filter's expectations.  Returns (J, 2n, n)."""
    n = means.shape[-1]
    lam, U = np.linalg.eigh(covs)
    axes = np.swapaxes(math.sqrt(n) * np.sqrt(np.clip(lam, 0.0, None))[:, None, :] * U, 1, 2)
    return np.concatenate([means[:, None] + axes, means[:, None] - axes], axis=1)


def times_exp_quadratic(A, B, C, at, covs, s0, g, S):
    """Multiply each component exp(−xᵀAx − Bᵀx − C) by exp(s0 + gᵀ(x − at) + ½(x − at)ᵀS(x − at)).

    Where the product would not be integrable (P⁻¹ − S not positive definite: a wide component and
    a convex factor) S is damped to θS with θ = 0.9/λ_max(PS) (counted in ``clipped``).
    """
    S = 0.5 * (S + np.swapaxes(S, -1, -2))
    try:  # λ_max(PS) < 0.9 iff P⁻¹ − S/0.9 = 2A − S/0.9 > 0: no damping (the common case)
        np.linalg.cholesky(2.0 * A - S / 0.9)
    except np.linalg.LinAlgError:
        top = np.linalg.eigvals(covs @ S).real.max(-1)  # λ_max(PS): P⁻¹ − θS > 0 iff θλ_max < 1
        theta = np.where(top > 0.9, 0.9 / np.where(top > 0.9, top, 1.0), 1.0)
        S = theta[:, None, None] * S
    else:
        theta = np.ones(len(S))
    Sm = (S @ at[..., None])[..., 0]
    A2 = A - 0.5 * S
    B2 = B - (g - Sm)
    C2 = C - (s0 - (g * at).sum(-1) + 0.5 * (at * Sm).sum(-1))
    return A2, B2, C2, int((theta < 1.0).sum())


def split_all(means, covs, logw):
    """Every component split in three along its widest axis (the prior's first refinement)."""
    lam, U = np.linalg.eigh(covs)
    u = U[:, :, -1] * np.sqrt(lam[:, -1])[:, None]
    child = covs - (1.0 - SPLIT_WIDTH**2) * np.einsum("ja,jb->jab", u, u)
    m = (means[:, None, :] + SPLIT_OFFSETS[None, :, None] * u[:, None, :]).reshape(-1, means.shape[1])
    P = np.repeat(child, 3, axis=0)
    w = (logw[:, None] + np.log(SPLIT_WEIGHTS)[None, :]).reshape(-1)
    return m, P, w


def pair_costs(means, covs, w, ld, i, j):
    """Runnalls' bound ½[(w_i+w_j) log det P_ij − w_i log det P_i − w_j log det P_j] of merging the
    pairs (i, j) into one Gaussian with the pair's weight, mean and covariance; returns (cost, P_ij)."""
    wi, wj = w[i], w[j]
    tot = wi + wj
    d = means[i] - means[j]
    Pij = (wi[:, None, None] * covs[i] + wj[:, None, None] * covs[j]) / tot[:, None, None] \
        + (wi * wj / tot**2)[:, None, None] * np.einsum("pa,pb->pab", d, d)
    return 0.5 * (tot * np.linalg.slogdet(Pij)[1] - wi * ld[i] - wj * ld[j]), Pij


def merge_to(means, covs, logw, cap: int):
    """Merge the cheapest pair (Runnalls' bound), moments kept, until at most ``cap`` components
    are left: the costs of all pairs once, then only the merged component's row per merge."""
    J = len(logw)
    if J <= max(cap, 1):
        return means, covs, logw
    top = logw.max()
    w, means, covs = np.exp(logw - top), means.copy(), covs.copy()
    ld = np.linalg.slogdet(covs)[1]
    cost = np.full((J, J), np.inf)
    i, j = np.triu_indices(J, 1)
    cost[i, j] = pair_costs(means, covs, w, ld, i, j)[0]
    alive = np.ones(J, bool)
    for _ in range(J - max(cap, 1)):
        a, b = divmod(int(np.argmin(cost)), J)
        tot = w[a] + w[b]
        d = means[a] - means[b]
        covs[a] = (w[a] * covs[a] + w[b] * covs[b]) / tot + (w[a] * w[b] / tot**2) * np.outer(d, d)
        means[a], w[a] = (w[a] * means[a] + w[b] * means[b]) / tot, tot
        P = covs[a]
        ld[a] = np.linalg.slogdet(P)[1]
        alive[b] = False
        cost[b, :] = cost[:, b] = np.inf
        others = np.flatnonzero(alive)
        others = others[others != a]
        row = pair_costs(means, covs, w, ld, others, np.full(len(others), a))[0]
        cost[np.minimum(others, a), np.maximum(others, a)] = row
    return means[alive], covs[alive], np.log(w[alive]) + top
