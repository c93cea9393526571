"""The fixed-interval smoother of the Yau–Hu filter (solver/exact/yau_hu.py): forward mixture × backward
message, exact for the filter's model (the seeds give no smoother; this is the adjoint of the same flow).

The filter's step over a gap τ_k is the exact robust flow ∂σ/∂t = L*σ − Vσ with the observation path
linear over the gap (V = ½|h|²_R − hᵀR⁻¹ẏ, ẏ = Δy_k/τ_k; seed 000 Theorem 3.1 restarted per interval),
so the rows' joint posterior is a chain of pairwise Feynman–Kac kernels and

    p(x_k | every row) ∝ σ_k(x) β_k(x),   β_K = 1,   β_(k−1) = the adjoint flow of β_k over τ_k,

    ∂β/∂s = ½Δβ + f·∇β − Vβ   (s: time run backwards; a = I as the method requires).

With f = ℓ + ∇F (seed 000 (2.6)), β = e^{−F} w turns it into

    ∂w/∂s = ½Δw + ℓ·∇w − (½η − ½|ℓ|² − ½ div ℓ − hᵀR⁻¹ẏ) w,

η = |f|² + div f + |h|²_R (seed 000 (2.5)) quadratic by (C3): the potential of the filter's own
observation-free equation (3.1) (yau_hu_step.step_equations: Q = ½(E − DᵀD), q = ½e − Dᵀd) less the
data's linear term, with drift −ℓ in riccati.py's convention (D → −D, d → −d).  So w stays a finite
sum of exp(−xᵀA'x − B'ᵀx − C'): it starts as e^{F} = Σ_T exp(log c_T + s_Tᵀx) (A' = 0, B' = −s_T,
C' = −log c_T: the terms the filter's moments already need), and each term flows exactly (Hamiltonian
exponentials; C' by the flow's Gauss–Legendre rule over pieces of the gap, riccati.gap_pieces, since the
terms' relative weights matter).  The smoothed density is σ_k β_k = v_k w_k with v_k = e^{−F}σ_k the
filter's mixture: a product of two exponential-quadratic sums, a Gaussian mixture of J·T components
whose moments are closed-form — e^{F} cancels.

A missing or gated row flows without the observation (η without |h|², no data term); a partly missing
row with h_o, R_oo; discrete measurements multiply β_k by N(z_o; H_o x + h0_o, R_oo) at t_k before the
observation-free flow over the gap (as the filter predicts, then updates).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from typing import Any

import numpy as np

from ..filtering import ChunkResult
from ..measurement import check_rows
from .kalman_bucy_backward import observed_terms
from .mixtures import mixture_moments
from .riccati import GaussianKolmogorov, gap_pieces, gaussian_terms_batch
from .yau_hu_step import step_equations


def smooth_arrays(flt: Any, state: Any, increments: Any, times: Any, steps: Callable,
                  whitened: Callable) -> tuple[Any, ChunkResult]:
    """(the filter's state after the chunk, its ChunkResult with the smoothed mean and cov); ``steps`` is
    the filter's row-by-row pass (its exponents after each row), ``whitened(key)`` its step terms (the
    shift of η for the observed components ``key``)."""
    new_state, result = flt.run_arrays(state, increments, times)
    K = len(result)
    if K == 0:
        return new_state, result
    rows = check_rows(increments, flt.model.m)
    keys = flt.observation.pattern_keys(~np.isnan(rows))
    if result.gated is not None:
        keys = np.where(result.gated, 0, keys)
    gaps = np.diff(np.asarray(result.t, dtype=float), prepend=float(state.t))
    _, (A, B, C) = steps(state, rows, keys, gaps)  # v_k = e^{−F}σ_k after each row
    mean, cov = np.empty_like(result.mean), np.empty_like(result.cov)
    w = _terminal(flt)
    for k in range(K - 1, -1, -1):
        mean[k], cov[k] = _product_moments((A[k], B[k], C[k]), w)
        if k:
            w = _backward(flt, whitened, w, rows[k], int(keys[k]), float(gaps[k]))
    return new_state, dataclasses.replace(result, mean=mean, cov=cov)


def _terminal(flt: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """w_K = e^{F}·β_K = e^{F} as exponents (T, n, n), (T, n), (T,)."""
    slopes, logc = flt.system.exp_F_slopes, flt.system.exp_F_logc
    n = flt.model.n
    return np.zeros((len(logc), n, n)), -np.asarray(slopes, float), -np.asarray(logc, float)


def _product_moments(v, w) -> tuple[np.ndarray, np.ndarray]:
    """Mean and covariance of v·w, both sums of exp(−xᵀAx − Bᵀx − C): the J·T pairwise products."""
    (A, B, C), (A2, B2, C2) = v, w
    mean, cov, log_mass = gaussian_terms_batch(A[:, None] + A2[None], B[:, None] + B2[None],
                                               C[:, None] + C2[None])
    n = A.shape[-1]
    return mixture_moments(log_mass.reshape(-1), mean.reshape(-1, n), cov.reshape(-1, n, n))


def _equation(flt: Any, whitened: Callable, key: int) -> GaussianKolmogorov:
    """The backward equation of w with the observed components ``key`` in η (0: none) — riccati.py's
    form with drift −ℓ; the data's linear term is passed per row (:func:`_data_term`)."""
    cache = flt.__dict__.setdefault("_backward_equations", {})
    found = cache.get(key)
    if found is None:
        _, _, shift, _ = whitened(key)
        system = flt.system
        forward, _ = step_equations(system.D, system.d, system.E + shift[0], system.e + shift[1],
                                    system.e0 + shift[2], np.zeros((flt.model.m, flt.model.n)))
        found = cache[key] = GaussianKolmogorov(-system.D, -system.d, Q=forward.Q, q=forward.q,
                                                        a=np.eye(flt.model.n))
    return found


def _data_term(flt: Any, row: np.ndarray, key: int, tau: float) -> np.ndarray:
    """The potential's linear part from −hᵀR⁻¹ẏ of the observed components: −H_oᵀR_oo⁻¹ẏ_o."""
    index, H_o, _, R_inv = observed_terms(flt, key)
    return -H_o.T @ (R_inv @ (row[index] / tau))


def _backward(flt: Any, whitened: Callable, w, row: np.ndarray, key: int, tau: float):
    """w_(k−1) from w_k over row k's gap τ (its observation: ``row``, ``key``)."""
    A, B, C = w
    if flt.discrete:
        if key:  # β_k × N(z_o; H_o x + h0_o, R_oo) at t_k (the constant is common to every term)
            index, H_o, h0_o, R_inv = observed_terms(flt, key)
            resid = row[index] - h0_o
            A = A + 0.5 * H_o.T @ R_inv @ H_o
            B = B - H_o.T @ (R_inv @ resid)
        key, eq, q = 0, _equation(flt, whitened, 0), None
    else:
        eq = _equation(flt, whitened, key)
        q = eq.q + (_data_term(flt, row, key, tau) if key else 0.0)
    largest = float(np.linalg.eigvalsh(A)[..., -1].max())
    delta = 1.0 / (2.0 * largest) if largest > 0 else math.inf
    flows = flt.__dict__.setdefault("_backward_flows", {})
    for piece in gap_pieces(tau, eq.spectrum()[1], delta):
        flow = flows.get((piece, key))
        if flow is None:
            if len(flows) > 256:
                flows.clear()
            flow = flows[(piece, key)] = eq.gap_flow(piece)
        terms = flow.step(A, B, C, q, 0.0)
        A, B, C = terms.A, terms.B, terms.C
    return A, B, C
