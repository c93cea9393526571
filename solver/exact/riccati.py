"""Gaussian solutions of the Kolmogorov equation with linear drift and quadratic potential.

    ∂u/∂t = ½ Σ a_ij ∂i∂j u − (Dx + d)·∇u − (tr D + xᵀQx + qᵀx + r) u

has solutions u(x, t) = exp(−xᵀA(t)x − Bᵀ(t)x − C(t)) (A symmetric) whenever

    A' = Q − AD − DᵀA − 2AaA
    B' = q − 2Ad − (Dᵀ + 2Aa)B
    C' = r + tr D + tr(aA) − ½BᵀaB − dᵀB

(derived by substitution; tests/solver/test_oracles.py checks it with SymPy).  This is seed 000
Theorem 3.2, (3.8)–(3.10), and seed 001 Theorem 4.2, (4.14)–(4.16), up to sign conventions:
the seeds write u = exp(+xᵀAx + Bᵀx + C) and put the potential with the opposite sign.

Two ways to get A, B, C:

* :meth:`GaussianKolmogorov.solve` integrates the ODEs with ``solve_ivp`` (reference);
* :class:`GaussianFlow` is the exact flow over a fixed step dt: the Riccati equation is
  linearised as A = Y X⁻¹ with [X; Y]' = [[D, 2a], [Q, −Dᵀ]] [X; Y], so that
  B(t) = X⁻ᵀ[B0 + ∫(Xᵀq − 2Yᵀd) ds] and ∫tr(aA) = ½(log det X − t tr D); only ∫(½BᵀaB + dᵀB)
  is left to a Gauss–Legendre rule.  One step costs a few n×n products (Kalman-like).

Chunks of steps (the filters' ``run``): A does not depend on the data, B enters linearly, C is
a sum.  :class:`FlowFamily` holds the flows a step may use (with / without the observation
potential); ``FlowFamily.path`` is the Riccati path of A (sequential, scalar loop for n = 1),
:class:`StepBatch` the data-free matrices of all K steps at once, :func:`affine_path` the one
sequential recursion B_k = W_k B_{k−1} + v_k, and ``StepBatch.finish`` the C gains in batch.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.integrate import solve_ivp
from scipy.linalg import expm

from ..errors import InputError, SpecError

_GAUSS_NODES = 8  # Gauss–Legendre nodes for ∫(½BᵀaB + dᵀB) over one step
_BLOW_UP = "the Riccati solution blows up within the step (det X <= 0)"
SPECTRAL_COND = 1e4  # eigenvector condition number up to which gap flows use M's eigen-decomposition
MAX_PIECES = 4096  # most pieces a gap flow is split into (gap_pieces)


def _matrix(value, n: int, field: str) -> np.ndarray:
    arr = np.zeros((n, n)) if value is None else np.asarray(value, dtype=float)
    if arr.shape != (n, n) or not np.all(np.isfinite(arr)):
        raise SpecError(field, f"must be a finite {n}x{n} matrix")
    return arr


def _vector(value, n: int, field: str) -> np.ndarray:
    arr = np.zeros(n) if value is None else np.asarray(value, dtype=float).reshape(-1)
    if arr.shape != (n,) or not np.all(np.isfinite(arr)):
        raise SpecError(field, f"must be {n} finite numbers")
    return arr


@dataclass(frozen=True)
class GaussianTerms:
    """Exponent of u = exp(−xᵀAx − Bᵀx − C); arrays carry a leading time axis when solved."""

    A: np.ndarray
    B: np.ndarray
    C: np.ndarray


def gaussian_to_terms(mean, cov, weight: float = 1.0) -> GaussianTerms:
    """(A, B, C) of weight·N(mean, cov): A = ½P⁻¹, B = −P⁻¹m, C = ½mᵀP⁻¹m + ½log det(2πP) − log w."""
    m = np.atleast_1d(np.asarray(mean, dtype=float))
    P = np.atleast_2d(np.asarray(cov, dtype=float))
    if weight <= 0:
        raise InputError("weight", "must be positive")
    chol = np.linalg.cholesky(P)
    P_inv = np.linalg.inv(P)
    log_det = 2.0 * np.log(np.diag(chol)).sum() + len(m) * np.log(2 * np.pi)
    return GaussianTerms(0.5 * P_inv, -P_inv @ m, 0.5 * m @ P_inv @ m + 0.5 * log_det - np.log(weight))


def terms_to_gaussian(A, B, C) -> tuple[np.ndarray, np.ndarray, float]:
    """Inverse of :func:`gaussian_to_terms`: (mean, cov, log mass) of exp(−xᵀAx − Bᵀx − C).

    Raises InputError when A is not positive definite (u is then not integrable).
    """
    A = np.atleast_2d(np.asarray(A, dtype=float))
    B = np.atleast_1d(np.asarray(B, dtype=float))
    try:
        chol = np.linalg.cholesky(2.0 * A)
    except np.linalg.LinAlgError:
        raise InputError("A", "not positive definite: the exponential is not integrable") from None
    cov = np.linalg.inv(2.0 * A)
    mean = -cov @ B
    log_det = 2.0 * np.log(np.diag(chol)).sum()
    # ∫exp(−xᵀAx − Bᵀx − C) dx = (2π)^{n/2} det(2A)^{-1/2} exp(¼Bᵀ A⁻¹ B − C)
    log_mass = 0.5 * len(B) * np.log(2 * np.pi) - 0.5 * log_det + 0.5 * B @ cov @ B - float(C)
    return mean, 0.5 * (cov + cov.T), float(log_mass)


class GaussianKolmogorov:
    """The Kolmogorov equation of the module docstring with constant coefficients."""

    def __init__(self, D, d=None, Q=None, q=None, r: float = 0.0, a=None):
        D = np.atleast_2d(np.asarray(D, dtype=float))
        n = D.shape[0]
        self.n = n
        self.D = _matrix(D, n, "D")
        self.d = _vector(d, n, "d")
        Q = _matrix(Q, n, "Q")
        self.Q = 0.5 * (Q + Q.T)  # only the symmetric part enters xᵀQx
        self.q = _vector(q, n, "q")
        if not np.isfinite(r):
            raise SpecError("r", "must be finite")
        self.r = float(r)
        self.a = np.eye(n) if a is None else _matrix(a, n, "a")
        if not np.allclose(self.a, self.a.T):
            raise SpecError("a", "must be symmetric")

    # -- the ODEs -------------------------------------------------------------------
    def rhs(self, A: np.ndarray, B: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
        """(A', B', C') at (A, B)."""
        D, a = self.D, self.a
        dA = self.Q - A @ D - D.T @ A - 2.0 * A @ a @ A
        dB = self.q - 2.0 * A @ self.d - (D.T + 2.0 * A @ a) @ B
        dC = self.r + np.trace(D) + np.trace(a @ A) - 0.5 * B @ a @ B - self.d @ B
        return dA, dB, float(dC)

    def solve(self, A0, B0, C0, t_grid, rtol: float = 1e-11, atol: float = 1e-12) -> GaussianTerms:
        """Integrate the ODEs from t_grid[0] (arrays of shape (T, n, n), (T, n), (T,))."""
        n = self.n
        t_grid = np.asarray(t_grid, dtype=float)
        y0 = np.concatenate([_matrix(A0, n, "A0").ravel(), _vector(B0, n, "B0"), [float(C0)]])

        def f(_t, y):
            A = y[: n * n].reshape(n, n)
            dA, dB, dC = self.rhs(0.5 * (A + A.T), y[n * n: n * n + n])
            return np.concatenate([dA.ravel(), dB, [dC]])

        sol = solve_ivp(f, (t_grid[0], t_grid[-1]), y0, t_eval=t_grid, method="DOP853",
                        rtol=rtol, atol=atol)
        if not sol.success or not np.all(np.isfinite(sol.y)):
            raise InputError("t_grid", f"Riccati integration failed ({sol.message}); A may blow up")
        Y = sol.y.T
        return GaussianTerms(Y[:, : n * n].reshape(-1, n, n), Y[:, n * n: n * n + n], Y[:, -1])

    def u(self, x, terms: GaussianTerms) -> np.ndarray:
        """u at points x (P, n) for each time of ``terms``: shape (T, P) (or (P,) for one time)."""
        return np.exp(self.log_u(x, terms))

    def log_u(self, x, terms: GaussianTerms) -> np.ndarray:
        X = np.atleast_2d(np.asarray(x, dtype=float))
        A, B, C = np.asarray(terms.A), np.asarray(terms.B), np.asarray(terms.C)
        if A.ndim == 2:
            return -np.einsum("pi,ij,pj->p", X, A, X) - X @ B - C
        return -np.einsum("pi,tij,pj->tp", X, A, X) - B @ X.T - C[:, None]

    def flow(self, dt: float) -> "GaussianFlow":
        return GaussianFlow(self, dt)

    # -- flows over arbitrary gaps (irregular observation times) ------------------------------
    @property
    def hamiltonian(self) -> np.ndarray:
        """M = [[D, 2a], [Q, −Dᵀ]]: [X; Y]' = M [X; Y] linearises the Riccati equation."""
        return np.block([[self.D, 2.0 * self.a], [self.Q, -self.D.T]])

    def spectrum(self):
        """((λ, V, V⁻¹) of M = V diag(λ) V⁻¹, or None when M is (nearly) defective (cond V >
        SPECTRAL_COND); ρ = max |λ|).  Computed once per equation."""
        found = self.__dict__.get("_spectrum")
        if found is None:
            M = self.hamiltonian
            lam, V = np.linalg.eig(M)
            rho = float(np.abs(lam).max()) if len(lam) else 0.0
            ok = np.all(np.isfinite(V)) and np.linalg.cond(V) <= SPECTRAL_COND
            found = self._spectrum = ((lam, V, np.linalg.inv(V)) if ok else None, rho)
        return found

    def gap_flow(self, dt: float) -> "GaussianFlow":
        """The flow over a gap dt with e^{Ms} from the eigen-decomposition of M (a few products per gap
        instead of nine matrix exponentials; expm where M is nearly defective)."""
        return GaussianFlow(self, dt, spectral=True)


def gap_pieces(tau: float, rho: float, delta: float) -> tuple[float, ...]:
    """Lengths that add up to a gap τ, over each of which a flow's Gauss–Legendre rule (the C
    integral) is accurate to ~1e-12.  The integrand is analytic but for the zeros of det X(s), the
    nearest where the covariance would reach 0 backwards in time, at a distance δ ≈ λ_min(P)/λ_max(a)
    (``delta``); the rule converges like that distance over the piece's length.  So the first piece
    is δ/2, each next at most twice the previous (the prediction widens P, pushing the zero away),
    and none longer than 1/ρ (``rho``: the spectral radius of the linear system, the rate at which
    the exponentials vary).  Measured on a scalar flow against 8192 pieces: 1e-13 to 1e-10 in the
    log-mass where one piece errs by 1e-6 (P = 0.8, τ = 3) to 39 (P = 0.001, τ = 1).  Splitting is
    exact: the observation path is linear over the gap.  At most MAX_PIECES (equal pieces beyond:
    a gap of thousands of the model's time scales costs bounded work, less accurately)."""
    cap = 1.0 / rho if rho > 0 and math.isfinite(rho) else math.inf
    first = 0.5 * delta if delta > 0 else math.inf
    if tau <= min(first, cap):
        return (float(tau),)
    if tau > MAX_PIECES * cap:
        return (tau / MAX_PIECES,) * MAX_PIECES
    pieces, done = [], 0.0
    length = max(min(first, cap), tau * 1e-12)
    while done < tau and len(pieces) < MAX_PIECES - 1:
        piece = min(length, cap, tau - done)
        if tau - done - piece < 1e-6 * piece:
            piece = tau - done
        pieces.append(piece)
        done += piece
        length = 2.0 * piece
    if done < tau:
        pieces.append(tau - done)
    return tuple(pieces)


class GaussianFlow:
    """Exact map (A, B, C)(t) -> (A, B, C)(t + dt) of a :class:`GaussianKolmogorov`.

    The potential's linear part q and constant r may change from step to step (the Yau–Hu
    filter feeds the observation through them); D, a, Q are fixed, so the matrix
    exponentials are computed once.
    """

    def __init__(self, eq: GaussianKolmogorov, dt: float, spectral: bool = False):
        if not (np.isfinite(dt) and dt > 0):
            raise SpecError("dt", "must be positive")
        self.eq = eq
        self.dt = float(dt)
        n = eq.n
        M = np.block([[eq.D, 2.0 * eq.a], [eq.Q, -eq.D.T]])
        nodes, w = np.polynomial.legendre.leggauss(_GAUSS_NODES)
        self.s = 0.5 * self.dt * (nodes + 1.0)
        self.w = 0.5 * self.dt * w
        self._family = None
        decomposed = eq.spectrum()[0] if spectral else None
        if decomposed is not None:
            # Φ(s) = V e^{Λs} V⁻¹, Ψ(s) = ∫0^s Φ = V diag(s·(e^{λs} − 1)/(λs)) V⁻¹
            lam, V, V_inv = decomposed
            at = np.append(self.s, self.dt)[:, None]
            z = lam[None, :] * at
            with np.errstate(invalid="ignore", divide="ignore"):
                phi1 = np.where(z == 0, 1.0, np.expm1(z) / np.where(z == 0, 1.0, z))
            self.Phi = np.einsum("ij,sj,jk->sik", V, np.exp(z), V_inv).real
            self.Psi = np.einsum("ij,sj,jk->sik", V, at * phi1, V_inv).real
            return
        # Φ(s) = e^{Ms} and Ψ(s) = ∫0^s e^{Mτ}dτ, at the nodes and at dt (Van Loan block trick)
        big = np.zeros((4 * n, 4 * n))
        big[: 2 * n, : 2 * n] = M
        big[: 2 * n, 2 * n:] = np.eye(2 * n)
        blocks = [expm(big * s) for s in np.append(self.s, self.dt)]
        self.Phi = np.stack([b[: 2 * n, : 2 * n] for b in blocks])
        self.Psi = np.stack([b[: 2 * n, 2 * n:] for b in blocks])

    @property
    def family(self) -> "FlowFamily":
        if self._family is None:
            self._family = FlowFamily([self])
        return self._family

    def step(self, A, B, C, q=None, r=None) -> GaussianTerms:
        """Advance (A, B, C) over dt; A may be (n, n) or a stack (K, n, n) of components."""
        eq = self.eq
        q = eq.q if q is None else np.asarray(q, dtype=float)
        r = eq.r if r is None else float(r)
        A = np.asarray(A, dtype=float)
        single = A.ndim == 2
        A, B, C = (A[None] if single else A), np.atleast_2d(B), np.atleast_1d(C)
        once = np.zeros(1, dtype=int)
        family = self.family
        A_new = family.path(once, A)[1]
        B_new, gain = family.batch(once, A[None], q[None], np.array([r])).finish(B[None])
        if single:
            return GaussianTerms(A_new[0], B_new[0, 0], float(C[0] + gain[0, 0]))
        return GaussianTerms(A_new, B_new[0], C + gain[0])


class FlowFamily:
    """Flows over the same dt that share D, d and a (only Q, q, r differ): a step may pick any.

    The filters use two: with the observation potential (an observed step) and without (a
    missing row).  Their matrices are stacked once so that a chunk of steps is gathered in one go.
    """

    def __init__(self, flows: list[GaussianFlow]):
        first = flows[0]
        for other in flows[1:]:
            same = other.dt == first.dt and all(np.array_equal(getattr(other.eq, k), getattr(first.eq, k))
                                                for k in ("D", "d", "a"))
            if not same:
                raise SpecError("flows", "a flow family needs one dt and the same D, d and a")
        self.eq, self.dt, self.w = first.eq, first.dt, first.w
        self.Phi = np.stack([f.Phi for f in flows])  # (F, S+1, 2n, 2n)
        self.Psi = np.stack([f.Psi for f in flows])
        n = first.eq.n
        at_dt = self.Phi[:, -1]
        corners = ((0, 0), (0, 1), (1, 0), (1, 1))
        self._mobius = [at_dt[:, i, j].tolist() for i, j in corners] if n == 1 else None  # scalar Möbius map

    def path(self, choice, A0) -> np.ndarray:
        """A_k = Y X⁻¹ with [X; Y] = Φ(dt) [I; A_{k−1}], step k by flow choice[k] (exact Riccati flow).

        A0 (J, n, n) are J independent starts; returns (K + 1, J, n, n).  Observation-free: the
        whole path of a chunk is known before the data enter.  Scalar Python loop for n = 1.
        """
        A0 = np.asarray(A0, dtype=float)
        J, n = A0.shape[0], A0.shape[-1]
        choice = np.asarray(choice, dtype=int)
        out = np.empty((len(choice) + 1, J, n, n))
        out[0] = A0
        if self._mobius is not None:
            p11, p12, p21, p22 = self._mobius
            picks = choice.tolist()
            for j in range(J):
                a, path = float(A0[j, 0, 0]), []
                for f in picks:
                    x = p11[f] + p12[f] * a
                    if not x > 0.0:
                        raise InputError("dt", _BLOW_UP)
                    a = (p21[f] + p22[f] * a) / x
                    path.append(a)
                out[1:, j, 0, 0] = path
            return out
        phis, A = self.Phi[:, -1], A0
        for k, f in enumerate(choice.tolist()):
            X = phis[f, :n, :n] + phis[f, :n, n:] @ A
            sign, _ = np.linalg.slogdet(X)
            if np.any(sign <= 0):
                raise InputError("dt", _BLOW_UP)
            A = (phis[f, n:, :n] + phis[f, n:, n:] @ A) @ np.linalg.inv(X)
            A = out[k + 1] = 0.5 * (A + np.swapaxes(A, -1, -2))
        return out

    def batch(self, choice, A_prev, q, r) -> "StepBatch":
        return StepBatch(self, choice, A_prev, q, r)


def affine_path(W, v, x0) -> np.ndarray:
    """x_k = W_k x_{k−1} + v_k for W (K, J, n, n), v (K, J, n), x0 (J, n) -> (K + 1, J, n).

    The only sequential part of a chunk once the Riccati path is known (scalar loop for n = 1).
    """
    K, J, n = v.shape
    out = np.empty((K + 1, J, n))
    out[0] = x0
    if n == 1:
        for j in range(J):
            x, path = float(x0[j, 0]), []
            for w, c in zip(W[:, j, 0, 0].tolist(), v[:, j, 0].tolist(), strict=True):
                x = w * x + c
                path.append(x)
            out[1:, j, 0] = path
        return out
    x = np.asarray(x0, dtype=float)
    for k in range(K):
        x = out[k + 1] = (W[k] @ x[..., None])[..., 0] + v[k]
    return out


class StepBatch:
    """K steps of a :class:`FlowFamily` at once from known start exponents A_prev (K, J, n, n).

    Step k uses flow choice[k] with the potential's linear part q[k] (n,) and constant r[k] (or one
    per component: q (K, J, n), r (K, J)).
    B enters linearly:
    B_next = W_k B_prev + v_k with W = X(dt)⁻ᵀ (see :class:`GaussianFlow`), so a chunk is the
    data-free part here, one :func:`affine_path` and :meth:`finish`, all batched but the path.
    """

    def __init__(self, family: FlowFamily, choice, A_prev, q, r):
        eq, n = family.eq, family.eq.n
        self.eq, self.w = eq, family.w
        choice = np.asarray(choice, dtype=int)
        Phi = family.Phi[choice][:, :, None]  # (K, S+1, 1, 2n, 2n)
        Psi = family.Psi[choice][:, :, None]
        A = np.asarray(A_prev, dtype=float)[:, None]  # (K, 1, J, n, n)
        # 1×1 matrices: elementwise products (same result, no per-element matmul dispatch)
        self.mm = mm = np.multiply if n == 1 else np.matmul
        X = Phi[..., :n, :n] + mm(Phi[..., :n, n:], A)
        IX = Psi[..., :n, :n] + mm(Psi[..., :n, n:], A)
        IY = Psi[..., n:, :n] + mm(Psi[..., n:, n:], A)
        if n == 1:
            x_dt = X[:, -1, :, 0, 0]
            if not np.all(x_dt > 0):
                raise InputError("dt", _BLOW_UP)
            log_det = np.log(x_dt)
            self.XinvT = 1.0 / X
        else:
            sign, log_det = np.linalg.slogdet(X[:, -1])
            if np.any(sign <= 0) or not np.all(np.isfinite(log_det)):
                raise InputError("dt", _BLOW_UP)
            self.XinvT = np.swapaxes(np.linalg.inv(X), -1, -2)
        # B(s) = X(s)⁻ᵀ [B0 + ∫0^s (Xᵀq − 2Yᵀd)]: the forcing integral at the nodes and at dt
        q = np.asarray(q, dtype=float)  # (K, n), or (K, J, n): a linear term per component
        q = q[:, None, None, :, None] if q.ndim == 2 else q[:, None, :, :, None]
        d = eq.d[:, None]
        self.forcing = (mm(np.swapaxes(IX, -1, -2), q) - 2.0 * mm(np.swapaxes(IY, -1, -2), d))[..., 0]
        self.W = self.XinvT[:, -1]
        self.v = mm(self.W, self.forcing[:, -1, ..., None])[..., 0]
        # ∫tr(aA) = ½(log det X − dt tr D), so C gains ½ log det X + (r + ½ tr D) dt − ∫(½BᵀaB + dᵀB)
        r = np.asarray(r, dtype=float)  # (K,), or (K, J) per component
        r = r[:, None] if r.ndim == 1 else r
        self.gain0 = 0.5 * log_det + (r + 0.5 * np.trace(eq.D)) * family.dt

    def finish(self, B_prev) -> tuple[np.ndarray, np.ndarray]:
        """(B at dt (K, J, n), gain of C (K, J)) from the start values B_prev (K, J, n)."""
        eq = self.eq
        Bs = self.mm(self.XinvT, (np.asarray(B_prev, dtype=float)[:, None] + self.forcing)[..., None])[..., 0]
        nodes = Bs[:, :-1]
        quad = 0.5 * np.einsum("ksji,il,ksjl->ksj", nodes, eq.a, nodes) + nodes @ eq.d
        return Bs[:, -1], self.gain0 - np.einsum("s,ksj->kj", self.w, quad)


def gaussian_terms_batch(A, B, C) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`terms_to_gaussian` over stacks: A (..., n, n), B (..., n), C (...) -> mean, cov, log mass."""
    A, B, C = (np.asarray(v, dtype=float) for v in (A, B, C))
    n = A.shape[-1]
    if n == 1:
        two_a = 2.0 * A[..., 0, 0]
        if not np.all(two_a > 0):
            raise InputError("A", "not positive definite: the exponential is not integrable")
        cov = 1.0 / two_a
        mean = -cov * B[..., 0]
        log_mass = 0.5 * np.log(2 * np.pi * cov) + 0.5 * cov * B[..., 0] ** 2 - C
        return mean[..., None], cov[..., None, None], log_mass
    try:
        chol = np.linalg.cholesky(2.0 * A)
    except np.linalg.LinAlgError:
        raise InputError("A", "not positive definite: the exponential is not integrable") from None
    cov = np.linalg.inv(2.0 * A)
    cov = 0.5 * (cov + np.swapaxes(cov, -1, -2))
    mean = -(cov @ B[..., None])[..., 0]
    log_det = 2.0 * np.log(np.diagonal(chol, axis1=-2, axis2=-1)).sum(-1)
    log_mass = 0.5 * n * np.log(2 * np.pi) - 0.5 * log_det - 0.5 * (mean * B).sum(-1) - C
    return mean, cov, log_mass


def settle(path: np.ndarray) -> tuple[int, bool]:
    """Steps of ``path`` (L+1, n, n) to keep: up to the first step that no longer moves it."""
    moved = np.abs(np.diff(path, axis=0)).max(axis=(1, 2))
    still = moved <= 4.0 * np.finfo(float).eps * np.abs(path[1:]).max(axis=(1, 2))
    if still.any():
        return int(np.argmax(still)) + 1, True
    return len(path) - 1, False


def linear_recursion(W: np.ndarray, b: np.ndarray, x0: np.ndarray) -> np.ndarray:
    """x_k = W_k x_{k−1} + b_k for W (K, n, n), b (K, n) -> (K + 1, n), without a per-step loop.

    n = 1: x_k = Π_k (x_0 + Σ_{j≤k} b_j / Π_j) with Π_k = w_1⋯w_k (cumulative products, in
    blocks short enough that Π stays far from overflow); n > 1: a prefix scan of the affine maps
    (log₂ K rounds of batched products).
    """
    K, n = b.shape
    out = np.empty((K + 1, n))
    out[0] = x0
    if n == 1:
        w, c = W[:, 0, 0], b[:, 0]
        if np.all(w > 0.0):  # W = X⁻ᵀ > 0 (continuous) and (1 − G Hd)Φ > 0 (discrete) for n = 1
            span = max(1, int(500.0 / max(float(np.abs(np.log(w)).max()), 1e-300)))
            x = float(x0[0])
            for start in range(0, K, span):
                prod = np.cumprod(w[start:start + span])
                segment = prod * (x + np.cumsum(c[start:start + span] / prod))
                out[start + 1:start + 1 + len(segment), 0] = segment
                x = float(segment[-1])
            return out
        return affine_path(W[:, None], b[:, None], out[:1])[:, 0]
    Wc, bc, shift = W.copy(), b.copy(), 1
    while shift < K:  # after a round, (Wc_k, bc_k) maps x_{k−2·shift} (or x_0) to x_k
        bc[shift:] = (Wc[shift:] @ bc[:-shift, :, None])[..., 0] + bc[shift:]
        Wc[shift:] = Wc[shift:] @ Wc[:-shift]
        shift *= 2
    out[1:] = (Wc @ x0) + bc
    return out


def mixture_state_from_dict(cls, data, n: int, method: str):
    """``cls(A=..., B=..., C=..., **rest)`` from a state's ``to_dict`` (the exponents of a Gaussian
    mixture, as the Yau–Hu and Yau–Jia states store them); InputError('state') naming ``method``."""
    try:
        values = dict(data)
        A = np.asarray(values.pop("A"), float).reshape(-1, n, n)
        B = np.asarray(values.pop("B"), float).reshape(-1, n)
        C = np.asarray(values.pop("C"), float).reshape(-1)
        if not (len(A) == len(B) == len(C)) or not all(np.all(np.isfinite(v)) for v in (A, B, C)):
            raise ValueError("A, B, C must be finite with matching lengths")
        return cls(A=A, B=B, C=C, **values)
    except (KeyError, TypeError, ValueError) as exc:
        raise InputError("state", f"not a valid {method} state: {exc}") from None
