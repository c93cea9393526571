"""The Yau–Jia filter's compiled pieces (``YAUYAU_KERNEL`` = compiled, solver/jit.py).

One piece of a row — the step over an interval, the normalisation, the error control and the
normalisation again (YauJiaFilter._row's loop body) — as a handful of numba kernels over whole
component stacks (solver/exact/mixture_kernels.py, solver/exact/mixture_control.py) with the sensor
evaluated between them by the numpy path's own functions: four calls of h per observed piece instead
of ~1 800 numpy calls.  :meth:`FastPieces.piece` returns None where the numpy path must take the piece
(a component that is not integrable, a blow-up, φ ≠ 0, an inexact prediction flow): the numpy path
then raises or expands as before, so the fast path changes no outcome.  Numbers: the numpy path's
to ~1e-13 relative per step, but for exact ties of merge and split choices, which rounding decides
in either path (mirror-image split children in a prediction over a gap in pieces;
tests/solver/exact/test_yau_jia_fast.py).
"""

from __future__ import annotations

from typing import Any, Callable

import numpy as np

from .mixtures import SPLIT_OFFSETS, SPLIT_WEIGHTS, SPLIT_WIDTH


class FastPieces:
    """The compiled route through one piece of a row; see the module docstring."""

    def __init__(self, *, sensor: Callable[[np.ndarray], np.ndarray], h: Callable[[np.ndarray], np.ndarray],
                 R_inv: np.ndarray, whiten: np.ndarray, q: list, r: list, predict_exact: bool,
                 max_components: int, split_tolerance: float, split_budget: int, prune: float,
                 sigma: float):
        from . import mixture_control, mixture_kernels  # imports numba

        self.mk, self.mc = mixture_kernels, mixture_control
        self.sensor, self.h = sensor, h
        self.R_inv, self.whiten = np.ascontiguousarray(R_inv, float), np.ascontiguousarray(whiten, float)
        self.q = [np.ascontiguousarray(v, float) for v in q]
        self.r = [float(v) for v in r]
        self.predict_exact = predict_exact
        self.max_components, self.budget = max_components, split_budget
        self.tolerance = float(split_tolerance)
        self.prune, self.sigma = float(prune), float(sigma)
        self.n = len(self.q[0])
        self.ws = mixture_kernels.lapack_workspace(self.n)
        self._flows: dict[int, tuple] = {}

    def _flow(self, family: Any, choice: int) -> tuple:
        """The contiguous arrays of flow ``choice`` of ``family`` (kept per family object)."""
        key = (id(family), choice)
        found = self._flows.get(key)
        if found is None or found[0] is not family:
            eq = family.eq
            found = (family, np.ascontiguousarray(family.Phi[choice]),
                     np.ascontiguousarray(family.Psi[choice]), np.ascontiguousarray(family.w, float),
                     np.ascontiguousarray(eq.D, float), np.ascontiguousarray(eq.d, float),
                     np.ascontiguousarray(eq.a, float), float(family.dt))
            if len(self._flows) > 64:
                self._flows.clear()
            self._flows[key] = found
        return found[1:]

    def piece(self, A, B, C, row, tau: float, family: Any):
        """(A, B, C, log ∫σ gained, clipped, splits, (logw, means, covs, (mean, cov))) after the step
        over ``tau`` with ``row`` (None: prediction), the error control and the normalisation; None
        where the numpy path must take it."""
        mk, n = self.mk, self.n
        J = len(C)
        A, B, C = (np.ascontiguousarray(v, float) for v in (A, B, C))
        A1, B1, C1 = np.empty_like(A), np.empty_like(B), np.empty_like(C)
        clipped = np.zeros(1, np.int64)
        if row is None:
            if not self.predict_exact:
                return None
            Phi, Psi, w, D, d, a, dt = self._flow(family, 1)
            if mk.predict_flow(A, B, C, self.q[1], self.r[1], Phi, Psi, w, D, d, a, dt, A1, B1, C1) != mk.OK:
                return None
            A2, B2, C2 = A1, B1, C1
        else:
            Phi, Psi, w, D, d, a, dt = self._flow(family, 0)
            means, covs, lm = np.empty((J, n)), np.empty((J, n, n)), np.empty(J)
            points = np.empty((J, 2 * n, n))
            if mk.prepare(A, B, C, means, covs, lm, points, self.ws) != mk.OK:
                return None
            F0 = self.sensor(points.reshape(-1, n))
            c = self.R_inv @ np.asarray(row, float)
            c_dot = c / tau
            m = len(c)
            means1, covs1, lm1 = np.empty((J, n)), np.empty((J, n, n)), np.empty(J)
            points1 = np.empty((J, 2 * n, n))
            h0, J0 = np.empty((J, m)), np.empty((J, m, n))
            if mk.observe_flow(A, B, C, means, covs, F0, c, c_dot, self.q[0], self.r[0], Phi, Psi, w, D, d, a,
                               dt, A1, B1, C1, means1, covs1, lm1, points1, h0, J0, self.ws,
                               clipped) != mk.OK:
                return None
            F1 = self.sensor(points1.reshape(-1, n))
            A2, B2, C2 = np.empty_like(A), np.empty_like(B), np.empty_like(C)
            if mk.observe_finish(A1, B1, C1, means, means1, covs1, F1, h0, J0, c, A2, B2, C2,
                                 clipped) != mk.OK:
                return None
        return self._control(A2, B2, C2, int(clipped[0]))

    def _control(self, A, B, C, clipped: int):
        mc, n = self.mc, self.n
        J = len(C)
        means, covs, logw, C_norm = np.empty((J, n)), np.empty((J, n, n)), np.empty(J), np.empty(J)
        kept, lam, U = np.empty(J, np.int64), np.empty((J, n)), np.empty((J, n, n))
        points = np.empty((J, n, 2, n))
        code, gain, count = mc.normalise_axes(A, B, C, self.prune, means, covs, logw, C_norm, kept, lam, U,
                                              points, self.ws, self.sigma)
        if code != mc.OK:
            return None
        if count < J:
            idx = kept[:count]
            means_k, covs_k, logw_k = means[idx], covs[idx], logw[idx]
            lam, U, points = lam[:count], U[:count], points[:count]
        else:
            means_k, covs_k, logw_k = means, covs, logw
        F = self.sensor(means_k)
        h_at = np.ascontiguousarray(self.h(points.reshape(-1, n)), float)
        rate = np.empty((count, n))
        mc.rates(means_k, F, h_at, lam, U, self.whiten, self.sigma, rate)
        means2, covs2, logw2, splits = mc.control(means_k, covs_k, logw_k, rate, lam, U, SPLIT_WEIGHTS,
                                                  SPLIT_OFFSETS, SPLIT_WIDTH, self.tolerance, self.budget,
                                                  self.max_components)
        J2 = len(logw2)
        A_out, B_out, C_out = np.empty((J2, n, n)), np.empty((J2, n)), np.empty(J2)
        mean, cov = np.empty(n), np.empty((n, n))
        code, _ = mc.finish_control(means2, covs2, logw2, bool(splits or J2 != J), A, B, C_norm, A_out, B_out,
                                    C_out, mean, cov)
        if code != mc.OK:
            return None
        return A_out, B_out, C_out, float(gain), clipped, int(splits), (logw2, means2, covs2, (mean, cov))
