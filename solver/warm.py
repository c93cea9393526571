"""Compile (or load from numba's cache) the engine's row loops before the first real chunk.

The compiled loops (solver/engine/compiled.py) are compiled on first use, per argument type: about 4 s
the first time on a machine, about 0.7 s in each later process (numba's import and its on-disk cache,
solver/jit.py ``cache_dir``).  :func:`warm_kernels` pays that up front — ``yauyau precompute``
(which fills the cache), and the service's start-up (so no timed request pays it) — by running a tiny
1-D filter through every compiled loop (regular, irregular, a moving ball, fused or keeping σ, streams
stepped together), in double and single precision: the same calls, with the same array types, as any
model's chunks; and a 1-D Yau–Jia filter through its kernels (solver/exact/yau_jia_fast.py), and 2-D
Yau–Niu filters of independent sensors and of a coupled block through theirs (solver/qmc/kernels.py).
"""

from __future__ import annotations

import time

import numpy as np

from . import jit

_TOY = {"name": "warm-up", "state": ["x"], "drift": ["-x"], "observation": ["x"],
        "initial": {"kind": "gaussian", "mean": [0.0], "cov": [[0.5]]},
        "domain": {"radius": 4.0}, "discretization": {"dt": 0.05, "basis": 8}, "method": "yau-yau"}
_DONE: list[float] = []


def warm_kernels() -> float | None:
    """Seconds it took to make the compiled loops ready in this process (0 when they already were);
    None where they are off (``YAUYAU_KERNEL=numpy`` or no numba)."""
    if not jit.enabled():
        return None
    if _DONE:
        return 0.0
    from .methods import make_filter
    from .model import compile_model
    from .offline.pipeline import precompute
    from .spec import spec_from_dict

    started = time.perf_counter()
    # every row observed: the fused loop (solver/engine/fused.py); a missing row: the loops that keep σ
    chunks = (np.zeros((4, 1)), np.array([[0.0], [np.nan], [0.0], [0.0]]))
    times = np.array([0.05, 0.12, 0.2, 0.31])
    for follow in (False, True):
        domain = {"radius": 4.0, "follow": True} if follow else {"radius": 4.0}
        drift = ["1"] if follow else ["-x"]  # a following ball needs a shift-invariant or affine drift
        model = compile_model(spec_from_dict({**_TOY, "domain": domain, "drift": drift}))
        offline = precompute(model)
        for precision in ("double", "single"):
            flt = make_filter(model, offline, "yau-yau", precision=precision)
            state = flt.initial_state()
            for rows in chunks:
                flt.run_arrays(state, rows)
                if not follow:
                    flt.run_arrays(state, rows, times)
    # streams stepped together (solver/engine/compiled_batch.py; in double the rows take one product PΠ
    # on this mesh, in single two: the same array types as any model's)
    batched = {**_TOY, "discretization": {"dt": 0.05, "basis": 8, "mesh": 4}}
    model = compile_model(spec_from_dict(batched))
    offline = precompute(model)
    for precision in ("double", "single"):
        flt = make_filter(model, offline, "yau-yau", precision=precision)
        flt.run_batch([flt.initial_state()] * 2, [chunks[0]] * 2)
    # the Yau–Jia filter's kernels (solver/exact/yau_jia_fast.py): observed, missing and gated rows, a gap
    # in pieces; their array types do not depend on the dimension
    toy = {**_TOY, "observation": ["sqrt(1 + x**2)"], "method": "yau-jia"}
    flt = make_filter(compile_model(spec_from_dict(toy)), None, "yau-jia")
    rows = np.array([[0.05], [np.nan], [0.04], [5.0]])
    flt.run_arrays(flt.initial_state(), rows, np.array([0.05, 0.1, 2.0, 2.05]))
    # the Yau–Niu row of independent one-coordinate blocks (solver/qmc/kernels.py): increments, Gaussian
    # and Student-t readings, a missing component
    two = {**_TOY, "state": ["x", "y"], "drift": ["-x", "-y"], "observation": ["x", "y**3"],
           "observation_noise": [[1.0, 0.0], [0.0, 1.0]], "method": "yau-niu",
           "initial": {"kind": "gaussian", "mean": [0.0, 0.0], "cov": [[0.5, 0.0], [0.0, 0.5]]},
           "discretization": {"dt": 0.05, "points": 64}}
    rows = np.array([[0.05, 0.01], [np.nan, 0.02]])
    for measurement in ({"kind": "continuous"}, {"kind": "discrete"},
                        {"kind": "discrete", "likelihood": "student-t", "dof": 4}):
        flt = make_filter(compile_model(spec_from_dict({**two, "measurement": measurement})), None, "yau-niu")
        flt.run_arrays(flt.initial_state(), rows)
    # ... and of a coupled block (solver/qmc/coupled.py)
    ring = {**two, "drift": ["-x + 0.5*tanh(y)", "-y"]}
    flt = make_filter(compile_model(spec_from_dict(ring)), None, "yau-niu")
    flt.run_arrays(flt.initial_state(), rows)
    _DONE.append(time.perf_counter() - started)
    return _DONE[0]
