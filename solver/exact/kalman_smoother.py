"""The Rauch–Tung–Striebel smoother of the Kalman–Bucy filter (solver/exact/kalman_bucy.py), exact where
its forward step is a Fokker–Planck prediction followed by a Kalman update:

* discrete measurements z_k = H x(t_k) + h0 + v_k (continuous dynamics, discrete readings: the
  continuous–discrete Kalman filter), at regular or irregular times, missing or gated rows;
* the time-sampled increment model (``KalmanBucyFilter(model, kind="discrete")``): x_k = Φ x_(k−1) +
  Γf0 + N(0, Q_τ), Δy_k = H x_k τ + h0 τ + N(0, Rτ).

The prediction over each gap τ_k is Van Loan's (Φ, Γf0, Q_τ) of the drift F x + f0 and the diffusion a
(solver/reference/kalman.py), the flow the filter predicts with; the filtered moments are the filter's
own (``run_arrays``).  Backwards from the last row (the filter there):

    J_k = P_(k−1) Φ_kᵀ (P⁻_k)⁻¹,   m^s_(k−1) = m_(k−1) + J_k (m^s_k − m⁻_k),
    P^s_(k−1) = P_(k−1) + J_k (P^s_k − P⁻_k) J_kᵀ,

with m⁻_k = Φ_k m_(k−1) + Γf0, P⁻_k = Φ_k P_(k−1) Φ_kᵀ + Q_k (a gated or missing row is filtered = predicted,
which the recursion takes as it is).

Continuous increments through the robust Kalman–Bucy flow (the default kind) integrate the update over
each gap together with the dynamics, so their smoother is not this recursion but the two-filter form of
solver/exact/kalman_bucy_backward.py (filtered × the adjoint flow's backward message), exact for the
same model.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from ..errors import InputError
from ..filtering import ChunkResult
from ..reference.kalman import van_loan


def smooth_arrays(flt: Any, state: Any, increments: Any, times: Any = None) -> tuple[Any, ChunkResult]:
    """(the filter's state after the chunk, its ChunkResult with the RTS-smoothed mean, cov and mode)."""
    new_state, result = flt.run_arrays(state, increments, times)
    K = len(result)
    if K == 0:
        return new_state, result
    if result.degenerate.any():
        k = int(np.argmax(result.degenerate))
        raise InputError(f"increments[{k}]", f"the filter degenerated at this row ({result.reason})")
    if not (flt.discrete or flt.sampled):
        from .kalman_bucy_backward import smooth_continuous

        return smooth_continuous(flt, state, increments, new_state, result)
    model = flt.model
    F, f0, a = np.asarray(flt.F, float), np.asarray(flt.f0, float), np.asarray(model.a, float)
    gaps = np.diff(np.concatenate([[float(state.t)], np.asarray(result.t, dtype=float)]))
    means = np.concatenate([np.asarray(state.mean, float)[None], result.mean])
    covs = np.concatenate([np.asarray(state.cov, float)[None], result.cov])
    m_s, P_s = result.mean.copy(), result.cov.copy()
    flows: dict[float, tuple] = {}
    for k in range(K - 1, 0, -1):  # row k (index k in result) from row k + 1 (means[k + 1])
        tau = float(gaps[k])
        if tau not in flows:
            flows[tau] = van_loan(F, a, f0, tau)
        phi, shift, Q = flows[tau]
        m, P = means[k], covs[k]
        m_pred, P_pred = phi @ m + shift, phi @ P @ phi.T + Q
        J = np.linalg.solve(P_pred.T, (P @ phi.T).T).T  # P Φᵀ (P⁻)⁻¹ (P⁻ symmetric)
        m_s[k - 1] = m + J @ (m_s[k] - m_pred)
        P_new = P + J @ (P_s[k] - P_pred) @ J.T
        P_s[k - 1] = 0.5 * (P_new + P_new.T)
    return new_state, dataclasses.replace(result, mean=m_s, cov=P_s, mode=m_s.copy())
