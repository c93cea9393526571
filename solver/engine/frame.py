"""A frame that moves with the mean's ODE: a following ball for an affine drift f(x) = Ax + b.

For an affine drift the Fokker–Planck operator is not invariant under a shift of the ball (f depends
on x), but it is in a frame that moves with the deterministic flow.  With ċ = Ac + b and
q(t, ξ) = p(t, c(t) + ξ),

    ∂q/∂t = ∂p/∂t + ċ·∇p = ½ a:∇²q − tr(A) q − (Ax + b)·∇p + (Ac + b)·∇p
          = ½ a:∇²q − div(Aξ q),

the Fokker–Planck equation of the drift Aξ, whatever c.  So one propagator, solved once on B_R(c₀) for
the drift f(x) − f(c₀) = A(x − c₀), serves a ball whose centre rides the ODE
c(t + τ) = e^{Aτ}c(t) + ∫₀^τ e^{As} ds b, and every re-centre (solver/engine/follow.py) is a move of the same
frame: the ball may follow the posterior along every coordinate, not only along those f does not
depend on.  The observation factor is evaluated at the moved nodes c_k + ξ_i of each step.

A drift that is invariant along every coordinate (a random walk with trend) needs no frame: the plain
translation of solver/engine/follow.py is used, so its stored arrays are unchanged.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Callable

import numpy as np

if TYPE_CHECKING:  # types only
    from ..model import Model

SEGMENT = 256  # rows of a regular path computed from one start (powers of e^{Aτ} kept per τ)


@dataclass(frozen=True, eq=False)
class AffineFrame:
    """The flow of ċ = Ac + b, and ``origin`` c₀ the ball the propagator was solved on."""

    A: np.ndarray
    b: np.ndarray
    origin: np.ndarray
    _steps: dict = field(default_factory=dict, repr=False)
    _powers: dict = field(default_factory=dict, repr=False)

    @property
    def offset(self) -> np.ndarray:
        """f(c₀) = Ac₀ + b, what the stored propagator's drift f(x) − f(c₀) leaves out."""
        return self.A @ self.origin + self.b

    def step(self, tau: float) -> tuple[np.ndarray, np.ndarray]:
        """(e^{Aτ}, ∫₀^τ e^{As} ds b) (Van Loan's exponential, solver/reference/kalman.py; kept per τ)."""
        key = float(tau)
        found = self._steps.get(key)
        if found is None:
            from ..reference.kalman import van_loan

            phi, shift, _ = van_loan(self.A, np.zeros_like(self.A), self.b, key)
            found = (phi, shift)
            if len(self._steps) < 64:
                self._steps[key] = found
        return found

    def path(self, start: np.ndarray, gaps: np.ndarray) -> np.ndarray:
        """The centres after each gap (K, n), from ``start`` at the first gap's beginning.  Equal gaps
        (regular rows) in segments: c_j = Φʲc + Σ_(i<j) Φⁱs for j ≤ SEGMENT (:meth:`powers`)."""
        gaps = np.asarray(gaps, dtype=float)
        out = np.empty((len(gaps), len(self.b)))
        c = np.asarray(start, dtype=float)
        if len(gaps) > 1 and np.all(gaps == gaps[0]):
            powers, sums = self.powers(float(gaps[0]))
            for first in range(0, len(gaps), SEGMENT):
                size = min(SEGMENT, len(gaps) - first)
                out[first:first + size] = powers[:size] @ c + sums[:size]
                c = out[first + size - 1]
            return out
        for k, tau in enumerate(gaps.tolist()):
            phi, shift = self.step(tau)
            c = phi @ c + shift
            out[k] = c
        return out

    def powers(self, tau: float) -> tuple[np.ndarray, np.ndarray]:
        """Φʲ and Σ_(i<j) Φⁱs for j = 1..SEGMENT, (Φ, s) = :meth:`step` (τ) (kept for a few τ)."""
        found = self._powers.get(tau)
        if found is None:
            phi, shift = self.step(tau)
            powers, sums = np.empty((SEGMENT,) + phi.shape), np.empty((SEGMENT, len(shift)))
            powers[0], sums[0] = phi, shift
            for j in range(1, SEGMENT):
                powers[j] = phi @ powers[j - 1]
                sums[j] = phi @ sums[j - 1] + shift
            found = (powers, sums)
            if len(self._powers) < 8:
                self._powers[tau] = found
        return found

    def drift(self, f: Callable[[np.ndarray], np.ndarray]) -> Callable[[np.ndarray], np.ndarray]:
        """The stored propagator's drift x ↦ f(x) − f(c₀) (= A(x − c₀))."""
        offset = self.offset

        def framed(X: np.ndarray) -> np.ndarray:
            return f(X) - offset

        return framed


def affine_frame(model: Model) -> AffineFrame | None:
    """The moving frame of a ``[domain] follow`` model whose drift is affine but depends on some
    coordinate (else None: no follow, a nonlinear drift, or a drift invariant along every one)."""
    domain = model.spec.domain
    if not domain.follow or len(model.shift_directions) == model.n:
        return None
    found = model.affine_drift
    if found is None:
        return None
    A, b = found
    return AffineFrame(A=A, b=b, origin=np.asarray(model.center, dtype=float))


def drift_of(model: Model) -> Callable[[np.ndarray], np.ndarray]:
    """The drift the offline stage solves with: f, or f(x) − f(c₀) in a moving frame."""
    frame = affine_frame(model)
    return model.f if frame is None else frame.drift(model.f)
