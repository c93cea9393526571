"""The Fokker–Planck flow over any interval τ ≥ 0 on the basis (irregular observation times).

The offline stage stores the Galerkin generator of the Fokker–Planck equation on the basis,

    A = Φᵀ K Φ   (N×N),   dc/dt = A c,

K the finite-element Fokker–Planck matrix (W du/dt = K u) and Φ the W-orthonormal basis, so that
e^{τA} is the flow of the coefficients over τ (the projected semigroup; for τ = dt the stored
propagator e^{dt L}φ_k of solver/offline/propagator.py is the same flow before projection).  Online, the
real eigen-decomposition A V = V Λ — Λ block diagonal, real eigenvalues λ and 2×2 blocks
[[α, β], [−β, α]] for the pairs α ± iβ — gives e^{τA} = V e^{τΛ} V⁻¹ for every τ at O(N) cost in the
modal coordinates d = V⁻¹ c:

    s  = (Φ V) (e^{τΛ} d)            nodal values of the propagated density       (Q×N product)
    d' = (V⁻¹ Φᵀ W) (s · e_k)        back to modal coordinates after the update   (N×Q product)

the same two products as a regular step, plus N multiplications (a pair as one complex number:
(d_u + i d_w) ← e^{(α − iβ)τ}(d_u + i d_w)).  The decomposition is exact algebra, but loses
digits in proportion to cond(V) (measured: about 1e-17·cond(V) relative); where cond(V) exceeds
:data:`MAX_CONDITION` (1e10 in double precision, 1e7 in single: a strongly non-normal generator, a stiff
confining drift on a large ball) the
loops run in the orthogonal real Schur basis U instead (``form = "schur"``: A = U T Uᵀ, the same two
products with U for V, and e^{τT} as a product of a few precomputed matrices and a short Taylor
polynomial, O(N²) a row: solver/engine/powers.py).  Only where those tables would not fit in
powers.MAX_TABLE_BYTES is the flow formed as e^{τA} = scipy.linalg.expm(τA) per distinct τ
(``form = "expm"``, :attr:`SpectralFlow.exact`: O(N³) once per distinct gap, cached).
"""

from __future__ import annotations

import math
from collections import OrderedDict
from functools import cached_property

import numpy as np

from . import powers

# double precision: the relative rounding of a step is ≈ 1e-17·cond(V) (measured), ≤ 1e-7 under this
# cap; measured through the filter on 2000 rows at gaps of 0.5–1.5 dt, the modal form against the Schur
# form: yau_jia_1d (cond 9.0e9, its flow 8.5e-8 off expm) means within 6.7e-7, variances 9.2e-7
# relative, log-likelihood 5.9e-8; the double well on basis 96 (4.8e8) 1.3e-11 (and against expm:
# tests/solver/engine/test_semigroup.py)
MAX_CONDITION = 1e10
MAX_CONDITION_SINGLE = 1e7  # single precision: the cap before the double one was measured (unchanged)
FORMS = ("modal", "schur", "expm")
_CACHE = 64  # distinct τ kept by the exact (expm) form


class SpectralFlow:
    """e^{τA} of a Galerkin generator for any τ, with the two (augmented) products of the engine.

    ``B`` (Q, N+1) and ``C`` (N+1, Q) are the engine's propagate and project matrices in modal
    coordinates: ``B`` has a zero last column (the carried mass), ``C`` the quadrature weights as its
    last row (it gives ∫σ with the coefficients), both in ``dtype``.
    """

    def __init__(self, generator: np.ndarray, basis: np.ndarray, projector: np.ndarray,
                 weights: np.ndarray, dtype=np.float64, form: str | None = None):
        import scipy.linalg as sla

        self.generator = np.asarray(generator, dtype=float)
        self.basis = np.asarray(basis, dtype=float)
        self.projector = np.asarray(projector, dtype=float)
        self.weights = np.asarray(weights, dtype=float)
        self.dtype = dtype
        N = self.generator.shape[0]
        self.N = N
        lam, vectors = sla.eig(self.generator)
        real = np.abs(lam.imag) <= 1e-12 * np.maximum(1.0, np.abs(lam))
        upper = ~real & (lam.imag > 0)
        columns = [vectors[:, real].real]
        pairs = lam[upper]
        pair_vectors = vectors[:, upper]
        interleaved = np.empty((N, 2 * pairs.size))
        interleaved[:, 0::2] = pair_vectors.real
        interleaved[:, 1::2] = pair_vectors.imag
        columns.append(interleaved)
        V = np.concatenate(columns, axis=1)
        self.real_rates = lam[real].real.copy()
        self.pair_rates = np.conj(pairs)  # (d_u + i d_w)' = (α − iβ)(d_u + i d_w)
        self.r = int(real.sum())
        self.condition = float(np.linalg.cond(V)) if V.shape[1] == N else math.inf
        if form is None:
            cap = MAX_CONDITION if np.dtype(dtype) == np.float64 else min(MAX_CONDITION, MAX_CONDITION_SINGLE)
            form = "modal" if V.shape[1] == N and self.condition <= cap else "schur"
        if form not in FORMS or (form == "modal" and V.shape[1] != N):
            raise ValueError(f"form {form!r}: expected one of {', '.join(FORMS)} (modal: a full eigenbasis)")
        self.powers: powers.SchurPowers | None = None
        if form == "schur":
            base = powers.table_base(N, np.dtype(dtype).itemsize)
            if base is None:  # the tables would not fit: expm per distinct gap
                form = "expm"
            else:
                T, U = sla.schur(self.generator, output="real")
                self.powers = powers.SchurPowers(T, base, dtype)
                self.V, self.V_inv = U, U.T.copy()
        elif form == "modal":
            self.V = V
            self.V_inv = np.linalg.inv(V)
        self.form = form
        self._expm_cache: OrderedDict[float, np.ndarray] = OrderedDict()

    @property
    def exact(self) -> bool:
        """True where the flow is expm(τA) per gap at the nodes (``form = "expm"``); else the loops run in
        the coordinates V⁻¹c (modal or Schur)."""
        return self.form == "expm"

    # -- the engine's matrices ---------------------------------------------------------------
    @cached_property
    def B(self) -> np.ndarray:
        """Φ V with a zero column (modal coefficients, mass) -> nodal values."""
        return _augmented_columns(self.basis @ self.V, self.dtype)

    @cached_property
    def C(self) -> np.ndarray:
        """[V⁻¹ Φᵀ W; wᵀ]: nodal values -> (modal coefficients, ∫)."""
        return np.asfortranarray(np.vstack([self.V_inv @ self.projector, self.weights]), dtype=self.dtype)

    def to_modal(self, coefficients: np.ndarray) -> np.ndarray:
        return self.V_inv @ coefficients

    def from_modal(self, modal: np.ndarray) -> np.ndarray:
        return self.V @ modal

    def apply(self, tau: float, coefficients: np.ndarray) -> np.ndarray:
        """e^{τA} c through this flow's form (the loops' operations; tests compare it with expm)."""
        c = np.asarray(coefficients, dtype=float)
        if self.form == "expm":
            import scipy.linalg as sla

            return sla.expm(float(tau) * self.generator) @ c
        d = self.to_modal(c).astype(self.dtype)
        if self.powers is not None:
            indices, remainders = self.powers.plan(np.array([float(tau)]))
            w, saved = np.empty_like(d), np.empty_like(d)
            self.powers.advance(d, indices[0], float(remainders[0]), w, saved)
        else:
            real, pairs = self.scales(np.array([float(tau)]))
            d[: self.r] *= real[0]
            z = (d[self.r::2] + 1j * d[self.r + 1::2]) * pairs[0]
            d[self.r::2], d[self.r + 1::2] = z.real, z.imag
        return self.from_modal(d.astype(float))

    def scales(self, taus: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Per step, the factors of the real modes (K, r) and of the pairs (K, p), complex."""
        taus = np.asarray(taus, dtype=float)[:, None]
        cdtype = np.complex64 if self.dtype == np.float32 else np.complex128
        with np.errstate(over="ignore", under="ignore", invalid="ignore"):  # far ahead: e^{-inf} = 0
            real = np.exp(taus * self.real_rates[None, :]).astype(self.dtype)
            pairs = np.exp(taus * self.pair_rates[None, :]).astype(cdtype)
        return real, pairs

    # -- the exact form -------------------------------------------------------------------------
    def nodal_flow(self, tau: float) -> np.ndarray:
        """Φ e^{τA} with a zero column (coefficients, mass) -> nodal values, e^{τA} by
        scipy.linalg.expm; cached per τ (the form used when V is ill-conditioned)."""
        key = float(tau)
        found = self._expm_cache.get(key)
        if found is None:
            import scipy.linalg as sla

            found = _augmented_columns(self.basis @ sla.expm(key * self.generator), self.dtype)
            if len(self._expm_cache) >= _CACHE:
                self._expm_cache.popitem(last=False)
            self._expm_cache[key] = found
        else:
            self._expm_cache.move_to_end(key)
        return found


def _augmented_columns(matrix: np.ndarray, dtype) -> np.ndarray:
    return np.asfortranarray(np.hstack([matrix, np.zeros((matrix.shape[0], 1))]), dtype=dtype)


def galerkin_generator(basis: np.ndarray, fokker_planck, mass=None, weights=None) -> np.ndarray:
    """A = Φᵀ K Φ from the basis values Φ (Q, N) and the finite-element matrix K (Q, Q) of
    W du/dt = K u; for M du/dt = K u (a sparse ``mass`` M, ``scheme = "supg"``) A = Φᵀ W M⁻¹ K Φ."""
    basis = np.asarray(basis, dtype=float)
    if mass is None:
        return basis.T @ np.asarray(fokker_planck @ basis)
    import scipy.sparse as sps
    from scipy.sparse.linalg import splu

    rates = splu(sps.csc_matrix(mass)).solve(np.asfortranarray(fokker_planck @ basis))
    return (basis * np.asarray(weights, dtype=float)[:, None]).T @ rates
