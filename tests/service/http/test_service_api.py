"""The HTTP API in-process: models, sessions, exactly-once chunks, problem+json errors.

Numbers are checked against independent truth: the exact discrete Kalman filter for the
Ornstein–Uhlenbeck example (linear, so the optimal filter is Gaussian), the Gaussian prior's
closed-form density and the normalisation ∫p = 1.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from fastapi.testclient import TestClient
from helpers import EXAMPLES
from yauyau.service.http.app import create_app
from yauyau.service.settings import Settings
from yauyau.solver.model import compile_model
from yauyau.solver.reference.kalman import DiscreteKalmanFilter
from yauyau.solver.simulate import simulate
from yauyau.solver.spec import load_spec

PROBLEM = "application/problem+json"


@pytest.fixture(scope="module")
def api(example_store, tmp_path_factory):
    store, ids = example_store
    db = tmp_path_factory.mktemp("db") / "sessions.sqlite3"
    settings = Settings(store=store, session_db=db, max_chunk_rows=500, max_body_bytes=64 * 1024)
    with TestClient(create_app(settings), raise_server_exceptions=False) as client:
        client.ids = ids
        yield client


def _session(api, name="cubic_sensor", **extra):
    r = api.post("/v1/sessions", json={"model": api.ids[name], **extra})
    assert r.status_code == 201, r.text
    return r.json()


def _problem(r, status, field=None):
    assert r.status_code == status, r.text
    assert r.headers["content-type"].startswith(PROBLEM)
    body = r.json()
    assert body["status"] == status and body["title"] and body["detail"]
    if field is not None:
        assert body.get("field") == field, body
    return body


def test_health_and_metrics(api):
    assert api.get("/livez").json() == {"status": "ok"}
    ready = api.get("/readyz")
    assert ready.status_code == 200 and ready.json()["models"] == 2
    text = api.get("/metrics").text
    assert "yauyau_http_requests_total" in text


def test_models_describe_the_stored_specs(api):
    listed = {m["id"]: m for m in api.get("/v1/models").json()}
    assert set(listed) == set(api.ids.values())
    cubic = api.get(f"/v1/models/{api.ids['cubic_sensor']}").json()
    spec = load_spec(EXAMPLES / "cubic_sensor.toml")
    assert (cubic["name"], cubic["state"], cubic["n"], cubic["m"]) == ("cubic-sensor", ["x"], 1, 1)
    assert (cubic["dt"], cubic["radius"], cubic["basis"]) == (0.01, 7.0, 128)
    assert (cubic["follow"], cubic["region"], cubic["shape"]) == (False, None, None)  # a fixed ball
    assert all(m["follow"] is False for m in listed.values())
    assert cubic["spec"]["observation"] == spec.observation
    _problem(api.get("/v1/models/0123456789abcdef0123"), 404, "model")


def test_initial_estimate_and_density_are_the_prior(api):
    created = _session(api)
    est = created["estimate"]
    assert created["step"] == 0 and created["t"] == 0.0 and est["degenerate"] is False
    # prior N(0.5, 1) restricted to |x| < 7: the truncation is below 1e-9
    assert est["mean"][0] == pytest.approx(0.5, abs=1e-4)
    assert est["cov"][0][0] == pytest.approx(1.0, abs=1e-3)
    r = api.get(f"/v1/sessions/{created['id']}/density", params={"points": "-1;0.5;2"})
    x = np.array([-1.0, 0.5, 2.0])
    exact = np.exp(-0.5 * (x - 0.5) ** 2) / math.sqrt(2 * math.pi)
    assert np.allclose(r.json()["density"], exact, rtol=2e-3, atol=1e-4)
    grid = api.get(f"/v1/sessions/{created['id']}/density", params={"grid": "-7:7:701"}).json()
    assert len(grid["points"]) == 701
    assert np.trapezoid(grid["density"], np.linspace(-7, 7, 701)) == pytest.approx(1.0, abs=1e-3)


def test_prior_override_and_bad_prior(api):
    created = _session(api, prior={"kind": "gaussian", "mean": [-1.5], "cov": [[0.25]]})
    assert created["estimate"]["mean"][0] == pytest.approx(-1.5, abs=1e-3)
    assert created["estimate"]["cov"][0][0] == pytest.approx(0.25, abs=1e-3)
    bad = api.post("/v1/sessions", json={"model": api.ids["ou"],
                                         "prior": {"kind": "gaussian", "mean": [0, 1], "cov": [[1.0]]}})
    _problem(bad, 422, "prior.mean")
    _problem(api.post("/v1/sessions", json={"model": "nope"}), 404, "model")


def _stream(api, sid, increments, chunk=40):
    means, covs = [], []
    for seq, start in enumerate(range(0, len(increments), chunk)):
        rows = [None if np.isnan(r[0]) else r.tolist() for r in increments[start:start + chunk]]
        r = api.post(f"/v1/sessions/{sid}/observations", json={"seq": seq, "increments": rows})
        assert r.status_code == 200, r.text
        body = r.json()
        assert [e["step"] for e in body["estimates"]] == list(range(start + 1, start + len(rows) + 1))
        means += [e["mean"][0] for e in body["estimates"]]
        covs += [e["cov"][0][0] for e in body["estimates"]]
    return np.array(means), np.array(covs), body


@pytest.mark.parametrize("method, tol", [("yau-yau", 2e-3), (None, 2e-2)])
def test_ou_session_matches_the_exact_kalman_filter(api, method, tol):
    """yau-yau approximates the sampled-time Kalman filter up to space error; the default method
    of a linear model is Kalman–Bucy (exact in continuous time, O(dt) from the sampled filter)."""
    model = compile_model(load_spec(EXAMPLES / "ou.toml"))
    increments = simulate(model, 200, np.random.default_rng(7)).increments
    increments[50:60] = np.nan  # a gap without observations: prediction only
    created = _session(api, "ou", **({"method": method} if method else {}))
    assert created["method"] == (method or "kalman-bucy")
    means, covs, last = _stream(api, created["id"], increments)
    kalman = DiscreteKalmanFilter(model)
    _, exact = kalman.run(kalman.initial_state(), increments)
    assert np.abs(means - [e.mean[0] for e in exact]).max() < tol
    assert np.abs(covs - [e.cov[0, 0] for e in exact]).max() < tol
    assert last["step"] == 200 and last["t"] == pytest.approx(2.0)
    assert last["loglik"] == pytest.approx(exact[-1].loglik, abs=5 * tol)


def test_chunks_are_applied_exactly_once(api):
    sid = _session(api)["id"]
    url = f"/v1/sessions/{sid}/observations"
    first = api.post(url, json={"seq": 0, "increments": [[0.01], [0.02]]})
    again = api.post(url, json={"seq": 0, "increments": [[0.01], [0.02]]})
    assert again.status_code == 200 and again.json() == first.json()
    _problem(api.post(url, json={"seq": 2, "increments": [[0.0]]}), 409)
    info = api.get(f"/v1/sessions/{sid}").json()
    assert (info["step"], info["next_seq"]) == (2, 1)
    assert info["estimate"]["mean"] == first.json()["estimates"][-1]["mean"]
    assert api.post(url, json={"seq": 1, "increments": [[0.0]]}).json()["step"] == 3
    assert api.delete(f"/v1/sessions/{sid}").status_code == 204
    _problem(api.get(f"/v1/sessions/{sid}"), 404)
    _problem(api.delete(f"/v1/sessions/{sid}"), 404)


def test_far_out_observations_give_a_gated_or_degenerate_answer_not_nan(api):
    """With the outlier gate on (the default) the rows are gated; with it off the density degenerates
    (tests/service/http/test_service_fast_path.py); either way the answer is strict JSON without NaN."""
    sid = _session(api)["id"]
    r = api.post(f"/v1/sessions/{sid}/observations", json={"seq": 0, "increments": [[1e8], [-1e8]]})
    assert r.status_code == 200
    body = json.loads(r.text)  # strict JSON: the service never writes NaN
    for est in body["estimates"]:
        assert est["mean"] is None or all(math.isfinite(v) for v in est["mean"])


@pytest.mark.parametrize("payload, status, field", [
    ('{"seq": 0, "increments": [[NaN]]}', 422, "increments[0][0]"),
    ('{"seq": 0, "increments": [[1.0], [Infinity]]}', 422, "increments[1][0]"),
    ('{"seq": 0, "increments": [[1e999]]}', 422, "increments[0][0]"),
    ('{"seq": 0, "increments": [["0.1"]]}', 422, "increments[0][0]"),
    ('{"seq": 0, "increments": [[true]]}', 422, "increments[0][0]"),
    ('{"seq": 0, "increments": [[0.1, 0.2]]}', 422, "increments[0]"),
    ('{"seq": 0, "increments": [["x", null]]}', 422, "increments[0][0]"),
    ('{"seq": 0, "increments": []}', 422, "increments"),
    ('{"seq": 0}', 422, "increments"),
    ('{"seq": 0, "observations": [[0.1]]}', 422, "observations"),
    ('{"seq": 0, "increments": [[0.1]], "observations": [[0.1]]}', 422, "observations"),
    ('{"seq": 0, "increments": [[0.1]], "times": [NaN]}', 422, "times[0]"),
    ('{"seq": 0, "increments": [[0.1]], "times": [null]}', 422, "times[0]"),
    ('{"seq": 0, "increments": [[0.1], [0.2]], "times": [0.5, 0.5]}', 422, "times[1]"),
    ('{"seq": 0, "increments": [[0.1], [0.2]], "times": [0.5]}', 422, "times"),
    ('{"seq": -1, "increments": [[0.1]]}', 422, "seq"),
    ('{"increments": [[0.1]]}', 422, "seq"),
    ('{"seq": 0, "increments": [[0.1]], "extra": 1}', 422, "extra"),
    ('{"seq": 0, "increments": [[0.1]', 400, "body"),
    ('', 400, "body"),
])
def test_bad_chunks_are_problems_naming_the_field(api, payload, status, field):
    sid = _session(api)["id"]
    r = api.post(f"/v1/sessions/{sid}/observations", content=payload,
                 headers={"content-type": "application/json"})
    _problem(r, status, field)
    assert api.get(f"/v1/sessions/{sid}").json()["next_seq"] == 0  # nothing applied


def test_size_limits(api):
    sid = _session(api)["id"]
    url = f"/v1/sessions/{sid}/observations"
    _problem(api.post(url, json={"seq": 0, "increments": [[0.0]] * 501}), 422, "increments")
    big = json.dumps({"seq": 0, "increments": [[0.001]] * 20000})
    _problem(api.post(url, content=big, headers={"content-type": "application/json"}), 413, "body")

    def chunks():  # no Content-Length: the limit applies while reading
        for _ in range(100):
            yield b" " * 1024
    _problem(api.post(url, content=chunks(), headers={"content-type": "application/json"}), 413, "body")
    _problem(api.post("/v1/sessions/nope/observations", json={"seq": 0, "increments": [[0.0]]}), 404)


def test_density_query_errors(api):
    sid = _session(api)["id"]
    url = f"/v1/sessions/{sid}/density"
    _problem(api.get(url), 422, "points")
    _problem(api.get(url, params={"points": "1,2"}), 422, "points")
    _problem(api.get(url, params={"points": "abc"}), 422, "points")
    _problem(api.get(url, params={"points": "nan"}), 422, "points")
    _problem(api.get(url, params={"grid": "0:1"}), 422, "grid")
    _problem(api.get(url, params={"grid": "0:1:1000000000"}), 422, "grid")


def test_analyze(api):
    spec = load_spec(EXAMPLES / "ou.toml").model_dump(mode="json")
    r = api.post("/v1/analyze", json=spec)
    assert r.status_code == 200, r.text
    assert isinstance(r.json(), dict) and r.json()
    _problem(api.post("/v1/analyze", json={**spec, "drift": ["x", "x"]}), 422, "drift")
    _problem(api.post("/v1/analyze", json={**spec, "drift": ["__import__('os')"]}), 422, "drift[0]")


@pytest.mark.slow
def test_analyze_takes_the_body_of_post_models(api):
    """{"spec": ...}, as POST /v1/models takes it, besides the bare spec: OU is linear, so both recommend
    the Kalman–Bucy filter (exact for it); a field at fault is named spec.<field>, as POST /v1/models does."""
    spec = load_spec(EXAMPLES / "ou.toml").model_dump(mode="json")
    wrapped, bare = api.post("/v1/analyze", json={"spec": spec}), api.post("/v1/analyze", json=spec)
    assert wrapped.status_code == bare.status_code == 200, wrapped.text
    methods = [r.json()["recommendation"]["method"] for r in (wrapped, bare)]
    assert methods == ["kalman-bucy", "kalman-bucy"]
    _problem(api.post("/v1/analyze", json={"spec": {**spec, "drift": ["x", "x"]}}), 422, "spec.drift")
    _problem(api.post("/v1/analyze", json={"spec": {**spec, "drift": ["x^3"]}}), 422, "spec.drift[0]")
    _problem(api.post("/v1/analyze", json={"spec": spec, "colour": "red"}), 422, "colour")
    _problem(api.post("/v1/analyze", json={"spec": [1, 2]}), 422, "spec")


def test_unknown_route_and_method_are_problems(api):
    _problem(api.get("/v1/nothing"), 404)
    _problem(api.put("/v1/models"), 405)


# -- quantiles and the mode on request ----------------------------------------------------------------
def test_chunk_quantiles_and_mode_on_request_match_the_normal_posterior(api):
    """OU: the Yau–Hu session's quantiles (grid inversion) are the normal quantiles of the exact
    Kalman–Bucy posterior on the same data; the mode of a normal is its mean."""
    from scipy.stats import norm
    from yauyau.solver.simulate import simulate as simulate_model

    model = compile_model(load_spec(EXAMPLES / "ou.toml"))
    rows = simulate_model(model, 40, np.random.default_rng(8)).increments.tolist()
    kb = api.post("/v1/sessions", json={"model": api.ids["ou"], "method": "kalman-bucy"}).json()["id"]
    yh = api.post("/v1/sessions", json={"model": api.ids["ou"], "method": "yau-hu"}).json()["id"]
    exact = api.post(f"/v1/sessions/{kb}/observations", json={"seq": 0, "increments": rows}).json()
    probs = [0.05, 0.5, 0.95]
    body = {"seq": 0, "increments": rows, "quantiles": probs, "mode": True}
    r = api.post(f"/v1/sessions/{yh}/observations", json=body)
    assert r.status_code == 200, r.text
    got = r.json()
    for e, k in zip(got["estimates"], exact["estimates"], strict=True):
        truth = norm.ppf(probs, loc=k["mean"][0], scale=np.sqrt(k["cov"][0][0]))
        np.testing.assert_allclose(e["quantiles"]["x"], truth, atol=1e-3)
        assert e["mode"][0] == pytest.approx(k["mean"][0], abs=1e-3)
    assert api.post(f"/v1/sessions/{yh}/observations", json=body).json() == got  # replay: stored answer
    info = api.get(f"/v1/sessions/{yh}", params={"quantiles": "0.5", "mode": "true"}).json()["estimate"]
    assert info["quantiles"]["x"][0] == pytest.approx(got["estimates"][-1]["quantiles"]["x"][1], abs=1e-9)
    plain = api.get(f"/v1/sessions/{yh}").json()["estimate"]
    assert "quantiles" not in plain and "mode" not in plain


@pytest.mark.parametrize("extra", [{"quantiles": [1.5]}, {"quantiles": []}, {"quantiles": [0.5, None]},
                                   {"mode": "yes"}])
def test_bad_summary_requests_are_422_and_apply_nothing(api, extra):
    sid = api.post("/v1/sessions", json={"model": api.ids["ou"]}).json()["id"]
    r = api.post(f"/v1/sessions/{sid}/observations", json={"seq": 0, "increments": [[0.1]], **extra})
    assert r.status_code == 422 and r.headers["content-type"].startswith("application/problem+json")
    assert api.get(f"/v1/sessions/{sid}").json()["next_seq"] == 0
    r = api.get(f"/v1/sessions/{sid}", params={"quantiles": "0,1"})
    assert r.status_code == 422 and "quantiles" in r.text
