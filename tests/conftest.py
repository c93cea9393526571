"""Shared fixtures: a model store with precomputed example models, free loopback ports."""

from __future__ import annotations

import os
import socket
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
EXAMPLES = ROOT / "examples"


def pytest_configure(config):
    """Under pytest-xdist (``python3 dev.py test``), each worker's BLAS gets its share of the cores: two
    workers with a thread per core each would oversubscribe the dense solves."""
    workers = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "0"))
    if workers > 1:
        from threadpoolctl import threadpool_limits

        config._blas_share = threadpool_limits(max(1, (os.cpu_count() or 1) // workers))


def pytest_collection_modifyitems(config, items):
    """The files with ``slow`` tests first (the order within a file kept): with parallel workers
    (``--dist loadfile``) the longest files start at once instead of last, on one worker."""
    slow = {item.path for item in items if item.get_closest_marker("slow")}
    items.sort(key=lambda item: item.path not in slow)


def precompute_into(store: Path, spec_path: Path) -> str:
    """Solve the offline stage of an example spec and save it (method chosen once); returns the id."""
    import yauyau

    return yauyau.precompute(spec_path, store)


@pytest.fixture(scope="session")
def example_store(tmp_path_factory) -> tuple[Path, dict[str, str]]:
    """A store holding the 1-D examples (cubic sensor, Ornstein–Uhlenbeck): (dir, {name: id})."""
    store = tmp_path_factory.mktemp("store")
    ids = {name: precompute_into(store, EXAMPLES / f"{name}.toml") for name in ("cubic_sensor", "ou")}
    return store, ids


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


@pytest.fixture(scope="session")
def postgres():
    """A real PostgreSQL server for the session (tests/pg_server.py); ``database(name)`` gives a fresh
    database's DSN."""
    sys.path.insert(0, str(ROOT / "scripts"))
    from pg_server import PostgresServer

    server = PostgresServer()
    yield server
    server.stop()
