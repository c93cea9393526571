"""The fixed-interval smoother on a ball that follows the state (``[domain] follow``; an atlas, a moving
frame too), issue 38.

The filter's own pass (:meth:`FollowingFilter.run_arrays`) decides where the ball goes: rows a_j … b_j − 1
are filtered on the ball around c_j, and after row b_j − 1 the state moves onto the ball around c_(j+1).
Between two moves the ball is a fixed ball (the centred engine; with an atlas, the centre's own
propagator), whose forward–backward recursion is solver/engine/smoother.py's.  A move is linear in the
state (solver/engine/carry.py): with C the carry (the old expansion at the new nodes, 0 outside the old
ball), Φ the basis at the nodes and Π = ΦᵀW the projector (the same on every ball),

    c' = Π C Φ c,

so in the measures μ = w ⊙ σ of smoother.py the move is ν = W C Φ Φᵀ μ_(b−1), the measure on the new
ball that its first row a = b propagates.  The adjoint of that map carries the backward pass over the move:

    β_(b−1) = Φ Φᵀ Cᵀ (w ⊙ β̃),        β̃ = Φ P_aᵀ(ẽ_a ⊙ w ⊙ β_a) / ∫σ_a,

β̃ being what the new ball's backward pass gives before its first row (``smooth_from``).  The backward pass
thus runs over the same sequence of balls from the last, and the smoothed density of row k is
w ⊙ σ_k ⊙ β_k on row k's own ball, normalised: the exact forward–backward smoother of the discretised
model with its moves.  The smoother's forward pass moves the state by this same C (the filter's kept carry
for a move by whole mesh steps, one built the same way for any other offset), so the backward pass is its
adjoint exactly.

Cost: the filter's pass (it places the balls), the filter again over each ball's rows keeping the state at
each ball's start (one state a ball), then each ball's smoother (its forward pass once more, kept whole or
checkpointed, and the backward pass).  In a moving frame (solver/engine/frame.py) a ball's run is the
frame's engine over the rows between two moves (its nodes ride the frame row by row, the coefficients'
recursion is the fixed ball's), and a move carries from where the frame took the ball.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from ..errors import InputError
from ..filtering import ChunkResult, concat_results
from .carry import Carry
from .smoother import Visit, smooth_from, validated
from .state import YauYauState

Ball = tuple[int, int, np.ndarray]  # rows a … b − 1 on the ball around the centre


def smooth_following(follow: Any, state: YauYauState, increments: Any, times: Any = None,
                     block: int | None = None, visit: Visit | None = None) -> tuple[YauYauState, ChunkResult]:
    """(the filter's state after the chunk, its result with the smoothed mean, cov and mode) of a
    FollowingFilter ``follow`` over one chunk from ``state`` (module docstring); ``block`` and ``visit`` as
    smoother.py's (``visit`` gets states with their ball's ``center``)."""
    chunk = validated(follow.home, state, increments, times)  # the rows, times and state checked
    if chunk is None:
        return follow.run_arrays(state, np.empty((0, follow.model.m)), times)
    rows, field = chunk[0], chunk[-1]
    stamps = None if times is None else np.asarray(times, dtype=float).reshape(-1)
    new_state, first = follow.run_arrays(state, rows, stamps)
    if first.degenerate.any():
        k = int(np.argmax(first.degenerate))
        raise InputError(f"{field}[{k}]", f"the filter degenerated at this row ({first.reason}): the "
                                          "smoother needs every row of the chunk filtered")
    balls = ball_runs(np.asarray(state.center, dtype=float), np.asarray(first.center, dtype=float),
                      first.recentred if follow.frame is not None else None)
    starts, moves = ball_starts(follow, state, rows, stamps, balls)
    beta, parts = None, []
    for j in range(len(balls) - 1, -1, -1):
        a, b, center = balls[j]
        seen = None if visit is None else _on_ball(visit, a, None if follow.frame is not None else center)
        try:
            _, part, beta = smooth_from(follow.runner(center), starts[j], rows[a:b],
                                        None if stamps is None else stamps[a:b], block, seen, beta)
        except InputError as exc:  # the row in the whole chunk
            raise exc.shifted(a) from None
        parts.append(part)
        if j:
            beta = carried_back(follow, *moves[j - 1], beta, f"{field}[{a - 1}]")
    smoothed = concat_results(parts[::-1])
    return new_state, dataclasses.replace(first, mean=smoothed.mean, cov=smoothed.cov, mode=smoothed.mode)


def ball_runs(start: np.ndarray, centers: np.ndarray, moved: np.ndarray | None = None) -> list[Ball]:
    """The runs of rows filtered on one ball: row 0's is ``start``, row k's the centre after row k − 1
    (``ChunkResult.center``: where a move after that row took the ball).  In a moving frame (its centre
    changes every row) the runs end at the moves ``moved`` instead."""
    K = len(centers)
    balls = np.concatenate([start[None, :], centers[:-1]])
    if moved is None:
        ends = np.flatnonzero(np.any(balls[1:] != balls[:-1], axis=1)) + 1
    else:
        ends = np.flatnonzero(np.asarray(moved[:-1], dtype=bool)) + 1
    changes = [0, *ends.tolist(), K]
    return [(a, b, balls[a]) for a, b in zip(changes[:-1], changes[1:], strict=True)]


def ball_starts(follow: Any, state: YauYauState, rows: np.ndarray, stamps: np.ndarray | None,
                balls: list[Ball]) -> tuple[list[YauYauState], list[tuple[np.ndarray, np.ndarray]]]:
    """The state before each ball's first row, on that ball: the filter over the ball's rows, then the
    move (:func:`carried`); and each move's (centre before, centre after) (in a moving frame the centre
    before is where the frame took the ball over the run)."""
    starts, moves, current = [state], [], state
    for (a, b, center), (_, _, after) in zip(balls[:-1], balls[1:], strict=True):
        given = None if stamps is None else stamps[a:b]
        current, _ = follow.runner(center).run_arrays(current, rows[a:b], given)
        before = center if follow.frame is None else np.asarray(current.center, dtype=float)
        moves.append((before, after))
        current = carried(follow, current, before, after)
        starts.append(current)
    return starts, moves


def move_map(follow: Any, before: np.ndarray, after: np.ndarray) -> Carry:
    """C of the move from the ball around ``before`` onto the one around ``after``: the filter's kept carry
    (a move by whole mesh steps), else built the same way for this offset."""
    offset = np.asarray(after, dtype=float) - np.asarray(before, dtype=float)
    found = follow.carry(offset)
    if found is None:
        home = follow.home
        found = Carry.build(home.offline, follow.home_center, follow.radius, offset, home.node_tree)
    return found


def carried(follow: Any, state: YauYauState, before: np.ndarray, after: np.ndarray) -> YauYauState:
    """The state moved onto the ball around ``after``: c' = Π C Φ c, ∫σ of the carried density its mass
    (as FollowingFilter.recentre moves it)."""
    moved = move_map(follow, before, after).apply(follow.home.nodal_density(state))
    mass = float(follow.home.weights @ moved)
    if not mass > 0.0:
        raise InputError("state", "a move of the ball left no probability mass: nothing to smooth")
    coefficients = np.asarray(follow.home.offline.projector) @ moved
    return dataclasses.replace(state, coefficients=coefficients, mass=mass,
                               center=np.array(after, dtype=float))


def carried_back(follow: Any, before: np.ndarray, after: np.ndarray, beta: np.ndarray,
                 row: str) -> np.ndarray:
    """β over the move after ``row``: Φ Φᵀ Cᵀ (w ⊙ β̃) (module docstring), divided by its largest magnitude."""
    basis = np.asarray(follow.home.offline.basis, dtype=float)
    back = move_map(follow, before, after).adjoint(follow.home.weights * beta)
    found = basis @ (basis.T @ back)
    top = float(np.max(np.abs(found)))
    if not (np.isfinite(top) and top > 0.0):
        raise InputError(row, "the backward pass lost every node at the move of the ball after this row: "
                              "nothing to smooth")
    return found / top


def _on_ball(visit: Visit, first: int, center: np.ndarray | None) -> Visit:
    """``visit`` for a ball's rows: the chunk's row numbers, each state with the ball's centre (None: a
    moving frame's states already have theirs, row by row)."""
    def seen(start: int, states: list) -> None:
        if center is not None:
            states = [dataclasses.replace(s, center=np.array(center, dtype=float)) for s in states]
        visit(first + start, states)
    return seen
