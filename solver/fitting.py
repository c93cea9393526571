"""Maximum likelihood of a spec's parameters from a record's log-likelihood (issue 39).

The filter of the method the spec resolves to gives the record's log-likelihood (the ``loglik``
column of ``run_arrays``: exact for Kalman–Bucy and the other exact filters, the engine's
near-exact one otherwise).  :func:`fit` maximises it over a box of free names with scipy:

* free names are entries of the spec's ``parameters`` table and the reserved
  ``observation_noise[i][i]`` / ``diffusion[i][i]`` (the noise variances); the spec's values start;
* the optimiser is scipy's bounded L-BFGS-B on the box scaled to [0, 1]ᵏ with finite-difference
  gradients: measured on OU's exact (Kalman–Bucy) likelihood of 1 000 irregular readings, it took 10
  evaluations where Powell with bounds took 40, both at the same optimum (θ within 3e-6, log-likelihood
  within 1e-9); the likelihood is smooth in the parameters;
* standard errors are from the observed information, the Hessian of the log-likelihood at the
  optimum by ``scipy.differentiate.hessian`` (central differences, steps scaled to each parameter);
* the offline stage depends on the drift and the diffusion only: a name entering neither reuses it; one
  that does recomputes it, cached by content (solver/fit_likelihood.py, which also says which parameters
  the drift uses: the free symbols of its SymPy expressions);
* with ``workers`` > 1 (or a Dask ``scheduler``) and a free name entering the offline stage, the
  evaluations that do not depend on each other run on Dask: L-BFGS-B's finite-difference points (scipy's
  own ``workers`` option: the optimiser unchanged), the Hessian's points, the profile's grid;
* a free parameter that no expression uses is bad input (InputError naming ``free.NAME``); a likelihood
  flat in a free name at the optimum (it changes by at most FLAT_TOL relative over the Hessian's step
  either side: the record does not determine it there, and the optimiser would stop anywhere) stops the
  fit with ``converged`` False and the reason naming it, its standard error NaN;
* a likelihood that is not finite (or a filter that refuses the parameters) somewhere the optimiser
  goes stops the fit: ``converged`` False and ``reason`` says where.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .blas import blas_threads, limited_blas
from .errors import InputError
from .fit_likelihood import RESERVED, Likelihood, Mapper, Stop, evaluations_on, offline_key, with_values
from .spec import ModelSpec

__all__ = ["FitResult", "fit", "offline_key", "with_values"]

PROFILE_POINTS = 21
FLAT_TOL = 1e-9  # relative change of the log-likelihood below which it is flat in a name


@dataclass
class FitResult:
    """The maximum-likelihood estimates of the free names and how they were found."""

    estimates: dict[str, float]
    stderr: dict[str, float]
    """From the observed information (NaN where the Hessian is not negative definite)."""
    loglik: float
    evaluations: int
    converged: bool
    method: str
    bounds_hit: list[str] = field(default_factory=list)
    reason: str = ""
    seconds: float = 0.0
    profile: dict[str, Any] | None = None
    """With ``profile=NAME``: {"name", "grid", "loglik"} (the other free names re-maximised)."""
    spec: ModelSpec | None = None
    """The spec with the fitted values."""
    note: str = ""
    """Where the evaluations ran (with workers)."""

    def as_json(self, profile: bool = False) -> dict[str, Any]:
        """The six keys of ``yauyau fit --json``; with ``profile`` a seventh, "profile"."""
        out = {"estimates": self.estimates, "stderr": self.stderr, "loglik": self.loglik,
               "evaluations": self.evaluations, "converged": self.converged, "method": self.method}
        if profile:
            out["profile"] = self.profile
        return _json_numbers(out)


def _json_numbers(value: Any) -> Any:
    """``value`` with every non-finite float as None (JSON's null: NaN and ±inf are not JSON)."""
    if isinstance(value, dict):
        return {key: _json_numbers(v) for key, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_json_numbers(v) for v in value]
    if isinstance(value, (float, np.floating)):
        return float(value) if math.isfinite(value) else None
    return value


# Continuous increments: the record's quadratic variation fixes R (Σ dy² over [0, T] → R·T), and the
# log-likelihood, a density against the noise's own Wiener measure, is not comparable across R: it grows
# without bound as R → 0, so a "maximum" would be the lower bound.
CONTINUOUS_NOISE = ("cannot be fitted from continuous increments: their quadratic variation fixes it "
                    "(R ≈ Σ dy² / T over the record) and the log-likelihood grows without bound as R → 0; "
                    "set it in the spec from Σ dy² / T, or fit it from discrete readings ([measurement] "
                    "kind = \"discrete\")")


def _check_free(spec: ModelSpec, free: Any) -> dict[str, tuple[float, float, float]]:
    """{name: (lo, hi, start)}, or InputError naming the field."""
    if not isinstance(free, dict) or not free:
        raise InputError("free", "name at least one parameter to fit: {NAME: (LO, HI)}")
    out = {}
    for name, box in free.items():
        where = f"free.{name}"
        match = RESERVED.match(str(name))
        if match:
            table, i, j = match.group(1), int(match.group(2)), int(match.group(3))
            size = spec.n if table == "diffusion" else spec.m
            if i != j or i >= size:
                raise InputError(where, f"only the diagonal {table}[i][i], i < {size}, can be fitted")
            if table == "observation_noise" and spec.measurement.kind == "continuous":
                raise InputError(where, CONTINUOUS_NOISE)
            start = float((spec.diffusion_matrix() if table == "diffusion" else spec.noise_matrix())[i, i])
            positive = True
        elif name in spec.parameters:
            start, positive = float(spec.parameters[name]), False
        else:
            raise InputError(where, f"is not in the spec's parameters table ({sorted(spec.parameters)}) nor "
                                    "observation_noise[i][i] / diffusion[i][i]")
        try:
            lo, hi = (float(b) for b in box)
        except (TypeError, ValueError):
            raise InputError(where, "must be a pair (LO, HI) of numbers") from None
        if not (math.isfinite(lo) and math.isfinite(hi)):
            raise InputError(where, "bounds must be finite")
        if lo >= hi:
            raise InputError(where, f"LO = {lo:g} must be below HI = {hi:g}")
        if positive and lo <= 0:
            raise InputError(where, f"a variance must be positive: LO = {lo:g}")
        if not lo <= start <= hi:
            raise InputError(where, f"the spec's value {start:g} (the start) is outside [{lo:g}, {hi:g}]")
        out[str(name)] = (lo, hi, start)
    return out


def _check_record(spec: ModelSpec, rows: Any, times: Any, k: int) -> tuple[np.ndarray, np.ndarray | None]:
    try:
        arr = np.asarray(rows, dtype=float)
    except (TypeError, ValueError):
        raise InputError("rows", "must be numbers (K, m)") from None
    if arr.ndim == 1 and spec.m == 1:
        arr = arr[:, None]
    if arr.ndim != 2 or arr.shape[1] != spec.m:
        raise InputError("rows", f"must be (K, {spec.m})")
    observed = int(np.sum(np.any(np.isfinite(arr), axis=1)))
    if observed < 2 * k + 1:
        raise InputError("rows", f"{observed} observed rows are too few for {k} free parameters "
                                 f"(at least {2 * k + 1})")
    if times is None:
        return arr, None
    t = np.asarray(times, dtype=float)
    if t.shape != (arr.shape[0],):
        raise InputError("times", f"must be ({arr.shape[0]},), one per row")
    return arr, t


def fit(spec: ModelSpec, rows: Any, times: Any = None, free: dict[str, tuple[float, float]] | None = None,
        profile: str | None = None, *, t0: float = 0.0, method: str | None = None, workers: int | None = None,
        scheduler: str | None = None) -> FitResult:
    """Maximum-likelihood estimates of the ``free`` names ({NAME: (LO, HI)}) from ``rows`` (K, m) at
    ``times`` (K,) (None: one dt apart from ``t0``); ``profile=NAME`` adds the profile log-likelihood of
    a free name; ``workers``/``scheduler``: Dask, see the module's docstring.  BLAS runs on
    $YAUYAU_BLAS_THREADS threads (default 1) meanwhile, as :func:`yauyau.open_filter` has it."""
    with limited_blas(blas_threads(None)):  # as open_filter: 1 unless told
        return _fit(spec, rows, times, free, profile, t0, method, workers, scheduler)


def _check_used(like: Likelihood, names: list[str]) -> None:
    """A free parameter that no expression depends on cannot change the likelihood: bad input."""
    used = frozenset().union(*like.parts.values())
    for name in names:
        if not RESERVED.match(name) and name not in used:
            raise InputError(f"free.{name}", "no expression of the drift, the observation or the prior "
                                             "depends on it, so the likelihood cannot: leave it out of the "
                                             "free names")


def _fit(spec: ModelSpec, rows: Any, times: Any, free: Any, profile: str | None, t0: float,
         method: str | None, workers: int | None, scheduler: str | None) -> FitResult:
    started = time.perf_counter()
    boxes = _check_free(spec, free)
    if profile is not None and profile not in boxes:
        raise InputError("profile", f"{profile!r} is not a free name ({sorted(boxes)})")
    arr, t = _check_record(spec, rows, times, len(boxes))
    like = Likelihood(spec, arr, t, t0, method)
    _check_used(like, list(boxes))
    with evaluations_on(workers, scheduler, like, list(boxes)) as (mapper, note):
        result = _maximise(like, boxes, profile, mapper)
    result.note = note
    result.seconds = time.perf_counter() - started
    return result


def _counted(like: Likelihood, mapper: Mapper | None) -> Mapper | None:
    """scipy's ``workers`` map: the points run elsewhere, counted here."""
    if mapper is None:
        return None

    def run(fun, items):
        items = list(items)
        like.evaluations += len(items)
        return mapper(fun, items)
    return run


def _maximise(like: Likelihood, boxes: dict[str, tuple[float, float, float]], profile: str | None,
              mapper: Mapper | None) -> FitResult:
    from scipy.optimize import minimize

    names = list(boxes)
    lo = np.array([boxes[n][0] for n in names])
    hi = np.array([boxes[n][1] for n in names])
    start = np.array([boxes[n][2] for n in names])
    width = hi - lo

    def values(u: np.ndarray) -> dict[str, float]:
        return dict(zip(names, (lo + np.clip(u, 0.0, 1.0) * width).tolist(), strict=True))

    options = {"eps": 1e-7, "maxiter": 200}
    if mapper is not None:
        options["workers"] = _counted(like, mapper)
    try:
        scale = max(1.0, abs(like(values((start - lo) / width))))
        found = minimize(_Objective(like, values, scale), (start - lo) / width, method="L-BFGS-B",
                         bounds=[(0.0, 1.0)] * len(names), options=options)
        u_hat, converged = np.clip(found.x, 0.0, 1.0), bool(found.success)
        reason = "" if converged else f"the optimiser stopped: {found.message}"
        best = like(values(u_hat))
    except Stop as stop:
        return FitResult(estimates=dict(zip(names, start.tolist(), strict=True)),
                         stderr=dict.fromkeys(names, math.nan), loglik=math.nan, evaluations=like.evaluations,
                         converged=False, method=like.method, reason=str(stop))
    estimates = values(u_hat)
    p_hat = np.array([estimates[n] for n in names])
    hit = [n for n, u in zip(names, u_hat, strict=True) if u <= 1e-6 or u >= 1 - 1e-6]
    stderr = dict.fromkeys(names, math.nan)
    try:
        flat = _flat(like, names, p_hat, lo, hi, best, mapper)
        keep = [i for i, n in enumerate(names) if n not in flat]
        if keep:
            stderr.update(_stderr(like, names, p_hat, lo, hi, keep, mapper))
        if flat:
            converged, reason = False, "; ".join(flat.values())
    except Stop as stop:
        converged, reason = False, f"standard errors: {stop}"
    result = FitResult(estimates=estimates, stderr=stderr, loglik=best, evaluations=0, converged=converged,
                       method=like.method, bounds_hit=hit, reason=reason,
                       spec=with_values(like.spec, estimates))
    if profile is not None:
        try:
            result.profile = _profile(like, names, profile, p_hat, lo, hi, mapper)
        except Stop as stop:
            result.profile = {"name": profile, "error": str(stop)}
    result.evaluations = like.evaluations
    return result


class _Objective:
    """−log-likelihood / scale on the box scaled to [0, 1]ᵏ (a class: Dask workers unpickle it)."""

    def __init__(self, like: Likelihood, values: Any, scale: float) -> None:
        self.like, self.values, self.scale = like, values, scale

    def __call__(self, u: np.ndarray) -> float:
        return -self.like(self.values(u)) / self.scale


def _steps(p_hat: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """The Hessian's step of each parameter: 1e-2 of it (or of its box near 0), at most a quarter of
    the room to the nearer bound."""
    step = 1e-2 * np.maximum(np.abs(p_hat), 1e-3 * (hi - lo))
    room = np.minimum(p_hat - lo, hi - p_hat)
    return np.where(room > 0, np.minimum(step, room / 4.0), step)


def _flat(like: Likelihood, names: list[str], p_hat: np.ndarray, lo: np.ndarray, hi: np.ndarray,
          best: float, mapper: Mapper | None) -> dict[str, str]:
    """{name: why} for each name in which the log-likelihood is flat at the optimum: it changes by at
    most FLAT_TOL·max(1, |ℓ|) a Hessian step either side (inside the box; the points are the Hessian's,
    evaluated once)."""
    step = _steps(p_hat, lo, hi)
    probes = []
    for i in range(len(names)):
        for sign in (-1.0, 1.0):
            q = p_hat.copy()
            q[i] = min(max(p_hat[i] + sign * step[i], lo[i]), hi[i])
            if q[i] != p_hat[i]:
                probes.append((i, q))
    found = like.many([dict(zip(names, q.tolist(), strict=True)) for _, q in probes], mapper)
    change = np.zeros(len(names))
    for (i, _), value in zip(probes, found, strict=True):
        change[i] = max(change[i], abs(value - best))
    tol = FLAT_TOL * max(1.0, abs(best))
    return {n: (f"the log-likelihood is flat in {n} at {n} = {p_hat[i]:.6g}: it changes by {change[i]:.2g} "
                f"(at most {tol:.2g}) over ±{step[i]:.2g}, so the record does not determine {n} there (the "
                f"optimiser stops anywhere on a plateau); fix {n} in the spec, or narrow its box to where "
                "the model depends on it")
            for i, n in enumerate(names) if change[i] <= tol}


def _stderr(like: Likelihood, names: list[str], p_hat: np.ndarray, lo: np.ndarray, hi: np.ndarray,
            keep: list[int], mapper: Mapper | None) -> dict[str, float]:
    """Standard errors of the names ``keep`` from the observed information: the Hessian of the
    log-likelihood at the optimum (scipy.differentiate.hessian, its points one batch per call) in
    coordinates scaled so that one unit is :func:`_steps`' step of each parameter."""
    from scipy.differentiate import hessian

    step = _steps(p_hat, lo, hi)[keep]

    def f(u: np.ndarray) -> np.ndarray:
        flat = u.reshape(len(keep), -1)
        points = []
        for j in range(flat.shape[1]):
            p = p_hat.copy()
            p[keep] += step * flat[:, j]
            points.append(dict(zip(names, p.tolist(), strict=True)))
        return np.array(like.many(points, mapper)).reshape(u.shape[1:])

    found = hessian(f, np.zeros(len(keep)), initial_step=1.0, maxiter=1, order=2)
    H = np.asarray(found.ddf, dtype=float) / np.outer(step, step)
    try:
        cov = np.linalg.inv(-H)
    except np.linalg.LinAlgError:
        return {}
    var = np.diag(cov)
    return {names[i]: (math.sqrt(v) if v > 0 and math.isfinite(v) else math.nan)
            for i, v in zip(keep, var, strict=True)}


def _profile(like: Likelihood, names: list[str], name: str, p_hat: np.ndarray, lo: np.ndarray,
             hi: np.ndarray, mapper: Mapper | None) -> dict[str, Any]:
    """The profile log-likelihood of ``name`` on PROFILE_POINTS points of its box (the others
    re-maximised from the estimates by L-BFGS-B); one free name: the grid is one batch."""
    from scipy.optimize import minimize

    i = names.index(name)
    grid = np.linspace(lo[i], hi[i], PROFILE_POINTS)
    others = [j for j in range(len(names)) if j != i]
    if not others:
        points = [{name: float(g)} for g in grid]
        return {"name": name, "grid": grid.tolist(), "loglik": like.many(points, mapper)}
    out = []
    w = hi[others] - lo[others]
    options = {"eps": 1e-7} if mapper is None else {"eps": 1e-7, "workers": _counted(like, mapper)}
    for g in grid:
        def values(u: np.ndarray, g: float = g) -> dict[str, float]:
            p = p_hat.copy()
            p[i] = g
            p[others] = lo[others] + np.clip(u, 0, 1) * w
            return dict(zip(names, p.tolist(), strict=True))

        found = minimize(_Objective(like, values, 1.0), (p_hat[others] - lo[others]) / w, method="L-BFGS-B",
                         bounds=[(0.0, 1.0)] * len(others), options=options)
        out.append(-float(found.fun))
    return {"name": name, "grid": grid.tolist(), "loglik": out}
