"""solver/warm.py: after :func:`warm_kernels` no chunk compiles — the first chunk of every bundled
kind of model (1-D and 2-D, regular and irregular rows, a following ball; double and single precision)
finds its compiled loops already typed for its arrays (numba's signatures do not grow).  Each case in a
fresh process, since a process keeps what it compiled."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest
from helpers import ROOT

pytest.importorskip("numba")

PROBE = """
import json, sys
import numpy as np
from yauyau.solver import compile_model, load_spec
from yauyau.solver.engine import compiled, compiled_batch
from yauyau.solver.methods import make_filter
from yauyau.solver.offline.pipeline import precompute
from yauyau.solver.warm import warm_kernels

spec = load_spec(sys.argv[1])
spec = spec.model_copy(update={"discretization": spec.discretization.model_copy(update={"basis": 24})})
model = compile_model(spec)
offline = precompute(model)
seconds = warm_kernels()
loops = ("run_rows", "run_modal", "run_moving", "run_fused", "sum_rows", "exp_factors")
count = lambda: (sum(len(getattr(compiled, f).signatures) for f in loops)
                 + len(compiled_batch.run_fused_batch.signatures))
warmed = count()
for precision in ("double", "single"):
    flt = make_filter(model, offline, "yau-yau", precision=precision)
    rows = np.zeros((6, len(spec.observation)))
    flt.run_arrays(flt.initial_state(), rows)
    flt.run_batch([flt.initial_state()] * 2, [rows] * 2)
    if not spec.domain.follow:
        flt.run_arrays(flt.initial_state(), rows, spec.discretization.dt * np.array([1, 2.5, 3, 4.2, 6, 7]))
print(json.dumps({"seconds": seconds, "warmed": warmed, "after": count(), "again": warm_kernels()}))
"""


@pytest.mark.parametrize("example", ["cubic_sensor", "range_2d", "random_walk_trend"])
def test_no_chunk_compiles_after_the_warm_up(example, tmp_path):
    env = dict(os.environ, YAUYAU_CACHE_DIR=str(tmp_path / "cache"))
    env.pop("YAUYAU_KERNEL", None)
    done = subprocess.run([sys.executable, "-c", PROBE, str(ROOT / "examples" / f"{example}.toml")],
                          env=env, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    out = json.loads(done.stdout.strip().splitlines()[-1])
    assert isinstance(out["seconds"], float) and out["again"] == 0.0  # warmed here, then nothing left to do
    # 7 kernels x (double, single): nothing new
    assert out["warmed"] == 14 and out["after"] == out["warmed"]


def test_the_warm_up_is_off_with_the_numpy_kernel(monkeypatch):
    from yauyau.solver.warm import warm_kernels

    monkeypatch.setenv("YAUYAU_KERNEL", "numpy")
    assert warm_kernels() is None


NIU_PROBE = """
import json
import numpy as np
from yauyau.solver import compile_model
from yauyau.solver.methods import make_filter
from yauyau.solver.qmc import kernels
from yauyau.solver.spec import spec_from_dict
from yauyau.solver.warm import warm_kernels

n = 12
doc = {"name": "sensors", "state": [f"x{i}" for i in range(n)], "drift": [f"-0.5*x{i}" for i in range(n)],
       "observation": [f"x{i}**3" for i in range(n)], "observation_noise": np.eye(n).tolist(),
       "method": "yau-niu", "initial": {"kind": "gaussian", "mean": [0.5] * n, "cov": np.eye(n).tolist()},
       "discretization": {"dt": 0.01, "points": 256}}
warm_kernels()
loops = ("kolmogorov", "log_factors", "normalise", "moments")
count = lambda: sum(len(getattr(kernels, f).signatures) for f in loops)
warmed = count()
rows = np.random.default_rng(0).normal(size=(5, n)) * 0.1
rows[1, 3] = np.nan
rows[2] = np.nan
for measurement in ({"kind": "continuous"}, {"kind": "discrete"},
                    {"kind": "discrete", "likelihood": "student-t", "dof": 5}):
    flt = make_filter(compile_model(spec_from_dict({**doc, "measurement": measurement})), None, "yau-niu")
    state, _ = flt.run_arrays(flt.initial_state(), rows)
    flt.run_arrays(state, rows, state.t + np.array([0.01, 0.035, 0.04, 0.06, 0.07]))
print(json.dumps({"warmed": warmed, "after": count()}))
"""


@pytest.mark.slow  # a fresh cache: every kernel compiled (~70 s on a loaded machine)
def test_no_yau_niu_chunk_compiles_after_the_warm_up(tmp_path):
    """The same for the Yau–Niu row of independent sensors (solver/qmc/kernels.py), 12 states."""
    env = dict(os.environ, YAUYAU_CACHE_DIR=str(tmp_path / "cache"))
    env.pop("YAUYAU_KERNEL", None)
    done = subprocess.run([sys.executable, "-c", NIU_PROBE], env=env, capture_output=True, text=True,
                          timeout=600)
    assert done.returncode == 0, done.stderr
    out = json.loads(done.stdout.strip().splitlines()[-1])
    assert out["warmed"] >= 4 and out["after"] == out["warmed"], out
