"""The exact filters with rows at irregular times, partly missing rows, discrete measurements and the
outlier gate (kalman-bucy, yau-hu, yau-jia; wei-norman refuses), against independent truth:

* ``kalman_irregular`` (tests/helpers/irregular_refs.py): the exact Kalman filter at irregular times (Van
  Loan predictions, the observed components only): the oracle of discrete measurements and of the
  time-sampled increment model (KalmanBucyFilter(kind="discrete"));
* the Kalman–Bucy ODEs for (m, P, log Z) with the constant rate ẏ_o = Δy_o/τ over each gap, by
  solve_ivp (DOP853, rtol 1e-12): the robust DMZ solution with y linear between samples, which the
  continuous filters compute exactly (log Z: d log Z/dt = ĥᵀR⁻¹ẏ − ½ĥᵀR⁻¹ĥ − ½tr(HᵀR⁻¹HP));
* the Beneš closed forms: the posterior is cosh(x)·N(μ, Σ) with (μ, Σ) the Kalman–Bucy filter of
  dx = dv, dy = x dt + dw (Σ = tanh/coth(s + c), μ − ẏ ∝ e^{−∫Σ}; log Z by quad of ẏE[x] − ½E[x²]),
  and for discrete measurements the Kalman update of cosh(x)·N(μ, Σ + τ) with evidence
  N(z; μ, Σ + τ + R)·e^{Σ'/2}cosh μ' / (e^{(Σ+τ)/2} cosh μ).

Gaps: exponential with mean dt, 5% of them 10x longer (``random_times``).  Measured (these seeds,
largest errors over 120-300 rows, ~15% missing components): kalman-bucy discrete vs kalman_irregular
7e-16 (mean), 4e-15 (predictive log-lik), 1e-13 (cumulative log-lik); the sampled model 7e-16;
kalman-bucy continuous vs the ODEs 2e-13 (mean), 1e-13 (log-lik increments); yau-hu vs the same
truths 2e-14 (mean), 8e-12 (predictive log-lik, discrete); Beneš closed forms: yau-hu 2e-14
(continuous), 3e-14 and 2e-13 in the evidence (discrete), yau-jia 1e-14; yau-jia vs the ODEs 2e-14.
Tolerances: 1e-10 against the Kalman oracle and Beneš, 1e-9 against the ODEs (their own rtol 1e-12)
and for cumulative sums.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from helpers.irregular_refs import kalman_irregular, linear_prediction, random_times, simulate_irregular
from scipy.integrate import quad, solve_ivp
from threadpoolctl import threadpool_limits
from yauyau.solver.errors import InputError, SpecError
from yauyau.solver.exact.kalman_bucy import KalmanBucyFilter
from yauyau.solver.exact.wei_norman import WeiNormanFilter
from yauyau.solver.exact.yau_hu import YauHuFilter
from yauyau.solver.exact.yau_jia import YauJiaFilter
from yauyau.solver.methods import make_filter
from yauyau.solver.model import compile_model
from yauyau.solver.spec import spec_from_dict

DT = 0.05
# a = I (a Yau filtering system: all three filters apply), m = 2, correlated R
LINEAR = {"name": "lin", "state": ["x", "y"], "drift": ["-0.5*x + 0.4*y + 0.1", "-0.4*x - 0.3*y"],
          "observation": ["x + 0.5*y - 0.2", "y"], "observation_noise": [[0.5, 0.1], [0.1, 0.3]],
          "initial": {"kind": "gaussian", "mean": [0.5, -0.3], "cov": [[0.8, 0.1], [0.1, 0.5]]},
          "domain": {"radius": 8.0}, "discretization": {"dt": DT, "basis": 8}}
LIN = {"F": [[-0.5, 0.4], [-0.4, -0.3]], "f0": [0.1, 0.0], "a": np.eye(2), "H": [[1.0, 0.5], [0.0, 1.0]],
       "h0": [-0.2, 0.0], "R": [[0.5, 0.1], [0.1, 0.3]], "m0": [0.5, -0.3], "P0": [[0.8, 0.1], [0.1, 0.5]]}
# cross-diffusion (Kalman–Bucy only)
CROSS = {"name": "cross", "state": ["x1", "x2"], "drift": ["-0.5*x1 + x2", "-x1 - 0.5*x2"],
         "observation": ["x1", "x2 + 0.5"], "diffusion": [[1.0, 0.3], [0.3, 0.5]],
         "observation_noise": [[0.5, 0.1], [0.1, 0.8]],
         "initial": {"kind": "gaussian", "mean": [0.5, 0.0], "cov": [[1.0, 0.2], [0.2, 0.8]]},
         "domain": {"radius": 4.5}, "discretization": {"dt": DT, "basis": 8}}
CROSS_M = {"F": [[-0.5, 1.0], [-1.0, -0.5]], "f0": [0.0, 0.0], "a": [[1.0, 0.3], [0.3, 0.5]], "H": np.eye(2),
           "h0": [0.0, 0.5], "R": [[0.5, 0.1], [0.1, 0.8]], "m0": [0.5, 0.0], "P0": [[1.0, 0.2], [0.2, 0.8]]}
M0, P0 = 0.3, 0.5  # Beneš prior cosh(x)·N(M0, P0): N(M0 ± P0, P0) with weights ∝ e^{±M0}
BENES = {"name": "benes", "state": ["x"], "drift": ["tanh(x)"], "observation": ["x"],
         "initial": {"kind": "mixture", "weights": [math.exp(-M0), math.exp(M0)],
                     "means": [[M0 - P0], [M0 + P0]], "covs": [[[P0]], [[P0]]]},
         "domain": {"radius": 10.0}, "discretization": {"dt": DT, "basis": 8}}


@pytest.fixture(autouse=True)
def _one_blas_thread():
    """Small matrices: one BLAS thread (the machine is shared; threads only contend)."""
    with threadpool_limits(1):
        yield


def _model(spec, kind="continuous", **measurement):
    return compile_model(spec_from_dict(dict(spec, measurement=dict(kind=kind, **measurement))))


def _data(spec, kind, K, seed, missing=0.15):
    """Random irregular times, simulated rows with ~15% missing components and one missing row."""
    rng = np.random.default_rng(seed)
    times = random_times(rng, K, DT)
    _, rows = simulate_irregular(_model(spec, kind), times, kind, rng)
    rows[rng.random(rows.shape) < missing] = np.nan
    rows[K // 3] = np.nan
    return rows, times


def _oracle(coeffs, rows, times, kind):
    c = coeffs
    return kalman_irregular(c["F"], c["f0"], c["a"], c["H"], c["h0"], c["R"], c["m0"], c["P0"], rows, times,
                            kind)


def _ode_oracle(coeffs, rows, times):
    """(means, covs, log-likelihood increments) of the Kalman–Bucy ODEs, ẏ_o = Δy_o/τ per gap."""
    F, f0, a = (np.asarray(coeffs[k], float) for k in ("F", "f0", "a"))
    H, h0, R = (np.asarray(coeffs[k], float) for k in ("H", "h0", "R"))
    m, P = np.asarray(coeffs["m0"], float), np.asarray(coeffs["P0"], float)
    n, out = len(m), []
    for row, tau in zip(rows, np.diff(times, prepend=0.0), strict=True):
        o = ~np.isnan(row)
        Ho, h0o, Ri, yd = H[o], h0[o], np.linalg.inv(R[np.ix_(o, o)]), row[o] / tau

        def rhs(_t, y, Ho=Ho, h0o=h0o, Ri=Ri, yd=yd):
            mean, cov = y[:n], y[n:n + n * n].reshape(n, n)
            hhat = Ho @ mean + h0o
            dm = F @ mean + f0 + cov @ Ho.T @ Ri @ (yd - hhat)
            dP = F @ cov + cov @ F.T + a - cov @ Ho.T @ Ri @ Ho @ cov
            dlog = hhat @ Ri @ yd - 0.5 * hhat @ Ri @ hhat - 0.5 * np.trace(Ho.T @ Ri @ Ho @ cov)
            return np.concatenate([dm, dP.ravel(), [dlog]])

        y = solve_ivp(rhs, (0.0, tau), np.concatenate([m, P.ravel(), [0.0]]), method="DOP853", rtol=1e-12,
                      atol=1e-14).y[:, -1]
        m, P = y[:n], y[n:n + n * n].reshape(n, n)
        out.append((m, P, y[-1] if o.any() else 0.0))
    means, covs, ll = zip(*out, strict=True)
    return np.array(means), np.array(covs), np.array(ll)


def _log_normal_offset(rows, times, R):
    """log N(Δy_o; 0, R_oo τ) per row (NaN for a missing row): predictive = Girsanov + this."""
    out = []
    for row, tau in zip(rows, np.diff(times, prepend=0.0), strict=True):
        o = ~np.isnan(row)
        if not o.any():
            out.append(np.nan)
            continue
        S = np.asarray(R, float)[np.ix_(o, o)] * tau
        out.append(-0.5 * row[o] @ np.linalg.solve(S, row[o]) - 0.5 * np.linalg.slogdet(2 * np.pi * S)[1])
    return np.array(out)


def _close(result, mean, cov, atol=1e-10):
    np.testing.assert_allclose(result.mean, mean, rtol=0, atol=atol)
    np.testing.assert_allclose(result.cov, cov, rtol=0, atol=atol)


# -- kalman-bucy ---------------------------------------------------------------------------------
@pytest.mark.slow
@pytest.mark.parametrize("spec, coeffs", [(LINEAR, LIN), (CROSS, CROSS_M)], ids=["a=I", "cross-diffusion"])
def test_kalman_bucy_discrete_measurements_equal_the_irregular_kalman_oracle(spec, coeffs):
    rows, times = _data(spec, "discrete", 300, 1)
    kb = KalmanBucyFilter(_model(spec, "discrete"))
    state, result = kb.run_arrays(kb.initial_state(), rows, times)
    truth = _oracle(coeffs, rows, times, "discrete")
    _close(result, truth.mean, truth.cov)
    np.testing.assert_allclose(result.predictive_loglik, truth.predictive_loglik, rtol=0, atol=1e-10)
    np.testing.assert_allclose(result.loglik, truth.loglik, rtol=0, atol=1e-9)
    np.testing.assert_array_equal(result.t, times)
    assert state.t == times[-1] and state.step == len(rows) and not result.gated.any()
    # in odd chunks, one-row steps included: the same numbers
    state, parts = kb.initial_state(), []
    for piece in np.array_split(np.arange(len(rows)), [1, 2, 40, 41, 200]):
        state, part = kb.run_arrays(state, rows[piece], times[piece])
        parts.append(part.mean)
    np.testing.assert_allclose(np.concatenate(parts), truth.mean, rtol=0, atol=1e-10)


def test_kalman_bucy_discrete_measurements_at_regular_times_and_partial_rows():
    # regular rows (no times): the scheduled fast path for whole rows, row by row for partial ones
    rows, _ = _data(LINEAR, "discrete", 200, 2, missing=0.0)
    rows[50:53] = np.nan
    rows[120:130, 0] = np.nan
    times = DT * np.arange(1, len(rows) + 1)
    kb = KalmanBucyFilter(_model(LINEAR, "discrete"))
    _, result = kb.run_arrays(kb.initial_state(), rows)
    truth = _oracle(LIN, rows, times, "discrete")
    _close(result, truth.mean, truth.cov)
    np.testing.assert_allclose(result.predictive_loglik, truth.predictive_loglik, rtol=0, atol=1e-10)
    np.testing.assert_allclose(result.t, times, rtol=1e-15)


@pytest.mark.slow
def test_sampled_increment_model_equals_the_oracle_of_continuous_rows():
    # KalmanBucyFilter(kind="discrete") is the time-sampled model dy = H x(t_k) τ + h0 τ + N(0, Rτ),
    # exactly kalman_irregular's continuous kind; its log-likelihood is relative to N(dy; 0, Rτ)
    rows, times = _data(CROSS, "continuous", 300, 3)
    kb = KalmanBucyFilter(_model(CROSS), kind="discrete")
    assert kb.sampled and not kb.discrete
    _, result = kb.run_arrays(kb.initial_state(), rows, times)
    truth = _oracle(CROSS_M, rows, times, "continuous")
    _close(result, truth.mean, truth.cov)
    np.testing.assert_allclose(result.predictive_loglik, truth.predictive_loglik, rtol=0, atol=1e-10)
    girsanov = truth.predictive_loglik - _log_normal_offset(rows, times, CROSS_M["R"])
    np.testing.assert_allclose(result.loglik_increment, np.nan_to_num(girsanov), rtol=0, atol=1e-10)


@pytest.mark.slow
@pytest.mark.parametrize("spec, coeffs", [(LINEAR, LIN), (CROSS, CROSS_M)], ids=["a=I", "cross-diffusion"])
def test_kalman_bucy_continuous_irregular_increments_solve_the_kalman_bucy_odes(spec, coeffs):
    rows, times = _data(spec, "continuous", 200, 4)
    kb = KalmanBucyFilter(_model(spec))
    _, result = kb.run_arrays(kb.initial_state(), rows, times)
    means, covs, ll = _ode_oracle(coeffs, rows, times)
    _close(result, means, covs, atol=1e-9)
    np.testing.assert_allclose(result.loglik_increment, ll, rtol=0, atol=1e-10)
    np.testing.assert_allclose(result.predictive_loglik, ll + _log_normal_offset(rows, times, coeffs["R"]),
                               rtol=0, atol=1e-10)


def test_a_long_gap_from_a_narrow_covariance_is_taken_in_pieces():
    # one Gauss–Legendre rule over the whole gap would miss log Z by O(1) here (riccati.gap_pieces)
    spec = dict(LINEAR, initial={"kind": "gaussian", "mean": [0.5, -0.3], "cov": [[1e-3, 0.0], [0.0, 2e-3]]},
                observation_noise=[[0.01, 0.0], [0.0, 0.02]])
    coeffs = dict(LIN, P0=[[1e-3, 0.0], [0.0, 2e-3]], R=[[0.01, 0.0], [0.0, 0.02]])
    rows, times = np.array([[0.9, -0.4], [0.3, np.nan]]), np.array([1.5, 4.0])
    kb = KalmanBucyFilter(compile_model(spec_from_dict(spec)), gate=0)
    _, result = kb.run_arrays(kb.initial_state(), rows, times)
    means, covs, ll = _ode_oracle(coeffs, rows, times)
    _close(result, means, covs, atol=1e-9)
    np.testing.assert_allclose(result.loglik_increment, ll, rtol=0, atol=1e-8)


def test_predict_to_an_irregular_time_is_the_fokker_planck_flow():
    kb = KalmanBucyFilter(_model(CROSS))
    state, _ = kb.run(kb.initial_state(), [[0.01, 0.02], [np.nan, 0.01]])
    phi, shift, Q = linear_prediction(CROSS_M["F"], CROSS_M["f0"], CROSS_M["a"], 0.73)
    later, estimate = kb.predict(state, state.t + 0.73)
    np.testing.assert_allclose(estimate.mean, phi @ state.mean + shift, rtol=0, atol=1e-13)
    np.testing.assert_allclose(estimate.cov, phi @ state.cov @ phi.T + Q, rtol=0, atol=1e-13)
    assert later.t == pytest.approx(state.t + 0.73) and estimate.predictive_loglik is None


def test_discrete_row_at_the_prior_time_is_a_plain_kalman_update():
    kb = KalmanBucyFilter(_model(LINEAR, "discrete"))
    z = np.array([0.4, np.nan])
    _, estimate = kb.step(kb.initial_state(), z, t=0.0)
    P, H, R = np.array(LIN["P0"]), np.array(LIN["H"])[:1], np.array(LIN["R"])[:1, :1]
    S = H @ P @ H.T + R
    gain = P @ H.T / S
    resid = z[0] - H @ LIN["m0"] - LIN["h0"][0]
    np.testing.assert_allclose(estimate.mean, LIN["m0"] + (gain * resid)[:, 0], rtol=0, atol=1e-14)
    np.testing.assert_allclose(estimate.cov, P - gain @ S @ gain.T, rtol=0, atol=1e-14)
    expected = -0.5 * float(resid @ resid) / S[0, 0] - 0.5 * math.log(2 * math.pi * S[0, 0])
    assert estimate.predictive_loglik == pytest.approx(expected, abs=1e-14)


def test_times_on_the_regular_grid_are_regular_rows():
    rows, _ = _data(LINEAR, "continuous", 60, 5, missing=0.0)
    kb = KalmanBucyFilter(_model(LINEAR))
    _, plain = kb.run_arrays(kb.initial_state(), rows)
    _, timed = kb.run_arrays(kb.initial_state(), rows, plain.t)
    np.testing.assert_array_equal(timed.mean, plain.mean)
    np.testing.assert_array_equal(timed.loglik, plain.loglik)


# -- the gate --------------------------------------------------------------------------------------
def _predicted_row(coeffs, rows, times, k, index):
    """(ν, S) of row k's observed components ``index`` from the oracle's filter before it."""
    c = {key: np.asarray(v, float) for key, v in coeffs.items()}
    if k:
        before = _oracle(coeffs, rows[:k], times[:k], "discrete")
        mean, cov = before.mean[-1], before.cov[-1]
    else:
        mean, cov = c["m0"], c["P0"]
    phi, shift, Q = linear_prediction(c["F"], c["f0"], c["a"], times[k] - (times[k - 1] if k else 0.0))
    mean, cov = phi @ mean + shift, phi @ cov @ phi.T + Q
    H, R = c["H"][index], c["R"][np.ix_(index, index)]
    return rows[k, index] - H @ mean - c["h0"][index], H @ cov @ H.T + R


@pytest.mark.slow
@pytest.mark.parametrize("method", ["kalman-bucy", "yau-hu"])
def test_a_1000_sigma_outlier_is_gated_and_the_rest_is_the_oracle_without_it(method):
    rows, times = _data(LINEAR, "discrete", 150, 6)
    rows[60] = [1000.0, -1000.0]  # both components, over 500 predictive standard deviations out
    rows[90] = [np.nan, 0.0]
    without = rows.copy()
    without[60] = np.nan
    nu, S = _predicted_row(LIN, without, times, 90, np.array([1]))
    rows[90, 1] = without[90, 1] = nu[0] + 1000.0 * math.sqrt(S[0, 0])  # one component: d = |ν|/√S
    filt = (KalmanBucyFilter if method == "kalman-bucy" else YauHuFilter)(_model(LINEAR, "discrete"))
    _, result = filt.run_arrays(filt.initial_state(), rows, times)
    assert np.flatnonzero(result.gated).tolist() == [60, 90]
    nu, S = _predicted_row(LIN, without, times, 90, np.array([1]))
    assert result.gate_score[90] == pytest.approx(abs(nu[0]) / math.sqrt(S[0, 0]), rel=1e-9)
    assert result.gate_score[60] > 500.0 and np.isnan(result.gate_score[~result.gated]).all()
    without[90] = np.nan
    truth = _oracle(LIN, without, times, "discrete")
    _close(result, truth.mean, truth.cov)
    kept = ~result.gated
    np.testing.assert_allclose(result.predictive_loglik[kept], truth.predictive_loglik[kept], rtol=0,
                               atol=1e-9)
    assert np.all(result.loglik_increment[result.gated] == 0.0)
    np.testing.assert_allclose(result.loglik, truth.loglik, rtol=0, atol=1e-8)
    # the gated row keeps its (tiny) predictive log-likelihood: log N(ν; 0, S) of the outlier
    assert result.predictive_loglik[90] == pytest.approx(-0.5 * nu[0] ** 2 / S[0, 0]
                                                         - 0.5 * math.log(2 * math.pi * S[0, 0]), rel=1e-9)
    estimates = filt.run(filt.initial_state(), rows, times)[1]
    assert estimates[60].gated and "gated" in estimates[60].reason and not estimates[59].gated
    # the gate off: the outliers go in
    off = make_filter(_model(LINEAR, "discrete"), None, method, gate=0)
    _, result = off.run_arrays(off.initial_state(), rows, times)
    assert not result.gated.any() and abs(result.mean[60, 0] - truth.mean[60, 0]) > 1.0


@pytest.mark.slow
def test_continuous_outlier_is_gated_in_any_chunking():
    rows, times = _data(LINEAR, "continuous", 120, 7)
    tau = times[45] - times[44]
    rows[45] = [0.0, np.nan]
    rows[45, 0] = 1000.0 * math.sqrt(0.5 * tau)
    kb = KalmanBucyFilter(_model(LINEAR))
    _, result = kb.run_arrays(kb.initial_state(), rows, times)
    without = rows.copy()
    without[45] = np.nan
    _, clean = kb.run_arrays(kb.initial_state(), without, times)
    assert np.flatnonzero(result.gated).tolist() == [45] and result.gate_score[45] > 900.0
    np.testing.assert_allclose(result.mean, clean.mean, rtol=0, atol=1e-12)
    np.testing.assert_allclose(result.loglik, clean.loglik, rtol=0, atol=1e-12)
    means, _, _ = _ode_oracle(LIN, without, times)
    np.testing.assert_allclose(result.mean, means, rtol=0, atol=1e-9)
    state, parts = kb.initial_state(), []
    for piece in np.array_split(np.arange(len(rows)), [44, 45, 46, 80]):
        state, part = kb.run_arrays(state, rows[piece], times[piece])
        parts.append(part)
    assert np.concatenate([p.gated for p in parts]).tolist() == result.gated.tolist()
    np.testing.assert_allclose(np.concatenate([p.mean for p in parts]), clean.mean, rtol=0, atol=1e-12)


# -- yau-hu ------------------------------------------------------------------------------------------
@pytest.mark.slow
def test_yau_hu_on_a_linear_model_at_irregular_times_is_exact():
    rows, times = _data(LINEAR, "continuous", 150, 8)
    yh = YauHuFilter(_model(LINEAR))
    _, result = yh.run_arrays(yh.initial_state(), rows, times)
    means, covs, ll = _ode_oracle(LIN, rows, times)
    _close(result, means, covs, atol=1e-9)
    np.testing.assert_allclose(result.loglik, np.cumsum(ll), rtol=0, atol=1e-9)
    rows, times = _data(LINEAR, "discrete", 150, 9)
    yh = YauHuFilter(_model(LINEAR, "discrete"))
    _, result = yh.run_arrays(yh.initial_state(), rows, times)
    truth = _oracle(LIN, rows, times, "discrete")
    _close(result, truth.mean, truth.cov)
    np.testing.assert_allclose(result.predictive_loglik, truth.predictive_loglik, rtol=0, atol=1e-9)


def _benes_sigma(S0, s):
    """(Σ(s), ∫0^s Σ) of Σ' = 1 − Σ² from Σ(0) = S0."""
    if S0 == 1.0:
        return 1.0, s
    c = math.atanh(S0 if S0 < 1.0 else 1.0 / S0)
    if S0 < 1.0:
        return math.tanh(s + c), math.log(math.cosh(s + c) / math.cosh(c))
    return 1.0 / math.tanh(s + c), math.log(math.sinh(s + c) / math.sinh(c))


def _benes_continuous(rows, times):
    """(mean, variance, log-lik increment) per row of the continuous Beneš filter (y linear per gap)."""
    mu, S, out = M0, P0, []
    for y, tau in zip(rows, np.diff(times, prepend=0.0), strict=True):
        ll = 0.0
        if np.isnan(y):
            S = S + tau  # the heat flow of cosh(x)·N(μ, Σ)
        else:
            yd = y / tau

            def rate(s, mu=mu, S=S, yd=yd):
                Ss, integral = _benes_sigma(S, s)
                m = yd + (mu - yd) * math.exp(-integral)
                mean, var = m + Ss * math.tanh(m), Ss + Ss * Ss / math.cosh(m) ** 2
                return yd * mean - 0.5 * (var + mean * mean)

            ll = quad(rate, 0.0, tau, epsabs=1e-14, epsrel=1e-13, limit=200)[0]
            S_new, integral = _benes_sigma(S, tau)
            mu, S = yd + (mu - yd) * math.exp(-integral), S_new
        out.append((mu + S * math.tanh(mu), S + S * S / math.cosh(mu) ** 2, ll))
    return np.array(out)


def _log_cosh(x):
    return abs(x) + math.log1p(math.exp(-2.0 * abs(x))) - math.log(2.0)


def _benes_discrete(rows, times, R=1.0):
    """(mean, variance, predictive log-lik) per row of the Beneš filter of z_k = x(t_k) + N(0, R)."""
    mu, S, out = M0, P0, []
    for z, tau in zip(rows, np.diff(times, prepend=0.0), strict=True):
        S, pll = S + tau, np.nan
        if not np.isnan(z):
            V = S + R
            S_new, mu_new = S * R / V, (mu * R + z * S) / V
            pll = (-0.5 * (z - mu) ** 2 / V - 0.5 * math.log(2 * math.pi * V)
                   + 0.5 * S_new + _log_cosh(mu_new) - 0.5 * S - _log_cosh(mu))
            mu, S = mu_new, S_new
        out.append((mu + S * math.tanh(mu), S + S * S / math.cosh(mu) ** 2, pll))
    return np.array(out)


def _benes_start(filt):
    """v = e^{−F}σ0 = N(M0, P0) exactly, normalised (∫σ = ∫cosh(x)·v = 1)."""
    C = M0 * M0 / (2 * P0) + 0.5 * math.log(2 * math.pi * P0) + 0.5 * P0 + math.log(math.cosh(M0))
    return filt.state_from_dict({**filt.initial_state().to_dict(), "A": [[[0.5 / P0]]], "B": [[-M0 / P0]],
                                 "C": [C]})


@pytest.mark.slow
@pytest.mark.parametrize("method", ["yau-hu", "yau-jia"])
def test_benes_at_irregular_times_equals_the_closed_form(method):
    cls = YauHuFilter if method == "yau-hu" else YauJiaFilter
    rows, times = _data(BENES, "continuous", 120, 10, missing=0.0)
    filt = cls(_model(BENES))
    _, result = filt.run_arrays(_benes_start(filt), rows, times)
    truth = _benes_continuous(rows[:, 0], times)
    np.testing.assert_allclose(result.mean[:, 0], truth[:, 0], rtol=0, atol=1e-10)
    np.testing.assert_allclose(result.cov[:, 0, 0], truth[:, 1], rtol=0, atol=1e-10)
    np.testing.assert_allclose(result.loglik_increment, truth[:, 2], rtol=0, atol=1e-10)
    if method == "yau-jia":
        return
    rows, times = _data(BENES, "discrete", 120, 11, missing=0.0)
    filt = cls(_model(BENES, "discrete"))
    _, result = filt.run_arrays(_benes_start(filt), rows, times)
    truth = _benes_discrete(rows[:, 0], times)
    np.testing.assert_allclose(result.mean[:, 0], truth[:, 0], rtol=0, atol=1e-10)
    np.testing.assert_allclose(result.cov[:, 0, 0], truth[:, 1], rtol=0, atol=1e-10)
    np.testing.assert_allclose(result.predictive_loglik, truth[:, 2], rtol=0, atol=1e-10)


# -- yau-jia -------------------------------------------------------------------------------------------
@pytest.mark.slow
def test_yau_jia_on_a_linear_model_at_irregular_times_is_exact():
    rows, times = _data(LINEAR, "continuous", 120, 12, missing=0.0)
    rows[50] = [rows[50, 0] + 1000.0 * math.sqrt(0.5 * (times[50] - times[49])), rows[50, 1]]
    yj = YauJiaFilter(_model(LINEAR))
    _, result = yj.run_arrays(yj.initial_state(), rows, times)
    assert np.flatnonzero(result.gated).tolist() == [50]
    without = rows.copy()
    without[50] = np.nan
    means, covs, ll = _ode_oracle(LIN, without, times)
    _close(result, means, covs, atol=1e-9)
    np.testing.assert_allclose(result.loglik_increment, ll, rtol=0, atol=1e-10)
    kept = ~result.gated
    offset = _log_normal_offset(rows, times, LIN["R"])
    np.testing.assert_allclose(result.predictive_loglik[kept], (ll + offset)[kept], rtol=0, atol=1e-10)


# -- what is refused, and how ---------------------------------------------------------------------------
def test_refused_forms_name_the_field_and_the_alternative():
    student = _model(LINEAR, "discrete", likelihood="student-t", dof=4.0)
    for cls in (KalmanBucyFilter, YauHuFilter):
        with pytest.raises(SpecError) as err:
            cls(student)
        assert err.value.field == "measurement.likelihood" and "yau-yau" in err.value.message
    with pytest.raises(SpecError) as err:
        YauJiaFilter(_model(LINEAR, "discrete"))
    assert err.value.field == "measurement.kind" and "yau-yau" in err.value.message
    with pytest.raises(SpecError) as err:
        WeiNormanFilter(_model(LINEAR, "discrete"), lambda t, X: np.ones(len(X)))
    assert err.value.field == "measurement.kind" and "yau-yau" in err.value.message
    with pytest.raises(SpecError) as err:
        KalmanBucyFilter(_model(LINEAR, "discrete"), kind="discrete")
    assert err.value.field == "kind"
    with pytest.raises(SpecError) as err:  # make_filter says which method does not apply
        make_filter(student, None, "yau-hu")
    assert err.value.field == "method" and "yau-yau" in err.value.message
    yj = YauJiaFilter(_model(LINEAR))
    with pytest.raises(InputError) as err:
        yj.run_arrays(yj.initial_state(), [[0.1, 0.2], [0.1, np.nan]])
    assert err.value.field == "increments[1]" and "yau-yau" in err.value.message
    kb = KalmanBucyFilter(_model(LINEAR))
    with pytest.raises(InputError) as err:  # an increment needs an interval
        kb.run_arrays(kb.initial_state(), [[0.1, 0.2]], [0.0])
    assert err.value.field == "times[0]"
    with pytest.raises(InputError) as err:
        kb.run_arrays(kb.initial_state(), [[0.1, 0.2], [0.1, 0.2]], [0.2, 0.1])
    assert err.value.field == "times[1]"


def test_wei_norman_refuses_times_and_missing_components():
    model = compile_model(spec_from_dict({
        "name": "ou", "state": ["x"], "drift": ["-0.5*x"], "observation": ["x"],
        "initial": {"kind": "gaussian", "mean": [1.0], "cov": [[0.5]]}, "domain": {"radius": 8.0},
        "discretization": {"dt": DT, "basis": 8}}))
    wn = WeiNormanFilter(model, lambda t, X: np.exp(-X[:, 0] ** 2))
    with pytest.raises(InputError) as err:
        wn.run_arrays(wn.initial_state(), [[0.1]], [0.3])
    assert err.value.field == "times" and "yau-yau" in err.value.message
    with pytest.raises(InputError) as err:
        wn.run_arrays(wn.initial_state(), [[0.1], [np.nan]])
    assert err.value.field == "increments" and "yau-yau" in err.value.message
