"""Reference filters against independent truth: closed forms, quadrature, convergence, Monte Carlo."""

import numpy as np
import pytest
import sympy as sp
from yauyau.solver.errors import SpecError
from yauyau.solver.model import compile_model
from yauyau.solver.reference import (
    BenesFilter,
    BootstrapParticleFilter,
    DiscreteKalmanFilter,
    ExtendedKalmanFilter,
    PointMassFilter,
    UnscentedKalmanFilter,
    affine_coefficients,
    van_loan,
)
from yauyau.solver.simulate import simulate
from yauyau.solver.spec import load_spec, spec_from_dict

OU = {"name": "ou", "state": ["x"], "drift": ["-theta*x + 0.3"], "observation": ["2*x - 0.5"],
      "parameters": {"theta": 0.8}, "diffusion": [[0.6]], "observation_noise": [[0.5]],
      "initial": {"kind": "gaussian", "mean": [1.0], "cov": [[0.4]]},
      "domain": {"radius": 6.0}, "discretization": {"dt": 0.02, "basis": 16}}
ROT = {"name": "rot", "state": ["x1", "x2"], "drift": ["-0.5*x1 + x2", "-x1 - 0.5*x2"],
       "observation": ["x1"],
       "initial": {"kind": "gaussian", "mean": [0.5, 0.0], "cov": [[0.5, 0.1], [0.1, 0.4]]},
       "domain": {"radius": 6.0}, "discretization": {"dt": 0.01, "basis": 16}}


def _model(base, **over):
    spec = dict(base)
    spec.update(over)
    return compile_model(spec_from_dict(spec))


# -- Van Loan and the affine coefficients ---------------------------------------------------
def test_van_loan_matches_the_ou_closed_form():
    theta, a, f0, dt = 0.8, 0.6, 0.3, 0.02
    phi, shift, q = van_loan(np.array([[-theta]]), np.array([[a]]), np.array([f0]), dt)
    assert phi[0, 0] == pytest.approx(np.exp(-theta * dt), rel=1e-13)
    assert shift[0] == pytest.approx(f0 * (1 - np.exp(-theta * dt)) / theta, rel=1e-12)
    assert q[0, 0] == pytest.approx(a * (1 - np.exp(-2 * theta * dt)) / (2 * theta), rel=1e-12)


def test_van_loan_matches_the_damped_rotation_closed_form():
    lam, omega, s2, dt = 0.5, 1.0, 1.3, 0.3
    F = np.array([[-lam, omega], [-omega, -lam]])
    phi, _, q = van_loan(F, s2 * np.eye(2), np.zeros(2), dt)
    rotation = np.array([[np.cos(omega * dt), np.sin(omega * dt)], [-np.sin(omega * dt), np.cos(omega * dt)]])
    assert np.allclose(phi, np.exp(-lam * dt) * rotation, atol=1e-13)
    # rotation keeps an isotropic covariance isotropic
    assert np.allclose(q, s2 * (1 - np.exp(-2 * lam * dt)) / (2 * lam) * np.eye(2), atol=1e-13)


def test_affine_coefficients_are_exact_and_nonaffine_is_refused():
    model = _model(OU)
    A, b = affine_coefficients(model.drift, model.symbols, "drift")
    assert A[0, 0] == -0.8 and b[0] == 0.3
    cubic = _model(OU, observation=["x**3"])
    with pytest.raises(SpecError) as err:
        DiscreteKalmanFilter(cubic)
    assert err.value.field == "observation"
    with pytest.raises(SpecError) as err:
        DiscreteKalmanFilter(_model(OU, drift=["sin(x)"]))
    assert err.value.field == "drift"


def test_kalman_step_matches_bayes_by_quadrature():
    """One step: predictive N(m⁻, P⁻) times the update factor, integrated on a fine grid."""
    model = _model(OU)
    kf = DiscreteKalmanFilter(model)
    dy = np.array([0.07])
    state, est = kf.step(kf.initial_state(), dy)
    m_pred = 1.0 * np.exp(-0.8 * 0.02) + 0.3 * (1 - np.exp(-0.8 * 0.02)) / 0.8
    p_pred = 0.4 * np.exp(-1.6 * 0.02) + 0.6 * (1 - np.exp(-1.6 * 0.02)) / 1.6
    x = np.linspace(m_pred - 12 * np.sqrt(p_pred), m_pred + 12 * np.sqrt(p_pred), 200001)
    prior = np.exp(-(x - m_pred) ** 2 / (2 * p_pred)) / np.sqrt(2 * np.pi * p_pred)
    h = 2 * x - 0.5
    post = prior * np.exp(h * dy[0] / 0.5 - 0.5 * h**2 / 0.5 * 0.02)
    z = np.trapezoid(post, x)
    mean = np.trapezoid(x * post, x) / z
    var = np.trapezoid((x - mean) ** 2 * post, x) / z
    assert est.mean[0] == pytest.approx(mean, rel=1e-10)
    assert est.cov[0, 0] == pytest.approx(var, rel=1e-8)
    assert est.loglik == pytest.approx(np.log(z), abs=1e-10)
    # a missing observation only predicts
    _, est2 = kf.step(state, np.array([np.nan]))
    q = 0.6 * (1 - np.exp(-1.6 * 0.02)) / 1.6
    assert est2.loglik_increment == 0.0 and est2.loglik == est.loglik
    assert est2.cov[0, 0] == pytest.approx(np.exp(-1.6 * 0.02) * est.cov[0, 0] + q, rel=1e-12)


def test_kalman_state_round_trips_through_a_dict():
    model = _model(ROT)
    kf = DiscreteKalmanFilter(model)
    sim = simulate(model, 20, np.random.default_rng(3))
    state, _ = kf.run(kf.initial_state(), sim.increments)
    again = kf.state_from_dict(state.to_dict())
    assert np.array_equal(again.mean, state.mean) and again.loglik == state.loglik and again.step == 20


# -- point-mass reference: convergence to the exact sampled Kalman filter ----------------------
def _errors_vs_kalman(model, filt, increments):
    kf = DiscreteKalmanFilter(model)
    _, exact = kf.run(kf.initial_state(), increments)
    _, approx = filt.run(filt.initial_state(), increments)
    pairs = list(zip(exact, approx, strict=True))
    mean_err = max(np.abs(a.mean - b.mean).max() for a, b in pairs)
    cov_err = max(np.abs(a.cov - b.cov).max() / np.abs(a.cov).max() for a, b in pairs)
    return mean_err, cov_err, abs(exact[-1].loglik - approx[-1].loglik)


def test_point_mass_converges_to_kalman_at_second_order_in_1d():
    model = _model(OU)
    sim = simulate(model, 200, np.random.default_rng(11))
    errors = [_errors_vs_kalman(model, PointMassFilter(model, cells=c), sim.increments)
              for c in (96, 192, 384)]
    for coarse, fine in zip(errors[:-1], errors[1:], strict=True):
        for e_c, e_f in zip(coarse, fine, strict=True):
            assert e_c / e_f > 3.2  # ≈ 4 for a second-order scheme
    mean_err, cov_err, loglik_err = errors[-1]
    assert mean_err < 2e-3 and cov_err < 2e-3 and loglik_err < 1e-3


def test_point_mass_converges_to_kalman_in_2d():
    model = _model(ROT)
    sim = simulate(model, 60, np.random.default_rng(12))
    coarse = _errors_vs_kalman(model, PointMassFilter(model, cells=40), sim.increments)
    fine = _errors_vs_kalman(model, PointMassFilter(model, cells=80), sim.increments)
    assert coarse[0] / fine[0] > 3.0 and coarse[1] / fine[1] > 3.0
    assert fine[0] < 5e-3 and fine[1] < 1e-2


def test_point_mass_density_is_normalised_and_matches_kalman():
    model = _model(OU)
    pm = PointMassFilter(model, cells=1024)
    kf = DiscreteKalmanFilter(model)
    sim = simulate(model, 50, np.random.default_rng(13))
    s_pm, _ = pm.run(pm.initial_state(), sim.increments)
    s_kf, _ = kf.run(kf.initial_state(), sim.increments)
    x = np.linspace(-6, 6, 4001)[:, None]
    p, q = pm.density(s_pm, x), kf.density(s_kf, x)
    assert np.trapezoid(p, x[:, 0]) == pytest.approx(1.0, abs=1e-4)
    assert np.trapezoid(np.abs(p - q), x[:, 0]) < 1e-3


def test_point_mass_refuses_3d():
    spec = dict(ROT, state=["a", "b", "c"], drift=["-a", "-b", "-c"], observation=["a"],
                initial={"kind": "gaussian", "mean": [0, 0, 0], "cov": np.eye(3).tolist()})
    with pytest.raises(SpecError) as err:
        PointMassFilter(compile_model(spec_from_dict(spec)))
    assert err.value.field == "state"


# -- bootstrap particle filter: Monte-Carlo agreement with the Kalman filter --------------------
def test_particle_filter_agrees_with_kalman_within_monte_carlo_error():
    model = _model(OU)
    sim = simulate(model, 100, np.random.default_rng(21))
    kf = DiscreteKalmanFilter(model)
    _, exact = kf.run(kf.initial_state(), sim.increments)
    n = 20000
    pf = BootstrapParticleFilter(model, n, np.random.default_rng(22), substeps=4)
    _, approx = pf.run(pf.initial_state(), sim.increments)
    z = np.array([(a.mean[0] - b.mean[0]) / np.sqrt(a.cov[0, 0] / (n / 2))
                  for a, b in zip(exact, approx, strict=True)])
    assert np.abs(z).max() < 5.0  # ESS ≥ N/2 between resamplings
    ratio = np.array([b.cov[0, 0] / a.cov[0, 0] for a, b in zip(exact, approx, strict=True)])
    assert np.abs(ratio - 1).max() < 5 * np.sqrt(2 / (n / 2))
    assert abs(exact[-1].loglik - approx[-1].loglik) < 0.1


# -- Beneš: the closed form verified symbolically, then against the fine grid --------------------
def test_benes_flow_solves_the_fokker_planck_equation_symbolically():
    """cosh(x)·e^{−t/2}·N(x; m, P + t) solves ∂p/∂t = ½p'' − (tanh(x) p)'."""
    x, m = sp.symbols("x m", real=True)
    t, P = sp.symbols("t P", positive=True)
    p = sp.cosh(x) * sp.exp(-t / 2) * sp.exp(-(x - m) ** 2 / (2 * (P + t))) / sp.sqrt(2 * sp.pi * (P + t))
    residual = sp.diff(p, t) - (sp.diff(p, x, 2) / 2 - sp.diff(sp.tanh(x) * p, x))
    assert sp.simplify((residual / p).rewrite(sp.exp)) == 0


def test_benes_update_is_the_kalman_update_symbolically():
    """cosh(x)N(m,P)·exp(xΔy − ½x²dt) ∝ cosh(x)N(m',P') with 1/P' = 1/P + dt, m' = P'(m/P + Δy)."""
    x, m, dy = sp.symbols("x m dy", real=True)
    P, dt = sp.symbols("P dt", positive=True)
    p_new = 1 / (1 / P + dt)
    m_new = p_new * (m / P + dy)
    log_ratio = (-(x - m) ** 2 / (2 * P) + x * dy - x**2 * dt / 2) - (-(x - m_new) ** 2 / (2 * p_new))
    assert sp.simplify(sp.diff(log_ratio, x)) == 0  # cosh(x) cancels; the ratio does not depend on x


def test_benes_moments_and_density_are_normalised_closed_forms():
    model = compile_model(load_spec("examples/benes.toml"))
    bf = BenesFilter(model)
    m, p = 0.7, 0.4
    state = bf.initial_state().__class__(mean=np.array([m]), cov=np.array([[p]]))
    x = np.linspace(-12, 12, 200001)
    dens = bf.density(state, x[:, None])
    assert np.trapezoid(dens, x) == pytest.approx(1.0, abs=1e-10)
    mean = np.trapezoid(x * dens, x)
    assert bf.estimate(state).mean[0] == pytest.approx(mean, abs=1e-10)
    assert bf.estimate(state).cov[0, 0] == pytest.approx(np.trapezoid((x - mean) ** 2 * dens, x), abs=1e-9)


def test_benes_filter_matches_the_fine_grid_on_the_benes_model():
    model = compile_model(load_spec("examples/benes.toml"))
    sim = simulate(model, 200, np.random.default_rng(31))
    bf, pm = BenesFilter(model), PointMassFilter(model, cells=2048)
    s_b, e_b = bf.run(bf.initial_state(), sim.increments)
    s_p, e_p = pm.run(pm.initial_state(), sim.increments)
    x = np.linspace(-10, 10, 8001)[:, None]
    l1 = np.trapezoid(np.abs(bf.density(s_b, x) - pm.density(s_p, x)), x[:, 0])
    assert l1 < 2e-4
    assert max(abs(a.mean[0] - b.mean[0]) for a, b in zip(e_b, e_p, strict=True)) < 1e-4
    assert abs(e_b[-1].loglik - e_p[-1].loglik) < 1e-4


def test_benes_refuses_other_models_naming_the_field():
    with pytest.raises(SpecError) as err:
        BenesFilter(_model(OU))
    assert err.value.field == "drift"
    benes = load_spec("examples/benes.toml").model_dump()
    benes["initial"] = {"kind": "mixture", "weights": [0.5, 0.5], "means": [[-1.0], [1.0]],
                        "covs": [[[0.5]], [[0.5]]]}
    with pytest.raises(SpecError) as err:
        BenesFilter(compile_model(spec_from_dict(benes)))
    assert err.value.field == "initial"


# -- EKF and UKF: exact on linear models; the unscented transform exact for quadratics ------------
@pytest.mark.parametrize("cls", [ExtendedKalmanFilter, UnscentedKalmanFilter])
@pytest.mark.parametrize("base", [OU, ROT])
def test_gaussian_approximations_equal_kalman_on_linear_models(cls, base):
    model = _model(base)
    sim = simulate(model, 100, np.random.default_rng(41))
    kf, approx = DiscreteKalmanFilter(model), cls(model)
    _, exact = kf.run(kf.initial_state(), sim.increments)
    _, got = approx.run(approx.initial_state(), sim.increments)
    for a, b in zip(exact, got, strict=True):
        assert np.allclose(a.mean, b.mean, atol=1e-9) and np.allclose(a.cov, b.cov, atol=1e-9)
    assert exact[-1].loglik == pytest.approx(got[-1].loglik, abs=1e-8)


def test_ukf_update_is_exact_for_a_quadratic_sensor_moment():
    """With h = x², the unscented transform gives E h = m² + P exactly (while the EKF gives m²)."""
    model = _model(OU, observation=["x**2"], observation_noise=[[1.0]])
    ukf, ekf = UnscentedKalmanFilter(model), ExtendedKalmanFilter(model)
    m, p = np.array([0.8]), np.array([[0.3]])
    y_u, _, c_u = ukf._observation_moments(m, p)
    y_e, _, _ = ekf._observation_moments(m, p)
    dt = model.dt
    assert y_u[0] == pytest.approx((0.8**2 + 0.3) * dt, rel=1e-12)
    assert c_u[0, 0] == pytest.approx(2 * 0.8 * 0.3 * dt, rel=1e-12)  # Cov(x, x²) = 2mP
    assert y_e[0] == pytest.approx(0.8**2 * dt, rel=1e-12)


def test_ekf_prediction_of_a_nonlinear_drift_matches_the_ode_solution():
    """f = −x³ with a tiny P: ṁ = −m³ has m(t) = m0/√(1 + 2 m0² t)."""
    model = _model(OU, drift=["-x**3"], diffusion=[[1e-8]])
    ekf = ExtendedKalmanFilter(model)
    state = ekf.initial_state().__class__(mean=np.array([1.5]), cov=np.array([[1e-10]]))
    state, est = ekf.run(state, np.full((50, 1), np.nan))
    t = 50 * model.dt
    assert est[-1].mean[0] == pytest.approx(1.5 / np.sqrt(1 + 2 * 1.5**2 * t), rel=1e-9)


# -- the update factor and the particle filter's machinery -------------------------------------
def test_update_factor_is_the_gaussian_likelihood_ratio():
    """seed 002 (5.35): exp(hᵀR⁻¹Δy − ½hᵀR⁻¹h dt) = N(Δy; h dt, R dt) / N(Δy; 0, R dt)."""
    from scipy.stats import multivariate_normal
    from yauyau.solver.reference._base import log_update_factor

    r = [[0.7, 0.2], [0.2, 0.4]]
    model = _model(ROT, observation=["x1**3", "sin(x2)"], observation_noise=r)
    X = np.random.default_rng(51).normal(size=(7, 2))
    dy = np.array([0.03, -0.05])
    dt = model.dt
    expected = [multivariate_normal(h * dt, np.array(r) * dt).logpdf(dy)
                - multivariate_normal(np.zeros(2), np.array(r) * dt).logpdf(dy) for h in model.h(X)]
    assert np.allclose(log_update_factor(model, X, dy), expected, rtol=1e-10, atol=1e-10)


def test_systematic_resampling_keeps_each_count_within_one_of_n_w():
    from yauyau.solver.reference.particle import systematic_resample

    w = np.random.default_rng(52).dirichlet(np.ones(50))
    counts = np.bincount(systematic_resample(w, np.random.default_rng(53)), minlength=50)
    assert counts.sum() == 50 and np.all(np.abs(counts - 50 * w) < 1.0 + 1e-12)


def test_particle_filter_stays_finite_under_a_sharp_cubic_observation():
    model = _model(OU, observation=["x**3"], observation_noise=[[1.0]])
    pf = BootstrapParticleFilter(model, 500, np.random.default_rng(54))
    dy = np.array([[40.0], [np.nan], [-40.0]])  # far outside the prior's reach
    _, est = pf.run(pf.initial_state(), dy)
    for e in est:
        assert np.all(np.isfinite(e.mean)) and np.all(np.isfinite(e.cov)) and np.isfinite(e.loglik)
    assert est[1].loglik_increment == 0.0
