"""The Kalman–Bucy filter for linear models f = F x + f0, h = H x + h0 (method "kalman-bucy").

Continuous increments (the spec's ``[measurement] kind = "continuous"``, default): between
observation times the observation path is taken linear, ẏ = Δy_k/τ_k over the gap τ_k, and the
robust DMZ equation

    ∂σ/∂t = ½Σa_ij∂i∂jσ − div(fσ) − ½hᵀR⁻¹h σ + hᵀR⁻¹ẏ σ

is solved exactly over τ_k.  It is the Kolmogorov equation of solver/exact/riccati.py with
D = F, d = f0, Q = ½HᵀR⁻¹H, q = HᵀR⁻¹(h0 − ẏ), r = ½h0ᵀR⁻¹h0 − h0ᵀR⁻¹ẏ, so a Gaussian σ stays
Gaussian and its mean and covariance follow the Kalman–Bucy equations

    dm = (F m + f0) dt + P HᵀR⁻¹ (dy − (H m + h0) dt),   dP = (FP + PFᵀ + a − PHᵀR⁻¹HP) dt,

integrated exactly (matrix exponentials of the Hamiltonian matrix, see GaussianFlow).  Regular
rows (one dt apart) use the flows over dt; rows at irregular ``times`` one flow per distinct gap
(kept in a bounded cache).  A partly missing row enters with its observed components o only
(H_o, h0_o, R_oo in the potential).

Discrete measurements (``[measurement] kind = "discrete"``, z_k = H x(t_k) + h0 + v_k,
v_k ~ N(0, R)): the exact discrete Kalman filter — the Fokker–Planck flow over τ_k (Van Loan's
exponentials: x ← Φ_τ x + Γ_τ f0 + N(0, Q_τ), cached per gap), then the Kalman update with the
observed components, z_o = H_o x + h0_o + N(0, R_oo).  Student-t measurement noise is refused
(SpecError: the posterior is not Gaussian; use yau-yau).

The time-sampled increment model (constructor ``kind="discrete"``, called *sampled* here; it is not
the spec's measurement kind): the exact Kalman filter of
x_k = e^{Fτ} x_{k−1} + w_k, w_k ~ N(0, ∫0^τ e^{Fs} a e^{Fᵀs} ds), Δy_k = H x_k τ + h0 τ + N(0, R τ)
(over dt the matrices of solver.reference.DiscreteKalmanFilter, shared rather than duplicated).

A regular chunk of whole rows is filtered in three passes, because the covariance does not depend
on the data: the covariance path (sequential, scalar loop for n = 1), then the mean as the affine
recursion m_k = W_k m_{k−1} + v_k (W, v batched; one scalar loop), then estimates and
log-likelihoods batched — from cached schedules once the path repeats.  Rows at irregular times or
partly missing take a step-by-step loop with the same exact flows.  ``run_arrays`` returns the arrays
(as the engine's); ``run``/``step`` wrap it.

Log-likelihood convention: continuous increments — the log of the ratio of the normalisers ∫σ,
i.e. the density of the observations relative to the Brownian reference measure
(Δy_o ~ N(0, R_oo τ)), the quantity log ∫σ the Yau–Yau engine accumulates;
``predictive_loglik`` adds log N(Δy_o; 0, R_oo τ) back (a density of the row).  Discrete
measurements: both are log p(z_o | past) = log N(z_o; H_o m⁻ + h0_o, S).  A NaN row only predicts
(log-likelihood increment 0, predictive log-likelihood NaN).

Outlier gate (solver/measurement.py): the predictive standard score of an observed row is
d² = −2 log p(row | past) − log det 2πS with S the row's predictive covariance
S = κ² H_o P⁻ H_oᵀ + S₀, P⁻ the Fokker–Planck prediction of the covariance over the gap
(κ = τ, S₀ = R_oo τ for increments; κ = 1, S₀ = R_oo for measurements).  For discrete measurements
and the sampled model it is exactly the Mahalanobis distance νᵀS⁻¹ν of the innovation; for
continuous increments it is the measurement module's definition with the exact predicted covariance
(the robust flow's log-likelihood is Gaussian in Δy to O(τ²)).  A row with d² over the threshold
only predicts and is flagged (``gated``, ``gate_score``); the chunk is re-run from it
(solver/exact/schedule.py: ``gated_chunk``).
"""

from __future__ import annotations

import math
from dataclasses import astuple, replace
from typing import TYPE_CHECKING, Any

import numpy as np

from ..errors import SpecError
from ..expressions import affine_coefficients
from ..filtering import ChunkedFilter, ChunkResult, chunk_clock
from ..gaussian import GaussianFilter, GaussianState, log_normal
from ..measurement import LOG_2PI, Observation, check_first_gap, check_gate, check_rows, resolve_times
from ..model import Model
from ..reference.kalman import DiscreteKalmanFilter, van_loan
from .kalman_steps import (
    LinearSteps,
    continuous_coefficients,
    kalman_coefficients,
    kalman_covariances,
    quadratic,
)
from .riccati import (
    FlowFamily,
    GaussianKolmogorov,
    affine_path,
    gap_pieces,
    gaussian_terms_batch,
    gaussian_to_terms,
    linear_recursion,
    settle,
    terms_to_gaussian,
)
from .schedule import (
    BoundedCache,
    Schedule,
    ScheduleCache,
    Segment,
    gated_chunk,
    regular_gaps,
)

if TYPE_CHECKING:  # types only
    from numpy.typing import ArrayLike

    from ..offline.pipeline import OfflineArrays

KINDS = ("continuous", "discrete")  # the constructor's increment model: "discrete" = the sampled model


class KalmanBucyFilter(ChunkedFilter, GaussianFilter):
    """Filter protocol implementation; state: mean, cov and the accumulated log-likelihood.

    ``kind="discrete"`` selects the time-sampled increment model (see the module docstring; the
    attribute ``sampled``), not the spec's ``[measurement] kind``, which the filter reads itself.
    """

    method = "kalman-bucy"
    exact_prior = True  # a mixture prior is refused, never moment-matched

    def __init__(self, model: Model, kind: str = "continuous", gate: float | None = None):
        if kind not in KINDS:
            raise SpecError("kind", f"must be one of {KINDS}, got {kind!r}")
        measurement = model.spec.measurement
        if measurement.likelihood != "gaussian":
            raise SpecError("measurement.likelihood", f"kalman-bucy is exact for Gaussian noise, not "
                                                      f"{measurement.likelihood}; use yau-yau (the general "
                                                      "engine)")
        self.model = model
        self.kind = kind
        self.sampled = kind == "discrete"  # the time-sampled increment model
        self.discrete = measurement.kind == "discrete"  # discrete measurements z = h(x(t_k)) + v
        if self.sampled and self.discrete:
            raise SpecError("kind", "the time-sampled increment model (kind=\"discrete\") is for continuous "
                                    "increments; discrete measurements are filtered by the discrete Kalman "
                                    "filter already (leave kind at \"continuous\")")
        self.gate_override = check_gate(gate)
        self.F, self.f0 = affine_coefficients(model.drift, model.symbols, "drift")
        self.H, self.h0 = affine_coefficients(model.observation, model.symbols, "observation")
        self._HtR = self.H.T @ model.R_inv
        observed_eq = GaussianKolmogorov(self.F, self.f0, Q=0.5 * self._HtR @ self.H, a=model.a)
        predicted_eq = GaussianKolmogorov(self.F, self.f0, a=model.a)
        self._flows = FlowFamily([observed_eq.flow(model.dt), predicted_eq.flow(model.dt)])
        self._gap_flows = BoundedCache()  # (gap, pattern) -> GaussianFlow (continuous kind)
        self._equations: dict[int, GaussianKolmogorov] = {}
        self._a_max = float(np.linalg.eigvalsh(np.asarray(model.a, float))[-1])
        self._gap_moments = BoundedCache()  # gap -> (Φ, shift, Q) of the Fokker–Planck flow
        self._kalman = self._linear_steps()  # None: the continuous (Kalman–Bucy) kind
        self._schedules = ScheduleCache()  # covariance -> (schedule, step index)
        self._patterns: dict[int, tuple] = {}  # pattern -> its observation pieces

    def _linear_steps(self) -> LinearSteps | None:
        model = self.model
        if self.sampled:
            kf, dt = DiscreteKalmanFilter(model), model.dt
            return LinearSteps(kf.phi, kf.shift, kf.Q, kf.H * dt, kf.h0 * dt, model.R * dt, True)
        if self.discrete:
            phi, shift, Q = self._moments_over(model.dt)
            return LinearSteps(phi, shift, Q, self.H, self.h0, np.asarray(model.R, float), False)
        return None

    def potential_terms(self, increment: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(q, r) of the observation potential ½hᵀR⁻¹h − hᵀR⁻¹ẏ for ẏ = Δy/dt; rows for (K, m)."""
        ydot = np.asarray(increment, dtype=float) / self.model.dt
        R_inv = self.model.R_inv
        q = (self.h0 - ydot) @ self._HtR.T
        r = 0.5 * self.h0 @ R_inv @ self.h0 - ydot @ (R_inv @ self.h0)
        return q, r

    # -- Filter protocol -----------------------------------------------------------------
    def run_arrays(self, state: GaussianState, increments: np.ndarray,
                   times: ArrayLike | None = None) -> tuple[GaussianState, "ChunkResult"]:
        """Advance over a chunk (K, m) of rows (NaN: a missing component; a NaN row: prediction only)
        at ``times`` (absolute, strictly increasing) or one dt apart; estimates as arrays."""
        model = self.model
        rows = check_rows(increments, model.m)
        K, n = len(rows), model.n
        taus = resolve_times(state.t, state.step > 0, K, model.dt, times)
        steps, t_out = chunk_clock(state, K, model.dt, times, taus)
        if K == 0:
            empty = np.empty((0, n))
            return state, ChunkResult(steps, t_out, empty, np.empty((0, n, n)), empty, np.empty(0),
                                      np.empty(0), np.zeros(0, bool))
        check_first_gap(taus, self.discrete, self.method)
        taus = regular_gaps(taus, model.dt, t_out, state.t)
        obs = self.observation
        if taus is None and K == 1 and n == 1 and model.m == 1 and not np.isnan(rows[0, 0]):
            lean = self._lean_row(state, float(rows[0, 0]), obs)
            if lean is not None:
                return self._one_row_result(state, int(steps[0]), float(t_out[0]), *lean, obs.gate)
        keys = obs.pattern_keys(~np.isnan(rows))
        gaps = np.full(K, model.dt) if taus is None else taus
        terms = obs.row_terms(rows, gaps, keys)
        done = gated_chunk(state, rows, keys, taus, gaps, obs, terms, self._segment, self._h_cov)
        increments_ll = done.ll
        loglik = np.cumsum(np.concatenate([[state.loglik], increments_ll]))[1:]  # sequential sums
        mean, cov = done.mean, done.cov
        new_state = replace(state, step=int(steps[-1]), t=float(t_out[-1]), loglik=float(loglik[-1]),
                            loglik_increment=float(increments_ll[-1]), mean=mean[-1].copy(),
                            cov=cov[-1].copy())
        return new_state, ChunkResult(step=steps, t=t_out, mean=mean, cov=cov, mode=mean.copy(),
                                      loglik=loglik, loglik_increment=increments_ll,
                                      degenerate=np.zeros(K, bool), predictive_loglik=done.predictive,
                                      gated=done.gated, gate_score=done.score, gate=obs.gate)

    def smooth_arrays(self, state: GaussianState, increments: Any, times: Any = None):
        """Rauch–Tung–Striebel over a chunk (exact/kalman_smoother.py): (state after, smoothed result)."""
        from .kalman_smoother import smooth_arrays  # lazy: the filter alone never loads it

        return smooth_arrays(self, state, increments, times)

    def _segment(self, state: GaussianState, rows: np.ndarray, keys: np.ndarray, taus) -> Segment:
        """(mean, cov, ll) of consecutive rows from ``state`` (the gate's unit of work)."""
        whole = self._whole_key()
        if taus is None and np.all((keys == 0) | (keys == whole)):
            mean, cov, ll = self._regular_chunk(state, rows)
        elif self._kalman is not None:
            mean, cov, ll = self._kalman_steps(state, rows, keys, taus)
        else:
            mean, cov, ll = self._continuous_steps(state, rows, keys, taus)
        return Segment(mean, cov, ll, lambda i: replace(state, mean=mean[i], cov=cov[i]))

    def _whole_key(self) -> int:
        return (1 << self.model.m) - 1

    def _regular_chunk(self, state: GaussianState, dy: np.ndarray):
        """Rows one dt apart, each whole or missing: scheduled coefficients or the chunk code."""
        missing = np.isnan(dy[:, 0])
        scheduled = None
        if not missing.any():
            if len(dy) == 1 and dy.shape[1] == 1 and self.model.n == 1:
                lean = self._one_row(state, float(dy[0, 0]))
                if lean is not None:
                    mean, cov, ll = lean
                    return np.array([[mean]]), cov[None].copy(), np.array([ll])
            scheduled = self._scheduled_chunk(state, dy)
        if scheduled is None:  # missing rows or an unsettled long path: the general chunk code
            dy = np.where(missing[:, None], 0.0, dy)
            chunk = self._kalman_chunk if self._kalman is not None else self._continuous_chunk
            scheduled = chunk(state, dy, missing)
        return scheduled

    def _lean_row(self, state: GaussianState, dy: float, obs: Observation):
        """One observed row of a scalar model at dt (the service's chunk of 1) in plain floats:
        (mean, cov, ll, predictive ll), or None (no schedule, or the gate must look at it)."""
        lean = self._one_row(state, dy)
        if lean is None:
            return None
        mean, cov, ll = lean
        pattern = obs.pattern(1)
        if self.discrete:
            pll, log_det_S0 = ll, pattern.log_det_R + LOG_2PI
        else:
            dt = self.model.dt
            log_det_S0 = pattern.log_det_R + LOG_2PI + math.log(dt)
            pll = ll - 0.5 * dy * dy * float(pattern.R_inv[0, 0]) / dt - 0.5 * log_det_S0
        if -2.0 * pll - log_det_S0 > pattern.threshold:  # maybe an outlier: the general code decides
            return None
        return mean, cov, ll, float(pll)

    def _one_row_result(self, state: GaussianState, step: int, t: float, mean: float, cov: np.ndarray,
                        ll: float, pll: float, gate: float):
        """The new state and the one-row ChunkResult of a scalar step (plain floats in, arrays out)."""
        loglik = state.loglik + ll
        new_state = replace(state, step=step, t=t, loglik=loglik, loglik_increment=ll, mean=np.array([mean]),
                            cov=cov)
        return new_state, ChunkResult(step=np.array([step]), t=np.array([t]), mean=np.array([[mean]]),
                                      cov=cov[None].copy(), mode=np.array([[mean]]),
                                      loglik=np.array([loglik]), loglik_increment=np.array([ll]),
                                      degenerate=np.zeros(1, bool), predictive_loglik=np.array([pll]),
                                      gate=gate)

    # -- the gate's predicted covariance -------------------------------------------------------
    def _moments_over(self, tau: float):
        """(Φ, shift, Q_τ) of the Fokker–Planck flow over τ (Van Loan), cached per gap."""
        return self._gap_moments.get(float(tau), lambda: van_loan(self.F, self.model.a, self.f0, float(tau)))

    def _h_cov(self, state: GaussianState, tau: float, index: np.ndarray) -> np.ndarray:
        """Cov_pred(h_o) = H_o P⁻ H_oᵀ, P⁻ = Φ P Φᵀ + Q_τ: the predicted covariance at the row."""
        phi, _, Q = self._moments_over(tau)
        P = phi @ state.cov @ phi.T + Q
        H_o = self.H[index]
        return H_o @ P @ H_o.T

    # -- rows at irregular times or partly missing: step by step -------------------------------
    def _pattern(self, key: int):
        """(index, H_o, h0_o, R_oo, R_oo⁻¹) of the observed components ``key``."""
        found = self._patterns.get(key)
        if found is None:
            pat = self.observation.pattern(key)
            index, R_oo = pat.index, pat.R
            found = self._patterns[key] = (index, self.H[index], self.h0[index], R_oo, pat.R_inv)
        return found

    def _kalman_steps(self, state: GaussianState, rows: np.ndarray, keys: np.ndarray, taus):
        """The discrete Kalman filter row by row: predict over each gap, update with the observed
        components (measurements: z_o = H_o x + h0_o + N(0, R_oo); the sampled increment model:
        Δy_o = H_o x τ + h0_o τ + N(0, R_oo τ), log-likelihood relative to N(Δy_o; 0, R_oo τ))."""
        K, n = len(rows), self.model.n
        means, covs, lls = np.empty((K, n)), np.empty((K, n, n)), np.zeros(K)
        mean, P = np.asarray(state.mean, float), np.asarray(state.cov, float)
        dt = self.model.dt
        for k in range(K):
            tau = dt if taus is None else float(taus[k])
            phi, shift, Q = self._moments_over(tau)
            mean = phi @ mean + shift
            P = phi @ P @ phi.T + Q
            key = int(keys[k])
            if key:
                index, H_o, h0_o, R_oo, _ = self._pattern(key)
                scale = tau if self.sampled else 1.0
                C, c, V = H_o * scale, h0_o * scale, R_oo * scale
                y = rows[k, index]
                S = C @ P @ C.T + V
                S = 0.5 * (S + S.T)
                predicted = C @ mean + c
                G = np.linalg.solve(S, C @ P).T
                mean = mean + G @ (y - predicted)
                P = P - G @ S @ G.T
                lls[k] = float(log_normal(y, predicted, S))
                if self.sampled:
                    lls[k] -= float(log_normal(y, np.zeros(len(index)), V))
            P = 0.5 * (P + P.T)
            means[k], covs[k] = mean, P
        return means, covs, lls

    def _observed_eq(self, key: int) -> GaussianKolmogorov:
        """The Kolmogorov equation of an observed step with the components ``key`` (cached)."""
        found = self._equations.get(key)
        if found is None:
            _, H_o, _, _, R_inv = self._pattern(key)
            found = self._equations[key] = GaussianKolmogorov(self.F, self.f0, Q=0.5 * H_o.T @ R_inv @ H_o,
                                                              a=self.model.a)
        return found

    def _gap_flow(self, length: float, key: int):
        """The exact flow over ``length`` with the potential of the observed components ``key``."""
        return self._gap_flows.get((float(length), key), lambda: self._observed_eq(key).gap_flow(length))

    def _continuous_steps(self, state: GaussianState, rows: np.ndarray, keys: np.ndarray, taus):
        """The Kalman–Bucy flow row by row: σ = exp(−xᵀAx − Bᵀx − C) over each gap τ with
        ẏ_o = Δy_o/τ in the potential of the observed components (over pieces of a long gap, see
        riccati.gap_pieces: the path is linear over the gap, so that is exact); log ∫σ_k − log ∫σ_{k−1}
        per row.  A missing row is the
        Fokker–Planck prediction over its gap (Van Loan)."""
        K, n = len(rows), self.model.n
        means, covs, lls = np.empty((K, n)), np.empty((K, n, n)), np.zeros(K)
        mean, cov = np.asarray(state.mean, float), np.asarray(state.cov, float)
        dt = self.model.dt
        for k in range(K):
            tau = dt if taus is None else float(taus[k])
            key = int(keys[k])
            if key == 0:
                phi, shift, Q = self._moments_over(tau)
                mean, cov = phi @ mean + shift, phi @ cov @ phi.T + Q
                cov = 0.5 * (cov + cov.T)
            else:
                index, H_o, h0_o, _, R_inv = self._pattern(key)
                ydot = rows[k, index] / tau
                q = H_o.T @ R_inv @ (h0_o - ydot)
                r = 0.5 * h0_o @ R_inv @ h0_o - ydot @ (R_inv @ h0_o)
                start = gaussian_to_terms(mean, cov)
                A, B, C = start.A, start.B, 0.0
                before = terms_to_gaussian(A, B, C)[2]
                delta = float(np.linalg.eigvalsh(cov)[0]) / self._a_max if self._a_max > 0 else math.inf
                for piece in gap_pieces(tau, self._observed_eq(key).spectrum()[1], delta):
                    A, B, C = astuple(self._gap_flow(piece, key).step(A, B, C, q, r))
                mean, cov, after = terms_to_gaussian(A, B, C)
                lls[k] = after - before
            means[k], covs[k] = mean, cov
        return means, covs, lls

    # -- scheduled chunks (observed rows from a remembered covariance) ------------------------
    def _schedule_at(self, state: GaussianState) -> tuple[Schedule, int]:
        """The schedule and position whose covariance is ``state.cov`` (a new schedule if unseen)."""
        if self._kalman is not None:
            return self._schedules.at(state.cov)
        return self._schedules.at(state.cov, lambda: gaussian_to_terms(state.mean, state.cov).A)

    def _extend(self, schedule: Schedule, count: int) -> None:
        """Append ``count`` observed steps to an unsettled schedule (fewer if the path settles)."""
        zeros = np.zeros(count, dtype=bool)
        if self._kalman is None:
            path = self._flows.path(zeros.astype(int), schedule.end[None])[:, 0]
            keep, settled = settle(path)
            parts = continuous_coefficients(self.model, self._flows, self._HtR, self.h0, path[:keep],
                                            path[1:keep + 1])
        else:
            kf = self._kalman
            pieces = kalman_covariances(kf.phi, kf.Q, kf.C, kf.V, schedule.end, zeros)
            path = np.concatenate([schedule.end[None], pieces[-1]])
            keep, settled = settle(path)
            parts = kalman_coefficients(kf, self.model, path[:keep], *(p[:keep] for p in pieces))
        schedule.append(parts, settled, path[keep])

    def _scheduled_chunk(self, state: GaussianState, dy: np.ndarray):
        """(mean, cov, ll) of an all-observed chunk from cached coefficients, or None (path unsettled)."""
        schedule, j = self._schedule_at(state)
        K = len(dy)
        count = schedule.extension(j, K)
        if count is None:
            return None
        if count:
            self._extend(schedule, count)
        L = schedule.length
        idx = np.minimum(np.arange(j, j + K), L - 1) if schedule.settled and j + K > L else slice(j, j + K)
        first = min(j, L - 1)
        x0 = state.mean if self._kalman is not None else -2.0 * schedule.prev[first] @ state.mean
        W, Vy, cov = schedule.W[idx], schedule.Vy[idx], schedule.cov[idx]
        if Vy.shape[1:] == (1, 1):
            b = schedule.v0[idx] + Vy[:, 0] * dy
        else:
            b = schedule.v0[idx] + (Vy @ dy[..., None])[..., 0]
        x = linear_recursion(W, b, x0)
        u = np.concatenate([x[:-1], dy], axis=1)
        ll = quadratic(schedule.kappa[idx], schedule.ell[idx], schedule.M[idx], u)
        if self._kalman is not None:
            mean = x[1:]
        elif self.model.n == 1:
            mean = -cov[:, 0] * x[1:]
        else:
            mean = -(cov @ x[1:, :, None])[..., 0]
        self._remember(cov[-1], schedule, j + K)
        return mean, cov, ll

    def _remember(self, cov: np.ndarray, schedule: Schedule, position: int) -> None:
        self._schedules.remember(cov, schedule, position)

    def _one_row(self, state: GaussianState, dy: float):
        """One observed row of a scalar model in plain floats (the service's chunk of 1), or None."""
        schedule, j = self._schedule_at(state)
        count = schedule.extension(j, 1)
        if count is None:
            return None
        if count:
            self._extend(schedule, count)
        if schedule.scalars is None:
            names = ("W", "Vy", "v0", "kappa", "ell", "M", "prev", "cov")
            schedule.scalars = list(zip(*(getattr(schedule, k).reshape(schedule.length, -1).tolist()
                                         for k in names), strict=True))
        (w,), (vy,), (v0,), (kappa,), (l0, l1), (m00, m01, _, m11), (prev,), (p,) = \
            schedule.scalars[min(j, schedule.length - 1)]
        mean0 = float(state.mean[0])
        x0 = mean0 if self._kalman is not None else -2.0 * prev * mean0
        x = w * x0 + vy * dy + v0
        ll = kappa + l0 * x0 + l1 * dy + 0.5 * (m00 * x0 * x0 + m11 * dy * dy) + m01 * x0 * dy
        mean = x if self._kalman is not None else -p * x
        cov = np.array([[p]])
        self._remember(cov, schedule, j + 1)
        return mean, cov, ll

    # -- regular chunks of the two kinds -------------------------------------------------------
    def _continuous_chunk(self, state: GaussianState, dy: np.ndarray, missing: np.ndarray):
        """σ = exp(−xᵀAx − Bᵀx − C): A by the Riccati flow, B affine in the data, log ∫σ at the end."""
        start = gaussian_to_terms(state.mean, state.cov)
        choice = missing.astype(int)  # 0: observed flow, 1: prediction only (no potential)
        q, r = self.potential_terms(dy)
        q[missing], r[missing] = 0.0, 0.0
        A = self._flows.path(choice, start.A[None])  # (K+1, 1, n, n)
        batch = self._flows.batch(choice, A[:-1], q, r)
        B = affine_path(batch.W, batch.v, start.B[None])  # (K+1, 1, n)
        _, gain = batch.finish(B[:-1])
        mean, cov, log_mass = gaussian_terms_batch(A[:, 0], B[:, 0], np.zeros(len(A)))
        # log ∫σ_k / ∫σ_{k−1}, with C_{k−1} = 0 and C_k = gain_k (C only shifts the mass)
        increments_ll = np.where(missing, 0.0, log_mass[1:] - gain[:, 0] - log_mass[:-1])
        return mean[1:], cov[1:], increments_ll

    def _kalman_chunk(self, state: GaussianState, dy: np.ndarray, missing: np.ndarray):
        """Discrete-time Kalman filter (the sampled model or discrete measurements) over regular
        rows: covariance path, then the mean recursion."""
        kf, model = self._kalman, self.model
        n, m = model.n, model.m
        Hd, Rdt = kf.C, kf.V
        cov_pred, gain, innovation, cov = kalman_covariances(kf.phi, kf.Q, Hd, Rdt, state.cov, missing)
        # m_k = (I − G_k Hd)(Φ m_{k−1} + shift) + G_k (Δy_k − c)
        I_GH = np.eye(n) - gain @ Hd
        W = I_GH @ kf.phi
        v = (I_GH @ kf.shift) + (gain @ (dy - kf.c)[..., None])[..., 0]
        means = affine_path(W[:, None], v[:, None], state.mean[None])[:, 0]
        predicted = (means[:-1] @ kf.phi.T + kf.shift) @ Hd.T + kf.c
        ll = log_normal(dy, predicted, innovation)
        if kf.relative:
            ll = ll - log_normal(dy, np.zeros(m), Rdt[None])
        return means[1:], cov, np.where(missing, 0.0, ll)


def build(model: Model, offline: OfflineArrays | None = None, gate: float | None = None,
          **_: Any) -> KalmanBucyFilter:
    """The registry's constructor (solver/registry.py)."""
    return KalmanBucyFilter(model, gate=gate)
