"""Kalman–Bucy filter against closed forms and against the discrete Kalman filter as dt -> 0."""

import numpy as np
import pytest
from scipy.integrate import quad
from yauyau.solver.errors import InputError, SpecError
from yauyau.solver.exact.kalman_bucy import KINDS, KalmanBucyFilter
from yauyau.solver.filtering import Filter
from yauyau.solver.model import compile_model
from yauyau.solver.reference.kalman import DiscreteKalmanFilter
from yauyau.solver.simulate import simulate
from yauyau.solver.spec import spec_from_dict


def _model(dt=0.05, drift=("-0.8*x + 0.3",), observation=("1.5*x - 0.2",), a=0.6, R=0.4,
           state=("x",), prior=None):
    prior = prior or {"kind": "gaussian", "mean": [0.7] * len(state), "cov": np.eye(len(state)).tolist()}
    spec = {"name": "kb", "state": list(state), "drift": list(drift), "observation": list(observation),
            "diffusion": (np.eye(len(state)) * a).tolist(),
            "observation_noise": (np.eye(len(observation)) * R).tolist(),
            "initial": prior, "domain": {"radius": 10.0}, "discretization": {"dt": dt, "basis": 8}}
    return compile_model(spec_from_dict(spec))


def test_scalar_riccati_closed_form():
    # P' = 2FP + a − (H²/R)P²: (P − p₊)/(P − p₋) = (P0 − p₊)/(P0 − p₋)·exp(−β(p₊ − p₋)t)
    F, a, H, R, dt = -0.8, 0.6, 1.5, 0.4, 0.05
    model = _model(dt=dt)
    kb = KalmanBucyFilter(model)
    assert isinstance(kb, Filter) and kb.method == "kalman-bucy"
    state = kb.initial_state()
    rng = np.random.default_rng(0)
    state, ests = kb.run(state, rng.normal(size=(20, 1)) * 0.1)
    beta = H * H / R
    root = np.sqrt(F * F + a * beta)
    p_plus, p_minus = (F + root) / beta, (F - root) / beta
    t = dt * np.arange(1, 21)
    ratio = (1.0 - p_plus) / (1.0 - p_minus) * np.exp(-beta * (p_plus - p_minus) * t)
    P = (p_plus - ratio * p_minus) / (1 - ratio)
    np.testing.assert_allclose([e.cov[0, 0] for e in ests], P, rtol=1e-10)


def test_scalar_mean_and_loglik_closed_form_at_stationary_covariance():
    # P0 = p₊: P stays constant, m' = κ m + c is linear with a constant observation rate ẏ,
    # and d log Z/dt = ĥR⁻¹ẏ − ½ĥR⁻¹ĥ − ½H²P/R (mass of the robust DMZ solution)
    F, f0, a, H, h0, R, dt = -0.8, 0.3, 0.6, 1.5, -0.2, 0.4, 0.05
    beta = H * H / R
    p = (F + np.sqrt(F * F + a * beta)) / beta
    m0, ydot = 0.7, 0.9
    model = _model(dt=dt, prior={"kind": "gaussian", "mean": [m0], "cov": [[p]]})
    kb = KalmanBucyFilter(model)
    state, ests = kb.run(kb.initial_state(), np.full((30, 1), ydot * dt))
    kappa, c = F - p * beta, f0 + p * H / R * (ydot - h0)
    m = lambda s: -c / kappa + (m0 + c / kappa) * np.exp(kappa * s)  # noqa: E731
    t = dt * np.arange(1, 31)
    np.testing.assert_allclose([e.mean[0] for e in ests], m(t), rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose([e.cov[0, 0] for e in ests], p, rtol=1e-10)
    rate = lambda s: ((H * m(s) + h0) * ydot - 0.5 * (H * m(s) + h0) ** 2 - 0.5 * H * H * p) / R  # noqa: E731
    assert state.loglik == pytest.approx(quad(rate, 0, t[-1], epsabs=1e-13)[0], abs=1e-9)


def test_missing_rows_only_predict():
    model = _model(dt=0.1)
    kb = KalmanBucyFilter(model)
    state, ests = kb.run(kb.initial_state(), np.full((5, 1), np.nan))
    F, a = -0.8, 0.6
    t = 0.1 * np.arange(1, 6)
    P = np.exp(2 * F * t) * 1.0 + a * (np.exp(2 * F * t) - 1) / (2 * F)
    m = np.exp(F * t) * 0.7 + 0.3 * (np.exp(F * t) - 1) / F
    np.testing.assert_allclose([e.cov[0, 0] for e in ests], P, rtol=1e-11)
    np.testing.assert_allclose([e.mean[0] for e in ests], m, rtol=1e-11)
    assert all(e.loglik_increment == 0.0 for e in ests)


def _run_final(model_dt, fine, ratio, kind):
    """Run on the fine increments summed ``ratio`` at a time (the same path at step model_dt)."""
    model = _model(dt=model_dt, drift=("-0.5*x + 0.4*y", "-0.6*x - 0.3*y"), observation=("x + 0.5*y",),
                   state=("x", "y"), a=0.5, R=0.3)
    kb = KalmanBucyFilter(model, kind=kind)
    incs = fine.reshape(-1, ratio, fine.shape[1]).sum(axis=1)
    state, _ = kb.run(kb.initial_state(), incs)
    return state


def test_kalman_bucy_and_discrete_kalman_converge_at_rate_one():
    fine_dt, K = 0.0025, 320  # a 2-D model, one path on [0, 0.8]
    sim = simulate(_model(dt=fine_dt, drift=("-0.5*x + 0.4*y", "-0.6*x - 0.3*y"), observation=("x + 0.5*y",),
                          state=("x", "y"), a=0.5, R=0.3), K, np.random.default_rng(3))
    gaps = []
    for ratio in (32, 16, 8):
        dt = fine_dt * ratio
        kb, dk = (_run_final(dt, sim.increments, ratio, kind) for kind in ("continuous", "discrete"))
        gaps.append((np.linalg.norm(kb.mean - dk.mean), np.linalg.norm(kb.cov - dk.cov),
                     abs(kb.loglik - dk.loglik)))
    gaps = np.array(gaps)
    rates = np.log2(gaps[:-1, :2] / gaps[1:, :2])  # mean and covariance gaps: O(dt)
    assert np.all(rates > 0.9) and np.all(rates < 1.1), rates
    assert gaps[-1, 0] < 0.01 and gaps[-1, 1] < 0.01
    # the log-likelihood gap is a sum of random O(dt²) terms (no clean rate on one path): bound it
    assert np.all(gaps[:, 2] < 0.1 * fine_dt * np.array([32, 16, 8]))


def test_errors_name_the_field():
    with pytest.raises(SpecError, match="^drift"):
        KalmanBucyFilter(_model(drift=("tanh(x)",)))
    with pytest.raises(SpecError, match="^observation"):
        KalmanBucyFilter(_model(observation=("x**3",)))
    with pytest.raises(SpecError, match="^kind"):
        KalmanBucyFilter(_model(), kind="extended")
    kb = KalmanBucyFilter(_model())
    with pytest.raises(InputError):
        kb.run(kb.initial_state(), [[np.inf]])
    with pytest.raises(InputError):
        kb.state_from_dict({"mean": "x"})


def test_state_round_trip_and_density():
    kb = KalmanBucyFilter(_model())
    state, _ = kb.run(kb.initial_state(), [[0.1], [np.nan], [-0.05]])
    again = kb.state_from_dict(state.to_dict())
    s1, e1 = kb.step(state, np.array([0.02]))
    s2, e2 = kb.step(again, np.array([0.02]))
    assert e1.mean == pytest.approx(e2.mean) and s1.loglik == pytest.approx(s2.loglik)
    x = np.linspace(-8, 8, 4001)[:, None]
    assert np.sum(kb.density(s1, x)) * (x[1, 0] - x[0, 0]) == pytest.approx(1.0, abs=1e-8)


def _assert_matches_reference(ests, ref, incs, rtol, loglik_abs):
    """Estimates against the step-by-step reference Kalman filter on the same rows."""
    state = ref.initial_state()
    for k, row in enumerate(incs):
        state, e2 = ref.step(state, row)
        np.testing.assert_allclose(ests[k].mean, e2.mean, rtol=rtol, atol=rtol / 10)
        np.testing.assert_allclose(ests[k].cov, e2.cov, rtol=rtol, atol=1e-12)
        assert ests[k].loglik == pytest.approx(e2.loglik, abs=loglik_abs)


@pytest.mark.parametrize("state", [("x",), ("x", "y")])
def test_discrete_kind_equals_the_reference_kalman_filter_step_by_step(state):
    # the chunked discrete kind (covariance path, then one affine mean recursion) against the
    # step-by-step reference Kalman filter, missing rows included (scalar and matrix paths)
    two = len(state) == 2
    drift = ("-0.5*x + 0.4*y", "-0.6*x - 0.3*y") if two else ("-0.8*x + 0.3",)
    observation = ("x + 0.5*y", "y - 0.1") if two else ("1.5*x - 0.2",)
    model = _model(dt=0.05, state=state, drift=drift, observation=observation)
    incs = simulate(model, 80, np.random.default_rng(7)).increments
    incs[20:25] = np.nan
    kb, ref = KalmanBucyFilter(model, kind="discrete"), DiscreteKalmanFilter(model)
    s1, e1 = kb.run(kb.initial_state(), incs)
    _assert_matches_reference(e1, ref, incs, rtol=1e-11, loglik_abs=1e-10)
    assert all(e.loglik_increment == 0.0 for e in e1[20:25])


@pytest.mark.parametrize("kind", KINDS)
def test_chunking_does_not_change_the_estimates(kind):
    kb = KalmanBucyFilter(_model(), kind=kind)
    incs = simulate(kb.model, 60, np.random.default_rng(8)).increments
    incs[30] = np.nan
    whole, est = kb.run(kb.initial_state(), incs)
    state, parts = kb.initial_state(), []
    for piece in (incs[:1], incs[1:31], incs[31:59], incs[59:]):
        state, part = kb.run(state, piece)
        parts += part
    state, last = kb.step(state, np.array([0.01]))
    whole, again = kb.step(whole, np.array([0.01]))
    np.testing.assert_allclose([e.mean for e in parts], [e.mean for e in est], rtol=1e-12, atol=1e-14)
    assert state.loglik == pytest.approx(whole.loglik, abs=1e-12) and last.mean == pytest.approx(again.mean)


# -- cached schedules: long runs that cross the point where the covariance path settles --------
_TWO_D = {"state": ("x", "y"), "drift": ("-0.5*x + 0.4*y", "-0.6*x - 0.3*y"), "observation": ("x + 0.5*y",),
          "a": 0.5, "R": 0.3}


def _pieces(incs, sizes):
    """Split rows into chunks of the given sizes (cycled), one-row chunks included."""
    out, start, k = [], 0, 0
    while start < len(incs):
        out.append(incs[start:start + sizes[k % len(sizes)]])
        start, k = start + sizes[k % len(sizes)], k + 1
    return out


def _kalman_bucy_ode_step(F, f0, a, H, h0, R_inv, m, P, ydot, dt):
    """m, P, log Z over one step of constant ẏ: the Kalman–Bucy ODEs with the robust-DMZ mass rate
    d log Z/dt = ĥᵀR⁻¹ẏ − ½ĥᵀR⁻¹ĥ − ½tr(HᵀR⁻¹HP), ĥ = Hm + h0 (integrated by solve_ivp)."""
    from scipy.integrate import solve_ivp
    n = len(m)

    def rhs(_t, y):
        mean, cov = y[:n], y[n:n + n * n].reshape(n, n)
        hhat = H @ mean + h0
        dm = F @ mean + f0 + cov @ H.T @ R_inv @ (ydot - hhat)
        dP = F @ cov + cov @ F.T + a - cov @ H.T @ R_inv @ H @ cov
        dlog = hhat @ R_inv @ ydot - 0.5 * hhat @ R_inv @ hhat - 0.5 * np.trace(H.T @ R_inv @ H @ cov)
        return np.concatenate([dm, dP.ravel(), [dlog]])

    y = solve_ivp(rhs, (0, dt), np.concatenate([m, P.ravel(), [0.0]]), method="DOP853", rtol=1e-12,
                  atol=1e-13).y[:, -1]
    return y[:n], y[n:n + n * n].reshape(n, n), y[-1]


@pytest.mark.parametrize("two", [False, True])
def test_continuous_kind_against_the_kalman_bucy_odes_across_settling(two):
    # chunks of 1, 7 and 40 rows: the covariance path settles (to rounding) on the way (after 169
    # steps in 1-D, 415 in 2-D), then the steady step is reused; estimates checked against the ODEs
    kw = _TWO_D if two else {}
    model = _model(dt=0.05, **kw)
    kb = KalmanBucyFilter(model)
    incs = simulate(model, 480 if two else 240, np.random.default_rng(11)).increments
    state, ests = kb.initial_state(), []
    for piece in _pieces(incs, (1, 7, 40, 1, 1)):
        state, part = kb.run(state, piece)
        ests += part
    assert any(schedule.settled for schedule, _ in kb._schedules._positions.values())
    F, f0 = kb.F, kb.f0
    m, P, loglik = np.full(model.n, 0.7), np.eye(model.n), 0.0
    for k, row in enumerate(incs):
        m, P, dlog = _kalman_bucy_ode_step(F, f0, model.a, kb.H, kb.h0, model.R_inv, m, P, row / model.dt,
                                           model.dt)
        loglik += dlog
        if k % 13 == 0 or k == len(incs) - 1:
            np.testing.assert_allclose(ests[k].mean, m, rtol=1e-8, atol=1e-9)
            np.testing.assert_allclose(ests[k].cov, P, rtol=1e-8, atol=1e-10)
            assert ests[k].loglik == pytest.approx(loglik, abs=1e-8)


def test_settled_covariance_is_the_algebraic_riccati_solution():
    # P∞ solves FP + PFᵀ + a − PHᵀR⁻¹HP = 0: closed form in 1-D, scipy's CARE solver in 2-D
    from scipy.linalg import solve_continuous_are
    F, a, H, R = -0.8, 0.6, 1.5, 0.4
    beta = H * H / R
    kb = KalmanBucyFilter(_model(dt=0.05))
    state, _ = kb.run(kb.initial_state(), np.zeros((400, 1)))
    assert state.cov[0, 0] == pytest.approx((F + np.sqrt(F * F + a * beta)) / beta, rel=1e-13)
    kb2 = KalmanBucyFilter(_model(dt=0.05, **_TWO_D))
    state, _ = kb2.run(kb2.initial_state(), np.zeros((1200, 1)))
    care = solve_continuous_are(kb2.F.T, kb2.H.T, kb2.model.a, kb2.model.R)
    np.testing.assert_allclose(state.cov, care, rtol=1e-11)


@pytest.mark.parametrize("two", [False, True])
def test_discrete_kind_long_run_in_odd_chunks_equals_the_reference(two):
    # scheduled steps (one-row and longer chunks, before and after settling, a missing row after
    # settling that starts a new schedule) against the step-by-step reference Kalman filter
    kw = _TWO_D if two else {}
    model = _model(dt=0.05, **kw)
    incs = simulate(model, 560, np.random.default_rng(12)).increments
    incs[500] = np.nan  # after the path settled (169 steps in 1-D, 424 in 2-D)
    kb, ref = KalmanBucyFilter(model, kind="discrete"), DiscreteKalmanFilter(model)
    state, ests = kb.initial_state(), []
    for piece in _pieces(incs, (1, 1, 50, 3)):
        state, part = kb.run(state, piece)
        ests += part
    assert any(schedule.settled for schedule, _ in kb._schedules._positions.values())
    _assert_matches_reference(ests, ref, incs, rtol=1e-10, loglik_abs=1e-9)
    assert ests[500].loglik_increment == 0.0
