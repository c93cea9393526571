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
from functools import cached_property
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike

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
    check_first_gap,
    check_gate,
    check_rows,
    resolve_times,
)
from ..model import Model, compile_model
from ..registry import FORMS, PRECISIONS
from ..spec import DensityPrior, GaussianPrior, MixturePrior, spec_from_dict
from .batch import run_batch
from .diagnostics import Diagnostics
from .finish import Summary, Until, finish
from .fused import run_fused
from .gate import Gate, Prepared
from .kernel import (
    ARITHMETIC,
    blocks,
    moment_features,
    moments,
    stack_results,
    with_zero_column,
)
from .loops import loop_irregular, loop_moving, loop_regular, update_factors
from .pieces import row_pieces, run_in_pieces
from .recentring import Recentring
from .semigroup import SpectralFlow
from .state import YauYauState, state_from_dict
from .translated import TranslatedOffline

if TYPE_CHECKING:  # types only
    from ..offline.pipeline import OfflineArrays
    from .follow import FollowingFilter
    from .frame import AffineFrame

    # (follower, velocity, moves, irregular): a ball that moves inside the loop (engine/recentring.py)
    Follow = tuple[FollowingFilter, np.ndarray | None, list[tuple[int, np.ndarray]], bool]

_MIN_PRIOR_MASS = 0.5  # of a gaussian/mixture prior on the ball
MAX_CHUNK_PIECES = 8192  # pieces filtered at once (the rest of a chunk follows, block by block)


class YauYauFilter(ChunkedFilter):
    """The Yau–Yau filter on precomputed offline arrays (the :class:`solver.filtering.Filter` protocol).

    ``offline`` is any :class:`solver.offline.OfflineArrays` (nodes, weights, basis, projector, the two
    propagators, ``evaluate_basis``).  ``precision="single"`` runs the two matrix-vector products per
    step in float32 (speed-up: bench/results/engine.md; relative rounding ~1e-7 per step); the moments,
    log-likelihood and state stay in float64.
    """

    method = "yau-yau"

    def __init__(self, model: Model, offline: OfflineArrays, form: str = "stable", precision: str = "double",
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
        self.arith = arith = ARITHMETIC[precision]
        self.nodes = np.ascontiguousarray(offline.nodes, dtype=float)
        self.weights = np.ascontiguousarray(offline.weights, dtype=float)
        projector = np.asarray(offline.projector, dtype=float)
        self.N = projector.shape[0]
        _check_offline_shapes(self.nodes, self.weights, projector, offline, model.n)
        # Fortran order: gemv reads it without a copy.  The weights ride along as an extra row of
        # the projector, so one call gives the coefficients and the mass ∫σ; the propagators get a
        # zero column for it, so the next call takes that vector as it is (and 1/∫σ as its alpha).
        self.projection = np.asfortranarray(np.vstack([projector, self.weights]), dtype=arith.dtype)
        self.propagator = with_zero_column(offline.propagator_fp, arith.dtype)
        literal = form == "literal"
        self.observation_propagator = (with_zero_column(offline.propagator_k, arith.dtype) if literal
                                       else self.propagator)
        h_nodes = model.h(self.nodes)
        self.h_nodes = h_nodes  # (Q, m): the update factors of every kind (solver/measurement.py)
        self._pairs = [(i, j) for i in range(model.n) for j in range(i, model.n)]
        self._features = moment_features(self.weights, self.nodes, self._pairs)
        self.diagnostics = Diagnostics(model, self.nodes, self.weights, projector, offline, h_nodes)
        # solver/engine/frame.py: the ball rides ċ = Ac + b (set by framed())
        self.frame: AffineFrame | None = None

    def framed(self, frame: AffineFrame) -> "YauYauFilter":
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

    def h_shifted(self, shifts: np.ndarray) -> np.ndarray:
        """h at each row's moved nodes, (K, Q, m)."""
        K, (Q, n) = len(shifts), self.nodes.shape
        points = (self.nodes[None, :, :] + shifts[:, None, :]).reshape(K * Q, n)
        return np.asarray(self.model.h(points), dtype=float).reshape(K, Q, -1)

    def centred_at(self, center: ArrayLike) -> "YauYauFilter":
        """This engine on the ball translated to ``center`` (solver/engine/follow.py): the same basis,
        projector and propagators (shared, not copied), the observation and the moments at the
        translated nodes.  Right where the Fokker–Planck operator is invariant under the move (f does
        not depend on the coordinates that move); the caller checks that."""
        center = np.asarray(center, dtype=float)
        home = getattr(self.offline, "home", self.offline)
        shift = center - np.asarray(getattr(self.offline, "home_center", self.model.center), dtype=float)
        new = copy.copy(self)
        new.__dict__.pop("_marginal_operators", None)
        new.__dict__.pop("node_tree", None)  # the KD-tree of the old nodes
        new.__dict__.pop("_factor_cache", None)  # h R⁻¹ at the old nodes: the new ball's differ
        new.__dict__.setdefault("_flow_owner", self)
        new.model = self.model.translated(center)
        new.offline = TranslatedOffline(home, shift, center - shift)
        new.nodes = np.ascontiguousarray(home.nodes + shift, dtype=float)
        new.h_nodes = new.model.h(new.nodes)
        new._features = moment_features(self.weights, new.nodes, self._pairs)
        new.diagnostics = self.diagnostics.translated(new.h_nodes)
        return new

    # -- states ------------------------------------------------------------------------
    def initial_state(self, prior: Any | None = None) -> YauYauState:
        """σ(0) = σ0: the prior (the model's, or ``prior``, a spec prior or its dict) on the basis."""
        model = self.model if prior is None else self.prior_model(prior)
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
        projected = self.arith.gemv(1.0, self.projection, sigma.astype(self.arith.dtype))
        mean, cov, mode = self.moments(sigma[None, :], np.ones(1))
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

    def prior_model(self, prior: Any) -> Model:
        """The model with another prior (validated like the spec's ``initial`` field)."""
        data = self.model.spec.model_dump(mode="json")
        data["initial"] = prior.model_dump(mode="json") if hasattr(prior, "model_dump") else prior
        return compile_model(spec_from_dict(data))

    def ball_center(self, state: YauYauState) -> np.ndarray:
        """The centre of the ball the state's density lives on."""
        return self.model.center

    def state_from_dict(self, data: dict[str, Any]) -> YauYauState:
        """Inverse of :meth:`YauYauState.to_dict` (validated; bad fields raise InputError('state.…'))."""
        return state_from_dict(data, self.N, self.model.n, self.form, self.precision, len(self.nodes))

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
                            dtype=self.arith.dtype)

    def run_arrays(self, state: YauYauState, increments: np.ndarray,
                   times: np.ndarray | None = None) -> tuple[YauYauState, ChunkResult]:
        """Advance over a chunk (K, m) of rows at ``times`` (or one dt apart); estimates as arrays."""
        return self._chunk(state, increments, times)

    def smooth_arrays(self, state: YauYauState, increments: Any, times: Any = None, block: Any = None,
                      visit: Any = None):
        """Fixed-interval smoothing of a chunk: (state after, smoothed ChunkResult): engine/smoother.py."""
        from .smoother import smooth_arrays  # lazy: the filter alone never loads it
        return smooth_arrays(self, state, increments, times, block, visit)

    def smooth_following(self, follow: Any, *args: Any):  # FollowingFilter.smooth_arrays
        from .follow_smoother import smooth_following  # here: from follow.py it would be an import circle
        return smooth_following(follow, *args)

    def run_until(self, state: YauYauState, increments: np.ndarray, times: np.ndarray | None,
                  until: Until | None) -> tuple[YauYauState, ChunkResult]:
        """:meth:`run_arrays` for a ball that follows the state (solver/engine/follow.py): ``until(mean,
        centers)``, given the rows' means (K, n) and, in a moving frame, their centres (else None), is
        the number j ≥ 1 of rows to keep, or None for all.  The chunk then ends after row j − 1: the
        result has j rows and the new state is the one the hot loop carried there, bit for bit, as if
        the chunk had been j rows long.  Rows over long gaps (filtered in pieces) always run whole."""
        return self._chunk(state, increments, times, until=until)

    def run_moving(self, state: YauYauState, increments: np.ndarray, follower: FollowingFilter,
                   velocity: np.ndarray | None, moves: list[tuple[int, np.ndarray]],
                   times: np.ndarray | None = None) -> tuple[YauYauState, ChunkResult]:
        """Rows at ``times`` (None: one dt apart) on a ball that moves inside the loop (recentring.py;
        ``moves`` gets (row, new centre) per move): ``state.center`` is the ball's centre, the result has
        each row's, and the chunk may end early (after a row the loop could not move from: the caller
        re-centres)."""
        return self._chunk(state, increments, times, follow=(follower, velocity, moves, times is not None))

    def _chunk(self, state: YauYauState, increments: np.ndarray, times: np.ndarray | None = None,
               until: Until | None = None,
               follow: Follow | None = None) -> tuple[YauYauState, ChunkResult]:
        model, obs = self.model, self.observation
        rows = check_rows(increments, model.m, "observations" if obs.discrete else "increments")
        K = rows.shape[0]
        taus = resolve_times(state.t, state.step > 0, K, model.dt, times)
        check_first_gap(taus, obs.discrete)
        if K == 0:
            return state, stack_results(np.empty(0, int), np.empty(0), *self._empty_moments(), np.empty(0),
                                         np.empty(0), state.last, None)
        steps, times = chunk_clock(state, K, model.dt, times, taus)
        if self.form == "literal":
            self.check_literal(rows, taus)
        if state.degenerate:
            return self._stay_degenerate(state, steps, times, state.reason)
        pieces = row_pieces(self, rows, taus)
        if pieces is None:
            return self.run_rows(state, rows, steps, times, taus, gating=True, until=until, follow=follow)
        parts, start = [], 0
        for stop in blocks(pieces, MAX_CHUNK_PIECES):  # bounded memory: the pieces of a block at a time
            if state.degenerate:  # an earlier block degenerated: the rest stays so
                state, part = self._stay_degenerate(state, steps[start:], times[start:], state.reason)
                parts.append(part)
                break
            state, part = run_in_pieces(self, state, rows[start:stop], steps[start:stop], times[start:stop],
                                        taus[start:stop], pieces[start:stop])
            parts.append(part)
            start = stop
        return state, concat_results(parts)

    def run_batch(self, states: list[YauYauState], chunks: list[ArrayLike],
                  times: list[ArrayLike | None] | None = None,
                  return_exceptions: bool = False) -> list[tuple[YauYauState, ChunkResult] | InputError]:
        """Many states through their chunks together, one matrix–matrix product per step (engine/batch.py):
        [(new state, ChunkResult)] as ``run_arrays`` gives one by one, up to rounding."""
        return run_batch(self, states, chunks, times, return_exceptions)

    def run_rows(self, state: YauYauState, rows: np.ndarray, steps: np.ndarray, times: np.ndarray,
             taus: np.ndarray | None, gating: bool, until: Until | None = None,
             follow: Follow | None = None) -> tuple[YauYauState, ChunkResult]:
        """The chunk's rows through the hot loop (validated; ``taus`` None: regular rows), fused where
        it can be (solver/engine/fused.py)."""
        fused = None if until or follow else run_fused(self, state, rows, steps, times, taus, gating)
        if fused is not None:
            return fused
        ready = self.prepare(state, rows, taus, gating, follow)
        loop = self.propagate(ready.initial, ready.log_factor, ready.top, ready.skip.tolist(), ready.gate,
                              taus, ready.moving)
        return self.finish(state, rows, steps, times, taus, ready, *loop, until=until)

    def propagate(self, carried: np.ndarray, log_factor: np.ndarray, top: np.ndarray, skip: list[bool],
                  gate: Gate | None, taus: np.ndarray | None = None, moving: Recentring | None = None):
        """The hot loop of the chunk's kind (solver/engine/loops.py): (σ_k, ∫σ_k, carried, done, reason).
        ``carried`` is [coefficients, ∫σ] (N+1,); ``skip`` the rows that only predict."""
        if moving is not None:
            return loop_moving(self, carried, log_factor, top, skip, gate, moving, taus)
        factor = update_factors(self.arith, log_factor)
        if taus is not None:
            return loop_irregular(self, carried, factor, log_factor, top, skip, gate, taus)
        return loop_regular(self, carried, factor, log_factor, top, skip, gate)

    def finish(self, state: YauYauState, rows: np.ndarray, steps: np.ndarray, times: np.ndarray,
               taus: np.ndarray | None, ready: Prepared, sigma, masses, carried, done: int,
               reason: str | None, until: Until | None = None, summary: Summary | None = None):
        """The chunk's estimates, checks and new state from what the hot loop left
        (solver/engine/finish.py)."""
        return finish(self, state, rows, steps, times, taus, ready, sigma, masses, carried, done, reason,
                      until, summary)

    def prepare(self, state: YauYauState, rows: np.ndarray, taus: np.ndarray | None,
                 gating: bool, follow: Follow | None = None) -> Prepared:
        """What the hot loop needs of a chunk: the update factors, the gate, the carried vector (on a
        ball that moves in the loop, the factors come a window at a time: solver/engine/recentring.py)."""
        obs = self.observation
        gaps = np.full(len(rows), self.model.dt) if taus is None else taus
        moving, origin = None, None if self.frame is None else self.frame.origin
        if follow is None:
            shifts = self._shifts(state, gaps)
            keys, terms, log_factor, top, impossible = self.factors(rows, gaps, shifts)
        else:
            keys = obs.pattern_keys(~np.isnan(rows))
            terms = obs.row_terms(rows, gaps, keys)
            moving = Recentring(self, follow[0], state, rows, gaps, keys, terms, keys == 0, *follow[1:])
            log_factor, top, impossible = moving.log_factor, moving.top, moving.impossible
            shifts, origin = moving.shifts, moving.origin
        missing = keys == 0
        gate = Gate(obs, terms, keys, gaps, self, shifts) if obs.gating and gating else None
        skip = missing.copy()
        if gate is not None:  # rejected before the loop: no finite factor to weigh
            skip |= impossible
            gate.scores.update({int(k): math.inf for k in np.flatnonzero(impossible)})
        if moving is not None:  # its windows add their impossible rows to these
            moving.skip, moving.gate = skip, gate
        initial = np.append(state.coefficients, state.mass).astype(self.arith.dtype)
        # rescue may shift top[k]: the growth is relative to the factor's maximum
        top_before = top.copy() if moving is None else moving.top_before
        return Prepared(gaps, keys, terms, log_factor, top, top_before, impossible, missing, skip, gate,
                         initial, shifts, origin, moving)

    def factors(self, rows: np.ndarray, gaps: np.ndarray, shifts: np.ndarray | None = None):
        """Per row: the pattern key of its observed components, the row terms, log e_k at the nodes
        minus its maximum (returned apart, 0 on rows without a finite factor) and which observed rows
        have no finite factor at all (an overflow: impossible under the model).  ``shifts``: each
        row's nodes moved (a moving frame), h evaluated there."""
        obs = self.observation
        keys = obs.pattern_keys(~np.isnan(rows))
        missing = keys == 0
        terms = obs.row_terms(rows, gaps, keys)
        if shifts is None:
            h_points, cache = self.h_nodes, self._factor_cache
        else:
            h_points, cache = self.h_shifted(shifts), None
        log_factor = obs.log_factors(h_points, rows, gaps, keys, terms, cache,
                                     penalty=self.form != "literal")
        with np.errstate(invalid="ignore"):
            top = log_factor.max(axis=1)
        impossible = ~missing & ~np.isfinite(top)
        top[missing | impossible] = 0.0
        log_factor -= top[:, None]
        log_factor[missing | impossible] = 0.0
        return keys, terms, log_factor, top, impossible

    def check_literal(self, rows: np.ndarray, taus) -> None:
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

    def explained(self, sigma, state, rows, steps, missing, k: int, why: str, gaps, shifts=None) -> str:
        """``why`` the filter failed at row k, led by the outlier it met there, if it was one (in a
        moving frame, E[h] over that row's moved nodes)."""
        if missing[k]:
            return why
        before = sigma[k - 1] if k > 0 else np.asarray(self.offline.basis) @ state.density_coefficients
        h_nodes = None if shifts is None else self.h_shifted(shifts[k:k + 1])[0]
        return self.diagnostics.explain_outlier(before, rows[k], int(steps[k]), why, float(gaps[k]),
                                                 self.observation.discrete, h_nodes)

    def update_terms(self, key: int) -> tuple[np.ndarray, np.ndarray]:
        """h_o R_oo⁻¹ (|o|, Q) and ½h_oᵀR_oo⁻¹h_o (Q,) at the nodes for the pattern ``key``, cached."""
        return self.observation.point_terms(self.h_nodes, key, self._factor_cache)

    @cached_property
    def _factor_cache(self) -> dict:
        """Per pattern of observed components: h_o R_oo⁻¹ and ½h_oᵀR_oo⁻¹h_o at the nodes."""
        return {}

    def carried_after(self, sigma, masses, step: int, initial: np.ndarray, taus=None) -> np.ndarray:
        """[coefficients, ∫σ] as the hot loop carried them after row ``step`` − 1 (bit for bit), in the
        loop's coordinates (modal for irregular gaps)."""
        modal = taus is not None and not self.flow.exact
        if step == 0:
            if modal:
                initial = initial.copy()
                initial[: self.N] = self.flow.to_modal(initial[: self.N].astype(float))
            return initial
        project = self.flow.C if modal else self.projection
        carried = self.arith.gemv(1.0, project, sigma[step - 1])
        carried[self.N] = masses[step - 1]
        return carried

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
        result = stack_results(steps, times, *self._empty_moments(), np.empty(0), np.empty(0), last, reason,
                                **frame)
        return new_state, result

    def _empty_moments(self):
        n = self.model.n
        return np.empty((0, n)), np.empty((0, n, n)), np.empty((0, n))

    def moments(self, sigma: np.ndarray, mass: np.ndarray, shifts: np.ndarray | None = None):
        """Mean, covariance and mode of each row of nodal σ (K, Q) with ∫σ = mass (engine/kernel.py)."""
        return moments(sigma, mass, self._features, self._pairs, self.nodes, shifts)

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


def build(model: Model, offline: OfflineArrays, form: str = "stable", precision: str = "double",
          gate: float | None = None, **_: Any) -> YauYauFilter:
    """The registry's constructor (solver/registry.py); ``[domain] follow``: on a ball that follows the
    state (solver/engine/follow.py)."""
    engine = YauYauFilter(model, offline, form=form, precision=precision, gate=gate)
    if model.spec.domain.follow:
        from .follow import FollowingFilter  # lazy: a fixed ball never loads the following (scipy.sparse)

        return FollowingFilter(engine)
    return engine
