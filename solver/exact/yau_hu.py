"""The Yau–Hu direct method for Yau filtering systems (method "yau-hu").

For dx = f dt + dv, dy = h dt + dw (a = I; R is whitened away) with
    (C1) f = ℓ + ∇F, ℓ = Dx + d        seed 000 (2.6)
    (C2) h = Hx + h0                     seed 000 (2.7)
    (C3) η = |f|² + div f + |h|² quadratic   seed 000 (2.5), (2.8)
the robust DMZ solution is (seed 000 Theorem 3.1, (3.2))
    u(t, x + b) = exp(−c − aᵀx + F(x + b)) ũ(t, x),   σ = exp(yᵀh) u,
where ũ solves the observation-free Kolmogorov equation (3.1)
    ũ_t = ½Δũ − ℓ·∇ũ + ½(|ℓ|² − div ℓ − η) ũ,   ũ(0) = e^{−F}σ0,
and a, b, c solve the observation-driven linear ODEs (3.3)–(3.5).  With ũ(0) a Gaussian
mixture, ũ(t) is one too (Riccati ODEs (3.8)–(3.10), solver/exact/riccati.py).

Each observation interval restarts the method from the current density (y reset to 0,
y(s) = s·Δy/dt inside the interval): the mixture stays exact (v = e^{−F}σ is a mixture after
every step, only the prior needs fitting), and a(t), b(t), which grow like e^{t} for the Beneš
model, never leave one step.  Per step: one exact Riccati flow per component, one precomputed
linear map for (a, b), a Gauss–Legendre sum for c — Kalman-like cost.  All-observed chunks go
further: the A path is data-free, so each filter caches the step coefficients (B affine, the C
gain quadratic in (B_prev, Δy)) until the path settles, and reuses them (solver/exact/schedule.py).

Moments need ∫e^{F}·Gaussian in closed form: e^{F} must be a finite sum of positive multiples of
exponentials of affine functions (F = 0, log cosh, ...), found symbolically; otherwise SpecError.
Log-likelihood: log ratio of ∫σ (the Brownian-reference convention of KalmanBucyFilter).

The spec's ``[measurement]`` (solver/measurement.py):

* rows at irregular ``times``: each interval is its gap τ_k (y(s) = s·Δy/τ_k), with flows and maps
  per gap (kept in a bounded cache; the Riccati flow from the eigen-decomposition of its linear
  system); a long gap is taken in pieces, each with its share of the linear path
  (riccati.gap_pieces: the Gauss–Legendre rules stay accurate; splitting is exact);
* a partly missing row: the method with the observed components o only (whitened by R_oo, η with
  |h_o|² in place of |h|² — still quadratic as h is affine);
* discrete measurements z = Hx(t_k) + h0 + v, v ~ N(0, R): the prediction over the gap (the
  observation-free flow), then every component times N(z_o; H_o x + h0_o, R_oo) — a Gaussian
  factor, so A, B, C change in closed form and the filter stays exact; log-likelihoods are the
  densities log p(z_o | past).  Student-t noise is refused (SpecError; use yau-yau);
* ``predictive_loglik``: log p(row | past) (continuous: the Girsanov increment plus log N(Δy_o; 0,
  R_oo τ)); the gate's score uses the exact predictive covariance S = κ²H_o Cov_pred(x) H_oᵀ + S₀,
  Cov_pred(x) from the predicted mixture (solver/exact/schedule.py ``gated_chunk``).

Rows at irregular times, partly missing or discrete go row by row (no cached schedules).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Any

import numpy as np
import sympy as sp
from scipy.special import logsumexp

from ..errors import InputError, SpecError
from ..expressions import affine_coefficients
from ..filtering import ChunkedFilter, ChunkResult, Estimate, StepState, chunk_clock
from ..gaussian import log_normal
from ..measurement import LOG_2PI, Observation, check_first_gap, check_gate, check_rows, resolve_times
from ..model import Model, compile_model
from ..spec_tables import DensityPrior, GaussianPrior, MixturePrior
from .mixtures import log_sum_exp, mixture_moments, mixture_terms, scalar_mixture
from .prior_fit import fit_mixture_grid, weighted_em
from .riccati import (
    FlowFamily,
    affine_path,
    gap_pieces,
    gaussian_terms_batch,
    gaussian_to_terms,
    linear_recursion,
    mixture_state_from_dict,
    settle,
)
from .schedule import (
    MAX_ENTRIES,
    MAX_STEPS,
    BoundedCache,
    Schedule,
    ScheduleCache,
    Segment,
    gated_chunk,
    regular_gaps,
)
from .yau_hu_step import StepKit, YauHuStep, schedule_coefficients
from .yau_system import yau_system

if TYPE_CHECKING:  # types only
    from numpy.typing import ArrayLike

    from ..offline.pipeline import OfflineArrays


@dataclass(frozen=True)
class YauHuState(StepState):
    """v = e^{−F}σ = Σ_i exp(−xᵀA_ix − B_iᵀx − C_i), normalised so that ∫σ = 1."""

    A: np.ndarray = field(default_factory=lambda: np.full((1, 1, 1), 0.5))
    B: np.ndarray = field(default_factory=lambda: np.zeros((1, 1)))
    C: np.ndarray = field(default_factory=lambda: np.zeros(1))
    fit_error: float = 0.0

    def to_dict(self) -> dict[str, Any]:
        return {"A": self.A.tolist(), "B": self.B.tolist(), "C": self.C.tolist(), "step": self.step,
                "t": self.t, "loglik": self.loglik, "loglik_increment": self.loglik_increment,
                "degenerate": self.degenerate, "reason": self.reason, "fit_error": self.fit_error}


class YauHuFilter(ChunkedFilter):
    """Filter protocol; exact for Gaussian-mixture e^{−F}σ0, else the prior is fitted."""

    method = "yau-hu"

    def __init__(self, model: Model, n_components: int = 8, gate: float | None = None):
        self.model = model
        if not isinstance(n_components, int) or not 1 <= n_components <= 64:
            raise SpecError("n_components", "must be an integer in 1..64")
        measurement = model.spec.measurement
        if measurement.likelihood != "gaussian":
            raise SpecError("measurement.likelihood", f"yau-hu is exact for Gaussian noise, not "
                                                      f"{measurement.likelihood}; use yau-yau (the general "
                                                      "engine)")
        self.discrete = measurement.kind == "discrete"  # measurements z = h(x(t_k)) + v
        self.gate_override = check_gate(gate)
        self.n_components = n_components
        self.system = yau_system(model)
        L = np.linalg.cholesky(model.R)
        self.L_inv = np.linalg.inv(L)
        H, h0 = affine_coefficients(model.observation, model.symbols, "observation")
        self.H, self.h0 = H, h0
        Hw, h0w = self.L_inv @ H, self.L_inv @ h0
        self._observed = YauHuStep(self.system, Hw, h0w, (0, 0, 0), model.dt)
        # a missing row: the signal alone, η without |h|²
        minus_h = (-Hw.T @ Hw, -2 * Hw.T @ h0w, -float(h0w @ h0w))
        self._minus_h = minus_h
        predicted = YauHuStep(self.system, np.zeros_like(Hw), np.zeros_like(h0w), minus_h, model.dt)
        flows = [self._observed.flow, predicted.flow]  # choice 0: observed step, 1: missing row
        self._family = FlowFamily(flows)
        self._q = np.stack([f.eq.q for f in flows])
        self._r = np.array([f.eq.r for f in flows])
        self._Hw, self._h0w = Hw, h0w
        self._scalar_whitening = float(self.L_inv[0, 0])  # the one-row path (n = m = 1)
        self._schedules = ScheduleCache()  # exponents A -> (schedule, step index)
        self._kits = BoundedCache()  # (gap, pattern) -> StepKit (irregular gaps, partly missing rows)
        self._steps_by_key: dict[int, tuple] = {}
        self._patterns: dict[int, tuple] = {}

    # -- mixtures of e^{F}·exp(−xᵀAx − Bᵀx − C) ------------------------------------------
    def _components(self, A, B, C):
        """(log weights, means, covs) of σ = e^{F}v as flat Gaussian mixtures.

        A (..., J, n, n), B (..., J, n), C (..., J) -> (..., J·T), (..., J·T, n), (..., J·T, n, n)
        with e^{F} = Σ_T exp(log c + sᵀx); InputError('A') if a component is not integrable.
        """
        slopes, logc = self.system.exp_F_slopes, self.system.exp_F_logc
        A, B, C = np.asarray(A, float), np.asarray(B, float), np.asarray(C, float)
        mean, cov, log_mass = gaussian_terms_batch(A[..., None, :, :], B[..., None, :] - slopes,
                                                   C[..., None] - logc)
        lead, n = C.shape, self.model.n
        cov = np.repeat(cov, len(logc), axis=-3)  # A does not depend on the term of e^{F}
        return (log_mass.reshape(lead[:-1] + (-1,)), mean.reshape(lead[:-1] + (-1, n)),
                cov.reshape(lead[:-1] + (-1, n, n)))

    def _normalised(self, A, B, C):
        log_mass = float(log_sum_exp(self._components(A, B, C)[0]))
        return C + log_mass, log_mass

    # -- prior -------------------------------------------------------------------------
    def initial_state(self, prior: Any | None = None) -> YauHuState:
        prior = self.model.spec.initial if prior is None else prior
        if isinstance(prior, (GaussianPrior, MixturePrior)) and len(self.system.exp_F_logc) == 1 \
                and not np.any(self.system.exp_F_slopes):
            A, B, C = mixture_terms(prior)  # F constant: e^{−F}σ0 is the prior mixture itself
            fit_error = 0.0
        elif isinstance(prior, (GaussianPrior, MixturePrior, DensityPrior)):
            A, B, C, fit_error = self._fit_prior(prior)
        else:
            raise SpecError("initial", "unsupported prior kind")
        C, _ = self._normalised(A, B, C)
        return YauHuState(A=A, B=B, C=C, fit_error=fit_error)

    def _fit_prior(self, prior):
        """Fit e^{−F}σ0 on a grid by a weighted EM Gaussian mixture; L¹ relative fit error."""
        # a prior override is checked by the model
        model = self.model if prior is self.model.spec.initial else compile_model(
            self.model.spec.model_copy(update={"initial": prior}))
        X, vol = fit_mixture_grid(model)
        F_at = np.asarray(sp.lambdify(model.symbols, self.system.F, "numpy")(*X.T), float) * np.ones(len(X))
        log_target = model.log_prior(X) - F_at
        ok = np.isfinite(log_target)
        top = log_target[ok].max()
        weights = np.where(ok, np.exp(log_target - top), 0.0) * vol
        log_total = np.log(weights.sum()) + top  # log ∫v0 on the grid
        target = np.where(ok, np.exp(log_target - log_total), 0.0)
        best = None
        for K in sorted({1, 2, 4, self.n_components} & set(range(1, self.n_components + 1))):
            mix_w, means, covs = weighted_em(X, weights / weights.sum(), K)
            terms = [gaussian_to_terms(mu, P, w) for w, mu, P in zip(mix_w, means, covs, strict=False)]
            A = np.stack([t.A for t in terms])
            B = np.stack([t.B for t in terms])
            C = np.array([t.C for t in terms])  # mass 1: the scale of v0 drops out when σ is normalised
            fitted = np.exp(logsumexp(-np.einsum("pi,kij,pj->kp", X, A, X) - B @ X.T - C[:, None], axis=0))
            error = float(np.sum(np.abs(fitted - target)) * vol)
            if best is None or error < best[3]:
                best = (A, B, C, error)
        return best

    # -- Filter protocol -----------------------------------------------------------------
    def run_arrays(self, state: YauHuState, increments: np.ndarray,
                   times: ArrayLike | None = None) -> tuple[YauHuState, "ChunkResult"]:
        """Advance over a chunk (K, m) of rows (NaN: a missing component; a NaN row: prediction only)
        at ``times`` (absolute, strictly increasing) or one dt apart; estimates as arrays.

        Regular chunks of whole continuous increments use the cached schedule of data-free step
        coefficients (solver/exact/schedule.py); chunks with missing rows (or a path that never
        settles) take the general chunk code; irregular gaps, partly missing rows and discrete
        measurements go row by row (:meth:`_steps`).  The outlier gate: solver/exact/schedule.py.
        """
        model = self.model
        rows = check_rows(increments, model.m)
        K, n = len(rows), model.n
        taus = resolve_times(state.t, state.step > 0, K, model.dt, times)
        steps, times = chunk_clock(state, K, model.dt, times, taus)
        if K == 0:
            return state, ChunkResult(steps, times, np.empty((0, n)), np.empty((0, n, n)), None,
                                       np.empty(0), np.empty(0), np.zeros(0, bool))
        check_first_gap(taus, self.discrete, self.method)
        taus = regular_gaps(taus, model.dt, times, state.t)
        obs = self.observation
        if taus is None and K == 1 and n == 1 and model.m == 1 and not self.discrete \
                and not np.isnan(rows[0, 0]):
            lean = self._lean_row(state, float(rows[0, 0]), obs)
            if lean is not None:
                return _one_row_result(state, int(steps[0]), float(times[0]), *lean, obs.gate)
        keys = obs.pattern_keys(~np.isnan(rows))
        gaps = np.full(K, model.dt) if taus is None else taus
        terms = obs.row_terms(rows, gaps, keys)
        done = gated_chunk(state, rows, keys, taus, gaps, obs, terms, self._segment, self._h_cov)
        increments_ll, last = done.ll, done.last
        loglik = np.cumsum(np.concatenate([[state.loglik], increments_ll]))[1:]
        new_state = replace(state, step=int(steps[-1]), t=float(times[-1]), loglik=float(loglik[-1]),
                            loglik_increment=float(increments_ll[-1]), A=last.A, B=last.B, C=last.C)
        return new_state, ChunkResult(steps, times, done.mean, done.cov, None, loglik, increments_ll,
                                       np.zeros(K, bool), predictive_loglik=done.predictive, gated=done.gated,
                                       gate_score=done.score, gate=obs.gate)

    def smooth_arrays(self, state: YauHuState, increments: Any, times: Any = None):
        """The exact fixed-interval smoother (exact/yau_hu_smoother.py): (state after, smoothed result)."""
        from .yau_hu_smoother import smooth_arrays  # lazy: the filter alone never loads it

        return smooth_arrays(self, state, increments, times, self._steps, self._whitened)

    def _segment(self, state: YauHuState, rows: np.ndarray, keys: np.ndarray, taus) -> Segment:
        """Estimates, log-likelihood increments and the exponents after each row (the gate's unit)."""
        whole = (1 << self.model.m) - 1
        if taus is None and not self.discrete and np.all((keys == 0) | (keys == whole)):
            missing = keys == 0
            done = None
            if not missing.any():
                done = self._scheduled_chunk(state, rows @ self.L_inv.T)  # whitened increments
            if done is None:
                done = self._general_chunk(state, rows, missing)
        else:
            done = self._steps(state, rows, keys, taus)
        (mean, cov, increments_ll), (A, B, C) = done
        return Segment(mean, cov, increments_ll, lambda i: replace(state, A=A[i], B=B[i], C=C[i]))

    def _lean_row(self, state: YauHuState, dy: float, obs: Observation):
        """One observed row of a scalar model at dt in plain floats (the service's chunk of 1), or
        None (no schedule, or the gate must look at it)."""
        lean = self._one_row(state, dy * self._scalar_whitening)
        if lean is None:
            return None
        ll = lean[2]
        pattern, dt = obs.pattern(1), self.model.dt
        log_det_S0 = pattern.log_det_R + LOG_2PI + math.log(dt)
        pll = ll - 0.5 * dy * dy * float(pattern.R_inv[0, 0]) / dt - 0.5 * log_det_S0
        if -2.0 * pll - log_det_S0 > pattern.threshold:  # maybe an outlier: the general code decides
            return None
        return (*lean, float(pll))

    def _advance(self, family: FlowFamily, q, r, obs: YauHuStep, choice, dyw, A0, B0, C0):
        """The exponent paths (K+1) of K steps of one flow family from (A0, B0, C0): the Riccati path
        of the A_k, B as an affine recursion in the (whitened) data, C by sums."""
        A = family.path(choice, A0)  # (K+1, J, n, n)
        batch = family.batch(choice, A[:-1], q[choice], r[choice])
        a, b, c = obs.observation_terms(dyw / obs.dt)  # 0 on missing rows
        # seed 000 (3.2) restarted each step: B2 = B_flow − 2A b + a − Hᵀdy (YauHuStep's (a, b, c) shift)
        Ab = batch.mm(A[1:], b[:, None, :, None])[..., 0]  # (K, J, n)
        shift = -2.0 * Ab + (a - dyw @ obs.H)[:, None]
        B = affine_path(batch.W, batch.v + shift, B0)  # (K+1, J, n)
        B_flow, gain = batch.finish(B[:-1])
        dC = gain + ((Ab - B_flow) * b[:, None]).sum(-1) + (c - (a * b).sum(-1) - dyw @ obs.h0)[:, None]
        C = np.concatenate([C0[None], C0 + np.cumsum(dC, axis=0)])
        return A, B, C

    def _general_chunk(self, state: YauHuState, dy: np.ndarray, missing: np.ndarray):
        """Any regular chunk: Riccati path of the A_k, B as an affine recursion in the data, C, the
        normaliser log Σ∫σ_i and the moments in batch (cumulative, renormalised at the end)."""
        dyw = np.where(missing[:, None], 0.0, dy) @ self.L_inv.T  # whitened; 0 on missing rows
        choice = missing.astype(int)
        A, B, C = self._advance(self._family, self._q, self._r, self._observed, choice, dyw, state.A, state.B,
                                state.C)
        logw, means, covs = self._integrable(A, B, C)
        log_mass = log_sum_exp(logw)  # log ∫σ_k relative to the normalised start
        increments_ll = np.where(missing, 0.0, log_mass[1:] - log_mass[:-1])
        mean, cov = mixture_moments(logw[1:], means[1:], covs[1:])
        return (mean, cov, increments_ll), (A[1:], B[1:], C[1:] + log_mass[1:, None])

    def _integrable(self, A, B, C):
        """The mixture's (log weights, means, covs); InputError when a component lost integrability."""
        try:
            return self._components(A, B, C)
        except InputError:
            raise InputError("increments", "the mixture lost integrability (a component is not "
                                           "positive definite)") from None

    # -- irregular gaps, partly missing rows, discrete measurements: row by row ----------------
    def _pattern(self, key: int):
        """(index, L_o⁻¹, H_o, h0_o, R_oo⁻¹, ½ log det 2πR_oo) of the observed components ``key``."""
        found = self._patterns.get(key)
        if found is None:
            pat = self.observation.pattern(key)
            index, R_oo = pat.index, pat.R
            L_inv = np.linalg.inv(np.linalg.cholesky(R_oo))
            found = self._patterns[key] = (index, L_inv, self.H[index], self.h0[index], pat.R_inv,
                                           0.5 * (pat.log_det_R + len(index) * LOG_2PI))
        return found

    def _whitened(self, key: int):
        """(Hw, h0w, η shift, rate) of the step with the observed components ``key`` (0: none)."""
        found = self._steps_by_key.get(key)
        if found is None:
            if key == 0:
                Hw, h0w = np.zeros_like(self._Hw), np.zeros_like(self._h0w)
                shift = self._minus_h
            else:
                _, L_inv, H_o, h0_o, _, _ = self._pattern(key)
                Hw, h0w = L_inv @ H_o, L_inv @ h0_o
                # η with |h_o|² (whitened by R_oo) in place of |h|²
                shift = tuple(full + part for full, part in zip(self._minus_h, (
                    Hw.T @ Hw, 2 * Hw.T @ h0w, float(h0w @ h0w)), strict=True))
            found = self._steps_by_key[key] = (Hw, h0w, shift, YauHuStep.rate(self.system, Hw, shift))
        return found

    def _kit(self, length: float, key: int) -> StepKit:
        """The step over ``length`` with the observed components ``key`` (0: prediction only), cached."""
        def make():
            Hw, h0w, shift, _ = self._whitened(key)
            step = YauHuStep(self.system, Hw, h0w, shift, length, gap=True)
            return StepKit(step, FlowFamily([step.flow]), step.flow.eq.q[None], np.array([step.flow.eq.r]))
        return self._kits.get((float(length), key), make)

    def _pieces(self, A: np.ndarray, tau: float, key: int) -> tuple[float, ...]:
        """The pieces of a gap (riccati.gap_pieces; δ: the narrowest component, a = I)."""
        delta = 1.0 / (2.0 * float(np.linalg.eigvalsh(A)[..., -1].max()))
        return gap_pieces(tau, self._whitened(key)[3], delta)

    def _predicted(self, A, B, C, tau: float):
        """The exponents after the prediction (no observation) over τ."""
        return self._observed_over(A, B, C, tau, 0, np.zeros(self.model.m))

    def _observed_over(self, A, B, C, tau: float, key: int, yw: np.ndarray):
        """The exponents after a gap τ with the whitened increment ``yw`` of the observed components
        ``key`` (0: none), over the gap's pieces, each with its share of the linear path."""
        zero = np.zeros(1, dtype=int)
        for piece in self._pieces(A, tau, key):
            kit = self._kit(piece, key)
            share = (yw * (piece / tau))[None]
            path = self._advance(kit.family, kit.q, kit.r, kit.step, zero, share, A, B, C)
            A, B, C = path[0][-1], path[1][-1], path[2][-1]
        return A, B, C

    def _steps(self, state: YauHuState, rows: np.ndarray, keys: np.ndarray, taus):
        """Rows one by one, each over its own gap.  Continuous increments: the method restarted over
        the gap (or its substeps, each with its share of the linear path) with the observed
        components; discrete measurements: the prediction over the gap, then each component times
        N(z_o; H_o x + h0_o, R_oo) (a Gaussian factor: A, B, C change in closed form)."""
        K = len(rows)
        A, B, C = state.A, state.B, state.C
        paths = []
        for k in range(K):
            tau = self.model.dt if taus is None else float(taus[k])
            key = int(keys[k])
            if self.discrete:
                A, B, C = self._predicted(A, B, C, tau)
                if key:
                    index, _, H_o, h0_o, R_inv, half_log_det = self._pattern(key)
                    resid = rows[k, index] - h0_o
                    A = A + 0.5 * H_o.T @ R_inv @ H_o
                    B = B - H_o.T @ (R_inv @ resid)
                    C = C + 0.5 * resid @ R_inv @ resid + half_log_det
            elif key == 0:
                A, B, C = self._predicted(A, B, C, tau)
            else:
                index, L_inv = self._pattern(key)[:2]
                A, B, C = self._observed_over(A, B, C, tau, key, L_inv @ rows[k, index])
            paths.append((A, B, C))
        A, B, C = (np.stack(v) for v in zip(*paths, strict=True))
        logw, means, covs = self._integrable(A, B, C)
        log_mass = log_sum_exp(logw)  # log ∫σ_k relative to the normalised start
        start_mass = float(log_sum_exp(self._components(state.A, state.B, state.C)[0]))
        increments_ll = np.where(keys == 0, 0.0, np.diff(log_mass, prepend=start_mass))
        mean, cov = mixture_moments(logw, means, covs)
        return (mean, cov, increments_ll), (A, B, C + log_mass[:, None])

    def _h_cov(self, state: YauHuState, tau: float, index: np.ndarray) -> np.ndarray:
        """Cov_pred(h_o) = H_o Cov_pred(x) H_oᵀ under the mixture predicted over τ (the gate's exact S)."""
        A, B, C = self._predicted(state.A, state.B, state.C, tau)
        _, cov = mixture_moments(*self._components(A, B, C))
        H_o = self.H[index]
        return H_o @ cov @ H_o.T

    # -- scheduled chunks (observed rows from remembered exponents A) -----------------------
    # The exponents A_k of every component follow an observation-free Riccati path that converges to
    # the steady solution; B enters each step affinely and the C gain quadratically in (B_prev, y)
    # (yau_hu_step.schedule_coefficients).  A schedule stores those coefficients step by step from one
    # start until the path stops moving (to rounding), then reuses the last (steady) entry.  Positions
    # are keyed by the bytes of A: the coefficients of a step depend only on the A it starts from.
    def _schedule_at(self, state: YauHuState) -> tuple[Schedule, int]:
        """The schedule and position whose exponents are ``state.A`` (a new schedule if unseen)."""
        return self._schedules.at(state.A)

    def _ready(self, schedule: Schedule, j: int, K: int) -> bool:
        """Extend an unsettled schedule to cover steps j..j+K−1.

        False (the general chunk code takes over, and reports any failure at its step) if that is
        past the size cap, or the path blows up or leaves the positive-definite exponents first.
        """
        J, n = schedule.end.shape[0], self.model.n
        count = schedule.extension(j, K, min(MAX_STEPS, MAX_ENTRIES // (J * (n + self.model.m) ** 2)))
        if count is None:
            return False
        if count == 0:
            return True
        try:
            path = self._family.path(np.zeros(count, dtype=int), schedule.end)  # (count+1, J, n, n)
        except InputError:
            return False
        keep, settled = settle(path.reshape(len(path), J * n, n))
        bad = np.flatnonzero(np.linalg.eigvalsh(path[1:keep + 1]).min(axis=(1, 2)) <= 0.0)
        if len(bad):  # keep the good steps; a later extension starts at the bad one and fails
            keep, settled = int(bad[0]), False
        if keep:
            parts = schedule_coefficients(self._observed, self._family, self._q, self._r, path[:keep],
                                          path[1:keep + 1])
            schedule.append(parts, settled, path[keep])
        return j + K <= schedule.length or schedule.settled

    def _position(self, state: YauHuState, K: int):
        """(schedule, start index j, step indices) covering K observed steps from ``state``, or None."""
        schedule, j = self._schedule_at(state)
        if not self._ready(schedule, j, K):
            return None
        L = schedule.length
        idx = np.minimum(np.arange(j, j + K), L - 1) if schedule.settled and j + K > L else slice(j, j + K)
        return schedule, j, idx

    def _scheduled_chunk(self, state: YauHuState, y: np.ndarray):
        """Outputs of an all-observed chunk (whitened y (K, m)) from cached coefficients, or None."""
        found = self._position(state, len(y))
        if found is None:
            return None
        schedule, j, idx = found
        if self.model.n == 1 and self.model.m == 1:
            outputs, (B, C) = self._scalar_chunk(state, schedule.row_view(), idx, y[:, 0])
        else:
            outputs, (B, C) = self._matrix_chunk(state, schedule.parts, idx, y)
        A = np.array(schedule.parts["A"][idx])  # (K, J, n, n), a copy
        self._schedules.remember(A[-1], schedule, j + len(y))
        return outputs, (A, B, C)

    def _matrix_chunk(self, state: YauHuState, parts: dict, idx, y: np.ndarray):
        """Any n, m: coefficients (K, J, ...) from the schedule, recursion per component."""
        c = {name: value[idx] for name, value in parts.items()}
        b = c["v0"] + np.einsum("kjam,km->kja", c["Vy"], y)
        J = b.shape[1]
        B = np.stack([linear_recursion(c["W"][:, i], b[:, i], state.B[i]) for i in range(J)], axis=1)
        x = B[:-1]
        dC = (c["kappa"] + (c["lx"] * x).sum(-1) + np.einsum("kjm,km->kj", c["ly"], y)
              + np.einsum("kja,kjab,kjb->kj", x, 0.5 * c["Mxx"], x)
              + np.einsum("kja,kjam,km->kj", x, c["Mxy"], y)
              + np.einsum("km,kjmp,kp->kj", y, 0.5 * c["Myy"], y))
        C = state.C + np.cumsum(dC, axis=0)
        logw, means, covs = self._terms(c["cov"], c["half_log_det"], B[1:], C)
        log_mass = log_sum_exp(logw)
        start_mass = log_sum_exp(self._components(state.A, state.B, state.C)[0])
        increments_ll = np.diff(log_mass, prepend=start_mass)
        mean, cov = mixture_moments(logw, means, covs)
        return (mean, cov, increments_ll), (B[1:], C + log_mass[:, None])

    def _scalar_chunk(self, state: YauHuState, rows: dict, idx, y: np.ndarray):
        """n = m = 1: coefficient rows (J, K) (time last, so sums over components are vectorised)."""
        c = {name: value[:, idx] for name, value in rows.items()}
        b = c["v0"] + c["Vy"] * y
        J, K = b.shape
        B = np.empty((J, K + 1))
        for i in range(J):
            B[i] = linear_recursion(c["W"][i, :, None, None], b[i, :, None], state.B[i])[:, 0]
        x = B[:, :-1]
        dC = c["kappa"] + c["lx"] * x + c["ly"] * y + 0.5 * (c["Mxx"] * x * x + c["Myy"] * y * y) \
            + c["Mxy"] * x * y
        C = np.cumsum(dC, axis=1) + state.C[:, None]
        slopes, logc = self.system.exp_F_slopes[:, 0], self.system.exp_F_logc
        dev = B[:, None, 1:] - slopes[:, None]  # (J, T, K)
        p = c["cov"][:, None]
        means = (-p * dev).reshape(J * len(logc), K)
        logw = (c["half_log_det"][:, None] + 0.5 * p * dev * dev - C[:, None] + logc[:, None]).reshape(-1, K)
        var = np.broadcast_to(p, dev.shape).reshape(-1, K)
        if len(logw) == 1:
            log_mass, mean, cov = logw[0], means[0], var[0]
        else:
            top = logw.max(axis=0)
            w = np.exp(logw - top)
            total = w.sum(axis=0)
            mean = (w * means).sum(axis=0) / total
            cov = (w * (var + (means - mean) ** 2)).sum(axis=0) / total
            log_mass = top + np.log(total)
        start_mass = scalar_mixture((0.5 / state.A[:, 0, 0]).tolist(), None, state.B[:, 0].tolist(),
                                     state.C.tolist(), slopes.tolist(), logc.tolist())[0]
        increments_ll = np.diff(log_mass, prepend=start_mass)
        return (mean[:, None], cov[:, None, None], increments_ll), (B[:, 1:].T[..., None], (C + log_mass).T)

    def _terms(self, cov, half_log_det, B, C):
        """:meth:`_components` from cached covariances: cov (K, J, n, n), B (K, J, n), C (K, J)."""
        slopes, logc = self.system.exp_F_slopes, self.system.exp_F_logc
        dev = B[:, :, None, :] - slopes  # (K, J, T, n)
        P_dev = np.einsum("kjab,kjtb->kjta", cov, dev)
        logw = half_log_det[..., None] + 0.5 * (dev * P_dev).sum(-1) - C[..., None] + logc
        K, J, T, n = dev.shape
        covs = np.broadcast_to(cov[:, :, None], (K, J, T, n, n)).reshape(K, J * T, n, n)
        return logw.reshape(K, J * T), -P_dev.reshape(K, J * T, n), covs

    def _one_row(self, state: YauHuState, y: float):
        """One observed row of a scalar model in plain floats (the service's chunk of 1), or None."""
        schedule, j = self._schedule_at(state)
        if not self._ready(schedule, j, 1):
            return None
        if schedule.scalars is None:
            names = ("W", "Vy", "v0", "kappa", "lx", "ly", "Mxx", "Mxy", "Myy", "cov", "half_log_det")
            columns = [schedule.parts[k].reshape(schedule.length, -1).tolist() for k in names]
            schedule.scalars = [list(zip(*row, strict=True)) for row in zip(*columns, strict=True)]
        k = min(j, schedule.length - 1)
        slopes = self.system.exp_F_slopes[:, 0].tolist()
        logc = self.system.exp_F_logc.tolist()
        B_new, C_new, cov_new, hl_new = [], [], [], []
        for (w, vy, v0, kappa, lx, ly, mxx, mxy, myy, p, hl), x, c in zip(
                schedule.scalars[k], state.B[:, 0].tolist(), state.C.tolist(), strict=True):
            B_new.append(w * x + vy * y + v0)
            C_new.append(c + kappa + lx * x + ly * y + 0.5 * (mxx * x * x + myy * y * y) + mxy * x * y)
            cov_new.append(p)
            hl_new.append(hl)
        cov_old = [0.5 / a for a in state.A[:, 0, 0].tolist()]
        start_mass = scalar_mixture(cov_old, None, state.B[:, 0].tolist(), state.C.tolist(), slopes, logc)[0]
        log_mass, mean, var = scalar_mixture(cov_new, hl_new, B_new, C_new, slopes, logc)
        A_last = schedule.parts["A"][k].copy()
        self._schedules.remember(A_last, schedule, j + 1)
        return mean, var, log_mass - start_mass, A_last, B_new, [c + log_mass for c in C_new]

    def estimate(self, state: YauHuState) -> Estimate:
        mean, cov = mixture_moments(*self._components(state.A, state.B, state.C))
        return Estimate(step=state.step, t=state.t, mean=mean, cov=cov, loglik=state.loglik,
                        loglik_increment=state.loglik_increment, degenerate=state.degenerate,
                        reason=state.reason)

    def density(self, state: YauHuState, points: np.ndarray) -> np.ndarray:
        X = np.atleast_2d(np.asarray(points, float))
        if X.shape[1] != self.model.n or not np.all(np.isfinite(X)):
            raise InputError("points", f"must be finite points of shape (P, {self.model.n})")
        logw, means, covs = self._components(state.A, state.B, state.C)
        logs = [lw + log_normal(X, mu, P) for lw, mu, P in zip(logw, means, covs, strict=False)]
        return np.exp(logsumexp(np.stack(logs), axis=0))

    def state_from_dict(self, data: dict[str, Any]) -> YauHuState:
        return mixture_state_from_dict(YauHuState, data, self.model.n, "yau-hu")


def _one_row_result(state: YauHuState, step: int, t: float, mean: float, var: float, ll: float, A, B: list,
                    C: list, pll: float, gate: float):
    """The new state and the one-row ChunkResult of a scalar step (plain floats in, arrays out)."""
    loglik = state.loglik + ll
    new_state = replace(state, step=step, t=t, loglik=loglik, loglik_increment=ll, A=A,
                        B=np.array(B)[:, None], C=np.array(C))
    return new_state, ChunkResult(step=np.array([step]), t=np.array([t]), mean=np.array([[mean]]),
                                 cov=np.array([[[var]]]), mode=None, loglik=np.array([loglik]),
                                 loglik_increment=np.array([ll]), degenerate=np.zeros(1, bool),
                                 predictive_loglik=np.array([pll]), gate=gate)


def build(model: Model, offline: OfflineArrays | None = None, gate: float | None = None,
          **_: Any) -> YauHuFilter:
    """The registry's constructor (solver/registry.py)."""
    return YauHuFilter(model, gate=gate)
