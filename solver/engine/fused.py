"""Fused chunks: the update factor and the moments inside each compiled row, no K×Q arrays.

The common chunk — every row observed with the same components, continuous increments (the stable
form's factor exp(Δyᵀ R⁻¹h − τ ½hᵀR⁻¹h)) or discrete Gaussian rows, regular rows or irregular rows
in modal coordinates (each row's scales e^{τΛ} made in the row, not K×N in numpy before the loop) or
in the Schur coordinates of an ill-conditioned generator (e^{τT} by solver/engine/powers.py's tables in
the row), no
moving frame or ball, no caller that cuts the chunk — runs in
solver/engine/compiled.py ``run_fused``: each row computes its factor's exponent at the nodes (the
operations of solver/measurement.py ``log_factors``, in its order: bit for bit), its max, the factor,
σ = s ⊙ e and Πσ, then keeps of σ only the sums the estimates and checks read (the moments' features
· σ, the diagnostics' functionals · σ, Σ w min(σ, 0) and argmax σ: solver/engine/finish.py
``Summary``).  Neither the factors (K×Q), nor their exponents, nor σ (K×Q) are stored.  On regular
rows in double precision with fewer nodes than 2(N + 1) (the 1-D meshes) a row is one product: s_{k+1} =
PΠσ_k/∫σ_k by the Q × Q operator PΠ made once (:func:`_operator`; Πσ only after the chunk's last row):
examples/cubic_sensor.toml's rows 5.8 against 8.1 µs (Q = 159, N = 128; bench/results/compiled.md).

The factor's exponential is solver/engine/compiled.py's ``exp_shifted`` (a polynomial LLVM vectorises,
within 2 ulp of numpy's), and the sums are BLAS's (numpy's einsum adds in another order): the fused
chunk agrees with the numpy path to rounding (tests/solver/engine/test_compiled.py: 1e-10 relative in
double, 1e-5 in single, per column).  The exponents and ``top`` are bit-identical.  The compiled loops
that keep σ use the same exp (loops.py ``update_factors``) and the same sums (finish.py
``summarise``): a compiled chunk's numbers do not depend on whether it ran fused, so they do not
depend on how the rows are chunked.

Chunks of regular rows of several states of one engine step together in :func:`run_fused_batch`
(solver/engine/compiled_batch.py: gemms a row for all of them; called by solver/engine/batch.py).

Anything rarer goes back to the path that keeps σ, for the whole chunk (:func:`run_fused` returns
None): a row whose ∫σ is outside (tiny, huge) or under the gate's floor (the slow path needs s and
the log factor), an exponent that is not finite, or a step the checks find implausible (its
explanation and the state there need σ).
"""

from __future__ import annotations

import weakref
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from .. import jit
from .finish import Recompute, Summary, summary_rows
from .gate import Gate, Prepared


def fusable(engine: Any, rows: np.ndarray, taus: np.ndarray | None) -> bool:
    """Whether a chunk can run fused (before its factors are computed)."""
    obs = engine.observation
    if not jit.enabled() or engine.form == "literal" or engine.frame is not None or not len(rows):
        return False
    if obs.discrete and obs.likelihood != "gaussian":
        return False
    if taus is not None and engine.flow.exact:
        return False
    return not np.isnan(rows).any()


def run_fused(engine: Any, state: Any, rows: np.ndarray, steps: np.ndarray, times: np.ndarray,
              taus: np.ndarray | None, gating: bool):
    """The chunk fused (module docstring): (new state, ChunkResult), or None where it must run on the
    path that keeps σ."""
    if not fusable(engine, rows, taus):  # before the import: the numpy kernel never imports numba
        return None
    from . import compiled  # numba: imported on the first chunk
    K, N, dtype = len(rows), engine.N, engine.arith.dtype
    given = _inputs(engine, state, rows, taus, gating)
    fixed, carried = given.fixed, given.initial.copy()
    following = np.empty_like(carried)
    real, pairs, triangular = fixed.real, fixed.pairs, fixed.no_schur
    if taus is None:
        P, projection = fixed.propagator, fixed.projection
    else:
        flow = engine.flow
        carried[:N] = flow.to_modal(carried[:N].astype(float))
        P, projection = flow.B, flow.C
        if flow.powers is None:
            real = np.ascontiguousarray(flow.real_rates, dtype=float)
            pairs = np.ascontiguousarray(flow.pair_rates, dtype=complex)
        else:
            triangular = _schur_arguments(flow.powers, taus, N, dtype)
    combined = taus is None and fixed.operator is not None
    from_nodal = combined and _continues(state, fixed.projection, fixed.weights, given.initial)
    nodal = state.nodal.copy() if from_nodal else np.empty(len(engine.nodes), dtype=dtype)
    summary = fixed.summary
    sums = np.empty((K, summary.shape[1]))
    negative, mode, top, masses = np.empty(K), np.empty(K, dtype=np.int64), np.empty(K), np.empty(K)
    done = compiled.run_fused(0, K, np.asfortranarray(P), np.asfortranarray(projection), carried, following,
                              carried.item(N), fixed.exponent_terms, given.y, given.gaps, given.constants,
                              bool(engine.observation.discrete), fixed.negligible, given.floor_exponents,
                              summary, fixed.weights, sums, negative, mode, top, masses, engine.arith.tiny,
                              engine.arith.huge, taus is not None and not triangular[0], real, pairs,
                              *triangular, combined,
                              fixed.no_operator if fixed.operator is None else fixed.operator, nodal,
                              from_nodal)
    if done < K:
        return None
    if K % 2:  # the compiled loop swapped the buffers after each row
        carried = following
    return _finished(engine, state, rows, steps, times, taus, given, (sums, negative, mode, top, masses),
                     carried.copy(), nodal if combined else None)


def batch_fusable(engine: Any, rows: np.ndarray) -> bool:
    """Whether a chunk of regular rows can run in :func:`run_fused_batch`."""
    return fusable(engine, rows, None)


def run_fused_batch(engine: Any, items: list[tuple], gating: bool = True) -> list[tuple | None]:
    """Chunks of regular rows of several states, each :func:`batch_fusable`, their rows stepped together
    (solver/engine/compiled_batch.py): per item (state, rows, steps, times) its (new state, ChunkResult)
    as :func:`run_fused` gives it alone up to rounding, or None where it must run alone."""
    from .compiled_batch import run_fused_batch as kernel

    order = sorted(range(len(items)), key=lambda i: -len(items[i][1]))  # the kernel's: longest first
    if order != list(range(len(items))):
        ordered = run_fused_batch(engine, [items[i] for i in order], gating)
        return [ordered[order.index(i)] for i in range(len(items))]

    S, Kmax, N, dtype = len(items), len(items[0][1]), engine.N, engine.arith.dtype
    given = [_inputs(engine, state, rows, None, gating) for state, rows, _, _ in items]
    fixed = given[0].fixed
    combined = fixed.operator is not None
    Q, F, m = len(engine.nodes), fixed.summary.shape[1], given[0].y.shape[1]
    lengths = np.array([len(rows) for _, rows, _, _ in items], dtype=np.int64)
    y, constants = np.zeros((S, Kmax, m)), np.zeros((S, Kmax))
    floors = np.full((S, Kmax), -np.inf)
    nodal, from_nodal = np.empty((S, Q), dtype=dtype), np.zeros(S, dtype=bool)
    for j, ((state, _, _, _), ready) in enumerate(zip(items, given, strict=True)):
        K = lengths[j]
        y[j, :K], constants[j, :K], floors[j, :K] = ready.y, ready.constants, ready.floor_exponents
        if combined and _continues(state, fixed.projection, fixed.weights, ready.initial):
            nodal[j], from_nodal[j] = state.nodal, True
    initial = np.stack([ready.initial for ready in given])
    sums = np.empty((S, Kmax, F))
    negative, mode, top, masses = (np.empty((S, Kmax)), np.empty((S, Kmax), dtype=np.int64),
                                   np.empty((S, Kmax)), np.empty((S, Kmax)))
    following, done = np.empty((S, N + 1), dtype=dtype), np.empty(S, dtype=np.int64)
    # placeholder: Fortran-only (a 1 × 1 array would type as C: another compiled signature)
    operator = fixed.operator if combined else np.empty((2, 2), dtype=dtype, order="F")
    kernel(lengths, combined, operator, fixed.propagator,
           fixed.projection, initial, from_nodal, nodal, fixed.exponent_terms, y,
           np.full(Kmax, engine.model.dt), constants, bool(engine.observation.discrete), fixed.negligible,
           floors, fixed.summary, fixed.weights, sums, negative, mode, top, masses, engine.arith.tiny,
           engine.arith.huge, following, done)
    out: list[tuple | None] = []
    for j, ((state, rows, steps, times), ready) in enumerate(zip(items, given, strict=True)):
        K = lengths[j]
        out.append(None if done[j] < K else _finished(
            engine, state, rows, steps, times, None, ready,
            (sums[j, :K], negative[j, :K], mode[j, :K], top[j, :K], masses[j, :K]), following[j].copy(),
            nodal[j].copy() if combined else None))
    return out


@dataclass(frozen=True)
class _Inputs:
    """One fused chunk's inputs: what :func:`_inputs` makes of its rows before the compiled loop."""

    fixed: _Fixed
    gaps: np.ndarray  # (K,) each row's τ
    keys: np.ndarray  # (K,) the observed components' pattern (all)
    terms: Any  # measurement.py row_terms
    y: np.ndarray  # (K, |o|) the observed components
    gate: Gate | None
    floor_exponents: np.ndarray  # (K,) the gate's floors (−inf: none)
    constants: np.ndarray  # (K,) discrete rows' constants (0 for increments)
    initial: np.ndarray  # [c, ∫σ] carried in, the matrices' precision


def _inputs(engine: Any, state: Any, rows: np.ndarray, taus: np.ndarray | None, gating: bool) -> _Inputs:
    obs, K = engine.observation, len(rows)
    gaps = np.full(K, engine.model.dt) if taus is None else np.ascontiguousarray(taus, dtype=float)
    keys = np.full(K, (1 << rows.shape[1]) - 1, dtype=np.int64)  # every component observed (fusable)
    terms = obs.row_terms(rows, gaps, keys)
    fixed = _fixed(engine, int(keys[0]))
    gate = Gate(obs, terms, keys, gaps, engine, None) if obs.gating and gating else None
    floor_exponents = (np.full(K, -np.inf) if gate is None else
                       np.ascontiguousarray(gate.floor_exponents(np.zeros(K, dtype=bool)), dtype=float))
    constants = np.ascontiguousarray(terms.constant, dtype=float) if obs.discrete else np.zeros(K)
    initial = np.append(state.coefficients, state.mass).astype(engine.arith.dtype)
    return _Inputs(fixed, gaps, keys, terms, np.ascontiguousarray(rows[:, fixed.index], dtype=float), gate,
                   floor_exponents, constants, initial)


def _finished(engine: Any, state: Any, rows: np.ndarray, steps: np.ndarray, times: np.ndarray,
              taus: np.ndarray | None, given: _Inputs, kept: tuple, carried: np.ndarray,
              nodal: np.ndarray | None):
    """(new state, ChunkResult) from the compiled loop's ``kept`` (sums, negative, mode, top, masses) and
    the [c, ∫σ] ``carried`` after the last row (``nodal``: its σ, where the rows took one product), or
    None where the checks need σ."""
    sums, negative, mode, top, masses = kept
    K, missing = len(rows), np.zeros(len(rows), dtype=bool)
    features = sums.shape[1] - 3
    ready = Prepared(given.gaps, given.keys, given.terms, np.empty((K, 0)), top, top.copy(), missing.copy(),
                     missing, missing.copy(), given.gate, given.initial)
    checks = np.empty((K, 4))
    checks[:, :3], checks[:, 3] = sums[:, features:], negative
    result = Summary(sums[:, :features], checks, mode)
    try:
        new_state, chunk = engine.finish(state, rows, steps, times, taus, ready, None, masses, carried, K,
                                         None, summary=result)
    except Recompute:
        return None
    if nodal is not None and not new_state.degenerate:
        new_state = replace(new_state, nodal=nodal)
    return new_state, chunk


def _continues(state: Any, projection: np.ndarray, weights: np.ndarray, initial: np.ndarray) -> bool:
    """Whether the state's ``nodal`` σ is the one its (c, ∫σ) came from (compiled.nodal_matches)."""
    from . import compiled

    nodal = state.nodal
    if nodal is None or nodal.shape != (projection.shape[1],):
        return False
    return compiled.nodal_matches(projection, np.ascontiguousarray(nodal, dtype=projection.dtype), weights,
                                  initial)


@dataclass(frozen=True, eq=False)
class _Fixed:
    """What every fused chunk of one engine and pattern of observed components passes unchanged (made
    once: the arrays are only read)."""

    index: np.ndarray  # the observed components
    exponent_terms: np.ndarray  # [h_o R_oo⁻¹; ½h_oᵀR_oo⁻¹h_o] (|o| + 1, Q)
    propagator: np.ndarray  # Fortran order, the matrices' precision
    projection: np.ndarray
    summary: np.ndarray  # finish.py summary_rows
    weights: np.ndarray
    negligible: np.ndarray  # (1,) in the matrices' precision
    real: np.ndarray  # placeholders of the modal flow's rates (regular rows)
    pairs: np.ndarray
    no_schur: tuple  # :func:`_no_schur`
    operator: np.ndarray | None  # PΠ (Q × Q, Fortran) where it is the smaller product: :func:`_operator`
    no_operator: np.ndarray  # its placeholder (one compiled signature)


_FIXED: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()  # engine -> {pattern key: _Fixed}


def _fixed(engine: Any, key: int) -> _Fixed:
    """:class:`_Fixed` of ``engine`` for the pattern ``key``, cached per engine object (a translated or
    framed copy is another object, with its own)."""
    found = _FIXED.setdefault(engine, {}).get(key)
    if found is None:
        dtype = engine.arith.dtype
        hR, half = engine.update_terms(key)
        found = _Fixed(index=engine.observation.pattern(key).index,
                       exponent_terms=np.ascontiguousarray(np.vstack([hR, half[None]]), dtype=float),
                       propagator=np.asfortranarray(engine.observation_propagator),
                       projection=np.asfortranarray(engine.projection), summary=summary_rows(engine),
                       weights=np.ascontiguousarray(engine.weights, dtype=float),
                       negligible=np.array([engine.arith.negligible], dtype=dtype), real=np.empty(0),
                       pairs=np.empty(0, dtype=complex), no_schur=_no_schur(dtype),
                       operator=_operator(engine), no_operator=np.empty((1, 1), dtype=dtype, order="F"))
        _FIXED[engine][key] = found
    return found


def _operator(engine: Any) -> np.ndarray | None:
    """PΠ (Q × Q, Fortran order): regular rows' s_{k+1} = PΠσ_k/∫σ_k in one product where Q < 2(N + 1),
    fewer flops than P(Πσ) (0.62× on examples/cubic_sensor.toml's Q = 159, N = 128, as
    solver/engine/batch.py's); in double precision only (in single the reordered sums move the moments
    by ~1e-3, solver/engine/batch.py's BATCH_RTOL, beyond the fused rows' 1e-5)."""
    Q, N = engine.nodes.shape[0], engine.N
    if np.dtype(engine.arith.dtype) != np.float64 or Q >= 2 * (N + 1):
        return None
    return np.asfortranarray(np.asarray(engine.propagator, float) @ np.asarray(engine.projection, float))


def _schur_arguments(powers: Any, taus: np.ndarray, N: int, dtype: Any) -> tuple:
    """The Schur form's flow for compiled.run_fused (solver/engine/loops.py ``schur_rows``'s): True, T,
    the tables, the 2×2 blocks' subdiagonal rows and entries, each row's plan and remainder, the Taylor
    degree and two buffers."""
    indices, remainders = powers.plan(taus)
    w, saved = np.empty(N, dtype=dtype), np.empty(N, dtype=dtype)
    return (True, powers.T, powers.stack, powers.lower, powers.subs, indices, remainders, powers.degree, w,
            saved)


def _no_schur(dtype: Any) -> tuple:
    """Placeholders of the same array types as :func:`_schur_arguments` (one compiled signature)."""
    return (False, np.empty(3, dtype=dtype), np.empty((0, 3), dtype=dtype),
            np.empty(0, dtype=np.int64), np.empty((1, 0), dtype=dtype), np.empty((0, 1), dtype=np.int64),
            np.empty(0), 0, np.empty(0, dtype=dtype), np.empty(0, dtype=dtype))
