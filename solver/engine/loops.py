"""The hot loops of the engine: one per kind of chunk, each a few named steps over the kernel.

* :func:`loop_regular` — rows one dt apart: the stored propagator over dt (seed 002 (5.35)/(5.38)).
* :func:`loop_irregular` — rows at any times: the coefficients carried in the modal coordinates of
  solver/engine/semigroup.py and scaled by e^{τΛ} before the same two products (for an ill-conditioned
  generator: in its Schur coordinates, through e^{τT} by a few precomputed matrices, :func:`schur_rows`;
  or, where those would not fit, the nodal flow Φe^{τA} of each gap).
* :func:`loop_moving` — a ball that moves inside the loop (solver/engine/recentring.py): after a row
  whose mean or outer-shell mass calls for it, the carried density moves onto a ball around the mean;
  the update factors come a window at a time.  Irregular rows there run in the ball's modal
  coordinates, as :func:`loop_irregular`'s.

Each returns (σ_k, ∫σ_k, carried, done, reason): the nodal σ_k of the good steps (pre-projection, K×Q,
each relative to a unit-mass σ_{k−1}), their ∫σ_k, the carried vector [c, ∫σ] after the last, the
number of good steps and why the loop stopped early (None: it did not).  A step whose ∫σ under- or
overflows, or an observed row whose cheap gate bound is over its threshold, takes the slow path
(:func:`slow_step`: log scale, the exact gate score).

Where numba is (``YAUYAU_KERNEL``, solver/jit.py), the three loops run their rows in the
compiled loops of solver/engine/compiled.py, which stop at a row that needs the slow path (or, on a
moving ball, after a row whose trigger fired): :func:`run_compiled` and :func:`moving_compiled` take
that row's slow step (or the move, or the next window of factors) here and re-enter at the next row —
the same numbers to rounding (the compiled kernel's factors are its polynomial exponential,
:func:`update_factors`, within 2 ulp of numpy's; its moments BLAS sums, solver/engine/finish.py
``summarise``); the Python loops stay the reference, ``YAUYAU_KERNEL=numpy``.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any, Callable

import numpy as np

from .. import jit
from .gate import Gate
from .kernel import NO_MASS_AFTER_UPDATE, NO_MASS_ON_BALL, log_mean_factor, observe, predict, project, rescue

if TYPE_CHECKING:  # types only
    from .recentring import Recentring
    from .semigroup import SpectralFlow

Result = tuple[np.ndarray, np.ndarray, np.ndarray, int, "str | None"]


def update_factors(arith: Any, log_factor: np.ndarray) -> np.ndarray:
    """e_k = exp(log e_k − max) in the loop's precision, 0 under ``negligible`` (K, Q): numpy's exp, or
    with the compiled kernel the fused rows' (solver/engine/compiled.py ``exp_factors``)."""
    if jit.enabled() and log_factor.size:
        from . import compiled  # numba: imported on the first chunk

        factor = np.empty(log_factor.shape, dtype=arith.dtype)
        compiled.exp_factors(np.ascontiguousarray(log_factor, dtype=float),
                             np.array([arith.negligible], dtype=arith.dtype), factor)
        return factor
    factor = np.exp(log_factor).astype(arith.dtype, copy=False)
    factor[factor < arith.negligible] = 0.0
    return factor


class Rows:
    """What the loops share: the chunk's buffers, its factors and gate, and one step of the kernel."""

    def __init__(self, engine: Any, factor: np.ndarray, log_factor: np.ndarray, top: np.ndarray,
                 skip: list[bool], gate: Gate | None, compiled: bool = True):
        K, Q = log_factor.shape
        dtype = engine.arith.dtype
        self.engine, self.factor, self.log_factor, self.top, self.gate = engine, factor, log_factor, top, gate
        self.sigma = np.empty((K, Q), dtype=dtype)
        self.scratch = np.empty(Q, dtype=dtype)
        self.masses: Any = [0.0] * K
        self.observed = [not m for m in skip]
        # the gate's bound g = bias − 2(log ∫σ + top) ≤ threshold is ∫σ ≥ floor: one comparison a step
        self.floors = [0.0] * K if gate is None else gate.floors(top, skip)
        self.reason: str | None = None
        self.compiled = compiled and K > 0 and jit.enabled()
        if self.compiled:  # the compiled loops' arguments: arrays
            self.masses = np.zeros(K)
            self.observed_array = np.array(self.observed, dtype=bool)
            self.floor_array = np.array(self.floors, dtype=float)
        else:
            self.step = _stepper(engine, self, factor, log_factor, top, gate)

    def result(self, done: int, carried: np.ndarray) -> Result:
        return self.sigma, np.array(self.masses[:done]), carried.copy(), done, self.reason


def _stepper(engine: Any, rows: Rows, factor: np.ndarray, log_factor: np.ndarray, top: np.ndarray,
             gate: Gate | None) -> Callable[..., float]:
    """step(k, P, P_observe, Π, carried, following, mass) -> ∫σ_k: row k from the carried vector into
    ``following`` (a closure: the hot loop reads its constants from cells, not attributes)."""
    arith, N = engine.arith, engine.N
    tiny, huge = arith.tiny, arith.huge
    scratch = rows.scratch
    sigma_rows, factors, observed, floors, masses = (list(rows.sigma), list(factor), rows.observed,
                                                     rows.floors, rows.masses)

    def step(k: int, propagator: np.ndarray, observing: np.ndarray, projection: np.ndarray,
             carried: np.ndarray, following: np.ndarray, mass: float) -> float:
        row = sigma_rows[k]
        if observed[k]:
            observe(arith, observing, carried, mass, factors[k], scratch, row)
        else:
            predict(arith, propagator, carried, mass, row)
        new_mass = project(arith, projection, row, following, N)
        if not tiny < new_mass < huge or new_mass < floors[k]:  # rare: rescue, or a row near the gate
            s = scratch if observed[k] else row
            new_mass, rows.reason = slow_step(engine, k, new_mass, s, row, observed[k], log_factor, top, gate,
                                              projection, following)
        masses[k] = new_mass
        return new_mass

    return step


def loop_regular(engine: Any, carried: np.ndarray, factor: np.ndarray, log_factor: np.ndarray,
                 top: np.ndarray, skip: list[bool], gate: Gate | None) -> Result:
    """Rows one dt apart, two BLAS calls a step."""
    rows = Rows(engine, factor, log_factor, top, skip, gate)
    P, P_observe, projection = engine.propagator, engine.observation_propagator, engine.projection
    carried, following = carried.copy(), np.empty_like(carried)  # two buffers, alternately each
    mass = carried.item(engine.N)
    if rows.compiled:
        k, carried, _, _ = run_compiled(rows, 0, len(factor), (P, P_observe, projection), carried, following,
                                        mass)
        return rows.result(k, carried)
    step = rows.step
    for k in range(len(factor)):
        mass = step(k, P, P_observe, projection, carried, following, mass)
        if rows.reason is not None:
            return rows.result(k, carried)
        carried, following = following, carried
    return rows.result(len(factor), carried)


def loop_irregular(engine: Any, carried: np.ndarray, factor: np.ndarray, log_factor: np.ndarray,
                   top: np.ndarray, skip: list[bool], gate: Gate | None, taus: np.ndarray) -> Result:
    """Rows at any times: the flow e^{τA} of each gap (solver/engine/semigroup.py), modal where the
    generator's eigenbasis is well conditioned (a diagonal scaling before the products), else nodal."""
    rows, flow, N, K = Rows(engine, factor, log_factor, top, skip, gate), engine.flow, engine.N, len(factor)
    if flow.exact:  # ill-conditioned: Φe^{τA} at the nodes, one matrix a gap
        carried, following = carried.copy(), np.empty_like(carried)
        mass = carried.item(N)
        if rows.compiled:  # a compiled run of rows per run of equal gaps
            start = 0
            for stop in [*(np.flatnonzero(np.diff(taus)) + 1).tolist(), K]:
                P = flow.nodal_flow(taus[start])
                k, carried, following, mass = run_compiled(rows, start, stop, (P, P, engine.projection),
                                                           carried, following, mass)
                if rows.reason is not None:
                    return rows.result(k, carried)
                start = stop
            return rows.result(K, carried)
        for k in range(K):
            P = flow.nodal_flow(taus[k])
            mass = rows.step(k, P, P, engine.projection, carried, following, mass)
            if rows.reason is not None:
                return rows.result(k, carried)
            carried, following = following, carried
        return rows.result(K, carried)
    carried = carried.copy()
    carried[:N] = flow.to_modal(carried[:N].astype(float))
    carried, following = carried.copy(), np.empty_like(carried)
    mass = carried.item(N)
    if flow.powers is not None:  # Schur coordinates: e^{τT} by the tables before the two products
        return schur_rows(rows, flow, taus, carried, following, mass)
    scale = ModalScale(flow, taus, carried, following, N, engine.arith.dtype)
    if rows.compiled:
        k, carried, _, _ = run_compiled(rows, 0, K, (flow.B, flow.B, flow.C), carried, following, mass,
                                        scale.compiled())
        return rows.result(k, carried)
    for k in range(K):
        scale.apply(k)
        mass = rows.step(k, flow.B, flow.B, flow.C, carried, following, mass)
        if rows.reason is not None:
            return rows.result(k, carried)
        carried, following = following, carried
        scale.swap()
    return rows.result(K, carried)


def schur_rows(rows: Rows, flow: SpectralFlow, taus: np.ndarray, carried: np.ndarray, following: np.ndarray,
               mass: float) -> Result:
    """:func:`loop_irregular` in the Schur coordinates of an ill-conditioned generator: each row first
    takes the carried coefficients through e^{τ_kT} (solver/engine/powers.py: its Taylor polynomial and
    tables, product by product), then the engine's two products with ΦU and [UᵀΦᵀW; wᵀ]."""
    powers, engine, N, K = flow.powers, rows.engine, rows.engine.N, len(taus)
    assert powers is not None
    indices, remainders = powers.plan(taus)
    w, saved = np.empty(N, dtype=engine.arith.dtype), np.empty(N, dtype=engine.arith.dtype)
    if rows.compiled:
        k, carried, _, _ = run_compiled(rows, 0, K, (flow.B, flow.B, flow.C), carried, following, mass,
                                        schur=(powers.T, powers.stack, powers.lower, powers.subs, indices,
                                               remainders, powers.degree, w, saved))
        return rows.result(k, carried)
    remainder_list = remainders.tolist()
    for k in range(K):
        powers.advance(carried[:N], indices[k], remainder_list[k], w, saved)
        mass = rows.step(k, flow.B, flow.B, flow.C, carried, following, mass)
        if rows.reason is not None:
            return rows.result(k, carried)
        carried, following = following, carried
    return rows.result(K, carried)


def run_compiled(rows: Rows, start: int, stop: int, matrices: tuple[np.ndarray, np.ndarray, np.ndarray],
                 carried: np.ndarray, following: np.ndarray, mass: float,
                 scales: tuple[np.ndarray, ...] | None = None, schur: tuple | None = None):
    """Rows start..stop−1 in the compiled loops (solver/engine/compiled.py: ``matrices`` = (P, P for
    observed rows, Π), ``scales`` the modal scaling, ``schur`` the Schur form's (T, tables, subdiagonal
    rows and entries, plan, remainders, degree, two buffers), else None), each row that needs it through
    :func:`slow_step` here.  Returns (the row it stopped at: ``stop``, or the row whose slow step
    failed with ``rows.reason``; carried; following; ∫σ)."""
    from . import compiled  # numba: imported on the first chunk

    engine = rows.engine
    tiny, huge = engine.arith.tiny, engine.arith.huge
    P, P_observe, projection = (np.asfortranarray(matrix) for matrix in matrices)  # stored so: no copy
    masses, sigma, scratch = rows.masses, rows.sigma, rows.scratch
    k = start
    while k < stop:
        if schur is not None:
            j = compiled.run_schur(k, stop, P, projection, carried, following, mass, rows.factor,
                                   rows.observed_array, rows.floor_array, sigma, scratch, masses, tiny, huge,
                                   *schur)
        elif scales is None:
            j = compiled.run_rows(k, stop, P, P_observe, projection, carried, following, mass, rows.factor,
                                  rows.observed_array, rows.floor_array, sigma, scratch, masses, tiny, huge)
        else:
            j = compiled.run_modal(k, stop, P, projection, carried, following, mass, rows.factor,
                                   rows.observed_array, rows.floor_array, sigma, scratch, masses, tiny, huge,
                                   *scales)
        if (j - k) % 2:  # the compiled loop swapped the buffers after each row it finished
            carried, following = following, carried
        if j > k:
            mass = float(masses[j - 1])
        if j == stop:
            break
        observed = bool(rows.observed_array[j])  # as the compiled loop read it
        new_mass, rows.reason = slow_step(engine, j, float(masses[j]), scratch if observed else sigma[j],
                                          sigma[j], observed, rows.log_factor, rows.top, rows.gate,
                                          projection, following)
        masses[j] = new_mass
        if rows.reason is not None:
            return j, carried, following, mass
        mass = new_mass
        carried, following = following, carried
        k = j + 1
    return stop, carried, following, mass


class ModalScale:
    """e^{τ_kΛ} on the modal coefficients of the carried vector, in place: real rates, then each complex
    pair (u, w) ← u·(Re z, Im z) + w·(−Im z, Re z) — real products and sums (numpy's complex product
    may fuse them, by CPU), the operations of the compiled loop (views on both buffers, swapped with
    them)."""

    def __init__(self, flow: SpectralFlow, taus: np.ndarray, carried: np.ndarray, following: np.ndarray,
                 N: int, dtype: type):
        r = flow.r
        real, pairs = flow.scales(taus)
        self.real = real
        self.first = np.ascontiguousarray(np.stack([pairs.real, pairs.imag], axis=-1), dtype=dtype)
        self.second = np.ascontiguousarray(np.stack([-pairs.imag, pairs.real], axis=-1), dtype=dtype)
        self.real_scale, self.first_rows, self.second_rows = list(real), list(self.first), list(self.second)
        self.pairs = flow.pair_rates.size > 0
        p = pairs.shape[1]
        self.real_c, self.real_f = carried[:r], following[:r]
        self.pair_c, self.pair_f = carried[r:N].reshape(p, 2), following[r:N].reshape(p, 2)
        self.u_c, self.u_f = carried[r:N:2, None], following[r:N:2, None]
        self.w_c, self.w_f = carried[r + 1:N:2, None], following[r + 1:N:2, None]
        self.terms = (np.empty((p, 2), dtype=dtype), np.empty((p, 2), dtype=dtype))

    def compiled(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The scaling as the compiled loop takes it: real (K, r), pairs' first and second (K, p, 2)."""
        return self.real, self.first, self.second

    def apply(self, k: int) -> None:
        np.multiply(self.real_c, self.real_scale[k], out=self.real_c)
        if self.pairs:
            first, second = self.terms
            np.multiply(self.u_c, self.first_rows[k], out=first)
            np.multiply(self.w_c, self.second_rows[k], out=second)
            np.add(first, second, out=self.pair_c)

    def swap(self) -> None:
        self.real_c, self.real_f = self.real_f, self.real_c
        self.pair_c, self.pair_f = self.pair_f, self.pair_c
        self.u_c, self.u_f = self.u_f, self.u_c
        self.w_c, self.w_f = self.w_f, self.w_c


def loop_moving(engine: Any, carried: np.ndarray, log_factor: np.ndarray, top: np.ndarray,
                skip: list[bool], gate: Gate | None, moving: Recentring,
                taus: np.ndarray | None = None) -> Result:
    """Rows on a ball that moves inside the loop (solver/engine/recentring.py): the carried vector holds
    the trigger's sums after ∫σ (Σw(x − c)_iσ along the moving directions, then the outer shell's Σwσ);
    past ±reach·∫σ, or the shell over its limit, the ball moves onto the mean.  Rows one dt apart take
    the stored propagator (an atlas centre's); rows at gaps ``taus`` the ball's modal flow, as
    :func:`loop_irregular` (d = V⁻¹a scaled by e^{τΛ}, then ΦV and [V⁻¹ΦᵀW; wᵀ; the trigger's rows]),
    a move carrying Φ V d into the new ball's modal coordinates; the carried vector it returns is
    the nodal coefficients a = V d again."""
    rows = Rows(engine, moving.factor, log_factor, top, skip, gate)
    N, K, flow = engine.N, len(log_factor), moving.flow
    # the windows write the rows' floors and mark impossible rows unobserved: where the loop reads them
    moving.observed, moving.floors = ((rows.observed_array, rows.floor_array) if rows.compiled
                                      else (rows.observed, rows.floors))
    carried = np.concatenate([carried, np.zeros(moving.d + 1, dtype=carried.dtype)])
    if flow is not None:
        carried[:N] = flow.to_modal(carried[:N].astype(float))
    carried, following = carried.copy(), np.empty_like(carried)
    if rows.compiled:
        return _nodal(moving_compiled(rows, moving, carried, following, taus), moving, N)
    P, P_observe = moving.matrices()
    scale = None if flow is None else ModalScale(flow, taus, carried, following, N, engine.arith.dtype)
    step = rows.step
    watch, shell = tuple(range(N + 1, N + 1 + moving.d)), N + 1 + moving.d
    reach, shell_limit = moving.reach, moving.shell_limit
    mass, next_window = carried.item(N), 0
    for k in range(K):
        if k == next_window:  # the update factors of the next rows at the ball's centre
            next_window = moving.window(k)
        if scale is not None:
            scale.apply(k)
        mass = step(k, P, P_observe, moving.project, carried, following, mass)
        if rows.reason is not None:
            return _nodal(rows.result(k, carried), moving, N)
        carried, following = following, carried
        if scale is not None:
            scale.swap()
        if not watch or k == K - 1 or not _strayed(carried, mass, watch, reach, shell, shell_limit) \
                or k < moving.quiet:
            continue
        moved = moving.move(k, carried, following, mass)
        if moved is None:  # the loop cannot move on: the chunk ends after row k
            moving.stopped = k + 1
            return _nodal(rows.result(k + 1, carried), moving, N)
        if moved > 0.0:
            mass = moved
            carried, following = following, carried
            next_window = moving.window(k + 1)
            P, P_observe = moving.matrices()
            if scale is not None:  # the new ball's rates (an atlas centre's), on the swapped buffers
                scale = ModalScale(moving.flow, taus, carried, following, N, engine.arith.dtype)
    return _nodal(rows.result(K, carried), moving, N)


def _nodal(result: Result, moving: Recentring, N: int) -> Result:
    """The carried vector of :func:`loop_moving` back in nodal coefficients a = V d where it ran in the
    ball's modal coordinates (each ball its own V: the engine's state does not keep them)."""
    if moving.flow is None:
        return result
    sigma, masses, carried, done, reason = result
    carried = carried.astype(float)
    carried[:N] = moving.flow.from_modal(carried[:N])
    return sigma, masses, carried, done, reason


def moving_compiled(rows: Rows, moving: Any, carried: np.ndarray, following: np.ndarray,
                    taus: np.ndarray | None = None) -> Result:
    """:func:`loop_moving` with the rows between windows, slow steps and moves in the compiled loop
    (solver/engine/compiled.py ``run_moving``, irregular rows scaled there by e^{τΛ} with libm's exp, as
    the fused rows); the windows, slow steps and moves in Python, as there."""
    from . import compiled  # numba: imported on the first chunk

    engine = rows.engine
    N, K, d = engine.N, len(rows.factor), moving.d
    tiny, huge = engine.arith.tiny, engine.arith.huge
    watch, shell = tuple(range(N + 1, N + 1 + d)), N + 1 + d
    gaps = np.zeros(0) if taus is None else np.ascontiguousarray(taus, dtype=float)
    P, P_observe, projection, rates = _moving_arrays(moving)
    masses, sigma, scratch, observed = rows.masses, rows.sigma, rows.scratch, rows.observed_array
    mass, next_window, k = carried.item(N), 0, 0
    while k < K:
        if k == next_window:  # the update factors of the next rows at the ball's centre
            next_window = moving.window(k)
        stop = K if next_window < 0 else next_window
        j, strayed = compiled.run_moving(k, stop, P, P_observe, projection, carried, following, mass,
                                         rows.factor, observed, rows.floor_array, sigma, scratch, masses,
                                         tiny, huge, d, moving.reach, moving.shell_limit, moving.quiet, K - 1,
                                         moving.flow is not None, gaps, *rates)
        if (j - k) % 2:  # the compiled loop swapped the buffers after each row it finished
            carried, following = following, carried
        if j > k:
            mass = float(masses[j - 1])
        if j == stop and not strayed:
            k = stop
            continue
        if not strayed:  # row j through the slow path, then the trigger as after any row
            seen = bool(observed[j])
            s = scratch if seen else sigma[j]
            new_mass, rows.reason = slow_step(engine, j, float(masses[j]), s, sigma[j], seen, rows.log_factor,
                                              rows.top, rows.gate, projection, following)
            masses[j] = mass = new_mass
            if rows.reason is not None:
                return rows.result(j, carried)
            carried, following = following, carried
            j += 1
            if not watch or j - 1 == K - 1 or j - 1 < moving.quiet \
                    or not _strayed(carried, mass, watch, moving.reach, shell, moving.shell_limit):
                k = j
                continue
        moved = moving.move(j - 1, carried, following, mass)  # row j − 1's trigger fired
        if moved is None:  # the loop cannot move on: the chunk ends after row j − 1
            moving.stopped = j
            return rows.result(j, carried)
        if moved > 0.0:
            mass = moved
            carried, following = following, carried
            next_window = moving.window(j)
            P, P_observe, projection, rates = _moving_arrays(moving)
        k = j
    return rows.result(K, carried)


def _moving_arrays(moving: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray, tuple[np.ndarray, np.ndarray]]:
    """The compiled moving loop's (P, P of observed rows, projection, (real rates, pair rates)) on the
    current ball (rates empty for rows one dt apart)."""
    P, P_observe = moving.matrices()
    flow = moving.flow
    rates = (np.zeros(0), np.zeros(0, complex)) if flow is None else (flow.real_rates, flow.pair_rates)
    return (*(np.asfortranarray(m) for m in (P, P_observe, moving.project)), rates)


def _strayed(carried: np.ndarray, mass: float, watch: tuple[int, ...], reach: float, shell: int,
             shell_limit: float) -> bool:
    """The trigger: the shell's Σwσ over limit·∫σ, or the mean's offset Σw(x − c)_iσ beyond ±reach·∫σ."""
    if carried.item(shell) > shell_limit * mass:
        return True
    return any(not -reach * mass <= carried.item(i) <= reach * mass for i in watch)


def slow_step(engine: Any, k: int, new_mass: float, s: np.ndarray, row: np.ndarray, observed: bool,
              log_factor: np.ndarray, top: np.ndarray, gate: Gate | None, projection: np.ndarray,
              following: np.ndarray) -> tuple[float, str | None]:
    """Step k when ∫σ under/overflowed (recomputed in log scale) or an observed row's cheap gate
    bound is over the threshold (the exact score decides).  Returns (∫σ, reason or None); writes
    row and ``following`` as the hot loop would have."""
    arith, N = engine.arith, engine.N
    if not arith.tiny < new_mass < arith.huge:
        new_mass, reason = rescue(arith, engine.weights, s, log_factor, top, not observed, k, row)
        if reason is NO_MASS_AFTER_UPDATE and observed and gate is not None:
            ll = log_mean_factor(engine.weights, s, log_factor[k]) + float(top[k])  # in log scale
            score = gate.bias[k] - 2.0 * ll - gate.correction(k, s) if ll > -math.inf else math.inf
            if score > gate.threshold[k]:
                gate.attempted[k] = ll
                return reject(engine, gate, k, score, s, row, projection, following)
        if reason is not None:
            return 0.0, reason
        arith.gemv(1.0, projection, row, 0.0, following, 0, 1, 0, 1, 0, 1)
        following[N] = new_mass
    if gate is not None and observed:
        ll = math.log(new_mass) + float(top[k])
        bound = gate.bias[k] - 2.0 * ll
        if bound > gate.threshold[k]:  # maybe an outlier: the exact score needs Cov_pred(h)
            score = bound - gate.correction(k, s)
            if score > gate.threshold[k]:
                gate.attempted[k] = ll
                return reject(engine, gate, k, score, s, row, projection, following)
    return new_mass, None


def reject(engine: Any, gate: Gate, k: int, score: float, s: np.ndarray, row: np.ndarray,
           projection: np.ndarray, following: np.ndarray) -> tuple[float, str | None]:
    """Gate row k: the step only predicts (σ = the propagated density).  (∫σ, reason or None)."""
    gate.scores[k] = score
    if s is not row:
        np.copyto(row, s)
    new_mass = project(engine.arith, projection, row, following, engine.N)
    if not engine.arith.tiny < new_mass < engine.arith.huge:
        return 0.0, NO_MASS_ON_BALL
    return new_mass, None
