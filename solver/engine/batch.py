"""Many states of one model stepped together: the hot loop as matrix–matrix products.

Every session of a model shares its propagator P (Q×N) and projector Π (N×Q), so S states c_s
stepped through their chunks one row at a time are S matrix–vector products per step — or one
matrix–matrix product (seed 002 (5.35)/(5.38), as in :mod:`solver.engine`):

    S_k = (C_{k−1} diag(1/∫σ_{k−1}))ᵀ Pᵀ        (S×Q: each state's propagated nodal values)
    Σ_k = S_k ⊙ E_k                              (E_k: each state's update factors exp(log e − max))
    C_k = Σ_k Πᵀ,  ∫σ_k = Σ_k w                  (one product: the weights ride along as a row of Π)

Where the nodes are fewer than twice the basis (the 1-D meshes), P Π is the smaller operator and
one Q×(Q+1) product a step carries the nodal values and ∫σ at once (0.62× the flops of the two
products on the bundled 1-D mesh; measured in bench/engine_batch.py).  The update factors are
elementwise per state and step; chunks of unequal length run together while they last (the
states sorted longest first, the active ones a prefix); a missing row has the factor 1 (it only
predicts).  Before and after the loop each state is treated exactly as
:meth:`YauYauFilter.run_arrays` treats it (the same factors, gate, checks, estimates and new state),
so a result is that of stepping the state alone up to rounding: the products sum in another order
(BLAS gemm against gemv), which changes the last bits of a step.  Measured over chunks of up to 250
rows of the cubic sensor: covariances within 1e-11 relative in double precision and 1.4e-3 in single
(where the single loop itself is 3e-3 from double), means within 4e-13 and 8e-5 (``BATCH_RTOL``,
tested in tests/solver/engine/test_batch.py).  A decision that sits on its threshold to within that
rounding (the gate, a degeneracy check) can go either way, as it can between two BLAS builds.

Where the compiled kernels are on (solver/jit.py) and a chunk's rows are all observed, its state goes to
the compiled batched kernel instead (solver/engine/compiled_batch.py, driven by fused.py
``run_fused_batch``): the same products as gemms (one, PΠ, where it is the smaller; else P and Π) with
each state's factors and sums made inside the row, as the single fused loop makes them — 0.42 against
0.64 ms a 100-row chunk of the cubic sensor at 16 to 48 streams, 0.73 alone (bench/results/engine-batch.md).
A state alone runs ``run_arrays`` itself.

What the loop does not batch runs alone through ``run_arrays``, with the identical answer it always
had: the literal form, irregular ``times`` (each gap its own operator), a degenerate state, and a
state whose step left the fast path (a mass under- or overflowing, a row near the outlier gate:
the loop drops the state at that step and it is rerun alone from the start of its chunk).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from .. import jit
from ..filtering import chunk_clock, per_item
from ..measurement import check_first_gap, check_rows, resolve_times

if TYPE_CHECKING:  # types only
    from numpy.typing import ArrayLike

    from ..errors import InputError
    from ..filtering import ChunkResult
    from .gate import Prepared
    from .state import YauYauState

BATCH_RTOL = {"double": 1e-10, "single": 5e-3}  # relative, against stepping alone (module docstring)
MAX_BATCH_BYTES = 64 << 20  # per array of nodal values (steps × states × nodes) held at once


@dataclass
class _Member:
    """One state of the batch on the fast path."""

    index: int  # in the caller's list
    state: YauYauState
    rows: np.ndarray
    steps: np.ndarray
    times: np.ndarray
    ready: Prepared | None  # while its group runs


def run_batch(engine: Any, states: list[YauYauState], chunks: list[ArrayLike],
              times: list[ArrayLike | None] | None = None,
              return_exceptions: bool = False) -> list[tuple[YauYauState, ChunkResult] | InputError]:
    """Advance ``states[i]`` over ``chunks[i]`` (at ``times[i]``, or one dt apart) for every i:
    [(new state, ChunkResult)], as ``engine.run_arrays`` would give one by one.

    ``return_exceptions``: an item whose input is refused gives its :class:`InputError` in its place
    (the other items are unaffected); else the first such error is raised, naming the item
    (``chunks[i]…``)."""
    def item(i: int, state: YauYauState, chunk: ArrayLike, chunk_times: ArrayLike | None) -> Any:
        member = _fast_member(engine, i, state, chunk, chunk_times)
        return engine.run_arrays(state, chunk, chunk_times) if member is None else member

    out = per_item(states, chunks, times, return_exceptions, item)
    members = [m for m in out if isinstance(m, _Member)]
    for group in _groups(members, len(engine.nodes), np.dtype(engine.arith.dtype).itemsize):
        group = _fused_together(engine, group, out, times)
        if len(group) < 2:  # alone: run_arrays itself (its fused rows where they apply), the same bits
            for member in group:
                out[member.index] = _alone(engine, member, times)
            continue
        for member in group:  # the update factors of this group only: memory bounded by the group
            member.ready = engine.prepare(member.state, member.rows, None, gating=True)
        for member, loop in zip(group, _propagate_together(engine, group), strict=True):
            if loop is None:  # it left the fast path: alone, from the start of its chunk
                out[member.index] = _alone(engine, member, times)
            else:
                out[member.index] = engine.finish(member.state, member.rows, member.steps, member.times,
                                                   None, member.ready, *loop)
            member.ready = None
    return out


def _fused_together(engine: Any, group: list[_Member], out: list[Any],
                    times: list[ArrayLike | None] | None) -> list[_Member]:
    """The group's members whose rows are all observed stepped by the compiled batched kernel
    (solver/engine/compiled_batch.py, where ``jit.enabled()``): their results put in ``out`` (one that
    leaves the fast path: alone, from the start of its chunk); the other members returned, for the numpy
    loop below."""
    if len(group) < 2 or not jit.enabled():
        return group
    from .fused import batch_fusable, run_fused_batch

    fast = [batch_fusable(engine, member.rows) for member in group]
    if sum(fast) < 2:
        return group
    chosen = [member for member, ok in zip(group, fast, strict=True) if ok]
    results = run_fused_batch(engine, [(m.state, m.rows, m.steps, m.times) for m in chosen])
    for member, result in zip(chosen, results, strict=True):
        out[member.index] = result if result is not None else _alone(engine, member, times)
    return [member for member, ok in zip(group, fast, strict=True) if not ok]


def _alone(engine: Any, member: _Member, times: list[ArrayLike | None] | None) -> Any:
    """The member's chunk through ``run_arrays``, from the start, with its times as given."""
    return engine.run_arrays(member.state, member.rows, None if times is None else times[member.index])


def _fast_member(engine: Any, index: int, state: YauYauState, chunk: ArrayLike,
                 chunk_times: ArrayLike | None) -> _Member | None:
    """The item made ready for the batched loop, or None when it runs alone (module docstring)."""
    model, obs = engine.model, engine.observation
    rows = check_rows(chunk, model.m, "observations" if obs.discrete else "increments")
    K = rows.shape[0]
    taus = resolve_times(state.t, state.step > 0, K, model.dt, chunk_times)
    check_first_gap(taus, obs.discrete)
    if K == 0 or taus is not None or engine.form != "stable" or state.degenerate:
        return None
    steps, clock = chunk_clock(state, K, model.dt, None, None)
    return _Member(index, state, rows, steps, clock, None)  # prepared with its group (bounded memory)


def _groups(members: list[_Member], Q: int, itemsize: int) -> list[list[_Member]]:
    """The members, longest chunk first, in groups whose arrays (steps × states × nodes) stay under
    MAX_BATCH_BYTES (a group holds at least one)."""
    ordered = sorted(members, key=lambda m: -len(m.rows))
    groups: list[list[_Member]] = []
    for member in ordered:
        if groups and len(groups[-1][0].rows) * (len(groups[-1]) + 1) * Q * itemsize <= MAX_BATCH_BYTES:
            groups[-1].append(member)
        else:
            groups.append([member])
    return groups


def _propagate_together(engine: Any, group: list[_Member]) -> list[tuple | None]:
    """The hot loop of :meth:`YauYauFilter.propagate` for the group's states at once (sorted longest
    first).  Per member: (σ_k (K, Q), ∫σ_k (K,), carried (N+1,), K, None) as the single loop returns
    them, or None when the member needs a slow step (dropped: its row is zeroed and left to ride).
    The group has two members at least (one alone runs ``run_arrays`` itself)."""
    arith, N = engine.arith, engine.N
    dtype = arith.dtype
    S, Kmax, Q = len(group), len(group[0].rows), len(engine.nodes)
    lengths = np.array([len(m.rows) for m in group])
    factor = np.ones((Kmax, S, Q), dtype=dtype)  # 1 past a member's end and on rows that only predict
    # the fast path holds while tiny < ∫σ_k < huge and ∫σ_k ≥ the gate's floor (else a slow step)
    lower = np.full((Kmax, S), np.nextafter(arith.tiny, np.inf))
    for s, member in enumerate(group):
        ready, K = member.ready, len(member.rows)
        np.exp(ready.log_factor, out=factor[:K, s], casting="same_kind")
        if ready.gate is not None:
            np.maximum(lower[:K, s], ready.gate.floors(ready.top, ready.skip), out=lower[:K, s])
    factor[factor < arith.negligible] = 0.0
    sigma = np.empty((Kmax, S, Q), dtype=dtype)
    masses = np.zeros((Kmax, S))
    carried = np.stack([m.ready.initial for m in group]).astype(dtype, copy=False)  # (S, N+1)
    np.divide(carried, carried[:, N:].copy(), out=carried)  # a unit-mass σ: the loop's 1/∫σ
    following = np.empty_like(carried)
    propagate_t = np.ascontiguousarray(engine.propagator.T)  # (N+1, Q), zero last row
    project_t = np.ascontiguousarray(engine.projection.T)  # (Q, N+1), the weights as last column
    scratch = np.empty((S, Q), dtype=dtype)
    dropped = np.zeros(S, dtype=bool)
    finals: list[np.ndarray | None] = [None] * S
    ending: dict[int, list[int]] = {}
    for s, K in enumerate(lengths.tolist()):
        ending.setdefault(K - 1, []).append(s)
    huge, matmul, multiply, divide = arith.huge, np.matmul, np.multiply, np.divide
    actives = (lengths[None, :] > np.arange(Kmax)[:, None]).sum(axis=1).tolist()  # a prefix: longest first
    # Where the nodes are fewer than twice the basis, P Π is the smaller operator: the next step's
    # nodal values straight from this step's, σ ↦ (P Π σ) ⊙ e / ∫σ, with the weights as an extra
    # column giving ∫σ in the same product (one Q×(Q+1) product a step instead of two Q×(N+1)).
    fused = Q + 1 < 2 * (N + 1)
    if fused:
        operator = np.empty((Q, Q + 1), dtype=dtype)
        operator[:, :Q] = (engine.propagator[:, :N].astype(float) @ engine.projection[:N].astype(float)).T
        operator[:, Q] = engine.projection[N]
        extended = np.empty((S, Q + 1), dtype=dtype)

    def check(new: np.ndarray, step: int, rows: np.ndarray, low: np.ndarray) -> None:
        """Drop the members whose ∫σ at ``step`` leaves the fast path (their ``rows`` zeroed)."""
        if not ((new >= low[step]) & (new < huge)).all() or dropped.any():
            bad = ~((new >= low[step]) & (new < huge))
            n = len(new)
            dropped[:n] |= bad
            rows[dropped[:n]] = 0.0
            new[dropped[:n]] = 1.0  # a dropped member rides along as zeros

    a = -1
    for k, active in enumerate(actives):
        if active != a:  # the views of the active prefix, made again only when a member ends
            a = active
            c, f, s_a, low, mass_k = carried[:a], following[:a], scratch[:a], lower[:, :a], masses[:, :a]
        row = sigma[k, :a]
        if fused and k:
            e_a = extended[:a]
            matmul(sigma[k - 1, :a], operator, out=e_a)
            new = e_a[:, Q].astype(float)  # ∫σ_{k−1}
            check(new, k - 1, sigma[k - 1, :a], low)
            mass_k[k - 1] = new
            multiply(e_a[:, :Q], factor[k, :a], out=row)
            divide(row, new[:, None].astype(dtype), out=row)
            continue
        matmul(c, propagate_t, out=s_a)
        multiply(s_a, factor[k, :a], out=row)
        if fused:
            continue
        matmul(row, project_t, out=f)
        new = f[:, N].astype(float)
        check(new, k, f, low)
        mass_k[k] = new
        for s in ending.get(k, ()):  # a member's last row: keep its vector as the single loop has it
            finals[s] = f[s].copy()
        divide(f, new[:, None], out=f)
        carried, following = following, carried
        c, f = f, c
    if fused:  # each member's last step: its ∫σ and its coefficients, as the single loop carries them
        for s, K in enumerate(lengths.tolist()):
            final = sigma[K - 1, s] @ project_t
            if not lower[K - 1, s] <= float(final[N]) < huge:
                dropped[s] = True
            elif not dropped[s]:
                masses[K - 1, s] = final[N]
                finals[s] = final
    out: list[tuple | None] = []
    for s, member in enumerate(group):
        if dropped[s]:
            out.append(None)
            continue
        K = len(member.rows)
        out.append((sigma[:K, s], masses[:K, s], finals[s], K, None))
    return out
