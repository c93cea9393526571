"""The compiled row of independent one-coordinate blocks (solver/qmc/kernels.py) against the numpy path.

The numpy path of ``SingleBlocks`` is the reference (its accuracy is proved against independent truth in
test_yau_niu.py: point-mass filters, the Kalman filter); here both paths run the same rows on the same
seeded noise and must agree to rounding — every measurement kind (continuous increments, Gaussian and
Student-t readings), irregular times with long gaps in Euler pieces, missing components and rows, the
gate, the progressive correction, restarts and a zero likelihood — and the lattice noise they share
must be a QMC normal set (the 1-D lattice's moments and discrepancy, checked here against Φ).
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.special import ndtr
from yauyau.solver.model import compile_model
from yauyau.solver.qmc.cloud import lattice_normals
from yauyau.solver.qmc.yau_niu import YauNiuFilter
from yauyau.solver.simulate import simulate
from yauyau.solver.spec import spec_from_dict

DT = 0.01


def sensors(n: int, points: int, measurement: dict | None = None, r: np.ndarray | None = None):
    r = np.linspace(0.3, 1.2, n) if r is None else r
    doc = {"name": "t", "state": [f"x{i}" for i in range(n)], "drift": [f"-0.5*x{i} + 0.1*sin(x{i})"
                                                                        for i in range(n)],
           "observation": [f"x{i}**3" for i in range(n)], "observation_noise": np.diag(r).tolist(),
           "method": "yau-niu", "initial": {"kind": "gaussian", "mean": [0.5] * n, "cov": np.eye(n).tolist()},
           "discretization": {"dt": DT, "points": points}}
    if measurement is not None:
        doc["measurement"] = measurement
    return compile_model(spec_from_dict(doc))


def both_paths(monkeypatch, model, rows, times=None, gate=None, chunks=(None,)):
    """(numpy, compiled) results and final states of the same run, split at ``chunks``."""
    out = []
    for kernel in ("numpy", "compiled"):
        monkeypatch.setenv("YAUYAU_KERNEL", kernel)
        flt = YauNiuFilter(model, gate=gate)
        assert flt._singles is not None
        state, parts = flt.initial_state(), []
        bounds = [0, *(c for c in chunks if c is not None), len(rows)]
        for a, b in zip(bounds[:-1], bounds[1:], strict=True):
            state, result = flt.run_arrays(state, rows[a:b], None if times is None else times[a:b])
            parts.append(result)
        out.append((parts, state))
    return out


def assert_same(numpy_run, compiled_run, rtol=1e-9):
    (np_parts, np_state), (c_parts, c_state) = numpy_run, compiled_run
    for a, b in zip(np_parts, c_parts, strict=True):
        np.testing.assert_allclose(b.mean, a.mean, rtol=rtol, atol=1e-12)
        np.testing.assert_allclose(b.cov, a.cov, rtol=rtol, atol=1e-12)
        np.testing.assert_allclose(b.loglik, a.loglik, rtol=rtol)
        np.testing.assert_allclose(b.predictive_loglik, a.predictive_loglik, rtol=rtol)
        assert b.gated.tolist() == a.gated.tolist() and b.degenerate.tolist() == a.degenerate.tolist()
        np.testing.assert_allclose(b.gate_score, a.gate_score, rtol=1e-6)
    np.testing.assert_allclose(c_state.points, np_state.points, rtol=rtol, atol=1e-12)
    np.testing.assert_allclose(c_state.log_weights, np_state.log_weights, rtol=rtol, atol=1e-9)
    assert c_state.restarts == np_state.restarts and c_state.reason == np_state.reason


def test_continuous_increments_in_chunks(monkeypatch):
    model = sensors(6, 512)
    rows = simulate(model, 120, np.random.default_rng(3)).increments.copy()
    rows[50:53] = np.nan  # whole rows only predict
    rows[70, 2] = np.nan  # one block unobserved
    numpy_run, compiled_run = both_paths(monkeypatch, model, rows, chunks=(37,))
    assert numpy_run[1].restarts > 0  # restarts are exercised
    assert_same(numpy_run, compiled_run)


@pytest.mark.parametrize("likelihood", ["gaussian", "student-t"])
def test_discrete_readings_at_irregular_times_with_a_gated_row(monkeypatch, likelihood):
    measurement = {"kind": "discrete"} if likelihood == "gaussian" else {"kind": "discrete",
                                                                         "likelihood": likelihood, "dof": 4}
    model = sensors(5, 512, measurement)
    rng = np.random.default_rng(8)
    times = np.cumsum(rng.uniform(0.004, 0.04, 80))  # gaps past dt go in Euler pieces
    rows = simulate(model, 80, np.random.default_rng(4), times=times).observations.copy()
    rows[rng.random(rows.shape) < 0.2] = np.nan
    rows[30, 1] += 60.0  # far out: gated
    numpy_run, compiled_run = both_paths(monkeypatch, model, rows, times=times, chunks=(41,))
    assert_same(numpy_run, compiled_run)
    if likelihood == "gaussian":
        assert numpy_run[0][0].gated[30]


def test_tempered_reading_and_a_zero_likelihood(monkeypatch):
    """A reading of tiny noise in the prior's tail is tempered (progressive correction); one of 1e6 with
    the gate off cannot be reached: flagged the same way on both paths, the state's weights the
    predicted ones."""
    model = sensors(3, 256, {"kind": "discrete"}, r=np.array([1e-8, 1.0, 1.0]))
    rows = np.array([[np.nan, 0.1, 0.2], [3.0, 0.0, 0.1], [1e6, 0.0, 0.0], [0.0, 0.0, 0.0]])
    numpy_run, compiled_run = both_paths(monkeypatch, model, rows, gate=0.0)
    assert_same(numpy_run, compiled_run)
    assert numpy_run[1].degenerate and np.isfinite(numpy_run[1].log_weights).all()


def test_lattice_noise_is_a_normal_qmc_set():
    """Each block's noise set is {Φ⁻¹((j + U)/N)}: its empirical CDF is within 1/N of Φ everywhere
    (the star discrepancy of a shifted lattice), mean 0 and variance 1 to O(1/N); the blocks' orders
    differ."""
    N, B = 1024, 3
    Q, perm, offset = lattice_normals(N, B, np.random.default_rng(0))
    z = np.sort(Q[(perm[:, None] + offset[None, :]) % N], axis=0)
    ecdf_gap = np.max(np.abs(ndtr(z[:, 0]) - (np.arange(N) + 0.5) / N))
    assert ecdf_gap <= 1.0 / N
    assert abs(Q.mean()) < 5.0 / N and abs(Q.var() - 1.0) < 20.0 / N
    noise = Q[(perm[:, None] + offset[None, :]) % N]
    assert not np.array_equal(noise[:, 0], noise[:, 1])
    assert np.allclose(np.sort(noise, axis=0), np.sort(Q)[:, None])


def test_a_one_shot_command_compiles_only_where_the_rows_repay_numba(monkeypatch):
    """The CLI's kernel choice (solver/jit.py choose_for_rows with the filter's ``compiled_min_rows``):
    100 sensors at 4096 points repay numba's start-up within ~100 rows, 10 within ~1000; a coupled
    block of 2 states at 256 points (~0.5 µs a row saved) within ~10⁵."""
    from yauyau.solver import jit

    monkeypatch.delenv("YAUYAU_KERNEL", raising=False)
    hundred, ten = YauNiuFilter(sensors(100, 4096)), YauNiuFilter(sensors(10, 4096))
    assert 50 <= hundred.compiled_min_rows <= 200 and 500 <= ten.compiled_min_rows <= 2000
    with jit.one_shot():
        assert jit.choose_for_rows(300, hundred.compiled_min_rows) == "compiled"
    with jit.one_shot():
        assert jit.choose_for_rows(300, ten.compiled_min_rows) == "numpy"
    doc = {"name": "ring", "state": ["a", "b"], "drift": ["-a + 0.5*tanh(b)", "-b"], "observation": ["a**3"],
           "method": "yau-niu", "discretization": {"dt": DT, "points": 256},
           "initial": {"kind": "gaussian", "mean": [0.0, 0.0], "cov": np.eye(2).tolist()}}
    coupled = YauNiuFilter(compile_model(spec_from_dict(doc)))
    assert 50_000 <= coupled.compiled_min_rows <= 200_000
    with jit.one_shot():
        assert jit.choose_for_rows(10_000, coupled.compiled_min_rows) == "numpy"
    with jit.one_shot():
        assert jit.choose_for_rows(10**6, coupled.compiled_min_rows) == "compiled"
