"""Filtering sessions of method yau-niu over HTTP (issue 40: everything the other methods have).

Truth.  A 4-D linear model (a ring of damped, rotating coordinates seen through a two-component mixing
sensor, as tests/solver/qmc/test_yau_niu.py uses) is linear and Gaussian: its optimal filter is the
Kalman filter at the row times (tests/helpers/linear_kalman.py, written without the package), with
continuous increments or discrete readings, a missing component marginalised.  Tolerances as the
solver's yau-niu tests: rms mean gap ≤ 0.02 over rows and coordinates, the worst ≤ 0.06; every
variance within 10% here, at the default budget of 8192 points, where the worst of 300 rows × 4
coordinates is 3.5–9% off (median 5%, 28 runs: 7 paths × 4 seeds; the 5% proof is at 16 384 points,
tests/solver/qmc/test_yau_niu.py).  The answers also equal the Python
filter run on the same rows in one piece (bit for bit: the per-row noise is seeded by the step, so
chunking and the state's JSON round trip change nothing).  Sessions are real (an SQLite file); the
state the store keeps is the points and their log weights.
"""

from __future__ import annotations

import base64
import sqlite3

import numpy as np
import orjson
import pytest
from fastapi.testclient import TestClient
from helpers.linear_kalman import kalman, linear_model_matrices
from yauyau.service.http.app import create_app
from yauyau.service.sessions.manager import ChunkRequest
from yauyau.service.settings import Settings
from yauyau.solver.measurement import standard_score
from yauyau.solver.model import compile_model
from yauyau.solver.qmc.budget import DEFAULT_POINTS
from yauyau.solver.simulate import simulate
from yauyau.solver.spec import spec_from_dict
from yauyau.storage.session_base import session_checksum

import yauyau

N = 4
M0, P0 = np.full(N, 0.5), np.eye(N)
PROBLEM = "application/problem+json"


def _spec(name: str, discrete: bool = False, noise: float = 0.1) -> dict:
    drift = []
    for i in range(N):
        term = f"-0.5*x{i}" + (f" + 0.3*x{i + 1}" if i + 1 < N else "")
        drift.append(term + (f" - 0.3*x{i - 1}" if i > 0 else ""))
    doc = {"name": name, "state": [f"x{i}" for i in range(N)], "drift": drift,
           "observation": ["x0 + 0.2*x1", "x1 + 0.2*x2"], "observation_noise": (noise * np.eye(2)).tolist(),
           "method": "yau-niu", "initial": {"kind": "gaussian", "mean": M0.tolist(), "cov": P0.tolist()},
           "discretization": {"dt": 0.01}}  # no [domain] nor basis: yau-niu needs neither
    if discrete:
        doc["measurement"] = {"kind": "discrete"}
    return doc


SPECS = {"continuous": _spec("niu-4d"), "discrete": _spec("niu-4d-readings", discrete=True)}


@pytest.fixture(scope="module")
def api(tmp_path_factory):
    store = tmp_path_factory.mktemp("niu-store")
    ids = {name: yauyau.precompute(spec_from_dict(doc), store) for name, doc in SPECS.items()}
    db = tmp_path_factory.mktemp("niu-db") / "sessions.sqlite3"
    app = create_app(Settings(store=store, session_db=db))
    with TestClient(app, raise_server_exceptions=False) as client:
        client.ids, client.store, client.db = ids, store, db
        client.models = {name: compile_model(spec_from_dict(doc)) for name, doc in SPECS.items()}
        yield client


def _rows(array) -> list:
    """Rows as JSON: null for a missing row, null for a missing component."""
    return [None if np.isnan(row).all() else [None if np.isnan(v) else float(v) for v in row]
            for row in np.asarray(array, float)]


def _session(api, name: str, **options) -> str:
    r = api.post("/v1/sessions", json={"model": api.ids[name], **options})
    assert r.status_code == 201, r.text
    assert r.json()["method"] == "yau-niu"
    return r.json()["id"]


def _post(api, sid: str, seq: int, rows, field: str = "increments", times=None):
    body = {"seq": seq, field: _rows(rows)}
    if times is not None:
        body["times"] = [float(t) for t in times]
    r = api.post(f"/v1/sessions/{sid}/observations", json=body)
    assert r.status_code == 200, r.text
    return r


def _answer(r) -> dict:
    return orjson.loads(r.content)


def _means(estimates) -> tuple[np.ndarray, np.ndarray]:
    return (np.array([e["mean"] for e in estimates]),
            np.array([np.diag(np.array(e["cov"])) for e in estimates]))


def _against_kalman(estimates, model, rows, gaps, discrete=False, skip=(), variance_tol=0.10, rms_tol=0.02,
                    worst_tol=0.06):
    F, H = linear_model_matrices(model)
    means, variances, _ = kalman(F, model.a, H, model.R, M0, P0, rows, gaps, discrete, skip)
    got, got_var = _means(estimates)
    rms = float(np.sqrt(np.mean((got - means) ** 2)))
    worst = float(np.abs(got - means).max())
    variance = float(np.abs(got_var / variances - 1.0).max())
    assert rms <= rms_tol and worst <= worst_tol and variance <= variance_tol, (rms, worst, variance)
    return rms, worst, variance


def _stored_state(api, sid: str) -> bytes:
    with sqlite3.connect(api.db) as db:
        return db.execute("SELECT state FROM sessions WHERE id = ?", (sid,)).fetchone()[0]


def test_chunks_match_kalman_exactly_once_and_the_state_size(api):
    """300 increments in three chunks: the estimates match the Kalman filter and equal the Python filter
    run in one piece; seq 1 sent again returns the same bytes and leaves the stored state as it was;
    other data under seq 1 is 409, a gap is 409.  The stored state is the 8192 points × 4 coordinates
    and one row of log weights (the ring is one coupled block), 8192 × 5 numbers, each array the base64
    of its float64 bytes in the JSON (solver/qmc/packed.py), equal bit for bit to the one-piece run's."""
    model = api.models["continuous"]
    rows = simulate(model, 300, np.random.default_rng(21)).increments
    sid = _session(api, "continuous")
    answers = [_post(api, sid, seq, rows[100 * seq:100 * (seq + 1)]) for seq in range(3)]
    estimates = [e for r in answers for e in _answer(r)["estimates"]]
    assert [e["step"] for e in estimates] == list(range(1, 301))
    _against_kalman(estimates, model, rows, np.full(300, 0.01))
    flt = yauyau.open_filter(api.store, api.ids["continuous"])
    whole = flt.run(rows)
    assert np.array_equal(whole.mean, _means(estimates)[0])
    assert np.array_equal(whole.predictive_loglik, [e["predictive_loglik"] for e in estimates])

    state = _stored_state(api, sid)
    replay = _post(api, sid, 1, rows[100:200])
    assert replay.content == answers[1].content and _stored_state(api, sid) == state
    other = api.post(f"/v1/sessions/{sid}/observations", json={"seq": 1, "increments": _rows(rows[:100])})
    gap = api.post(f"/v1/sessions/{sid}/observations", json={"seq": 5, "increments": _rows(rows[:3])})
    for r in (other, gap):
        assert r.status_code == 409 and r.headers["content-type"].startswith(PROBLEM), r.text
    assert _stored_state(api, sid) == state
    info = api.get(f"/v1/sessions/{sid}").json()
    assert info["step"] == 300 and info["next_seq"] == 3

    stored = orjson.loads(state)
    assert stored["points"]["shape"] == [DEFAULT_POINTS, N]
    assert stored["log_weights"]["shape"] == [1, DEFAULT_POINTS]
    back = flt.filter.state_from_dict(stored)  # the one-piece run's state, bit for bit
    assert back.points.tobytes() == np.ascontiguousarray(flt.state.points).tobytes()
    assert back.log_weights.tobytes() == flt.state.log_weights.tobytes()
    numbers = DEFAULT_POINTS * (N + 1)
    print(f"yau-niu state: {len(state)} bytes for {DEFAULT_POINTS} points in {N}-D "
          f"({len(state) / numbers:.2f} bytes a number)")
    # docs/models.md: the base64 of 8 bytes a number (10.67 bytes) and a few hundred of the rest
    assert 8 * 4 / 3 * numbers < len(state) < 8 * 4 / 3 * numbers + 2000


def _rewrite_state(api, sid: str, change) -> None:
    """The session's stored state replaced by ``change(state)``, sealed with the row's checksum (as the
    store writes it): a session stored before the packed form, or a damaged one the checksum passes."""
    with sqlite3.connect(api.db) as db:
        model, method, seq, text, options, owner = db.execute(
            "SELECT model_id, method, next_seq, state, options, owner FROM sessions WHERE id = ?",
            (sid,)).fetchone()
        text = orjson.dumps(change(orjson.loads(text))).decode()
        db.execute("UPDATE sessions SET state = ?, checksum = ? WHERE id = ?",
                   (text, session_checksum(sid, model, method, seq, text, options, owner), sid))


def _as_lists(state: dict) -> dict:
    """The state as it was stored before the packed form: the arrays as JSON lists of numbers."""
    for name in ("points", "log_weights"):
        packed = state[name]
        raw = np.frombuffer(base64.b64decode(packed["base64"]), "<f8").reshape(packed["shape"])
        state[name] = raw.tolist()
    return state


def test_a_session_stored_as_lists_goes_on_and_a_damaged_state_is_a_problem(api):
    """A session whose state was stored before the packed form (lists of numbers) takes its next chunk
    and answers as the one-piece run, bit for bit; a state whose base64 is damaged (and whose checksum
    passes) is a 4xx problem+json naming state.points.base64, no traceback."""
    model = api.models["continuous"]
    rows = simulate(model, 40, np.random.default_rng(26)).increments
    sid = _session(api, "continuous")
    first = _answer(_post(api, sid, 0, rows[:20]))["estimates"]
    _rewrite_state(api, sid, _as_lists)
    assert isinstance(orjson.loads(_stored_state(api, sid))["points"], list)
    second = _answer(_post(api, sid, 1, rows[20:]))["estimates"]
    whole = yauyau.open_filter(api.store, api.ids["continuous"]).run(rows)
    assert np.array_equal(whole.mean, _means(first + second)[0])
    assert isinstance(orjson.loads(_stored_state(api, sid))["points"], dict)  # written back packed

    def damage(state: dict) -> dict:
        state["points"]["base64"] = state["points"]["base64"][:-5] + "!"
        return state

    _rewrite_state(api, sid, damage)
    for r in (api.post(f"/v1/sessions/{sid}/observations", json={"seq": 2, "increments": _rows(rows[:2])}),
              api.get(f"/v1/sessions/{sid}")):
        assert 400 <= r.status_code < 500 and r.headers["content-type"].startswith(PROBLEM), r.text
        assert r.json()["field"] == "state.points.base64" and "base64" in r.json()["detail"], r.text


def test_discrete_readings_at_irregular_times_with_partly_missing_rows(api):
    """60 readings at gaps of 0.05..0.3 in two chunks; one row in five missing, one in five with only
    its first component: the Kalman filter of the same times and components.  Informative readings
    restart the points often (~50 restarts in 60 readings, where 300 increments restart 15 times), and
    their sampling noise shows most on x3, the coordinate the sensor barely sees: over 12 runs at the
    default 8192 points (3 paths × 4 seeds) the rms mean gap was 0.022–0.039 (median 0.028), the worst
    mean 0.13, the worst variance 17% off (median 10%); so here rms ≤ 0.04, worst ≤ 0.15, variances
    within 20% (31% before the gaps were split into Euler steps of at most dt and far-off readings
    tempered)."""
    model = api.models["discrete"]
    gaps = np.random.default_rng(22).uniform(0.05, 0.3, 60)
    times = np.cumsum(gaps)
    rows = simulate(model, 60, np.random.default_rng(23), times=times).observations.copy()
    rows[::5] = np.nan
    rows[2::5, 1] = np.nan
    sid = _session(api, "discrete")
    first = _answer(_post(api, sid, 0, rows[:25], "observations", times[:25]))
    second = _answer(_post(api, sid, 1, rows[25:], "observations", times[25:]))
    estimates = first["estimates"] + second["estimates"]
    assert np.allclose([e["t"] for e in estimates], times)
    _against_kalman(estimates, model, rows, gaps, discrete=True, variance_tol=0.20, rms_tol=0.04,
                    worst_tol=0.15)
    wrong = api.post(f"/v1/sessions/{sid}/observations", json={"seq": 2, "increments": _rows(rows[:2])})
    assert wrong.status_code == 422 and wrong.headers["content-type"].startswith(PROBLEM), wrong.text


def _outlier_rows(model, seed: int = 24, at: int = 60, K: int = 120) -> tuple[np.ndarray, float]:
    """K increments with row ``at`` moved 40 noise sd off the exact prediction; its exact standard score."""
    rows = simulate(model, K, np.random.default_rng(seed)).increments.copy()
    F, H = linear_model_matrices(model)
    means, _, _ = kalman(F, model.a, H, model.R, M0, P0, rows[:at + 1], np.full(at + 1, 0.01))
    rows[at] += 40.0 * np.sqrt(0.01 * np.diag(model.R))
    _, _, d2 = kalman(F, model.a, H, model.R, M0, P0, rows[:at + 1], np.full(at + 1, 0.01))
    return rows, standard_score(float(d2[at]), 2)


def test_the_gate_and_on_degenerate(api):
    """The outlier row: gated under the spec's gate (6 sd), flagged with its score (within 3% of the
    exact Kalman one) and the rest the Kalman filter that skips it.  With gate 0, an impossible row
    (10^6) collapses the points: under "stop" the session stays degenerate, under "reinitialise" it
    starts again from the broadened prior, flags the row, and goes on with finite, undegenerate
    estimates."""
    model = api.models["continuous"]
    rows, exact = _outlier_rows(model)
    gated = _answer(_post(api, _session(api, "continuous"), 0, rows))
    flags = [bool(e.get("gated")) for e in gated["estimates"]]
    assert flags == [k == 60 for k in range(120)], flags
    assert "gate" in gated["estimates"][60]["reason"]
    score = float(gated["estimates"][60]["reason"].split("gated: ")[1].split()[0])
    assert abs(score / exact - 1.0) < 0.03, (score, exact, gated["estimates"][60]["reason"])
    _against_kalman(gated["estimates"], model, rows, np.full(120, 0.01), skip=(60,))

    rows[60] = 1e6
    stopped = _answer(_post(api, _session(api, "continuous", gate=0), 0, rows))
    flagged = [k for k, e in enumerate(stopped["estimates"]) if e.get("degenerate")]
    assert stopped["degenerate"] is True and flagged == list(range(60, 120)), flagged
    assert "restart cannot recover" in stopped["estimates"][60]["reason"]
    again = _session(api, "continuous", gate=0, on_degenerate="reinitialise")
    first = _answer(_post(api, again, 0, rows))
    assert first["reinitialised"] == [60] and not first["degenerate"], first["reinitialised"]
    later = _answer(_post(api, again, 1, simulate(model, 50, np.random.default_rng(25)).increments))
    assert not later["degenerate"] and np.isfinite(_means(later["estimates"])[0]).all()


def test_many_streams_batched_answer_as_each_alone(api):
    """Six sessions of the model stepped together (observe_many: the service's batching path) give
    the answers each gives alone, bit for bit, one with a missing row and one degenerating and
    re-initialised by its policy, and each stream matches the Kalman filter."""
    sessions = api.app.state.sessions
    model = api.models["continuous"]
    data = [simulate(model, 80, np.random.default_rng(30 + i)).increments for i in range(6)]
    data[2][10] = np.nan
    data[4][30] = 1e6  # impossible: degenerates (the gate is off for this session), then re-initialises

    def create(i):
        options = {"on_degenerate": "reinitialise", "gate": 0} if i == 4 else {}
        return sessions.create(api.ids["continuous"], None, None, **options)["id"]

    twins, batched = [create(i) for i in range(6)], [create(i) for i in range(6)]
    for seq, block in enumerate((slice(0, 50), slice(50, 80))):
        alone = [orjson.loads(sessions.observe(s, seq, _rows(d[block]), True))
                 for s, d in zip(twins, data, strict=True)]
        together = sessions.observe_many([ChunkRequest(s, seq, _rows(d[block]))
                                          for s, d in zip(batched, data, strict=True)])
        for a, b in zip(alone, together, strict=True):
            b = orjson.loads(b)
            assert a["estimates"] == b["estimates"] and a["reinitialised"] == b["reinitialised"]
        if seq == 0:
            assert alone[4]["reinitialised"] == [30]
    for i in (0, 2):
        estimates = [e for seq in (0, 1) for e in orjson.loads(sessions.store._stored_text(batched[i], seq))
                     ["estimates"]]
        _against_kalman(estimates, model, data[i], np.full(80, 0.01))


def test_a_session_whose_points_would_not_fit_here_is_413(tmp_path, monkeypatch):
    """A model stored where memory sufficed (10^6 points: about 0.8 GB a row), served on a machine of
    100 MB (memory_limit patched): POST /v1/sessions is 413 problem+json naming discretization.points,
    before any point is drawn."""
    import yauyau.solver.qmc.budget as budget
    import yauyau.solver.qmc.yau_niu as yau_niu

    doc = _spec("niu-4d-big")
    doc["discretization"] = {"dt": 0.01, "points": 10**6}
    mid = yauyau.precompute(spec_from_dict(doc), tmp_path / "store")
    monkeypatch.setattr(budget, "memory_limit", lambda: 100 * 2**20)
    monkeypatch.setattr(yau_niu, "qmc_normals", lambda *a: pytest.fail("points drawn"))
    app = create_app(Settings(store=tmp_path / "store", session_db=tmp_path / "s.sqlite3"))
    with TestClient(app, raise_server_exceptions=False) as client:
        r = client.post("/v1/sessions", json={"model": mid})
    assert r.status_code == 413 and r.headers["content-type"].startswith(PROBLEM), r.text
    body = r.json()
    assert body["field"] == "discretization.points" and "0.1 GiB this machine has" in body["detail"]
    assert "set discretization.points to at most" in body["detail"]
