"""The Yau filtering system of a model, found symbolically: conditions (C1)–(C3) and F.

A model is a Yau filtering system (Yau & Lai, 2003; Yau & Hu) when a = I, h is affine (C2), and the
drift is f = ∇φ + (affine) with ∇φ making the potential quadratic (C1), (C3).  :func:`yau_system`
checks them with SymPy and returns the pieces the Yau–Hu filter (yau_hu.py) integrates, or raises
SpecError naming the condition that fails.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import sympy as sp

from ..errors import SpecError
from ..expressions import affine_coefficients
from ..model import Model


@dataclass(frozen=True)
class YauSystem:
    """ℓ = Dx + d, F (SymPy), η = xᵀE x + eᵀx + e0 and e^{F} = Σ exp(log_c_k + k_kᵀx)."""

    D: np.ndarray
    d: np.ndarray
    F: sp.Expr
    E: np.ndarray
    e: np.ndarray
    e0: float
    exp_F_slopes: np.ndarray  # (T, n)
    exp_F_logc: np.ndarray  # (T,)


def _affine_part(expr: sp.Expr, symbols) -> sp.Expr:
    """The terms of ``expr`` that are polynomials of degree <= 1 in the state."""
    terms = sp.Add.make_args(sp.expand(expr))
    return sp.Add(*[t for t in terms
                    if t.is_polynomial(*symbols) and sp.Poly(t, *symbols).total_degree() <= 1])


def gradient_potential(g: list[sp.Expr], symbols) -> sp.Expr:
    """F with ∇F = g (g has a symmetric Jacobian), by successive integration."""
    F = sp.Integer(0)
    for i, xi in enumerate(symbols):
        rest = sp.simplify(g[i] - sp.diff(F, xi))
        part = sp.integrate(rest, xi)
        if part.has(sp.Integral):
            raise SpecError("drift", "cannot integrate the gradient part of the drift symbolically")
        F += part
    return sp.simplify(F)


def _quadratic(expr: sp.Expr, symbols, field: str):
    n = len(symbols)
    try:
        poly = sp.Poly(sp.expand(sp.simplify(expr)), *symbols)
    except sp.PolynomialError:
        poly = None
    if poly is None or poly.total_degree() > 2:
        raise SpecError(field, "η = |f|² + div f + |h|² is not a quadratic polynomial (condition C3)")
    E = np.zeros((n, n))
    e = np.zeros(n)
    for i in range(n):
        e[i] = float(poly.coeff_monomial(symbols[i]))
        for j in range(n):
            coeff = float(poly.coeff_monomial(symbols[i] * symbols[j]))
            E[i, j] = coeff if i == j else 0.5 * coeff
    return E, e, float(poly.coeff_monomial(1))


def exponential_sum(F: sp.Expr, symbols):
    """e^{F} = Σ_k c_k exp(s_kᵀx) (c_k > 0), or None."""
    total = sp.expand(sp.simplify(sp.exp(F).rewrite(sp.exp)).rewrite(sp.exp))
    slopes, logc = [], []
    for term in sp.Add.make_args(total):
        coeff, rest = term.as_independent(*symbols, as_Add=False)
        arg = sp.Integer(0)
        for factor in sp.Mul.make_args(rest):
            base, power = factor.as_base_exp()
            if base == sp.E or isinstance(factor, sp.exp):
                arg += factor.args[0] if isinstance(factor, sp.exp) else power
            elif factor != 1:
                return None
        arg = sp.expand(arg)
        if not arg.is_polynomial(*symbols) or (arg != 0 and sp.Poly(arg, *symbols).total_degree() > 1):
            return None
        const = arg.subs({s: 0 for s in symbols})
        if not (coeff.is_number and coeff.is_positive):
            return None
        slopes.append([float(arg.coeff(s)) for s in symbols])
        logc.append(float(sp.log(coeff) + const))
    return np.array(slopes, float).reshape(-1, len(symbols)), np.array(logc, float)


def yau_system(model: Model) -> YauSystem:
    """Check (C1)–(C3) for ``model`` (a = I) and return ℓ, F, η; SpecError names the field."""
    if not np.allclose(model.a, np.eye(model.n)):
        raise SpecError("diffusion", "the Yau–Hu filter needs a = I (orthogonal g, as in Yau & Lai (2003))")
    xs = model.symbols
    affine_coefficients(model.observation, xs, "observation")  # (C2)
    f = [sp.expand(fi) for fi in model.drift]
    ell = [_affine_part(fi, xs) for fi in f]
    g = [fi - li for fi, li in zip(f, ell, strict=False)]
    J = sp.Matrix(g).jacobian(xs)
    anti = sp.simplify((J - J.T) / 2)
    if any(entry.free_symbols & set(xs) for entry in anti):
        raise SpecError("drift", "∂f_j/∂x_i − ∂f_i/∂x_j is not constant: not affine + gradient (C1)")
    shift = list(anti * sp.Matrix(xs))
    ell = [li + si for li, si in zip(ell, shift, strict=False)]
    g = [sp.simplify(gi - si) for gi, si in zip(g, shift, strict=False)]
    D, d = affine_coefficients(ell, xs, "drift")
    F = gradient_potential(g, xs)
    # η is fixed by f and h (R whitened): |f|² + div f + hᵀR⁻¹h
    eta = sum(fi**2 for fi in f) + sum(sp.diff(fi, xi) for fi, xi in zip(f, xs, strict=True))
    eta += 2 * model.potential
    E, e, e0 = _quadratic(eta, xs, "drift")
    found = exponential_sum(F, xs)
    if found is None:
        raise SpecError("drift", f"e^F (F = {F}) is not a sum of exponentials of affine functions: "
                                 "no closed-form moments")
    slopes, logc = found
    # a numerically safe form of F for evaluation: log Σ c_k e^{s_kᵀx} (log cosh, not x − log(1 + tanh))
    F_safe = sp.log(sum(sp.exp(float(lc) + sum(float(sk) * xi for sk, xi in zip(row, xs, strict=False)))
                        for row, lc in zip(slopes, logc, strict=False)))
    return YauSystem(D, d, F_safe if len(logc) > 1 else F, E, e, e0, slopes, logc)
