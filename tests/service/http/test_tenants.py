"""Tenants (issue 35, item 4) against real `yauyau serve` processes, SQLite files and PostgreSQL.

A tenants file holds SHA-256 hashes of bearer tokens; the tokens here are random and their hashes
computed with hashlib.  Every /v1 request then needs a tenant's token (401 with WWW-Authenticate
otherwise), a session is its creator's (another tenant gets exactly the unknown-id 404 on every
route, and never sees it listed), model creation and jobs need an admin (403).  Without tenants the
server refuses a public bind, says at start that it runs without authentication, and checks the
Host header like any server.  A session made before tenants (an old file, migrated when opened) is
owned by no tenant.  No 5xx problem carries a server path.  The live page with tenants is in
tests/service/http/test_live_page.py.  docs/reliability.md ("Tenants") lists what each test proves.
"""

from __future__ import annotations

import hashlib
import os
import secrets
import sqlite3
import subprocess
import sys
import tempfile
from pathlib import Path

import httpx
import pytest
from helpers import free_port
from helpers.server import Server, session_db

PROBLEM = "application/problem+json"
ROWS = [[0.01 * ((i * 7) % 5 - 2)] for i in range(20)]
# the columns of the sessions table before tenants (storage/session_base.py on main, issue 35)
COLUMNS_BEFORE_TENANTS = ["id", "model_id", "method", "state", "initial_response", "next_seq", "step", "t",
                          "loglik", "created", "updated", "version", "options"]


def sha256(token: str) -> str:
    return hashlib.sha256(token.encode()).hexdigest()


@pytest.fixture
def tenants(tmp_path):
    """A tenants file of alice, bob (no admin) and root (admin): (path, {name: token})."""
    tokens = {name: secrets.token_urlsafe(24) for name in ("alice", "bob", "root")}
    text = "".join(f'[[tenant]]\nname = "{name}"\ntoken_sha256 = "{sha256(token)}"\n'
                   + ("admin = true\n" if name == "root" else "") + "\n" for name, token in tokens.items())
    path = tmp_path / "tenants.toml"
    path.write_text(text)
    assert all(token not in text for token in tokens.values())  # the file never holds a token
    return path, tokens


def auth(token: str) -> dict[str, str]:
    return {"Authorization": f"Bearer {token}"}


def problem(r: httpx.Response, status: int, field: str | None = None) -> dict:
    assert r.status_code == status, (r.status_code, r.text)
    assert r.headers["content-type"].startswith(PROBLEM), r.headers["content-type"]
    body = r.json()
    if field is not None:
        assert body["field"] == field, body
    return body


def first_event(client: httpx.Client, url: str, headers: dict) -> str:
    """The event name of the first Server-Sent Event of ``url`` (then the stream is closed)."""
    with client.stream("GET", url, headers=headers, timeout=30) as r:
        assert r.status_code == 200, r.read()
        for line in r.iter_lines():
            if line.startswith("event:"):
                return line.split(":", 1)[1].strip()
    raise AssertionError("no event")


# the session routes: (method, path under /v1/sessions/{id}, request options)
SESSION_ROUTES = [
    ("GET", "", {}),
    ("POST", "/observations", {"json": {"seq": 1, "increments": ROWS}}),
    ("POST", "/reset", {"json": {"seq": 1, "from": "model"}}),
    ("GET", "/density", {"params": {"grid": "-1:1:5"}}),
    ("GET", "/forecast", {"params": {"t": "5"}}),
    ("GET", "/view", {}),
    ("GET", "/events", {}),
    ("DELETE", "", {}),
]


@pytest.mark.service
@pytest.mark.slow
@pytest.mark.parametrize("kind", ["sqlite", pytest.param("postgres", marks=pytest.mark.postgres)])
def test_a_session_is_its_tenants_alone(example_store, tenants, tmp_path, request, kind):
    store, ids = example_store
    path, tokens = tenants
    server = Server(store, session_db(kind, request, tmp_path), env={"YAUYAU_TENANTS_FILE": str(path)})
    try:
        with httpx.Client(base_url=server.url, timeout=60) as client:
            _unauthenticated(client)
            alice, bob, root = (auth(tokens[n]) for n in ("alice", "bob", "root"))
            body = {"model": ids["ou"]}
            mine = client.post("/v1/sessions", json=body, headers=alice).json()["id"]
            theirs = client.post("/v1/sessions", json=body, headers=bob).json()["id"]
            assert client.post(f"/v1/sessions/{mine}/observations", json={"seq": 0, "increments": ROWS},
                               headers=alice).status_code == 200
            # another tenant: the problem of an unknown id, on every route, and nothing changes
            for method, tail, options in SESSION_ROUTES:
                for sid in (mine, "no-such-session"):
                    r = client.request(method, f"/v1/sessions/{sid}{tail}", headers=bob, **options)
                    unknown = {"type": "about:blank", "title": "Not found", "status": 404, "field": "session",
                               "detail": f"no session {sid!r}", "instance": f"/v1/sessions/{sid}{tail}"}
                    assert problem(r, 404, "session") == unknown, (method, tail)
            info = client.get(f"/v1/sessions/{mine}", headers=alice).json()
            assert (info["next_seq"], info["step"]) == (1, len(ROWS))  # bob's chunk and reset did nothing
            # the owner may do all of it
            for method, tail, options in [*SESSION_ROUTES[:2], ("POST", "/reset", {"json": {
                    "seq": 2, "from": "model"}}), *SESSION_ROUTES[3:5]]:
                r = client.request(method, f"/v1/sessions/{mine}{tail}", headers=alice, **options)
                assert r.status_code == 200, (method, tail, r.text)
            view = client.get(f"/v1/sessions/{mine}/view", headers=alice)
            assert view.status_code == 200 and "default-src 'none'" in view.headers["content-security-policy"]
            assert first_event(client, f"/v1/sessions/{mine}/events", alice) == "frame"
            # listing: each tenant sees its own sessions only
            listed = {name: [s["id"] for s in client.get("/v1/sessions", headers=h).json()["sessions"]]
                      for name, h in (("alice", alice), ("bob", bob), ("root", root))}
            assert listed == {"alice": [mine], "bob": [theirs], "root": []}
            by_model = client.get("/v1/sessions", params={"model": ids["ou"]}, headers=bob).json()
            assert [s["id"] for s in by_model["sessions"]] == [theirs]
            # models: any tenant lists and reads them; creating one and reading jobs needs an admin
            assert client.get("/v1/models", headers=bob).status_code == 200
            assert client.get(f"/v1/models/{ids['ou']}", headers=bob).status_code == 200
            problem(client.post("/v1/models", json={"spec": {}}, headers=bob), 403, "Authorization")
            problem(client.get("/v1/jobs/abc", headers=bob), 403, "Authorization")
            problem(client.post("/v1/models", json={"spec": {}}, headers=root), 422)  # past the admin check
            problem(client.get("/v1/jobs/abc", headers=root), 404, "job")
            problem(client.post("/v1/analyze", json={}, headers=bob), 422)  # any tenant may analyse
            assert client.delete(f"/v1/sessions/{mine}", headers=alice).status_code == 204
            problem(client.get(f"/v1/sessions/{mine}", headers=alice), 404, "session")
    finally:
        server.kill()


def _unauthenticated(client: httpx.Client) -> None:
    """401 without a token, with a wrong one or another scheme; health, metrics and the API
    description stay open; a browser opening a live page gets the page (to type the token)."""
    for path in ("/v1/models", "/v1/sessions", "/v1/jobs/x", "/v1/sessions/x/events", "/nowhere"):
        r = client.get(path)
        problem(r, 401, "Authorization")
        assert r.headers["www-authenticate"] == 'Bearer realm="yauyau"'
    for header in ("Bearer " + secrets.token_urlsafe(24), "bearer wrong", "Bearer " + "a" * 64):
        r = client.get("/v1/sessions", headers={"Authorization": header})
        problem(r, 401, "Authorization")
        assert r.headers["www-authenticate"] == 'Bearer realm="yauyau", error="invalid_token"'
    problem(client.get("/v1/sessions", headers={"Authorization": "Basic YWxpY2U6eA=="}), 401)
    problem(client.post("/v1/sessions", json={"model": "x"}), 401)
    for path in ("/livez", "/readyz", "/metrics", "/openapi.json"):
        assert client.get(path).status_code == 200, path
    page = client.get("/v1/sessions/whatever/view", headers={"Accept": "text/html,*/*;q=0.8"})
    assert page.status_code == 401 and page.headers["content-type"].startswith("text/html")
    assert 'type="password"' in page.text and page.headers["www-authenticate"] == 'Bearer realm="yauyau"'
    assert "script-src 'sha256-" in page.headers["content-security-policy"]
    problem(client.get("/v1/sessions/whatever/view"), 401)  # not a browser: problem+json


@pytest.mark.service
@pytest.mark.slow
@pytest.mark.parametrize("kind", ["sqlite", pytest.param("postgres", marks=pytest.mark.postgres)])
def test_sessions_of_an_old_store_are_owned_by_no_tenant(example_store, tenants, tmp_path, request, kind):
    """A session made before tenants (its store without the owner column) is migrated when the store
    is opened: owned by no tenant, visible without tenants, invisible to every tenant."""
    store, ids = example_store
    path, tokens = tenants
    db = session_db(kind, request, tmp_path)
    server = Server(store, db)
    try:
        old = httpx.post(server.url + "/v1/sessions", json={"model": ids["ou"]}).json()["id"]
        assert httpx.post(f"{server.url}/v1/sessions/{old}/observations",
                          json={"seq": 0, "increments": ROWS}).status_code == 200
    finally:
        server.kill()
    # the store as the release before tenants (and row checksums) left it
    assert _columns(kind, db, drop=("owner", "checksum")) == COLUMNS_BEFORE_TENANTS

    server = Server(store, db)  # no tenants: the old session as before
    try:
        info = httpx.get(f"{server.url}/v1/sessions/{old}").json()
        assert (info["next_seq"], info["step"]) == (1, len(ROWS))
        assert [s["id"] for s in httpx.get(server.url + "/v1/sessions").json()["sessions"]] == [old]
    finally:
        server.kill()
    assert "owner" in _columns(kind, db) and _owners(kind, db) == [None]

    server = Server(store, db, env={"YAUYAU_TENANTS_FILE": str(path)})
    try:
        for name in ("alice", "root"):
            problem(httpx.get(f"{server.url}/v1/sessions/{old}", headers=auth(tokens[name])), 404, "session")
            listed = httpx.get(server.url + "/v1/sessions", headers=auth(tokens[name])).json()
            assert listed["sessions"] == []
    finally:
        server.kill()


def _columns(kind: str, db: str, drop: tuple[str, ...] = ()) -> list[str]:
    """The sessions table's columns (after dropping ``drop``, to make the store an old one)."""
    if kind == "sqlite":
        with sqlite3.connect(db) as con:
            for column in drop:
                con.execute(f"ALTER TABLE sessions DROP COLUMN {column}")
            return [row[1] for row in con.execute("PRAGMA table_info(sessions)")]
    import psycopg

    with psycopg.connect(db, autocommit=True) as con:
        for column in drop:
            con.execute(f"ALTER TABLE sessions DROP COLUMN {column}")
        rows = con.execute("SELECT column_name FROM information_schema.columns WHERE table_name = 'sessions' "
                           "ORDER BY ordinal_position").fetchall()
    return [row[0] for row in rows]


def _owners(kind: str, db: str) -> list:
    if kind == "sqlite":
        with sqlite3.connect(db) as con:
            return [row[0] for row in con.execute("SELECT owner FROM sessions")]
    import psycopg

    with psycopg.connect(db) as con:
        return [row[0] for row in con.execute("SELECT owner FROM sessions").fetchall()]


# -- starting the server ----------------------------------------------------------------------------
def serve(*args, env=None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "yauyau.service.cli", "serve", *map(str, args)],
                          capture_output=True, text=True, timeout=120, env={**os.environ, **(env or {})})


def test_a_public_bind_without_tenants_is_refused(example_store, tmp_path):
    store, _ = example_store
    result = serve("--store", store, "--session-db", tmp_path / "s.sqlite3", "--host", "0.0.0.0",
                   "--port", free_port())
    assert result.returncode == 2, result.stderr
    line = result.stderr.strip()
    assert "\n" not in line and "Traceback" not in line
    assert "0.0.0.0" in line and "without authentication" in line
    assert "--tenants FILE" in line and "--insecure-bind" in line  # the two fixes


HASH, OTHER = "ab" * 32, "cd" * 32


@pytest.mark.slow
@pytest.mark.parametrize("text, names", [
    ('[[tenant]]\nname = "alice"\ntoken_sha256 = "' + HASH[:63] + '"\n', ["alice", "token_sha256", "64"]),
    ('[[tenant]]\nname = "alice"\ntoken_sha256 = "' + "g" * 64 + '"\n', ["alice", "token_sha256"]),
    ('[[tenant]]\nname = "alice"\n', ["alice", "token_sha256", "missing"]),
    ('[[tenant]]\nname = "alice"\ntoken = "s3cret"\n', ["alice", "token", "never holds a token"]),
    (f'[[tenant]]\nname = "alice"\ntoken_sha256 = "{HASH}"\nadmin = "yes"\n', ["alice", "admin"]),
    (f'[[tenant]]\ntoken_sha256 = "{HASH}"\n', ["#1", "name"]),
    (f'[[tenant]]\nname = "a"\ntoken_sha256 = "{HASH}"\n[[tenant]]\nname = "a"\ntoken_sha256 = "{OTHER}"\n',
     ["'a'", "name", "twice"]),
    (f'[[tenant]]\nname = "a"\ntoken_sha256 = "{HASH}"\n[[tenant]]\nname = "b"\ntoken_sha256 = "{HASH}"\n',
     ["'b'", "token_sha256", "'a'"]),
    ('[[tenant]\nname = "alice"\n', ["not valid TOML"]),
    ("", ["no [[tenant]]"]),
])
def test_a_bad_tenants_file_is_one_line_naming_file_tenant_and_field(example_store, tmp_path, text, names):
    store, _ = example_store
    path = tmp_path / "tenants.toml"
    path.write_text(text)
    result = serve("--store", store, "--session-db", tmp_path / "s.sqlite3", "--port", free_port(),
                   "--tenants", path)
    assert result.returncode == 2, result.stderr
    line = result.stderr.strip()
    assert "\n" not in line and "Traceback" not in line
    assert line.startswith("yauyau serve: error: tenants_file: ") and str(path) in line
    for name in names:
        assert name in line, (name, line)
    missing = serve("--store", store, "--port", free_port(),
                    env={"YAUYAU_TENANTS_FILE": str(tmp_path / "no")})
    assert missing.returncode == 2 and "cannot read the tenants file" in missing.stderr


def test_insecure_bind_is_the_operators_choice():
    """--insecure-bind lets a public host start without tenants (not started here: the tests listen on
    loopback only); a tenants file lets it too; loopback needs neither."""
    from yauyau.service.http.tenants import serve_notes
    from yauyau.service.settings import Settings
    from yauyau.solver.errors import InputError

    with pytest.raises(InputError, match="--insecure-bind"):
        serve_notes(Settings(host="0.0.0.0"))
    assert "WITHOUT authentication" in serve_notes(Settings(host="0.0.0.0", insecure_bind=True))[0]
    for host in ("127.0.0.1", "localhost", "::1", "127.0.0.2"):
        assert "WITHOUT authentication" in serve_notes(Settings(host=host))[0]


# -- the Host header ----------------------------------------------------------------------------
@pytest.mark.service
@pytest.mark.slow
def test_host_header_must_name_this_server(example_store, tmp_path):
    store, ids = example_store
    server = Server(store, tmp_path / "s.sqlite3", env={"YAUYAU_ALLOWED_HOSTS": None})  # the default
    try:
        port = server.port
        for host in ("evil.example", f"evil.example:{port}", "127.0.0.1.nip.io", "[::2]", "localhost.evil"):
            for path in ("/v1/models", "/metrics", "/openapi.json", "/v1/sessions/x/view"):
                body = problem(httpx.get(server.url + path, headers={"Host": host}), 400, "Host")
                assert "YAUYAU_ALLOWED_HOSTS" in body["detail"]
            for path in ("/livez", "/readyz"):  # probes by IP address: any Host
                assert httpx.get(server.url + path, headers={"Host": host}).status_code == 200
        for host in (f"localhost:{port}", f"127.0.0.1:{port}", f"[::1]:{port}", "LOCALHOST", "localhost."):
            assert httpx.get(server.url + "/v1/models", headers={"Host": host}).status_code == 200, host
        assert httpx.post(server.url + "/v1/sessions", json={"model": ids["ou"]},
                          headers={"Host": "evil.example"}).status_code == 400
    finally:
        log = server.kill()
    assert "WITHOUT authentication" in log  # said at start
    server = Server(store, tmp_path / "s.sqlite3", env={"YAUYAU_ALLOWED_HOSTS": "api.example.org, 127.0.0.1"})
    try:
        named = httpx.get(server.url + "/v1/models", headers={"Host": "api.example.org:443"})
        assert named.status_code == 200
        problem(httpx.get(server.url + "/v1/models", headers={"Host": "localhost"}), 400, "Host")
    finally:
        server.kill()


# -- no server path in a 5xx ----------------------------------------------------------------------
@pytest.mark.service
@pytest.mark.slow
def test_no_server_path_in_503_problems(example_store, tmp_path):
    store, ids = example_store
    db = tmp_path / "sessions.sqlite3"
    server = Server(store, db)
    try:
        sid = httpx.post(server.url + "/v1/sessions", json={"model": ids["ou"]}).json()["id"]
        chunk = {"seq": 0, "increments": ROWS}
        assert httpx.post(f"{server.url}/v1/sessions/{sid}/observations", json=chunk).status_code == 200
        db.unlink()
        chunk["seq"] = 1
        answers = [httpx.post(f"{server.url}/v1/sessions/{sid}/observations", json=chunk),
                   httpx.get(server.url + "/readyz"), httpx.get(f"{server.url}/v1/sessions/{sid}"),
                   httpx.post(server.url + "/v1/sessions", json={"model": ids["ou"]})]
    finally:
        log = server.kill()
    private = {str(tmp_path), str(db), db.name, str(store), tempfile.gettempdir(), str(Path.home())}
    for r in answers:
        body = problem(r, 503)
        assert "session database" in body["detail"] and "removed" in body["detail"], body
        assert not [p for p in private if p in r.text], (r.text, private)
    assert str(db) in log  # the operator's log keeps the path


def test_a_5xx_detail_loses_its_paths_a_4xx_keeps_its_text():
    """The safety net of service/problems.py, on what PostgreSQL and the OS put in their messages."""
    from yauyau.service.problems import problem_response

    home = str(Path.home())
    for detail in ('no connection: connection to server on socket "/tmp/.s.PGSQL.5432" failed',
                   f"cannot read {home}/store/ab12.h5 (Permission denied)",
                   "cannot open session database /srv/yauyau/sessions.sqlite3: disk I/O error"):
        shown = problem_response(503, detail).body.decode()
        assert "/tmp/" not in shown and home not in shown and "/srv/" not in shown, shown
        assert "<" in shown  # replaced by what it is, not dropped
    kept = problem_response(404, "no precompute job 'x' (POST /v1/models starts one)").body.decode()
    assert "POST /v1/models" in kept
