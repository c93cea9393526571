"""The peers on n-state cubic-sensor models: `particles`' bootstrap filter and FilterPy's UKF.

    bench/out/peers-venv/bin/python bench/peer_cubic_nd.py IN.npz OUT.npz

Runs in its OWN virtual environment (bench/out/peers-venv, made by
``python -m bench.measurements --setup-peers``: particles pins numpy < 2, which yauyau does not
support), so bench/yau_niu.py calls this script as a subprocess.  This file imports nothing from
yauyau.

Two models of n states, unit diffusion, continuous increments Δy_k ~ N(h(x_k) dt, dt I) with
h_i(x) = c1·x_i + c3·x_i·x_i·x_i, and x(0) ~ N(prior_mean, I) at t = 0 (the first row at t = dt):

* ``model = "ou"``: dx_i = −0.5 x_i dt + dW_i, the EXACT transition x' = Φx + N(0, (1 − e^{−dt}) I),
  Φ = e^{−0.5 dt};
* ``model = "ring"``: dx_i = (−x_i + 0.5 tanh x_{i+1}) dt + dW_i (indices mod n): no exact transition,
  so Euler–Maruyama with ``substeps`` steps per row (the UKF's fx: the same steps without noise,
  Q = dt I).

IN.npz: ``model``, ``increments`` (K, n), ``seeds`` (S,), ``dt``, ``substeps``, ``c1``, ``c3``,
``prior_mean``, ``particles`` (N), ``ukf`` (1: run the UKF too).
OUT.npz: ``pf_means`` (S, K, n), ``pf_seconds`` (S,) (CPU time of ``SMC.run``), ``ukf_means`` (K, n)
and ``ukf_seconds`` (NaN where not run or where it failed; ``ukf_error`` says why), ``versions`` —
all with one BLAS thread.
"""

from __future__ import annotations

import os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import math  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402
from peer_range_only import run_bootstrap  # noqa: E402  (this folder: the script's sys.path[0])


class Setup:
    def __init__(self, d):
        self.model = str(d["model"])
        self.dt, self.substeps = float(d["dt"]), int(d["substeps"])
        self.c1, self.c3 = float(d["c1"]), float(d["c3"])
        self.prior_mean = float(d["prior_mean"])
        self.n = d["increments"].shape[1]

    def sensor(self, x):
        return self.c1 * x + self.c3 * (x * x * x)

    def drift(self, x):  # the ring's drift (the OU model moves exactly)
        return -x + 0.5 * np.tanh(np.roll(x, -1, axis=-1))

    def euler(self, x, noise: bool):
        small = self.dt / self.substeps
        for _ in range(self.substeps):
            x = x + self.drift(x) * small
            if noise:
                x = x + math.sqrt(small) * np.random.standard_normal(x.shape)
        return x


def bootstrap(setup: Setup, data, seed: int, N: int):
    from particles import distributions as dists
    from particles import state_space_models as ssm

    n, dt = setup.n, setup.dt
    eye = np.eye(n)
    decay, spread = math.exp(-0.5 * dt), math.sqrt(1.0 - math.exp(-dt))

    class Moved(dists.ProbDist):
        """The ring's Euler–Maruyama law of x(t + dt) given xp (None: the prior at t = 0)."""

        dim = n

        def __init__(self, xp):
            self.xp = xp

        def rvs(self, size=None):
            xp = self.xp
            if xp is None:
                xp = setup.prior_mean + np.random.standard_normal((size, n))
            return setup.euler(np.asarray(xp, dtype=float), noise=True)

    class Cubic(ssm.StateSpaceModel):
        def PX0(self):
            if setup.model == "ou":  # N(m, I) moved exactly over dt: N(Φm, Φ² + 1 − e^{−dt}) = N(Φm, I)
                return dists.MvNormal(loc=np.full(n, decay * setup.prior_mean), cov=eye)
            return Moved(None)

        def PX(self, t, xp):
            if setup.model == "ou":
                return dists.MvNormal(loc=decay * xp, scale=spread, cov=eye)
            return Moved(xp)

        def PY(self, t, xp, x):
            return dists.MvNormal(loc=setup.sensor(x) * dt, scale=math.sqrt(dt), cov=eye)

    return run_bootstrap(ssm.Bootstrap(ssm=Cubic(), data=data), seed, N)


def unscented(setup: Setup, data):
    """FilterPy's UKF (Merwe sigma points, α = 0.1, β = 2, κ = 0)."""
    from filterpy.kalman import MerweScaledSigmaPoints, UnscentedKalmanFilter

    n, dt = setup.n, setup.dt
    decay = math.exp(-0.5 * dt)
    if setup.model == "ou":
        fx, Q = (lambda x, _dt: decay * x), (1.0 - math.exp(-dt)) * np.eye(n)
    else:
        fx, Q = (lambda x, _dt: setup.euler(x, noise=False)), dt * np.eye(n)
    points = MerweScaledSigmaPoints(n, alpha=0.1, beta=2.0, kappa=0.0)
    ukf = UnscentedKalmanFilter(dim_x=n, dim_z=n, dt=dt, points=points, fx=fx,
                                hx=lambda x: setup.sensor(x) * dt)
    # the prior moved over the first gap (the first row is at t = dt): the UKF's first predict does it
    ukf.x, ukf.P = np.full(n, setup.prior_mean), np.eye(n)
    ukf.Q, ukf.R = Q, dt * np.eye(n)
    means = []
    start = time.process_time()
    for dy in data:
        ukf.predict()
        ukf.update(np.asarray(dy, float))
        means.append(ukf.x.copy())
    return np.array(means), time.process_time() - start


def main(argv: list[str]) -> int:
    src, dst = argv[1], argv[2]
    d = np.load(src)
    setup = Setup(d)
    data, N = d["increments"], int(d["particles"])
    # warm-up outside the timed runs: particles' imports and numba's compilation of its resampler
    bootstrap(setup, data[:5], 0, N)
    pf_means, pf_seconds = [], []
    for seed in d["seeds"]:
        means, seconds = bootstrap(setup, data, int(seed), N)
        pf_means.append(means)
        pf_seconds.append(seconds)
    ukf_means, ukf_seconds, ukf_error = np.full(data.shape, np.nan), math.nan, ""
    if int(d["ukf"]):
        try:
            unscented(setup, data[:5])
            ukf_means, ukf_seconds = unscented(setup, data)
        except (np.linalg.LinAlgError, ValueError) as exc:  # a covariance that lost positive definiteness
            ukf_error = f"{type(exc).__name__}: {exc}"
    from importlib.metadata import version

    np.savez(dst, pf_means=np.array(pf_means), pf_seconds=np.array(pf_seconds), ukf_means=ukf_means,
             ukf_seconds=np.array(ukf_seconds), ukf_error=np.array(ukf_error),
             versions=np.array([f"particles {version('particles')}", f"filterpy {version('filterpy')}",
                                f"numpy {np.__version__}"]))
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv))
