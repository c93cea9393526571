"""``OnlineFilter.smooth`` (yauyau/api.py): the engine's smoother through open_filter, a method without a
smoother refused by name.  The numbers are checked against independent references in
tests/solver/engine/test_smoother.py and tests/solver/exact/test_kalman_smoother.py."""

from __future__ import annotations

import tomllib

import numpy as np
import pytest
from helpers import EXAMPLES
from yauyau.solver import spec_from_dict

import yauyau


@pytest.fixture(scope="module")
def stored(tmp_path_factory):
    doc = tomllib.loads((EXAMPLES / "ou.toml").read_text())
    doc["discretization"]["basis"] = 48
    doc["domain"]["radius"] = 6.0
    spec = spec_from_dict(doc)
    store = tmp_path_factory.mktemp("store")
    return spec, store, yauyau.precompute(spec, store)


def test_smooth_through_open_filter(stored):
    spec, store, model_id = stored
    sim = yauyau.simulate(spec, steps=200, seed=2)
    flt = yauyau.open_filter(store, model_id, method="yau-yau")
    result = flt.smooth(sim.increments)
    assert len(result) == 200 and result.mean.shape == (200, 1) and result.cov.shape == (200, 1, 1)
    filtered = yauyau.open_filter(store, model_id, method="yau-yau").run(sim.increments)
    assert abs(result.mean[-1, 0] - filtered.mean[-1, 0]) < 1e-12  # the last row: the filter
    assert np.all(result.cov[:-1, 0, 0] < filtered.cov[:-1, 0, 0])  # everywhere else: more data
    assert flt.state.step == 200  # the filter stands after the chunk, as run leaves it
    lagged = yauyau.open_filter(store, model_id, method="yau-yau").smooth(sim.increments[:30], lag=3)
    assert len(lagged) == 30


def test_a_method_without_smoother_is_refused_by_name(stored):
    _, store, model_id = stored
    flt = yauyau.open_filter(store, model_id, method="yau-jia")
    with pytest.raises(yauyau.SpecError) as err:
        flt.smooth(np.zeros((5, 1)))
    assert err.value.field == "method" and "yau-jia" in str(err.value) and "yau-yau" in str(err.value)


def test_smooth_quantiles_through_open_filter(stored):
    """The smoothed quantiles beside the smoothed moments: OU's smoothed law is Gaussian, so the median is
    the mean and the 0.1/0.9 quantiles are mean ∓ 1.2816 sd (within 5e-3; measured 1.9e-3 on 48 basis
    functions); the moments are smooth()'s."""
    spec, store, model_id = stored
    sim = yauyau.simulate(spec, steps=120, seed=4)
    result, table = yauyau.open_filter(store, model_id, method="yau-yau").smooth_quantiles(
        sim.increments, [0.1, 0.5, 0.9])
    plain = yauyau.open_filter(store, model_id, method="yau-yau").smooth(sim.increments)
    assert np.abs(result.mean - plain.mean).max() < 1e-12 and table.shape == (120, 1, 3)
    sd = np.sqrt(result.cov[:, 0, 0])
    expected = result.mean[:, 0, None] + sd[:, None] * np.array([-1.2815516, 0.0, 1.2815516])
    print(f"api smoothed quantiles vs Gaussian: {np.abs(table[:, 0, :] - expected).max():.1e}")
    assert np.abs(table[:, 0, :] - expected).max() < 5e-3
