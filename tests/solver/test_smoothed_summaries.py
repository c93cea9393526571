"""Quantiles of the smoothed density (solver/smoothed_summaries.py) against independent references: the
point-mass forward–backward smoother of tests/helpers/smoothing_refs.py for the bimodal x²/2 sensor
(its smoothed masses on the grid, their distribution function inverted), and RTS's Gaussian quantiles
for OU through the engine and through Kalman–Bucy's smoother."""

from __future__ import annotations

import tomllib

import numpy as np
from helpers import EXAMPLES
from helpers.smoothing_refs import DT, A, R, point_mass_smoother, rts_sampled, sample_ou, simulate_bimodal
from scipy.special import ndtri
from yauyau.solver import compile_model, spec_from_dict
from yauyau.solver.engine.filter import YauYauFilter
from yauyau.solver.offline.pipeline import precompute
from yauyau.solver.smoothed_summaries import smooth_with_quantiles

PROBS = [0.05, 0.25, 0.5, 0.75, 0.95]
BIMODAL = {"name": "bimodal", "state": ["x"], "drift": ["-0.5*x"], "observation": ["x**2/2"],
           "diffusion": [[1.0]], "observation_noise": [[0.1]], "measurement": {"kind": "discrete"},
           "initial": {"kind": "gaussian", "mean": [0.3], "cov": [[1.0]]},
           "domain": {"radius": 6.0}, "discretization": {"dt": 0.01, "basis": 128}}


def grid_quantiles(x, masses, probs):
    """Quantiles of the point masses at x, by the midpoint rule's distribution function interpolated."""
    cdf = np.cumsum(masses) - 0.5 * masses
    return np.interp(probs, cdf / masses.sum(), x)


def test_bimodal_smoothed_quantiles_match_the_point_mass_smoother():
    """150 readings of the x²/2 sensor, 5% missing: every row's smoothed quantiles within 0.02 of the
    point-mass smoother's (1200 cells, spacing 0.01); the smoothed median differs from the filtered one."""
    model = compile_model(spec_from_dict(BIMODAL))
    engine = YauYauFilter(model, precompute(model))
    K = 150
    taus = np.full(K, DT)
    rows = simulate_bimodal(taus, seed=11, missing=0.05)
    states = {}
    _, result, table = smooth_with_quantiles(engine, engine.initial_state(), rows[:, None], probs=PROBS,
                                             each=lambda k, s: states.update({k: s} if k % 50 == 0 else {}))
    _, mean, _, x, smoothed = point_mass_smoother(rows, taus, cells=1200, full=True)
    reference = np.array([grid_quantiles(x, smoothed[k], PROBS) for k in range(K)])
    gap = np.abs(table[:, 0, :] - reference).max()
    print(f"bimodal smoothed quantiles: {gap:.2e}")
    assert table.shape == (K, 1, len(PROBS)) and gap < 0.02
    assert np.abs(result.mean[:, 0] - mean).max() < 0.01
    # the density of a smoothed state: its mean by quadrature is the smoothed mean
    for k, state in states.items():
        grid = np.linspace(-6, 6, 2001)
        values = np.asarray(engine.density(state, grid[:, None]), dtype=float)
        assert abs(np.trapezoid(values, grid) - 1) < 1e-3
        assert abs(np.trapezoid(values * grid, grid) - result.mean[k, 0]) < 1e-3


def test_ou_smoothed_quantiles_are_rts_gaussian_ones():
    """OU increments, 400 rows: the engine's smoothed quantiles within 0.01 of RTS's Gaussian ones on the
    sampled model (the smoothed law is Gaussian; measured: 3.5e-4 on most rows, as the filter's own
    quantiles at the last row, 2.9e-4; at most 6.1e-3, a 0.95 quantile two rows before the end), and the
    Kalman–Bucy smoother's closed form (the sampled model) to 1e-6."""
    from yauyau.solver.exact.kalman_bucy import KalmanBucyFilter

    doc = tomllib.loads((EXAMPLES / "ou.toml").read_text())
    doc["diffusion"], doc["observation_noise"] = [[A]], [[R]]
    doc["domain"]["radius"], doc["discretization"]["basis"] = 6.0, 64
    model = compile_model(spec_from_dict(doc))
    _, dy = sample_ou(400, seed=3)
    _, _, ms, Ps = rts_sampled(dy, 1.0, 0.5)
    reference = ms[:, None] + np.sqrt(Ps)[:, None] * ndtri(PROBS)[None, :]
    engine = YauYauFilter(model, precompute(model))
    _, _, table = smooth_with_quantiles(engine, engine.initial_state(), dy[:, None], probs=PROBS)
    gap = np.abs(table[:, 0, :] - reference).max()
    print(f"OU smoothed quantiles: {gap:.2e}")
    assert gap < 0.01
    kb = KalmanBucyFilter(model, kind="discrete")  # the sampled model: RTS itself
    _, result, exact = smooth_with_quantiles(kb, kb.initial_state(), dy[:, None], probs=PROBS)
    sd = np.sqrt(result.cov[:, 0, 0])
    assert np.abs(exact[:, 0, :] - (result.mean[:, 0, None] + sd[:, None] * ndtri(PROBS))).max() < 1e-12
    assert np.abs(exact[:, 0, :] - reference).max() < 1e-6
