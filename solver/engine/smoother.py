"""The fixed-interval smoother of the engine: p(x_k | all the rows of a chunk), issue 38.

The forward pass is the filter's (solver/engine/loops.py).  Written at the nodes, each of its steps is
linear in the nodal σ: with Π = ΦᵀW the projector, P_k the row's propagator (Q×N: ``propagator_fp``
over dt, ``propagator_k`` for an observed row of the literal form, Φe^{τ_kA} over an irregular gap) and
ẽ_k the row's update factor (exp(log e_k − max) at the nodes; 1 for a row that only predicts: missing
or gated),

    σ_k = ẽ_k ⊙ P_k Π σ_(k−1) / ∫σ_(k−1),      the filtered measure of row k: w ⊙ σ_k / ∫σ_k.

So the forward pass is the forward recursion of a linear model on the Q nodes, with transition
W P_k Π W⁻¹ between the measures, and its exact backward recursion (the adjoint of that transition in
the same basis) is, for β_k the nodal likelihood of the rows after k (β_K = 1),

    b_(k−1) = P_kᵀ (ẽ_k ⊙ w ⊙ β_k)   (N,),      β_(k−1) = Φ b_(k−1)   (Q,).

Then wᵀ(σ_k ⊙ β_k) is the same for every k (the chunk's likelihood), and the smoothed measure of row k
is w ⊙ σ_k ⊙ β_k normalised: mean, covariance and mode by the filter's own quadrature
(``engine.moments``).  This is exactly the forward–backward smoother of the discretised model; at the
last row it is the filter.  Each β is divided by its largest magnitude (the scale cancels in the
normalisation), so nothing under- or overflows: ẽ_k ≤ 1 is already relative to its maximum.

Irregular gaps in the generator's modal coordinates (solver/engine/semigroup.py): the forward step is
s = B S_k d, d = C σ (B = ΦV, C = V⁻¹ΦᵀW, S_k = e^{τ_kΛ} as real scalings and 2×2 rotations), so its
adjoint is b = V⁻ᵀ S_kᵀ Bᵀ(ẽ ⊙ w ⊙ β), β = Φb: the pairs scaled by the conjugate factors.  In the Schur
or expm forms of an ill-conditioned generator the adjoint uses Φe^{τA} by scipy's expm per gap.

Memory: a chunk whose K×Q nodal values fit :data:`KEEP` (32 MiB an array: 21 500 rows at Q = 195) keeps
its whole forward pass (σ_k, the factors), as the filter itself holds them for the chunk, and the filter
runs once.  A longer chunk goes in checkpointed blocks of max(256, ⌈√K⌉, KEEP // Q) rows: the first pass
is the filter itself (its fused compiled rows, no K×Q arrays) keeping the state (N + 1 numbers) at each
block's start; the backward pass takes the blocks from the last, runs each block's forward pass again
from its checkpoint keeping its σ_k, factors and exponents (equal to the first pass's to rounding),
overwrites σ_k with σ_k ⊙ β_k in place and carries one β (Q,) into the block before.  So the rows cost
O(KEEP + K/B·N) numbers besides the K rows of the result.  The last block (a whole one: the remainder
block comes first) keeps its first pass's σ_k, factors and exponents, as a chunk kept whole does, so its
forward pass runs once.  The backward step is one gemv with the
Q×Q matrix ΦPᵀ (computed once per engine), in numba's compiled loop where the filter's are
(solver/engine/compiled_backward.py, the same BLAS call).  Measured on examples/ou.toml (Q = 195, N = 96;
bench/smoother.py, docs/benchmarks.md; CPU time, one BLAS thread, 2 shared cores at load ~6.5): 22 µs a
row against the fused filter's 9.9 (2.3×) kept whole (20 000 rows), 28 µs against 10.6 (2.65×)
checkpointed (100 000 rows; 3.2× before the last block kept its first pass); 10⁶ rows in one chunk peaked
at 533 MB RSS against 429 MB for the engine and the rows alone.

Increments over long gaps are smoothed in the filter's pieces (solver/engine/pieces.py), the gate judging
whole rows.  A ball that follows the state (an atlas, a moving frame too) is smoothed over its sequence
of balls, the backward pass carrying the adjoint of each move (solver/engine/follow_smoother.py, through
:func:`smooth_from`); in a moving frame each row's nodes are moved (``ready.shifts``: the factors and
moments at them), the recursion in the coefficients is unchanged.  Refused (InputError naming the row): a
chunk whose filter degenerates.
"""

from __future__ import annotations

import dataclasses
import math
import weakref
from typing import Any, Callable

import numpy as np
from scipy.linalg.blas import dgemv

from .. import jit
from ..errors import InputError
from ..filtering import ChunkResult, chunk_clock, concat_results
from ..measurement import check_first_gap, check_rows, resolve_times
from .loops import loop_irregular, loop_regular, update_factors
from .pieces import row_pieces
from .state import YauYauState

CHECK = 32  # rows between the backward pass's magnitude checks
BLOCK = 256  # rows of a checkpointed block at least (√K where that is more)
KEEP = 1 << 22  # nodal values (32 MiB a K×Q array) up to which a chunk's forward pass is kept whole
Visit = Callable[[int, list], None]


def smooth_arrays(engine: Any, state: YauYauState, increments: Any, times: Any = None,
                  block: int | None = None, visit: Visit | None = None) -> tuple[YauYauState, ChunkResult]:
    """The fixed-interval smoother of ``engine`` (a YauYauFilter) over one chunk from ``state``: (the
    filter's state after the chunk, a ChunkResult whose mean, cov and mode are the smoothed ones given
    every row of the chunk; its log-likelihoods, gating and the rest are the forward pass's).  ``block``:
    rows per checkpointed block (default max(256, ⌈√K⌉)).  ``visit(start, states)``, where given, is
    called once per block (from the last) with the smoothed densities of rows start, start + 1, … as
    filter states (:func:`smoothed_states`): what the filter's quantiles, mode and density read."""
    new_state, result, _ = smooth_from(engine, state, increments, times, block, visit)
    return new_state, result


def smooth_from(engine: Any, state: YauYauState, increments: Any, times: Any = None, block: int | None = None,
                visit: Visit | None = None, beta: np.ndarray | None = None):
    """:func:`smooth_arrays` with the rows after the chunk given as ``beta`` (Q,): the nodal likelihood of
    those rows given the state after the chunk's last row (None: no rows after, β = 1), as the backward
    pass of a ball that follows the state carries it in (solver/engine/follow_smoother.py).  Returns
    (state after, smoothed result, β before the chunk's first row (Q,): Φ P_0ᵀ(ẽ_0 ⊙ w ⊙ β_0), up to a
    positive factor)."""
    chunk = validated(engine, state, increments, times)
    if chunk is None:
        new_state, result = engine.run_arrays(state, np.empty((0, engine.model.m)), times)
        return new_state, result, np.ones(len(engine.weights)) if beta is None else beta
    rows, steps, times_out, taus, pieces, field = chunk
    if pieces is not None:
        if visit is not None:
            raise InputError(field, "the smoothed densities of increments filtered in pieces (long gaps) "
                                    "are not offered yet: ask for the moments alone")
        return _in_pieces(engine, state, rows, steps, times_out, taus, pieces, block, field, beta)
    return _blocks(engine, state, rows, steps, times_out, taus, block, field, gating=True, visit=visit,
                   beta=beta)


def validated(engine: Any, state: YauYauState, increments: Any, times: Any):
    """(rows, steps, times, gaps τ_k or None, pieces or None, the rows' field name) of a chunk the smoother
    takes, None for an empty chunk; SpecError/InputError naming what it cannot take."""
    model, obs = engine.model, engine.observation
    field = "observations" if obs.discrete else "increments"
    rows = check_rows(increments, model.m, field)
    K = rows.shape[0]
    taus = resolve_times(state.t, state.step > 0, K, model.dt, times)
    check_first_gap(taus, obs.discrete)
    if state.degenerate:
        raise InputError("state", f"the filter state is degenerate ({state.reason}): nothing to smooth from")
    if K == 0:
        return None
    steps, times_out = chunk_clock(state, K, model.dt, times, taus)
    if engine.form == "literal":
        engine.check_literal(rows, taus)
    return rows, steps, times_out, taus, row_pieces(engine, rows, taus), field


def _blocks(engine: Any, state: YauYauState, rows: np.ndarray, steps: np.ndarray, times: np.ndarray,
            taus: np.ndarray | None, block: int | None, field: str, gating: bool, visit: Visit | None = None,
            beta: np.ndarray | None = None):
    """The checkpointed forward pass, then the backward pass block by block from the last (from ``beta``
    after the last row, default 1): (state after, smoothed result, β before the first row)."""
    K, Q = len(rows), len(engine.weights)
    if block is not None:
        size = max(1, int(block))
    elif K * Q <= KEEP:  # the whole forward pass is kept: it runs once
        size = K
    else:
        size = max(BLOCK, math.isqrt(K - 1) + 1, KEEP // Q)
    # the remainder first, so that the last block, whose forward pass is kept from the first pass (the
    # backward pass starts there), is a whole one
    first = K - (K - 1) // size * size
    bounds = [(0, first)] + [(start, start + size) for start in range(first, K, size)]
    checkpoints, current, kept = [], state, None  # the forward pass: the state at each block's start
    for start, stop in bounds:
        if stop == K:
            kept = forward_block(engine, current, rows, steps, times, taus, start, stop, field, gating)
            checkpoints.append((current, kept[1]))
            current = kept[0]
        else:
            found = checkpoint(engine, current, rows, steps, times, taus, start, stop, field, gating)
            checkpoints.append((current, found[1]))
            current = found[0]
    parts: list[ChunkResult] = []
    beta = np.ones(len(engine.weights)) if beta is None else np.array(beta, dtype=float)
    for (start, stop), (begin, filtered) in zip(reversed(bounds), reversed(checkpoints), strict=True):
        if kept is not None:  # the last block
            _, _, sigma, factor, masses, ready = kept
            kept = None  # (its arrays go with the block: one block's at a time)
            only_predicts = ready.skip | filtered.gated
        else:  # the block's σ_k again, from its checkpoint: the loop alone (its filtered rows are kept)
            sigma, factor, masses, ready, gated = forward_sigma(engine, begin, rows, taus, start, stop, field,
                                                                gating)
            only_predicts = ready.skip | gated
        block_taus = None if taus is None else taus[start:stop]
        beta = backward(engine, sigma, factor, masses, only_predicts, block_taus, ready.skip, beta)
        masses = sigma @ engine.weights
        if not np.all(masses > 0.0):
            k = int(np.argmax(~(masses > 0.0)))
            raise InputError(f"{field}[{start + k}]", "the smoothed density has no positive mass at this row")
        mean, cov, mode = engine.moments(sigma, masses, ready.shifts)
        parts.append(dataclasses.replace(filtered, mean=mean, cov=cov, mode=mode))
        if visit is not None:
            visit(start, smoothed_states(engine, begin, sigma, parts[-1]))
    return current, concat_results(parts[::-1]), beta


def smoothed_states(engine: Any, like: YauYauState, sigma: np.ndarray, smoothed: ChunkResult) -> list:
    """The smoothed densities w ⊙ σ_k ⊙ β_k of a block (``sigma`` after the backward pass) as filter states:
    their projection Π(σ_k ⊙ β_k) = [c, ∫] as the filter carries σ_k, the smoothed estimate as ``last``."""
    carried = sigma @ np.asarray(engine.projection, dtype=float).T  # (B, N + 1)
    N = engine.N
    centers = [like.center] * len(carried) if smoothed.center is None else list(smoothed.center)  # a frame's
    return [dataclasses.replace(like, coefficients=carried[i, :N].copy(), mass=float(carried[i, N]),
                                step=int(smoothed.step[i]), t=float(smoothed.t[i]),
                                loglik=float(smoothed.loglik[i]), last=estimate, degenerate=False,
                                reason=None, center=centers[i])
            for i, estimate in enumerate(smoothed.estimates())]


def _in_pieces(engine: Any, state: YauYauState, rows: np.ndarray, steps: np.ndarray, times: np.ndarray,
               taus: np.ndarray, pieces: np.ndarray, block: int | None, field: str,
               beta: np.ndarray | None = None):
    """Increments over long gaps, as the filter takes them (solver/engine/pieces.py): each row in
    ``pieces[k]`` equal pieces of its gap and increment.  The whole rows are filtered first (the gate
    judges whole rows: a gated row is then missing for the smoother), the pieces smoothed without the
    gate, and each row takes its last piece's smoothed moments."""
    new_state, filtered = engine.run_arrays(state, rows, times)
    if filtered.degenerate.any():
        k = int(np.argmax(filtered.degenerate))
        raise InputError(f"{field}[{k}]", f"the filter degenerated at this row ({filtered.reason}): the "
                                          "smoother needs every row of the chunk filtered")
    data = rows.copy()
    data[filtered.gated] = np.nan
    count = np.where(np.isnan(data).all(axis=1), 1, pieces)
    owner = np.repeat(np.arange(len(data)), count)
    first = np.cumsum(count) - count
    last = first + count - 1
    share = taus[owner] / count[owner]
    before = np.concatenate([[state.t], times[:-1]])
    piece_times = before[owner] + share * (np.arange(len(owner)) - first[owner] + 1)
    piece_times[last] = times  # each row ends exactly at its time
    _, smoothed, beta = _blocks(engine, state, data[owner] / count[owner, None], steps[owner], piece_times,
                                share, block, field, gating=False, beta=beta)
    return new_state, dataclasses.replace(filtered, mean=smoothed.mean[last], cov=smoothed.cov[last],
                                          mode=None if smoothed.mode is None else smoothed.mode[last]), beta


def checkpoint(engine: Any, state: YauYauState, rows: np.ndarray, steps: np.ndarray, times: np.ndarray,
               taus: np.ndarray | None, start: int, stop: int, field: str, gating: bool):
    """(the filter's state after rows start … stop − 1 from ``state``, their filtered result): the filter
    itself (its fused compiled rows where they apply: no K×Q arrays, equal to :func:`forward_block`'s to
    rounding) where it gates as the smoother does, else :func:`forward_block`; InputError at a degenerate
    row."""
    if not gating:
        return forward_block(engine, state, rows, steps, times, taus, start, stop, field, gating)[:2]
    new_state, filtered = engine.run_arrays(state, rows[start:stop],
                                            None if taus is None else times[start:stop])
    if filtered.degenerate.any():
        k = int(np.argmax(filtered.degenerate))
        raise InputError(f"{field}[{start + k}]", f"the filter degenerated at this row ({filtered.reason}): "
                                                  "the smoother needs every row of the chunk filtered")
    return new_state, filtered


def forward_sigma(engine: Any, state: YauYauState, rows: np.ndarray, taus: np.ndarray | None, start: int,
                  stop: int, field: str, gating: bool):
    """Rows start … stop − 1 through the filter's loop alone from a checkpoint (no estimates: the first
    pass gave them): (nodal σ_k, the factors ẽ_k, their ∫σ_k, the prepared chunk, the rows the gate
    refused); InputError where the loop stopped early."""
    rows, taus = rows[start:stop], None if taus is None else taus[start:stop]
    ready = engine.prepare(state, rows, taus, gating=gating)
    factor = update_factors(engine.arith, ready.log_factor)
    given = (engine, ready.initial, factor, ready.log_factor, ready.top, ready.skip.tolist(), ready.gate)
    sigma, masses, _, done, reason = loop_regular(*given) if taus is None else loop_irregular(*given, taus)
    if done < len(rows) or reason is not None or (ready.gate is None and ready.impossible.any()):
        k = done if done < len(rows) else int(np.argmax(ready.impossible))
        raise InputError(f"{field}[{start + k}]", f"the filter degenerated at this row ({reason}): the "
                                                  "smoother needs every row of the chunk filtered")
    gated = np.zeros(len(rows), dtype=bool)
    if ready.gate is not None:
        gated[list(ready.gate.scores)] = True
    return np.asarray(sigma, dtype=float), factor, np.asarray(masses, dtype=float), ready, gated


def forward_block(engine: Any, state: YauYauState, rows: np.ndarray, steps: np.ndarray, times: np.ndarray,
             taus: np.ndarray | None, start: int, stop: int, field: str, gating: bool = True):
    """Rows start … stop − 1 through the filter's loop from ``state``: (state after, the filtered result,
    nodal σ_k (in double), the factors ẽ_k, their ∫σ_k, the prepared chunk); InputError at a degenerate
    row."""
    rows, steps, times = rows[start:stop], steps[start:stop], times[start:stop]
    taus = None if taus is None else taus[start:stop]
    ready = engine.prepare(state, rows, taus, gating=gating)
    factor = update_factors(engine.arith, ready.log_factor)
    given = (engine, ready.initial, factor, ready.log_factor, ready.top, ready.skip.tolist(), ready.gate)
    loop = loop_regular(*given) if taus is None else loop_irregular(*given, taus)
    new_state, filtered = engine.finish(state, rows, steps, times, taus, ready, *loop)
    if filtered.degenerate.any():
        k = int(np.argmax(filtered.degenerate))
        raise InputError(f"{field}[{start + k}]", f"the filter degenerated at this row ({filtered.reason}): "
                                                  "the smoother needs every row of the chunk filtered")
    return new_state, filtered, np.asarray(loop[0], dtype=float), factor, np.asarray(loop[1], float), ready


def backward(engine: Any, sigma: np.ndarray, factor: np.ndarray, masses: np.ndarray,
             only_predicts: np.ndarray, taus: np.ndarray | None, skip: np.ndarray,
             beta: np.ndarray) -> np.ndarray:
    """σ_k ← σ_k ⊙ β_k in place, k = K−1 … 0, from ``beta`` = β_(K−1) (the module's recursion; ``factor``
    the loop's ẽ_k, ``masses`` its ∫σ_k, ``only_predicts`` the rows without an update, ``skip`` those the
    loop predicted without observing); returns β before the first row (the previous block's last).
    Each β is divided by the forward pass's ∫σ_k (the scaled forward–backward recursion: wᵀ(σ_k ⊙ β_k)
    stays 1 for unit-mass σ), and every :data:`CHECK` rows by its largest magnitude where that has left
    [1e-100, 1e100]."""
    K, Q = sigma.shape
    w = engine.weights
    basis = np.asfortranarray(engine.offline.basis, dtype=float)
    adjoint = adjoint_of(engine, basis, taus, skip)
    weighted = factor.astype(float) * w  # ẽ_k ⊙ w, and w where the row only predicted
    weighted[only_predicts] = w
    scale = 1.0 / np.asarray(masses, dtype=float)
    beta, v = np.array(beta, dtype=float), np.empty(Q)
    if taus is None and jit.enabled() and sigma.flags.c_contiguous:  # the compiled loop, same numbers
        from .compiled_backward import backward_regular

        M, M_k = regular_adjoints(engine)
        lost = backward_regular(sigma, weighted, scale, np.asarray(skip, dtype=bool), M, M_k, beta, v, CHECK)
        if lost >= 0:
            raise InputError("increments", f"the backward pass lost every node at row {lost}: nothing to "
                                           "smooth")
        return beta
    for k in range(K - 1, -1, -1):
        sigma[k] *= beta
        np.multiply(weighted[k], beta, out=v)
        beta = adjoint(k, v, scale[k])
        if k % CHECK == 0:
            top = float(np.max(np.abs(beta)))
            if not np.isfinite(top) or top == 0.0:
                raise InputError("increments", f"the backward pass lost every node at row {k}: nothing to "
                                               "smooth")
            if not 1e-100 < top < 1e100:
                beta /= top
    return beta


_ADJOINTS: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def regular_adjoints(engine: Any) -> tuple[np.ndarray, np.ndarray]:
    """(ΦPᵀ, ΦP_kᵀ) (Q×Q, Fortran order) of an engine's regular step (predicting, observing: the same
    matrix but in the literal form), computed once per engine: one gemv a backward step."""
    found = _ADJOINTS.get(engine)
    if found is None:
        basis = np.asarray(engine.offline.basis, dtype=float)
        P = np.asarray(engine.offline.propagator_fp, dtype=float)
        M = np.asfortranarray(basis @ P.T)
        M_k = (np.asfortranarray(basis @ np.asarray(engine.offline.propagator_k, dtype=float).T)
               if engine.form == "literal" else M)
        found = _ADJOINTS[engine] = (M, M_k)
    return found


def adjoint_of(engine: Any, basis: np.ndarray, taus: np.ndarray | None, missing: np.ndarray):
    """adjoint(k, v, α) -> α Φ P_kᵀ v (Q,), β_(k−1) from v = ẽ_k ⊙ w ⊙ β_k, for row k's propagator P_k."""
    N = basis.shape[1]
    if taus is None:
        M, M_k = regular_adjoints(engine)  # literal: observed rows used P_k
        matrices = [M if m else M_k for m in np.asarray(missing, dtype=bool).tolist()]

        def regular(k: int, v: np.ndarray, alpha: float) -> np.ndarray:
            return dgemv(alpha, matrices[k], v)

        return regular
    flow = engine.flow
    if flow.form != "modal":  # Schur or expm forms: Φ e^{τA} by expm per gap
        def exact(k: int, v: np.ndarray, alpha: float) -> np.ndarray:
            nodal = np.asarray(flow.nodal_flow(float(taus[k])), dtype=float)[:, :-1]
            return alpha * (basis @ (nodal.T @ v))

        return exact
    B = np.asarray(flow.B, dtype=float)[:, :-1]
    G = basis @ np.linalg.inv(flow.V).T  # Φ V⁻ᵀ (Q, N)
    real, pairs = flow.scales(taus)
    real, pairs = np.asarray(real, dtype=float), np.asarray(pairs, dtype=complex)
    r = flow.r

    def modal(k: int, v: np.ndarray, alpha: float) -> np.ndarray:
        d = B.T @ v
        d[:r] *= real[k]
        z = (d[r:N:2] + 1j * d[r + 1:N:2]) * np.conj(pairs[k])
        d[r:N:2], d[r + 1:N:2] = z.real, z.imag
        return alpha * (G @ d)

    return modal
