"""Exact Beneš filter: dx = tanh(x) dt + dv, dy = x dt + dw (a = R = 1).

With f = tanh x, f' + f² = 1, and p = cosh(x)·q turns the Fokker–Planck equation
∂p/∂t = ½p'' − (tanh(x) p)' into the heat equation with a constant potential,
∂q/∂t = ½q'' − ½q.  Hence the flow over t maps cosh(x)·N(x; m, P) to
cosh(x)·e^{−t/2}·(N(m, P) ∗ N(0, t)) = cosh(x)·e^{−t/2}·N(x; m, P + t) (mass is kept: the
normaliser e^{P/2}cosh m is unchanged).  The update by exp(xΔy − ½x²dt) maps
cosh(x)·N(m, P) to cosh(x)·N(m', P') with 1/P' = 1/P + dt, m' = P'(m/P + Δy): the Kalman
filter of dx = dv, dy = x dt + dw.  So a prior ∝ cosh(x)·N(m0, P0) stays of that form, and

    density  = cosh(x) N(x; m, P) / (e^{P/2} cosh m),
    mean     = m + P tanh m,       variance = P + P² sech² m,

a two-component mixture N(m ± P, P) with weights e^{±m}/(2 cosh m).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import sympy as sp

from ..errors import SpecError
from ..filtering import Estimate
from ..gaussian import GaussianState
from ..model import Model
from ..spec import MixturePrior
from ._base import ReferenceFilter, advance


def log_cosh(x: np.ndarray | float) -> np.ndarray | float:
    ax = np.abs(x)
    return ax + np.log1p(np.exp(-2.0 * ax)) - np.log(2.0)


def benes_prior(model: Model) -> tuple[float, float]:
    """(m0, P0) of a mixture prior equal to cosh(x)·N(m0, P0): N(m0 ± P0, P0), weights ∝ e^{±m0}."""
    prior = model.spec.initial
    reason = "the Beneš filter needs a prior ∝ cosh(x)·N(m0, P0): two components N(m0 ± P0, P0) " \
             "with weights ∝ e^{±m0}"
    if not isinstance(prior, MixturePrior) or len(prior.weights) != 2:
        raise SpecError("initial", reason)
    (lo, w_lo), (hi, w_hi) = sorted(zip((mu[0] for mu in prior.means), prior.weights, strict=True))
    p_lo, p_hi = (c[0][0] for c in prior.covs)
    m0, p0 = 0.5 * (lo + hi), 0.5 * (hi - lo)
    consistent = (np.isclose(p_lo, p_hi, rtol=1e-9) and np.isclose(p0, p_lo, rtol=1e-9)
                  and w_lo > 0 and np.isclose(np.log(w_hi / w_lo), 2.0 * m0, atol=1e-9))
    if not consistent:
        raise SpecError("initial", reason)
    return m0, p0


def check_benes_model(model: Model) -> None:
    x = model.symbols[0]
    if model.n != 1 or sp.simplify(model.drift[0] - sp.tanh(x)) != 0:
        raise SpecError("drift", "the Beneš filter needs the scalar drift tanh(x)")
    if model.m != 1 or sp.simplify(model.observation[0] - x) != 0:
        raise SpecError("observation", "the Beneš filter needs the observation h = x")
    if not np.allclose(model.a, 1.0):
        raise SpecError("diffusion", "the Beneš filter needs a = 1")
    if not np.allclose(model.R, 1.0):
        raise SpecError("observation_noise", "the Beneš filter needs R = 1")


class BenesFilter(ReferenceFilter):
    """Closed-form filter of the time-sampled Beneš model; the state holds (m, P) of cosh(x)·N(m, P)."""

    method = "benes"

    def __init__(self, model: Model):
        check_benes_model(model)
        super().__init__(model)
        self.m0, self.p0 = benes_prior(model)

    def initial_state(self, prior: Any | None = None) -> GaussianState:
        if prior is not None:
            raise SpecError("initial", "the Beneš filter uses the model's prior")
        return GaussianState(mean=np.array([self.m0]), cov=np.array([[self.p0]]))

    def _advance(self, state: GaussianState, increment: np.ndarray | None) -> GaussianState:
        dt = self.model.dt
        m, p = float(state.mean[0]), float(state.cov[0, 0]) + dt  # flow: P → P + dt, m kept
        loglik = 0.0
        if increment is not None:
            p_new = 1.0 / (1.0 / p + dt)
            m_new = p_new * (m / p + float(increment[0]))
            # ∫cosh N(m,P) e^{xΔy − x²dt/2} / ∫cosh N(m,P), the Gaussian factor c times the cosh normalisers
            log_c = 0.5 * np.log(p_new / p) - m * m / (2 * p) + m_new * m_new / (2 * p_new)
            loglik = float(log_c + 0.5 * (p_new - p) + log_cosh(m_new) - log_cosh(m))
            m, p = m_new, p_new
        return advance(state, dt, loglik, mean=np.array([m]), cov=np.array([[p]]))

    @staticmethod
    def moments(m: float, p: float) -> tuple[float, float]:
        """Mean and variance of cosh(x)·N(m, P) (normalised)."""
        return m + p * np.tanh(m), p + p * p / np.cosh(m) ** 2

    def estimate(self, state: GaussianState) -> Estimate:
        m, p = float(state.mean[0]), float(state.cov[0, 0])
        mean, var = self.moments(m, p)
        return Estimate(step=state.step, t=state.t, mean=np.array([mean]), cov=np.array([[var]]),
                        loglik=state.loglik, loglik_increment=state.loglik_increment, mode=None)

    def density(self, state: GaussianState, points: np.ndarray) -> np.ndarray:
        x = np.atleast_2d(np.asarray(points, float))[:, 0]
        m, p = float(state.mean[0]), float(state.cov[0, 0])
        log_n = -(x - m) ** 2 / (2 * p) - 0.5 * np.log(2 * np.pi * p)
        return np.exp(log_cosh(x) + log_n - 0.5 * p - log_cosh(m))

    def state_from_dict(self, data: dict[str, Any]) -> GaussianState:
        return GaussianState.from_dict(data)
