"""Independent references for filtering with observations at IRREGULAR times (truth for tests).

Nothing here imports the solver's filters: a compiled model is read only through ``model.n``,
``model.m``, ``model.f``, ``model.h``, ``model.a``, ``model.R``, ``model.center``, ``model.radius``
and ``model.log_prior`` (the simulator also reads ``model.spec.initial`` to draw the initial state).

The problem
-----------
Signal  dx = f(x) dt + G dv,  a = G Q Gᵀ.  Its density solves the Fokker–Planck equation

    ∂p/∂t = L*p = ½ Σ_ij a_ij ∂i∂j p − Σ_i ∂i(f_i p).

Observations are rows at times t_1 < t_2 < … (t_0 given; gaps τ_k = t_k − t_{k−1} > 0, arbitrary).
Each step predicts p over τ_k with the Fokker–Planck equation, multiplies by the likelihood of row k
at the state x(t_k) and normalises.  Likelihoods (o = the observed, i.e. non-NaN, components):

* ``kind="continuous"`` — row k is the increment dy_k of y over [t_{k−1}, t_k]:
      p(dy_k | x) = N(dy_{k,o}; h_o(x) τ_k, R_oo τ_k).
* ``kind="discrete"`` — row k is z_k = h(x(t_k)) + v_k:
      gaussian:   p(z_k | x) = N(z_{k,o}; h_o(x), R_oo)
      student-t:  p(z_k | x) = Γ((ν+m)/2) / (Γ(ν/2) (νπ)^{m/2} det(R_oo)^{1/2})
                               · (1 + dᵀ R_oo⁻¹ d / ν)^{−(ν+m)/2},   d = z_{k,o} − h_o(x), m = |o|
      (the marginal of a multivariate t over some components is t with the same ν and scale R_oo).
* A row that is all NaN only predicts (its predictive log-likelihood is NaN).

``predictive_loglik[k] = log p(row_k | rows_1..k−1) = log ∫ p(row_k | x) p_pred(x) dx`` with every
normalising constant included; ``loglik`` is its cumulative sum over the observed rows.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sps
from scipy.linalg import eigh_tridiagonal
from scipy.sparse.linalg import expm_multiply
from scipy.special import gammaln
from threadpoolctl import threadpool_limits

KINDS = ("continuous", "discrete")
METHODS = ("auto", "expm_multiply", "eigh")
LIKELIHOODS = ("gaussian", "student-t")


@dataclass(frozen=True)
class FilterResult:
    """Per-row filtering output: after the update with row k (or only the prediction, all-NaN row).

    mean (K, n), cov (K, n, n), predictive_loglik (K,) (NaN where the row is all missing),
    loglik (K,) = cumulative sum of predictive_loglik over the observed rows."""

    mean: np.ndarray
    cov: np.ndarray
    predictive_loglik: np.ndarray
    loglik: np.ndarray


def _check_rows(rows, times, kind, t0, m):
    rows = np.asarray(rows, dtype=float)
    if rows.ndim == 1:
        rows = rows[:, None]
    times = np.asarray(times, dtype=float).ravel()
    if rows.shape != (times.size, m):
        raise ValueError(f"rows must be ({times.size}, {m}), got {rows.shape}")
    if kind not in KINDS:
        raise ValueError(f"kind must be one of {KINDS}, got {kind!r}")
    gaps = np.diff(np.concatenate([[t0], times]))
    if np.any(~(gaps > 0)):
        raise ValueError("times must be strictly increasing and after t0")
    return rows, times, gaps


def _cumulative(pll: np.ndarray) -> np.ndarray:
    return np.cumsum(np.where(np.isnan(pll), 0.0, pll))


def log_gaussian(d: np.ndarray, S: np.ndarray) -> np.ndarray:
    """log N(d; 0, S) for residuals d (P, m)."""
    d = np.atleast_2d(d)
    c, low = sla.cho_factor(S, lower=True)
    sol = sla.cho_solve((c, low), d.T).T
    logdet = 2.0 * np.sum(np.log(np.diag(c)))
    return -0.5 * (np.einsum("pi,pi->p", d, sol) + logdet + d.shape[1] * math.log(2.0 * math.pi))


def log_student_t(d: np.ndarray, S: np.ndarray, dof: float) -> np.ndarray:
    """log of the multivariate Student-t density (scale S, dof ν) of residuals d (P, m)."""
    d = np.atleast_2d(d)
    m = d.shape[1]
    c, low = sla.cho_factor(S, lower=True)
    q = np.einsum("pi,pi->p", d, sla.cho_solve((c, low), d.T).T)
    logdet = 2.0 * np.sum(np.log(np.diag(c)))
    return (gammaln((dof + m) / 2.0) - gammaln(dof / 2.0) - 0.5 * m * math.log(dof * math.pi)
            - 0.5 * logdet - 0.5 * (dof + m) * np.log1p(q / dof))


# =====================================================================================
# 1. Fine-grid point-mass filter
# =====================================================================================
def _axis_ops(N: int, h: float):
    """1-D finite-volume pieces on N cells of width h (zero flux through the two end faces).

    avg (N−1, N): ½(p_L + p_R) at the N−1 interior faces;  diff (N−1, N): (p_R − p_L)/h;
    div (N, N−1) = diffᵀ: dp_i/dt = −(F_{i+½} − F_{i−½})/h with F = 0 on the box boundary;
    grad (N, N): cell-centred ∂p (central inside, one-sided at the two end cells)."""
    k = np.arange(N - 1)
    avg = sps.csr_matrix((np.full(2 * (N - 1), 0.5), (np.r_[k, k], np.r_[k, k + 1])), shape=(N - 1, N))
    diff = sps.csr_matrix((np.r_[np.full(N - 1, -1.0 / h), np.full(N - 1, 1.0 / h)],
                           (np.r_[k, k], np.r_[k, k + 1])), shape=(N - 1, N))
    div = diff.T.tocsr()
    i = np.arange(1, N - 1)
    r = np.r_[i, i, 0, 0, N - 1, N - 1]
    c = np.r_[i - 1, i + 1, 0, 1, N - 2, N - 1]
    v = np.r_[np.full(N - 2, -0.5 / h), np.full(N - 2, 0.5 / h), -1.0 / h, 1.0 / h, -1.0 / h, 1.0 / h]
    grad = sps.csr_matrix((v, (r, c)), shape=(N, N))
    return avg, diff, div, grad


class GridReference:
    """Point-mass filter on a fine uniform cell-centred grid, exact in time.

    Grid: ``cells`` cells per axis on the box [c − R·box, c + R·box]^n (c = model.center,
    R = model.radius; default 1024 cells in 1-D, 96 per axis in 2-D).  The state is the vector of
    cell masses w_i (Σ w_i = 1; the density is w_i / cell volume at the cell centre x_i).

    Prediction: the Fokker–Planck operator is discretised by finite volumes, zero flux through the
    box boundary (mass is conserved exactly: the columns of L sum to 0).  Flux through the face
    between cells L and R along axis i (face centre x_f, spacing h_i):

        F_i = f_i(x_f) (p_L + p_R)/2 − ½ a_ii (p_R − p_L)/h_i − ½ a_ij (∂_j p)_f     (j ≠ i),

    with (∂_j p)_f the face average of cell-centred central differences (only when a_01 ≠ 0), and
    dp/dt = −Σ_i (F_i(right face) − F_i(left face))/h_i, i.e. dw/dt = L w (L scipy.sparse).  Over a
    gap τ the prediction is w ← exp(τL) w computed by ``scipy.sparse.linalg.expm_multiply`` (one call
    per gap, no time stepping), tiny negatives clipped to 0 and the total mass reset to 1.

    ``method``: "expm_multiply" is the above.  "eigh" (1-D only) is the same exact exp(τL), faster:
    the tridiagonal L has L_{i,i+1} L_{i+1,i} > 0 (cell Péclet |f| h / a < 1), so S = D L D⁻¹ with
    d_{i+1}/d_i = (L_{i,i+1}/L_{i+1,i})^{1/2} is symmetric tridiagonal, S = U Λ Uᵀ
    (``eigh_tridiagonal``) and exp(τL) w = D⁻¹ U e^{τΛ} Uᵀ D w: two dense products per gap instead of
    the ~5 τ‖L‖₁ sparse products of the Taylor method (1-D OU, 1024 cells: ~0.3 ms instead of
    ~10–40 ms per gap).  Its rounding error is amplified by max d / min d: against expm_multiply (and
    dense ``scipy.linalg.expm``) it agrees to ~1e-14 in total variation for the prior of the OU
    example, ~1e-8 for a unit mass in an END cell of the box (the worst case).  "auto" (default)
    takes "eigh" in 1-D when it applies (positive off-diagonal products, max ln d − min ln d ≤ 25)
    AND :meth:`eigh_error` ≤ 1e-7; otherwise "expm_multiply".  ``self.method`` says which was taken.

    Update: log-likelihood ℓ_i of the row at the cell centres (see the module docstring); with
    M = max ℓ, predictive log-likelihood = M + log Σ w_i e^{ℓ_i − M}, posterior w_i ∝ w_i e^{ℓ_i − M}.
    The initial masses are exp(model.log_prior(x_i)) normalised.
    """

    def __init__(self, model, cells: int | None = None, box: float = 1.0, method: str = "auto"):
        n = int(model.n)
        if n not in (1, 2):
            raise ValueError(f"GridReference handles n = 1 or 2, got {n}")
        self.model = model
        self.n = n
        self.m = int(model.m)
        self.cells = int(cells if cells is not None else (1024 if n == 1 else 96))
        c = np.asarray(model.center, dtype=float).reshape(n)
        half = float(model.radius) * float(box)
        self.lo = c - half
        self.hi = c + half
        self.h = (self.hi - self.lo) / self.cells
        self.axes = [self.lo[i] + (np.arange(self.cells) + 0.5) * self.h[i] for i in range(n)]
        mesh = np.meshgrid(*self.axes, indexing="ij")
        self.points = np.stack([g.ravel() for g in mesh], axis=1)  # (N^n, n), C order
        self.a = np.asarray(model.a, dtype=float).reshape(n, n)
        self.R = np.asarray(model.R, dtype=float).reshape(self.m, self.m)
        self.L = self._generator().tocsr()
        self.trace = float(self.L.diagonal().sum())
        self.hx = np.asarray(model.h(self.points), dtype=float).reshape(-1, self.m)
        lp = np.asarray(model.log_prior(self.points), dtype=float).ravel()
        w = np.exp(lp - lp.max())
        self.w0 = w / w.sum()
        if method not in METHODS:
            raise ValueError(f"method must be one of {METHODS}, got {method!r}")
        self.method = "expm_multiply"
        if method != "expm_multiply":
            ok = n == 1 and self._setup_eigh()
            if method == "eigh" and not ok:
                raise ValueError("method 'eigh' needs n = 1 and a symmetrisable, well-scaled generator")
            if ok and method == "auto":
                ok = self.eigh_error() <= 1e-7
            if ok:
                self.method = "eigh"

    def eigh_error(self, tau: float = 0.02) -> float:
        """Largest total-variation (L1) gap between the "eigh" and expm_multiply propagations over τ
        of four probes: the prior and unit masses in the first, middle and last cells (the end
        cells are the worst case: the error there grows like 1e-16·max d / min d)."""
        N = self.cells
        B = np.zeros((N, 4))
        B[:, 0] = self.w0
        B[[0, N // 2, N - 1], [1, 2, 3]] = 1.0
        ref = expm_multiply(tau * self.L, B, traceA=tau * self.trace)
        with threadpool_limits(1):
            fast = np.stack([self._eigh(B[:, j], tau) for j in range(4)], axis=1)
        return float(np.abs(fast - ref).sum(axis=0).max())

    def _setup_eigh(self) -> bool:
        """Symmetrise the 1-D tridiagonal L (see the class docstring); False where it does not apply."""
        lo = self.L.diagonal(-1)
        up = self.L.diagonal(1)
        if not (np.all(lo > 0) and np.all(up > 0)):
            return False
        lnd = np.concatenate([[0.0], np.cumsum(0.5 * np.log(up / lo))])
        if lnd.max() - lnd.min() > 25.0:
            return False
        lnd -= 0.5 * (lnd.max() + lnd.min())
        self._d = np.exp(lnd)
        self._lam, self._U = eigh_tridiagonal(self.L.diagonal(), np.sqrt(lo * up))
        self._Ut = np.ascontiguousarray(self._U.T)
        return True

    # -- the generator ----------------------------------------------------------------
    def _generator(self) -> sps.spmatrix:
        n, N, a, f = self.n, self.cells, self.a, self.model.f
        ops = [_axis_ops(N, self.h[i]) for i in range(n)]
        eye = sps.identity(N, format="csr")

        def along(i, op):  # the 1-D operator ``op`` acting on axis i of the C-ordered grid
            if n == 1:
                return op
            return sps.kron(op, eye, format="csr") if i == 0 else sps.kron(eye, op, format="csr")

        L = sps.csr_matrix((N ** n, N ** n))
        for i in range(n):
            avg, diff, div, _ = ops[i]
            faces_1d = self.lo[i] + np.arange(1, N) * self.h[i]
            coords = [faces_1d if j == i else self.axes[j] for j in range(n)]
            mesh = np.meshgrid(*coords, indexing="ij")
            fpts = np.stack([g.ravel() for g in mesh], axis=1)
            f_face = np.asarray(f(fpts), dtype=float).reshape(-1, n)[:, i]
            A = along(i, avg)
            flux = sps.diags(f_face) @ A - 0.5 * a[i, i] * along(i, diff)
            if n == 2 and a[0, 1] != 0.0:
                j = 1 - i
                flux = flux - 0.5 * a[i, j] * (A @ along(j, ops[j][3]))
            L = L + along(i, div) @ flux
        return L

    # -- one step ---------------------------------------------------------------------
    def _expm_multiply(self, w: np.ndarray, tau: float) -> np.ndarray:
        return expm_multiply(tau * self.L, w, traceA=tau * self.trace)

    def _eigh(self, w: np.ndarray, tau: float) -> np.ndarray:
        return (self._U @ (np.exp(tau * self._lam) * (self._Ut @ (self._d * w)))) / self._d

    def predict_masses(self, w: np.ndarray, tau: float) -> np.ndarray:
        """w ← exp(τ L) w (exact in time, ``self.method``), negatives clipped, mass renormalised to 1."""
        w = self._eigh(w, tau) if self.method == "eigh" else self._expm_multiply(w, tau)
        w = np.clip(w, 0.0, None)
        return w / w.sum()

    def loglik_cells(self, row: np.ndarray, tau: float, kind: str, R: np.ndarray,
                     likelihood: str, dof: float | None) -> np.ndarray:
        """ℓ_i = log p(row | x_i) at every cell centre (observed components only)."""
        o = ~np.isnan(row)
        R_oo = R[np.ix_(o, o)]
        hx = self.hx[:, o]
        if kind == "continuous":
            return log_gaussian(row[o][None, :] - hx * tau, R_oo * tau)
        d = row[o][None, :] - hx
        if likelihood == "gaussian":
            return log_gaussian(d, R_oo)
        return log_student_t(d, R_oo, dof)

    def moments(self, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        mean = w @ self.points
        d = self.points - mean
        return mean, (d * w[:, None]).T @ d

    def run(self, rows, times, kind: str, R=None, likelihood: str = "gaussian", dof: float | None = None,
            t0: float = 0.0, max_piece: float | None = None) -> FilterResult:
        """Filter rows (K, m) observed at times (K,) (strictly increasing, > t0).  ``R`` overrides
        model.R; ``likelihood`` ("gaussian" or "student-t" with ``dof``) applies to kind "discrete".

        ``max_piece`` (continuous kind): an increment over a gap τ is taken with y linear over the
        gap, in n = max(1, ⌈τ/max_piece − ¼⌉) equal pieces: predict over τ/n, multiply by the
        Girsanov ratio N(dy/n; h τ/n, R τ/n) / N(dy/n; 0, R τ/n), n times; the row's predictive
        log-likelihood is the sum of the pieces' log normalisers plus log N(dy; 0, R τ)."""
        rows, times, gaps = _check_rows(rows, times, kind, t0, self.m)
        if likelihood not in LIKELIHOODS:
            raise ValueError(f"likelihood must be one of {LIKELIHOODS}")
        if likelihood == "student-t" and kind == "discrete" and not (dof is not None and dof > 0):
            raise ValueError("student-t needs dof > 0")
        R = self.R if R is None else np.asarray(R, dtype=float).reshape(self.m, self.m)
        K = times.size
        means = np.empty((K, self.n))
        covs = np.empty((K, self.n, self.n))
        pll = np.full(K, np.nan)
        w = self.w0.copy()
        with threadpool_limits(1):  # dense 1024² products ("eigh"): one BLAS thread is far faster under load
            self._loop(rows, gaps, kind, R, likelihood, dof, w, means, covs, pll, max_piece)
        return FilterResult(means, covs, pll, _cumulative(pll))

    def _loop(self, rows, gaps, kind, R, likelihood, dof, w, means, covs, pll, max_piece=None) -> None:
        for k in range(gaps.size):
            row = rows[k]
            observed = ~np.isnan(row)
            n = 1
            if kind == "continuous" and max_piece is not None and observed.any():
                n = max(1, math.ceil(gaps[k] / max_piece - 0.25))
            if n > 1:
                tau = gaps[k] / n
                R_oo = R[np.ix_(observed, observed)]
                total = log_gaussian(row[observed][None, :], R_oo * gaps[k])[0]
                for _ in range(n):
                    w = self.predict_masses(w, tau)
                    ell = self.loglik_cells(row / n, tau, kind, R, likelihood, dof)
                    ell = ell - log_gaussian(row[observed][None, :] / n, R_oo * tau)[0]  # the Girsanov ratio
                    top = ell.max()
                    u = w * np.exp(ell - top)
                    s = u.sum()
                    total += top + math.log(s)
                    w = u / s
                pll[k] = total
                means[k], covs[k] = self.moments(w)
                continue
            w = self.predict_masses(w, gaps[k])
            if not np.all(np.isnan(row)):
                ell = self.loglik_cells(row, gaps[k], kind, R, likelihood, dof)
                top = ell.max()
                u = w * np.exp(ell - top)
                s = u.sum()
                pll[k] = top + math.log(s)
                w = u / s
            means[k], covs[k] = self.moments(w)


# =====================================================================================
# 2. Exact Kalman filter at irregular times
# =====================================================================================
def linear_prediction(F, f0, a, tau: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(Φ, shift, Q_τ) of dx = (F x + f0) dt + G dv over τ (Van Loan):

        Φ = e^{Fτ},   shift = ∫_0^τ e^{Fs} ds f0,   Q_τ = ∫_0^τ e^{Fs} a e^{Fᵀs} ds,

    from expm([[−F, a], [0, Fᵀ]] τ) = [[·, E12], [0, E22]]: Φ = E22ᵀ, Q_τ = Φ E12 (symmetrised),
    and expm([[F, f0], [0, 0]] τ) = [[Φ, shift], [0, 1]]."""
    F = np.atleast_2d(np.asarray(F, float))
    n = F.shape[0]
    a = np.asarray(a, float).reshape(n, n)
    f0 = np.asarray(f0, float).reshape(n)
    M = np.zeros((2 * n, 2 * n))
    M[:n, :n] = -F
    M[:n, n:] = a
    M[n:, n:] = F.T
    E = sla.expm(M * tau)
    Phi = E[n:, n:].T
    Q = Phi @ E[:n, n:]
    Q = 0.5 * (Q + Q.T)
    B = np.zeros((n + 1, n + 1))
    B[:n, :n] = F
    B[:n, n] = f0
    Eb = sla.expm(B * tau)
    return Phi, Eb[:n, n], Q


def kalman_irregular(F, f0, a, H, h0, R, m0, P0, rows, times, kind: str, t0: float = 0.0,
                     max_piece: float | None = None) -> FilterResult:
    """Exact Kalman filter of f = F x + f0, h = H x + h0 with rows at irregular times.

    Predict over τ_k:  m ← Φ m + shift,  P ← Φ P Φᵀ + Q_τ  (:func:`linear_prediction`).
    Update with the observed components o of row k:
        discrete:    z_o  = H_o x + h0_o + N(0, R_oo)            → C = H_o,   c = h0_o,   V = R_oo
        continuous:  dy_o = H_o x τ + h0_o τ + N(0, R_oo τ)      → C = H_o τ, c = h0_o τ, V = R_oo τ
    (x = the state at t_k after the prediction);  S = C P Cᵀ + V,  K = P Cᵀ S⁻¹,
    m ← m + K (row_o − C m − c),  P ← (I − K C) P (I − K C)ᵀ + K V Kᵀ,
    predictive_loglik = log N(row_o; C m + c, S) (NaN for an all-missing row).

    ``max_piece`` (continuous kind): y linear over the gap, in n = max(1, ⌈τ/max_piece − ¼⌉) equal
    pieces (predict over τ/n, update with dy/n); the row's predictive log-likelihood is then
    Σ_j [log N(dy/n; ŷ_j, S_j) − log N(dy/n; 0, R τ/n)] + log N(dy; 0, R τ) (the Girsanov form)."""
    F = np.atleast_2d(np.asarray(F, float))
    n = F.shape[0]
    H = np.asarray(H, float).reshape(-1, n)
    m_obs = H.shape[0]
    h0 = np.asarray(h0, float).reshape(m_obs)
    R = np.asarray(R, float).reshape(m_obs, m_obs)
    rows, times, gaps = _check_rows(rows, times, kind, t0, m_obs)
    mean = np.asarray(m0, float).reshape(n).copy()
    P = np.asarray(P0, float).reshape(n, n).copy()
    K_ = times.size
    means = np.empty((K_, n))
    covs = np.empty((K_, n, n))
    pll = np.full(K_, np.nan)
    for k in range(K_):
        row = rows[k]
        o = ~np.isnan(row)
        pieces = 1
        if kind == "continuous" and max_piece is not None and o.any():
            pieces = max(1, math.ceil(gaps[k] / max_piece - 0.25))
        if pieces > 1:
            tau = gaps[k] / pieces
            Phi, shift, Q = linear_prediction(F, f0, a, tau)
            V = R[np.ix_(o, o)] * tau
            total = log_gaussian(row[o][None, :], R[np.ix_(o, o)] * gaps[k])[0]
            for _ in range(pieces):
                mean, P = Phi @ mean + shift, Phi @ P @ Phi.T + Q
                C, c, piece = H[o] * tau, h0[o] * tau, row[o] / pieces
                S = C @ P @ C.T + V
                resid = piece - C @ mean - c
                total += log_gaussian(resid[None, :], S)[0] - log_gaussian(piece[None, :], V)[0]
                Kg = sla.solve(S, C @ P, assume_a="pos").T
                mean = mean + Kg @ resid
                IKC = np.eye(n) - Kg @ C
                P = IKC @ P @ IKC.T + Kg @ V @ Kg.T
                P = 0.5 * (P + P.T)
            pll[k] = total
            means[k], covs[k] = mean, P
            continue
        tau = gaps[k]
        Phi, shift, Q = linear_prediction(F, f0, a, tau)
        mean = Phi @ mean + shift
        P = Phi @ P @ Phi.T + Q
        if o.any():
            scale = tau if kind == "continuous" else 1.0
            C = H[o] * scale
            c = h0[o] * scale
            V = R[np.ix_(o, o)] * scale
            S = C @ P @ C.T + V
            S = 0.5 * (S + S.T)
            resid = row[o] - C @ mean - c
            pll[k] = log_gaussian(resid[None, :], S)[0]
            Kg = sla.solve(S, C @ P, assume_a="pos").T
            mean = mean + Kg @ resid
            IKC = np.eye(n) - Kg @ C
            P = IKC @ P @ IKC.T + Kg @ V @ Kg.T
            P = 0.5 * (P + P.T)
        means[k] = mean
        covs[k] = P
    return FilterResult(means, covs, pll, _cumulative(pll))


# =====================================================================================
# 3. Random irregular times
# =====================================================================================
def random_times(rng: np.random.Generator, K: int, mean_gap: float, long_fraction: float = 0.05,
                 long_factor: float = 10.0, t0: float = 0.0) -> np.ndarray:
    """K strictly increasing times t0 + cumsum(gaps).

    Gaps are exponential; round(long_fraction·K) of them (chosen at random) are multiplied by
    ``long_factor``.  The exponential's mean is mean_gap / (1 − φ + φ·long_factor) (φ the actual
    fraction of long gaps) so that the mean gap is ``mean_gap``; every gap is at least 1e-6·mean_gap.
    Gaps are continuous random numbers, hence distinct (almost surely)."""
    K = int(K)
    n_long = int(round(long_fraction * K))
    phi = n_long / K if K else 0.0
    base = mean_gap / (1.0 - phi + phi * long_factor)
    gaps = rng.exponential(base, K)
    if n_long:
        gaps[rng.choice(K, n_long, replace=False)] *= long_factor
    gaps = np.maximum(gaps, 1e-6 * mean_gap)
    return t0 + np.cumsum(gaps)


# =====================================================================================
# 4. Simulator
# =====================================================================================
def _sym_sqrt(A: np.ndarray) -> np.ndarray:
    """Symmetric square root of a positive semi-definite matrix (negative eigenvalues clipped)."""
    vals, vecs = np.linalg.eigh(0.5 * (A + A.T))
    return (vecs * np.sqrt(np.clip(vals, 0.0, None))) @ vecs.T


def sample_prior(model, rng: np.random.Generator) -> np.ndarray:
    """One draw of the initial state: gaussian / mixture priors exactly from spec.initial, a density
    prior by inverse-CDF on a fine grid of the domain box (uniform jitter inside the cell)."""
    init = model.spec.initial
    n = int(model.n)
    kind = getattr(init, "kind", None)
    if kind == "gaussian":
        return rng.multivariate_normal(np.asarray(init.mean, float), np.asarray(init.cov, float))
    if kind == "mixture":
        w = np.asarray(init.weights, float)
        w = w / w.max()
        j = rng.choice(w.size, p=w / w.sum())
        return rng.multivariate_normal(np.asarray(init.means[j], float), np.asarray(init.covs[j], float))
    N = 4096 if n == 1 else 400
    c = np.asarray(model.center, float)
    h = 2.0 * model.radius / N
    axes = [c[i] - model.radius + (np.arange(N) + 0.5) * h for i in range(n)]
    pts = np.stack([g.ravel() for g in np.meshgrid(*axes, indexing="ij")], axis=1)
    lp = np.asarray(model.log_prior(pts), float).ravel()
    p = np.exp(lp - lp.max())
    i = rng.choice(p.size, p=p / p.sum())
    return pts[i] + (rng.random(n) - 0.5) * h


def simulate_irregular(model, times, kind: str, rng: np.random.Generator, substeps_per_unit: float = 2000,
                       likelihood: str = "gaussian", dof: float | None = None, t0: float = 0.0):
    """Simulate (states (K, n) at the times, rows (K, m)).

    Euler–Maruyama  x ← x + f(x) δ + a^{1/2} √δ ε  (a^{1/2} the symmetric square root), each gap τ
    split into ceil(τ·substeps_per_unit) equal substeps δ; the initial state is drawn from the prior.
    continuous:  row_k = Σ_substeps h(x_s) δ (left-point rule for ∫ h(x) ds over the gap) + N(0, R τ)
    discrete:    row_k = h(x(t_k)) + v,  v ~ N(0, R)  or  v = chol(R) ε · sqrt(ν / χ²_ν)  (Student-t)."""
    if kind not in KINDS:
        raise ValueError(f"kind must be one of {KINDS}")
    times = np.asarray(times, float).ravel()
    gaps = np.diff(np.concatenate([[t0], times]))
    if np.any(~(gaps > 0)):
        raise ValueError("times must be strictly increasing and after t0")
    n, m = int(model.n), int(model.m)
    sq = _sym_sqrt(np.asarray(model.a, float).reshape(n, n))
    R = np.asarray(model.R, float).reshape(m, m)
    cholR = np.linalg.cholesky(R)
    x = np.asarray(sample_prior(model, rng), float).reshape(1, n)
    K = times.size
    states = np.empty((K, n))
    rows = np.empty((K, m))
    for k, tau in enumerate(gaps):
        steps = max(1, int(math.ceil(tau * substeps_per_unit)))
        delta = tau / steps
        noise = rng.standard_normal((steps, n)) @ sq.T * math.sqrt(delta)
        integral = np.zeros(m)
        for s in range(steps):
            if kind == "continuous":
                integral += np.asarray(model.h(x), float).reshape(m) * delta
            x = x + np.asarray(model.f(x), float).reshape(1, n) * delta + noise[s]
        states[k] = x[0]
        if kind == "continuous":
            rows[k] = integral + cholR @ rng.standard_normal(m) * math.sqrt(tau)
        else:
            v = cholR @ rng.standard_normal(m)
            if likelihood == "student-t":
                v = v * math.sqrt(dof / rng.chisquare(dof))
            rows[k] = np.asarray(model.h(x), float).reshape(m) + v
    return states, rows
