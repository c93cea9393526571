"""The compiled model: SymPy expressions of f, h and the prior, and their numpy forms.

Derivatives needed by the offline stage and the analysis are taken symbolically:
div f, the Jacobians of f and h, and hᵀR⁻¹h (the potential of seed 002 (5.31)).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

import numpy as np
import sympy as sp

from .errors import SpecError
from .expressions import number, parse_expression, state_symbols, vectorize, vectorize_many
from .spec import DensityPrior, GaussianPrior, MixturePrior, ModelSpec


@dataclass(frozen=True, eq=False)
class Model:
    """A validated model: ``symbols`` are internal (x_0, ...), ``spec.state`` the user's names."""

    spec: ModelSpec
    symbols: tuple[sp.Symbol, ...]
    drift: tuple[sp.Expr, ...]  # f
    observation: tuple[sp.Expr, ...]  # h
    prior_expr: sp.Expr | None = None  # unnormalised prior density, kind="density"
    _cache: dict = field(default_factory=dict, repr=False)

    # -- sizes and matrices ---------------------------------------------------------
    @property
    def n(self) -> int:
        return len(self.symbols)

    @property
    def m(self) -> int:
        return len(self.observation)

    @cached_property
    def a(self) -> np.ndarray:
        """Diffusion a = G Q Gᵀ."""
        return self.spec.diffusion_matrix()

    @cached_property
    def R(self) -> np.ndarray:
        return self.spec.noise_matrix()

    @cached_property
    def R_inv(self) -> np.ndarray:
        return np.linalg.inv(self.R)

    @property
    def dt(self) -> float:
        return self.spec.discretization.dt

    @property
    def radius(self) -> float:
        return self.spec.domain.radius

    @cached_property
    def center(self) -> np.ndarray:
        return self.spec.center()

    # -- symbolic derived quantities --------------------------------------------------
    @cached_property
    def div_drift(self) -> sp.Expr:
        return sp.simplify(sum(sp.diff(fi, xi) for fi, xi in zip(self.drift, self.symbols, strict=True)))

    @cached_property
    def jacobian_drift(self) -> sp.Matrix:
        return sp.Matrix(self.drift).jacobian(self.symbols)

    @cached_property
    def jacobian_observation(self) -> sp.Matrix:
        return sp.Matrix(self.observation).jacobian(self.symbols)

    @cached_property
    def potential(self) -> sp.Expr:
        """½ hᵀR⁻¹h, the observation-independent potential of seed 002 (5.31)."""
        h = sp.Matrix(self.observation)
        r_inv = sp.Matrix([[number(float(v)) for v in row] for row in self.R_inv])
        return sp.expand((h.T * r_inv * h)[0, 0] / 2)

    # -- numpy evaluators (points X of shape (P, n)) ----------------------------------
    @cached_property
    def f(self):
        return vectorize_many(self.drift, self.symbols)

    @cached_property
    def h(self):
        return vectorize_many(self.observation, self.symbols)

    @cached_property
    def div_f(self):
        return vectorize(self.div_drift, self.symbols)

    @cached_property
    def half_hRh(self):
        """½ hᵀR⁻¹h at points."""
        return vectorize(self.potential, self.symbols)

    @cached_property
    def jac_f(self):
        """Jacobian of f at points, shape (P, n, n)."""
        flat = vectorize_many(list(self.jacobian_drift), self.symbols)
        return lambda X: flat(X).reshape(-1, self.n, self.n)

    @cached_property
    def jac_h(self):
        """Jacobian of h at points, shape (P, m, n)."""
        flat = vectorize_many(list(self.jacobian_observation), self.symbols)
        return lambda X: flat(X).reshape(-1, self.m, self.n)

    # -- prior -----------------------------------------------------------------------
    def log_prior(self, X: np.ndarray) -> np.ndarray:
        """Log of the prior density at points (normalised for gaussian/mixture kinds)."""
        X = np.atleast_2d(np.asarray(X, dtype=float))
        prior = self.spec.initial
        if isinstance(prior, GaussianPrior):
            return _log_gaussian(X, np.asarray(prior.mean), np.asarray(prior.cov))
        if isinstance(prior, MixturePrior):
            w = np.asarray(prior.weights, float) / np.sum(prior.weights)
            logs = np.stack([np.log(wi) + _log_gaussian(X, np.asarray(mu), np.asarray(c))
                             for wi, mu, c in zip(w, prior.means, prior.covs, strict=True) if wi > 0])
            top = logs.max(axis=0)
            return top + np.log(np.exp(logs - top).sum(axis=0))
        with np.errstate(divide="ignore"):
            return np.log(np.clip(self._prior_fn(X), 0.0, None))

    def prior_density(self, X: np.ndarray) -> np.ndarray:
        return np.exp(self.log_prior(X))

    @cached_property
    def _prior_fn(self):
        return vectorize(self.prior_expr, self.symbols)

    def prior_moments(self) -> tuple[np.ndarray, np.ndarray] | None:
        """Mean and covariance of a gaussian/mixture prior; None for a density prior."""
        prior = self.spec.initial
        if isinstance(prior, GaussianPrior):
            return np.asarray(prior.mean, float), np.asarray(prior.cov, float)
        if isinstance(prior, MixturePrior):
            w = np.asarray(prior.weights, float) / np.sum(prior.weights)
            mus = np.asarray(prior.means, float)
            covs = np.asarray(prior.covs, float)
            mean = w @ mus
            d = mus - mean
            cov = np.einsum("k,kij->ij", w, covs) + np.einsum("k,ki,kj->ij", w, d, d)
            return mean, cov
        return None


def _log_gaussian(X: np.ndarray, mean: np.ndarray, cov: np.ndarray) -> np.ndarray:
    chol = np.linalg.cholesky(cov)
    z = np.linalg.solve(chol, (X - mean).T)
    log_det = 2.0 * np.log(np.diag(chol)).sum()
    return -0.5 * (z * z).sum(axis=0) - 0.5 * (len(mean) * np.log(2 * np.pi) + log_det)


def compile_model(spec: ModelSpec) -> Model:
    """Parse every expression of ``spec`` (safely) and build the :class:`Model`."""
    symbols = state_symbols(spec.n)
    names: dict[str, sp.Expr] = {name: number(float(v)) for name, v in spec.parameters.items()}
    names.update(dict(zip(spec.state, symbols, strict=True)))
    drift = tuple(parse_expression(e, names, f"drift[{i}]") for i, e in enumerate(spec.drift))
    obs = tuple(parse_expression(e, names, f"observation[{i}]") for i, e in enumerate(spec.observation))
    prior_expr = None
    if isinstance(spec.initial, DensityPrior):
        prior_expr = parse_expression(spec.initial.expression, names, "initial.expression")
    model = Model(spec=spec, symbols=symbols, drift=drift, observation=obs, prior_expr=prior_expr)
    _check_finite_on_domain(model)
    return model


def _check_finite_on_domain(model: Model) -> None:
    """Reject models whose f, h or prior are not finite on the ball (e.g. log(x) at 0)."""
    rng = np.random.default_rng(0)
    n = model.n
    direction = rng.normal(size=(256, n))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    radii = model.radius * rng.uniform(0, 1, size=(256, 1)) ** (1.0 / n)
    X = np.vstack([model.center + direction * radii, model.center[None, :]])
    for field_name, values in (("drift", model.f(X)), ("observation", model.h(X))):
        if not np.all(np.isfinite(values)):
            raise SpecError(field_name, "is not finite everywhere on the domain ball")
    if model.prior_expr is not None:
        values = model._prior_fn(X)
        if not np.all(np.isfinite(values)) or np.any(values < 0) or not np.any(values > 0):
            raise SpecError("initial.expression",
                            "prior density must be finite, non-negative and not identically zero on the ball")
