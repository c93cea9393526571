"""The fixed-interval smoother of the Kalman–Bucy filter's continuous increments (the robust flow, the
default kind): the two-filter (Mayne–Fraser) form, exact for the filter's own model.

The forward step over a gap τ_k (solver/exact/kalman_bucy.py) solves the robust DMZ equation with the
observation path linear over the gap, ẏ = Δy_k/τ_k:

    ∂σ/∂t = L*σ − V σ,   L* = ½Σa_ij∂i∂j − div(f ·),   V = ½hᵀR⁻¹h − hᵀR⁻¹ẏ,

so σ_k(x') = ∫ K_k(x', x) σ_(k−1)(x) dx with K_k the Feynman–Kac kernel of that equation over τ_k
(a missing or gated row: V = 0, the Fokker–Planck flow; a partly missing row: h_o, R_oo).  The rows'
joint posterior is then ∝ p_0(x_0) Π_k K_k(x_k, x_(k−1)): a Markov chain of pairwise factors, whose
marginals are filtered × backward message,

    p(x_k | every row) ∝ σ_k(x) β_k(x),   β_K = 1,   β_(k−1)(x) = ∫ K_k(x', x) β_k(x') dx'.

β_(k−1) is the solution over τ_k of the adjoint (backward Kolmogorov) equation with the same potential,

    ∂β/∂s = ½Σa_ij∂i∂jβ + (F x + f0)·∇β − V β    (s: time run backwards),

which is riccati.py's equation with D = −F, d = −f0 (its tr D term only scales β): β stays
exp(−xᵀA_b x − B_bᵀx − C_b), A_b ≥ 0 from A_b = 0 (the information form of the backward filter; no
inverse of A_b is needed), by the same exact flows as the forward filter (Hamiltonian exponentials;
a long irregular gap in pieces of at most 1/ρ).  The smoothed moments are the product's:

    Λ = P⁻¹ + 2A_b,  P^s = Λ⁻¹ = (I + 2P A_b)⁻¹ P,  m^s = (I + 2P A_b)⁻¹ (m − P B_b).

Not the RTS recursion of the time-sampled model: this smoother conditions on what the forward filter
conditions on (the linear path over each gap), and equals the RTS recursion of the exact discrete
model of each gap (the joint Gaussian of (x_(k−1), x_k) given the rows up to k) — what
tests/solver/exact/test_kalman_bucy_backward.py checks it against.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np

from ..filtering import ChunkResult
from ..measurement import check_rows
from .riccati import FlowFamily, GaussianKolmogorov, affine_path, gap_pieces
from .schedule import regular_gaps


def smooth_continuous(flt: Any, state: Any, increments: Any, new_state: Any,
                      result: ChunkResult) -> tuple[Any, ChunkResult]:
    """(state after the chunk, ``result`` with the smoothed mean, cov, mode) of the robust flow's rows;
    ``result`` is the filter's own pass over them from ``state``."""
    K, n = len(result), flt.model.n
    rows = check_rows(increments, flt.model.m)
    keys = flt.observation.pattern_keys(~np.isnan(rows))
    if result.gated is not None:
        keys = np.where(result.gated, 0, keys)
    stamps = np.asarray(result.t, dtype=float)
    gaps = regular_gaps(np.diff(stamps, prepend=float(state.t)), flt.model.dt, stamps, float(state.t))
    whole = (1 << flt.model.m) - 1
    if gaps is None and np.all((keys == 0) | (keys == whole)):
        A_b, B_b = _regular_messages(flt, rows, keys)
    else:
        gaps = np.full(K, flt.model.dt) if gaps is None else gaps
        A_b, B_b = _messages(flt, rows, keys, gaps)
    P, m = result.cov, result.mean
    I_2PA = np.eye(n) + 2.0 * P @ A_b  # (K, n, n)
    cov = np.linalg.solve(I_2PA, P)
    cov = 0.5 * (cov + np.swapaxes(cov, -1, -2))
    mean = np.linalg.solve(I_2PA, (m - (P @ B_b[..., None])[..., 0])[..., None])[..., 0]
    return new_state, dataclasses.replace(result, mean=mean, cov=cov, mode=mean.copy())


def _adjoint(flt: Any, key: int) -> GaussianKolmogorov:
    """The backward equation of a row with the observed components ``key`` (0: no potential)."""
    F, f0, a = np.asarray(flt.F, float), np.asarray(flt.f0, float), np.asarray(flt.model.a, float)
    if key == 0:
        return GaussianKolmogorov(-F, -f0, a=a)
    _, H_o, _, R_inv = observed_terms(flt, key)
    return GaussianKolmogorov(-F, -f0, Q=0.5 * H_o.T @ R_inv @ H_o, a=a)


def observed_terms(flt: Any, key: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(index, H_o, h0_o, R_oo⁻¹) of the observed components ``key``."""
    pattern = flt.observation.pattern(key)
    index = pattern.index
    return index, np.asarray(flt.H, float)[index], np.asarray(flt.h0, float)[index], pattern.R_inv


def _potential(flt: Any, row: np.ndarray, key: int, tau: float) -> np.ndarray:
    """q = H_oᵀR_oo⁻¹(h0_o − ẏ_o) of the potential's linear part, ẏ = Δy/τ (0 for a row without data)."""
    if key == 0:
        return np.zeros(flt.model.n)
    index, H_o, h0_o, R_inv = observed_terms(flt, key)
    return H_o.T @ R_inv @ (h0_o - row[index] / tau)


def _regular_messages(flt: Any, rows: np.ndarray, keys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(A_b, B_b) of β_k for every row of a regular chunk of whole or missing rows: the data-free A path,
    then B affine in the data (one recursion), as the forward chunk code does."""
    K, n, dt = len(rows), flt.model.n, flt.model.dt
    whole = (1 << flt.model.m) - 1
    family = FlowFamily([_adjoint(flt, whole).flow(dt), _adjoint(flt, 0).flow(dt)])
    later = slice(K - 1, 0, -1)  # rows K−1 … 1 carry β_k back to β_(k−1)
    choice = (keys[later] == 0).astype(int)
    q = np.stack([_potential(flt, rows[k], int(keys[k]), dt) for k in range(K - 1, 0, -1)]) \
        if K > 1 else np.zeros((0, n))
    A = family.path(choice, np.zeros((1, n, n)))  # (K, 1, n, n): β_(K−1), β_(K−2), …, β_0
    batch = family.batch(choice, A[:-1], q, np.zeros(K - 1))
    B = affine_path(batch.W, batch.v, np.zeros((1, n)))
    return A[::-1, 0], B[::-1, 0]


def _messages(flt: Any, rows: np.ndarray, keys: np.ndarray,
              gaps: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(A_b, B_b) of β_k row by row (irregular gaps, partly missing rows): each gap in pieces of at most
    1/ρ (ρ the spectral radius of the flow's linear system; the path is linear over the gap, so splitting
    is exact), flows cached per (piece, pattern)."""
    K, n = len(rows), flt.model.n
    A_b, B_b = np.zeros((K, n, n)), np.zeros((K, n))
    equations: dict[int, GaussianKolmogorov] = {}
    flows: dict[tuple[float, int], Any] = {}
    A, B = np.zeros((n, n)), np.zeros(n)
    for k in range(K - 1, 0, -1):
        key, tau = int(keys[k]), float(gaps[k])
        eq = equations.get(key)
        if eq is None:
            eq = equations[key] = _adjoint(flt, key)
        q = _potential(flt, rows[k], key, tau)
        for piece in gap_pieces(tau, eq.spectrum()[1], math.inf):
            flow = flows.get((piece, key))
            if flow is None:
                flow = flows[(piece, key)] = eq.gap_flow(piece)
            terms = flow.step(A, B, 0.0, q, 0.0)
            A, B = terms.A, terms.B
        A_b[k - 1], B_b[k - 1] = A, B
    return A_b, B_b
