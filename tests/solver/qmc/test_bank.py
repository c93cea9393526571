"""The Yau–Niu filter's bank of QMC normal sets (solver/qmc/bank.py).

Each draw must be a standard normal set (its moments and its distribution function against the normal
law's, written here), the signed order of the coordinates folded into the diffusion's root must give the
deviates it stands for, the signs must take both values and every set must be drawn, and a filter's rows
must draw from the bank instead of building a Sobol set each: over 40 rows of the coupled ring with
restarts, only the bank's sets are built.  The filter's accuracy with the bank is proved in
test_yau_niu.py (the Kalman filter at 4 and 6 states, a particle reference of the ring).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.special import ndtr
from yauyau.solver.model import compile_model
from yauyau.solver.qmc import bank as bank_module
from yauyau.solver.qmc.bank import SETS, Banks, NormalBank, bank_sets, deviates
from yauyau.solver.qmc.yau_niu import YauNiuFilter
from yauyau.solver.simulate import simulate
from yauyau.solver.spec import spec_from_dict


def test_each_draw_is_a_standard_normal_set():
    bank, rng = NormalBank(8192, 4, seed=3), np.random.default_rng(0)
    for _ in range(5):
        Z, offset, cols, signs = drawn = bank.draw(rng)
        z = deviates(*drawn)
        assert np.abs(z.mean(axis=0)).max() < 2e-3  # N(0, 1): mean 0 (iid sampling: sd 0.011)
        assert np.abs(np.cov(z.T) - np.eye(4)).max() < 5e-3  # covariance I (iid: sd ~0.016)
        for j in range(4):  # the distribution function: Kolmogorov distance to Φ (iid: ~0.9/√N = 0.01)
            x = np.sort(z[:, j])
            empirical = np.arange(1, len(x) + 1) / len(x)
            assert np.abs(empirical - ndtr(x)).max() < 1e-3
        assert 0 <= offset < 8192 and sorted(cols.tolist()) == [0, 1, 2, 3]
        # point i takes the set's point (i + offset) mod N, its coordinates in the signed order
        i = 8191 - offset // 2
        np.testing.assert_array_equal(z[i], [signs[j] * Z[(i + offset) % 8192, cols[j]] for j in range(4)])


def test_the_signed_order_folds_into_the_root():
    """Z @ M = (Z[:, cols] · signs) @ root for the root M the bank gives."""
    bank, rng = NormalBank(64, 3, seed=0), np.random.default_rng(1)
    root = rng.standard_normal((3, 3))
    Z, _, cols, signs = bank.draw(rng)
    folded = Z @ NormalBank.root(root, cols, signs)
    by_definition = np.column_stack([signs[j] * Z[:, cols[j]] for j in range(3)]) @ root
    np.testing.assert_allclose(folded, by_definition, rtol=0, atol=1e-13)


def test_draws_take_every_set_both_signs_and_new_orders():
    bank, rng = NormalBank(256, 2, seed=0), np.random.default_rng(2)
    assert bank.sets.shape == (SETS, 256, 2)
    seen_sets, signs, firsts = set(), [], set()
    for _ in range(400):
        Z, offset, _, s = bank.draw(rng)
        seen_sets.add(next(i for i in range(SETS) if np.shares_memory(Z, bank.sets[i])))
        signs.append(s)
        firsts.add(offset)
    assert seen_sets == set(range(SETS))
    share = (np.array(signs) > 0).mean()
    assert abs(share - 0.5) < 0.05  # 800 fair signs: sd 0.018
    assert len(firsts) > 150  # a new offset each row (400 draws of 256: ~200 distinct)


def test_a_bank_is_fixed_by_its_seed_and_sized_by_memory():
    np.testing.assert_array_equal(NormalBank(128, 2, 7).sets, NormalBank(128, 2, 7).sets)
    assert not np.array_equal(NormalBank(128, 2, 7).sets, NormalBank(128, 2, 8).sets)
    assert bank_sets(8192, 4) == SETS
    assert bank_sets(2**20, 100) == 1  # 800 MB a set: one
    assert bank_sets(2**20, 4) * 8 * 2**20 * 4 <= bank_module.MAX_BYTES
    banks = Banks(2, keep=2)
    first = banks.get(0, 64)
    assert banks.get(0, 64) is first
    banks.get(1, 64), banks.get(2, 64)
    assert banks.get(0, 64) is not first  # the least recently built was dropped


def ring(points: int):
    doc = {"name": "ring", "state": [f"x{i}" for i in range(4)],
           "drift": [f"-x{i} + 0.5*tanh(x{(i + 1) % 4})" for i in range(4)],
           "observation": [f"x{i}**3" for i in range(4)], "method": "yau-niu",
           "observation_noise": (0.05 * np.eye(4)).tolist(),
           "initial": {"kind": "gaussian", "mean": [0.5] * 4, "cov": np.eye(4).tolist()},
           "discretization": {"dt": 0.01, "points": points}}
    return compile_model(spec_from_dict(doc))


@pytest.mark.parametrize("kernel", ["numpy", "compiled"])
def test_rows_draw_from_the_bank_instead_of_building_sets(monkeypatch, kernel):
    monkeypatch.setenv("YAUYAU_KERNEL", kernel)
    built = []
    original = bank_module.sobol_set
    monkeypatch.setattr(bank_module, "sobol_set", lambda *a: built.append(a[:2]) or original(*a))
    model = ring(512)
    flt = YauNiuFilter(model, seed=0)
    state = flt.initial_state()
    rows = simulate(model, 40, np.random.default_rng(0)).increments
    state, result = flt.run_arrays(state, rows)
    assert state.restarts > 0 and np.isfinite(result.mean).all()
    # the bank's sets only (the prior's own set comes through cloud.qmc_normals)
    assert len(built) == bank_sets(512, 4) and all(shape == (512, 4) for shape in built)
    assert math.isfinite(state.loglik)
