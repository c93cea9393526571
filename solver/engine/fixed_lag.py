"""Fixed-lag smoothing in the engine: row k given the rows up to k + L, for a recorded chunk (issue 38).

The forward pass runs block by block (blocks of max(256, L + 1) rows, solver/engine/smoother.py
``forward_block``) keeping of each block its nodal σ_k, the weighted factors ẽ_k ⊙ w (w on a row that
only predicts), ∫σ_k and gaps; with the next block in as well, each row k of a block takes its own short
backward pass from β = 1 at row min(k + L, K − 1), b = P_jᵀ(ẽ_j ⊙ w ⊙ β)/∫σ_j, β = Φb down to row k + 1
(the recursion of smoother.py), and σ_k ⊙ β normalised is p(x_k | rows up to k + L) of the discretised
model: exactly row k of the fixed-interval smoother over rows … k + L.  L backward steps a row; two
blocks of σ in memory.  Increments filtered in pieces are left to the generic window of
solver/smoothing.py (None).
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from ..errors import InputError
from ..filtering import ChunkResult, concat_results
from .smoother import BLOCK, CHECK, Visit, adjoint_of, forward_block, smoothed_states, validated
from .state import YauYauState


def smooth_lag_arrays(engine: Any, state: YauYauState, increments: Any, times: Any = None, lag: int = 0,
                      block: int | None = None,
                      visit: Visit | None = None) -> tuple[YauYauState, ChunkResult] | None:
    """(the filter's state after the chunk, the result with each row's moments given the ``lag`` rows
    after it), or None where the chunk's increments are filtered in pieces.  ``visit(start, states)``,
    where given, gets the smoothed densities block by block as filter states (smoother.py's
    ``smoothed_states``)."""
    if lag == 0 and visit is None:
        return engine.run_arrays(state, increments, times)
    chunk = validated(engine, state, increments, times)
    if chunk is None:
        return engine.run_arrays(state, increments, times)
    rows, steps, times_out, taus, pieces, field = chunk
    if pieces is not None:
        return None
    K = len(rows)
    size = max(BLOCK, lag + 1) if block is None else max(lag + 1, int(block))
    bounds = [(start, min(start + size, K)) for start in range(0, K, size)]
    pending: list[tuple] = []
    parts: list[ChunkResult] = []
    current = state
    for start, stop in bounds:
        found = forward_block(engine, current, rows, steps, times_out, taus, start, stop, field)
        current, filtered, sigma, factor, masses, ready = found
        weighted = factor.astype(float) * engine.weights
        weighted[ready.skip | filtered.gated] = engine.weights
        pending.append((start, stop, filtered, sigma, weighted, masses, ready.skip))
        while pending and (pending[0][1] + lag <= stop or stop == K):
            part, smoothed = _lagged(engine, pending, taus, lag, K)
            parts.append(part)
            if visit is not None:
                visit(pending[0][0], smoothed_states(engine, state, smoothed, part))
            pending.pop(0)
    return current, concat_results(parts)


def _lagged(engine: Any, pending: list[tuple], taus: np.ndarray | None, lag: int,
            K: int) -> tuple[ChunkResult, np.ndarray]:
    """The first pending block's rows, each given the ``lag`` rows after it (from the pending blocks), and
    their smoothed nodal σ_k ⊙ β_k."""
    start, stop, filtered, sigma, _, _, _ = pending[0]
    end = pending[-1][1]
    weighted = np.concatenate([p[4] for p in pending])
    scale = 1.0 / np.concatenate([p[5] for p in pending])
    skip = np.concatenate([p[6] for p in pending])
    basis = np.asfortranarray(engine.offline.basis, dtype=float)
    adjoint = adjoint_of(engine, basis, None if taus is None else taus[start:end], skip)
    Q = sigma.shape[1]
    smoothed, v = np.empty_like(sigma), np.empty(Q)
    for i in range(stop - start):
        beta = np.ones(Q)
        for j in range(min(i + lag, K - 1 - start), i, -1):
            np.multiply(weighted[j], beta, out=v)
            beta = adjoint(j, v, scale[j])
            if j % CHECK == 0:
                top = float(np.max(np.abs(beta)))
                if not np.isfinite(top) or top == 0.0:
                    raise InputError("increments", f"the backward pass lost every node at row {start + j}")
                if not 1e-100 < top < 1e100:
                    beta /= top
        np.multiply(sigma[i], beta, out=smoothed[i])
    masses = smoothed @ engine.weights
    if not np.all(masses > 0.0):
        k = int(np.argmax(~(masses > 0.0)))
        raise InputError(f"increments[{start + k}]", "the smoothed density has no positive mass at this row")
    mean, cov, mode = engine.moments(smoothed, masses, None)
    return dataclasses.replace(filtered, mean=mean, cov=cov, mode=mode), smoothed
