"""The smoother tests' independent references (tests/solver/engine/test_smoother.py,
tests/solver/exact/test_kalman_smoother.py, test_kalman_bucy_backward.py): a scalar Kalman filter +
Rauch–Tung–Striebel smoother and the OU sample it is checked on; RTS on the exact discrete model of each
gap of the continuous linear model (the augmented Kalman–Bucy equations by solve_ivp); a forward–backward
point-mass smoother for the bimodal sensor h = x²/2 with discrete readings and its sample; written
without the package."""

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


def rts_exact_gaps(F, f0, a, H, h0, R_, m0, P0, rows, taus, skip):
    """Filtered and RTS-smoothed moments of dx = (Fx + f0)dt + dv (cov a), dy = (Hx + h0)dt + dw (cov R_)
    with Δy_k spread linearly over τ_k (rows where ``skip`` or all-NaN: prediction only; NaN components:
    not observed), from N(m0, P0), independent of the package: per gap the Kalman–Bucy equations of the
    augmented state (x(t), x_(k−1)) by solve_ivp (rtol 1e-12) give the joint Gaussian of (x_(k−1), x_k)
    given the rows up to k, then RTS in its joint form (x_(k−1) | x_k is Markov given later rows)."""
    from scipy.integrate import solve_ivp

    n, K = len(m0), len(rows)
    Fz = np.block([[F, np.zeros((n, n))], [np.zeros((n, 2 * n))]])
    fz = np.concatenate([f0, np.zeros(n)])
    az = np.block([[a, np.zeros((n, n))], [np.zeros((n, 2 * n))]])
    mf, Pf, mb, Pb, Cb = (np.empty((K, n)), np.empty((K, n, n)), np.empty((K, n)), np.empty((K, n, n)),
                          np.empty((K, n, n)))
    m, P = np.asarray(m0, float), np.asarray(P0, float)
    for k in range(K):
        tau, obs = taus[k], ~np.isnan(rows[k]) & ~skip[k]
        Hz = np.hstack([H[obs], np.zeros((obs.sum(), n))])
        Rinv = np.linalg.inv(R_[np.ix_(obs, obs)])
        ydot, h0o = rows[k, obs] / tau, h0[obs]

        def rhs(_t, y, Hz=Hz, Rinv=Rinv, ydot=ydot, h0o=h0o):
            mz, Pz = y[:2 * n], y[2 * n:].reshape(2 * n, 2 * n)
            gain = Pz @ Hz.T @ Rinv
            dm = Fz @ mz + fz + gain @ (ydot - Hz @ mz - h0o)
            dP = Fz @ Pz + Pz @ Fz.T + az - gain @ Hz @ Pz
            return np.concatenate([dm, dP.ravel()])

        y0 = np.concatenate([m, m, np.block([[P, P], [P, P]]).ravel()])
        y = solve_ivp(rhs, (0.0, tau), y0, method="DOP853", rtol=1e-12, atol=1e-14).y[:, -1]
        mz, Pz = y[:2 * n], y[2 * n:].reshape(2 * n, 2 * n)
        Pz = 0.5 * (Pz + Pz.T)
        m, P = mz[:n], Pz[:n, :n]
        mf[k], Pf[k], mb[k], Pb[k], Cb[k] = m, P, mz[n:], Pz[n:, n:], Pz[n:, :n]
    ms, Ps = mf.copy(), Pf.copy()
    for k in range(K - 1, 0, -1):  # x_(k−1) | x_k, rows ≤ k: mean mb + J (x_k − m_k), J = C P_k⁻¹
        J = np.linalg.solve(Pf[k], Cb[k].T).T
        ms[k - 1] = mb[k] + J @ (ms[k] - mf[k])
        Ps[k - 1] = Pb[k] + J @ (Ps[k] - Pf[k]) @ J.T
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


def point_mass_smoother(rows, taus, cells=400, radius=6.0, r=0.1, m0=0.3, P0=1.0, full=False):
    """Forward–backward smoother on a uniform grid: the finite-difference Fokker–Planck generator L of
    dx = −x/2 dt + dw (p_t = ½p'' + (x p/2)'), its flow by expm_multiply over each gap, Lᵀ backwards; the
    likelihood N(z; x²/2, r) at the grid points (a NaN row: none).  Returns (filtered mean, smoothed mean,
    smoothed variance) per row; ``full``: also the grid and the smoothed masses at its points
    (K, cells − 1)."""
    from scipy.sparse import diags
    from scipy.sparse.linalg import expm_multiply

    x = np.linspace(-radius, radius, cells + 1)[1:-1]
    h = x[1] - x[0]
    drift = -0.5 * x
    # ½p'' − (f p)' by central differences (Dirichlet: p = 0 outside)
    L = (diags([0.5 / h**2, -1.0 / h**2, 0.5 / h**2], [-1, 0, 1], shape=(len(x), len(x)))
         - diags([-drift[:-1] / (2 * h), drift[1:] / (2 * h)], [-1, 1], shape=(len(x), len(x)))).tocsc()
    LT = L.T.tocsc()
    p = np.exp(-0.5 * (x - m0) ** 2 / P0)
    p /= p.sum()
    K = len(rows)
    filtered, likes = np.empty((K, len(x))), np.ones((K, len(x)))
    for k in range(K):
        p = expm_multiply(L * taus[k], p)
        if not np.isnan(rows[k]):
            likes[k] = np.exp(-0.5 * (rows[k] - x * x / 2) ** 2 / r)
        p = p * likes[k]
        p /= p.sum()
        filtered[k] = p
    beta = np.ones(len(x))
    smoothed = np.empty_like(filtered)
    for k in range(K - 1, -1, -1):
        s = filtered[k] * beta
        smoothed[k] = s / s.sum()
        beta = expm_multiply(LT * taus[k], likes[k] * beta)
        beta /= beta.max()
    fmean = filtered @ x
    mean = smoothed @ x
    var = smoothed @ (x * x) - mean**2
    if full:
        return fmean, mean, var, x, smoothed
    return fmean, mean, var


def simulate_bimodal(taus, seed, missing=0.0):
    rng = np.random.default_rng(seed)
    x = rng.normal(0.3, 1.0)
    rows = np.empty(len(taus))
    for k, tau in enumerate(taus):
        phi = math.exp(-0.5 * tau)
        x = phi * x + rng.normal(0, math.sqrt(1 - phi * phi))
        rows[k] = x * x / 2 + rng.normal(0, math.sqrt(0.1))
    rows[rng.random(len(taus)) < missing] = np.nan
    return rows
