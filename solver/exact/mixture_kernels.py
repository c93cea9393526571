"""The Yau–Jia filter's mixture arithmetic compiled by numba: whole component stacks per call.

The fast path of solver/exact/yau_jia.py (``YAUYAU_KERNEL``, solver/jit.py; driven by
solver/exact/yau_jia_fast.py).  Each kernel does for all J components of a mixture what the numpy
path does with a few dozen calls of numpy's wrappers around small (J, n, n) stacks: exponents to
moments (:func:`prepare`), the first half of the data factor and the exact Gaussian flow
(:func:`observe_flow`, :func:`predict_flow`), the second half (:func:`observe_finish`), the
normalisation, pruning and principal axes of the error control (:func:`normalise_axes`), and the
rates, merges, splits, exponents and moments (solver/exact/mixture_control.py).  The sensor h (a
sympy expression) is evaluated between the kernels by the numpy path's own generated function, so
both paths see the same values of h; the kernels return a code instead of raising, and the driver
takes the numpy path for that piece (a non-integrable component, a blow-up), which raises as before.

Linear algebra on n×n blocks is written out (Cholesky, Gauss–Jordan with partial pivoting, cyclic
Jacobi for the principal axes: LAPACK's dsyevd costs ~7 µs per 4×4 matrix through any wrapper, more
than the rest of a component's step).  Results agree with the numpy path to ~1e-13 relative per step
(tests/solver/exact/test_yau_jia_fast.py).  Importing this module imports numba.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from ..jit import writable_cache_dir

CACHE_DIR = writable_cache_dir()
_previous_cache_dir = numba.config.CACHE_DIR
if CACHE_DIR is not None:
    numba.config.CACHE_DIR = str(CACHE_DIR)
kernel = numba.njit(cache=CACHE_DIR is not None, nogil=True, error_model="numpy")  # also mixture_control.py's

LOG_2PI = math.log(2.0 * math.pi)
OK, FALLBACK = 0, 1


def lapack_workspace(n: int):
    """Scratch for :func:`eigh` on n×n matrices."""
    return np.empty((n, n))


@kernel
def eigh(M, lam, U, a):
    """Eigenvalues (ascending) and eigenvectors (columns of U) of the symmetric M by cyclic Jacobi
    rotations (``a``: n×n scratch); returns 0 (converged) or 1.  Eigenvalues to rounding, eigenvectors
    up to sign (the cubature and the rates are symmetric in ±u; a split's three children come out
    in the opposite order)."""
    n = M.shape[0]
    for i in range(n):
        for j in range(n):
            a[i, j] = M[i, j]
            U[i, j] = 1.0 if i == j else 0.0
    done = False
    for _ in range(60):
        rotated = False
        for p in range(n - 1):
            for q in range(p + 1, n):
                apq = a[p, q]
                if apq == 0.0:
                    continue
                app, aqq = a[p, p], a[q, q]
                small = 100.0 * abs(apq)  # negligible beside both diagonal entries (Numerical Recipes)
                if abs(app) + small == abs(app) and abs(aqq) + small == abs(aqq):
                    a[p, q] = 0.0
                    a[q, p] = 0.0
                    continue
                rotated = True
                theta = (aqq - app) / (2.0 * apq)
                if abs(theta) > 1e150:
                    t = 0.5 / theta
                else:
                    t = 1.0 / (abs(theta) + math.sqrt(theta * theta + 1.0))
                    if theta < 0.0:
                        t = -t
                c = 1.0 / math.sqrt(t * t + 1.0)
                s = t * c
                a[p, p] = app - t * apq
                a[q, q] = aqq + t * apq
                a[p, q] = 0.0
                a[q, p] = 0.0
                for r in range(n):
                    if r != p and r != q:
                        arp, arq = a[r, p], a[r, q]
                        a[r, p] = c * arp - s * arq
                        a[p, r] = a[r, p]
                        a[r, q] = s * arp + c * arq
                        a[q, r] = a[r, q]
                for r in range(n):
                    urp, urq = U[r, p], U[r, q]
                    U[r, p] = c * urp - s * urq
                    U[r, q] = s * urp + c * urq
        if not rotated:
            done = True
            break
    for i in range(n):
        lam[i] = a[i, i]
    for i in range(1, n):  # ascending, as LAPACK
        j = i
        while j > 0 and lam[j - 1] > lam[j]:
            t = lam[j]
            lam[j] = lam[j - 1]
            lam[j - 1] = t
            for r in range(n):
                t = U[r, j]
                U[r, j] = U[r, j - 1]
                U[r, j - 1] = t
            j -= 1
    for i in range(n):
        if not math.isfinite(lam[i]):
            done = False
    return 0 if done else 1


@kernel
def cholesky(M, L):
    """Lower Cholesky factor of M into L; False where M is not positive definite (as LAPACK potrf)."""
    n = M.shape[0]
    for j in range(n):
        s = M[j, j]
        for k in range(j):
            s -= L[j, k] * L[j, k]
        if not s > 0.0:
            return False
        d = math.sqrt(s)
        L[j, j] = d
        for i in range(j + 1, n):
            t = M[i, j]
            for k in range(j):
                t -= L[i, k] * L[j, k]
            L[i, j] = t / d
        for i in range(j):
            L[i, j] = 0.0
    return True


@kernel
def spd_inverse(L, out, tmp):
    """out = (L Lᵀ)⁻¹ from the Cholesky factor L (``tmp``: n×n scratch for L⁻¹); returns log det."""
    n = L.shape[0]
    log_det = 0.0
    for i in range(n):
        log_det += math.log(L[i, i])
        for j in range(n):
            tmp[i, j] = 0.0
    for j in range(n):  # L⁻¹ column by column (forward substitution)
        tmp[j, j] = 1.0 / L[j, j]
        for i in range(j + 1, n):
            s = 0.0
            for k in range(j, i):
                s -= L[i, k] * tmp[k, j]
            tmp[i, j] = s / L[i, i]
    for i in range(n):
        for j in range(i + 1):
            s = 0.0
            for k in range(i, n):
                s += tmp[k, i] * tmp[k, j]
            out[i, j] = s
            out[j, i] = s
    return 2.0 * log_det


@kernel
def lu_inverse(M, out, work):
    """out = M⁻¹ by Gauss–Jordan with partial pivoting (``work``: n×2n scratch); returns (sign of
    det M, log |det M|), sign 0 where M is singular."""
    n = M.shape[0]
    for i in range(n):
        for j in range(n):
            work[i, j] = M[i, j]
            work[i, n + j] = 1.0 if i == j else 0.0
    sign, log_det = 1.0, 0.0
    for c in range(n):
        p, best = c, abs(work[c, c])
        for r in range(c + 1, n):
            if abs(work[r, c]) > best:
                p, best = r, abs(work[r, c])
        if not best > 0.0:
            return 0.0, -np.inf
        if p != c:
            sign = -sign
            for j in range(2 * n):
                t = work[c, j]
                work[c, j] = work[p, j]
                work[p, j] = t
        pivot = work[c, c]
        if pivot < 0.0:
            sign = -sign
        log_det += math.log(abs(pivot))
        for j in range(2 * n):
            work[c, j] /= pivot
        for r in range(n):
            if r != c:
                f = work[r, c]
                if f != 0.0:
                    for j in range(2 * n):
                        work[r, j] -= f * work[c, j]
    for i in range(n):
        for j in range(n):
            out[i, j] = work[i, n + j]
    return sign, log_det


@kernel
def terms_to_moments(A, B, C, means, covs, log_mass):
    """Means, covariances and log masses of exp(−xᵀA_jx − B_jᵀx − C_j) (gaussian_terms_batch);
    False where a component is not integrable."""
    J, n = B.shape
    M, L, tmp = np.empty((n, n)), np.empty((n, n)), np.empty((n, n))
    for j in range(J):
        for a in range(n):
            for b in range(n):
                M[a, b] = 2.0 * A[j, a, b]
        if not cholesky(M, L):
            return False
        log_det = spd_inverse(L, covs[j], tmp)
        quad = 0.0
        for a in range(n):
            s = 0.0
            for b in range(n):
                s += covs[j, a, b] * B[j, b]
            means[j, a] = -s
            quad += -s * B[j, a]
        log_mass[j] = 0.5 * n * LOG_2PI - 0.5 * log_det - 0.5 * quad - C[j]
    return True


@kernel
def cubature(means, covs, points, ws):
    """The 2n points m ± √n·√λ_k u_k of each component (mixtures.cubature_points); False if eigh fails."""
    J, n = means.shape
    lam, U = np.empty(n), np.empty((n, n))
    root_n = math.sqrt(n)
    for j in range(J):
        if eigh(covs[j], lam, U, ws) != 0:
            return False
        for k in range(n):
            s = root_n * math.sqrt(max(lam[k], 0.0))
            for a in range(n):
                points[j, k, a] = means[j, a] + s * U[a, k]
                points[j, n + k, a] = means[j, a] - s * U[a, k]
    return True


@kernel
def prepare(A, B, C, means, covs, log_mass, points, ws):
    """Moments of the components and their cubature points: OK or FALLBACK."""
    if not terms_to_moments(A, B, C, means, covs, log_mass):
        return FALLBACK
    if points.shape[0] and not cubature(means, covs, points, ws):
        return FALLBACK
    return OK


@kernel
def half_curvature(H, c, m, n, S):
    """S = ½ Σ_i c_i H_i, symmetrised (the data factor's quadratic term: ½ ∂²(cᵀh))."""
    for x in range(n):
        for y in range(n):
            t = 0.0
            for i in range(m):
                t += H[i, x, y] * c[i]
            S[x, y] = 0.5 * t
    for x in range(n):
        for y in range(x + 1):
            t = 0.5 * (S[x, y] + S[y, x])
            S[x, y] = t
            S[y, x] = t


@kernel
def expected(F, j, m, n, h, Jh, H):
    """E[h], E[∂h], E[∂²h] over component j from the sensor's values F (J·2n points, flat columns)."""
    P = 2 * n
    for i in range(m):
        s = 0.0
        for p in range(P):
            s += F[j * P + p, i]
        h[i] = s / P
        for a in range(n):
            s = 0.0
            for p in range(P):
                s += F[j * P + p, m + i * n + a]
            Jh[i, a] = s / P
            for b in range(n):
                s = 0.0
                for p in range(P):
                    s += F[j * P + p, m + m * n + (i * n + a) * n + b]
                H[i, a, b] = s / P


@kernel
def damping(cov, S, L):
    """θ = 0.9/λ_max(PS) where λ_max(PS) > 0.9, else 1 (mixtures.times_exp_quadratic's damping;
    λ(PS) = λ(LᵀSL) with P = LLᵀ); NaN where P is not positive definite."""
    n = S.shape[0]
    if not cholesky(cov, L):
        return np.nan
    M = np.zeros((n, n))
    for a in range(n):
        for b in range(n):
            t = 0.0
            for x in range(a, n):
                for y in range(b, n):
                    t += L[x, a] * S[x, y] * L[y, b]
            M[a, b] = t
    lam, U = np.empty(n), np.empty((n, n))
    if eigh(M, lam, U, np.empty((n, n))) != 0:
        return np.nan
    top = lam[n - 1]
    return 0.9 / top if top > 0.9 else 1.0


@kernel
def times_exp(A, B, C, j, at, cov, s0, g, S, A2, B2, C2, M, L):
    """Component j times exp(s0 + gᵀ(x − at) + ½(x − at)ᵀS(x − at)) (mixtures.times_exp_quadratic
    with S symmetric; S is damped to θS where P⁻¹ − S/0.9 is not positive definite).  Returns 0, 1
    (damped) or −1 (no damping found)."""
    n = at.shape[0]
    for a in range(n):
        for b in range(n):
            M[a, b] = 2.0 * A[j, a, b] - S[a, b] / 0.9
    theta = 1.0
    if not cholesky(M, L):
        theta = damping(cov, S, L)
        if not math.isfinite(theta):
            return -1
    c = 0.0
    for a in range(n):
        Sm = 0.0
        for b in range(n):
            Sm += theta * S[a, b] * at[b]
            A2[j, a, b] = A[j, a, b] - 0.5 * (theta * S[a, b])
        B2[j, a] = B[j, a] - (g[a] - Sm)
        c += g[a] * at[a] - 0.5 * at[a] * Sm
    C2[j] = C[j] - (s0 - c)
    return 1 if theta < 1.0 else 0


@kernel
def solve_transposed(X, b, out, work):
    """out = X⁻ᵀ b by Gaussian elimination with partial pivoting (``work``: n×2n scratch)."""
    n = X.shape[0]
    for i in range(n):
        for j in range(n):
            work[i, j] = X[j, i]
        work[i, n] = b[i]
    for c in range(n):
        p, best = c, abs(work[c, c])
        for r in range(c + 1, n):
            if abs(work[r, c]) > best:
                p, best = r, abs(work[r, c])
        if p != c:
            for j in range(c, n + 1):
                t = work[c, j]
                work[c, j] = work[p, j]
                work[p, j] = t
        for r in range(c + 1, n):
            f = work[r, c] / work[c, c]
            for j in range(c + 1, n + 1):
                work[r, j] -= f * work[c, j]
    for i in range(n - 1, -1, -1):
        t = work[i, n]
        for j in range(i + 1, n):
            t -= work[i, j] * out[j]
        out[i] = t / work[i, i]


@kernel
def flow(A, B, C, j, q, r, Phi, Psi, w, D, d, a, dt, A1, B1, C1, X, Y, Xinv, work, Bs):
    """Component j over one step of the exact Gaussian flow (riccati.FlowFamily.path and StepBatch
    for one flow Phi, Psi (S+1, 2n, 2n)); False where det X ≤ 0 (a blow-up).  B(s) = X(s)⁻ᵀ[B0 +
    IX(s)ᵀq − 2IY(s)ᵀd] at the Gauss nodes by a solve, the inverse of X only at dt (for A); ``Bs``:
    4×n scratch."""
    n = q.shape[0]
    S1 = Phi.shape[0]
    trace_D = 0.0
    for i in range(n):
        trace_D += D[i, i]
    quad_sum, log_det = 0.0, 0.0
    for s in range(S1):
        for i in range(n):
            for k in range(n):
                x = Phi[s, i, k]
                for l in range(n):
                    x += Phi[s, i, n + l] * A[j, l, k]
                X[i, k] = x
        # the forcing IXᵀq − 2IYᵀd with IX = Ψ11 + Ψ12 A, IY = Ψ21 + Ψ22 A, as (Ψ·)ᵀ products: O(n²)
        for l in range(n):
            u, v = 0.0, 0.0
            for i in range(n):
                u += Psi[s, i, n + l] * q[i] - 2.0 * Psi[s, n + i, n + l] * d[i]
                v += Psi[s, i, l] * q[i] - 2.0 * Psi[s, n + i, l] * d[i]
            Bs[1, l] = u
            Bs[2, l] = v
        for k in range(n):
            f = Bs[2, k]
            for l in range(n):
                f += A[j, l, k] * Bs[1, l]
            Bs[3, k] = B[j, k] + f
        if s < S1 - 1:
            solve_transposed(X, Bs[3], Bs[0], work)
            quad = 0.0
            for i in range(n):
                t = 0.0
                for l in range(n):
                    t += a[i, l] * Bs[0, l]
                quad += 0.5 * Bs[0, i] * t + Bs[0, i] * d[i]
            quad_sum += w[s] * quad
            continue
        sign, ld = lu_inverse(X, Xinv, work)
        if not sign > 0.0 or not math.isfinite(ld):
            return False
        log_det = ld
        for i in range(n):
            t = 0.0
            for k in range(n):
                t += Xinv[k, i] * Bs[3, k]
            B1[j, i] = t
        # A1 = (Φ21 + Φ22 A) X⁻¹, symmetrised
        for i in range(n):
            for k in range(n):
                y = Phi[s, n + i, k]
                for l in range(n):
                    y += Phi[s, n + i, n + l] * A[j, l, k]
                Y[i, k] = y
        for i in range(n):
            for k in range(n):
                t = 0.0
                for l in range(n):
                    t += Y[i, l] * Xinv[l, k]
                A1[j, i, k] = t
        for i in range(n):
            for k in range(i + 1):
                t = 0.5 * (A1[j, i, k] + A1[j, k, i])
                A1[j, i, k] = t
                A1[j, k, i] = t
    C1[j] = C[j] + (0.5 * log_det + (r + 0.5 * trace_D) * dt - quad_sum)
    return True


@kernel
def observe_flow(A, B, C, means, covs, F0, c, c_dot, q0, r0, Phi, Psi, w, D, d, a, dt,
                 A1, B1, C1, means1, covs1, log_mass1, points1, h0, J0, ws, clipped):
    """The first half of the data factor (its curvature), the flow with the statistically linearised
    data term, the new moments and their cubature points (YauJiaFilter._step up to ``h1``); the
    damped second-order factors are counted in ``clipped[0]``."""
    J, n = B.shape
    m = c.shape[0]
    Aw, Bw, Cw = np.empty_like(A), np.empty_like(B), np.empty_like(C)
    H = np.empty((m, n, n))
    S, g, q = np.empty((n, n)), np.zeros(n), np.empty(n)
    M, L, X, Y, Xinv = np.empty((n, n)), np.empty((n, n)), np.empty((n, n)), np.empty((n, n)), \
        np.empty((n, n))
    work, Bs = np.empty((n, 2 * n)), np.empty((4, n))
    for j in range(J):
        expected(F0, j, m, n, h0[j], J0[j], H)
        tr = 0.0
        half_curvature(H, c, m, n, S)
        for x in range(n):
            for y in range(n):
                tr += covs[j, x, y] * S[y, x]
        damped = times_exp(A, B, C, j, means[j], covs[j], -0.5 * tr, g, S, Aw, Bw, Cw, M, L)
        if damped < 0:
            return FALLBACK
        clipped[0] += damped
        r = r0
        for i in range(m):
            t = h0[j, i]
            for x in range(n):
                t -= J0[j, i, x] * means[j, x]
            r -= t * c_dot[i]
        for x in range(n):
            t = q0[x]
            for i in range(m):
                t -= J0[j, i, x] * c_dot[i]
            q[x] = t
        if not flow(Aw, Bw, Cw, j, q, r, Phi, Psi, w, D, d, a, dt, A1, B1, C1, X, Y, Xinv, work, Bs):
            return FALLBACK
    return prepare(A1, B1, C1, means1, covs1, log_mass1, points1, ws)


@kernel
def predict_flow(A, B, C, q0, r0, Phi, Psi, w, D, d, a, dt, A1, B1, C1):
    """The observation-free flow of every component (a prediction step)."""
    J, n = B.shape
    X, Y, Xinv = np.empty((n, n)), np.empty((n, n)), np.empty((n, n))
    work, Bs = np.empty((n, 2 * n)), np.empty((4, n))
    for j in range(J):
        if not flow(A, B, C, j, q0, r0, Phi, Psi, w, D, d, a, dt, A1, B1, C1, X, Y, Xinv, work, Bs):
            return FALLBACK
    return OK


@kernel
def observe_finish(A1, B1, C1, means, means1, covs1, F1, h0, J0, c, A2, B2, C2, clipped):
    """The second half of exp(Δyᵀ R⁻¹ ρ_j), ρ_j = h − h0 − J0(x − m_j), to degree 2."""
    J, n = B1.shape
    m = c.shape[0]
    h1, J1, H = np.empty(m), np.empty((m, n)), np.empty((m, n, n))
    S, g = np.empty((n, n)), np.empty(n)
    M, L = np.empty((n, n)), np.empty((n, n))
    for j in range(J):
        expected(F1, j, m, n, h1, J1, H)
        half_curvature(H, c, m, n, S)
        s0, tr = 0.0, 0.0
        for i in range(m):
            t = h1[i] - h0[j, i]
            for x in range(n):
                t -= J0[j, i, x] * (means1[j, x] - means[j, x])
            s0 += t * c[i]
        for x in range(n):
            t = 0.0
            for i in range(m):
                t += (J1[i, x] - J0[j, i, x]) * c[i]
            g[x] = 0.5 * t
            for y in range(n):
                tr += covs1[j, x, y] * S[y, x]
        damped = times_exp(A1, B1, C1, j, means1[j], covs1[j], 0.5 * s0 - 0.5 * tr, g, S, A2, B2, C2, M, L)
        if damped < 0:
            return FALLBACK
        clipped[0] += damped
    return OK


@kernel
def log_sum_exp(v, count):
    top = -np.inf
    for i in range(count):
        top = max(top, v[i])
    s = 0.0
    for i in range(count):
        s += math.exp(v[i] - top)
    return top + math.log(s)


numba.config.CACHE_DIR = _previous_cache_dir
