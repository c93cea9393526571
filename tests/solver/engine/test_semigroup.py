"""The flow e^{τA} of irregular rows (solver/engine/semigroup.py, solver/engine/powers.py) against
scipy.linalg.expm(τA) — an independent computation — on random coefficient vectors, τ in [0.1 dt, 100 dt]:
the modal form of a well-conditioned generator and the Schur form of an ill-conditioned one (a double
well x − x³ with h = x² on a wide ball: cond(V) ≈ 1e11), and the engine's rows on the double well
through the Schur form against the same rows through the expm form, at gaps equal to dt (the nodal
flow Φe^{dtA}: one matrix, the regular-row loop) and at random gaps.
"""

from __future__ import annotations

import numpy as np
import pytest
import scipy.linalg as sla
from helpers.irregular_refs import random_times, simulate_irregular
from yauyau.solver.engine import powers
from yauyau.solver.engine.filter import YauYauFilter
from yauyau.solver.engine.semigroup import MAX_CONDITION, SpectralFlow
from yauyau.solver.model import compile_model
from yauyau.solver.offline.pipeline import precompute
from yauyau.solver.spec import spec_from_dict

DT = 0.01
DOUBLE_WELL = {"name": "double-well", "state": ["x"], "drift": ["x - x**3"], "observation": ["x**2"],
               "initial": {"kind": "gaussian", "mean": [0.5], "cov": [[1.0]]},
               "domain": {"radius": 3.5}, "discretization": {"dt": DT, "basis": 128}}
OU = {"name": "ou", "state": ["x"], "drift": ["-0.5*x"], "observation": ["x"],
      "initial": {"kind": "gaussian", "mean": [1.0], "cov": [[0.5]]},
      "domain": {"radius": 6.0}, "discretization": {"dt": DT, "basis": 48}}
_CACHE: dict = {}


def _offline(doc):
    if doc["name"] not in _CACHE:
        model = compile_model(spec_from_dict(doc))
        _CACHE[doc["name"]] = model, precompute(model)
    return _CACHE[doc["name"]]


def _flow(doc, form=None) -> SpectralFlow:
    _, offline = _offline(doc)
    return SpectralFlow(offline.fokker_planck_generator(), offline.basis, offline.projector,
                        np.ones(offline.basis.shape[0]), form=form)


@pytest.mark.parametrize("doc, form", [(DOUBLE_WELL, "schur"), (OU, "modal"), (OU, "schur")])
def test_the_flow_matches_expm_on_random_vectors(doc, form):
    flow = _flow(doc, form)
    if doc is DOUBLE_WELL:
        assert flow.condition > MAX_CONDITION and flow.form == "schur"  # picked, not forced
    rng = np.random.default_rng(1)
    drawn = np.exp(rng.uniform(np.log(0.1 * DT), np.log(100 * DT), 9))
    taus = np.concatenate([[0.1 * DT, DT, 100 * DT], drawn])
    worst = 0.0
    for tau in taus:
        c = rng.standard_normal((flow.N, 2))
        truth = sla.expm(tau * flow.generator) @ c
        for j in range(2):
            got = flow.apply(tau, c[:, j])
            worst = max(worst, np.linalg.norm(got - truth[:, j]) / np.linalg.norm(truth[:, j]))
    assert worst <= 1e-9, worst


def test_the_schur_plan_splits_each_gap_into_tables_and_a_short_remainder():
    flow = _flow(DOUBLE_WELL)
    p = flow.powers
    taus = np.array([0.0, 0.1 * DT, DT, 1.37 * DT, 100 * DT, 1e6])
    indices, remainders = p.plan(taus)
    assert np.all(np.abs(remainders) <= p.delta / 2 * (1 + 1e-9))
    for tau, row, r in zip(taus, indices, remainders, strict=True):
        digits = [(m % (p.base - 1)) + 1 for m in row if m >= 0]
        positions = [m // (p.base - 1) for m in row if m >= 0]
        n = sum(d * p.base ** j for d, j in zip(digits, positions, strict=True))
        assert n * p.delta + r == pytest.approx(tau, rel=1e-12, abs=1e-15)
    assert indices[0].max() == -1 and remainders[0] == 0.0  # a zero gap: the identity
    assert powers.taylor_degree(p.delta * np.linalg.norm(p.schur, 1) / 2) == p.degree


@pytest.mark.slow
@pytest.mark.parametrize("kind", ["continuous", "discrete"])
def test_double_well_rows_through_the_schur_form_match_the_exponential(monkeypatch, kind):
    """Gaps of dt: the Schur form's rows against the expm form's, which runs them as regular rows with
    the one matrix Φe^{dtA}; then random gaps.  Means, covariances and log-likelihoods to 1e-9."""
    model, offline = _offline(DOUBLE_WELL)
    if kind == "discrete":
        model = compile_model(spec_from_dict(dict(DOUBLE_WELL, measurement={"kind": "discrete"})))
    schur = YauYauFilter(model, offline)
    assert schur.flow.form == "schur"
    monkeypatch.setattr(powers, "MAX_TABLE_BYTES", 0)
    expm = YauYauFilter(model, offline)
    assert expm.flow.form == "expm"
    rng = np.random.default_rng(5)
    for times in (DT * np.arange(1, 301), random_times(rng, 300, DT)):
        _, rows = simulate_irregular(model, times, kind, rng)
        _assert_same_rows(schur, expm, rows, times, 1e-9)


def test_a_generator_between_the_caps_runs_modal_within_its_rounding(monkeypatch):
    """The double well on basis 96 (cond(V) ≈ 5e8: above single precision's cap, under double's) takes
    the modal form: its flow within 1e-17·cond(V) × 10 of expm(τA) (measured 3e-9), and 300 rows at
    random gaps within 1e-7 of the expm form's means, covariances and log-likelihoods (measured 1e-11):
    rounding far under the engine's gap to the optimal filter, at the modal form's cost."""
    doc = dict(DOUBLE_WELL, name="double-well-96", discretization={"dt": DT, "basis": 96})
    flow = _flow(doc)
    assert 1e7 < flow.condition <= MAX_CONDITION and flow.form == "modal"
    rng = np.random.default_rng(2)
    drawn = np.exp(rng.uniform(np.log(0.1 * DT), np.log(100 * DT), 4))
    for tau in np.concatenate([[0.1 * DT, 100 * DT], drawn]):
        c = rng.standard_normal(flow.N)
        truth = sla.expm(tau * flow.generator) @ c
        assert np.linalg.norm(flow.apply(tau, c) - truth) <= 1e-16 * flow.condition * np.linalg.norm(truth)
    model, offline = _offline(doc)
    modal = YauYauFilter(model, offline)
    assert modal.flow.form == "modal"  # made now (the flow is made on first use)
    monkeypatch.setattr(powers, "MAX_TABLE_BYTES", 0)
    monkeypatch.setattr("yauyau.solver.engine.semigroup.MAX_CONDITION", 0.0)
    expm = YauYauFilter(model, offline)
    assert modal.flow.form == "modal" and expm.flow.form == "expm"
    times = random_times(rng, 300, DT)
    _, rows = simulate_irregular(model, times, "continuous", rng)
    _assert_same_rows(modal, expm, rows, times, 1e-7)


def _assert_same_rows(first, exact, rows, times, tol: float) -> None:
    """The two filters' means, covariances and log-likelihoods over the rows within ``tol`` (``exact``'s
    flow: expm(τA) per gap)."""
    _, a = first.run_arrays(first.initial_state(), rows, times)
    _, b = exact.run_arrays(exact.initial_state(), rows, times)
    assert not a.degenerate.any() and not b.degenerate.any()
    assert np.max(np.abs(a.mean - b.mean)) <= tol
    assert np.max(np.abs(a.cov - b.cov)) <= tol
    assert np.max(np.abs(a.loglik - b.loglik)) <= tol * max(1.0, np.max(np.abs(b.loglik)))
