"""The engine's kernel: one step of seed 002 (5.35)/(5.38) over plain arrays, and the moments.

With c the basis coefficients carried with their mass ∫σ as one vector [c, ∫σ] (N+1,), P a stored
propagator with a zero column for ∫σ (Q×(N+1)), Π the projector with the quadrature weights w as an
extra row ((N+1)×Q) and e_k the update factor exp(log e_k − max) at the Q nodes:

    s_k          = P [c, ∫σ]_{k−1} / ∫σ_{k−1}      predict   (5.38): the propagated density, unit mass
    σ_k          = s_k ⊙ e_k                        observe   (5.35): the update
    [c, ∫σ]_k    = Π σ_k                            project   back onto the basis, and ∫σ_k = w·σ_k
    moments(σ_k)                                    mean, covariance and mode by quadrature

The functions write into the arrays they are given (no allocation in the hot loop) and call BLAS
with positional arguments (keyword parsing costs as much as a small product).  The loops of
solver/engine/loops.py, the batch of solver/engine/batch.py and the ball that follows the state
(solver/engine/follow.py, recentring.py) are built from them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, DTypeLike
from scipy.linalg.blas import dgemv, sgemv

from ..filtering import ChunkResult, Estimate

NO_MASS_AFTER_UPDATE = "no positive mass after the update: observation impossible under the model"
NO_MASS_ON_BALL = "all probability mass has left the domain ball"
FACTOR_OVERFLOWS = "the update factor exp(hᵀR⁻¹Δy) overflows: observation incompatible with the model"


@dataclass(frozen=True)
class Arithmetic:
    """Floating point of the hot loop.  A pre-projection mass outside [tiny, huge] is recomputed in
    log scale (rare slow path); update factors (relative to their max) below ``negligible`` count as 0,
    so the BLAS calls never work on subnormal numbers (slow)."""

    dtype: type
    gemv: Any
    tiny: float
    huge: float
    negligible: float


ARITHMETIC = {"double": Arithmetic(np.float64, dgemv, 1e-280, 1e280, 1e-250),
              "single": Arithmetic(np.float32, sgemv, 1e-30, 1e30, 1e-25)}


def predict(arith: Arithmetic, propagator: np.ndarray, carried: np.ndarray, mass: float,
            out: np.ndarray) -> None:
    """out = P [c, ∫σ] / ∫σ: the density propagated over the gap (a row without observation)."""
    arith.gemv(1.0 / mass, propagator, carried, 0.0, out, 0, 1, 0, 1, 0, 1)


def observe(arith: Arithmetic, propagator: np.ndarray, carried: np.ndarray, mass: float,
            factor: np.ndarray, scratch: np.ndarray, out: np.ndarray) -> None:
    """out = (P [c, ∫σ] / ∫σ) ⊙ e: propagated, then updated (``scratch`` keeps the propagated values)."""
    arith.gemv(1.0 / mass, propagator, carried, 0.0, scratch, 0, 1, 0, 1, 0, 1)
    np.multiply(scratch, factor, out=out)


def project(arith: Arithmetic, projection: np.ndarray, sigma: np.ndarray, out: np.ndarray,
            mass_index: int) -> float:
    """out = Π σ (the coefficients, ∫σ at ``mass_index``, and any further rows); returns ∫σ."""
    arith.gemv(1.0, projection, sigma, 0.0, out, 0, 1, 0, 1, 0, 1)
    return out.item(mass_index)


def with_zero_column(propagator: ArrayLike, dtype: DTypeLike) -> np.ndarray:
    """A propagator (Q×N) with a zero column for ∫σ, in Fortran order (gemv reads it without a copy)."""
    matrix = np.asarray(propagator, dtype=float)
    return np.asfortranarray(np.hstack([matrix, np.zeros((matrix.shape[0], 1))]), dtype=dtype)


def moment_features(weights: np.ndarray, nodes: np.ndarray, pairs: list[tuple[int, int]]) -> np.ndarray:
    """Rows w·x_i (i < n), then w·x_i·x_j for the pairs i ≤ j: the moments as one product."""
    n = nodes.shape[1]
    return np.vstack([weights * nodes[:, i] for i in range(n)]
                     + [weights * nodes[:, i] * nodes[:, j] for i, j in pairs])


def moments(sigma: np.ndarray, mass: np.ndarray, features: np.ndarray, pairs: list[tuple[int, int]],
            nodes: np.ndarray, shifts: np.ndarray | None = None):
    """Mean, covariance and mode of each row of nodal σ (K, Q) with ∫σ = mass (``shifts``: each
    row's nodes moved, a moving frame: the mean and mode move with them, the covariance does not).

    One einsum (numpy's own loops, no BLAS): each row's value does not depend on K.
    """
    K = sigma.shape[0]
    sums = np.einsum("kq,fq->kf", sigma, features)
    mode = np.argmax(sigma, axis=1) if K else np.empty(0, dtype=int)
    return moments_from(sums, mass, mode, pairs, nodes, shifts)


def moments_from(sums: np.ndarray, mass: np.ndarray, mode_index: np.ndarray, pairs: list[tuple[int, int]],
                 nodes: np.ndarray, shifts: np.ndarray | None = None):
    """:func:`moments` from each row's sums features · σ (K, F) and the node of its largest σ (K,): what
    the fused compiled rows (solver/engine/fused.py) leave instead of σ."""
    n = nodes.shape[1]
    K = sums.shape[0]
    values = sums / mass[:, None]
    first = values[:, :n]
    cov = np.empty((K, n, n))
    for p, (i, j) in enumerate(pairs):
        cov[:, i, j] = cov[:, j, i] = values[:, n + p] - first[:, i] * first[:, j]
    mode = nodes[mode_index] if K else np.empty((0, n))
    if shifts is not None:
        first, mode = first + shifts, mode + shifts
    return first, cov, mode


def moment_pairs(n: int) -> list[tuple[int, int]]:
    """The index pairs i ≤ j of the second moments, in the order of :func:`moment_features`."""
    return [(i, j) for i in range(n) for j in range(i, n)]


def log_mean_factor(weights: np.ndarray, s: ArrayLike, log_factor_row: np.ndarray) -> float:
    """log Σ_q w_q s_q e_q over the nodes where s > 0 (e relative to its maximum), by log-sum-exp: what
    the hot loop's log ∫σ would be for a factor too small to sum directly (−inf: nothing left)."""
    s = np.asarray(s, dtype=float)
    positive = s > 0.0
    if not positive.any():
        return -math.inf
    terms = np.log(weights[positive] * s[positive]) + log_factor_row[positive]
    top = float(terms.max())
    if not math.isfinite(top):
        return -math.inf
    return top + math.log(float(np.exp(terms - top).sum()))


def rescue(arith: Arithmetic, weights: np.ndarray, s: ArrayLike, log_factor: np.ndarray, top: np.ndarray,
           missing: bool, k: int, row: np.ndarray) -> tuple[float, str | None]:
    """Step k again in log scale when ∫σ under/overflows (s: the propagated nodal values): writes
    ``row``, may shift top[k]; (∫σ, None) or (0, the reason the step cannot be taken)."""
    s = np.array(s, dtype=float)
    prior_mass = float(weights @ s)
    if not prior_mass > 0.0 or not math.isfinite(prior_mass):
        return 0.0, NO_MASS_ON_BALL
    if not missing and not np.all(np.isfinite(log_factor[k])):
        return 0.0, FACTOR_OVERFLOWS
    with np.errstate(divide="ignore"):
        log_abs = np.log(np.abs(s)) + (0.0 if missing else log_factor[k])
    shift = float(log_abs.max())
    row[:] = np.sign(s) * np.exp(log_abs - shift)
    new_mass = float(weights @ row)
    if not arith.tiny < new_mass < arith.huge:
        return 0.0, NO_MASS_AFTER_UPDATE
    top[k] += shift
    return new_mass, None


def blocks(pieces: np.ndarray, limit: int) -> list[int]:
    """Ends of consecutive blocks of rows whose pieces add up to at most ``limit`` (at least one row)."""
    ends, total = [], 0
    for k, count in enumerate(pieces.tolist()):
        if total and total + count > limit:
            ends.append(k)
            total = 0
        total += count
    return ends + [len(pieces)]


def stack_results(steps, times, mean, cov, mode, loglik, increments, last: Estimate, reason,
                  **rows: Any) -> ChunkResult:
    """Pad the good steps' estimates with the last good one for the degenerate tail (``rows``: the
    ChunkResult's other per-row arrays, as they are)."""
    K, done = len(steps), len(loglik)
    if done < K:
        tail = K - done
        mean = np.concatenate([mean, np.repeat(last.mean[None], tail, axis=0)])
        cov = np.concatenate([cov, np.repeat(last.cov[None], tail, axis=0)])
        last_mode = last.mode if last.mode is not None else last.mean
        mode = np.concatenate([mode, np.repeat(last_mode[None], tail, axis=0)])
        loglik = np.concatenate([loglik, np.full(tail, last.loglik)])
        increments = np.concatenate([increments, np.zeros(tail)])
    degenerate = np.arange(K) >= done
    return ChunkResult(step=steps, t=times, mean=mean, cov=cov, mode=mode, loglik=loglik,
                       loglik_increment=increments, degenerate=degenerate, reason=reason, **rows)
