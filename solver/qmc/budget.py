"""The Yau–Niu filter's point budget (solver/qmc/yau_niu.py): its defaults, the memory a budget needs,
and the check that refuses one beyond this machine's memory before anything is allocated."""

from __future__ import annotations

import os
from typing import Any

from ..errors import SpecError, TooLarge

DEFAULT_POINTS = 8192  # measured: see default_points
SINGLE_POINTS = 4096  # the same, for independent one-coordinate blocks
WORKING_ARRAYS = 9  # (N, n) float arrays alive during a row: points, drift, noise, deviations, ..., and the
# bank's normal set (solver/qmc/bank.py: one set where sets would pass its MAX_BYTES, else up to MAX_BYTES)
STATE_NUMBER_BYTES = 56  # a state number as JSON: a Python float and its list slot (32), its text (~24)


def default_points(n: int, singles: bool = False) -> int:
    """The default point budget: 8192 for every dimension (measured on the linear 4-D model: rms mean
    gap to Kalman 0.028 at 4096, 0.009 at 8192, 0.007 at 16384, at 5, 6 and 11 ms a row), SINGLE_POINTS
    where every block is one coordinate (independent sensors, each block a 1-D filter on its own
    lattice noise: ten cubic sensors 0.0107 from their exact filters at 4096 points, 0.0119 at 8192;
    bench/results/yau-niu.md), which keeps 100 of them in real time at dt = 0.01 on an AVX-512 machine
    (9.1 ms a row; 20 ms on an AVX2 one, where numpy's float64 exp has no SIMD loop)."""
    return SINGLE_POINTS if singles else DEFAULT_POINTS


def memory_needed(points: int, n: int, m: int, blocks: int | None = None) -> int:
    """Bytes a row needs for ``points`` points in n dimensions with m observation components: the
    row's (N, n) and (N, m) work arrays, plus the state written as JSON (n coordinates and one log
    weight per block per point; ``blocks`` None: n, the most there can be).  Nothing holds an N × N
    matrix (the kernel-matrix form was dropped: solver/qmc/yau_niu.py's docstring)."""
    blocks = n if blocks is None else blocks
    return 8 * points * (WORKING_ARRAYS * n + 2 * m + 4) + STATE_NUMBER_BYTES * points * (n + blocks)


def memory_limit() -> int:
    """The point budget's memory ceiling: this machine's physical memory."""
    return os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")


def check_points(points: Any, n: int, m: int, blocks: int | None = None, limit: int | None = None) -> int:
    """The point budget, or SpecError('discretization.points'): TooLarge (the service's 413) naming
    the memory it would need, the limit (``limit``; None: :func:`memory_limit`) and the largest budget
    that fits — checked before anything is allocated."""
    if isinstance(points, bool) or not isinstance(points, int) or points < 16:
        raise SpecError("discretization.points", "must be an integer of at least 16 (the QMC point budget)")
    limit = memory_limit() if limit is None else limit
    need = memory_needed(points, n, m, blocks)
    if need > limit:
        fits = limit // (memory_needed(1, n, m, blocks))
        raise TooLarge("discretization.points",
                       f"{points} points in {n} dimensions would need about {need / 2**30:.1f} GiB of "
                       f"memory ({memory_needed(1, n, m, blocks)} bytes a point), over the "
                       f"{limit / 2**30:.1f} GiB this machine has; set discretization.points to at most "
                       f"{fits} (the default, left out, is {DEFAULT_POINTS}; {SINGLE_POINTS} where every "
                       "block is one coordinate)")
    return points
