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

A chunk is computed at once (``run_arrays``): (13) is linear, so r1, r2 of every row come from one
data-free affine recursion; log σ at the flow's nodes is then a (rows × nodes) matrix: a small
product of per-row coefficients with per-node features (R⁻¹h, x_k, the shift integral as a
polynomial in r2) plus log e^{tL0}σ0, which does not depend on the data and is cached per step.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
import scipy.linalg
import sympy as sp

from ..analysis import exact_matrix, is_identity, observed_coordinate, seed004_structure
from ..errors import InputError, SpecError
from ..expressions import vectorize
from ..filtering import ChunkResult, Estimate, chunk_clock, refuse_form
from ..measurement import check_rows
from ..model import Model

if TYPE_CHECKING:  # types only
    from numpy.typing import ArrayLike

    from ..offline.pipeline import OfflineModel

DEFAULT_POINTS_PER_AXIS = {1: 801, 2: 161, 3: 61}
FLOW_CACHE_BYTES = 256 * 2**20  # log e^{tL0}σ0 at the nodes, kept for the first steps up to this size
# rows handled at once: rows × nodes × 16 under OpenBLAS's threading threshold (2^18 multiply-adds),
# so the skinny products stay single-threaded (threads cost 4-20x on a loaded machine, measured)
BLOCK_PRODUCT = 2**18
MAX_SHIFT_DEGREE = 8  # the shift integral as a polynomial in r2 up to this degree, else pointwise


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
    follows = False  # the Filter contract: its grid does not move

    def __init__(self, model: Model, kolmogorov_flow: Callable[[float, np.ndarray], np.ndarray], *,
                 log_flow: bool = False, nodes: np.ndarray | None = None, weights: np.ndarray | None = None,
                 points_per_axis: int | None = None):
        if model.spec.measurement.kind == "discrete":
            raise SpecError("measurement.kind", "the Wei-Norman representation (12) is driven by the "
                                                "observation path y(t) of continuous increments; discrete "
                                                "measurements: use yau-yau (the general engine)")
        self.model = model
        self.flow = kolmogorov_flow
        self.log_flow = log_flow
        k = observed_coordinate(model)
        if not is_identity(model.a):
            raise SpecError("diffusion", "the Wei-Norman filter of Shi et al. (2017) needs a = I")
        structure = seed004_structure(model, k) if k is not None else None
        if structure is None:
            raise SpecError("method", "wei-norman needs omega_kj = 0, eta = A x_k^2 + B x_k + gamma(others) "
                                      "and h affine in one coordinate x_k (Shi et al. (2017) (I), (II), (v))")
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
        self._features, self._shift_poly = self._node_features()
        self._r2_range = self._shift_range()
        self._moment_features = _moment_features(self.nodes - model.center)
        self._log_v = np.empty((0, len(self.nodes)))  # rows: steps 0, 1, ... of log e^{tL0}σ0
        self._log_v_count = 0
        self._lock = threading.Lock()  # the cache is shared by every session of the model

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

    # -- the chunk: r of every row, then log σ at the nodes as one matrix --------------------------
    def _r_path(self, state: WeiNormanState, dy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(y, r) after each row: y (K, m), r (K, 3); the affine recursion of (13) row by row."""
        dt = self.model.dt
        ys = np.cumsum(np.vstack([state.y[None], dy]), axis=0)  # sequential sums, as step by step
        Y = ys @ self.gain
        Ydot = np.diff(Y) / dt
        phi, gram = self._step_map
        inputs = np.column_stack([Y[:-1], Ydot, np.ones(len(dy))])  # (Y, Ẏ, 1) of each interval
        drive = inputs @ phi[:2, 2:].T  # the data part of (r1, r2)' = Φ z
        (m00, m01), (m10, m11) = phi[:2, :2].tolist()
        r1, r2 = float(state.r[1]), float(state.r[2])
        path = np.empty((len(dy) + 1, 2))
        path[0] = r1, r2
        for k, (d1, d2) in enumerate(drive.tolist(), start=1):  # 2 × 2 affine map: plain floats
            r1, r2 = m00 * r1 + m01 * r2 + d1, m10 * r1 + m11 * r2 + d2
            path[k] = r1, r2
        z0 = np.column_stack([path[:-1], inputs])
        gains = 0.5 * np.einsum("ki,ij,kj->k", z0, gram, z0)  # ṙ0 integrated exactly per interval
        r0 = np.cumsum(np.concatenate([[state.r[0]], gains]))[1:]
        return ys[1:], np.column_stack([r0, path[1:]])

    def _node_features(self) -> tuple[np.ndarray, np.ndarray | None]:
        """Per-node rows F with log σ(z − r2 e_k) − log v = coefficients(row) @ F.

        log σ(x) − log v(x + r2 e_k) = hᵀR⁻¹y + r0 + r1 x_k − ∫_0^{r2} f_k(x + τ e_k) dτ at
        x = z − r2 e_k.  h is affine in x_k: R⁻¹h(z − r2 e_k) = R⁻¹h(z) − r2 R⁻¹c.  The shift
        integral becomes ∫_{−r2}^0 f_k(z + s e_k) ds, expanded in powers of r2 when it is a polynomial.
        """
        z, k = self.nodes, self.k
        rows = [self._hR(z).T, z[:, k][None], np.ones((1, len(z)))]
        s, r = sp.Symbol("s_", real=True), sp.Symbol("r_", real=True)
        xk = self.model.symbols[k]
        shifted = sp.expand(sp.integrate(self.model.drift[k].subs(xk, xk + s), (s, -r, 0)))
        if not shifted.is_polynomial(r) or sp.degree(shifted, r) > MAX_SHIFT_DEGREE:
            return np.vstack(rows), None
        coefficients = sp.Poly(shifted, r).all_coeffs()[::-1]  # c_0 + c_1 r + ...
        rows.append(np.stack([vectorize(c, self.model.symbols)(z) for c in coefficients]))
        return np.vstack(rows), np.arange(len(coefficients))

    def _shift_range(self) -> tuple[np.ndarray, np.ndarray]:
        """Per node z, the shifts r2 for which x = z − r2 e_k stays in the domain (ball or box)."""
        zk = self.nodes[:, self.k]
        if self._box is not None:
            return zk - self._box[1][self.k], zk - self._box[0][self.k]
        d = self.nodes - self.model.center
        room = self.model.radius**2 * (1 + 1e-12) - np.einsum("ij,ij->i", d, d) + d[:, self.k] ** 2
        half = np.sqrt(np.maximum(room, 0.0))
        return d[:, self.k] - half, d[:, self.k] + half

    def _log_flow(self, first: int, count: int) -> np.ndarray:
        """log e^{tL0}σ0 at the nodes for steps first, ..., first + count − 1 (cached, data-free)."""
        with self._lock:
            return self._log_flow_locked(first, count)

    def _log_flow_locked(self, first: int, count: int) -> np.ndarray:
        Q = len(self.nodes)
        limit = max(1, FLOW_CACHE_BYTES // (8 * Q))
        end = first + count
        if end > self._log_v_count and self._log_v_count < limit:
            grow_to = min(limit, end)
            if grow_to > len(self._log_v):
                bigger = np.empty((min(limit, max(grow_to, 2 * len(self._log_v))), Q))
                bigger[:self._log_v_count] = self._log_v[:self._log_v_count]
                self._log_v = bigger
            for step in range(self._log_v_count, grow_to):
                self._log_v[step] = self._log_flow_at(step)
            self._log_v_count = grow_to
        if end <= self._log_v_count:
            return self._log_v[first:end]
        cached = self._log_v[first:self._log_v_count]
        rest = [self._log_flow_at(step) for step in range(max(first, self._log_v_count), end)]
        return np.vstack([cached, *rest]) if len(cached) else np.vstack(rest)

    def _log_flow_at(self, step: int) -> np.ndarray:
        values = np.asarray(self.flow(step * self.model.dt, self.nodes), dtype=float).reshape(-1)
        if values.shape != (len(self.nodes),):
            raise InputError("kolmogorov_flow", f"must return {len(self.nodes)} values, got {values.shape}")
        with np.errstate(divide="ignore", invalid="ignore"):
            log_v = values if self.log_flow else np.log(np.where(values > 0, values, 0.0))
        return np.where(np.isnan(log_v), -np.inf, log_v)

    def _log_sigma(self, steps: np.ndarray, y: np.ndarray, r: np.ndarray) -> np.ndarray:
        """log σ(t, z − r2 e_k) at the nodes z, rows × nodes (−inf where x leaves the domain)."""
        r0, r1, r2 = r.T
        Y = y @ self.gain
        columns = [y, r1[:, None], (r0 - r1 * r2 - r2 * Y)[:, None]]
        if self._shift_poly is not None:
            columns.append(-(r2[:, None] ** self._shift_poly))
        log_s = np.column_stack(columns) @ self._features
        log_s += self._log_flow(int(steps[0]), len(steps))
        if self._shift_poly is None:  # the shift integral pointwise (not a polynomial in r2)
            K, Q = log_s.shape
            X = np.repeat(self.nodes[None], K, axis=0)
            X[:, :, self.k] -= r2[:, None]
            points = np.column_stack([X.reshape(K * Q, -1), np.repeat(r2, Q)])
            log_s -= self._shift_integral(points).reshape(K, Q)
        lo, hi = self._r2_range
        log_s[(r2[:, None] < lo) | (r2[:, None] > hi)] = -np.inf
        return log_s

    def _chunk_moments(self, steps: np.ndarray, y: np.ndarray, r: np.ndarray):
        """log ∫σ, mean, cov, mode of every row (zeros where σ vanished at every node)."""
        K, n = len(steps), self.model.n
        block = max(1, BLOCK_PRODUCT // (16 * len(self.nodes)))
        log_z, mean, cov, mode = np.empty(K), np.zeros((K, n)), np.zeros((K, n, n)), np.zeros((K, n))
        for a in range(0, K, block):
            b = min(K, a + block)
            log_s = self._log_sigma(steps[a:b], y[a:b], r[a:b])
            best = np.argmax(log_s, axis=1)
            log_s += self.log_weights
            top = np.max(log_s, axis=1)
            ok = np.isfinite(top)
            w = np.exp(log_s - np.where(ok, top, 0.0)[:, None])
            moments = w @ self._moment_features  # Σw, Σw z, Σw z zᵀ (z from the centre)
            total = np.where(ok, moments[:, 0], 1.0)
            centred = moments[:, 1:n + 1] / total[:, None]
            second = moments[:, n + 1:].reshape(-1, n, n) / total[:, None, None]
            shift = np.zeros((b - a, n))
            shift[:, self.k] = r[a:b, 2]
            log_z[a:b] = np.where(ok, top + np.log(total), -np.inf)
            mean[a:b] = np.where(ok[:, None], centred + self.model.center - shift, 0.0)
            cov[a:b] = np.where(ok[:, None, None], second - centred[:, :, None] * centred[:, None, :], 0.0)
            mode[a:b] = np.where(ok[:, None], self.nodes[best] - shift, 0.0)
        return log_z, mean, cov, mode

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

    def _state_moments(self, state: WeiNormanState):
        log_z, mean, cov, mode = self._chunk_moments(np.array([state.step]), state.y[None], state.r[None])
        return float(log_z[0]), mean[0], cov[0], mode[0]

    # -- Filter protocol ---------------------------------------------------------------------------
    def initial_state(self, prior: Any | None = None) -> WeiNormanState:
        if prior is not None:
            raise InputError("prior", "the Wei-Norman filter keeps the prior its Kolmogorov flow starts from")
        return WeiNormanState(step=0, t=0.0, y=np.zeros(self.model.m), r=np.zeros(3), loglik=0.0)

    gate_override: float | None = None  # the Wei-Norman filter cannot skip a row, so it never gates
    restartable = False  # its representation (12) runs from t = 0: no restart mid-stream

    def step(self, state: WeiNormanState, increment: np.ndarray | None,
             t: float | None = None) -> tuple[WeiNormanState, Estimate]:
        if increment is None:
            raise InputError("increment", MISSING)
        new, result = self.run_arrays(state, np.reshape(np.asarray(increment, dtype=float), (1, -1)),
                                      None if t is None else [t])
        return new, result.estimates()[0]

    def run(self, state: WeiNormanState, increments: np.ndarray,
            times: ArrayLike | None = None) -> tuple[WeiNormanState, list[Estimate]]:
        new, result = self.run_arrays(state, increments, times)
        return new, result.estimates()

    def with_gate(self, gate: float | None) -> "WeiNormanFilter":
        return self  # it never gates

    def predict(self, state: WeiNormanState, t: float) -> tuple[WeiNormanState, Estimate]:
        raise InputError("t", "the Wei-Norman representation (12) needs the observation path: it cannot "
                              "forecast without observations; use method yau-yau")

    def run_arrays(self, state: WeiNormanState, increments: np.ndarray,
                   times: ArrayLike | None = None) -> tuple[WeiNormanState, ChunkResult]:
        """Advance over a chunk (K, m) of increments; estimates as arrays (the engine's ChunkResult)."""
        dy = check_rows(increments, self.model.m)
        refuse_form(self.method, dy, times, self.model, partial_ok=True)  # irregular times, discrete rows
        if np.isnan(dy).any():  # a missing row or component
            raise InputError("increments", MISSING)
        K, n = len(dy), self.model.n
        steps, times = chunk_clock(state, K, self.model.dt, None, None)  # t0 + k·dt
        if K == 0:
            return state, ChunkResult(steps, times, np.empty((0, n)), np.empty((0, n, n)), np.empty((0, n)),
                                     np.empty(0), np.empty(0), np.zeros(0, bool))
        y, r = self._r_path(state, dy)
        log_z, mean, cov, mode = self._chunk_moments(steps, y, r)
        degenerate = ~np.isfinite(log_z)
        # a vanished step keeps the previous log-likelihood (increment 0), as the stepwise filter did
        loglik = np.where(degenerate, np.nan, log_z)
        loglik = _carry_forward(np.concatenate([[state.loglik], loglik]))
        increments_ll = np.diff(loglik)
        reason = None
        if degenerate.any():
            first = int(np.argmax(degenerate))
            reason = ("the conditional density vanished on the quadrature nodes: the shift r2 = "
                      f"{r[first, 2]:.3g} moved e^(tL0)sigma0 off its domain")
        new = WeiNormanState(step=int(steps[-1]), t=float(times[-1]), y=y[-1].copy(), r=r[-1].copy(),
                             loglik=float(loglik[-1]), degenerate=bool(degenerate[-1]))
        if new.degenerate:
            new.reason = ("the conditional density vanished on the quadrature nodes: the shift r2 = "
                          f"{r[-1, 2]:.3g} moved e^(tL0)sigma0 off its domain")
        return new, ChunkResult(step=steps, t=times, mean=mean, cov=cov, mode=mode, loglik=loglik[1:],
                           loglik_increment=increments_ll, degenerate=degenerate, reason=reason)

    def estimate(self, state: WeiNormanState) -> Estimate:
        log_z, mean, cov, mode = self._state_moments(state)
        vanished = not np.isfinite(log_z)
        return Estimate(step=state.step, t=state.t, mean=mean, cov=cov, loglik=state.loglik,
                        loglik_increment=0.0, degenerate=state.degenerate or vanished,
                        reason=state.reason, mode=None if vanished else mode)

    def density(self, state: WeiNormanState, points: np.ndarray) -> np.ndarray:
        """Normalised conditional density at points (normaliser from the quadrature nodes)."""
        log_z = self._state_moments(state)[0]
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
        if state.step < 0:
            raise InputError("state", "step must be >= 0")
        return state


MISSING = ("the Wei-Norman representation (12) needs every increment; missing observations are not "
           "supported (use yau-yau)")


def _carry_forward(values: np.ndarray) -> np.ndarray:
    """NaN entries replaced by the last number before them (values[0] is a number)."""
    index = np.where(np.isnan(values), 0, np.arange(len(values)))
    return values[np.maximum.accumulate(index)]


def _moment_features(d: np.ndarray) -> np.ndarray:
    """(Q, 1 + n + n²) columns 1, d_i, d_i d_j of the node offsets d: Σ w · these are the moments."""
    Q, n = d.shape
    return np.column_stack([np.ones(Q), d, (d[:, :, None] * d[:, None, :]).reshape(Q, n * n)])


class _softplus(sp.Function):
    """softplus(z) = log(1 + e^z), evaluated as numpy's logaddexp(0, z): finite for every z."""


def _stable_logs(expr: sp.Expr) -> sp.Expr:
    """log(1 ± tanh u) = log 2 − softplus(∓2u): SymPy's antiderivative of tanh is log(tanh u + 1),
    which is log(0) = −inf in floating point for u ≲ −19 (and −inf − (−inf) = NaN downstream)."""
    def stable(arg: sp.Expr):
        rest = sp.expand(arg - 1)  # ±tanh(u)
        if rest.func == sp.tanh:
            return sp.log(2) - _softplus(-2 * rest.args[0])
        if (-rest).func == sp.tanh:
            return sp.log(2) - _softplus(2 * (-rest).args[0])
        return None

    return expr.replace(lambda e: e.func == sp.log and stable(e.args[0]) is not None,
                        lambda e: stable(e.args[0]))


def _shift_integral(model: Model, k: int):
    """(x, r) ↦ ∫_0^r f_k(x + τ e_k) dτ, the log of the integrating factor of e^{r D_k}."""
    tau, r = sp.Symbol("tau_", real=True), sp.Symbol("r_", real=True)
    xk = model.symbols[k]
    integral = _stable_logs(sp.simplify(sp.integrate(model.drift[k].subs(xk, xk + tau), (tau, 0, r))))
    return vectorize(integral, [*model.symbols, r], {"_softplus": lambda z: np.logaddexp(0.0, z)})


def _observation_weights(model: Model):
    """x ↦ R⁻¹h(x), shape (P, m): log σ − log u = hᵀR⁻¹y   (seed 004 (9))."""
    h = sp.Matrix(model.observation)
    weights = exact_matrix(model.R).inv() * h
    parts = [vectorize(w, model.symbols) for w in weights]
    return lambda X: np.stack([p(X) for p in parts], axis=1)


class KolmogorovFlow:
    """e^{t L0} σ0 from the stored Kolmogorov propagator (``propagator_k``, seed 002 (5.31)).

    σ at the nodes after k intervals is (propagator_k · projector)^k σ0, interpolated at any
    points by the finite-element space; t must be a multiple of dt (the filter only asks for those).
    Memory is bounded by ``cache_bytes``: checkpoints every ``stride`` steps (the stride doubles when
    they would exceed it) and the last vector computed, so a later step is a few products away.
    Thread-safe: one flow serves every session of a model.
    """

    def __init__(self, offline: OfflineModel, cache_bytes: int | None = None):
        self.offline = offline
        self.model = offline.model
        self.nodes, self.weights = offline.nodes, offline.weights  # the filter's default quadrature
        vector_bytes = 8 * len(offline.nodes)
        self.max_vectors = max(4, (FLOW_CACHE_BYTES if cache_bytes is None else cache_bytes) // vector_bytes)
        self.stride = 1
        self._checkpoints: dict[int, np.ndarray] = {0: np.exp(self.model.log_prior(offline.nodes))}
        self._last = (0, self._checkpoints[0])
        self._lock = threading.Lock()

    @property
    def held_bytes(self) -> int:
        return 8 * len(self.nodes) * (len(self._checkpoints) + 1)

    def __call__(self, t: float, points: np.ndarray) -> np.ndarray:
        k = int(round(t / self.model.dt))
        if k < 0 or abs(k * self.model.dt - t) > 1e-9 * max(1.0, t):
            raise InputError("t", "the stored Kolmogorov flow is known at multiples of dt only")
        values = self._at(k)
        if points is self.nodes:  # its own nodes: the nodal values, no element search
            return values
        return self.offline.interpolate(values, points)

    def _at(self, k: int) -> np.ndarray:
        with self._lock:
            start = max((j for j in self._checkpoints if j <= k), default=0)
            if self._last[0] <= k and self._last[0] > start:
                start = self._last[0]
                vector = self._last[1]
            else:
                vector = self._checkpoints[start]
            for j in range(start + 1, k + 1):
                vector = self.offline.propagator_k @ (self.offline.projector @ vector)
                if j % self.stride == 0:
                    self._checkpoints[j] = vector
                    if len(self._checkpoints) > self.max_vectors:
                        self.stride *= 2
                        self._checkpoints = {i: v for i, v in self._checkpoints.items()
                                             if i % self.stride == 0}
            self._last = (k, vector)
            return vector


def kolmogorov_flow_from_offline(offline: OfflineModel) -> KolmogorovFlow:
    """e^{t L0} σ0 from the stored Kolmogorov propagator (see :class:`KolmogorovFlow`)."""
    return KolmogorovFlow(offline)


def build(model: Model, offline: OfflineModel, **_: Any) -> WeiNormanFilter:
    """The registry's constructor (solver/registry.py): the Kolmogorov flow from the stored arrays."""
    return WeiNormanFilter(model, kolmogorov_flow_from_offline(offline))
