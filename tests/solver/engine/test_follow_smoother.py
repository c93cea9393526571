"""The smoother on a ball that follows the state (solver/engine/follow_smoother.py), against independent truth
written here: Rauch–Tung–Striebel of the sampled random walk with a trend (x_k = x_(k−1) + bτ + N(0, aτ),
dy_k = x_k τ + N(0, Rτ): the engine's own time discretisation, exact for this model at any gap), whose
state travels several radii beyond the ball it started on; RTS of the exactly sampled linear growth
f = 0.1x + 0.2 (a moving frame); and, for an atlas (a drift that is not shift-invariant), a
forward–backward point-mass smoother on a fine grid (finite volumes, the dense exp(dt L) and its
transpose).

Measured gaps (fixed seeds) in each test's docstring; bounds 0.02 in the mean and 5% in the variance.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import scipy.linalg as sla
from helpers.atlas import SIN
from helpers.irregular_refs import GridReference
from helpers.linear_rts import TREND, rts_linear, rts_trend
from scipy.special import ndtri
from yauyau.solver import compile_model, spec_from_dict
from yauyau.solver.engine.filter import build
from yauyau.solver.engine.follow import FollowingFilter
from yauyau.solver.offline.pipeline import precompute
from yauyau.solver.simulate import simulate
from yauyau.solver.smoothed_summaries import smooth_with_quantiles

K = 2000  # t in [0, 20]: the state travels ~20 units, beyond three radii of the ball


@pytest.fixture(scope="module")
def trend():
    model = compile_model(spec_from_dict(TREND))
    return model, build(model, precompute(model))


def _gaps(result, ms, Ps):
    return np.abs(result.mean[:, 0] - ms).max(), np.abs(result.cov[:, 0, 0] / Ps - 1).max()


def test_a_travelling_state_is_smoothed_over_the_balls_it_went_through(trend):
    """2000 regular rows (the moves made inside the filter's loop): measured mean 1.5e-5, variance 4.3e-5
    relative, against RTS; the smoother is not the filter (the filtered mean is 1.7 away somewhere)."""
    model, flt = trend
    assert isinstance(flt, FollowingFilter) and flt.moves_in_loop
    sim = simulate(model, K, np.random.default_rng(3))
    assert sim.states[-1, 0] - sim.states[0, 0] > 3 * 6.0
    state = flt.initial_state()
    new_state, result = flt.smooth_arrays(state, sim.increments)
    mf, _, ms, Ps = rts_trend(sim.increments[:, 0], np.full(K, 0.01))
    mean_gap, var_gap = _gaps(result, ms, Ps)
    print(f"follow: {int(result.recentred.sum())} moves, mean {mean_gap:.2e}, var {var_gap:.2e}")
    assert mean_gap < 0.02 and var_gap < 0.05
    assert result.recentred.sum() >= 10 and np.abs(mf - ms).max() > 0.5
    # the result is the filter's (centres, moves, log-likelihood) with the smoothed moments
    filtered_state, filtered = flt.run_arrays(state, sim.increments)
    np.testing.assert_array_equal(result.center, filtered.center)
    np.testing.assert_array_equal(result.recentred, filtered.recentred)
    np.testing.assert_array_equal(result.loglik, filtered.loglik)
    assert abs(result.mean[-1, 0] - filtered.mean[-1, 0]) < 1e-9  # at the last row, the filter
    np.testing.assert_array_equal(new_state.center, filtered_state.center)
    # each ball's rows in checkpointed blocks of 7: the same smoother
    _, blocked = flt.smooth_arrays(state, sim.increments, block=7)
    assert np.abs(blocked.mean - result.mean).max() < 1e-9


def test_irregular_times_with_missing_rows(trend):
    """Gaps of 0.5 to 1.5 dt, 5% of the rows missing (the moves made inside the filter's loop, in the
    modal flow's coordinates): measured mean 2.8e-5, variance 4.1e-5 relative, against RTS over the same
    gaps."""
    _, flt = trend
    rng = np.random.default_rng(5)
    taus = 0.01 * rng.uniform(0.5, 1.5, K)
    x, dy = rng.normal(0.0, 1.0), np.empty(K)
    for k, tau in enumerate(taus):
        x += tau + rng.normal(0.0, math.sqrt(tau))
        dy[k] = x * tau + rng.normal(0.0, math.sqrt(tau))
    dy[rng.random(K) < 0.05] = np.nan
    _, result = flt.smooth_arrays(flt.initial_state(), dy[:, None], np.cumsum(taus))
    _, _, ms, Ps = rts_trend(dy, taus)
    mean_gap, var_gap = _gaps(result, ms, Ps)
    print(f"irregular: {int(result.recentred.sum())} moves, mean {mean_gap:.2e}, var {var_gap:.2e}")
    assert result.recentred.sum() >= 10 and mean_gap < 0.02 and var_gap < 0.05


def test_quantiles_of_the_smoothed_density_on_each_ball(trend):
    """The smoothed densities handed over ball by ball (with their centres) give the Gaussian smoother's
    quantiles m + √P Φ⁻¹(p): measured 0.021 (the 5% quantile of a row just before a move).  The gap is the
    projection of the nodal σ_k ⊙ β_k onto the 48 basis functions (how smoothed_states hands a density
    over): up to 2.4% in L1 on the rows before a move, where the density leans 0.4 R off the centre and β
    carries the rows after the move; the moments (read at the nodes) are within 1.5e-5.  The filter's own
    quantiles on the same ball are within 2.3e-4."""
    model, flt = trend
    sim = simulate(model, 800, np.random.default_rng(4))
    probs = [0.05, 0.5, 0.95]
    _, result, table = smooth_with_quantiles(flt, flt.initial_state(), sim.increments, None, probs)
    _, _, ms, Ps = rts_trend(sim.increments[:, 0], np.full(800, 0.01))
    exact = ms[:, None] + np.sqrt(Ps)[:, None] * ndtri(np.array(probs))[None, :]
    gap = np.abs(table[:, 0, :] - exact).max()
    print(f"quantiles: {int(result.recentred.sum())} moves, gap {gap:.2e}")
    assert result.recentred.sum() >= 3 and gap < 0.03


def _grid_smoother(model, dy, cells=800, center=7.5, radius=17.5):
    """Forward–backward point-mass smoother of the sin-drift model on [center ± radius] (helpers/atlas.py's
    grid, finite volumes): p_k ∝ ℓ_k ⊙ E p_(k−1), β_(k−1) = Eᵀ(ℓ_k ⊙ β_k), E = exp(dt L) dense; ℓ_k the
    continuous-increment likelihood exp(h dy − h² dt / 2).  (smoothed mean, smoothed variance)."""
    doc = json.loads(json.dumps(SIN))
    doc["domain"] = {"radius": radius, "center": [center]}
    grid = GridReference(compile_model(spec_from_dict(doc)), cells=cells, method="expm_multiply")
    step = sla.expm(model.dt * grid.L.toarray())
    x, hx = grid.points[:, 0], grid.hx[:, 0]
    p, filtered, likes = grid.w0.copy(), np.empty((len(dy), len(x))), np.empty((len(dy), len(x)))
    for k, v in enumerate(dy):
        ell = hx * v - 0.5 * hx * hx * model.dt
        likes[k] = np.exp(ell - ell.max())
        p = likes[k] * (step @ p)
        filtered[k] = p = p / p.sum()
    beta, mean, var = np.ones(len(x)), np.empty(len(dy)), np.empty(len(dy))
    for k in range(len(dy) - 1, -1, -1):
        s = filtered[k] * beta
        s /= s.sum()
        mean[k] = s @ x
        var[k] = s @ (x * x) - mean[k] ** 2
        beta = step.T @ (likes[k] * beta)
        beta /= beta.max()
    return mean, var


def test_an_atlas_is_smoothed_over_its_centres_propagators():
    """f = 0.8 + 0.3 sin x (an atlas of propagators, region [-5, 30]), 1000 rows travelling ~10 units:
    measured mean 3.1e-4, variance 6.1e-4 relative, against this 800-cell grid; against 2400 cells on
    [-12.5, 37.5], 6e-5 and 1.4e-4 (the rest is the coarser grid's own error)."""
    doc = json.loads(json.dumps(SIN))
    doc["domain"]["region"] = [[-5.0, 30.0]]
    model = compile_model(spec_from_dict(doc))
    flt = build(model, precompute(model))
    assert isinstance(flt, FollowingFilter) and flt.atlas is not None
    sim = simulate(model, 1000, np.random.default_rng(1))
    assert sim.states[-1, 0] > 6.0
    _, result = flt.smooth_arrays(flt.initial_state(), sim.increments)
    mean, var = _grid_smoother(model, sim.increments[:, 0])
    mean_gap, var_gap = np.abs(result.mean[:, 0] - mean).max(), np.abs(result.cov[:, 0, 0] / var - 1).max()
    print(f"atlas: {int(result.recentred.sum())} moves, mean {mean_gap:.2e}, var {var_gap:.2e}")
    assert result.recentred.sum() >= 10 and mean_gap < 0.02 and var_gap < 0.05


GROWTH = {**TREND, "drift": ["0.1*x + 0.2"], "initial": {"kind": "gaussian", "mean": [2.0], "cov": [[0.5]]},
          "discretization": {"dt": 0.01, "basis": 120}}


def test_a_moving_frame_is_smoothed_over_its_moves():
    """f = 0.1x + 0.2 (affine: the ball rides the frame ċ = 0.1c + 0.2, solver/engine/frame.py, and moves
    when the posterior strays), 3000 rows from x = 2 to ~140, against RTS of the exactly sampled linear
    model x_k = φx_(k−1) + (φ − 1)b/a + N(0, (φ² − 1)/2a), φ = e^{a dt}: measured mean 7.0e-6, variance
    3.2e-5 relative; quantiles 1.9e-3; checkpointed blocks of 7 the same smoother."""
    model = compile_model(spec_from_dict(GROWTH))
    flt = build(model, precompute(model))
    assert isinstance(flt, FollowingFilter) and flt.frame is not None
    sim = simulate(model, 3000, np.random.default_rng(4))
    dt, a, b = 0.01, 0.1, 0.2
    phi = math.exp(a * dt)
    shift, q = (phi - 1) * b / a, (phi * phi - 1) / (2 * a)
    mf, _, ms, Ps = rts_linear(sim.increments[:, 0], np.full(3000, dt), 2.0, 0.5, phi, shift, q)
    probs = [0.05, 0.5, 0.95]
    _, result, table = smooth_with_quantiles(flt, flt.initial_state(), sim.increments, None, probs)
    mean_gap, var_gap = _gaps(result, ms, Ps)
    exact = ms[:, None] + np.sqrt(Ps)[:, None] * ndtri(np.array(probs))[None, :]
    q_gap = np.abs(table[:, 0, :] - exact).max()
    print(f"frame: {int(result.recentred.sum())} moves, mean {mean_gap:.2e}, var {var_gap:.2e}, "
          f"quantiles {q_gap:.2e}")
    assert result.recentred.sum() >= 10 and np.abs(mf - ms).max() > 0.5
    assert mean_gap < 0.02 and var_gap < 0.05 and q_gap < 0.02
    _, blocked = flt.smooth_arrays(flt.initial_state(), sim.increments, block=7)
    assert np.abs(blocked.mean - result.mean).max() < 1e-9
