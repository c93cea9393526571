"""Solving and attaching an atlas of propagators (``[domain] region``; the lattice and the moves are
solver/engine/atlas.py): every lattice centre's e^{dt L_c}φ_k and generator, the home ball's basis on
each ball, solved as jobs (solver/offline/jobs.py) and checked like the home propagator.
"""

from __future__ import annotations

import uuid
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Callable

import numpy as np

from ..engine.atlas import Atlas, Lattice, Sink, model_lattice, point_label
from ..engine.semigroup import galerkin_generator
from ..errors import InputError, SpecError
from .jobs import Job, check_stable, propagate_jobs

if TYPE_CHECKING:  # types only
    from ..model import Model


@dataclass(frozen=True)
class AtlasArrays:
    """A solved atlas in memory: centres (K, n), propagators (K, Q, N), generators (K, N, N)."""

    centers: np.ndarray
    propagator_fp: np.ndarray
    generator: np.ndarray
    lattice: Lattice

    def load(self, k: int) -> dict[str, np.ndarray]:
        return {"propagator_fp": self.propagator_fp[k], "generator": self.generator[k]}


def solve_atlas(model: Model, disc: Any, phi: Any, space: Callable[[Any], Any], grid: Lattice,
                workers: int = 1, progress: Callable[[int, int], None] | None = None,
                scheduler: str | None = None, sink: Sink | None = None) -> AtlasArrays | None:
    """The propagator e^{dt L_c}φ_k and generator of every lattice centre c (module docstring), the
    home ball's basis ``phi`` on each; the solves as Dask tasks (offline/distributed.py).  With ``sink``
    each centre k goes to ``sink(k, K, {name: row})`` (names :data:`LAZY_NAMES`) as soon as it is
    solved, in any order, and nothing is kept (returns None): a store writes the atlas centre by centre."""
    centers = grid.centers()
    home = np.asarray(model.center, dtype=float)
    jobs, nodes = [], []  # (a centre's discretisation is not kept: its job holds the matrices needed)
    for center in centers:
        moved = model.translated(center)
        d = space(moved)
        tol = 1e-9 * max(1.0, float(np.abs(center).max()))
        moved_nodes = disc.nodes + (center - home)
        if d.nodes.shape != disc.nodes.shape or not np.allclose(d.nodes, moved_nodes, rtol=0, atol=tol):
            raise SpecError("domain.region", "the translated mesh does not match the home mesh node for node")
        nodes.append(d.nodes)
        jobs.append(Job(d.fokker_planck, None, disc.weights, model.dt, model.spec.discretization.substeps,
                         phi.values, token=uuid.uuid4().hex, mass=d.mass))
    K, N = len(centers), phi.values.shape[1]
    kept = None if sink is not None else AtlasArrays(
        centers=centers, propagator_fp=np.empty((K,) + phi.values.shape), generator=np.empty((K, N, N)),
        lattice=grid)

    def finished(k: int, fp: np.ndarray, _: Any) -> None:
        center, job = centers[k], jobs[k]
        if not np.all(np.isfinite(fp)):
            raise SpecError("discretization", f"the propagator of the atlas centre {point_label(center)} is "
                                              "not finite: refine the mesh or the substeps")
        check_stable(model.translated(center), nodes[k], disc.weights, phi.values, phi.projector, fp)
        generator = galerkin_generator(phi.values, job.fokker_planck, job.mass, disc.weights)
        if kept is None:
            sink(k, K, {"atlas_propagator_fp": fp, "atlas_generator": generator})
        else:
            kept.propagator_fp[k], kept.generator[k] = fp, generator

    propagate_jobs(jobs, workers, progress, scheduler, finished=finished)
    return kept


def attach_solved(offline: Any, solved: AtlasArrays | None, grid: Lattice) -> None:
    """``offline.atlas`` from a just-solved atlas: every centre in memory, or (None) none, the centres
    having gone to a store as they were solved (read them back with the stored model)."""
    if solved is None:
        def load(k: int) -> dict[str, np.ndarray]:
            raise InputError("model", "this atlas was written to the model store centre by centre as it was "
                                      "solved: open the model from the store to filter with it")

        offline.atlas = Atlas(offline, grid, load)
        return
    offline.atlas = Atlas(offline, solved.lattice, solved.load)
    offline.atlas.solved = solved


def attach_stored(offline: Any, centers: Any, lazy: Any) -> None:
    """``offline.atlas`` read from a store: ``lazy.read(name, k)`` gives centre k's row of a stored
    (K, ...) array; the stored centres must be the spec's lattice."""
    grid = model_lattice(offline.model, offline.mesh_points)
    if centers is None or lazy is None:
        raise InputError("arrays.atlas_centers", "is missing: this file was saved without its atlas; run "
                                                 "yauyau precompute again")
    centers = np.asarray(centers, dtype=float)
    expected = grid.centers()
    if centers.shape != expected.shape or not np.allclose(centers, expected, rtol=0, atol=1e-9 * (
            1.0 + float(np.abs(expected).max()))):
        raise InputError("arrays.atlas_centers", f"hold {len(centers)} centres that are not the spec's "
                                                 f"lattice of {len(expected)}: the file was altered")

    def load(k: int) -> dict[str, np.ndarray]:
        return {"propagator_fp": lazy.read("atlas_propagator_fp", k),
                "generator": lazy.read("atlas_generator", k)}

    offline.atlas = Atlas(offline, grid, load)
