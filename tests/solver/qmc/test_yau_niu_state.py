"""The Yau–Niu state's stored form (solver/qmc/packed.py; issue 40): the points and log weights as the
base64 of their float64 bytes inside the JSON dict.

Truth: the arrays the filter held (the round trip must give them back bit for bit, and a run continued
from the decoded state must equal the run continued from the original, bit for bit), the list form a
state was stored in before this change (read back as the same numbers: Python's float repr round-trips
exactly), and the byte count of the format (8 bytes a number, 4/3 of that in base64).
"""

from __future__ import annotations

import base64
import json
from dataclasses import replace

import numpy as np
import orjson
import pytest
from yauyau.solver.errors import InputError
from yauyau.solver.model import compile_model
from yauyau.solver.qmc.yau_niu import YauNiuFilter
from yauyau.solver.simulate import simulate
from yauyau.solver.spec import spec_from_dict


def _model(n: int, coupled: bool, points: int):
    """A coupled ring (one block of n coordinates) or n independent cubic sensors (n blocks)."""
    if coupled:
        drift = [f"-0.5*x{i} + 0.3*x{(i + 1) % n}" for i in range(n)]
        observation = [f"x0 + 0.2*x{n - 1}"]
    else:
        drift = [f"-0.5*x{i}" for i in range(n)]
        observation = [f"x{i}**3" for i in range(n)]
    m = len(observation)
    doc = {"name": "t", "state": [f"x{i}" for i in range(n)], "drift": drift, "observation": observation,
           "observation_noise": (0.1 * np.eye(m)).tolist(), "method": "yau-niu",
           "initial": {"kind": "gaussian", "mean": [0.5] * n, "cov": np.eye(n).tolist()},
           "discretization": {"dt": 0.01, "points": points}}
    return compile_model(spec_from_dict(doc))


@pytest.fixture(scope="module", params=["coupled", "independent"])
def case(request):
    model = _model(4, request.param == "coupled", 512)
    flt = YauNiuFilter(model)
    rows = simulate(model, 60, np.random.default_rng(7)).increments
    state, _ = flt.run_arrays(flt.initial_state(), rows[:30])
    return flt, state, rows[30:]


def _bits(a: np.ndarray) -> bytes:
    return np.ascontiguousarray(a, dtype="<f8").tobytes()


def test_the_round_trip_is_bit_exact_and_compact(case):
    """Through orjson (the store's encoder): the same bytes back, and the rest of the run equals the
    rest of the run from the original state; the stored text is ~10.7 bytes a number (8 · 4/3)."""
    flt, state, rest = case
    data = state.to_dict()
    assert data["points"]["dtype"] == "<f8" and data["points"]["shape"] == list(state.points.shape)
    text = orjson.dumps(data)
    back = flt.state_from_dict(orjson.loads(text))
    assert _bits(back.points) == _bits(state.points) and _bits(back.log_weights) == _bits(state.log_weights)
    assert back.points.flags.writeable and back.log_weights.flags.writeable
    assert (back.step, back.t, back.loglik, back.restarts, back.seed) == \
        (state.step, state.t, state.loglik, state.restarts, state.seed)
    _, want = flt.run_arrays(state, rest)
    _, got = flt.run_arrays(back, rest)
    assert np.array_equal(got.mean, want.mean) and np.array_equal(got.cov, want.cov)
    assert np.array_equal(got.loglik, want.loglik)
    numbers = state.points.size + state.log_weights.size
    assert len(text) < 8 * 4 / 3 * numbers + 400  # the two arrays' base64 and ~250 bytes of fields


def test_a_zero_weight_survives_and_the_run_goes_on(case):
    """A point of zero weight (log weight -inf: a density prior that vanishes there) round-trips
    bit for bit (the list form could not hold it: JSON has no infinity) and the run stays finite."""
    flt, state, rest = case
    logW = state.log_weights.copy()
    logW[:, 3] = -np.inf
    zero = replace(state, log_weights=logW)
    back = flt.state_from_dict(orjson.loads(orjson.dumps(zero.to_dict())))
    assert _bits(back.log_weights) == _bits(logW)
    _, result = flt.run_arrays(back, rest)
    assert np.isfinite(result.mean).all() and not result.degenerate.any()


def test_the_list_form_of_older_sessions_still_loads(case):
    """A state stored before this change (points and log weights as JSON lists) loads as the same
    numbers and continues the run exactly as the state it was written from."""
    flt, state, rest = case
    old = {**state.to_dict(), "points": state.points.tolist(), "log_weights": state.log_weights.tolist()}
    back = flt.state_from_dict(json.loads(json.dumps(old, allow_nan=False)))
    assert _bits(back.points) == _bits(state.points) and _bits(back.log_weights) == _bits(state.log_weights)
    _, want = flt.run_arrays(state, rest)
    _, got = flt.run_arrays(back, rest)
    assert np.array_equal(got.mean, want.mean)


def _packed(array, **change) -> dict:
    raw = np.ascontiguousarray(array, dtype="<f8")
    return {"dtype": "<f8", "shape": list(raw.shape), "base64": base64.b64encode(raw.tobytes()).decode(),
            **change}


def test_a_malformed_state_names_its_field(case):
    flt, state, _ = case
    good = state.to_dict()
    X, L = state.points, state.log_weights
    nan_points, inf_weights, dead_block = X.copy(), L.copy(), L.copy()
    nan_points[5, 1] = np.nan
    inf_weights[0, 2] = np.inf
    dead_block[-1] = -np.inf
    short = base64.b64encode(_bits(X)[:-8]).decode()
    cases = [
        ({"points": _packed(X[:, :3])}, "state.points", "shape (N, 4)"),
        ({"points": _packed(X, shape=[len(X), 3])}, "state.points.base64", "needs"),
        ({"points": _packed(X, base64=short)}, "state.points.base64", "bytes"),
        ({"points": _packed(X, base64="not base64!")}, "state.points.base64", "not valid base64"),
        ({"points": _packed(X, dtype=">f4")}, "state.points.dtype", "'<f8'"),
        ({"points": _packed(X, shape=[len(X), "4"])}, "state.points.shape", "non-negative integers"),
        ({"points": _packed(X, extra=1)}, "state.points", "unknown key"),
        ({"points": "AAAA"}, "state.points", "base64"),
        ({"points": None}, "state.points", "required"),
        ({"points": [["a"] * 4]}, "state.points", "list of numbers"),
        ({"points": _packed(nan_points)}, "state.points", "finite"),
        ({"log_weights": _packed(L[:, :-1])}, "state.log_weights", f"({len(L)}, {L.shape[1]})"),
        ({"log_weights": _packed(inf_weights)}, "state.log_weights", "finite"),
        ({"log_weights": _packed(dead_block)}, "state.log_weights", "every block"),
        ({"step": "x"}, "state", "not a yau-niu state"),
    ]
    for change, field, words in cases:
        with pytest.raises(InputError) as caught:
            flt.state_from_dict({**good, **change})
        assert caught.value.field == field and words in caught.value.message, (change.keys(), caught.value)
    with pytest.raises(InputError) as caught:
        flt.state_from_dict([])
    assert caught.value.field == "state"


def test_a_state_of_non_finite_numbers_is_refused_by_the_store(case, tmp_path):
    """A NaN point or a +inf log weight leaves to_dict as a list (not base64, where the store could not
    see it), so the session store refuses the state before writing it, as it did the list form; a -inf
    log weight (a zero weight) is packed and stored."""
    from yauyau.storage.errors import StoreError
    from yauyau.storage.session_store import SqliteSessionStore

    flt, state, _ = case
    store = SqliteSessionStore(tmp_path / "sessions.sqlite")
    X, L, zero = state.points.copy(), state.log_weights.copy(), state.log_weights.copy()
    X[1, 2] = np.nan
    L[0, 4] = np.inf
    zero[0, 4] = -np.inf
    for bad in (replace(state, points=X), replace(state, log_weights=L)):
        with pytest.raises(StoreError) as caught:
            store.create("m", "yau-niu", bad.to_dict())
        assert caught.value.field == "state" and "NaN or infinity" in str(caught.value)
    sid = store.create("m", "yau-niu", replace(state, log_weights=zero).to_dict())
    back = flt.state_from_dict(store.get(sid).state)
    assert _bits(back.log_weights) == _bits(zero) and _bits(back.points) == _bits(state.points)
