"""The filter contract and the defects found in v0.1, each against an independent truth.

* Beneš shift integral ∫_0^r tanh(x + τ) dτ = log cosh(x + r) − log cosh(x) (closed form), finite
  far out (v0.1: log(tanh x + 1) = log 0 → NaN for x ≲ −19).
* Wei–Norman's stored Kolmogorov flow: its memory stays under its bound however long the model lives
  (v0.1 kept every step), and its values are (propagator_k · projector)^k σ0 (the definition), also
  when threads share it.
* Kalman–Bucy with a ±2 bimodal prior: refused (v0.1 moment-matched it to N(0, 4.1): its first
  estimate's variance was 4.1, not the prior's).
* ``step(state, None)``: the engine predicts (no likelihood); Wei–Norman, whose representation needs
  every increment, refuses with InputError('increment'), not a TypeError.
* An Estimate returned earlier is never changed by later steps.
* One registry: the spec, the CLI and make_filter take their method names from it; a new method is a
  module plus one registry line.
"""

from __future__ import annotations

import ast
import threading

import numpy as np
import pytest
from helpers import ROOT
from yauyau.solver.errors import InputError, SpecError
from yauyau.solver.exact import wei_norman
from yauyau.solver.methods import make_filter
from yauyau.solver.model import compile_model
from yauyau.solver.offline.pipeline import precompute
from yauyau.solver.spec import spec_from_dict


def spec(**changes):
    doc = {"name": "t", "state": ["x"], "drift": ["-x"], "observation": ["x"],
           "initial": {"kind": "gaussian", "mean": [0.0], "cov": [[1.0]]}, "domain": {"radius": 6.0},
           "discretization": {"dt": 0.05, "basis": 24}}
    doc.update(changes)
    return spec_from_dict(doc)


def test_benes_shift_integral_is_finite_and_exact_far_out():
    model = compile_model(spec(drift=["tanh(x)"], domain={"radius": 500.0}))
    shift = wei_norman._shift_integral(model, 0)
    x = np.array([-400.0, -30.0, -19.0, -5.0, 0.0, 5.0, 25.0, 400.0])
    r = np.array([1.0, 0.5, 0.5, -0.3, 0.5, 2.0, 0.5, -1.0])

    def log_cosh(u):  # |u| + log(1 + e^{-2|u|}) − log 2, exact in floating point
        return np.abs(u) + np.log1p(np.exp(-2 * np.abs(u))) - np.log(2.0)

    values = shift(np.column_stack([x, r]))
    assert np.all(np.isfinite(values))
    assert np.allclose(values, log_cosh(x + r) - log_cosh(x), rtol=1e-12, atol=1e-12)


@pytest.fixture(scope="module")
def ou_offline():
    model = compile_model(spec())
    return model, precompute(model)


def test_wei_norman_flow_memory_is_bounded_and_its_values_exact(ou_offline):
    model, offline = ou_offline
    Q = len(offline.nodes)
    flow = wei_norman.KolmogorovFlow(offline, cache_bytes=16 * 8 * Q)  # room for 16 vectors
    reference = [np.exp(model.log_prior(offline.nodes))]
    for _ in range(400):
        reference.append(offline.propagator_k @ (offline.projector @ reference[-1]))
    for k in range(0, 401, 7):
        assert np.array_equal(flow(k * model.dt, offline.nodes), reference[k])
    assert flow.held_bytes <= 17 * 8 * Q  # 16 checkpoints and the last vector; v0.1 kept all 401
    assert np.array_equal(flow(3 * model.dt, offline.nodes), reference[3])  # going back is exact too


def test_wei_norman_flow_shared_by_threads(ou_offline):
    model, offline = ou_offline
    flow = wei_norman.KolmogorovFlow(offline, cache_bytes=8 * 8 * len(offline.nodes))
    truth = [np.exp(model.log_prior(offline.nodes))]
    for _ in range(120):
        truth.append(offline.propagator_k @ (offline.projector @ truth[-1]))
    errors = []

    def worker(seed):
        for k in np.random.default_rng(seed).integers(0, 121, size=60):
            if not np.array_equal(flow(int(k) * model.dt, offline.nodes), truth[int(k)]):
                errors.append(int(k))

    threads = [threading.Thread(target=worker, args=(s,)) for s in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors


def test_kalman_bucy_refuses_a_bimodal_prior():
    bimodal = {"kind": "mixture", "weights": [0.5, 0.5], "means": [[-2.0], [2.0]], "covs": [[[0.1]], [[0.1]]]}
    model = compile_model(spec(initial=bimodal))
    flt = make_filter(model, None, "kalman-bucy")
    with pytest.raises(SpecError) as err:
        flt.initial_state()
    assert err.value.field == "initial" and "gaussian prior" in err.value.message
    # the exact filter for a mixture prior is Yau–Hu: its first estimate has the prior's variance
    prior_var = 0.1 + 4.0  # E[Var] + Var[E] of the ±2 mixture
    assert make_filter(model, None, "yau-hu").initial_state() is not None
    assert make_filter(model, None, "yau-hu").estimate(
        make_filter(model, None, "yau-hu").initial_state()).cov[0, 0] == pytest.approx(prior_var, rel=1e-6)


def test_step_none_predicts_or_says_why(ou_offline):
    model, offline = ou_offline
    engine = make_filter(model, offline, "yau-yau")
    state, est = engine.step(engine.initial_state(), None)
    assert est.step == 1 and est.loglik_increment == pytest.approx(0.0, abs=1e-7)  # mass lost at the wall
    assert est.mean[0] == pytest.approx(0.0, abs=1e-9)
    assert est.cov[0, 0] == pytest.approx(np.exp(-2 * 0.05) + (1 - np.exp(-2 * 0.05)) / 2, rel=2e-3)  # OU
    wn = make_filter(model, offline, "wei-norman")
    with pytest.raises(InputError) as err:
        wn.step(wn.initial_state(), None)
    assert err.value.field == "increment" and "every increment" in err.value.message


@pytest.mark.parametrize("method", ["yau-yau", "kalman-bucy", "yau-hu", "wei-norman"])
def test_estimates_returned_earlier_never_change(ou_offline, method):
    model, offline = ou_offline
    flt = make_filter(model, offline, method)
    dy = np.random.default_rng(0).normal(scale=0.2, size=(30, 1))
    state, first = flt.run(flt.initial_state(), dy[:10])
    frozen = [(e.step, e.mean.copy(), e.cov.copy(), e.loglik, e.degenerate, e.reason) for e in first]
    flt.run(state, dy[10:])
    again = [(e.step, e.mean, e.cov, e.loglik, e.degenerate, e.reason) for e in first]
    for a, b in zip(frozen, again, strict=True):
        assert a[0] == b[0] and np.array_equal(a[1], b[1]) and np.array_equal(a[2], b[2]) and a[3:] == b[3:]


def test_one_registry_drives_the_method_names(monkeypatch, ou_offline, tmp_path):
    from yauyau.solver import registry
    from yauyau.solver.registry import REGISTRY, Method

    assert set(registry.METHODS) == {"auto", *REGISTRY}
    with pytest.raises(SpecError) as err:
        spec(method="kalman")
    assert err.value.field == "method" and all(name in err.value.message for name in REGISTRY)
    # a new exact filter: one module with build(), one registry line
    module = tmp_path / "toy_filter.py"
    module.write_text("from yauyau.solver.exact.kalman_bucy import KalmanBucyFilter\n"
                      "class ToyFilter(KalmanBucyFilter):\n    method = 'toy'\n"
                      "def build(model, offline=None, **_):\n    return ToyFilter(model)\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setitem(REGISTRY, "toy", Method("toy", "toy_filter", "ToyFilter", False, "a test"))
    model, offline = ou_offline
    assert spec(method="toy").method == "toy"
    assert make_filter(model, offline, "toy").method == "toy"


def test_exact_filters_import_neither_the_engine_nor_private_bases():
    for path in (ROOT / "solver" / "exact").glob("*.py"):
        tree = ast.parse(path.read_text())
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom):
                name = ("." * node.level) + (node.module or "")
                assert name not in ("..engine", "..reference._base"), (path.name, name)
