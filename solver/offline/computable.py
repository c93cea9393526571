"""Whether the general engine's discretisation of a spec can be computed in floating point at all.

Checked before any solve (``yauyau precompute``: exit 2; ``POST /v1/models``: 422 before a job starts),
from the spec and its mesh's element width only — the mesh of the unit ball at the spec's resolution,
scaled, never the propagators.  Each rule is what breaks the offline stage, measured (issue 35):

* **a radius below what the mesh resolves** (``domain.radius``): elements narrower than a double
  tells apart around the centre, or so narrow that 1/h² overflows (radius 1e-300: the propagators
  were NaN);
* **a diffusion beyond one step's precision** (``diffusion``): a·dt, a/h² or dt·a/h² past 1/ε ≈ 4.5e15
  (``diffusion = [[1e308]]``: a/h² overflowed, the propagators were NaN);
* **a drift beyond one step's precision** (``discretization``): dt·|f|/h past 1/ε — the drift carries
  the density across more elements in one step than a double has significant digits, and the
  propagator creates mass (``-x**64`` on radius 7: mass ×1e30 from the first step, also with basis
  48 where the engine stored a model degenerate from its first step; ``exp(exp(x))`` on radius 6:
  ×1e84).

Below these limits a propagator may still be too stiff for its mesh (a drift whose stationary
density is narrower than the elements): ``solver.offline.check_stable`` refuses it after the solve,
from the mass it creates.  Values that overflow on the ball (f, h, hᵀR⁻¹h) are refused by the spec
itself (solver/spec.py).
"""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np

from ..errors import SpecError

PRECISION_LIMIT = 1.0 / np.finfo(float).eps  # ≈ 4.5e15: a step past this keeps no significant digit
SEPARATION = 64.0  # distinct nodes must be this many float spacings apart around the centre


def check_computable(model) -> None:
    """SpecError naming the field when the engine's offline stage of ``model`` cannot be computed in
    floating point (the rules above); nothing for a mesh-free model (no offline stage)."""
    from ..registry import mesh_free

    if mesh_free(model.spec):
        return
    width, unit_nodes = element_width(model)
    _check_radius(model, width)
    _check_diffusion(model, width)
    _check_drift(model, width, unit_nodes)


def element_width(model) -> tuple[float, np.ndarray]:
    """The smallest distance between two mesh nodes of the model's domain (the ball of its radius,
    mapped by its shape), and the unit ball's nodes it was measured on."""
    from .fem import effective_order, mesh_resolution

    spec = model.spec
    order = effective_order(model.n, spec.discretization.order, spec.element())
    unit_width, nodes = _unit_mesh(model.n, mesh_resolution(spec), order, bool(spec.domain.follow))
    squeeze = 1.0 if model.shape is None else float(np.linalg.svd(model.shape, compute_uv=False).min())
    return model.radius * unit_width * squeeze, nodes


@lru_cache(maxsize=32)
def _unit_mesh(n: int, resolution: int, order: int, lattice: bool) -> tuple[float, np.ndarray]:
    from scipy.spatial import cKDTree

    from .fem import build

    nodes = build(n, np.zeros(n), 1.0, resolution, order, lattice=lattice).nodes
    distances, _ = cKDTree(nodes).query(nodes, k=2)
    nodes.setflags(write=False)
    return float(distances[:, 1].min()), nodes


def _check_radius(model, width: float) -> None:
    extent = float(np.abs(model.center).max()) + model.radius * _stretch(model)
    spacing = float(np.spacing(max(extent, np.finfo(float).tiny)))
    overflow = not width >= math.sqrt(1.0 / np.finfo(float).max)  # 1/h^2 beyond the float range
    if overflow or width < SEPARATION * spacing:
        a = float(np.linalg.eigvalsh(np.asarray(model.a, dtype=float)).max())
        # the narrowest element that keeps its nodes apart and dt*a/h^2 within a double's precision
        narrowest = max(SEPARATION * spacing, math.sqrt(model.dt * a / PRECISION_LIMIT), 1e-150)
        why = ("1/h^2 overflows" if overflow else
               f"a double around the centre tells apart only points {spacing:.3g} apart")
        raise SpecError("domain.radius", f"{model.radius:g} is below what the mesh can resolve: its elements "
                                         f"would be {width:.3g} wide and {why}; use a radius of at least "
                                         f"{model.radius * narrowest / width:.3g} (or fewer basis functions "
                                         "/ a coarser mesh)")


def _stretch(model) -> float:
    return 1.0 if model.shape is None else float(np.linalg.svd(model.shape, compute_uv=False).max())


def _check_diffusion(model, width: float) -> None:
    a = np.float64(np.linalg.eigvalsh(np.asarray(model.a, dtype=float)).max())
    dt = model.dt
    with np.errstate(over="ignore", divide="ignore"):
        per_step, per_width = a * dt, a / np.float64(width) ** 2
        stiffness = per_width * dt
    if not (math.isfinite(per_step) and math.isfinite(per_width) and stiffness <= PRECISION_LIMIT):
        raise SpecError("diffusion", (
            f"its largest eigenvalue {a:.3g} is beyond one step's precision: over dt = {dt:g} and elements "
            f"{width:.3g} wide, dt*a/h^2 = {stiffness:.3g} (at most {PRECISION_LIMIT:.3g}, 1/eps of a double;"
            f" a*dt = {per_step:.3g}, a/h^2 = {per_width:.3g}): lower the diffusion, lower discretization.dt "
            "or use a larger domain.radius"))


def _check_drift(model, width: float, unit_nodes: np.ndarray) -> None:
    offsets = model.radius * unit_nodes
    points = model.center + (offsets if model.shape is None else offsets @ model.shape.T)
    with np.errstate(all="ignore"):
        speed = np.linalg.norm(np.atleast_2d(np.asarray(model.f(points), dtype=float)), axis=1)
        fastest = float(np.nanmax(speed)) if speed.size else 0.0
        crossed = model.dt * fastest / width
    if not (math.isfinite(crossed) and crossed <= PRECISION_LIMIT):
        where = points[int(np.nanargmax(speed))]
        at = ", ".join(f"{name} = {v:.3g}" for name, v in zip(model.spec.state, where, strict=True))
        raise SpecError("discretization", (
            f"the Fokker-Planck propagator would be unstable: the drift reaches |f| = {fastest:.3g} on the "
            f"ball (at {at}), so one step of dt = {model.dt:g} carries the density across {crossed:.3g} "
            f"elements {width:.3g} wide, more than a double resolves ({PRECISION_LIMIT:.3g}): the propagator "
            "would create mass. Shrink domain.radius, lower discretization.dt or change the drift"))
