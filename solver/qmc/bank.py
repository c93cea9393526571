"""The Yau–Niu filter's QMC normal sets, built once (solver/qmc/yau_niu.py): the part of its Kolmogorov
step and of its restarts that does not depend on the data.

Each row of a coupled model moves every point by x ↦ x + f(x)τ + τ^{1/2} a^{1/2} z with z from a QMC
normal set in random order, and each restart spreads the resampled points by such a set too.  Building
the set is a scrambled Sobol sequence and the inverse normal CDF of each of its N·n numbers: 7.4 ms at
65 536 points in 4 dimensions, 1.6 ms at 8192 (scipy's ``qmc.Sobol`` and ``ndtri``), as much as the
rest of the ring's row.  None of it depends on the data, so the filter builds a bank of ``sets``
scrambled sets once per seed and point count, each in a random order of its points, and each row
draws from it:

    z_i = s_j · Z^{(b)}_{(i + o) mod N, c_j},     j = 1 … n,

a set b and an offset o uniformly, and a random signed order (c, s) of the coordinates.  Each z_i is
N(0, I), independent of the point's earlier rows (a new b and o each row: reusing an order across rows
correlates the points' noises), and each row's multiset of deviates is a low-discrepancy normal set;
the signs keep a set's own odd moments (its small skewness) from adding up with one sign row after row.
The offset replaces a random order per row (0.7 ms at 65 536 points) and makes the gather sequential.
The signed order is folded into the diffusion's root, M[c_j] = s_j · (a^{1/2})_j, so the row's noise
costs what it did (:meth:`NormalBank.root`).

Measured (one-off scripts, summarised in bench/results/yau-niu-speed.md) on the 4-state ring against
bench/yau_niu.py's 10⁶-particle truth, 300 rows, seeds 0–4, rms mean gap median (mean), with a new
scrambled set and a random order each row as before: 0.0145 (0.0160) at 32 768 points, 0.0120 (0.0136) at
65 536; one set: 0.0183 (0.0179), 0.0152 (0.0146); eight sets, random orders: 0.0167 (0.0163), 0.0123
(0.0124); eight sets, offsets: 0.0158 (0.0150), 0.0090 (0.0104).  On the 4-D linear model against the
Kalman filter (8192 points, 300 increments, 4 paths × 4 seeds) eight sets left the rms mean gap 20%
larger than a new set each row (median 0.0119 against 0.0096) and 32 sets did not (0.0096; worst
variance median 4.8% against 5.2%): hence 32.
"""

from __future__ import annotations

import threading
import warnings

import numpy as np
from scipy.special import ndtri
from scipy.stats import qmc

SETS = 32  # scrambled sets per bank (measured: see the module docstring)
MAX_BYTES = 64 * 2**20  # a bank of larger sets keeps fewer of them (at least one)


def bank_sets(N: int, n: int) -> int:
    """How many (N, n) sets a bank keeps: :data:`SETS`, fewer where they would pass MAX_BYTES."""
    return max(1, min(SETS, MAX_BYTES // max(1, 8 * N * n)))


def sobol_set(N: int, n: int, rng: np.random.Generator) -> np.ndarray:
    """A scrambled Sobol normal set (N, n) in Sobol's order (Yau–Niu, QMC sampling)."""
    with warnings.catch_warnings():  # N need not be a power of 2 (the balance is then approximate)
        warnings.simplefilter("ignore", UserWarning)
        u = qmc.Sobol(n, scramble=True, seed=rng).random(N)
    return ndtri(np.clip(u, 1e-16, 1.0 - 1e-16))


class NormalBank:
    """``sets`` scrambled Sobol normal sets (N, n) of one seed, each in a random order of its points;
    :meth:`draw` takes one per row."""

    def __init__(self, N: int, n: int, seed: int, sets: int | None = None):
        rng = np.random.default_rng([seed, 0, 1])  # apart from the rows' (seed, step) generators
        sets = bank_sets(N, n) if sets is None else sets
        self.sets = np.stack([sobol_set(N, n, rng)[rng.permutation(N)] for _ in range(sets)])

    def draw(self, rng: np.random.Generator) -> tuple[np.ndarray, int, np.ndarray, np.ndarray]:
        """(Z, offset, cols, signs): a set, where its points start and a signed random order of its
        coordinates; the row's deviates are :func:`deviates` of them."""
        S, N, n = self.sets.shape
        Z = self.sets[int(rng.integers(S))]
        return Z, int(rng.integers(N)), rng.permutation(n), rng.choice(np.array([-1.0, 1.0]), n)

    @staticmethod
    def root(root: np.ndarray, cols: np.ndarray, signs: np.ndarray) -> np.ndarray:
        """M with Z' @ M = (Z'[:, cols] · signs) @ root for any Z' (N, n): the signed order folded into
        the diffusion's root (n, n)."""
        M = np.empty_like(root)
        M[cols] = signs[:, None] * root
        return M

    def normals(self, rng: np.random.Generator, d: int) -> np.ndarray:
        """N standard normal deviates in d ≤ n dimensions, in random order (a restart's spread)."""
        Z, offset, cols, signs = self.draw(rng)
        return deviates(Z, offset, cols[:d], signs[:d])


def deviates(Z: np.ndarray, offset: int, cols: np.ndarray, signs: np.ndarray) -> np.ndarray:
    """A draw's deviates (N, len(cols)): point i takes s_j · Z[(i + offset) mod N, c_j] (the first
    coordinates of the signed order only, where ``cols`` and ``signs`` are cut short)."""
    return np.roll(Z[:, cols], -offset, axis=0) * signs


class Banks:
    """The banks of one filter by (seed, N), built on first use and shared by its sessions (threads);
    the ``keep`` last used are kept."""

    def __init__(self, n: int, keep: int = 4):
        self.n, self.keep = n, keep
        self._banks: dict[tuple[int, int], NormalBank] = {}
        self._lock = threading.Lock()

    def get(self, seed: int, N: int) -> NormalBank:
        key = (int(seed), int(N))
        bank = self._banks.get(key)
        if bank is None:
            with self._lock:
                bank = self._banks.get(key)
                if bank is None:
                    bank = self._banks[key] = NormalBank(N, self.n, seed)
                    while len(self._banks) > self.keep:
                        self._banks.pop(next(iter(self._banks)))
        return bank
