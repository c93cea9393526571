"""What the tests share, importable from any test folder (pyproject.toml puts tests/ on sys.path
through pytest's ``pythonpath``): the checkout's paths, free loopback ports, precomputed examples.

The other modules here: ``server`` (a real `yauyau serve` process and its client calls), ``readme``
(the README's blocks), ``cluster`` (a real Dask cluster), ``atlas`` (the sin-drift atlas and its
fine-grid reference), ``specs``, and the independent references ``oracles``, ``irregular_refs`` and
``loop_moves``.
"""

from __future__ import annotations

import socket
from pathlib import Path

import yauyau

ROOT = Path(__file__).resolve().parents[2]
EXAMPLES = ROOT / "examples"


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def precompute_into(store: Path, spec_path: Path) -> str:
    """Solve the offline stage of an example spec and save it (method chosen once); returns the id."""
    return yauyau.precompute(spec_path, store)
