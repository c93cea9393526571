"""What a filter does when its density degenerates: stop, or start again from a broadened prior.

A degenerate step (solver/engine/diagnostics.py: the data pushed the density out of the ball, the basis
cannot resolve it, every bit of mass vanished) used to end a stream for good.  Two policies:

* ``on_degenerate = "stop"`` (the default, as before): the state stays degenerate, keeps returning its
  last good estimate with the reason, and waits for the user to reset it (``restart``; over HTTP
  ``POST /v1/sessions/{id}/reset``);
* ``on_degenerate = "reinitialise"``: the filter starts again at the failing row's time from
  :func:`broadened_prior` of the last good estimate — N(m, 4P + s²I), the standard deviations doubled, s
  the finest scale the filter resolves, on a ball no wider than R/4.5 — and goes on with the next row.
  The failing row's observation is not used; the row is flagged ``reinitialised`` with the reason.  The
  log-likelihood is carried on across the restart.  A ball that follows the state (solver/engine/follow.py)
  restarts centred on that prior; the row's ``center`` is the new centre and it is flagged
  ``recentred``.  If the broadened prior is refused, a fixed ball starts from the model's own prior; a
  following ball does not (that prior describes t₀, where a travelling state no longer is; a state that
  left ``[domain] region`` cannot be filtered at all): it stays degenerate with the reason, as under
  "stop".

"stop" is the default because a restart hides a model that does not fit its data; a stream that must
not stop (a service) asks for "reinitialise".
"""

from __future__ import annotations

import dataclasses
import math
from typing import TYPE_CHECKING, Any

import numpy as np

from .errors import InputError, SpecError
from .filtering import ChunkResult, Estimate, concat_results, slice_result
from .registry import DEFAULT_POLICY, POLICIES
from .spec import spec_from_dict

if TYPE_CHECKING:  # types only
    from numpy.typing import ArrayLike

    from .filtering import Filter, FilterState

BROADEN = 2.0  # the restart's standard deviations: the last good ones times this
FIT = 4.5  # ... but on a ball at most R/FIT (N(0, (R/4.5)²) leaves 7e-6 of its mass beyond R)


def check_policy(policy: Any, field: str = "on_degenerate") -> str:
    if policy not in POLICIES:
        raise InputError(field, f"must be one of {', '.join(POLICIES)}, got {policy!r}")
    return policy


def broadened_prior(flt: Filter, estimate: Estimate) -> dict[str, Any]:
    """N(m, BROADEN²·P + s²I) around the last good estimate (m, P); s the node spacing of a mesh
    (the finest feature the engine resolves), else 1e-6 of the state's scale.  On a ball of radius R
    each variance is at most (R/FIT)², unless P's own is larger (on an ellipsoid, in its coordinates
    z = L⁻¹(x − c))."""
    mean = np.asarray(estimate.mean, dtype=float)
    cov = np.asarray(estimate.cov, dtype=float)
    cov = 0.5 * (cov + cov.T)
    n = len(mean)
    spacing = float(getattr(flt, "node_spacing", 0.0) or 0.0)
    resolved = math.isfinite(spacing) and spacing > 0
    floor = spacing ** 2 if resolved else 1e-12 * (1.0 + float(np.abs(mean).max()))
    radius = getattr(getattr(flt, "model", None), "radius", None) if resolved else None
    shape = getattr(flt.model, "shape", None) if radius else None
    if shape is not None:  # an ellipsoid ([domain] shape, x = c + Lz): broadened and capped in z
        inverse = flt.model.shape_inverse
        cov = inverse @ cov @ inverse.T
    lam, U = np.linalg.eigh(cov) if np.all(np.isfinite(cov)) else (np.zeros(n), np.eye(n))
    lam = np.clip(lam, 0.0, None)
    wide = BROADEN ** 2 * lam + floor
    if radius:  # on a ball: no wider than FIT standard deviations across the radius (else the
        # restarted density leaks through ∂B_R and degenerates again at once), nor narrower than before
        wide = np.minimum(wide, np.maximum((float(radius) / FIT) ** 2, lam + floor))
    cov = (U * wide) @ U.T
    if shape is not None:
        cov = shape @ cov @ shape.T
    return {"kind": "gaussian", "mean": mean.tolist(), "cov": (0.5 * (cov + cov.T)).tolist()}


def restart(flt: Filter, state: FilterState, prior: Any | None = None) -> FilterState:
    """The filter started again at ``state``'s step and time from ``prior`` (a spec prior or its dict;
    None: the model's), the log-likelihood carried on."""
    if not getattr(flt, "restartable", True):
        raise InputError("on_degenerate", f"method {flt.method} cannot start again mid-stream (its "
                                          "representation runs from t = 0): use yau-yau, or start a new "
                                          "session")
    if isinstance(prior, dict):
        doc = flt.model.spec.model_dump(mode="json")
        doc["initial"] = prior
        prior = spec_from_dict(doc).initial
    new = flt.initial_state(prior)
    fields = {"step": state.step, "t": state.t, "loglik": state.loglik}
    if hasattr(new, "last"):
        fields["last"] = dataclasses.replace(new.last, step=state.step, t=state.t, loglik=state.loglik,
                                             loglik_increment=0.0)
    return dataclasses.replace(new, **fields)


def restart_from_last(flt: Filter, state: FilterState) -> tuple[FilterState, str]:
    """Start again around the last good estimate; if that prior does not fit the filter (e.g. too
    close to the ball's rim), from the model's own prior — not on a ball that follows the state, where
    :class:`NoRestart` says why.  (new state, what was done)."""
    last = flt.estimate(state)
    try:
        return restart(flt, state, broadened_prior(flt, last)), "re-initialised around the last good estimate"
    except (SpecError, InputError) as exc:
        if flt.follows:
            raise NoRestart(exc.message) from None
        return restart(flt, state, None), f"re-initialised from the model's prior ({exc.message})"


def _not_restarted(reason: str | None, why: str) -> str:
    if reason and "left domain.region" in reason and "domain.region" in why:
        return f"{reason} (not re-initialised: the last good estimate is outside the region too)"
    return f"{reason}; not re-initialised: {why}"


class NoRestart(InputError):
    """A following filter cannot start again around its last good estimate (the message says why;
    over HTTP and in the library a 4xx / InputError on ``from``: send a prior instead)."""

    def __init__(self, message: str):
        super().__init__("from", f"cannot start again around the last good estimate: {message}; send a "
                                 "prior where the state is now, or precompute a wider region")
        self.reason = message


def run_with_policy(flt: Filter, state: FilterState, rows: np.ndarray, times: ArrayLike | None = None,
                    policy: str = DEFAULT_POLICY,
                    tracker: Any | None = None) -> tuple[FilterState, ChunkResult]:  # watch.Tracker: circle
    """``flt.run_arrays`` under an ``on_degenerate`` policy (module docstring).  ``tracker``
    (solver/watch.py) is told of each restart before it happens; when it answers a reason (the filter
    has lost track), the filter does not restart: it stays degenerate from that row with the reason."""
    check_policy(policy)
    if policy == "stop" or not getattr(flt, "restartable", True):  # wei-norman cannot start mid-stream
        return flt.run_arrays(state, rows, times)
    rows = np.asarray(rows, dtype=float)
    times_arr = None if times is None else np.asarray(times, dtype=float).reshape(-1)
    parts: list[ChunkResult] = []
    offset, K = 0, len(rows)
    restarted_before = None
    if state.degenerate and K:
        lost = tracker.restarted(int(state.step) + 1) if tracker is not None else None
        if lost is not None:  # lost track: stays degenerate, and says so
            return flt.run_arrays(dataclasses.replace(state, reason=lost), rows, times)
        try:
            state, restarted_before = _restart_note(flt, state, state.reason, before=True)
        except NoRestart:
            return flt.run_arrays(state, rows, times)  # stays degenerate (its reason says why)
    while True:
        chunk_times = None if times_arr is None else times_arr[offset:]
        new_state, result = flt.run_arrays(state, rows[offset:], chunk_times)
        if restarted_before is not None and len(result):
            result = _flag(result, 0, restarted_before)
            restarted_before = None
        if not result.degenerate.any():
            state = new_state
            parts.append(result)
            break
        k = int(np.argmax(result.degenerate))
        if k:
            parts.append(slice_result(result, slice(0, k)))
        at = dataclasses.replace(_degenerate_at(new_state, result, k), degenerate=True)
        lost = tracker.restarted(int(result.step[k])) if tracker is not None else None
        if lost is not None:  # lost track: the rest of the chunk stays degenerate with that reason
            rest = slice_result(result, slice(k, None))
            parts.append(dataclasses.replace(rest, reason=lost))
            state = dataclasses.replace(new_state, reason=lost) if hasattr(new_state, "reason") else new_state
            break
        try:
            state, note = _restart_note(flt, at, result.reason)
        except NoRestart as exc:  # stays degenerate, as under "stop", and says why it did not restart
            rest = slice_result(result, slice(k, None))
            why = _not_restarted(result.reason, exc.reason)
            parts.append(dataclasses.replace(rest, reason=why))
            state = dataclasses.replace(new_state, reason=why) if hasattr(new_state, "reason") else new_state
            break
        parts.append(_restart_row(flt, state, note))
        offset += k + 1
        if offset >= K:
            break
    return state, concat_results(parts)


def _restart_note(flt, state, reason, before: bool = False) -> tuple[FilterState, str]:
    new_state, how = restart_from_last(flt, state)
    if before:  # the state came degenerate from an earlier chunk: the restart precedes this row
        return new_state, f"the filter was degenerate ({reason}); {how} before this row, which was used"
    return new_state, f"the filter degenerated ({reason}); {how}; this row's observation was not used"


def _degenerate_at(state: FilterState, result: ChunkResult, k: int) -> FilterState:
    """The degenerate state as of row k (its last good estimate is what the restart broadens)."""
    loglik = float(result.loglik[k - 1]) if k else float(state.last.loglik if hasattr(state, "last")
                                                         else state.loglik)
    return dataclasses.replace(state, step=int(result.step[k]), t=float(result.t[k]), loglik=loglik)


def _restart_row(flt: Filter, state: FilterState, note: str) -> ChunkResult:
    """A one-row result: the restarted state's estimate, flagged reinitialised."""
    e = flt.estimate(state)
    n = len(e.mean)
    mode = np.asarray(e.mode if e.mode is not None else e.mean, dtype=float)[None]
    # a following ball restarts centred on the new prior: the row has its centre, like every other row
    center = getattr(state, "center", None) if flt.follows else None
    return ChunkResult(step=np.array([state.step]), t=np.array([float(state.t)]),
                       mean=np.asarray(e.mean)[None], cov=np.asarray(e.cov).reshape(1, n, n), mode=mode,
                       loglik=np.array([float(state.loglik)]),
                       loglik_increment=np.zeros(1), degenerate=np.zeros(1, dtype=bool),
                       reinitialised=np.ones(1, dtype=bool), notes={0: note},
                       center=None if center is None else np.asarray(center, dtype=float).reshape(1, n),
                       recentred=np.array([center is not None]))


def _flag(result: ChunkResult, k: int, note: str) -> ChunkResult:
    again = result.reinitialised.copy()
    again[k] = True
    notes = dict(result.notes or {})
    notes[k] = note
    return dataclasses.replace(result, reinitialised=again, notes=notes)
