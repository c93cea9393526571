"""The public API (yauyau/__init__.py, yauyau/api.py) against independent truth.

Truth here: the Ornstein–Uhlenbeck model observed linearly has the Kalman–Bucy filter as its exact
optimal filter (a Riccati ODE, closed form in 1-D), so a filter opened through the API must give it;
the conditional density of a Gaussian state is the normal density.
"""

from __future__ import annotations

import json
import math
import subprocess
import sys

import numpy as np
import pytest
from helpers import ROOT
from yauyau.solver.errors import InputError, SpecError
from yauyau.storage.errors import StoreError

import yauyau

OU = ROOT / "examples" / "ou.toml"


@pytest.fixture(scope="module")
def ou_store(tmp_path_factory):
    store = tmp_path_factory.mktemp("api-store")
    return store, yauyau.precompute(OU, store)


def test_every_public_name_resolves_and_import_is_light():
    for name in yauyau.__all__:
        assert getattr(yauyau, name) is not None, name
    assert sorted(yauyau.__all__) == dir(yauyau)
    code = ("import sys, yauyau; heavy = [m for m in ('sympy', 'scipy', 'h5py', 'fastapi', 'skfem') "
            "if m in sys.modules]; print(heavy)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                         env={"PYTHONPATH": str(ROOT), "PATH": "/usr/bin:/bin"})
    assert out.stdout.strip() == "[]"
    with pytest.raises(AttributeError):
        yauyau.no_such_name  # noqa: B018


@pytest.mark.slow
def test_precompute_stores_the_chosen_method_once(ou_store):
    store, mid = ou_store
    loaded = yauyau.load_model(store, mid)
    assert loaded.method == "kalman-bucy"  # OU: the analysis finds the linear case
    assert "linear" in loaded.method_reason.lower() or "kalman" in loaded.method_reason.lower()
    again = yauyau.precompute(OU, store)  # already stored: verified, not recomputed
    assert again == mid
    assert yauyau.ModelStore(store).ids() == [mid]


def test_open_filter_is_kalman_bucy_and_the_engine_agrees(ou_store):
    store, mid = ou_store
    spec = yauyau.load_spec(OU)
    sim = yauyau.simulate(spec, steps=400, seed=3)
    exact = yauyau.open_filter(store, mid)
    engine = yauyau.open_filter(store, mid, method="yau-yau")
    assert (exact.method, engine.method) == ("kalman-bucy", "yau-yau")
    a, b = exact.run(sim.increments), engine.run(sim.increments)
    # Kalman–Bucy by hand: dP/dt = -2θP + 1 - P², dm = -θm dt + P (dy - m dt), θ = 0.5
    m, P, dt = 1.0, 0.5, 0.01
    means = []
    for dy in sim.increments[:, 0]:
        for _ in range(100):  # fine Euler sub-steps of the Riccati ODE
            P += (-P + 1.0 - P * P) * dt / 100
        m += -0.5 * m * dt + P * (dy - m * dt)
        means.append(m)
    # measured 4.0e-3 (the O(dt) of this Euler recursion) and 4.8e-3 (the engine's O(dt) splitting gap)
    assert np.max(np.abs(a.mean[:, 0] - np.array(means))) < 0.01
    assert np.max(np.abs(a.mean - b.mean)) < 0.01
    # the steady Riccati solution: P² + P - 1 = 0
    assert exact.cov[0, 0] == pytest.approx((math.sqrt(5.0) - 1.0) / 2, rel=1e-3)


def test_step_estimate_density_marginal_and_state(ou_store):
    store, mid = ou_store
    flt = yauyau.open_filter(store, mid, method="yau-yau")
    first = flt.step([0.01])
    assert first.step == 1 and flt.estimate.step == 1
    predicted = flt.step(None)  # no observation: predict only
    assert predicted.step == 2 and predicted.loglik_increment == pytest.approx(0.0, abs=1e-6)
    grid = np.linspace(-6, 6, 1201)
    density = flt.density(grid)
    assert np.trapezoid(density, grid) == pytest.approx(1.0, abs=1e-4)
    mean, var = flt.mean[0], flt.cov[0, 0]
    normal = np.exp(-0.5 * (grid - mean) ** 2 / var) / math.sqrt(2 * math.pi * var)
    assert np.max(np.abs(density - normal)) < 2e-3  # the posterior of a linear-Gaussian model is Gaussian
    assert np.allclose(flt.marginal("x", grid), density)
    saved = json.loads(json.dumps(flt.state_dict()))
    continued = flt.step([0.02])
    flt.restore(saved)
    assert flt.step([0.02]).mean == pytest.approx(continued.mean, abs=0)  # exact restart
    flt.reset()
    assert flt.estimate.step == 0 and flt.mean[0] == pytest.approx(1.0, abs=1e-3)


def test_user_errors_name_the_field(ou_store, tmp_path):
    store, mid = ou_store
    with pytest.raises(StoreError):
        yauyau.open_filter(store, "0" * 20)
    with pytest.raises(InputError) as err:
        yauyau.open_filter(store, 12)
    assert err.value.field == "model_id"
    with pytest.raises(SpecError) as err:
        yauyau.open_filter(store, mid, method="auto")
    assert err.value.field == "method"
    flt = yauyau.open_filter(store, mid)
    with pytest.raises(InputError):
        flt.step([1.0, 2.0])  # m = 1
    with pytest.raises(InputError) as err:
        flt.marginal("y", [0.0])
    assert err.value.field == "variable"
    with pytest.raises(InputError) as err:
        yauyau.simulate(OU, steps=0)
    assert err.value.field == "steps"


def test_marginal_of_a_gaussian_filter_in_2d_is_the_normal_marginal(tmp_path):
    """Filters without a marginal of their own (here Kalman–Bucy) integrate the joint density out:
    the marginal of N(m, P) in coordinate i is N(m_i, P_ii)."""
    doc = {"name": "ou-2d", "state": ["p", "q"], "drift": ["-p", "-0.5*q + 0.3*p"], "observation": ["p"],
           "initial": {"kind": "gaussian", "mean": [0.4, -0.2], "cov": [[0.5, 0.2], [0.2, 0.8]]},
           "domain": {"radius": 5.0}, "discretization": {"dt": 0.05, "basis": 20}}
    from yauyau.solver.spec import spec_from_dict

    mid = yauyau.precompute(spec_from_dict(doc), tmp_path / "store")
    flt = yauyau.open_filter(tmp_path / "store", mid)
    assert flt.method == "kalman-bucy"
    flt.run([[0.1], [0.05], [-0.02]])
    grid = np.linspace(-3, 3, 61)
    for i, name in enumerate(("p", "q")):
        m, v = flt.mean[i], flt.cov[i, i]
        normal = np.exp(-0.5 * (grid - m) ** 2 / v) / math.sqrt(2 * math.pi * v)
        assert np.max(np.abs(flt.marginal(name, grid) - normal)) < 1e-3


def test_analyze_takes_a_spec_as_precompute_and_simulate_do():
    """A spec file's path (a str, as a newcomer types it) or a ModelSpec, not only a compiled model; the
    linear OU model gets the Kalman–Bucy filter, which is exact for it."""
    for spec in (str(OU), yauyau.load_spec(OU)):
        report = yauyau.analyze(spec)
        assert report.method == "kalman-bucy", type(spec)
    with pytest.raises(SpecError) as err:
        yauyau.analyze("no/such/spec.toml")
    assert err.value.field == "spec"


def test_examples_ship_with_the_package():
    on_disk = sorted(p.stem for p in (ROOT / "examples").glob("*.toml"))
    assert yauyau.examples.names() == on_disk and "cubic_sensor" in on_disk
    shipped = yauyau.examples.path("cubic_sensor")
    assert shipped.read_bytes() == (ROOT / "examples" / "cubic_sensor.toml").read_bytes()
    assert yauyau.examples.path("ou.toml").name == "ou.toml"
    with pytest.raises(SpecError) as err:
        yauyau.examples.path("cubic")
    assert err.value.field == "example" and "cubic_sensor" in err.value.message


BLAS_PROBE = """
import json, sys, yauyau
import numpy, scipy.linalg  # noqa: F401  (their BLAS loaded before, to be seen unchanged or not)
from threadpoolctl import threadpool_info
kwargs = json.loads(sys.argv[3])
before = sorted({i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas"})
try:
    yauyau.open_filter(sys.argv[1], sys.argv[2], **kwargs)
except yauyau.InputError as error:
    print(json.dumps({"error": [error.field, str(error)]}))
    raise SystemExit(0)
after = sorted({i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas"})
print(json.dumps({"before": before, "after": after}))
"""


def _blas_after_open(store, mid, env_threads=None, **kwargs):
    import os

    env = {k: v for k, v in os.environ.items()
           if not k.endswith("_NUM_THREADS") and k != "YAUYAU_BLAS_THREADS"}
    if env_threads is not None:
        env["YAUYAU_BLAS_THREADS"] = env_threads
    done = subprocess.run([sys.executable, "-c", BLAS_PROBE, str(store), mid, json.dumps(kwargs)], env=env,
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout.strip().splitlines()[-1])


def test_open_filter_runs_blas_on_one_thread_unless_asked(ou_store):
    """Issue 37 item 3: the library, like the CLI and the service, limits BLAS to one thread per process
    by default (bench/results/blas.md: the default threads are 1.5x slower beside one busy process);
    blas_threads= or $YAUYAU_BLAS_THREADS raise it, 0 leaves BLAS as the process has it, and a bad
    count is refused naming the field (fresh processes: OpenBLAS starts with a thread per core)."""
    store, mid = ou_store
    assert _blas_after_open(store, mid)["after"] == [1]
    assert _blas_after_open(store, mid, blas_threads=3)["after"] == [3]
    assert _blas_after_open(store, mid, env_threads="2")["after"] == [2]
    assert _blas_after_open(store, mid, env_threads="2", blas_threads=1)["after"] == [1]  # the argument wins
    kept = _blas_after_open(store, mid, blas_threads=0)
    assert kept["after"] == kept["before"]
    assert _blas_after_open(store, mid, blas_threads=-1)["error"][0] == "blas_threads"
    assert _blas_after_open(store, mid, blas_threads=2.5)["error"][0] == "blas_threads"
    field, message = _blas_after_open(store, mid, env_threads="many")["error"]
    assert field == "YAUYAU_BLAS_THREADS" and "'many'" in message
