"""Request and response bodies of the HTTP API (pydantic; they spell out the OpenAPI at /docs).

Numbers are strict and finite: JSON has no NaN, and the NaN/Infinity tokens Python's parser
accepts are rejected here, naming the offending entry (``increments[3][0]``).
"""

from __future__ import annotations

from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field
from yauyau.solver.registry import METHODS
from yauyau.solver.spec import Prior

Number = Annotated[float, Field(strict=True, allow_inf_nan=False)]
Method = Literal[METHODS]  # type: ignore[valid-type]


class _Body(BaseModel):
    model_config = ConfigDict(extra="forbid", strict=True)  # "1", true and 1.0 are not a seq


class SessionCreate(_Body):
    model: str = Field(min_length=1, max_length=200, description="id of a stored model (GET /v1/models)")
    prior: Prior | None = Field(None, description="prior density at t = 0 (default: the model's)")
    method: Method | None = Field(None, description="filter to run (default: the model spec's method)")

    model_config = ConfigDict(extra="forbid", json_schema_extra={"examples": [
        {"model": "3f9c2a...", "prior": {"kind": "gaussian", "mean": [0.5], "cov": [[1.0]]}}]})


class Observations(_Body):
    seq: int = Field(ge=0, le=2**53, description="chunk number: 0 for the first chunk, then +1 per chunk")
    increments: list[list[Number] | None] = Field(
        min_length=1,
        description="observation increments Δy_k = y(k·dt) − y((k−1)·dt), one row of m numbers per step; "
                    "null marks a step without an observation (prediction only)")
    quantiles: list[Number] | None = Field(
        None, min_length=1, max_length=99,
        description="also return these marginal quantiles of every state variable with each estimate "
                    "(probabilities strictly between 0 and 1, e.g. [0.05, 0.5, 0.95])")
    mode: bool = Field(False, strict=True, description="also return the mode (MAP point) with each estimate")

    model_config = ConfigDict(extra="forbid", json_schema_extra={"examples": [
        {"seq": 0, "increments": [[0.0012], [-0.0031], None, [0.0008]]},
        {"seq": 1, "increments": [[0.0009]], "quantiles": [0.05, 0.5, 0.95], "mode": True}]})


class EstimateOut(BaseModel):
    step: int = Field(description="number of steps taken since t = 0")
    t: float = Field(description="time step·dt")
    mean: list[float] | None = Field(description="conditional mean E[x(t) | y]; null when degenerate")
    cov: list[list[float]] | None = Field(description="conditional covariance; null when degenerate")
    mode: list[float] | None = Field(None, description="MAP point (when asked for; null when degenerate)")
    quantiles: dict[str, list[float]] | None = Field(
        None, description="per state variable, the marginal quantiles asked for, in the order asked")


class EstimateFull(EstimateOut):
    loglik: float | None = Field(description="log-likelihood of the observations so far")
    degenerate: bool = Field(description="the density lost its mass (e.g. observations far outside the ball)")
    reason: str | None = None


class SessionCreated(BaseModel):
    id: str
    model: str
    method: str
    step: int
    t: float
    estimate: EstimateFull

    model_config = ConfigDict(json_schema_extra={"examples": [{
        "id": "b1c2...", "model": "3f9c2a...", "method": "yau-yau", "step": 0, "t": 0.0,
        "estimate": {"step": 0, "t": 0.0, "mean": [0.5], "cov": [[1.0]], "loglik": 0.0,
                     "degenerate": False, "reason": None}}]})


class ChunkResult(BaseModel):
    seq: int
    step: int
    t: float
    estimates: list[EstimateOut] = Field(description="one estimate per increment row, in order")
    loglik: float | None
    degenerate: bool
    reason: str | None = None

    model_config = ConfigDict(json_schema_extra={"examples": [{
        "seq": 0, "step": 2, "t": 0.02, "loglik": 0.013, "degenerate": False, "reason": None,
        "estimates": [{"step": 1, "t": 0.01, "mean": [0.49], "cov": [[0.97]]},
                      {"step": 2, "t": 0.02, "mean": [0.47], "cov": [[0.95]]}]}]})


class SessionInfo(BaseModel):
    id: str
    model: str
    method: str
    step: int
    t: float
    next_seq: int = Field(description="seq the next chunk must carry")
    estimate: EstimateFull


class DensityOut(BaseModel):
    step: int
    t: float
    points: list[list[float]]
    density: list[float] = Field(description="normalised conditional density at each point")


class ModelSummary(BaseModel):
    id: str
    name: str | None = None
    state: list[str] | None = None
    n: int | None = None
    m: int | None = None
    dt: float | None = None
    radius: float | None = None
    basis: int | None = None
    method: str | None = Field(None, description="the filter a session runs by default (chosen at "
                                                 "precompute)")
    error: str | None = Field(None, description="set, and the rest left out, when the model file is "
                                                "unreadable")


class ModelDetail(ModelSummary):
    spec: dict[str, Any]


class Health(BaseModel):
    status: str
    models: int | None = None


class AnalyzeReport(BaseModel):
    model_config = ConfigDict(extra="allow")


class ProblemOut(BaseModel):
    """RFC 9457 problem details (``application/problem+json``)."""

    type: str = "about:blank"
    title: str
    status: int
    detail: str
    field: str | None = Field(None, description="the request field at fault")
    instance: str | None = None
