"""The record's log-likelihood as a function of a spec's free names, for :mod:`.fitting` (issue 39).

* :func:`with_values` sets parameters and the reserved noise variances ``observation_noise[i][i]`` /
  ``diffusion[i][i]`` in a spec (validated again);
* :func:`parameters_in` says which parameters each part of the model uses: the free symbols of its
  SymPy expressions (solver/expressions.py ``parameters_used``), never a match on the text;
* :class:`Likelihood` runs the filter of the spec's method once per point; the offline stage depends on
  the drift and the diffusion only (the stable form filters with ``propagator_fp``), so it is cached by
  the content hash of those (:func:`offline_key`, as precompute hashes a spec into a model id): a name
  entering only h, the observation noise or the prior reuses it, one entering the drift or the diffusion
  recomputes it;
* :func:`evaluations_on` maps a batch of points to a Dask cluster (a local one of K processes, or a
  running scheduler, as ``yauyau precompute`` does: solver/offline/distributed.py ``dask_client``).
"""

from __future__ import annotations

import hashlib
import json
import math
import re
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import replace
from typing import Any

import numpy as np

from .errors import InputError, YauyauError
from .expressions import parameters_used
from .spec import DensityPrior, ModelSpec, spec_from_dict

RESERVED = re.compile(r"^(observation_noise|diffusion)\[(\d+)\]\[(\d+)\]\Z")
OFFLINE_CACHE = 8  # offline stages kept per likelihood (by content)

Mapper = Callable[[Callable[[Any], Any], list], list]


class Stop(Exception):
    """The likelihood is not usable at a point: the fit stops and says so."""


def with_values(spec: ModelSpec, values: dict[str, float]) -> ModelSpec:
    """``spec`` with the named parameters / noise variances set (validated again)."""
    data = spec.model_dump(mode="json")
    for name, value in values.items():
        match = RESERVED.match(name)
        if match:
            table, i = match.group(1), int(match.group(2))
            matrix = (spec.diffusion_matrix() if table == "diffusion" else spec.noise_matrix()).tolist()
            if data.get(table) is not None:
                matrix = data[table]
            matrix[i][i] = float(value)
            data[table] = matrix
        else:
            data["parameters"][name] = float(value)
    return spec_from_dict(data)


def parameters_in(spec: ModelSpec) -> dict[str, frozenset[str]]:
    """{"drift", "observation", "initial"}: the spec's parameters each part's expressions depend on (the
    free symbols of their SymPy trees)."""
    names, state = list(spec.parameters), list(spec.state)
    parts = {"drift": parameters_used(spec.drift, state, names, "drift"),
             "observation": parameters_used(spec.observation, state, names, "observation"),
             "initial": frozenset()}
    if isinstance(spec.initial, DensityPrior):
        parts["initial"] = parameters_used([spec.initial.expression], state, names, "initial.expression")
    return parts


def enters_offline(name: str, drift_names: frozenset[str]) -> bool:
    """Whether changing ``name`` changes the offline stage: the diffusion, or a parameter of the drift."""
    if name.startswith("diffusion["):
        return True
    return not name.startswith("observation_noise[") and name in drift_names


def offline_key(spec: ModelSpec, drift_names: frozenset[str] | None = None) -> str:
    """The content hash of what the offline stage depends on: drift, diffusion, the parameters the
    drift uses (``drift_names``; from :func:`parameters_in` when None), the domain and the
    discretisation."""
    if drift_names is None:
        drift_names = parameters_in(spec)["drift"]
    data = json.loads(spec.canonical_json())
    part = {k: data.get(k) for k in ("drift", "diffusion", "domain", "discretization", "state")}
    part["parameters"] = {k: v for k, v in spec.parameters.items() if k in drift_names}
    return hashlib.sha256(json.dumps(part, sort_keys=True).encode()).hexdigest()


class Likelihood:
    """log p(record | values), one filter run per new point (values seen are kept); the offline stage
    cached by content.  Picklable without its caches (a Dask worker starts empty)."""

    def __init__(self, spec: ModelSpec, rows: np.ndarray, times: np.ndarray | None, t0: float,
                 method: str | None) -> None:
        from .methods import choose_method
        from .model import compile_model
        from .registry import REGISTRY

        self.spec, self.rows, self.times, self.t0 = spec, rows, times, t0
        self.method = choose_method(compile_model(spec), method)[0]  # auto: the analysis, once, at the start
        self.needs_offline = REGISTRY[self.method].needs_offline
        self.parts = parameters_in(spec)
        self.cache: dict[str, Any] = {}
        self.seen: dict[tuple, float] = {}
        self.evaluations = 0

    def __getstate__(self) -> dict[str, Any]:
        return {**self.__dict__, "cache": {}, "seen": {}, "evaluations": 0}

    def offline(self, spec: ModelSpec, model: Any) -> Any:
        if not self.needs_offline:
            return None
        from .offline.pipeline import precompute

        key = offline_key(spec, self.parts["drift"])
        found = self.cache.get(key)
        if found is None:
            if len(self.cache) >= OFFLINE_CACHE:
                self.cache.clear()
            found = self.cache[key] = precompute(model)
        return replace(found, model=model) if found.model is not model else found

    def __call__(self, values: dict[str, float]) -> float:
        key = tuple(values.items())
        if key not in self.seen:
            self.seen[key] = self._run(values)
            self.evaluations += 1
        return self.seen[key]

    def many(self, points: list[dict[str, float]], mapper: Mapper | None) -> list[float]:
        """The log-likelihood at each point; the new ones through ``mapper`` (None: here, in turn)."""
        new = list({tuple(p.items()): p for p in points if tuple(p.items()) not in self.seen}.values())
        if mapper is not None and len(new) > 1:
            for p, value in zip(new, mapper(self._run, new), strict=True):
                self.seen[tuple(p.items())] = value
            self.evaluations += len(new)
        return [self(p) for p in points]

    def _run(self, values: dict[str, float]) -> float:
        from .filtering import at_time
        from .methods import make_filter
        from .model import compile_model

        where = ", ".join(f"{k} = {v:.6g}" for k, v in values.items())
        try:
            spec = with_values(self.spec, values)
            model = compile_model(spec)
            # no gating: every row counts in the likelihood
            flt = make_filter(model, self.offline(spec, model), self.method, gate=0)
            state = at_time(flt.initial_state(None), self.t0)
            _, result = flt.run_arrays(state, self.rows, self.times)
        except YauyauError as exc:
            raise Stop(f"the filter refuses {where}: {exc}") from None
        loglik = float(np.asarray(result.loglik)[-1])
        if not math.isfinite(loglik) or bool(np.any(np.asarray(result.degenerate))):
            raise Stop(f"the log-likelihood is not finite (or the filter degenerated) at {where}")
        return loglik


@contextmanager
def evaluations_on(workers: int | None, scheduler: str | None, like: Likelihood,
                   free: list[str]) -> Iterator[tuple[Mapper | None, str]]:
    """(mapper, note): a map of the likelihood over a batch of points on Dask where it pays, else None
    (here, in turn).  It pays where a free name enters the offline stage (every point recomputes it,
    seconds) and ``workers`` > 1 or a ``scheduler`` is given; elsewhere an evaluation costs
    milliseconds and the points stay here (the note says why)."""
    if workers is not None and workers < 1:
        raise InputError("workers", "must be a positive integer")
    asked = scheduler is not None or (workers or 1) > 1
    drift = [n for n in free if enters_offline(n, like.parts["drift"])]
    if not asked:
        yield None, ""
        return
    if not (like.needs_offline and drift):
        yield None, (f"evaluations in this process: no free name enters the offline stage of {like.method} "
                     "(each evaluation takes milliseconds)")
        return
    from concurrent.futures import CancelledError

    from distributed.scheduler import KilledWorker

    from .offline.distributed import dask_client

    where = scheduler or f"a local Dask cluster of {workers} processes"
    with dask_client(workers or 1, scheduler) as client:
        def mapper(fun: Callable[[Any], Any], items: Any) -> list:
            try:
                return client.gather(client.map(fun, list(items), pure=False))
            except (OSError, TimeoutError, CancelledError, KilledWorker) as exc:  # the cluster, not the spec
                raise InputError("scheduler" if scheduler else "workers",
                                 f"{where} failed during the fit ({type(exc).__name__}: {exc}); run it "
                                 "again, or without --workers / --scheduler (in this process)") from None

        yield mapper, f"evaluations of {', '.join(drift)} (offline stage recomputed) in parallel on {where}"
