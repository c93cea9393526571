"""A domain that follows the state: the ball B_R(c) re-centred on the posterior (``[domain] follow``).

The offline stage solves the Fokker–Planck equation on one ball B_R(c₀).  A state that travels (a
random walk with a trend, the position of a tracked target) leaves any fixed ball; Luo and Yau
(IEEE TAC 58(10), 2013, "Hermite spectral method to 1-D forward Kolmogorov equation and its
application to nonlinear filtering problems") move the window with the density.  Here the
offline/online split survives the move because the operator does:

    L u = ½ a:∇²u − div(f u)   is invariant under x ↦ x + s   when ∂f/∂x_i ≡ 0 for every i with s_i ≠ 0

(:attr:`Model.shift_directions`, checked symbolically with SymPy).  Then e^{dt L} on B_R(c₀ + s) is
e^{dt L} on B_R(c₀) translated: one stored propagator serves every centre, and a centred engine
(:meth:`YauYauFilter.centred_at`) only evaluates h and the moments at the translated nodes.  The
literal form's Kolmogorov operator L − ½hᵀR⁻¹h is not invariant (h moves with x): follow runs the
stable form.

Online, a chunk runs in blocks (:class:`FollowingFilter`).  After a block the ball is re-centred when

* the mean is more than ``follow_distance``·R from c along a shift direction, or
* more than ``follow_mass`` of ∫σ lies in the ball's outer tenth (|x − c| > 0.9 R),

onto c' = c with the shift coordinates replaced by the mean's (rounded to whole elements in 1-D, to
whole steps of the 2-D lattice mesh, so the new nodes are old nodes and the carry is exact where the
balls overlap).  The carry is the
issue's: evaluate the old expansion at the new nodes, zero outside the old ball, project onto the
basis.  ∫σ of the carried density becomes the state's mass, so the next step renormalises by it;
the log-likelihood is not touched by a move (it is the sum of the steps' log ∫σ_k/∫σ_(k−1), none of
which the move changes).  The mass the move leaves outside the new ball is measured and reported.
A move by whole mesh steps is the same map wherever the ball is (every ball is the home ball
translated), so it is built once per offset and kept (:class:`Carry`).  A block ends in the engine
before a row whose mean strays beyond ``follow_distance`` + 0.1 of R (one that degenerates runs again,
shorter), so a fast state is caught before it reaches the wall.

Where every move is a kept carry (a mesh with steps: ``moves_in_loop``), the engine's loop applies the
same trigger and carry after any row (solver/engine/recentring.py; with an atlas it also switches to the
new centre's propagator, or for irregular rows its modal flow): a block's fixed cost is then paid once per
chunk instead of once per move.  Irregular rows do so where the flow is modal and no gap is filtered in
pieces, outside a moving frame; else they run in blocks.
"""

from __future__ import annotations

import dataclasses
from collections import OrderedDict
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike, DTypeLike

from ..errors import InputError, SpecError
from ..filtering import ChunkedFilter, ChunkResult, Estimate, concat_results, run_batch_alone
from ..measurement import check_rows
from .atlas import kept, move_step, needs_atlas
from .carry import Carry, carried_at, unshaped_points
from .frame import affine_frame
from .kernel import with_zero_column

if TYPE_CHECKING:  # types only
    from ..model import Model
    from .state import YauYauState

SHELL = 0.9  # |x − c| > SHELL·R is the outer shell whose mass the trigger reads
STRAY = 0.1  # of R beyond follow_distance: a block whose mean strays further runs again, shorter
FIRST_BLOCK = 32  # rows of the first block of a chunk; later blocks adapt to the mean's speed
MIN_BLOCK, MAX_BLOCK = 4, 512
CACHE = 16  # centred engines kept (each shares the stored arrays; owns h and moments at its nodes)
CARRIES = 64  # carries kept, one per move offset in mesh steps (index arrays and a few interpolated rows)
# The carries of every offset a move usually takes are built with the filter (FollowingFilter._table):
# a move goes to the lead point, at most the stray limit (follow_distance + STRAY)·R from the centre plus
# the lead's ½·follow_distance·R along each axis; offsets within that length (Euclidean) are tabled.
LEAD = 0.5


def check_follow(model: Model, form: str = "stable") -> tuple[int, ...]:
    """The directions the ball may move along (every one with ``[domain] region``: an atlas,
    solver/engine/atlas.py); SpecError when follow cannot apply."""
    directions = model.shift_directions
    if model.spec.domain.region is not None or affine_frame(model) is not None:
        directions = tuple(range(model.n))  # an atlas, or a frame moving with ċ = Ac + b (engine/frame.py)
    if not directions:
        raise SpecError("domain.follow", "the drift depends on every state variable and is not affine, so "
                                         "the Fokker-Planck operator changes when the ball moves and one "
                                         "stored propagator cannot serve a moved ball; declare where the "
                                         "state may go, "
                                         "domain.region = [[lo, hi], ...] (one pair per state variable), for "
                                         "an atlas of propagators, or leave follow out (and size "
                                         "domain.radius for the whole path)")
    if form != "stable":
        raise SpecError("form", "a following ball needs the stable form (the literal form's Kolmogorov "
                                "operator contains h, which does not move with the ball)")
    return directions


class FollowingFilter(ChunkedFilter):
    """The Yau–Yau engine on a ball that follows the posterior (module docstring).  Its state is the
    engine's with ``center`` set; results carry the centre after every row (``ChunkResult.center``)."""

    method = "yau-yau"
    follows = True

    def __init__(self, engine: Any):  # YauYauFilter (engine/filter.py imports this module)
        self.home = engine
        self.model = engine.model
        self.directions = check_follow(engine.model, engine.form)
        domain = engine.model.spec.domain
        self.radius = float(domain.radius)
        self.distance = float(domain.follow_distance) * self.radius
        self.stray = (float(domain.follow_distance) + STRAY) * self.radius
        self.mass_limit = float(domain.follow_mass)
        self.home_center = np.asarray(engine.model.center, dtype=float)
        # on an ellipsoid ([domain] shape, x = c + Lz) the lattice and every distance are the ball's, in z
        if engine.model.shape is not None and len(self.directions) < engine.model.n:
            raise SpecError("domain.shape", "a following ellipsoid moves along every coordinate, but the "
                                            "drift depends on some (neither shift-invariant nor affine): "
                                            "leave shape out")
        points = unshaped_points(engine.model, getattr(engine.offline, "mesh_points", None))
        self._lattice = move_step(points, engine.model.n, engine.model.center, engine.model.radius)
        self._engines: OrderedDict[tuple, Any] = OrderedDict()
        self.region = None if domain.region is None else np.asarray(domain.region, dtype=float)
        self.atlas = getattr(engine.offline, "atlas", None)  # solver/engine/atlas.py: a propagator per centre
        self._bases: OrderedDict[int, Any] = OrderedDict()
        self._predicts: OrderedDict[int, np.ndarray] = OrderedDict()  # an atlas centre's, for the loop
        self._modal: OrderedDict[tuple, Any] = OrderedDict()  # a centre's modal flow, for irregular rows
        if self.atlas is None and needs_atlas(engine.model):
            raise SpecError("domain.region", "these offline arrays have no atlas (the region was added after "
                                             "they were solved): precompute the spec again")
        self._shell = engine.model.ball_distance(engine.nodes - self.home_center) > SHELL * self.radius
        self.frame = affine_frame(engine.model) if self.atlas is None else None
        self._framed: OrderedDict[float | None, Any] = OrderedDict()
        self._carries: OrderedDict[tuple, Carry] = OrderedDict()
        self._table = self._carry_table() if self._lattice else {}
        # moves inside the engine's loop (engine/recentring.py): a kept carry for every move by whole steps
        self.moves_in_loop = bool(self._lattice)
        self._watch: dict[DTypeLike, tuple[np.ndarray, np.ndarray]] = {}
        self._h: OrderedDict[tuple, tuple[np.ndarray, dict]] = OrderedDict()

    def runner(self, center: np.ndarray) -> Any:
        """The engine that runs a block from ``center``: the centred engine, or in a moving frame
        (solver/engine/frame.py) the one engine whose nodes move every step."""
        if self.frame is None:
            return self.engine(center)

        def make():
            found = self.home.framed(self.frame)
            found.gate_override = self.gate_override
            return found

        return kept(self._framed, self.gate_override, make, 4)

    def smooth_arrays(self, state: YauYauState, increments: Any, times: Any = None, block: Any = None,
                      visit: Any = None):
        """Fixed-interval smoothing over the same sequence of balls (solver/engine/follow_smoother.py)."""
        return self.home.smooth_following(self, state, increments, times, block, visit)

    def __getattr__(self, name: str) -> Any:  # offline, nodes, weights, N, form, precision, flow...
        if name.startswith("__") or name == "home":
            raise AttributeError(name)
        return getattr(self.home, name)

    # -- the engine at a centre ------------------------------------------------------------------
    def engine(self, center: np.ndarray) -> Any:
        """The centred engine (kept, a few at a time) with this filter's gate."""
        def make():
            base = self.home if self.atlas is None else self._atlas_engine(self.atlas.lattice.index(center))
            found = base.centred_at(center)
            found.gate_override = self.gate_override
            return found

        return kept(self._engines, (tuple(float(c) for c in center), self.gate_override), make, CACHE)

    def _atlas_engine(self, k: int) -> Any:
        """The engine on the ball of atlas centre k (its own propagator; kept a few at a time)."""
        def make():
            offline = self.atlas.offline(k)
            return type(self.home)(offline.model, offline, form=self.home.form, precision=self.home.precision)

        return kept(self._bases, k, make, CACHE)

    def ball_center(self, state: YauYauState) -> np.ndarray:
        return np.asarray(state.center, dtype=float)

    def snapped(self, center: np.ndarray, target: np.ndarray) -> np.ndarray:
        """``center`` with the shift coordinates moved to ``target``'s, on the mesh's step (move_step)."""
        new = np.array(center, dtype=float)
        axes = () if self.atlas is None else self.atlas.lattice.axes
        # whole steps from the home centre; in a moving frame (any centre) from the current one
        base = self.home_center if self.frame is None else new.copy()
        if self.model.shape is not None:  # an ellipsoid: whole steps of its lattice, L·s·(integers)
            offset = self.model.unshaped(np.asarray(target, dtype=float) - base)
            if self._lattice:
                offset = np.round(offset / self._lattice) * self._lattice
            return base + self.model.shaped(offset)
        for i in self.directions:
            offset = float(target[i]) - base[i]
            if self._lattice and i not in axes:
                offset = round(offset / self._lattice) * self._lattice
            new[i] = base[i] + offset
        return new if self.atlas is None else self.atlas.lattice.nearest(new)

    def left_region(self, point: np.ndarray) -> str | None:
        """Why ``point`` is beyond ``[domain] region`` (None: inside, or no region)."""
        if self.region is None or not np.any((point < self.region[:, 0]) | (point > self.region[:, 1])):
            return None
        bounds = ", ".join(f"[{lo:g}, {hi:g}]" for lo, hi in self.region)
        return (f"the posterior mean {_point(point)} left domain.region ({bounds}), where the state was "
                "declared to stay (and where an atlas of propagators ends): widen the region and precompute "
                "again")

    # -- states ---------------------------------------------------------------------------------------
    def initial_state(self, prior: Any | None = None) -> YauYauState:
        """The prior on the ball centred at its mean along the shift directions."""
        start = self.home_center
        mean = _prior_mean(self.home, prior)
        if mean is not None:
            outside = self.left_region(mean)
            if outside:
                raise SpecError("initial" if prior is None else "prior", outside.replace(
                    "the posterior mean", "the prior mean").replace("left", "lies outside"))
            start = self.snapped(self.home_center, mean)
        state = self.engine(start).initial_state(prior)
        return dataclasses.replace(state, center=start)

    def state_from_dict(self, data: dict[str, Any]) -> YauYauState:
        state = self.home.state_from_dict(data)
        center = data.get("center")
        try:
            center = np.array(center, dtype=float)
        except (TypeError, ValueError):
            center = None
        if center is None or center.shape != (self.model.n,) or not np.all(np.isfinite(center)):
            raise InputError("state.center", f"must be {self.model.n} finite numbers (the ball's centre)")
        if self.atlas is not None and not np.allclose(self.atlas.lattice.nearest(center), center,
                                                      rtol=0, atol=1e-9 * (1 + float(np.abs(center).max()))):
            raise InputError("state.center", f"{_point(center)} is not a centre of this model's atlas")
        return dataclasses.replace(state, center=center)

    def estimate(self, state: YauYauState) -> Estimate:
        return self.home.estimate(state)

    def density(self, state: YauYauState, points: np.ndarray) -> np.ndarray:
        return self.engine(state.center).density(state, points)

    def centred(self, state: YauYauState) -> Any:
        """The engine of the ball where ``state`` is: its ``nodes`` are those of ``nodal_density``."""
        return self.engine(state.center)

    def nodal_density(self, state: YauYauState) -> np.ndarray:
        return self.centred(state).nodal_density(state)

    def marginal(self, state: YauYauState, var_index: int, grid: np.ndarray,
                 resolution: int = 64) -> np.ndarray:
        return self.engine(state.center).marginal(state, var_index, grid, resolution)

    # -- stepping -------------------------------------------------------------------------------------
    def run_arrays(self, state: YauYauState, increments: np.ndarray,
                   times: ArrayLike | None = None) -> tuple[YauYauState, ChunkResult]:
        """The chunk in blocks, re-centring between them (module docstring)."""
        rows = check_rows(increments, self.model.m,
                          "observations" if self.observation.discrete else "increments")
        K, taus = len(rows), None
        if times is not None:
            from ..measurement import check_first_gap, resolve_times

            taus = resolve_times(state.t, state.step > 0, K, self.model.dt, times)
            check_first_gap(taus, self.observation.discrete)
            times = np.asarray(times, dtype=float)
        if K == 0 or state.degenerate:
            new, result = self.runner(state.center).run_arrays(state, rows, times)
            return self._placed(new, state.center), _with_centers(result, state.center)
        if self.moves_in_loop and (taus is None or self._irregular_in_loop(state, rows, taus)):
            return self._run_moving(state, rows, times)
        return self._run_blocks(state, rows, times)

    def _irregular_in_loop(self, state: YauYauState, rows: np.ndarray, taus: np.ndarray) -> bool:
        """Whether irregular rows move the ball inside the loop: the modal flow at the ball's centre, no
        moving frame, no gap long enough to be filtered in pieces (solver/engine/pieces.py)."""
        from .pieces import row_pieces

        return (self.frame is None and row_pieces(self.home, rows, taus) is None
                and self.modal_at(state.center, self.home.arith.dtype) is not None)

    def _run_blocks(self, state: YauYauState, rows: np.ndarray,
                    times: np.ndarray | None) -> tuple[YauYauState, ChunkResult]:
        """The chunk in blocks of the centred engine, re-centring between them (module docstring)."""
        K = len(rows)
        parts, start, block, velocity, jitter = [], 0, FIRST_BLOCK, None, 0.0
        along = list(self.directions)
        while start < K:
            stop = min(K, start + block)
            center = np.asarray(state.center, dtype=float)
            new, part = self.runner(center).run_until(state, rows[start:stop],
                                                      None if times is None else times[start:stop],
                                                      self._keep_until(center))
            stop = start + len(part.step)  # the engine ends the block before a row that strays
            # (K, n) in a moving frame (an engine that only stayed degenerate gives none: the centre stays)
            centers = center if self.frame is None or part.center is None else part.center
            stray = self._strayed(part.mean, centers)
            if (stray is not None or new.degenerate) and stop - start > 1:
                # again from the block's start: up to the row before the stray one (or half the block)
                block = max(1, stray if stray else (stop - start) // 2)
                continue
            length = stop - start
            offsets = part.mean - centers  # the mean relative to the ball (whose centre may ride a frame)
            drift = (offsets[-1, along] - (state.last.mean - center)[along]) / length  # per row
            velocity = drift if velocity is None else 0.5 * (velocity + drift)
            if length > 1:  # the mean's random part: its mean square move per row, drift removed
                steps = np.diff(offsets[:, along], axis=0)
                jitter = float(np.max(np.mean((steps - steps.mean(axis=0)) ** 2, axis=0)))
            state = self._placed(new, center)
            block = self._block_for(velocity, jitter)
            center = self.ball_center(state)  # the frame's centre at the block's end
            if not state.degenerate:
                # the travel looked ahead to is this chunk's next block only (none after its last row:
                # the next chunk starts afresh), so a stream of short chunks does not move on noise
                state = self._maybe_recentre(state, velocity * min(block, K - stop))
                if state.degenerate:  # the move failed, or the mean left the region: flag its row
                    part = _flagged(part, len(part.degenerate) - 1, state.reason)
            parts.append(_with_centers(part, center, state.center))
            start = stop
            if state.degenerate and start < K:  # the rest stays degenerate
                state = self._stay(state, rows[start:], None if times is None else times[start:], parts)
                break
        return state, concat_results(parts)

    def _run_moving(self, state: YauYauState, rows: np.ndarray,
                    times: np.ndarray | None = None) -> tuple[YauYauState, ChunkResult]:
        """The chunk through the loop of the home engine (or the frame's), which re-centres the ball itself
        (solver/engine/recentring.py); between passes (where the loop could not move on) the block logic's
        re-centre, or its degenerate reason.  Irregular rows (``times``) from a centre whose flow is not
        modal go on in blocks."""
        parts, start, K, velocity = [], 0, len(rows), None
        along = list(self.directions)
        while start < K:
            if times is not None and not state.degenerate \
                    and self.modal_at(state.center, self.home.arith.dtype) is None:
                state, part = self._run_blocks(state, rows[start:], times[start:])
                parts.append(part)
                break
            before, moves = state.last.mean[along], []
            engine = self.home if self.frame is None else self.runner(state.center)  # nodes at home
            new, part = engine.run_moving(state, rows[start:], self, velocity, moves,
                                          None if times is None else times[start:])
            length = len(part.mean)  # rows with estimates (fewer when it degenerated)
            if length and self.frame is None:  # (in a frame the loop leads by nothing)
                drift = (part.mean[-1, along] - before) / length  # per row
                velocity = drift if velocity is None else 0.5 * (velocity + drift)
            state = new
            centers = np.array(part.center, dtype=float)  # each row's ball, then where a move took it
            moved = np.zeros(len(centers), dtype=bool)
            for k, target in moves:
                centers[k], moved[k] = target, True
            end = np.asarray(state.center, dtype=float)
            if not state.degenerate:
                state = self._maybe_recentre(state, np.zeros(len(along)))
                if state.degenerate:  # the move failed, or the mean left the region: flag its row
                    part = _flagged(part, length - 1, state.reason)
                elif not np.array_equal(state.center, end):
                    centers[-1], moved[-1] = state.center, True
            parts.append(dataclasses.replace(part, center=centers, recentred=moved))
            start += len(part.step)
            if state.degenerate and start < K:  # the rest stays degenerate
                state = self._stay(state, rows[start:], None if times is None else times[start:], parts)
                break
        return state, concat_results(parts)

    def _stay(self, state: YauYauState, rows: np.ndarray, times: np.ndarray | None,
              parts: list[ChunkResult]) -> YauYauState:
        """A degenerate state through the rest of the chunk (its result appended to ``parts``)."""
        new, part = self.runner(state.center).run_arrays(state, rows, times)
        parts.append(_with_centers(part, state.center))
        return self._placed(new, state.center)

    def propagator_at(self, center: np.ndarray) -> np.ndarray | None:
        """With an atlas, the stored propagator (with the engine's zero column) of the lattice centre
        ``center`` is at; None without one (every ball shares the home propagator).  Only that matrix
        is made (a loop's move needs nothing else of the centre's engine) and kept a few at a time."""
        if self.atlas is None:
            return None
        k = self.atlas.lattice.index(center)

        def make():
            engine = self._bases.get(k)  # the centre's engine, where the block path built it: its matrix
            if engine is not None:
                return engine.propagator
            return with_zero_column(self.atlas.offline(k).propagator_fp, self.home.arith.dtype)

        return kept(self._predicts, k, make, CACHE)

    def modal_at(self, center: np.ndarray, dtype: DTypeLike) -> tuple[Any, np.ndarray] | None:
        """For irregular rows moving in the loop: the flow e^{τA} of the ball at ``center`` (an atlas
        centre's generator, else the home one: solver/engine/semigroup.py) and the loop's projection in
        its modal coordinates, [V⁻¹ΦᵀW; wᵀ; the trigger's rows of :meth:`watch_arrays`]; None where
        that flow is not modal (the Schur form, expm)."""
        key = (None if self.atlas is None else self.atlas.lattice.index(center), np.dtype(dtype).str)

        def make():
            flow = (self.home if key[0] is None else self._atlas_engine(key[0])).flow
            if flow.form != "modal":
                return None
            watch = self.watch_arrays(dtype)[0][self.home.N + 1:]
            return flow, np.asfortranarray(np.vstack([flow.C, watch]), dtype=dtype)

        return kept(self._modal, key, make, CACHE)

    def h_at(self, center: np.ndarray, carry: "Carry | None" = None,
             before: np.ndarray | None = None) -> tuple[np.ndarray, dict]:
        """h at the nodes of the ball around ``center`` (Q, m) and a factor cache for them (kept a few
        at a time: what a centred engine holds for the update factors, without the rest of it).  With
        the ``carry`` that moved the ball there and h at the old ball's nodes (``before``), h is read
        off where a new node is an old one and evaluated only at the others (a move shares most
        nodes)."""
        def make():
            nodes = self.home.nodes + (center - self.home_center)
            if carry is None or before is None:
                return np.asarray(self.model.h(nodes), dtype=float), {}
            h = np.empty_like(before)
            h[carry.matched] = before[carry.source]
            h[carry.others] = np.asarray(self.model.h(nodes[carry.others]), dtype=float).reshape(
                -1, h.shape[1])
            return h, {}

        return kept(self._h, tuple(float(c) for c in center), make, CACHE)

    def watch_arrays(self, dtype: DTypeLike) -> tuple[np.ndarray, np.ndarray]:
        """For a loop that moves the ball (solver/engine/recentring.py), in the loop's precision: the home
        engine's projector with the trigger's rows w·(x − c)_i along the shift directions (on an
        ellipsoid w·(L⁻¹(x − c))_i: the loop reads the mean in the ball's coordinates) and w on the
        outer shell, and the basis with a zero column (it reads the carried vector [a, ∫σ, …])."""
        found = self._watch.get(dtype)
        if found is None:
            home = self.home
            offsets = self.model.unshaped(home.nodes - self.home_center)
            rows = [home.weights * offsets[:, i] for i in self.directions] + [home.weights * self._shell]
            project = np.vstack([np.asarray(home.projection, dtype=float), rows])
            found = self._watch[dtype] = (np.asfortranarray(project, dtype=dtype),
                                          with_zero_column(home.offline.basis, dtype))
        return found

    def run_batch(self, states: list[YauYauState], chunks: list[ArrayLike],
                  times: list[ArrayLike | None] | None = None,
                  return_exceptions: bool = False) -> list[tuple[YauYauState, ChunkResult] | InputError]:
        return run_batch_alone(self, states, chunks, times, return_exceptions)

    def _block_for(self, velocity: np.ndarray, jitter: float) -> int:
        """Rows L in which the mean's expected excursion stays within the stray limit: half its drift
        (the ball leads the mean by the other half, :meth:`_maybe_recentre`) plus two standard
        deviations of its random part, |v|L/2 + 2√(jitter·L) ≤ stray."""
        speed, noise = float(np.abs(velocity).max()), 2.0 * float(np.sqrt(max(jitter, 0.0)))
        if speed > 0:
            root = (-noise + np.sqrt(noise * noise + 2.0 * speed * self.stray)) / speed
        elif noise > 0:
            root = self.stray / noise
        else:
            return MAX_BLOCK
        return int(np.clip(root * root, MIN_BLOCK, MAX_BLOCK))

    def _placed(self, state: YauYauState, center: np.ndarray) -> YauYauState:
        """The engine's new state with the centre it was computed on (engine states do not carry it;
        in a moving frame the engine's state has the frame's centre after its last row)."""
        if self.frame is not None and state.center is not None:
            return state
        return dataclasses.replace(state, center=np.asarray(center, dtype=float))

    def _keep_until(self, center: np.ndarray):
        """The engine's ``until`` rule for a block run from ``center``: keep the rows before the first
        that strays (at least one), so the block need not run again shorter."""
        def keep(means: np.ndarray, centers: np.ndarray | None) -> int | None:
            stray = self._strayed(means, center if centers is None else centers)
            return None if stray is None else max(1, stray)
        return keep

    def _strayed(self, means: np.ndarray, center: np.ndarray) -> int | None:
        """The first row whose mean is further than the stray limit from the centre ((n,), or (K, n) in
        a moving frame) (None: none)."""
        if not len(means):
            return None
        along = list(self.directions)
        gap = np.abs(self.model.unshaped(means - np.asarray(center))[:, along]).max(axis=1)
        far = np.flatnonzero(~(gap <= self.stray))
        return int(far[0]) if len(far) else None

    def _maybe_recentre(self, state: YauYauState, travel: np.ndarray) -> YauYauState:
        """Re-centre when the mean is beyond the trigger distance, or will be by the end of the next
        block (``travel``: its expected move over that block), or when the outer shell holds too much
        mass; the new centre leads the mean by half the expected travel."""
        center = np.asarray(state.center, dtype=float)
        mean = state.last.mean
        outside = self.left_region(mean)
        if outside:
            return dataclasses.replace(state, degenerate=True, reason=outside)
        along = list(self.directions)
        offset = mean[along] - center[along]
        # in the ball's coordinates (an ellipsoid follows along every direction, so along is all of them)
        unshaped = self.model.unshaped
        far = max(np.abs(unshaped(offset)).max(), np.abs(unshaped(offset + travel)).max()) > self.distance
        if not far:  # the basis and weights are the same on every ball: no engine at this centre needed
            sigma = np.clip(self.home.nodal_density(state), 0.0, None) * self.home.weights
            total = float(sigma.sum())
            far = total > 0 and float(sigma[self._shell].sum()) > self.mass_limit * total
        if not far:
            return state
        ahead = np.array(mean, dtype=float)  # led by half the travel, at most half the trigger distance
        ahead[along] += np.clip(0.5 * travel, -0.5 * self.distance, 0.5 * self.distance)
        target = self.snapped(center, ahead)
        if np.array_equal(target, center):
            return state
        return self.recentre(state, target)

    def recentre(self, state: YauYauState, center: np.ndarray) -> YauYauState:
        """The state carried onto the ball around ``center``: the old expansion at the new nodes (0
        outside the old ball), projected; ∫σ of the carried density is the new mass."""
        new = self.engine(center)
        if not np.all(np.isfinite(new.h_nodes)):
            return dataclasses.replace(state, degenerate=True, reason=(
                f"the ball cannot move to {_point(center)}: the observation function is not finite there"))
        carried, before = self._carried_to(state, new)
        mass = float(new.weights @ carried)
        if not (mass > 0.0 and before > 0.0):
            return dataclasses.replace(state, degenerate=True, reason=(
                f"re-centring onto {_point(center)} left no probability mass on the new ball"))
        coefficients = np.asarray(new.offline.projector) @ carried
        return dataclasses.replace(state, coefficients=coefficients, mass=mass, center=np.array(center))

    def moved_mass(self, state: YauYauState, center: np.ndarray) -> float:
        """The fraction of ∫σ a move onto ``center`` would leave outside the new ball."""
        new = self.engine(center)
        carried, before = self._carried_to(state, new)
        return 1.0 - float(new.weights @ carried) / before

    def _carried_to(self, state: YauYauState, new: Any) -> tuple[np.ndarray, float]:
        """The state's density at ``new``'s nodes, and its ∫σ on the old ball."""
        center = np.asarray(state.center, dtype=float)
        nodal = self.home.nodal_density(state)  # the basis is the same on every ball
        carry = self.carry(np.asarray(new.model.center, dtype=float) - center)
        carried = carried_at(self.engine(center), nodal, new.nodes) if carry is None else carry.apply(nodal)
        return carried, float(self.home.weights @ nodal)

    def carry(self, offset: np.ndarray) -> "Carry | None":
        """The carry by a move of whole mesh steps (1-D elements, the 2-D lattice), kept per move: it
        depends on the offset only, every ball being the home ball translated (None: a move of any
        other length, or a mesh without steps: :func:`carried_at` then works on the nodes themselves)."""
        if not self._lattice:
            return None
        raw, offset = offset, self.model.unshaped(np.asarray(offset, dtype=float))  # (the ball's: the same)
        steps = np.round(offset / self._lattice)
        if not float(np.abs(offset - steps * self._lattice).max()) <= 1e-9 * self.radius:
            return None
        key = tuple(int(k) for k in steps)
        found = self._table.get(key)
        if found is not None:
            return found
        return kept(self._carries, key,
                    lambda: Carry.build(self.home.offline, self.home_center, self.radius, raw,
                                         self.home.node_tree), CARRIES)

    def _carry_table(self) -> dict[tuple, "Carry"]:
        """The carries of the offsets (whole steps along the shift directions) no longer than a move
        usually goes (:data:`LEAD`, ``STRAY``), built at once with the filter, so that a move in the
        stream costs the projection only, also the first one by an offset (a carry built alone costs
        8–20 steps of the fixed ball, bench/results/follow.md)."""
        reach = (float(self.distance) * (1.0 + LEAD) + STRAY * self.radius) / self._lattice
        span = np.arange(-int(reach), int(reach) + 1)
        grid = np.stack(np.meshgrid(*[span] * len(self.directions), indexing="ij"), axis=-1)
        grid = grid.reshape(-1, len(self.directions))
        grid = grid[(np.linalg.norm(grid, axis=1) <= reach) & np.any(grid != 0, axis=1)]
        offsets = np.zeros((len(grid), self.model.n))
        offsets[:, list(self.directions)] = grid * self._lattice
        carries = Carry.build_many(self.home.offline, self.home_center, self.radius,
                                    self.model.shaped(offsets), self.home.node_tree)
        return {tuple(int(k) for k in np.round(o / self._lattice)): c
                for o, c in zip(offsets, carries, strict=True)}


def _with_centers(result: ChunkResult, before: np.ndarray, after: np.ndarray | None = None) -> ChunkResult:
    """The result with the ball's centre after each row (the last row's is ``after``: a re-centre)."""
    K = len(result)
    centers = np.repeat(np.asarray(before, dtype=float)[None, :], K, axis=0)
    if result.center is not None and len(result.center) == K:  # a moving frame's centres, row by row
        centers = np.array(result.center, dtype=float)
        before = centers[-1] if K else before
    moved = np.zeros(K, dtype=bool)
    if after is not None and K and not np.array_equal(after, before):
        centers[-1], moved[-1] = after, True
    return dataclasses.replace(result, center=centers, recentred=moved)


def _flagged(result: ChunkResult, row: int, reason: str | None) -> ChunkResult:
    """The result with ``row`` flagged degenerate (a move after it failed, or it left the region)."""
    flags = result.degenerate.copy()
    flags[row] = True
    return dataclasses.replace(result, degenerate=flags, reason=result.reason or reason)


def _prior_mean(engine: Any, prior: Any | None) -> np.ndarray | None:
    moments = (engine.model if prior is None else engine.prior_model(prior)).prior_moments()
    return None if moments is None else moments[0]


def _point(center: np.ndarray) -> str:
    return "(" + ", ".join(f"{c:.4g}" for c in center) + ")"
