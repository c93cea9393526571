"""Yau–Hu filter: seed 000 Theorem 3.1 checked symbolically, then the filter against the exact
Beneš filter and the Kalman–Bucy filter."""

import numpy as np
import pytest
import sympy as sp
from yauyau.solver.errors import InputError, SpecError
from yauyau.solver.exact.kalman_bucy import KalmanBucyFilter
from yauyau.solver.exact.yau_hu import YauHuFilter, yau_system
from yauyau.solver.filtering import Filter
from yauyau.solver.model import compile_model
from yauyau.solver.simulate import simulate
from yauyau.solver.spec import load_spec, spec_from_dict

t, z, xi, x = sp.symbols("t z xi x", real=True)

LINEAR_2D = {"name": "lin", "state": ["x", "y"], "drift": ["-0.5*x + 0.4*y + 0.1", "-0.4*x - 0.3*y"],
             "observation": ["x + 0.5*y - 0.2", "y"], "observation_noise": [[0.5, 0.1], [0.1, 0.3]],
             "initial": {"kind": "gaussian", "mean": [0.5, -0.3], "cov": [[0.8, 0.1], [0.1, 0.5]]},
             "domain": {"radius": 8.0}, "discretization": {"dt": 0.05, "basis": 8}}


def _theorem31_residual(F, ell, h, eta_coeffs, half_b_term=True):
    """Residual of the robust DMZ e^{−yh}L0 e^{yh} for u built from (3.2) with (3.3)–(3.5)."""
    W, y = sp.Function("W"), sp.Function("y")(t)
    a, b, c = (sp.Function(s)(t) for s in "abc")
    e2, e1, e0 = eta_coeffs
    f = ell + sp.diff(F, x)
    u = sp.exp(-c - a * (z - b) + F.subs(x, z)) * W(t, z - b)
    sigma = sp.exp(y * h.subs(x, z)) * u
    fz = f.subs(x, z)
    L0 = (sp.diff(sigma, z, 2) / 2 - fz * sp.diff(sigma, z) - sp.diff(fz, z) * sigma
          - h.subs(x, z) ** 2 / 2 * sigma)
    res = (sp.diff(u, t) - sp.exp(-y * h.subs(x, z)) * L0).doit().subs(z, xi + b).doit()
    q = (ell**2 - sp.diff(ell, x) - (e2 * x**2 + e1 * x + e0)) / 2  # (3.1)
    Wt = sp.diff(W(t, xi), xi, 2) / 2 - ell.subs(x, xi) * sp.diff(W(t, xi), xi) + q.subs(x, xi) * W(t, xi)
    res = res.subs(sp.Derivative(W(t, xi), t), Wt)
    D, d = sp.Poly(ell, x).coeff_monomial(x), sp.Poly(ell, x).coeff_monomial(1)
    C = sp.Poly(h, x).coeff_monomial(x)
    bp = a + D * b - C * y  # (3.3)
    ap = e2 * b - D * bp  # (3.4), n = 1: ½(η11 + η11) = η11
    cp = -bp**2 / 2 + a * bp - d * bp + e2 * b**2 / 2 + (e1 / 2 if half_b_term else e1) * b  # (3.5)
    res = res.subs(sp.Derivative(b, t), bp).subs({sp.Derivative(a, t): ap, sp.Derivative(c, t): cp})
    return sp.simplify((res / sp.exp(-c - a * xi + F.subs(x, xi + b))).rewrite(sp.exp))


@pytest.mark.slow
def test_theorem31_linear_and_benes_symbolically():
    d1, d0, c1, c0 = sp.symbols("d1 d0 c1 c0", real=True)
    ell, h = d1 * x + d0, c1 * x + c0
    P = sp.Poly(sp.expand(ell**2 + d1 + h**2), x)
    eta = (P.coeff_monomial(x**2), P.coeff_monomial(x), P.coeff_monomial(1))
    assert _theorem31_residual(sp.Integer(0), ell, h, eta) == 0
    # Beneš F = log cosh x, ℓ = 0: η = 1 + h²
    assert _theorem31_residual(sp.log(sp.cosh(x)), sp.Integer(0), h, (c1**2, 2 * c1 * c0, 1 + c0**2)) == 0


@pytest.mark.slow
def test_example33_c_equation_misprint():
    # seed 000 Example 3.3: ℓ = x + 1, h = x + 1, η = 2x² + x + 9/4 (η1 = 1); the printed c' has
    # "+ b(t)" where (3.5) gives ½η1 b = ½b.  On a model with η1 ≠ 0 (same ℓ, h, F = −x/4) the
    # (3.5) coefficient ½η1 solves the robust DMZ and the example's η1 does not
    ell, h = x + 1, x + 1
    F = sp.Rational(-1, 4) * x
    f = ell + sp.diff(F, x)
    P = sp.Poly(sp.expand(f**2 + sp.diff(f, x) + h**2), x)
    eta = (P.coeff_monomial(x**2), P.coeff_monomial(x), P.coeff_monomial(1))
    assert eta[1] != 0
    assert _theorem31_residual(F, ell, h, eta, half_b_term=True) == 0
    assert _theorem31_residual(F, ell, h, eta, half_b_term=False) != 0
    # and Example 3.3's η: with F' = g'/g − 3/2, g' = e^{−(x−½)²}, f² + f' + h² = 2x² + x + 9/4
    g = sp.Function("g")(x)
    w = g.diff(x) / g
    f33 = x - sp.Rational(1, 2) + w
    expr = (f33**2 + f33.diff(x) + h**2).subs(g.diff(x, 2), -2 * (x - sp.Rational(1, 2)) * g.diff(x))
    assert sp.simplify(expr - (2 * x**2 + x + sp.Rational(9, 4))) == 0


def test_benes_posterior_formula_symbolically():
    # σ = cosh(x)·exp(−(x − m)²/(2P) + ζ) solves σ_t = ½σ'' − (tanh σ)' − ½x²σ + xẏσ when
    # m' = P(ẏ − m), P' = 1 − P²: the Kalman–Bucy filter of dx = dw, dy = x dt + dw
    m, P, zeta = (sp.Function(s)(t) for s in ("m", "P", "zeta"))
    yd = sp.Symbol("ydot")
    sigma = sp.cosh(x) * sp.exp(-(x - m) ** 2 / (2 * P) + zeta)
    res = sp.diff(sigma, t) - (sp.diff(sigma, x, 2) / 2 - sp.diff(sp.tanh(x) * sigma, x)
                               - x**2 / 2 * sigma + x * yd * sigma)
    res = sp.simplify(res.subs({sp.Derivative(m, t): P * (yd - m), sp.Derivative(P, t): 1 - P**2}) / sigma)
    assert sp.simplify(sp.diff(res.rewrite(sp.exp), x)) == 0  # only ζ' is left: a function of t


def _benes_exact(model, increments, m0=0.0, P0=1.0):
    """Exact Beneš filter: posterior ∝ cosh(x) N(m, P), (m, P) by Kalman–Bucy for dx = dw, h = x."""
    spec = model.spec.model_dump()
    spec.update(drift=["0"], initial={"kind": "gaussian", "mean": [m0], "cov": [[P0]]})
    kb = KalmanBucyFilter(compile_model(spec_from_dict(spec)))
    _, ests = kb.run(kb.initial_state(), increments)
    m = np.array([e.mean[0] for e in ests])
    P = np.array([e.cov[0, 0] for e in ests])
    mean = m + P * np.tanh(m)
    var = P + P**2 / np.cosh(m) ** 2
    return mean, var


def test_benes_model_matches_exact_benes_filter():
    model = compile_model(load_spec("examples/benes.toml"))  # prior cosh(x)N(0, 1)
    yh = YauHuFilter(model, n_components=4)
    assert isinstance(yh, Filter) and yh.method == "yau-hu"
    state = yh.initial_state()
    assert state.fit_error < 1e-4
    sim = simulate(model, 200, np.random.default_rng(5))
    state, ests = yh.run(state, sim.increments)
    mean, var = _benes_exact(model, sim.increments)
    np.testing.assert_allclose([e.mean[0] for e in ests], mean, atol=2e-4)
    np.testing.assert_allclose([e.cov[0, 0] for e in ests], var, atol=2e-4)
    x = np.linspace(-15, 15, 6001)[:, None]
    assert np.sum(yh.density(state, x)) * (x[1, 0] - x[0, 0]) == pytest.approx(1.0, abs=1e-8)


def test_linear_model_equals_kalman_bucy_including_loglik_and_missing_rows():
    model = compile_model(spec_from_dict(LINEAR_2D))
    incs = simulate(model, 60, np.random.default_rng(2)).increments
    incs[10:14] = np.nan
    yh, kb = YauHuFilter(model), KalmanBucyFilter(model)
    s1, e1 = yh.run(yh.initial_state(), incs)
    s2, e2 = kb.run(kb.initial_state(), incs)
    np.testing.assert_allclose([e.mean for e in e1], [e.mean for e in e2], atol=1e-9)
    np.testing.assert_allclose([e.cov for e in e1], [e.cov for e in e2], atol=1e-9)
    assert s1.loglik == pytest.approx(s2.loglik, abs=1e-8)
    again = yh.state_from_dict(s1.to_dict())
    assert yh.estimate(again).mean == pytest.approx(e1[-1].mean)


@pytest.mark.slow
def test_conditions_are_checked_and_name_the_field():
    base = {"name": "bad", "state": ["x"], "drift": ["tanh(x)"], "observation": ["x"],
            "initial": {"kind": "gaussian", "mean": [0.0], "cov": [[1.0]]},
            "domain": {"radius": 5.0}, "discretization": {"dt": 0.1, "basis": 8}}
    with pytest.raises(SpecError, match="^observation"):
        yau_system(compile_model(spec_from_dict({**base, "observation": ["x**3"]})))
    with pytest.raises(SpecError, match="^drift"):  # η = sin² + cos + x² is not quadratic (C3)
        yau_system(compile_model(spec_from_dict({**base, "drift": ["sin(x)"]})))
    with pytest.raises(SpecError, match="^drift"):  # rotation with a non-constant curl (C1)
        yau_system(compile_model(spec_from_dict({**base, "state": ["x", "y"], "drift": ["x*y", "0"],
                                                 "observation": ["x"], "initial": {
                                                     "kind": "gaussian", "mean": [0, 0],
                                                     "cov": [[1, 0], [0, 1]]}})))
    with pytest.raises(SpecError, match="^diffusion"):
        yau_system(compile_model(spec_from_dict({**base, "diffusion": [[2.0]]})))
    with pytest.raises(SpecError, match="^n_components"):
        YauHuFilter(compile_model(spec_from_dict(base)), n_components=0)
    yh = YauHuFilter(compile_model(spec_from_dict(base)))
    with pytest.raises(InputError):
        yh.state_from_dict({"A": [[[1.0]]], "B": [[0.0]], "C": [np.inf]})
    with pytest.raises(InputError):
        yh.run(yh.initial_state(), [[np.inf]])


def test_benes_missing_rows_and_chunks_match_the_exact_benes_filter():
    # the chunked recursion (Riccati path, affine B, cumulative C renormalised per chunk) against
    # the closed-form Beneš posterior, with a gap of missing rows and odd chunk boundaries
    model = compile_model(load_spec("examples/benes.toml"))
    yh = YauHuFilter(model, n_components=4)
    incs = simulate(model, 150, np.random.default_rng(9)).increments
    incs[40:52] = np.nan
    state, ests = yh.initial_state(), []
    for piece in (incs[:1], incs[1:45], incs[45:149], incs[149:]):
        state, part = yh.run(state, piece)
        ests += part
    mean, var = _benes_exact(model, incs)
    np.testing.assert_allclose([e.mean[0] for e in ests], mean, atol=2e-4)
    np.testing.assert_allclose([e.cov[0, 0] for e in ests], var, atol=2e-4)
    assert all(e.loglik_increment == 0.0 for e in ests[40:52])
    # log-likelihood: σ = cosh(x) e^{−t/2} ρ with ρ the DMZ solution of dx = dw, h = x (Kalman–Bucy;
    # also on missing rows, where ρ_t = ½ρ''), and ∫cosh·N(m, P) = e^{P/2} cosh m, so
    # log Z(t) = log Z_KB(t) + P/2 + log cosh m − (½ + log cosh 0) − t/2 (prior mass e^{1/2})
    spec = model.spec.model_dump()
    spec.update(drift=["0"], initial={"kind": "gaussian", "mean": [0.0], "cov": [[1.0]]})
    kb = KalmanBucyFilter(compile_model(spec_from_dict(spec)))
    kb_state, kb_ests = kb.run(kb.initial_state(), incs)
    m, P = kb_ests[-1].mean[0], kb_ests[-1].cov[0, 0]
    log_cosh_mass = lambda mu, p: 0.5 * p + np.log(np.cosh(mu))  # noqa: E731
    expected = kb_state.loglik + log_cosh_mass(m, P) - log_cosh_mass(0.0, 1.0) - 0.5 * kb_state.t
    assert state.loglik == pytest.approx(expected, abs=1e-6)


def _in_pieces(filt, increments, sizes):
    """run_arrays over consecutive chunks of the given sizes (the rest in one chunk)."""
    state, results, pos = filt.initial_state(), [], 0
    for size in [*sizes, len(increments)]:
        if pos >= len(increments):
            break
        state, part = filt.run_arrays(state, increments[pos:pos + size])
        results.append(part)
        pos += size
    cat = {k: np.concatenate([getattr(r, k) for r in results]) for k in ("mean", "cov", "loglik")}
    return state, cat


@pytest.mark.slow
def test_benes_past_the_settled_riccati_path_in_any_chunking():
    # 1100 observed steps at dt = 0.01 (the cached schedule settles after ~850): one chunk, one-row
    # chunks (the scalar path) and odd chunks agree to rounding and with the closed-form posterior
    model = compile_model(load_spec("examples/benes.toml"))
    incs = simulate(model, 1100, np.random.default_rng(4)).increments
    mean, var = _benes_exact(model, incs)
    states = []
    for sizes in ([], [1] * 40 + [7, 900] + [1] * 30, [333, 1, 1, 500, 2]):
        yh = YauHuFilter(model, n_components=4)  # a fresh cache each time
        state, out = _in_pieces(yh, incs, sizes)
        np.testing.assert_allclose(out["mean"][:, 0], mean, atol=2e-4)
        np.testing.assert_allclose(out["cov"][:, 0, 0], var, atol=2e-4)
        states.append((state, out))
    (s0, first), rest = states[0], states[1:]
    for state, out in rest:
        for key in ("mean", "cov", "loglik"):
            np.testing.assert_allclose(out[key], first[key], rtol=0, atol=1e-11)
        np.testing.assert_allclose(state.C, s0.C, rtol=0, atol=1e-11)
    # normaliser: log Z = log Z_KB + P/2 + log cosh m − ½ − t/2 (see the missing-rows test)
    spec = model.spec.model_dump()
    spec.update(drift=["0"], initial={"kind": "gaussian", "mean": [0.0], "cov": [[1.0]]})
    kb = KalmanBucyFilter(compile_model(spec_from_dict(spec)))
    kb_state, kb_out = kb.run_arrays(kb.initial_state(), incs)
    m, P = kb_out.mean[-1, 0], kb_out.cov[-1, 0, 0]
    expected = kb_state.loglik + 0.5 * P + np.log(np.cosh(m)) - 0.5 - 0.5 * kb_state.t
    assert s0.loglik == pytest.approx(expected, abs=1e-6)


def test_mixture_prior_is_the_gaussian_sum_of_kalman_bucy_filters():
    # F = 0 and a two-component prior: each component is a Kalman–Bucy filter and the posterior
    # weights are the prior weights times the components' likelihoods (exact Gaussian sum)
    spec = load_spec("examples/ou.toml").model_dump(mode="json")
    weights, means, covs = [0.3, 0.7], [-1.0, 2.0], [0.4, 0.9]
    spec["initial"] = {"kind": "mixture", "weights": weights, "means": [[m] for m in means],
                       "covs": [[[c]] for c in covs]}
    model = compile_model(spec_from_dict(spec))
    incs = simulate(model, 1500, np.random.default_rng(8)).increments  # past the settling (~1350)
    yh = YauHuFilter(model)
    state, out = _in_pieces(yh, incs, [1] * 25 + [400, 1, 1, 900] + [1] * 20)
    assert state.A.shape[0] == 2
    parts = []
    for m0, P0 in zip(means, covs, strict=True):
        spec["initial"] = {"kind": "gaussian", "mean": [m0], "cov": [[P0]]}
        kb = KalmanBucyFilter(compile_model(spec_from_dict(spec)))
        parts.append(kb.run_arrays(kb.initial_state(), incs)[1])
    logw = np.log(weights)[:, None] + np.stack([p.loglik for p in parts])  # (2, K)
    w = np.exp(logw - logw.max(0))
    w /= w.sum(0)
    m = np.stack([p.mean[:, 0] for p in parts])
    P = np.stack([p.cov[:, 0, 0] for p in parts])
    mean = (w * m).sum(0)
    np.testing.assert_allclose(out["mean"][:, 0], mean, atol=1e-9)
    np.testing.assert_allclose(out["cov"][:, 0, 0], (w * (P + (m - mean) ** 2)).sum(0), atol=1e-9)
    top = logw.max(0)
    np.testing.assert_allclose(out["loglik"], top + np.log(np.exp(logw - top).sum(0)), atol=1e-8)


def test_two_dimensional_scheduled_chunks_equal_kalman_bucy():
    model = compile_model(spec_from_dict(LINEAR_2D))
    incs = simulate(model, 320, np.random.default_rng(3)).increments  # the path settles after ~190
    kb = KalmanBucyFilter(model)
    kb_state, ref = kb.run_arrays(kb.initial_state(), incs)
    for sizes in ([], [1, 1, 150, 1, 17]):
        state, out = _in_pieces(YauHuFilter(model), incs, sizes)
        np.testing.assert_allclose(out["mean"], ref.mean, atol=1e-9)
        np.testing.assert_allclose(out["cov"], ref.cov, atol=1e-9)
        np.testing.assert_allclose(out["loglik"], ref.loglik, atol=1e-8)


def test_one_row_chunks_on_ou_equal_kalman_bucy():
    # one Gaussian component, one term of e^F (the one-row path's shortcut); offsets in f and h
    # so that every data term of the step (linear in y, in B_prev·y) is exercised
    spec = load_spec("examples/ou.toml").model_dump(mode="json")
    spec.update(drift=["-theta*x + 0.3"], observation=["x - 0.4"], observation_noise=[[0.6]])
    model = compile_model(spec_from_dict(spec))
    incs = simulate(model, 1400, np.random.default_rng(6)).increments
    kb = KalmanBucyFilter(model)
    _, ref = kb.run_arrays(kb.initial_state(), incs)
    _, out = _in_pieces(YauHuFilter(model), incs, [1] * 60 + [1250] + [1] * 40)
    np.testing.assert_allclose(out["mean"], ref.mean, atol=1e-9)
    np.testing.assert_allclose(out["cov"], ref.cov, atol=1e-9)
    np.testing.assert_allclose(out["loglik"], ref.loglik, atol=1e-8)
