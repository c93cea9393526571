"""Exact solutions used as independent truth by the tests (each checked in test_oracles.py).

1. Cubic sensor, seed 003 Theorems 4.1–4.2: the 1-D Kolmogorov equation (seed 003 (4.3))

       u_t = ½u'' − f u' − (f' + ½h²) u,   f(x) = a x + b,   h(x) = h0 x³ + h1 x² + h2 x + h3,

   has the solution u = exp(c0x⁴ + c1x³ + c2x² + c3x + c4(t)) exactly when (derived with SymPy,
   see docs/seed-errata.md — the printed conditions have slips)

       branch "4.1":  c0 = −h0/4, c1 = −h1/3, c2 = (a − h2)/2, c3 = b − h3,  a² = −3h0, h1 = −ab,
                      c4' = −(a + b² + h2)/2
       branch "4.2":  c0 = +h0/4, c1 = +h1/3, c2 = (a + h2)/2, c3 = b + h3,  a² = +3h0, h1 = +ab,
                      c4' = −(a + b² − h2)/2

   (the two branches are h ↔ −h of each other).  In both, c0 = a²/12 ≥ 0: the solution GROWS
   like exp(a²x⁴/12); it is an exact solution on any ball B_R but not a density, so an FE test
   must impose its boundary values (or compare with a matching boundary condition).

2. Beneš transition density for p_t = ½p'' − (tanh(x) p)':
       p(x, t | x0) = (2πt)^(-1/2) cosh(x)/cosh(x0) e^(−t/2) exp(−(x − x0)²/(2t)).

3. Linear drift, quadratic ½h²: :func:`linear_kolmogorov` maps the same Kolmogorov form with
   f = Dx + d, h = Hx + h0 (a general) to :class:`solver.exact.riccati.GaussianKolmogorov`,
   whose Gaussian solutions decay at infinity (good for Dirichlet problems on a large ball).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from yauyau.solver.exact.riccati import GaussianKolmogorov


# -- 1. cubic sensor ------------------------------------------------------------------
@dataclass(frozen=True)
class CubicSolution:
    """u(x, t) = exp(c0x⁴ + c1x³ + c2x² + c3x + c4(0) + rate·t) for f = a x + b and h."""

    a: float
    b: float
    h: tuple[float, float, float, float]  # (h0, h1, h2, h3)
    c: tuple[float, float, float, float]  # (c0, c1, c2, c3)
    c4_0: float
    rate: float  # dc4/dt

    def f(self, x):
        return self.a * np.asarray(x, float) + self.b

    def df(self, x):
        return np.full_like(np.asarray(x, float), self.a)

    def h_of(self, x):
        return np.polyval(self.h, np.asarray(x, float))

    def potential(self, x):
        """The zeroth-order coefficient f' + ½h² of the Kolmogorov equation."""
        return self.a + 0.5 * self.h_of(x) ** 2

    def log_u(self, x, t):
        x = np.asarray(x, float)
        return np.polyval((*self.c, 0.0), x) + self.c4_0 + self.rate * np.asarray(t, float)

    def u(self, x, t):
        return np.exp(self.log_u(x, t))


def cubic_conditions(a, b, h0, h1, h2, h3, branch: str = "4.1") -> tuple[float, float]:
    """Residuals of the (corrected) algebraic conditions; both zero iff the solution exists."""
    s = 1.0 if branch == "4.1" else -1.0
    return a * a + s * 3.0 * h0, a * b + s * h1


def cubic_solution(a, b, h0, h1, h2, h3, branch: str = "4.1", c4_0: float = 0.0,
                   tol: float = 1e-12) -> CubicSolution:
    """The closed-form solution of seed 003 Theorem 4.1 (branch "4.1") or 4.2 ("4.2")."""
    if branch not in ("4.1", "4.2"):
        raise ValueError("branch must be '4.1' or '4.2'")
    res = cubic_conditions(a, b, h0, h1, h2, h3, branch)
    if max(abs(res[0]), abs(res[1])) > tol * max(1.0, a * a, abs(h0), abs(h1)):
        raise ValueError(f"parameters violate the conditions of Theorem {branch}: residuals {res}")
    s = 1.0 if branch == "4.1" else -1.0
    c = (-s * h0 / 4, -s * h1 / 3, (a - s * h2) / 2, b - s * h3)
    rate = -(a + b * b + s * h2) / 2
    return CubicSolution(float(a), float(b), (h0, h1, h2, h3), c, float(c4_0), rate)


def cubic_family(a, b, h2=0.0, h3=0.0, branch: str = "4.1", c4_0: float = 0.0) -> CubicSolution:
    """A member of the 4-parameter family: h0, h1 are fixed by the conditions (a ≠ 0)."""
    if a == 0:
        raise ValueError("a must be non-zero (a = 0 forces h0 = 0: no cubic term)")
    s = 1.0 if branch == "4.1" else -1.0
    return cubic_solution(a, b, -s * a * a / 3, -s * a * b, h2, h3, branch, c4_0)


# -- 2. Beneš -------------------------------------------------------------------------
def log_cosh(x):
    x = np.asarray(x, float)
    return np.logaddexp(x, -x) - np.log(2.0)


def benes_log_transition(x, t, x0):
    """log p(x, t | x0) for the Fokker–Planck equation p_t = ½p'' − (tanh(x) p)'."""
    x = np.asarray(x, float)
    return (-0.5 * np.log(2 * np.pi * t) + log_cosh(x) - log_cosh(x0) - 0.5 * t
            - (x - x0) ** 2 / (2 * t))


def benes_transition(x, t, x0):
    return np.exp(benes_log_transition(x, t, x0))


def benes_transition_mean(t, x0):
    """E[x_t | x_0] = x0 + t tanh(x0) (from the two shifted Gaussians of cosh)."""
    return x0 + t * np.tanh(x0)


# -- 3. linear drift, quadratic potential --------------------------------------------
def linear_kolmogorov(D, d, H, h0, a=None) -> GaussianKolmogorov:
    """u_t = ½Σa_ij∂i∂ju − f·∇u − (div f + ½|h|²)u with f = Dx + d, h = Hx + h0 (R = I)."""
    H = np.atleast_2d(np.asarray(H, float))
    h0 = np.atleast_1d(np.asarray(h0, float))
    return GaussianKolmogorov(D, d, Q=0.5 * H.T @ H, q=H.T @ h0, r=0.5 * h0 @ h0, a=a)
