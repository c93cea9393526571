"""The analysis report: conditions, estimation algebra, the recommended method and why, with the
papers it rests on named in words; rendered as text (``yauyau analyze``) or as a dict (``--json``
and POST /v1/analyze).

For dx = f dt + G dv, dy = h dt + dw (a = GQGᵀ, E dw dwᵀ = R dt) the DMZ equation reads
dσ = L0 σ dt + Σ_i L_i σ dy_i with (seed 002 (2.2), seed 004 (2))

    L0 = ½ Σ a_ij ∂_i∂_j − Σ f_i ∂_i − div f − ½ hᵀR⁻¹h,      L_i = multiplication by (R⁻¹h)_i.

:func:`analyze` decides the conditions of :mod:`.conditions` (at most half of the time limit) and
builds the estimation algebra of :mod:`.algebra` (the rest), then :func:`recommend_method_from`
chooses kalman-bucy | yau-hu | wei-norman | yau-jia | yau-yau | yau-niu (past 3 states).
"""

from __future__ import annotations

import dataclasses
import textwrap
import time
from dataclasses import dataclass, field
from typing import Any, Callable

from ..expressions import nonsmooth_functions
from ..model import Model
from ..papers import cite, cite_full, reference
from ..registry import MAX_MESH_DIMENSION
from .algebra import DEFAULT_MAX_DEPTH, DEFAULT_MAX_DIMENSION, EstimationAlgebra, bounded_algebra
from .budget import DEFAULT_MAX_SIZE, DEFAULT_TIME_LIMIT, Budget, bounded
from .conditions import Condition, Facts, all_of, decide_conditions, observed_coordinate
from .operators import DIGITS, ZERO_POINTS, is_identity, show, show_operator

# the papers every report rests on: (C1)-(C3) from seed 000, E and its algorithm from seed 002, the
# non-maximal-rank class from seed 004
CITED = ("000", "001", "002", "004")
YAU_HU = cite_full("000", "Theorem 3.1")  # the direct method: DMZ -> Kolmogorov equation + ODEs
WEI_NORMAN = cite_full("004", "Theorem 1")
YAU_YAU = cite_full("002", "Section 5")
YAU_JIA = cite_full("001", "Theorem 4.2")
YAU_NIU = ("S.-T. Yau and Y.-S. Niu, An Improved Yau-Yau Algorithm for High Dimensional Nonlinear Filtering "
           "Problems, arXiv:2509.16896 (2025)")
CLASS_004 = cite("004")  # the non-maximal-rank class (i)-(v) of seed 004 §III


@dataclass
class AnalysisReport:
    model: str
    state: list[str]
    wong_matrix: list[list[str]]
    wong_constant: bool | None
    eta: str
    notes: list[str]
    conditions: dict[str, Condition]
    seed004: dict[str, Condition]
    algebra: EstimationAlgebra
    algebra_basis: list[str]
    method: str
    reason: str
    summary: str = ""  # two or three plain sentences: what the model is, which filter, what to look at
    elapsed: float = 0.0  # seconds the analysis took
    references: list[str] = field(default_factory=lambda: list(CITED))  # keys of solver.papers.PAPERS

    def to_dict(self) -> dict[str, Any]:
        alg = self.algebra
        return {
            "model": self.model, "state": self.state,
            "wong_matrix": self.wong_matrix, "wong_constant": self.wong_constant,
            "eta": self.eta, "notes": self.notes,
            "conditions": {k: c.to_dict() for k, c in self.conditions.items()},
            "wei_norman_conditions": {k: c.to_dict() for k, c in self.seed004.items()},
            "estimation_algebra": {
                "closed": alg.closed, "dimension": alg.dimension, "basis": self.algebra_basis,
                "linear_rank": alg.linear_rank, "maximal_rank": alg.maximal_rank,
                "rounds": alg.rounds, "max_depth": alg.max_depth, "max_dimension": alg.max_dimension,
                "stopped_by": alg.stopped_by, "time_limit": alg.time_limit, "max_size": alg.max_size,
                "rank_test": "exact over Q" if alg.exact else f"numeric, {DIGITS} digits at random points"},
            "summary": self.summary,
            "recommendation": {"method": self.method, "reason": self.reason},
            "elapsed_s": round(self.elapsed, 3),
            "references": [reference(key) for key in self.references],
        }

    def render(self) -> str:
        d = self.to_dict()
        width = max(len(e) for row in self.wong_matrix for e in row)
        lines = [*textwrap.wrap(self.summary, 100), "",
                 f"model: {self.model}   state: {', '.join(self.state)}", "",
                 "Wong matrix Omega (omega_ij = df_j/dx_i - df_i/dx_j):"]
        lines += ["  [ " + "  ".join(e.rjust(width) for e in row) + " ]" for row in self.wong_matrix]
        constant = _mark(self.wong_constant, "yes", "no", "undecided")
        lines += [f"  constant: {constant}", "", f"eta = {self.eta}"]
        lines += [f"  note: {note}" for note in self.notes]
        lines += ["", "conditions:"]
        lines += [f"  [{_mark(c.holds)}] {c.title}" + (f"  ({c.detail})" if c.detail else "")
                  for c in self.conditions.values()]
        if self.seed004:
            lines += [f"  {CLASS_004} class, items:"]
            lines += [f"    [{_mark(c.holds)}] {k}" + (f"  ({c.detail})" if c.detail else "")
                      for k, c in self.seed004.items()]
        alg = d["estimation_algebra"]
        lines += ["", "estimation algebra E = <L0, h_1, ..., h_m>:"]
        if alg["closed"]:
            lines += [f"  dimension {alg['dimension']}, linear rank {alg['linear_rank']}, "
                      f"{'maximal' if alg['maximal_rank'] else 'non-maximal'} rank  ({alg['rank_test']})"]
            lines += [f"  basis: {{{', '.join(alg['basis'])}}}"]
        else:
            lines += [f"  {alg['stopped_by']}"] if (alg["stopped_by"] or "").startswith("not computed") else [
                      f"  does not close within {alg['stopped_by']} "
                      f"({alg['rounds']} rounds of brackets, {len(alg['basis'])} independent elements found)"]
        lines += ["", f"recommended method: {self.method}", f"  reason: {self.reason}",
                  f"  (analysis took {self.elapsed:.2f} s)"]
        lines += ["", "references:"] + [f"  {_reference_line(key)}" for key in self.references]
        return "\n".join(lines)


def _reference_line(key: str) -> str:
    doi = reference(key)["doi"]
    return cite_full(key) + (f", doi:{doi}" if doi else "")


def _mark(holds: bool | None, yes: str = "x", no: str = " ", undecided: str = "?") -> str:
    return undecided if holds is None else (yes if holds else no)


def analyze(model: Model, max_depth: int = DEFAULT_MAX_DEPTH, max_dimension: int = DEFAULT_MAX_DIMENSION,
            time_limit: float | None = DEFAULT_TIME_LIMIT,
            max_size: int | None = DEFAULT_MAX_SIZE,
            on_conditions: Callable[[Facts], None] | None = None) -> AnalysisReport:
    """Wong matrix, η, conditions, estimation algebra and the recommended exact/general method.

    Bounded: the conditions get at most half of `time_limit` (they usually take milliseconds), the
    algebra the rest; an item that reaches a bound is reported undecided (holds None) and the
    algebra as not closing within that bound.  A single SymPy call cannot be interrupted, so the
    size cap keeps each one small; the report may come back after the deadline (minutes, for a
    ``sp.simplify`` of nested trigonometric functions): a caller that needs the deadline to hold runs
    it in a process of its own (:mod:`.isolated`).  ``on_conditions(facts)`` is called once the
    conditions are decided, before the algebra (the isolated process sends them to its parent).
    """
    start = time.monotonic()
    rough = nonsmooth_functions([*model.drift, *model.observation])
    if rough:
        report = _nonsmooth_report(model, rough, max_depth, max_dimension)
        report.elapsed = time.monotonic() - start
        return report
    half = None if time_limit is None else time_limit / 2
    name = None if time_limit is None else f"time {time_limit:g} s (half of it for the conditions)"
    with bounded(Budget(half, max_size, start, name)) as budget:
        facts = decide_conditions(model)
        facts.numeric = budget.numeric_zero_tests
    if on_conditions is not None:
        on_conditions(facts)
    with bounded(Budget(time_limit, max_size, start)) as budget:
        algebra = bounded_algebra(model, max_depth, max_dimension)
        basis = [show_operator(op, model, label)
                 for op, label in zip(algebra.basis, algebra.labels, strict=True)]
        facts.numeric += budget.numeric_zero_tests
        report = _report(model, facts, algebra, basis)  # simplifies for display only while time is left
    report.elapsed = time.monotonic() - start
    return report


def stopped_report(model: Model, facts: Facts | None, time_limit: float, note: str,
                   max_depth: int = DEFAULT_MAX_DEPTH, max_dimension: int = DEFAULT_MAX_DIMENSION,
                   max_size: int | None = DEFAULT_MAX_SIZE) -> AnalysisReport:
    """The report of an analysis stopped from outside at its time limit (its process was killed):
    what the analysis itself reports when its deadline stops it, built from the conditions it had
    decided (``facts``, None when it was stopped before them): every other condition undecided
    within ``time {time_limit} s``, the algebra not closing within it, the Wong matrix and η not
    computed, ``note`` added (how it was stopped).  Without decided facts the recommendation is the
    general engine (method yau-yau), which is always valid."""
    bound = f"time {time_limit:g} s"
    if facts is None:
        k = observed_coordinate(model)
        facts = Facts(k=k, structure_holds=None if k is not None and is_identity(model.a) else False)
    if None in (facts.c1, facts.c2, facts.c3, facts.linear, facts.structure_holds, facts.yau_jia):
        if bound not in facts.stopped_by:
            facts.stopped_by.append(bound)
    algebra = EstimationAlgebra(closed=False, dimension=None, basis=[], labels=[], linear_rank=None,
                                maximal_rank=None, rounds=0, max_depth=max_depth, max_dimension=max_dimension,
                                exact=False, stopped_by=bound, time_limit=time_limit, max_size=max_size)
    report = _report(model, facts, algebra, [])
    shown = f"not computed within {bound}"
    report.wong_matrix = [[shown] * model.n for _ in range(model.n)]
    if not facts.eta_why:
        report.eta = shown
    report.notes.append(note)
    return report


def _nonsmooth_report(model: Model, rough: list[str], max_depth: int, max_dimension: int) -> AnalysisReport:
    """f or h uses abs/sign/min/max: the exact filters need derivatives of f and h (div f in eta,
    the brackets of E), which are distributions here (a DiracDelta at the kink), so none applies;
    the general engine needs only values."""
    names = ", ".join(rough)
    verb = "is" if len(rough) == 1 else "are"
    why = f"not computed: f or h uses {names}, not differentiable everywhere"
    facts = Facts(c1=False, c2=False, c3=False, linear=False, structure_holds=False, yau_jia=False)
    algebra = EstimationAlgebra(closed=False, dimension=None, basis=[], labels=[], linear_rank=None,
                                maximal_rank=None, rounds=0, max_depth=max_depth, max_dimension=max_dimension,
                                exact=False, stopped_by=why)
    report = _report(model, facts, algebra, [])
    report.wong_matrix = [["not computed"] * model.n for _ in range(model.n)]
    report.eta = why
    report.conditions = {k: dataclasses.replace(c, detail=f"needs smooth f and h; {names} {verb} not "
                                                           "differentiable everywhere")
                         for k, c in report.conditions.items()}
    report.notes.append(f"{names}: continuous but not differentiable everywhere; the exact filters need "
                        "smooth f and h, the general engine only values (the EKF/UKF Jacobians use the "
                        "derivative almost everywhere)")
    return report


def _report(model: Model, facts: Facts, algebra: EstimationAlgebra, basis: list[str]) -> AnalysisReport:
    a_is_identity = is_identity(model.a)
    notes = []
    if not is_identity(model.R):
        notes.append("R != I: eta and L0 use h^T R^-1 h")
    if not a_is_identity:
        notes.append("a != I: the papers assume a = I (g orthogonal); eta here is f^T a^-1 f + div f + "
                     "h^T R^-1 h and (C'1) is tested on a J^T - J a "
                     "(the Wong matrix of z = L^-1 x, a = L L^T); "
                     f"the {CLASS_004} class is only tested for a = I")
    if facts.numeric:
        notes.append(f"non-polynomial zero tests are numeric ({DIGITS} digits at {ZERO_POINTS} "
                     "random points)")
    undecided = ""
    if facts.stopped_by:
        undecided = f"not decided within {' / '.join(facts.stopped_by)}"
        notes.append(f"some conditions were {undecided}")
    k = facts.k
    conditions = {
        "yau_filtering_system": Condition(
            facts.c1, "" if facts.c1 is not None else undecided,
            "(C'1) the Wong matrix Omega is constant, i.e. the drift is affine plus a gradient "
            f"(C1) ({cite('000', 'Theorem 2.1')})"),
        "h_affine": Condition(facts.c2, "" if facts.c2 is not None else undecided,
                              f"(C2) the sensor h is affine in x ({cite('000', '(2.7)')}, needed by "
                              "Theorem 3.1)"),
        "eta_quadratic": Condition(facts.c3, facts.eta_why or ("" if facts.c3 is not None else undecided),
                                   "(C3) eta = f^T a^-1 f + div f + h^T R^-1 h is a polynomial of degree "
                                   "<= 2 "
                                   f"({cite('000', '(2.8)')}, needed by Theorem 3.1)"),
        "linear": Condition(facts.linear, "" if facts.linear is not None else undecided,
                            "linear model: f and h affine, a Gaussian prior stays Gaussian (Kalman-Bucy)"),
        "wei_norman_structure": Condition(
            facts.structure_holds,
            ("" if k is None else f"x_k = {model.spec.state[k]}")
            + ("" if facts.structure_holds is not None else f"; {undecided}"),
            f"{CLASS_004} (I), (II), (v): omega_kj = 0, eta quadratic in x_k plus a function of the others, "
            "h affine in x_k only"),
    }
    conditions["yau_jia"] = Condition(
        facts.yau_jia, facts.yau_jia_detail if facts.yau_jia is not None else undecided,
        f"{cite('001', '(4.1), (4.2)')}: f = Lx + l + a grad(phi) and V = h^T R^-1 h + tr(a D^2 phi) + "
        "grad(phi)^T a grad(phi) + 2 (Lx + l).grad(phi) quadratic: the Kolmogorov equation maps Gaussians "
        "to Gaussians, h may be nonlinear (Yau-Jia)")
    if facts.seed004:
        conditions["wei_norman_class"] = Condition(all(c.holds for c in facts.seed004.values()), "",
                                                   f"{CLASS_004} class: conditions (i)-(v)")
    yau = all_of([facts.c1, facts.c2, facts.c3])
    method, reason = recommend_method_from(model, facts.linear is True, yau is True,
                                           facts.structure_holds is True, a_is_identity,
                                           yau_jia=facts.yau_jia is True)
    if method in ("yau-yau", "yau-niu") and undecided:
        reason += f" (the exact-filter conditions were {undecided}; the general engine is always valid)"
    n = model.n
    shown = f"not computed within {' / '.join(facts.stopped_by)}" if facts.stopped_by else "not computed"
    return AnalysisReport(
        model=model.spec.name, state=list(model.spec.state),
        wong_matrix=[[show(facts.omega[i, j], model) if facts.omega is not None else shown
                      for j in range(n)] for i in range(n)],
        wong_constant=facts.wong_constant,
        eta=show(facts.eta, model) if facts.eta is not None else facts.eta_why or shown,
        notes=notes, conditions=conditions, seed004=facts.seed004, algebra=algebra, algebra_basis=basis,
        method=method, reason=reason, summary=plain_summary(model, method, facts, algebra, a_is_identity))


# Cost per observation of the general engine over the exact filter, measured side by side on the
# bundled examples (python -m bench; docs/benchmarks.md "exact ODE filters vs the engine").
CHEAPER = {"kalman-bucy": 47, "yau-hu": 35}


def plain_summary(model: Model, method: str, facts: Facts, algebra: EstimationAlgebra,
                  a_is_identity: bool) -> str:
    """Two or three sentences a newcomer understands: what kind of model this is, which filter runs
    and why in words, and what to read off the output."""
    n, m = model.n, model.m
    shape = f"{n} state variable{'s' if n > 1 else ''} observed through {m} sensor{'s' if m > 1 else ''}"
    if method == "kalman-bucy":
        first = (f"The model ({shape}) is linear with Gaussian noise and a Gaussian prior: the "
                 f"Kalman-Bucy filter is exact here and about {CHEAPER['kalman-bucy']}x cheaper per "
                 "observation than the general engine, so yauyau uses it.")
    elif method == "yau-hu":
        first = (f"The model ({shape}) is a Yau filtering system: its drift is affine plus a gradient, "
                 "its sensor is linear and eta is quadratic, so the conditional density is carried exactly "
                 "by ordinary differential equations (the Yau-Hu direct method, about "
                 f"{CHEAPER['yau-hu']}x cheaper per observation than the general engine).")
    elif method == "yau-jia":
        first = (f"The model ({shape}) has an affine-plus-gradient drift and a sensor whose energy "
                 "h^T R^-1 h is quadratic (Yau and Jia, 2005): the density is carried as a Gaussian mixture "
                 "moved exactly by ODEs, and the nonlinear sensor enters each step with a controlled "
                 "second-order error; no mesh, so any dimension up to 6.")
    elif method == "yau-niu":
        first = (f"The model ({shape}) has no exact finite-dimensional filter and more states than the "
                 f"general engine's finite elements take ({MAX_MESH_DIMENSION}): the quasi-Monte Carlo "
                 "Yau-Yau method (Yau and Niu, 2025) carries the density on low-discrepancy points with "
                 "log weights, restarting them where they stop covering it; its accuracy grows with "
                 "[discretization] points.")
    elif method == "wei-norman":
        first = (f"The model ({shape}) belongs to the non-maximal-rank class of Shi, Chen, Dong and Yau "
                 "(2017): its estimation algebra is finite-dimensional, so the Wei-Norman filter is exact "
                 "and needs no mesh.")
    else:
        yau = all_of([facts.c1, facts.c2, facts.c3])
        exact_if_a_were_identity = facts.linear or yau or facts.structure_holds
        if not a_is_identity and exact_if_a_were_identity:
            why = "an exact filter would apply if the diffusion were the identity, but it is not"
        elif (algebra.stopped_by or "").startswith("not computed: "):
            why = algebra.stopped_by.removeprefix("not computed: ") + ", so no exact filter applies"
        elif algebra.closed is False or algebra.stopped_by:
            why = ("its estimation algebra does not close in a few dimensions, so no exact "
                   "finite-dimensional filter applies")
        else:
            why = "no exact finite-dimensional filter applies"
        first = (f"The model ({shape}) is nonlinear: {why}. The general Yau-Yau algorithm computes the "
                 "conditional density on a basis: the Kolmogorov equation is solved once offline, and each "
                 "observation then costs a pointwise factor and a small matrix product.")
    sentences = [first]
    if method == "kalman-bucy":
        sentences.append("The conditional density stays Gaussian, so its mean and covariance say all there "
                         "is to say.")
    elif method in ("yau-hu", "wei-norman"):
        sentences.append("No mesh or basis is needed; the density need not be Gaussian (it can have "
                         "two peaks), so read its quantiles and mode too (yauyau filter --quantiles "
                         "0.05,0.5,0.95 --mode).")
    if facts.c2 is False:
        sentences.append("The sensor is nonlinear, so the conditional density need not be Gaussian and its "
                         "mean and covariance can mislead (for a sensor like x^2 the mean sits between two "
                         "peaks): read the quantiles and the mode too (yauyau filter --quantiles "
                         "0.05,0.5,0.95 --mode).")
    return " ".join(sentences)


def recommend_method_from(model: Model, linear: bool, yau: bool, seed004: bool,
                          a_is_identity: bool, yau_jia: bool = False) -> tuple[str, str]:
    gaussian = model.spec.initial.kind == "gaussian"
    if linear and gaussian:
        return "kalman-bucy", "f and h are affine and the prior is Gaussian: the Kalman-Bucy filter is exact"
    if yau and a_is_identity:
        return "yau-hu", ("Yau filtering system with (C1), (C2), (C3): the Yau-Hu direct method reduces the "
                          "DMZ equation to a Kolmogorov equation and ODEs "
                          f"({YAU_HU}; {cite('002', 'Section 4')})")
    if seed004 and a_is_identity:
        return "wei-norman", (f"{CLASS_004} class: E = {{L0, D1, x1, 1}} is finite dimensional; "
                              "u = e^r0 e^(r1 x1) e^(r2 D1) e^(t L0) sigma0, the Wei-Norman filter "
                              f"({WEI_NORMAN})")
    if yau_jia and model.spec.initial.kind in ("gaussian", "mixture"):
        return "yau-jia", ("f is affine plus a gradient and V is quadratic (seed 001 (4.1), (4.2)): the "
                           "Kolmogorov equation maps Gaussians to Gaussians by ODEs, the nonlinear sensor "
                           f"enters as a Gaussian-mixture update with controlled error ({YAU_JIA})")
    if model.n > MAX_MESH_DIMENSION:  # past the engine's finite elements: the QMC method
        return "yau-niu", (f"no finite-dimensional exact filter applies and the model has {model.n} "
                           f"states, past the general engine's {MAX_MESH_DIMENSION}-D finite elements: the "
                           f"quasi-Monte Carlo Yau-Yau method on points, any dimension ({YAU_NIU})")
    if (linear or yau or seed004) and not a_is_identity:
        return "yau-yau", "an exact filter would apply with a = I, but a != I here: the general engine"
    return "yau-yau", ("no finite-dimensional exact filter applies: the general Yau-Yau algorithm "
                      f"({YAU_YAU})")


def recommend_method(report: AnalysisReport) -> tuple[str, str]:
    """The method the analysis recommends and why: kalman-bucy | yau-hu | wei-norman | yau-jia | yau-yau
    | yau-niu (no exact filter, more than 3 states)."""
    return report.method, report.reason
