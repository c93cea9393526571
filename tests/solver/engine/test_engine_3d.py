"""The general engine end to end in 3-D (solver.offline.precompute + solver.engine.YauYauFilter).

Reference: the exact discrete Kalman filter of the sampled linear model (solver.reference.kalman,
Van Loan over dt, update at τ_k), the same time discretisation as the engine, so the gaps are the
engine's spatial error only.  Model: a damped rotation in (x1, x2) plus decay in x3, h = (x1, x3),
a = R = I, prior N(0, ½I), B_R with R = 3.5 (posterior std ≈ 0.65: 5σ to the boundary).

Why these tolerances (measured on 300 simulated steps, dt = 0.02, three seeds):
* 3-D meshes are refinements of scikit-fem's ball; refinement 3 has Q = 575 P1 nodes (spacing
  ≈ 0.44 ≈ 0.7σ), refinement 4 has Q = 4991 and takes ~35–50 s to precompute on the loaded 2-core
  machine — too slow here.  Refinement 2 (Q = 63) goes degenerate within ~35 steps.
* With refinement 3 the basis must span (almost) the whole P1 space: N = 200 lets the variance of
  even an unobserved coordinate collapse (0.5 → 0.04 in 30 prediction steps, then degenerate);
  N = 500–575 keeps it.  So N = 575, the full space.
* Gaps, refinement 3, N = 575: mean rms 0.010–0.015, mean max 0.068–0.072, covariance max
  0.10–0.125, log-likelihood max 0.07–0.10.  Convergence (dt = 0.05, seed 5): mean rms 0.026 at
  refinement 3 (N = 500) → 0.008 at refinement 4 (N = 500), max 0.21 → 0.066, a ratio ≈ 3.2 for
  spacing halved: the O(h²) of P1, so the gaps are discretisation error, not a wrong formula (a
  misprint in exp(hᵀR⁻¹Δy − ½hᵀR⁻¹h dt) moves the mean by O(1), see tests/solver/engine/test_engine.py).
"""

from __future__ import annotations

import numpy as np
import pytest
from yauyau.solver import compile_model, spec_from_dict
from yauyau.solver.engine.filter import YauYauFilter, build
from yauyau.solver.exact.kalman_bucy import KalmanBucyFilter
from yauyau.solver.offline.pipeline import precompute
from yauyau.solver.reference.kalman import DiscreteKalmanFilter
from yauyau.solver.simulate import simulate

STEPS = 300
FOLLOWING = {"radius": 3.5, "follow": True}


@pytest.fixture(scope="module")
def linear_3d():
    doc = {"name": "linear-3d", "state": ["x1", "x2", "x3"],
           "drift": ["-x1 + 0.5*x2", "-0.5*x1 - x2", "-x3"], "observation": ["x1", "x3"],
           "initial": {"kind": "gaussian", "mean": [0.0, 0.0, 0.0], "cov": (0.5 * np.eye(3)).tolist()},
           "domain": {"radius": 3.5},
           "discretization": {"dt": 0.02, "basis": 575, "mesh": 3, "order": 1}}
    model = compile_model(spec_from_dict(doc))
    offline = precompute(model)
    assert offline.nodes.shape == (575, 3)
    return model, offline


def _stack(estimates, name):
    return np.array([getattr(e, name) for e in estimates])


def _gaps(model, offline, increments):
    yy = YauYauFilter(model, offline)
    _, ours = yy.run(yy.initial_state(), increments)
    kalman = DiscreteKalmanFilter(model)
    _, ref = kalman.run(kalman.initial_state(), increments)
    assert not any(e.degenerate for e in ours)
    return ours, ref


@pytest.mark.slow
def test_3d_linear_model_matches_discrete_kalman(linear_3d):
    model, offline = linear_3d
    increments = simulate(model, STEPS, np.random.default_rng(5)).increments
    ours, ref = _gaps(model, offline, increments)
    mean_gap = _stack(ours, "mean") - _stack(ref, "mean")
    assert np.sqrt(np.mean(mean_gap**2)) <= 0.02
    assert np.max(np.abs(mean_gap)) <= 0.1
    # the filter tracks the data: the Kalman mean moves ~10x further from the prior mean 0
    assert np.sqrt(np.mean(_stack(ref, "mean") ** 2)) > 10 * np.sqrt(np.mean(mean_gap**2))
    assert np.max(np.abs(_stack(ours, "cov") - _stack(ref, "cov"))) <= 0.16
    assert np.max(np.abs(_stack(ours, "loglik") - _stack(ref, "loglik"))) <= 0.15
    assert all(np.all(np.isfinite(e.mean)) and np.all(np.isfinite(e.cov)) for e in ours)


def test_3d_missing_rows_are_kalman_predictions(linear_3d):
    model, offline = linear_3d
    increments = simulate(model, 120, np.random.default_rng(6)).increments
    missing = [40, 41, 42, 90]
    increments[missing] = np.nan
    ours, ref = _gaps(model, offline, increments)
    mean_gap = _stack(ours, "mean") - _stack(ref, "mean")
    assert np.max(np.abs(mean_gap)) <= 0.1 and np.sqrt(np.mean(mean_gap**2)) <= 0.02
    assert np.max(np.abs(_stack(ours, "cov") - _stack(ref, "cov"))) <= 0.16
    # on a missing row the engine's own moments move as the exact linear prediction moves them:
    # mean ← Φ mean, cov ← Φ cov Φᵀ + Q (Van Loan), whatever its discretisation error before
    kalman = DiscreteKalmanFilter(model)
    for k in missing:
        mean, cov = kalman.predict(ours[k - 1].mean, ours[k - 1].cov)
        assert np.max(np.abs(ours[k].mean - mean)) <= 2e-3  # measured 1.5e-4–3.8e-4
        assert np.max(np.abs(ours[k].cov - cov)) <= 0.01  # measured 1.9e-3–2.5e-3
        assert abs(ours[k].loglik_increment) <= 1e-3  # no observation: only the boundary leak
        assert ours[k].loglik_increment == pytest.approx(ours[k].loglik - ours[k - 1].loglik, abs=1e-12)


def _against_kalman_bucy(domain, workers=1, basis=1000, **disc):
    """Issue 10 part 6's model on ``domain``, N = ``basis``, seed 5, 500 steps against the exact Kalman
    filter: (moves, mean gaps (K, 3), variance errors (K, 3), interior nodes).  ``disc``: the rest of
    ``[discretization]`` (left out: the defaults, solver/defaults.py)."""
    doc = {"name": "linear-3d-follow", "state": ["x1", "x2", "x3"], "method": "yau-yau",
           "drift": ["-x1 + 0.5*x2", "-x2", "-0.5*x3"], "observation": ["x1", "x3"],
           "initial": {"kind": "gaussian", "mean": [0.0, 0.0, 0.0], "cov": (0.5 * np.eye(3)).tolist()},
           "domain": domain, "discretization": {"dt": 0.02, "basis": basis, **disc}}
    model = compile_model(spec_from_dict(doc))
    offline = precompute(model, workers=workers)
    flt = build(model, offline)
    if domain.get("follow"):
        assert flt.frame is not None and flt.directions == (0, 1, 2)
    increments = simulate(model, 500, np.random.default_rng(5)).increments
    _, ours = flt.run_arrays(flt.initial_state(), increments)
    kalman = KalmanBucyFilter(model, kind="discrete")
    _, ref = kalman.run_arrays(kalman.initial_state(), increments)
    assert not ours.degenerate.any(), ours.reason
    gap = ours.mean - ref.mean
    var = np.abs(np.diagonal(ours.cov, axis1=1, axis2=2) / np.diagonal(ref.cov, axis1=1, axis2=2) - 1)
    moves = 0 if ours.recentred is None else int(ours.recentred.sum())
    print(f"3-D, Q = {len(offline.weights)}: {moves} moves, rms gap {np.sqrt(np.mean(gap ** 2)):.2e}, "
          f"max {np.abs(gap).max():.2e}, variance median {np.median(var):.2e} max {var.max():.2e}")
    return moves, gap, var, len(offline.weights)


@pytest.mark.slow
def test_3d_follow_rides_the_linear_frame_on_the_default_mesh():
    """Issue 10 part 6: f = (−x1 + 0.5x2, −x2, −0.5x3), h = (x1, x3), a = R = I, dt = 0.02, through the
    general engine.  Before: a fixed ball of radius 4, basis 500, P1 on its mesh of about 2N nodes
    (Q = 4991): rms mean gap 0.023 (max 0.18) and variance errors up to 67% (bench/results/3d.md).  Here a
    ball of radius 3.5 that follows the posterior in the frame of ċ = Ac (solver/engine/frame.py), N = 1000
    on the same P1 mesh.  Measured (seed 5, 500 steps, ~25 moves): rms mean gap 6.8e-3, max 2.6e-2;
    variance error median 1.6%, max 5.2% (the issue asks 5%: each P1 carry blurs it by ~2.5 points; the
    next test's P2 + bubbles element, the default, meets it)."""
    moves, gap, var, _ = _against_kalman_bucy(FOLLOWING, element="lagrange")
    assert moves > 5
    assert np.sqrt(np.mean(gap ** 2)) <= 0.01 and np.abs(gap).max() <= 0.04
    assert np.median(var) <= 0.025 and var.max() <= 0.07


@pytest.mark.slow
def test_a_plain_3d_spec_on_a_following_ball_meets_the_issue_targets():
    """Issue 10 part 6 at its targets, and issue 36's plain spec: the model of the test above with
    ``[discretization]`` holding only dt and basis (600).  The defaults (solver/defaults.py) make it
    P2 + bubbles (the 15-node mass-lumped tetrahedron, solver/offline/fem.py) on scikit-fem's ball refined
    three times (Q = 17023, a Lanczos basis), radius 3.5, following in the frame of ċ = Ac; a move
    interpolates exactly to quadratics (P1: to linear functions).  Measured (seeds 5 and 6, 500 steps
    each, two local workers): rms mean gap 3.3e-3 and 4.3e-3, max 2.1e-2 and 2.3e-2, variance error
    median 1.1–1.2%, max 4.1% and 4.0%; precompute 3.3 min and 0.8 GB (N = 1000: 3.0e-3 and 4.4e-3,
    variance max 3.9% and 4.4%, 6 min; P1 meets the targets only on the ball refined five times, after
    ~25 min and 3.5 GB: bench/results/3d.md; P2 + bubbles refined twice, 6.8e-3 and 9.7%:
    bench/results/default-3d.md)."""
    moves, gap, var, nodes = _against_kalman_bucy(FOLLOWING, workers=2, basis=600)
    assert nodes == 17023 and moves > 5
    assert np.sqrt(np.mean(gap ** 2)) <= 0.005 and np.abs(gap).max() <= 0.03
    assert np.median(var) <= 0.02 and var.max() <= 0.05


@pytest.mark.slow
def test_the_plain_3d_spec_of_issue_36_on_a_fixed_ball():
    """Issue 36's spec written with the defaults: a fixed ball of radius 4, basis 500, nothing else.  The
    default is now P2 + bubbles on the ball of about 2N nodes (refined twice, Q = 2047).  Measured (seed 5,
    500 steps): rms mean gap 5.9e-3, max 3.1e-2, variance error median 2.8%, max 14% (seeds 5 and 6: 6.6e-3
    and 21%); P1 on 4991 nodes, the old default: 2.6e-2, 0.18, 5.3%, 67% (bench/results/default-3d.md).  On
    a fixed ball the basis of 500 is what limits (P1 with basis 1500: 4.4e-3 and 7.7%, bench/results/3d.md);
    the issue's targets need the following ball above."""
    _, gap, var, nodes = _against_kalman_bucy({"radius": 4.0}, basis=500)
    assert nodes == 2047
    assert np.sqrt(np.mean(gap ** 2)) <= 0.008 and np.abs(gap).max() <= 0.05
    assert np.median(var) <= 0.04 and var.max() <= 0.2
