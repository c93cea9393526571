"""Yau–Niu's blocks: the coordinates nothing couples, and one-coordinate blocks in one step.

:func:`independent_blocks` splits the coordinates into blocks that no term couples, over which the
exact filter factorises.  :class:`SingleBlocks`: every block one coordinate with at most one sensor.

Ten or a hundred independent cubic sensors: the exact filter is the product of n 1-D filters, and the
Yau–Niu filter keeps one row of log weights per coordinate on a shared point set.  The generic row
loops over the blocks in Python (about 1 ms a block: 119 ms a row at 100 states); here each part of
the row is one array operation over all blocks at once (arrays (N, B) or (B, N)):

* Kolmogorov step: the kernel's mean m_b = Σ_i w_bi (x_ib + f_b(x_i)τ) and variance
  Var_w(x_b + f_bτ) + a_bb τ per coordinate, the moved points mapped affinely onto them (the 1-D case
  of ``match_moments``);
* observation step: each block's factor exp(h_b y_b/R_bb − ½h_b²τ/R_bb) (continuous increments), or the
  discrete readings' Gaussian / Student-t density, by one call of a unit-noise Observation on the scaled
  data y_b/√R_bb, h_b/√R_bb (the blocks as its rows, measurement.Observation.log_factors per row): the
  quadratic forms are those of R_bb; log det R_bb, which the unit noise leaves out, is added back to the
  block's log-likelihood (``log_r``);
* moments: per coordinate, the covariance diagonal.

The noise of the Kolmogorov step is each block's own 1-D QMC set (``cloud.lattice_normals``: a randomly
shifted lattice, in a random order per block and row) instead of a row of an n-dimensional Sobol set:
the blocks' filters are separate, so only each coordinate's own set matters (their restarts draw from
the lattice too: over 6 paths × 2 seeds of ten sensors as close as from Sobol), and the lattice has the
least discrepancy there at the cost of N inverse-CDF values (a 100-D Sobol set with its scrambling and
N·n values was 12 ms of a 44 ms row).  With the compiled kernels on (``YAUYAU_KERNEL``, solver/jit.py)
the row runs in the kernels of solver/qmc/kernels.py on the points in Fortran order (each coordinate
contiguous), the numpy path staying the reference (tests/solver/qmc/test_singles_kernels.py).

Restarts stay per block (``YauNiuFilter._restart``), for the blocks whose coverage fell.
"""

from __future__ import annotations

import math
from types import SimpleNamespace
from typing import Any

import numpy as np

from .. import jit
from ..measurement import Observation
from ..spec import GaussianPrior
from .cloud import lattice_normals


class SingleBlocks:
    """The vectorised row parts for ``blocks`` of one coordinate each, block b seeing the observation
    component ``components[b]`` (or none)."""

    def __init__(self, model: Any, blocks: list[np.ndarray], components: list[np.ndarray]):
        self.cols = np.array([int(c[0]) for c in blocks])
        # block b is coordinate b (the usual order): whole arrays, no gathered copies
        self.identity = bool(np.array_equal(self.cols, np.arange(model.n)))
        self.comp = np.array([int(c[0]) if len(c) else -1 for c in components])
        self.has_sensor = self.comp >= 0
        R = np.asarray(model.R, float)
        r = np.array([R[c, c] if c >= 0 else 1.0 for c in self.comp])
        self.scale = 1.0 / np.sqrt(r)
        self.log_r = np.where(self.has_sensor, -0.5 * np.log(r), 0.0)  # −½ log R_bb: not in the unit noise
        self.a = np.diag(np.asarray(model.a, float))[self.cols]
        self.root = np.sqrt(np.maximum(self.a, 0.0))
        self.discrete = model.spec.measurement.kind == "discrete"
        self.unit = Observation(SimpleNamespace(spec=model.spec, m=1, R=np.ones((1, 1))))

    @staticmethod
    def applies(blocks: list[np.ndarray], components: list[np.ndarray]) -> bool:
        return len(blocks) > 1 and all(len(c) == 1 for c in blocks) and all(len(c) <= 1 for c in components)

    # -- Kolmogorov step ------------------------------------------------------------------------
    def kolmogorov_step(self, X: np.ndarray, f: Any, W: np.ndarray, tau: float,
                        rng: np.random.Generator) -> np.ndarray:
        """The Kolmogorov step over τ of every block (YauNiuFilter._kolmogorov) on the lattice noise
        (:func:`lattice_normals`).  Compiled (solver/qmc/kernels.py, ``YAUYAU_KERNEL``): X, which
        must be the caller's own array, is moved in place and made Fortran-ordered (each coordinate
        contiguous); numpy: a new array."""
        N, B = X.shape[0], len(self.cols)
        Q, perm, offset = lattice_normals(N, B, rng)
        sd = math.sqrt(tau) * self.root
        if self.identity and jit.enabled():
            from . import kernels

            X = X if X.T.flags.c_contiguous else np.asfortranarray(X)
            F = f(X)
            kernels.kolmogorov(X.T, np.ascontiguousarray(F.T), W, Q, perm, offset, sd, self.a * tau, tau)
            return X
        drifted = X + f(X) * tau
        moved = drifted.copy()
        noise = Q[(perm[:, None] + offset[None, :]) % N] * sd
        if self.identity:
            moved += noise
        else:
            moved[:, self.cols] += noise
        return self.kolmogorov(drifted, moved, W, tau)

    def kolmogorov(self, drifted: np.ndarray, moved: np.ndarray, W: np.ndarray, tau: float) -> np.ndarray:
        """``moved`` (N, n) with each coordinate matched to the kernel's mean and variance under its
        block's weights W (B, N); edited in place and returned (``drifted`` is used up)."""
        D = drifted if self.identity else drifted[:, self.cols]
        M = moved if self.identity else moved[:, self.cols]
        mean = np.einsum("bi,ib->b", W, D)
        D -= mean
        np.square(D, out=D)
        var = np.einsum("bi,ib->b", W, D) + self.a * tau
        here = np.einsum("bi,ib->b", W, M)
        M -= here
        spread = np.einsum("bi,ib->b", W, M * M)
        ok = spread > 1e-300  # a collapsed coordinate is only shifted (match_moments' rule)
        ratio = np.sqrt(np.divide(var, spread, out=np.ones_like(var), where=ok))
        M *= np.where(ok, ratio, 1.0)
        M += mean
        if not self.identity:
            moved[:, self.cols] = M
        return moved

    def moments(self, X: np.ndarray, W: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        n = X.shape[1]
        if self.identity and X.T.flags.c_contiguous and jit.enabled():
            from . import kernels

            m, v = np.empty(n), np.empty(n)
            kernels.moments(X.T, np.ascontiguousarray(W), m, v)
        else:
            D = X if self.identity else X[:, self.cols]
            m = np.einsum("bi,ib->b", W, D)
            D = D - m
            v = np.einsum("bi,ib->b", W, D * D)
        mean, cov = np.empty(n), np.zeros((n, n))
        mean[self.cols] = m
        cov[self.cols, self.cols] = v
        return mean, cov

    # -- observation step -----------------------------------------------------------------------
    def chunk_terms(self, rows: np.ndarray, gaps: np.ndarray) -> tuple[np.ndarray, np.ndarray, Any]:
        """The chunk's scaled data (K·B, 1), keys (K·B,) and unit-noise row terms, block b of row k at
        index k·B + b."""
        K, B = len(rows), len(self.cols)
        y = np.full((K, B), np.nan)
        y[:, self.has_sensor] = rows[:, self.comp[self.has_sensor]] * self.scale[self.has_sensor]
        y = y.reshape(K * B, 1)
        keys = Observation.pattern_keys(~np.isnan(y))
        taus = np.repeat(np.asarray(gaps, float), B)
        return y, keys, self.unit.row_terms(y, taus, keys)

    def seen(self, chunk: tuple, k: int) -> bool:
        """Whether row k observes any block."""
        B = len(self.cols)
        return bool(chunk[1][k * B:(k + 1) * B].any())

    def observe(self, logW: np.ndarray, hX: np.ndarray, chunk: tuple, k: int, tau: float, temper: float,
                coverage: np.ndarray):
        """Row k's update of the log weights logW (B, N), in place (compiled: also where the likelihood is
        zero, which leaves logW for the caller to restore), with each observed block's ``coverage``
        1/Σw² (B,) written from the normalisation's own exponential (the restarts then need no pass of
        their own over the points: an exp per point and block costs ~6 ns where numpy's exp has no SIMD
        loop, as on AVX2 machines, 2.4 ms a row at 100 states and 4096 points): (the row's predictive
        log-likelihood, its sum of offsets, the gate's bound −2·that − Σ log det 2πS₀
        (solver/measurement.py), the observed components, the log factors (up to a constant of each
        block) of the observed blocks whose coverage fell under ``temper`` × N, for the progressive
        correction); the log-likelihood None where an observed block's likelihood is zero at every
        point."""
        if jit.enabled():
            return self._observe_compiled(logW, hX, chunk, k, tau, temper, coverage)
        y, keys, terms = chunk
        B = len(self.cols)
        part = slice(k * B, (k + 1) * B)
        row_keys = keys[part]
        observed = row_keys != 0
        h = np.zeros((B, hX.shape[0], 1))
        h[self.has_sensor, :, 0] = (hX[:, self.comp[self.has_sensor]] * self.scale[self.has_sensor]).T
        factors = self.unit.log_factors(h, y[part], np.full(B, tau), row_keys,
                                        terms.rows(k * B, (k + 1) * B, keys))
        every = bool(observed.all())
        total = factors + logW if every else factors[observed] + logW[observed]  # Yau–Niu, log domain
        top = total.max(axis=1)
        if not np.isfinite(top).all():
            return None, 0.0, 0.0, 0, {}
        total -= top[:, None]
        e = np.exp(total)  # one exponential for both the log-sum-exp and the coverage 1/Σw²
        sums = e.sum(axis=1)
        gains = top + np.log(sums)
        total += (top - gains)[:, None]
        seen_coverage = sums * sums / np.einsum("bi,bi->b", e, e)
        coverage[observed] = seen_coverage
        if every:
            logW[...] = total
        else:
            logW[observed] = total
        low = np.flatnonzero(observed)[seen_coverage < temper * logW.shape[1]]
        return self._row_sums(gains, observed, terms, part, {int(b): factors[b] for b in low})

    def _observe_compiled(self, logW: np.ndarray, hX: np.ndarray, chunk: tuple, k: int, tau: float,
                          temper: float, coverage: np.ndarray):
        """:meth:`observe` by the kernels of solver/qmc/kernels.py (same results to rounding)."""
        from . import kernels

        y, keys, terms = chunk
        B, N = logW.shape
        part = slice(k * B, (k + 1) * B)
        observed = keys[part] != 0
        kind = (kernels.CONTINUOUS if not self.discrete else
                kernels.GAUSSIAN if self.unit.likelihood == "gaussian" else kernels.STUDENT)
        dof = float(self.unit.dof) if kind == kernels.STUDENT else 1.0
        top = np.empty(B)
        HT = np.ascontiguousarray(hX.T)
        comp = np.maximum(self.comp, 0)
        kernels.log_factors(logW, HT, comp, self.scale, y[part, 0], observed, kind, tau,
                            terms.constant[part], terms.quadratic[part], dof, top)
        if not np.isfinite(top[observed]).all():  # logW is the caller's to restore
            return None, 0.0, 0.0, 0, {}
        every = bool(observed.all())
        E = np.exp(logW) if every else np.zeros((B, N))
        if not every:
            np.exp(logW, out=E, where=observed[:, None])
        sums = np.ones(B)
        kernels.normalise(E, observed, logW, sums, coverage)  # (an unobserved block's coverage untouched)
        gains = (top + np.log(sums))[observed]
        factors = {}
        for b in np.flatnonzero(observed & (coverage < temper * N)):
            h = (hX[:, self.comp[b]] * self.scale[b])[None, :, None]
            factors[int(b)] = self.unit.log_factors(h, y[k * B + b:k * B + b + 1], np.array([tau]),
                                                    keys[k * B + b:k * B + b + 1],
                                                    terms.rows(k * B + b, k * B + b + 1, keys))[0]
        return self._row_sums(gains, observed, terms, part, factors)

    def _row_sums(self, gains: np.ndarray, observed: np.ndarray, terms: Any, part: slice, factors: dict):
        """(the row's predictive log-likelihood, its offsets, the gate's bound, the observed count,
        ``factors``) from each observed block's log-sum-exp ``gains`` (:meth:`observe`)."""
        log_r = self.log_r[observed]
        offsets = terms.offset[part][observed] + (0.0 if self.discrete else log_r)
        gains = gains + (log_r if self.discrete else 0.0)
        gain = float(np.sum(gains + offsets))
        log_det = float(np.sum(terms.log_det_S0[part][observed] - 2.0 * log_r))
        return gain, float(np.sum(offsets)), -2.0 * gain - log_det, int(observed.sum()), factors

    @staticmethod
    def coverage(logW: np.ndarray, known: np.ndarray) -> np.ndarray:
        """1/Σ_i w_bi² per block: ``known`` (B,) where it is not NaN (the observation step's), else from
        the log weights logW (B, N)."""
        unknown = np.isnan(known)
        if not unknown.any():
            return known
        w = np.exp(logW[unknown])
        out = known.copy()
        out[unknown] = 1.0 / np.einsum("bi,bi->b", w, w)
        return out


def independent_blocks(model: Any) -> list[np.ndarray]:
    """The coordinates split into blocks that no term couples: f_i depending on x_j, a_ij ≠ 0, an
    observation component depending on both, correlated observation noise (R_kl ≠ 0) or prior
    (a mixture or density prior couples everything).  The exact filter factorises over them."""
    n = model.n
    parent = list(range(n))

    def find(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    def join(group) -> None:
        group = list(group)
        for j in group[1:]:
            parent[find(j)] = find(group[0])

    index = {s: i for i, s in enumerate(model.symbols)}
    for i, expr in enumerate(model.drift):
        join([i] + [index[s] for s in expr.free_symbols if s in index])
    a = np.asarray(model.a, float)
    for i, j in zip(*np.nonzero(a), strict=True):
        join([int(i), int(j)])
    uses = [[index[s] for s in expr.free_symbols if s in index] for expr in model.observation]
    for used in uses:
        join(used)
    R = np.asarray(model.R, float)
    for k, l in zip(*np.nonzero(R), strict=True):
        join(uses[k] + uses[l])
    prior = model.spec.initial
    if isinstance(prior, GaussianPrior):
        for i, j in zip(*np.nonzero(np.asarray(prior.cov, float)), strict=True):
            join([int(i), int(j)])
    else:
        join(range(n))
    roots = [find(i) for i in range(n)]
    order = list(dict.fromkeys(roots))
    return [np.array([i for i in range(n) if roots[i] == r]) for r in order]
