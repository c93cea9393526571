"""An atlas of propagators: a following ball for a drift that is not shift-invariant (``[domain] region``).

Where f depends on a coordinate, the Fokker–Planck operator L u = ½ a:∇²u − div(f u) on B_R(c) changes
with c, and one stored propagator cannot serve a moved ball (solver/engine/follow.py).  The atlas stores one
for each centre of a lattice covering the declared region

    c_j = c₀ + Σ_i j_i s e_i     (i over the coordinates f depends on; c₀ the spec's centre),

s = ``follow_distance``·R (a whole number of elements in 1-D, of lattice steps in 2-D, so the
balls' nodes coincide and a move carries the density exactly where the balls overlap).  A re-centre
goes to the lattice centre nearest the point the ball should be at, which is within s/2 of it along
every coordinate: the ball holds the density by the same margin as the shift-invariant case.  Along
the coordinates f does not depend on the ball still moves freely (the centre's propagator, translated).

The basis (the Dirichlet eigenfunctions of −½div(a∇), a constant) is the same on every translated ball:
only the propagators differ.  The stable form never needs e^{dt L_K}, so the atlas stores e^{dt L}φ_k
and the Galerkin generator per centre (irregular times).  The solves of every centre are independent
Dask tasks (offline/distributed.py), bit-identical whatever the cluster.  A stored atlas is read lazily,
one centre at a time (``load``), and at most ``CACHE`` centres are kept.

Leaving the region is a degenerate state with its reason (solver/engine/follow.py): there is no propagator
there, and no garbage is produced instead.
"""

from __future__ import annotations

import dataclasses
import itertools
from collections import OrderedDict
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Callable, TypeVar

import numpy as np
from numpy.typing import ArrayLike

from ..errors import SpecError

if TYPE_CHECKING:  # types only
    from ..model import Model

Key = TypeVar("Key")
Kept = TypeVar("Kept")

MAX_CENTERS = 4096  # a larger atlas is refused with its count (raise follow_distance or shrink the region)
CACHE = 32  # centres kept in memory at once (lazily loaded from the file)
LAZY_NAMES = ("atlas_propagator_fp", "atlas_generator")  # (K, Q, N), (K, N, N): one centre per read
Sink = Callable[[int, int, dict[str, np.ndarray]], None]  # (k, K, that centre's row of each LAZY_NAMES)


@dataclass(frozen=True)
class Lattice:
    """Centres c₀ + j·s along ``axes`` (j_i from ``first`` to ``last``), c₀ elsewhere."""

    anchor: np.ndarray  # (n,) the spec's centre
    spacing: float
    axes: tuple[int, ...]
    first: tuple[int, ...]
    last: tuple[int, ...]
    region: np.ndarray  # (n, 2)

    @property
    def counts(self) -> tuple[int, ...]:
        return tuple(b - a + 1 for a, b in zip(self.first, self.last, strict=True))

    @property
    def size(self) -> int:
        return int(np.prod(self.counts)) if self.axes else 1

    def centers(self) -> np.ndarray:
        """(K, n) in C order over ``axes``."""
        out = []
        for js in itertools.product(*(range(a, b + 1) for a, b in zip(self.first, self.last, strict=True))):
            c = np.array(self.anchor, dtype=float)
            for axis, j in zip(self.axes, js, strict=True):
                c[axis] = self.anchor[axis] + j * self.spacing
            out.append(c)
        return np.array(out).reshape(-1, len(self.anchor))

    def steps(self, point: np.ndarray) -> tuple[int, ...]:
        """The lattice steps j nearest ``point`` along the axes, clipped to the lattice."""
        anchor = self.anchor.tolist()  # (Python numbers: numpy on scalars costs microseconds a call)
        return tuple(min(max(round((float(point[a]) - anchor[a]) / self.spacing), lo), hi)
                     for a, lo, hi in zip(self.axes, self.first, self.last, strict=True))

    def nearest(self, point: np.ndarray) -> np.ndarray:
        """``point`` with its lattice coordinates moved to the nearest centre's."""
        out = np.array(point, dtype=float)
        for axis, j in zip(self.axes, self.steps(point), strict=True):
            out[axis] = self.anchor[axis] + j * self.spacing
        return out

    def index(self, center: np.ndarray) -> int:
        """The row of ``centers()`` whose lattice coordinates are ``center``'s."""
        js = [j - a for j, a in zip(self.steps(center), self.first, strict=True)]
        return int(np.ravel_multi_index(js, self.counts)) if self.axes else 0

    def outside(self, point: np.ndarray) -> bool:
        x = np.asarray(point, dtype=float)
        return bool(np.any(x < self.region[:, 0]) or np.any(x > self.region[:, 1]))


def needs_atlas(model: Model) -> bool:
    """``[domain] follow`` with a region, and a drift that depends on some coordinate the ball moves
    along and is not affine: the propagator differs from ball to ball."""
    domain = model.spec.domain
    return bool(domain.follow and domain.region is not None and len(model.shift_directions) < model.n
                and model.affine_drift is None)  # an affine drift rides a moving frame (engine/frame.py)


def lattice(model: Model, element: float | None = None) -> Lattice:
    """The atlas lattice of ``model`` (module docstring); ``element``: the 1-D element length."""
    domain = model.spec.domain
    region = np.asarray(domain.region, dtype=float)
    anchor = np.asarray(model.center, dtype=float)
    spacing = float(domain.follow_distance) * float(domain.radius)
    if element:
        spacing = max(1, round(spacing / element)) * element
    axes = tuple(i for i in range(model.n) if i not in model.shift_directions)
    first = tuple(int(np.ceil((region[i, 0] - anchor[i]) / spacing - 0.5)) for i in axes)
    last = tuple(int(np.floor((region[i, 1] - anchor[i]) / spacing + 0.5)) for i in axes)
    found = Lattice(anchor, spacing, axes, first, last, region)
    if found.size > MAX_CENTERS:
        raise SpecError("domain.region", (
            f"the atlas would need {found.size} centres ({' x '.join(map(str, found.counts))}, spaced "
            f"{spacing:.3g} = follow_distance x radius), more than {MAX_CENTERS}: shrink the region along "
            f"the coordinates the drift depends on, or raise domain.follow_distance or domain.radius"))
    return found


def move_step(mesh_points: ArrayLike | None, n: int, center: ArrayLike | None = None,
              radius: float | None = None) -> float | None:
    """The step by which a ball may move so that its nodes meet the old ones: 1-D the element length
    of the uniform interval mesh (points (1, Np)); 2-D the step of a lattice mesh (fem.lattice_disk_mesh,
    ``center`` and ``radius`` given); None for any other mesh."""
    if mesh_points is None:
        return None
    if n == 2 and center is not None and radius is not None:
        return lattice_step(mesh_points, center, radius)
    if n != 1:
        return None
    points = np.sort(np.asarray(mesh_points, dtype=float).ravel())
    if len(points) < 2:
        return None
    steps = np.diff(points)
    return float(steps.mean()) if np.allclose(steps, steps.mean(), rtol=1e-9) else None


def lattice_step(mesh_points: ArrayLike, center: ArrayLike, radius: float) -> float | None:
    """The step s of a lattice mesh: every vertex within R/2 of the centre is c + s·(integers), s
    fitted by least squares; None when the vertices are not such a lattice (the 2-D rings)."""
    points = np.asarray(mesh_points, dtype=float).T - np.asarray(center, dtype=float)
    near = points[np.linalg.norm(points, axis=1) < 0.5 * radius].ravel()
    steps = np.diff(np.unique(np.round(near, 9)))
    steps = steps[steps > 1e-9 * radius]
    if len(near) < 6 or not len(steps):
        return None
    k = np.round(near / steps.min())
    step = float(near @ k / (k @ k))
    return step if np.allclose(near, k * step, rtol=0, atol=1e-9 * radius) else None


def kept(cache: OrderedDict[Key, Kept], key: Key, make: Callable[[], Kept], limit: int) -> Kept:
    """``cache[key]``, made by ``make()`` when missing; the least recently used beyond ``limit`` go."""
    found = cache.get(key)
    if found is None:
        found = cache[key] = make()
        if len(cache) > limit:
            cache.popitem(last=False)
    else:
        cache.move_to_end(key)
    return found


class Atlas:
    """The per-centre offline arrays of a lattice, loaded on demand (``load(k)`` -> the arrays of
    :data:`LAZY_NAMES` for centre k, without the prefix) and kept ``cache`` at a time."""

    def __init__(self, home: Any, grid: Lattice, load: Callable[[int], dict[str, np.ndarray]],
                 cache: int = CACHE):
        self.home, self.lattice, self._load, self._cache = home, grid, load, cache
        self._kept: OrderedDict[int, Any] = OrderedDict()
        self.loads = 0  # centres read so far (a cache miss each)
        self.solved: Any = None  # the solved AtlasArrays, all centres in memory (just precomputed)

    @property
    def size(self) -> int:
        return self.lattice.size

    def centers(self) -> np.ndarray:
        return self.lattice.centers()

    def clear(self) -> None:
        """Forget the kept centres (the next use of each reads it again)."""
        self._kept.clear()

    def offline(self, k: int) -> Any:
        """The offline arrays of the ball around centre k (an OfflineModel: evaluate, interpolate)."""
        return kept(self._kept, k, lambda: self._read(k), self._cache)

    def _read(self, k: int) -> Any:
        arrays = self._load(k)
        self.loads += 1
        center = self.center(k)
        shift = center - np.asarray(self.home.model.center, dtype=float)
        fp = np.asarray(arrays["propagator_fp"], dtype=float)
        return dataclasses.replace(
            self.home, model=self.home.model.translated(center), nodes=self.home.nodes + shift,
            mesh_points=self.home.mesh_points + shift[:, None], propagator_fp=fp, propagator_k=fp,
            generator=np.asarray(arrays["generator"], dtype=float), _space=None, _tree=None, atlas=None)

    def center(self, k: int) -> np.ndarray:
        """The centre of row k of ``centers()``."""
        grid = self.lattice
        js = np.unravel_index(k, grid.counts)
        c = np.array(grid.anchor, dtype=float)
        for axis, j, a in zip(grid.axes, js, grid.first, strict=True):
            c[axis] = grid.anchor[axis] + (int(j) + a) * grid.spacing
        return c


def model_lattice(model: Model, mesh_points: ArrayLike | None) -> Lattice:
    """The atlas lattice of ``model`` on a mesh with these points (its move step)."""
    return lattice(model, _step(model, mesh_points))


def _step(model: Model, mesh_points: ArrayLike | None) -> float | None:
    return move_step(mesh_points, model.n, model.center, model.radius)


def point_label(center: np.ndarray) -> str:
    return "(" + ", ".join(f"{c:.4g}" for c in center) + ")"
