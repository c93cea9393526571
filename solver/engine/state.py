"""The Yau–Yau engine's state and its exact JSON form (what the service stores between chunks).

The state is (c, ∫σ): the basis coefficients at the scale the hot loop carries them and the mass of
the pre-projection density, plus the step, time, cumulative log-likelihood and the last good
estimate.  ``to_dict``/``state_from_dict`` round-trip it exactly (floats as Python floats), so a run
split into chunks, or continued in another process, is bit-identical to an uninterrupted one.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..errors import InputError
from ..filtering import Estimate


@dataclass(frozen=True, eq=False)
class YauYauState:
    """Filter state after ``step`` steps (time ``t``).

    ``coefficients`` are the basis coefficients of the conditional density at a scale where the
    (pre-projection) density has mass ``mass``: the normalised coefficients are
    ``coefficients / mass`` (:attr:`density_coefficients`).  Keeping the pair exactly as the hot
    loop carries it makes a run split into chunks bit-identical to an uninterrupted one.
    ``loglik`` is the log normaliser of σ (the cumulative log-likelihood).  ``last`` is the last
    good estimate; a ``degenerate`` state keeps it and keeps returning it.
    """

    coefficients: np.ndarray  # (N,)
    mass: float
    step: int
    t: float
    loglik: float
    last: Estimate
    degenerate: bool = False
    reason: str | None = None
    form: str = "stable"
    precision: str = "double"
    center: np.ndarray | None = None  # the ball's centre when it follows the state (solver/engine/follow.py)
    # σ at the nodes after the last row, where the fused rows take one product a row (solver/engine/fused.py):
    # the next chunk's first row continues from it, as the uninterrupted run's next row does
    nodal: np.ndarray | None = None

    def to_dict(self) -> dict[str, Any]:
        """JSON-safe; floats as Python floats (repr round-trips exactly)."""
        out = {"method": "yau-yau", "form": self.form, "precision": self.precision, "step": self.step,
               "t": self.t,
               "loglik": self.loglik, "degenerate": self.degenerate, "reason": self.reason,
               "coefficients": self.coefficients.tolist(), "mass": self.mass, "last": self.last.to_dict()}
        if self.center is not None:
            out["center"] = np.asarray(self.center, dtype=float).tolist()
        if self.nodal is not None:
            out["nodal"] = np.asarray(self.nodal, dtype=float).tolist()
        return out

    @property
    def density_coefficients(self) -> np.ndarray:
        """Coefficients of the normalised conditional density."""
        return self.coefficients / self.mass


def state_from_dict(data: Any, size: int, n: int, form: str, precision: str,
                    nodes: int | None = None) -> YauYauState:
    """Inverse of :meth:`YauYauState.to_dict` for a filter with ``size`` basis functions, state
    dimension ``n``, ``form`` and ``precision`` (validated; bad fields raise InputError('state.…'));
    ``nodal`` is read where given with ``nodes`` values."""
    if not isinstance(data, dict):
        raise InputError("state", "must be an object")
    if data.get("method") != "yau-yau":
        raise InputError("state.method", f"is {data.get('method')!r}, this filter is 'yau-yau'")
    for name, ours in (("form", form), ("precision", precision)):
        if data.get(name) != ours:
            raise InputError(f"state.{name}", f"is {data.get(name)!r}, this filter uses {ours!r}")
    coefficients = _float_array(data.get("coefficients"), "state.coefficients", (size,))
    step = data.get("step")
    if not isinstance(step, int) or isinstance(step, bool) or step < 0:
        raise InputError("state.step", "must be a non-negative integer")
    reason = data.get("reason")
    if reason is not None and not isinstance(reason, str):
        raise InputError("state.reason", "must be a string or null")
    if not isinstance(data.get("degenerate"), bool):
        raise InputError("state.degenerate", "must be true or false")
    mass = _finite_float(data.get("mass"), "state.mass")
    if not mass > 0.0:
        raise InputError("state.mass", "must be positive")
    nodal = data.get("nodal")
    if nodal is not None:
        nodal = None if nodes is None else _float_array(nodal, "state.nodal", (nodes,))
    return YauYauState(coefficients=coefficients, mass=mass, step=step, nodal=nodal,
                       t=_finite_float(data.get("t"), "state.t"),
                       loglik=_finite_float(data.get("loglik"), "state.loglik"),
                       last=_estimate_from_dict(data.get("last"), n),
                       degenerate=data["degenerate"], reason=reason, form=form,
                       precision=precision)


def _finite_float(value: Any, field: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise InputError(field, "must be a finite number")
    return float(value)


def _float_array(value: Any, field: str, shape: tuple[int, ...]) -> np.ndarray:
    try:
        arr = np.array(value, dtype=float)
    except (TypeError, ValueError):
        raise InputError(field, "must be a list of numbers") from None
    if arr.shape != shape:
        raise InputError(field, f"must have shape {shape}, got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise InputError(field, "must be finite")
    return arr


def _estimate_from_dict(data: Any, n: int) -> Estimate:
    if not isinstance(data, dict):
        raise InputError("state.last", "must be an estimate object")
    step = data.get("step")
    if not isinstance(step, int) or isinstance(step, bool) or step < 0:
        raise InputError("state.last.step", "must be a non-negative integer")
    mode = data.get("mode")
    return Estimate(step=step, t=_finite_float(data.get("t"), "state.last.t"),
                    mean=_float_array(data.get("mean"), "state.last.mean", (n,)),
                    cov=_float_array(data.get("cov"), "state.last.cov", (n, n)),
                    loglik=_finite_float(data.get("loglik"), "state.last.loglik"),
                    loglik_increment=_finite_float(data.get("loglik_increment"),
                                                   "state.last.loglik_increment"),
                    degenerate=bool(data.get("degenerate", False)), reason=data.get("reason"),
                    mode=None if mode is None else _float_array(mode, "state.last.mode", (n,)))
