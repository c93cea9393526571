"""The exact filter of a linear model dx = Fx dt + dv (E dv dvᵀ = a dt) sampled at given gaps, observed
by continuous increments dy = Hx τ + w (w ~ N(0, Rτ)) or discrete readings z = Hx + v (v ~ N(0, R)),
NaN marking a missing component (only the observed rows of H and R update), a row in ``skip`` only
predicting: the truth of the yau-niu tests (tests/solver/qmc/, tests/service/sessions/).  Written
without the package: the transition over τ by Van Loan's matrix exponential (scipy)."""

from __future__ import annotations

import numpy as np
from scipy.linalg import expm


def transition(F: np.ndarray, a: np.ndarray, tau: float) -> tuple[np.ndarray, np.ndarray]:
    """Φ = e^{Fτ} and Q = ∫₀^τ e^{Fs} a e^{Fᵀs} ds (Van Loan, 1978)."""
    n = len(F)
    block = np.zeros((2 * n, 2 * n))
    block[:n, :n], block[:n, n:], block[n:, n:] = -F, a, F.T
    E = expm(block * tau)
    phi = E[n:, n:].T
    return phi, phi @ E[:n, n:]


def linear_model_matrices(model) -> tuple[np.ndarray, np.ndarray]:
    """F and H of a compiled model whose drift and sensor are linear without offset (read off its
    numeric f and h at the unit vectors)."""
    n = model.n
    X = np.eye(n)
    zero = np.zeros((1, n))
    return model.f(X).T - model.f(zero)[0][:, None], model.h(X).T - model.h(zero)[0][:, None]


def kalman(F, a, H, R, m0, P0, rows, gaps, discrete: bool = False, skip=()):
    """Means (K, n), variances (K, n) and exact innovations' d² (K,; NaN: no update) per row."""
    F, a, H, R = (np.asarray(v, float) for v in (F, a, H, R))
    mean, cov = np.asarray(m0, float), np.asarray(P0, float)
    means, variances, d2 = [], [], []
    for k, (row, tau) in enumerate(zip(np.asarray(rows, float), gaps, strict=True)):
        phi, Q = transition(F, a, float(tau))
        mean, cov = phi @ mean, phi @ cov @ phi.T + Q
        seen = ~np.isnan(row)
        score = np.nan
        if seen.any() and k not in skip:
            kappa = 1.0 if discrete else float(tau)
            Ho = H[seen] * kappa
            S = Ho @ cov @ Ho.T + R[np.ix_(seen, seen)] * kappa
            v = row[seen] - Ho @ mean
            score = float(v @ np.linalg.solve(S, v))
            gain = np.linalg.solve(S, Ho @ cov).T
            mean, cov = mean + gain @ v, cov - gain @ Ho @ cov
        means.append(mean)
        variances.append(np.diag(cov).copy())
        d2.append(score)
    return np.array(means), np.array(variances), np.array(d2)
