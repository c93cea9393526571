"""Shared fixtures: a model store with precomputed example models, a PostgreSQL server; the order of
the files.  What tests import (paths, ports, servers, references) is in tests/helpers/."""

from __future__ import annotations

from pathlib import Path

import pytest
from helpers import EXAMPLES, precompute_into
from pg_server import PostgresServer


def pytest_collection_modifyitems(config, items):
    """The files with ``slow`` tests first (the order within a file kept): with parallel workers
    (``--dist loadfile``) the longest files start at once instead of last, on one worker."""
    slow = {item.path for item in items if item.get_closest_marker("slow")}
    items.sort(key=lambda item: item.path not in slow)


@pytest.fixture(scope="session", autouse=True)
def _testclient_host():
    """Starlette's TestClient sends ``Host: testserver``: the in-process apps of the tests accept that
    name besides the loopback ones (the Host check, service/http/tenants.py; servers the tests start
    inherit the list, and tests of the check set their own)."""
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("YAUYAU_ALLOWED_HOSTS", "testserver,localhost,127.0.0.1,::1")
        yield


@pytest.fixture(scope="session")
def example_store(tmp_path_factory) -> tuple[Path, dict[str, str]]:
    """A store holding the 1-D examples (cubic sensor, Ornstein–Uhlenbeck): (dir, {name: id})."""
    store = tmp_path_factory.mktemp("store")
    ids = {name: precompute_into(store, EXAMPLES / f"{name}.toml") for name in ("cubic_sensor", "ou")}
    return store, ids


@pytest.fixture(scope="session")
def postgres():
    """A real PostgreSQL server for the session (scripts/pg_server.py); ``database(name)`` gives a fresh
    database's DSN."""
    server = PostgresServer()
    yield server
    server.stop()
