"""The offline stage's independent solves: column blocks of the basis through the propagators.

A :class:`Job` is one ball's matrices (M du/dt = A u for e^{dt L}, and e^{dt L_K} for the literal
form) and the basis values it starts from; its columns are solved in fixed blocks of 32, in this
process or as Dask tasks (solver/offline/distributed.py), so the arrays are bit-identical whoever
solves them.  :func:`check_stable` judges what a job solved before it is used.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

from ..engine.diagnostics import MASS_GROWTH_LIMIT
from ..errors import SpecError
from ..model import Model
from .distributed import run_blocks

Progress = Callable[[int, int], None]


@dataclass(frozen=True)
class Job:
    fokker_planck: object
    kolmogorov: object | None  # None: only e^{dt L} (an atlas centre: the stable form never needs L_K)
    weights: np.ndarray
    dt: float
    substeps: int
    initial: np.ndarray  # (Q, N) basis values
    token: str = ""  # names the job on Dask workers (their factorisations are kept per token)
    mass: object | None = None  # sparse M of M du/dt = A u (scheme = "supg"); None: diag(weights)


WORKER: dict = {}


def setup(job: Job) -> None:
    """Factor both matrices once per process."""
    from .propagator import SdirkPropagator  # lazy: SuperLU loads only where a job runs

    WORKER["initial"] = job.initial
    WORKER["fp"] = SdirkPropagator(job.fokker_planck, job.weights, job.dt, job.substeps, job.mass)
    WORKER["k"] = (None if job.kolmogorov is None else
                    SdirkPropagator(job.kolmogorov, job.weights, job.dt, job.substeps, job.mass))


def propagate_block(columns: tuple[int, int]) -> tuple[int, int, np.ndarray, np.ndarray]:
    """One block of columns with the matrices this process factored (:func:`setup`)."""
    from .basis import blas_threads  # lazy: scipy.sparse loads only where a job runs

    start, stop = columns
    u0 = WORKER["initial"][:, start:stop]
    kolmogorov = WORKER["k"]
    with blas_threads(1):  # SuperLU's small dense kernels: threads only add contention (measured)
        return start, stop, WORKER["fp"].apply(u0), None if kolmogorov is None else kolmogorov.apply(u0)


def column_blocks(size: int, width: int = 32) -> list[tuple[int, int]]:
    """Fixed blocks of basis columns (independent of the worker count: reproducible output)."""
    return [(s, min(s + width, size)) for s in range(0, size, width)]


def propagate_all(job: Job, workers: int = 1, progress: Progress | None = None,
                  scheduler: str | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Every column block of ``job`` (:func:`propagate_jobs` of one job)."""
    return propagate_jobs([job], workers, progress, scheduler)[0]


def propagate_jobs(jobs: list[Job], workers: int = 1, progress: Progress | None = None,
                   scheduler: str | None = None,
                   finished: Callable[[int, np.ndarray, np.ndarray | None], None] | None = None,
                   ) -> list[tuple[np.ndarray, np.ndarray | None] | None]:
    """Every column block of every job: in this process (one worker and no scheduler, or a single
    block), else as Dask tasks (solver/offline/distributed.py).  The blocks are fixed, so the arrays are
    bit-identical whoever solves them.  ``progress(done, total)`` counts basis columns over all jobs.
    ``finished(j, e^{dt L}φ, e^{dt L_K}φ)``: called as soon as job j's last block is in, which then
    keeps nothing of it (its entry is None): an atlas's centres are not all held at once."""
    out: list[Any] = [None] * len(jobs)
    left = [job.initial.shape[1] for job in jobs]
    tasks = [(j, block) for j, job in enumerate(jobs) for block in column_blocks(job.initial.shape[1])]
    total = sum(job.initial.shape[1] for job in jobs)
    done = 0

    def store(j, result):
        nonlocal done
        start, stop, a, b = result
        if out[j] is None:  # the job's arrays, made when its first block arrives
            initial = jobs[j].initial
            out[j] = (np.empty_like(initial), None if jobs[j].kolmogorov is None else np.empty_like(initial))
        out[j][0][:, start:stop] = a
        if b is not None:
            out[j][1][:, start:stop] = b
        left[j] -= stop - start
        done += stop - start
        if progress is not None:
            progress(done, total)
        if finished is not None and left[j] == 0:
            finished(j, *out[j])
            out[j] = None

    if scheduler is None and (workers <= 1 or len(tasks) == 1):
        for j, job in enumerate(jobs):
            setup(job)
            try:
                for block in column_blocks(job.initial.shape[1]):
                    store(j, propagate_block(block))
            finally:
                WORKER.clear()
    else:
        run_blocks(jobs, tasks, store, dask_block, workers=workers, scheduler=scheduler)
    return out


def dask_block(job: Job, columns: tuple[int, int]) -> tuple[int, int, np.ndarray, np.ndarray]:
    """One column block on a Dask worker: both matrices factored once per worker and job (kept
    under the job's token), then the block's solves."""
    if WORKER.get("token") != job.token:
        WORKER.clear()
        setup(job)
        WORKER["token"] = job.token
    return propagate_block(columns)


def check_stable(model: Model, nodes: np.ndarray, weights: np.ndarray, basis_values: np.ndarray,
                 projector: np.ndarray, propagator_fp: np.ndarray) -> None:
    """Predict the prior (no data) over t = 1 (at most 2000 steps): SpecError naming the cure when a
    step creates mass (e.g. drift -x**64 on a radius-7 ball: ×1e34 per step, the log-likelihood then
    grows by ~79 a step while the data allow at most ~5), positive or negative (the same drift with
    basis 48: ×-6e30, a model degenerate from its first step)."""
    step = projector @ propagator_fp  # coefficients -> coefficients
    mass_of = weights @ basis_values
    log_prior = model.log_prior(nodes)
    finite = np.isfinite(log_prior)
    if not finite.any():
        return  # the prior's own error is reported where the prior is used
    density = np.where(finite, np.exp(np.where(finite, log_prior - log_prior[finite].max(), 0.0)), 0.0)
    c = projector @ density
    mass = float(mass_of @ c)
    for k in range(int(min(2000, max(1, round(1.0 / model.dt))))):
        if not mass > 0.0:
            return  # all mass left the ball: the engine reports that as it happens
        c = step @ c / mass
        new_mass = float(mass_of @ c)
        if not abs(new_mass) <= 1.0 + MASS_GROWTH_LIMIT:  # more mass, or a huge negative one (-x**64: -6e30)
            with np.errstate(all="ignore"):
                speed = float(np.max(np.abs(model.f(nodes))))
            raise SpecError("discretization", (
                f"the Fokker-Planck propagator is unstable: step {k + 1} of dt = {model.dt:g} multiplies the "
                f"probability mass by {new_mass:.3g} (a stable flow never creates mass); the drift reaches "
                f"|f| = {speed:.3g} on the ball, too stiff for this mesh and dt: shrink domain.radius, "
                "lower discretization.dt or raise discretization.substeps"))
        mass = new_mass
