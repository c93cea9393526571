"""The exact solutions are checked by substitution into their PDEs (SymPy) and numerically.

Also checks the seed formulas they come from: seed 000 (3.8)–(3.10), seed 001 (4.11)/(4.12)/
(4.14)–(4.16) and seed 003 Theorems 4.1–4.2 (misprints recorded in docs/seed-errata.md).
"""

import numpy as np
import pytest
import sympy as sp
from helpers.oracles import (
    benes_transition,
    benes_transition_mean,
    cubic_conditions,
    cubic_family,
    cubic_solution,
    linear_kolmogorov,
)
from scipy.linalg import expm
from yauyau.solver.errors import InputError, SpecError
from yauyau.solver.exact.riccati import GaussianKolmogorov, gaussian_to_terms, terms_to_gaussian

X1, X2, T = sp.symbols("x1 x2 t", real=True)
XV = sp.Matrix([X1, X2])


def _sym_matrix(name, symmetric=False):
    M = sp.Matrix(2, 2, lambda i, j: sp.Symbol(f"{name}{min(i, j) if symmetric else i}"
                                                f"{max(i, j) if symmetric else j}"))
    return M


def _sym_vector(name):
    return sp.Matrix([sp.Symbol(f"{name}0"), sp.Symbol(f"{name}1")])


def _operator(drift, zeroth, a=None):
    """u -> ½Σ a_ij ∂i∂j u − drift·∇u + zeroth·u in the variables XV (a = I by default)."""
    a = sp.eye(2) if a is None else a

    def apply(u):
        second = sum(a[i, j] * sp.diff(u, XV[i], XV[j]) for i in range(2) for j in range(2)) / 2
        return second - sum(drift[i] * sp.diff(u, XV[i]) for i in range(2)) + zeroth * u

    return apply


def _residual_with_rates(phi, dphi_dt, operator):
    """(∂u/∂t − operator(u))/u for u = e^φ, with ∂φ/∂t replaced by the claimed rates."""
    u = sp.exp(phi)
    return sp.expand(sp.simplify((dphi_dt * u - operator(u)) / u))


# -- Riccati ODEs (solver/exact/riccati.py) ---------------------------------------------
def test_riccati_odes_solve_the_kolmogorov_equation_symbolically():
    A, a, Q = _sym_matrix("A", True), _sym_matrix("a", True), _sym_matrix("Q", True)
    D, B, d, q = _sym_matrix("D"), _sym_vector("B"), _sym_vector("d"), _sym_vector("q")
    r, C = sp.symbols("r C")
    phi = -(XV.T * A * XV)[0] - (B.T * XV)[0] - C
    # the rates as coded in GaussianKolmogorov.rhs
    dA = Q - A * D - D.T * A - 2 * A * a * A
    dB = q - 2 * A * d - (D.T + 2 * A * a) * B
    dC = r + D.trace() + (a * A).trace() - (B.T * a * B)[0] / 2 - (d.T * B)[0]
    rate = -(XV.T * dA * XV)[0] - (dB.T * XV)[0] - dC
    f = D * XV + d
    pot = (XV.T * Q * XV)[0] + (q.T * XV)[0] + r
    assert _residual_with_rates(phi, rate, _operator(f, -(D.trace() + pot), a)) == 0


def test_seed000_theorem32_as_printed_solves_36():
    # seed 000 (3.6): ũ_t = ½Δũ − ℓ·∇ũ + q ũ with q = xᵀQx + pᵀx + r, ũ = exp(xᵀAx + Bᵀx + C)
    A, Q, D = _sym_matrix("A", True), _sym_matrix("Q", True), _sym_matrix("D")
    B, d, p = _sym_vector("B"), _sym_vector("d"), _sym_vector("p")
    r, C = sp.symbols("r C")
    phi = (XV.T * A * XV)[0] + (B.T * XV)[0] + C
    dA = 2 * A * A - (A * D + D.T * A) + Q  # (3.8)
    dBT = 2 * B.T * A - B.T * D - 2 * d.T * A + p.T  # (3.9)
    dC = A.trace() + (B.T * B)[0] / 2 - (d.T * B)[0] + r  # (3.10)
    rate = (XV.T * dA * XV)[0] + (dBT * XV)[0] + dC
    ell = D * XV + d
    q = (XV.T * Q * XV)[0] + (p.T * XV)[0] + r
    assert _residual_with_rates(phi, rate, _operator(ell, q)) == 0


def test_seed001_theorem42_solves_411_but_not_412_as_printed():
    A, Q, L = _sym_matrix("A", True), _sym_matrix("Q", True), _sym_matrix("L")
    B, ell0, qv = _sym_vector("B"), _sym_vector("l"), _sym_vector("q")
    q0, C = sp.symbols("q0 C")
    phi = (XV.T * A * XV)[0] + (B.T * XV)[0] + C
    dA = 2 * A * A - A * L - L.T * A - Q / 2  # (4.14)
    dBT = 2 * B.T * A - B.T * L - 2 * ell0.T * A - qv.T / 2  # (4.15)
    dC = A.trace() + (B.T * B)[0] / 2 - (ell0.T * B)[0] - q0 / 2 - L.trace()  # (4.16)
    rate = (XV.T * dA * XV)[0] + (dBT * XV)[0] + dC
    ell = L * XV + ell0
    quad = (XV.T * Q * XV)[0] + (qv.T * XV)[0] + q0  # (4.2): Σh² + Δφ + |∇φ|² + 2∇φ·ℓ
    # (4.11), its bracket written through (4.2)
    assert _residual_with_rates(phi, rate, _operator(ell, -(quad / 2 + L.trace()))) == 0
    # (4.12) as printed has +½Σh² ũ as its only zeroth-order term: not what (4.14)–(4.16) solve
    h = sp.Symbol("h")
    assert _residual_with_rates(phi, rate, _operator(ell, h**2 / 2)) != 0


def test_seed001_411_is_the_gauge_transform_of_48():
    # σ̃ = e^φ ũ with f = ℓ + ∇φ turns (4.8) into (4.11) (1-D, generic φ and h)
    x = sp.Symbol("x", real=True)
    phi, h, w = sp.Function("phi")(x), sp.Function("h")(x), sp.Function("w")(x)
    l1, l0 = sp.symbols("l1 l0")
    f = l1 * x + l0 + phi.diff(x)
    s = sp.exp(phi) * w
    lhs_48 = s.diff(x, 2) / 2 - f * s.diff(x) - (f.diff(x) + h**2 / 2) * s
    bracket = (phi.diff(x, 2) / 2 + phi.diff(x) ** 2 / 2 + phi.diff(x) * (l1 * x + l0) + l1 + h**2 / 2)
    rhs_411 = w.diff(x, 2) / 2 - (l1 * x + l0) * w.diff(x) - bracket * w
    assert sp.simplify(lhs_48 * sp.exp(-phi) - rhs_411) == 0


def test_gaussian_kolmogorov_is_fokker_planck_when_potential_vanishes():
    # Q = q = r = 0: the PDE is the FP equation of dx = (Dx + d)dt + dv, Cov dv = a dt, whose
    # Gaussian solution has m' = Dm + d, P' = DP + PDᵀ + a (closed form via matrix exponentials)
    D = np.array([[-0.7, 0.4], [-0.3, -0.2]])
    d = np.array([0.3, -0.5])
    a = np.array([[0.8, 0.2], [0.2, 0.4]])
    m0, P0 = np.array([1.0, -1.0]), np.array([[0.5, 0.1], [0.1, 0.3]])
    eq = GaussianKolmogorov(D, d, a=a)
    t = 0.9
    init = gaussian_to_terms(m0, P0, weight=2.5)
    sol = eq.solve(init.A, init.B, init.C, [0.0, t])
    mean, cov, log_mass = terms_to_gaussian(sol.A[-1], sol.B[-1], sol.C[-1])
    E = expm(D * t)
    big = expm(np.block([[D, np.eye(2)], [np.zeros((2, 2)), np.zeros((2, 2))]]) * t)
    m_true = E @ m0 + big[:2, 2:] @ d
    van = expm(np.block([[-D, a], [np.zeros((2, 2)), D.T]]) * t)  # Van Loan: ∫e^{Ds}ae^{Dᵀs}
    P_true = E @ P0 @ E.T + van[2:, 2:].T @ van[:2, 2:]
    np.testing.assert_allclose(mean, m_true, atol=1e-9)
    np.testing.assert_allclose(cov, P_true, atol=1e-9)
    assert log_mass == pytest.approx(np.log(2.5), abs=1e-9)


def test_gaussian_kolmogorov_scalar_closed_form():
    # u_t = ½u'' − ½x²u (D = 0, Q = ½): A' = ½ − 2A², stationary A = ½; A(t) = ½ tanh(t + atanh 2A0)
    eq = GaussianKolmogorov([[0.0]], Q=[[0.5]])
    A0 = 0.2
    t = np.linspace(0, 2, 5)
    sol = eq.solve([[A0]], [0.0], 0.0, t)
    np.testing.assert_allclose(sol.A[:, 0, 0], 0.5 * np.tanh(t + np.arctanh(2 * A0)), atol=1e-10)
    # C' = A: C = ½ log(cosh(t + k)/cosh k)
    k = np.arctanh(2 * A0)
    np.testing.assert_allclose(sol.C, 0.5 * np.log(np.cosh(t + k) / np.cosh(k)), atol=1e-10)


def test_flow_matches_finite_difference_pde_residual():
    # the exact step map, checked against the PDE by finite differences at random points
    eq = linear_kolmogorov([[-0.4]], [0.2], [[1.3]], [0.4], a=[[0.7]])
    init = gaussian_to_terms([0.5], [[0.6]])
    flow = eq.flow(2e-3)
    x, eps = np.linspace(-2, 2, 9)[:, None], 1e-4
    s0 = flow.step(init.A, init.B, init.C)
    s1 = flow.step(s0.A, s0.B, s0.C)
    s2 = flow.step(s1.A, s1.B, s1.C)
    u = lambda s, xx: eq.u(xx, s)  # noqa: E731
    ut = (u(s2, x) - u(s0, x)) / (2 * flow.dt)
    uxx = (u(s1, x + eps) - 2 * u(s1, x) + u(s1, x - eps)) / eps**2
    ux = (u(s1, x + eps) - u(s1, x - eps)) / (2 * eps)
    f = -0.4 * x[:, 0] + 0.2
    pot = -0.4 + 0.5 * (1.3 * x[:, 0] + 0.4) ** 2
    resid = ut - (0.35 * uxx - f * ux - pot * u(s1, x))
    assert np.max(np.abs(resid)) < 1e-4 * np.max(np.abs(ut))


def test_flow_agrees_with_ode_integration_for_several_components():
    rng = np.random.default_rng(4)
    D, Q = rng.normal(size=(2, 2)), np.array([[0.6, 0.1], [0.1, 0.3]])
    eq = GaussianKolmogorov(D, rng.normal(size=2), Q, rng.normal(size=2), 0.2, [[1.0, 0.3], [0.3, 0.6]])
    inits = [gaussian_to_terms(rng.normal(size=2), np.eye(2) * s) for s in (0.3, 1.0, 2.0)]
    flow = eq.flow(0.1)
    A, B, C = (np.stack([getattr(i, k) for i in inits]) for k in "ABC")
    for _ in range(5):
        A, B, C = flow.step(A, B, C).__dict__.values()
    for k, init in enumerate(inits):
        ref = eq.solve(init.A, init.B, init.C, [0.0, 0.5])
        np.testing.assert_allclose(A[k], ref.A[-1], atol=1e-10)
        np.testing.assert_allclose(B[k], ref.B[-1], atol=1e-9)
        assert C[k] == pytest.approx(ref.C[-1], abs=1e-9)


def test_bad_inputs_name_the_field():
    with pytest.raises(SpecError, match="^a:"):
        GaussianKolmogorov([[0.0]], a=[[np.nan]])
    with pytest.raises(InputError, match="^A:"):
        terms_to_gaussian([[-1.0]], [0.0], 0.0)
    # Q < 0 strongly enough makes A blow up (det X -> 0) within the step
    eq = GaussianKolmogorov([[0.0]], Q=[[-50.0]])
    with pytest.raises(InputError, match="^dt:"):
        eq.flow(1.0).step([[0.5]], [0.0], 0.0)


# -- seed 003, cubic sensor ------------------------------------------------------------
def _cubic_residual(a, b, hs, cs, rate):
    x, t = sp.symbols("x t", real=True)
    h = sum(hk * x ** (3 - k) for k, hk in enumerate(hs))
    phi = sum(ck * x ** (4 - k) for k, ck in enumerate(cs)) + rate * t
    u = sp.exp(phi)
    res = sp.diff(u, t) - (sp.diff(u, x, 2) / 2 - (a * x + b) * sp.diff(u, x) - (a + h**2 / 2) * u)
    return sp.expand(sp.simplify(res / u))


@pytest.mark.parametrize("branch", ["4.1", "4.2"])
def test_cubic_family_solves_43_symbolically(branch):
    a, b, h2, h3 = sp.symbols("a b h2 h3", real=True)
    s = 1 if branch == "4.1" else -1
    h0, h1 = -s * a**2 / 3, -s * a * b  # the corrected conditions
    cs = (-s * h0 / 4, -s * h1 / 3, (a - s * h2) / 2, b - s * h3)
    rate = -(a + b**2 + s * h2) / 2
    assert _cubic_residual(a, b, (h0, h1, h2, h3), cs, rate) == 0
    # and the code's numbers are those coefficients
    sol = cubic_family(1.5, -0.4, 0.3, 0.7, branch=branch)
    num = {a: 1.5, b: -0.4, h2: 0.3, h3: 0.7}
    np.testing.assert_allclose(sol.c, [float(c.subs(num)) for c in cs], rtol=1e-14)
    np.testing.assert_allclose(sol.h[:2], [float(h0.subs(num)), float(h1.subs(num))], rtol=1e-14)
    assert sol.rate == pytest.approx(float(rate.subs(num)), rel=1e-14)


def test_cubic_printed_conditions_are_wrong():
    # printed (4.4)/(4.5) with h1 = 0 reduce to a² = −3h0 (no solution when h0 > 0, as the
    # theorem assumes) and, printed, (4.5) to 2b h2 − 2h2h3 − ab = 0; take a point satisfying
    # the printed (4.5) but not ab + h1 = 0: the printed c's then leave a non-zero residual
    a, b, h2, h3 = 3, 1, 2, 0  # printed (4.5): 2·1·2 − 0 − 0 − 3·1 = 1 ≠ 0 -> adjust h3
    h3 = sp.Rational(1, 4)  # printed (4.5): 4 − 1 − 3 = 0 with h1 = 0
    h0, h1 = -sp.Integer(a) ** 2 / 3, 0
    printed_45 = sp.Rational(h2) / h0 * (b * h0 - h0 * h3) - h1 - b * (a - h2) - h2 * h3
    assert printed_45 == 0
    cs = (-h0 / 4, -sp.Integer(h1) / 3, sp.Rational(a - h2, 2), b - h3)
    rate = -(a + b**2 + h2) / sp.Integer(2)
    assert _cubic_residual(a, b, (h0, h1, h2, h3), cs, rate) != 0
    assert cubic_conditions(a, b, float(h0), h1, h2, float(h3))[1] != 0
    # Theorem 4.1 assumes h0 > 0, but its (corrected) first condition a² = −3h0 then has no real a
    with pytest.raises(ValueError):
        cubic_solution(1.0, 0.0, 0.5, 0.0, 0.0, 0.0, "4.1")


def test_cubic_solution_numerically_by_finite_differences():
    sol = cubic_family(-1.2, 0.5, 0.4, -0.3, branch="4.2", c4_0=-2.0)
    x, t, e = np.linspace(-1.5, 1.5, 13), 0.4, 1e-4
    ut = (sol.u(x, t + e) - sol.u(x, t - e)) / (2 * e)
    ux = (sol.u(x + e, t) - sol.u(x - e, t)) / (2 * e)
    uxx = (sol.u(x + e, t) - 2 * sol.u(x, t) + sol.u(x - e, t)) / e**2
    resid = ut - (0.5 * uxx - sol.f(x) * ux - sol.potential(x) * sol.u(x, t))
    assert np.max(np.abs(resid)) < 1e-5 * np.max(np.abs(sol.u(x, t)))


# -- Beneš transition density -----------------------------------------------------------
def test_benes_transition_solves_fokker_planck_symbolically():
    x, x0 = sp.symbols("x x0", real=True)
    t = sp.Symbol("t", positive=True)
    p = sp.cosh(x) / sp.cosh(x0) * sp.exp(-t / 2) * sp.exp(-(x - x0) ** 2 / (2 * t)) / sp.sqrt(2 * sp.pi * t)
    res = sp.diff(p, t) - (sp.diff(p, x, 2) / 2 - sp.diff(sp.tanh(x) * p, x))
    assert sp.simplify((res / p).rewrite(sp.exp)) == 0


def test_benes_transition_is_a_density_with_the_closed_form_mean():
    x = np.linspace(-30, 30, 24001)
    dx = x[1] - x[0]
    for x0, t in ((0.3, 0.5), (-1.2, 2.0), (2.0, 0.1)):
        p = benes_transition(x, t, x0)
        assert np.sum(p) * dx == pytest.approx(1.0, abs=1e-10)
        assert np.sum(x * p) * dx == pytest.approx(benes_transition_mean(t, x0), abs=1e-9)
    assert np.all(np.isfinite(benes_transition(np.array([-800.0, 800.0]), 1.0, 700.0)))
