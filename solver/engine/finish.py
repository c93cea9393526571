"""From what the hot loop left to the chunk's estimates, checks and new state, one job at a time.

:func:`finish` runs the jobs in order on an :class:`Outcome`: stop at an impossible row the gate did
not catch; weigh the gated rows; take the moments; cut the chunk where the caller (a ball that
follows the state) wants it to end; check each step's plausibility (solver/engine/diagnostics.py)
and explain a failure; then the new state and the :class:`~solver.filtering.ChunkResult`.
"""

from __future__ import annotations

import dataclasses
import math
import weakref
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from .. import jit
from ..filtering import ChunkResult, Estimate
from ..measurement import standard_score
from .gate import Prepared
from .kernel import FACTOR_OVERFLOWS, moment_features, moment_pairs, moments_from, stack_results
from .state import YauYauState

# ``until(means, centers)``: the rows of a chunk to keep (None: all), solver/engine/follow.py
Until = Callable[[np.ndarray, np.ndarray | None], int | None]


class Recompute(Exception):
    """A fused chunk (no σ kept: solver/engine/fused.py) met a step whose explanation or new state needs
    σ: the caller runs the chunk again on the path that keeps it."""


@dataclass(frozen=True)
class Summary:
    """What the fused compiled rows keep of each σ_k instead of σ: the moments' sums features · σ (K, F),
    the checks' sums (K, 4: Diagnostics.functionals · σ, Σ w min(σ, 0)) and the node of the largest σ."""

    moments: np.ndarray
    checks: np.ndarray
    mode: np.ndarray


_SUMMARIES: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def summary_rows(engine: Any) -> np.ndarray:
    """The rows the compiled kernel sums σ against, as columns (Q, S) in Fortran order (its gemv('T')):
    the moments' features, then the diagnostics' functionals (engine/diagnostics.py)."""
    found = _SUMMARIES.get(engine)
    if found is None:
        features = moment_features(engine.weights, engine.nodes, moment_pairs(engine.nodes.shape[1]))
        found = np.asfortranarray(np.vstack([features, engine.diagnostics.functionals()]).T, dtype=float)
        _SUMMARIES[engine] = found
    return found


def summarise(engine: Any, sigma: np.ndarray) -> Summary:
    """:class:`Summary` of σ rows a compiled loop kept (compiled.sum_rows: the fused rows' operations)."""
    from . import compiled  # numba: imported on the first chunk

    summary = summary_rows(engine)
    K, features = len(sigma), summary.shape[1] - 3
    sums, negative, mode = np.empty((K, summary.shape[1])), np.empty(K), np.empty(K, dtype=np.int64)
    compiled.sum_rows(np.ascontiguousarray(sigma), summary, np.ascontiguousarray(engine.weights, dtype=float),
                      sums, negative, mode)
    return Summary(sums[:, :features], np.column_stack([sums[:, features:], negative]), mode)


@dataclass
class Outcome:
    """A chunk's rows with what the loop left for them (σ_k, ∫σ_k of the good steps, the carried vector
    after the last, how many were good and why it stopped), and what the jobs add."""

    rows: np.ndarray
    steps: np.ndarray
    times: np.ndarray
    sigma: np.ndarray | None
    masses: np.ndarray
    carried: np.ndarray
    done: int
    reason: str | None
    pll: np.ndarray | None = None  # log E_pred[e_k]
    gated: np.ndarray | None = None
    scores: np.ndarray | None = None
    mean: np.ndarray | None = None
    cov: np.ndarray | None = None
    mode: np.ndarray | None = None
    shifts: np.ndarray | None = None
    skip: np.ndarray | None = None
    missing: np.ndarray | None = None
    summary: Summary | None = None

    @property
    def K(self) -> int:
        return len(self.rows)


def finish(engine: Any, state: YauYauState, rows: np.ndarray, steps: np.ndarray, times: np.ndarray,
           taus: np.ndarray | None, ready: Prepared, sigma, masses, carried, done: int,
           reason: str | None, until: Until | None = None,
           summary: Summary | None = None) -> tuple[YauYauState, ChunkResult]:
    """The chunk's estimates, checks and new state from what the hot loop left (``sigma``: the
    nodal σ_k of its good steps, ``masses`` their ∫σ_k, ``carried`` the vector after the last; or
    ``sigma`` None and the ``summary`` of a fused chunk, whose every row was good and which raises
    :class:`Recompute` where σ is needed)."""
    if ready.moving is not None:  # a moving ball's loop carries nodal coefficients out, whatever the gaps
        taus = None
    out = Outcome(rows, steps, times, sigma, masses, carried, done, reason, shifts=ready.shifts,
                  skip=ready.skip, missing=ready.missing, summary=summary)
    stop_at_overflow(engine, out, ready, taus)
    weigh_gate(out, ready)
    if out.sigma is None or jit.enabled():  # compiled: the sums of the fused rows, whether fused or not
        sums = summary if out.sigma is None else summarise(engine, out.sigma[:out.done])
        assert sums is not None
        out.summary = sums  # the checks read its sums too, as a fused chunk's do
        done = out.done
        out.mean, out.cov, out.mode = moments_from(sums.moments[:done], out.masses[:done], sums.mode[:done],
                                                   moment_pairs(engine.nodes.shape[1]), engine.nodes,
                                                   None if out.shifts is None else out.shifts[:done])
    else:
        out.mean, out.cov, out.mode = engine.moments(out.sigma[:out.done], out.masses[:out.done],
                                                     None if out.shifts is None else out.shifts[:out.done])
    cut(engine, out, ready, taus, until)
    check_plausible(engine, state, out, ready, taus)
    return new_state(engine, state, out, ready, taus)


def stop_at_overflow(engine: Any, out: Outcome, ready: Prepared, taus: np.ndarray | None) -> None:
    """Without a gate, an observed row whose factor overflows ends the good steps; a loop that stopped
    early leaves the vector it carried after the last good step."""
    if ready.gate is None and ready.impossible[:out.done].any():
        out.done = int(np.argmax(ready.impossible))
        out.reason = FACTOR_OVERFLOWS
        out.sigma, out.masses = out.sigma[:out.done], out.masses[:out.done]
    if out.reason is not None:  # the loop stopped early (and may have scaled its vector for the next gap)
        out.carried = engine.carried_after(out.sigma, out.masses, out.done, ready.initial, taus)


def weigh_gate(out: Outcome, ready: Prepared) -> None:
    """The predictive log-likelihood log E_pred[e_k] of each row; a gated row's score and the
    log-likelihood of the update it refused."""
    with np.errstate(divide="ignore"):
        out.pll = np.log(out.masses) + ready.top[:len(out.masses)]
    out.gated = np.zeros(out.K, dtype=bool)
    out.scores = np.full(out.K, np.nan)
    gate = ready.gate
    if gate is None:
        return
    for k, score in gate.scores.items():
        out.gated[k], out.scores[k] = True, standard_score(score, gate.size(k))
        ready.top[k] = ready.top_before[k] = 0.0
        if k < len(out.pll):
            out.pll[k] = gate.attempted.get(k, -math.inf)


def cut(engine: Any, out: Outcome, ready: Prepared, taus: np.ndarray | None, until: Until | None) -> None:
    """End the chunk after row j − 1 where ``until(mean, centres)`` says so, or where a ball moving in
    the loop could not move on: the state is then the one the loop carried there, bit for bit."""
    shifts = out.shifts
    found = None if until is None or not out.done else until(
        out.mean, None if shifts is None else shifts[:out.done] + ready.origin)
    stopped = None if ready.moving is None else ready.moving.stopped
    if stopped is not None:  # the loop could not move the ball after row stopped − 1: it ends there
        found = stopped
    if found is None or not (1 <= found < out.K and (found < out.done or found == stopped)):
        return
    K = out.done = int(found)
    out.rows, out.steps, out.times = out.rows[:K], out.steps[:K], out.times[:K]
    out.missing, out.skip = out.missing[:K], out.skip[:K]
    out.sigma, out.masses, out.pll = out.sigma[:K], out.masses[:K], out.pll[:K]
    out.gated, out.scores = out.gated[:K], out.scores[:K]
    out.mean, out.cov, out.mode = out.mean[:K], out.cov[:K], out.mode[:K]
    out.shifts = None if shifts is None else shifts[:K]
    out.carried, out.reason = engine.carried_after(out.sigma, out.masses, K, ready.initial, taus), None


def check_plausible(engine: Any, state: YauYauState, out: Outcome, ready: Prepared,
                    taus: np.ndarray | None) -> None:
    """The first implausible step (pushed against ∂B_R, unresolved, leaking mass) ends the good steps;
    the reason is led by the outlier met there, if it was one."""
    done, top, top_before = out.done, ready.top, ready.top_before
    with np.errstate(over="ignore", invalid="ignore"):
        growth = out.masses[:done] * np.exp(top[:done] - top_before[:done])
    # compiled, fused or not: the checks' sums the kernel left (no second pass over σ); else from σ
    checks = None if out.summary is None else out.summary.checks[:done]
    if out.sigma is None:
        assert checks is not None
        bad, why = engine.diagnostics.first_implausible(None, out.masses[:done], out.cov, growth, checks)
        if bad is not None or out.reason is not None:
            raise Recompute(why)
    else:
        bad, why = engine.diagnostics.first_implausible(out.sigma[:done], out.masses[:done], out.cov, growth,
                                                        checks)
    if bad is None:
        if out.reason is not None:  # the hot loop stopped at step `done` (no positive mass, overflow)
            out.reason = engine.explained(out.sigma, state, out.rows, out.steps, out.skip, done, out.reason,
                                          ready.gaps, out.shifts)
        return
    out.done, out.reason = bad, engine.explained(out.sigma, state, out.rows, out.steps, out.skip, bad, why,
                                                 ready.gaps, out.shifts)
    out.carried = engine.carried_after(out.sigma, out.masses, bad, ready.initial, taus)
    out.mean, out.cov, out.mode = out.mean[:bad], out.cov[:bad], out.mode[:bad]


def new_state(engine: Any, state: YauYauState, out: Outcome, ready: Prepared,
              taus: np.ndarray | None) -> tuple[YauYauState, ChunkResult]:
    """The state after the chunk's good steps, and the chunk's result (the tail padded when it
    degenerated; in a moving frame, the centre after each row)."""
    done, K = out.done, out.K
    masses = out.masses[:done]
    increments_ll = np.log(masses) + ready.top[:done]
    # sequential sums from the carried value: identical however the data are chunked
    running = np.empty(done + 1)
    running[0], running[1:] = state.loglik, increments_ll
    loglik = np.cumsum(running)[1:]
    predictive = np.full(K, np.nan)
    predictive[:done] = out.pll[:done] + ready.terms.offset[:done]
    predictive[out.missing] = np.nan
    good = done == K
    if done:
        last = Estimate(step=int(out.steps[done - 1]), t=float(out.times[done - 1]), mean=out.mean[-1],
                        cov=out.cov[-1], loglik=float(loglik[-1]), loglik_increment=float(increments_ll[-1]),
                        mode=out.mode[-1])
    else:
        last = state.last
    coefficients = out.carried[: engine.N].astype(float)
    if taus is not None and not engine.flow.exact:
        coefficients = engine.flow.from_modal(coefficients)
    state_after = YauYauState(coefficients=coefficients, mass=out.carried.item(engine.N),
                              step=int(out.steps[-1]), t=float(out.times[-1]), precision=engine.precision,
                              loglik=last.loglik, last=last, degenerate=not good, reason=out.reason,
                              form=engine.form)
    out.gated[done:], out.scores[done:] = False, np.nan
    frame = {}
    if out.shifts is not None:  # the frame's centre after each row (after the last good one when stopped)
        centers = out.shifts + ready.origin
        end = centers[-1] if good else (centers[done - 1] if done else np.asarray(state.center, float))
        state_after = dataclasses.replace(state_after, center=np.array(end))
        frame = {"center": centers}
    return state_after, stack_results(out.steps, out.times, out.mean, out.cov, out.mode, loglik,
                                      increments_ll, last, out.reason, predictive_loglik=predictive,
                                      gated=out.gated, gate_score=out.scores, gate=engine.observation.gate,
                                      **frame)
