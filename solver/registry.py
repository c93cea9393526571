"""The filter methods, by name: the one list the spec, the CLI, the service and ``make_filter`` use.

It also holds the other names a filter is configured with (the yau-yau step's forms and precisions,
the policies on a degenerate density), so that the CLI and the HTTP schemas list them from here: this
module imports nothing heavy (the CLI's start-up).

A method is a class implementing the filter contract (solver/filtering.py) in its own module, with a
module-level ``build(model, offline=None, **options)`` that makes it; the module is imported only when
the method is used.  Adding an exact filter is one module plus one line here.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Method:
    name: str
    module: str  # has build(model, offline=None, **options); imported on first use
    cls: str  # the filter class (for documentation and isinstance checks)
    needs_offline: bool  # built from the precomputed arrays (the offline stage)
    summary: str


REGISTRY: dict[str, Method] = {m.name: m for m in (
    Method("yau-yau", "yauyau.solver.engine.filter", "YauYauFilter", True,
           "the general Yau-Yau algorithm: offline propagators, online updates (Yau, 2008, section 5)"),
    Method("kalman-bucy", "yauyau.solver.exact.kalman_bucy", "KalmanBucyFilter", False,
           "exact for affine f and h with a Gaussian prior"),
    Method("yau-hu", "yauyau.solver.exact.yau_hu", "YauHuFilter", False,
           "exact for Yau filtering systems: Kolmogorov equation and ODEs (Yau & Lai, 2003, Theorem 3.1)"),
    Method("yau-jia", "yauyau.solver.exact.yau_jia", "YauJiaFilter", False,
           "affine-plus-gradient drift, nonlinear h with quadratic V: Gaussian-mixture ODE filter, no mesh "
           "(Yau & Jia, 2005, Theorem 4.2)"),
    Method("yau-niu", "yauyau.solver.qmc.yau_niu", "YauNiuFilter", False,
           "quasi-Monte Carlo Yau-Yau method for any model up to 100 states: QMC points, Euler kernel, "
           "log-domain update, local resampling-restart (Yau & Niu, 2025)"),
    Method("wei-norman", "yauyau.solver.exact.wei_norman", "WeiNormanFilter", True,
           "exact for the finite-dimensional estimation algebras of Shi et al. (2017), Theorem 1"),
)}

AUTO = "auto"  # resolved once, at precompute, by the estimation-algebra analysis
METHODS: tuple[str, ...] = (AUTO, *REGISTRY)

FORMS = ("stable", "literal")  # the yau-yau step (solver/engine/filter.py); stable is the default
PRECISIONS = ("double", "single")  # the yau-yau matrix-vector products ([discretization] precision)
POLICIES = ("stop", "reinitialise")  # what a degenerate density does (solver/recovery.py)
DEFAULT_POLICY = "stop"


MAX_STATES = 100  # the spec's cap on state variables: past MAX_GRID_STATES, method "yau-niu" only
MAX_GRID_STATES = 6  # the cap for every other method
MAX_GRID_OBSERVATIONS = 16  # the other methods' cap on observation components (yau-niu: MAX_STATES)
QMC_ONLY = "yau-niu"  # the method that runs past MAX_GRID_STATES

MAX_MESH_DIMENSION = 3  # the general engine's finite elements: intervals, disks, balls


def mesh_free(spec) -> bool:
    """True when the spec gets no offline stage (no mesh, no basis): more than three state variables,
    or a method named in the spec that needs no precomputed arrays (kalman-bucy, yau-hu, yau-jia).
    A mesh-free method filters it."""
    method = REGISTRY.get(spec.method)
    return len(spec.state) > MAX_MESH_DIMENSION or (method is not None and not method.needs_offline)


def check_method(name: object) -> str:
    """``name`` if it is a registered method or ``auto``; else ValueError naming the choices."""
    if not isinstance(name, str) or not (name == AUTO or name in REGISTRY):
        raise ValueError(f"must be one of {', '.join((AUTO, *REGISTRY))}, got {name!r}")
    return name
