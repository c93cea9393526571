"""The online Yau–Yau filter: memoryless propagation of the unnormalised conditional density σ.

Seed 002 (5.35)–(5.38), observation times τ_k = k·dt, increments Δy_k = y(τ_k) − y(τ_{k−1}):

    u_k(τ_k) = e^{dt (L − ½hᵀR⁻¹h)} σ(τ_{k−1})             (5.38), the Kolmogorov-type equation (5.31)
    σ(τ_k)   = exp(hᵀR⁻¹Δy_k) · u_k(τ_k)                     (5.35)

with L the Fokker–Planck operator, on the ball B_R with Dirichlet boundary conditions.  The
propagators e^{dt·(…)} φ_j of the basis functions are computed offline (``solver/offline/pipeline.py``).

Two forms of one step (both first order in dt, Lie–Trotter splitting of the same equation):

* ``literal`` — exactly (5.35)/(5.38): the Kolmogorov propagator (−½hᵀR⁻¹h inside) and the
  factor exp(hᵀR⁻¹Δy).  With a truncated basis this factor is huge at the rim of the ball
  (e^{70} for the cubic sensor at radius 7) and amplifies the basis' ripples there.
* ``stable`` (default) — the Fokker–Planck propagator e^{dt L} and the factor
  exp(hᵀR⁻¹Δy − ½hᵀR⁻¹h·dt) ≤ exp(½ΔyᵀR⁻¹Δy/dt), which never amplifies the rim.

A step works in nodal values (``nodes``/``weights`` of the offline arrays):

    s = P c                       P = propagator_fp (stable) or propagator_k (literal)
    σ = s · exp(log e − max log e)   (the max goes to the log normaliser: log scale throughout)
    estimates = moments of σ with the quadrature weights (before projection)
    c = projector σ,  ∫σ          back onto the basis; the next step divides by ∫σ (renormalises)

A row of NaN increments (missing observation) only predicts: s = propagator_fp c.
The log-likelihood increment is log ∫σ(τ_k) − log ∫σ(τ_{k−1}), the Girsanov likelihood ratio of
the increment against pure noise.

A step is degenerate (flagged with a reason; the state keeps the last good coefficients and
estimate) when its update factor overflows, when ∫σ is not positive even in log scale, or when the
checks of solver/engine/diagnostics.py find it implausible (pushed against ∂B_R, unresolved, leaking mass
through the wall).  The state and its exact JSON form are in solver/engine/state.py.
"""

from __future__ import annotations

import copy
import dataclasses
import math
from dataclasses import dataclass
from functools import cached_property
from typing import Any

import numpy as np
from scipy.linalg.blas import dgemv, sgemv

from ..errors import InputError, SpecError
from ..filtering import (
    ChunkedFilter,
    ChunkResult,
    Estimate,
    chunk_clock,
    concat_results,
    marginal_by_quadrature,
)
from ..measurement import (
    Observation,
    RowTerms,
    check_first_gap,
    check_gate,
    check_rows,
    resolve_times,
    standard_score,
)
from ..model import Model
from ..registry import FORMS, PRECISIONS
from ..spec import DensityPrior, GaussianPrior, MixturePrior
from .diagnostics import Diagnostics
from .semigroup import SpectralFlow
from .state import YauYauState, state_from_dict


@dataclass(frozen=True)
class _Arithmetic:
    """Floating point of the hot loop.  A pre-projection mass outside [tiny, huge] is recomputed in
    log scale (rare slow path); update factors (relative to their max) below ``negligible`` count as 0,
    so the BLAS calls never work on subnormal numbers (slow)."""

    dtype: type
    gemv: Any
    tiny: float
    huge: float
    negligible: float


_ARITHMETIC = {"double": _Arithmetic(np.float64, dgemv, 1e-280, 1e280, 1e-250),
               "single": _Arithmetic(np.float32, sgemv, 1e-30, 1e30, 1e-25)}
_MIN_PRIOR_MASS = 0.5  # of a gaussian/mixture prior on the ball
PIECE = 2.0  # an increment over a gap longer than (PIECE + 1/4)·dt is filtered in pieces of about PIECE·dt
MAX_PIECES = 64  # pieces of one increment at most (a longer gap gets longer pieces)
MAX_CHUNK_PIECES = 8192  # pieces filtered at once (the rest of a chunk follows, block by block)
_NO_MASS_AFTER_UPDATE = "no positive mass after the update: observation impossible under the model"


class YauYauFilter(ChunkedFilter):
    """The Yau–Yau filter on precomputed offline arrays (the :class:`solver.filtering.Filter` protocol).

    ``offline`` is any :class:`solver.offline.OfflineArrays` (nodes, weights, basis, projector, the two
    propagators, ``evaluate_basis``).  ``precision="single"`` runs the two matrix-vector products per
    step in float32 (speed-up: docs/bench-engine.md; relative rounding ~1e-7 per step); the moments,
    log-likelihood and state stay in float64.
    """

    method = "yau-yau"

    def __init__(self, model: Model, offline: Any, form: str = "stable", precision: str = "double",
                 gate: float | None = None):
        if form not in FORMS:
            raise SpecError("form", f"must be one of {', '.join(FORMS)}, got {form!r}")
        if precision not in PRECISIONS:
            raise SpecError("precision", f"must be one of {', '.join(PRECISIONS)}, got {precision!r}")
        self.model = model
        self.offline = offline
        self.form = form
        self.precision = precision
        self.gate_override = check_gate(gate)
        self._arith = arith = _ARITHMETIC[precision]
        self.nodes = np.ascontiguousarray(offline.nodes, dtype=float)
        self.weights = np.ascontiguousarray(offline.weights, dtype=float)
        projector = np.asarray(offline.projector, dtype=float)
        self.N = projector.shape[0]
        _check_offline_shapes(self.nodes, self.weights, projector, offline, model.n)
        # Fortran order: gemv reads it without a copy.  The weights ride along as an extra row of
        # the projector, so one call gives the coefficients and the mass ∫σ; the propagators get a
        # zero column for it, so the next call takes that vector as it is (and 1/∫σ as its alpha).
        self._project = np.asfortranarray(np.vstack([projector, self.weights]), dtype=arith.dtype)
        self._predict = _with_zero_column(offline.propagator_fp, arith.dtype)
        literal = form == "literal"
        self._observe = _with_zero_column(offline.propagator_k, arith.dtype) if literal else self._predict
        h_nodes = model.h(self.nodes)
        self._h_nodes = h_nodes  # (Q, m): the update factors of every kind (solver/measurement.py)
        self._pairs = [(i, j) for i in range(model.n) for j in range(i, model.n)]
        self._features = _moment_features(self.weights, self.nodes, self._pairs)
        self._diagnostics = Diagnostics(model, self.nodes, self.weights, projector, offline, h_nodes)
        self.frame = None  # solver/engine/frame.py: the ball rides ċ = Ac + b (set by framed())

    def framed(self, frame: Any) -> "YauYauFilter":
        """This engine in a frame moving with the mean's ODE (solver/engine/frame.py): each step's nodes are
        these nodes moved by c_k − c₀, c_k the frame's centre after the step (from the state's
        ``center``); the stored propagator must be the frame's (f(x) − f(c₀))."""
        new = copy.copy(self)
        new.__dict__.setdefault("_flow_owner", self)
        new.frame = frame
        return new

    def _shifts(self, state: YauYauState, gaps: np.ndarray) -> np.ndarray | None:
        """In a moving frame, each row's node shift c_k − c₀ (K, n); else None."""
        if self.frame is None:
            return None
        if state.center is None:
            raise InputError("state.center", "a filter in a moving frame needs the ball's centre in its "
                                             "state")
        return self.frame.path(state.center, gaps) - self.frame.origin

    def _h_shifted(self, shifts: np.ndarray) -> np.ndarray:
        """h at each row's moved nodes, (K, Q, m)."""
        K, (Q, n) = len(shifts), self.nodes.shape
        points = (self.nodes[None, :, :] + shifts[:, None, :]).reshape(K * Q, n)
        return np.asarray(self.model.h(points), dtype=float).reshape(K, Q, -1)

    def centred_at(self, center: Any) -> "YauYauFilter":
        """This engine on the ball translated to ``center`` (solver/engine/follow.py): the same basis,
        projector and propagators (shared, not copied), the observation and the moments at the
        translated nodes.  Right where the Fokker–Planck operator is invariant under the move (f does
        not depend on the coordinates that move); the caller checks that."""
        from .follow import TranslatedOffline

        center = np.asarray(center, dtype=float)
        home = getattr(self.offline, "home", self.offline)
        shift = center - np.asarray(getattr(self.offline, "home_center", self.model.center), dtype=float)
        new = copy.copy(self)
        new.__dict__.pop("_marginal_operators", None)
        new.__dict__.pop("node_tree", None)  # the KD-tree of the old nodes
        new.__dict__.setdefault("_flow_owner", self)
        new.model = self.model.translated(center)
        new.offline = TranslatedOffline(home, shift, center - shift)
        new.nodes = np.ascontiguousarray(home.nodes + shift, dtype=float)
        new._h_nodes = new.model.h(new.nodes)
        new._features = _moment_features(self.weights, new.nodes, self._pairs)
        new._diagnostics = self._diagnostics.translated(new._h_nodes)
        return new

    # -- states ------------------------------------------------------------------------
    def initial_state(self, prior: Any | None = None) -> YauYauState:
        """σ(0) = σ0: the prior (the model's, or ``prior``, a spec prior or its dict) on the basis."""
        model = self.model if prior is None else _override_model(self.model, prior)
        self._check_resolved(model.spec.initial)
        log_prior = model.log_prior(self.nodes)
        finite = np.isfinite(log_prior)
        if not finite.any():
            raise SpecError("initial", "the prior density vanishes at every node of the domain ball")
        top = log_prior[finite].max()
        sigma = np.where(finite, np.exp(np.where(finite, log_prior - top, 0.0)), 0.0)
        mass = float(self.weights @ sigma)
        if not mass > 0.0:
            raise SpecError("initial", "the prior has no mass on the domain ball")
        if not isinstance(model.spec.initial, DensityPrior):  # normalised: its mass on the ball is known
            ball_mass = math.exp(min(top + math.log(mass), 0.0))
            if ball_mass < _MIN_PRIOR_MASS:
                raise SpecError("initial", f"only {ball_mass:.3g} of the prior mass lies on the domain ball "
                                "(move the prior or enlarge domain.radius)")
        sigma = sigma / mass
        projected = self._arith.gemv(1.0, self._project, sigma.astype(self._arith.dtype))
        mean, cov, mode = self._moments(sigma[None, :], np.ones(1))
        last = Estimate(step=0, t=0.0, mean=mean[0], cov=cov[0], loglik=0.0, loglik_increment=0.0,
                        mode=mode[0])
        return YauYauState(coefficients=projected[: self.N].astype(float), mass=projected.item(self.N),
                           step=0, t=0.0, loglik=0.0, last=last, form=self.form, precision=self.precision)

    @cached_property
    def node_tree(self) -> Any:
        """scipy's cKDTree of the nodes (built once: a move's carry, the mode, the node spacing)."""
        from scipy.spatial import cKDTree

        return cKDTree(self.nodes)

    @cached_property
    def node_spacing(self) -> float:
        """The median distance from a node to its nearest neighbour: the finest feature the nodes see."""
        if len(self.nodes) < 2:
            return math.inf
        distances, _ = self.node_tree.query(self.nodes, k=2)
        return float(np.median(distances[:, 1]))

    def _check_resolved(self, prior: Any) -> None:
        """A Gaussian (or mixture component) narrower than half the node spacing cannot be represented: its
        nodal values miss its mass and its covariance comes out ~0.  Refuse it, saying what to change."""
        if isinstance(prior, GaussianPrior):
            parts = [("initial.cov", prior.cov)]
        elif isinstance(prior, MixturePrior):
            parts = [(f"initial.covs[{i}]", c) for i, (w, c) in enumerate(zip(prior.weights, prior.covs,
                                                                               strict=True)) if w > 0]
        else:
            return
        h = self.node_spacing
        for field, cov in parts:
            sd = math.sqrt(max(float(np.linalg.eigvalsh(np.asarray(cov, dtype=float)).min()), 0.0))
            if sd < h / 2:  # two standard deviations between nodes: its nodal values miss the peak
                raise SpecError(field, (
                    f"the prior is narrower than the mesh resolves: its smallest standard deviation {sd:.3g} "
                    f"is below half the node spacing {h:.3g} (domain.radius {self.model.radius:g}, "
                    f"{len(self.nodes)} nodes); widen it to a variance of at least {h * h / 4:.3g}, or "
                    "resolve it: shrink domain.radius or raise discretization.mesh and discretization.basis"))

    def ball_center(self, state: YauYauState) -> np.ndarray:
        """The centre of the ball the state's density lives on."""
        return self.model.center

    def state_from_dict(self, data: dict[str, Any]) -> YauYauState:
        """Inverse of :meth:`YauYauState.to_dict` (validated; bad fields raise InputError('state.…'))."""
        return state_from_dict(data, self.N, self.model.n, self.form, self.precision)

    def estimate(self, state: YauYauState) -> Estimate:
        """The last good estimate; flagged (with the reason) when the state is degenerate."""
        if not state.degenerate:
            return state.last
        return dataclasses.replace(state.last, step=state.step, t=state.t, loglik_increment=0.0,
                                   degenerate=True, reason=state.reason)

    # -- stepping (step, run and predict: ChunkedFilter) -------------------------------------
    @cached_property
    def flow(self) -> SpectralFlow:
        """e^{τA} on the basis for any gap τ (irregular times; solver/engine/semigroup.py), built on first use
        (a centred engine's is its home engine's: the generator does not move with the ball)."""
        owner = self.__dict__.get("_flow_owner")
        if owner is not None:
            return owner.flow
        generator = getattr(self.offline, "fokker_planck_generator", None)
        if generator is None:
            raise InputError("times", "these offline arrays have no Fokker-Planck generator: irregular times "
                                      "need a model precomputed by yauyau precompute")
        return SpectralFlow(generator(), self.offline.basis, self.offline.projector, self.weights,
                            dtype=self._arith.dtype)

    def run_arrays(self, state: YauYauState, increments: np.ndarray,
                   times: np.ndarray | None = None, until: Any = None,
                   follow: Any = None) -> tuple[YauYauState, ChunkResult]:
        """Advance over a chunk (K, m) of rows at ``times`` (or one dt apart); estimates as arrays.

        ``until(mean, centers)`` (a ball that follows the state, solver/engine/follow.py): given the rows'
        means (K, n) and, in a moving frame, their centres (else None), the number j ≥ 1 of rows to
        keep, or None for all.  The chunk then ends after row j − 1: the result has j rows and the new
        state is the one the hot loop carried there, bit for bit, as if the chunk had been j rows long.
        Rows over long gaps (filtered in pieces) always run whole.

        ``follow`` (regular rows only): ``(follower, velocity, moves)``, a ball that moves inside the
        loop (solver/engine/recentring.py; ``moves`` gets (row, new centre) per move); ``state.center`` is the
        ball's centre, the result has each row's, and the chunk may end early (after a row the loop
        could not move from: the caller re-centres)."""
        model, obs = self.model, self.observation
        rows = check_rows(increments, model.m, "observations" if obs.discrete else "increments")
        K = rows.shape[0]
        taus = resolve_times(state.t, state.step > 0, K, model.dt, times)
        check_first_gap(taus, obs.discrete)
        if K == 0:
            return state, _stack_results(np.empty(0, int), np.empty(0), *self._empty_moments(), np.empty(0),
                                         np.empty(0), state.last, None)
        steps, times = chunk_clock(state, K, model.dt, times, taus)
        if self.form == "literal":
            self._check_literal(rows, taus)
        if state.degenerate:
            return self._stay_degenerate(state, steps, times, state.reason)
        if follow is not None and taus is not None:
            raise ValueError("a ball that moves inside the loop takes regular rows only")
        pieces = self._pieces(rows, taus)
        if pieces is None:
            return self._run(state, rows, steps, times, taus, gating=True, until=until, follow=follow)
        parts, start = [], 0
        for stop in _blocks(pieces, MAX_CHUNK_PIECES):  # bounded memory: the pieces of a block at a time
            if state.degenerate:  # an earlier block degenerated: the rest stays so
                state, part = self._stay_degenerate(state, steps[start:], times[start:], state.reason)
                parts.append(part)
                break
            state, part = self._run_in_pieces(state, rows[start:stop], steps[start:stop], times[start:stop],
                                              taus[start:stop], pieces[start:stop])
            parts.append(part)
            start = stop
        return state, concat_results(parts)

    def run_batch(self, states: list[YauYauState], chunks: list[Any], times: list[Any] | None = None,
                  return_exceptions: bool = False) -> list[Any]:
        """Many states through their chunks together, one matrix–matrix product per step (engine/batch.py):
        [(new state, ChunkResult)] as ``run_arrays`` gives one by one, up to rounding."""
        from .batch import run_batch

        return run_batch(self, states, chunks, times, return_exceptions)

    def _run(self, state: YauYauState, rows: np.ndarray, steps: np.ndarray, times: np.ndarray,
             taus: np.ndarray | None, gating: bool, until: Any = None,
             follow: Any = None) -> tuple[YauYauState, ChunkResult]:
        """The chunk's rows through the hot loop (validated; ``taus`` None: regular rows)."""
        ready = self._prepare(state, rows, taus, gating, follow)
        loop = self._propagate(ready.initial, ready.log_factor, ready.top, ready.skip.tolist(), ready.gate,
                               taus, ready.moving)
        return self._finish(state, rows, steps, times, taus, ready, *loop, until=until)

    def _prepare(self, state: YauYauState, rows: np.ndarray, taus: np.ndarray | None,
                 gating: bool, follow: Any = None) -> "_Prepared":
        """What the hot loop needs of a chunk: the update factors, the gate, the carried vector (on a
        ball that moves in the loop, the factors come a window at a time: solver/engine/recentring.py)."""
        obs = self.observation
        gaps = np.full(len(rows), self.model.dt) if taus is None else taus
        moving, origin = None, None if self.frame is None else self.frame.origin
        if follow is None:
            shifts = self._shifts(state, gaps)
            keys, terms, log_factor, top, impossible = self._factors(rows, gaps, shifts)
        else:
            from .recentring import Recentring

            keys = obs.pattern_keys(~np.isnan(rows))
            terms = obs.row_terms(rows, gaps, keys)
            moving = Recentring(self, follow[0], state, rows, gaps, keys, terms, keys == 0, *follow[1:])
            log_factor, top, impossible = moving.log_factor, moving.top, moving.impossible
            shifts, origin = moving.shifts, moving.origin
        missing = keys == 0
        gate = _Gate(obs, terms, keys, gaps, self, shifts) if obs.gating and gating else None
        skip = missing.copy()
        if gate is not None:  # rejected before the loop: no finite factor to weigh
            skip |= impossible
            gate.scores.update({int(k): math.inf for k in np.flatnonzero(impossible)})
        if moving is not None:  # its windows add their impossible rows to these
            moving.skip, moving.gate = skip, gate
        initial = np.append(state.coefficients, state.mass).astype(self._arith.dtype)
        # _rescue may shift top[k]: the growth is relative to the factor's maximum
        top_before = top.copy() if moving is None else moving.top_before
        return _Prepared(gaps, keys, terms, log_factor, top, top_before, impossible, missing, skip, gate,
                         initial, shifts, origin, moving)

    def _finish(self, state: YauYauState, rows: np.ndarray, steps: np.ndarray, times: np.ndarray,
                taus: np.ndarray | None, ready: "_Prepared", sigma, masses, carried, done: int,
                reason: str | None, until: Any = None) -> tuple[YauYauState, ChunkResult]:
        """The chunk's estimates, checks and new state from what the hot loop left (``sigma``: the
        nodal σ_k of its good steps, ``masses`` their ∫σ_k, ``carried`` the vector after the last)."""
        obs = self.observation
        K = len(rows)
        gaps, terms, top, top_before = ready.gaps, ready.terms, ready.top, ready.top_before
        impossible, missing, skip, gate, initial = (ready.impossible, ready.missing, ready.skip, ready.gate,
                                                     ready.initial)
        if gate is None and impossible[:done].any():
            done = int(np.argmax(impossible))
            reason = "the update factor exp(hᵀR⁻¹Δy) overflows: observation incompatible with the model"
            sigma, masses = sigma[:done], masses[:done]
        if reason is not None:  # the loop stopped early (and may have scaled its vector for the next gap)
            carried = self._carried_after(sigma, masses, done, initial, taus)
        with np.errstate(divide="ignore"):
            pll = np.log(masses) + top[:len(masses)]  # log E_pred[e_k]
        gated = np.zeros(K, dtype=bool)
        scores = np.full(K, np.nan)
        if gate is not None:
            for k, score in gate.scores.items():
                gated[k], scores[k] = True, standard_score(score, gate.size(k))
                top[k] = top_before[k] = 0.0
                if k < len(pll):
                    pll[k] = gate.attempted.get(k, -math.inf)
        shifts = ready.shifts
        mean, cov, mode = self._moments(sigma[:done], masses[:done],
                                        None if shifts is None else shifts[:done])
        cut = None if until is None or not done else until(
            mean, None if shifts is None else shifts[:done] + ready.origin)
        stopped = None if ready.moving is None else ready.moving.stopped
        if stopped is not None:  # the loop could not move the ball after row stopped − 1: it ends there
            cut = stopped
        if cut is not None and 1 <= cut < K and (cut < done or cut == stopped):
            K = done = int(cut)
            rows, steps, times, missing, skip = rows[:K], steps[:K], times[:K], missing[:K], skip[:K]
            sigma, masses, pll, gated, scores = sigma[:K], masses[:K], pll[:K], gated[:K], scores[:K]
            mean, cov, mode = mean[:K], cov[:K], mode[:K]
            shifts = None if shifts is None else shifts[:K]
            carried, reason = self._carried_after(sigma, masses, K, initial, taus), None
        with np.errstate(over="ignore", invalid="ignore"):
            growth = masses[:done] * np.exp(top[:done] - top_before[:done])
        bad, why = self._diagnostics.first_implausible(sigma[:done], masses[:done], cov, growth)
        if bad is not None:
            why = self._explained(sigma, state, rows, steps, skip, bad, why, gaps, shifts)
        elif reason is not None:  # the hot loop stopped at step `done` (no positive mass, overflow)
            reason = self._explained(sigma, state, rows, steps, skip, done, reason, gaps, shifts)
        if bad is not None:
            done, reason = bad, why
            carried = self._carried_after(sigma, masses, bad, initial, taus)
            mean, cov, mode = mean[:done], cov[:done], mode[:done]
        masses = masses[:done]
        increments_ll = np.log(masses) + top[:done]
        # sequential sums from the carried value: identical however the data are chunked
        loglik = np.cumsum(np.concatenate([[state.loglik], increments_ll]))[1:]
        predictive = np.full(K, np.nan)
        predictive[:done] = pll[:done] + terms.offset[:done]
        predictive[missing] = np.nan
        good = done == K
        if done:
            last = Estimate(step=int(steps[done - 1]), t=float(times[done - 1]), mean=mean[-1], cov=cov[-1],
                            loglik=float(loglik[-1]), loglik_increment=float(increments_ll[-1]),
                            mode=mode[-1])
        else:
            last = state.last
        coefficients = carried[: self.N].astype(float)
        if taus is not None and not self.flow.exact:
            coefficients = self.flow.from_modal(coefficients)
        new_state = YauYauState(coefficients=coefficients, mass=carried.item(self.N),
                                step=int(steps[-1]), t=float(times[-1]), precision=self.precision,
                                loglik=last.loglik, last=last, degenerate=not good,
                                reason=reason, form=self.form)
        gated[done:], scores[done:] = False, np.nan
        frame = {}
        if shifts is not None:  # the frame's centre after each row (after the last good one when stopped)
            centers = shifts + ready.origin
            end = centers[-1] if good else (centers[done - 1] if done else np.asarray(state.center, float))
            new_state = dataclasses.replace(new_state, center=np.array(end))
            frame = {"center": centers}
        return new_state, _stack_results(steps, times, mean, cov, mode, loglik, increments_ll, last, reason,
                                         predictive_loglik=predictive, gated=gated, gate_score=scores,
                                         gate=obs.gate, **frame)

    def _pieces(self, rows: np.ndarray, taus: np.ndarray | None) -> np.ndarray | None:
        """How many pieces each row's gap is filtered in: an increment over a gap longer than
        (PIECE + ¼)·dt in ⌈τ/(PIECE·dt) − ¼⌉ equal pieces (None: every row in one)."""
        if taus is None or self.observation.discrete or self.form == "literal":
            return None
        observed = ~np.isnan(rows).all(axis=1)
        with np.errstate(over="ignore", invalid="ignore"):
            wanted = np.ceil(np.minimum(taus / (PIECE * self.model.dt), MAX_PIECES) - 0.25)
        count = np.where(observed, np.clip(wanted, 1, MAX_PIECES), 1)
        return count.astype(int) if count.max() > 1 else None

    def _run_in_pieces(self, state: YauYauState, rows, steps, times, taus, pieces):
        """Increments over long gaps, each in ``pieces[k]`` equal pieces of its gap and of its increment
        (y taken linear over the gap, as the exact filters do: the factor of seed 002 (5.35) freezes x
        over each piece only).  The gate judges whole rows: a chunk runs without it, then again with
        a rejected row left out, until no row is over its threshold (outliers are rare)."""
        obs = self.observation
        keys = obs.pattern_keys(~np.isnan(rows))
        terms = obs.row_terms(rows, taus, keys)
        data, rejected = rows.copy(), {}
        while True:
            count = np.where(np.isnan(data).all(axis=1), 1, pieces)
            owner = np.repeat(np.arange(len(data)), count)
            first = np.cumsum(count) - count
            share = taus[owner] / count[owner]
            before = np.concatenate([[state.t], times[:-1]])
            piece_times = before[owner] + share * (np.arange(len(owner)) - first[owner] + 1)
            piece_times[first + count - 1] = times  # each row ends exactly at its time
            new_state, sub = self._run(state, data[owner] / count[owner, None], steps[owner], piece_times,
                                       share, gating=False)
            ll = np.add.reduceat(sub.loglik_increment, first)
            last = first + count - 1
            found = (self._first_rejected(state, data, times, taus, ll, terms, keys, sub.degenerate[last],
                                          rejected) if obs.gating else None)
            if found is None:
                break
            data[found] = np.nan
        predictive = np.where(keys == 0, np.nan, ll + terms.offset)
        gated, scores = np.zeros(len(rows), dtype=bool), np.full(len(rows), np.nan)
        for k, (score, attempted) in rejected.items():
            gated[k], scores[k] = True, standard_score(score, int(keys[k]).bit_count())
            predictive[k] = attempted + terms.offset[k]
        degenerate = sub.degenerate[last]
        predictive[degenerate] = np.nan
        return new_state, ChunkResult(step=steps, t=times, mean=sub.mean[last], cov=sub.cov[last],
                                      mode=sub.mode[last], loglik=sub.loglik[last],
                                      loglik_increment=np.where(degenerate, 0.0, ll), degenerate=degenerate,
                                      reason=sub.reason, predictive_loglik=predictive, gated=gated,
                                      gate_score=scores, gate=obs.gate,
                                      center=None if sub.center is None else sub.center[last])

    def _first_rejected(self, state, data, times, taus, ll, terms, keys, degenerate, rejected):
        """The first row over the gate (recorded in ``rejected``: its d² and log E_pred[e]), or None.
        The bound g first; the exact score predicts the state to the row (rare: rows over the bound)."""
        obs = self.observation
        bias = terms.bound_bias()
        bound = bias - 2.0 * ll
        gate = _Gate(obs, terms, keys, taus, self)
        observed = ~np.isnan(data).all(axis=1)
        suspects = observed & ~degenerate & (bound > terms.threshold)
        if degenerate.any():  # the first degenerate row may be an outlier the pieces could not carry
            suspects[int(np.argmax(degenerate))] |= observed[int(np.argmax(degenerate))]
        for k in np.flatnonzero(suspects).tolist():
            at, _ = self.run_arrays(state, data[:k], times[:k]) if k else (state, None)
            predicted, _ = self.predict(at, times[k])
            s = np.asarray(self.offline.basis) @ predicted.density_coefficients
            attempted = float(ll[k])
            shift = None if self.frame is None else np.asarray(predicted.center) - self.frame.origin
            if degenerate[k]:  # its pieces never finished: the whole row's factor on the prediction
                _, _, log_factor, top, _ = self._factors(data[k:k + 1], taus[k:k + 1],
                                                         None if shift is None else shift[None])
                attempted = self._log_mean_factor(s, log_factor[0]) + float(top[0])
            score = bias[k] - 2.0 * attempted - gate.correction(k, s, shift)
            if score > terms.threshold[k]:
                rejected[k] = (score, attempted)
                return k
        return None

    def _factors(self, rows: np.ndarray, gaps: np.ndarray, shifts: np.ndarray | None = None):
        """Per row: the pattern key of its observed components, the row terms, log e_k at the nodes
        minus its maximum (returned apart, 0 on rows without a finite factor) and which observed rows
        have no finite factor at all (an overflow: impossible under the model).  ``shifts``: each
        row's nodes moved (a moving frame), h evaluated there."""
        obs = self.observation
        keys = obs.pattern_keys(~np.isnan(rows))
        missing = keys == 0
        terms = obs.row_terms(rows, gaps, keys)
        if shifts is None:
            h_points, cache = self._h_nodes, self._factor_cache
        else:
            h_points, cache = self._h_shifted(shifts), None
        log_factor = obs.log_factors(h_points, rows, gaps, keys, terms, cache,
                                     penalty=self.form != "literal")
        with np.errstate(invalid="ignore"):
            top = log_factor.max(axis=1)
        impossible = ~missing & ~np.isfinite(top)
        top[missing | impossible] = 0.0
        log_factor -= top[:, None]
        log_factor[missing | impossible] = 0.0
        return keys, terms, log_factor, top, impossible

    def _check_literal(self, rows: np.ndarray, taus) -> None:
        """The literal form of seed 002 (5.35) has the potential inside the stored propagator over dt:
        regular, whole continuous increments only."""
        why = None
        if self.observation.discrete:
            why = ("measurement.kind", "discrete measurements")
        elif taus is not None:
            why = ("times", "irregular times")
        elif (np.isnan(rows).any(axis=1) & ~np.isnan(rows).all(axis=1)).any():
            why = ("increments", "partly missing rows")
        if why is not None:
            raise InputError(why[0], f"the literal form (propagator_k over dt) cannot take {why[1]}: use the "
                                     "stable form (the default)")

    def _explained(self, sigma, state, rows, steps, missing, k: int, why: str, gaps, shifts=None) -> str:
        """``why`` the filter failed at row k, led by the outlier it met there, if it was one (in a
        moving frame, E[h] over that row's moved nodes)."""
        if missing[k]:
            return why
        before = sigma[k - 1] if k > 0 else np.asarray(self.offline.basis) @ state.density_coefficients
        h_nodes = None if shifts is None else self._h_shifted(shifts[k:k + 1])[0]
        return self._diagnostics.explain_outlier(before, rows[k], int(steps[k]), why, float(gaps[k]),
                                                 self.observation.discrete, h_nodes)

    @cached_property
    def _factor_cache(self) -> dict:
        """Per pattern of observed components: h_o R_oo⁻¹ and ½h_oᵀR_oo⁻¹h_o at the nodes."""
        return {}

    def _propagate(self, carried: np.ndarray, log_factor: np.ndarray, top: np.ndarray, missing: list[bool],
                   gate: "_Gate | None", taus: np.ndarray | None, moving: Any = None):
        """The hot loop, two BLAS calls per step.  ``carried`` is [coefficients, ∫σ] (N+1,).

        Regular steps use the stored propagator over dt; with ``taus`` (irregular gaps) the coefficients
        are carried in the modal coordinates of solver/engine/semigroup.py and scaled by e^{τΛ} before the
        same two products (or, for an ill-conditioned generator, multiplied by Φe^{τA} per gap).
        ``gate``: an observed row whose predictive score exceeds the gate only predicts (its
        ``scores`` and ``attempted`` log E_pred[e] are recorded there).  Returns nodal σ_k
        (pre-projection, K×Q, each relative to a unit-mass σ_{k−1}), ∫σ_k, the final carried vector,
        the number of good steps and the reason it stopped early (or None).

        ``moving`` (solver/engine/recentring.py): the ball re-centres after a row whose mean or shell mass
        calls for it; the factors come a window at a time; the carried vector has the trigger's sums
        after ∫σ (the projector's extra rows).
        """
        K, Q = log_factor.shape
        N = self.N
        arith = self._arith
        if moving is None:
            factor = np.exp(log_factor).astype(arith.dtype, copy=False)
            factor[factor < arith.negligible] = 0.0
        else:  # filled a window at a time
            factor = moving.factor
        sigma = np.empty((K, Q), dtype=arith.dtype)
        scratch = np.empty(Q, dtype=arith.dtype)
        masses = [0.0] * K
        predict, observe, project, gemv = self._predict, self._observe, self._project, arith.gemv
        next_window, last, watch = -1, K - 1, ()
        if moving is not None:  # the trigger: Σw(x − c)_iσ beyond ±reach·∫σ, or the shell's Σwσ over limit·∫σ
            project = moving.project
            if moving.predict is not None:  # an atlas centre's propagator
                predict = observe = moving.predict
            carried = np.concatenate([carried, np.zeros(moving.d + 1, dtype=carried.dtype)])
            next_window, watch = 0, tuple(range(N + 1, N + 1 + moving.d))
            reach, shell, shell_limit = moving.reach, N + 1 + moving.d, moving.shell_limit
        flow = self.flow if taus is not None else None
        modal = flow is not None and not flow.exact
        if modal:
            predict = observe = flow.B
            project = flow.C
            real_scale, pair_scale = (list(part) for part in flow.scales(taus))  # row views made once
            carried = carried.copy()
            carried[:N] = flow.to_modal(carried[:N].astype(float))
        # two buffers, alternately the carried vector and the next projection (and their views)
        carried, following = carried.copy(), np.empty_like(carried)
        r = flow.r if modal else 0
        pairs = modal and flow.pair_rates.size > 0
        cdtype = np.complex64 if arith.dtype == np.float32 else np.complex128
        real_c, real_f = carried[:r], following[:r]
        pair_c, pair_f = (carried[r:N].view(cdtype), following[r:N].view(cdtype)) if pairs else (None, None)
        # the gate's bound g = bias − 2(log ∫σ + top) ≤ threshold is ∫σ ≥ floor: one comparison a step
        floors = [0.0] * K if gate is None else gate.floors(top, missing)
        observed = [not m for m in missing]
        if moving is not None:
            moving.observed, moving.floors = observed, floors
        tiny, huge, multiply = arith.tiny, arith.huge, np.multiply
        rows, factors = list(sigma), list(factor)  # made once, not per step
        mass = carried.item(N)
        for k in range(K):
            row = rows[k]
            if k == next_window:  # the update factors of the next rows at the ball's centre
                next_window = moving.window(k)
            if modal:
                multiply(real_c, real_scale[k], out=real_c)
                if pairs:
                    multiply(pair_c, pair_scale[k], out=pair_c)
            elif flow is not None:
                predict = observe = flow.nodal_flow(taus[k])
            # positional gemv arguments (alpha, a, x, beta, y, offx, incx, offy, incy, trans,
            # overwrite_y): keyword parsing costs as much as a small product
            if observed[k]:
                gemv(1.0 / mass, observe, carried, 0.0, scratch, 0, 1, 0, 1, 0, 1)
                multiply(scratch, factors[k], out=row)
            else:
                gemv(1.0 / mass, predict, carried, 0.0, row, 0, 1, 0, 1, 0, 1)
            gemv(1.0, project, row, 0.0, following, 0, 1, 0, 1, 0, 1)
            new_mass = following.item(N)
            if not tiny < new_mass < huge or new_mass < floors[k]:  # rare: rescue, or a row near the gate
                s = scratch if observed[k] else row
                new_mass, reason = self._slow_step(k, new_mass, s, row, observed[k], log_factor, top, gate,
                                                   project, following)
                if reason is not None:
                    return sigma, np.array(masses[:k]), carried.copy(), k, reason
            masses[k] = mass = new_mass
            carried, following = following, carried
            if modal:
                real_c, real_f = real_f, real_c
                pair_c, pair_f = pair_f, pair_c
            elif watch and k < last:
                far = carried.item(shell) > shell_limit * mass
                for i in watch:
                    if far:
                        break
                    far = not -reach * mass <= carried.item(i) <= reach * mass
                if not far or k < moving.quiet:
                    continue
                moved = moving.move(k, carried, following, mass)
                if moved is None:  # the loop cannot move on: the chunk ends after row k
                    moving.stopped = k + 1
                    return sigma, np.array(masses[:k + 1]), carried.copy(), k + 1, None
                if moved > 0.0:
                    mass = moved
                    carried, following = following, carried
                    next_window = moving.window(k + 1)
                    if moving.predict is not None:
                        predict = observe = moving.predict
        return sigma, np.array(masses), carried.copy(), K, None

    def _slow_step(self, k, new_mass, s, row, observed, log_factor, top, gate, project, following):
        """Step k when ∫σ under/overflowed (recomputed in log scale) or an observed row's cheap gate
        bound is over the threshold (the exact score decides).  Returns (∫σ, reason or None); writes
        row and ``following`` as the hot loop would have."""
        arith, N = self._arith, self.N
        if not arith.tiny < new_mass < arith.huge:
            new_mass, reason = self._rescue(s, log_factor, top, not observed, k, row)
            if reason is _NO_MASS_AFTER_UPDATE and observed and gate is not None:
                ll = self._log_mean_factor(s, log_factor[k]) + float(top[k])  # in log scale throughout
                score = gate.bias[k] - 2.0 * ll - gate.correction(k, s) if ll > -math.inf else math.inf
                if score > gate.threshold[k]:
                    gate.attempted[k] = ll
                    return self._reject(gate, k, score, s, row, project, following)
            if reason is not None:
                return 0.0, reason
            arith.gemv(1.0, project, row, 0.0, following, 0, 1, 0, 1, 0, 1)
            following[N] = new_mass
        if gate is not None and observed:
            ll = math.log(new_mass) + float(top[k])
            bound = gate.bias[k] - 2.0 * ll
            if bound > gate.threshold[k]:  # maybe an outlier: the exact score needs Cov_pred(h)
                score = bound - gate.correction(k, s)
                if score > gate.threshold[k]:
                    gate.attempted[k] = ll
                    return self._reject(gate, k, score, s, row, project, following)
        return new_mass, None

    def _log_mean_factor(self, s, log_factor_row) -> float:
        """log Σ_q w_q s_q e_q over the nodes where s > 0 (e relative to its maximum), by log-sum-exp: what
        the hot loop's log ∫σ would be for a factor too small to sum directly (−inf: nothing left)."""
        s = np.asarray(s, dtype=float)
        positive = s > 0.0
        if not positive.any():
            return -math.inf
        terms = np.log(self.weights[positive] * s[positive]) + log_factor_row[positive]
        top = float(terms.max())
        if not math.isfinite(top):
            return -math.inf
        return top + math.log(float(np.exp(terms - top).sum()))

    def _reject(self, gate: "_Gate", k: int, score: float, s, row, project, following):
        """Gate row k: the step only predicts (σ = the propagated density).  (∫σ, reason or None)."""
        gate.scores[k] = score
        if s is not row:
            np.copyto(row, s)
        self._arith.gemv(1.0, project, row, 0.0, following, 0, 1, 0, 1, 0, 1)
        new_mass = following.item(self.N)
        if not self._arith.tiny < new_mass < self._arith.huge:
            return 0.0, "all probability mass has left the domain ball"
        return new_mass, None

    def _carried_after(self, sigma, masses, step: int, initial: np.ndarray, taus=None) -> np.ndarray:
        """[coefficients, ∫σ] as the hot loop carried them after row ``step`` − 1 (bit for bit), in the
        loop's coordinates (modal for irregular gaps)."""
        modal = taus is not None and not self.flow.exact
        if step == 0:
            if modal:
                initial = initial.copy()
                initial[: self.N] = self.flow.to_modal(initial[: self.N].astype(float))
            return initial
        project = self.flow.C if modal else self._project
        carried = self._arith.gemv(1.0, project, sigma[step - 1])
        carried[self.N] = masses[step - 1]
        return carried

    def _rescue(self, s, log_factor, top, missing, k, row) -> tuple[float, str | None]:
        """Recompute step k in log scale when ∫σ under/overflows (s: the propagated nodal values);
        writes row, may shift top[k]."""
        s = np.array(s, dtype=float)
        prior_mass = float(self.weights @ s)
        if not prior_mass > 0.0 or not math.isfinite(prior_mass):
            return 0.0, "all probability mass has left the domain ball"
        if not missing and not np.all(np.isfinite(log_factor[k])):
            return 0.0, "the update factor exp(hᵀR⁻¹Δy) overflows: observation incompatible with the model"
        with np.errstate(divide="ignore"):
            log_abs = np.log(np.abs(s)) + (0.0 if missing else log_factor[k])
        shift = float(log_abs.max())
        row[:] = np.sign(s) * np.exp(log_abs - shift)
        new_mass = float(self.weights @ row)
        if not self._arith.tiny < new_mass < self._arith.huge:
            return 0.0, _NO_MASS_AFTER_UPDATE
        top[k] += shift
        return new_mass, None

    def _stay_degenerate(self, state: YauYauState, steps, times, reason):
        K = len(steps)
        last = state.last
        new_state = YauYauState(coefficients=state.coefficients, mass=state.mass, precision=self.precision,
                                step=int(steps[-1]) if K else state.step,
                                t=float(times[-1]) if K else state.t, loglik=state.loglik, last=last,
                                degenerate=True, reason=reason, form=self.form)
        frame = {}
        if self.frame is not None and state.center is not None:  # the frame stops where it degenerated
            new_state = dataclasses.replace(new_state, center=np.array(state.center, dtype=float))
            frame = {"center": np.repeat(np.asarray(state.center, dtype=float)[None], K, axis=0)}
        result = _stack_results(steps, times, *self._empty_moments(), np.empty(0), np.empty(0), last, reason,
                                **frame)
        return new_state, result

    def _empty_moments(self):
        n = self.model.n
        return np.empty((0, n)), np.empty((0, n, n)), np.empty((0, n))

    def _moments(self, sigma: np.ndarray, mass: np.ndarray, shifts: np.ndarray | None = None):
        """Mean, covariance and mode of each row of nodal σ (K, Q) with ∫σ = mass (``shifts``: each
        row's nodes moved, a moving frame: the mean and mode move with them, the covariance does not).

        One einsum (numpy's own loops, no BLAS): each row's value does not depend on K.
        """
        n = self.model.n
        K = sigma.shape[0]
        moments = np.einsum("kq,fq->kf", sigma, self._features) / mass[:, None]
        first = moments[:, :n]
        cov = np.empty((K, n, n))
        for p, (i, j) in enumerate(self._pairs):
            cov[:, i, j] = cov[:, j, i] = moments[:, n + p] - first[:, i] * first[:, j]
        mode = self.nodes[np.argmax(sigma, axis=1)] if K else np.empty((0, n))
        if shifts is not None:
            first, mode = first + shifts, mode + shifts
        return first, cov, mode

    # -- densities -----------------------------------------------------------------------
    def density(self, state: YauYauState, points: np.ndarray) -> np.ndarray:
        """Normalised conditional density at points (P, n).

        The truncated basis expansion can ripple below zero: negative values are clipped at 0 and
        the clipped density is renormalised over the ball (quadrature nodes).  Zero outside the ball.
        """
        basis = self.offline.evaluate_basis(points)  # validates points (InputError); 0 outside the ball
        values = np.clip(basis @ state.density_coefficients, 0.0, None)
        return values / self._clipped_mass(state)

    def nodal_density(self, state: YauYauState) -> np.ndarray:
        """The unnormalised density σ at the quadrature nodes (Q,) (what the mode search reads)."""
        return np.asarray(self.offline.basis) @ state.density_coefficients

    def _clipped_mass(self, state: YauYauState) -> float:
        nodal = np.clip(np.asarray(self.offline.basis) @ state.density_coefficients, 0.0, None)
        mass = float(self.weights @ nodal)
        if not mass > 0.0:
            raise InputError("state", "the density has no positive mass (degenerate state)")
        return mass

    def marginal(self, state: YauYauState, var_index: int, grid: np.ndarray,
                 resolution: int = 64) -> np.ndarray:
        """Marginal density of state variable ``var_index`` at the values ``grid`` (G,).

        The other coordinates are integrated out with the trapezoidal rule on ``resolution`` points
        per direction across the ball.  The map from coefficients to the marginal on a grid is linear:
        it is built once per (variable, grid, resolution) and kept (a few grids), so a quantile or a
        plot per step costs one (G, N) product.  Negative ripples of the expansion are clipped after
        integrating (in 1-D: pointwise, as :meth:`density`); normalised by the clipped mass on the ball.
        """
        n = self.model.n
        if not isinstance(var_index, (int, np.integer)) or not 0 <= var_index < n:
            raise InputError("var_index", f"must be an integer in [0, {n})")
        grid = np.asarray(grid, dtype=float)
        if grid.ndim != 1 or not np.all(np.isfinite(grid)):
            raise InputError("grid", "must be a 1-D list of finite numbers")
        operator = self._marginal_operator(int(var_index), grid, int(resolution))
        values = np.clip(operator @ state.density_coefficients, 0.0, None)
        return values / self._clipped_mass(state)

    def _marginal_operator(self, var_index: int, grid: np.ndarray, resolution: int) -> np.ndarray:
        key = (var_index, resolution, grid.tobytes())
        cache = self.__dict__.setdefault("_marginal_operators", {})
        if key in cache:
            return cache[key]
        n = self.model.n
        center, radius = self.model.center, self.model.half_widths
        basis = self.offline.evaluate_basis
        if n == 1:
            operator = basis(grid[:, None])
        else:
            N = np.asarray(self.offline.basis).shape[1]
            block = max(1, 4_000_000 // (resolution ** (n - 1) * N))
            parts = []
            for start in range(0, len(grid), block):
                part = grid[start:start + block]
                parts.append(marginal_by_quadrature(basis, n, var_index, part, center - radius,
                                                    center + radius, resolution))
            operator = np.concatenate(parts, axis=0)
        if len(cache) >= 8:
            cache.pop(next(iter(cache)))
        cache[key] = operator
        return operator


@dataclass(frozen=True, eq=False)
class _Prepared:
    """A chunk made ready for the hot loop (:meth:`YauYauFilter._prepare`)."""

    gaps: np.ndarray
    keys: np.ndarray
    terms: RowTerms
    log_factor: np.ndarray  # (K, Q) log e_k − top[k]
    top: np.ndarray  # (K,)
    top_before: np.ndarray
    impossible: np.ndarray
    missing: np.ndarray
    skip: np.ndarray  # rows that only predict
    gate: "_Gate | None"
    initial: np.ndarray  # [coefficients, ∫σ] in the loop's precision
    shifts: np.ndarray | None = None  # (K, n) each row's node shift in a moving frame (engine/frame.py)
    origin: np.ndarray | None = None  # the centre the shifts are from
    moving: Any = None  # solver/engine/recentring.py: a ball that moves inside the loop


class _Gate:
    """The outlier gate of one chunk (solver/measurement.py): per row the bound's bias and the
    threshold; ``correction`` the exact term from the predicted density; ``scores`` the gated rows."""

    def __init__(self, obs: Observation, terms: RowTerms, keys: np.ndarray, gaps: np.ndarray,
                 engine: YauYauFilter, shifts: np.ndarray | None = None):
        self.obs, self.keys, self.gaps, self.engine = obs, keys, gaps, engine
        self.shifts = shifts  # (K, n) in a moving frame: h at each row's moved nodes
        self.terms = terms
        self.bias = terms.bound_bias().tolist()
        self.threshold = terms.threshold.tolist()
        self.scores: dict[int, float] = {}  # gated row -> d²
        self.attempted: dict[int, float] = {}  # gated row -> log E_pred[e] of the rejected update

    def size(self, k: int) -> int:
        return int(self.keys[k]).bit_count()

    def floor_exponents(self, missing: np.ndarray, start: int = 0) -> np.ndarray:
        """(bias − threshold)/2 of the rows from ``start`` (``missing``: theirs), −inf where nothing is
        gated (a row without observation, the gate off for its size): log of :meth:`floors` but the top."""
        part = slice(start, start + len(missing))
        threshold = self.terms.threshold[part]
        with np.errstate(invalid="ignore"):
            exponent = 0.5 * (self.terms.bound_bias()[part] - threshold)
        exponent[np.asarray(missing) | ~np.isfinite(threshold)] = -np.inf
        return np.nan_to_num(exponent, nan=np.inf, posinf=np.inf, neginf=-np.inf)

    def floors(self, top: np.ndarray, missing: np.ndarray, start: int = 0) -> list[float]:
        """Per row, the ∫σ below which the cheap bound is over the threshold: exp((bias − threshold)/2
        − top) (0 where nothing is gated); ``top`` and ``missing`` of the rows from ``start`` on."""
        with np.errstate(over="ignore", invalid="ignore"):
            return np.exp(self.floor_exponents(missing, start) - top).tolist()

    def correction(self, k: int, s: np.ndarray, shift: np.ndarray | None = None) -> float:
        """log det(I + κ²S₀⁻¹C), C = Cov(h_o) under the propagated nodal density s (its nodes moved by
        ``shift``, or by the row's in a moving frame)."""
        key = int(self.keys[k])
        index = self.obs.pattern(key).index
        ws = self.engine.weights * np.asarray(s, dtype=float)
        total = float(ws.sum())
        if not total > 0.0:
            return 0.0
        if shift is None and self.shifts is not None:
            shift = self.shifts[k]
        h = (self.engine._h_nodes if shift is None else self.engine._h_shifted(shift[None])[0])[:, index]
        centred = h - (ws @ h) / total
        cov = (centred * ws[:, None]).T @ centred / total
        tau = float(self.gaps[k])
        return max(0.0, self.obs.covariance_correction(key, float(self.terms.kappa2[k]), cov,
                                                       self.obs.S0_scale(tau)))


# -- helpers ---------------------------------------------------------------------------------
def _moment_features(weights: np.ndarray, nodes: np.ndarray, pairs: list[tuple[int, int]]) -> np.ndarray:
    """Rows w·x_i (i < n), then w·x_i·x_j for the pairs i ≤ j: the moments as one product."""
    n = nodes.shape[1]
    return np.vstack([weights * nodes[:, i] for i in range(n)]
                     + [weights * nodes[:, i] * nodes[:, j] for i, j in pairs])


def _blocks(pieces: np.ndarray, limit: int) -> list[int]:
    """Ends of consecutive blocks of rows whose pieces add up to at most ``limit`` (at least one row)."""
    ends, total = [], 0
    for k, count in enumerate(pieces.tolist()):
        if total and total + count > limit:
            ends.append(k)
            total = 0
        total += count
    return ends + [len(pieces)]


def _with_zero_column(propagator: np.ndarray, dtype) -> np.ndarray:
    matrix = np.asarray(propagator, dtype=float)
    return np.asfortranarray(np.hstack([matrix, np.zeros((matrix.shape[0], 1))]), dtype=dtype)


def _stack_results(steps, times, mean, cov, mode, loglik, increments, last: Estimate, reason, **rows):
    """Pad the good steps' estimates with the last good one for the degenerate tail (``rows``: the
    ChunkResult's other per-row arrays, as they are)."""
    K, done = len(steps), len(loglik)
    if done < K:
        tail = K - done
        mean = np.concatenate([mean, np.repeat(last.mean[None], tail, axis=0)])
        cov = np.concatenate([cov, np.repeat(last.cov[None], tail, axis=0)])
        last_mode = last.mode if last.mode is not None else last.mean
        mode = np.concatenate([mode, np.repeat(last_mode[None], tail, axis=0)])
        loglik = np.concatenate([loglik, np.full(tail, last.loglik)])
        increments = np.concatenate([increments, np.zeros(tail)])
    degenerate = np.arange(K) >= done
    return ChunkResult(step=steps, t=times, mean=mean, cov=cov, mode=mode, loglik=loglik,
                       loglik_increment=increments, degenerate=degenerate, reason=reason, **rows)


def _override_model(model: Model, prior: Any) -> Model:
    """The model with another prior (validated like the spec's ``initial`` field)."""
    from ..model import compile_model
    from ..spec import spec_from_dict

    data = model.spec.model_dump(mode="json")
    data["initial"] = prior.model_dump(mode="json") if hasattr(prior, "model_dump") else prior
    return compile_model(spec_from_dict(data))


def _check_offline_shapes(nodes, weights, projector, offline, n: int) -> None:
    Q, N = len(weights), projector.shape[0]
    expected = {"nodes": (Q, n), "projector": (N, Q), "propagator_fp": (Q, N), "propagator_k": (Q, N),
                "basis": (Q, N)}
    for name, shape in expected.items():
        array = np.asarray(getattr(offline, name))
        if array.shape != shape:
            raise SpecError(f"offline.{name}", f"has shape {array.shape}, expected {shape}")
        if not np.all(np.isfinite(array)):
            raise SpecError(f"offline.{name}", "contains non-finite values")
    if not np.all(weights > 0):
        raise SpecError("offline.weights", "quadrature weights must be positive")


def build(model: Model, offline: Any, form: str = "stable", precision: str = "double",
          gate: float | None = None, **_: Any) -> YauYauFilter:
    """The registry's constructor (solver/registry.py); ``[domain] follow``: on a ball that follows the
    state (solver/engine/follow.py)."""
    engine = YauYauFilter(model, offline, form=form, precision=precision, gate=gate)
    if model.spec.domain.follow:
        from .follow import FollowingFilter

        return FollowingFilter(engine)
    return engine
