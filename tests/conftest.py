"""Shared fixtures: a model store with precomputed example models, free loopback ports."""

from __future__ import annotations

import socket
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
EXAMPLES = ROOT / "examples"


def precompute_into(store: Path, spec_path: Path) -> str:
    """Solve the offline stage of an example spec and save it; returns the model id."""
    from yauyau.solver.model import compile_model
    from yauyau.solver.offline import precompute
    from yauyau.solver.spec import load_spec
    from yauyau.storage.model_store import ModelStore

    spec = load_spec(spec_path)
    offline = precompute(compile_model(spec))
    return ModelStore(store).save(spec.canonical_json(), offline.to_arrays(), {"source": spec_path.name})


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
