"""Real sensor streams over HTTP: discrete measurements at irregular times, partly missing rows, the
outlier gate, per-session options and recovery (reset, on_degenerate = reinitialise).

Truth.  The Ornstein–Uhlenbeck example (examples/ou.toml: dx = −θx dt + dv, θ = 0.5, a = 1; prior
N(1, 0.5)) observed by discrete sensors z = Hx + v, v ~ N(0, R), is linear and Gaussian: the optimal
filter is the Kalman filter at the observation times, written out here (:func:`kalman`: the exact OU
transition e^{−θτ}, Q_τ = a(1 − e^{−2θτ})/(2θ), a missing component marginalised by using only the
observed rows of H and R, a gated row only predicting).  The HTTP answers must also equal (to 1e-12)
the Python engine run on the same rows and times (``yauyau.open_filter(...).run``): the service adds
nothing to the numbers.  Sessions are real (SQLite files; a real ``yauyau serve`` process is
killed and restarted for the options).
"""

from __future__ import annotations

import json
import math

import httpx
import numpy as np
import pytest
from fastapi.testclient import TestClient
from helpers import EXAMPLES
from helpers.server import Server
from yauyau.service.http.app import create_app
from yauyau.service.settings import Settings
from yauyau.solver.spec import load_spec, spec_from_dict

import yauyau

PROBLEM = "application/problem+json"
THETA, A, M0, P0 = 0.5, 1.0, 1.0, 0.5  # examples/ou.toml
R_TWO = np.array([[1.0, 0.3], [0.3, 0.5]])  # two correlated sensors of the same x


def _ou_variant(name: str, **changes) -> dict:
    doc = load_spec(EXAMPLES / "ou.toml").model_dump(mode="json")
    doc.update(name=name, method="yau-yau", **changes)
    return doc


SPECS = {
    "ou_discrete": _ou_variant("ou-discrete", measurement={"kind": "discrete"}),
    "two_sensors": _ou_variant("ou-two-sensors", observation=["x", "x"], observation_noise=R_TWO.tolist(),
                               measurement={"kind": "discrete"}),
}


def kalman(times, rows, H, R, m=M0, P=P0, t=0.0, skip=()):
    """The exact filter of the OU state observed at ``times`` by z = Hx + v (NaN: a missing component,
    a row of NaN: no observation; rows in ``skip`` only predict): [(mean, variance, predictive
    log-likelihood or None)] per row."""
    H, R = np.asarray(H, float), np.asarray(R, float)
    out = []
    for k, (tk, z) in enumerate(zip(times, np.asarray(rows, float), strict=True)):
        tau, t = tk - t, tk
        F = math.exp(-THETA * tau)
        m, P = F * m, F * F * P + A * (1 - math.exp(-2 * THETA * tau)) / (2 * THETA)
        seen = ~np.isnan(z)
        pll = None
        if seen.any() and k not in skip:
            h, Ro = H[seen], R[np.ix_(seen, seen)]
            S = P * np.outer(h, h) + Ro
            v = z[seen] - h * m
            S_inv = np.linalg.inv(S)
            pll = float(-0.5 * v @ S_inv @ v - 0.5 * np.linalg.slogdet(2 * np.pi * S)[1])
            gain = P * h @ S_inv
            m, P = m + gain @ v, P - gain @ h * P
        out.append((m, P, pll))
    return out


@pytest.fixture(scope="module")
def models(tmp_path_factory):
    store = tmp_path_factory.mktemp("measurement-store")
    ids = {name: yauyau.precompute(spec_from_dict(doc), store) for name, doc in SPECS.items()}
    ids.update({name: yauyau.precompute(EXAMPLES / f"{name}.toml", store) for name in ("cubic_sensor", "ou")})
    return store, ids


@pytest.fixture(scope="module")
def api(models, tmp_path_factory):
    store, ids = models
    db = tmp_path_factory.mktemp("measurement-db") / "sessions.sqlite3"
    app = create_app(Settings(store=store, session_db=db))
    with TestClient(app, raise_server_exceptions=False) as client:
        client.ids, client.store = ids, store
        yield client


def _session(api, name, **options) -> dict:
    r = api.post("/v1/sessions", json={"model": api.ids[name], **options})
    assert r.status_code == 201, r.text
    return r.json()


def _rows(array) -> list:
    """Rows as JSON: null for a missing row, null for a missing component."""
    out = []
    for row in np.asarray(array, float):
        out.append(None if np.isnan(row).all() else [None if np.isnan(v) else float(v) for v in row])
    return out


def _post(api, sid, seq, field="observations", rows=None, times=None, **extra) -> dict:
    body = {"seq": seq, field: _rows(rows), **extra}
    if times is not None:
        body["times"] = [float(t) for t in times]
    r = api.post(f"/v1/sessions/{sid}/observations", json=body)
    assert r.status_code == 200, r.text
    return json.loads(r.content, parse_constant=lambda c: pytest.fail(f"{c} in a response"))


def _problem(r, status, field=None) -> dict:
    assert r.status_code == status, r.text
    assert r.headers["content-type"].startswith(PROBLEM)
    body = r.json()
    assert body["status"] == status and body["detail"]
    if field is not None:
        assert body.get("field") == field, body
    return body


def _stream(api, sid, rows, times, chunk=20, field="observations", seq0=0) -> list[dict]:
    estimates = []
    for seq, start in enumerate(range(0, len(rows), chunk), start=seq0):
        body = _post(api, sid, seq, field, rows[start:start + chunk],
                     None if times is None else times[start:start + chunk])
        estimates += body["estimates"]
    return estimates


def _random_times(rng, K, low=0.02, high=0.6, start=0.0):
    return start + np.cumsum(rng.uniform(low, high, K))


# -- 1. discrete measurements at random times -----------------------------------------------------
@pytest.mark.slow
def test_discrete_measurements_at_random_times_match_the_engine_and_the_exact_kalman_filter(api):
    rng = np.random.default_rng(5)
    K = 60
    times = _random_times(rng, K)
    rows = yauyau.simulate(spec_from_dict(SPECS["ou_discrete"]), K, seed=11, times=times).rows
    rows[[7, 20, 41]] = np.nan  # times without an observation: prediction only
    created = _session(api, "ou_discrete")
    assert created["method"] == "yau-yau" and created["options"] == {"on_degenerate": "stop", "t0": 0.0,
                                                                     "gate": 6.0}
    got = _stream(api, created["id"], rows, times)
    assert [e["step"] for e in got] == list(range(1, K + 1))
    assert [e["t"] for e in got] == times.tolist()  # each estimate at its row's time, exactly

    # the Python engine on the same chunks (the service adds nothing to the numbers) ...
    flt = yauyau.open_filter(api.store, api.ids["ou_discrete"])
    parts = [flt.run(rows[s:s + 20], times[s:s + 20]) for s in range(0, K, 20)]
    mean, var = np.array([e["mean"][0] for e in got]), np.array([e["cov"][0][0] for e in got])
    pll = np.array([np.nan if e["predictive_loglik"] is None else e["predictive_loglik"] for e in got])
    assert np.abs(mean - np.concatenate([p.mean[:, 0] for p in parts])).max() <= 1e-12
    assert np.abs(var - np.concatenate([p.cov[:, 0, 0] for p in parts])).max() <= 1e-12
    engine_pll = np.concatenate([p.predictive_loglik for p in parts])
    np.testing.assert_array_equal(np.isnan(pll), np.isnan(engine_pll))
    assert np.nanmax(np.abs(pll - engine_pll)) <= 1e-12
    # ... and in one run (the engine's chunked products round differently: ~3e-12 measured)
    whole = yauyau.open_filter(api.store, api.ids["ou_discrete"]).run(rows, times)
    assert np.abs(mean - whole.mean[:, 0]).max() <= 1e-10 and np.abs(var - whole.cov[:, 0, 0]).max() <= 1e-10

    exact = kalman(times, rows, [1.0], [[1.0]])
    assert np.abs(mean - [e[0] for e in exact]).max() < 1e-3
    assert np.abs(var / [e[1] for e in exact] - 1).max() < 0.01
    missing = [i for i, e in enumerate(exact) if e[2] is None]
    assert np.flatnonzero(np.isnan(pll)).tolist() == missing == [7, 20, 41]
    assert max(abs(p - e[2]) for p, e in zip(pll, exact, strict=True) if e[2] is not None) < 1e-3
    info = api.get(f"/v1/sessions/{created['id']}").json()
    assert (info["step"], info["t"], info["next_seq"]) == (K, times[-1], 3)
    assert info["estimate"]["loglik"] == pytest.approx(sum(e[2] for e in exact if e[2] is not None), abs=1e-3)


def test_partly_missing_components_are_marginalised(api):
    """Two correlated sensors of one state, 30% of the components null (some rows entirely): each
    row uses its observed components only (H_o, R_oo), as the exact filter does."""
    rng = np.random.default_rng(8)
    K = 50
    times = _random_times(rng, K)
    rows = yauyau.simulate(spec_from_dict(SPECS["two_sensors"]), K, seed=13, times=times).rows
    rows[rng.uniform(size=rows.shape) < 0.3] = np.nan
    partial = np.isnan(rows).any(axis=1) & ~np.isnan(rows).all(axis=1)
    assert partial.sum() >= 10 and np.isnan(rows).all(axis=1).any()
    sid = _session(api, "two_sensors")["id"]
    got = _stream(api, sid, rows, times, chunk=25)
    exact = kalman(times, rows, [1.0, 1.0], R_TWO)
    mean, var = np.array([e["mean"][0] for e in got]), np.array([e["cov"][0][0] for e in got])
    assert np.abs(mean - [e[0] for e in exact]).max() < 1e-3
    assert np.abs(var / [e[1] for e in exact] - 1).max() < 0.01
    for e, x in zip(got, exact, strict=True):
        assert (e["predictive_loglik"] is None) == (x[2] is None)
        if x[2] is not None:
            assert e["predictive_loglik"] == pytest.approx(x[2], abs=1e-3)
    # a one-component model: [[null]] is a row without an observation
    sid = _session(api, "ou_discrete")["id"]
    body = _post(api, sid, 0, rows=[[np.nan], [0.4]], times=[0.5, 1.0])
    assert body["estimates"][0]["predictive_loglik"] is None and body["estimates"][1]["predictive_loglik"]
    exact = kalman([0.5, 1.0], [[np.nan], [0.4]], [1.0], [[1.0]])
    assert [e["mean"][0] for e in body["estimates"]] == pytest.approx([e[0] for e in exact], abs=1e-3)


def test_a_1000_sigma_outlier_is_gated_and_the_session_stays_healthy(api):
    rng = np.random.default_rng(21)
    K, k = 40, 25
    times = _random_times(rng, K)
    rows = yauyau.simulate(spec_from_dict(SPECS["ou_discrete"]), K, seed=22, times=times).rows
    m, P, _ = kalman(times[:k + 1], np.vstack([rows[:k], [[np.nan]]]), [1.0], [[1.0]])[-1]  # predicted at k
    rows[k, 0] = m + 1000 * math.sqrt(P + 1.0)  # 1000 predictive standard deviations away
    sid = _session(api, "ou_discrete")["id"]
    first = _post(api, sid, 0, rows=rows[:30], times=times[:30])
    assert first["gated"] == [k] and first["degenerate"] is False and first["reason"] is None
    row = first["estimates"][k]
    assert row["gated"] is True and "gated" in row["reason"] and "beyond the gate of 6" in row["reason"]
    assert row["predictive_loglik"] < -1e5  # the Gaussian predictive density at 1000 sd: about −5e5
    assert all("gated" not in e and "reason" not in e for i, e in enumerate(first["estimates"]) if i != k)
    second = _post(api, sid, 1, rows=rows[30:], times=times[30:])
    assert second["gated"] == [] and second["degenerate"] is False
    got = first["estimates"] + second["estimates"]
    exact = kalman(times, rows, [1.0], [[1.0]], skip={k})  # the gated row only predicts
    assert np.abs(np.array([e["mean"][0] for e in got]) - [e[0] for e in exact]).max() < 1e-3
    assert np.abs(np.array([e["cov"][0][0] for e in got]) / [e[1] for e in exact] - 1).max() < 0.01
    assert api.get(f"/v1/sessions/{sid}").json()["estimate"]["degenerate"] is False


# -- 2. bad input: 422 naming the row and field, nothing applied ----------------------------------
BAD_DISCRETE = [
    ('{"seq": 1, "observations": [[0.1], [0.2], [0.3]], "times": [5.0, 5.5, 5.5]}', "times[2]"),
    ('{"seq": 1, "observations": [[0.1], [0.2]], "times": [5.0, 4.0]}', "times[1]"),
    ('{"seq": 1, "observations": [[0.1]], "times": [1.0]}', "times[0]"),  # not after the session's time
    ('{"seq": 1, "observations": [[0.1], [0.2]], "times": [5.0, NaN]}', "times[1]"),
    ('{"seq": 1, "observations": [[0.1], [0.2]], "times": [5.0, Infinity]}', "times[1]"),
    ('{"seq": 1, "observations": [[0.1], [0.2]], "times": [5.0, null]}', "times[1]"),
    ('{"seq": 1, "observations": [[0.1], [0.2]], "times": [5.0, "6"]}', "times[1]"),
    ('{"seq": 1, "observations": [[0.1], [0.2]], "times": [5.0]}', "times"),  # a time missing
    ('{"seq": 1, "observations": [[0.1], [0.2, 0.3]], "times": [5.0, 6.0]}', "observations[1]"),
    ('{"seq": 1, "observations": [[0.1], [Infinity]], "times": [5.0, 6.0]}', "observations[1][0]"),
    ('{"seq": 1, "observations": [[0.1], [NaN]]}', "observations[1][0]"),
    ('{"seq": 1, "increments": [[0.1]], "times": [5.0]}', "increments"),  # the wrong kind of rows
    ('{"seq": 1, "increments": [[0.1]], "observations": [[0.1]]}', "increments"),
    ('{"seq": 1, "times": [5.0]}', "observations"),
    ('{"seq": 1, "observations": [], "times": []}', "observations"),
]


@pytest.mark.parametrize("payload, field", BAD_DISCRETE)
def test_bad_chunks_are_422_naming_the_row_and_field_and_apply_nothing(api, payload, field):
    sid = _session(api, "ou_discrete")["id"]
    _post(api, sid, 0, rows=[[0.8], [0.9]], times=[1.0, 2.0])
    before = api.get(f"/v1/sessions/{sid}").json()
    body = _problem(api.post(f"/v1/sessions/{sid}/observations", content=payload,
                             headers={"content-type": "application/json"}), 422, field)
    if field == "increments" and "observations" not in payload:
        assert '"observations"' in body["detail"]  # the fix: which field this model takes
    assert api.get(f"/v1/sessions/{sid}").json() == before  # next_seq, step, t and estimate unchanged
    assert _post(api, sid, 1, rows=[[0.7]], times=[5.0])["step"] == 3  # and the seq is still free


def test_rows_of_the_wrong_kind_or_form_for_the_model_or_method(api):
    cubic = _session(api, "cubic_sensor")["id"]
    body = _problem(api.post(f"/v1/sessions/{cubic}/observations", json={"seq": 0, "observations": [[0.1]]}),
                    422, "observations")
    assert '"increments"' in body["detail"]
    # an exact filter takes irregular times, or says it cannot (its error passed through: 422 naming
    # the field, nothing applied); never anything else
    kb = _session(api, "ou", method="kalman-bucy")["id"]
    r = api.post(f"/v1/sessions/{kb}/observations", json={"seq": 0, "increments": [[0.01]], "times": [0.5]})
    if r.status_code == 200:
        assert r.json()["estimates"][0]["t"] == 0.5
    else:
        assert _problem(r, 422)["field"].startswith("times")
        assert api.get(f"/v1/sessions/{kb}").json()["next_seq"] == 0
    # a regular chunk of a continuous model is unchanged by all this
    kb = _session(api, "ou", method="kalman-bucy")["id"]
    assert _post(api, kb, 0, "increments", [[0.01], [np.nan]])["step"] == 2


def test_a_resent_seq_must_carry_the_same_rows_times_and_kind(api):
    sid = _session(api, "ou_discrete")["id"]
    url = f"/v1/sessions/{sid}/observations"
    body = {"seq": 0, "observations": [[0.8], None, [1.1, ]], "times": [0.5, 0.7, 1.25]}
    first = api.post(url, json=body)
    assert first.status_code == 200 and api.post(url, json=body).content == first.content
    for other in ({**body, "times": [0.5, 0.7, 1.5]}, {**body, "observations": [[0.8], [0.9], [1.1]]},
                  {"seq": 0, "observations": body["observations"]}):
        _problem(api.post(url, json=other), 409, "seq")
    assert api.get(f"/v1/sessions/{sid}").json()["next_seq"] == 1


# -- 3. options, reset, re-initialisation -----------------------------------------------------------
def test_session_options_are_checked_and_shown(api):
    created = _session(api, "ou_discrete", on_degenerate="reinitialise", t0=2.5, gate=3.0)
    assert created["options"] == {"on_degenerate": "reinitialise", "t0": 2.5, "gate": 3.0}
    assert created["t"] == 2.5 and created["estimate"]["t"] == 2.5
    info = api.get(f"/v1/sessions/{created['id']}").json()
    assert info["options"] == created["options"] and info["t"] == 2.5
    for extra, field in (({"on_degenerate": "retry"}, "on_degenerate"), ({"gate": -1}, "gate"),
                         ({"gate": "6"}, "gate"), ({"t0": None}, "t0"), ({"t0": "0"}, "t0")):
        _problem(api.post("/v1/sessions", json={"model": api.ids["ou_discrete"], **extra}), 422, field)
    r = api.post("/v1/sessions", content=f'{{"model": "{api.ids["ou_discrete"]}", "t0": NaN}}',
                 headers={"content-type": "application/json"})
    _problem(r, 422, "t0")
    # rows start at t0: the first may be at t0 itself (a measurement of the prior's time), regular rows
    # one dt on
    body = _post(api, created["id"], 0, rows=[[0.9], [1.0]], times=[2.5, 2.75])
    assert [e["t"] for e in body["estimates"]] == [2.5, 2.75]
    m, P, _ = kalman([0.0, 0.25], [[0.9], [1.0]], [1.0], [[1.0]])[-1]
    assert body["estimates"][-1]["mean"][0] == pytest.approx(m, abs=1e-3)
    regular = _session(api, "ou_discrete", t0=2.5)["id"]
    regular_times = [e["t"] for e in _post(api, regular, 0, rows=[[0.9], [1.0]])["estimates"]]
    assert regular_times == pytest.approx([2.51, 2.52], abs=1e-12)


def test_reset_recovers_a_degenerate_session_and_its_replay_is_the_same_bytes(api):
    """Cubic sensor, gate off: one increment of 1e5 makes the density degenerate; with the default
    policy it stays so (its last good estimate, flagged) until POST /reset from the last estimate;
    the session then tracks the true state again."""
    sim = yauyau.simulate(EXAMPLES / "cubic_sensor.toml", 400, seed=4)
    rows = sim.increments.copy()
    rows[60, 0] = 1e5
    sid = _session(api, "cubic_sensor", gate=0)["id"]
    url = f"/v1/sessions/{sid}"
    first = _post(api, sid, 0, "increments", rows[:100])
    assert first["degenerate"] is True and first["reason"] and first["gated"] == []
    assert all("degenerate" not in e for e in first["estimates"][:60])
    assert all(e["degenerate"] is True and e["reason"] for e in first["estimates"][60:])
    stuck = _post(api, sid, 1, "increments", rows[100:150])
    assert stuck["degenerate"] is True and all(e["degenerate"] for e in stuck["estimates"])
    assert api.get(url).json()["estimate"]["degenerate"] is True

    _problem(api.post(f"{url}/reset", json={"seq": 5, "from": "last"}), 409, "seq")  # a gap
    _problem(api.post(f"{url}/reset", json={"seq": 2}), 422, "prior")
    _problem(api.post(f"{url}/reset", json={"seq": 2, "from": "last", "prior": {"kind": "gaussian",
                                            "mean": [0.0], "cov": [[1.0]]}}), 422, "from")
    _problem(api.post(f"{url}/reset", json={"seq": 2, "from": "first"}), 422, "from")
    _problem(api.post(f"{url}/reset", json={"seq": 2, "prior": {"kind": "gaussian", "mean": [0.0, 1.0],
                                                                  "cov": [[1.0]]}}), 422, "prior.mean")
    assert api.get(url).json()["next_seq"] == 2  # none of these applied anything
    reset = api.post(f"{url}/reset", json={"seq": 2, "from": "last"})
    assert reset.status_code == 200, reset.text
    body = reset.json()
    assert (body["seq"], body["step"], body["t"]) == (2, 150, pytest.approx(1.5))
    assert body["estimate"]["degenerate"] is False and "last good estimate" in body["note"]
    last_good = first["estimates"][59]
    assert body["estimate"]["mean"][0] == pytest.approx(last_good["mean"][0], abs=1e-3)
    assert body["estimate"]["cov"][0][0] == pytest.approx(4 * last_good["cov"][0][0], rel=0.01)  # N(m, 4P)
    assert api.post(f"{url}/reset", json={"seq": 2, "from": "last"}).content == reset.content  # replay
    _problem(api.post(f"{url}/reset", json={"seq": 2, "from": "model"}), 409, "seq")  # other data
    _problem(api.post(f"{url}/observations", json={"seq": 2, "increments": [[0.0]]}), 409, "seq")
    info = api.get(url).json()
    assert (info["next_seq"], info["step"], info["estimate"]["degenerate"]) == (3, 150, False)
    # it tracks again: healthy rows, and the truth within 3 posterior standard deviations at the end
    after = _stream(api, sid, rows[150:], None, chunk=125, field="increments", seq0=3)
    assert [e["step"] for e in after] == list(range(151, 401))
    assert not any("degenerate" in e for e in after)
    end = after[-1]
    assert abs(end["mean"][0] - sim.states[-1, 0]) < 3 * math.sqrt(end["cov"][0][0])


def test_reset_to_a_prior_continues_as_the_exact_filter_from_that_prior(api):
    """Discrete OU, gate off: a measurement of 1e5 degenerates the session; reset to N(0.2, 0.3) at its
    time t_k, the next rows give the Kalman filter started from that prior at t_k."""
    rng = np.random.default_rng(31)
    K = 40
    times = _random_times(rng, K)
    rows = yauyau.simulate(spec_from_dict(SPECS["ou_discrete"]), K, seed=32, times=times).rows
    sid = _session(api, "ou_discrete", gate=0)["id"]
    bad = rows[:10].copy()
    bad[9, 0] = 1e5
    assert _post(api, sid, 0, rows=bad, times=times[:10])["degenerate"] is True
    prior = {"kind": "gaussian", "mean": [0.2], "cov": [[0.3]]}
    r = api.post(f"/v1/sessions/{sid}/reset", json={"seq": 1, "prior": prior})
    assert r.status_code == 200, r.text
    body = r.json()
    assert body["t"] == times[9] and body["step"] == 10 and "prior sent" in body["note"]
    assert body["estimate"]["mean"][0] == pytest.approx(0.2, abs=1e-3)
    assert body["estimate"]["cov"][0][0] == pytest.approx(0.3, rel=0.01)
    got = _post(api, sid, 2, rows=rows[10:], times=times[10:])
    exact = kalman(times[10:], rows[10:], [1.0], [[1.0]], m=0.2, P=0.3, t=times[9])
    assert got["degenerate"] is False
    assert np.abs(np.array([e["mean"][0] for e in got["estimates"]]) - [e[0] for e in exact]).max() < 1e-3
    var = np.array([e["cov"][0][0] for e in got["estimates"]])
    assert np.abs(var / [e[1] for e in exact] - 1).max() < 0.01


def test_on_degenerate_reinitialise_recovers_by_itself(api):
    sim = yauyau.simulate(EXAMPLES / "cubic_sensor.toml", 300, seed=6)
    rows = sim.increments.copy()
    k = 80
    rows[k, 0] = 1e5
    sid = _session(api, "cubic_sensor", gate=0, on_degenerate="reinitialise")["id"]
    body = _post(api, sid, 0, "increments", rows[:150])
    assert body["degenerate"] is False and body["reason"] is None and body["reinitialised"] == [k]
    row, before = body["estimates"][k], body["estimates"][k - 1]
    assert row["reinitialised"] is True and "re-initialised around the last good estimate" in row["reason"]
    assert row["mean"][0] == pytest.approx(before["mean"][0], abs=1e-3)  # N(m, 4P + s²) of the last good
    assert row["cov"][0][0] == pytest.approx(4 * before["cov"][0][0], rel=0.01)
    assert row["predictive_loglik"] is None  # the row's observation was not used
    assert all("reason" not in e for i, e in enumerate(body["estimates"]) if i != k)
    info = api.get(f"/v1/sessions/{sid}").json()
    assert (info["step"], info["estimate"]["mean"]) == (150, body["estimates"][-1]["mean"])
    after = _post(api, sid, 1, "increments", rows[150:])["estimates"]
    assert [e["step"] for e in after] == list(range(151, 301))
    assert not any("degenerate" in e for e in after)
    end = after[-1]
    assert abs(end["mean"][0] - sim.states[-1, 0]) < 3 * math.sqrt(end["cov"][0][0])


# -- 4. summaries, forecast -----------------------------------------------------------------------
def test_quantiles_and_mode_with_irregular_times_match_the_normal_posterior(api):
    from scipy.stats import norm

    rng = np.random.default_rng(41)
    K = 12
    times = _random_times(rng, K)
    rows = yauyau.simulate(spec_from_dict(SPECS["ou_discrete"]), K, seed=42, times=times).rows
    rows[4] = np.nan
    plain = _post(api, _session(api, "ou_discrete")["id"], 0, rows=rows, times=times)
    probs = [0.1, 0.5, 0.9]
    rich = _post(api, _session(api, "ou_discrete")["id"], 0, rows=rows, times=times, quantiles=probs,
                 mode=True)
    exact = kalman(times, rows, [1.0], [[1.0]])
    for p, e, x in zip(plain["estimates"], rich["estimates"], exact, strict=True):
        # stepped row by row (to summarise each density) = the chunk at once, to the engine's rounding
        assert abs(e["mean"][0] - p["mean"][0]) <= 1e-9
        assert e["predictive_loglik"] == pytest.approx(p["predictive_loglik"], abs=1e-9)
        np.testing.assert_allclose(e["quantiles"]["x"], norm.ppf(probs, x[0], math.sqrt(x[1])), atol=2e-3)
        assert e["mode"][0] == pytest.approx(x[0], abs=2e-3)


def test_forecast_is_the_exact_prediction_and_changes_nothing(api):
    sid = _session(api, "ou_discrete")["id"]
    _post(api, sid, 0, rows=[[0.9], [1.3]], times=[0.4, 1.1])
    before = api.get(f"/v1/sessions/{sid}").json()
    m, P = before["estimate"]["mean"][0], before["estimate"]["cov"][0][0]
    r = api.get(f"/v1/sessions/{sid}/forecast", params={"t": 3.1, "quantiles": "0.5"})
    assert r.status_code == 200, r.text
    ahead = r.json()
    tau = 3.1 - 1.1
    assert (ahead["t"], ahead["step"]) == (3.1, 2)
    assert ahead["estimate"]["mean"][0] == pytest.approx(math.exp(-THETA * tau) * m, abs=1e-3)
    exact_var = math.exp(-2 * THETA * tau) * P + A * (1 - math.exp(-2 * THETA * tau)) / (2 * THETA)
    assert ahead["estimate"]["cov"][0][0] == pytest.approx(exact_var, rel=0.01)
    assert ahead["estimate"]["quantiles"]["x"][0] == pytest.approx(ahead["estimate"]["mean"][0], abs=2e-3)
    assert api.get(f"/v1/sessions/{sid}").json() == before  # the session is unchanged
    now = api.get(f"/v1/sessions/{sid}/forecast", params={"t": 1.1}).json()
    assert now["estimate"]["mean"] == before["estimate"]["mean"]
    _problem(api.get(f"/v1/sessions/{sid}/forecast", params={"t": 0.5}), 422, "t")
    _problem(api.get(f"/v1/sessions/{sid}/forecast", params={"t": "nan"}), 422, "t")
    _problem(api.get(f"/v1/sessions/{sid}/forecast"), 422, "t")
    _problem(api.get("/v1/sessions/nope/forecast", params={"t": 1.0}), 404)


# -- 5. options kept by a real server across a restart ----------------------------------------------
@pytest.mark.service
@pytest.mark.slow
def test_options_survive_a_restart_of_a_real_server(models, tmp_path):
    """Two sessions with their own options; the server is SIGKILLed and restarted with two workers
    sharing the SQLite file: the options still hold (the gate of 2.5 gates a 4-sd row that the
    spec's 6 would pass; re-initialisation happens by itself; t0 places the rows) and the numbers
    are the Python engine's with the same options."""
    store, ids = models
    db = tmp_path / "sessions.sqlite3"
    rng = np.random.default_rng(51)
    K = 30
    times = _random_times(rng, K, start=3.5)
    rows = yauyau.simulate(spec_from_dict(SPECS["ou_discrete"]), K, seed=52, times=times - 3.5).rows
    k = 20
    options = {"on_degenerate": "reinitialise", "t0": 3.5, "gate": 2.5}
    cubic_rows = yauyau.simulate(EXAMPLES / "cubic_sensor.toml", 40, seed=53).increments
    cubic_rows[30, 0] = 1e5
    server = Server(store, db)
    try:
        with httpx.Client(timeout=60) as client:
            a = client.post(f"{server.url}/v1/sessions", json={"model": ids["ou_discrete"], **options}).json()
            b = client.post(f"{server.url}/v1/sessions", json={"model": ids["cubic_sensor"], "gate": 0,
                                                               "on_degenerate": "reinitialise"}).json()
            assert a["options"] == options and a["t"] == 3.5
            r = client.post(f"{server.url}/v1/sessions/{a['id']}/observations",
                            json={"seq": 0, "observations": _rows(rows[:k]), "times": times[:k].tolist()})
            assert r.status_code == 200, r.text
            first = r.json()
        server.kill()
        server = Server(store, db, workers=2)
        with httpx.Client(timeout=60) as client:
            info = client.get(f"{server.url}/v1/sessions/{a['id']}").json()
            assert info["options"] == options and info["t"] == times[k - 1]
            m, P, _ = kalman(times[:k + 1] - 3.5, np.vstack([rows[:k], [[np.nan]]]), [1.0], [[1.0]])[-1]
            rows[k, 0] = m + 4.0 * math.sqrt(P + 1.0)  # 4 predictive sd: gated at 2.5, not at 6
            r = client.post(f"{server.url}/v1/sessions/{a['id']}/observations",
                            json={"seq": 1, "observations": _rows(rows[k:]), "times": times[k:].tolist()})
            assert r.status_code == 200, r.text
            second = r.json()
            assert second["gated"][:1] == [0]
            r = client.post(f"{server.url}/v1/sessions/{b['id']}/observations",
                            json={"seq": 0, "increments": _rows(cubic_rows)})
            assert r.status_code == 200 and r.json()["reinitialised"] == [30] and not r.json()["degenerate"]
            assert client.get(f"{server.url}/v1/sessions/{b['id']}").json()["options"]["gate"] == 0.0
    finally:
        server.kill()
    engine = yauyau.open_filter(store, ids["ou_discrete"], gate=2.5, t0=3.5, on_degenerate="reinitialise")
    result = engine.run(rows, times)
    assert np.flatnonzero(result.gated).tolist() == first["gated"] + [k + i for i in second["gated"]]
    assert not yauyau.open_filter(store, ids["ou_discrete"], t0=3.5).run(rows, times).gated[k]  # at 6 sd
    got = first["estimates"] + second["estimates"]
    assert np.abs(np.array([e["mean"][0] for e in got]) - result.mean[:, 0]).max() <= 1e-12
    assert np.abs(np.array([e["cov"][0][0] for e in got]) - result.cov[:, 0, 0]).max() <= 1e-12
