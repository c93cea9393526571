"""The smoother tests' independent references (tests/solver/engine/test_smoother.py,
tests/solver/exact/test_kalman_smoother.py): a scalar Kalman filter + Rauch–Tung–Striebel smoother and
the OU sample it is checked on, written without the package."""

from __future__ import annotations

import math

import numpy as np

THETA, A, R, DT = 0.5, 0.7, 0.5, 0.01  # OU: dx = −θx dt + √a dv, dy = x dt + √R dw


def rts_sampled(dy, m0, P0, theta=THETA, a=A, r=R, taus=None, H=1.0):
    """Kalman filter and RTS smoother of x_k = φ x_(k−1) + N(0, q), dy_k = H x_k τ + N(0, r τ) (a NaN row:
    no update), from N(m0, P0) at time 0 (independent of the package)."""
    K = len(dy)
    taus = np.full(K, DT) if taus is None else taus
    H, r = np.broadcast_to(H, K), np.broadcast_to(r, K)  # per row where given so
    mf, Pf, mp, Pp = (np.empty(K) for _ in range(4))
    m, P = m0, P0
    for k in range(K):
        phi = math.exp(-theta * taus[k])
        q = a * (1 - phi * phi) / (2 * theta)
        m, P = phi * m, phi * phi * P + q
        mp[k], Pp[k] = m, P
        if not np.isnan(dy[k]):
            Hk = H[k] * taus[k]
            S = Hk * P * Hk + r[k] * taus[k]
            gain = P * Hk / S
            m, P = m + gain * (dy[k] - Hk * m), (1 - gain * Hk) * P
        mf[k], Pf[k] = m, P
    ms, Ps = mf.copy(), Pf.copy()
    for k in range(K - 2, -1, -1):
        phi = math.exp(-theta * taus[k + 1])
        J = Pf[k] * phi / Pp[k + 1]
        ms[k] = mf[k] + J * (ms[k + 1] - mp[k + 1])
        Ps[k] = Pf[k] + J * J * (Ps[k + 1] - Pp[k + 1])
    return mf, Pf, ms, Ps


def sample_ou(K, seed, m0=1.0, P0=0.5):
    rng = np.random.default_rng(seed)
    phi = math.exp(-THETA * DT)
    q = A * (1 - phi * phi) / (2 * THETA)
    x = rng.normal(m0, math.sqrt(P0))
    xs, dy = np.empty(K), np.empty(K)
    for k in range(K):
        x = phi * x + rng.normal(0, math.sqrt(q))
        xs[k], dy[k] = x, x * DT + rng.normal(0, math.sqrt(R * DT))
    return xs, dy
