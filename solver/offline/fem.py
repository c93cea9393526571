"""Finite elements on the ball B_R(c) for the operators of the offline stage.

Weak forms (u = v = 0 on ∂B_R, seed 002 (5.31), seed 001 §3), with a = GQGᵀ constant SPD:

    Fokker–Planck  (L u, v)   = −½ ∫ a∇u·∇v + ∫ u f·∇v              (L u = ½ a:∇²u − div(f u))
    Kolmogorov     (L_K u, v) = (L u, v) − ∫ q u v,   q = ½ hᵀR⁻¹h     (L_K = L − q)

because −f·∇u − (div f) u = −div(f u): the two operators differ only by the potential q.
Densities live at the interior degrees of freedom ("nodes"); the mass matrix is lumped
(row sums), which for P1 (any n), for P2 on intervals (Simpson weights h/6, 4h/6, h/6) and for
P2 plus the cubic bubble on triangles (``[discretization] element = "bubble"`` in 2-D, the
mass-lumped element of Cohen, Joly and Tordjman: nodes at the vertices, edge midpoints and
centroid, weights |T|/20, 2|T|/15, 9|T|/20) and for P2 plus the cubic face bubbles and the quartic
interior bubble on tetrahedra (``element = "bubble"`` in 3-D, the 15-node degree-2 mass-lumped
tetrahedron of Chin-Joe-Kong, Mulder and Van Veldhuizen, J. Eng. Math. 35, 1999: nodes at the
vertices, edge midpoints, face centroids and centroid, weights 17|T|/840, 4|T|/105, 27|T|/280,
32|T|/105, exact for cubics; tests/solver/offline/test_fem_bubble.py derives the weights with SymPy)
gives positive quadrature weights, so pointwise products at the nodes are exact in the discrete L²
inner product.  scikit-fem's P2+bubble triangle is hierarchical (the bubble is added to the P2
functions), so every matrix is taken to the nodal (Lagrange) basis ψ = φ P⁻¹, P_ij = φ_j(x_i):
A ↦ P⁻ᵀ A P⁻¹; its tetrahedron (``ElementTetCCR``) is nodal at those 15 points already.

Meshes: n = 1 a uniform interval mesh; n = 2 concentric rings of 6i points triangulated by
Delaunay (near-equilateral triangles, boundary vertices on the circle), or with ``[domain] follow`` a
square lattice of about as many points (moves by whole steps meet the old vertices); n = 3 the
scikit-fem ball (refined, vertices pushed to the sphere).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sps
from scipy.spatial import Delaunay
from skfem import (
    Basis,
    BilinearForm,
    ElementLineP1,
    ElementLineP2,
    ElementTetCCR,
    ElementTetP1,
    ElementTriCCR,
    ElementTriP1,
    Mesh,
    MeshLine,
    MeshTet,
    MeshTri,
    asm,
)
from skfem.helpers import dot, grad

from ..defaults import default_refinements
from ..errors import SpecError
from .basis import DENSE_NODES

# Interior degrees of freedom per basis function when the mesh is not given (Q ≈ 2N).  The online
# step costs ~2·Q·N flops per observation.  Chosen by measurement (bench/default_mesh.py,
# bench/results/default-mesh.md): of Q/N ≈ 1.25, 1.5 and 2, only 2 keeps the largest mean gap ≤ 1e-3 on
# every bundled 1-D model (the two-peaked √(1+x²) sensor: 4.4e-2, 3.0e-3, 4.3e-6; the cubic sensor
# 3.2e-4, 1.7e-4, 6.2e-5).  A spec may set ``mesh`` to trade the margin for speed (the cubic example).
NODES_PER_MODE = {1: 2.0, 2: 2.0, 3: 2.0}
# Up to DENSE_NODES the basis comes from a dense eigensolve, beyond from shift-invert Lanczos
# (solver/offline/basis.py).  MAX_NODES bounds what a spec may ask for: the 3-D ball refined five times
# (41727 nodes), N = 1000: its eigensolve takes ~8 min and 2.6 GB, the whole precompute ~25 min and
# 3.5 GB on one process (bench/results/3d.md).  A default mesh stays within the dense solver.
MAX_NODES = 50000
# Interior vertices of the ball refined r times.
BALL_INTERIOR = {1: 7, 2: 63, 3: 575, 4: 4991, 5: 41727}
# Interior DOFs of the P2 + bubbles tetrahedra on the same balls (interior vertices + edges + faces +
# tetrahedra); refinement 4 is listed so that a service's node limit quotes its true size, and refused.
BALL_INTERIOR_BUBBLE = {1: 239, 2: 2047, 3: 17023, 4: 139007}
MAX_BUBBLE_REFINEMENTS = 3


@dataclass(frozen=True)
class FESpace:
    """A mesh of B_R, its finite-element basis and the interior DOFs where densities live."""

    mesh: Mesh
    basis: Basis
    interior: np.ndarray  # (Q,) indices of interior DOFs
    order: int
    to_nodal: sps.csr_matrix | None = None  # P⁻¹ (2-D P2+bubble): nodal values -> element coefficients

    @property
    def nodes(self) -> np.ndarray:
        """Coordinates of the interior DOFs, shape (Q, n)."""
        return self.basis.doflocs[:, self.interior].T

    def nodal(self, matrix: sps.spmatrix) -> sps.csr_matrix:
        """A form's matrix in the nodal basis (P⁻ᵀ A P⁻¹; A itself for a Lagrange element)."""
        if self.to_nodal is None:
            return sps.csr_matrix(matrix)
        return (self.to_nodal.T @ matrix @ self.to_nodal).tocsr()


def element_for(n: int, order: int):
    """Effective order 2: P2 on intervals (its lumped mass is Simpson's rule), P2 plus bubbles on
    triangles and tetrahedra (positive lumped weights, module docstring); P1 otherwise."""
    if n == 1:
        return ElementLineP2() if order == 2 else ElementLineP1()
    if n == 2:
        return ElementTriCCR() if order == 2 else ElementTriP1()
    return ElementTetCCR() if order == 2 else ElementTetP1()


def effective_order(n: int, order: int, element: str = "lagrange") -> int:
    """The degree the element family gives ``order`` (``[discretization] element``): 1-D Lagrange P1
    or P2; 2-D and 3-D P1, or P2 + bubbles with element = "bubble"."""
    if n == 1:
        return order
    return 2 if order == 2 and element == "bubble" else 1


def _space(mesh: Mesh, n: int, order: int) -> FESpace:
    """The basis on ``mesh``, its interior DOFs and (2-D order 2) the map to the nodal basis; the
    bubbles' DOF locations are their triangles' centroids."""
    basis = Basis(mesh, element_for(n, order))
    interior = np.asarray(basis.complement_dofs(basis.get_dofs()))
    to_nodal = None
    if n == 2 and order == 2:
        bubbles = basis.element_dofs[-1]  # the last local DOF of each triangle
        centroids = mesh.p[:, mesh.t].mean(axis=1)
        basis.doflocs[:, bubbles] = centroids
        # P = I but for the bubble rows: every function at its triangle's centroid (the P2 functions
        # are nodal at the vertices and midpoints, where the bubble vanishes)
        at = basis.probes(centroids).tocsr()  # (triangles, DOFs)
        at.data[np.abs(at.data) < 1e-14] = 0.0
        at.eliminate_zeros()
        rows, cols = at.nonzero()
        values = np.asarray(at[rows, cols]).ravel()
        diag = np.asarray(at[np.arange(len(bubbles)), bubbles]).ravel()
        off = cols != bubbles[rows]
        # P⁻¹: identity rows, and for a bubble row b: e_b/P_bb − Σ_j P_bj e_j/P_bb (j not a bubble)
        plain = np.setdiff1d(np.arange(basis.N), bubbles)
        inv_rows = np.concatenate([plain, bubbles, bubbles[rows[off]]])
        inv_cols = np.concatenate([plain, bubbles, cols[off]])
        inv_vals = np.concatenate([np.ones(basis.N - len(bubbles)), 1.0 / diag,
                                   -values[off] / diag[rows[off]]])
        to_nodal = sps.csr_matrix((inv_vals, (inv_rows, inv_cols)), shape=(basis.N, basis.N))
    return FESpace(mesh=mesh, basis=basis, interior=interior, order=order, to_nodal=to_nodal)


# -- meshes of the ball ------------------------------------------------------------------------
def interval_mesh(center: np.ndarray, radius: float, cells_per_radius: int) -> MeshLine:
    x = np.linspace(-radius, radius, 2 * cells_per_radius + 1) + center[0]
    return MeshLine(x)


def ring_points(rings: int) -> np.ndarray:
    """Unit-disk points on rings r = i/rings with 6i points each (hexagonal-like density)."""
    pts = [np.zeros((1, 2))]
    for i in range(1, rings + 1):
        k = 6 * i
        angle = 2 * np.pi * (np.arange(k) + 0.5 * (i % 2)) / k
        pts.append(i / rings * np.column_stack([np.cos(angle), np.sin(angle)]))
    return np.vstack(pts)


def disk_mesh(center: np.ndarray, radius: float, rings: int) -> MeshTri:
    unit = ring_points(rings)
    tri = Delaunay(unit).simplices
    return MeshTri(np.ascontiguousarray((radius * unit + center).T), np.ascontiguousarray(tri.T))


def lattice_disk_points(rings: int) -> tuple[np.ndarray, float]:
    """Unit-disk points of a square lattice of step h (about as many as the ring mesh's: h = √(π/3)/rings)
    inside |p| < 1 − h/2, and ~2π/h points on the circle; (points, h)."""
    h = float(np.sqrt(np.pi / 3.0) / rings)
    k = int(np.floor(1.0 / h))
    i, j = np.meshgrid(np.arange(-k, k + 1), np.arange(-k, k + 1), indexing="ij")
    grid = h * np.column_stack([i.ravel(), j.ravel()])
    grid = grid[np.linalg.norm(grid, axis=1) < 1.0 - 0.5 * h]
    count = max(12, int(np.ceil(2 * np.pi / h)))
    angle = 2 * np.pi * np.arange(count) / count
    return np.vstack([grid, np.column_stack([np.cos(angle), np.sin(angle)])]), h


def lattice_disk_mesh(center: np.ndarray, radius: float, rings: int) -> MeshTri:
    """The disk triangulated on a square lattice (interior vertices c + R·h·(i, j)), so that a ball moved
    by whole lattice steps has the same interior vertices where the two overlap ([domain] follow:
    the carry reads them off instead of interpolating).  Delaunay on slightly sheared points gives
    every lattice square the same diagonal."""
    unit, h = lattice_disk_points(rings)
    sheared = unit + np.column_stack([1e-6 * h * unit[:, 1], np.zeros(len(unit))])
    tri = Delaunay(sheared).simplices
    return MeshTri(np.ascontiguousarray((radius * unit + center).T), np.ascontiguousarray(tri.T))


def ball_mesh(center: np.ndarray, radius: float, refinements: int) -> MeshTet:
    """scikit-fem's ball, refined with boundary vertices projected onto the sphere."""
    mesh = MeshTet.init_ball(0)
    for _ in range(refinements):
        mesh = mesh.refined()
        p = mesh.p.copy()
        on_boundary = mesh.boundary_nodes()
        p[:, on_boundary] /= np.linalg.norm(p[:, on_boundary], axis=0)
        mesh = MeshTet(p, mesh.t)
    return MeshTet(radius * mesh.p + center[:, None], mesh.t)


def interior_count(n: int, order: int, resolution: int) -> int:
    """Number of interior DOFs of the mesh of the given resolution (no mesh is built for n < 3)."""
    if n == 1:
        return (2 * resolution) * order - 1
    if n == 2:  # rings: V = 3r(r+1)+1 vertices, 6r² triangles, 9r²+3r edges (6r of them on the circle)
        vertices = 3 * resolution * (resolution - 1) + 1
        edges, triangles = 9 * resolution ** 2 - 3 * resolution, 6 * resolution ** 2
        return vertices if order == 1 else vertices + edges + triangles
    return (BALL_INTERIOR if order == 1 else BALL_INTERIOR_BUBBLE).get(resolution, MAX_NODES + 1)


def default_resolution(n: int, order: int, size: int) -> int:
    """Smallest resolution whose interior DOF count reaches NODES_PER_MODE[n] · N; if that one is
    beyond the dense eigensolver (DENSE_NODES), the previous one when it still has N nodes (coarse
    3-D steps: a finer ball is for a spec that asks for it with ``mesh``)."""
    target = NODES_PER_MODE[n] * size
    resolution = 1 if n == 3 else 2
    while interior_count(n, order, resolution) < target:
        resolution += 1
    if interior_count(n, order, resolution) > DENSE_NODES and resolution > 1:
        if interior_count(n, order, resolution - 1) >= size:
            resolution -= 1
    return resolution


def mesh_resolution(spec, size: int | None = None) -> int:
    """The mesh of ``spec`` (a ModelSpec) for ``size`` basis functions (default: its basis): its own, or
    where left out the one measured for its dimension, element and ball (solver/defaults.py), else the
    smallest with about NODES_PER_MODE · N nodes (:func:`default_resolution`)."""
    disc, n = spec.discretization, len(spec.state)
    if disc.mesh is not None:
        return disc.mesh
    element = spec.element()
    fixed = default_refinements(n, element, bool(spec.domain.follow))
    return fixed or default_resolution(n, effective_order(n, disc.order, element),
                                       disc.basis if size is None else size)


def planned_nodes(spec) -> int:
    """How many interior nodes the spec's discretisation will have (no mesh is built): what a service
    checks against its limit before it accepts a precompute.  A mesh-free spec (more than three state
    variables, or a method without offline arrays) plans none."""
    from ..registry import mesh_free

    if mesh_free(spec):
        return 0
    n = len(spec.state)
    order = effective_order(n, spec.discretization.order, spec.element())
    return interior_count(n, order, mesh_resolution(spec))


def build(n: int, center: np.ndarray, radius: float, resolution: int, order: int,
          lattice: bool = False, shape: np.ndarray | None = None) -> FESpace:
    """Mesh B_R with ``resolution`` (cells across the radius / rings / refinements) for elements of
    ``order`` (the effective one, :func:`effective_order`); ``lattice``: the 2-D disk on a square
    lattice (a ball that follows the state); ``shape`` L: the ball mapped by x = c + L(x − c) (an
    ellipsoid, ``[domain] shape``: affine images of the elements, the same elements)."""
    if n == 1:
        mesh = interval_mesh(center, radius, resolution)
    elif n == 2:
        mesh = (lattice_disk_mesh if lattice else disk_mesh)(center, radius, resolution)
    elif n == 3:
        mesh = ball_mesh(center, radius, resolution)
    else:
        raise SpecError("state", f"dimension {n} is not supported (1, 2 or 3)")
    if shape is not None:
        c = np.asarray(center, dtype=float)[:, None]
        mesh = type(mesh)(np.ascontiguousarray(c + np.asarray(shape, dtype=float) @ (mesh.p - c)), mesh.t)
    return _space(mesh, n, order)


def discretise(model, size: int | None = None) -> FESpace:
    """The discretisation of ``model``'s ball; checks there are at least N interior DOFs."""
    spec = model.spec.discretization
    size = spec.basis if size is None else size
    order = effective_order(model.n, spec.order, model.spec.element())
    if model.n == 3 and spec.mesh is not None and spec.mesh > max(BALL_INTERIOR):
        raise SpecError("discretization.mesh",
                        f"in 3-D mesh counts refinements of the ball, at most {max(BALL_INTERIOR)}")
    if model.n == 3 and order == 2 and spec.mesh is not None and spec.mesh > MAX_BUBBLE_REFINEMENTS:
        raise SpecError("discretization.mesh", "in 3-D the P2 + bubbles element allows at most "
                        f"{MAX_BUBBLE_REFINEMENTS} refinements ({BALL_INTERIOR_BUBBLE[3]} nodes); "
                        "finer balls are for element = \"lagrange\"")
    cells = mesh_resolution(model.spec, size)
    nodes = interior_count(model.n, order, cells)
    if nodes > MAX_NODES:
        field = "discretization.mesh" if spec.mesh else "discretization.basis"
        raise SpecError(field, f"needs {nodes} mesh nodes, more than the {MAX_NODES} allowed; "
                               "use a smaller basis or mesh")
    disc = build(model.n, model.center, model.radius, cells, order,
                 lattice=bool(model.spec.domain.follow), shape=model.shape)
    if len(disc.interior) < size:
        raise SpecError("discretization.basis",
                        f"{size} basis functions need at least as many interior mesh nodes; "
                        f"mesh={cells} gives {len(disc.interior)}")
    return disc


# -- forms ---------------------------------------------------------------------------------------
def _at(fn, x: np.ndarray) -> np.ndarray:
    """Evaluate a (P, n) -> (P, ...) model function at scikit-fem quadrature points x (n, E, q)."""
    pts = x.reshape(x.shape[0], -1).T
    values = np.asarray(fn(pts), dtype=float)
    if values.ndim == 1:
        return values.reshape(x.shape[1:])
    return values.T.reshape((values.shape[1],) + x.shape[1:])


def stiffness(basis: Basis, a: np.ndarray) -> sps.csr_matrix:
    """∫ a∇u·∇v."""
    @BilinearForm
    def form(u, v, w):
        return dot(np.einsum("ij,j...->i...", a, grad(u)), grad(v))

    return asm(form, basis).tocsr()


def advection(basis: Basis, f) -> sps.csr_matrix:
    """∫ u f·∇v (the weak form of −div(f u))."""
    @BilinearForm
    def form(u, v, w):
        return u * dot(_at(f, w.x), grad(v))

    return asm(form, basis).tocsr()


def reaction(basis: Basis, q) -> sps.csr_matrix:
    """∫ q u v."""
    @BilinearForm
    def form(u, v, w):
        return _at(q, w.x) * u * v

    return asm(form, basis).tocsr()


def lumped_mass(basis: Basis, disc: FESpace | None = None) -> np.ndarray:
    """Row sums of the (nodal) mass matrix: ∫ψ_i (positive for P1, interval P2, triangle P2+bubble)."""
    @BilinearForm
    def form(u, v, w):
        return u * v

    mass = asm(form, basis)
    weights = np.asarray((mass if disc is None else disc.nodal(mass)).sum(axis=1)).ravel()
    if np.any(weights <= 0):
        raise SpecError("discretization.order", "the lumped mass of this element is not positive")
    return weights


def consistent_mass(basis: Basis) -> sps.csr_matrix:
    """∫ u v."""
    @BilinearForm
    def form(u, v, w):
        return u * v

    return asm(form, basis).tocsr()


def streamline_tau(b: np.ndarray, h: np.ndarray, a: np.ndarray) -> np.ndarray:
    """The SUPG parameter τ = h ξ(Pe) / (2|b|) at points (b: (n, ...) drift, h: element size),
    ξ(Pe) = coth Pe − 1/Pe, Pe = |b| h / (2ε), ε = ½ bᵀab/|b|² the diffusion along the streamline
    (Brooks & Hughes 1982; ξ → 1 without diffusion along b, ξ ≈ Pe/3 where diffusion dominates)."""
    speed = np.sqrt(np.sum(b * b, axis=0))
    moving = speed > 1e-300
    along = 0.5 * np.einsum("i...,ij,j...->...", b, a, b) / np.where(moving, speed ** 2, 1.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        pe = np.where(along > 0, speed * h / (2.0 * np.where(along > 0, along, 1.0)), np.inf)
        xi = np.where(pe < 1e-3, pe / 3.0, 1.0 / np.tanh(np.minimum(pe, 50.0)) - 1.0 / pe)
        return np.where(moving, h * xi / (2.0 * np.where(moving, speed, 1.0)), 0.0)


def supg(basis: Basis, model, drift=None) -> tuple[sps.csr_matrix, sps.csr_matrix, sps.csr_matrix]:
    """The streamline-upwind Petrov–Galerkin terms of ∂u/∂t = L u − q u (L u = ½a:∇²u − div(f u))
    on P1 elements: the test function v + τ f·∇v applied to the strong residual

        r(u) = u_t − ½ a:∇²u + f·∇u + (div f + q) u,

    whose second derivatives a P1 function lacks inside an element; they are those of its recovered
    gradient g_k = W⁻¹ ∫ ψ ∂_k u (lumped L² projection, so a:∇²u ≈ Σ a_kl ∂_l g_k): without them the
    scheme is consistent only to O(h) (measured while building it: the predicted mean of
    bench/results/psd.md was 5e-2, 3.4e-2, 2.2e-2 off at N = 300, 600, 1200; with them 3.5e-3, 2.0e-3,
    1.1e-3).  With τ from :func:`streamline_tau`,

        S_M(u, v) = ∫ τ u f·∇v,   S_A(u, v) = ∫ τ (f·∇u + (div f) u − ½ Σ a_kl ∂_l g_k(u)) f·∇v,
        S_q(u, v) = ∫ τ q u f·∇v,

    and (M + S_M) du/dt = (A − S_A) u for Fokker–Planck, (A_K − S_A − S_q) u for Kolmogorov, A and A_K
    the Galerkin matrices (``drift``: f, or the moving frame's, engine/frame.py).  Returns (S_M, S_A, S_q)."""
    a = np.asarray(model.a, dtype=float)
    f = model.f if drift is None else drift
    n = a.shape[0]

    def streamline(w):
        b = _at(f, w.x)
        return b, streamline_tau(b, np.broadcast_to(np.asarray(w.h), b.shape[1:]), a)

    def weighted(coefficient):  # ∫ τ c u f·∇v
        @BilinearForm
        def form(u, v, w):
            b, tau = streamline(w)
            return tau * (1.0 if coefficient is None else _at(coefficient, w.x)) * u * dot(b, grad(v))
        return asm(form, basis).tocsr()

    @BilinearForm
    def transport_form(u, v, w):
        b, tau = streamline(w)
        return tau * dot(b, grad(u)) * dot(b, grad(v))

    def derivative(k):  # ∫ ψ_i ∂_k u
        @BilinearForm
        def form(u, v, w):
            return grad(u)[k] * v
        return asm(form, basis).tocsr()

    def streamline_derivative(l):  # ∫ τ ∂_l u f·∇v
        @BilinearForm
        def form(u, v, w):
            b, tau = streamline(w)
            return tau * grad(u)[l] * dot(b, grad(v))
        return asm(form, basis).tocsr()

    recover = sps.diags(1.0 / np.asarray(consistent_mass(basis).sum(axis=1)).ravel())
    gradients = [recover @ derivative(k) for k in range(n)]
    along = [streamline_derivative(l) for l in range(n)]
    second = sum(a[k, l] * (along[l] @ gradients[k]) for k in range(n) for l in range(n) if a[k, l] != 0.0)
    s_a = asm(transport_form, basis) + weighted(model.div_f) - 0.5 * second
    return weighted(None), s_a.tocsr(), weighted(model.half_hRh)


@dataclass(frozen=True)
class Operators:
    """Interior blocks: lumped mass w, ½ ā-stiffness K of the basis's operator (ā = a where a is
    positive definite, Model.basis_diffusion), Fokker–Planck A_fp and Kolmogorov A_k, so that
    w ⊙ du/dt = A u is the semi-discrete equation (seed 002 (5.31)); with ``scheme = "consistent"``
    ``mass`` is the consistent mass M, with ``"supg"`` the stabilised M + S_M, and M du/dt = A u."""

    weights: np.ndarray
    half_stiffness: sps.csr_matrix
    fokker_planck: sps.csr_matrix
    kolmogorov: sps.csr_matrix
    mass: sps.csr_matrix | None = None


def assemble(model, disc: FESpace) -> Operators:
    idx = disc.interior
    basis = disc.basis
    half_k = disc.nodal(0.5 * stiffness(basis, model.a))
    ab = model.basis_diffusion
    half_basis = half_k if np.array_equal(ab, model.a) else disc.nodal(0.5 * stiffness(basis, ab))
    from ..engine.frame import drift_of

    drift = drift_of(model)  # f, or f(x) − f(c₀) in a frame moving with the mean's ODE
    fp = -half_k + disc.nodal(advection(basis, drift))
    kol = fp - disc.nodal(reaction(basis, model.half_hRh))
    mass, scheme = None, model.spec.scheme()
    if scheme != "galerkin":
        if model.n == 1 or (disc.order != 1 and scheme == "supg"):
            raise SpecError("discretization.scheme",
                            f"{scheme} is built for the P1 elements of 2-D and 3-D balls")
        mass = disc.nodal(consistent_mass(basis))  # (P2 + bubble: in the nodal basis, as A)
    if scheme == "supg":
        s_mass, s_fp, s_q = supg(basis, model, drift)
        mass = mass + s_mass
        fp, kol = fp - s_fp, kol - s_fp - s_q
    sub = lambda mat: mat[idx][:, idx].tocsr()  # noqa: E731 - Dirichlet: keep interior rows/cols
    return Operators(weights=lumped_mass(basis, disc)[idx], half_stiffness=sub(half_basis),
                     fokker_planck=sub(fp), kolmogorov=sub(kol), mass=None if mass is None else sub(mass))


# -- rebuilding and point location ---------------------------------------------------------------
def space_from_arrays(n: int, points: np.ndarray, cells: np.ndarray, order: int) -> FESpace:
    """The FESpace of stored mesh arrays (the interior DOFs are recomputed the same way)."""
    mesh_type = {1: MeshLine, 2: MeshTri, 3: MeshTet}[n]
    mesh = mesh_type(np.asarray(points, float), np.asarray(cells, dtype=np.int64))
    return _space(mesh, n, order)


def local_weights(space: FESpace, elem: np.ndarray, lam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The nodal basis functions of the order-2 elements ``elem`` at points with barycentrics ``lam``
    (P, n+1): (DOFs (k, P), values (k, P)), so that a function with nodal values u is
    Σ_j values[j] u[DOFs[j]] (P1's are the barycentrics themselves).  Triangle P2 + bubble:
    B = 27λ₀λ₁λ₂,  ψ_i = λ_i(2λ_i − 1) + B/9,  ψ_ij = 4λ_iλ_j − 4B/9,  ψ_c = B.  Tetrahedron P2 +
    bubbles: scikit-fem's nodal ``ElementTetCCR`` at the reference coordinates λ₁, λ₂, λ₃ (the mapping
    is affine, and λ is in the order of the mesh's vertices)."""
    n = lam.shape[1] - 1
    dofs = space.basis.element_dofs[:, elem]
    if n == 3:
        reference = np.ascontiguousarray(lam[:, 1:].T)  # (3, P)
        return dofs, np.stack([space.basis.elem.lbasis(reference, j)[0] for j in range(dofs.shape[0])])
    pairs = _edge_pairs(space)[:, :, elem]  # (3, 2, P): the vertices of each local edge
    B = 27.0 * lam[:, 0] * lam[:, 1] * lam[:, 2]
    rows = np.arange(len(elem))
    weights = [lam[:, i] * (2.0 * lam[:, i] - 1.0) + B / 9.0 for i in range(3)]
    weights += [4.0 * lam[rows, pairs[k, 0]] * lam[rows, pairs[k, 1]] - 4.0 * B / 9.0 for k in range(3)]
    weights.append(B)
    return dofs, np.stack(weights)


def _edge_pairs(space: FESpace) -> np.ndarray:
    """(3, 2, T): for each edge DOF of each triangle, the two local vertices whose midpoint it is."""
    cached = space.basis.__dict__.get("_yauyau_edge_pairs")
    if cached is not None:
        return cached
    mesh, dofs = space.mesh, space.basis.element_dofs
    corners = mesh.p[:, mesh.t]  # (2, 3, T)
    candidates = [(0, 1), (1, 2), (0, 2)]
    mids = np.stack([0.5 * (corners[:, a] + corners[:, b]) for a, b in candidates])  # (3 pairs, 2, T)
    out = np.empty((3, 2, mesh.t.shape[1]), dtype=int)
    for k in range(3):
        loc = space.basis.doflocs[:, dofs[3 + k]]  # (2, T)
        which = np.argmin(np.linalg.norm(mids - loc[None], axis=1), axis=0)
        out[k] = np.asarray(candidates).T[:, which]
    space.basis.__dict__["_yauyau_edge_pairs"] = out
    return out


def barycentric(points: np.ndarray, cells: np.ndarray, elem: np.ndarray, X: np.ndarray) -> np.ndarray:
    """Barycentric coordinates (P, k, n+1) of X (P, n) in candidate simplices elem (P, k): with the
    edges e_i = v_i − v_0 and r = X − v_0, λ = E⁻¹r by Cramer's rule (2-D: λ_1 = r×e_2 / e_1×e_2; 3-D:
    λ_i = r·(e_j × e_k) / det E, (i, j, k) cyclic), elementwise instead of a batched LAPACK solve of
    many 2×2 or 3×3 systems.  A cell of zero area or volume gets non-finite coordinates (no point is
    found in it), where the solve raised."""
    vert = points[:, cells[:, elem]]  # (n, n+1, P, k)
    v0 = vert[:, 0]
    e = vert[:, 1:] - v0[:, None]  # (n, n, P, k): e[c, i] is component c of edge i
    r = X.T[:, :, None] - v0  # (n, P, k)
    n = points.shape[0]
    with np.errstate(divide="ignore", invalid="ignore"):
        lam = _cramer(e, r, n)
        return np.concatenate([1.0 - lam.sum(axis=-1, keepdims=True), lam], axis=-1)


def _cramer(e: np.ndarray, r: np.ndarray, n: int) -> np.ndarray:
    """λ = E⁻¹r (P, k, n) for the edges e (n, n, P, k) and the points r (n, P, k) (barycentric)."""
    if n == 2:
        det = e[0, 0] * e[1, 1] - e[0, 1] * e[1, 0]
        lam = np.stack([(r[0] * e[1, 1] - r[1] * e[0, 1]) / det,
                        (e[0, 0] * r[1] - e[1, 0] * r[0]) / det], axis=-1)
    elif n == 3:
        edges = np.moveaxis(e, 1, 0)  # (edge, component, P, k)
        cross = [np.cross(edges[j], edges[k], axis=0) for j, k in ((1, 2), (2, 0), (0, 1))]
        det = np.einsum("cpk,cpk->pk", edges[0], cross[0])
        lam = np.stack([np.einsum("cpk,cpk->pk", r, c) / det for c in cross], axis=-1)
    else:
        edges = np.moveaxis(e, (0, 1), (-2, -1))  # (P, k, n, n)
        lam = np.linalg.solve(edges, np.moveaxis(r, 0, -1)[..., None])[..., 0]
    return lam


def locate(points: np.ndarray, cells: np.ndarray, tree, X: np.ndarray,
           candidates: tuple[int, ...] = (3, 8, 64)) -> tuple[np.ndarray, np.ndarray]:
    """Element index (−1 where none: outside the polygonal ball) and barycentrics of each point: the
    first element, nearest centroid first, that holds it, among ``candidates[0]`` centroids, then more
    for the points not found (a point on an edge or vertex shared by several elements may get any of
    them; the finite-element function has the same value there)."""
    n_cells = cells.shape[1]
    elem = np.full(len(X), -1)
    bary = np.zeros((len(X), cells.shape[0]))
    todo = np.arange(len(X))
    for k in candidates:
        if not len(todo):
            break
        k = min(k, n_cells)
        cand = tree.query(X[todo], k=k)[1].reshape(len(todo), k)
        lam = barycentric(points, cells, cand, X[todo])
        ok = lam.min(axis=-1) >= -1e-10
        hit = ok.any(axis=1)
        first = ok.argmax(axis=1)
        rows = todo[hit]
        elem[rows] = cand[hit, first[hit]]
        bary[rows] = np.clip(lam[hit, first[hit]], 0.0, 1.0)
        todo = todo[~hit]
    return elem, bary
