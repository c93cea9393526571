"""Simulation against closed forms: OU moments, increment statistics, prior sampling."""

import numpy as np
import pytest
from scipy.stats import norm
from yauyau.solver.errors import InputError
from yauyau.solver.model import compile_model
from yauyau.solver.simulate import sample_prior, simulate, simulate_paths
from yauyau.solver.spec import spec_from_dict


def _spec(**over):
    base = {"name": "t", "state": ["x"], "drift": ["-theta*x"], "observation": ["x"],
            "parameters": {"theta": 0.7}, "diffusion": [[0.5]],
            "initial": {"kind": "gaussian", "mean": [1.5], "cov": [[0.3]]},
            "domain": {"radius": 8.0}, "discretization": {"dt": 0.02, "basis": 16}}
    base.update(over)
    return compile_model(spec_from_dict(base))


def test_ou_moments_match_exact_formulas():
    model = _spec()
    theta, a, m0, p0 = 0.7, 0.5, 1.5, 0.3
    paths, steps = 4000, 50
    sim = simulate_paths(model, steps, np.random.default_rng(1), substeps=20, paths=paths)
    for k in (10, 50):
        t = sim.times[k]
        mean = m0 * np.exp(-theta * t)
        var = p0 * np.exp(-2 * theta * t) + a * (1 - np.exp(-2 * theta * t)) / (2 * theta)
        x = sim.states[:, k, 0]
        assert abs(x.mean() - mean) < 4 * np.sqrt(var / paths)
        # var of the sample variance ≈ 2σ⁴/N
        assert abs(x.var() - var) < 4 * var * np.sqrt(2 / paths) + 2e-3
    # one-step autocovariance of the stationary-type transition: Cov(x_t, x_{t+s}) = e^{-θs} Var(x_t)
    x0, x1 = sim.states[:, 40, 0], sim.states[:, 50, 0]
    cov = np.mean((x0 - x0.mean()) * (x1 - x1.mean()))
    assert abs(cov - np.exp(-theta * 0.2) * x0.var()) < 0.03


def test_increments_of_ou_have_the_integrated_mean():
    model = _spec()
    theta, m0 = 0.7, 1.5
    paths, steps = 4000, 50
    sim = simulate_paths(model, steps, np.random.default_rng(2), substeps=20, paths=paths)
    y_end = sim.increments[:, :, 0].sum(axis=1)
    T = steps * model.dt
    mean = m0 * (1 - np.exp(-theta * T)) / theta  # E ∫ x dt
    assert abs(y_end.mean() - mean) < 4 * y_end.std() / np.sqrt(paths)
    # Δy − ∫h dt is N(0, R dt): for a linear h the integral is close to the trapezoid of x
    resid = sim.increments[:, :, 0] - 0.5 * (sim.states[:, :-1, 0] + sim.states[:, 1:, 0]) * model.dt
    assert abs(resid.var() / model.dt - 1.0) < 0.02


def test_increments_with_constant_h_are_gaussian_with_covariance_R_dt():
    r = [[2.0, 0.6], [0.6, 1.0]]
    model = _spec(observation=["1.5", "-0.5"], observation_noise=r)
    sim = simulate_paths(model, 20, np.random.default_rng(3), substeps=2, paths=3000)
    dy = sim.increments.reshape(-1, 2)
    dt = model.dt
    n = dy.shape[0]
    assert np.allclose(dy.mean(axis=0), [1.5 * dt, -0.5 * dt], atol=4 * np.sqrt(2 * dt / n))
    assert np.allclose(np.cov(dy.T) / dt, r, atol=0.05)


def test_single_path_shapes_and_determinism():
    model = _spec()
    a = simulate(model, 30, np.random.default_rng(5))
    b = simulate(model, 30, np.random.default_rng(5))
    assert a.states.shape == (31, 1) and a.increments.shape == (30, 1) and a.times.shape == (31,)
    assert np.array_equal(a.states, b.states) and np.array_equal(a.increments, b.increments)
    assert a.times[-1] == pytest.approx(30 * model.dt)


def test_mixture_prior_sampling_moments():
    model = _spec(initial={"kind": "mixture", "weights": [1.0, 3.0], "means": [[-2.0], [1.0]],
                           "covs": [[[0.25]], [[0.5]]]})
    x = sample_prior(model, 40000, np.random.default_rng(6))[:, 0]
    mean, cov = model.prior_moments()
    assert abs(x.mean() - mean[0]) < 0.03
    assert abs(x.var() - cov[0, 0]) < 0.05
    cdf = 0.25 * norm.cdf(-0.5, -2.0, 0.5) + 0.75 * norm.cdf(-0.5, 1.0, np.sqrt(0.5))
    assert abs(np.mean(x < -0.5) - cdf) < 0.01


def test_density_prior_sampling_by_inverse_cdf():
    # p ∝ exp(-x²/2) * (1 + x²): mean 0, E x² = (1 + 3)/(1 + 1) = 2
    model = _spec(initial={"kind": "density", "expression": "exp(-x**2/2)*(1 + x**2)"})
    x = sample_prior(model, 40000, np.random.default_rng(7))[:, 0]
    assert abs(x.mean()) < 0.03
    assert abs(np.mean(x**2) - 2.0) < 0.06


def test_density_prior_2d_sampling():
    model = _spec(state=["x", "y"], drift=["-x", "-y"], observation=["x"], diffusion=None,
                  parameters={}, initial={"kind": "density", "expression": "exp(-(x-1)**2/2 - y**2/8)"})
    x = sample_prior(model, 20000, np.random.default_rng(8))
    assert np.allclose(x.mean(axis=0), [1.0, 0.0], atol=0.06)
    assert np.allclose(x.var(axis=0), [1.0, 4.0], rtol=0.06)


def test_bad_counts_raise_input_error():
    model = _spec()
    with pytest.raises(InputError) as err:
        simulate(model, 0, np.random.default_rng(0))
    assert err.value.field == "steps"
    with pytest.raises(InputError) as err:
        simulate(model, 3, np.random.default_rng(0), substeps=0)
    assert err.value.field == "substeps"
