"""The Beneš model dx = tanh(x) dt + dv observed through h = x (R = 0.5), its simulation, and a
forward–backward point-mass smoother on a fine uniform grid for continuous increments (the robust flow:
the finite-difference generator L* of the Fokker–Planck equation less the potential ½h²/R − hẏ/R,
ẏ = Δy/τ, by expm_multiply over each gap; backwards its transpose) or discrete readings z = x + N(0, R)
(L* over the gap, then the likelihood); written without the package (tests/solver/exact/
test_yau_hu_smoother.py)."""

from __future__ import annotations

import math

import numpy as np

R, M0, P0 = 0.5, 0.5, 0.5
BENES = {"name": "benes", "state": ["x"], "drift": ["tanh(x)"], "observation": ["x"], "diffusion": [[1.0]],
         "observation_noise": [[R]], "initial": {"kind": "gaussian", "mean": [M0], "cov": [[P0]]},
         "domain": {"radius": 10.0}, "discretization": {"dt": 0.02, "basis": 32}}


def simulate(taus, seed, discrete=False, missing=0.05):
    """Rows over the gaps ``taus`` (Euler–Maruyama in substeps of at most 1e-3): increments Δy or
    readings z; a share ``missing`` of them NaN."""
    rng = np.random.default_rng(seed)
    x, out = rng.normal(M0, math.sqrt(P0)), np.empty(len(taus))
    for k, tau in enumerate(taus):
        n = max(1, int(tau / 1e-3))
        h, acc = tau / n, 0.0
        for _ in range(n):
            acc += x * h + rng.normal(0, math.sqrt(R * h))
            x += math.tanh(x) * h + rng.normal(0, math.sqrt(h))
        out[k] = x + rng.normal(0, math.sqrt(R)) if discrete else acc
    out[rng.random(len(taus)) < missing] = np.nan
    return out


def point_mass_smoother(rows, taus, discrete=False, cells=3200, radius=14.0):
    """(smoothed mean, smoothed variance) per row (a NaN row: no observation)."""
    from scipy.sparse import diags
    from scipy.sparse.linalg import expm_multiply

    x = np.linspace(-radius, radius, cells + 1)[1:-1]
    h, f, size = x[1] - x[0], np.tanh(x), (cells - 1, cells - 1)
    L = (diags([0.5 / h**2, -1.0 / h**2, 0.5 / h**2], [-1, 0, 1], shape=size)
         - diags([-f[:-1] / (2 * h), f[1:] / (2 * h)], [-1, 1], shape=size)).tocsc()
    p = np.exp(-0.5 * (x - M0) ** 2 / P0)
    p /= p.sum()
    K = len(rows)
    filtered, generators, likes = np.empty((K, len(x))), [], np.ones((K, len(x)))
    for k in range(K):
        if discrete:
            G = L
            if not np.isnan(rows[k]):
                likes[k] = np.exp(-0.5 * (rows[k] - x) ** 2 / R)
        else:
            V = 0.0 * x if np.isnan(rows[k]) else 0.5 * x * x / R - x * rows[k] / taus[k] / R
            G = (L - diags(V)).tocsc()
        generators.append(G)
        p = expm_multiply(G * taus[k], p) * likes[k]
        p /= p.sum()
        filtered[k] = p
    beta, smoothed = np.ones(len(x)), np.empty_like(filtered)
    for k in range(K - 1, -1, -1):
        s = filtered[k] * beta
        smoothed[k] = s / s.sum()
        beta = expm_multiply(generators[k].T.tocsc() * taus[k], likes[k] * beta)
        beta /= beta.max()
    mean = smoothed @ x
    return mean, smoothed @ (x * x) - mean**2
