"""The seams of issue "one library": the problem apart from its discretisation, and the offline
pipeline as three replaceable builders.

Truth: the Ornstein–Uhlenbeck model observed linearly has the discrete-time Kalman filter as its
exact optimal filter at the observation times (solver.reference.kalman, Van Loan), so any basis that
resolves the density must give it; the default eigenbasis is replaced here by the exact Dirichlet
sine basis of the interval, orthonormalised in the quadrature inner product.
"""

from __future__ import annotations

import numpy as np
import pytest
from helpers import ROOT
from yauyau.solver.engine.filter import YauYauFilter
from yauyau.solver.errors import SpecError
from yauyau.solver.model import compile_model
from yauyau.solver.offline.basis import OrthonormalBasis
from yauyau.solver.offline.pipeline import OfflineArrays, precompute
from yauyau.solver.reference.kalman import DiscreteKalmanFilter
from yauyau.solver.simulate import simulate
from yauyau.solver.spec import DiscretisationSpec, ModelSpec, ProblemSpec, load_spec


def test_one_problem_two_discretisations():
    spec = load_spec(ROOT / "examples" / "ou.toml")
    assert isinstance(spec.problem, ProblemSpec) and isinstance(spec.discretisation, DiscretisationSpec)
    finer = spec.with_discretisation({"domain": {"radius": 6.0},
                                      "discretization": {"dt": 0.005, "basis": 64}})
    assert finer.problem == spec.problem and finer.name == spec.name and finer.method == spec.method
    assert (finer.domain.radius, finer.discretization.dt) == (6.0, 0.005)
    again = ModelSpec.compose(spec.name, spec.problem, spec.discretisation, spec.method)
    assert again.canonical_json() == spec.canonical_json()  # the file format is unchanged
    X = np.linspace(-3, 3, 11)[:, None]
    assert np.array_equal(compile_model(finer).f(X), compile_model(spec).f(X))
    with pytest.raises(SpecError) as err:
        spec.with_discretisation({"domain": {"radius": 6.0}, "discretization": {"dt": -1, "basis": 8}})
    assert err.value.field == "discretization.dt"


def sine_basis(disc, size):
    """sin(kπ(x + R)/2R), k = 1..N, on the nodes, W-orthonormalised (Gram–Schmidt via QR)."""
    x = disc.nodes[:, 0]
    radius = np.max(np.abs(disc.space.mesh.p))  # the ball [-R, R], boundary included in the mesh
    raw = np.stack([np.sin(k * np.pi * (x + radius) / (2 * radius)) for k in range(1, size + 1)], axis=1)
    root = np.sqrt(disc.weights)[:, None]
    q, r = np.linalg.qr(root * raw)
    values = (q * np.sign(np.diag(r))) / root
    eigen = (np.arange(1, size + 1) * np.pi / (2 * radius)) ** 2 / 2
    return OrthonormalBasis(values=values, projector=(values * disc.weights[:, None]).T, eigenvalues=eigen)


def test_a_new_basis_is_one_builder_and_the_engine_still_meets_kalman():
    model = compile_model(load_spec(ROOT / "examples" / "ou.toml"))
    offline = precompute(model, basis=sine_basis)
    assert isinstance(offline, OfflineArrays)
    assert np.allclose(offline.projector @ offline.basis, np.eye(offline.size), atol=1e-10)
    dy = simulate(model, 300, np.random.default_rng(5)).increments
    engine = YauYauFilter(model, offline)
    _, result = engine.run_arrays(engine.initial_state(), dy)
    kalman = DiscreteKalmanFilter(model)
    _, ref = kalman.run(kalman.initial_state(), dy)
    assert not result.degenerate.any()
    assert np.max(np.abs(result.mean[:, 0] - [e.mean[0] for e in ref])) < 2e-3
    assert np.max(np.abs(result.cov[:, 0, 0] / [e.cov[0, 0] for e in ref] - 1)) < 0.02


def test_spec_validation_builds_no_model_and_the_model_reuses_its_checked_expressions():
    """v0.1's spec_from_dict compiled a Model (SymPy) and threw it away, and spec.py imported model.py
    (which imports spec.py): now validation parses the expressions once and compile_model reuses them."""
    import subprocess
    import sys

    code = ("import sys; from yauyau.solver.spec import load_spec; "
            f"load_spec({str(ROOT / 'examples' / 'cubic_sensor.toml')!r}); "
            "print('yauyau.solver.model' in sys.modules, 'sympy' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                         env={"PYTHONPATH": str(ROOT), "PATH": "/usr/bin:/bin"})
    assert out.stdout.split() == ["False", "False"]
    spec = load_spec(ROOT / "examples" / "cubic_sensor.toml")
    checked = spec.numeric()
    model = compile_model(spec)
    assert model.f is checked[0] and model.h is checked[1]
