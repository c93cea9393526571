"""The compiled model: numpy forms of f, h, ½hᵀR⁻¹h and the prior, and (lazily) their SymPy forms.

    dx = f(x) dt + G dv,   dy = h(x) dt + dw        (the problem part of the spec)

``compile_model`` builds the numpy evaluators straight from the checked syntax trees
(solver/expressions.py), without SymPy: a stored model filters without ever importing it.  The
exact SymPy expressions (``drift``, ``observation``, ``prior_expr`` on the internal symbols
``x_0, x_1, ...``) and what is derived from them symbolically — div f, the Jacobians of f and h,
½hᵀR⁻¹h, the potential of seed 002 (5.31) — are built on first use, by the offline stage, the
analysis and the exact filters.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from typing import TYPE_CHECKING, Any, Callable

import numpy as np

from .errors import SpecError
from .expressions import (
    affine_coefficients,
    number,
    parse_expression,
    state_symbols,
    vectorize,
    vectorize_many,
)
from .gaussian import log_normal
from .spec import POSTERIOR_NEEDS_LINEAR, ModelSpec
from .spec_tables import DensityPrior, GaussianPrior, MixturePrior, mixture_weights

if TYPE_CHECKING:
    import sympy as sp
    from numpy.typing import ArrayLike

Points = Callable[[np.ndarray], np.ndarray]


@dataclass(frozen=True, eq=False)
class Model:
    """A validated model.  ``f``, ``h``, ``half_hRh`` and ``log_prior`` are numpy functions of points
    X (P, n); ``symbols`` (internal, x_0, ...), ``drift``, ``observation`` and ``prior_expr`` are the
    SymPy forms, parsed on first use; ``spec.state`` holds the user's names."""

    spec: ModelSpec
    f: Points  # (P, n) -> (P, n)
    h: Points  # (P, n) -> (P, m)
    _prior_fn: Points | None = None  # unnormalised prior density (kind = "density")

    # -- the two parts of the spec ----------------------------------------------------
    @property
    def problem(self):
        """The filtering problem (solver.spec.ProblemSpec): what f, h, the noises and prior are."""
        return self.spec.problem

    @property
    def discretisation(self):
        """How it is discretised (solver.spec.DiscretisationSpec): dt, the domain ball, resolution.
        ``dt``, ``radius`` and ``center`` below read it."""
        return self.spec.discretisation

    # -- sizes and matrices ---------------------------------------------------------
    @property
    def n(self) -> int:
        return self.spec.n

    @property
    def m(self) -> int:
        return self.spec.m

    @cached_property
    def a(self) -> np.ndarray:
        """Diffusion a = G Q Gᵀ."""
        return self.spec.diffusion_matrix()

    @cached_property
    def basis_diffusion(self) -> np.ndarray:
        """The matrix ā of the basis's operator −½div(ā∇) (solver/offline/basis.py): a itself where it is
        positive definite; where it is only semi-definite, a plus its largest eigenvalue on its null
        space (diag(0, 1) ↦ I), so the Dirichlet eigenbasis resolves every direction and stays
        L²(B_R)-orthonormal.  On an ellipsoid (``[domain] shape`` = Σ): Σ, so the basis is that of the
        ball in the coordinates z of x = c + Lz."""
        if self.shape is not None:  # an ellipsoid: the basis resolves it as the ball resolves B_R
            return self.shape @ self.shape.T
        lam, vectors = np.linalg.eigh(self.a)
        scale = max(1.0, float(np.abs(self.a).max()))
        null = vectors[:, lam <= 1e-12 * scale]
        return self.a + float(lam.max()) * null @ null.T

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

    @cached_property
    def shape(self) -> np.ndarray | None:
        """L of the domain's shape Σ = LLᵀ (``[domain] shape``; lower triangular): the domain is the ball
        B_R mapped by x = c + Lz; None: the ball itself."""
        shape = self.spec.domain.shape
        if shape == "posterior":
            shape = self.steady_posterior_covariance()
        return None if shape is None else np.linalg.cholesky(np.asarray(shape, dtype=float))

    def steady_posterior_covariance(self) -> np.ndarray:
        """Σ of ``shape = "posterior"``: the stabilising solution of the Kalman–Bucy Riccati equation
        AΣ + ΣAᵀ + a − ΣHᵀR⁻¹HΣ = 0 (scipy), for f = Ax + b and h = Hx + h₀ (SymPy checks both)."""
        import scipy.linalg as sla

        why = POSTERIOR_NEEDS_LINEAR
        drift = self.affine_drift
        try:
            H, _ = affine_coefficients(self.observation, self.symbols, "observation")
        except SpecError:
            H = None
        if drift is None or H is None:
            which = "drift" if drift is None else "observation"
            raise SpecError("domain.shape", f"the {which} is not affine: {why}")
        try:
            sigma = sla.solve_continuous_are(drift[0].T, H.T, np.asarray(self.a, float),
                                             np.asarray(self.R, float))
        except (np.linalg.LinAlgError, ValueError) as exc:
            raise SpecError("domain.shape", f"the Riccati equation has no stabilising solution ({exc}): "
                                            f"{why}") from None
        sigma = 0.5 * (sigma + sigma.T)
        if not np.all(np.isfinite(sigma)) or np.linalg.eigvalsh(sigma).min() <= 0:
            raise SpecError("domain.shape", f"the steady-state covariance is not positive definite: {why}")
        return sigma

    @cached_property
    def shape_inverse(self) -> np.ndarray | None:
        return None if self.shape is None else np.linalg.inv(self.shape)

    def unshaped(self, offsets: np.ndarray) -> np.ndarray:
        """Offsets x − c (..., n) in the ball's coordinates z = L⁻¹(x − c) (themselves on a ball)."""
        return offsets if self.shape is None else offsets @ self.shape_inverse.T

    def shaped(self, offsets: np.ndarray) -> np.ndarray:
        """Offsets z (..., n) in the ball's coordinates as offsets x − c = Lz (:meth:`unshaped` undone)."""
        return offsets if self.shape is None else offsets @ self.shape.T

    @cached_property
    def half_widths(self) -> np.ndarray:
        """Half the sides of the box around the domain (n,): R, or R·√Σ_ii on an ellipsoid."""
        if self.shape is None:
            return np.full(self.n, float(self.radius))
        return float(self.radius) * np.linalg.norm(self.shape, axis=1)

    def ball_distance(self, offsets: np.ndarray) -> np.ndarray:
        """|L⁻¹(x − c)| of offsets x − c (P, n): below ``radius`` inside the domain."""
        return np.linalg.norm(self.unshaped(offsets), axis=-1)

    def translated(self, center: ArrayLike) -> "Model":
        """The same model on the ball moved to ``center`` (the numpy functions shared)."""
        domain = self.spec.domain.model_copy(update={"center": [float(c) for c in center]})
        spec = self.spec.model_copy(update={"domain": domain})
        return Model(spec=spec, f=self.f, h=self.h, _prior_fn=self._prior_fn)

    # -- symbolic forms (SymPy, on first use) ----------------------------------------------
    @cached_property
    def symbols(self) -> tuple["sp.Symbol", ...]:
        return state_symbols(self.n)

    @cached_property
    def _sympy_names(self) -> dict[str, Any]:
        names: dict[str, Any] = {name: number(float(v)) for name, v in self.spec.parameters.items()}
        names.update(dict(zip(self.spec.state, self.symbols, strict=True)))
        return names

    @cached_property
    def drift(self) -> tuple["sp.Expr", ...]:
        """f as exact SymPy expressions."""
        return tuple(parse_expression(e, self._sympy_names, f"drift[{i}]")
                     for i, e in enumerate(self.spec.drift))

    @cached_property
    def observation(self) -> tuple["sp.Expr", ...]:
        """h as exact SymPy expressions."""
        return tuple(parse_expression(e, self._sympy_names, f"observation[{i}]")
                     for i, e in enumerate(self.spec.observation))

    @cached_property
    def prior_expr(self) -> "sp.Expr | None":
        """The unnormalised prior density of kind "density" (None for the other kinds)."""
        if not isinstance(self.spec.initial, DensityPrior):
            return None
        return parse_expression(self.spec.initial.expression, self._sympy_names, "initial.expression")

    @cached_property
    def div_drift(self) -> "sp.Expr":
        import sympy as sp

        return sp.simplify(sum(sp.diff(fi, xi) for fi, xi in zip(self.drift, self.symbols, strict=True)))

    @cached_property
    def shift_directions(self) -> tuple[int, ...]:
        """The coordinates no drift component depends on (∂f_j/∂x_i ≡ 0 for every j, SymPy): along
        them the Fokker–Planck operator is translation-invariant (a random walk with trend, the
        position of constant-velocity tracking)."""
        import sympy as sp

        jacobian = self.jacobian_drift
        return tuple(i for i in range(self.n)
                     if all(sp.simplify(jacobian[j, i]) == 0 for j in range(self.n)))

    @cached_property
    def affine_drift(self) -> tuple[np.ndarray, np.ndarray] | None:
        """(A, b) when f(x) = Ax + b exactly (the Jacobian of f is constant, SymPy), else None."""
        try:
            return affine_coefficients(self.drift, self.symbols, "drift")
        except SpecError:
            return None

    @cached_property
    def jacobian_drift(self) -> "sp.Matrix":
        import sympy as sp

        return sp.Matrix(self.drift).jacobian(self.symbols)

    @cached_property
    def jacobian_observation(self) -> "sp.Matrix":
        import sympy as sp

        return sp.Matrix(self.observation).jacobian(self.symbols)

    @cached_property
    def potential(self) -> "sp.Expr":
        """½ hᵀR⁻¹h, the observation-independent potential of seed 002 (5.31)."""
        import sympy as sp

        h = sp.Matrix(self.observation)
        r_inv = sp.Matrix([[number(float(v)) for v in row] for row in self.R_inv])
        return sp.expand((h.T * r_inv * h)[0, 0] / 2)

    # -- numpy evaluators (points X of shape (P, n)) ----------------------------------
    def half_hRh(self, X: np.ndarray) -> np.ndarray:
        """½ hᵀR⁻¹h at points (P,)."""
        h = self.h(X)
        return 0.5 * np.einsum("pi,ij,pj->p", h, self.R_inv, h)

    @cached_property
    def div_f(self):
        """div f at points (from the symbolic derivative)."""
        return vectorize(self.div_drift, self.symbols)

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
            return log_normal(X, np.asarray(prior.mean), np.asarray(prior.cov))
        if isinstance(prior, MixturePrior):
            w = mixture_weights(prior.weights)
            logs = np.stack([np.log(wi) + log_normal(X, np.asarray(mu), np.asarray(c))
                             for wi, mu, c in zip(w, prior.means, prior.covs, strict=True) if wi > 0])
            top = logs.max(axis=0)
            return top + np.log(np.exp(logs - top).sum(axis=0))
        with np.errstate(divide="ignore"):
            return np.log(np.clip(self._prior_fn(X), 0.0, None))

    def prior_density(self, X: np.ndarray) -> np.ndarray:
        return np.exp(self.log_prior(X))

    def prior_moments(self) -> tuple[np.ndarray, np.ndarray] | None:
        """Mean and covariance of a gaussian/mixture prior; None for a density prior."""
        prior = self.spec.initial
        if isinstance(prior, GaussianPrior):
            return np.asarray(prior.mean, float), np.asarray(prior.cov, float)
        if isinstance(prior, MixturePrior):
            w = mixture_weights(prior.weights)
            mus = np.asarray(prior.means, float)
            covs = np.asarray(prior.covs, float)
            mean = w @ mus
            d = mus - mean
            cov = np.einsum("k,kij->ij", w, covs) + np.einsum("k,ki,kj->ij", w, d, d)
            return mean, cov
        return None


def compile_model(spec: ModelSpec) -> Model:
    """The :class:`Model` of ``spec``: its expressions parsed (safely) into numpy functions and checked
    finite on the domain ball (``ModelSpec.numeric``).  SymPy is not used here."""
    f, h, prior = spec.numeric()  # built once per spec (spec_from_dict already did)
    return Model(spec=spec, f=f, h=h, _prior_fn=prior)
