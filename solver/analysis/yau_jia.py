"""The class of seed 001 §4 (Yau & Jia, 2005), found symbolically: (4.1) and (4.2) for a general a.

Seed 001 takes a = I.  For dx = f dt + G dv, dy = h dt + dw with a = GQGᵀ (constant, possibly only
positive semi-definite: noise on velocities only) and E dw dwᵀ = R dt, write

    f = Lx + ℓ + a∇φ                                                       (4.1), a∇φ for ∇φ

and substitute σ = e^{φ} v in the observation-free Kolmogorov equation (4.8)
∂σ/∂t = ½Σa_ij∂i∂jσ − div(fσ) − ½hᵀR⁻¹hσ.  The terms (a∇φ)·∇v cancel and

    ∂v/∂t = ½Σa_ij∂i∂jv − (Lx + ℓ)·∇v − [tr L + ½V] v,
    V = hᵀR⁻¹h + tr(a∇²φ) + ∇φᵀa∇φ + 2(Lx + ℓ)·∇φ                          (4.2) for general a

(a = R = I: V = Σh² + Δφ + |∇φ|² + 2∇φ·(f − ∇φ), the seed's (4.2)).  When V = xᵀQx + qᵀx + q0 the
equation maps exp(xᵀAx + Bᵀx + C) to itself with (derived here, checked by SymPy in
tests/solver/exact/test_yau_jia.py)

    A' = 2AaA − AL − LᵀA − ½Q,   B' = 2AaB − LᵀB − 2Aℓ − ½q,
    C' = tr(aA) + ½BᵀaB − ℓᵀB − ½q0 − tr L                                   ((4.14)–(4.16) at a = I)

— equivalently, for a component v = w·N(m, P): Ṗ = LP + PLᵀ + a − PQP, ṁ = Lm + ℓ − P(Qm + ½q),
d log w/dt = −½(tr QP + mᵀQm + qᵀm + q0): a Kalman–Bucy predictor with the potential ½V, which
is why a semi-definite a is no obstacle.

:func:`yau_jia_structure` finds L, ℓ, φ, Q, q, q0 (and V without hᵀR⁻¹h, used by a step without an
observation) or raises SpecError naming the condition that fails.  The affine part Lx + ℓ is the
degree ≤ 1 part of f; the rest must be a∇φ (a⁻¹ times it curl-free; for a singular a it must lie in
the range of a, and φ is taken from its pseudo-inverse).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import sympy as sp

from ..errors import SpecError
from ..exact.yau_system import gradient_potential  # φ with ∇φ = w, by successive integration
from ..model import Model
from .budget import expand
from .operators import exact_matrix, is_zero, observation_energy, show


@dataclass(frozen=True)
class YauJiaStructure:
    """f = Lx + ℓ + a∇φ and V = xᵀQx + qᵀx + q0 (``V_predict``: the same without hᵀR⁻¹h, or None
    when that part alone is not quadratic)."""

    L: np.ndarray
    ell: np.ndarray
    phi: sp.Expr
    Q: np.ndarray
    q: np.ndarray
    q0: float
    V: sp.Expr
    V_predict: tuple[np.ndarray, np.ndarray, float] | None

    def describe(self, model: Model) -> str:
        return (f"L = {np.array2string(self.L, precision=4)}, l = {np.array2string(self.ell, precision=4)}, "
                f"phi = {show(self.phi, model)}, V = {show(self.V, model)}")


def affine_part(expr: sp.Expr, symbols) -> sp.Expr:
    """The terms of ``expr`` that are polynomials of degree <= 1 in the state."""
    terms = sp.Add.make_args(expand(expr))
    return sp.Add(*[t for t in terms
                    if t.is_polynomial(*symbols) and sp.Poly(t, *symbols).total_degree() <= 1])


def _affine_coefficients(exprs, symbols) -> tuple[np.ndarray, np.ndarray]:
    n = len(symbols)
    L = np.array([[float(sp.diff(e, s)) for s in symbols] for e in exprs]).reshape(len(exprs), n)
    ell = np.array([float(e.subs({s: 0 for s in symbols})) for e in exprs])
    return L, ell


def quadratic_coefficients(expr: sp.Expr, symbols) -> tuple[np.ndarray, np.ndarray, float] | None:
    """(Q, q, q0) with expr = xᵀQx + qᵀx + q0 (Q symmetric), or None if expr is not such a polynomial
    (decided by derivatives: sqrt(1 + x²)² passes, as it should)."""
    n = len(symbols)
    e = expand(expr)
    for i in range(n):
        for j in range(i, n):
            for k in range(j, n):
                if not is_zero(sp.diff(e, symbols[i], symbols[j], symbols[k]), symbols):
                    return None
    at0 = {s: 0 for s in symbols}
    try:
        Q = np.array([[float(sp.diff(e, si, sj).subs(at0)) / 2 for sj in symbols] for si in symbols])
        q = np.array([float(sp.diff(e, s).subs(at0)) for s in symbols])
        q0 = float(e.subs(at0))
    except (TypeError, ValueError):
        return None
    if not (np.all(np.isfinite(Q)) and np.all(np.isfinite(q)) and np.isfinite(q0)):
        return None
    return Q, q, q0


def yau_jia_structure(model: Model) -> YauJiaStructure:
    """Check (4.1) and (4.2) for ``model`` (general constant a) and return their pieces; SpecError
    names the field (drift / observation) and the condition that fails."""
    xs, n = model.symbols, model.n
    f = [expand(fi) for fi in model.drift]
    affine = [affine_part(fi, xs) for fi in f]
    g = [expand(fi - ai) for fi, ai in zip(f, affine, strict=True)]
    L, ell = _affine_coefficients(affine, xs)
    a = exact_matrix(model.a)
    if all(gi == 0 or is_zero(gi, xs) for gi in g):
        phi = sp.Integer(0)
    else:
        if a.det() != 0:
            w = list(a.inv() * sp.Matrix(g))
        else:
            null = a.nullspace()
            for v in null:
                if not is_zero(expand((v.T * sp.Matrix(g))[0, 0]), xs):
                    raise SpecError("drift", "(4.1) fails: the non-affine part of f is not in the range of "
                                             "the diffusion a (it moves a coordinate that has no noise)")
            w = list(a.pinv() * sp.Matrix(g))
        J = sp.Matrix(w).jacobian(xs)
        for i in range(n):
            for j in range(i + 1, n):
                if not is_zero(expand(J[i, j] - J[j, i]), xs):
                    raise SpecError("drift", "(4.1) fails: f is not affine plus a times a gradient "
                                             f"(d w_{i}/dx_{j} != d w_{j}/dx_{i} for w = a^-1 (f - affine))")
        phi = gradient_potential(w, xs)
    grad = sp.Matrix([sp.diff(phi, s) for s in xs])
    hess = sp.hessian(phi, xs) if phi != 0 else sp.zeros(n, n)
    drift_affine = sp.Matrix(affine)
    gauge = (a * hess).trace() + (grad.T * a * grad)[0, 0] + 2 * (drift_affine.T * grad)[0, 0]
    energy = observation_energy(model)
    V = expand(energy + gauge)
    found = quadratic_coefficients(V, xs)
    if found is None:
        raise SpecError("observation", "(4.2) fails: V = h^T R^-1 h + tr(a D^2 phi) + grad(phi)^T a "
                                       "grad(phi) "
                                       "+ 2 (Lx + l).grad(phi) is not a quadratic polynomial "
                                       f"(V = {show(V, model)})")
    Q, q, q0 = found
    return YauJiaStructure(L=L, ell=ell, phi=phi, Q=Q, q=q, q0=q0, V=V,
                           V_predict=quadratic_coefficients(expand(gauge), xs))
