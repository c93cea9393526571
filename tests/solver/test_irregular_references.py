"""The irregular-time references of tests/helpers/irregular_refs.py against closed forms.

Measured agreement (fixed seeds; the grid tolerances below are about 2x these):
* kalman_irregular vs a hand-written scalar OU recursion (both kinds, NaN rows): mean/var <= 4e-15,
  predictive log-lik <= 1.2e-13 (tolerance 1e-12);
  Van Loan (Φ, shift, Q_τ) vs e^{Fτ}, F⁻¹(Φ − I) f0 and the Lyapunov form Q∞ − Φ Q∞ Φᵀ: < 1e-13.
* GridReference (1024 cells) vs kalman_irregular, examples/ou.toml, K = 200, mean gap 0.05:
      discrete   mean 4.5e-5, var 2.0e-4 (relative), predictive log-lik 5.8e-5, total log-lik 3.7e-5
      continuous mean 5.2e-5, var 1.1e-4,            predictive log-lik 1.7e-5, total log-lik 2.3e-5
* 2-D linear model (cross-diffusion a01 = 0.3, m = 2, ~15% NaN components + one all-NaN row,
  128 cells per axis on radius 4.5, K = 200):
      discrete   mean 2.8e-3, var 1.2%,  predictive log-lik 3.6e-3
      continuous mean 2.9e-3, var 0.68%, predictive log-lik 7.5e-3
  (the O(h²) finite-volume error: 96 cells give ~1.8x these, e.g. var 3.2% discrete).
* Student-t, one discrete row after a gap 0.3, vs quadrature (2048 cells): mean 1.9e-5, var 2.4e-5
  (relative), evidence 1.2e-5 (1024 cells: mean 7.5e-5).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from helpers import ROOT
from helpers.irregular_refs import (
    GridReference,
    kalman_irregular,
    linear_prediction,
    log_gaussian,
    log_student_t,
    random_times,
    simulate_irregular,
)
from scipy import integrate, stats
from scipy.linalg import expm, solve_continuous_lyapunov
from yauyau.solver.model import compile_model
from yauyau.solver.spec import load_spec, spec_from_dict

THETA = 0.5  # examples/ou.toml: dx = -theta x dt + dv, dy = x dt + dw (R = 1), prior N(1, 0.5)


@pytest.fixture(scope="module")
def ou_model():
    return compile_model(load_spec(ROOT / "examples" / "ou.toml"))


@pytest.fixture(scope="module")
def ou_grid(ou_model):
    return GridReference(ou_model)


def ou_kalman(rows, times, kind, R=1.0):
    return kalman_irregular([[-THETA]], [0.0], [[1.0]], [[1.0]], [0.0], [[R]], [1.0], [[0.5]],
                            rows, times, kind)


LIN2 = dict(
    name="linear-2d", state=["x1", "x2"], drift=["-0.5*x1 + x2", "-x1 - 0.5*x2"],
    observation=["x1", "x2 + 0.5"], diffusion=[[1.0, 0.3], [0.3, 0.5]],
    observation_noise=[[0.5, 0.1], [0.1, 0.8]],
    initial=dict(kind="gaussian", mean=[0.5, 0.0], cov=[[1.0, 0.2], [0.2, 0.8]]),
    domain=dict(radius=4.5), discretization=dict(dt=0.01, basis=32))
LIN2_F = np.array([[-0.5, 1.0], [-1.0, -0.5]])


# -- small pieces -----------------------------------------------------------------------
def test_log_densities_match_scipy():
    rng = np.random.default_rng(0)
    S = np.array([[0.5, 0.1, 0.0], [0.1, 0.8, 0.2], [0.0, 0.2, 1.3]])
    d = rng.normal(size=(7, 3)) * 3
    want = stats.multivariate_normal(np.zeros(3), S).logpdf(d)
    assert np.allclose(log_gaussian(d, S), want, rtol=0, atol=1e-12)
    for dof in (1.0, 3.5, 30.0):
        want = stats.multivariate_t(np.zeros(3), S, df=dof).logpdf(d)
        assert np.allclose(log_student_t(d, S, dof), want, rtol=0, atol=1e-12)
        # the marginal of components (0, 2) of a multivariate t is t with scale S[o][:, o], same dof
        o = np.array([0, 2])
        want_o = stats.multivariate_t(np.zeros(2), S[np.ix_(o, o)], df=dof).logpdf(d[:, o])
        assert np.allclose(log_student_t(d[:, o], S[np.ix_(o, o)], dof), want_o, atol=1e-12)


def test_linear_prediction_closed_forms():
    """Van Loan against the closed forms: scalar OU, and a stable 2-D F via the Lyapunov equation
    (Q_τ = Q∞ − Φ Q∞ Φᵀ with F Q∞ + Q∞ Fᵀ + a = 0) and shift = F⁻¹(Φ − I) f0."""
    for tau in (1e-7, 0.013, 0.37, 4.0):
        Phi, shift, Q = linear_prediction([[-THETA]], [0.7], [[1.3]], tau)
        e = math.exp(-THETA * tau)
        assert abs(Phi[0, 0] - e) < 1e-15
        assert abs(shift[0] - 0.7 * (1 - e) / THETA) < 1e-14
        assert abs(Q[0, 0] - 1.3 * (1 - e * e) / (2 * THETA)) < 1e-14
        a = np.array([[1.0, 0.3], [0.3, 0.5]])
        f0 = np.array([0.2, -0.4])
        Phi, shift, Q = linear_prediction(LIN2_F, f0, a, tau)
        Qinf = solve_continuous_lyapunov(LIN2_F, -a)
        assert np.allclose(Phi, expm(LIN2_F * tau), rtol=0, atol=1e-14)
        assert np.allclose(Q, Qinf - Phi @ Qinf @ Phi.T, rtol=0, atol=1e-13)
        assert np.allclose(shift, np.linalg.solve(LIN2_F, (Phi - np.eye(2)) @ f0), rtol=0, atol=1e-13)


def scalar_kalman(rows, times, kind, theta, mu, a, H, h0, R, m0, P0):
    """Hand-written scalar Kalman filter for dx = theta (mu − x) dt + sqrt(a) dv at irregular times."""
    m, P, t = m0, P0, 0.0
    out_m, out_P, out_l = [], [], []
    for z, tk in zip(rows, times, strict=True):
        tau = tk - t
        t = tk
        e = math.exp(-theta * tau)
        m = mu + (m - mu) * e
        P = P * e * e + a * (1 - e * e) / (2 * theta)
        if math.isnan(z):
            out_l.append(math.nan)
        else:
            s = tau if kind == "continuous" else 1.0
            S = (H * s) ** 2 * P + R * s
            r = z - H * s * m - h0 * s
            out_l.append(-0.5 * (math.log(2 * math.pi * S) + r * r / S))
            K = P * H * s / S
            m = m + K * r
            P = P - K * H * s * P
        out_m.append(m)
        out_P.append(P)
    return np.array(out_m), np.array(out_P), np.array(out_l)


@pytest.mark.slow
@pytest.mark.parametrize("kind", ["discrete", "continuous"])
def test_kalman_matches_scalar_recursion(kind):
    rng = np.random.default_rng(1)
    K = 300
    times = random_times(rng, K, 0.05)
    rows = rng.normal(size=(K, 1)) * (0.3 if kind == "continuous" else 1.5) + 0.4
    rows[rng.random(K) < 0.1] = np.nan
    theta, mu, a, H, h0, R = 0.7, 0.8, 1.3, 1.7, -0.2, 0.45
    res = kalman_irregular([[-theta]], [theta * mu], [[a]], [[H]], [h0], [[R]], [1.0], [[0.5]],
                           rows, times, kind)
    m, P, ll = scalar_kalman(rows[:, 0], times, kind, theta, mu, a, H, h0, R, 1.0, 0.5)
    assert np.max(np.abs(res.mean[:, 0] - m)) < 1e-12
    assert np.max(np.abs(res.cov[:, 0, 0] - P)) < 1e-12
    assert np.array_equal(np.isnan(res.predictive_loglik), np.isnan(ll))
    assert np.nanmax(np.abs(res.predictive_loglik - ll)) < 1e-12
    assert abs(res.loglik[-1] - np.nansum(ll)) < 1e-10


def test_all_missing_row_only_predicts(ou_grid):
    """Discrete rows: an all-NaN row at an intermediate time splits a gap without changing anything
    (semigroup property of the exact prediction)."""
    times = np.array([0.3, 0.55, 1.4])
    rows = np.array([[0.8], [1.1], [-0.2]])
    t2 = np.array([0.3, 0.4, 0.55, 1.0, 1.4])
    r2 = np.array([[0.8], [np.nan], [1.1], [np.nan], [-0.2]])
    keep = [0, 2, 4]
    k1, k2 = ou_kalman(rows, times, "discrete"), ou_kalman(r2, t2, "discrete")
    assert np.allclose(k2.mean[keep], k1.mean, atol=1e-14) and np.allclose(k2.cov[keep], k1.cov, atol=1e-14)
    assert np.isnan(k2.predictive_loglik[[1, 3]]).all()
    g1, g2 = ou_grid.run(rows, times, "discrete"), ou_grid.run(r2, t2, "discrete")
    assert np.allclose(g2.mean[keep], g1.mean, atol=1e-11) and np.allclose(g2.cov[keep], g1.cov, atol=1e-11)
    assert np.allclose(g2.predictive_loglik[keep], g1.predictive_loglik, atol=1e-11)
    assert np.allclose(g2.loglik[keep], g1.loglik, atol=1e-11)


# -- the grid ---------------------------------------------------------------------------
def test_grid_generator_and_methods(ou_model, ou_grid):
    """Zero-flux finite volumes conserve mass (columns of L sum to 0), in 1-D and 2-D; the fast
    "eigh" propagation equals expm_multiply."""
    assert ou_grid.method == "eigh"
    assert np.abs(np.asarray(ou_grid.L.sum(axis=0))).max() < 1e-9 * abs(ou_grid.L.diagonal()).max()
    g2 = GridReference(compile_model(spec_from_dict(LIN2)), cells=24)
    assert g2.method == "expm_multiply"
    assert np.abs(np.asarray(g2.L.sum(axis=0))).max() < 1e-11 * abs(g2.L.diagonal()).max()
    assert ou_grid.eigh_error() < 1e-7
    rng = np.random.default_rng(2)
    times = random_times(rng, 20, 0.1)
    rows = rng.normal(size=(20, 1)) + 1.0
    slow = GridReference(ou_model, method="expm_multiply").run(rows, times, "discrete")
    fast = ou_grid.run(rows, times, "discrete")
    assert np.abs(fast.mean - slow.mean).max() < 1e-10
    assert np.abs(fast.cov - slow.cov).max() < 1e-10
    assert np.abs(fast.predictive_loglik - slow.predictive_loglik).max() < 1e-9


@pytest.mark.slow
@pytest.mark.parametrize("kind, tol", [("discrete", (1e-4, 4e-4, 1.2e-4)),
                                       ("continuous", (1e-4, 4e-4, 1.2e-4))])
def test_grid_ou(ou_model, ou_grid, kind, tol):
    rng = np.random.default_rng(3)
    times = random_times(rng, 200, 0.05)
    _, rows = simulate_irregular(ou_model, times, kind, rng)
    rows[[17, 90]] = np.nan
    g = ou_grid.run(rows, times, kind)
    k = ou_kalman(rows, times, kind)
    dm = np.abs(g.mean - k.mean).max()
    dv = np.abs(g.cov / k.cov - 1).max()
    dl = np.nanmax(np.abs(g.predictive_loglik - k.predictive_loglik))
    dL = abs(g.loglik[-1] - k.loglik[-1])
    print(f"OU {kind}: mean {dm:.2e}  var {dv:.2e}  pll {dl:.2e}  total loglik {dL:.2e}")
    assert dm < tol[0] and dv < tol[1] and dl < tol[2]
    assert np.array_equal(np.isnan(g.predictive_loglik), np.isnan(k.predictive_loglik))
    assert dL < 20 * tol[2]


def test_grid_extreme_row_does_not_underflow(ou_grid):
    """A row 40 standard deviations out: the likelihood underflows in linear scale, not in log scale."""
    g = ou_grid.run(np.array([[40.0]]), np.array([0.1]), "discrete")
    assert np.isfinite(g.predictive_loglik[0]) and np.isfinite(g.mean).all()
    assert g.mean[0, 0] > 7.5  # the posterior sits at the box edge (x = 8)


@pytest.mark.slow
@pytest.mark.parametrize("kind, tol", [("discrete", (6e-3, 2.5e-2, 7e-3)),
                                       ("continuous", (6e-3, 1.4e-2, 1.5e-2))])
def test_grid_2d_missing_components(kind, tol):
    model = compile_model(spec_from_dict(LIN2))
    rng = np.random.default_rng(4)
    K = 200
    times = random_times(rng, K, 0.05)
    _, rows = simulate_irregular(model, times, kind, rng)
    rows[rng.random(rows.shape) < 0.15] = np.nan
    rows[5] = np.nan
    k = kalman_irregular(LIN2_F, [0.0, 0.0], model.a, np.eye(2), [0.0, 0.5], model.R, [0.5, 0.0],
                         [[1.0, 0.2], [0.2, 0.8]], rows, times, kind)
    g = GridReference(model, cells=128).run(rows, times, kind)
    dm = np.abs(g.mean - k.mean).max()
    dv = np.abs(np.diagonal(g.cov, axis1=1, axis2=2) / np.diagonal(k.cov, axis1=1, axis2=2) - 1).max()
    dl = np.nanmax(np.abs(g.predictive_loglik - k.predictive_loglik))
    print(f"2-D {kind}: mean {dm:.2e}  var {dv:.2e}  pll {dl:.2e}")
    assert np.array_equal(np.isnan(g.predictive_loglik), np.isnan(k.predictive_loglik))
    assert dm < tol[0] and dv < tol[1] and dl < tol[2]


@pytest.mark.slow
@pytest.mark.parametrize("observation, R, row", [
    (["x"], [[0.3]], [4.0]),
    (["x", "0.5*x"], [[0.3, 0.1], [0.1, 0.6]], [4.0, np.nan]),  # marginal of the observed component
    (["x + 0.2*x**3"], [[0.3]], [-2.5]),
])
def test_grid_student_t_single_row(observation, R, row):
    """Posterior after one discrete Student-t row at t1 = 0.3: the OU prediction of the prior
    N(1, 0.5) is N(e^{−θτ}, 0.5 e^{−2θτ} + (1 − e^{−2θτ})/(2θ)); posterior mean and evidence by quad."""
    dof, t1 = 3.0, 0.3
    spec = spec_from_dict(dict(name="t1d", state=["x"], drift=["-theta*x"], observation=observation,
                               observation_noise=R, parameters={"theta": THETA},
                               initial=dict(kind="gaussian", mean=[1.0], cov=[[0.5]]),
                               domain=dict(radius=8.0), discretization=dict(dt=0.01, basis=32)))
    model = compile_model(spec)
    # 2048 cells: the O(h²) finite-volume error of the mean is 7.5e-5 with 1024 cells, 1.9e-5 here
    g = GridReference(model, cells=2048).run(np.array([row]), np.array([t1]), "discrete",
                                             likelihood="student-t", dof=dof)
    e = math.exp(-THETA * t1)
    pred = stats.norm(e, math.sqrt(0.5 * e * e + (1 - e * e) / (2 * THETA)))
    h = model.h
    scale = math.sqrt(R[0][0])

    def joint(x):
        return pred.pdf(x) * stats.t(dof, loc=h(np.array([[x]]))[0, 0], scale=scale).pdf(row[0])

    kw = dict(points=[-1.0, 1.0, 3.0], limit=400, epsabs=0, epsrel=1e-12)
    Z = integrate.quad(joint, -8, 8, **kw)[0]
    mean = integrate.quad(lambda x: x * joint(x), -8, 8, **kw)[0] / Z
    var = integrate.quad(lambda x: (x - mean) ** 2 * joint(x), -8, 8, **kw)[0] / Z
    print(f"student-t {observation}: mean {abs(g.mean[0, 0] - mean):.2e}"
          f"  var {abs(g.cov[0, 0, 0] / var - 1):.2e}  pll {abs(g.predictive_loglik[0] - math.log(Z)):.2e}")
    assert abs(g.mean[0, 0] - mean) < 1e-4
    assert abs(g.cov[0, 0, 0] / var - 1) < 1e-4
    assert abs(g.predictive_loglik[0] - math.log(Z)) < 1e-4


# -- times and simulator ------------------------------------------------------------------
def test_random_times():
    rng = np.random.default_rng(5)
    t = random_times(rng, 5000, 0.02, t0=1.5)
    gaps = np.diff(np.concatenate([[1.5], t]))
    assert t.shape == (5000,) and np.all(gaps > 0)
    assert np.all(gaps >= 1e-6 * 0.02)
    assert abs(gaps.mean() / 0.02 - 1) < 0.1
    assert (gaps >= 5 * 0.02).sum() >= 100  # 5% of the gaps are 10x longer
    assert np.unique(gaps).size == gaps.size


@pytest.mark.slow
@pytest.mark.parametrize("kind", ["discrete", "continuous"])
def test_simulator_innovations_are_standard(ou_model, kind):
    """Rows simulated from the OU model give Kalman innovations with unit variance (χ² check)."""
    rng = np.random.default_rng(6)
    K = 600
    times = random_times(rng, K, 0.05)
    _, rows = simulate_irregular(ou_model, times, kind, rng, substeps_per_unit=1000)
    k = ou_kalman(rows, times, kind)
    # -2 pll = log(2π S) + r²/S; recover r²/S from the innovation variance S of the Kalman filter
    gaps = np.diff(np.concatenate([[0.0], times]))
    s = gaps if kind == "continuous" else np.ones(K)
    P_pred = np.empty(K)
    P = 0.5
    for i, tau in enumerate(gaps):
        e = math.exp(-THETA * tau)
        P_pred[i] = P * e * e + (1 - e * e) / (2 * THETA)
        P = k.cov[i, 0, 0]
    S = s * s * P_pred + s
    chi2 = -2 * k.predictive_loglik - np.log(2 * np.pi * S)
    assert abs(chi2.mean() - 1) < 4 * math.sqrt(2 / K)


@pytest.mark.slow
def test_simulator_student_t_noise(ou_model):
    """Discrete Student-t rows: z − h(x) has variance R ν/(ν − 2) and the t distribution."""
    rng = np.random.default_rng(7)
    K, dof = 20000, 5.0
    times = np.arange(1, K + 1) * 1e-3
    states, rows = simulate_irregular(ou_model, times, "discrete", rng, substeps_per_unit=1000,
                                      likelihood="student-t", dof=dof)
    noise = rows[:, 0] - states[:, 0]
    assert stats.kstest(noise, stats.t(dof).cdf).pvalue > 1e-3
