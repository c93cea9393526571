"""The Yau–Jia filter: nonlinear observations, Kolmogorov equation by ODEs (method "yau-jia").

Seed 001 §4 (Yau & Jia, 2005, Theorem 4.2): when f = Lx + ℓ + a∇φ (4.1) and
V = hᵀR⁻¹h + tr(a∇²φ) + ∇φᵀa∇φ + 2(Lx + ℓ)·∇φ = xᵀQx + qᵀx + q0 (4.2) — found symbolically by
solver/analysis/yau_jia.py, for any constant a ≥ 0 — the observation-free part of the robust DMZ
equation maps Gaussians to Gaussians: with σ = e^{φ}v,

    ∂v/∂t = ½Σa_ij∂i∂jv − (Lx + ℓ)·∇v − (tr L + ½V − ẏᵀR⁻¹h) v        (4.11) plus the data term

and v is carried as a Gaussian mixture Σ_j exp(−xᵀA_jx − B_jᵀx − C_j).  No mesh: any dimension.
Per observation interval (ẏ = Δy/dt, as the Kalman–Bucy filter takes the path):

1. the data term ẏᵀR⁻¹h is split, per component j, into its first-order Taylor part about the
   component's mean m_j — affine in x, so it enters the exact Gaussian flow with (4.14)–(4.16) as the
   linear and constant terms of the potential (solver/exact/riccati.py: one cached matrix exponential,
   exact over dt) — and the remainder ρ_j(x) = h(x) − h(m_j) − J_j(x − m_j);
2. the factor exp(Δyᵀ R⁻¹ ρ_j(x)) is applied by its second-order expansion about the new mean (a
   Gaussian times exp(quadratic) is a Gaussian).  For h affine, ρ = 0: the filter is Kalman–Bucy.

The error is the third-order remainder of h over each component.  It is controlled by splitting:
after each step, for every component the sensor's departure from its quadratic model at the
±√3σ points of each principal axis, ε, is measured (whitened by R); the log-likelihood error it
causes accumulates at about ε·(|h(m)|_R + 1) per unit time, and the ``split_budget`` components
(default max_components / 8) with the largest rates above ``split_tolerance`` are split along that
axis into three (moment-preserving weights 0.2252, 0.5496, 0.2252, offsets ±1.0575σ).  The budget
grows with the cap because the diffusion widens every component at every step: with one split per
step a large mixture starves and its components grow wide (a 2-D ring-shaped posterior was then
*less* accurate at 128 components than at 32).  Room for the splits is made first, by merging the
cheapest pairs (Runnalls' bound, moments kept) among the other components, so that a fresh split is
never merged back.  Components whose weight falls below e^{−30} of the largest are pruned.  The cap
(``default_components``) is 64 in 1-D, 128 in 2-D and 16 above.  Log-scale weights throughout; the
log-likelihood (log of the ratio of ∫σ, the convention of KalmanBucyFilter) is carried; a step that loses
integrability is reported degenerate and the state keeps the last good mixture.

σ = e^{φ}v: moments need ∫e^{φ}·Gaussian in closed form, so e^{φ} must be a sum of exponentials of
affine functions (φ = 0: linear drift; log cosh: Beneš); otherwise SpecError.

Rows at irregular ``times``: the step over each gap τ (ẏ = Δy/τ, flows per gap in a bounded cache),
a long gap in pieces (riccati.gap_pieces), each with its share of the path and the error control
after it.  ``predictive_loglik`` = the Girsanov increment + log N(Δy; 0, Rτ); the outlier gate is
described at ``run_arrays``.  Refused: discrete measurements (SpecError 'measurement.kind') and
partly missing rows (InputError 'increments[k]': the class condition is on hᵀR⁻¹h of the whole
sensor); yau-yau takes both.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Any

import numpy as np
import sympy as sp

from .. import jit
from ..analysis.yau_jia import YauJiaStructure, yau_jia_structure
from ..errors import InputError, SpecError
from ..filtering import ChunkedFilter, ChunkResult, Estimate, StepState, chunk_clock, refuse_form
from ..gaussian import log_normal
from ..measurement import check_first_gap, check_gate, check_rows, resolve_times, standard_score
from ..model import Model
from ..spec import DensityPrior, GaussianPrior, MixturePrior
from .mixtures import (
    SPLIT_OFFSETS,
    SPLIT_WEIGHTS,
    SPLIT_WIDTH,
    cubature_points,
    exponent_terms,
    log_sum_exp,
    merge_to,
    split_all,
    times_exp_quadratic,
)
from .riccati import (
    FlowFamily,
    GaussianKolmogorov,
    gap_pieces,
    gaussian_terms_batch,
    gaussian_to_terms,
    mixture_state_from_dict,
)
from .schedule import BoundedCache, regular_gaps
from .sensor_tape import Tape, Uncompilable, sensor_tapes
from .yau_system import exponential_sum

if TYPE_CHECKING:  # types only
    from numpy.typing import ArrayLike

    from ..offline.pipeline import OfflineArrays
    from .yau_jia_fast import FastPieces

PRUNE_LOG_WEIGHT = -30.0  # relative to the largest component
SIGMA = math.sqrt(3.0)  # the ±√3σ points where the sensor's quadratic model is checked
MAX_COMPONENTS = {1: 64, 2: 128}  # by dimension; 16 above (measured: bench/results/yau-jia-speed.md)
SPLIT_SHARE = 8  # at most max_components / 8 splits per step (diffusion widens every component)
SPLIT_TOLERANCE = 0.05  # log-likelihood error per unit time at the ±√3σ points, per component
_UNCOMPILED: set[str] = set()  # the reasons already warned about (solver/exact/sensor_tape.py)


@dataclass(frozen=True)
class YauJiaState(StepState):
    """v = e^{−φ}σ = Σ_j exp(−xᵀA_jx − B_jᵀx − C_j), normalised so that ∫σ = 1."""

    A: np.ndarray = field(default_factory=lambda: np.full((1, 1, 1), 0.5))
    B: np.ndarray = field(default_factory=lambda: np.zeros((1, 1)))
    C: np.ndarray = field(default_factory=lambda: np.zeros(1))
    splits: int = 0  # components split so far (bookkeeping of the error control)
    clipped: int = 0  # second-order factors damped to keep a component integrable

    def to_dict(self) -> dict[str, Any]:
        return {"A": self.A.tolist(), "B": self.B.tolist(), "C": self.C.tolist(), "step": self.step,
                "t": self.t, "loglik": self.loglik, "loglik_increment": self.loglik_increment,
                "degenerate": self.degenerate, "reason": self.reason, "splits": self.splits,
                "clipped": self.clipped}


class _Sensor:
    """h, its Jacobian and its Hessians at points, from one generated function (common subexpressions
    shared): X (P, n) -> (P, m), (P, m, n), (P, m, n, n)."""

    def __init__(self, model: Model):
        xs, n, m = model.symbols, model.n, model.m
        h = list(model.observation)
        jac = [sp.diff(hi, s) for hi in h for s in xs]
        hess = [sp.diff(hi, s, t) for hi in h for s in xs for t in xs]
        table = {"DiracDelta": lambda *a: np.zeros_like(np.asarray(a[0], float))}
        self._fn = sp.lambdify(list(xs), h + jac + hess, modules=[table, "numpy"], cse=True)
        self.n, self.m = n, m
        self.h, self.symbols = h, xs

    def tapes(self) -> tuple[Tape, Tape] | None:
        """The compiled kernels' programs of h, ∂h, ∂²h and of h (solver/exact/sensor_tape.py), or None
        (with one warning per reason) where an expression has no instruction."""
        try:
            return sensor_tapes(self.h, self.symbols)
        except Uncompilable as reason:
            key = str(reason)
            if key not in _UNCOMPILED:
                _UNCOMPILED.add(key)
                warnings.warn(f"yauyau: the yau-jia filter takes its numpy path: the sensor has no compiled "
                              f"form ({reason})", RuntimeWarning, stacklevel=4)
            return None

    def flat(self, X: np.ndarray) -> np.ndarray:
        """(P, m + mn + mn²): h, then ∂h and ∂²h row-major, at the points X (P, n)."""
        X = np.asarray(X, float)
        with np.errstate(all="ignore"):
            values = self._fn(*X.T)
        flat = np.empty((len(X), len(values)))
        for column, value in enumerate(values):  # a constant entry broadcasts over the points
            flat[:, column] = value
        return flat

    def __call__(self, X: np.ndarray):
        flat = self.flat(X)
        P, n, m = len(flat), self.n, self.m
        return (flat[:, :m], flat[:, m:m + m * n].reshape(P, m, n),
                flat[:, m + m * n:].reshape(P, m, n, n))


def default_components(n: int) -> int:
    """The default cap on the mixture: 64 in 1-D, 128 in 2-D (a ring-shaped posterior: at 32 and 64
    the worst of 20 seeds × 1000 steps missed 0.01, at 128 it is 0.0066; tests/solver/exact/test_yau_jia.py),
    16 from 3-D on, where each component costs O(n³): on 4-D range-only tracking, rows 50-400 of 3 seeds,
    the mean gap to 10⁶ particles was 0.021 at 16, 0.019 at 32 and 64 (seed to seed ±0.005), 0.058 at 8
    (one seed lost), 10k particles 0.059; 16 costs 0.4× of 32 per row (bench/results/yau-jia-speed.md)."""
    return MAX_COMPONENTS.get(n, 16)


class YauJiaFilter(ChunkedFilter):
    """Filter protocol; see the module docstring."""

    method = "yau-jia"
    # a one-shot command's break-even (solver/jit.py choose_for_rows): numba's start-up, ~1.3 s
    # of CPU, against ~5 ms a row saved at the default cap (bench/results/yau-jia-speed.md)
    compiled_min_rows = 300

    def __init__(self, model: Model, max_components: int | None = None,
                 split_tolerance: float = SPLIT_TOLERANCE, gate: float | None = None,
                 split_budget: int | None = None):
        max_components = default_components(model.n) if max_components is None else max_components
        if not isinstance(max_components, int) or not 1 <= max_components <= 256:
            raise SpecError("max_components", "must be an integer in 1..256")
        split_budget = max(1, max_components // SPLIT_SHARE) if split_budget is None else split_budget
        if not isinstance(split_budget, int) or not 1 <= split_budget <= max_components:
            raise SpecError("split_budget", "must be an integer in 1..max_components")
        if not (math.isfinite(split_tolerance) and split_tolerance > 0):
            raise SpecError("split_tolerance", "must be a positive number")
        if model.spec.measurement.kind == "discrete":
            raise SpecError("measurement.kind", "yau-jia filters continuous increments dy = h dt + dw (its "
                                                "data term rides on the Kolmogorov flow); discrete "
                                                "measurements: use yau-yau (the general engine)")
        self.gate_override = check_gate(gate)
        self.model = model
        self.max_components, self.split_tolerance = max_components, float(split_tolerance)
        self.split_budget = split_budget
        self.structure: YauJiaStructure = yau_jia_structure(model)
        s, n = self.structure, model.n
        if s.phi == 0:
            self.exp_phi_slopes, self.exp_phi_logc = np.zeros((1, n)), np.zeros(1)
        else:
            found = exponential_sum(s.phi, model.symbols)
            if found is None:
                raise SpecError("drift", f"e^phi (phi = {s.phi}) is not a sum of exponentials of affine "
                                         "functions: the moments of sigma = e^phi v have no closed form")
            self.exp_phi_slopes, self.exp_phi_logc = found
        self.R_inv = model.R_inv
        self._whiten = np.linalg.inv(np.linalg.cholesky(model.R))
        observed = GaussianKolmogorov(s.L, s.ell, Q=0.5 * s.Q, q=0.5 * s.q, r=0.5 * s.q0, a=model.a)
        flows = [observed.flow(model.dt)]
        self._predict_exact = s.V_predict is not None
        if self._predict_exact:
            Qp, qp, q0p = s.V_predict
            flows.append(GaussianKolmogorov(s.L, s.ell, Q=0.5 * Qp, q=0.5 * qp, r=0.5 * q0p,
                                            a=model.a).flow(model.dt))
        self._family = FlowFamily(flows)
        self._equations = [f.eq for f in flows]
        self._gap_families = BoundedCache()  # piece length -> FlowFamily (irregular times)
        self._a_max = float(np.linalg.eigvalsh(np.asarray(model.a, float))[-1])
        self._q = [f.eq.q for f in flows]
        self._r = [f.eq.r for f in flows]
        self.sensor = _Sensor(model)
        self._fast: FastPieces | None = None

    # -- σ = e^{φ}v as a flat Gaussian mixture ---------------------------------------------
    def _components(self, A, B, C):
        """(log weights, means, covs) of σ's Gaussian terms (J·T of them)."""
        slopes, logc = self.exp_phi_slopes, self.exp_phi_logc
        mean, cov, log_mass = gaussian_terms_batch(A[:, None], B[:, None] - slopes, C[:, None] - logc)
        n = A.shape[-1]
        cov = np.broadcast_to(cov, (len(C), len(logc), n, n))
        return log_mass.reshape(-1), mean.reshape(-1, n), cov.reshape(-1, n, n)

    def _normalise(self, A, B, C, components=None):
        """C of ∫σ = 1, log ∫σ before, and σ's components (log weights, means, covs) after."""
        logw, means, covs = self._components(A, B, C) if components is None else components
        log_mass = float(log_sum_exp(logw))
        if not math.isfinite(log_mass):
            raise InputError("increments", "the mixture has no finite mass")
        return C + log_mass, log_mass, (logw - log_mass, means, covs)

    # -- prior ------------------------------------------------------------------------------
    def initial_state(self, prior: Any | None = None) -> YauJiaState:
        prior = self.model.spec.initial if prior is None else prior
        if isinstance(prior, DensityPrior):
            raise SpecError("initial", "yau-jia needs a gaussian or mixture prior (kind = \"gaussian\" or "
                                       "\"mixture\")")
        if not isinstance(prior, (GaussianPrior, MixturePrior)):
            raise SpecError("initial", "unsupported prior kind")
        if isinstance(prior, GaussianPrior):
            weights, means, covs = [1.0], [prior.mean], [prior.cov]
        else:
            weights, means, covs = prior.weights, prior.means, prior.covs
        top = max(weights)
        terms = [gaussian_to_terms(mu, P, w / top) for w, mu, P in zip(weights, means, covs, strict=True)
                 if w > 0]
        A = np.stack([t.A for t in terms])
        B = np.stack([t.B for t in terms])
        C = np.array([t.C for t in terms])
        if self.structure.phi != 0:
            A, B, C = self._times_exp_minus_phi(A, B, C)
        C = self._normalise(A, B, C)[0]
        A, B, C, splits, _ = self._control(A, B, C)
        C = self._normalise(A, B, C)[0]
        return YauJiaState(A=A, B=B, C=C, splits=splits)

    def _times_exp_minus_phi(self, A, B, C):
        """v0 = e^{−φ}σ0 by the second-order expansion of φ about each component (split first where
        φ is far from quadratic over a component)."""
        xs = self.model.symbols
        phi = self.structure.phi
        fn = sp.lambdify(list(xs), [phi] + [sp.diff(phi, s) for s in xs]
                         + [sp.diff(phi, s, t) for s in xs for t in xs], "numpy", cse=True)
        n = len(xs)
        for _ in range(4):  # split wide components, then expand
            means, covs, log_mass = gaussian_terms_batch(A, B, C)
            if len(C) * 3 > self.max_components:
                break
            A, B, C = exponent_terms(*split_all(means, covs, log_mass))
        means, covs, _ = gaussian_terms_batch(A, B, C)
        with np.errstate(all="ignore"):
            vals = fn(*means.T)
        flat = np.stack([np.broadcast_to(np.asarray(v, float), (len(C),)) for v in vals], axis=1)
        s0, g, S = -flat[:, 0], -flat[:, 1:1 + n], -flat[:, 1 + n:].reshape(-1, n, n)
        A, B, C, _ = times_exp_quadratic(A, B, C, means, covs, s0, g, S)
        return A, B, C

    # -- the step -----------------------------------------------------------------------------
    def _expected(self, means, covs):
        """E[h], E[∂h], E[∂²h] over each component N(m_j, P_j): the mean over the 2n points
        m ± √n·√λ_k u_k (third-degree cubature, exact for quadratic integrands)."""
        J_count, n = means.shape
        points = cubature_points(means, covs)
        h, Jh, H = self.sensor(points.reshape(-1, n))
        m = h.shape[1]
        return (h.reshape(J_count, 2 * n, m).mean(1), Jh.reshape(J_count, 2 * n, m, n).mean(1),
                H.reshape(J_count, 2 * n, m, n, n).mean(1))

    def _step(self, A, B, C, row, tau: float | None = None, family: FlowFamily | None = None):
        """One interval τ (default dt, over the flows ``family``): the exact flow with the
        statistically linearised data term, then the second-order (Hermite) expansion of the
        remainder factor.  Returns (A, B, C, clipped)."""
        model = self.model
        tau = model.dt if tau is None else tau
        family = self._family if family is None else family
        means, covs, _ = gaussian_terms_batch(A, B, C)
        J_count = len(C)
        if row is None:
            choice = 1 if self._predict_exact else 0
            q = np.broadcast_to(self._q[choice], (J_count, model.n))
            r = np.full(J_count, self._r[choice])
        else:
            choice = 0
            c = self.R_inv @ row
            c_dot = c / tau
            h0, J0, H0 = self._expected(means, covs)  # h ≈ h0 + J0 (x − m_j) over component j
            # Strang splitting: half of exp(Δyᵀ R⁻¹ ρ_j) before the flow, half after.  Before, ρ_j
            # has mean and mean gradient 0 over the component: only its curvature term is left.
            S = 0.5 * np.einsum("jmab,m->jab", H0, c)
            s0 = -0.5 * np.einsum("jab,jba->j", covs, S)
            A, B, C, damped0 = times_exp_quadratic(A, B, C, means, covs, s0, np.zeros_like(means), S)
            q = self._q[0] - np.einsum("jmn,m->jn", J0, c_dot)
            r = self._r[0] - (h0 - np.einsum("jmn,jn->jm", J0, means)) @ c_dot
        A1 = family.path([choice], A)[1]
        batch = family.batch([choice], A[None], q[None], r[None])
        B1, gain = batch.finish(B[None])
        B1, C1 = B1[0], C + gain[0]
        means1, covs1, _ = gaussian_terms_batch(A1, B1, C1)
        if row is not None:  # the other half of exp(Δyᵀ R⁻¹ ρ_j), ρ_j = h − h0 − J0(x − m_j), to degree 2
            h1, J1, H1 = self._expected(means1, covs1)
            S = 0.5 * np.einsum("jmab,m->jab", H1, c)
            s0 = 0.5 * (h1 - h0 - np.einsum("jmn,jn->jm", J0, means1 - means)) @ c \
                - 0.5 * np.einsum("jab,jba->j", covs1, S)
            g = 0.5 * np.einsum("jmn,m->jn", J1 - J0, c)
            A1, B1, C1, damped1 = times_exp_quadratic(A1, B1, C1, means1, covs1, s0, g, S)
            return A1, B1, C1, damped0 + damped1
        if not self._predict_exact:  # the flow took ½hᵀR⁻¹h dt off: put it back, to second order
            h1, J1, H1 = self.sensor(means1)
            Rh = h1 @ self.R_inv
            dt = tau
            s0 = 0.5 * (Rh * h1).sum(-1) * dt
            g = np.einsum("jmn,jm->jn", J1, Rh) * dt
            S = (np.einsum("jma,mk,jkb->jab", J1, self.R_inv, J1) + np.einsum("jmab,jm->jab", H1, Rh)) * dt
            return times_exp_quadratic(A1, B1, C1, means1, covs1, s0, g, S)
        return A1, B1, C1, 0

    # -- error control ---------------------------------------------------------------------------
    def _rates(self, means, covs):
        """Per component and principal axis: the sensor's departure from its quadratic model at
        ±√3σ (whitened), times (|h(m)|_R + 1) — the log-likelihood error per unit time."""
        J_count, n = means.shape
        lam, U = np.linalg.eigh(covs)
        steps = SIGMA * np.sqrt(np.clip(lam, 0.0, None))[:, None, :] * U  # (J, n, k): column k = axis k
        axes = np.swapaxes(steps, 1, 2)  # (J, k, n)
        h0, J0, H0 = self.sensor(means)
        points = means[:, None, None, :] + np.array([-1.0, 1.0])[None, None, :, None] * axes[:, :, None, :]
        h_at = self.model.h(points.reshape(-1, n)).reshape(J_count, n, 2, -1)
        lin = np.einsum("jmn,jkn->jkm", J0, axes)
        quad = 0.5 * np.einsum("jmab,jka,jkb->jkm", H0, axes, axes)
        model_at = h0[:, None, None, :] + np.array([-1.0, 1.0])[None, None, :, None] * lin[:, :, None, :] \
            + quad[:, :, None, :]
        eps = (h_at - model_at) @ self._whiten.T
        err = np.sqrt((eps**2).sum(-1)).max(-1)  # (J, k)
        size = np.sqrt(((h0 @ self._whiten.T) ** 2).sum(-1)) + 1.0
        rate = err * size[:, None]
        return np.where(np.isfinite(rate), rate, np.inf), U, lam

    def _control(self, A, B, C, components=None):
        """Prune the negligible components; split the ``split_budget`` worst of those whose rate
        exceeds the tolerance, first merging the cheapest pairs among the others to make room
        (merging before splitting keeps a fresh split from being merged back at once).  Returns
        (A, B, C, splits, σ's components where φ = 0 (they are v's), else None); ``components``:
        v's, if known."""
        if components is None or self.structure.phi != 0:
            means, covs, logw = gaussian_terms_batch(A, B, C)
        else:
            logw, means, covs = components
        keep = logw >= logw.max() + PRUNE_LOG_WEIGHT
        if not keep.all():
            means, covs, logw = means[keep], covs[keep], logw[keep]
        rates, U, lam = self._rates(means, covs)
        worst = rates.max(-1)
        order = np.argsort(-worst)[:self.split_budget]
        chosen = order[worst[order] > self.split_tolerance]
        # k splits need 3k places, plus one for the others merged into one (if there are others)
        k = min(len(chosen), self.max_components // 3)
        if k and len(logw) > k and 3 * k + 1 > self.max_components:
            k -= 1
        chosen = chosen[:k]
        if len(chosen):
            split = np.zeros(len(logw), bool)
            split[chosen] = True
            room = self.max_components - 2 * len(chosen)  # components left for the unsplit ones
            rest = merge_to(means[~split], covs[~split], logw[~split], room - len(chosen))
            axis = np.argmax(rates[chosen], axis=1)  # split along the axis of the largest rate
            u = U[chosen, :, axis] * np.sqrt(lam[chosen, axis])[:, None]
            child = covs[chosen] - (1.0 - SPLIT_WIDTH**2) * np.einsum("ja,jb->jab", u, u)
            means = np.concatenate([rest[0], (means[chosen][:, None, :] + SPLIT_OFFSETS[None, :, None]
                                              * u[:, None, :]).reshape(-1, means.shape[1])])
            covs = np.concatenate([rest[1], np.repeat(child, 3, axis=0)])
            logw = np.concatenate([rest[2], (logw[chosen][:, None] + np.log(SPLIT_WEIGHTS)).reshape(-1)])
        elif len(logw) > self.max_components:  # a prior with more components than the cap
            means, covs, logw = merge_to(means, covs, logw, self.max_components)
        if len(chosen) or len(logw) != len(C):
            covs = 0.5 * (covs + np.swapaxes(covs, -1, -2))
            A, B, C = exponent_terms(means, covs, logw)
        return A, B, C, int(len(chosen)), ((logw, means, covs) if self.structure.phi == 0 else None)

    # -- Filter protocol ---------------------------------------------------------------------
    def run_arrays(self, state: YauJiaState, increments: np.ndarray,
                   times: ArrayLike | None = None) -> tuple[YauJiaState, ChunkResult]:
        """Advance over a chunk (K, m) of increments (a NaN row: prediction only) at ``times``
        (absolute, strictly increasing) or one dt apart.  A gap longer than the flow's accuracy
        allows is taken in pieces (riccati.gap_pieces), each with its share of the linear path and
        the mixture's error control after it.  Partly missing rows are refused (the class condition
        (4.2) is on hᵀR⁻¹h of the whole sensor).

        The gate: g = −2 log p(row | past) − log det 2πR τ, over the threshold, is corrected by
        log det(I + τ S₀⁻¹ C) with C = Cov(h) under the predicted mixture (each component by the
        third-degree cubature of ``_expected``: exact for affine h, else an approximation of the
        exact score d² ≤ g); a gated row keeps the prediction-only step."""
        model = self.model
        rows = check_rows(increments, model.m)
        refuse_form(self.method, rows, times, model, times_ok=True)
        K, n = len(rows), model.n
        taus = resolve_times(state.t, state.step > 0, K, model.dt, times)
        steps, times = chunk_clock(state, K, model.dt, times, taus)
        check_first_gap(taus, False, self.method)
        taus = regular_gaps(taus, model.dt, times, state.t)
        obs = self.observation
        keys = obs.pattern_keys(~np.isnan(rows))
        gaps = np.full(K, model.dt) if taus is None else taus
        terms = obs.row_terms(rows, gaps, keys)
        mean_out, cov_out = np.empty((K, n)), np.empty((K, n, n))
        ll_inc, bad = np.zeros(K), np.zeros(K, bool)
        pll, gated, scores = np.full(K, np.nan), np.zeros(K, bool), np.full(K, np.nan)
        A, B, C = state.A, state.B, state.C
        splits, clipped, reason = state.splits, state.clipped, state.reason
        mean, cov = self._moments(A, B, C)
        done = K
        if state.degenerate:
            done = 0
        for k in range(done):
            row = rows[k] if keys[k] else None
            tau = None if taus is None else float(taus[k])
            try:
                A1, B1, C1, log_mass, damped, split, components = self._row(A, B, C, row, tau)
                if row is not None:
                    pll[k] = log_mass + terms.offset[k]
                    bound = -2.0 * pll[k] - terms.log_det_S0[k]
                    if obs.gating and bound > terms.threshold[k]:
                        predicted = self._row(A, B, C, None, tau)
                        score = bound - obs.covariance_correction(int(keys[k]), float(terms.kappa2[k]),
                                                                  self._h_cov(*predicted[:3]),
                                                                  obs.S0_scale(float(gaps[k])))
                        if score > terms.threshold[k]:
                            (A1, B1, C1, _, damped, split, components), row = predicted, None
                            gated[k], scores[k] = True, standard_score(score, model.m)
                mean1, cov1 = self._moments(A1, B1, C1, components)
            except (InputError, np.linalg.LinAlgError) as exc:
                done = k
                pll[k] = np.nan
                reason = (f"step {int(steps[k])}: the Gaussian mixture lost integrability "
                          f"({getattr(exc, 'message', str(exc))}); reset the session or use the general "
                          "engine (method = \"yau-yau\")")
                break
            A, B, C, mean, cov = A1, B1, C1, mean1, cov1
            splits, clipped = splits + split, clipped + damped
            mean_out[k], cov_out[k] = mean, cov
            ll_inc[k] = 0.0 if row is None else log_mass
        if done < K:  # degenerate from here: repeat the last good estimate, flagged
            mean_out[done:], cov_out[done:] = mean, cov
            bad[done:] = True
        loglik = np.cumsum(np.concatenate([[state.loglik], ll_inc]))[1:]  # sequential: chunk-independent
        last = K - 1
        new_state = replace(state, step=int(steps[last]) if K else state.step,
                            t=float(times[last]) if K else state.t,
                            loglik=float(loglik[last]) if K else state.loglik,
                            loglik_increment=float(ll_inc[last]) if K else state.loglik_increment,
                            A=A, B=B, C=C, splits=splits, clipped=clipped,
                            degenerate=bool(state.degenerate or done < K),
                            reason=reason if (state.degenerate or done < K) else None)
        return new_state, ChunkResult(steps, times, mean_out, cov_out, None, loglik, ll_inc, bad,
                                      reason=new_state.reason if bad.any() else None, predictive_loglik=pll,
                                      gated=gated, gate_score=scores, gate=obs.gate)

    def _row(self, A, B, C, row, tau: float | None):
        """One row: the step over dt (``tau`` None) or over the pieces of a gap τ, each followed by
        the error control.  Returns (A, B, C, log ∫σ_k/∫σ_(k−1), clipped, splits)."""
        if tau is None:
            pieces, families = (None,), (self._family,)
        else:
            means, covs, _ = gaussian_terms_batch(A, B, C)
            narrowest = float(np.linalg.eigvalsh(covs)[..., 0].min())
            delta = narrowest / self._a_max if self._a_max > 0 else math.inf
            pieces = gap_pieces(tau, self._equations[0].spectrum()[1], delta)
            families = [self._gap_family(piece) for piece in pieces]
        log_mass, damped, splits = 0.0, 0, 0
        fast = self._fast_pieces()
        for piece, family in zip(pieces, families, strict=True):
            share = row if row is None or piece is None else row * (piece / tau)
            length = self.model.dt if piece is None else piece
            done = None if fast is None else fast.piece(A, B, C, share, length, family)
            if done is not None:  # the compiled route (solver/exact/yau_jia_fast.py)
                A, B, C, gain, clip, split, components = done
            else:
                A, B, C, clip = self._step(A, B, C, share, piece, family)
                C, gain, components = self._normalise(A, B, C)
                A, B, C, split, components = self._control(A, B, C, components)
                C, _, components = self._normalise(A, B, C, components)
            log_mass, damped, splits = log_mass + gain, damped + clip, splits + split
        return A, B, C, log_mass, damped, splits, components

    def _fast_pieces(self) -> FastPieces | None:
        """The compiled pieces where ``YAUYAU_KERNEL`` (solver/jit.py) asks for them, φ = 0 and the
        sensor compiles to a tape (else the numpy path, with one warning: _Sensor.tapes)."""
        if not jit.enabled() or self.structure.phi != 0:
            return None
        if self._fast is None:
            tapes = self.sensor.tapes()
            if tapes is None:
                return None
            from .yau_jia_fast import FastPieces

            self._fast = FastPieces(tapes=tapes, R_inv=self.R_inv, whiten=self._whiten, q=self._q, r=self._r,
                                    predict_exact=self._predict_exact,
                                    max_components=self.max_components, split_tolerance=self.split_tolerance,
                                    split_budget=self.split_budget, prune=PRUNE_LOG_WEIGHT, sigma=SIGMA)
        return self._fast

    def _gap_family(self, length: float) -> FlowFamily:
        """The flows (observed, and exact prediction where the class has one) over ``length``."""
        return self._gap_families.get(float(length), lambda: FlowFamily([eq.gap_flow(length)
                                                                         for eq in self._equations]))

    def _h_cov(self, A, B, C) -> np.ndarray:
        """Cov(h) under the mixture σ = e^{φ}Σ_j exp(−xᵀA_jx − B_jᵀx − C_j): per component E[h] and
        E[hhᵀ] by the 2n-point cubature of :meth:`_expected` (exact for affine h)."""
        logw, means, covs = self._components(A, B, C)
        w = np.exp(logw - log_sum_exp(logw))
        J_count, n = means.shape
        points = cubature_points(means, covs)
        h = self.sensor(points.reshape(-1, n))[0].reshape(J_count, 2 * n, -1)
        first = np.einsum("j,jpm->m", w, h) / (2 * n)
        second = np.einsum("j,jpa,jpb->ab", w, h, h) / (2 * n)
        return second - np.outer(first, first)

    def _moments(self, A, B, C, components=None):
        """Mean and covariance of σ (its components if known; with them, by the compiled path)."""
        if components is not None and len(components) == 4:
            return components[3]
        logw, means, covs = self._components(A, B, C) if components is None else components
        w = np.exp(logw - log_sum_exp(logw))
        mean = w @ means
        dev = means - mean
        cov = np.einsum("j,jab->ab", w, covs) + np.einsum("j,ja,jb->ab", w, dev, dev)
        return mean, 0.5 * (cov + cov.T)

    def estimate(self, state: YauJiaState) -> Estimate:
        mean, cov = self._moments(state.A, state.B, state.C)
        return Estimate(step=state.step, t=state.t, mean=mean, cov=cov, loglik=state.loglik,
                        loglik_increment=state.loglik_increment, degenerate=state.degenerate,
                        reason=state.reason)

    def density(self, state: YauJiaState, points: np.ndarray) -> np.ndarray:
        X = np.atleast_2d(np.asarray(points, float))
        if X.ndim != 2 or X.shape[1] != self.model.n or not np.all(np.isfinite(X)):
            raise InputError("points", f"must be finite points of shape (P, {self.model.n})")
        logw, means, covs = self._components(state.A, state.B, state.C)
        logs = np.stack([lw + log_normal(X, mu, P) for lw, mu, P in zip(logw, means, covs, strict=True)])
        return np.exp(log_sum_exp(logs, axis=0) - log_sum_exp(logw))

    def state_from_dict(self, data: dict[str, Any]) -> YauJiaState:
        return mixture_state_from_dict(YauJiaState, data, self.model.n, "yau-jia")


def build(model: Model, offline: OfflineArrays | None = None, gate: float | None = None,
          **_: Any) -> YauJiaFilter:
    """The registry's constructor (solver/registry.py)."""
    return YauJiaFilter(model, gate=gate)
