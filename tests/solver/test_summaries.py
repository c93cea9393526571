"""Quantiles and the mode against independent truth (yauyau.solver.summaries).

* OU (examples/ou.toml): the posterior is N(m, P); its quantiles are m + √P Φ⁻¹(p).  The Kalman–
  Bucy filter answers in closed form; the Yau–Hu filter (a non-Gaussian representation of the same
  posterior) goes through the grid inversion of the marginal; both within 1e-3 of scipy's normal
  quantiles.  The general engine on the same data within 1e-2 (its discretisation, not the inversion).
* Beneš (examples/benes.toml): the posterior is cosh(x)·N(x; μ, P)/(e^{P/2} cosh μ) = a mixture of
  N(μ ± P, P) with weights ∝ e^{±μ}; its distribution function in closed form, the quantiles by
  brentq; (μ, P) by the recursion of the time-sampled model (as in test_engine.py).
* Mode: the quadratic sensor h = x² with a prior leaning right has a two-peaked posterior; the
  engine's mode sits on the taller peak of a fine-grid point-mass reference density.
"""

from __future__ import annotations

import numpy as np
import pytest
from helpers import EXAMPLES
from scipy.optimize import brentq
from scipy.special import ndtr
from scipy.stats import norm
from yauyau.solver import compile_model, load_spec, spec_from_dict, summaries
from yauyau.solver.errors import InputError
from yauyau.solver.reference.pointmass import PointMassFilter
from yauyau.solver.simulate import simulate

from yauyau import api

PROBS = np.array([0.01, 0.05, 0.25, 0.5, 0.75, 0.95, 0.99])


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    return tmp_path_factory.mktemp("summaries-store")


def _open(store, name, method=None):
    spec = load_spec(EXAMPLES / name)
    mid = api.precompute(spec, store)
    return spec, (lambda m=method, **options: api.open_filter(store, mid, method=m, **options))


@pytest.mark.slow
def test_ou_quantiles_are_the_normal_quantiles(store):
    spec, opener = _open(store, "ou.toml")
    kb, yh, yy = opener("kalman-bucy"), opener("yau-hu"), opener("yau-yau")
    increments = simulate(kb.model, 600, np.random.default_rng(3)).increments
    worst_exact, worst_engine = 0.0, 0.0
    for chunk in np.array_split(increments, 6):
        for flt in (kb, yh, yy):
            flt.run(chunk)
        m, sd = kb.mean[0], np.sqrt(kb.cov[0, 0])
        truth = norm.ppf(PROBS, loc=m, scale=sd)
        worst_exact = max(worst_exact, np.abs(kb.quantiles(PROBS)[0] - truth).max(),
                          np.abs(yh.quantiles(PROBS)[0] - truth).max())
        worst_engine = max(worst_engine, np.abs(yy.quantiles(PROBS)[0] - truth).max())
    assert worst_exact < 1e-3
    assert worst_engine < 1e-2


def _benes_cdf(x, mu, P):
    w_plus = 1.0 / (1.0 + np.exp(-2.0 * mu))
    s = np.sqrt(P)
    return w_plus * ndtr((x - mu - P) / s) + (1 - w_plus) * ndtr((x - mu + P) / s)


# Yau–Hu solves the continuous-time filter exactly; against the time-sampled recursion its variance
# differs by ≈0.01 (an O(dt) model difference, not the quantile inversion: its mean is within 3e-3).
@pytest.mark.slow
@pytest.mark.parametrize("method, tol", [("yau-yau", 2e-3), ("yau-hu", 1.5e-2)])
def test_benes_quantiles_match_the_exact_density(store, method, tol):
    spec, opener = _open(store, "benes.toml")
    flt = opener(method)
    dt = flt.model.dt
    increments = simulate(flt.model, 300, np.random.default_rng(5)).increments
    mu, P = 0.0, 1.0  # prior ∝ cosh(x) N(x; 0, 1)
    worst = 0.0
    for k, dy in enumerate(increments):
        flt.step(dy)
        P = P + dt
        mu, P = (mu / P + dy[0]) / (1.0 / P + dt), 1.0 / (1.0 / P + dt)
        if k % 60 == 59:
            exact = [brentq(lambda x, p=p, mu=mu, P=P: _benes_cdf(x, mu, P) - p, -30, 30, xtol=1e-12)
                     for p in PROBS]
            worst = max(worst, np.abs(flt.quantiles(PROBS)[0] - exact).max())
    assert worst < tol


def _quadratic_spec():
    return spec_from_dict({
        "name": "quadratic-sensor", "state": ["x"], "drift": ["-0.1*x"], "observation": ["x**2"],
        "initial": {"kind": "mixture", "weights": [0.35, 0.65], "means": [[-1.2], [1.2]],
                    "covs": [[[0.15]], [[0.15]]]},
        "domain": {"radius": 5.0}, "discretization": {"dt": 0.01, "basis": 128}})


@pytest.mark.slow
def test_mode_sits_on_the_taller_peak_of_the_reference(store):
    spec = _quadratic_spec()
    mid = api.precompute(spec, store)
    flt = api.open_filter(store, mid, method="yau-yau")
    model = compile_model(spec)
    ref = PointMassFilter(model, cells=2000)
    ref_state = ref.initial_state()
    increments = simulate(model, 60, np.random.default_rng(11)).increments
    grid = np.linspace(-5, 5, 20001)
    for dy in increments:
        flt.step(dy)
        ref_state, _ = ref.step(ref_state, dy)
    ref_density = ref.density(ref_state, grid[:, None])
    peak = grid[np.argmax(ref_density)]
    other = -peak
    near_other = np.abs(grid - other) < 0.8
    assert ref_density[near_other].max() > 0.2 * ref_density.max()  # really two peaks
    assert abs(flt.mean[0]) < abs(peak) - 0.3  # the mean sits between them
    mode = flt.mode
    assert mode[0] == pytest.approx(peak, abs=0.02)
    # refined: closer to the reference peak than the tallest node
    node_mode = flt.estimate.mode[0]
    assert abs(mode[0] - peak) <= abs(node_mode - peak) + 1e-9


def test_gaussian_mode_is_the_mean_and_degenerate_has_none(store):
    spec, opener = _open(store, "ou.toml")
    kb = opener("kalman-bucy")
    assert np.array_equal(kb.mode, kb.mean)
    yy = opener("yau-yau", gate=0)  # the gate off: the impossible row reaches the update
    yy.run(np.array([[1e6]]))
    assert yy.degenerate and yy.mode is None
    assert np.isnan(yy.quantiles([0.5])).all()


@pytest.mark.slow
def test_a_summarised_run_gives_each_row_the_normal_quantiles_and_none_once_degenerate(store):
    """solver/summarised.py, the one path of ``yauyau filter --quantiles/--mode`` and of a session chunk
    that asks for them: row by row, the Yau–Hu filter's quantiles are the normal quantiles of the exact
    Kalman–Bucy posterior at that row and its mode is that posterior's mean; after an impossible row
    (the gate off) the density is degenerate and neither is given."""
    from yauyau.solver.summarised import summarised_rows
    from yauyau.solver.watch import Watch

    spec, opener = _open(store, "ou.toml")
    kb, yh = opener("kalman-bucy"), opener("yau-hu")
    increments = simulate(kb.model, 40, np.random.default_rng(5)).increments
    rows = list(summarised_rows(yh.filter, yh.state, Watch(), increments, mode=True, probs=PROBS))
    assert len(rows) == len(increments)
    for dy, row in zip(increments, rows, strict=True):
        kb.step(dy)
        m, sd = kb.mean[0], np.sqrt(kb.cov[0, 0])
        assert row.estimate.step == kb.estimate.step and not row.estimate.degenerate
        np.testing.assert_allclose(row.quantiles[0], norm.ppf(PROBS, loc=m, scale=sd), atol=1e-3)
        assert row.mode[0] == pytest.approx(m, abs=1e-3)
    yy = opener("yau-yau", gate=0)
    [bad] = summarised_rows(yy.filter, yy.state, Watch(), np.array([[1e6]]), mode=True, probs=PROBS)
    assert bad.estimate.degenerate and bad.mode is None and bad.quantiles is None
    [plain] = summarised_rows(yh.filter, rows[-1].state, rows[-1].watch, increments[:1])
    assert plain.mode is None and plain.quantiles is None  # nothing asked: nothing computed


@pytest.mark.parametrize("bad", [[], [0.0], [1.0], [0.5, float("nan")], "a,b", [[0.5]] * 100])
def test_probabilities_are_checked(bad):
    with pytest.raises(InputError) as err:
        summaries.check_probabilities(bad)
    assert err.value.field == "quantiles"
