"""Rauch–Tung–Striebel of a scalar linear model sampled exactly (the truth of the smoother on a ball that
follows the state: tests/solver/engine/test_follow_smoother.py, tests/service/cli/test_cli_smooth.py),
and the random walk with a trend whose state travels beyond its ball (``TREND``, ``[domain] follow``).
Written without the package."""

from __future__ import annotations

import numpy as np

TREND = {"name": "random walk with trend", "state": ["x"], "drift": ["1.0"], "observation": ["x"],
         "method": "yau-yau", "initial": {"kind": "gaussian", "mean": [0.0], "cov": [[1.0]]},
         "domain": {"radius": 6.0, "follow": True}, "discretization": {"dt": 0.01, "basis": 48}}


def rts_linear(dy, taus, m0, P0, phi, shift, q, r=1.0):
    """Kalman filter and RTS smoother of x_k = φ_k x_(k−1) + s_k + N(0, q_k), dy_k = x_k τ_k + N(0, rτ_k) (a
    NaN row: no update; φ, s, q per row or one for all), from N(m0, P0): (filtered mean, var, smoothed
    mean, var)."""
    n = len(dy)
    phi, shift, q = (np.broadcast_to(v, n) for v in (phi, shift, q))
    mf, Pf, mp, Pp = (np.empty(n) for _ in range(4))
    m, P = m0, P0
    for k in range(n):
        m, P = phi[k] * m + shift[k], phi[k] ** 2 * P + q[k]
        mp[k], Pp[k] = m, P
        if not np.isnan(dy[k]):
            gain = P * taus[k] / (taus[k] ** 2 * P + r * taus[k])
            m, P = m + gain * (dy[k] - taus[k] * m), (1 - gain * taus[k]) * P
        mf[k], Pf[k] = m, P
    ms, Ps = mf.copy(), Pf.copy()
    for k in range(n - 2, -1, -1):
        J = Pf[k] * phi[k + 1] / Pp[k + 1]
        ms[k] = mf[k] + J * (ms[k + 1] - mp[k + 1])
        Ps[k] = Pf[k] + J * J * (Ps[k + 1] - Pp[k + 1])
    return mf, Pf, ms, Ps


def rts_trend(dy, taus):
    """The random walk with trend: φ = 1, s = bτ, q = aτ (b = a = 1), from N(0, 1)."""
    return rts_linear(dy, taus, 0.0, 1.0, 1.0, taus, taus)
