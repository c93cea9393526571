"""How a row of data enters a filter: the update factor of each observation kind, missing
components, the predictive log-likelihood and the outlier gate (docs/measurements.md).

One step over an interval τ = t_k − t_(k−1) is: propagate the density by the Fokker–Planck flow
e^{τL}, multiply it pointwise by the update factor e_k(x), renormalise (Bayes).  Only e_k depends on
the kind of data (the spec's ``[measurement]`` table):

* continuous (seed 002 (5.35), stable form): the row is dy = ∫h dt + dw over the interval,
  p(dy | x) = N(dy; h τ, R τ) with x frozen over the interval, and

      e(x) = exp(hᵀR⁻¹dy − ½hᵀR⁻¹h τ) = p(dy | x) / N(dy; 0, R τ)     (the Girsanov factor);

* discrete, gaussian: the row is z = h(x(t_k)) + v, v ~ N(0, R):  e(x) = N(z; h(x), R)
  = exp(hᵀR⁻¹z − ½hᵀR⁻¹h − ½zᵀR⁻¹z − ½ log det 2πR) — the continuous factor with dy → z, τ → 1;
* discrete, student-t (ν degrees of freedom, scale R):  e(x) = t_ν(z; h(x), R).

A missing component (NaN) is marginalised: only the observed components o enter, with R_oo (the
marginal of a Gaussian or a Student-t vector is of the same family with the sub-matrix).

**Predictive log-likelihood.**  log p(row_k | rows before) = log E_pred[e_k] + b_k, with b_k =
log N(dy_o; 0, R_oo τ) for the continuous kind (the factor is relative to that) and 0 otherwise.

**Gate.**  The predictive standard score of a row is d² = −2 log p(row | past) − log det(2π S),
S the exact predictive covariance of the row: S = κ²C + S₀ with C = Cov_pred(h_o(x)), κ = τ and
S₀ = R_oo τ (continuous), κ = 1 and S₀ = R_oo (gaussian) or R_oo ν/(ν − 2) (student-t, ν > 2; R_oo
otherwise).  For a Gaussian prediction d² is exactly the Mahalanobis distance of the innovation; for
any other prediction it is that of a Gaussian with the same covariance and the same density at the
observation, so a row lying where the predicted density has mass passes even far out in a heavy
tail.  The gate rejects a row when d² exceeds the χ²_|o| quantile of the two-sided probability of
K standard deviations (for one component: d > K).  Because C ⪰ 0, g = −2 log p − log det(2π S₀) ≥ d²:
a filter checks the cheap bound g first and computes C only when g is over the threshold.
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass
from functools import lru_cache
from typing import Any

import numpy as np

from .errors import InputError

LOG_2PI = math.log(2.0 * math.pi)


GATE_MAX = 37.0  # beyond, the two-sided tail probability of K standard deviations underflows double precision


def check_gate(gate: Any) -> float | None:
    """A gate override (None: the spec's): a number in [0, GATE_MAX], else InputError('gate')."""
    if gate is None:
        return None
    if isinstance(gate, bool) or not isinstance(gate, numbers.Real) or not math.isfinite(gate) \
            or not 0 <= gate <= GATE_MAX:
        raise InputError("gate", f"must be a number from 0 to {GATE_MAX:g} (predictive standard deviations; "
                                 f"0 turns the gate off), got {gate!r}")
    return float(gate)


@lru_cache(maxsize=64)
def gate_threshold(gate: float, components: int) -> float:
    """The d² beyond which a row of ``components`` observed numbers is gated: the χ² quantile of the
    two-sided tail probability of ``gate`` standard deviations (inf: the gate is off)."""
    if gate <= 0 or components < 1:
        return math.inf
    if components == 1:
        return float(gate * gate)
    from scipy.special import chdtri, ndtr

    return float(chdtri(components, 2.0 * ndtr(-gate)))  # P(|N(0, 1)| > K), positive up to GATE_MAX


def standard_score(d2: float, components: int) -> float:
    """The number of one-dimensional standard deviations with the same tail probability as d² of a
    χ²_components variable (d itself for one component); in log scale where the tail underflows."""
    if not math.isfinite(d2):
        return math.inf
    d2 = max(d2, 0.0)
    if components <= 1:
        return math.sqrt(d2)
    from scipy.special import chdtrc, gammaln, log_ndtr, ndtri

    tail = float(chdtrc(components, d2))
    if tail > 1e-300:
        return float(-ndtri(tail / 2.0))
    # log Q(a, y) = log Γ(a, y)/Γ(a) ~ (a − 1) log y − y − log Γ(a) + log(1 + (a − 1)/y), y = d²/2
    a, y = 0.5 * components, 0.5 * d2
    log_tail = (a - 1.0) * math.log(y) - y - float(gammaln(a)) + math.log1p((a - 1.0) / y)
    from scipy.optimize import brentq

    return float(brentq(lambda z: math.log(2.0) + float(log_ndtr(-z)) - log_tail, 1.0, math.sqrt(d2) + 10.0))


@dataclass(frozen=True)
class Pattern:
    """The observed components ``index`` of a row and what its factor needs of R."""

    index: np.ndarray  # observed components (sorted)
    R: np.ndarray  # R_oo (|o|, |o|)
    R_inv: np.ndarray  # its inverse
    log_det_R: float  # log det R_oo
    threshold: float  # d² gate threshold for |o| components


class Observation:
    """The spec's ``[measurement]`` of a model: factors, predictive log-likelihoods, the gate."""

    def __init__(self, model: Any, gate: float | None = None):
        spec = model.spec.measurement
        self.model = model
        self.kind: str = spec.kind
        self.likelihood: str = spec.likelihood
        self.dof: float | None = spec.dof
        self.gate: float = spec.gate if gate is None else float(gate)
        self.m: int = model.m
        self.R = np.asarray(model.R, dtype=float)
        self._patterns: dict[int, Pattern] = {}

    @property
    def discrete(self) -> bool:
        return self.kind == "discrete"

    @property
    def gating(self) -> bool:
        return self.gate > 0

    def describe(self) -> str:
        what = ("increments dy of y over each interval" if not self.discrete else
                f"measurements z = h(x) + v, {self.likelihood} noise"
                + (f" with {self.dof:g} degrees of freedom" if self.dof else ""))
        return f"{self.kind}: {what}; gate {'off' if not self.gating else f'{self.gate:g} sd'}"

    # -- patterns of observed components -----------------------------------------------------
    def pattern(self, key: int) -> Pattern:
        """The pattern of a row whose observed components are the bits of ``key``."""
        found = self._patterns.get(key)
        if found is None:
            index = np.array([j for j in range(self.m) if key >> j & 1], dtype=int)
            R_oo = self.R[np.ix_(index, index)]
            found = Pattern(index=index, R=R_oo, R_inv=np.linalg.inv(R_oo),
                            log_det_R=float(np.linalg.slogdet(R_oo)[1]),
                            threshold=gate_threshold(self.gate, len(index)))
            self._patterns[key] = found
        return found

    @staticmethod
    def pattern_keys(observed: np.ndarray) -> np.ndarray:
        """Bit keys (K,) of the observed masks (K, m) (0: nothing observed)."""
        return (observed.astype(np.int64) << np.arange(observed.shape[1], dtype=np.int64)).sum(axis=1)

    # -- per-row constants -------------------------------------------------------------------
    @staticmethod
    def groups(keys: np.ndarray) -> list[tuple[int, Any]]:
        """(key, rows) per pattern of a chunk: a slice over the whole chunk when it has one pattern
        (the usual case: no fancy indexing), else the row indices."""
        if len(keys) == 0:
            return []
        first = int(keys[0])
        if (keys == first).all():
            return [(first, slice(None))]
        return [(int(key), np.flatnonzero(keys == key)) for key in np.unique(keys).tolist()]

    def row_terms(self, rows: np.ndarray, taus: np.ndarray, keys: np.ndarray) -> "RowTerms":
        """Per row: the offset b_k to the predictive log-likelihood, log det 2πS₀, κ², the gate's
        threshold, and (discrete) −½ zᵀR⁻¹z − ½ log det 2πR (gaussian) or the t constant."""
        K = len(rows)
        offset, log_det_S0 = np.zeros(K), np.zeros(K)
        threshold, constant = np.empty(K), np.zeros(K)
        threshold.fill(math.inf)
        quadratic = np.zeros(K)  # yᵀR_oo⁻¹y (the row's own quadratic form)
        groups = self.groups(keys)
        with np.errstate(over="ignore", invalid="ignore"):  # a row of 1e307: inf, the gate's business
            self._fill_terms(rows, taus, groups, offset, log_det_S0, threshold, constant, quadratic)
            kappa2 = taus * taus if not self.discrete else np.ones(K)
        return RowTerms(offset=offset, log_det_S0=log_det_S0, kappa2=kappa2, threshold=threshold,
                        constant=constant, quadratic=quadratic, groups=groups)

    def _fill_terms(self, rows, taus, groups, offset, log_det_S0, threshold, constant, quadratic) -> None:
        for key, sel in groups:
            if key == 0:
                continue
            pat = self.pattern(key)
            y = rows[sel][:, pat.index]
            size = len(pat.index)
            if size == 1:
                quadratic[sel] = y[:, 0] * y[:, 0] * pat.R_inv[0, 0]
            else:
                quadratic[sel] = np.einsum("ki,ij,kj->k", y, pat.R_inv, y)
            threshold[sel] = pat.threshold
            if not self.discrete:
                tau = taus[sel]
                log_det = pat.log_det_R + size * (LOG_2PI + np.log(tau))
                offset[sel] = -0.5 * quadratic[sel] / tau - 0.5 * log_det
                log_det_S0[sel] = log_det
            elif self.likelihood == "gaussian":
                log_det = pat.log_det_R + size * LOG_2PI
                constant[sel] = -0.5 * quadratic[sel] - 0.5 * log_det
                log_det_S0[sel] = log_det
            else:
                nu = float(self.dof)
                from scipy.special import gammaln

                constant[sel] = (gammaln(0.5 * (nu + size)) - gammaln(0.5 * nu)
                                 - 0.5 * size * math.log(nu * math.pi) - 0.5 * pat.log_det_R)
                log_det_S0[sel] = pat.log_det_R + size * (LOG_2PI + math.log(self.S0_scale(0.0)))

    # -- the factor at given points ----------------------------------------------------------
    def log_factors(self, h_points: np.ndarray, rows: np.ndarray, taus: np.ndarray, keys: np.ndarray,
                    terms: "RowTerms", cache: dict | None = None, penalty: bool = True,
                    out: np.ndarray | None = None) -> np.ndarray:
        """log e_k at the points (K, P) of h (P, m), or of h per row (K, P, m): a moving frame's nodes;
        rows with key 0 (nothing observed) get 0.

        Elementwise numpy per row (no BLAS): a row's bits do not depend on the chunk it came in.
        ``cache`` keeps, per pattern, h_o R_oo⁻¹ and ½h_oᵀR_oo⁻¹h_o at the points (the engine's
        nodes are fixed).  ``penalty=False``: the continuous factor without −½hᵀR⁻¹h τ (the literal
        form of seed 002 (5.35), whose propagator carries it).  ``out``: a (K, P) array to write into."""
        K, P = len(rows), h_points.shape[-2]
        per_row = h_points.ndim == 3
        groups = terms.groups
        whole = len(groups) == 1  # one pattern (the usual chunk): work in place on the whole array
        if out is None:
            out = np.empty((K, P)) if whole else np.zeros((K, P))
        elif not whole:
            out[...] = 0.0
        with np.errstate(over="ignore", invalid="ignore"):
            for key, sel in groups:
                if key == 0:
                    out[sel] = 0.0
                    continue
                pat = self.pattern(key)
                if per_row:  # (k, |o|, P) and (k, P): each row its own points
                    hR, half = self._row_terms(h_points[sel], pat)
                else:
                    hR, half = self._point_terms(h_points, key, pat, cache)
                    hR = hR[None]
                y = rows[sel][:, pat.index]
                block = out if whole else np.empty((len(y), P))
                np.multiply(y[:, 0, None], hR[:, 0], out=block)
                for j in range(1, len(pat.index)):
                    block += y[:, j, None] * hR[:, j]
                if not self.discrete:
                    if penalty:
                        tau = taus[sel]
                        if per_row:
                            block -= tau[:, None] * half
                        else:
                            block -= tau[0] * half if np.all(tau == tau[0]) else np.multiply.outer(tau, half)
                elif self.likelihood == "gaussian":
                    block -= half
                    block += terms.constant[sel, None]
                else:  # Student-t: T = (z − h)ᵀR⁻¹(z − h) = zᵀR⁻¹z − 2hᵀR⁻¹z + hᵀR⁻¹h
                    block *= -2.0
                    block += 2.0 * half
                    block += terms.quadratic[sel, None]
                    np.maximum(block, 0.0, out=block)
                    block /= float(self.dof)
                    np.log1p(block, out=block)
                    block *= -0.5 * (float(self.dof) + len(pat.index))
                    block += terms.constant[sel, None]
                if not whole:
                    out[sel] = block
        return out

    @staticmethod
    def _row_terms(h_rows: np.ndarray, pat: Pattern) -> tuple[np.ndarray, np.ndarray]:
        """h_o R_oo⁻¹ (k, |o|, P) and ½h_oᵀR_oo⁻¹h_o (k, P) of h per row (k, P, m)."""
        h_o = h_rows[:, :, pat.index]
        hR = np.einsum("kpi,ij->kpj", h_o, pat.R_inv)
        # two two-operand einsums: numpy's three-operand one loops generically (3× the time at 65 536
        # points); each element still sums over i, then j, in order, whatever the chunk's K
        half = 0.5 * np.einsum("kpj,kpj->kp", hR, h_o)
        return np.ascontiguousarray(hR.transpose(0, 2, 1)), half

    def point_terms(self, h_points: np.ndarray, key: int, cache: dict | None = None):
        """h_o R_oo⁻¹ (|o|, P) and ½h_oᵀR_oo⁻¹h_o (P,) of h at the points (P, m) for the pattern ``key``
        (``cache``: kept per pattern, as :meth:`log_factors` keeps them)."""
        return self._point_terms(h_points, key, self.pattern(key), cache)

    def _point_terms(self, h_points, key: int, pat: Pattern, cache: dict | None):
        if cache is not None and key in cache:
            return cache[key]
        h_o = h_points[:, pat.index]
        h_R = h_o @ pat.R_inv
        hR = np.ascontiguousarray(h_R.T)  # (|o|, P)
        half = 0.5 * (h_R * h_o).sum(axis=1)
        if cache is not None:
            cache[key] = (hR, half)
        return hR, half

    def covariance_correction(self, key: int, kappa2: float, cov_h: np.ndarray, S0_scale: float) -> float:
        """log det(I + κ² S₀⁻¹ C) for the pattern ``key``: what the exact score removes from the bound."""
        pat = self.pattern(key)
        S0_inv = pat.R_inv / S0_scale
        M = np.eye(len(pat.index)) + kappa2 * S0_inv @ cov_h
        sign, log_det = np.linalg.slogdet(M)
        return float(log_det) if sign > 0 else 0.0

    def S0_scale(self, tau: float) -> float:
        """S₀ = R_oo × this."""
        if not self.discrete:
            return tau
        if self.likelihood == "student-t":
            nu = float(self.dof)
            return nu / (nu - 2.0) if nu > 2.0 else 1.0
        return 1.0


@dataclass(frozen=True)
class RowTerms:
    """Per-row constants of a chunk (see :meth:`Observation.row_terms`)."""

    offset: np.ndarray  # predictive log-likelihood = log E_pred[e] + offset
    log_det_S0: np.ndarray  # log det 2πS₀
    kappa2: np.ndarray  # κ²
    threshold: np.ndarray  # d² gate threshold (inf: not gated)
    constant: np.ndarray  # the discrete factor's constant part
    quadratic: np.ndarray  # yᵀR_oo⁻¹y
    groups: list = ()  # (key, rows) per pattern (Observation.groups)

    def bound_bias(self) -> np.ndarray:
        """g = bias − 2 log E_pred[e]: −2·offset − log det 2πS₀."""
        return -2.0 * self.offset - self.log_det_S0

    def rows(self, start: int, stop: int, keys: np.ndarray) -> "RowTerms":
        """The terms of rows start..stop − 1 (``keys``: the whole chunk's pattern keys)."""
        part = slice(start, stop)
        return RowTerms(offset=self.offset[part], log_det_S0=self.log_det_S0[part], kappa2=self.kappa2[part],
                        threshold=self.threshold[part], constant=self.constant[part],
                        quadratic=self.quadratic[part], groups=Observation.groups(keys[part]))


# -- rows and times --------------------------------------------------------------------------
def check_rows(rows: Any, m: int, field: str = "increments") -> np.ndarray:
    """A chunk of rows (K, m) of finite numbers; NaN marks a missing component (a row of NaN: no
    observation).  InputError names the row at fault."""
    try:
        arr = np.asarray(rows, dtype=float)
    except (TypeError, ValueError):
        raise InputError(field, "must be a list of rows of numbers (null for a missing value)") from None
    if arr.ndim == 1 and m == 1:
        arr = arr[:, None]
    if arr.ndim != 2 or arr.shape[1] != m:
        got = arr.shape[1] if arr.ndim == 2 else f"shape {arr.shape}"
        raise InputError(field, f"each row must have {m} number(s) (one per observation component); "
                                f"got {got}")
    if np.isinf(arr).any():
        row = int(np.argmax(np.isinf(arr).any(axis=1)))
        raise InputError(f"{field}[{row}]", "must be finite numbers (null for a missing value)")
    return arr


def check_first_gap(taus: np.ndarray | None, discrete: bool, method: str | None = None,
                    field: str = "times") -> None:
    """A continuous increment covers [t_(k−1), t_k]: a first row at the prior's time itself (τ = 0) is
    an empty interval, allowed for discrete measurements only."""
    if taus is not None and len(taus) and taus[0] <= 0.0 and not discrete:
        who = f"method {method}: " if method else ""
        raise InputError(f"{field}[0]", f"{who}an increment dy over [t_(k-1), t_k] needs t_k after the "
                                        "filter's time (a row at the prior's time t0 is for discrete "
                                        "measurements only): start the rows after t0, or give the prior an "
                                        "earlier t0")


SPACING_BITS = 10  # a step must span at least 2^10 float spacings of its time: ~3 of its digits survive


def min_step(t: float) -> float:
    """The shortest step that keeps its precision at time ``t``: 2^SPACING_BITS float spacings there."""
    return math.ulp(abs(t)) * (1 << SPACING_BITS)


def check_spacing(t: float, step: float, field: str, what: str = "t") -> None:
    """InputError naming ``field`` when a step of ``step`` at time ``t`` is shorter than :func:`min_step`:
    t + step would round to t, or keep fewer than about three significant digits of the step, and rows
    would report the same (or a wrong) time."""
    if not step >= min_step(t):
        raise InputError(field, f"{what} = {t:.17g} is too large for steps of {step:g}: floats there "
                                f"are {math.ulp(abs(t)):.3g} apart, and a step must span at least "
                                f"2^{SPACING_BITS} of those ({min_step(t):.3g}) to keep its precision "
                                "(else every row reports the same t); count time from a nearer origin "
                                "(subtract a fixed offset from t0 and from every time)")


def resolve_times(t_now: float, started: bool, K: int, dt: float, times: Any,
                  field: str = "times") -> np.ndarray | None:
    """The gaps τ_k (K,) of a chunk that carries ``times`` (absolute t_k, strictly increasing, after
    the state's time ``t_now``; at the prior's time itself when nothing was observed yet, i.e. not
    ``started``), or None for a regular chunk (times None: t_k = t_now + k·dt).  InputError names the
    row at fault."""
    if times is None:
        return None
    try:
        t = np.asarray(times, dtype=float).reshape(-1)
    except (TypeError, ValueError):
        raise InputError(field, "must be a list of numbers (one time per row)") from None
    if len(t) != K:
        raise InputError(field, f"needs one time per row: {K} row(s), got {len(t)} time(s)")
    if K == 0:
        return np.empty(0)
    bad = ~np.isfinite(t)
    if bad.any():
        row = int(np.argmax(bad))
        raise InputError(f"{field}[{row}]", "must be a finite number")
    taus = np.diff(t, prepend=t_now)
    first_ok = taus[0] > 0 or (taus[0] == 0 and not started)
    if not first_ok:
        raise InputError(f"{field}[0]", f"t = {float(t[0]):.17g} is not after the filter's time "
                                       f"{float(t_now):.17g}: times must increase strictly")
    later = taus[1:] <= 0
    if later.any():
        row = int(np.argmax(later)) + 1
        raise InputError(f"{field}[{row}]", f"t = {float(t[row]):.17g} is not after t = "
                                            f"{float(t[row - 1]):.17g} (row {row - 1}): times must increase "
                                            "strictly")
    _check_gaps(t, taus, t_now, field)
    return taus


def _check_gaps(t: np.ndarray, taus: np.ndarray, t_now: float, field: str) -> None:
    """Each gap τ_k at least :func:`min_step` of its two ends (a first row at the prior's time, τ = 0,
    is allowed where resolve_times allows it); InputError naming the first row at fault."""
    before = np.concatenate([[t_now], t[:-1]]) if math.isfinite(t_now) else np.concatenate([t[:1], t[:-1]])
    size = np.maximum(np.abs(t), np.abs(before))
    with np.errstate(over="ignore"):  # times near the float maximum: their spacing overflows to inf (short)
        short = taus < np.spacing(size) * float(1 << SPACING_BITS)
    short[0] &= taus[0] > 0 and math.isfinite(t_now)
    if short.any():
        row = int(np.argmax(short))
        at = float(size[row])
        raise InputError(f"{field}[{row}]", f"t = {float(t[row]):.17g} is {float(taus[row]):.3g} after "
                                            f"the time before it: at {at:.3g} floats are {math.ulp(at):.3g} "
                                            f"apart, and a gap must span at least 2^{SPACING_BITS} of those "
                                            f"({min_step(at):.3g}) to keep its precision; count time from a "
                                            "nearer origin (subtract a fixed offset from t0 and from every "
                                            "time)")
