"""Wei–Norman filter of seed 004 Theorem 1 against independent truths.

1. (13) checked symbolically: u = e^{r0} e^{r1 x1} e^{r2 D1} v with ∂v/∂t = L0 v solves the robust DMZ
   equation (10) exactly when r follows (13) (and not with a sign changed).
2. n = 1 linear model: for a piecewise-linear path y the DMZ solution is Gaussian with mean and
   covariance from the Kalman–Bucy ODEs driven by ẏ (integrated here with solve_ivp) and
   log ∫σ = ∫ (E h) R⁻¹ẏ − ½ R⁻¹ E h² dt.
3. Seed 004's n = 3 example: a finite-difference solution of the DMZ equation ∂σ/∂t = L0σ + ẏ h σ
   (same piecewise-linear y) on a grid, short horizon; mean gap ≤ 0.02.
4. Beneš (f = tanh x, h = x; η = 1 + x², A = 1, a shift integral log cosh that is no polynomial):
   σ = cosh(x)·q with q the Kalman–Bucy density of dx = dv (ODEs below), through ``run_arrays``
   in uneven chunks.
"""

from __future__ import annotations

import numpy as np
import pytest
import sympy as sp
from scipy.integrate import solve_ivp
from scipy.interpolate import RegularGridInterpolator
from yauyau.solver.errors import InputError, SpecError
from yauyau.solver.exact.wei_norman import WeiNormanFilter, kolmogorov_flow_from_offline
from yauyau.solver.filtering import Filter
from yauyau.solver.model import compile_model
from yauyau.solver.spec import spec_from_dict

SEED004_DRIFT = ["x1 + x2 - x3", "x1 + x2**2 + x3**2 + x3 - x2 + 1", "-x1 + x2**2 + x3**2"]


def make(state, drift, obs, mean, cov, radius, dt, **extra):
    spec = {"name": "wn", "state": state, "drift": drift, "observation": obs,
            "initial": {"kind": "gaussian", "mean": mean, "cov": cov},
            "domain": {"radius": radius}, "discretization": {"dt": dt, "basis": 10}}
    spec.update(extra)
    return compile_model(spec_from_dict(spec))


# ---------------------------------------------------------------------------------------------
# 1. the ODEs (13), symbolically on the seed's example
# ---------------------------------------------------------------------------------------------
def kolmogorov(w, f, h, X):
    """L0 w = ½Δw − f·∇w − (div f) w − ½h² w   (seed 004 (2))."""
    return (sum(sp.diff(w, xi, 2) for xi in X) / 2
            - sum(fi * sp.diff(w, xi) for fi, xi in zip(f, X, strict=True))
            - sum(sp.diff(fi, xi) for fi, xi in zip(f, X, strict=True)) * w - h**2 * w / 2)


def robust_dmz_residual(rdot):
    """Residual of (10) for the ansatz (12) on the seed's example, h = x1 (c = 1).

    v(t, ·) is a generic function V with ∂v/∂t = L0 v; u is written in s = x1 + r2, x2, x3, so
    ∂/∂x1 = ∂/∂s and d/dt at fixed x adds ṙ2 ∂/∂s.
    """
    s, x2, x3, r0, r1, r2, Y = sp.symbols("s x2 x3 r0 r1 r2 Y", real=True)
    X = (s, x2, x3)

    def drift(x1):
        return [x1 + x2 - x3, x1 + x2**2 + x3**2 + x3 - x2 + 1, -x1 + x2**2 + x3**2]

    x1 = s - r2
    V = sp.Function("V")(*X)
    # e^{r2 D1} v = v(x1 + r2) exp(−∫_0^{r2} f1(x1 + τ) dτ), f1 = x1 + x2 − x3
    log_factor = r0 + r1 * x1 - (r2 * (x1 + x2 - x3) + r2**2 / 2)
    u = sp.exp(log_factor) * V
    v_t = kolmogorov(V, drift(s), s, X)  # at the shifted point: f(s, x2, x3), h = s
    du_dt = (sp.diff(u, r0) * rdot[0] + sp.diff(u, r1) * rdot[1] + sp.diff(u, r2) * rdot[2]
             + sp.diff(u, s) * rdot[2] + sp.exp(log_factor) * v_t)
    f = drift(x1)
    rhs = kolmogorov(u, f, x1, X) + Y * (sp.diff(u, s) - f[0] * u) + Y**2 * u / 2  # (10) = (23)
    return sp.simplify(sp.expand((du_dt - rhs) / sp.exp(log_factor)))


def test_seed004_odes_13_solve_the_robust_dmz_equation():
    r1, r2, Y = sp.symbols("r1 r2 Y", real=True)
    a2, a1 = 4, 2  # η = 4x1² + 2x1 + γ(x2, x3) for the seed's example
    rdot = (r1**2 / 2 + a2 * r2**2 / 2 + Y * r1 + a1 * r2 / 2 + Y**2 / 2, a2 * r2, r1 + Y)  # (13)
    assert robust_dmz_residual(rdot) == 0
    assert robust_dmz_residual((rdot[0], rdot[1], r1 - Y)) != 0  # a sign slip in ṙ2 is caught
    assert robust_dmz_residual((rdot[0] - a1 * r2, rdot[1], rdot[2])) != 0  # and one in ṙ0


# ---------------------------------------------------------------------------------------------
# 2. n = 1 linear model against the Kalman–Bucy ODEs driven by ẏ
# ---------------------------------------------------------------------------------------------
THETA, B, C, D, R = 0.5, 0.3, 2.0, 0.1, 0.5  # f = −θx + b, h = c x + d, E dw² = R dt
MEAN0, VAR0, DT = 0.4, 0.6, 0.05


def kalman_bucy(ydot, t_end, state0):
    """(m, P, log Z)' for ∂σ/∂t = L0 σ + ẏ R⁻¹ h σ with a Gaussian σ (exact for linear models)."""
    def rhs(_, z):
        m, P, _logz = z
        eh = C * m + D
        return [-THETA * m + B + P * C / R * (ydot - eh), -2 * THETA * P + 1.0 - P * P * C * C / R,
                eh * ydot / R - 0.5 * (eh * eh + C * C * P) / R]
    return solve_ivp(rhs, (0.0, t_end), state0, rtol=1e-11, atol=1e-12, dense_output=True)


def test_linear_model_matches_kalman_bucy_with_loglik():
    model = make(["x"], [f"-{THETA}*x + {B}"], [f"{C}*x + {D}"], [MEAN0], [[VAR0]], radius=8.0, dt=DT,
                 observation_noise=[[R]])
    K = 16
    flow = kalman_bucy(0.0, K * DT, [MEAN0, VAR0, 0.0]).sol  # e^{tL0}σ0 = Z0 N(m0, P0)

    def log_flow(t, X):
        m, P, logz = flow(t)
        return logz - 0.5 * (X[:, 0] - m) ** 2 / P - 0.5 * np.log(2 * np.pi * P)

    wn = WeiNormanFilter(model, log_flow, log_flow=True)
    assert isinstance(wn, Filter)
    increments = np.random.default_rng(3).normal(0.2 * DT, np.sqrt(R * DT), size=(K, 1))
    state, estimates = wn.run(wn.initial_state(), increments)
    truth = [MEAN0, VAR0, 0.0]
    for k, est in enumerate(estimates):
        truth = kalman_bucy(increments[k, 0] / DT, DT, truth).y[:, -1]
        assert est.mean[0] == pytest.approx(truth[0], abs=1e-6)
        assert est.cov[0, 0] == pytest.approx(truth[1], abs=1e-6)
        assert est.loglik == pytest.approx(truth[2], abs=1e-6)
    again = wn.state_from_dict(state.to_dict())
    assert wn.estimate(again).mean[0] == pytest.approx(estimates[-1].mean[0], abs=1e-12)

    # the same path as arrays, in uneven chunks continued from the returned states
    state, truth, k = wn.initial_state(), [MEAN0, VAR0, 0.0], 0
    for size in (5, 1, 10):
        state, chunk = wn.run_arrays(state, increments[k:k + size])
        for j in range(size):
            truth = kalman_bucy(increments[k + j, 0] / DT, DT, truth).y[:, -1]
            assert chunk.step[j] == k + j + 1 and chunk.t[j] == pytest.approx((k + j + 1) * DT)
            assert chunk.mean[j, 0] == pytest.approx(truth[0], abs=1e-6)
            assert chunk.cov[j, 0, 0] == pytest.approx(truth[1], abs=1e-6)
            assert chunk.loglik[j] == pytest.approx(truth[2], abs=1e-6)
        k += size
    assert not chunk.degenerate.any() and state.step == K


def test_linear_model_with_the_stored_kolmogorov_propagator():
    from yauyau.solver.offline.pipeline import precompute

    model = make(["x"], [f"-{THETA}*x + {B}"], [f"{C}*x + {D}"], [MEAN0], [[VAR0]], radius=8.0, dt=DT,
                 observation_noise=[[R]], discretization={"dt": DT, "basis": 120})
    wn = WeiNormanFilter(model, kolmogorov_flow_from_offline(precompute(model)))
    increments = np.random.default_rng(3).normal(0.2 * DT, np.sqrt(R * DT), size=(12, 1))
    _, estimates = wn.run(wn.initial_state(), increments)
    truth = [MEAN0, VAR0, 0.0]
    for k, est in enumerate(estimates):
        truth = kalman_bucy(increments[k, 0] / DT, DT, truth).y[:, -1]
        assert est.mean[0] == pytest.approx(truth[0], abs=1e-3)
        assert est.cov[0, 0] == pytest.approx(truth[1], abs=1e-3)
        assert est.loglik == pytest.approx(truth[2], abs=1e-3)


# ---------------------------------------------------------------------------------------------
# 3. seed 004's n = 3 example against a finite-difference DMZ solution
# ---------------------------------------------------------------------------------------------
class GridDMZ:
    """∂σ/∂t = ½Δσ − ∇·(fσ) − ½h²σ + ẏ h σ on a box, zero outside; Heun in time, central in space."""

    def __init__(self, model, half_width, spacing):
        self.h = spacing
        self.axis = np.arange(-half_width, half_width + spacing / 2, spacing)
        mesh = np.meshgrid(*([self.axis] * 3), indexing="ij")
        self.points = np.stack([g.ravel() for g in mesh], axis=1)
        shape = mesh[0].shape
        self.f = model.f(self.points).T.reshape(3, *shape)
        self.hx = model.h(self.points)[:, 0].reshape(shape)
        self.shape = shape

    def rhs(self, s, ydot):
        h = self.h
        p = np.pad(s, 1)
        out = (p[2:, 1:-1, 1:-1] + p[:-2, 1:-1, 1:-1] + p[1:-1, 2:, 1:-1] + p[1:-1, :-2, 1:-1]
               + p[1:-1, 1:-1, 2:] + p[1:-1, 1:-1, :-2] - 6 * s) / (2 * h * h)
        for i in range(3):
            F = np.pad(self.f[i] * s, 1)
            lo = [slice(1, -1)] * 3
            hi = [slice(1, -1)] * 3
            lo[i], hi[i] = slice(None, -2), slice(2, None)
            out -= (F[tuple(hi)] - F[tuple(lo)]) / (2 * h)
        return out + (ydot * self.hx - 0.5 * self.hx**2) * s

    def advance(self, s, ydot, duration, steps):
        tau = duration / steps
        for _ in range(steps):
            k1 = self.rhs(s, ydot)
            s = s + 0.5 * tau * (k1 + self.rhs(s + tau * k1, ydot))
        return s


@pytest.mark.slow
def test_seed004_example_matches_finite_difference_dmz():
    dt, K, var0 = 0.05, 6, 0.1  # short: this drift (x2' ~ x2²) explodes in finite time
    model = make(["x1", "x2", "x3"], SEED004_DRIFT, ["x1"], [0.0, 0.0, 0.0],
                 (var0 * np.eye(3)).tolist(), radius=3.0, dt=dt)
    grid = GridDMZ(model, half_width=3.0, spacing=0.1)
    sigma0 = np.exp(-0.5 * (grid.points**2).sum(axis=1) / var0).reshape(grid.shape)
    sigma0 /= sigma0.sum() * grid.h**3
    substeps = 20  # Heun step dt/20 = 0.0025: stable for ½Δ with spacing 0.1 (λ·τ = 1.5 < 2)
    increments = 0.3 + np.random.default_rng(7).normal(0.0, np.sqrt(dt), size=(K, 1))

    snapshots, v = [sigma0], sigma0
    for _ in range(K):
        v = grid.advance(v, 0.0, dt, substeps)
        snapshots.append(v)
    interpolants = [RegularGridInterpolator((grid.axis,) * 3, snap, bounds_error=False, fill_value=0.0)
                    for snap in snapshots]

    def kolmogorov_flow(t, X):
        return interpolants[int(round(t / dt))](X)

    weights = np.full(len(grid.points), grid.h**3)
    wn = WeiNormanFilter(model, kolmogorov_flow, nodes=grid.points, weights=weights)
    state, estimates = wn.run(wn.initial_state(), increments)
    sigma, gaps = sigma0, []
    for k, est in enumerate(estimates):
        sigma = grid.advance(sigma, increments[k, 0] / dt, dt, substeps)
        w = sigma.ravel() / sigma.sum()
        gaps.append(np.abs(est.mean - w @ grid.points).max())
        assert not est.degenerate
    # the shift e^{r2 D1} is exercised: without it (or with the integrating factor inverted) the
    # mean gap is about 0.16-0.19 on this path; with it about 0.0015
    assert state.r[2] > 0.2
    assert np.mean(gaps) <= 0.02 and max(gaps) <= 0.02


# ---------------------------------------------------------------------------------------------
# 4. Beneš: σ = cosh(x) q, q the Kalman–Bucy density of dx = dv, dy = x dt + dw
# ---------------------------------------------------------------------------------------------
def benes_truth(ydot, t_end, state0):
    """(m, P, log Z) of q = Z N(m, P): ∂q/∂t = ½q'' − ½q − ½x²q + ẏ x q (f' + f² = 1 for tanh)."""
    def rhs(_, z):
        m, P, _logz = z
        return [P * (ydot - m), 1.0 - P * P, m * ydot - 0.5 * (m * m + P) - 0.5]
    return solve_ivp(rhs, (0.0, t_end), state0, rtol=1e-11, atol=1e-12, dense_output=True)


def log_cosh(x):
    return np.logaddexp(x, -x) - np.log(2.0)


def test_benes_through_run_arrays_in_chunks():
    m0, p0, dt = 0.3, 0.5, 0.05
    model = make(["x"], ["tanh(x)"], ["x"], [m0], [[p0]], radius=9.0, dt=dt)
    start = [m0, p0, -(0.5 * p0 + log_cosh(m0))]  # σ0 = cosh(x) N(m0, P0) / (e^{P0/2} cosh m0)
    flow = benes_truth(0.0, 1.0, start).sol

    def log_flow(t, X):
        m, P, logz = flow(t)
        return logz + log_cosh(X[:, 0]) - 0.5 * (X[:, 0] - m) ** 2 / P - 0.5 * np.log(2 * np.pi * P)

    wn = WeiNormanFilter(model, log_flow, log_flow=True)
    assert wn.A == 1.0 and wn._shift_poly is None  # the pointwise shift integral is exercised
    increments = np.random.default_rng(5).normal(1.5 * dt, np.sqrt(dt), size=(18, 1))
    state, truth, k = wn.initial_state(), start, 0
    for size in (7, 1, 10):
        state, chunk = wn.run_arrays(state, increments[k:k + size])
        for j in range(size):
            truth = benes_truth(increments[k + j, 0] / dt, dt, truth).y[:, -1]
            m, P, logz = truth
            mean, var = m + P * np.tanh(m), P + P * P / np.cosh(m) ** 2
            assert chunk.mean[j, 0] == pytest.approx(mean, abs=1e-6)
            assert chunk.cov[j, 0, 0] == pytest.approx(var, abs=1e-6)
            assert chunk.loglik[j] == pytest.approx(logz + 0.5 * P + log_cosh(m), abs=1e-6)
        k += size
    assert abs(state.r[2]) > 0.05  # the shift is exercised (log cosh moves by ~r2: far above 1e-6)


def test_a_vanished_step_inside_a_chunk_is_flagged_and_the_rest_continues():
    dt = 0.1

    def flow(t, X):  # e^{tL0}σ0 reported as zero at step 3 only
        return np.zeros(len(X)) if round(t / dt) == 3 else np.exp(-0.5 * X[:, 0] ** 2 * (1 + t))

    wn = WeiNormanFilter(ou(), flow)
    state, chunk = wn.run_arrays(wn.initial_state(), np.full((6, 1), 0.05))
    assert chunk.degenerate.tolist() == [False, False, True, False, False, False]
    assert chunk.reason and "r2" in chunk.reason and not state.degenerate
    assert chunk.loglik[2] == chunk.loglik[1] and chunk.loglik_increment[2] == 0.0
    assert chunk.loglik_increment[3] == pytest.approx(chunk.loglik[3] - chunk.loglik[1], abs=1e-12)
    for array in (chunk.mean, chunk.cov, chunk.mode, chunk.loglik):
        assert np.all(np.isfinite(array))
    estimates = chunk.estimates()
    assert estimates[2].degenerate and estimates[2].mode is None and not estimates[3].degenerate


# ---------------------------------------------------------------------------------------------
# refusals, each naming the field
# ---------------------------------------------------------------------------------------------
def ou(**extra):
    return make(["x"], ["-x"], ["x"], [0.0], [[1.0]], radius=6.0, dt=0.1, **extra)


def test_outside_the_class_is_refused():
    cubic = make(["x"], ["-x"], ["x**3"], [0.0], [[1.0]], radius=6.0, dt=0.1)
    with pytest.raises(SpecError) as err:
        WeiNormanFilter(cubic, lambda t, X: np.ones(len(X)))
    assert err.value.field == "method"
    with pytest.raises(SpecError) as err:
        WeiNormanFilter(ou(diffusion=[[2.0]]), lambda t, X: np.ones(len(X)))
    assert err.value.field == "diffusion"


def test_bad_online_input_is_refused():
    wn = WeiNormanFilter(ou(), lambda t, X: np.exp(-X[:, 0] ** 2))
    state = wn.initial_state()
    with pytest.raises(InputError) as err:
        wn.step(state, np.array([np.nan]))
    assert err.value.field == "increments"
    with pytest.raises(InputError):
        wn.run(state, [[0.1], [np.inf]])
    with pytest.raises(InputError) as err:
        wn.run_arrays(state, [[0.1], [np.nan]])
    assert err.value.field == "increments"
    with pytest.raises(InputError) as err:
        wn.initial_state(prior={"kind": "gaussian"})
    assert err.value.field == "prior"
    with pytest.raises(InputError) as err:
        wn.state_from_dict({"step": 1})
    assert err.value.field == "state"
    # (12) runs from t = 0: no irregular times, no forecast, no restart mid-stream; t0 only shifts the clock
    with pytest.raises(InputError) as err:
        wn.run_arrays(state, [[0.1]], [0.5])
    assert err.value.field == "times" and "yau-yau" in err.value.message
    with pytest.raises(InputError) as err:
        wn.predict(state, 1.0)
    assert err.value.field == "t"
    from yauyau.solver.filtering import at_time
    from yauyau.solver.recovery import restart, run_with_policy

    later, result = wn.run_arrays(at_time(state, 2.0), [[0.1], [0.2]])
    dt = wn.model.dt
    assert result.t.tolist() == pytest.approx([2.0 + dt, 2.0 + 2 * dt]) and later.t == result.t[-1]
    with pytest.raises(InputError) as err:
        restart(wn, later, None)
    assert err.value.field == "on_degenerate"
    _, same = run_with_policy(wn, state, [[0.1], [0.2]], None, "reinitialise")  # = "stop" for wei-norman
    assert np.array_equal(same.mean, wn.run_arrays(state, [[0.1], [0.2]])[1].mean)


def test_flow_that_vanishes_is_reported_as_degenerate():
    wn = WeiNormanFilter(ou(), lambda t, X: np.zeros(len(X)))
    _, est = wn.step(wn.initial_state(), np.array([0.1]))
    assert est.degenerate and est.reason and np.all(np.isfinite(est.mean)) and np.all(np.isfinite(est.cov))
