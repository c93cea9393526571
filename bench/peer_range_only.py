"""The peers on a linear-Gaussian state seen through a nonlinear sensor: `particles`' bootstrap filter
and FilterPy's UKF (constant-velocity range-only tracking; a linear drift with a cubic sensor).

    bench/out/peers-venv/bin/python bench/peer_range_only.py IN.npz OUT.npz

Runs in its OWN virtual environment (bench/out/peers-venv, made by
``python -m bench.measurements --setup-peers``: particles pins numpy < 2, which yauyau does not
support), so bench/yau_jia.py and bench/range_2d.py call this script as a subprocess.  This file
imports nothing from yauyau.

The sampled model (state x = (p, v), p and v of ``dims`` coordinates each):

    x_k = Φ x_{k−1} + N(0, Q),   Δy_k ~ N(h(x_k) dt, R dt),

with Φ and Q the exact Gaussian transition of the linear drift over dt (computed by the caller) and
h chosen by ``sensor``: "range" (the default), h(x) = √(offset + |p|²) with p the first half of x;
"cube1", h(x) = x1·x1·x1.

IN.npz: ``increments`` (S, K), ``seeds`` (S,), ``Phi``, ``Q``, ``prior_mean``, ``prior_cov``,
``dt``, ``noise_var``, ``offset``, ``particles`` (N), optionally ``sensor`` ("range" or "cube1").
OUT.npz: ``pf_means`` (S, K, n), ``pf_seconds`` (S,) (CPU time of ``SMC.run``), ``ukf_means``,
``ukf_seconds`` (S,), ``versions`` — all with one BLAS thread.
"""

from __future__ import annotations

import os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import sys  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402

SENSOR = "range"  # set by main() from IN.npz


def sensor(x: np.ndarray, dims: int, offset: float) -> np.ndarray:
    if SENSOR == "cube1":
        return x[..., 0] * x[..., 0] * x[..., 0]
    return np.sqrt(offset + (x[..., :dims] ** 2).sum(-1))


def bootstrap(data, seed: int, N: int, Phi, Q, mean0, cov0, dt, r, offset):
    from particles import distributions as dists
    from particles import state_space_models as ssm

    dims = len(mean0) // 2

    class LinearGaussian(ssm.StateSpaceModel):
        def PX0(self):
            return dists.MvNormal(loc=mean0, cov=cov0)

        def PX(self, t, xp):
            return dists.MvNormal(loc=xp @ Phi.T, cov=Q)

        def PY(self, t, xp, x):
            return dists.Normal(loc=sensor(x, dims, offset) * dt, scale=np.sqrt(r * dt))

    return run_bootstrap(ssm.Bootstrap(ssm=LinearGaussian(), data=data), seed, N)


def run_bootstrap(fk, seed: int, N: int):
    """particles' SMC on the Feynman–Kac model ``fk`` with N particles, numpy's global generator seeded:
    the filtering means (K, n) and the CPU seconds of ``SMC.run``."""
    import particles

    np.random.seed(seed)
    alg = particles.SMC(fk=fk, N=N, collect=[particles.collectors.Moments()])
    start = time.process_time()
    alg.run()
    seconds = time.process_time() - start
    return np.array([m["mean"] for m in alg.summaries.moments]), seconds


def unscented(data, Phi, Q, mean0, cov0, dt, r, offset):
    """FilterPy's UKF (Merwe sigma points, α = 0.1, β = 2, κ = 0)."""
    from filterpy.kalman import MerweScaledSigmaPoints, UnscentedKalmanFilter

    n = len(mean0)
    points = MerweScaledSigmaPoints(n, alpha=0.1, beta=2.0, kappa=0.0)
    ukf = UnscentedKalmanFilter(dim_x=n, dim_z=1, dt=dt, points=points, fx=lambda x, _dt: Phi @ x,
                                hx=lambda x: np.array([sensor(x, n // 2, offset) * dt]))
    ukf.x, ukf.P = mean0.copy(), cov0.copy()
    ukf.Q, ukf.R = Q, np.array([[r * dt]])
    means = []
    start = time.process_time()
    for dy in data:
        ukf.predict()
        ukf.update(np.array([dy]))
        means.append(ukf.x.copy())
    return np.array(means), time.process_time() - start


def main(argv: list[str]) -> int:
    src, dst = argv[1], argv[2]
    d = np.load(src)
    global SENSOR
    SENSOR = str(d["sensor"]) if "sensor" in d.files else "range"
    if SENSOR not in ("range", "cube1"):
        raise SystemExit(f"sensor must be 'range' or 'cube1', got {SENSOR!r}")
    args = (d["Phi"], d["Q"], d["prior_mean"], d["prior_cov"], float(d["dt"]), float(d["noise_var"]),
            float(d["offset"]))
    pf_means, pf_seconds, ukf_means, ukf_seconds = [], [], [], []
    # warm-up outside the timed runs: particles' imports and numba's compilation of its resampler
    bootstrap(d["increments"][0][:5], 0, int(d["particles"]), *args)
    unscented(d["increments"][0][:5], *args)
    for data, seed in zip(d["increments"], d["seeds"], strict=True):
        means, seconds = bootstrap(data, int(seed), int(d["particles"]), *args)
        pf_means.append(means)
        pf_seconds.append(seconds)
        means, seconds = unscented(data, *args)
        ukf_means.append(means)
        ukf_seconds.append(seconds)
    import filterpy
    import particles

    np.savez(dst, pf_means=np.array(pf_means), pf_seconds=np.array(pf_seconds), ukf_means=np.array(ukf_means),
             ukf_seconds=np.array(ukf_seconds),
             versions=np.array([f"particles {particles.__version__}", f"filterpy {filterpy.__version__}",
                                f"numpy {np.__version__}"]))
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv))
