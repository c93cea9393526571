"""Wei–Norman filter of seed 004, Theorem 1, for the class with E = {L0, D_k, x_k, 1}.

The robust DMZ equation (seed 004 (10)) for u = exp(−hᵀR⁻¹y) σ, with h affine in x_k alone,
Y(t) = cᵀR⁻¹y(t) (c = ∂h/∂x_k) and a = I, reads

    ∂u/∂t = L0 u + Y D_k u + ½ Y² u,     D_k = ∂/∂x_k − f_k,

and has the solution (seed 004 (12))  u = e^{r0} e^{r1 x_k} e^{r2 D_k} e^{t L0} σ0  with

    ṙ1 = A r2,   ṙ2 = r1 + Y,   ṙ0 = ½ (r1 + Y)² + ½ A r2² + ½ B r2,     r(0) = 0     (seed 004 (13))

where η = A x_k² + B x_k + γ(other x).  e^{r D_k} is the flow of D_k: a shift along x_k times an
integrating factor,  (e^{r D_k} v)(x) = v(x + r e_k) · exp(−∫_0^r f_k(x + τ e_k) dτ).

e^{t L0} σ0 does not depend on the observations: it is given as a callable
``kolmogorov_flow(t, points) -> values`` (the Kolmogorov equation of seed 002 (5.31) from the prior).
Between observation times y is interpolated linearly (the Wong–Zakai path, for which the
Stratonovich DMZ (2) is the right equation); on each interval the linear ODEs for (r1, r2) and the
quadratic integral for r0 are solved exactly with a matrix exponential (Van Loan).
The representation is global in time: r1, r2 grow like e^{√A t}, so the shift r2 leaves the domain
of a stored flow after a finite horizon; the filter reports that as degeneracy.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import scipy.linalg
import sympy as sp

from ..analysis import exact_matrix, is_identity, observed_coordinate, seed004_structure
from ..errors import InputError, SpecError
from ..expressions import vectorize
from ..filtering import Estimate, check_increments
from ..model import Model

DEFAULT_POINTS_PER_AXIS = {1: 801, 2: 161, 3: 61}


@dataclass
class WeiNormanState:
    step: int
    t: float
    y: np.ndarray  # (m,) observation path y(t)
    r: np.ndarray  # (3,) r0, r1, r2
    loglik: float
    degenerate: bool = False
    reason: str | None = None

    def to_dict(self) -> dict[str, Any]:
        return {"step": self.step, "t": self.t, "y": self.y.tolist(), "r": self.r.tolist(),
                "loglik": self.loglik, "degenerate": self.degenerate, "reason": self.reason}


def ball_quadrature(model: Model, points_per_axis: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Midpoint rule on a tensor grid of the box around B_R, restricted to the ball."""
    n, R = model.n, model.radius
    k = points_per_axis or DEFAULT_POINTS_PER_AXIS[n]
    h = 2 * R / k
    axis = -R + h * (np.arange(k) + 0.5)
    grid = np.stack(np.meshgrid(*([axis] * n), indexing="ij"), axis=-1).reshape(-1, n)
    inside = np.einsum("ij,ij->i", grid, grid) <= R * R
    return grid[inside] + model.center, np.full(int(inside.sum()), h**n)


class WeiNormanFilter:
    """Exact filter of seed 004 Theorem 1 (Filter protocol of solver.filtering)."""

    method = "wei-norman"

    def __init__(self, model: Model, kolmogorov_flow: Callable[[float, np.ndarray], np.ndarray], *,
                 log_flow: bool = False, nodes: np.ndarray | None = None, weights: np.ndarray | None = None,
                 points_per_axis: int | None = None):
        self.model = model
        self.flow = kolmogorov_flow
        self.log_flow = log_flow
        k = observed_coordinate(model)
        if not is_identity(model.a):
            raise SpecError("diffusion", "the Wei-Norman filter of seed 004 needs a = I")
        structure = seed004_structure(model, k) if k is not None else None
        if structure is None:
            raise SpecError("method", "wei-norman needs omega_kj = 0, eta = A x_k^2 + B x_k + gamma(others) "
                                      "and h affine in one coordinate x_k (seed 004 (I), (II), (v))")
        self.k = k
        self.A = float(structure["A"])
        self.B = float(structure["B"])
        slopes = np.array([float(c) for c in structure["slopes"]])
        self.gain = model.R_inv @ slopes  # Y = cᵀR⁻¹y = gain·y
        self._shift_integral = _shift_integral(model, k)
        self._hR = _observation_weights(model)
        self._box = None if nodes is None else (np.min(nodes, axis=0), np.max(nodes, axis=0))
        if nodes is None and points_per_axis is None and hasattr(kolmogorov_flow, "nodes"):
            nodes, weights = kolmogorov_flow.nodes, kolmogorov_flow.weights  # where the flow is known
        if nodes is None:
            nodes, weights = ball_quadrature(model, points_per_axis)
        self.nodes = np.asarray(nodes, dtype=float)
        self.log_weights = np.log(np.asarray(weights, dtype=float))
        self._step_map = self._van_loan(model.dt)

    # -- the ODEs (13), exactly on one interval ------------------------------------------------
    def _van_loan(self, dt: float) -> tuple[np.ndarray, np.ndarray]:
        """(Φ, G) with z(t + dt) = Φ z(t) and r0 gaining ½ z(t)ᵀ G z(t) over dt, z = (r1, r2, Y, Ẏ, 1).

        Carrying the slope Ẏ in the state makes the flow data-free: Φ and G are computed once per dt.
        """
        A, B = self.A, self.B
        F = np.zeros((5, 5))
        F[0, 1] = A  # ṙ1 = A r2
        F[1, 0] = F[1, 2] = 1.0  # ṙ2 = r1 + Y
        F[2, 3] = 1.0  # Ẏ is constant on the interval (y linear)
        Q = np.zeros((5, 5))  # ṙ0 = ½ zᵀ Q z = ½ (r1 + Y)² + ½ A r2² + ½ B r2
        Q[np.ix_([0, 2], [0, 2])] = 1.0
        Q[1, 1] = A
        Q[1, 4] = Q[4, 1] = B / 2
        big = scipy.linalg.expm(np.block([[-F.T, Q], [np.zeros((5, 5)), F]]) * dt)  # Van Loan
        phi = big[5:, 5:]
        return phi, phi.T @ big[:5, 5:]  # ∫_0^dt e^{Fᵀs} Q e^{Fs} ds

    def advance(self, r: np.ndarray, Y0: float, Y1: float, dt: float) -> np.ndarray:
        """r(t + dt) from r(t) with Y linear from Y0 to Y1 over [t, t + dt]   (seed 004 (13))."""
        phi, gram = self._step_map if dt == self.model.dt else self._van_loan(dt)
        z0 = np.array([r[1], r[2], Y0, (Y1 - Y0) / dt, 1.0])
        z1 = phi @ z0
        return np.array([r[0] + 0.5 * z0 @ gram @ z0, z1[0], z1[1]])

    # -- density --------------------------------------------------------------------------------
    def log_density_unnormalised(self, state: WeiNormanState, X: np.ndarray) -> np.ndarray:
        """log σ(t, x) = hᵀR⁻¹y + r0 + r1 x_k + log v(t, x + r2 e_k) − ∫_0^{r2} f_k(x + τ e_k) dτ."""
        X = np.atleast_2d(np.asarray(X, dtype=float))
        r0, r1, r2 = state.r
        shifted = X.copy()
        shifted[:, self.k] += r2
        values = np.asarray(self.flow(state.t, shifted), dtype=float).reshape(-1)
        if values.shape != (X.shape[0],):
            raise InputError("kolmogorov_flow", f"must return {X.shape[0]} values, got shape {values.shape}")
        with np.errstate(divide="ignore", invalid="ignore"):
            log_v = values if self.log_flow else np.log(np.where(values > 0, values, 0.0))
        log_v = np.where(np.isnan(log_v), -np.inf, log_v)
        integral = self._shift_integral(np.column_stack([X, np.full(len(X), r2)]))
        return self._hR(X) @ state.y + r0 + r1 * X[:, self.k] + log_v - integral

    def _log_weights_shifted(self, state: WeiNormanState) -> tuple[np.ndarray, np.ndarray]:
        """(X, log σ(X) + log w) at X = z − r2 e_k for the quadrature nodes z of the flow.

        ∫ g σ dx is taken in z = x + r2 e_k, where v = e^{tL0}σ0 is evaluated: the flow is asked for
        its own nodes every step (no interpolation at shifted points), and the integrand keeps
        x = z − r2 e_k inside the domain (B_R, or the box of nodes given), the same integral as before.
        """
        r0, r1, r2 = state.r
        values = np.asarray(self.flow(state.t, self.nodes), dtype=float).reshape(-1)
        if values.shape != (len(self.nodes),):
            raise InputError("kolmogorov_flow", f"must return {len(self.nodes)} values, got {values.shape}")
        with np.errstate(divide="ignore", invalid="ignore"):
            log_v = values if self.log_flow else np.log(np.where(values > 0, values, 0.0))
        log_v = np.where(np.isnan(log_v), -np.inf, log_v)
        X = self.nodes.copy()
        X[:, self.k] -= r2
        log_v[~self._in_domain(X)] = -np.inf
        integral = self._shift_integral(np.column_stack([X, np.full(len(X), r2)]))
        return X, self._hR(X) @ state.y + r0 + r1 * X[:, self.k] + log_v - integral + self.log_weights

    def _in_domain(self, X: np.ndarray) -> np.ndarray:
        """x in the domain of the density: the ball B_R, or the box of nodes given by the caller."""
        if self._box is not None:
            return np.all((X >= self._box[0]) & (X <= self._box[1]), axis=1)
        d = X - self.model.center
        return np.einsum("ij,ij->i", d, d) <= self.model.radius**2 * (1 + 1e-12)

    def _moments(self, state: WeiNormanState) -> tuple[float, np.ndarray, np.ndarray, np.ndarray | None]:
        X, log_w = self._log_weights_shifted(state)
        top = np.max(log_w)
        if not np.isfinite(top):
            return -np.inf, np.zeros(self.model.n), np.zeros((self.model.n,) * 2), None
        w = np.exp(log_w - top)
        total = w.sum()
        mean = w @ X / total
        d = X - mean
        cov = (w[:, None] * d).T @ d / total
        return top + np.log(total), mean, cov, X[int(np.argmax(log_w - self.log_weights))]

    def _estimate(self, state: WeiNormanState, log_z: float, mean, cov, mode, increment: float) -> Estimate:
        return Estimate(step=state.step, t=state.t, mean=mean, cov=cov, loglik=state.loglik,
                        loglik_increment=increment, degenerate=state.degenerate, reason=state.reason,
                        mode=mode)

    # -- Filter protocol ---------------------------------------------------------------------------
    def initial_state(self, prior: Any | None = None) -> WeiNormanState:
        if prior is not None:
            raise InputError("prior", "the Wei-Norman filter keeps the prior its Kolmogorov flow starts from")
        return WeiNormanState(step=0, t=0.0, y=np.zeros(self.model.m), r=np.zeros(3), loglik=0.0)

    def step(self, state: WeiNormanState, increment: np.ndarray | None) -> tuple[WeiNormanState, Estimate]:
        if increment is None or np.isnan(np.asarray(increment, dtype=float)).any():
            raise InputError("increments", "the Wei-Norman representation (12) needs every increment; "
                                           "missing observations are not supported (use yau-yau)")
        dy = check_increments(np.reshape(increment, (1, -1)), self.model.m)[0]
        dt = self.model.dt
        y1 = state.y + dy
        r = self.advance(state.r, float(self.gain @ state.y), float(self.gain @ y1), dt)
        new = WeiNormanState(step=state.step + 1, t=state.t + dt, y=y1, r=r, loglik=state.loglik)
        log_z, mean, cov, mode = self._moments(new)
        if not np.isfinite(log_z):
            new.degenerate = True
            new.reason = ("the conditional density vanished on the quadrature nodes: the shift r2 = "
                          f"{r[2]:.3g} moved e^(tL0)sigma0 off its domain")
            return new, self._estimate(new, log_z, mean, cov, mode, 0.0)
        new.loglik = log_z
        return new, self._estimate(new, log_z, mean, cov, mode, log_z - state.loglik)

    def run(self, state: WeiNormanState, increments: np.ndarray) -> tuple[WeiNormanState, list[Estimate]]:
        rows = check_increments(increments, self.model.m)
        estimates = []
        for row in rows:
            state, est = self.step(state, row)
            estimates.append(est)
        return state, estimates

    def estimate(self, state: WeiNormanState) -> Estimate:
        log_z, mean, cov, mode = self._moments(state)
        return self._estimate(state, log_z, mean, cov, mode, 0.0)

    def density(self, state: WeiNormanState, points: np.ndarray) -> np.ndarray:
        """Normalised conditional density at points (normaliser from the quadrature nodes)."""
        log_z = self._moments(state)[0]
        if not np.isfinite(log_z):
            return np.zeros(np.atleast_2d(points).shape[0])
        return np.exp(self.log_density_unnormalised(state, points) - log_z)

    def state_from_dict(self, data: dict[str, Any]) -> WeiNormanState:
        try:
            state = WeiNormanState(step=int(data["step"]), t=float(data["t"]),
                                   y=np.asarray(data["y"], dtype=float).reshape(self.model.m),
                                   r=np.asarray(data["r"], dtype=float).reshape(3),
                                   loglik=float(data["loglik"]),
                                   degenerate=bool(data.get("degenerate", False)), reason=data.get("reason"))
        except (KeyError, TypeError, ValueError) as exc:
            raise InputError("state", f"not a Wei-Norman filter state: {exc}") from None
        if not (np.all(np.isfinite(state.y)) and np.all(np.isfinite(state.r))):
            raise InputError("state", "y and r must be finite")
        return state


def _shift_integral(model: Model, k: int):
    """(x, r) ↦ ∫_0^r f_k(x + τ e_k) dτ, the log of the integrating factor of e^{r D_k}."""
    tau, r = sp.Symbol("tau_", real=True), sp.Symbol("r_", real=True)
    xk = model.symbols[k]
    integral = sp.integrate(model.drift[k].subs(xk, xk + tau), (tau, 0, r))
    return vectorize(sp.simplify(integral), [*model.symbols, r])


def _observation_weights(model: Model):
    """x ↦ R⁻¹h(x), shape (P, m): log σ − log u = hᵀR⁻¹y   (seed 004 (9))."""
    h = sp.Matrix(model.observation)
    weights = exact_matrix(model.R).inv() * h
    parts = [vectorize(w, model.symbols) for w in weights]
    return lambda X: np.stack([p(X) for p in parts], axis=1)


def kolmogorov_flow_from_offline(offline) -> Callable[[float, np.ndarray], np.ndarray]:
    """e^{t L0} σ0 from the stored Kolmogorov propagator (``propagator_k``, seed 002 (5.31)).

    σ at the nodes after k intervals is (propagator_k · projector)^k σ0, interpolated at any
    points by the finite-element space; t must be a multiple of dt (the filter only asks for those).
    """
    model = offline.model
    history = [np.exp(model.log_prior(offline.nodes))]

    def flow(t: float, points: np.ndarray) -> np.ndarray:
        k = int(round(t / model.dt))
        if k < 0 or abs(k * model.dt - t) > 1e-9 * max(1.0, t):
            raise InputError("t", "the stored Kolmogorov flow is known at multiples of dt only")
        while len(history) <= k:
            history.append(offline.propagator_k @ (offline.projector @ history[-1]))
        if points is offline.nodes:  # its own nodes: the nodal values, no element search
            return history[k]
        return offline.interpolate(history[k], points)

    flow.nodes, flow.weights = offline.nodes, offline.weights  # the filter's default quadrature
    return flow
