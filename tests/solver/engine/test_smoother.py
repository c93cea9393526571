"""The engine's fixed-interval smoother (solver/engine/smoother.py) against independent references
written here: Rauch–Tung–Striebel on the exactly sampled OU model, and a forward–backward point-mass
smoother on a fine grid for a bimodal sensor h = x²/2 (transition by expm_multiply of the
finite-difference generator and of its transpose).

Measured gaps (fixed seeds): in each test's docstring.  About 13 s of CPU for the file.
"""

from __future__ import annotations

import math
import tomllib

import numpy as np
import pytest
from helpers import EXAMPLES
from helpers.smoothing_refs import (
    DT,
    THETA,
    A,
    R,
    point_mass_smoother,
    rts_sampled,
    sample_ou,
    simulate_bimodal,
)
from yauyau.solver import compile_model, spec_from_dict
from yauyau.solver.engine.filter import YauYauFilter
from yauyau.solver.errors import InputError
from yauyau.solver.offline.pipeline import precompute


@pytest.fixture(scope="module")
def ou_engine():
    doc = tomllib.loads((EXAMPLES / "ou.toml").read_text())
    doc["diffusion"] = [[A]]
    doc["observation_noise"] = [[R]]
    doc["domain"]["radius"] = 6.0
    doc["discretization"]["basis"] = 64
    model = compile_model(spec_from_dict(doc))
    return YauYauFilter(model, precompute(model))


def test_ou_smoother_matches_rts(ou_engine):
    """1000 regular rows: smoothed mean within 0.01 and variance within 3% of RTS on the sampled model
    (measured: mean 1.5e-5, variance 2.2e-5 relative)."""
    _, dy = sample_ou(1000, seed=3)
    state = ou_engine.initial_state()
    new_state, result = ou_engine.smooth_arrays(state, dy[:, None])
    mf, Pf, ms, Ps = rts_sampled(dy, 1.0, 0.5)
    mean_gap = np.abs(result.mean[:, 0] - ms).max()
    var_gap = np.abs(result.cov[:, 0, 0] / Ps - 1).max()
    print(f"smoothed: mean {mean_gap:.2e}, var {var_gap:.2e}")
    assert mean_gap < 0.01 and var_gap < 0.03
    assert np.abs(Ps / Pf - 1).max() > 0.2  # the smoother is not the filter here
    # checkpointed blocks of 7 rows (the default is 256 here): the same smoother
    _, blocked = ou_engine.smooth_arrays(state, dy[:, None], block=7)
    assert np.abs(blocked.mean[:, 0] - ms).max() < 0.01 and np.abs(blocked.cov[:, 0, 0] / Ps - 1).max() < 0.03
    assert np.abs(blocked.mean - result.mean).max() < 1e-10
    # at the last row the smoother is the filter; the state after it is the filter's
    _, filtered = ou_engine.run_arrays(state, dy[:, None])
    assert abs(result.mean[-1, 0] - filtered.mean[-1, 0]) < 1e-12
    assert new_state.step == 1000


@pytest.mark.parametrize("block", [None, 13])
def test_ou_smoother_missing_and_irregular(ou_engine, block):
    """Irregular gaps (0.5 to 1.5 dt) with 5% missing rows, against RTS over the same gaps
    (measured: mean 6.7e-6, variance 2.1e-5 relative)."""
    rng = np.random.default_rng(5)
    K = 400
    taus = DT * rng.uniform(0.5, 1.5, K)
    phi_q = [(math.exp(-THETA * t), A * (1 - math.exp(-2 * THETA * t)) / (2 * THETA)) for t in taus]
    x, dy = rng.normal(1.0, math.sqrt(0.5)), np.empty(K)
    for k, (phi, q) in enumerate(phi_q):
        x = phi * x + rng.normal(0, math.sqrt(q))
        dy[k] = x * taus[k] + rng.normal(0, math.sqrt(R * taus[k]))
    dy[rng.random(K) < 0.05] = np.nan
    times = np.cumsum(taus)
    _, result = ou_engine.smooth_arrays(ou_engine.initial_state(), dy[:, None], times, block=block)
    _, _, ms, Ps = rts_sampled(dy, 1.0, 0.5, taus=taus)
    mean_gap = np.abs(result.mean[:, 0] - ms).max()
    var_gap = np.abs(result.cov[:, 0, 0] / Ps - 1).max()
    print(f"irregular smoothed: mean {mean_gap:.2e}, var {var_gap:.2e}")
    assert mean_gap < 0.01 and var_gap < 0.03


def test_ou_increments_over_long_gaps_in_pieces(ou_engine):
    """Increments over gaps of 1 to 10 dt: the filter takes a gap over 2.25 dt in ⌈τ/(2dt) − ¼⌉ equal pieces
    of its gap and increment (y linear over the gap); RTS on those pieces of the sampled model, each row
    read at its last piece (measured: mean 4.2e-6, variance 1.6e-5)."""
    rng = np.random.default_rng(15)
    K = 200
    taus = DT * rng.uniform(1.0, 10.0, K)
    x, dy = rng.normal(1.0, math.sqrt(0.5)), np.empty(K)
    for k, tau in enumerate(taus):
        phi = math.exp(-THETA * tau)
        x = phi * x + rng.normal(0, math.sqrt(A * (1 - phi * phi) / (2 * THETA)))
        dy[k] = x * tau + rng.normal(0, math.sqrt(R * tau))
    dy[rng.random(K) < 0.05] = np.nan
    _, result = ou_engine.smooth_arrays(ou_engine.initial_state(), dy[:, None], np.cumsum(taus))
    count = np.where(np.isnan(dy), 1, np.maximum(1, np.ceil(taus / (2 * DT) - 0.25))).astype(int)
    assert count.max() > 1
    owner = np.repeat(np.arange(K), count)
    _, _, ms, Ps = rts_sampled(dy[owner] / count[owner], 1.0, 0.5, taus=taus[owner] / count[owner])
    last = np.cumsum(count) - 1
    mean_gap = np.abs(result.mean[:, 0] - ms[last]).max()
    var_gap = np.abs(result.cov[:, 0, 0] / Ps[last] - 1).max()
    print(f"pieces: mean {mean_gap:.2e}, var {var_gap:.2e}")
    assert mean_gap < 0.01 and var_gap < 0.03


def test_bad_rows_are_refused(ou_engine):
    with pytest.raises(InputError) as err:
        ou_engine.smooth_arrays(ou_engine.initial_state(), [[0.1], [math.inf]])
    assert "increments" in err.value.field


# -- a bimodal sensor: h = x²/2, discrete readings ---------------------------------------------------
BIMODAL = {"name": "bimodal", "state": ["x"], "drift": ["-0.5*x"], "observation": ["x**2/2"],
           "diffusion": [[1.0]], "observation_noise": [[0.1]],
           "measurement": {"kind": "discrete"},
           "initial": {"kind": "gaussian", "mean": [0.3], "cov": [[1.0]]},
           "domain": {"radius": 6.0}, "discretization": {"dt": 0.01, "basis": 128}}


@pytest.fixture(scope="module")
def bimodal_engine():
    model = compile_model(spec_from_dict(BIMODAL))
    return YauYauFilter(model, precompute(model))


def test_bimodal_smoother_regular(bimodal_engine):
    """300 readings one dt apart (the sign of x is never observed: a bimodal posterior) against the
    point-mass forward–backward smoother (measured on 400 cells: mean 3.1e-5, variance 0.10%; on 1200
    cells, 18 s of CPU for the reference: mean 3.3e-6, variance 0.009%)."""
    K = 300
    taus = np.full(K, DT)
    rows = simulate_bimodal(taus, seed=11)
    _, result = bimodal_engine.smooth_arrays(bimodal_engine.initial_state(), rows[:, None])
    fmean, mean, var = point_mass_smoother(rows, taus)
    mean_gap = np.abs(result.mean[:, 0] - mean).max()
    var_gap = np.abs(result.cov[:, 0, 0] / var - 1).max()
    print(f"bimodal regular: mean {mean_gap:.2e}, var {var_gap:.2e}, smoothing moved the mean by "
          f"{np.abs(mean - fmean).max():.2f}")
    assert np.abs(mean - fmean).max() > 0.1  # the smoother differs from the filter here
    assert mean_gap < 0.01 and var_gap < 0.03


def test_bimodal_smoother_irregular_missing(bimodal_engine):
    """200 readings at random gaps (mean 0.05), 5% missing, against the point-mass smoother
    (measured: mean 2.0e-4, variance 0.36%, the reference on 400 cells)."""
    rng = np.random.default_rng(12)
    taus = rng.exponential(0.05, 200) + 1e-3
    rows = simulate_bimodal(taus, seed=13, missing=0.05)
    assert np.isnan(rows).any()
    _, result = bimodal_engine.smooth_arrays(bimodal_engine.initial_state(), rows[:, None], np.cumsum(taus))
    fmean, mean, var = point_mass_smoother(rows, taus)
    mean_gap = np.abs(result.mean[:, 0] - mean).max()
    var_gap = np.abs(result.cov[:, 0, 0] / var - 1).max()
    print(f"bimodal irregular: mean {mean_gap:.2e}, var {var_gap:.2e}, smoothing moved the mean by "
          f"{np.abs(mean - fmean).max():.2f}")
    assert np.abs(mean - fmean).max() > 0.1
    assert mean_gap < 0.01 and var_gap < 0.03


@pytest.mark.parametrize("irregular, block", [(False, None), (False, 7), (True, 9)])
def test_fixed_lag_is_the_interval_smoother_of_the_rows_up_to_k_plus_lag(ou_engine, irregular, block):
    """Row k of the lag-L smoother (solver/engine/fixed_lag.py) equals row k of the fixed-interval smoother
    over rows 0 … k + L (1e-8), the last L rows the whole chunk's; lag 0 is the filter; irregular times
    with missing rows, blocks smaller than the chunk."""
    from yauyau.solver.engine.fixed_lag import smooth_lag_arrays
    from yauyau.solver.smoothing import smooth_lag

    _, dy = sample_ou(40, seed=4)
    rows, L = dy[:, None], 5
    times = None
    if irregular:
        rows[[3, 17, 18]] = np.nan
        times = np.cumsum(DT * np.random.default_rng(2).uniform(0.5, 1.5, 40))
    state = ou_engine.initial_state()
    after, lagged = smooth_lag_arrays(ou_engine, state, rows, times, lag=L, block=block)
    for k in (0, 7, 20, 34):
        upto = None if times is None else times[:k + L + 1]
        _, whole = ou_engine.smooth_arrays(state, rows[:k + L + 1], upto)
        assert abs(lagged.mean[k, 0] - whole.mean[k, 0]) < 1e-8
        assert abs(lagged.cov[k, 0, 0] - whole.cov[k, 0, 0]) < 1e-8
    _, whole = ou_engine.smooth_arrays(state, rows, times)
    assert np.abs(lagged.mean[-L:, 0] - whole.mean[-L:, 0]).max() < 1e-8
    filtered_state, filtered = ou_engine.run_arrays(state, rows, times)
    # (irregular rows in blocks: the modal coordinates round-trip at each block's edge, to rounding)
    assert np.abs(after.coefficients - filtered_state.coefficients).max() < 1e-12
    _, zero = smooth_lag(ou_engine, state, rows, times, lag=0)
    assert np.array_equal(zero.mean, filtered.mean)
    _, through = smooth_lag(ou_engine, state, rows, times, lag=L)  # the dispatcher takes the engine's
    assert np.abs(through.mean - lagged.mean).max() < 1e-12
    with pytest.raises(InputError) as err:
        smooth_lag(ou_engine, state, rows, lag=-1)
    assert err.value.field == "lag"


# -- 2-D: a linear model through the engine against a matrix RTS --------------------------------------
TWO_D = {"name": "linear-2d", "state": ["p", "q"], "drift": ["-p", "-0.5*q"],
         "observation": ["p + 0.5*q", "q"],
         "initial": {"kind": "gaussian", "mean": [0.3, -0.2], "cov": [[0.5, 0.0], [0.0, 0.5]]},
         "domain": {"radius": 4.0}, "discretization": {"dt": 0.02, "basis": 200, "mesh": 16}}


def rts_matrix(dy, F_diag, H, m0, P0, dt):
    """Kalman + RTS of x_k = Φx + N(0, Q) (dx = diag(F) x dt + dw), dy_k = H x_k dt + N(0, I dt) (NaN: a
    component not observed)."""
    phi = np.diag(np.exp(np.asarray(F_diag) * dt))
    Q = np.diag([(1 - math.exp(2 * f * dt)) / (-2 * f) for f in F_diag])
    K, n = len(dy), len(m0)
    mf, Pf, mp, Pp = np.empty((K, n)), np.empty((K, n, n)), np.empty((K, n)), np.empty((K, n, n))
    m, P = np.asarray(m0, float), np.asarray(P0, float)
    Hd = H * dt
    for k in range(K):
        m, P = phi @ m, phi @ P @ phi.T + Q
        mp[k], Pp[k] = m, P
        seen = ~np.isnan(dy[k])  # a partly missing row: its observed components only
        Ho = Hd[seen]
        S = Ho @ P @ Ho.T + np.eye(int(seen.sum())) * dt
        G = P @ Ho.T @ np.linalg.inv(S)
        m, P = m + G @ (dy[k][seen] - Ho @ m), P - G @ Ho @ P
        mf[k], Pf[k] = m, P
    ms, Ps = mf.copy(), Pf.copy()
    for k in range(K - 2, -1, -1):
        J = Pf[k] @ phi.T @ np.linalg.inv(Pp[k + 1])
        ms[k] = mf[k] + J @ (ms[k + 1] - mp[k + 1])
        Ps[k] = Pf[k] + J @ (Ps[k + 1] - Pp[k + 1]) @ J.T
    return ms, Ps


def test_two_dimensional_linear_model_against_rts():
    """300 rows of a 2-D linear model (the observation couples p and q; 5% of the values missing, so some
    rows partly missing): smoothed mean within 0.02 and covariance within 5% of RTS on the sampled model
    (measured: mean 7.3e-3, variances 2.5%, cross-covariance 4.5e-3; the filter itself is about 1.6e-2 and
    3.8% from the Kalman filter on this mesh: 120 basis functions on 271 nodes give 1.9e-2 and 7% smoothed,
    3.3e-2 and 7.6% filtered, the discretisation's error, not the smoother's)."""
    model = compile_model(spec_from_dict(TWO_D))
    engine = YauYauFilter(model, precompute(model))
    rng = np.random.default_rng(21)
    H, dt, K = np.array([[1.0, 0.5], [0.0, 1.0]]), 0.02, 300
    x = rng.normal([0.3, -0.2], math.sqrt(0.5))
    decay = np.exp(np.array([-1.0, -0.5]) * dt)
    q = (1 - decay**2) / np.array([2.0, 1.0])
    dy = np.empty((K, 2))
    for k in range(K):
        x = decay * x + rng.normal(0, np.sqrt(q))
        dy[k] = H @ x * dt + rng.normal(0, math.sqrt(dt), 2)
    dy[rng.random((K, 2)) < 0.05] = np.nan  # partly missing rows (and a few wholly missing)
    _, result = engine.smooth_arrays(engine.initial_state(), dy)
    ms, Ps = rts_matrix(dy, [-1.0, -0.5], H, [0.3, -0.2], 0.5 * np.eye(2), dt)
    mean_gap = np.abs(result.mean - ms).max()
    cov_gap = max(np.abs(result.cov[:, i, i] / Ps[:, i, i] - 1).max() for i in range(2))
    cross_gap = np.abs(result.cov[:, 0, 1] - Ps[:, 0, 1]).max() / np.sqrt(Ps[:, 0, 0] * Ps[:, 1, 1]).min()
    print(f"2-D: mean {mean_gap:.2e}, variances {cov_gap:.2e}, cross-covariance {cross_gap:.2e}")
    assert mean_gap < 0.02 and cov_gap < 0.05 and cross_gap < 0.05


def test_gated_row_only_predicts_in_the_smoother_too(ou_engine):
    """An outlier the gate rejects is a prediction-only row for the backward pass as well: the smoother
    equals RTS with that row missing (measured: mean 3.4e-6, variance 1.7e-5)."""
    _, dy = sample_ou(300, seed=9)
    dy[150] += 3.0  # about 40 standard deviations of an increment: gated
    _, result = ou_engine.smooth_arrays(ou_engine.initial_state(), dy[:, None])
    assert result.gated[150] and result.gated.sum() == 1
    dy[150] = np.nan
    _, _, ms, Ps = rts_sampled(dy, 1.0, 0.5)
    mean_gap = np.abs(result.mean[:, 0] - ms).max()
    var_gap = np.abs(result.cov[:, 0, 0] / Ps - 1).max()
    print(f"gated: mean {mean_gap:.2e}, var {var_gap:.2e}")
    assert mean_gap < 0.01 and var_gap < 0.03


def test_forward_pass_kept_or_checkpointed_and_both_backward_loops(ou_engine, monkeypatch):
    """The forward pass kept whole (K·Q ≤ KEEP), in checkpointed blocks of KEEP // Q rows beyond it (the
    checkpoints from the filter itself), and the backward pass of the Python loop (YAUYAU_KERNEL=numpy):
    the same smoother to rounding."""
    from yauyau.solver import jit
    from yauyau.solver.engine import smoother

    _, dy = sample_ou(600, seed=9)
    state = ou_engine.initial_state()
    _, whole = ou_engine.smooth_arrays(state, dy[:, None])
    monkeypatch.setattr(smoother, "KEEP", 100 * len(ou_engine.weights))  # blocks of 256 rows
    _, blocked = ou_engine.smooth_arrays(state, dy[:, None])
    assert np.abs(blocked.mean - whole.mean).max() < 1e-10 and np.abs(blocked.cov - whole.cov).max() < 1e-10
    monkeypatch.setattr(jit, "enabled", lambda: False)
    _, python = ou_engine.smooth_arrays(state, dy[:, None])
    assert np.abs(python.mean - whole.mean).max() < 1e-10 and np.abs(python.cov - whole.cov).max() < 1e-10
    ms, Ps = rts_sampled(dy, 1.0, 0.5)[2:]
    assert np.abs(whole.mean[:, 0] - ms).max() < 0.01 and np.abs(whole.cov[:, 0, 0] / Ps - 1).max() < 0.03
