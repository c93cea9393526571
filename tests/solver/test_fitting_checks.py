"""yauyau.fit's checks of the model (solver/fitting.py, solver/fit_likelihood.py, issue 39): which
parameters the drift uses (the SymPy tree's free symbols, not the text), a likelihood flat in a free
name reported rather than optimised into an arbitrary value, a free name no expression uses refused,
and the evaluations on a real local Dask cluster giving the in-process answer."""

from __future__ import annotations

import math

import numpy as np
import pytest
from helpers.fit_specs import OU, SQUARE, irregular_times, ou_path, ou_record
from yauyau.solver.errors import InputError
from yauyau.solver.fit_likelihood import offline_key, parameters_in, with_values

import yauyau

NAMES = (OU.replace('drift = ["-theta*x"]', 'drift = ["-alpha*x + 0*a"]')
         .replace('observation = ["x"]', 'observation = ["a*x + h0"]')
         .replace("theta = 0.5 }", "alpha = 0.5, a = 1.0, h0 = 0.1 }"))


def test_parameters_of_the_drift_are_the_free_symbols_of_its_tree():
    """``a`` is a substring of ``alpha`` and appears in the drift's text (0*a: no dependence); it enters
    only h, as ``h0`` does: neither changes the offline stage's key, alpha does."""
    spec = yauyau.parse_spec_text(NAMES, "toml")
    parts = parameters_in(spec)
    assert parts["drift"] == {"alpha"}
    assert parts["observation"] == {"a", "h0"}
    key = offline_key(spec)
    assert offline_key(with_values(spec, {"a": 2.0})) == key
    assert offline_key(with_values(spec, {"h0": -1.0})) == key
    assert offline_key(with_values(spec, {"alpha": 0.7})) != key


FLAT = OU.replace('observation = ["x"]', 'observation = ["x + max(c, 0)"]').replace(
    "theta = 0.5 }", "theta = 0.5, c = -0.5, unused = 1.0 }")


def flat_record():
    """OU readings shifted by 0.3: the truth is c = 0.3, but from c = -0.5 the likelihood is flat in c
    (h = x + max(c, 0) does not change for c < 0)."""
    z, t = ou_record(200, 1, dyadic=True)
    return z[:, None] + 0.3, t


def test_a_likelihood_flat_in_a_free_name_is_reported_not_optimised():
    spec = yauyau.parse_spec_text(FLAT, "toml")
    z, t = flat_record()
    found = yauyau.fit(spec, z, t, free={"theta": (0.05, 5.0), "c": (-1.0, 1.0)})
    assert not found.converged
    assert found.reason.startswith("the log-likelihood is flat in c at c = -0.5")
    assert "flat in theta" not in found.reason
    assert math.isnan(found.stderr["c"])
    assert math.isfinite(found.stderr["theta"]) and found.stderr["theta"] > 0


def test_a_free_name_no_expression_uses_is_bad_input():
    spec = yauyau.parse_spec_text(FLAT, "toml")
    z, t = flat_record()
    with pytest.raises(InputError) as err:
        yauyau.fit(spec, z, t, free={"unused": (0.5, 2.0)})
    assert err.value.field == "free.unused"


SQUARE_SMALL = SQUARE.replace("basis = 40", "basis = 24")


@pytest.mark.slow
def test_workers_on_a_local_dask_cluster_give_the_in_process_estimate():
    """θ enters the drift of a yau-yau model: every evaluation recomputes the offline stage, and with
    workers=2 (a real LocalCluster of 2 processes) the gradient's, Hessian's and profile's points run
    there; the estimate, standard error, log-likelihood and profile are the in-process ones."""
    spec = yauyau.parse_spec_text(SQUARE_SMALL, "toml")
    rng = np.random.default_rng(7)
    t = irregular_times(rng, 100, dyadic=True)
    z = ou_path(rng, t, 1.0, rng.normal(1.0, 0.5)) ** 2 / 2 + rng.normal(0.0, math.sqrt(0.05), 100)
    free = {"theta": (0.2, 3.0)}
    here = yauyau.fit(spec, z[:, None], t, free=free, profile="theta")
    there = yauyau.fit(spec, z[:, None], t, free=free, profile="theta", workers=2)
    assert here.converged and there.converged and here.method == "yau-yau"
    assert "Dask" in there.note and here.note == ""
    assert there.estimates["theta"] == pytest.approx(here.estimates["theta"], rel=1e-9)
    assert there.stderr["theta"] == pytest.approx(here.stderr["theta"], rel=1e-9)
    assert there.loglik == pytest.approx(here.loglik, rel=1e-12)
    np.testing.assert_allclose(there.profile["loglik"], here.profile["loglik"], rtol=1e-12)
    assert there.evaluations == here.evaluations
