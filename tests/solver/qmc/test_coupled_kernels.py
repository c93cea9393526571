"""The compiled Kolmogorov step and moments of coupled blocks (solver/qmc/coupled.py, kernels.py) against
the numpy path.

The numpy path is the reference (its accuracy is proved against independent truth in test_yau_niu.py:
the Kalman filter at 4 and 6 states, a 10⁶-particle filter of the coupled ring); here both paths run the
same rows on the same seeded noise and must agree to rounding: a coupled ring with restarts, a
diffusion that couples the noise (a non-diagonal a^{1/2}), two coupled blocks with their own weights,
discrete readings at irregular times with long gaps in Euler pieces and missing components, and a
chunked run.  The kernels' moments are also checked against the definitions written here.
"""

from __future__ import annotations

import numpy as np
import pytest
from yauyau.solver.model import compile_model
from yauyau.solver.qmc import kernels
from yauyau.solver.qmc.yau_niu import YauNiuFilter
from yauyau.solver.simulate import simulate
from yauyau.solver.spec import spec_from_dict

DT = 0.01


def coupled(drift, observation, points=2048, diffusion=None, measurement=None):
    n = len(drift)
    doc = {"name": "t", "state": [f"x{i}" for i in range(n)], "drift": drift, "observation": observation,
           "observation_noise": (0.5 * np.eye(len(observation))).tolist(), "method": "yau-niu",
           "initial": {"kind": "gaussian", "mean": [0.5] * n, "cov": np.eye(n).tolist()},
           "discretization": {"dt": DT, "points": points}}
    if diffusion is not None:
        doc["diffusion"] = diffusion
    if measurement is not None:
        doc["measurement"] = measurement
    return compile_model(spec_from_dict(doc))


RING = [f"-x{i} + 0.5*tanh(x{(i + 1) % 4})" for i in range(4)]


def both_paths(monkeypatch, model, rows, times=None, chunks=(None,)):
    out = []
    for kernel in ("numpy", "compiled"):
        monkeypatch.setenv("YAUYAU_KERNEL", kernel)
        flt = YauNiuFilter(model)
        assert flt._singles is None
        state, parts = flt.initial_state(), []
        bounds = [0, *(c for c in chunks if c is not None), len(rows)]
        for a, b in zip(bounds[:-1], bounds[1:], strict=True):
            state, result = flt.run_arrays(state, rows[a:b], None if times is None else times[a:b])
            parts.append(result)
        out.append((flt, parts, state))
    return out


def assert_same(numpy_run, compiled_run, rtol=1e-9):
    (_, np_parts, np_state), (_, c_parts, c_state) = numpy_run, compiled_run
    for a, b in zip(np_parts, c_parts, strict=True):
        np.testing.assert_allclose(b.mean, a.mean, rtol=rtol, atol=1e-12)
        np.testing.assert_allclose(b.cov, a.cov, rtol=rtol, atol=1e-12)
        np.testing.assert_allclose(b.loglik, a.loglik, rtol=rtol)
        assert b.degenerate.tolist() == a.degenerate.tolist()
    np.testing.assert_allclose(c_state.points, np_state.points, rtol=rtol, atol=1e-11)
    np.testing.assert_allclose(c_state.log_weights, np_state.log_weights, rtol=rtol, atol=1e-9)
    assert c_state.restarts == np_state.restarts > 0


def test_the_coupled_ring_with_restarts_in_chunks(monkeypatch):
    """The row and its restarts (coupled.restart by the kernels on the compiled path) against numpy's."""
    model = coupled(RING, [f"x{i}**3" for i in range(4)])
    rows = simulate(model, 60, np.random.default_rng(3)).increments
    numpy_run, compiled_run = both_paths(monkeypatch, model, rows, chunks=(25,))
    assert_same(numpy_run, compiled_run)
    assert compiled_run[2].points.flags.f_contiguous  # the compiled row keeps each coordinate contiguous


def test_a_diffusion_that_couples_the_noise(monkeypatch):
    a = [[1.0, 0.6, 0.0], [0.6, 1.0, 0.3], [0.0, 0.3, 0.5]]
    model = coupled(["-x0 + 0.4*sin(x1)", "-0.5*x1 + 0.2*x2", "-x2 + 0.3*tanh(x0)"], ["x0**3", "x1 + x2"],
                    diffusion=a)
    rows = simulate(model, 50, np.random.default_rng(4)).increments
    assert_same(*both_paths(monkeypatch, model, rows))


def test_two_coupled_blocks_keep_their_own_weights(monkeypatch):
    drift = ["-x0 + 0.5*tanh(x1)", "-x1 + 0.5*tanh(x0)", "-x2 + 0.5*sin(x3)", "-x3 + 0.5*sin(x2)"]
    model = coupled(drift, ["x0**3", "x1", "x2**3", "x3"])
    rows = simulate(model, 50, np.random.default_rng(5)).increments
    numpy_run, compiled_run = both_paths(monkeypatch, model, rows)
    assert len(compiled_run[0].blocks) == 2
    assert_same(numpy_run, compiled_run)


def test_discrete_readings_at_irregular_times_with_missing_components(monkeypatch):
    model = coupled(RING, ["x0**3", "x1 + x2", "x3"], measurement={"kind": "discrete"})
    rng = np.random.default_rng(6)
    times = np.cumsum(rng.uniform(0.5, 3.5, 40) * DT)  # gaps over dt: Euler pieces
    rows = simulate(model, 40, rng, times=times).observations
    rows[::5, 1] = np.nan
    rows[7] = np.nan
    assert_same(*both_paths(monkeypatch, model, rows, times=times, chunks=(17,)))


@pytest.mark.parametrize("owner", [[0, 0, 0], [0, 1, 1]])
def test_the_kernels_moments_against_their_definition(owner):
    rng = np.random.default_rng(7)
    X, W = rng.standard_normal((3, 500)) + 2.0, rng.random((2, 500))
    W /= W.sum(axis=1, keepdims=True)
    owner = np.array(owner, np.int64)
    mean, cov = np.empty(3), np.empty((3, 3))
    kernels.block_moments(X, owner, W, mean, cov)
    for j in range(3):
        w = W[owner[j]]
        assert mean[j] == pytest.approx(sum(w[i] * X[j, i] for i in range(500)), rel=1e-13)
        for k in range(3):
            want = (sum(w[i] * (X[j, i] - mean[j]) * (X[k, i] - mean[k]) for i in range(500))
                    if owner[j] == owner[k] else 0.0)
            assert cov[j, k] == pytest.approx(want, rel=1e-12, abs=1e-15)


def test_the_restart_kernels_against_their_definitions():
    """Systematic resampling: point i takes the first j whose cumulative weight reaches (u + i)/N of
    the total (the inverse CDF at a stratified grid, written out here); the shape sums: Σ w z³ and
    Σ w z⁴ of the whitened cloud along each axis."""
    rng = np.random.default_rng(8)
    N = 300
    w = rng.random(N) ** 4
    w[::7] = 0.0  # points the resampling must never pick
    w /= w.sum()
    picks = np.empty(N, np.int64)
    kernels.systematic(w, 0.37, picks)
    cumulative = np.cumsum(w)
    for i in range(N):
        u = (0.37 + i) / N * cumulative[-1]
        first = next(j for j in range(N) if cumulative[j] >= u)
        assert picks[i] == first and w[picks[i]] > 0.0
    counts = np.bincount(picks, minlength=N)
    assert np.all(np.abs(counts - N * w) < 1.0)  # systematic: each count within 1 of N·w
    X = rng.standard_normal((3, N)) * [[1.0], [2.0], [0.5]] + 1.0
    mean = w @ X.T
    B = np.linalg.cholesky(np.linalg.inv(np.cov(X, aweights=w)))
    third, fourth = np.empty(3), np.empty(3)
    kernels.shape_sums(np.ascontiguousarray(X), w, mean, B, third, fourth)
    for k in range(3):
        z = [sum((X[j, i] - mean[j]) * B[j, k] for j in range(3)) for i in range(N)]
        assert third[k] == pytest.approx(sum(w[i] * z[i] ** 3 for i in range(N)), rel=1e-10, abs=1e-12)
        assert fourth[k] == pytest.approx(sum(w[i] * z[i] ** 4 for i in range(N)), rel=1e-10)
