"""Method choice: which filter solves the DMZ equation of a model.

    ∂σ = ½ Σ a_ij ∂_i∂_j σ − div(f σ) dt + σ hᵀR⁻¹ dy        (the Duncan–Mortensen–Zakai equation)

``yau-yau`` is the general real-time algorithm of seed 002 §5 (solver/engine.py, needs the offline
propagators).  ``kalman-bucy`` (linear models), ``yau-hu`` (Yau filtering systems, seed 000) and
``wei-norman`` (seed 004) are exact finite-dimensional filters where the estimation algebra allows
them.  ``auto`` asks the estimation-algebra analysis (solver/analysis.py) which one applies.
Exact filters are imported lazily: the engine works without them.
"""

from __future__ import annotations

import importlib
from typing import Any

from .errors import SpecError
from .filtering import Filter
from .model import Model
from .spec import METHODS

_EXACT = {
    "kalman-bucy": ("yauyau.solver.exact.kalman_bucy", "KalmanBucyFilter"),
    "yau-hu": ("yauyau.solver.exact.yau_hu", "YauHuFilter"),
    "wei-norman": ("yauyau.solver.exact.wei_norman", "WeiNormanFilter"),
}


def resolve_method(model: Model, method: str | None = None) -> str:
    """The concrete method name: the argument, else the spec's; ``auto`` asks the analysis."""
    method = model.spec.method if method is None else method
    if method not in METHODS:
        raise SpecError("method", f"must be one of {', '.join(METHODS)}, got {method!r}")
    if method != "auto":
        return method
    try:
        analysis = importlib.import_module("yauyau.solver.analysis")
    except ImportError:
        return "yau-yau"  # no analysis in this installation: the general engine
    chosen, _reason = analysis.recommend_method(analysis.analyze(model))
    return chosen if _available(chosen) else "yau-yau"


def make_filter(model: Model, offline: Any | None = None, method: str | None = None,
                form: str = "stable", precision: str | None = None) -> Filter:
    """A filter for ``model``; ``offline`` (solver.offline.OfflineModel) is needed by yau-yau and
    wei-norman.  ``form``/``precision`` are the yau-yau engine's options (solver.engine).  An exact
    method that is unavailable or does not apply raises SpecError('method').  ``precision`` defaults
    to the spec's ``discretization.precision``."""
    requested = method
    precision = precision or model.spec.discretization.precision
    method = resolve_method(model, method)
    if method == "yau-yau":
        if offline is None:
            raise SpecError("method", "yau-yau needs the precomputed propagators (run yauyau precompute)")
        from .engine import YauYauFilter

        return YauYauFilter(model, offline, form=form, precision=precision)
    cls = _exact_class(method)
    try:
        if method == "wei-norman":
            if offline is None:
                raise SpecError("method", "wei-norman needs the precomputed Kolmogorov flow "
                                          "(run yauyau precompute)")
            wei_norman = importlib.import_module("yauyau.solver.exact.wei_norman")
            flow = wei_norman.kolmogorov_flow_from_offline(offline)
            return cls(model, flow)
        return cls(model)
    except SpecError as exc:
        if (requested or model.spec.method) == "auto" and offline is not None:
            from .engine import YauYauFilter  # the analysis was too optimistic: the general engine

            return YauYauFilter(model, offline, form=form, precision=precision)
        raise SpecError("method", f"{method} does not apply to this model: {exc}") from None


def _available(method: str) -> bool:
    if method == "yau-yau":
        return True
    try:
        _exact_class(method)
    except SpecError:
        return False
    return True


def _exact_class(method: str):
    module_name, class_name = _EXACT[method]
    try:
        module = importlib.import_module(module_name)
    except ImportError:
        raise SpecError("method", f"{method} is not available in this installation") from None
    cls = getattr(module, class_name, None)
    if cls is None:
        raise SpecError("method", f"{method} is not available in this installation")
    return cls
