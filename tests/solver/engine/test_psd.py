"""Noise on some coordinates only: a positive semi-definite diffusion through the general engine.

Constant-velocity tracking, f = (v, −0.2v), a = diag(0, 1): the Fokker–Planck operator is
hypoelliptic (no diffusion along p) and plain Galerkin with the lumped mass rings along the drift.
The default for such a diffusion is ``scheme = "supg"`` (solver/offline/fem.py: streamline-upwind
Petrov–Galerkin with the consistent mass and the recovered second derivatives).

Truth, independent of the engine:
* the exact moments of the linear SDE (mean e^{tA}m₀, covariance by Van Loan's matrix exponential);
* the exact Kalman filter of the sampled linear model (KalmanBucyFilter(kind="discrete"));
* for the nonlinear sensor h = atan(p/5), a fine-grid filter written here: p on a periodic grid
  moved by Fourier phase shifts (p' = v is an exact shift for each v), v by the sampled exact
  Ornstein–Uhlenbeck kernel (its moments are exact to e^{−2π²(s/Δv)²}), Strang-split.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
import scipy.linalg as sla
from helpers.specs import modified
from yauyau.solver import compile_model, spec_from_dict
from yauyau.solver.engine.filter import build
from yauyau.solver.engine.follow import FollowingFilter
from yauyau.solver.errors import SpecError
from yauyau.solver.exact.kalman_bucy import KalmanBucyFilter
from yauyau.solver.offline.fem import streamline_tau
from yauyau.solver.offline.pipeline import precompute
from yauyau.solver.simulate import simulate

import yauyau

CV = {"name": "constant velocity", "state": ["p", "v"], "drift": ["v", "-0.2*v"], "observation": ["p"],
      "diffusion": [[0.0, 0.0], [0.0, 1.0]], "method": "yau-yau",
      "initial": {"kind": "gaussian", "mean": [-2.0, 1.0], "cov": [[0.2, 0.0], [0.0, 0.2]]},
      "domain": {"radius": 6.0}, "discretization": {"dt": 0.01, "basis": 600}}
A = np.array([[0.0, 1.0], [0.0, -0.2]])
NOISE = np.diag([0.0, 1.0])


def _doc(**changes):
    return modified(CV, **changes)


def _exact_moments(mean0, cov0, t):
    """Mean and covariance of dx = Ax dt + dW, E dWdWᵀ = NOISE dt (Van Loan 1978)."""
    E = sla.expm(A * t)
    G = sla.expm(np.block([[-A, NOISE], [np.zeros((2, 2)), A.T]]) * t)
    return E @ mean0, E @ cov0 @ E.T + G[2:, 2:].T @ G[:2, 2:]


# -- the spec ------------------------------------------------------------------------------------
def test_a_semi_definite_diffusion_is_accepted_with_the_stabilised_scheme():
    spec = spec_from_dict(_doc())
    assert spec.scheme() == "supg"
    assert "scheme" not in json.loads(spec.canonical_json())["discretization"]  # chosen, not stored
    assert spec_from_dict(_doc(discretization={"scheme": "galerkin"})).scheme() == "galerkin"
    pd = spec_from_dict(_doc(diffusion=[[0.05, 0.0], [0.0, 1.0]]))
    assert pd.scheme() == "galerkin" and "scheme" not in pd.canonical_json()  # old ids stay
    for bad, words in (([[-1.0, 0.0], [0.0, 1.0]], "semi-definite"), ([[0.0, 0.5], [0.0, 1.0]], "symmetric"),
                       ([[0.0, 0.0], [0.0, 0.0]], "not zero")):
        with pytest.raises(SpecError) as info:
            spec_from_dict(_doc(diffusion=bad))
        assert info.value.field == "diffusion" and words in info.value.message
    with pytest.raises(SpecError) as info:
        spec_from_dict(_doc(discretization={"element": "bubble", "order": 2}))
    assert info.value.field == "discretization.element" and 'element = "lagrange"' in info.value.message
    one = {"name": "x", "state": ["x"], "drift": ["-x"], "observation": ["x"],
           "initial": {"kind": "gaussian", "mean": [0.0], "cov": [[1.0]]}, "domain": {"radius": 5.0},
           "discretization": {"dt": 0.01, "basis": 20, "scheme": "supg"}}
    with pytest.raises(SpecError) as info:
        spec_from_dict(one)
    assert info.value.field == "discretization.scheme"


def test_the_basis_resolves_every_direction_and_stays_orthonormal():
    """ā = a + λmax on the null space of a (diag(0, 1) ↦ I): the Dirichlet eigenbasis of −½Δ on the
    disk, whose first eigenvalues are ½ j²/R² (Bessel zeros j₀₁ = 2.404826, j₁₁ = 3.831706)."""
    model = compile_model(spec_from_dict(_doc(discretization={"basis": 200})))
    assert np.array_equal(model.basis_diffusion, np.eye(2))
    offline = precompute(model)
    phi, w = offline.basis, offline.weights
    assert np.abs(phi.T @ (w[:, None] * phi) - np.eye(200)).max() < 1e-10
    exact = 0.5 * np.array([2.404826, 3.831706, 3.831706]) ** 2 / 6.0 ** 2
    assert np.abs(offline.eigenvalues[:3] / exact - 1).max() < 0.02


def test_the_streamline_parameter_has_its_limits():
    """τ = h ξ(Pe)/(2|b|), ξ = coth Pe − 1/Pe: no diffusion along b gives h/(2|b|); strong
    diffusion ε along b gives h²/(12ε) (ξ ≈ Pe/3); no drift gives 0."""
    h = np.array([0.1, 0.1, 0.1, 0.1])
    b = np.array([[2.0, 0.0, 1e-3, 0.0], [0.0, 2.0, 0.0, 0.0]])
    tau = streamline_tau(b, h, NOISE)
    assert tau[0] == pytest.approx(0.1 / 4)  # along p: no diffusion
    pe = 2.0 * 0.1 / (2 * 0.5)  # along v: ε = ½
    assert tau[1] == pytest.approx(0.1 * (1 / np.tanh(pe) - 1 / pe) / 4, rel=1e-12)
    assert tau[2] == pytest.approx(0.1 / (2e-3))  # along p, however slow
    assert tau[3] == 0.0
    slow = streamline_tau(np.array([[0.0], [1e-4]]), np.array([0.1]), NOISE)
    assert slow[0] == pytest.approx(0.1 ** 2 / (12 * 0.5), rel=1e-6)


# -- prediction against the exact moments ----------------------------------------------------------
@pytest.fixture(scope="module")
def predicted():
    """The prior N((−2, 1), 0.2 I) moved over t = 1 (100 steps without data) by each scheme."""
    out = {}
    for scheme in ("galerkin", "supg"):
        model = compile_model(spec_from_dict(_doc(discretization={"scheme": scheme})))
        flt = build(model, precompute(model))
        state, _ = flt.run_arrays(flt.initial_state(), np.full((100, 1), np.nan))
        sigma, w = flt.nodal_density(state), flt.weights
        mass = w @ sigma
        mean = (w * sigma) @ flt.nodes / mass
        d = flt.nodes - mean
        out[scheme] = (mean, (w * sigma * d.T) @ d / mass, sigma.min() / sigma.max())
    return out


@pytest.mark.slow
def test_supg_predicts_the_exact_moments_and_rings_less_than_plain_galerkin(predicted):
    """Measured (N = 600, Q = 1250): SUPG mean 2.0e-3 and covariance 1.5% from exact, min/max of the
    density −4e-3; plain Galerkin (lumped) 8e-4 and 0.8%, but its density rings to −2.2e-2 of its
    peak along the drift (bench/results/psd.md)."""
    mean, cov = _exact_moments(np.array([-2.0, 1.0]), 0.2 * np.eye(2), 1.0)
    m, c, ring = predicted["supg"]
    assert np.abs(m - mean).max() < 4e-3
    assert np.abs(np.diag(c) / np.diag(cov) - 1).max() < 0.03
    _, _, galerkin_ring = predicted["galerkin"]
    assert galerkin_ring < -1e-2  # plain Galerkin rings ...
    assert ring > galerkin_ring / 3  # ... at least three times deeper than SUPG


# -- filtering against Kalman, with a ball that follows ------------------------------------------
TRACK = _doc(initial={"kind": "gaussian", "mean": [0.0, 0.0], "cov": [[1.0, 0.0], [0.0, 1.0]]},
             domain={"radius": 8.0, "follow": True}, discretization={"basis": 1000})


@pytest.fixture(scope="module")
def tracking():
    model = compile_model(spec_from_dict(TRACK))
    return model, precompute(model)


def _against_kalman(model, flt, increments):
    """The filter's run and the exact Kalman filter's of the sampled model: (result, exact, the largest
    coordinate gap of the means per step, the relative variance errors per step and coordinate)."""
    _, result = flt.run_arrays(flt.initial_state(), increments)
    kalman = KalmanBucyFilter(model, kind="discrete")
    _, exact = kalman.run_arrays(kalman.initial_state(), increments)
    gap = np.abs(result.mean - exact.mean).max(axis=1)
    var = np.abs(np.diagonal(result.cov, axis1=1, axis2=2) / np.diagonal(exact.cov, axis1=1, axis2=2) - 1)
    return result, exact, gap, var


@pytest.mark.slow
def test_constant_velocity_tracking_follows_the_target_and_stays_near_kalman(tracking):
    """Over t = 0..50 the target travels 50 units (six radii).  f = (v, −0.2v) is affine, so the ball
    rides the frame of ċ = (c_v, −0.2c_v) and moves along p and v (solver/engine/frame.py).  Measured: mean
    gap median 3.3e-3, max 2.0e-2, variance within 4.2% (with p alone moving, before the frame: 5.0e-3,
    3.8e-2 where |v̂| = 3.5 put the tail at the ball's edge along v, 6.9%).  On a round ball the gap
    halves as N doubles: basis 2000 gives a median of 1.7e-3, basis 4000 9.5e-4 (max 5.2e-3;
    bench/results/cv-basis.md).  The issue's 1e-3 at every step is met on the posterior's ellipse
    (``[domain] shape``, tests/solver/offline/test_shape.py)."""
    model, offline = tracking
    flt = build(model, offline)
    assert isinstance(flt, FollowingFilter) and flt.directions == (0, 1)
    sim = simulate(model, 5000, np.random.default_rng(1))
    assert np.ptp(sim.states[:, 0]) > 6 * model.radius
    result, exact, gap, var = _against_kalman(model, flt, sim.increments)
    print(f"CV tracking: {int(result.recentred.sum())} moves, gap median {np.median(gap):.2e} "
          f"max {gap.max():.2e}, variance {var.max():.2e}, "
          f"loglik gap {abs(result.loglik[-1] - exact.loglik[-1]):.2e}")
    assert not result.degenerate.any()
    assert result.recentred.sum() > 20
    assert np.median(gap) < 5e-3 and gap.max() < 0.03 and var.max() < 0.06
    assert abs(result.loglik[-1] - exact.loglik[-1]) < 0.05


@pytest.mark.slow
def test_the_bubble_element_with_the_consistent_mass_tracks_closer_to_kalman_at_the_same_cost():
    """The path above on P2 + bubble with the consistent mass (``scheme = "consistent"``), radius 6.5,
    N = 1000 (Q = 2129: the cost per observation of P1's Q = 2093).  Measured: gap median 3.8e-4, 90%
    1.7e-3, max 1.3e-2, variance within 3.6%; P1 SUPG at this radius: 2.1e-3, 3.7e-3, 2.6e-2, 4.6%
    (bench/results/cv-basis.md).  The worst steps are a stretch near t = 42.3 where σ has ~1% of
    negative, oscillating mass beyond 5 standard deviations (the core's moments are within 1e-3)."""
    model = compile_model(spec_from_dict(modified(TRACK, domain={"radius": 6.5, "follow": True},
                                                  discretization={"basis": 1000, "element": "bubble",
                                                                  "scheme": "consistent"})))
    flt = build(model, precompute(model))
    path = simulate(model, 5000, np.random.default_rng(1))
    result, _, gap, var = _against_kalman(model, flt, path.increments)
    print(f"CV on the bubble, consistent mass: gap median {np.median(gap):.2e} "
          f"90% {np.quantile(gap, 0.9):.2e} max {gap.max():.2e}, variance {var.max():.2e}")
    assert not result.degenerate.any() and result.recentred.sum() > 20
    assert np.median(gap) < 1e-3 and np.quantile(gap, 0.9) < 3e-3 and gap.max() < 0.02 and var.max() < 0.05


def _grid_reference(model, increments, p_box, cells_p, v_box, cells_v):
    """The fine-grid filter of the module docstring: means (K, 2)."""
    dt = model.dt
    p = np.linspace(p_box[0], p_box[1], cells_p, endpoint=False)
    v = np.linspace(v_box[0], v_box[1], cells_v)
    dv = v[1] - v[0]
    P, V = np.meshgrid(p, v)  # (cells_v, cells_p)
    X = np.stack([P.ravel(), V.ravel()], axis=1)
    density = np.exp(model.log_prior(X)).reshape(P.shape)
    k = 2 * np.pi * np.fft.fftfreq(cells_p, d=p[1] - p[0])
    half_shift = np.exp(-1j * np.outer(v, k) * dt / 2)  # p ↦ p + v dt/2: û(k) e^{−ikv dt/2}
    decay, var = np.exp(-0.2 * dt), (1 - np.exp(-0.4 * dt)) / 0.4  # OU over dt
    ou = np.exp(-0.5 * (v[:, None] - decay * v[None, :]) ** 2 / var) / np.sqrt(2 * np.pi * var) * dv
    h = model.h(X)[:, 0].reshape(P.shape)
    r_inv = float(model.R_inv[0, 0])
    means = np.empty((len(increments), 2))
    for i, dy in enumerate(increments[:, 0]):
        density = np.fft.ifft(np.fft.fft(density, axis=1) * half_shift, axis=1).real
        density = ou @ density
        density = np.fft.ifft(np.fft.fft(density, axis=1) * half_shift, axis=1).real
        log_e = h * r_inv * dy - 0.5 * h * h * r_inv * dt
        density *= np.exp(log_e - log_e.max())
        density /= density.sum()
        means[i] = density.sum(axis=0) @ p, density.sum(axis=1) @ v
    return means


@pytest.mark.slow
def test_a_nonlinear_sensor_against_a_fine_grid_reference():
    """h = atan(p/5) (a bearing-like sensor) with R = 0.01: the target drifts from p = −8, v ≈ 3 over
    t = 0..8 (17 units, twice the radius 8 of the following ball); the engine's mean against the
    fine-grid filter (p: 768 Fourier points on [−24, 24), v: 161 points on [−8, 8]).  Measured: gap
    median 5.9e-3, max 3.6e-2 (at the end, where p̂ = 10.7 and the flattening sensor has let the
    posterior widen to sd 1.7 with a long tail towards +p)."""
    doc = _doc(observation=["atan(p/5)"], observation_noise=[[0.01]],
               initial={"kind": "gaussian", "mean": [-8.0, 3.0], "cov": [[0.25, 0.0], [0.0, 0.25]]},
               domain={"radius": 8.0, "follow": True}, discretization={"basis": 1000})
    model = compile_model(spec_from_dict(doc))
    flt = build(model, precompute(model))
    sim = simulate(model, 800, np.random.default_rng(5))
    assert sim.states[-1, 0] - sim.states[0, 0] > 2 * model.radius
    _, result = flt.run_arrays(flt.initial_state(), sim.increments)
    reference = _grid_reference(model, sim.increments, (-24.0, 24.0), 768, (-8.0, 8.0), 161)
    assert np.abs(reference[0] - result.mean[0]).max() < 1e-4  # the same first step
    gap = np.abs(result.mean - reference).max(axis=1)
    print(f"atan sensor: {int(result.recentred.sum())} moves, gap median {np.median(gap):.2e} "
          f"max {gap.max():.2e}")
    assert not result.degenerate.any() and result.recentred.sum() >= 1
    # the ball rode the frame of ċ = (c_v, −0.2c_v) (engine/frame.py) with the target, and moved onto it
    assert result.center[-1, 0] - result.center[0, 0] > 2 * model.radius
    assert np.median(gap) < 0.01 and gap.max() < 0.05


# -- the seams ------------------------------------------------------------------------------------
@pytest.mark.slow
def test_precompute_stores_and_reopens_a_semi_definite_model(tmp_path):
    """Once refused by the engine ("must be positive definite"); the stored file has the stabilised
    generator, so irregular times work too."""
    spec = spec_from_dict(_doc(discretization={"basis": 150}))
    model_id = yauyau.precompute(spec, tmp_path)
    flt = yauyau.open_filter(tmp_path, model_id)
    model = compile_model(spec)
    sim = simulate(model, 50, np.random.default_rng(0))
    estimates = flt.run(sim.increments).estimates()
    assert len(estimates) == 50 and np.all(np.isfinite(estimates[-1].mean))
    times = np.cumsum(np.full(20, 0.01))
    times[10:] += 0.035  # a gap of 4.5 dt
    again = yauyau.open_filter(tmp_path, model_id)
    irregular = again.run(sim.increments[:20], times=times).estimates()
    assert np.all(np.isfinite(irregular[-1].mean)) and not irregular[-1].degenerate


# -- the method chosen when the spec names none ----------------------------------------------------
@pytest.mark.slow
def test_the_analysis_of_a_semi_definite_diffusion_says_eta_is_not_defined():
    """η = fᵀa⁻¹f + div f + hᵀR⁻¹h needs a⁻¹: with a = diag(0, 1) it is not defined, so (C3) fails and the
    Yau–Hu filter is not offered.  The model is linear with a Gaussian prior, and the Kalman–Bucy filter
    needs no a⁻¹ (its Riccati equation takes a as it is): it is recommended.  (Before, SymPy's a.inv()
    raised, and a spec without `method` crashed precompute with a traceback.)"""
    from yauyau.solver.analysis import analyze

    doc = {k: v for k, v in CV.items() if k != "method"}
    report = analyze(compile_model(spec_from_dict(doc)))
    eta_quadratic = report.conditions["eta_quadratic"]
    assert eta_quadratic.holds is False and "singular" in eta_quadratic.detail
    assert report.conditions["linear"].holds is True and "singular" in report.eta
    assert report.method == "kalman-bucy"
    nonlinear = analyze(compile_model(spec_from_dict(modified(doc, observation=["atan(p/5)"]))))
    assert nonlinear.conditions["eta_quadratic"].holds is False and nonlinear.method == "yau-yau"


@pytest.mark.slow
def test_a_semi_definite_spec_without_method_precomputes_from_the_cli(tmp_path, capsys):
    """`yauyau precompute` on the constant-velocity spec with no `method`: the analysis chooses, exit 0."""
    from yauyau.service.cli import main

    doc = {k: v for k, v in CV.items() if k != "method"}
    doc = modified(doc, observation=["atan(p/5)"], discretization={"basis": 60})
    spec_file = tmp_path / "cv.json"
    spec_file.write_text(json.dumps(doc))
    capsys.readouterr()
    assert main(["precompute", str(spec_file), "--store", str(tmp_path / "store"), "--quiet"]) == 0
    flt = yauyau.open_filter(tmp_path / "store", capsys.readouterr().out.strip())
    result = flt.run(simulate(compile_model(spec_from_dict(doc)), 30, np.random.default_rng(0)).increments)
    assert np.all(np.isfinite(result.mean)) and not result.degenerate.any()
