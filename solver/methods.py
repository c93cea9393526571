"""Method choice: which filter solves the DMZ equation of a model, and making it.

    ∂σ = ½ Σ a_ij ∂_i∂_j σ − div(f σ) dt + σ hᵀR⁻¹ dy        (the Duncan–Mortensen–Zakai equation)

The methods are those of solver/registry.py: ``yau-yau``, the general real-time algorithm (needs
the offline propagators), and the exact finite-dimensional filters where the estimation algebra
allows them.  ``auto`` asks the estimation-algebra analysis (solver/analysis/) once — at precompute
(yauyau.api.precompute stores the choice with the model) — never at filtering time.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING

from .errors import SpecError, TooLarge
from .measurement import check_gate
from .registry import AUTO, METHODS, REGISTRY, check_method

if TYPE_CHECKING:
    from .filtering import Filter
    from .model import Model
    from .offline.pipeline import OfflineArrays

__all__ = ["METHODS", "choose_method", "make_filter", "resolve_method"]


def _checked(method: str) -> str:
    try:
        return check_method(method)
    except ValueError as exc:
        raise SpecError("method", str(exc)) from None


def choose_method(model: "Model", method: str | None = None, *, offline: OfflineArrays | None = None,
                  time_limit: float | None = 60.0, grace: float | None = None) -> tuple[str, str]:
    """The concrete method for ``model`` and why: the argument, else the spec's; ``auto`` runs the
    estimation-algebra analysis in a process of its own, killed ``grace`` seconds (default 2) after
    ``time_limit`` (solver/analysis/isolated.py: what it had not decided by then is undecided, and the
    general engine is chosen unless the conditions it decided name an exact filter); ``time_limit``
    None runs it here, unbounded.  With ``offline`` (the precomputed arrays) an exact method the
    analysis recommends is built once to check that it applies; if it does not, the general engine is
    chosen and the reason says why."""
    requested = _checked(model.spec.method if method is None else method)
    if requested != AUTO:
        return requested, (f"method = {requested!r} in the spec" if method is None else "asked for")
    chosen, reason = _analysed_method(model, time_limit, grace)
    if chosen not in REGISTRY:
        return "yau-yau", f"the analysis recommends {chosen}, not in this installation: the general engine"
    if chosen != "yau-yau":
        try:
            make_filter(model, offline, chosen)
        except SpecError as exc:
            if offline is not None or not REGISTRY[chosen].needs_offline:
                return "yau-yau", (f"the analysis recommends {chosen} ({reason}), but it does not apply: "
                                   f"{exc.message}")
    return chosen, reason


def _analysed_method(model: "Model", time_limit: float | None, grace: float | None) -> tuple[str, str]:
    from . import analysis

    if time_limit is None:
        return analysis.recommend_method(analysis.analyze(model, time_limit=None))
    from .analysis.isolated import DEFAULT_GRACE, analyze_isolated

    done = analyze_isolated(model, time_limit, grace=DEFAULT_GRACE if grace is None else grace)
    if done.stopped:
        return done.method, f"{done.reason}; {done.report['notes'][-1]}"
    return done.method, done.reason


def resolve_method(model: "Model", method: str | None = None) -> str:
    """The concrete method name (``choose_method`` without the reason)."""
    return choose_method(model, method)[0]


def make_filter(model: "Model", offline: OfflineArrays | None = None, method: str | None = None,
                form: str = "stable", precision: str | None = None, gate: float | None = None) -> "Filter":
    """A filter for ``model`` by registry name (``auto``: the analysis chooses, now).  ``offline``
    (the precomputed arrays, solver.offline.OfflineArrays) is needed by the methods that say so;
    ``form``/``precision`` are the engine's options (precision defaults to the spec's); ``gate``
    overrides the spec's ``[measurement] gate`` (0: off).  A method that is unknown, unavailable or
    does not apply raises SpecError('method')."""
    requested = _checked(model.spec.method if method is None else method)
    method = resolve_method(model, requested) if requested == AUTO else requested
    entry = REGISTRY[method]
    if entry.needs_offline and offline is None:
        raise SpecError("method", f"{method} needs the precomputed arrays (run yauyau precompute)")
    try:
        module = importlib.import_module(entry.module)
    except ImportError:
        raise SpecError("method", f"{method} is not available in this installation") from None
    precision = precision or model.spec.discretization.precision
    try:
        flt = module.build(model, offline, form=form, precision=precision, gate=gate)
    except SpecError as exc:
        if method == "yau-yau" or exc.field in ("form", "precision") or isinstance(exc, TooLarge):
            raise
        if requested == AUTO and offline is not None:  # the analysis was too optimistic
            return make_filter(model, offline, "yau-yau", form=form, precision=precision, gate=gate)
        raise SpecError("method", f"{method} does not apply to this model: {exc}") from None
    if gate is not None and getattr(flt, "gate_override", None) is None:
        flt.gate_override = check_gate(gate)
    return flt
