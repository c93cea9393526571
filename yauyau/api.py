"""The public Python face of yauyau: spec -> precompute -> open a filter -> step it.

    import yauyau

    spec = yauyau.load_spec(yauyau.examples.path("cubic_sensor"))   # the examples ship with the package
    yauyau.analyze(spec).method                            # the recommended filter, and why (.reason)
    model_id = yauyau.precompute(spec, "var/store")        # offline stage, once, into an HDF5 store
    flt = yauyau.open_filter("var/store", model_id)        # the method chosen at precompute
    sim = yauyau.simulate(spec, steps=500, seed=1)          # truth and increments dy_k
    chunk = flt.run(sim.increments)                         # ChunkResult: mean, cov, mode, loglik...
    flt.density([[0.0], [1.0]])                             # conditional density now

A filter of :mod:`yauyau.solver` is a function of (state, data) (the ``Filter`` protocol of
``yauyau.solver.filtering``); :class:`OnlineFilter` carries its state along, as a stream needs.
"""

from __future__ import annotations

import os
import warnings
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike

from .solver.check import coarser_than_measured
from .solver.errors import InputError, SpecError
from .solver.filtering import (
    ChunkResult,
    Estimate,
    Filter,
    FilterState,
    MarginalFilter,
    marginal_by_quadrature,
)
from .solver.methods import choose_method
from .solver.spec import ModelSpec, load_spec
from .storage.model_store import ModelStore

if TYPE_CHECKING:  # types only: at run time these modules load when a function first needs them
    from .solver.analysis.report import AnalysisReport
    from .solver.model import Model
    from .solver.offline.jobs import Progress
    from .solver.offline.pipeline import OfflineModel
    from .solver.simulate import Simulation
    from .solver.watch import LostTrack, Watch, WatchSettings

DEFAULT_TIME_LIMIT = 60.0  # seconds the estimation-algebra analysis may spend choosing the method

PathArg = str | os.PathLike[str]
"""A file or directory: a string or a path."""
AtlasSink = Callable[[int, int, dict[str, Any]], None]
"""Where an atlas's centres go as they are solved: ``sink(k, K, arrays of centre k)``."""


def _as_spec(spec: ModelSpec | PathArg) -> ModelSpec:
    return spec if isinstance(spec, ModelSpec) else load_spec(Path(spec))


def _as_store(store: ModelStore | PathArg) -> ModelStore:
    return store if isinstance(store, ModelStore) else ModelStore(store)


@dataclass(frozen=True)
class Solved:
    """The offline stage of one spec, solved: the model, its arrays, the method chosen and why."""

    spec: ModelSpec
    """The spec solved."""
    model: Model
    """Its compiled model."""
    offline: OfflineModel | None
    """The offline stage's arrays (None: a mesh-free model has none)."""
    method: str
    """The filter method chosen (a registry name)."""
    method_reason: str
    """Why that method was chosen."""
    seconds: float
    """Wall-clock seconds the offline stage took."""
    workers: int
    """The local processes that solved it."""
    scheduler: str | None = None  # ``workers`` then unused
    """The running Dask cluster that solved it (None: local processes)."""

    def attrs(self) -> dict[str, Any]:
        """What the model file records besides the arrays (read back by :func:`load_model`): where it was
        solved is ``workers`` local processes, or the cluster at ``scheduler``."""
        where = {"workers": self.workers} if self.scheduler is None else {"scheduler": self.scheduler}
        return {"precompute_seconds": round(self.seconds, 3), **where, "name": self.spec.name,
                "method": self.method, "method_reason": self.method_reason,
                "offline": self.offline is not None}

    def arrays(self) -> dict[str, np.ndarray]:
        """The arrays to store: the offline stage's, none for a mesh-free model."""
        return {} if self.offline is None else self.offline.to_arrays()

    def lazy_arrays(self) -> dict[str, np.ndarray]:
        """The arrays to store row by row: an atlas's per-centre propagators ([domain] region)."""
        return {} if self.offline is None else self.offline.lazy_arrays()


def solve(spec: ModelSpec | PathArg, *, workers: int = 1,
          time_limit: float | None = DEFAULT_TIME_LIMIT, progress: Progress | None = None,
          scheduler: str | None = None, atlas_sink: AtlasSink | None = None,
          analysis_grace: float | None = None) -> Solved:
    """The offline stage of ``spec`` (seed 002 §5) and the method choice (``auto``: the analysis, in a
    process of its own killed ``analysis_grace`` seconds (default 2) after ``time_limit``: a wall-clock
    bound), without storing anything.  The propagators' independent solves run
    as Dask tasks on ``workers`` local processes, or on the cluster at ``scheduler``
    ("tcp://HOST:PORT"); the arrays are bit-identical either way.  ``atlas_sink(k, K, rows)``: an
    atlas's centres go there as they are solved instead of being kept (a ``ModelWriter.rows``)."""
    import time

    from .solver.model import compile_model
    from .solver.offline.pipeline import precompute as solve_offline

    spec = _as_spec(spec)
    model = compile_model(spec)
    started = time.perf_counter()
    if mesh_free_only(model):
        method, reason = _mesh_free_method(model, time_limit, analysis_grace)
        return Solved(spec, model, None, method, reason, time.perf_counter() - started, workers)
    if spec.domain.follow:  # one stored propagator must serve every centre: say so before solving
        from .solver.engine.follow import check_follow

        check_follow(model)
    from .solver.offline.computable import check_computable

    check_computable(model)  # a radius, diffusion or drift beyond a double's precision: before solving
    offline = solve_offline(model, workers=workers, progress=progress, scheduler=scheduler,
                            atlas_sink=atlas_sink)
    seconds = time.perf_counter() - started
    method, reason = choose_method(model, offline=offline, time_limit=time_limit, grace=analysis_grace)
    return Solved(spec, model, offline, method, reason, seconds, workers, scheduler)


def mesh_free_only(model: Model) -> bool:
    """True when the model gets no offline stage: more than three state variables (the general
    engine's finite elements go up to 3), or a method named in the spec that needs none (kalman-bucy,
    yau-jia: nothing to precompute).  A mesh-free method filters it.  (A diffusion that is only
    positive semi-definite is the engine's too, with the stabilised scheme: Discretization.scheme.)"""
    from .solver.registry import mesh_free

    return mesh_free(model.spec)


def _mesh_free_method(model: Model, time_limit: float | None, grace: float | None) -> tuple[str, str]:
    from .solver.methods import make_filter
    from .solver.registry import REGISTRY

    method, reason = choose_method(model, offline=None, time_limit=time_limit, grace=grace)
    if REGISTRY[method].needs_offline:
        why = f"{model.n} state variables (the engine's finite elements go up to 3)"
        raise SpecError("state", f"{why}: the general engine cannot filter this model and no mesh-free exact "
                               f"method applies ({reason}); mesh-free methods: kalman-bucy (linear models), "
                               "yau-jia (Yau & Jia (2005) class: f = Lx + l + a grad(phi), h^T R^-1 h + ... "
                               "quadratic)")
    make_filter(model, None, method)  # it applies (SpecError naming why, otherwise)
    return method, reason + "; mesh-free model: no offline stage"


def precompute(spec: ModelSpec | PathArg, store: ModelStore | PathArg, *,
               workers: int = 1, time_limit: float | None = DEFAULT_TIME_LIMIT, force: bool = False,
               progress: Progress | None = None, scheduler: str | None = None,
               analysis_grace: float | None = None) -> str:
    """Solve the offline stage of ``spec`` (a :class:`ModelSpec` or a spec file) and save it in
    ``store`` (a directory or a :class:`ModelStore`); returns the model id (a content hash).

    The filter method is chosen here, once (``auto`` asks the estimation-algebra analysis within
    ``time_limit`` seconds, wall clock: its process is killed ``analysis_grace`` seconds (default 2)
    later and the general engine is chosen unless what it had decided names an exact filter), and
    stored with its reason; :func:`open_filter` reads it back.  A model
    already in the store is verified and kept unless ``force``.  A mesh coarser than the measured
    default of the spec's dimension is warned about (a ``UserWarning`` naming the field and the fix)
    before the solve.
    """
    from .storage.errors import StoreError
    from .storage.model_store import model_id

    spec = _as_spec(spec)
    store = _as_store(store)
    spec_json = spec.canonical_json()
    mid = model_id(spec_json)
    if not force and store.exists(mid):
        try:
            store.load(mid)
            return mid
        except StoreError:
            pass  # unusable file: compute it again
    coarse = coarser_than_measured(spec)
    if coarse is not None:
        warnings.warn(f"{coarse[0]}: {coarse[1]}", UserWarning, stacklevel=2)
    return save_solved(store, spec, workers=workers, time_limit=time_limit, progress=progress,
                       scheduler=scheduler, analysis_grace=analysis_grace)[0]


def save_solved(store: ModelStore, spec: ModelSpec, **solve_args: Any) -> tuple[str, Solved]:
    """:func:`solve` ``spec`` into ``store``: the file is opened first (an unwritable store fails
    before the long computation), an atlas's centres are written as they are solved, the rest at the
    end; returns the model id and what was solved."""
    with store.writer(spec.canonical_json()) as writer:
        solved = solve(spec, atlas_sink=writer.rows, **solve_args)
        writer.arrays_by_row(solved.lazy_arrays())
        return writer.finish(solved.arrays(), solved.attrs()), solved


@dataclass(frozen=True)
class StoredFilterModel:
    """A stored model opened for filtering: the compiled model, its offline arrays and the method
    chosen at precompute (with the reason)."""

    id: str
    """The model id (a content hash of the spec)."""
    model: Model
    """The compiled model."""
    offline: OfflineModel | None
    """The offline stage's arrays (None: a mesh-free model)."""
    method: str
    """The filter method chosen at precompute (a registry name)."""
    method_reason: str
    """Why that method was chosen."""
    attrs: dict[str, Any]
    """What the model file records besides the arrays (:meth:`Solved.attrs`)."""


def load_model(store: ModelStore | PathArg, model_id: str) -> StoredFilterModel:
    """Read and verify a stored model.  The method is the one chosen at precompute; only a file saved
    without one (``ModelStore.save`` called directly, with no "method" attr) makes the analysis run,
    here, once, with a warning."""
    from .solver.model import compile_model
    from .solver.offline.pipeline import OfflineModel
    from .solver.spec import parse_spec_text

    stored = _as_store(store).load(model_id)
    model = compile_model(parse_spec_text(stored.spec_json, "json"))
    offline = (None if stored.attrs.get("offline") is False else
               OfflineModel.from_arrays(model, stored.arrays, lazy=stored.lazy))
    method, reason = stored.attrs.get("method"), stored.attrs.get("method_reason", "")
    if not method:
        warnings.warn(f"model {model_id} was saved without a method: choosing it now (yauyau.precompute "
                      "stores it)", stacklevel=2)
        method, reason = choose_method(model, offline=offline)
    return StoredFilterModel(id=model_id, model=model, offline=offline, method=method, method_reason=reason,
                             attrs=stored.attrs)


def open_filter(store: ModelStore | PathArg, model_id: str, method: str | None = None, *,
                prior: Any | None = None, form: str = "stable", precision: str | None = None,
                gate: float | None = None, on_degenerate: str = "stop", t0: float = 0.0,
                lost_track: LostTrack | dict[str, int] | None = None,
                monitor: float | None = None, blas_threads: int | None = None) -> OnlineFilter:
    """A ready-to-step filter of a stored model.

    ``method`` overrides the one chosen at precompute (``yau-yau``, ``kalman-bucy``, ...; an exact
    filter that does not apply raises SpecError('method')); ``prior`` (a spec prior, e.g.
    ``{"kind": "gaussian", "mean": [0], "cov": [[1]]}``) overrides the model's and holds at time
    ``t0``; ``gate`` overrides the spec's ``[measurement] gate`` (0: off); ``on_degenerate`` is
    "stop" (the state stays degenerate until ``reinitialise``) or "reinitialise" (start again from a
    broadened prior around the last good estimate, yauyau.solver.recovery).  ``lost_track`` (a dict of
    ``gated``, ``restarts``, ``window``; None: the defaults) says when a filter that keeps gating or
    restarting has lost track, and ``monitor`` sets the innovation monitor (healthy rows per false
    alarm; 0: off; None: the spec's ``[measurement] monitor``): yauyau.solver.watch.  ``blas_threads``
    limits this process's BLAS to that many threads (threadpoolctl), as ``yauyau filter`` and ``yauyau
    serve`` do: None is ``$YAUYAU_BLAS_THREADS`` or 1 (one thread per process is the faster on a
    machine doing anything else, bench/results/blas.md), 0 leaves BLAS as the process has it.
    """
    from .solver.blas import blas_threads as thread_count
    from .solver.blas import limit_process_blas
    from .solver.methods import make_filter

    threads = thread_count(blas_threads, allow_keep=True)  # bad input refused before anything is read

    if not isinstance(model_id, str):
        raise InputError("model_id", "must be a model id (a string; yauyau models lists them)")
    loaded = load_model(store, model_id)
    if method == "auto":
        raise SpecError("method", "auto is resolved at precompute; name a method or leave it out")
    flt = make_filter(loaded.model, loaded.offline, method or loaded.method, form=form, precision=precision,
                      gate=gate)
    online = OnlineFilter(flt, prior=prior, on_degenerate=on_degenerate, t0=t0, lost_track=lost_track,
                          monitor=monitor)
    limit_process_blas(threads)
    return online


def simulate(spec: ModelSpec | PathArg | Model, steps: int, seed: int | None = 0,
             substeps: int = 10, times: Any | None = None) -> Simulation:
    """A sample path of the model and its observations (Euler–Maruyama with ``substeps`` per dt):
    ``.times`` (K+1,) from 0, ``.states`` (K+1, n), ``.rows`` (K, m): the ``.increments`` of a
    continuous model or the ``.observations`` of a discrete one (``[measurement] kind``).  ``times``
    (K,): observe at these times (strictly increasing, > 0) instead of every dt."""
    from .solver.model import Model, compile_model
    from .solver.simulate import simulate as simulate_model

    model = spec if isinstance(spec, Model) else compile_model(_as_spec(spec))
    if isinstance(steps, bool) or not isinstance(steps, int) or steps < 1:
        raise InputError("steps", "must be a positive integer")
    return simulate_model(model, steps, np.random.default_rng(seed), substeps=substeps, times=times)


def analyze(spec: ModelSpec | PathArg | Model, **bounds: Any) -> AnalysisReport:
    """The estimation-algebra analysis of ``spec`` (a :class:`ModelSpec`, a spec file, or a compiled
    model), in this process: an :class:`yauyau.solver.analysis.AnalysisReport` (Wong matrix, η, the
    structural conditions, the algebra, ``.method`` recommended and ``.reason``; ``.render()`` is the
    text of ``yauyau analyze``, ``.to_dict()`` its JSON).  ``bounds``: ``max_depth``,
    ``max_dimension``, ``time_limit`` (seconds; None: unbounded) and ``max_size``, as
    :func:`yauyau.solver.analysis.analyze` takes them (its defaults when left out)."""
    from .solver.analysis import analyze as analyze_model
    from .solver.model import Model, compile_model

    model = spec if isinstance(spec, Model) else compile_model(_as_spec(spec))
    return analyze_model(model, **bounds)


class OnlineFilter:
    """A filter and its current state: ``step`` one row or ``run`` a chunk (at regular or given times);
    ``estimate``, ``mean``, ``cov``, ``mode`` and ``loglik`` now; the ``density`` and ``marginal`` now;
    ``predict(t)`` a forecast.

    ``mode`` and ``quantiles(probs)`` summarise a density that a mean cannot (yauyau.solver.summaries).
    ``filter`` is the underlying :class:`yauyau.solver.filtering.Filter` (a pure function of state
    and data); ``state`` is its JSON-safe state (``state_dict()``/``restore`` move it between
    processes, exactly).  ``on_degenerate``: "stop" or "reinitialise" (yauyau.solver.recovery).
    ``watch`` (yauyau.solver.watch) is what the rows said so far: whether the filter lost track (then
    it stays degenerate until ``reset`` or ``reinitialise``) and the innovation monitor's charts
    (``alarm`` on the rows where it is raised); it is part of ``state_dict()``.
    """

    def __init__(self, flt: Filter, prior: Any | None = None, state: FilterState | None = None, *,
                 on_degenerate: str = "stop", t0: float = 0.0,
                 lost_track: LostTrack | dict[str, int] | None = None, monitor: float | None = None,
                 watch: Watch | None = None) -> None:
        from .solver.filtering import check_t0
        from .solver.recovery import check_policy
        from .solver.watch import Watch, settings_for

        self.filter: Filter = flt
        self.model: Model = flt.model
        self.method: str = flt.method
        self.on_degenerate: str = check_policy(on_degenerate)
        self.t0: float = check_t0(t0, "t0", float(flt.model.dt))
        self.watch_settings: WatchSettings = settings_for(flt, lost_track, monitor)
        self.watch: Watch = Watch() if watch is None else watch
        self.state: FilterState = self._initial(prior) if state is None else state

    def _initial(self, prior: Any | None) -> FilterState:
        from .solver.filtering import at_time

        return at_time(self.filter.initial_state(prior), self.t0)

    def __repr__(self) -> str:
        return f"<OnlineFilter {self.model.spec.name!r} method={self.method} step={self.state.step}>"

    # -- stepping -----------------------------------------------------------------------
    def step(self, row: ArrayLike | None = None, t: float | None = None) -> Estimate:
        """One row: an increment Δy (continuous kind) or a measurement z (discrete kind), m numbers
        (NaN: that component missing), or None to only predict; at time ``t`` (default: one dt on)."""
        from .solver.filtering import one_row

        rows = one_row(row, self.model.m, "row")
        gate: float | None = getattr(self.filter, "gate", None)  # a filter that never gates has none
        return self.run(rows, None if t is None else [t]).estimates(gate)[0]

    def run(self, rows: ArrayLike, times: ArrayLike | None = None) -> ChunkResult:
        """A chunk of rows (K, m) (NaN: missing), at ``times`` (K,) (absolute, strictly increasing) or
        one dt apart; returns the chunk's estimates as arrays (``step``, ``t``, ``mean`` (K, n), ``cov``
        (K, n, n), ``mode``, ``loglik``, ``predictive_loglik``, ``gated``, ``degenerate``,
        ``reinitialised``, ``reason``; ``.estimates()`` gives Estimate objects)."""
        from .solver.watch import watched_run

        self.state, self.watch, result = watched_run(self.filter, self.state, self.watch, rows, times,
                                                     self.on_degenerate, self.watch_settings)
        return result

    def smooth(self, rows: ArrayLike, times: ArrayLike | None = None, lag: int | None = None) -> ChunkResult:
        """The optimal smoother over a recorded chunk from the current state: the result of :meth:`run`
        with each row's ``mean``, ``cov`` and ``mode`` given every row of the chunk (``lag`` L: given
        the rows up to L after it, fixed-lag); the filter then stands after the chunk, as ``run`` leaves
        it.  Methods yau-yau, kalman-bucy and yau-hu (exact); another raises SpecError('method') naming it
        (yauyau.solver.smoothing)."""
        from .solver.smoothing import smooth, smooth_lag

        if lag is None:
            self.state, result = smooth(self.filter, self.state, rows, times)
        else:
            self.state, result = smooth_lag(self.filter, self.state, rows, times, lag)
        return result

    def smooth_quantiles(self, rows: ArrayLike, probs: ArrayLike, times: ArrayLike | None = None,
                         lag: int | None = None) -> tuple[ChunkResult, np.ndarray]:
        """:meth:`smooth` with the marginal quantiles of each row's smoothed density (``lag`` L: given the
        rows up to L after it): (the result, quantiles (K, n, len(probs))), by the filter's own quantile
        code on the smoothed densities (yau-yau) or the Gaussian's closed form (kalman-bucy);
        yauyau.solver.smoothed_summaries."""
        from .solver.smoothed_summaries import smooth_lag_with_quantiles, smooth_with_quantiles

        if lag is None:
            self.state, result, table = smooth_with_quantiles(self.filter, self.state, rows, times, probs)
        else:
            self.state, result, table = smooth_lag_with_quantiles(self.filter, self.state, rows, times, lag,
                                                                  probs)
        return result, table

    def iterate(self, rows: ArrayLike, times: Iterable[float] | None = None) -> Iterator[Estimate]:
        """Yield one Estimate per row, stepping as it goes."""
        from .solver.measurement import check_rows

        checked = check_rows(rows, self.model.m)
        at: list[float | None] = [None] * len(checked) if times is None else list(times)
        if len(at) != len(checked):
            raise InputError("times", f"needs one time per row: {len(checked)} row(s), got {len(at)} time(s)")
        for row, t in zip(checked, at, strict=True):
            yield self.step(None if np.isnan(row).all() else row, t)

    def predict(self, t: float) -> "OnlineFilter":
        """The forecast at time ``t`` (after now) with no observation: an OnlineFilter of its own (its
        ``mean``, ``cov``, ``density(points)``, ``quantiles()``, ...); this one is unchanged."""
        state, _ = self.filter.predict(self.state, t)
        return OnlineFilter(self.filter, state=state, on_degenerate=self.on_degenerate, t0=self.t0,
                            lost_track=self.watch_settings.lost, monitor=self.watch_settings.monitor,
                            watch=self.watch)

    # -- now ------------------------------------------------------------------------------
    @property
    def estimate(self) -> Estimate:
        """The :class:`Estimate` now (mean, covariance, log-likelihood, ...), without stepping."""
        return self.filter.estimate(self.state)

    @property
    def t(self) -> float:
        """The filter's time now."""
        return float(self.state.t)

    @property
    def mean(self) -> np.ndarray:
        """(n,) the conditional mean now."""
        return self.estimate.mean

    @property
    def cov(self) -> np.ndarray:
        """(n, n) the conditional covariance now."""
        return self.estimate.cov

    @property
    def mode(self) -> np.ndarray | None:
        """The MAP point (the tallest node refined by a local quadratic fit for the engine; a
        search of the density for the other filters); None when degenerate."""
        from .solver.summaries import mode

        return mode(self.filter, self.state)

    def quantiles(self, probs: Sequence[float] | np.ndarray = (0.05, 0.5, 0.95)) -> np.ndarray:
        """Marginal quantiles now: an array (n, len(probs)), row i for state variable i."""
        from .solver.summaries import quantiles

        return quantiles(self.filter, self.state, probs)

    @property
    def loglik(self) -> float:
        """The cumulative log-likelihood of the rows so far (log of the normaliser ratio)."""
        return self.estimate.loglik

    @property
    def degenerate(self) -> bool:
        """Whether the filter could not resolve a step (it stays so until ``reinitialise`` or
        ``reset``, or restarts by itself with ``on_degenerate="reinitialise"``)."""
        return bool(self.state.degenerate)

    @property
    def lost(self) -> str | None:
        """Why the filter lost track (None: it did not); cleared by ``reset`` and ``reinitialise``."""
        return self.watch.lost

    @property
    def monitor(self) -> float:
        """The innovation monitor's statistic after the last row (±1: an alarm; yauyau.solver.watch)."""
        return self.watch.statistic

    def density(self, points: ArrayLike) -> np.ndarray:
        """Normalised conditional density at points (P, n) (for n = 1 a flat list will do)."""
        points = np.asarray(points, dtype=float)
        if points.ndim == 1 and self.model.n == 1:
            points = points[:, None]
        return self.filter.density(self.state, points)

    def marginal(self, variable: int | str, grid: ArrayLike, resolution: int = 64) -> np.ndarray:
        """Marginal density of one state variable (index or name) at the values ``grid``."""
        names = list(self.model.spec.state)
        if isinstance(variable, str):
            if variable not in names:
                raise InputError("variable", f"unknown state variable {variable!r} (have {names})")
            variable = names.index(variable)
        values = np.asarray(grid, dtype=float)
        if isinstance(self.filter, MarginalFilter):  # the engine's own, on its nodes
            return self.filter.marginal(self.state, variable, values, resolution)
        return _gaussian_box_marginal(self, variable, values, resolution)

    # -- state ------------------------------------------------------------------------------
    def state_dict(self) -> dict[str, Any]:
        """The state as JSON-safe data (carried log-likelihood and the watch included; yau-niu's points
        and log weights as {"dtype": "<f8", "shape", "base64"} of their bytes: exact)."""
        from .solver.watch import join_state

        return join_state(self.state, self.watch)

    def restore(self, data: dict[str, Any]) -> None:
        """Continue from a :meth:`state_dict` (validated; bad fields raise InputError)."""
        from .solver.watch import split_state

        data, watch = split_state(data)
        self.state = self.filter.state_from_dict(data)
        self.watch = watch

    def reset(self, prior: Any | None = None) -> None:
        """Back to the start (t0) with the model's prior (or ``prior``); the watch starts again."""
        from .solver.watch import Watch

        self.state = self._initial(prior)
        self.watch = Watch()

    def reinitialise(self, prior: Any | None = "last") -> Estimate:
        """Start again now (same step and time, log-likelihood carried) from ``prior``: "last" (a prior
        broadened around the last good estimate: a degenerate filter recovers), None (the model's)
        or a spec prior.  Returns the new estimate."""
        from .solver.recovery import restart, restart_from_last
        from .solver.watch import Watch

        if isinstance(prior, str) and prior == "last":
            self.state, _ = restart_from_last(self.filter, self.state)
        else:
            self.state = restart(self.filter, self.state, prior)
        self.watch = Watch()  # a filter that lost track is on track again: the counts start again
        return self.estimate


def _gaussian_box_marginal(flt: OnlineFilter, variable: int, grid: np.ndarray, resolution: int) -> np.ndarray:
    """Marginal over a box of ±8 standard deviations around the mean (the filters without a marginal
    of their own have light-tailed densities)."""
    mean, sd = flt.mean, np.sqrt(np.clip(np.diag(flt.cov), 1e-300, None))
    return marginal_by_quadrature(flt.density, flt.model.n, variable, grid, mean - 8 * sd, mean + 8 * sd,
                                  resolution)


__all__ = ["OnlineFilter", "Solved", "StoredFilterModel", "choose_method", "load_model", "open_filter",
           "precompute", "simulate", "solve"]
