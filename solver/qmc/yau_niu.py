"""The Yau–Niu filter: the quasi-Monte Carlo Yau–Yau method past three states (method "yau-niu").

S.-T. Yau and Y.-S. Niu, "An Improved Yau–Yau Algorithm for High Dimensional Nonlinear Filtering
Problems" (arXiv:2509.16896, 2025; only its abstract and summary could be read here, so the
citations below name the paper's parts, not equation numbers).  The DMZ equation
dσ = L*σ dt + σ hᵀR⁻¹dy is split into the Kolmogorov step Aσ = L*σ and the observation step
Bσ = σ hᵀR⁻¹dy (Yau–Niu, offline–online update), on quasi-Monte Carlo low-discrepancy points
(Yau–Niu, QMC sampling: scrambled Sobol points mapped to normal deviates, scipy.stats.qmc) that
cover where the density lives.  σ is carried as N points x_i with log weights ℓ_i
(σ ≈ Σ_i e^{ℓ_i} δ_{x_i}; Yau–Niu, log-domain likelihood).  One row over a gap τ:

1. Kolmogorov step (Yau–Niu, the transition kernel between point sets): every point moves by the
   Euler kernel of dx = f dt + G dv, x ↦ x + f(x)τ + (aτ)^{1/2} z with z a QMC normal set in a new
   random order each row (reusing a Sobol index across rows correlates the points' noises, measured),
   drawn from the filter's bank of scrambled sets built once (solver/qmc/bank.py: the data-free part
   of the step, offline); blocks of one coordinate: each its own shifted 1-D lattice a row, which costs
   next to nothing (solver/qmc/blocks.py);
   then the cloud is mapped affinely so that its weighted mean and covariance are exactly those of
   the kernel, m = Σ w_i(x_i + f_iτ), P = Cov_w(x + fτ) + aτ (second-order moment matching: exact
   for linear drift; chosen by measurement, see below).
2. Observation step (Yau–Niu, log-domain update): ℓ_i += log e(x_i), the measurement's factor
   (solver/measurement.py: exp(hᵀR⁻¹Δy − ½hᵀR⁻¹hτ) for increments, N(z; h, R) or Student-t for
   discrete readings; NaN components marginalised); normalised by log-sum-exp, whose log is the
   row's log-likelihood increment.
3. Local resampling-restart (Yau–Niu): when the effective coverage 1/Σw_i² falls below
   ``restart`` × N, the points are resampled (systematic, by the weights) and spread by the
   multi-scale kernel: x ↦ √(1−h²)x + (1−√(1−h²))m + h P^{1/2} z (Liu–West shrinkage, which keeps
   the mean and covariance; h = ``bandwidth``: h = 1 is a Gaussian restart on a QMC set (the bank's),
   h → 0 plain resampling), then matched to the posterior's mean and covariance.  A posterior that
   collapsed onto fewer than two points cannot be restarted: the row is flagged degenerate.

Where the coordinates split into blocks that nothing couples (drift, diffusion, sensor, noise, prior:
:func:`independent_blocks`), the exact filter is the product of the blocks' filters, and each block
keeps its own log weights and restarts on its own (our reading of the paper's *local* resampling):
ten independent cubic sensors are then ten 1-D filters on one point set, and the cost grows
linearly with the dimension instead of the weights degenerating.

Choices by measurement (load 4–6 on 2 shared cores; /tmp scripts summarised in the report), against
the Kalman filter (linear 4-D, 300 rows of dt = 0.01) and ten 1-D point-mass filters (ten cubic sensors):

* the kernel-matrix form of the Kolmogorov step (the predicted density Σ_i w_i K(y|x_i), Liu–West
  kernel at Silverman's bandwidth, evaluated on a new QMC set, N² a row) was tried first and
  dropped: the per-row density noise accumulated to a mean gap 0.10 at N = 1024 and 50 ms a row;
* the Lagrangian form with Sobol indices reused row after row: rms gap 0.21 at N = 16384; with a
  fresh permuted QMC set per row and moment matching: 0.009 at N = 8192;
* one block for the ten cubic sensors: rms gap 0.12 (N = 8192); per-block weights: 0.009 (N = 4096);
* the restart's bandwidth: a Gaussian restart (h = 1) is best for the linear model (max variance
  gap 4.7% against 7.6% at h = 0.5) and worst for the cubic sensors (rms 0.080 against 0.010 at
  Silverman's h = 0.2): ``multiscale_bandwidth`` (solver/qmc/cloud.py) picks one per restart
  (0.0296 / 4.7% linear, 0.0087 cubic);
* the restart threshold 0.5 (0.7: cubic 0.012, linear max gap 0.048; 0.9: cubic 0.024);
* a gap longer than dt (irregular times, discrete readings) is moved in Euler steps of at most dt:
  in one step of up to 0.3, 60 readings of the linear 4-D model were 0.045 rms from Kalman (0.030 split);
* an update that leaves fewer than TEMPER × N effective points (a reading far in the prediction's
  tail) is redone in powers of its factor with a restart after each (progressive correction): the
  same 60 readings' worst variance 31% → 10.6% off at N = 8192 (TEMPER = 0.5, tempering at every
  restart: 6.8%, but the 4-D mode test drifted to 0.15 from 0.05; 0.05 leaves the regular rows as
  they were), and a 3-sd reading of noise sd 1e-4 on 256 points is followed instead of degenerating.

The state is the points and log weights: N(n + B) numbers (B blocks).  ``to_dict`` writes each array
as {"dtype": "<f8", "shape": [...], "base64": ...}, the base64 of its float64 bytes (solver/qmc/packed.py,
chosen by measurement there; an array of NaN or infinity stays a list, which the session store refuses;
``state_from_dict`` still reads the lists states were stored in before): 10.7 bytes a number,
437 257 bytes at the default N = 8192 for the 4-D linear model (one block; 813 049 as lists;
tests/service/sessions/test_yau_niu_sessions.py), 8.7 MB for 100 states at 4096 points (15.7 MB),
rewritten with every chunk.  The per-row noise comes from a generator seeded by
(seed, step), so a chunked run is bit-identical to one run.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from types import SimpleNamespace
from typing import TYPE_CHECKING, Any

import numpy as np
from scipy.special import logsumexp

from .. import jit
from ..errors import InputError, SpecError
from ..filtering import ChunkedFilter, ChunkResult, Estimate, StepState, chunk_clock
from ..gaussian import log_normal
from ..measurement import (
    Observation,
    check_first_gap,
    check_gate,
    check_rows,
    gate_threshold,
    resolve_times,
    standard_score,
)
from ..model import Model
from ..spec import DensityPrior, GaussianPrior, MixturePrior
from .bank import Banks, NormalBank
from .blocks import SingleBlocks, independent_blocks
from .budget import check_points, default_points
from .cloud import (
    gradient_bandwidth,
    log_sum_exp,
    match_moments,
    multiscale_bandwidth,
    qmc_normals,
    silverman,
    symmetric_root,
    weighted_moments,
)
from .coupled import CoupledBlocks, block_log_factor, sensor_rows
from .coupled import restart as coupled_restart
from .packed import pack_finite, unpack

if TYPE_CHECKING:
    from numpy.typing import ArrayLike

RESTART = 0.5  # restart when 1/Σw² < RESTART·N
TEMPER = 0.05  # an update leaving 1/Σw² < TEMPER·N is redone in powers (progressive correction)
MAX_TEMPER_STAGES = 20
MAX_BLOCK_COMPONENTS = 62  # observation components per block (Observation's pattern keys are int64 bits)
NUMBA_START_SECONDS = 1.3  # numba's import and the load of its cached kernels, CPU (solver/jit.py)
COMPILED_SAVING_SECONDS = 30e-9  # what the compiled row saves a point-coordinate


@dataclass(frozen=True)
class YauNiuState(StepState):
    """σ ≈ Π_b Σ_i exp(log_weights[b, i]) δ(x_b − points[i, b]) over the independent blocks b of
    coordinates (one block for a coupled model); each row of log weights has log-sum-exp 0."""

    points: np.ndarray = field(default_factory=lambda: np.zeros((1, 1)))
    log_weights: np.ndarray = field(default_factory=lambda: np.zeros((1, 1)))
    restarts: int = 0
    seed: int = 0

    def to_dict(self) -> dict[str, Any]:
        return {"points": pack_finite(self.points), "log_weights": pack_finite(self.log_weights, True),
                "step": self.step, "t": self.t, "loglik": self.loglik,
                "loglik_increment": self.loglik_increment, "degenerate": self.degenerate,
                "reason": self.reason, "restarts": self.restarts, "seed": self.seed}


class YauNiuFilter(ChunkedFilter):
    """Filter protocol; see the module docstring."""

    method = "yau-niu"

    def __init__(self, model: Model, points: int | None = None, restart: float = RESTART,
                 bandwidth: float | None = None, seed: int = 0, gate: float | None = None,
                 blocks: bool = True):
        if points is None:
            points = model.spec.discretization.points
        self.blocks = independent_blocks(model) if blocks else [np.arange(model.n)]
        if not (0.0 < restart <= 1.0):
            raise SpecError("restart", "must be in (0, 1]: the share of the points the effective coverage "
                                       "may fall to before a restart")
        if bandwidth is not None and not (0.0 <= bandwidth <= 1.0):
            raise SpecError("bandwidth", "must be in [0, 1] (1: a Gaussian restart; None: multi-scale)")
        self.gate_override = check_gate(gate)
        self.model = model
        self.restart, self.seed = float(restart), int(seed)
        self.bandwidth = None if bandwidth is None else float(bandwidth)
        self._noise_root = symmetric_root(np.asarray(model.a, float))  # (aτ)^{1/2} = √τ a^{1/2}
        owner = np.zeros(model.n, int)
        for b, coords in enumerate(self.blocks):
            owner[coords] = b
        index = {s: i for i, s in enumerate(model.symbols)}
        used = [sorted(index[s] for s in expr.free_symbols if s in index) for expr in model.observation]
        block_of = [int(owner[u[0]]) if u else 0 for u in used]  # a constant component: block 0
        self._components = [np.flatnonzero(np.array(block_of) == b) for b in range(len(self.blocks))]
        widest = max(len(c) for c in self._components)
        if widest > MAX_BLOCK_COMPONENTS:
            raise SpecError("observation", f"{widest} observation components act on one coupled block of "
                                           f"states; yau-niu takes at most {MAX_BLOCK_COMPONENTS} per block")
        # each block's measurement sees its own components (their pattern keys are bits of an int64)
        self._block_observations = [Observation(SimpleNamespace(spec=model.spec, m=len(c),
                                                          R=np.asarray(model.R, float)[np.ix_(c, c)]))
                              for c in self._components]
        # every block one coordinate with at most one sensor (independent sensors): one vectorised row
        singles = SingleBlocks.applies(self.blocks, self._components)
        points = default_points(model.n, singles) if points is None else points
        self.points = check_points(points, model.n, model.m, len(self.blocks))
        self._singles = SingleBlocks(model, self.blocks, self._components) if singles else None
        self._coupled = CoupledBlocks(model, self.blocks, self._noise_root)
        self._banks = Banks(model.n)  # the coupled rows' QMC normal sets (solver/qmc/bank.py)

    @property
    def compiled_min_rows(self) -> int:
        """A one-shot command's break-even (solver/jit.py ``choose_for_rows``): numba's start-up against
        what the compiled row saves, ~30 ns a point-coordinate (one-coordinate blocks: 28 at 10 states,
        49 at 100, bench/results/yau-niu-speed.md; the coupled ring: 27), so 106 rows for 100 sensors
        at 4096 points and 1 600 for the ring at 8192."""
        saving = COMPILED_SAVING_SECONDS * self.points * self.model.n
        return max(1, math.ceil(NUMBA_START_SECONDS / saving))

    def marginal(self, state: YauNiuState, variable: int, grid: np.ndarray,
                 resolution: int = 0) -> np.ndarray:
        """p_i(x_i) at ``grid``: a weighted Gaussian KDE (Scott's bandwidth) of coordinate ``variable``
        of the points under its block's weights; ``resolution`` is unused (no quadrature is needed)."""
        from scipy.stats import gaussian_kde

        block = next(b for b, coords in enumerate(self.blocks) if variable in coords)
        w = np.exp(state.log_weights[block] - logsumexp(state.log_weights[block]))
        return gaussian_kde(state.points[:, variable], weights=w)(np.asarray(grid, float))

    def point_mode(self, state: YauNiuState, candidates: int = 256) -> np.ndarray:
        """The MAP point, read as the candidate of highest kernel density among the ``candidates``
        heaviest points (a grid search over n ≥ 4 dimensions cannot be held in memory)."""
        heaviest = np.argsort(state.log_weights.sum(axis=0))[-candidates:]
        X = state.points[heaviest]
        return X[int(np.argmax(self.mode_density(state, X)))].copy()

    def mode_density(self, state: YauNiuState, points: np.ndarray) -> np.ndarray:
        """:meth:`density` at the bandwidth for its gradient (:func:`gradient_bandwidth`): what the mode
        search climbs (solver/summaries.py)."""
        return self.density(state, points, gradient=True)

    # -- prior ------------------------------------------------------------------------------
    def initial_state(self, prior: Any | None = None) -> YauNiuState:
        """QMC points of the prior (gaussian or mixture: points of each component in proportion, equal
        weights; a density prior: points of a Gaussian covering the domain ball, weighted by the
        density)."""
        prior = self.model.spec.initial if prior is None else prior
        rng = np.random.default_rng([self.seed, 0])
        N, n = self.points, self.model.n
        Z = qmc_normals(N, n, rng)
        logw = np.full(N, -math.log(N))
        if isinstance(prior, GaussianPrior):
            X = np.asarray(prior.mean, float) + Z @ symmetric_root(np.asarray(prior.cov, float))
        elif isinstance(prior, MixturePrior):
            w = np.asarray(prior.weights, float)
            counts = np.floor(w / w.sum() * N).astype(int)
            counts[np.argmax(w)] += N - counts.sum()
            parts, start = [], 0
            for c, mu, P in zip(counts, prior.means, prior.covs, strict=True):
                root = symmetric_root(np.asarray(P, float))
                parts.append(np.asarray(mu, float) + Z[start:start + c] @ root)
                start += c
            X = np.concatenate(parts)
        elif isinstance(prior, DensityPrior):
            scale = self.model.radius / 3.0
            X = self.model.center + scale * Z
            logw = self.model.log_prior(X) - log_normal(X, self.model.center, scale**2 * np.eye(n))
            total = logsumexp(logw)
            if not np.isfinite(total):
                raise SpecError("initial", "the prior density is zero at every QMC point of the domain ball")
            logw = logw - total
        else:
            raise SpecError("initial", "unsupported prior kind")
        if self._singles is None:
            self._banks.get(self.seed, N)  # the rows' normal sets now, not in the first chunk
        return YauNiuState(points=X, log_weights=np.tile(logw, (len(self.blocks), 1)), seed=self.seed)

    # -- one row ----------------------------------------------------------------------------
    def _kolmogorov(self, X: np.ndarray, W: np.ndarray, tau: float, rng: np.random.Generator,
                    bank: NormalBank | None) -> np.ndarray:
        """The Kolmogorov step over τ (Yau–Niu, offline–online split: the A part): the Euler transition
        kernel N(x + f(x)τ, aτ) on a QMC normal set (``bank``'s), each block matched to the kernel's exact
        mean and covariance under its weights."""
        if self._singles is not None:  # blocks of one coordinate: lattice noise, compiled where on
            return self._singles.kolmogorov_step(X, self.model.f, W, tau, rng)
        return self._coupled.kolmogorov_step(X, W, tau, rng, bank)

    def _restart(self, X: np.ndarray, w: np.ndarray, rng: np.random.Generator,
                 bank: NormalBank | None) -> np.ndarray:
        """Local resampling-restart (Yau–Niu) of one block's points X (N, d): systematic resampling by
        the weights, the multi-scale (Liu–West) kernel of bandwidth h about the posterior, matched to
        its mean and covariance."""
        if bank is not None and jit.enabled():  # a coupled block: the same steps by the kernels
            return coupled_restart(X, w, rng, bank, self.bandwidth)
        N, d = X.shape
        mean, cov = weighted_moments(X, w)
        cdf = np.cumsum(w)
        picks = np.minimum(np.searchsorted(cdf, (rng.random() + np.arange(N)) / N * cdf[-1]), N - 1)
        h = self.bandwidth if self.bandwidth is not None else multiscale_bandwidth(X, w, mean, cov)
        shrink = math.sqrt(1.0 - h * h)
        Y = shrink * X[picks] + (1.0 - shrink) * mean
        if h > 0:
            Z = qmc_normals(N, d, rng, lattice=True) if bank is None else bank.normals(rng, d)
            Y = Y + h * (Z @ symmetric_root(cov))
        return match_moments(Y, np.full(N, 1.0 / N), mean, cov)

    def _gate_score(self, k: int, gain: float, h: np.ndarray, predicted: np.ndarray, blocks,
                    gaps: np.ndarray) -> float | None:
        """The gate (solver/measurement.py): row k's predictive standard score when it is over the gate,
        else None.  The measurement's score d² = g − log det(I + κ²S₀⁻¹C), g = −2 log p(row | past) −
        log det 2πS₀, C = Cov(h_o) under the predicted weights, reads p(row | past) off the points; where
        the noise is narrower than the points' spacing that estimate falls far below the true density
        (a 3-sd reading of noise sd 1e-4 on 256 points: d = 2912), so a row is gated only when the
        moment score vᵀS⁻¹v (v = y_o − κE[h_o], S = κ²C + S₀: the Gaussian prediction's, exact for a
        linear model) is over the threshold too; the smaller of the two is reported.  The blocks'
        components are independent under the product density and R is block-diagonal across them, so
        both scores are sums over the blocks."""
        obs = self.observation
        seen = [(b, *parts) for b, parts in enumerate(blocks) if parts[3][k]]
        patterns = [block_obs.pattern(int(keys[k])) for _, _, block_obs, _, keys, _ in seen]
        components = sum(len(pat.index) for pat in patterns)
        threshold = gate_threshold(obs.gate, components)
        bound = -2.0 * gain - sum(float(terms.log_det_S0[k]) for *_, terms in seen)
        if not bound > threshold:
            return None
        correction = moment = 0.0
        for (b, comps, block_obs, part, keys, terms), pat in zip(seen, patterns, strict=True):
            kappa2, scale = float(terms.kappa2[k]), block_obs.S0_scale(float(gaps[k]))
            mean_h, cov_h = weighted_moments(h[:, comps[pat.index]], np.exp(predicted[b]))
            correction += max(0.0, block_obs.covariance_correction(int(keys[k]), kappa2, cov_h, scale))
            innovation = part[k, pat.index] - math.sqrt(kappa2) * mean_h
            moment += float(innovation @ np.linalg.solve(kappa2 * cov_h + pat.R * scale, innovation))
        score = min(bound - correction, moment)
        return standard_score(score, components) if score > threshold else None

    def _temper(self, X: np.ndarray, predicted: np.ndarray, logW: np.ndarray, factors: dict[int, np.ndarray],
                blocks, k: int, gaps: np.ndarray, rng: np.random.Generator,
                bank: NormalBank | None, known: np.ndarray | None = None) -> tuple[np.ndarray, int]:
        """Progressive correction (tempering) of every block whose update left an effective coverage
        under TEMPER × N (an observation far in the prediction's tail): from the predicted weights, the
        factor is applied in powers β₁ + β₂ + … = 1, each the largest that keeps the coverage at
        ``restart`` × N, the points restarted after each and the factor re-read at the new points; its
        rows of ``logW`` are replaced in place.  (The points, how many restarts.)  Without it the
        posterior's covariance is read off a handful of points (a 4-sd reading of the 4-D linear model:
        variance 31% off at 8192 points).  ``known``: each block's coverage after the update where the
        observation step made it (NaN where not)."""
        count = 0
        for b, factor in factors.items():
            N = logW.shape[1]
            if known is not None and known[b] >= TEMPER * N:  # (NaN: not known, read below)
                continue
            w = np.exp(logW[b])
            if 1.0 / float(np.sum(w * w)) >= TEMPER * N:
                continue
            comps, block_obs, part, keys, terms = blocks[b]
            coords = self.blocks[b]
            logw, remaining = predicted[b].copy(), 1.0
            for _ in range(MAX_TEMPER_STAGES):
                total = logw + remaining * factor
                total -= log_sum_exp(total)
                w = np.exp(total)
                if 1.0 / float(np.sum(w * w)) >= self.restart * N:
                    break
                low, high = 0.0, remaining  # the largest power keeping the coverage at restart × N
                for _ in range(40):
                    beta = 0.5 * (low + high)
                    trial = logw + beta * factor
                    w = np.exp(trial - log_sum_exp(trial))
                    kept = 1.0 / float(np.sum(w * w)) >= self.restart * N
                    low, high = (beta, high) if kept else (low, beta)
                if low <= 0.0:
                    break
                trial = logw + low * factor
                w = np.exp(trial - log_sum_exp(trial))
                X = X.copy(order="K")
                X[:, coords] = self._restart(X[:, coords], w, rng, bank)
                logw, remaining, count = np.full(N, -math.log(N)), remaining - low, count + 1
                h = self.model.h(X)[None]
                factor = block_obs.log_factors(h[:, :, comps], part[k:k + 1], gaps[k:k + 1], keys[k:k + 1],
                                               terms.rows(k, k + 1, keys))[0]
            logW[b] = total
            if known is not None:
                known[b] = np.nan  # its rows replaced: read again where needed
        return X, count

    def _restarts(self, X: np.ndarray, logW: np.ndarray, rng: np.random.Generator, bank: NormalBank | None,
                  step: int, known: np.ndarray | None = None) -> tuple[np.ndarray, int, str | None]:
        """Local resampling-restart of every block whose effective coverage fell below ``restart`` × N
        (its ``logW`` row reset in place; X is not written): (the points, how many blocks restarted,
        None), or (X, 0, the reason) when a posterior collapsed onto fewer than two points.  ``known``:
        each block's coverage where the row's observation step made it (NaN, or None for all, where
        not: read here from logW); a block known to be above the threshold is not exponentiated."""
        moved, count = X, 0
        if self._singles is None:
            candidates = range(len(self.blocks))
        else:  # blocks of one coordinate: the coverage of all at once, the fallen ones only
            known = np.full(len(self.blocks), np.nan) if known is None else known
            known = self._singles.coverage(logW, known)
            candidates = np.flatnonzero(known < self.restart * logW.shape[1]).tolist()
        for b in candidates:
            coords = self.blocks[b]
            if known is not None and known[b] >= self.restart * logW.shape[1]:  # (NaN: read below)
                continue
            w = np.exp(logW[b])
            coverage = 1.0 / float(np.sum(w * w))
            if coverage < self.restart * len(w):
                if coverage < 2.0:
                    return X, 0, (f"step {int(step)}: the posterior collapsed onto {coverage:.2g} of "
                                  f"{len(w)} points and the restart cannot recover it; use more points "
                                  "(discretization.points) or a smaller dt")
                moved = X.copy(order="K") if moved is X else moved
                moved[:, coords] = self._restart(moved[:, coords], w, rng, bank)
                logW[b] = -math.log(len(w))
                count += 1
        return moved, count, None

    def _block_terms(self, rows: np.ndarray, gaps: np.ndarray):
        """Per block: its observation (the block's components only), rows, pattern keys and row terms."""
        out = []
        for comps, obs in zip(self._components, self._block_observations, strict=True):
            part = rows[:, comps]
            keys = obs.pattern_keys(~np.isnan(part))
            out.append((comps, obs, part, keys, obs.row_terms(part, gaps, keys)))
        return out

    def _moments(self, X: np.ndarray, W: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Mean and (block-diagonal) covariance of the product over the blocks."""
        if self._singles is not None:
            return self._singles.moments(X, W)
        return self._coupled.moments(X, W)

    # -- the observation step of one row --------------------------------------------------------
    def _update_blocks(self, k: int, logW: np.ndarray, hX: np.ndarray, blocks: list, gaps: np.ndarray,
                       known: np.ndarray) -> tuple[float | None, float, dict[int, np.ndarray]]:
        """Row k's observation step at the sensor values hX (P, m), block by block (logW edited in
        place, and each observed block's coverage 1/Σw² in ``known``, from the log-sum-exp's own
        exponentials): (the row's predictive log-likelihood, its sum of offsets, each observed block's
        log factor), or None for the first where an observed block's likelihood is zero at every
        point."""
        gain = offsets = 0.0
        factors: dict[int, np.ndarray] = {}
        for b, (comps, block_obs, part, keys, terms) in enumerate(blocks):
            if keys[k]:
                factor = block_log_factor(block_obs, hX, comps, part, gaps, keys, terms, k)
                total = logW[b] + factor  # Yau–Niu, log-domain update
                top = float(total.max())
                if not math.isfinite(top):
                    return None, 0.0, {}
                e = np.exp(total - top)  # cloud.log_sum_exp's, kept for the coverage
                total_e = float(e.sum())
                block_gain = top + math.log(total_e)
                if not math.isfinite(block_gain):
                    return None, 0.0, {}
                known[b] = total_e * total_e / float(e @ e)
                logW[b] = total - block_gain
                gain += block_gain + float(terms.offset[k])
                offsets += float(terms.offset[k])
                factors[b] = factor
        return gain, offsets, factors

    # -- Filter protocol ---------------------------------------------------------------------
    def run_arrays(self, state: YauNiuState, increments: np.ndarray,
                   times: ArrayLike | None = None) -> tuple[YauNiuState, ChunkResult]:
        """Advance over a chunk (K, m) of rows (NaN: a missing component; a NaN row: prediction only)
        at ``times`` (absolute, strictly increasing) or one dt apart.  A row the gate rejects
        (:meth:`_gate_score`) keeps the predicted weights: it only predicts, flagged ``gated``."""
        model = self.model
        obs = self.observation
        rows = check_rows(increments, model.m, "observations" if obs.discrete else "increments")
        K, n = len(rows), model.n
        taus = resolve_times(state.t, state.step > 0, K, model.dt, times)
        steps, times_out = chunk_clock(state, K, model.dt, times, taus)
        check_first_gap(taus, obs.discrete, self.method)
        gaps = np.full(K, model.dt) if taus is None else np.asarray(taus, float)
        singles = self._singles
        chunk = singles.chunk_terms(rows, gaps) if singles is not None else None
        blocks = self._block_terms(rows, gaps) if singles is None else None  # singles: only for the gate
        mean_out, cov_out = np.empty((K, n)), np.empty((K, n, n))
        ll_inc, bad, pll = np.zeros(K), np.zeros(K, bool), np.full(K, np.nan)
        gated, scores = np.zeros(K, bool), np.full(K, np.nan)
        X, logW = state.points, state.log_weights.copy()
        if singles is not None or jit.enabled():  # each coordinate contiguous (singles: moved in place)
            X = np.array(X, order="F")
        restarts, reason = state.restarts, state.reason
        done = 0 if state.degenerate else K
        W = np.exp(logW)  # the weights, kept with logW from row to row
        mean, cov = self._moments(X, W)
        bank = None if singles is not None else self._banks.get(state.seed, len(X))
        for k in range(done):
            step = int(steps[k])
            rng = np.random.default_rng([state.seed, step])
            if gaps[k] > 0:
                pieces = max(1, math.ceil(float(gaps[k]) / model.dt - 1e-9))  # Euler steps of at most dt
                for _ in range(pieces):
                    X = self._kolmogorov(X, W, float(gaps[k]) / pieces, rng, bank)
            seen = singles.seen(chunk, k) if singles is not None else any(keys[k] for *_, keys, _ in blocks)
            columns = singles is None and X.flags.f_contiguous  # coupled: each component contiguous
            hX = None if not seen else sensor_rows(model.h, X.T).T if columns else model.h(X)
            predicted = logW.copy() if seen else None
            known = np.full(len(self.blocks), np.nan)  # each block's coverage, once made
            gain, offsets, over, factors = 0.0, 0.0, True, {}
            if seen and singles is not None:
                row = singles.observe(logW, hX, chunk, k, float(gaps[k]), TEMPER, known)
                gain, offsets, bound, components, factors = row
                over = gain is not None and bound > gate_threshold(obs.gate, components)
            elif seen:
                gain, offsets, factors = self._update_blocks(k, logW, hX, blocks, gaps, known)
            if gain is None:
                logW = predicted  # (the compiled update leaves its partial work in logW)
                reason, done = _zero_likelihood(step), k
                break
            if singles is not None and blocks is None and ((obs.gating and over) or factors):
                blocks = self._block_terms(rows, gaps)  # singles: the blocks' terms only for these rows
            if predicted is not None and obs.gating and over:
                score = self._gate_score(k, gain, hX, predicted, blocks, gaps)
                if score is not None:  # the gate: the row only predicts
                    logW, gated[k], scores[k] = predicted, True, score
            if predicted is not None and not gated[k] and factors:
                X, count = self._temper(X, predicted, logW, factors, blocks, k, gaps, rng, bank, known)
                restarts += count
            if gated[k]:  # logW back to the prediction: every coverage read from it again
                known = None
            X, count, failure = self._restarts(X, logW, rng, bank, step, known)
            restarts += count
            if failure is not None:
                reason, done = failure, k
                break
            if seen:
                pll[k] = gain
                if not gated[k]:
                    ll_inc[k] = gain - offsets
            W = np.exp(logW)
            mean, cov = self._moments(X, W)
            mean_out[k], cov_out[k] = mean, cov
        if done < K:
            mean_out[done:], cov_out[done:] = mean, cov
            bad[done:] = True
            pll[done:] = np.nan
            ll_inc[done:] = 0.0
        loglik = np.cumsum(np.concatenate([[state.loglik], ll_inc]))[1:]
        last = K - 1
        degenerate = bool(state.degenerate or done < K)
        new_state = replace(state, step=int(steps[last]) if K else state.step,
                            t=float(times_out[last]) if K else state.t,
                            loglik=float(loglik[last]) if K else state.loglik,
                            loglik_increment=float(ll_inc[last]) if K else state.loglik_increment,
                            points=X, log_weights=logW, restarts=restarts, degenerate=degenerate,
                            reason=reason if degenerate else None)
        return new_state, ChunkResult(steps, times_out, mean_out, cov_out, None, loglik, ll_inc, bad,
                                      reason=new_state.reason if bad.any() else None,
                                      predictive_loglik=pll, gated=gated, gate_score=scores,
                                      gate=obs.gate)

    def estimate(self, state: YauNiuState) -> Estimate:
        mean, cov = self._moments(state.points, np.exp(state.log_weights))
        return Estimate(step=state.step, t=state.t, mean=mean, cov=cov, loglik=state.loglik,
                        loglik_increment=state.loglik_increment, degenerate=state.degenerate,
                        reason=state.reason)

    def density(self, state: YauNiuState, points: np.ndarray, gradient: bool = False) -> np.ndarray:
        """The product over the blocks of the multi-scale kernel estimates
        Σ_i w_i N(x_b; √(1−h²)x_ib + (1−√(1−h²))m_b, h²P_b) (h: the bandwidth, at least Silverman's
        for N points — with ``gradient``, at least :func:`gradient_bandwidth`): the density the restart
        would sample."""
        X = np.atleast_2d(np.asarray(points, float))
        n = self.model.n
        if X.ndim != 2 or X.shape[1] != n or not np.all(np.isfinite(X)):
            raise InputError("points", f"must be finite points of shape (P, {n})")
        log_density = np.zeros(len(X))
        for coords, logw in zip(self.blocks, state.log_weights, strict=True):
            log_density += self._block_log_density(state.points[:, coords], logw, X[:, coords], gradient)
        return np.exp(log_density)

    def _block_log_density(self, centres: np.ndarray, logw: np.ndarray, X: np.ndarray,
                           gradient: bool = False) -> np.ndarray:
        N, d = centres.shape
        mean, cov = weighted_moments(centres, np.exp(logw))
        h = max(self.bandwidth or 0.0, (gradient_bandwidth if gradient else silverman)(N, d))
        shrink = math.sqrt(1.0 - h * h)
        kernel = h * h * cov + 1e-12 * np.eye(d)
        shrunk = shrink * centres + (1.0 - shrink) * mean
        out = np.empty(len(X))
        for start in range(0, len(X), 256):
            block = X[start:start + 256]
            logs = np.stack([log_normal(shrunk, x, kernel) for x in block])  # (B, N)
            out[start:start + 256] = logsumexp(logs + logw[None, :], axis=1)
        return out

    def state_from_dict(self, data: dict[str, Any]) -> YauNiuState:
        """Inverse of :meth:`YauNiuState.to_dict`: the points and log weights packed (solver/qmc/packed.py)
        or as lists of numbers (states stored before); bad fields raise InputError('state.…')."""
        if not isinstance(data, dict):
            raise InputError("state", "not a yau-niu state (points, log_weights, step, t, loglik)")
        X = unpack(data.get("points"), "state.points", (None, self.model.n))
        logW = unpack(data.get("log_weights"), "state.log_weights", (len(self.blocks), len(X)))
        if not len(X) or not np.isfinite(X).all():
            raise InputError("state.points", "must be at least one point, every coordinate finite")
        if np.isnan(logW).any() or (logW == np.inf).any() or not np.isfinite(logW.max(axis=1)).all():
            raise InputError("state.log_weights", "must be finite or -inf (a zero weight), with a finite one "
                                                  "in every block")
        try:
            return YauNiuState(points=X, log_weights=logW, step=int(data["step"]), t=float(data["t"]),
                               loglik=float(data["loglik"]),
                               loglik_increment=float(data.get("loglik_increment", 0.0)),
                               degenerate=bool(data.get("degenerate", False)), reason=data.get("reason"),
                               restarts=int(data.get("restarts", 0)), seed=int(data.get("seed", 0)))
        except (KeyError, TypeError, ValueError):
            raise InputError("state", "not a yau-niu state (points, log_weights, step, t, loglik)") from None


def _zero_likelihood(step: int) -> str:
    return (f"step {step}: the observation's likelihood is zero or not finite at every point; reset the "
            "session, or use more points (discretization.points)")


def build(model: Model, offline: Any = None, gate: float | None = None, **_: Any) -> YauNiuFilter:
    """The registry's constructor (solver/registry.py)."""
    return YauNiuFilter(model, gate=gate)
