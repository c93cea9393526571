"""Fuzz the API from its own OpenAPI schema (schemathesis, bounded): no 5xx, responses conform.

Generated requests (valid and invalid per the schema) go to the real application over ASGI, its
models loaded from a real store; every answer must match the documented status codes, content
types and response schemas.  Session routes are fuzzed against a live session as well as
unknown ids.
"""

from __future__ import annotations

import pytest
import schemathesis
from fastapi.testclient import TestClient
from hypothesis import HealthCheck, given, settings
from schemathesis import GenerationMode
from schemathesis.specs.openapi.checks import positive_data_acceptance
from yauyau.service.http.app import create_app
from yauyau.service.settings import Settings

pytestmark = pytest.mark.slow  # every test here takes seconds of CPU: the full run only

EXAMPLES = 50  # per operation, mode and path-parameter choice: bounded, derandomized (was 8)
OPERATIONS = [("GET", "/livez"), ("GET", "/readyz"), ("GET", "/v1/models"), ("GET", "/v1/models/{model_id}"),
              ("POST", "/v1/sessions"), ("POST", "/v1/sessions/{session_id}/observations"),
              ("GET", "/v1/sessions/{session_id}"), ("GET", "/v1/sessions/{session_id}/density"),
              ("GET", "/v1/sessions/{session_id}/view"), ("DELETE", "/v1/sessions/{session_id}"),
              ("POST", "/v1/sessions/{session_id}/reset"), ("GET", "/v1/sessions/{session_id}/forecast"),
              ("POST", "/v1/analyze")]
# /v1/sessions/{id}/events is a stream that ends when the session does: tests/service/http/test_live_page.py
# Every check is on, positive_data_acceptance (schema-valid data must get 2xx) too, except where a
# rule the schema cannot state makes schema-valid data invalid (422 naming the field, by design): a
# row of increments has m numbers and seq is the next one; a prior's covariance is positive
# definite and its weights sum to more than 0; a spec's expressions parse; density points have n
# coordinates; quantile probabilities lie strictly between 0 and 1; a chunk's times increase and its
# rows are those of the model's kind; a reset's seq is the next one; a forecast's t is not in the past.
SEMANTIC = {("POST", "/v1/sessions"), ("POST", "/v1/sessions/{session_id}/observations"),
            ("POST", "/v1/analyze"), ("GET", "/v1/sessions/{session_id}/density"),
            ("GET", "/v1/sessions/{session_id}"), ("POST", "/v1/sessions/{session_id}/reset"),
            ("GET", "/v1/sessions/{session_id}/forecast")}


@pytest.fixture(scope="module")
def fuzz_app(example_store, tmp_path_factory):
    store, ids = example_store
    db = tmp_path_factory.mktemp("fuzzdb") / "sessions.sqlite3"
    app = create_app(Settings(store=store, session_db=db, max_chunk_rows=200, max_body_bytes=256 * 1024))
    schema = schemathesis.openapi.from_asgi("/openapi.json", app)
    with TestClient(app) as client:
        live = client.post("/v1/sessions", json={"model": ids["cubic_sensor"]}).json()["id"]
    return schema, {"session_id": live, "model_id": ids["cubic_sensor"]}


def _fuzz(operation, mode, path_parameters, examples):
    semantic = (operation.method.upper(), operation.path) in SEMANTIC
    excluded = [positive_data_acceptance] if semantic else []

    @given(case=operation.as_strategy(mode, path_parameters=path_parameters))
    @settings(max_examples=examples, deadline=None, derandomize=True, database=None,
              suppress_health_check=list(HealthCheck))
    def check(case):
        response = case.call_and_validate(excluded_checks=excluded)
        assert response.status_code < 500

    check()


@pytest.mark.parametrize("mode", [GenerationMode.POSITIVE, GenerationMode.NEGATIVE])
@pytest.mark.parametrize("method, path", OPERATIONS)
def test_api_conforms_to_its_schema(fuzz_app, method, path, mode):
    schema, live = fuzz_app
    operation = schema[path][method]
    negative = mode == GenerationMode.NEGATIVE
    if not (negative and not (operation.path_parameters or operation.query or operation.body)):
        _fuzz(operation, mode, None, EXAMPLES)  # (an operation without inputs has nothing to make invalid)
    wanted = {name: value for name, value in live.items() if "{" + name + "}" in path}
    if wanted and method != "DELETE" and not (negative and not (operation.query or operation.body)):
        _fuzz(operation, mode, wanted, EXAMPLES)
