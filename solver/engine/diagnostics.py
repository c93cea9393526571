"""Degeneracy diagnostics of the Yau–Yau engine: when a step's density cannot be right, and why.

Read on the pre-projection nodal density σ_k of each step (after the hot loop, vectorised):

* most of σ within one element of ∂B_R: the Dirichlet condition forces σ = 0 there, so the data pull
  the state out of the ball;
* a variance ≤ 0 (or not finite): the basis' ripples dominate, it cannot resolve the density;
* mass leaking through ∂B_R: the leak of step k is the fraction of ∫σ_k lost by its projection and
  the next Fokker–Planck flow, ∫ e^{dt L} Π σ_k / ∫σ_k (= mass lost through ∂B_R, the FP flow
  conserving mass otherwise), less the basis' own mass errors (|projection mass change| and
  κ × the negative part of σ_k); a leak above ``LEAK_RATE``·dt is flagged (thresholds measured in
  tests/solver/engine/test_engine_boundary.py's docstring).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:  # types only
    from ..model import Model

RIM_FRACTION = 0.5  # of the mass within one element of ∂B_R: degenerate
# Boundary leak (fraction of the mass per unit time) beyond which the Dirichlet wall shows in the
# estimates.  Measured at dt = 0.01: Beneš (radius 10, 40 paths) reaches a mean gap of 0.01 at a
# leak of 2.5e-4..3.8e-4 per step, 1.2e-4 per step flags it with gaps ≤ 8.1e-3; healthy runs stay
# ≤ 1.1e-4 (2-D range, 60 paths × 300 steps), ≤ 1e-9 (cubic sensor), ≤ 1e-14 (OU).
LEAK_RATE = 0.012
# Weight of the negative part of σ (the basis' ripples) in the leak's noise: under-resolved 2-D
# densities show spurious flux of about 3× their negative mass; a real leak comes with none.
RIPPLE_WEIGHT = 10.0


# A Fokker–Planck flow with σ = 0 on ∂B_R never creates probability mass; the truncated basis adds
# a little of its own (measured: ≤ 1.3e-4 a step on the bundled examples, 2% on a coarse 2-D basis
# of 20 functions).  A step that multiplies the mass by more than 1 + MASS_GROWTH_LIMIT is an
# unstable discretisation (drift -x**64 on a radius-7 ball: ×1e34), checked online here and at
# precompute by solver.offline.check_stable.
MASS_GROWTH_LIMIT = 0.25
OUTLIER_SIGMAS = 5.0  # an increment this many standard deviations off is named as the cause


class Diagnostics:
    """The checks of one engine (its nodes, weights, projector and Fokker–Planck propagator)."""

    def __init__(self, model: Model, nodes: np.ndarray, weights: np.ndarray, projector: np.ndarray,
                 offline: Any, h_nodes: np.ndarray):  # OfflineArrays (offline/pipeline.py imports this)
        self.dt = model.dt
        self.weights = weights
        self._rim = rim_nodes(model.unshaped(nodes - model.center), 0.0, model.radius)
        # rows: ∫Πσ and ∫e^{dt L}Πσ as linear functionals of nodal σ (Π = basis · projector)
        kept = [np.asarray(m, dtype=float).T @ weights for m in (offline.basis, offline.propagator_fp)]
        self._kept = np.vstack([projector.T @ row for row in kept])
        self.leak_limit = LEAK_RATE * model.dt
        self.h_nodes = np.asarray(h_nodes, dtype=float)  # (Q, m), the engine's own evaluation
        self._r_diag = np.diag(model.R).astype(float)

    def translated(self, h_nodes: np.ndarray) -> "Diagnostics":
        """The same checks on the ball moved rigidly (the rim is the same nodes): h at the new nodes."""
        import copy

        new = copy.copy(self)
        new.h_nodes = np.asarray(h_nodes, dtype=float)
        return new

    def functionals(self) -> np.ndarray:
        """The checks' linear functionals of nodal σ (3, Q): ∫Πσ, ∫e^{dt L}Πσ and the rim's mass (the
        fused compiled rows take them as sums: solver/engine/fused.py)."""
        rim = np.zeros(len(self.weights))
        rim[self._rim] = self.weights[self._rim]
        return np.vstack([self._kept, rim[None]])

    def first_implausible(self, sigma, masses, cov, growth=None,
                          sums: np.ndarray | None = None) -> tuple[int | None, str | None]:
        """The first step whose density cannot be right, and why (None, None if every step is fine).

        * mostly within one element of the boundary: the Dirichlet condition forces σ = 0 on ∂B_R,
          so the data pull the state out of the ball (impossible under the model on this domain);
        * a variance ≤ 0 (or not finite): the basis' ripples dominate, it cannot resolve the density;
        * mass leaking through ∂B_R (:meth:`_boundary_leak`): the Dirichlet wall biases the estimates.

        ``sums``: instead of σ, per row the :meth:`functionals` · σ and Σ w min(σ, 0) (K, 4).
        """
        if not len(masses):
            return None, None
        if sums is None:
            leak = self.boundary_leak(sigma, masses)
        else:
            leak = self.leak_from(sums[:, 0], sums[:, 1], -sums[:, 3], masses)
        leaking = leak > self.leak_limit
        variances = np.diagonal(cov, axis1=1, axis2=2)
        unresolved = ~(np.isfinite(cov).all(axis=(1, 2)) & np.isfinite(masses))
        unresolved |= (variances <= 0.0).any(axis=1)
        flagged = leaking | unresolved  # one mask, one test: the usual chunk has no flag at all
        rim = growing = np.zeros(len(masses), dtype=bool)
        if self._rim.size and sums is not None:
            rim = sums[:, 2] > RIM_FRACTION * masses
        elif self._rim.size:
            rim = (sigma[:, self._rim] * self.weights[self._rim]).sum(axis=1) > RIM_FRACTION * masses
        flagged |= rim
        # growth: ∫σ_k for a unit-mass σ_{k-1}, the update factor divided by its maximum (None: unchecked)
        if growth is not None:
            growing = ~(growth <= 1.0 + MASS_GROWTH_LIMIT)
            flagged |= growing
        if not flagged.any():
            return None, None
        bad = int(np.argmax(flagged))
        if growing[bad]:
            # ∫σ_k for σ_{k-1} of mass 1 is ∫ e^{log e_k − max log e_k} e^{dt L}σ_{k-1} ≤ 1:
            # more means the propagator creates mass, and the log-likelihood gains more than the
            # observation noise allows (its increment is at most max_x log e_k)
            factor = growth[bad]
            return bad, (f"the probability mass grew by a factor {factor:.3g} in one step of dt = "
                         f"{self.dt:g} (a stable flow never creates mass, and the observation factor is at "
                         "most its maximum): the model is numerically unstable, its log-likelihood "
                         "meaningless; the drift is too stiff for this mesh and dt (shrink domain.radius, "
                         "lower discretization.dt or raise discretization.substeps)")
        if leaking[bad] and not unresolved[bad]:
            return bad, (f"probability mass leaks through the boundary of the domain ball ({leak[bad]:.2g} "
                         f"of it per step of dt = {self.dt:g}, limit {self.leak_limit:.2g}): the "
                         "Dirichlet condition on ∂B_R now biases the estimates; enlarge domain.radius "
                         "or re-centre domain.center on the state's path (domain.follow = true: the ball "
                         "follows it)")
        if rim[bad]:
            return bad, ("the conditional density is pushed against the boundary of the domain ball: the "
                         "data are incompatible with the model on this ball (enlarge domain.radius?)")
        return bad, ("the covariance is not positive: the basis cannot resolve the conditional density "
                     "(refine discretization.basis / mesh)")

    def explain_outlier(self, before: np.ndarray, row: np.ndarray, step: int, why: str,
                        tau: float | None = None, discrete: bool = False,
                        h_nodes: np.ndarray | None = None) -> str:
        """``why`` prefixed by the size of the row's surprise when it is an outlier: |Δy − E[h]τ| in
        standard deviations √(R_jj τ) (continuous; τ = dt unless given), |z − E[h]| in √R_jj
        (discrete), E[h] over the nodal density before the step (a glitch collapses the density or
        throws it at the wall, which is not the basis' or the ball's fault).  Missing components
        are skipped.  ``h_nodes``: h at the nodes where ``before`` lives (a moving frame's row; the
        ball's own nodes by default)."""
        h_nodes = self.h_nodes if h_nodes is None else h_nodes
        weights = self.weights * np.clip(np.nan_to_num(before), 0.0, None)
        total = weights.sum()
        if not total > 0 or not np.all(np.isfinite(h_nodes)):
            return why
        expected = weights @ h_nodes / total
        tau = self.dt if tau is None else tau
        scale = 1.0 if discrete else tau
        with np.errstate(invalid="ignore"):
            z = np.abs(row - expected * scale) / np.sqrt(self._r_diag * scale)
        z = np.where(np.isfinite(z), z, 0.0)
        worst = float(np.max(z))
        if not worst > OUTLIER_SIGMAS:
            return why
        j = int(np.argmax(z))
        what = "measurement" if discrete else "increment"
        return (f"the {what} of step {step} is an outlier: observation {j} is {worst:.3g} standard "
                f"deviations from what the model predicts, and the filter cannot follow it ({why}); if it "
                "is a sensor glitch, send that value as missing (null), or turn the gate on "
                "([measurement] gate)")

    def boundary_leak(self, sigma: np.ndarray, masses: np.ndarray) -> np.ndarray:
        """Per step, the fraction of ∫σ_k that projection + the next Fokker–Planck flow lose, beyond noise.

        The FP flow with σ = 0 on ∂B_R conserves mass up to the outflow through ∂B_R; the truncated
        basis adds signed mass errors of its own (projection, ripples).  Their sizes are subtracted:
        a loss smaller than the basis' mass errors cannot be told from truncation.  Elementwise
        einsum (no BLAS): each row's value does not depend on the chunk length.
        """
        projected, flowed = np.einsum("kq,fq->fk", sigma, self._kept)
        negative = -np.einsum("kq,q->k", np.minimum(sigma, 0.0), self.weights)
        return self.leak_from(projected, flowed, negative, masses)

    @staticmethod
    def leak_from(projected: np.ndarray, flowed: np.ndarray, negative: np.ndarray,
                  masses: np.ndarray) -> np.ndarray:
        """:meth:`boundary_leak` from each row's ∫Πσ, ∫e^{dt L}Πσ and −Σ w min(σ, 0)."""
        with np.errstate(divide="ignore", invalid="ignore"):
            noise = np.abs(1.0 - projected / masses) + RIPPLE_WEIGHT * negative / masses
            leak = (1.0 - flowed / projected) - noise
        return np.where(np.isfinite(leak) & (projected > 0.0), leak, 0.0)


def rim_nodes(nodes: np.ndarray, center: np.ndarray, radius: float) -> np.ndarray:
    """Nodes within about one element of the boundary (twice the gap of the outermost node); on an
    ellipsoid give the nodes in the ball's coordinates (Model.unshaped) and centre 0."""
    r = np.linalg.norm(nodes - center, axis=1)
    return np.flatnonzero(r >= radius - 2.0 * (radius - r.max()))
