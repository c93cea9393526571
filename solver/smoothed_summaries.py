"""What a smoothed density says beyond its mean and covariance (issue 38): each row's marginal quantiles
of p(x_k | all the rows), by the filter's own summaries (solver/summaries.py) read on the smoothed
density.

The engine (yau-yau) hands its smoothed densities w ⊙ σ_k ⊙ β_k over block by block as filter states
(solver/engine/smoother.py ``smoothed_states``), so quantiles, the mode and ``density(...)`` are the very
code the filter's rows use; a Gaussian smoother (Kalman–Bucy's RTS) answers in closed form from the
smoothed mean and covariance, m_i + √P_ii Φ⁻¹(p).  The fixed-lag smoother (``smooth_lag``) hands its
densities over the same way: :func:`smooth_lag_with_quantiles`.
"""

from __future__ import annotations

from typing import Any, Callable

import numpy as np

from .errors import InputError
from .filtering import ChunkResult
from .smoothing import smooth, smooth_lag
from .summaries import check_probabilities, is_gaussian, quantiles


def offers_densities(flt: Any) -> bool:
    """Whether ``flt``'s smoother gives each row's smoothed density (quantiles, mode, density files): the
    Gaussian smoothers (closed form) and the engine's (it hands its densities to a ``visit``)."""
    smoother = getattr(type(flt), "smooth_arrays", None)
    return is_gaussian(flt) or (callable(smoother) and "visit" in smoother.__code__.co_varnames)


def smooth_with_quantiles(flt: Any, state: Any, rows: Any, times: Any = None, probs: Any = None,
                          each: Callable[[int, Any], None] | None = None) -> tuple[Any, ChunkResult, Any]:
    """(the filter's state after the chunk, the smoothed result, marginal quantiles (K, n, len(probs)) of
    each row's smoothed density or None without ``probs``).  ``each(k, smoothed_state)``, where given, is
    called for every row with its smoothed density as a state of ``flt`` (``flt.density(state, points)``
    and the rest read it; engine only)."""
    def run(visit: Visit | None) -> tuple[Any, ChunkResult]:
        if visit is None:
            return smooth(flt, state, rows, times)
        if not offers_densities(flt):
            raise InputError("quantiles", f"method {flt.method}: quantiles of the smoothed density are "
                                          "offered by the engine (yau-yau) and the Gaussian smoothers")
        return flt.smooth_arrays(state, rows, times, visit=visit)

    return _summarised(flt, run, probs, each)


def smooth_lag_with_quantiles(flt: Any, state: Any, rows: Any, times: Any = None, lag: int = 0,
                              probs: Any = None, each: Callable[[int, Any], None] | None = None,
                              ) -> tuple[Any, ChunkResult, Any]:
    """:func:`smooth_with_quantiles` for the fixed-lag smoother: row k's density given the rows up to
    k + ``lag`` (solver/smoothing.py ``smooth_lag``)."""
    def run(visit: Visit | None) -> tuple[Any, ChunkResult]:
        return smooth_lag(flt, state, rows, times, lag, visit=visit)

    return _summarised(flt, run, probs, each)


Visit = Callable[[int, list], None]


def _summarised(flt: Any, run: Callable[[Visit | None], tuple[Any, ChunkResult]], probs: Any,
                each: Callable[[int, Any], None] | None) -> tuple[Any, ChunkResult, Any]:
    """``run(visit)`` (a smoother handing its densities to ``visit(start, states)``, or None: the moments
    alone) with the quantiles of each row read off its density (closed form for a Gaussian smoother)."""
    probs = None if probs is None else check_probabilities(probs)
    if is_gaussian(flt):
        if each is not None:
            raise InputError("density", f"method {flt.method}: its smoothed density is the Gaussian of the "
                                        "smoothed mean and cov (no density file); the engine (yau-yau) "
                                        "writes one")
        new_state, result = run(None)
        if probs is None:
            return new_state, result, None
        from scipy.special import ndtri

        sd = np.sqrt(np.clip(np.diagonal(result.cov, axis1=1, axis2=2), 0.0, None))  # (K, n)
        return new_state, result, result.mean[:, :, None] + sd[:, :, None] * ndtri(probs)[None, None, :]
    if probs is None and each is None:
        new_state, result = run(None)
        return new_state, result, None
    found: dict[int, np.ndarray] = {}

    def visit(start: int, states: list) -> None:
        for i, smoothed in enumerate(states):
            if probs is not None:
                found[start + i] = quantiles(flt, smoothed, probs, smoothed.last)
            if each is not None:
                each(start + i, smoothed)

    new_state, result = run(visit)
    table = None if probs is None else np.stack([found[k] for k in range(len(result.step))])
    return new_state, result, table
