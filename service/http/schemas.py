"""Request and response bodies of the HTTP API (pydantic; they spell out the OpenAPI at /docs).

Numbers are strict and finite: JSON has no NaN, and the NaN/Infinity tokens Python's parser
accepts are rejected here, naming the offending entry (``increments[3][0]``).  A missing value is
JSON null: a whole row (no observation at that time) or one component of it (partly missing).
"""

from __future__ import annotations

from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field
from yauyau.solver.registry import METHODS, POLICIES
from yauyau.solver.spec import Prior

Number = Annotated[float, Field(strict=True, allow_inf_nan=False)]
Method = Literal[METHODS]  # type: ignore[valid-type]


class _Body(BaseModel):
    model_config = ConfigDict(extra="forbid", strict=True)  # "1", true and 1.0 are not a seq


Policy = Literal[POLICIES]  # type: ignore[valid-type]
Row = list[Number | None] | None
ROWS_DOC = ("one row of m numbers per time; null for a whole row: no observation then (the filter only "
            "predicts); null for one component: that component is missing (the others are used)")


class LostTrackIn(_Body):
    gated: int = Field(20, ge=0, le=10**9, description="consecutive gated rows (0: this rule off)")
    restarts: int = Field(3, ge=0, le=10**9, description="restarts within `window` rows (0: this rule off)")
    window: int = Field(100, ge=1, le=10**9, description="rows")


class SessionCreate(_Body):
    model: str = Field(min_length=1, max_length=200, description="id of a stored model (GET /v1/models)")
    prior: Prior | None = Field(None, description="prior density at t0 (default: the model's)")
    method: Method | None = Field(None, description="filter to run (default: the model spec's method)")
    on_degenerate: Policy = Field(
        "stop", description="when the density degenerates (data the model cannot follow): 'stop' keeps the "
                            "session degenerate, answering its last good estimate with the reason, until "
                            "POST /v1/sessions/{id}/reset; 'reinitialise' starts again at once from a prior "
                            "broadened around the last good estimate (the row is flagged reinitialised)")
    t0: Number = Field(0.0, description="the time of the prior (chunks with times start after it)")
    gate: Number | None = Field(
        None, ge=0, le=37, description="outlier gate in predictive standard deviations (0: off; at most 37); "
                                       "default: the model spec's [measurement] gate (6)")
    lost_track: LostTrackIn | None = Field(
        None, description="when a filter that keeps gating or restarting has lost track (then its rows are "
                          "degenerate with a reason naming the domain and the fix, until a reset); default: "
                          "20 consecutive gated rows, or 3 restarts within 100 rows")
    monitor: Number | None = Field(
        None, ge=0, le=1e15,
        description="the innovation monitor (a sustained bias of the observations against their predictions "
                    "raises `alarm` on a row): the mean number of healthy rows per false alarm, from 1e3 to "
                    "1e15 (1e9 is a good choice), or 0 (off); default: the model spec's [measurement] "
                    "monitor (off unless set)")
    smooth_lag: Any = Field(
        None, json_schema_extra={"type": "integer", "minimum": 1, "maximum": 1000},
        description="fixed-lag smoothing, in rows (1 to 1000): every chunk response then also carries "
                    "`smoothed`, the estimate of each row given the smooth_lag rows after it, for the "
                    "rows this chunk completes (row k once row k + smooth_lag has come). Methods that "
                    "smooth only: yau-yau, kalman-bucy with discrete measurements")

    model_config = ConfigDict(extra="forbid", json_schema_extra={"examples": [
        {"model": "3f9c2a...", "prior": {"kind": "gaussian", "mean": [0.5], "cov": [[1.0]]}},
        {"model": "3f9c2a...", "on_degenerate": "reinitialise", "t0": 12.5, "gate": 4.0},
        {"model": "3f9c2a...", "lost_track": {"gated": 50, "restarts": 5, "window": 500}, "monitor": 1e9}]})


class Observations(_Body):
    seq: int = Field(ge=0, le=2**53, description="chunk number: 0 for the first chunk, then +1 per chunk "
                                                 "(a reset takes a number too)")
    increments: list[Row] | None = Field(
        None, min_length=1,
        description="continuous models ([measurement] kind = continuous): observation increments "
                    "Δy_k = y(t_k) − y(t_(k−1)); " + ROWS_DOC + ". Send either increments or observations, "
                    "as the model's kind says")
    observations: list[Row] | None = Field(
        None, min_length=1,
        description="discrete models ([measurement] kind = discrete): measurements z_k = h(x(t_k)) + v_k; "
                    + ROWS_DOC)
    times: list[Number] | None = Field(
        None, min_length=1,
        description="absolute time of each row, strictly increasing and after the session's time (at it "
                    "for the first row of a session that has not stepped yet); default: one dt apart")
    quantiles: list[Number] | None = Field(
        None, min_length=1, max_length=99,
        description="also return these marginal quantiles of every state variable with each estimate "
                    "(probabilities strictly between 0 and 1, e.g. [0.05, 0.5, 0.95])")
    mode: bool = Field(False, strict=True, description="also return the mode (MAP point) with each estimate")

    model_config = ConfigDict(extra="forbid", json_schema_extra={"examples": [
        {"seq": 0, "increments": [[0.0012], [-0.0031], None, [0.0008]]},
        {"seq": 1, "increments": [[0.0009]], "quantiles": [0.05, 0.5, 0.95], "mode": True},
        {"seq": 0, "observations": [[0.93], [None], [1.12]], "times": [0.25, 0.61, 1.4]},
        {"seq": 0, "observations": [[3.1, None], None, [2.7, 0.4]], "times": [0.5, 0.75, 1.0]}]})


class Reset(_Body):
    seq: int = Field(ge=0, le=2**53, description="the session's next seq (a reset is numbered like a chunk "
                                                 "and applied exactly once)")
    prior: Prior | None = Field(None, description="start again from this prior (a spec prior)")
    from_: Literal["last", "model"] | None = Field(
        None, alias="from", description="start again from 'last': a prior broadened around the last good "
                                        "estimate (a degenerate session recovers), or 'model': the model's "
                                        "prior")

    model_config = ConfigDict(extra="forbid", json_schema_extra={"examples": [
        {"seq": 3, "from": "last"},
        {"seq": 3, "prior": {"kind": "gaussian", "mean": [0.0], "cov": [[2.0]]}}]})


class EstimateOut(BaseModel):
    step: int = Field(description="number of rows taken since the session started")
    t: float = Field(description="time of the estimate: the row's time when the chunk carries times, "
                                 "else one dt after the previous row (t0 + step·dt while every chunk was "
                                 "regular)")
    mean: list[float] | None = Field(description="conditional mean E[x(t) | y]; null when not finite")
    cov: list[list[float]] | None = Field(description="conditional covariance; null when not finite")
    mode: list[float] | None = Field(None, description="MAP point (when asked for; null when degenerate)")
    quantiles: dict[str, list[float]] | None = Field(
        None, description="per state variable, the marginal quantiles asked for, in the order asked")


class RowEstimate(EstimateOut):
    predictive_loglik: float | None = Field(
        None, description="log p(row | rows before): the row's predictive log-likelihood (low: surprising "
                          "data); null when the row had no observation, when the density is degenerate "
                          "there, and when the row was impossible under the model (-inf, gated)")
    gated: bool = Field(False, description="present, true, only when the outlier gate rejected the row (the "
                                           "step only predicted)")
    reinitialised: bool = Field(False, description="present, true, only when the filter degenerated at this "
                                                   "row and started again (on_degenerate = reinitialise)")
    degenerate: bool = Field(False, description="present, true, only when the density is degenerate here "
                                                "(the estimate repeats the last good one; on the row where a "
                                                "following ball's mean left domain.region, or its move "
                                                "failed, that row's own estimate, good on the ball, is the "
                                                "last good one)")
    center: list[float] | None = Field(None, description="([domain] follow = true only) the centre of the "
                                                         "domain ball after this row")
    recentred: bool = Field(False, description="present, true, only when the ball that follows the state "
                                               "moved after this row ([domain] follow = true)")
    alarm: bool = Field(False, description="present, true, only on the row where the innovation monitor "
                                           "raised its alarm: the observations have drifted to one side of "
                                           "their predictions (a sensor bias?)")
    monitor: float | None = Field(None, description="with `alarm`: the monitor's statistic (±1 and beyond; "
                                                    "+: observations above their predictions)")
    reason: str | None = Field(None, description="why the row is gated, re-initialised or degenerate (only "
                                                 "then)")


class EstimateFull(EstimateOut):
    loglik: float | None = Field(description="log-likelihood of the observations so far")
    degenerate: bool = Field(description="the density lost its mass (e.g. observations far outside the ball)")
    reason: str | None = None


class LostTrackOut(BaseModel):
    gated: int
    restarts: int
    window: int


class SessionOptions(BaseModel):
    on_degenerate: Policy
    t0: float = Field(description="time of the prior")
    gate: float = Field(description="the outlier gate in force, in predictive standard deviations (0: off)")
    lost_track: LostTrackOut | None = Field(None, description="the lost-track rule in force")
    monitor: float | None = Field(None, description="the innovation monitor in force: healthy rows per false "
                                                    "alarm (0: off)")
    smooth_lag: int | None = Field(None, description="fixed-lag smoothing in rows (when set)")


class SessionCreated(BaseModel):
    id: str
    model: str
    method: str
    step: int
    t: float
    estimate: EstimateFull
    options: SessionOptions

    model_config = ConfigDict(json_schema_extra={"examples": [{
        "id": "b1c2...", "model": "3f9c2a...", "method": "yau-yau", "step": 0, "t": 0.0,
        "estimate": {"step": 0, "t": 0.0, "mean": [0.5], "cov": [[1.0]], "loglik": 0.0,
                     "degenerate": False, "reason": None},
        "options": {"on_degenerate": "stop", "t0": 0.0, "gate": 6.0,
                    "lost_track": {"gated": 20, "restarts": 3, "window": 100}, "monitor": 0.0}}]})


class ChunkResult(BaseModel):
    seq: int
    step: int
    t: float
    estimates: list[RowEstimate] = Field(description="one estimate per row, in order")
    loglik: float | None
    degenerate: bool = Field(description="some row is degenerate (the session stays so until a reset, with "
                                         "on_degenerate = stop)")
    reason: str | None = Field(None, description="why: of the first degenerate row")
    gated: list[int] = Field(default_factory=list, description="rows of this chunk (0-based) that the "
                                                               "outlier gate rejected")
    reinitialised: list[int] = Field(default_factory=list, description="rows of this chunk (0-based) where "
                                                                       "the filter started again")
    alarms: list[int] = Field(default_factory=list, description="rows of this chunk (0-based) where the "
                                                                "innovation monitor raised its alarm")
    smoothed: list[EstimateOut] | None = Field(
        None, description="(smooth_lag sessions) the fixed-lag smoothed estimates this chunk completes, in "
                          "order: row k's given the rows up to k + smooth_lag (its step is row k's; the mode "
                          "and quantiles when the chunk asks for them, as its estimates); empty "
                          "after a degenerate or re-initialised row (the lag starts again from there)")
    monitor: float | None = Field(None, description="the innovation monitor's statistic after the chunk (±1: "
                                                    "an alarm; null: the monitor is off)")

    model_config = ConfigDict(json_schema_extra={"examples": [{
        "seq": 0, "step": 3, "t": 1.4, "loglik": -2.71, "degenerate": False, "reason": None,
        "gated": [1], "reinitialised": [],
        "estimates": [{"step": 1, "t": 0.25, "mean": [0.91], "cov": [[0.33]], "predictive_loglik": -1.02},
                      {"step": 2, "t": 0.61, "mean": [0.76], "cov": [[0.41]], "predictive_loglik": -187.3,
                       "gated": True, "reason": "observation gated: 19.2 predictive standard deviations "
                                                "from the prediction, beyond the gate of 6; the step only "
                                                "predicted"},
                      {"step": 3, "t": 1.4, "mean": [0.98], "cov": [[0.31]], "predictive_loglik": -1.69}]}]})


class ResetResult(BaseModel):
    seq: int
    step: int = Field(description="unchanged by a reset: the session starts again where it is")
    t: float
    estimate: EstimateFull
    note: str = Field(description="what was done")


class MonitorOut(BaseModel):
    statistic: float | None = Field(description="after the last row (±1: an alarm; null: off)")
    alarms: int = Field(description="alarms raised since the session started or was reset")


class SessionInfo(BaseModel):
    id: str
    model: str
    method: str
    step: int
    t: float
    next_seq: int = Field(description="seq the next chunk (or reset) must carry")
    estimate: EstimateFull
    options: SessionOptions
    center: list[float] | None = Field(None, description="([domain] follow = true only) the centre of the "
                                                         "domain ball now")
    lost: str | None = Field(None, description="why the filter lost track (it stays degenerate until a "
                                               "reset); null: on track")
    monitor: MonitorOut | None = Field(None, description="the innovation monitor now")


class ModelCreate(_Body):
    spec: dict[str, Any] = Field(description="the model spec, as a spec file holds it (the fields of the "
                                             "spec format, docs/models.md: name, state, drift, ...)")

    model_config = ConfigDict(extra="forbid", json_schema_extra={"examples": [
        {"spec": {"name": "ou", "state": ["x"], "drift": ["-x"], "observation": ["x"],
                  "initial": {"kind": "gaussian", "mean": [0.0], "cov": [[1.0]]},
                  "domain": {"radius": 6.0}, "discretization": {"dt": 0.01, "basis": 64}}}]})


class Job(BaseModel):
    id: str = Field(description="the model id (the content hash of the spec): the same spec, the same job")
    status: str = Field(description="queued, running, done or failed")
    progress: float | None = Field(None, description="share of the propagators solved (0 to 1)")
    position: int | None = Field(None, description="a queued job's place in the queue (1: next to start)")
    error: str | None = Field(None, description="why the job failed")
    name: str | None = None
    job: str = Field(description="this job's URL (poll it)")
    model: str = Field(description="the model's URL, once done")


class SessionSummary(BaseModel):
    id: str
    model: str
    method: str
    step: int
    t: float
    next_seq: int
    created: str = Field(description="ISO 8601, UTC")
    updated: str = Field(description="ISO 8601, UTC: the last chunk or reset (idle expiry counts from it)")


class SessionPage(BaseModel):
    sessions: list[SessionSummary]
    next: str | None = Field(description="pass as ?after= for the next page (null: this is the last)")
    idle_expiry: float | None = Field(description="seconds without a chunk after which a session is deleted "
                                                  "(null: never)")


class Forecast(BaseModel):
    id: str
    step: int = Field(description="the session's step (a forecast adds no observation)")
    t: float = Field(description="the time forecast to")
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
    follow: bool | None = Field(None, description="[domain] follow: the domain ball re-centres on the "
                                                  "posterior (a session's rows then carry its centre)")
    region: list[list[float]] | None = Field(None, description="[domain] region, one [lo, hi] per state "
                                                               "variable: where a following ball may go")
    shape: list[list[float]] | str | None = Field(None, description="[domain] shape: the covariance Σ whose "
                                                                    "ellipsoid (x − c)ᵀΣ⁻¹(x − c) < R² is "
                                                                    "the domain, or \"posterior\"")
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
