"""The discretisation a spec gets for what it leaves out, per dimension, chosen by measurement.

``[discretization] element`` and ``mesh`` both left out in 3-D (order 2, a scheme other than "supg"): P2 +
bubbles (``"bubble"``), on a following ball (``[domain] follow``) on the ball refined three times, on a
fixed ball on the mesh of about 2N nodes (solver/offline/fem.py ``default_resolution``).  Elsewhere the
element is Lagrange and the mesh has about 2N nodes.  The measurement (bench/results/default-3d.md,
``python -m bench.default_3d``), the 3-D linear model of issue 36 against the exact Kalman filter,
500 steps, seeds 5 and 6 (rms mean gap / worst variance error):

* its plain spec, a fixed ball of radius 4 with basis 500: P1 on 4991 nodes (the old default) 2.3e-2 /
  67%; P2 + bubbles on 2047 nodes (the ball refined twice, the default now) 6.6e-3 / 21%; refined three
  times (17023 nodes) 1.4e-2 / 55% at 17x the precompute: on a fixed ball the basis of 500 is what
  limits (bench/results/3d.md: P1 with basis 1500 on the same 4991 nodes reaches 4.4e-3 / 7.7%);
* a ball of radius 3.5 following the posterior, basis 600: P2 + bubbles on 2047 nodes 6.8e-3 / 9.7%, on
  17023 nodes (the default now) 3.8e-3 / 4.1%: on a ball centred on the posterior the mesh limits.

``follow`` itself stays off unless set: it changes what ``radius`` means and is refused for a drift that
neither shifts nor is affine; and on the plain spec's ball (radius 4, basis 500, the ball refined twice)
following measured no closer (9.0e-3 / 23%).  1-D and 2-D keep their defaults (1-D: P2 with about 2N
nodes, bench/results/default-mesh.md; 2-D: P1, where P2 + bubbles is closer at the same cost,
tests/solver/offline/test_fem_bubble.py, but the 2-D tests and examples are measured on P1).

A default that changes what is computed enters the model's content hash: :func:`stored_discretization`
writes the element and the mesh it chose into the canonical JSON, so a plain 3-D spec gets the id of the
spec that states what it computes (never the stored arrays of the old default), reading the canonical JSON
back gives the same spec, and the id of every spec whose numbers did not change stays (but an explicit
``element = "lagrange"`` in 3-D without ``mesh``: absent now means the bubble, so it is written out).

``P1_REFINEMENTS`` and ``FOLLOW_REFINEMENTS`` are the rule ``yauyau precompute`` warns with
(solver/check.py ``coarser_than_measured``).
"""

from __future__ import annotations

from typing import Any

from .registry import mesh_free

# the element a spec that leaves element and mesh out gets, per dimension, where the order is 2 and the
# scheme is not "supg" (built on P1)
ELEMENT = {1: "lagrange", 2: "lagrange", 3: "bubble"}
# 3-D refinements of the ball for P2 + bubbles on a following ball when mesh is left out (17023 nodes)
FOLLOW_REFINEMENTS = 3
# 3-D P1 below this many refinements (41727 nodes at 5) is measured farther from the exact filter than
# P2 + bubbles (bench/results/3d.md: a following ball of radius 3.5, basis 1000: refined four times 6.3e-3 /
# 5.2%, five times 2.0e-3 / 4.4%)
P1_REFINEMENTS = 5


def default_element(n: int, order: int, scheme: str, mesh: int | None) -> str:
    """The element of a spec that leaves ``element`` out: ELEMENT[n] where the spec leaves the mesh out
    too and the P2 + bubbles element can be used (order 2, not SUPG), else Lagrange (a spec that sets
    the mesh keeps the element it was written for)."""
    if order != 2 or scheme == "supg" or mesh is not None:
        return "lagrange"
    return ELEMENT.get(n, "lagrange")


def default_refinements(n: int, element: str, follow: bool) -> int | None:
    """The mesh of a spec that leaves ``mesh`` out where the measurement fixes it (3-D P2 + bubbles on a
    following ball: three refinements); None where it follows from the basis (about 2N nodes)."""
    return FOLLOW_REFINEMENTS if n == 3 and element == "bubble" and follow else None


def stored_discretization(spec: Any, table: dict[str, Any]) -> None:
    """The ``[discretization]`` table of ``spec`` as it enters the content hash, edited in place.  Lagrange
    where it is also the default is left out (ids of specs from before ``element`` stay); an element or
    mesh chosen here is written out, so the id says what is computed and reading the canonical JSON
    back gives the same spec.  A mesh-free spec keeps its table (no mesh is built).  ``points`` left out
    (yau-niu's default) is not written, so ids of specs from before it stay."""
    if table.get("points") is None:
        table.pop("points", None)
    if mesh_free(spec):
        chosen = "lagrange"
    else:
        chosen = default_element(spec.n, table["order"], spec.scheme(), table["mesh"])
    element = table["element"] or chosen
    if element == "lagrange" and chosen == "lagrange":
        del table["element"]
        return
    table["element"] = element
    if table["mesh"] is None and not mesh_free(spec):
        table["mesh"] = default_refinements(spec.n, element, bool(spec.domain.follow))
