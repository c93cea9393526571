"""Increments over long gaps, filtered in pieces, and the outlier gate over whole rows.

An increment over a gap τ longer than (PIECE + ¼)·dt is filtered in ⌈τ/(PIECE·dt) − ¼⌉ equal pieces of
its gap and of its increment (y taken linear over the gap, as the exact filters do: the factor of
seed 002 (5.35) freezes x over each piece only).  The gate judges whole rows, not pieces.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

from ..filtering import ChunkResult
from ..measurement import standard_score
from .gate import Gate
from .kernel import log_mean_factor

if TYPE_CHECKING:  # types only
    from .state import YauYauState

PIECE = 2.0  # an increment over a gap longer than (PIECE + 1/4)·dt is filtered in pieces of about PIECE·dt
MAX_PIECES = 64  # pieces of one increment at most (a longer gap gets longer pieces)


def row_pieces(engine: Any, rows: np.ndarray, taus: np.ndarray | None) -> np.ndarray | None:
    """How many pieces each row's gap is filtered in: an increment over a gap longer than
    (PIECE + ¼)·dt in ⌈τ/(PIECE·dt) − ¼⌉ equal pieces (None: every row in one)."""
    if taus is None or engine.observation.discrete or engine.form == "literal":
        return None
    observed = ~np.isnan(rows).all(axis=1)
    with np.errstate(over="ignore", invalid="ignore"):
        wanted = np.ceil(np.minimum(taus / (PIECE * engine.model.dt), MAX_PIECES) - 0.25)
    count = np.where(observed, np.clip(wanted, 1, MAX_PIECES), 1)
    return count.astype(int) if count.max() > 1 else None


def run_in_pieces(engine: Any, state: YauYauState, rows: np.ndarray, steps: np.ndarray, times: np.ndarray,
              taus: np.ndarray, pieces: np.ndarray) -> tuple[YauYauState, ChunkResult]:
    """Increments over long gaps, each in ``pieces[k]`` equal pieces of its gap and of its increment
    (y taken linear over the gap, as the exact filters do: the factor of seed 002 (5.35) freezes x
    over each piece only).  The gate judges whole rows: a chunk runs without it, then again with
    a rejected row left out, until no row is over its threshold (outliers are rare)."""
    obs = engine.observation
    keys = obs.pattern_keys(~np.isnan(rows))
    terms = obs.row_terms(rows, taus, keys)
    data, rejected = rows.copy(), {}
    while True:
        count = np.where(np.isnan(data).all(axis=1), 1, pieces)
        owner = np.repeat(np.arange(len(data)), count)
        first = np.cumsum(count) - count
        share = taus[owner] / count[owner]
        before = np.concatenate([[state.t], times[:-1]])
        piece_times = before[owner] + share * (np.arange(len(owner)) - first[owner] + 1)
        piece_times[first + count - 1] = times  # each row ends exactly at its time
        new_state, sub = engine.run_rows(state, data[owner] / count[owner, None], steps[owner], piece_times,
                                   share, gating=False)
        ll = np.add.reduceat(sub.loglik_increment, first)
        last = first + count - 1
        found = (first_rejected(engine, state, data, times, taus, ll, terms, keys, sub.degenerate[last],
                                      rejected) if obs.gating else None)
        if found is None:
            break
        data[found] = np.nan
    predictive = np.where(keys == 0, np.nan, ll + terms.offset)
    gated, scores = np.zeros(len(rows), dtype=bool), np.full(len(rows), np.nan)
    for k, (score, attempted) in rejected.items():
        gated[k], scores[k] = True, standard_score(score, int(keys[k]).bit_count())
        predictive[k] = attempted + terms.offset[k]
    degenerate = sub.degenerate[last]
    predictive[degenerate] = np.nan
    return new_state, ChunkResult(step=steps, t=times, mean=sub.mean[last], cov=sub.cov[last],
                                  mode=sub.mode[last], loglik=sub.loglik[last],
                                  loglik_increment=np.where(degenerate, 0.0, ll), degenerate=degenerate,
                                  reason=sub.reason, predictive_loglik=predictive, gated=gated,
                                  gate_score=scores, gate=obs.gate,
                                  center=None if sub.center is None else sub.center[last])


def first_rejected(engine: Any, state: YauYauState, data, times, taus, ll, terms, keys, degenerate,
               rejected: dict) -> int | None:
    """The first row over the gate (recorded in ``rejected``: its d² and log E_pred[e]), or None.
    The bound g first; the exact score predicts the state to the row (rare: rows over the bound)."""
    obs = engine.observation
    bias = terms.bound_bias()
    bound = bias - 2.0 * ll
    gate = Gate(obs, terms, keys, taus, engine)
    observed = ~np.isnan(data).all(axis=1)
    suspects = observed & ~degenerate & (bound > terms.threshold)
    if degenerate.any():  # the first degenerate row may be an outlier the pieces could not carry
        suspects[int(np.argmax(degenerate))] |= observed[int(np.argmax(degenerate))]
    for k in np.flatnonzero(suspects).tolist():
        at, _ = engine.run_arrays(state, data[:k], times[:k]) if k else (state, None)
        predicted, _ = engine.predict(at, times[k])
        s = np.asarray(engine.offline.basis) @ predicted.density_coefficients
        attempted = float(ll[k])
        shift = None if engine.frame is None else np.asarray(predicted.center) - engine.frame.origin
        if degenerate[k]:  # its pieces never finished: the whole row's factor on the prediction
            _, _, log_factor, top, _ = engine.factors(data[k:k + 1], taus[k:k + 1],
                                                     None if shift is None else shift[None])
            attempted = log_mean_factor(engine.weights, s, log_factor[0]) + float(top[0])
        score = bias[k] - 2.0 * attempted - gate.correction(k, s, shift)
        if score > terms.threshold[k]:
            rejected[k] = (score, attempted)
            return k
    return None
