"""Watching a filter for answers that look healthy and are not: a lost track and a biased sensor.

Two checks ride on every chunk a filter runs through :func:`watched_run` (the library's
``OnlineFilter``, ``yauyau filter`` and the service).  They use what the rows already say, and their
state (:class:`Watch`) is part of the session's state: it goes into ``state_dict()``, is stored with
an HTTP session and restored after a restart.

**Lost track.**  A filter that keeps gating or restarting no longer follows the state.  On a fixed
ball that the state has left (the OU model, radius 7, increments of x = 12 under
``on_degenerate = "reinitialise"``) it restarts on every row and returns estimates inside the ball,
flagged healthy, while the truth is outside.  :class:`LostTrack` gives the count: ``gated``
consecutive gated rows (rows without an observation neither count nor break the run), or
``restarts`` restarts within ``window`` rows.  From the row that reaches it on, every row is
degenerate with a reason that names the domain and the fix (``domain.follow = true``, a larger
``domain.radius``; for a filter without a ball, that the model does not explain the data), and the
filter stays so — whatever ``on_degenerate`` says — until it is reset or re-initialised (which
clear the count).  The defaults were measured on the bundled models (docs/reliability.md: no
healthy run of 50 000 rows gated a row or restarted).

**Innovation monitor.**  A sensor with a sustained bias passes the gate row by row.  Each observed
row gets the normal score of its innovation,

    z_j = (y_j − E[y_j | past]) / sd(y_j | past),

under a Gaussian moment match of the row's one-step predictive distribution: E[y | past] = κ E[h],
Cov[y | past] = κ² Cov[h] + S₀ (κ = τ, S₀ = Rτ for increments; κ = 1, S₀ = R for measurements:
solver/measurement.py), the expectations unscented under the previous row's posterior mean and
covariance — carried to the row's time by Euler steps (at most dt) of the moment equations for a
measurement; for an increment E[h] moves by O(τ) over the row, which moves the score by O(τ^1.5).  Under a
correct model z has mean 0 and variance ≈ 1 (measured per model in docs/reliability.md).  It is not
the exact probability integral transform: the filters return their posterior per row, not their
predictive distribution, and the predictive log-likelihood they do return has no sign (a bias moves
it only at second order).  The normal scores feed three two-sided CUSUM charts (Page), reference
values k ∈ CHARTS (a large, a moderate and a small shift in standard deviations of z), each with the
threshold h that Siegmund's approximation gives for a mean run of ``monitor`` × (number of charts)
healthy rows, so that the monitor as a whole raises a false alarm about once in ``monitor`` healthy
rows.  The row where a chart crosses is flagged ``alarm`` and every chart starts again from 0.  The
monitor statistic (``ChunkResult.monitor``) is the largest chart over its threshold, signed by the
side (+: observations above their prediction); ±1 is the alarm.  Gated, degenerate and
re-initialised rows, missing components and rows after a gap longer than MAX_GAP·dt are not scored.
The monitor is off unless a session or the spec sets it (``monitor``; MONITOR_SUGGESTED = 1e9): it
costs about half a millisecond per chunk in the service, 9% of a 100-row chunk of the 1-D engine,
more than the whole budget of the service's protections (docs/reliability.md).  A posterior that one
moment match misplaces (a range-only sensor's ring, whose match puts E[h] inside the ring) biases the
scores: measured on examples/range_only_4d.toml, 10 false alarms in 50 000 rows.
"""

from __future__ import annotations

import dataclasses
import math
import numbers
from dataclasses import dataclass
from functools import lru_cache
from typing import TYPE_CHECKING, Any

import numpy as np

from .errors import InputError
from .filtering import ChunkResult, chunk_clock
from .measurement import check_rows, resolve_times
from .recovery import run_with_policy
from .spec import MONITOR_DEFAULT  # 0: the monitor is off unless a session or the spec sets it

if TYPE_CHECKING:  # types only
    from numpy.typing import ArrayLike

    from .filtering import Filter, FilterState, State
    from .model import Model

LOST_GATED = 20  # consecutive gated rows: lost track
LOST_RESTARTS = 3  # ... or this many restarts (on_degenerate = reinitialise)
LOST_WINDOW = 100  # ... within this many rows
CHARTS = (0.5, 0.1, 0.025)  # CUSUM reference values (standard deviations of the innovation's score)
MONITOR_RANGE = (1e3, 1e15)
MONITOR_SUGGESTED = 1e9  # healthy rows per false alarm: the setting measured in docs/reliability.md
BLOCK = 4096  # rows of the charts computed at once
SCORE_CLIP = 1000.0  # scores beyond are taken as ±1000 (an alarm either way)
QUANTUM_BITS = 20  # scores in multiples of 2^-20: the charts' sums (< 2^33) are exact
MAX_GAP = 64  # rows after a longer gap (in dt) are not scored: the moment prediction is Euler's
_SIEGMUND = 1.166  # Siegmund's correction of the CUSUM threshold (ρ = −ζ(1/2)/√(2π) · 2)


# -- settings -----------------------------------------------------------------------------------------
@dataclass(frozen=True)
class LostTrack:
    """When a filter has lost track: ``gated`` consecutive gated rows, or ``restarts`` restarts within
    ``window`` rows (0 turns either rule off)."""

    gated: int = LOST_GATED
    restarts: int = LOST_RESTARTS
    window: int = LOST_WINDOW

    def to_dict(self) -> dict[str, int]:
        return {"gated": self.gated, "restarts": self.restarts, "window": self.window}


def check_lost_track(value: Any, field: str = "lost_track") -> LostTrack:
    """A :class:`LostTrack` from None (the defaults), a LostTrack, or a dict of some of its fields;
    InputError naming ``field.name`` otherwise."""
    if value is None:
        return LostTrack()
    if isinstance(value, LostTrack):
        value = value.to_dict()
    if not isinstance(value, dict):
        raise InputError(field, 'must be an object like {"gated": 20, "restarts": 3, "window": 100}')
    unknown = sorted(set(value) - {"gated", "restarts", "window"})
    if unknown:
        raise InputError(f"{field}.{unknown[0]}", "unknown: the fields are gated, restarts and window")
    out = LostTrack().to_dict()
    for name, given in value.items():
        low = 1 if name == "window" else 0
        if isinstance(given, bool) or not isinstance(given, numbers.Integral) or not low <= given <= 10**9:
            what = "rows (at least 1)" if name == "window" else "a count (0 turns the rule off)"
            raise InputError(f"{field}.{name}", f"must be an integer from {low} to 10^9: {what}; "
                                                f"got {given!r}")
        out[name] = int(given)
    return LostTrack(**out)


def parse_lost_track(text: str, field: str = "--lost-track") -> LostTrack:
    """``GATED,RESTARTS,WINDOW`` (the command line's form) as a :class:`LostTrack`."""
    parts = [p.strip() for p in str(text).split(",")]
    if len(parts) != 3 or not all(p.isdigit() for p in parts):
        raise InputError(field, f"must be GATED,RESTARTS,WINDOW, three non-negative integers (e.g. "
                                f"{LOST_GATED},{LOST_RESTARTS},{LOST_WINDOW}; 0 turns a rule off), "
                                f"got {text!r}")
    gated, restarts, window = (int(p) for p in parts)
    return check_lost_track({"gated": gated, "restarts": restarts, "window": window}, field)


def check_monitor(value: Any, field: str = "monitor") -> float | None:
    """A monitor override (None: the spec's): 0 (off) or the mean number of healthy rows per false alarm,
    from 1e3 to 1e15."""
    if value is None:
        return None
    low, high = MONITOR_RANGE
    if isinstance(value, bool) or not isinstance(value, numbers.Real) or not math.isfinite(value) \
            or not (value == 0 or low <= value <= high):
        raise InputError(field, f"must be 0 (off) or the mean number of healthy rows per false alarm, from "
                                f"{low:g} to {high:g}; got {value!r}")
    return float(value)


@dataclass(frozen=True)
class WatchSettings:
    """What a watched filter checks: when it has lost track, and the monitor's false-alarm rate (rows
    per false alarm; 0: off)."""

    lost: LostTrack = LostTrack()
    monitor: float = MONITOR_DEFAULT


def settings_for(flt: Filter, lost_track: Any = None, monitor: Any = None) -> WatchSettings:
    """The settings of a filter: ``lost_track`` (None: the defaults) and ``monitor`` (None: the spec's
    ``[measurement] monitor``, off unless set)."""
    chosen = check_monitor(monitor)
    if chosen is None:
        chosen = float(getattr(flt.model.spec.measurement, "monitor", MONITOR_DEFAULT))
    return WatchSettings(lost=check_lost_track(lost_track), monitor=chosen)


# -- the state ----------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Watch:
    """The watch's state (JSON-safe through to_dict/from_dict): the current run of gated rows, the steps
    of the recent restarts, the lost-track reason (None: on track), the CUSUM charts (per side,
    component and chart: ``(2, m, len(CHARTS))`` flattened; empty: all 0), the monitor statistic after the
    last row and the number of alarms raised."""

    gated_run: int = 0
    restarts: tuple[int, ...] = ()
    lost: str | None = None
    charts: tuple[float, ...] = ()
    statistic: float = 0.0
    alarms: int = 0

    def to_dict(self) -> dict[str, Any]:
        return {"gated_run": self.gated_run, "restarts": list(self.restarts), "lost": self.lost,
                "charts": list(self.charts), "statistic": self.statistic, "alarms": self.alarms}

    @classmethod
    def from_dict(cls, data: Any) -> "Watch":
        """Inverse of :meth:`to_dict` (None or absent: a fresh watch); InputError('state.watch.…')."""
        if data is None:
            return cls()
        if not isinstance(data, dict):
            raise InputError("state.watch", "must be an object")
        return cls(gated_run=_count(data.get("gated_run", 0), "gated_run"),
                   restarts=tuple(_count(s, "restarts") for s in _list(data.get("restarts", []), "restarts")),
                   lost=_text(data.get("lost")),
                   charts=tuple(_number(c, "charts", positive=True) for c in _list(data.get("charts", []),
                                                                                  "charts")),
                   statistic=_number(data.get("statistic", 0.0), "statistic"),
                   alarms=_count(data.get("alarms", 0), "alarms"))


def _count(value: Any, name: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < 0:
        raise InputError(f"state.watch.{name}", "must be a non-negative integer")
    return value


def _list(value: Any, name: str) -> list:
    if not isinstance(value, list):
        raise InputError(f"state.watch.{name}", "must be a list")
    return value


def _text(value: Any) -> str | None:
    if value is not None and not isinstance(value, str):
        raise InputError("state.watch.lost", "must be a string or null")
    return value


def _number(value: Any, name: str, positive: bool = False) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) \
            or (positive and value < 0):
        raise InputError(f"state.watch.{name}", "must be a finite" + (" non-negative" if positive else "")
                         + " number")
    return float(value)


def split_state(data: Any) -> tuple[Any, Watch]:
    """(the filter's state dict, the :class:`Watch`) of a stored state (one stored before the watch: a
    fresh one)."""
    if isinstance(data, dict) and "watch" in data:
        rest = dict(data)
        return rest, Watch.from_dict(rest.pop("watch"))
    return data, Watch()


def join_state(state: FilterState, watch: Watch) -> dict[str, Any]:
    """The filter state's dict with the watch in it (what a session stores)."""
    out = state.to_dict()
    out["watch"] = watch.to_dict()
    return out


# -- running a chunk ----------------------------------------------------------------------------------
class Tracker:
    """Counts restarts while a chunk runs (:func:`solver.recovery.run_with_policy` asks it before each):
    :meth:`restarted` returns the lost-track reason when this restart is one too many."""

    def __init__(self, flt: Filter, watch: Watch, lost: LostTrack):
        self.flt = flt
        self.rule = lost
        self.restarts = list(watch.restarts)
        self.reason: str | None = None

    def restarted(self, step: int) -> str | None:
        rule = self.rule
        if not rule.restarts:
            return None
        self.restarts = [s for s in self.restarts if step - s < rule.window] + [int(step)]
        if len(self.restarts) >= rule.restarts:
            self.reason = lost_reason(self.flt, f"{len(self.restarts)} restarts within {rule.window} rows "
                                                f"(on_degenerate = reinitialise)")
        return self.reason


def watched_run(flt: Filter, state: FilterState, watch: Watch, rows: ArrayLike,
                times: ArrayLike | None = None, policy: str = "stop",
                settings: WatchSettings | None = None) -> tuple[FilterState, Watch, ChunkResult]:
    """``run_with_policy`` (solver/recovery.py) with the watch: (new state, new watch, result).  A
    filter that has lost track answers degenerate rows (its last estimate, the reason) and computes
    nothing until it is reset."""
    settings = settings or WatchSettings()
    if watch.lost is not None:
        new_state, result = hold(flt, state, rows, times, watch.lost)
        return new_state, watch, result
    tracker = Tracker(flt, watch, settings.lost)
    before = state
    state, result = run_with_policy(flt, state, rows, times, policy, tracker=tracker)
    return settle(flt, before, state, watch, result, np.asarray(rows, dtype=float), settings, tracker)


def settle(flt: Filter, before: FilterState, state: FilterState, watch: Watch, result: ChunkResult,
           rows: np.ndarray, settings: WatchSettings,
           tracker: Tracker | None = None) -> tuple[FilterState, Watch, ChunkResult]:
    """The watch over a chunk already run from ``before`` to ``state``: the runs of gated rows and the
    restarts (lost track), and the innovation monitor.  (new state, new watch, result with the
    ``alarm`` and ``monitor`` columns and the lost rows flagged)."""
    restarts = tuple(tracker.restarts) if tracker is not None else watch.restarts
    reason = tracker.reason if tracker is not None else None
    rows = rows.reshape(len(result), -1) if len(result) else rows
    gated_run, lost_at, why = _gated_runs(result, rows, watch.gated_run, settings.lost)
    if reason is None and lost_at is not None:
        reason = lost_reason(flt, why)
        result = _degenerate_from(result, lost_at, reason)
    if restarts and len(result):
        last = int(result.step[-1])
        restarts = tuple(s for s in restarts if last - s < settings.lost.window)
    charts, statistic, alarms = watch.charts, watch.statistic, watch.alarms
    if settings.monitor > 0 and len(result):
        scores = innovation_scores(flt, before, result, rows)
        charts, column, alarm = run_charts(charts, scores, settings.monitor)
        result = dataclasses.replace(result, alarm=alarm, monitor=column)
        statistic, alarms = float(column[-1]), alarms + int(alarm.sum())
    if reason is not None:
        state = _marked(state, reason)
    new = Watch(gated_run=gated_run, restarts=restarts, lost=reason, charts=charts, statistic=statistic,
                alarms=alarms)
    return state, new, result


def _gated_runs(result: ChunkResult, rows: np.ndarray, run: int, rule: LostTrack):
    """(the run of gated rows after the chunk, the row where it reached ``rule.gated`` or None, why)."""
    if not rule.gated or (not run and not result.gated.any()):
        return 0, None, None
    observed = ~np.isnan(rows).all(axis=1) if rows.size else np.zeros(len(result), dtype=bool)
    for k, (gated, bad, again, seen) in enumerate(zip(result.gated.tolist(), result.degenerate.tolist(),
                                                      result.reinitialised.tolist(), observed.tolist(),
                                                      strict=True)):
        if bad:
            return run, None, None
        if again:
            run = 0
        elif gated:
            run += 1
            if run >= rule.gated:
                return run, k, (f"{run} consecutive observations gated (each too far from what the filter "
                                "predicts to be used)")
        elif seen:
            run = 0
    return run, None, None


def lost_reason(flt: Filter, what: str) -> str:
    """The lost-track reason: what happened and, for a filter on a ball, the domain and the fix."""
    head = f"lost track: {what}; the estimates no longer follow the state"
    model = flt.model
    if flt.follows:
        where = ("or left domain.region (a wider region), " if model.spec.domain.region is not None else "")
        return (f"{head}: it probably moves faster than the ball of radius {model.radius:g} re-centres, "
                f"{where}or the model does not explain the data: set a larger domain.radius (or a smaller "
                "domain.follow_distance); then reset the filter (POST /v1/sessions/{id}/reset, "
                "reinitialise)")
    if getattr(flt, "method", None) == "yau-yau":
        center = ", ".join(f"{c:g}" for c in np.asarray(model.center, dtype=float).reshape(-1))
        return (f"{head}: the state has probably left the domain ball (radius {model.radius:g} around "
                f"[{center}]), where this filter cannot follow it: set domain.follow = true (the ball "
                "follows the state) or a larger domain.radius and precompute again; then reset the filter "
                "(POST /v1/sessions/{id}/reset, reinitialise)")
    return (f"{head}: the model does not explain these observations (method {flt.method} has no domain "
            "ball to leave): check the model and the sensor, then reset the filter "
            "(POST /v1/sessions/{id}/reset, reinitialise)")


def _degenerate_from(result: ChunkResult, k: int, reason: str) -> ChunkResult:
    """The result with rows k.. degenerate for ``reason`` (an earlier degenerate row keeps its own)."""
    flags = result.degenerate.copy()
    earlier = flags[:k].any()
    flags[k:] = True
    return dataclasses.replace(result, degenerate=flags, reason=result.reason if earlier else reason)


def _marked(state: State, reason: str) -> State:
    """The state flagged degenerate for ``reason`` (its estimate is kept: what the held rows repeat)."""
    fields = {f.name for f in dataclasses.fields(state)}
    changes = {name: value for name, value in (("degenerate", True), ("reason", reason)) if name in fields}
    return dataclasses.replace(state, **changes)


def hold(flt: Filter, state: FilterState, rows: ArrayLike, times: ArrayLike | None,
         reason: str) -> tuple[FilterState, ChunkResult]:
    """A chunk through a filter that lost track: each row degenerate with ``reason``, repeating the
    filter's estimate; the state moves to the chunk's last time and computes nothing."""
    model = flt.model
    discrete = model.spec.measurement.kind == "discrete"
    checked = check_rows(rows, model.m, "observations" if discrete else "increments")
    K = len(checked)
    taus = resolve_times(state.t, state.step > 0, K, model.dt, times)
    steps, clock = chunk_clock(state, K, model.dt, times, taus)
    e = flt.estimate(state)
    n = len(e.mean)
    mean = np.repeat(np.asarray(e.mean, dtype=float).reshape(1, n), K, axis=0)
    cov = np.repeat(np.asarray(e.cov, dtype=float).reshape(1, n, n), K, axis=0)
    loglik = np.full(K, float(state.loglik))
    center = getattr(state, "center", None)
    centers = None if center is None else np.repeat(np.asarray(center, dtype=float)[None], K, axis=0)
    result = ChunkResult(step=np.asarray(steps, dtype=int), t=np.asarray(clock, dtype=float), mean=mean,
                         cov=cov, mode=None, loglik=loglik, loglik_increment=np.zeros(K),
                         degenerate=np.ones(K, dtype=bool), reason=reason if K else None,
                         center=centers)
    if K:
        state = dataclasses.replace(_marked(state, reason), step=int(steps[-1]), t=float(clock[-1]))
    return state, result


# -- the innovation monitor ---------------------------------------------------------------------------
def innovation_scores(flt: Filter, before: FilterState, result: ChunkResult, rows: np.ndarray) -> np.ndarray:
    """The normal scores z (K, m) of the rows' innovations (module docstring); NaN where a row or
    component is not scored.  Written for few array operations (a chunk of the 1-D engine costs about
    a tenth of its filtering): every row is computed, then the rows not to score are blanked."""
    model = flt.model
    first = flt.estimate(before)
    t = result.t
    taus = np.empty(len(t))
    taus[0] = t[0] - float(before.t)
    np.subtract(t[1:], t[:-1], out=taus[1:])
    with np.errstate(all="ignore"):
        if model.n == 1:  # the usual case: no matrix square roots
            mean = np.concatenate([np.asarray(first.mean, dtype=float), result.mean[:-1, 0]])
            var = np.concatenate([np.asarray(first.cov, dtype=float)[0], result.cov[:-1, 0, 0]])
            h_mean, h_var = _predicted_h_1d(model, mean, var, taus)
        else:
            means = np.concatenate([np.asarray(first.mean, dtype=float)[None], result.mean[:-1]])
            covs = np.concatenate([np.asarray(first.cov, dtype=float)[None], result.cov[:-1]])
            if model.spec.measurement.kind != "continuous":  # increments: as in the 1-D case
                means, covs = predicted_moments(model, means, covs, taus)
            h_mean, h_var = _predicted_h(model, means, covs)
        z = _standardised(model, h_mean, h_var, rows, taus)
    skip = result.gated | result.degenerate | result.reinitialised  # (taus < 0 cannot be: times increase)
    far = taus > MAX_GAP * float(model.dt)
    skip |= far
    z[skip] = np.nan
    z[np.isinf(z)] = np.nan
    return z


def _predicted_h_1d(model: Model, mean: np.ndarray, var: np.ndarray,
                    taus: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """E[h] and the diagonal of Cov[h] (K, m) at each row's time for a 1-D state, with the three points
    m, m ± √(3P) (weights 2/3, 1/6, 1/6).  Increments: under the previous row's posterior (E[h] moves by
    O(τ) over the row, which changes the score by O(τ^1.5)); measurements: carried to the row's time
    first (:func:`predicted_moments`)."""
    if model.spec.measurement.kind != "continuous":
        dt, a = float(model.dt), float(model.a[0, 0])
        if taus.max() <= dt * (1.0 + 1e-9):  # regular rows: one step
            mean, var = _euler_1d(model, mean, var, taus, a)
        else:
            count = np.maximum(np.ceil(taus / dt - 1e-9), 1)
            mean, var = mean.copy(), var.copy()
            for s in range(int(min(count.max(), MAX_GAP))):
                active = np.flatnonzero(count > s)
                step = taus[active] / count[active]
                mean[active], var[active] = _euler_1d(model, mean[active], var[active], step, a)
    K = len(mean)
    root = np.sqrt(3.0 * np.maximum(var, 0.0))
    h = np.asarray(model.h(np.concatenate([mean, mean + root, mean - root])[:, None]), dtype=float)
    h = h.reshape(3, -1)  # (3, K·m); elementwise sums (not BLAS): the same bits however the rows are chunked
    h_mean = (4.0 * h[0] + h[1] + h[2]) / 6.0
    h -= h_mean
    h *= h
    h_var = (4.0 * h[0] + h[1] + h[2]) / 6.0
    return h_mean.reshape(K, -1), h_var.reshape(K, -1)


def _euler_1d(model: Model, mean: np.ndarray, var: np.ndarray, h: np.ndarray, a: float):
    """One Euler step of length h (K,) of the 1-D moment equations (three unscented points)."""
    root = np.sqrt(3.0 * np.maximum(var, 0.0))
    f = np.asarray(model.f(np.concatenate([mean, mean + root, mean - root])[:, None]), dtype=float)
    f = f.reshape(3, -1)
    cross = root * (f[1] - f[2])  # 6 E[(x − m)(f − E f)]
    return mean + h * ((4.0 * f[0] + f[1] + f[2]) / 6.0), var + h * (cross / 3.0 + a)


def sigma_points(mean: np.ndarray, cov: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unscented points (K, 2n+1, n) and weights (2n+1,) of N(mean_k, cov_k): m, m ± √(n+κ)·(columns of
    cov^½), κ = max(3 − n, 0) (the 3-point Gauss–Hermite rule in 1-D)."""
    K, n = mean.shape
    kappa = max(3.0 - n, 0.0)
    scale = n + kappa
    sym = 0.5 * (cov + np.swapaxes(cov, 1, 2))
    lam, U = np.linalg.eigh(sym)
    root = U * np.sqrt(np.clip(lam, 0.0, None) * scale)[:, None, :]  # (K, n, n), columns
    offsets = np.concatenate([np.zeros((K, 1, n)), np.swapaxes(root, 1, 2), -np.swapaxes(root, 1, 2)], axis=1)
    weights = np.concatenate([[kappa / scale], np.full(2 * n, 0.5 / scale)])
    return mean[:, None, :] + offsets, weights


def predicted_moments(model: Model, mean: np.ndarray, cov: np.ndarray,
                      taus: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mean and covariance carried over each gap τ_k by Euler steps of at most dt of the moment
    equations ṁ = E f, Ṗ = E[(x − m) fᵀ] + E[f (x − m)ᵀ] + a (unscented expectations)."""
    mean, cov = mean.copy(), cov.copy()
    count = np.maximum(np.ceil(taus / float(model.dt) - 1e-9), 1).astype(int)
    a = np.asarray(model.a, dtype=float)
    for s in range(int(min(count.max(), MAX_GAP)) if len(count) else 0):
        active = np.flatnonzero(count > s) if s else slice(None)
        m, P = mean[active], cov[active]
        h = (taus[active] / count[active])
        points, weights = sigma_points(m, P)
        K, p, n = points.shape
        f = model.f(points.reshape(-1, n)).reshape(K, p, n)
        f_mean = np.einsum("p,kpi->ki", weights, f)
        cross = np.einsum("p,kpi,kpj->kij", weights, points - m[:, None], f - f_mean[:, None])
        mean[active] = m + h[:, None] * f_mean
        cov[active] = P + h[:, None, None] * (cross + np.swapaxes(cross, 1, 2) + a)
    return mean, cov


def _predicted_h(model: Model, mean: np.ndarray, cov: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """E[h] and the diagonal of Cov[h] (K, m) under N(mean, cov) (unscented)."""
    points, weights = sigma_points(mean, cov)
    K, p, n = points.shape
    h = np.asarray(model.h(points.reshape(-1, n)), dtype=float).reshape(K, p, -1)
    h_mean = np.einsum("p,kpj->kj", weights, h)
    spread = h - h_mean[:, None]
    return h_mean, np.einsum("p,kpj,kpj->kj", weights, spread, spread)


def _standardised(model: Model, h_mean: np.ndarray, h_var: np.ndarray, rows: np.ndarray,
                  taus: np.ndarray) -> np.ndarray:
    """z (K, m) of the rows: (y − κE[h]) / √(κ²Var[h] + S₀) (module docstring)."""
    spec = model.spec.measurement
    noise = model.R.diagonal()[None, :]
    if spec.kind == "continuous":
        tau = taus[:, None]
        return (rows - tau * h_mean) / np.sqrt(tau * tau * h_var + noise * tau)
    if spec.likelihood == "student-t":
        dof = float(spec.dof)
        if dof <= 2.0:  # no variance: nothing to standardise by
            return np.full(rows.shape, np.nan)
        noise = noise * dof / (dof - 2.0)
    return (rows - h_mean) / np.sqrt(h_var + noise)


@lru_cache(maxsize=64)
def thresholds(monitor: float, components: int = 1) -> tuple[float, ...]:
    """The CUSUM threshold of each chart of CHARTS for ``monitor`` healthy rows per false alarm of the
    whole monitor (2 sides × len(CHARTS) charts × ``components`` share it): Siegmund's approximation of
    a one-sided chart's mean run, ARL(k, h) = (e^{2kb} − 2kb − 1)/(2k²), b = h + 1.166."""
    charts = 2 * len(CHARTS) * max(components, 1)
    target = float(monitor) * charts
    return tuple(_solve_siegmund(2.0 * k * k * target) / (2.0 * k) - _SIEGMUND for k in CHARTS)


def _solve_siegmund(goal: float) -> float:
    """u > 0 with e^u − u − 1 = goal (u = 2kb): Newton's method from the right, where the convex
    left side makes it decrease monotonically onto the root (no SciPy import: the CLI starts fast)."""
    u = math.log1p(goal) + 1.0
    for _ in range(100):
        step = (math.expm1(u) - u - goal) / math.expm1(u)
        u -= step
        if abs(step) < 1e-12 * u:
            break
    return u


def run_charts(charts: tuple[float, ...], z: np.ndarray,
               monitor: float) -> tuple[tuple[float, ...], np.ndarray, np.ndarray]:
    """The two-sided CUSUM charts over the scores z (K, m) (NaN: not scored, the charts hold):
    (the charts after, ordered (side, component, chart); the signed statistic after each row (K,);
    the alarm rows (K,) bool).  A chart S ← max(0, S ± z − k) runs as the cumulative sum minus its
    running minimum (Lindley), so a chunk costs a few array operations; after an alarm every chart
    starts again from 0.  The scores are clipped to ±SCORE_CLIP and rounded to multiples of
    2^-QUANTUM_BITS, so every sum is exact in double precision: the charts, the statistic and the
    alarms do not depend on how the rows were split into chunks (bit for bit)."""
    K, m = z.shape
    signs, offsets, limits = _chart_constants(float(monitor), m)
    scale = float(1 << QUANTUM_BITS)
    start = np.zeros(len(limits)) if not charts else np.asarray(charts, dtype=float) * scale
    q = np.rint(np.clip(z, -SCORE_CLIP, SCORE_CLIP) * scale)
    if m == 1:
        steps = q * signs - offsets  # (K, 2C): +z − k then −z − k
    else:
        steps = (np.concatenate([q, -q], axis=1)[:, :, None] - offsets[:len(CHARTS)]).reshape(K, -1)
    nan = np.isnan(steps)
    if nan.any():
        steps[nan] = 0.0  # not scored: the charts hold
    statistic = np.empty(K)
    alarm = np.zeros(K, dtype=bool)
    half = len(limits) // 2
    row = 0
    while row < K:  # a block at a time: after an alarm only the block's rest is computed again
        totals = np.cumsum(steps[row:row + BLOCK], axis=0)
        totals += start
        now = totals - np.minimum(np.minimum.accumulate(totals, axis=0), 0.0)
        ratio = now / limits
        up, down = ratio[:, :half].max(axis=1), ratio[:, half:].max(axis=1)
        top = np.maximum(up, down)
        over = top >= 1.0
        value = np.where(up >= down, up, -down)
        if not over.any():  # the usual block: no alarm in it
            statistic[row:row + len(totals)] = value
            start = now[-1]
            row += len(totals)
            continue
        a = int(np.argmax(over))
        statistic[row:row + a + 1] = value[:a + 1]
        alarm[row + a] = True
        start = np.zeros_like(start)
        row += a + 1
    return tuple((start / scale).tolist()), statistic, alarm


@lru_cache(maxsize=64)
def _chart_constants(monitor: float, m: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(signs, offsets, thresholds) of the 2·m·C charts (side-major), in units of 2^-QUANTUM_BITS."""
    scale = float(1 << QUANTUM_BITS)
    C = len(CHARTS)
    signs = np.repeat([1.0, -1.0], C)
    offsets = np.tile(np.rint(np.asarray(CHARTS) * scale), 2)
    limits = np.tile(np.asarray(thresholds(monitor, m)), 2 * m) * scale
    return signs, offsets, limits
