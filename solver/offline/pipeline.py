"""The offline stage of the Yau–Yau filter (seed 002 §5, (5.31)–(5.34); seed 001 §3).

For an L²(B_R)-orthonormal basis {φ_k} it solves, once per model,

    ∂u/∂t = L u    (Fokker–Planck, L u = ½ a:∇²u − div(f u)),          u(0) = φ_k,
    ∂u/∂t = L_K u  (Kolmogorov, L_K = L − ½hᵀR⁻¹h, seed 002 (5.31)),     u(0) = φ_k,

with u = 0 on ∂B_R, over one observation interval dt, and stores the nodal values of
e^{dt L}φ_k and e^{dt L_K}φ_k.

The pipeline is three builders, each replaceable (``precompute(model, space=..., basis=...,
propagators=...)``): a new basis or a moving domain touches one of them, not the engine:

* ``space(model) -> Discretisation``: nodes, quadrature weights and the two operators as sparse
  matrices on the nodal values (default :func:`finite_element_space`: scikit-fem, solver/offline/fem.py);
* ``basis(discretisation, N) -> OrthonormalBasis``: values, projector and eigenvalues (default
  :func:`dirichlet_eigenbasis`, solver/offline/basis.py);
* ``propagators(discretisation, basis, dt, substeps, workers, progress) -> (fp, k)``: the nodal
  values of e^{dt L}φ_k and e^{dt L_K}φ_k (default :func:`sdirk_propagators`, solver/offline/propagator.py;
  the N solves in fixed column blocks, so ``workers`` processes give bit-identical arrays).

What the online engine consumes is the :class:`OfflineArrays` protocol; :class:`OfflineModel`
implements it and round-trips through the HDF5 store (``to_arrays``/``from_arrays``).  Nothing
heavy (scikit-fem, SuperLU) is imported until a builder runs or a density is evaluated.
"""

from __future__ import annotations

import multiprocessing
import uuid
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Callable, Protocol, runtime_checkable

import numpy as np

from ..engine.atlas import needs_atlas
from ..engine.frame import affine_frame
from ..engine.semigroup import galerkin_generator
from ..errors import InputError, SpecError
from ..model import Model
from .atlas import attach_solved, attach_stored, model_lattice, solve_atlas
from .jobs import Job, Progress, check_stable, propagate_all

if TYPE_CHECKING:  # types only
    from ..engine.atlas import Atlas, Sink
    from .basis import OrthonormalBasis
    from .fem import FESpace

ARRAY_NAMES = ("mesh_points", "mesh_cells", "nodes", "weights", "basis", "projector",
               "propagator_fp", "propagator_k", "eigenvalues", "node_index", "element_order")
# stored since irregular times; a file without it rebuilds it from its mesh on first use.  "frame":
# f(c₀), what a moving frame's propagator leaves out of the drift (solver/engine/frame.py)
OPTIONAL_ARRAYS = ("generator", "frame")


@runtime_checkable
class OfflineArrays(Protocol):
    """What the online engine needs of the offline stage (Q nodes, N basis functions).

    ``nodes`` (Q, n) where densities are represented; ``weights`` (Q,) positive quadrature weights
    (∫u ≈ weights·u); ``basis`` (Q, N) nodal values of Φ with ΦᵀWΦ = I; ``projector`` (N, Q) = ΦᵀW;
    ``propagator_fp`` and ``propagator_k`` (Q, N) nodal values of e^{dt L}φ_k and e^{dt L_K}φ_k;
    ``evaluate_basis(points) -> (P, N)`` the basis anywhere (0 outside the domain).
    """

    nodes: np.ndarray
    weights: np.ndarray
    basis: np.ndarray
    projector: np.ndarray
    propagator_fp: np.ndarray
    propagator_k: np.ndarray

    def evaluate_basis(self, points: np.ndarray) -> np.ndarray: ...


@dataclass(frozen=True)
class Discretisation:
    """What a space builder returns: the nodes and weights, and the Fokker–Planck and Kolmogorov
    operators as sparse (Q, Q) matrices acting on nodal values (W = diag of ``weights`` the lumped
    mass, or ``mass`` where the scheme has its own: W du/dt = A u or M du/dt = A u);
    ``half_stiffness`` is ½K of −½div(ā∇) (for an eigenbasis, Model.basis_diffusion); ``space`` whatever
    the builder needs to evaluate functions at points later, and ``arrays`` what it must store for
    that (e.g. the mesh)."""

    nodes: np.ndarray
    weights: np.ndarray
    fokker_planck: Any
    kolmogorov: Any
    half_stiffness: Any
    space: Any
    arrays: dict[str, np.ndarray]
    mass: Any = None  # a sparse mass matrix M (M du/dt = A u, scheme = "supg"); None: W = diag(weights)


def finite_element_space(model: Model) -> Discretisation:
    """The default space: scikit-fem elements on the ball (solver/offline/fem.py)."""
    from . import fem

    space = fem.discretise(model)
    ops = fem.assemble(model, space)
    arrays = {"mesh_points": space.mesh.p, "mesh_cells": space.mesh.t, "node_index": space.interior,
              "element_order": np.array(space.order)}
    return Discretisation(nodes=space.nodes, weights=ops.weights, fokker_planck=ops.fokker_planck,
                          kolmogorov=ops.kolmogorov, half_stiffness=ops.half_stiffness, space=space,
                          arrays=arrays, mass=ops.mass)


def dirichlet_eigenbasis(disc: Discretisation, size: int) -> OrthonormalBasis:
    """The default basis: the ``size`` lowest Dirichlet eigenfunctions of −½div(a∇) (offline/basis.py)."""
    from .basis import eigenbasis

    return eigenbasis(disc.half_stiffness, disc.weights, size)


def sdirk_propagators(disc: Discretisation, basis: OrthonormalBasis, dt: float, substeps: int,
                      workers: int = 1, progress: Progress | None = None,
                      scheduler: str | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The default propagators: Alexander's L-stable SDIRK2 over dt (solver/offline/propagator.py), the
    column blocks as Dask tasks (``scheduler``: a running cluster's address; else ``workers``
    local processes)."""
    job = Job(disc.fokker_planck, disc.kolmogorov, disc.weights, dt, substeps, basis.values,
               token=uuid.uuid4().hex, mass=disc.mass)
    return propagate_all(job, workers, progress, scheduler)


# -- the offline model --------------------------------------------------------------------------
@dataclass(eq=False)
class OfflineModel:
    """The arrays of docs/architecture.md, plus ``node_index`` (nodes among the FE DOFs) and
    ``element_order`` (polynomial degree actually used)."""

    model: Model
    mesh_points: np.ndarray
    mesh_cells: np.ndarray
    nodes: np.ndarray
    weights: np.ndarray
    basis: np.ndarray
    projector: np.ndarray
    propagator_fp: np.ndarray
    propagator_k: np.ndarray
    eigenvalues: np.ndarray
    node_index: np.ndarray
    element_order: np.ndarray
    generator: np.ndarray | None = None  # (N, N) Galerkin Fokker–Planck generator Φᵀ K Φ (semigroup.py)
    atlas: Atlas | None = field(default=None, repr=False)  # solver/engine/atlas.py: [domain] region
    _space: FESpace | None = field(default=None, repr=False)  # built on first use
    _tree: Any | None = field(default=None, repr=False)  # scipy.spatial.cKDTree of the cells

    @property
    def size(self) -> int:
        """N, the number of basis functions."""
        return self.basis.shape[1]

    def to_arrays(self) -> dict[str, np.ndarray]:
        arrays = {name: getattr(self, name) for name in ARRAY_NAMES}
        arrays["generator"] = self.fokker_planck_generator()
        if self.atlas is not None:
            arrays["atlas_centers"] = self.atlas.centers()

        frame = affine_frame(self.model)
        if frame is not None:
            arrays["frame"] = frame.offset
        return arrays

    def lazy_arrays(self) -> dict[str, np.ndarray]:
        """The arrays a store should read one row (one atlas centre) at a time: (K, ...) each (none
        kept when the atlas went to a store centre by centre as it was solved)."""
        solved = None if self.atlas is None else self.atlas.solved
        if solved is None:
            return {}
        return {"atlas_propagator_fp": solved.propagator_fp, "atlas_generator": solved.generator}

    @classmethod
    def from_arrays(cls, model: Model, arrays: dict[str, np.ndarray],
                    lazy: Any | None = None) -> "OfflineModel":
        """The stored arrays; ``lazy`` (``read(name, k)`` of one row of a (K, ...) array: the store's
        lazy reader) holds an atlas's per-centre arrays."""
        values = {}
        for name in ARRAY_NAMES:
            if name not in arrays:
                raise InputError(f"arrays.{name}", "is missing")
            values[name] = np.asarray(arrays[name])
        _check_shapes(model, values)
        generator = arrays.get("generator")
        if generator is not None:
            generator = np.asarray(generator, dtype=float)
            size = values["basis"].shape[1]
            if generator.shape != (size, size) or not np.all(np.isfinite(generator)):
                raise InputError("arrays.generator", f"must be a finite ({size}, {size}) matrix")
        _check_frame(model, arrays.get("frame"))
        found = cls(model=model, generator=generator, **values)

        if needs_atlas(model):
            attach_stored(found, arrays.get("atlas_centers"), lazy)
        return found

    def fokker_planck_generator(self) -> np.ndarray:
        """A = Φᵀ K Φ, the Fokker–Planck generator on the basis (solver/engine/semigroup.py): stored, or
        rebuilt once from the mesh (a file written before irregular times)."""
        if self.generator is None:
            from . import fem

            operators = fem.assemble(self.model, self.space)
            self.generator = galerkin_generator(self.basis, operators.fokker_planck, operators.mass,
                                                operators.weights)
        return self.generator

    # -- evaluation at arbitrary points ----------------------------------------------------
    def evaluate_basis(self, points: np.ndarray) -> np.ndarray:
        """Values of the basis functions at points (P, n) -> (P, N); 0 outside the ball."""
        return self.interpolate(self.basis, points)

    def interpolate(self, nodal: np.ndarray, points: np.ndarray) -> np.ndarray:
        """The finite-element function(s) with these values at ``nodes`` ((Q,) or (Q, k)) at points."""
        return self.interpolation_matrix(points) @ np.asarray(nodal, dtype=float)

    def interpolation_matrix(self, points: np.ndarray) -> Any:
        """(P, Q) sparse: row p the weights with which the finite-element function takes its value at
        point p from its nodal values (the element's nodal basis functions there); a zero row outside
        the ball, and on ∂B_R itself (Dirichlet: every basis function is 0 there)."""
        import scipy.sparse as sps

        from . import fem

        X = check_points(points, self.model.n)
        Q = len(self.node_index)
        linear = self.model.n > 1 and int(self.element_order) == 1  # DOFs are the mesh's vertices
        column = np.full(self.mesh_points.shape[1] if linear else self.space.basis.N, -1)
        column[self.node_index] = np.arange(Q)
        # the interval mesh's element finder has no element for its right end point: the sphere is outside
        distance = self.model.ball_distance(X - self.model.center)
        inside = np.flatnonzero(distance < self.model.radius * (1 - 1e-12))
        if not len(inside):
            return sps.csr_matrix((len(X), Q))
        if self.model.n == 1:
            probe = self.space.basis.probes(X[inside].T).tocoo()
            rows, dofs, values = inside[probe.row], probe.col, probe.data
        else:
            if self._tree is None:
                from scipy.spatial import cKDTree

                self._tree = cKDTree(self.mesh_points[:, self.mesh_cells].mean(axis=1).T)
            elem, bary = fem.locate(self.mesh_points, self.mesh_cells, self._tree, X[inside])
            found = elem >= 0
            if linear:  # the barycentrics at the vertices (no finite-element space is built)
                local, weights = self.mesh_cells[:, elem[found]], bary[found].T
            else:
                local, weights = fem.local_weights(self.space, elem[found], bary[found])  # (k, P)
            rows = np.broadcast_to(inside[found], local.shape).ravel()
            dofs, values = local.ravel(), weights.ravel()
        kept = column[dofs] >= 0  # boundary DOFs carry 0
        return sps.csr_matrix((values[kept], (rows[kept], column[dofs[kept]])), shape=(len(X), Q))

    @property
    def space(self) -> FESpace:
        from . import fem

        if self._space is None:
            self._space = fem.space_from_arrays(self.model.n, self.mesh_points, self.mesh_cells,
                                                int(self.element_order))
        return self._space


def check_points(points, n: int) -> np.ndarray:
    try:
        X = np.asarray(points, dtype=float)
    except (TypeError, ValueError):
        raise InputError("points", "must be an array of numbers") from None
    if X.ndim == 1 and n == 1:
        X = X[:, None]
    if X.ndim != 2 or X.shape[1] != n:
        raise InputError("points", f"must have shape (P, {n}), got {X.shape}")
    if not np.all(np.isfinite(X)):
        raise InputError("points", "must be finite")
    return X


def _check_shapes(model: Model, a: dict[str, np.ndarray]) -> None:
    q, n = a["nodes"].shape if a["nodes"].ndim == 2 else (-1, -1)
    if n != model.n:
        raise InputError("arrays.nodes", f"must have shape (Q, {model.n})")
    size = a["basis"].shape[1] if a["basis"].ndim == 2 else -1
    expected = {"weights": (q,), "basis": (q, size), "projector": (size, q), "propagator_fp": (q, size),
                "propagator_k": (q, size), "eigenvalues": (size,), "node_index": (q,), "element_order": ()}
    for name, shape in expected.items():
        if a[name].shape != shape:
            raise InputError(f"arrays.{name}", f"has shape {a[name].shape}, expected {shape}")
    if a["mesh_points"].ndim != 2 or a["mesh_points"].shape[0] != model.n or a["mesh_cells"].ndim != 2:
        raise InputError("arrays.mesh_points", f"must be ({model.n}, Np) with cells (k, Nc)")
    for name in ARRAY_NAMES:
        if a[name].dtype.kind == "f" and not np.all(np.isfinite(a[name])):
            raise InputError(f"arrays.{name}", "contains NaN or infinity")
    if np.any(a["weights"] <= 0):
        raise InputError("arrays.weights", "must be positive")


def _check_frame(model: Model, stored: np.ndarray | None) -> None:
    """A moving frame's arrays must be the frame's: a file solved before frames (with f itself) is
    the same only where f(c₀) = 0."""

    frame = affine_frame(model)
    if frame is None:
        return
    offset = frame.offset
    found = np.zeros_like(offset) if stored is None and not np.any(offset) else stored
    if found is None or np.shape(found) != offset.shape or not np.allclose(found, offset, rtol=1e-12, atol=0):
        raise InputError("arrays.frame", "these offline arrays were not solved in the moving frame this "
                                         "model follows its state in (engine/frame.py): precompute the spec "
                                         "again")


# -- precompute ---------------------------------------------------------------------------------
def precompute(model: Model, workers: int = 1, progress: Progress | None = None, *,
               space: Callable[[Model], Discretisation] = finite_element_space,
               basis: Callable[[Discretisation, int], OrthonormalBasis] = dirichlet_eigenbasis,
               propagators: Callable[..., tuple[np.ndarray, np.ndarray]] = sdirk_propagators,
               scheduler: str | None = None, atlas_sink: Sink | None = None) -> OfflineModel:
    """Nodes, basis and propagators of ``model`` (seed 002 §5 offline stage), from the three builders;
    the propagators' solves on ``workers`` local processes or the Dask cluster at ``scheduler``
    (solver/offline/distributed.py).  ``atlas_sink(k, K, rows)``: an atlas's centres go there as they are
    solved instead of being kept (solver/engine/atlas.py ``solve_atlas``; a store's ``ModelWriter.rows``)."""
    if not isinstance(workers, int) or workers < 1:
        raise InputError("workers", "must be a positive integer")
    spec = model.spec.discretization
    disc = space(model)

    # an atlas where the drift depends on a coordinate the ball must move along (solver/engine/atlas.py);
    # its lattice first: a region too large is refused before any solve
    grid = model_lattice(model, disc.arrays.get("mesh_points")) if needs_atlas(model) else None
    home_progress = atlas_progress = progress
    if grid is not None and progress is not None:  # one count over the home ball's and every centre's
        total = spec.basis * (1 + grid.size)

        def home_progress(done, _):
            progress(done, total)

        def atlas_progress(done, _):
            progress(spec.basis + done, total)
    phi = basis(disc, spec.basis)
    where = {} if scheduler is None else {"scheduler": scheduler}
    prop_fp, prop_k = propagators(disc, phi, model.dt, spec.substeps, workers, home_progress, **where)
    for name, arr in (("propagator_fp", prop_fp), ("propagator_k", prop_k)):
        if not np.all(np.isfinite(arr)):
            raise SpecError("discretization", f"{name} is not finite: refine the mesh or the substeps")
    check_stable(model, disc.nodes, disc.weights, phi.values, phi.projector, prop_fp)

    found = OfflineModel(
        model=model, nodes=disc.nodes, weights=disc.weights, basis=phi.values, projector=phi.projector,
        propagator_fp=prop_fp, propagator_k=prop_k, eigenvalues=phi.eigenvalues, **disc.arrays,
        generator=galerkin_generator(phi.values, disc.fokker_planck, disc.mass, disc.weights),
        _space=disc.space)
    if grid is not None:

        attach_solved(found, solve_atlas(model, disc, phi, space, grid, workers, atlas_progress, scheduler,
                                         sink=atlas_sink), grid)
    return found


def default_workers() -> int:
    return max(1, min(4, (multiprocessing.cpu_count() or 1)))


__all__ = ["ARRAY_NAMES", "Discretisation", "OfflineArrays", "OfflineModel", "default_workers",
           "dirichlet_eigenbasis", "finite_element_space", "precompute", "sdirk_propagators"]
