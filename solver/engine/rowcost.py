"""What a row costs this engine, measured: regular rows (one dt apart) and irregular rows (gaps drawn in
0.5–1.5 dt, the flow e^{τA} of solver/engine/semigroup.py), for `yauyau check` and `yauyau precompute`
(and bench/irregular_cost.py).

A short timing: chunks of ``rows`` rows of zero increments (every row a full step), CPU time
(time.process_time) with one BLAS thread, after one warm-up chunk of each kind (the compiled loops,
the flow's decomposition and tables), the median of ``repeats``.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

import numpy as np

ROWS = 300
REPEATS = 3


@dataclass(frozen=True)
class RowCost:
    regular_us: float  # µs per regular row
    irregular_us: float  # µs per irregular row
    flow: str  # the flow's form for irregular rows: modal, schur or expm

    @property
    def ratio(self) -> float:
        return self.irregular_us / self.regular_us

    def line(self) -> str:
        return (f"cost per row: regular {self.regular_us:.1f} µs, irregular {self.irregular_us:.1f} µs "
                f"({self.ratio:.2f}x; flow {self.flow})")


def chunk_timer(engine: Any, rows: int, irregular: bool):
    """A function that runs one chunk of ``rows`` zero rows from the prior and returns its CPU seconds
    (irregular: new gaps each call, so that no flow cached per gap is reused)."""
    zeros = np.zeros((rows, engine.model.m))
    seeds = iter(range(3, 1 << 30))

    def run() -> float:
        state = engine.initial_state()
        times = irregular_times(engine, rows, next(seeds)) if irregular else None
        began = time.process_time()
        engine.run_arrays(state, zeros, times)
        return time.process_time() - began

    return run


def irregular_times(engine: Any, rows: int, seed: int = 3) -> np.ndarray:
    """Times whose gaps are drawn uniformly in [0.5, 1.5]·dt."""
    dt = engine.model.dt
    return engine.initial_state().t + np.cumsum(np.random.default_rng(seed).uniform(0.5, 1.5, rows) * dt)


def row_costs(engine: Any, rows: int = ROWS, repeats: int = REPEATS) -> RowCost:
    """The measured µs per regular and per irregular row of ``engine`` (a general engine: YauYauFilter, or
    a following ball)."""
    from threadpoolctl import threadpool_limits

    jobs = {"regular": chunk_timer(engine, rows, False), "irregular": chunk_timer(engine, rows, True)}
    seconds: dict[str, list[float]] = {name: [] for name in jobs}
    with threadpool_limits(limits=1, user_api="blas"):
        for job in jobs.values():  # warm: the compiled loops, the flow's decomposition and tables
            job()
        for _ in range(repeats):  # interleaved
            for name, job in jobs.items():
                seconds[name].append(job())
    regular, irregular = (1e6 * float(np.median(seconds[name])) / rows for name in jobs)
    return RowCost(regular, irregular, engine.flow.form)
