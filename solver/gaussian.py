"""Gaussian densities and the state of a filter whose posterior is N(mean, cov).

``log_normal`` is the one Gaussian log-density of the package (the prior, the Kalman filters'
likelihoods, the mixture components of Yau–Hu, the Beneš reference): log N(x; m, P) =
−½ zᵀz − log det L − (n/2) log 2π with P = LLᵀ, Lz = x − m.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

from .errors import InputError, SpecError
from .filtering import Estimate, StepState
from .spec_tables import GaussianPrior

LOG_2PI = math.log(2.0 * math.pi)


def log_normal(x: Any, mean: Any, cov: Any) -> np.ndarray:
    """log N(x; mean, cov) for points x (..., n).  ``cov`` (n, n) is shared by every point; a stack
    (K, n, n) (or (1, n, n)) goes with rows x (K, n) and means (K, n) or (n,).  Returns x's leading
    shape ((P,) for points (P, n), a 0-d array for one point)."""
    x, mean, cov = (np.asarray(a, dtype=float) for a in (x, mean, cov))
    n = x.shape[-1]
    chol = np.linalg.cholesky(cov)
    d = x - mean
    if chol.ndim == 2:
        z = np.linalg.solve(chol, d.reshape(-1, n).T).T.reshape(d.shape)
        log_det = np.log(np.diag(chol)).sum()
    else:
        z = np.linalg.solve(chol, d[..., None])[..., 0]
        log_det = np.log(np.diagonal(chol, axis1=-2, axis2=-1)).sum(-1)
    return -0.5 * (z * z).sum(-1) - log_det - 0.5 * n * LOG_2PI


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


def gaussian_estimate(state: GaussianState) -> Estimate:
    return Estimate(step=state.step, t=state.t, mean=state.mean.copy(), cov=state.cov.copy(),
                    loglik=state.loglik, loglik_increment=state.loglik_increment,
                    degenerate=state.degenerate, reason=state.reason, mode=state.mean.copy())


def gaussian_density(mean: np.ndarray, cov: np.ndarray, points: np.ndarray) -> np.ndarray:
    return np.exp(log_normal(np.atleast_2d(np.asarray(points, float)), mean, cov))


def gaussian_prior(model: Any, prior: Any | None = None, *,
                   exact: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Mean and covariance of the model's prior or of a gaussian override.  A mixture prior is
    moment-matched by the approximate filters (EKF, UKF); an ``exact`` filter refuses it, since its
    posterior would then be wrong from the first step."""
    if prior is None:
        if exact and model.spec.initial.kind != "gaussian":
            raise SpecError("initial", f"an exact Gaussian filter needs a gaussian prior, not a "
                                       f"{model.spec.initial.kind} one (moment-matching it would give a "
                                       "wrong posterior): use method yau-hu or yau-yau")
        moments = model.prior_moments()
        if moments is not None:
            return moments
    elif isinstance(prior, GaussianPrior):
        return np.asarray(prior.mean, float), np.asarray(prior.cov, float)
    raise SpecError("initial", "a Gaussian filter needs a gaussian prior"
                    + ("" if exact else " (or mixture)"))


class GaussianFilter:
    """Initial state, estimate, density and state (de)serialisation of a filter whose state is
    N(mean, cov) (``exact_prior``: refuse non-Gaussian priors instead of moment-matching them)."""

    model: Any
    exact_prior = False

    def initial_state(self, prior: Any | None = None) -> GaussianState:
        mean, cov = gaussian_prior(self.model, prior, exact=self.exact_prior)
        return GaussianState(mean=mean, cov=cov)

    def estimate(self, state: GaussianState) -> Estimate:
        return gaussian_estimate(state)

    def density(self, state: GaussianState, points: np.ndarray) -> np.ndarray:
        return gaussian_density(state.mean, state.cov, points)

    def state_from_dict(self, data: dict[str, Any]) -> GaussianState:
        return GaussianState.from_dict(data)
