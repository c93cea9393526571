"""The spec's tables: the prior (``[initial]``), ``[measurement]``, ``[domain]`` and
``[discretization]``, with the checks of a matrix and of a prior that :class:`~.spec.ModelSpec`
runs on them.

Pure pydantic and numpy (no model, no SymPy): everything that reads a prior or a table — the
Gaussian filters, the model, the exact filters — imports it from here or through ``spec``.
"""

from __future__ import annotations

import math
from typing import Annotated, Any, Literal, Union

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from .errors import SpecError


class Strict(BaseModel):
    """A table of the spec: unknown keys refused, frozen, strict types."""

    # strict: "16" is not a number and 16.5 not an integer (no silent coercion); ints pass as floats
    model_config = ConfigDict(extra="forbid", frozen=True, strict=True)


def _finite(values: Any, what: str) -> None:
    arr = np.asarray(values, dtype=float)
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{what} must be finite numbers")


def check_spd(matrix: list[list[float]], size: int, what: str, semi: bool = False) -> None:
    """Raise ValueError unless ``matrix`` is a symmetric positive definite size×size matrix
    (``semi``: positive semi-definite and not zero, as a diffusion with noise on some coordinates)."""
    arr = np.asarray(matrix, dtype=float)
    if arr.shape != (size, size):
        raise ValueError(f"{what} must be {size}x{size}, got shape {arr.shape}")
    _finite(arr, what)
    if not np.allclose(arr, arr.T, rtol=1e-12, atol=1e-12):
        raise ValueError(f"{what} must be symmetric")
    low, scale = np.linalg.eigvalsh(arr).min(), max(1.0, np.abs(arr).max())
    if semi and low >= -1e-12 * scale and np.abs(arr).max() > 0:
        return
    if low <= 1e-12 * scale:
        eigenvalues = ", ".join(f"{v:.4g}" for v in np.linalg.eigvalsh(arr))
        raise ValueError(f"{what} must be positive {'semi-' if semi else ''}definite"
                         + (" and not zero" if semi else "") + f" (its eigenvalues are {eigenvalues})")


def singular(matrix: np.ndarray) -> bool:
    """True for a (checked, positive semi-definite) matrix with a null direction: noise on some
    coordinates only."""
    matrix = np.asarray(matrix, dtype=float)
    scale = max(1.0, float(np.abs(matrix).max()))
    return bool(np.linalg.eigvalsh(matrix).min() <= 1e-12 * scale)


class GaussianPrior(Strict):
    kind: Literal["gaussian"]
    mean: list[float]
    cov: list[list[float]]


class MixturePrior(Strict):
    kind: Literal["mixture"]
    weights: list[float] = Field(min_length=1, max_length=64)
    means: list[list[float]]
    covs: list[list[list[float]]]

    @field_validator("weights")
    @classmethod
    def _weights(cls, w: list[float]) -> list[float]:
        _finite(w, "weights")
        if min(w) < 0 or sum(w) <= 0:
            raise ValueError("weights must be non-negative with a positive sum")
        return w


class DensityPrior(Strict):
    kind: Literal["density"]
    expression: str = Field(max_length=2000)


Prior = Annotated[Union[GaussianPrior, MixturePrior, DensityPrior], Field(discriminator="kind")]


MONITOR_DEFAULT = 0.0  # the innovation monitor (solver/watch.py): off unless set (rows per false alarm)
GATE_DEFAULT = 6.0  # predictive standard deviations (docs/measurements.md): 2e-9 of healthy Gaussian data


class Measurement(Strict):
    """How the observations arrive (docs/measurements.md).

    ``kind = "continuous"`` (default): each row is an increment dy of y over [t_(k-1), t_k],
    dy = h dt + dw, E[dw dwᵀ] = R dt (seed 002 (5.35)).  ``kind = "discrete"``: each row is a sampled
    measurement z_k = h(x(t_k)) + v_k, v_k ~ N(0, R) (``likelihood = "gaussian"``) or a Student-t with
    ``dof`` degrees of freedom and scale matrix R (``likelihood = "student-t"``, heavy-tailed sensors).
    ``gate = K``: an observation whose predictive standard score exceeds K (for m components: whose
    predictive probability is below that of K standard deviations) only predicts and is flagged;
    ``gate = 0`` turns the gate off.  ``monitor = N``: the innovation monitor (solver/watch.py) flags a
    sustained sensor bias, with a false alarm about once in N healthy rows (1e9 is a good choice);
    ``monitor = 0``, the default, leaves it off (it costs a few array operations per chunk).
    """

    kind: Literal["continuous", "discrete"] = "continuous"
    likelihood: Literal["gaussian", "student-t"] = "gaussian"
    dof: float | None = Field(default=None, gt=0, le=1e6)
    gate: float = Field(default=GATE_DEFAULT, ge=0, le=37)  # beyond 37 sd the tail probability underflows
    monitor: float = Field(default=MONITOR_DEFAULT, ge=0, le=1e15)  # healthy rows per false alarm (0: off)

    @model_validator(mode="after")
    def _consistent(self) -> "Measurement":
        if 0 < self.monitor < 1e3:
            raise SpecError("measurement.monitor", "is the mean number of healthy rows per false alarm of "
                                                   "the innovation monitor: 0 (off) or from 1e3 to 1e15")
        if self.likelihood == "student-t":
            if self.kind != "discrete":
                raise SpecError("measurement.likelihood", 'student-t needs kind = "discrete" (continuous '
                                "increments dy = h dt + dw have Gaussian noise)")
            if self.dof is None:
                raise SpecError("measurement.dof", "student-t needs dof (degrees of freedom, e.g. 4)")
        elif self.dof is not None:
            raise SpecError("measurement.dof", 'is only used with likelihood = "student-t"')
        return self


FOLLOW_DISTANCE = 0.15  # of the radius: the mean this far from the centre re-centres the ball
FOLLOW_MASS = 1e-4  # of ∫σ in the outer tenth of the ball: this much mass there re-centres it


class Domain(Strict):
    """The ball B_R(c) the density lives on.  ``follow = true``: c moves with the posterior
    (solver/engine/follow.py) — re-centred when the mean is more than ``follow_distance``·R from c, or when
    more than ``follow_mass`` of the mass lies in the ball's outer tenth; for an affine drift c also
    rides the mean's ODE ċ = Ac + b between moves (solver/engine/frame.py).  ``shape`` = Σ (symmetric positive
    definite): the domain is the ellipsoid (x − c)ᵀΣ⁻¹(x − c) < R² instead — R counts standard deviations
    of Σ — meshed as the ball mapped by x = c + Lz (Σ = LLᵀ, Cholesky), with the basis of −½div(Σ∇): give
    the shape of the posterior when it is long and thin (constant-velocity tracking,
    bench/results/cv-basis.md).  ``shape = "posterior"``: Σ is the steady-state Kalman–Bucy covariance of a
    linear model (solver/model.py ``Model.shape``)."""

    radius: float = Field(gt=0, le=1e6)
    center: list[float] | None = None
    follow: bool = False
    follow_distance: float = Field(default=FOLLOW_DISTANCE, gt=0, le=0.75)
    follow_mass: float = Field(default=FOLLOW_MASS, gt=0, lt=1)
    region: list[list[float]] | None = None
    shape: list[list[float]] | Literal["posterior"] | None = None

    @field_validator("shape", mode="before")
    @classmethod
    def _shape_form(cls, shape: Any) -> Any:
        """One clear message for both forms (pydantic's would name each member of the union)."""
        if shape is None or shape == "posterior":
            return shape
        rows_ok = isinstance(shape, list) and shape and all(isinstance(r, list) for r in shape)
        if not rows_ok or not all(isinstance(v, (int, float)) and not isinstance(v, bool)
                                  for row in shape for v in row):
            raise SpecError("domain.shape", f"must be a covariance matrix [[...], ...] (one row per state "
                                            f"variable) or \"posterior\", got {shape!r}")
        return shape

    @model_validator(mode="after")
    def _follow_options(self) -> "Domain":
        if not self.follow and (self.follow_distance != FOLLOW_DISTANCE or self.follow_mass != FOLLOW_MASS):
            raise SpecError("domain.follow", "follow_distance and follow_mass only apply with follow = true")
        if self.region is not None:
            if not self.follow:
                raise SpecError("domain.region", "the region of an atlas only applies with follow = true")
            for i, pair in enumerate(self.region):
                if len(pair) != 2 or not all(math.isfinite(v) for v in pair) or not pair[0] < pair[1]:
                    raise SpecError(f"domain.region[{i}]",
                                    f"must be [lo, hi] with finite lo < hi, got {pair}")
        return self

    def stored(self) -> dict[str, Any]:
        """The table as it enters the model's content hash: the follow keys only when set, so a spec
        written before they existed keeps its id."""
        data = self.model_dump(mode="json")
        for key in ("follow", "follow_distance", "follow_mass"):
            if not self.follow:
                data.pop(key)
        if self.region is None:
            data.pop("region")
        if self.shape is None:
            data.pop("shape")
        return data


class Discretization(Strict):
    """Time step and resolution of the offline stage.

    ``basis`` is N, the number of L²(B_R)-orthonormal basis functions.  ``mesh`` is the
    number of elements across the radius in 1-D, of rings in 2-D, of refinements of the ball in 3-D
    (at most 5: 41727 nodes, a Lanczos basis) (None: chosen from N and n).  ``order`` is the
    polynomial degree of the finite elements.  ``substeps`` splits dt for the offline time
    integration.  ``precision`` is the floating point of the online engine's two matrix-vector
    products per observation: "single" halves their memory traffic (the speed-up is measured in
    bench/results/engine.md) at a relative rounding of ~1e-7 per step; moments, log-likelihood and the
    stored state stay in double.  ``element = "bubble"`` (2-D or 3-D, order 2): P2 plus bubbles with
    their positive lumped mass instead of P1 (solver/offline/fem.py; in 2-D ~5x closer to the exact filter at
    the same cost, tests/solver/offline/test_fem_bubble.py; in 3-D ``mesh`` is at most 3).  Left out,
    ``element`` is chosen per dimension by measurement (solver/defaults.py): "bubble" in 3-D where
    ``mesh`` is left out too, order is 2 and the scheme not "supg" (on a following ball the ball refined
    three times), "lagrange" otherwise.  ``scheme`` is
    how the Fokker–Planck operator is discretised: "galerkin" (plain Galerkin with the lumped mass),
    "consistent" (Galerkin with the consistent mass, 2-D and 3-D, P1 or P2 + bubble: measured in 2-D) or
    "supg" (streamline-upwind Petrov–Galerkin: the test functions tilted along the drift, consistent
    mass; P1 elements in 2-D and 3-D).  For noise on some coordinates only, "consistent" on the bubble
    element is the closest to the exact filter at a given cost (bench/results/cv-basis.md).  Left out, it
    is "supg" where the diffusion is only positive semi-definite (noise on some coordinates: the
    operator is hypoelliptic and plain Galerkin rings along the drift, bench/results/psd.md) and "galerkin"
    otherwise.  ``points`` is the quasi-Monte Carlo point budget of method "yau-niu"
    (solver/qmc/yau_niu.py; None: its default, chosen by measurement).
    """

    dt: float = Field(gt=0, le=10.0)
    basis: int = Field(ge=2, le=4000)
    mesh: int | None = Field(default=None, ge=2, le=4000)
    order: Literal[1, 2] = 2
    substeps: int = Field(default=8, ge=1, le=1000)
    precision: Literal["double", "single"] = "double"
    element: Literal["lagrange", "bubble"] | None = None  # None: by dimension (ModelSpec.element)
    scheme: Literal["galerkin", "consistent", "supg"] | None = None
    points: int | None = Field(default=None, ge=16)  # yau-niu's QMC point budget (None: by dimension)


def mixture_weights(weights) -> np.ndarray:
    """Weights scaled to sum 1 without overflow: divided by their largest first ([1e308, 1e308] ->
    [0.5, 0.5]; the plain sum would be inf and every weight 0)."""
    w = np.asarray(weights, dtype=float)
    w = w / w.max()
    return w / w.sum()


def finite_or_raise(values: Any, field: str) -> None:
    """SpecError naming ``field`` unless every number of ``values`` is finite."""
    try:
        _finite(values, field)
    except ValueError as exc:
        raise SpecError(field, str(exc)) from None


def check_prior(prior: GaussianPrior | MixturePrior | DensityPrior, n: int) -> None:
    """The prior's means have ``n`` finite numbers and its covariances are n×n SPD (SpecError naming
    the field otherwise)."""
    if isinstance(prior, GaussianPrior):
        if len(prior.mean) != n:
            raise SpecError("initial.mean", f"needs {n} numbers, got {len(prior.mean)}")
        finite_or_raise(prior.mean, "initial.mean")
        try:
            check_spd(prior.cov, n, "cov")
        except ValueError as exc:
            raise SpecError("initial.cov", str(exc).removeprefix("cov ")) from None
    elif isinstance(prior, MixturePrior):
        k = len(prior.weights)
        if len(prior.means) != k or len(prior.covs) != k:
            raise SpecError("initial", f"weights, means and covs need the same length ({k})")
        for i, (mean, cov) in enumerate(zip(prior.means, prior.covs, strict=True)):
            if len(mean) != n:
                raise SpecError(f"initial.means[{i}]", f"needs {n} numbers, got {len(mean)}")
            finite_or_raise(mean, f"initial.means[{i}]")
            try:
                check_spd(cov, n, "cov")
            except ValueError as exc:
                raise SpecError(f"initial.covs[{i}]", str(exc).removeprefix("cov ")) from None


def check_prior_in_region(prior: GaussianPrior | MixturePrior | DensityPrior,
                          region: list[list[float]] | None) -> None:
    """A following ball starts at the prior's mean, which must lie in ``[domain] region`` (refused here,
    before any precompute, so nothing is stored for such a spec)."""
    if region is None or isinstance(prior, DensityPrior):
        return
    if isinstance(prior, GaussianPrior):
        field, mean = "initial.mean", [float(v) for v in prior.mean]
    else:  # the mixture's mean, as Model.prior_moments takes it
        field = "initial.means"
        mean = (mixture_weights(prior.weights) @ np.asarray(prior.means, dtype=float)).tolist()
    if all(lo <= v <= hi for v, (lo, hi) in zip(mean, region, strict=True)):
        return
    where = ", ".join(f"{v:.4g}" for v in mean)
    bounds = ", ".join(f"[{lo:g}, {hi:g}]" for lo, hi in region)
    raise SpecError(field, f"the prior mean ({where}) lies outside domain.region ({bounds}), where the state "
                           "is declared to stay: move the prior into the region or widen the region")
