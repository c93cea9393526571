"""Shared pieces of the reference filters: the observation update factor, the step loop, states.

Every reference filter advances one observation interval as the Yau–Yau engine does: the
signal's Fokker–Planck flow over dt, then multiplication by the bounded update factor

    exp(hᵀR⁻¹Δy − ½hᵀR⁻¹h dt)                      # seed 002 (5.35), issue 3 (stable form)

and renormalisation; log Z of the normaliser ratio is the step's log-likelihood.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, replace
from typing import Any

import numpy as np

from ..errors import InputError, SpecError
from ..filtering import ChunkedFilter, Estimate, StepState, check_increments, observed
from ..model import Model
from ..spec import GaussianPrior


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


@dataclass(frozen=True)
class GaussianState(StepState):
    """State of a Gaussian filter (Kalman, EKF, UKF, Beneš parameters): mean (n,), cov (n, n)."""

    mean: np.ndarray = field(default_factory=lambda: np.zeros(1))
    cov: np.ndarray = field(default_factory=lambda: np.eye(1))

    def to_dict(self) -> dict[str, Any]:
        out = asdict(self)
        out["mean"] = self.mean.tolist()
        out["cov"] = self.cov.tolist()
        return out

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> "GaussianState":
        try:
            values = dict(data)
            values["mean"] = np.asarray(values["mean"], float)
            values["cov"] = np.asarray(values["cov"], float)
            return cls(**values)
        except (KeyError, TypeError, ValueError) as exc:
            raise InputError("state", f"not a valid filter state: {exc}") from None


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


def gaussian_estimate(state: GaussianState) -> Estimate:
    return Estimate(step=state.step, t=state.t, mean=state.mean.copy(), cov=state.cov.copy(),
                    loglik=state.loglik, loglik_increment=state.loglik_increment,
                    degenerate=state.degenerate, reason=state.reason, mode=state.mean.copy())


def gaussian_density(mean: np.ndarray, cov: np.ndarray, points: np.ndarray) -> np.ndarray:
    points = np.atleast_2d(np.asarray(points, float))
    chol = np.linalg.cholesky(cov)
    z = np.linalg.solve(chol, (points - mean).T)
    log_det = 2.0 * np.log(np.diag(chol)).sum()
    return np.exp(-0.5 * (z * z).sum(axis=0) - 0.5 * (len(mean) * np.log(2 * np.pi) + log_det))


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
    loglik = _log_normal(increment, predicted, innovation_cov) - _log_normal(
        increment, np.zeros_like(increment), model.R * model.dt)
    return new_mean, new_cov, loglik


def _log_normal(x: np.ndarray, mean: np.ndarray, cov: np.ndarray) -> float:
    chol = np.linalg.cholesky(cov)
    z = np.linalg.solve(chol, x - mean)
    return float(-0.5 * z @ z - np.log(np.diag(chol)).sum() - 0.5 * len(x) * np.log(2 * np.pi))


def gaussian_prior(model: Model, prior: Any | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Mean and covariance of the model's prior (moments of a mixture) or of a gaussian override."""
    if prior is None:
        moments = model.prior_moments()
        if moments is not None:
            return moments
    elif isinstance(prior, GaussianPrior):
        return np.asarray(prior.mean, float), np.asarray(prior.cov, float)
    raise SpecError("initial", "a Gaussian filter needs a gaussian (or mixture) prior")


class GaussianReferenceFilter(ReferenceFilter):
    """A filter whose state is a Gaussian N(mean, cov) started from the model's prior moments."""

    def initial_state(self, prior: Any | None = None) -> GaussianState:
        mean, cov = gaussian_prior(self.model, prior)
        return GaussianState(mean=mean, cov=cov)

    def estimate(self, state: GaussianState) -> Estimate:
        return gaussian_estimate(state)

    def density(self, state: GaussianState, points: np.ndarray) -> np.ndarray:
        return gaussian_density(state.mean, state.cov, points)

    def state_from_dict(self, data: dict[str, Any]) -> GaussianState:
        return GaussianState.from_dict(data)
