"""Carrying a density onto a moved ball: the old expansion at the new nodes, 0 outside the old ball.

Where a new node is an old one (a move by whole mesh steps: 1-D elements, the 2-D lattice) its value
is read off; elsewhere inside the old ball it is interpolated in the old mesh.  Every ball being the
home ball translated, the carry by one offset depends on the offset only: it is built once
(:class:`Carry`, index arrays and a small sparse matrix) and applied to any density.
"""

from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING, Any

import numpy as np
import scipy.sparse as sps

if TYPE_CHECKING:  # types only
    from ..model import Model
    from ..offline.pipeline import OfflineModel


@dataclasses.dataclass(frozen=True)
class Carry:
    """The carry by one offset as index arrays and a small matrix: ``carried[matched] =
    nodal[source]``, ``carried[rest] = rows @ nodal`` (interpolation in the old mesh), 0 elsewhere."""

    size: int
    matched: np.ndarray
    source: np.ndarray
    rest: np.ndarray
    rows: Any  # (len(rest), Q) sparse; None: no row is interpolated
    others: np.ndarray  # the new nodes that are not old ones (``rest`` and those outside the old ball)

    @classmethod
    def build(cls, home: OfflineModel, center: np.ndarray, radius: float, offset: np.ndarray,
              tree: Any) -> "Carry":
        """On the home ball (nodes ``home.nodes`` around ``center``, ``tree`` their KD-tree): where its
        nodes moved by ``offset`` land, as :func:`carried_at` finds it."""
        return cls.build_many(home, center, radius, np.asarray(offset, dtype=float)[None, :], tree)[0]

    @classmethod
    def build_many(cls, home: OfflineModel, center: np.ndarray, radius: float, offsets: np.ndarray,
                   tree: Any) -> list["Carry"]:
        """:meth:`build` for every row of ``offsets`` (M, n) at once: one search of the landing nodes
        and one interpolation matrix for all of them (a carry alone pays both calls' fixed cost)."""
        nodes = np.asarray(home.nodes, dtype=float)
        Q = len(nodes)
        points = (nodes[None, :, :] + offsets[:, None, :]).reshape(-1, nodes.shape[1])
        nearest, matched, rest = landing(tree, nodes, points, center, radius, home.model)
        everywhere = np.flatnonzero(rest)
        rows = home.interpolation_matrix(points[everywhere]).tocsr() if len(everywhere) else None
        bounds = np.searchsorted(everywhere, np.arange(len(offsets) + 1) * Q)
        found = []
        for m in range(len(offsets)):
            part = slice(m * Q, (m + 1) * Q)
            hit = np.flatnonzero(matched[part])
            lo, hi = int(bounds[m]), int(bounds[m + 1])
            found.append(cls(Q, hit, nearest[part][hit], everywhere[lo:hi] - m * Q,
                             row_block(rows, lo, hi), np.flatnonzero(~matched[part])))
        return found

    def apply(self, nodal: np.ndarray) -> np.ndarray:
        out = np.zeros(self.size)
        out[self.matched] = nodal[self.source]
        if self.rows is not None:
            out[self.rest] = self.rows @ nodal
        return out

    def adjoint(self, values: np.ndarray) -> np.ndarray:
        """Cᵀv, the transpose of :meth:`apply` (values at the new nodes → the old nodes): what the backward
        pass of a smoother carries back over the move (solver/engine/follow_smoother.py)."""
        out = np.zeros(self.size)
        np.add.at(out, self.source, values[self.matched])
        if self.rows is not None:
            out += self.rows.T @ values[self.rest]
        return out


def row_block(rows: Any, lo: int, hi: int) -> Any:
    """Rows lo:hi of a CSR matrix as a CSR matrix of their own (None: no row), without scipy's slicing
    (~50 µs a call, for a table of carries the bulk of the split)."""
    if hi <= lo:
        return None
    start, stop = rows.indptr[lo], rows.indptr[hi]
    return sps.csr_matrix((rows.data[start:stop], rows.indices[start:stop], rows.indptr[lo:hi + 1] - start),
                          shape=(hi - lo, rows.shape[1]))


def carried_at(old: Any, nodal: np.ndarray, points: np.ndarray) -> np.ndarray:
    """The old engine's density (nodal values ``nodal``) at ``points``, 0 outside its ball: read off
    where a point is an old node (a move by whole steps: 1-D elements, the 2-D lattice), interpolated
    in the old mesh elsewhere (the nodes near the boundary, or a mesh without a lattice)."""
    nearest, matched, rest = landing(old.node_tree, old.nodes, points, old.model.center, old.model.radius,
                                      old.model)
    out = np.where(matched, nodal[nearest], 0.0)
    if rest.any():
        out[rest] = old.offline.interpolate(nodal, points[rest])
    return out


def landing(tree: Any, nodes: np.ndarray, points: np.ndarray, center: np.ndarray, radius: float,
             model: Model) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Where ``points`` land on the ball of ``nodes`` (``tree``: their KD-tree) around ``center``: a
    node at each point (where one is: the rest get an arbitrary valid index), the points inside the ball
    that are nodes (read off), and those inside that are not (interpolated).  The sphere itself counts
    as outside (Dirichlet: σ = 0 there)."""
    tolerance = 1e-9 * max(1.0, float(np.abs(nodes).max()))
    if nodes.shape[1] == 1 < len(nodes):
        gap, nearest = nearest_1d(nodes, points)
    else:  # only a node within the tolerance counts: the tree stops looking beyond it (~3× faster)
        gap, nearest = tree.query(points, distance_upper_bound=2.0 * tolerance)
        nearest = np.minimum(nearest, len(nodes) - 1)
    inside = model.ball_distance(points - center) < radius * (1 - 1e-12)  # (an ellipsoid's, model.shape)
    matched = (gap <= tolerance) & inside
    return nearest, matched, inside & ~matched



def unshaped_points(model: Model, mesh_points: np.ndarray | None) -> np.ndarray | None:
    """Mesh points (n, Np) of an ellipsoid in the ball's coordinates, c + L⁻¹(p − c) (where its lattice
    is the ball's); the ball's as they are."""
    if mesh_points is None or model.shape is None:
        return mesh_points
    c = np.asarray(model.center, dtype=float)[:, None]
    return c + model.unshaped((np.asarray(mesh_points, dtype=float) - c).T).T


def nearest_1d(nodes: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The distance to the nearest node and its index, on a line (a binary search of the sorted nodes:
    the KD-tree's query costs ~20 µs a call for a hundred points, this a few)."""
    x, p = nodes[:, 0], points[:, 0]
    order = np.argsort(x)
    xs = x[order]
    right = np.clip(np.searchsorted(xs, p), 1, len(xs) - 1)
    left = right - 1
    take_left = np.abs(p - xs[left]) <= np.abs(xs[right] - p)
    best = np.where(take_left, left, right)
    return np.abs(p - xs[best]), order[best]
