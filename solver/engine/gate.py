"""A chunk made ready for the hot loop, and its outlier gate (solver/measurement.py).

The gate judges an observed row by its predictive score d² against the threshold of its size: a
cheap bound g = bias − 2(log ∫σ + top) each step (one comparison: ∫σ ≥ floor), the exact score
(with the covariance correction log det(I + κ²S₀⁻¹C), C = Cov_pred(h)) only for the rows over it.
A gated row only predicts.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from typing import Any

import numpy as np

from ..measurement import Observation, RowTerms


@dataclass(frozen=True, eq=False)
class Prepared:
    """A chunk made ready for the hot loop (:meth:`YauYauFilter.prepare`)."""

    gaps: np.ndarray
    keys: np.ndarray
    terms: RowTerms
    log_factor: np.ndarray  # (K, Q) log e_k − top[k]
    top: np.ndarray  # (K,)
    top_before: np.ndarray
    impossible: np.ndarray
    missing: np.ndarray
    skip: np.ndarray  # rows that only predict
    gate: "Gate | None"
    initial: np.ndarray  # [coefficients, ∫σ] in the loop's precision
    shifts: np.ndarray | None = None  # (K, n) each row's node shift in a moving frame (engine/frame.py)
    origin: np.ndarray | None = None  # the centre the shifts are from
    moving: Any = None  # a Recentring (solver/engine/recentring.py): a ball that moves inside the loop


class Gate:
    """The outlier gate of one chunk (solver/measurement.py): per row the bound's bias and the
    threshold; ``correction`` the exact term from the predicted density; ``scores`` the gated rows."""

    def __init__(self, obs: Observation, terms: RowTerms, keys: np.ndarray, gaps: np.ndarray,
                 engine: Any, shifts: np.ndarray | None = None):
        self.obs, self.keys, self.gaps, self.engine = obs, keys, gaps, engine
        self.shifts = shifts  # (K, n) in a moving frame: h at each row's moved nodes
        self.terms = terms
        self.scores: dict[int, float] = {}  # gated row -> d²
        self.attempted: dict[int, float] = {}  # gated row -> log E_pred[e] of the rejected update

    @cached_property
    def bias(self) -> list[float]:
        """Per row, the bound's bias (the slow steps read it; a fused chunk never does)."""
        return self.terms.bound_bias().tolist()

    @cached_property
    def threshold(self) -> list[float]:
        """Per row, the d² threshold (inf: not gated)."""
        return self.terms.threshold.tolist()

    def size(self, k: int) -> int:
        return int(self.keys[k]).bit_count()

    def floor_exponents(self, missing: np.ndarray, start: int = 0) -> np.ndarray:
        """(bias − threshold)/2 of the rows from ``start`` (``missing``: theirs), −inf where nothing is
        gated (a row without observation, the gate off for its size): log of :meth:`floors` but the top."""
        part = slice(start, start + len(missing))
        threshold = self.terms.threshold[part]
        with np.errstate(invalid="ignore"):
            exponent = 0.5 * (self.terms.bound_bias()[part] - threshold)
        exponent[np.asarray(missing) | ~np.isfinite(threshold)] = -np.inf
        exponent[np.isnan(exponent)] = np.inf
        return exponent

    def floors(self, top: np.ndarray, missing: np.ndarray, start: int = 0) -> list[float]:
        """Per row, the ∫σ below which the cheap bound is over the threshold: exp((bias − threshold)/2
        − top) (0 where nothing is gated); ``top`` and ``missing`` of the rows from ``start`` on."""
        with np.errstate(over="ignore", invalid="ignore"):
            return np.exp(self.floor_exponents(missing, start) - top).tolist()

    def correction(self, k: int, s: np.ndarray, shift: np.ndarray | None = None) -> float:
        """log det(I + κ²S₀⁻¹C), C = Cov(h_o) under the propagated nodal density s (its nodes moved by
        ``shift``, or by the row's in a moving frame)."""
        key = int(self.keys[k])
        index = self.obs.pattern(key).index
        ws = self.engine.weights * np.asarray(s, dtype=float)
        total = float(ws.sum())
        if not total > 0.0:
            return 0.0
        if shift is None and self.shifts is not None:
            shift = self.shifts[k]
        h = (self.engine.h_nodes if shift is None else self.engine.h_shifted(shift[None])[0])[:, index]
        centred = h - (ws @ h) / total
        cov = (centred * ws[:, None]).T @ centred / total
        tau = float(self.gaps[k])
        return max(0.0, self.obs.covariance_correction(key, float(self.terms.kappa2[k]), cov,
                                                       self.obs.S0_scale(tau)))
