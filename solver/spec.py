"""Model specification: the filtering problem, and apart from it its discretisation.

    dx = f(x) dt + G dv,   dy = h(x) dt + dw,   E[dv dvᵀ] = Q dt,  E[dw dwᵀ] = R dt,

with x ∈ ℝⁿ (n = 1 … 6, up to 100 with method "yau-niu"; the general engine's finite elements up to 3)
and y ∈ ℝᵐ.  ``diffusion`` is a = G Q Gᵀ (n×n, symmetric positive semi-definite: zero rows for
noise-free coordinates, which the general engine discretises with ``scheme = "supg"`` and the
mesh-free methods take as they are) and ``observation_noise`` is R (m×m, SPD).

Two parts, one document.  The *problem* (:class:`ProblemSpec`: state, drift, observation, noises,
parameters, prior) is what the user knows about the system; the *discretisation*
(:class:`DiscretisationSpec`: the domain ball and the ``[discretization]`` table — dt, basis size,
mesh, element order, substeps, precision) is how the offline stage represents it.  A spec file keeps
both at its top level (unchanged format); ``ModelSpec.problem`` and ``ModelSpec.discretisation``
are the two parts, and :meth:`ModelSpec.compose` / :meth:`ModelSpec.with_discretisation` build a
spec from them (one problem, several discretisations: a finer mesh, another ball).  One schema
(pydantic) serves TOML and JSON; :func:`load_spec` turns every problem into one :class:`SpecError`
naming the field.

The tables a spec is made of (the prior, ``[measurement]``, ``[domain]``, ``[discretization]``) are
defined in solver/spec_tables.py and importable from here.
"""

from __future__ import annotations

import difflib
import json
import math
import re
import tomllib
from pathlib import Path
from typing import TYPE_CHECKING, Any, get_args

import numpy as np
from pydantic import (
    BaseModel,
    Field,
    PrivateAttr,
    ValidationError,
    field_validator,
    model_validator,
)

from .defaults import default_element, stored_discretization
from .errors import SpecError
from .expressions import RESERVED_NAMES, numeric_expression, numeric_many
from .registry import MAX_GRID_OBSERVATIONS, MAX_GRID_STATES, MAX_STATES, METHODS, QMC_ONLY, check_method  # noqa: F401
from .spec_tables import (  # noqa: F401  (the tables, also importable from here)
    FOLLOW_DISTANCE,
    FOLLOW_MASS,
    GATE_DEFAULT,
    MONITOR_DEFAULT,
    DensityPrior,
    Discretization,
    Domain,
    GaussianPrior,
    Measurement,
    MixturePrior,
    Prior,
    Strict,
    check_prior,
    check_prior_in_region,
    check_spd,
    finite_or_raise,
    singular,
)

if TYPE_CHECKING:  # types only
    from collections.abc import Callable

    Points = Callable[[np.ndarray], np.ndarray]  # as solver/model.py


_NAME = re.compile(r"^[A-Za-z][A-Za-z0-9_]{0,31}\Z")
MAX_SPEC_BYTES = 64 * 1024


PROBLEM_FIELDS = ("state", "drift", "observation", "diffusion", "observation_noise", "parameters", "initial",
                  "measurement")
DISCRETISATION_FIELDS = ("domain", "discretization")


class ProblemSpec(Strict):
    """The filtering problem: signal, observation, noises, parameters and prior (no numerics)."""

    state: list[str]
    drift: list[str]
    observation: list[str]
    diffusion: list[list[float]] | None = None
    observation_noise: list[list[float]] | None = None
    parameters: dict[str, float] = Field(default_factory=dict)
    initial: Prior
    measurement: Measurement = Field(default_factory=Measurement)


QMC_BASIS = 2  # the basis size a yau-niu spec that leaves it out is written with (yau-niu has no basis)
PRIOR_BALL_SDS = 6.0  # a yau-niu spec without [domain]: the ball of the prior's mean ± this many sd


def prior_ball(prior: Any) -> dict[str, Any] | None:
    """The ``[domain]`` of a yau-niu spec that leaves it out: centred on a gaussian prior's mean (a
    mixture's weighted mean), radius PRIOR_BALL_SDS × its largest standard deviation beyond the farthest
    component mean; None for a density prior or one that does not parse (its own error is reported)."""
    if hasattr(prior, "model_dump"):
        prior = prior.model_dump()
    try:
        kind = prior.get("kind", "gaussian")
        if kind == "gaussian":
            means, covs, weights = [prior["mean"]], [prior["cov"]], [1.0]
        elif kind == "mixture":
            means, covs, weights = prior["means"], prior["covs"], prior["weights"]
        else:
            return None
        means = np.asarray(means, float)
        weights = np.asarray(weights, float) / np.sum(weights)
        center = weights @ means
        sds = [math.sqrt(max(float(np.linalg.eigvalsh(np.asarray(c, float)).max()), 0.0)) for c in covs]
        reach = max(float(np.linalg.norm(mu - center)) + PRIOR_BALL_SDS * sd
                    for mu, sd in zip(means, sds, strict=True))
    except (AttributeError, KeyError, TypeError, ValueError, np.linalg.LinAlgError):
        return None
    if not (math.isfinite(reach) and reach > 0 and np.all(np.isfinite(center))):
        return None
    return {"radius": min(reach, 1e6), "center": center.tolist()}


class DiscretisationSpec(Strict):
    """How the offline stage represents the problem: the domain ball and the time step/resolution."""

    domain: Domain
    discretization: Discretization


class ModelSpec(Strict):
    """A problem and its discretisation, validated together (one flat document: the file format)."""

    name: str = Field(min_length=1, max_length=100)
    state: list[str] = Field(min_length=1, max_length=MAX_STATES)  # past MAX_GRID_STATES: yau-niu only

    @field_validator("name")
    @classmethod
    def _printable(cls, name: str) -> str:
        if not name.isprintable() or name != name.strip():
            raise ValueError("name must be printable text without control characters (such as a newline) "
                             "or surrounding spaces")
        return name
    drift: list[str]
    observation: list[str] = Field(min_length=1, max_length=MAX_STATES)  # past 16: yau-niu only
    diffusion: list[list[float]] | None = None
    observation_noise: list[list[float]] | None = None
    parameters: dict[str, float] = Field(default_factory=dict, max_length=64)
    initial: Prior
    measurement: Measurement = Field(default_factory=Measurement)
    domain: Domain
    discretization: Discretization
    method: str = Field("auto", description="auto or a name of solver/registry.py")
    _numeric: tuple | None = PrivateAttr(default=None)

    @field_validator("method")
    @classmethod
    def _method(cls, v: str) -> str:
        return check_method(v)

    @field_validator("name")
    @classmethod
    def _name(cls, v: str) -> str:
        if not v.strip() or any(ord(c) < 32 for c in v):
            raise ValueError("name must be printable and not blank")
        return v

    @field_validator("state")
    @classmethod
    def _state(cls, names: list[str]) -> list[str]:
        for name in names:
            if not _NAME.match(name):
                raise ValueError(f"{name!r} is not a valid variable name "
                                 "(an ASCII letter, then letters, digits, _)")
            if name in RESERVED_NAMES:
                raise ValueError(f"'{name}' is reserved (a function or constant name)")
        if len(set(names)) != len(names):
            raise ValueError("state names must be distinct")
        return names

    @field_validator("parameters")
    @classmethod
    def _parameters(cls, params: dict[str, float]) -> dict[str, float]:
        for name, value in params.items():
            if not _NAME.match(name) or name in RESERVED_NAMES:
                raise ValueError(f"{name!r} is not a valid parameter name "
                                 "(an ASCII letter, then letters, digits, _; not a function name)")
            if not math.isfinite(value):
                raise ValueError(f"parameter '{name}' must be finite")
        return params

    @model_validator(mode="before")
    @classmethod
    def _qmc_needs_no_mesh(cls, data: Any) -> Any:
        """Method "yau-niu" builds no mesh nor basis: its points cover the prior.  Left out, its
        ``[domain]`` is the ball around the prior (:func:`prior_ball`: the checks of f and h on the ball
        run there) and ``discretization.basis`` the smallest allowed, QMC_BASIS (never used); both are
        written into the canonical JSON, so the id is that of the spec stating them.  A density prior
        lives on its ``[domain]``: it still needs one.  Other methods are untouched."""
        if not isinstance(data, dict) or data.get("method") != QMC_ONLY:
            return data
        data = dict(data)
        if data.get("domain") is None:
            ball = prior_ball(data.get("initial"))
            if ball is not None:
                data["domain"] = ball
        table = data.get("discretization")
        if isinstance(table, dict) and "basis" not in table:
            data["discretization"] = {**table, "basis": QMC_BASIS}
        return data

    @model_validator(mode="after")
    def _shapes(self) -> "ModelSpec":
        n, m = len(self.state), len(self.observation)
        if n > MAX_GRID_STATES and self.method != QMC_ONLY:
            raise SpecError("state", f"{n} state variables: past {MAX_GRID_STATES}, only method = "
                                     f"\"{QMC_ONLY}\" runs (up to {MAX_STATES}); set method = \"{QMC_ONLY}\"")
        if m > MAX_GRID_OBSERVATIONS and self.method != QMC_ONLY:
            raise SpecError("observation", f"{m} observation components: past {MAX_GRID_OBSERVATIONS}, only "
                                           f"method = \"{QMC_ONLY}\" runs (up to {MAX_STATES})")
        clash = set(self.state) & set(self.parameters)
        if clash:
            raise SpecError("parameters", f"names also used as state variables: {sorted(clash)}")
        if len(self.drift) != n:
            raise SpecError("drift", f"needs {n} expressions (one per state variable), got {len(self.drift)}")
        for field, matrix, size in (("diffusion", self.diffusion, n),
                                    ("observation_noise", self.observation_noise, m)):
            if matrix is not None:
                try:
                    check_spd(matrix, size, field, semi=field == "diffusion")
                except ValueError as exc:
                    raise SpecError(field, str(exc).removeprefix(f"{field} ")) from None
        if self.domain.center is not None and len(self.domain.center) != n:
            raise SpecError("domain.center", f"needs {n} coordinates, got {len(self.domain.center)}")
        if self.domain.center is not None:
            finite_or_raise(self.domain.center, "domain.center")
        if self.discretization.element == "bubble" and (n == 1 or self.discretization.order != 2):
            raise SpecError("discretization.element", "bubble (P2 plus bubbles) is the element of order 2 on "
                                                      "triangles and tetrahedra: it needs 2 or 3 state "
                                                      "variables and order = 2")
        self._check_scheme(n)
        if self.domain.region is not None and len(self.domain.region) != n:
            raise SpecError("domain.region", f"needs one [lo, hi] pair per state variable ({n}), "
                                             f"got {len(self.domain.region)}")
        self._check_shape(n)
        check_prior(self.initial, n)
        check_prior_in_region(self.initial, self.domain.region)
        return self

    def _check_shape(self, n: int) -> None:
        if self.domain.shape is None:
            return
        if self.domain.region is not None:
            raise SpecError("domain.shape", "an atlas (domain.region) runs on round balls only: leave shape "
                                            "out or the region")
        if self.domain.shape == "posterior":  # solved from the model (Model.shape): needs it linear
            return
        try:
            check_spd(self.domain.shape, n, "domain.shape")
        except ValueError as exc:
            raise SpecError("domain.shape", str(exc).removeprefix("domain.shape ") + " (the covariance whose "
                            "ellipsoid, radius standard deviations wide, is the domain), or "
                            "\"posterior\"") from None

    def _check_scheme(self, n: int) -> None:
        if self.scheme() != "supg":
            return
        chosen = "" if self.discretization.scheme else (
            "a diffusion that is only positive semi-definite is discretised with scheme = \"supg\"; ")
        if n == 1:
            raise SpecError("discretization.scheme", "supg is built for 2-D and 3-D balls; in 1-D use "
                                                     "scheme = \"galerkin\"")
        if self.discretization.element == "bubble":
            raise SpecError("discretization.element", f"{chosen}supg is built on the P1 element: use "
                                                      "element = \"lagrange\" (or scheme = \"galerkin\", "
                                                      "measured to ring on such models: "
                                                      "bench/results/psd.md)")

    def scheme(self) -> str:
        """``[discretization] scheme``, or where left out "supg" for a diffusion that is only positive
        semi-definite (hypoelliptic) and "galerkin" otherwise."""
        if self.discretization.scheme is not None:
            return self.discretization.scheme
        return "supg" if singular(self.diffusion_matrix()) else "galerkin"

    def element(self) -> str:
        """``[discretization] element``, or where left out the one measured for the dimension
        (solver/defaults.py)."""
        if self.discretization.element is not None:
            return self.discretization.element
        return default_element(self.n, self.discretization.order, self.scheme(), self.discretization.mesh)

    # -- the two parts -------------------------------------------------------------------
    @property
    def problem(self) -> ProblemSpec:
        return ProblemSpec.model_validate({k: getattr(self, k) for k in PROBLEM_FIELDS})

    @property
    def discretisation(self) -> DiscretisationSpec:
        return DiscretisationSpec(domain=self.domain, discretization=self.discretization)

    @classmethod
    def compose(cls, name: str, problem: ProblemSpec | dict, discretisation: DiscretisationSpec | dict,
                method: str = "auto") -> "ModelSpec":
        """The spec of ``problem`` discretised by ``discretisation`` (validated as a whole)."""
        doc = {"name": name, "method": method}
        for part in (problem, discretisation):
            doc.update(part.model_dump(mode="json") if isinstance(part, BaseModel) else dict(part))
        return spec_from_dict(doc)

    def with_discretisation(self, discretisation: DiscretisationSpec | dict) -> "ModelSpec":
        """The same problem on another discretisation (another ball, dt or resolution)."""
        return ModelSpec.compose(self.name, self.problem, discretisation, self.method)

    # -- derived quantities ---------------------------------------------------------
    @property
    def n(self) -> int:
        return len(self.state)

    @property
    def m(self) -> int:
        return len(self.observation)

    def diffusion_matrix(self) -> np.ndarray:
        return np.eye(self.n) if self.diffusion is None else np.asarray(self.diffusion, dtype=float)

    def noise_matrix(self) -> np.ndarray:
        return np.eye(self.m) if self.observation_noise is None else np.asarray(self.observation_noise, float)

    def center(self) -> np.ndarray:
        return np.zeros(self.n) if self.domain.center is None else np.asarray(self.domain.center, float)

    def numeric(self) -> tuple[Points, Points, Points | None]:
        """f, h and the density prior (or None) as numpy functions of points (P, n), built once from the
        checked expressions (SymPy-free) and checked finite on the domain ball; SpecError names the
        expression at fault."""
        if self._numeric is None:
            self._numeric = _numeric_functions(self)
        return self._numeric

    def canonical_json(self) -> str:
        """Deterministic JSON of the spec (the input of the model's content hash).  A default
        ``[measurement]`` table is left out, so a spec written before it existed keeps its id."""
        data = self.model_dump(mode="json")
        if self.measurement == Measurement():
            del data["measurement"]
        elif self.measurement.monitor == MONITOR_DEFAULT:  # added later: ids of specs from before it stay
            del data["measurement"]["monitor"]
        data["domain"] = self.domain.stored()
        stored_discretization(self, data["discretization"])  # the defaults by dimension, written out
        if self.discretization.scheme is None:  # chosen from the diffusion: ids from before it stay
            del data["discretization"]["scheme"]
        return json.dumps(data, sort_keys=True, separators=(",", ":"))


def _numeric_functions(spec: ModelSpec) -> tuple[Points, Points, Points | None]:
    states = {name: i for i, name in enumerate(spec.state)}
    params = dict(spec.parameters)
    f = numeric_many([numeric_expression(e, states, params, f"drift[{i}]") for i, e in enumerate(spec.drift)])
    h = numeric_many([numeric_expression(e, states, params, f"observation[{i}]")
                      for i, e in enumerate(spec.observation)])
    prior = None
    if isinstance(spec.initial, DensityPrior):
        prior = numeric_expression(spec.initial.expression, states, params, "initial.expression")
    _check_finite_on_ball(spec, f, h, prior)
    if spec.domain.shape == "posterior":
        _check_straight(spec, f, h)
    return f, h, prior


POSTERIOR_NEEDS_LINEAR = ("domain.shape = \"posterior\" is the steady-state Kalman-Bucy covariance of a "
                          "linear model; give the covariance you expect the posterior to have instead, e.g. "
                          "shape = [[...], ...]")


def _check_straight(spec: ModelSpec, f, h) -> None:
    """``shape = "posterior"`` needs f and h affine.  SymPy decides it when the model is built
    (Model.steady_posterior_covariance); this SymPy-free test refuses at once what is plainly curved,
    so a service answers 422 instead of a failed job: at 64 points of the ball, the second difference
    g(x + d) + g(x − d) − 2g(x) of an affine g is zero up to rounding, so one far above it (1e-8 of
    the values) shows a curve.  A curve it misses is still refused by SymPy."""
    rng = np.random.default_rng(1)
    n, radius = spec.n, spec.domain.radius
    X = spec.center() + radius * rng.uniform(-0.5, 0.5, size=(64, n))
    step = 0.25 * radius * rng.normal(size=(64, n))
    for which, g in (("drift", f), ("observation", h)):
        with np.errstate(all="ignore"):
            at, ahead, behind = (np.asarray(g(points), dtype=float) for points in (X, X + step, X - step))
            curve = np.abs(ahead + behind - 2.0 * at)
            scale = np.abs(ahead) + np.abs(behind) + 2.0 * np.abs(at) + 1.0
        bent = np.isfinite(curve) & np.isfinite(scale) & (curve > 1e-8 * scale)
        if bent.any():
            row, column = np.argwhere(bent)[0]
            where = ", ".join(f"{name} = {v:.3g}" for name, v in zip(spec.state, X[row], strict=True))
            raise SpecError("domain.shape", f"the {which} is not affine ({which}[{column}] curves near "
                                            f"{where}): {POSTERIOR_NEEDS_LINEAR}")


def _check_finite_on_ball(spec: ModelSpec, f, h, prior) -> None:
    """Reject models whose f, h or prior are not finite on the ball (e.g. log(x) at 0): 256 random
    points of the ball and its centre."""
    rng = np.random.default_rng(0)
    n = spec.n
    direction = rng.normal(size=(256, n))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    radii = spec.domain.radius * rng.uniform(0, 1, size=(256, 1)) ** (1.0 / n)
    offsets = direction * radii
    if isinstance(spec.domain.shape, list):  # the ellipsoid: the ball mapped by its Cholesky factor
        offsets = offsets @ np.linalg.cholesky(np.asarray(spec.domain.shape, float)).T
    X = np.vstack([spec.center() + offsets, spec.center()[None, :]])
    for field_name, values in (("drift", f(X)), ("observation", h(X))):
        finite = np.isfinite(values)
        if not finite.all():
            row, column = np.argwhere(~finite)[0]
            where = ", ".join(f"{name} = {v:.3g}" for name, v in zip(spec.state, X[row], strict=True))
            raise SpecError(f"{field_name}[{column}]",
                            f"is not finite at {where} in the domain ball (a singularity such as log(x) at "
                            "0, or a value beyond the floating-point range of about 1e308)")
    _check_energy_on_ball(spec, h(X), X)
    if prior is not None:
        values = prior(X)
        if not np.all(np.isfinite(values)) or np.any(values < 0) or not np.any(values > 0):
            raise SpecError("initial.expression",
                            "prior density must be finite, non-negative and not identically zero on the ball")


def _check_energy_on_ball(spec: ModelSpec, values: np.ndarray, X: np.ndarray) -> None:
    """h^T R^-1 h, which every update of every filter uses (exp(h^T R^-1 dy - h^T R^-1 h dt / 2)), must be
    finite where h is: exp(exp(x)) on radius 6 is 3.7e175, its square overflows (the offline stage then
    failed with "Factor is exactly singular")."""
    values = np.asarray(values, dtype=float).reshape(len(X), -1)
    with np.errstate(all="ignore"):
        energy = np.einsum("pi,ij,pj->p", values, np.linalg.inv(spec.noise_matrix()), values)
    bad = ~np.isfinite(energy)
    if bad.any():
        row = int(np.argmax(bad))
        column = int(np.argmax(np.abs(values[row])))
        where = ", ".join(f"{name} = {v:.3g}" for name, v in zip(spec.state, X[row], strict=True))
        raise SpecError(f"observation[{column}]",
                        f"is {values[row, column]:.3g} at {where} in the domain ball: h^T R^-1 h, which "
                        "every update uses, overflows the floating-point range (about 1e308); shrink "
                        "domain.radius to where the sensor stays below about 1e154, or rescale the "
                        "observation")


def _field_path(loc: tuple[Any, ...]) -> str:
    path = ""
    for part in loc:
        if isinstance(part, int):
            path += f"[{part}]"
        elif part in ("gaussian", "mixture", "density"):
            continue  # discriminator tag pydantic inserts
        else:
            path += f".{part}" if path else str(part)
    return path or "spec"


_PRIOR_KINDS = {"gaussian": GaussianPrior, "mixture": MixturePrior, "density": DensityPrior}


def _table_keys(loc: tuple[Any, ...]) -> list[str]:
    """The keys the table holding ``loc``'s last part accepts (a model's fields; a prior's by its kind)."""
    models: list[type[BaseModel]] = [ModelSpec]
    for part in loc[:-1]:
        if isinstance(part, int):
            continue
        if part in _PRIOR_KINDS:  # the tag pydantic inserts for the prior's kind
            models = [_PRIOR_KINDS[part]]
            continue
        field = next((m.model_fields[part] for m in models if part in m.model_fields), None)
        if field is None:
            return []
        models = [t for t in _classes(field.annotation) if issubclass(t, BaseModel)]
    return sorted({key for m in models for key in m.model_fields})


def _classes(annotation: Any) -> list[type]:
    if isinstance(annotation, type):
        return [annotation]
    return [t for arg in get_args(annotation) for t in _classes(arg)]


def _unknown_key(loc: tuple[Any, ...]) -> str:
    """An unknown key's message: the nearest accepted key, if one is close, and the accepted keys."""
    key, allowed = str(loc[-1]), _table_keys(loc)
    if not allowed:
        return f"unknown key {key!r}"
    close = difflib.get_close_matches(key, allowed, n=1, cutoff=0.6) or [
        a for a in allowed if len(a) >= 3 and (key.lower().startswith(a) or a.startswith(key.lower()))][:1]
    hint = f"did you mean {close[0]!r}? " if close else ""
    return f"unknown key {key!r} ({hint}this table accepts {', '.join(allowed)})"


def spec_from_dict(data: Any) -> ModelSpec:
    """Validate a parsed document; every failure becomes one SpecError naming the field."""
    if not isinstance(data, dict):
        raise SpecError("spec", "must be a table/object")
    try:
        spec = ModelSpec.model_validate(data)
    except ValidationError as exc:
        errors = exc.errors()
        # a misspelt key first: the "Field required" pydantic also reports is its consequence
        err = next((e for e in errors if e["type"] == "extra_forbidden"), errors[0])
        ctx_error = (err.get("ctx") or {}).get("error")
        if isinstance(ctx_error, SpecError):
            raise ctx_error from None
        msg = err["msg"].removeprefix("Value error, ")
        if err["type"] == "extra_forbidden":
            msg = _unknown_key(tuple(err["loc"]))
        raise SpecError(_field_path(tuple(err["loc"])), msg) from None
    spec.numeric()  # the expressions, checked (safely) and finite on the ball; kept for compile_model
    return spec


def parse_spec_text(text: str, fmt: str) -> ModelSpec:
    """Parse TOML or JSON text (``fmt`` is 'toml' or 'json')."""
    if len(text.encode("utf-8", "replace")) > MAX_SPEC_BYTES:
        raise SpecError("spec", f"larger than {MAX_SPEC_BYTES} bytes")
    try:
        data = tomllib.loads(text) if fmt == "toml" else json.loads(text)
    except (tomllib.TOMLDecodeError, json.JSONDecodeError, RecursionError) as exc:
        raise SpecError("spec", f"not valid {fmt.upper()}: {exc}") from None
    return spec_from_dict(data)


def load_spec(path: str | Path) -> ModelSpec:
    """Read a spec file (.toml or .json; anything else is read as TOML)."""
    path = Path(path)
    fmt = "json" if path.suffix.lower() == ".json" else "toml"
    return parse_spec_text(read_spec_text(path), fmt)


def read_spec_text(path: str | Path) -> str:
    """The text of a spec file, reading at most MAX_SPEC_BYTES + 1 bytes: a larger file, or an endless
    stream (/dev/zero, a pipe), is refused after that many bytes instead of being read whole."""
    try:
        with open(path, "rb") as handle:
            data = handle.read(MAX_SPEC_BYTES + 1)
    except OSError as exc:
        raise SpecError("spec", f"cannot read {path}: {exc}") from None
    if len(data) > MAX_SPEC_BYTES:
        raise SpecError("spec", f"{path} is larger than {MAX_SPEC_BYTES} bytes, the most a spec may hold "
                                "(a spec is a short TOML or JSON file)")
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise SpecError("spec", f"cannot read {path}: {exc}") from None
