"""The online Yau–Yau filter (solver/engine/filter.py) against independent truth.

* OU (linear Gaussian, R ≠ 1, a ≠ 1): the exact sampled-time Kalman filter (Van Loan), both
  the stable form and the literal seed 002 (5.35)/(5.38) form — a misprint in exp(hᵀR⁻¹Δy) or
  in the ½hᵀR⁻¹h of (5.31) moves the mean/variance far beyond the tolerances.
* Beneš (f = tanh x, h = x): the exact density cosh(x)·N(x; μ, P)/(e^{P/2} cosh μ), (μ, P) from a
  three-line Kalman recursion written here.
* Cubic sensor: the fine-grid point-mass reference (finite volumes, independent of the FE).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest
from helpers import EXAMPLES
from yauyau.solver import compile_model, load_spec, spec_from_dict
from yauyau.solver.engine.filter import YauYauFilter
from yauyau.solver.errors import InputError, SpecError
from yauyau.solver.exact.riccati import (
    GaussianKolmogorov,
    GaussianTerms,
    gaussian_to_terms,
    terms_to_gaussian,
)
from yauyau.solver.filtering import Filter
from yauyau.solver.offline.pipeline import precompute
from yauyau.solver.reference.kalman import DiscreteKalmanFilter
from yauyau.solver.reference.pointmass import PointMassFilter
from yauyau.solver.simulate import simulate
from yauyau.solver.spec import GaussianPrior


@pytest.fixture(scope="module")
def benes():
    model = compile_model(load_spec(EXAMPLES / "benes.toml"))
    return model, precompute(model)


def _stack(estimates, name):
    return np.array([getattr(e, name) for e in estimates])


def _run_side_by_side(model, offline, reference, steps: int, seed: int):
    """The engine and a reference filter on one simulated path: (engine, state, estimates) × 2."""
    increments = simulate(model, steps, np.random.default_rng(seed)).increments
    yy = YauYauFilter(model, offline)
    ours = (yy, *yy.run(yy.initial_state(), increments))
    return ours, (reference, *reference.run(reference.initial_state(), increments))


# -- linear Gaussian: exact time-discrete filters ------------------------------------------------
def _kalman(model, dy):
    kalman = DiscreteKalmanFilter(model)
    _, ref = kalman.run(kalman.initial_state(), dy)
    return _stack(ref, "mean")[:, 0], _stack(ref, "cov")[:, 0, 0], _stack(ref, "loglik")


def _literal_exact(model, dy):
    """The literal seed form on Gaussians, exactly: u = exp(−Ax² − Bx − C) flows by the Kolmogorov
    equation (5.31) ∂u = ½a u'' + θx u' + (θ − ½x²/R) u (Riccati ODEs, solver/exact/riccati.py),
    then (5.35) multiplies it by exp(xΔy/R): B ← B − Δy/R."""
    theta, a, r = 0.5, model.a[0, 0], model.R[0, 0]
    flow = GaussianKolmogorov(D=[[-theta]], Q=[[0.5 / r]], a=[[a]]).flow(model.dt)
    terms = gaussian_to_terms([1.0], [[0.5]])  # examples/ou.toml prior
    means, variances, logliks = [], [], []
    for row in dy:
        terms = flow.step(terms.A, terms.B, terms.C)
        terms = GaussianTerms(terms.A, terms.B - row / r, terms.C)
        mean, cov, log_mass = terms_to_gaussian(terms.A, terms.B, terms.C)
        means.append(mean[0]), variances.append(cov[0, 0]), logliks.append(log_mass)
    return np.array(means), np.array(variances), np.array(logliks)


@pytest.mark.slow
@pytest.mark.parametrize("form, precision, exact", [("stable", "double", _kalman),
                                                     ("stable", "single", _kalman),
                                                     ("literal", "double", _literal_exact)])
def test_ou_matches_exact_time_discrete_filter(ou, form, precision, exact):
    model, offline = ou
    sim = simulate(model, 400, np.random.default_rng(11))
    yy = YauYauFilter(model, offline, form=form, precision=precision)
    assert isinstance(yy, Filter)
    _, estimates = yy.run(yy.initial_state(), sim.increments)
    ref_mean, ref_var, ref_loglik = exact(model, sim.increments)
    assert np.max(np.abs(_stack(estimates, "mean")[:, 0] - ref_mean)) < 1e-3
    assert np.max(np.abs(_stack(estimates, "cov")[:, 0, 0] / ref_var - 1.0)) < 0.01
    # the log normaliser is the likelihood ratio of the increments against pure noise
    assert np.max(np.abs(_stack(estimates, "loglik") - ref_loglik)) < 1e-3
    assert all(np.isfinite(e.mode).all() and not e.degenerate for e in estimates)


def test_the_two_forms_differ_by_the_splitting_error_only(ou):
    """Both are first order in dt: their gap is O(dt), here ~1e-3, not O(1)."""
    model, offline = ou
    dy = simulate(model, 200, np.random.default_rng(14)).increments
    stable, literal = (YauYauFilter(model, offline, form=f) for f in ("stable", "literal"))
    _, a = stable.run_arrays(stable.initial_state(), dy)
    _, b = literal.run_arrays(literal.initial_state(), dy)
    gap = np.max(np.abs(a.mean - b.mean))
    assert 1e-5 < gap < 20 * model.dt


def test_ou_density_matches_kalman_gaussian(ou):
    model, offline = ou
    kalman = DiscreteKalmanFilter(model)
    (yy, state, _), (_, kstate, _) = _run_side_by_side(model, offline, kalman, 150, 12)
    x = np.linspace(-model.radius, model.radius, 8001)
    p = yy.density(state, x[:, None])
    assert np.all(p >= 0.0)
    assert abs(np.trapezoid(p, x) - 1.0) < 1e-3
    assert np.trapezoid(np.abs(p - kalman.density(kstate, x[:, None])), x) < 1e-3
    assert np.allclose(yy.marginal(state, 0, x), p)
    assert np.all(yy.density(state, [[model.radius + 1.0]]) == 0.0)


def test_missing_row_is_a_pure_prediction(ou):
    model, offline = ou
    sim = simulate(model, 60, np.random.default_rng(13))
    dy = sim.increments.copy()
    dy[[5, 6, 30]] = np.nan
    yy = YauYauFilter(model, offline)
    state, estimates = yy.run(yy.initial_state(), dy[:30])
    # vs the Fokker–Planck propagator alone: σ = propagator_fp c, moments with the weights
    sigma = offline.propagator_fp @ state.density_coefficients
    mass = offline.weights @ sigma
    mean = offline.weights @ (sigma * offline.nodes[:, 0]) / mass
    _, predicted = yy.step(state, None)
    assert predicted.mean[0] == pytest.approx(mean, abs=1e-12)
    assert predicted.loglik_increment == pytest.approx(np.log(mass), abs=1e-12)
    assert abs(predicted.loglik_increment) < 1e-6  # no observation, (almost) no mass lost
    _, same = yy.step(state, np.array([np.nan]))
    assert same.mean[0] == predicted.mean[0]
    # vs Kalman with the same missing rows (its prediction is exact)
    kalman = DiscreteKalmanFilter(model)
    _, reference = kalman.run(kalman.initial_state(), dy)
    _, estimates = yy.run(yy.initial_state(), dy)
    assert np.max(np.abs(_stack(estimates, "mean") - _stack(reference, "mean"))) < 1e-3
    var, ref_var = _stack(estimates, "cov")[:, 0, 0], _stack(reference, "cov")[:, 0, 0]
    assert np.max(np.abs(var / ref_var - 1.0)) < 0.01


def test_prior_override_and_initial_moments(ou):
    model, offline = ou
    yy = YauYauFilter(model, offline)
    default = yy.estimate(yy.initial_state())
    assert default.mean[0] == pytest.approx(1.0, abs=1e-6)  # examples/ou.toml prior N(1, 0.5)
    assert default.cov[0, 0] == pytest.approx(0.5, rel=1e-4)
    for prior in (GaussianPrior(kind="gaussian", mean=[-1.5], cov=[[0.3]]),
                  {"kind": "gaussian", "mean": [-1.5], "cov": [[0.3]]}):
        first = yy.estimate(yy.initial_state(prior))
        assert first.mean[0] == pytest.approx(-1.5, abs=1e-6)
        assert first.cov[0, 0] == pytest.approx(0.3, rel=1e-4)
    mixture = {"kind": "mixture", "weights": [1, 3], "means": [[-1.0], [2.0]], "covs": [[[0.2]], [[0.5]]]}
    assert yy.estimate(yy.initial_state(mixture)).mean[0] == pytest.approx(0.25 * -1 + 0.75 * 2, abs=1e-6)
    with pytest.raises(SpecError) as err:
        yy.initial_state({"kind": "gaussian", "mean": [0.0, 1.0], "cov": [[1.0]]})
    assert err.value.field.startswith("initial")
    with pytest.raises(SpecError):
        yy.initial_state({"kind": "gaussian", "mean": [50.0], "cov": [[0.01]]})  # no mass on the ball


# -- Beneš: exact density ------------------------------------------------------------------------
@pytest.mark.slow
def test_benes_density_matches_exact_filter(benes):
    model, offline = benes
    sim = simulate(model, 250, np.random.default_rng(5))
    yy = YauYauFilter(model, offline)
    state = yy.initial_state()
    x = np.linspace(-model.radius, model.radius, 20001)
    mu, P, dt = 0.0, 1.0, model.dt  # prior ∝ cosh(x) N(x; 0, 1)  (examples/benes.toml)
    worst = 0.0
    for k, dy in enumerate(sim.increments):
        state, estimate = yy.step(state, dy)
        P = P + dt  # heat flow of the Gaussian factor; cosh carries the drift tanh x exactly
        mu, P = (mu / P + dy[0]) / (1.0 / P + dt), 1.0 / (1.0 / P + dt)
        if k % 50 == 49:
            exact = np.cosh(x) * np.exp(-(x - mu) ** 2 / (2 * P)) / np.sqrt(2 * np.pi * P)
            exact /= np.exp(P / 2) * np.cosh(mu)
            worst = max(worst, np.trapezoid(np.abs(yy.density(state, x[:, None]) - exact), x))
            assert estimate.mean[0] == pytest.approx(mu + P * np.tanh(mu), abs=1e-4)
    assert worst < 1e-3


# -- cubic sensor: fine-grid reference -----------------------------------------------------------
@pytest.mark.slow
def test_cubic_sensor_matches_point_mass_reference(cubic):
    model, offline = cubic
    (_, _, estimates), (_, _, ref) = _run_side_by_side(model, offline, PointMassFilter(model), 400, 3)
    assert np.max(np.abs(_stack(estimates, "mean") - _stack(ref, "mean"))) <= 0.01
    assert np.max(np.abs(_stack(estimates, "cov") - _stack(ref, "cov"))) <= 0.01


# -- degeneracy ------------------------------------------------------------------------------
@pytest.mark.parametrize("impossible, words", [(1e6, ""), (-1e6, ""), (1e307, "overflows")])
def test_impossible_data_flags_degenerate_and_keeps_last_estimate(cubic, impossible, words):
    model, offline = cubic
    dy = simulate(model, 20, np.random.default_rng(4)).increments
    dy[10] = impossible
    yy = YauYauFilter(model, offline, gate=0)  # the gate off: the row reaches the update
    state, estimates = yy.run(yy.initial_state(), dy)
    good = estimates[9]
    assert not any(e.degenerate for e in estimates[:10])
    assert all(e.degenerate and words in e.reason for e in estimates[10:])
    for e in estimates[10:]:
        assert np.array_equal(e.mean, good.mean) and np.array_equal(e.cov, good.cov)
        assert e.loglik == good.loglik and np.isfinite(e.loglik)
    assert state.degenerate and words in state.reason and state.step == 20
    assert state.last.step == good.step == 10  # row 9 is step 10
    current = yy.estimate(state)
    assert current.degenerate and current.reason == state.reason and current.step == 20
    assert np.array_equal(current.mean, good.mean) and current.loglik == good.loglik
    # a degenerate state keeps returning the last good estimate
    later, more = yy.run(state, dy[:3])
    assert later.degenerate and later.step == 23 and all(e.degenerate for e in more)
    assert np.array_equal(more[-1].mean, good.mean)
    json.dumps(later.to_dict(), allow_nan=False)


def test_impossible_first_row_keeps_the_initial_state(cubic):
    model, offline = cubic
    yy = YauYauFilter(model, offline, gate=0)
    start = yy.initial_state()
    state, estimates = yy.run(start, [[1e307], [0.01]])
    assert state.degenerate and "overflows" in state.reason and state.step == 2
    assert np.array_equal(state.coefficients, start.coefficients) and state.mass == start.mass
    assert all(e.degenerate and np.array_equal(e.mean, start.last.mean) for e in estimates)


def test_a_non_positive_variance_is_degenerate(ou):
    """Ripples of a basis too small for the density can give a variance ≤ 0: flagged, not returned."""
    model, offline = ou
    yy = YauYauFilter(model, offline)
    sigma = np.tile(offline.weights * 0 + 1e-3, (4, 1))
    cov = np.ones((4, 1, 1))
    cov[2, 0, 0] = -1e-3
    bad, reason = yy.diagnostics.first_implausible(sigma, np.ones(4), cov)
    assert bad == 2 and "covariance" in reason
    assert yy.diagnostics.first_implausible(sigma, np.ones(4), np.ones((4, 1, 1))) == (None, None)


# -- state round trip ----------------------------------------------------------------------------
@pytest.mark.parametrize("form, precision", [("stable", "double"), ("literal", "double"),
                                             ("stable", "single")])
def test_state_round_trip_continues_bit_identically(cubic, form, precision):
    model, offline = cubic
    dy = simulate(model, 300, np.random.default_rng(8)).increments
    dy[[20, 150, 151]] = np.nan
    yy = YauYauFilter(model, offline, form=form, precision=precision)
    start = yy.initial_state()
    whole, all_estimates = yy.run_arrays(start, dy)
    state, first = yy.run_arrays(start, dy[:70])
    restored = YauYauFilter(model, offline, form=form, precision=precision).state_from_dict(
        json.loads(json.dumps(state.to_dict(), allow_nan=False)))
    state, second = yy.run_arrays(restored, dy[70:])
    for name in ("mean", "cov", "mode", "loglik", "loglik_increment"):
        joined = np.concatenate([getattr(first, name), getattr(second, name)])
        assert np.array_equal(joined, getattr(all_estimates, name)), name
    assert np.array_equal(state.coefficients, whole.coefficients) and state.mass == whole.mass
    assert state.to_dict() == whole.to_dict()


def test_state_from_dict_names_the_bad_field(ou):
    model, offline = ou
    yy = YauYauFilter(model, offline)
    good = yy.initial_state().to_dict()
    for change, field in ((("coefficients", [1.0, 2.0]), "state.coefficients"),
                          (("method", "kalman-bucy"), "state.method"),
                          (("form", "literal"), "state.form"),
                          (("precision", "single"), "state.precision"),
                          (("mass", -1.0), "state.mass"),
                          (("step", -3), "state.step"),
                          (("loglik", "x"), "state.loglik"),
                          (("last", None), "state.last")):
        bad = dict(good)
        bad[change[0]] = change[1]
        with pytest.raises(InputError) as err:
            yy.state_from_dict(bad)
        assert err.value.field == field


def test_bad_increments_and_form_are_rejected(ou):
    model, offline = ou
    yy = YauYauFilter(model, offline)
    state = yy.initial_state()
    with pytest.raises(InputError):
        yy.run(state, np.ones((3, 2)))
    with pytest.raises(InputError) as err:
        yy.run(state, [[0.1], [np.inf]])
    assert err.value.field == "increments[1]"
    with pytest.raises(SpecError) as err:
        YauYauFilter(model, offline, form="magic")
    assert err.value.field == "form"
    same, estimates = yy.run(state, np.empty((0, 1)))
    assert same is state and estimates == []


# -- 2-D: marginals ------------------------------------------------------------------------------
def test_two_dimensional_marginals_of_the_prior():
    doc = {"name": "ou-2d", "state": ["x1", "x2"], "drift": ["-x1 + 0.5*x2", "-0.5*x2"],
           "observation": ["x1", "x2"],
           "initial": {"kind": "gaussian", "mean": [0.5, -0.8], "cov": [[1.0, 0.3], [0.3, 0.8]]},
           "domain": {"radius": 5.0}, "discretization": {"dt": 0.02, "basis": 120}}
    model = compile_model(spec_from_dict(doc))
    yy = YauYauFilter(model, precompute(model))
    state = yy.initial_state()
    grid = np.linspace(-4.0, 4.0, 161)
    for index, (mean, var) in enumerate(((0.5, 1.0), (-0.8, 0.8))):
        exact = np.exp(-(grid - mean) ** 2 / (2 * var)) / np.sqrt(2 * np.pi * var)
        marginal = yy.marginal(state, index, grid)
        assert np.all(marginal >= 0.0)
        assert np.trapezoid(np.abs(marginal - exact), grid) < 0.03
    with pytest.raises(InputError):
        yy.marginal(state, 2, grid)


_CONTINUE = """
import json, sys
import numpy as np
from yauyau.solver import compile_model, load_spec
from yauyau.solver.engine.filter import YauYauFilter
from yauyau.solver.offline.pipeline import OfflineModel
model = compile_model(load_spec(sys.argv[1]))
yy = YauYauFilter(model, OfflineModel.from_arrays(model, dict(np.load(sys.argv[2]))))
state = yy.state_from_dict(json.loads(open(sys.argv[3]).read()))
state, result = yy.run_arrays(state, np.load(sys.argv[4]))
print(json.dumps({"mean": result.mean.tolist(), "loglik": result.loglik.tolist(), "state": state.to_dict()}))
"""


@pytest.mark.slow
def test_a_restarted_process_continues_bit_identically(cubic, tmp_path):
    """A stored state continued in a fresh process (other BLAS thread count) = the uninterrupted run."""
    model, offline = cubic
    dy = simulate(model, 200, np.random.default_rng(9)).increments
    arrays, state_file, rest = tmp_path / "arrays.npz", tmp_path / "state.json", tmp_path / "rest.npy"
    np.savez(arrays, **offline.to_arrays())
    np.save(rest, dy[80:])
    yy = YauYauFilter(model, offline)
    whole, expected = yy.run_arrays(yy.initial_state(), dy)
    state, _ = yy.run_arrays(yy.initial_state(), dy[:80])
    state_file.write_text(json.dumps(state.to_dict()))
    env = {**os.environ, "OPENBLAS_NUM_THREADS": "1"}
    out = subprocess.run([sys.executable, "-c", _CONTINUE, str(EXAMPLES / "cubic_sensor.toml"), str(arrays),
                          str(state_file), str(rest)], capture_output=True, text=True, env=env, check=True)
    continued = json.loads(out.stdout)
    assert continued["mean"] == expected.mean[80:].tolist()
    assert continued["loglik"] == expected.loglik[80:].tolist()
    assert continued["state"] == json.loads(json.dumps(whole.to_dict()))
