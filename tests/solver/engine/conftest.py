"""The engine tests' models (tests/solver/engine/test_engine.py, test_batch.py), each precomputed once
per module: OU with R ≠ 1 and a ≠ 1, the cubic sensor."""

from __future__ import annotations

import tomllib

import pytest
from helpers import EXAMPLES
from yauyau.solver import compile_model, load_spec, spec_from_dict
from yauyau.solver.offline.pipeline import precompute


def ou_doc() -> dict:
    doc = tomllib.loads((EXAMPLES / "ou.toml").read_text())
    doc["diffusion"] = [[0.7]]
    doc["observation_noise"] = [[0.5]]
    return doc


@pytest.fixture(scope="module", name="ou_doc")
def ou_doc_fixture() -> dict:
    """:func:`ou_doc` for a test that varies it."""
    return ou_doc()


@pytest.fixture(scope="module")
def ou():
    model = compile_model(spec_from_dict(ou_doc()))
    return model, precompute(model)


@pytest.fixture(scope="module")
def cubic():
    model = compile_model(load_spec(EXAMPLES / "cubic_sensor.toml"))
    return model, precompute(model)
