"""A ball that moves inside the engine's hot loop (``[domain] follow``, solver/engine/follow.py).

Between blocks, :class:`~solver.follow.FollowingFilter` re-centres B_R(c) on the posterior.  Every
block is one pass through the engine, whose fixed cost (the chunk's row terms, factors, moments,
checks: ~0.1–0.3 ms) is paid per block; a state that moves a mesh step every few dozen rows paid it
that often (1-D: 3× the fixed ball's cost per observation).  Where a move is a fixed map of the
coefficients — a shift-invariant drift and a move by whole mesh steps (:class:`~solver.engine.carry.Carry`)
— the loop itself re-centres:

* the projection that gives the coefficients and ∫σ_k also gives Σ_q w_q (x_q − c)_i σ_k(x_q) along
  the shift directions and the outer shell's mass (extra rows of the projector), so the trigger of
  solver/engine/follow.py (mean beyond ``follow_distance``·R, or ``follow_mass`` in the shell) costs a few
  comparisons a row;
* a move after row k carries the vector: σ = Φ a at the old nodes, the kept carry onto the new nodes,
  the projection (coefficients and ∫σ of the carried density, the state's new mass); the log-likelihood
  is not touched, as between blocks;
* the update factors e_k depend on the ball (h at its nodes): they are computed a window of rows at a
  time at the current centre, and again from the row after a move.

Each row's ball is the home ball shifted by ``shifts[k]`` (the moments read it as in a moving frame).
In a moving frame (solver/engine/frame.py) the centre also rides ċ = Ac + b between moves: a window computes
the frame's path over its rows (from the centre a move left, after one) and h at each row's nodes.
With an atlas (``[domain] region``) a move also switches to the new centre's stored propagator.
Irregular rows (gaps τ_k) run in the modal coordinates d = V⁻¹a of the ball's flow e^{τA}
(solver/engine/semigroup.py; an atlas centre's own generator): d scaled by e^{τ_kΛ}, then Φ V and the
projection [V⁻¹ΦᵀW; wᵀ; the trigger's rows]; a move evaluates Φ V d at the old nodes, carries it and
projects into the new ball's modal coordinates (:meth:`FollowingFilter.modal_at`).
What the loop cannot do — leave ``[domain] region``, a carry that leaves no mass, an observation
function not finite at the new nodes — ends the pass after that row (``stopped``); the block logic of
solver/engine/follow.py then re-centres or reports the degenerate reason.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:  # types only
    from ..measurement import RowTerms
    from .follow import FollowingFilter
    from .state import YauYauState

QUIET = 16  # rows without a new trigger after one whose snapped centre is the current one
FIRST_WINDOW = 64  # rows between moves assumed before a move is seen (the lead, the first window)
MIN_WINDOW, MAX_WINDOW = 16, 512
# a window's fixed cost (the calls around the factors: ~28 µs) in node-rows of factors (~3.5 ns each),
# measured in 1-D (Q = 99) and 2-D (Q = 633); see :meth:`Recentring.window`
WINDOW_NODE_ROWS = 8000.0


class Recentring:
    """One pass of the hot loop on a ball that moves (module docstring).  ``engine``: the home engine;
    ``follower``: the :class:`~solver.follow.FollowingFilter`; the arrays of the chunk's rows;
    ``velocity``: the mean's drift per row so far (None: not known; no lead in a moving frame);
    ``moves``: a list that gets (row, new centre) for every move after a row."""

    def __init__(self, engine: Any, follower: FollowingFilter, state: YauYauState, rows: np.ndarray,
                 gaps: np.ndarray, keys: np.ndarray, terms: RowTerms, missing: np.ndarray,
                 velocity: np.ndarray | None, moves: list[tuple[int, np.ndarray]], irregular: bool = False):
        self.engine, self.follower, self.frame = engine, follower, engine.frame
        self.rows, self.gaps, self.keys, self.terms, self.missing = rows, gaps, keys, terms, missing
        K, Q = len(rows), len(engine.nodes)
        self.dtype = engine.arith.dtype
        self.log_factor = np.zeros((K, Q))
        self.factor = np.empty((K, Q), dtype=self.dtype)
        self.top, self.top_before = np.zeros(K), np.zeros(K)
        self.impossible = np.zeros(K, dtype=bool)
        self.origin = np.asarray(follower.home_center, dtype=float)
        center = np.array(state.center, dtype=float)  # the ball's (a frame's: where its path starts)
        self.shifts = np.repeat((center - self.origin)[None, :], K, axis=0)  # row k: origin + shifts[k]
        self.path_from: np.ndarray | None = center  # a frame's path is computed from here next
        self.project, self.basis = follower.watch_arrays(self.dtype)
        self.along = list(follower.directions)
        self.d = len(self.along)
        self.reach, self.shell_limit = follower.distance, follower.mass_limit
        self.velocity = [0.0] * self.d if velocity is None else [float(v) for v in velocity]
        self.moved = moves
        self.pace = float(FIRST_WINDOW)  # rows between moves (an average)
        self.window_cost = WINDOW_NODE_ROWS / Q  # a window's fixed cost in rows of factors
        self.last_move: tuple[int, list] | None = None  # row and mean (shift directions) of the last move
        self.stopped: int | None = None  # rows done when the loop ended before the chunk's end
        self.quiet = 0
        self.observed: list[bool] = []
        self.floors: list[float] = []
        self.skip = missing
        self.gate = None
        self.h, self.cache = follower.h_at(center)
        self.predict = follower.propagator_at(center)  # an atlas centre's (None: the engine's)
        self.flow = None  # irregular rows: the ball's modal flow, its coordinates the carried vector's
        if irregular:
            self.flow, self.project = follower.modal_at(center, self.dtype)
            self.basis = self.flow.B

    def matrices(self) -> tuple[np.ndarray, np.ndarray]:
        """The loop's (P, P of observed rows) on the current ball: the modal flow's ΦV (irregular rows,
        scaled by e^{τΛ} before each row), an atlas centre's propagator, or the engine's."""
        if self.flow is not None:
            return self.flow.B, self.flow.B
        if self.predict is not None:
            return self.predict, self.predict
        return self.engine.propagator, self.engine.observation_propagator

    # -- the update factors ---------------------------------------------------------------------
    def window(self, start: int) -> int:
        """The update factors of rows from ``start`` at the current centre, as the engine's
        ``_prepare`` computes them for a whole chunk; the row where the next window starts (−1: none)."""
        K = len(self.rows)
        stop = min(K, start + self.window_rows(start))
        engine, obs = self.engine, self.engine.observation
        part = slice(start, stop)
        h, cache = self.h, self.cache
        if self.frame is not None:  # the frame's centres over the window, h at each row's nodes
            begin = self.origin + self.shifts[start - 1] if self.path_from is None else self.path_from
            self.shifts[start:stop] = self.frame.path(begin, self.gaps[part]) - self.origin
            self.shifts[stop:] = self.shifts[stop - 1]  # beyond the rows run: where the frame stopped
            self.path_from = None
            h, cache = engine.h_shifted(self.shifts[part]), None
        log_factor = obs.log_factors(h, self.rows[part], self.gaps[part], self.keys[part],
                                     self.terms.rows(start, stop, self.keys), cache,
                                     penalty=engine.form != "literal", out=self.log_factor[part])
        missing = self.missing[part]
        top = log_factor.max(axis=1)
        if missing.any() or not np.isfinite(top).all():
            impossible = ~missing & ~np.isfinite(top)
            top[missing | impossible] = 0.0
            log_factor -= top[:, None]
            log_factor[missing | impossible] = 0.0
            self.impossible[part] = impossible
        else:
            impossible = None
            log_factor -= top[:, None]
        self.top[part], self.top_before[part] = top, top  # (log_factor is the view self.log_factor[part])
        factor = self.factor[part]
        if factor.dtype == log_factor.dtype:
            np.exp(log_factor, out=factor)
        else:
            factor[...] = np.exp(log_factor)
        factor[factor < engine.arith.negligible] = 0.0
        if self.gate is not None:
            if start == 0:  # the gate's floors but for the factor's top, once a chunk
                self._floor = self.gate.floor_exponents(self.missing)
            with np.errstate(over="ignore"):
                self.floors[part] = np.exp(self._floor[part] - top).tolist()
            for k in [] if impossible is None else (start + np.flatnonzero(impossible)).tolist():
                self.skip[k], self.observed[k] = True, False  # rejected before the loop reaches them
                self.gate.scores[k] = np.inf
        return stop if stop < K else -1

    def window_rows(self, start: int) -> int:
        """Rows of the window from ``start``.  Rows computed beyond the next move are wasted; a window
        ending before it costs another window's fixed part, c rows' worth of factors.  With T the rows
        expected to the next move (the pace of moves, or the rows since the last one when longer:
        the state has been slow), windows of W rows cost about c·T/W + W/2 rows: least at W = √(2cT)."""
        since = start - (0 if self.last_move is None else self.last_move[0])
        expected = max(self.pace, float(since))
        return int(min(MAX_WINDOW, max(MIN_WINDOW, np.sqrt(2.0 * self.window_cost * expected))))

    # -- a move ------------------------------------------------------------------------------------
    def move(self, k: int, carried: np.ndarray, following: np.ndarray, mass: float) -> float | None:
        """Re-centre after row k: ``following`` gets the carried vector; its ∫σ (0.0: no move, the
        snapped centre is the current one; None: the loop must stop after row k).

        The bookkeeping (the mean, its velocity, the lead, the new centre's lattice steps) is done in
        Python floats: it is a handful of numbers, which numpy handles at a microsecond a call (so in
        single precision the mean is read in double, as the block path reads it)."""
        N1 = self.engine.N + 1
        follower = self.follower
        center = self.origin + self.shifts[k]  # row k's ball
        at = center.tolist()
        mean = [at[i] + carried.item(N1 + j) / mass for j, i in enumerate(self.along)]
        if follower.model.shape is not None:  # the loop's rows read the mean in the ball's coordinates z
            mean = (center + follower.model.shaped(np.array(mean) - center)).tolist()
        if follower.region is not None:
            point = center.copy()
            point[self.along] = mean
            if follower.left_region(point):
                return None
        if self.last_move is not None and self.frame is None:  # (in a frame: relative to it, no lead)
            row, before = self.last_move
            rows = max(1, k - row)
            self.velocity = [0.5 * (v + (m - b) / rows)
                             for v, m, b in zip(self.velocity, mean, before, strict=True)]
            self.pace = 0.5 * (self.pace + rows)
        self.last_move = (k, mean)
        half = 0.5 * self.reach  # led by half the travel to the next move, at most half the trigger distance
        ahead = [m + min(max(0.5 * v * self.pace, -half), half)
                 for m, v in zip(mean, self.velocity, strict=True)]
        target = self._target(center, ahead)
        if target is None:
            self.quiet = k + QUIET
            return 0.0
        carry = follower.carry(target - center)
        if carry is None:
            return None
        # (in a frame, self.h is not h at row k's nodes: the window evaluates h along the frame's path)
        h, cache = follower.h_at(target) if self.frame is not None else follower.h_at(target, carry, self.h)
        if not np.all(np.isfinite(h)):
            return None
        predict = follower.propagator_at(target) if self.flow is None else None
        modal = None if self.flow is None else follower.modal_at(target, self.dtype)
        if self.flow is not None and modal is None:  # not a modal flow there: the rows go on in blocks
            return None
        arith = self.engine.arith
        nodal = arith.gemv(1.0, self.basis, carried)  # (irregular rows: Φ V d = Φ a)
        moved = carry.apply(nodal).astype(self.dtype, copy=False)
        project = self.project if modal is None else modal[1]  # (into the new ball's modal coordinates)
        arith.gemv(1.0, project, moved, 0.0, following, 0, 1, 0, 1, 0, 1)
        new_mass = following.item(self.engine.N)
        if not arith.tiny < new_mass < arith.huge:
            return None
        self.h, self.cache, self.predict = h, cache, predict
        if modal is not None:
            self.flow, self.project, self.basis = modal[0], modal[1], modal[0].B
        if self.frame is None:
            self.shifts[k + 1:] = target - self.origin
        else:  # the window from row k + 1 computes the path from here
            self.path_from = target
        self.moved.append((k, target))
        return new_mass

    def _target(self, center: np.ndarray, ahead: list[float]) -> np.ndarray | None:
        """The centre a move from ``center`` goes to for the lead point ``ahead`` (along the shift
        directions), :meth:`~solver.follow.FollowingFilter.snapped`; None: the current one."""
        point = center.copy()
        point[self.along] = ahead
        target = self.follower.snapped(center, point)
        return None if np.array_equal(target, center) else target
