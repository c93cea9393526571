"""Fixed-lag smoothing over HTTP (session option ``smooth_lag``, service/sessions/lagged.py).

Truth: the Python fixed-lag smoother ``flt.smooth(rows, lag=L)`` (solver/smoothing.py, itself tested
against RTS and the fixed-interval smoother in tests/solver/engine/test_smoother.py) over the same rows:
the smoothed estimate the service returns for row k (once row k + L has come) equals its row k to 1e-8,
whatever the chunking.  A real ``yauyau serve`` process (helpers/server.py) and its SQLite sessions.
"""

from __future__ import annotations

import tomllib

import httpx
import numpy as np
import pytest
from helpers import EXAMPLES
from helpers.server import Server
from helpers.smoothing_refs import sample_ou
from yauyau.solver import spec_from_dict

import yauyau

PROBLEM = "application/problem+json"
LAG = 7
KB_DISCRETE = {"name": "ou-kb-discrete", "state": ["x"], "drift": ["-0.5*x"], "observation": ["x"],
               "diffusion": [[1.0]], "observation_noise": [[0.5]], "measurement": {"kind": "discrete"},
               "method": "kalman-bucy", "initial": {"kind": "gaussian", "mean": [1.0], "cov": [[0.5]]},
               "domain": {"radius": 6.0}, "discretization": {"dt": 0.01, "basis": 16}}


@pytest.fixture(scope="module")
def served(tmp_path_factory):
    doc = tomllib.loads((EXAMPLES / "ou.toml").read_text())
    doc["discretization"]["basis"] = 48
    doc["domain"]["radius"] = 6.0
    store = tmp_path_factory.mktemp("lag-store")
    ids = {"ou": yauyau.precompute(spec_from_dict(doc), store),
           "kb": yauyau.precompute(spec_from_dict(KB_DISCRETE), store)}
    server = Server(store, tmp_path_factory.mktemp("lag-db") / "sessions.sqlite3")
    try:
        with httpx.Client(base_url=server.url, timeout=60.0) as client:
            yield client, store, ids
    finally:
        server.kill()


def _create(client, model, **options):
    r = client.post("/v1/sessions", json={"model": model, **options})
    assert r.status_code == 201, r.text
    return r.json()


def _post(client, sid, seq, field, rows, times=None):
    body = {"seq": seq, field: [[float(v)] for v in rows]}
    if times is not None:
        body["times"] = [float(t) for t in times]
    r = client.post(f"/v1/sessions/{sid}/observations", json=body)
    assert r.status_code == 200, r.text
    return r


def _stream(client, sid, field, rows, times, sizes):
    smoothed, answers, start = [], [], 0
    for seq, size in enumerate(sizes):
        stop = start + size
        r = _post(client, sid, seq, field, rows[start:stop], None if times is None else times[start:stop])
        answers.append(r)
        body = r.json()
        assert len(body["estimates"]) == size
        smoothed += body["smoothed"]
        start = stop
    assert start == len(rows)
    return smoothed, answers


def _check(smoothed, reference, K):
    assert [e["step"] for e in smoothed] == list(range(1, K - LAG + 1))  # row k once row k + L has come
    mean = np.array([e["mean"][0] for e in smoothed])
    var = np.array([e["cov"][0][0] for e in smoothed])
    gap = max(np.abs(mean - reference.mean[:K - LAG, 0]).max(),
              np.abs(var - reference.cov[:K - LAG, 0, 0]).max())
    print(f"smooth_lag over HTTP against flt.smooth(lag): {gap:.1e}")
    assert gap < 1e-8
    assert np.allclose([e["t"] for e in smoothed], reference.t[:K - LAG], rtol=0, atol=1e-12)


def test_engine_session_smooths_with_a_fixed_lag_exactly_once(served):
    client, store, ids = served
    K = 120
    _, dy = sample_ou(K, seed=21)
    created = _create(client, ids["ou"], method="yau-yau", smooth_lag=LAG)
    assert created["options"]["smooth_lag"] == LAG
    sizes = [3, 2, 1, 30, 4, 50, 1, 29]  # windows shorter and longer than the lag
    smoothed, answers = _stream(client, created["id"], "increments", dy, None, sizes)
    assert [len(a.json()["smoothed"]) for a in answers][:3] == [0, 0, 0]  # 6 rows < L: nothing yet
    reference = yauyau.open_filter(store, ids["ou"], method="yau-yau").smooth(dy, lag=LAG)
    _check(smoothed, reference, K)
    filtered = np.concatenate([[e["mean"][0] for e in a.json()["estimates"]] for a in answers])
    assert np.abs(filtered[:K - LAG] - reference.mean[:K - LAG, 0]).max() > 1e-3  # smoothing changed them
    # a resent seq returns the stored answer, byte for byte, and applies nothing
    for seq in (1, 3, len(sizes) - 1):
        start = sum(sizes[:seq])
        again = _post(client, created["id"], seq, "increments", dy[start:start + sizes[seq]])
        assert again.content == answers[seq].content
    info = client.get(f"/v1/sessions/{created['id']}").json()
    assert info["step"] == K and info["next_seq"] == len(sizes) and info["options"]["smooth_lag"] == LAG
    # a reset starts the window again at the session's step: rows after it only
    seq = len(sizes)
    r = client.post(f"/v1/sessions/{created['id']}/reset", json={"seq": seq, "from": "model"})
    assert r.status_code == 200, r.text
    after = [_post(client, created["id"], seq + 1 + i, "increments", dy[:n]).json()
             for i, n in enumerate((5, 10))]
    assert after[0]["smoothed"] == []
    assert [e["step"] for e in after[1]["smoothed"]] == list(range(K + 1, K + 15 - LAG + 1))


def test_smoothed_estimates_carry_the_mode_and_quantiles_the_chunk_asks_for(served):
    """A chunk with "quantiles" and "mode": each smoothed estimate carries them as its filtered estimates do
    (the same keys, by the same code on the row's smoothed density), the quantiles within 0.02 of the
    fixed-lag RTS's Gaussian m + √P Φ⁻¹(p) and the mode within 0.02 of its mean (measured 4.6e-3, 2.3e-3;
    the smoothed density is the projection of σ_k ⊙ β_k onto the basis); a chunk without them, neither."""
    from helpers.smoothing_refs import rts_sampled
    from scipy.special import ndtri

    client, store, ids = served
    K, probs = 60, [0.05, 0.5, 0.95]
    _, dy = sample_ou(K, seed=24)
    sid = _create(client, ids["ou"], method="yau-yau", smooth_lag=LAG)["id"]
    smoothed, start = [], 0
    for seq, size in enumerate((20, 25, 15)):
        extra = {"quantiles": probs, "mode": True} if seq < 2 else {}
        rows = [[float(v)] for v in dy[start:start + size]]
        r = client.post(f"/v1/sessions/{sid}/observations", json={"seq": seq, "increments": rows, **extra})
        assert r.status_code == 200, r.text
        body = r.json()
        for e in body["smoothed"]:
            assert set(e) == set(body["estimates"][0]) & {"step", "t", "mean", "cov", "mode", "quantiles"}
        smoothed += body["smoothed"] if seq < 2 else []
        start += size
    assert len(smoothed) == 45 - LAG and all("mode" in e and "quantiles" in e for e in smoothed)
    assert all("mode" not in e and "quantiles" not in e for e in r.json()["smoothed"])
    ms, Ps = np.empty(len(smoothed)), np.empty(len(smoothed))
    for k in range(len(smoothed)):  # row k's RTS given rows 0 … k + L
        _, _, m, P = rts_sampled(dy[:k + LAG + 1], 1.0, 0.5, theta=0.5, a=1.0, r=1.0)
        ms[k], Ps[k] = m[k], P[k]
    exact = ms[:, None] + np.sqrt(Ps)[:, None] * ndtri(probs)[None, :]
    q = np.array([e["quantiles"]["x"] for e in smoothed])
    mode = np.array([e["mode"][0] for e in smoothed])
    gap, mode_gap = np.abs(q - exact).max(), np.abs(mode - ms).max()
    print(f"smoothed quantiles over HTTP: {gap:.2e}, mode {mode_gap:.2e}")
    assert gap < 0.02 and mode_gap < 0.02


def test_kalman_bucy_discrete_session_smooths_at_irregular_times(served):
    client, store, ids = served
    rng = np.random.default_rng(22)
    K = 60
    times = np.cumsum(rng.uniform(0.02, 0.5, K))
    z = yauyau.simulate(spec_from_dict(KB_DISCRETE), K, seed=23, times=times).rows[:, 0]
    created = _create(client, ids["kb"], smooth_lag=LAG)
    assert created["method"] == "kalman-bucy"
    smoothed, _ = _stream(client, created["id"], "observations", z, times, [10, 5, 20, 25])
    reference = yauyau.open_filter(store, ids["kb"]).smooth(z, times=times, lag=LAG)
    _check(smoothed, reference, K)
    # a session with smooth_lag keeps its chunks all timed or all untimed
    r = client.post(f"/v1/sessions/{created['id']}/observations", json={"seq": 4, "observations": [[0.1]]})
    assert r.status_code == 422 and r.headers["content-type"].startswith(PROBLEM)
    assert r.json()["field"] == "times"


@pytest.mark.parametrize("options, field, words", [
    ({"smooth_lag": 0}, "smooth_lag", "1 to 1000"), ({"smooth_lag": 1001}, "smooth_lag", "1 to 1000"),
    ({"smooth_lag": 2.5}, "smooth_lag", "whole number"), ({"smooth_lag": "3"}, "smooth_lag", "whole number"),
    ({"smooth_lag": True}, "smooth_lag", "whole number"),
    ({"smooth_lag": 5, "method": "yau-jia"}, "smooth_lag", "yau-jia"),
])
def test_bad_smooth_lag_is_a_problem_naming_it(served, options, field, words):
    client, _, ids = served
    before = client.get("/v1/sessions").json()["sessions"]
    r = client.post("/v1/sessions", json={"model": ids["ou"], **options})
    assert r.status_code == 422, r.text
    assert r.headers["content-type"].startswith(PROBLEM)
    body = r.json()
    assert body["field"] == field and words in body["detail"], body
    assert client.get("/v1/sessions").json()["sessions"] == before  # nothing created
