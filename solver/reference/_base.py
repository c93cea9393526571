"""Shared pieces of the reference filters: the observation update factor, the step loop, states.

Every reference filter advances one observation interval as the Yau–Yau engine does: the
signal's Fokker–Planck flow over dt, then multiplication by the bounded update factor

    exp(hᵀR⁻¹Δy − ½hᵀR⁻¹h dt)                      # seed 002 (5.35), issue 3 (stable form)

and renormalisation; log Z of the normaliser ratio is the step's log-likelihood.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np

from ..filtering import Estimate, StepState, check_increments, observed
from ..gaussian import (
    GaussianFilter,
    log_normal,
)
from ..model import Model


def log_update_factor(model: Model, points: np.ndarray, increment: np.ndarray) -> np.ndarray:
    """log of exp(hᵀR⁻¹Δy − ½hᵀR⁻¹h dt) at points (P, n) -> (P,)."""
    return model.h(points) @ (model.R_inv @ increment) - model.half_hRh(points) * model.dt


def log_sum_exp(log_values: np.ndarray, weights: np.ndarray | None = None) -> float:
    """log Σ w·exp(v) without overflow; -inf if every term is zero."""
    finite = np.isfinite(log_values)
    if not finite.any():
        return -np.inf
    top = np.max(log_values[finite])
    terms = np.exp(log_values - top)
    total = terms.sum() if weights is None else terms @ weights
    return float(top + np.log(total)) if total > 0 else -np.inf


def advance(state: StepState, dt: float, loglik_increment: float, **changes: Any) -> StepState:
    """The next state: one more step, the log-likelihood accumulated."""
    return replace(state, step=state.step + 1, t=(state.step + 1) * dt,
                   loglik=state.loglik + loglik_increment, loglik_increment=loglik_increment, **changes)


class ReferenceFilter:
    """The Filter protocol's run/step loop; subclasses give ``_advance`` and ``estimate``."""

    method = "reference"

    def __init__(self, model: Model):
        self.model = model

    def _advance(self, state: Any, increment: np.ndarray | None) -> Any:
        raise NotImplementedError

    def estimate(self, state: Any) -> Estimate:
        raise NotImplementedError

    def step(self, state: Any, increment: np.ndarray | None) -> tuple[Any, Estimate]:
        state = self._advance(state, observed(increment, self.model.m))
        return state, self.estimate(state)

    def run(self, state: Any, increments: np.ndarray) -> tuple[Any, list[Estimate]]:
        rows = check_increments(increments, self.model.m)
        estimates = []
        for row in rows:
            state = self._advance(state, None if np.isnan(row).all() else row)
            estimates.append(self.estimate(state))
        return state, estimates


def gaussian_update(model: Model, mean: np.ndarray, cov: np.ndarray, predicted: np.ndarray,
                    innovation_cov: np.ndarray, cross_cov: np.ndarray, increment: np.ndarray):
    """Kalman-type update for Δy = h dt + v, v ~ N(0, R dt), given the predicted Δy moments.

    Returns (mean, cov, loglik increment).  The log-likelihood is that of the update factor,
    log E[exp(hᵀR⁻¹Δy − ½hᵀR⁻¹h dt)] = log N(Δy; ŷ, S) − log N(Δy; 0, R dt), exact when h is
    affine and the predictive density Gaussian.
    """
    gain = np.linalg.solve(innovation_cov, cross_cov.T).T
    residual = increment - predicted
    new_mean = mean + gain @ residual
    new_cov = cov - gain @ innovation_cov @ gain.T
    new_cov = 0.5 * (new_cov + new_cov.T)
    loglik = float(log_normal(increment, predicted, innovation_cov)
                   - log_normal(increment, np.zeros_like(increment), model.R * model.dt))
    return new_mean, new_cov, loglik


class GaussianReferenceFilter(GaussianFilter, ReferenceFilter):
    """A reference filter whose state is a Gaussian N(mean, cov) started from the model's prior
    moments (a mixture prior is moment-matched: these are approximations)."""
