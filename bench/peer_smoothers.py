"""FilterPy's Rauch–Tung–Striebel smoother and `particles`' FFBS on the sampled 1-D OU model.

    bench/out/peers-venv/bin/python bench/peer_smoothers.py IN.npz OUT.npz

Runs in its OWN virtual environment (bench/out/peers-venv, bench/measurements.py ``--setup-peers``):
particles pins numpy < 2.  bench/smoother.py calls it as a subprocess; it imports nothing from yauyau.

The model, exactly sampled on rows dt apart: x_k = φ x_(k−1) + N(0, q), dy_k = x_k dt + N(0, R dt),
x_0 ~ N(m0, P0).  IN.npz: ``dy`` (K,), ``phi``, ``q``, ``dt``, ``r``, ``m0``, ``P0``, ``rows_ffbs``
(the first rows FFBS smooths), ``particles`` (N), ``trajectories`` (M), ``repeats``.
OUT.npz: ``rts_mean``, ``rts_var`` (K,), ``rts_us`` (CPU µs a row, median: ``batch_filter`` then
``rts_smoother``), ``ffbs_mean``, ``ffbs_var`` (rows_ffbs,), ``ffbs_us`` (CPU µs a row, median:
``SMC.run`` with the history, then ``backward_sampling_ON2(M)``, the O(N·M) backward pass),
``ffbs_forward_us`` (the forward run alone), ``versions``.
"""

from __future__ import annotations

import os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import math  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402


def rts(args) -> tuple[np.ndarray, np.ndarray, float]:
    from filterpy.kalman import KalmanFilter

    dy, dt = args["dy"], float(args["dt"])
    kf = KalmanFilter(dim_x=1, dim_z=1)
    kf.F, kf.H = np.array([[float(args["phi"])]]), np.array([[dt]])
    kf.Q, kf.R = np.array([[float(args["q"])]]), np.array([[float(args["r"]) * dt]])
    kf.x, kf.P = np.array([[float(args["m0"])]]), np.array([[float(args["P0"])]])
    start = time.process_time()
    means, covs, _, _ = kf.batch_filter(dy[:, None])
    xs, Ps, _, _ = kf.rts_smoother(means, covs)
    return xs[:, 0, 0] if xs.ndim == 3 else xs[:, 0], Ps[:, 0, 0], time.process_time() - start


def ffbs(args) -> tuple[np.ndarray, np.ndarray, float, float]:
    import particles
    from particles import distributions as dists
    from particles import state_space_models as ssm

    phi, q, dt, r = (float(args[k]) for k in ("phi", "q", "dt", "r"))
    m0, P0 = float(args["m0"]), float(args["P0"])
    K = int(args["rows_ffbs"])

    class OU(ssm.StateSpaceModel):
        def PX0(self):  # x_1: the prior moved over the first step
            return dists.Normal(loc=phi * m0, scale=math.sqrt(phi * phi * P0 + q))

        def PX(self, t, xp):
            return dists.Normal(loc=phi * xp, scale=math.sqrt(q))

        def PY(self, t, xp, x):
            return dists.Normal(loc=dt * x, scale=math.sqrt(r * dt))

    data = args["dy"][:K]
    fk = ssm.Bootstrap(ssm=OU(), data=data)
    pf = particles.SMC(fk=fk, N=int(args["particles"]), store_history=True, collect="off")
    start = time.process_time()
    pf.run()
    forward = time.process_time() - start
    paths = np.array(pf.hist.backward_sampling_ON2(int(args["trajectories"])))  # (K, M)
    total = time.process_time() - start
    return paths.mean(axis=1), paths.var(axis=1), total, forward


def main() -> int:
    src, dst = sys.argv[1], sys.argv[2]
    args = dict(np.load(src))
    np.random.seed(1)
    K, KF = len(args["dy"]), int(args["rows_ffbs"])
    rts_runs, ffbs_runs, forward_runs = [], [], []
    for _ in range(int(args["repeats"])):
        rts_mean, rts_var, secs = rts(args)
        rts_runs.append(secs / K * 1e6)
    for _ in range(max(1, int(args["repeats"]) // 2)):
        ffbs_mean, ffbs_var, secs, forward = ffbs(args)
        ffbs_runs.append(secs / KF * 1e6)
        forward_runs.append(forward / KF * 1e6)
    import filterpy
    import particles

    np.savez(dst, rts_mean=rts_mean, rts_var=rts_var, rts_us=float(np.median(rts_runs)),
             ffbs_mean=ffbs_mean, ffbs_var=ffbs_var, ffbs_us=float(np.median(ffbs_runs)),
             ffbs_forward_us=float(np.median(forward_runs)),
             versions=f"filterpy {filterpy.__version__}, particles {particles.__version__}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
