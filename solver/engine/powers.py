"""e^{τT} for any τ on the real Schur form T = UᵀAU of an ill-conditioned generator, O(N²) a row.

Where the eigenvectors V of the Galerkin generator A are ill-conditioned (cond(V) over
solver/engine/semigroup.py's MAX_CONDITION: a strongly non-normal A, e.g. the double well x − x³ on a
wide ball), the modal form V e^{τΛ} V⁻¹ loses digits in proportion to cond(V); a block-diagonal
form does not help there (measured: Bavely–Stewart grouping by Sylvester equations puts 64–112 of
96–128 eigenvalues of such generators in one block, bench/irregular_cost.py).  The orthogonal Schur
basis U (cond 1) keeps every digit, and the flow over a gap τ is a product of precomputed matrices:

    τ = n·δ + r,  n = round(τ/δ),  |r| ≤ δ/2,  δ‖T‖₁ = STEP,
    e^{τT} = Π_j E_{j, n_j} · Σ_{i ≤ p} (rT)^i / i!      (n_j the base-b digits of n, E_{j,d} = e^{d·b^j·δT})

— the Taylor polynomial by Horner (p products with T, truncation ≤ TOLERANCE), then one product per
non-zero digit (about log_b(τ/δ) of them).  T and the tables are quasi-upper-triangular and kept
*packed* (the upper triangle column by column, BLAS's 'U' packed layout: N(N+1)/2 numbers, half a
square's memory traffic): every product is N²/2 multiply-adds plus the 2×2 blocks' subdiagonal terms.
On the numpy path each is one BLAS tpmv; the compiled loops (solver/engine/compiled.py's
``_packed_product``) run their own column loop, four columns at a time (measured on basis 128: 1.4–1.7
µs a product against 2.2 for BLAS trmv on a square T and 3.3 for a table from 45 squares, whose 5.9 MB
left the core's cache), the same operations in a different order: the two paths agree to rounding.
The tables take (b − 1)·N(N+1)/2 numbers per digit position, built on first use up to the longest gap
seen; the base is the largest of BASES whose tables for gaps up to 2^SPAN·δ fit in MAX_TABLE_BYTES.
"""

from __future__ import annotations

import math

import numpy as np

STEP = 0.05  # δ‖T‖₁: the remainder's |r|·‖T‖₁ ≤ STEP/2
TOLERANCE = 1e-10  # the Taylor remainder's truncation, relative: θ^{p+1}/(p+1)!·e^θ at θ = STEP/2
# (1e-10 takes degree 4 at STEP 0.05, one product a gap fewer than 1e-12's degree 5: a relative error
# per gap a thousand times under the modal form's rounding accepted up to cond(V) = 1e10, and far under
# the engine's own gap to the optimal filter)
BASES = (16, 8, 4, 2)
SPAN = 15  # the tables are sized for gaps up to 2^SPAN·δ (longer gaps add digit positions)
MAX_TABLE_BYTES = 128 * 2 ** 20
TOP = 2 ** 62  # n beyond: the flow has converged to its stationary state to double precision


def taylor_degree(theta: float, tolerance: float = TOLERANCE) -> int:
    """The smallest p with θ^{p+1}/(p+1)!·e^θ ≤ tolerance."""
    p = 1
    while theta ** (p + 1) / math.factorial(p + 1) * math.exp(theta) > tolerance:
        p += 1
    return p


def packed_size(N: int) -> int:
    """The numbers of an upper-triangular N×N matrix packed: N(N + 1)/2."""
    return N * (N + 1) // 2


def pack(matrix: np.ndarray, dtype=np.float64) -> np.ndarray:
    """The upper triangle of a square matrix, column by column (BLAS's 'U' packed layout: entry (i, j),
    i ≤ j, at j(j + 1)/2 + i)."""
    columns, rows = np.tril_indices(matrix.shape[0])
    return np.ascontiguousarray(matrix[rows, columns], dtype=dtype)


def table_base(N: int, itemsize: int, limit: int | None = None) -> int | None:
    """The largest base whose tables for gaps up to 2^SPAN·δ take at most ``limit`` bytes (None: none)."""
    limit = MAX_TABLE_BYTES if limit is None else limit
    for base in BASES:
        positions = math.ceil(SPAN / math.log2(base))
        if (base - 1) * positions * packed_size(N) * itemsize <= limit:
            return base
    return None


class SchurPowers:
    """The tables and the per-row plan of e^{τT} (T quasi-upper-triangular, N×N) in ``dtype``.  A function
    of T has T's block structure: its subdiagonal entries sit at T's (``lower``, ``before``).

    ``T`` is kept packed (:func:`pack`), the tables as one array ``stack`` (M, N(N+1)/2) whose
    ``stack[m]`` is E_m packed; E_{j,d} is ``stack[j·(b − 1) + d − 1]``.
    """

    def __init__(self, schur: np.ndarray, base: int, dtype=np.float64):
        self.schur = np.asarray(schur, dtype=float)
        self.N = self.schur.shape[0]
        self.base = base
        self.dtype = dtype
        norm = float(np.linalg.norm(self.schur, 1))
        self.delta = STEP / norm if norm > 0.0 else 1.0
        self.degree = taylor_degree(STEP / 2.0)
        self.T = pack(self.schur, dtype)
        from scipy.linalg.blas import dtpmv, stpmv

        self.tpmv = stpmv if np.dtype(dtype) == np.float32 else dtpmv
        self.stack = np.empty((0, packed_size(self.N)), dtype=dtype)
        self.positions = 0
        # the 2×2 blocks' subdiagonal entries (i + 1, i): the packed upper triangle leaves them out
        self.lower = np.flatnonzero(np.diag(self.schur, -1) != 0.0).astype(np.int64) + 1
        self.before = self.lower - 1
        self.subs = np.diag(self.schur, -1)[self.before][None, :].astype(dtype)  # row 0: T, 1 + m: table m

    def ensure(self, positions: int) -> None:
        """Build the tables of digit positions up to ``positions`` − 1 (once)."""
        if positions <= self.positions:
            return
        import scipy.linalg as sla

        built, subs = [self.stack], [self.subs]
        for j in range(self.positions, positions):
            first = sla.expm((self.base ** j * self.delta) * self.schur)
            power = first
            tables = np.empty((self.base - 1, packed_size(self.N)), dtype=self.dtype)
            entries = np.empty((self.base - 1, self.lower.size), dtype=self.dtype)
            for d in range(1, self.base):
                tables[d - 1] = pack(power, self.dtype)
                entries[d - 1] = power[self.lower, self.before]  # (E)_{i+1, i}
                if d + 1 < self.base:
                    power = first @ power
            built.append(tables)
            subs.append(entries)
        self.stack = np.concatenate(built)
        self.subs = np.ascontiguousarray(np.concatenate(subs))
        self.positions = positions

    def plan(self, taus: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Per row, the tables it multiplies by (K, P: index into ``stack`` or −1) and its remainder (K,)."""
        taus = np.asarray(taus, dtype=float)
        with np.errstate(over="ignore", invalid="ignore"):
            steps = np.rint(taus / self.delta)
        far = ~(steps < TOP)
        steps[far] = TOP
        remainders = np.where(far, 0.0, taus - steps * self.delta)
        n = steps.astype(np.int64)
        largest = int(n.max()) if n.size else 0
        positions = 1
        while self.base ** positions <= largest:
            positions += 1
        self.ensure(positions)
        indices = np.full((n.size, positions), -1, dtype=np.int64)
        for j in range(positions):
            digit = (n // self.base ** j) % self.base
            indices[:, j] = np.where(digit > 0, j * (self.base - 1) + digit - 1, -1)
        return indices, remainders

    def advance(self, d: np.ndarray, indices: np.ndarray, remainder: float, w: np.ndarray,
                saved: np.ndarray) -> None:
        """d ← e^{τT} d in place (``indices``, ``remainder``: the row's plan; ``w`` and ``saved`` buffers of
        N): the Taylor polynomial by Horner, w ← d + (r/i)·T w for i = p … 1, then w ← E w for the row's
        tables — each product a BLAS tpmv in place plus the 2×2 blocks' subdiagonal terms.  The steps of
        solver/engine/compiled.py's ``_advance`` (whose products sum in another order: to rounding)."""
        np.copyto(w, d)
        if remainder != 0.0:
            for i in range(self.degree, 0, -1):
                self.product(self.T, 0, w, saved)
                np.multiply(w, self.dtype(remainder / i), out=w)
                np.add(w, d, out=w)
        for m in indices:
            if m >= 0:
                self.product(self.stack[m], m + 1, w, saved)
        np.copyto(d, w)

    def product(self, packed: np.ndarray, row: int, w: np.ndarray, saved: np.ndarray) -> None:
        """w ← M w for a quasi-upper-triangular M, ``packed`` its upper triangle (``row``: its subdiagonal
        entries in ``subs``)."""
        below = saved[: self.before.size]
        np.take(w, self.before, out=below)
        out = self.tpmv(self.N, packed, w, overwrite_x=1)
        if out is not w:  # in place where w is contiguous and of the tables' dtype (the loops' buffers)
            w[:] = out
        if below.size:
            w[self.lower] += self.subs[row] * below
