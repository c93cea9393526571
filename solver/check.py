"""Does the discretisation resolve the posterior this model will have?  Answered before any data.

``resolution_check(spec)`` simulates a few short paths of the model, filters them with the spec's
discretisation (the general engine, seed 002 §5) and compares the conditional means with a reference:
the exact Kalman filter when the model is linear with a Gaussian prior and increments (then the
reference is exact), otherwise the same engine at twice the basis (and its default mesh) — a finer
resolution whose own error is far smaller where the coarse one is off; if that reference degenerates
on some step it is doubled once more, and one that still does judges nothing (no basis passes against
it).  A suggested basis is compared with a reference at twice its own basis.  It reports the mean and the
largest gap, the fraction of degenerate steps, a verdict against ``target`` (on the mean gap, with no
degenerate step allowed) and, when it fails, the smallest basis of N·(1.5, 2, 3) that passes.  The
paths are simulated from the model itself, so the posterior they make is the one the data will make
when the model is right.

It also reports the fraction of the simulated paths whose state leaves the domain — the fixed ball
(or ellipsoid), or ``[domain] region`` for a ball that follows the state — and fails when any does:
a filter on a fixed ball cannot follow a state outside it and loses track (solver/watch.py), so the
report names the fix (``domain.follow = true``, a larger ``domain.radius``; a wider region).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from .defaults import FOLLOW_REFINEMENTS, P1_REFINEMENTS
from .errors import InputError, SpecError
from .registry import mesh_free

if TYPE_CHECKING:  # types only
    from .model import Model
    from .offline.pipeline import OfflineArrays
    from .spec import ModelSpec

DEFAULT_TARGET = 0.05
SCALES = (1.5, 2.0, 3.0)  # bases tried, relative to the spec's, when it fails


@dataclass
class Trial:
    basis: int
    nodes: int
    mean_gap: float
    max_gap: float
    degenerate: float  # fraction of degenerate steps
    rmse: float  # of the estimates against the simulated states
    ok: bool
    against: str = ""  # the reference it was compared with, when not the report's (a finer engine)
    regular_us: float = float("nan")  # measured µs per regular row (resolution_check(timed=True))
    irregular_us: float = float("nan")  # and per irregular row (gaps 0.5–1.5 dt)
    flow: str = ""  # the flow's form for irregular rows (solver/engine/semigroup.py)


@dataclass
class CheckReport:
    reference: str  # the filter compared with, in words
    target: float
    paths: int
    steps: int
    trials: list[Trial] = field(default_factory=list)
    reference_rmse: float = float("nan")
    reference_degenerate: float = 0.0  # the reference's own degenerate steps (then nothing passes)
    region: list[list[float]] | None = None  # [domain] region of a following ball
    covered: list[list[float]] | None = None  # the simulated states' range along each variable
    left: float = 0.0  # fraction of the simulated paths whose state leaves the domain (ball or region)
    domain: str = ""  # that domain, in words (with the fix when some path leaves it)
    left_at: int | None = None  # the first step where a path left it

    @property
    def ok(self) -> bool:
        """Resolved, and no simulated path left the domain."""
        return self.requested.ok and not self.left

    @property
    def rate_bound(self) -> float:
        """95% upper bound on the per-step rate of degenerate steps when none of the paths·steps
        simulated had one (the rule of three, 3/n): a run longer than ~1/bound steps may still meet one."""
        return 3.0 / (self.paths * self.steps)

    @property
    def requested(self) -> Trial:
        return self.trials[0]

    @property
    def suggested(self) -> int | None:
        """The smallest basis that passed (None: none of those tried)."""
        passing = [t.basis for t in self.trials if t.ok]
        return min(passing) if passing else None

    def to_dict(self) -> dict[str, Any]:
        return {"reference": self.reference, "target": self.target, "paths": self.paths, "steps": self.steps,
                "ok": self.ok, "resolved": self.requested.ok, "left_domain": self.left,
                "domain": self.domain, "left_at_step": self.left_at, "suggested_basis": self.suggested,
                "reference_rmse": self.reference_rmse,
                "reference_degenerate": self.reference_degenerate, "degenerate_rate_bound": self.rate_bound,
                "region": self.region, "covered": self.covered, "trials": [t.__dict__ for t in self.trials]}

    def render(self) -> str:
        r = self.requested
        lines = [f"resolution check: {self.paths} simulated paths of {self.steps} steps, "
                 f"reference: {self.reference}",
                 f"  basis {r.basis} ({r.nodes} nodes): mean gap {r.mean_gap:.3g}, largest {r.max_gap:.3g}, "
                 f"degenerate steps {r.degenerate:.1%}, RMSE {r.rmse:.3g} "
                 f"(reference {self.reference_rmse:.3g})"]
        if r.flow:
            lines.append(f"  cost per row: regular {r.regular_us:.1f} µs, irregular {r.irregular_us:.1f} µs "
                         f"({r.irregular_us / r.regular_us:.2f}x; flow {r.flow})")
        lines += self._left()
        if r.ok:
            lines.append(f"  {'OK' if self.ok else 'resolved'}: the mean gap is within the target "
                         f"{self.target:g}")
            lines.append(f"  no degenerate step in {self.paths * self.steps}: the rate is below "
                         f"{self.rate_bound:.2g} per step (95%); a longer run may still meet one "
                         "(check it with --steps)")
            lines += self._coverage()
            return "\n".join(lines)
        lines.append(f"  NOT RESOLVED: the target is a mean gap <= {self.target:g} with no degenerate step")
        if self.reference_degenerate:
            lines.append(f"  the reference itself degenerates on {self.reference_degenerate:.1%} of the "
                         "steps: no basis can be judged against it")
        for t in self.trials[1:]:
            versus = f" (against {t.against})" if t.against else ""
            lines.append(f"  basis {t.basis} ({t.nodes} nodes): mean gap {t.mean_gap:.3g}, degenerate "
                         f"{t.degenerate:.1%}{versus}{'  <- passes' if t.ok else ''}")
        suggestion = self.suggested
        if self.left and not suggestion:
            lines.append("  suggestion: the domain first (above): no basis helps while the state leaves it")
        else:
            lines.append(f"  suggestion: discretization.basis = {suggestion}" if suggestion else
                         "  suggestion: none of the bases tried passes: shrink domain.radius or refine the "
                         "mesh")
        return "\n".join(lines + self._coverage())

    def _left(self) -> list[str]:
        """The paths that left the domain (nothing when none did)."""
        if not self.left:
            return []
        count = int(round(self.left * self.paths))
        return [f"  NOT OK: {count} of {self.paths} simulated paths ({self.left:.0%}) leave {self.domain} "
                f"(the first at step {self.left_at})"]

    def _coverage(self) -> list[str]:
        """Where a following ball has a region: how much of it the simulated paths crossed (the atlas's
        other centres are not checked)."""
        if self.region is None or self.covered is None:
            return []
        pairs = list(zip(self.covered, self.region, strict=True))
        parts = [f"[{a:.3g}, {b:.3g}] of [{lo:g}, {hi:g}]" for (a, b), (lo, hi) in pairs]
        share = min((min(b, hi) - max(a, lo)) / (hi - lo) for (a, b), (lo, hi) in pairs)
        line = f"  the paths crossed {', '.join(parts)} of domain.region"
        if share < 0.9:
            line += (f" ({max(share, 0.0):.0%}): the centres beyond are not checked (a longer --steps "
                     "reaches them)")
        return [line]


def resolution_check(spec: ModelSpec, paths: int = 4, steps: int = 300, seed: int = 0,
                     target: float = DEFAULT_TARGET, suggest: bool = True,
                     offline: OfflineArrays | None = None,
                     exact_only: bool = False, timed: bool = False) -> CheckReport | None:
    """The check of the module docstring for a :class:`ModelSpec` (the general engine's discretisation).
    ``offline``: the spec's own offline arrays when they exist (not computed again).  ``exact_only``:
    None unless the reference is exact (a linear model: the check then costs a few filtered paths).
    ``timed``: also measure the spec's µs per regular and per irregular row (solver/engine/rowcost.py)."""
    from .model import compile_model
    from .simulate import simulate

    for name, value, low, high in (("paths", paths, 1, 64), ("steps", steps, 1, 100_000)):
        if isinstance(value, bool) or not isinstance(value, int) or not low <= value <= high:
            raise InputError(name, f"must be an integer in [{low}, {high}]")
    if not 0 < target < float("inf"):
        raise InputError("target", "must be a positive number")
    model = compile_model(_engine_spec(spec, spec.discretization.basis))
    if exact_only and _kalman(model) is None:
        return None
    rng = np.random.default_rng(seed)
    data = [simulate(model, steps, rng) for _ in range(paths)]
    refs, name, wrong, finest = _reference(spec, model, data, 2 * spec.discretization.basis)
    report = CheckReport(reference=name, target=target, paths=paths, steps=steps,
                         reference_rmse=_rmse([t[0] for t in refs], data), reference_degenerate=wrong)
    if spec.domain.follow and spec.domain.region is not None:
        states = np.concatenate([d.states for d in data])
        report.region = [[float(lo), float(hi)] for lo, hi in spec.domain.region]
        report.covered = [[float(lo), float(hi)]
                          for lo, hi in zip(states.min(axis=0), states.max(axis=0), strict=True)]
    report.left, report.left_at, report.domain = _leaving(model, data)
    report.trials.append(_trial(spec, spec.discretization.basis, data, refs, target, offline, wrong, timed))
    if suggest and not report.requested.ok and not wrong and not report.left:  # the domain first
        for scale in SCALES:
            basis = int(round(spec.discretization.basis * scale))
            against = ""
            try:
                if finest and 2 * basis > finest:  # an engine reference: at twice the trial's basis
                    refs, against, wrong, finest = _reference(spec, model, data, 2 * basis)
                trial = _trial(spec, basis, data, refs, target, None, wrong)
            except SpecError:  # more nodes than the eigensolver takes: stop here
                break
            trial.against = against
            report.trials.append(trial)
            if trial.ok or wrong:
                break
    return report


def coarser_than_measured(spec: ModelSpec) -> tuple[str, str] | None:
    """(field, message naming the fix) when ``spec``'s 3-D mesh is one measured farther from the exact
    filter than the default (solver/defaults.py, bench/results/default-3d.md): P1 on fewer than
    ``P1_REFINEMENTS`` refinements of the ball, or P2 + bubbles on a following ball refined fewer than
    ``FOLLOW_REFINEMENTS`` times; else None.  The rule ``yauyau precompute`` warns with before it solves
    (no path is filtered, as the check would)."""
    from .offline.fem import effective_order, interior_count, mesh_resolution  # scikit-fem: with a mesh only

    if len(spec.state) != 3 or mesh_free(spec):
        return None
    disc, element = spec.discretization, spec.element()
    refinements = mesh_resolution(spec)
    if effective_order(3, disc.order, element) == 1 and refinements < P1_REFINEMENTS:
        nodes, better = interior_count(3, 1, refinements), interior_count(3, 1, P1_REFINEMENTS)
        if spec.scheme() == "supg":  # the stabilised scheme is built on P1: its finer ball
            field, fix = "discretization.mesh", f"set mesh = {P1_REFINEMENTS} ({better} nodes)"
        else:
            field = ("discretization.mesh" if disc.mesh is not None else "discretization.order"
                     if disc.order != 2 else "discretization.element")
            fix = ("leave mesh and element out" + (" with order = 2" if disc.order != 2 else "")
                   + f" (P2 + bubbles) or set mesh = {P1_REFINEMENTS}")
        return field, (f"P1 on {nodes} mesh nodes is measured farther from the exact filter than P2 + "
                       f"bubbles in 3-D (docs/benchmarks.md): {fix}, or see `yauyau check`")
    if element == "bubble" and spec.domain.follow and refinements < FOLLOW_REFINEMENTS:
        nodes = interior_count(3, 2, refinements)
        return "discretization.mesh", (
            f"P2 + bubbles on {nodes} mesh nodes is measured farther from the exact filter on a following "
            f"3-D ball than on the ball refined {FOLLOW_REFINEMENTS} times (docs/benchmarks.md): leave "
            f"mesh out or set mesh = {FOLLOW_REFINEMENTS}, or see `yauyau check`")
    return None


def _leaving(model: Model, data: list) -> tuple[float, int | None, str]:
    """(fraction of the paths whose state leaves the domain, the first step where one does, the domain in
    words with the fix): the fixed ball (or ellipsoid), or the region of a following ball (none without
    a region: the ball goes where the state goes)."""
    domain = model.spec.domain
    if domain.follow:
        if domain.region is None:
            return 0.0, None, "nothing (the ball follows the state)"
        box = np.asarray(domain.region, dtype=float)
        outside = [((d.states < box[:, 0]) | (d.states > box[:, 1])).any(axis=1) for d in data]
        where = ("domain.region " + ", ".join(f"[{lo:g}, {hi:g}]" for lo, hi in box)
                 + ", where the filter cannot follow the state: widen domain.region")
    else:
        center = np.asarray(model.center, dtype=float)
        outside = [model.ball_distance(d.states - center) >= float(model.radius) for d in data]
        shape = "ellipsoid" if model.shape is not None else "ball"
        around = ", ".join(f"{c:g}" for c in center)
        where = (f"the domain {shape} (radius {model.radius:g} around [{around}]), where a filter on a fixed "
                 "ball cannot follow the state (it loses track): set domain.follow = true (the ball follows "
                 "the state) or a larger domain.radius")
    left = [bool(o.any()) for o in outside]
    first = min((int(np.argmax(o)) for o in outside if o.any()), default=None)
    return float(np.mean(left)), first, where


def _engine_spec(spec: ModelSpec, basis: int) -> ModelSpec:
    from .spec import spec_from_dict

    doc = spec.model_dump(mode="json")
    disc = dict(doc["discretization"], basis=basis)
    if basis != spec.discretization.basis:
        disc.pop("mesh", None)  # the default mesh of that basis
    doc["discretization"], doc["method"] = disc, "yau-yau"
    return spec_from_dict(doc)


def _filter(spec: ModelSpec, basis: int, offline: OfflineArrays | None = None):
    """The general engine at ``basis`` (on a following ball with ``[domain] follow``)."""
    from .engine.filter import build
    from .model import compile_model
    from .offline.pipeline import precompute

    model = compile_model(_engine_spec(spec, basis))
    return build(model, offline if offline is not None else precompute(model))


def _kalman(model: Model):
    """The exact discrete Kalman filter of a linear model with a Gaussian prior and increments, else None."""
    from .reference.kalman import DiscreteKalmanFilter

    if model.spec.measurement.kind != "continuous" or getattr(model.spec.initial, "kind", "") != "gaussian":
        return None
    try:
        return DiscreteKalmanFilter(model)
    except (SpecError, InputError, ValueError):
        return None


def _reference(spec: ModelSpec, model: Model, data: list, fine: int) -> tuple[list, str, float, int]:
    """Per path (means (K, n), degenerate (K,)) of the reference, its name, the fraction of its own
    degenerate steps and its basis (an engine's): the exact Kalman filter, else the engine at basis
    ``fine`` — or at twice that, when ``fine`` degenerates on some step (then the gaps would be measured
    on the other steps only)."""
    kalman = _kalman(model)
    if kalman is not None:
        out = []
        for sim in data:
            _, estimates = kalman.run(kalman.initial_state(), sim.rows)
            out.append((np.array([e.mean for e in estimates]), np.zeros(len(estimates), dtype=bool)))
        return out, "the exact Kalman filter (the model is linear)", 0.0, 0
    for basis in (fine, 2 * fine):
        try:
            engine = _filter(spec, basis)
        except SpecError:
            if basis == fine:
                raise
            break
        out = []
        for sim in data:
            _, result = engine.run_arrays(engine.initial_state(), sim.rows)
            out.append((result.mean, result.degenerate))
        wrong = float(np.mean(np.concatenate([bad for _, bad in out])))
        name = f"the engine at basis {basis} ({len(engine.nodes)} nodes)"
        if not wrong:
            break
    return out, name, wrong, basis


def _trial(spec: ModelSpec, basis: int, data: list, refs: list, target: float,
           offline: OfflineArrays | None = None,
           wrong: float = 0.0, timed: bool = False) -> Trial:
    """``basis`` filtered on the paths against ``refs``; it passes only where the reference has no degenerate
    step (``wrong``: their fraction)."""
    engine = _filter(spec, basis, offline)
    gaps, worst, degenerate, total, means = [], 0.0, 0, 0, []
    for sim, (ref, ref_bad) in zip(data, refs, strict=True):
        _, result = engine.run_arrays(engine.initial_state(), sim.rows)
        good = ~ref_bad
        gap = np.max(np.abs(result.mean - ref), axis=1)[good]
        gaps.append(gap)
        worst = max(worst, float(gap.max()) if gap.size else 0.0)
        degenerate += int(result.degenerate.sum())
        total += len(result.degenerate)
        means.append(result.mean)
    mean_gap = float(np.mean(np.concatenate(gaps))) if gaps else 0.0
    fraction = degenerate / total if total else 0.0
    trial = Trial(basis=basis, nodes=len(engine.nodes), mean_gap=mean_gap, max_gap=worst, degenerate=fraction,
                  rmse=_rmse(means, data), ok=mean_gap <= target and degenerate == 0 and not wrong)
    if timed:
        from .engine.rowcost import row_costs

        cost = row_costs(engine)
        trial.regular_us, trial.irregular_us, trial.flow = cost.regular_us, cost.irregular_us, cost.flow
    return trial


def _rmse(means: list[np.ndarray], data: list) -> float:
    errors = np.concatenate([m - sim.states[1:] for m, sim in zip(means, data, strict=True)])
    return float(np.sqrt(np.mean(errors ** 2)))
