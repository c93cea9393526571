"""Yau–Niu's Kolmogorov step and moments for blocks of coupled coordinates (solver/qmc/yau_niu.py).

The Kolmogorov step of one row over τ: every point moves by the Euler kernel of dx = f dt + G dv,

    x ↦ x + f(x)τ + τ^{1/2} a^{1/2} z,     z from a scrambled Sobol normal set in random order
                                           (the filter's bank: solver/qmc/bank.py),

and then each block is mapped affinely, x ↦ m + C^{1/2}P^{-1/2}(x − x̄), so that its weighted mean and
covariance are the kernel's exactly: m = Σ w_i(x_i + f_iτ), C = Cov_w(x + fτ) + a_bb τ (second-order
moment matching; P, x̄ the moved cloud's own).  The moments of the row's output are each block's
weighted mean and covariance.

With the compiled kernels on (``YAUYAU_KERNEL``, solver/jit.py) the drift, the noise and the four
moments are a few passes over the points' coordinates, each contiguous (the points are kept in Fortran
order), and the affine map one more (solver/qmc/kernels.py ``euler``, ``block_moments``, ``affine``;
numpy's path makes about fifteen whole-array passes); the noise and the small matrices are the same,
so both paths agree to rounding (tests/solver/qmc/test_coupled_kernels.py).  The observation step's
Gaussian factor is a kernel too (:func:`block_log_factor`), reading the drift's and the sensor's values
as rows written straight from the contiguous coordinates (:func:`sensor_rows`).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from .. import jit
from .bank import NormalBank
from .cloud import match_moments, moment_map, shape_bandwidth, silverman, symmetric_root, weighted_moments


class CoupledBlocks:
    """The Kolmogorov step and the moments of ``blocks`` (lists of coordinates, each with its own row of
    weights) for a model whose diffusion is a = ``root``²."""

    def __init__(self, model: Any, blocks: list[np.ndarray], root: np.ndarray):
        self.blocks = blocks
        self.model = model
        self.root = np.ascontiguousarray(root, dtype=float)
        self.a = np.asarray(model.a, float)
        self.owner = np.zeros(model.n, np.int64)
        for b, coords in enumerate(blocks):
            self.owner[coords] = b

    def kolmogorov_step(self, X: np.ndarray, W: np.ndarray, tau: float, rng: np.random.Generator,
                        bank: NormalBank) -> np.ndarray:
        """The moved points (a new array) after one Euler step over τ, each block matched to the kernel's
        mean and covariance under its weights W (B, N); the noise drawn from ``bank``."""
        Z, offset, cols, signs = bank.draw(rng)
        root = bank.root(self.root, cols, signs)
        if jit.enabled():
            return self._step_compiled(X, W, tau, Z, offset, root)
        drifted = X + self.model.f(X) * tau
        noise = np.roll(Z, -offset, axis=0) @ root  # n² a point (the compiled kernel skips the root's zeros)
        moved = drifted + math.sqrt(tau) * noise
        for coords, w in zip(self.blocks, W, strict=True):
            mean, cov = weighted_moments(drifted[:, coords], w)
            cov = cov + self.a[np.ix_(coords, coords)] * tau
            moved[:, coords] = match_moments(moved[:, coords], w, mean, cov)
        return moved

    def _step_compiled(self, X: np.ndarray, W: np.ndarray, tau: float, Z: np.ndarray, offset: int,
                       root: np.ndarray) -> np.ndarray:
        """:meth:`kolmogorov_step` by the kernels: the new points in Fortran order (each coordinate
        contiguous; X in either order)."""
        from . import kernels

        N, n = X.shape
        XT = np.ascontiguousarray(X.T)  # no copy for Fortran-ordered points
        FT = sensor_rows(self.model.f, XT)
        GT, DT, MT = np.empty((n, N)), np.empty((n, N)), np.empty((n, N))
        kernels.euler(XT, FT, Z, offset, root, math.sqrt(tau), tau, GT, DT, MT)
        W = np.ascontiguousarray(W)
        drift_mean, moved_mean = np.empty(n), np.empty(n)
        drift_cov, moved_cov = np.empty((n, n)), np.empty((n, n))
        kernels.block_moments(DT, self.owner, W, drift_mean, drift_cov)
        kernels.block_moments(MT, self.owner, W, moved_mean, moved_cov)
        A = np.zeros((n, n))
        for coords in self.blocks:
            block = np.ix_(coords, coords)
            A_block = moment_map(moved_cov[block], drift_cov[block] + self.a[block] * tau)
            A[block] = np.eye(len(coords)) if A_block is None else A_block  # singular: only shifted
        kernels.affine(MT, moved_mean, A, drift_mean, DT)
        return DT.T

    def moments(self, X: np.ndarray, W: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Mean and (block-diagonal) covariance of the product over the blocks."""
        n = X.shape[1]
        mean, cov = np.empty(n), np.zeros((n, n))
        if jit.enabled() and X.flags.f_contiguous:
            from . import kernels

            kernels.block_moments(X.T, self.owner, np.ascontiguousarray(W), mean, cov)
            return mean, cov
        for coords, w in zip(self.blocks, W, strict=True):
            mean[coords], cov[np.ix_(coords, coords)] = weighted_moments(X[:, coords], w)
        return mean, cov


def sensor_rows(function: Any, XT: np.ndarray) -> np.ndarray:
    """A model's vector function (f or h) at the points given as coordinate rows XT (n, P): its values as
    rows (m, P), C-contiguous (solver/expressions.py's ``rows``; any other callable through its (P, m))."""
    rows = getattr(function, "rows", None)
    if rows is not None:
        return rows(XT)
    return np.ascontiguousarray(np.asarray(function(XT.T), dtype=float).T)


def block_log_factor(obs: Any, H: np.ndarray, comps: np.ndarray, part: np.ndarray, gaps: np.ndarray,
                     keys: np.ndarray, terms: Any, k: int) -> np.ndarray:
    """Row k's log factor (P,) for one block of the measurement (``obs``, its components ``comps`` of the
    sensor values H (P, m) at the row's own points): solver/measurement.py's ``log_factors``, or with the
    compiled kernels on, Gaussian noise and H Fortran-ordered (each component contiguous),
    kernels.block_log_factor (a few passes over the points instead of two einsums, a transposed copy and
    a dozen whole-array passes: ~3 ms a row at 65 536 points)."""
    if not jit.enabled() or obs.likelihood != "gaussian" or not H.flags.f_contiguous:
        return obs.log_factors(H[None][:, :, comps], part[k:k + 1], gaps[k:k + 1], keys[k:k + 1],
                               terms.rows(k, k + 1, keys))[0]
    from . import kernels

    pat = obs.pattern(int(keys[k]))
    cols = np.ascontiguousarray(comps[pat.index], dtype=np.int64)
    y = np.ascontiguousarray(part[k, pat.index], dtype=float)
    penalty, constant = (1.0, float(terms.constant[k])) if obs.discrete else (float(gaps[k]), 0.0)
    P = H.shape[0]
    out, half, hr = np.empty(P), np.empty(P), np.empty((len(cols), P))
    with np.errstate(over="ignore", invalid="ignore"):
        kernels.block_log_factor(H.T, cols, np.ascontiguousarray(pat.R_inv, dtype=float), y, penalty,
                                 constant, hr, half, out)
    return out


def restart(X: np.ndarray, w: np.ndarray, rng: np.random.Generator, bank: NormalBank,
            bandwidth: float | None) -> np.ndarray:
    """solver/qmc/yau_niu.py's local resampling-restart of one coupled block's points X (N, d) by the
    compiled kernels (the same steps and the same draws of ``rng``; ~16 ms of numpy passes at 65 536
    points in 4 dimensions): systematic resampling, the multi-scale kernel's bandwidth (``bandwidth``, or
    the cloud's shape), the spread by the bank's normals, the moment matching.  The new points (N, d) in
    Fortran order."""
    from . import kernels

    N, d = X.shape
    XT, W = np.ascontiguousarray(X.T), np.ascontiguousarray(w)[None]
    owner = np.zeros(d, np.int64)
    mean, cov = np.empty(d), np.empty((d, d))
    kernels.block_moments(XT, owner, W, mean, cov)
    picks = np.empty(N, np.int64)
    kernels.systematic(W[0], rng.random(), picks)
    h = bandwidth if bandwidth is not None else _bandwidth(XT, W[0], mean, cov)
    shrink = math.sqrt(1.0 - h * h)
    M = np.zeros((bank.sets.shape[2], d))
    offset = 0
    Z = bank.sets[0]
    if h > 0:
        Z, offset, cols, signs = bank.draw(rng)
        M[cols[:d]] = (signs[:d, None] * h) * symmetric_root(cov)
    YT = np.empty((d, N))
    kernels.spread(XT, picks, shrink, mean, Z, offset, M, np.empty((M.shape[0], N)), YT)
    here, P = np.empty(d), np.empty((d, d))
    kernels.block_moments(YT, owner, np.full((1, N), 1.0 / N), here, P)
    A = moment_map(P, cov)
    if A is None:
        return (YT - here[:, None] + mean[:, None]).T
    out = np.empty((d, N))
    kernels.affine(YT, here, A, mean, out)
    return out.T


def _bandwidth(XT: np.ndarray, w: np.ndarray, mean: np.ndarray, cov: np.ndarray) -> float:
    """cloud.multiscale_bandwidth of the points as rows XT (d, N), its moments by a kernel."""
    from . import kernels

    d, N = XT.shape
    lam, U = np.linalg.eigh(cov)
    if lam[0] <= 1e-12 * max(lam[-1], 1e-300):
        return silverman(N, d)
    third, fourth = np.empty(d), np.empty(d)
    kernels.shape_sums(XT, w, mean, np.ascontiguousarray(U / np.sqrt(lam)), third, fourth)
    return shape_bandwidth(third, fourth, w, N, d)
