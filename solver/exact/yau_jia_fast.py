"""The Yau–Jia filter's compiled pieces (``YAUYAU_KERNEL`` = compiled, solver/jit.py).

One piece of a row — the step over an interval, the normalisation, the error control and the
normalisation again (YauJiaFilter._row's loop body) — is one call of the numba kernel
solver/exact/mixture_piece.py over the whole component stack, the sensor's h, ∂h, ∂²h evaluated inside
it from a tape of their SymPy expressions (solver/exact/sensor_tape.py): no Python between the
stages, instead of ~1 800 numpy calls.  :meth:`FastPieces.piece` returns None where the numpy path
must take the piece (a component that is not integrable, a blow-up, φ ≠ 0, an inexact prediction
flow): the numpy path then raises or expands as before, so the fast path changes no outcome.  A
sensor the tape cannot express takes the numpy path throughout (YauJiaFilter._fast_pieces, one
warning).  Numbers: the numpy path's to ~1e-13 relative per step, but for exact ties of merge and
split choices, which rounding decides in either path (mirror-image split children in a prediction
over a gap in pieces; tests/solver/exact/test_yau_jia_fast.py).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from .mixtures import SPLIT_OFFSETS, SPLIT_WEIGHTS, SPLIT_WIDTH
from .sensor_tape import Tape


class FastPieces:
    """The compiled route through one piece of a row; see the module docstring."""

    def __init__(self, *, tapes: tuple[Tape, Tape], R_inv: np.ndarray, whiten: np.ndarray, q: list, r: list,
                 predict_exact: bool, max_components: int, split_tolerance: float, split_budget: int,
                 prune: float, sigma: float):
        from . import mixture_piece  # imports numba

        self.kernel = mixture_piece.piece
        self.tapes = tuple((t.code, t.constants, t.outputs) for t in tapes)
        self.R_inv, self.whiten = np.ascontiguousarray(R_inv, float), np.ascontiguousarray(whiten, float)
        self.q = [np.ascontiguousarray(v, float) for v in q]
        self.r = [float(v) for v in r]
        self.predict_exact = predict_exact
        self.settings = (float(prune), float(sigma), float(split_tolerance), int(split_budget),
                         int(max_components))
        self.split = (np.asarray(SPLIT_WEIGHTS, float), np.asarray(SPLIT_OFFSETS, float), float(SPLIT_WIDTH))
        self.no_data = np.zeros(len(self.R_inv))
        self._flows: dict[tuple[int, int], tuple] = {}

    def _flow(self, family: Any, choice: int) -> tuple:
        """(Phi, Psi, w, D, d, a, dt) of flow ``choice`` of ``family``, contiguous (kept per family)."""
        key = (id(family), choice)
        found = self._flows.get(key)
        if found is None or found[0] is not family:
            eq = family.eq
            arrays = (family.Phi[choice], family.Psi[choice], family.w, eq.D, eq.d, eq.a)
            found = (family, (*(np.ascontiguousarray(v, float) for v in arrays), float(family.dt)))
            if len(self._flows) > 64:
                self._flows.clear()
            self._flows[key] = found
        return found[1]

    def piece(self, A, B, C, row, tau: float, family: Any):
        """(A, B, C, log ∫σ gained, clipped, splits, (logw, means, covs, (mean, cov))) after the step
        over ``tau`` with ``row`` (None: prediction), the error control and the normalisation; None
        where the numpy path must take it."""
        observed = row is not None
        if not observed and not self.predict_exact:
            return None
        c = self.R_inv @ np.asarray(row, float) if observed else self.no_data
        A, B, C = (np.ascontiguousarray(v, float) for v in (A, B, C))
        choice = 0 if observed else 1
        code, A, B, C, gain, clipped, splits, logw, means, covs, mean, cov = self.kernel(
            A, B, C, observed, c, c / tau, self.q[choice], self.r[choice], self._flow(family, choice),
            *self.tapes, self.whiten, self.settings, self.split)
        if code != 0:
            return None
        return A, B, C, float(gain), int(clipped), int(splits), (logw, means, covs, (mean, cov))
