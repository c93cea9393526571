"""docs/models.md's "A state that travels" section runs as printed, and its numbers are the exact Kalman
filter's (the example is linear: KalmanBucyFilter(kind="discrete") on the same increments)."""

from __future__ import annotations

import re

import pytest
from helpers import ROOT
from helpers.atlas import reference_means
from helpers.readme import run_python_block

pytestmark = pytest.mark.slow  # every test here takes seconds of CPU: the full run only

PAGE = "docs/models.md"
SECTION = "A state that travels: a ball that follows it"


def _printed(stdout: str) -> tuple[float, float, float, float, str]:
    """x, mean, ball centre, moves and the degenerate flag of the block's printed line."""
    found = re.search(r"x = (-?[\d.]+): mean (-?[\d.]+), ball centre (-?[\d.]+), (\d+) moves, degenerate: "
                      r"(\w+)", stdout)
    return (*(float(v) for v in found.groups()[:4]), found.group(5))


def test_python_block_follows_the_state_and_matches_kalman(tmp_path):
    from yauyau.solver.exact.kalman_bucy import KalmanBucyFilter

    import yauyau

    stdout = run_python_block(SECTION, tmp_path, PAGE)
    x, mean, centre, moves, degenerate = _printed(stdout)
    spec = yauyau.load_spec(ROOT / "examples" / "random_walk_trend.toml")
    sim = yauyau.simulate(spec, steps=5000, seed=1)
    kalman = KalmanBucyFilter(yauyau.compile_model(spec), kind="discrete")
    _, exact = kalman.run_arrays(kalman.initial_state(), sim.increments)
    assert x == round(float(sim.states[-1, 0]), 2) and x > 20  # far beyond the radius 6
    assert abs(mean - exact.mean[-1, 0]) <= 0.006  # printed to 2 decimals; the gap itself is < 1e-3
    assert abs(centre - mean) < 1.5 and moves > 20 and degenerate == "False"


ATLAS_SECTION = "A drift that changes along the way: an atlas of balls"


def test_atlas_block_follows_a_drift_that_is_not_shift_invariant(tmp_path):
    """The printed mean against the fine-grid reference of tests/helpers/atlas.py on the same path."""
    import yauyau

    stdout = run_python_block(ATLAS_SECTION, tmp_path, PAGE)
    x, mean, centre, moves, degenerate = _printed(stdout)
    spec = yauyau.load_spec(ROOT / "examples" / "sin_drift_atlas.toml")
    sim = yauyau.simulate(spec, steps=3000, seed=2)
    truth = reference_means(yauyau.compile_model(spec), sim.increments)
    assert x == round(float(sim.states[-1, 0]), 2) and x > 25  # four radii beyond the start
    assert abs(mean - truth[-1]) <= 0.015  # printed to 2 decimals; the gap itself is < 0.01
    assert abs(centre - mean) < 1.5 and moves > 30 and degenerate == "False"


PSD_SECTION = "Noise on some coordinates only: constant-velocity tracking"


def test_constant_velocity_block_follows_the_target_and_matches_kalman(tmp_path):
    """The printed mean and velocity against the exact Kalman filter of the sampled model."""
    from yauyau.solver.exact.kalman_bucy import KalmanBucyFilter

    import yauyau

    stdout = run_python_block(PSD_SECTION, tmp_path, PAGE)
    found = re.search(r"p = (-?[\d.]+): mean (-?[\d.]+), velocity (-?[\d.]+), (\d+) moves, degenerate: (\w+)",
                      stdout)
    p, mean, velocity, moves = (float(v) for v in found.groups()[:4])
    spec = yauyau.load_spec(ROOT / "examples" / "constant_velocity.toml")
    sim = yauyau.simulate(spec, steps=2000, seed=1)
    kalman = KalmanBucyFilter(yauyau.compile_model(spec), kind="discrete")
    _, exact = kalman.run_arrays(kalman.initial_state(), sim.increments)
    assert p == round(float(sim.states[-1, 0]), 2) and abs(p) > 8  # beyond the radius
    assert abs(mean - exact.mean[-1, 0]) <= 0.03 and abs(velocity - exact.mean[-1, 1]) <= 0.03
    assert moves > 5 and found.group(5) == "False"
