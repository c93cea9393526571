"""The robust DMZ equation of the seeds, derived symbolically.

With σ the unnormalised conditional density (DMZ: dσ = Lσ dt + σ hᵀdy, a = I, R = I) and
K = Σ y_j h_j, the robust form u = e^{−K} σ solves, for each fixed path value y,

    u_t = e^{−K} (L − ½|h|²)(e^{K} u),    L u = ½Δu − div(f u).

Expanding the right-hand side gives seed 002 (5.17).  Seed 000 (2.4) prints the first-order term
with the opposite sign (docs/seed-errata.md); these tests pin both statements.
"""

import sympy as sp

x1, x2, y1 = sp.symbols("x1 x2 y1", real=True)
X = (x1, x2)
f = [sp.Function("f1")(*X), sp.Function("f2")(*X)]
h = sp.Function("h")(*X)
u = sp.Function("u")(*X)
K = y1 * h


def grad(g):
    return [sp.diff(g, xi) for xi in X]


def laplacian(g):
    return sum(sp.diff(g, xi, 2) for xi in X)


def dmz_robust_rhs():
    """e^{−K}(L − ½h²)(e^{K}u) with L the Fokker–Planck operator."""
    sigma = sp.exp(K) * u
    L_sigma = laplacian(sigma) / 2 - sum(sp.diff(fi * sigma, xi) for fi, xi in zip(f, X, strict=True))
    return sp.expand(sp.simplify(sp.exp(-K) * (L_sigma - h**2 * sigma / 2)))


def seed002_517():
    """Seed 002 (5.17)."""
    dK = grad(K)
    first = sum((-fi + dKi) * ui for fi, dKi, ui in zip(f, dK, grad(u), strict=True))
    zeroth = (-sum(sp.diff(fi, xi) for fi, xi in zip(f, X, strict=True)) - h**2 / 2 + laplacian(K) / 2
              - sum(fi * dKi for fi, dKi in zip(f, dK, strict=True)) + sum(d**2 for d in dK) / 2)
    return laplacian(u) / 2 + first + zeroth * u


def seed000_24(first_order_sign):
    """Seed 000 (2.4), m = 1; ``first_order_sign`` = −1 as printed, +1 corrected."""
    dh = grad(h)
    first = first_order_sign * sum((-fi + y1 * dhi) * ui for fi, dhi, ui in zip(f, dh, grad(u), strict=True))
    zeroth = -(sum(sp.diff(fi, xi) for fi, xi in zip(f, X, strict=True)) + h**2 / 2 - y1 * laplacian(h) / 2
               + y1 * sum(fj * dhj for fj, dhj in zip(f, dh, strict=True))
               - y1**2 * sum(d * d for d in dh) / 2)
    return laplacian(u) / 2 + first + zeroth * u


def test_seed002_517_is_the_robust_dmz_equation():
    assert sp.simplify(dmz_robust_rhs() - sp.expand(seed002_517())) == 0


def test_seed000_24_first_order_sign_is_a_misprint():
    assert sp.simplify(dmz_robust_rhs() - sp.expand(seed000_24(+1))) == 0
    printed = sp.simplify(dmz_robust_rhs() - sp.expand(seed000_24(-1)))
    assert printed != 0
    # the printed form is off by exactly 2(−f + y∇h)·∇u
    expected = 2 * sum((-fi + y1 * dhi) * ui for fi, dhi, ui in zip(f, grad(h), grad(u), strict=True))
    assert sp.simplify(printed - sp.expand(expected)) == 0
