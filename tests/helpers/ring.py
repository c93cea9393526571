"""A bootstrap particle filter of the coupled 4-state ring (tests/solver/qmc/test_yau_niu.py's ring_model,
examples/coupled_ring_4d.toml), written in numpy as independent truth:
dx_i = (−x_i + 0.5 tanh x_{i+1}) dt + dW_i (indices mod 4), dy_i = x_i³ dt + dw_i, x(0) ~ N(0.5, I)."""

from __future__ import annotations

import numpy as np

RING_SUBSTEPS = 4  # Euler–Maruyama steps a row


def ring_bootstrap(rows: np.ndarray, N: int, seed: int, dt: float = 0.01) -> np.ndarray:
    """Means of a bootstrap particle filter of the ring: N particles from the prior at t = 0, moved by
    RING_SUBSTEPS Euler–Maruyama steps a row, weighted by exp(hᵀΔy − ½|h|²dt), systematic resampling
    when the effective sample size falls below N/2."""
    rng = np.random.default_rng(seed)
    K, n = rows.shape
    small = dt / RING_SUBSTEPS
    X = 0.5 + rng.standard_normal((N, n))
    logw = np.zeros(N)
    means = np.empty((K, n))
    for k in range(K):
        for _ in range(RING_SUBSTEPS):
            X += (0.5 * np.tanh(np.roll(X, -1, axis=1)) - X) * small
            X += np.sqrt(small) * rng.standard_normal((N, n))
        h = X**3
        logw += h @ rows[k] - 0.5 * dt * np.einsum("ij,ij->i", h, h)
        w = np.exp(logw - logw.max())
        w /= w.sum()
        means[k] = w @ X
        if 1.0 / (w @ w) < N / 2:
            picks = np.minimum(np.searchsorted(np.cumsum(w), (rng.random() + np.arange(N)) / N), N - 1)
            X, logw = X[picks], np.zeros(N)
    return means
