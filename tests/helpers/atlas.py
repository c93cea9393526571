"""The sin-drift atlas (f = 0.8 + 0.3 sin x, h = x, unit noises; tests/solver/engine/test_atlas.py and
examples/sin_drift_atlas.toml) and its fine-grid reference.

Truth: the point-mass filter of helpers/irregular_refs.py (finite volumes, zero flux) on a box that
holds the whole path, [-17.5, 72.5] with 2400 cells, exact in time (the dense exp(dt L), computed once)
and with the same continuous-increment likelihood exp(h dy - h^2 dt / 2).
"""

from __future__ import annotations

import json

import numpy as np
import scipy.linalg as sla
from yauyau.solver import compile_model, spec_from_dict

from helpers.irregular_refs import GridReference

SIN = {"name": "sin drift", "state": ["x"], "drift": ["0.8 + 0.3*sin(x)"], "observation": ["x"],
       "method": "yau-yau", "initial": {"kind": "gaussian", "mean": [0.0], "cov": [[1.0]]},
       "domain": {"radius": 6.0, "follow": True, "region": [[-5.0, 60.0]]},
       "discretization": {"dt": 0.02, "basis": 48}}


def reference_means(model, increments, cells=2400):
    """The fine-grid filter's posterior means (module docstring) on [-17.5, 72.5]."""
    doc = json.loads(json.dumps(SIN))
    doc["domain"] = {"radius": 45.0, "center": [27.5]}
    grid = GridReference(compile_model(spec_from_dict(doc)), cells=cells, method="expm_multiply")
    step = sla.expm(model.dt * grid.L.toarray())
    x, hx = grid.points[:, 0], grid.hx[:, 0]
    w, means = grid.w0.copy(), np.empty(len(increments))
    for k, dy in enumerate(increments[:, 0]):
        w = step @ w
        ell = hx * dy - 0.5 * hx * hx * model.dt
        w = w * np.exp(ell - ell.max())
        w /= w.sum()
        means[k] = w @ x
    return means
