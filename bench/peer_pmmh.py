"""`particles`' PMMH (N. Chopin) for the drift rate θ of a 1-D Ornstein–Uhlenbeck model with a polynomial
sensor, on discrete readings one dt apart.

    bench/out/peers-venv/bin/python bench/peer_pmmh.py IN.npz OUT.npz

Runs in its OWN virtual environment (bench/out/peers-venv): particles pins numpy < 2, which yauyau does
not support, so bench/fit.py calls this script as a subprocess.  This file imports nothing from yauyau.

The model: dx = −θ x dt + √a dv (the exact OU transition over each gap dt), z_k = h(x(k·dt)) + N(0, R),
x(0) ~ N(prior_mean, prior_var) moved over the first gap; h a polynomial (numpy.polyval, highest power
first).  The prior on θ is flat on [lo, hi]; each chain starts at ``theta0`` with a random-walk proposal
of variance ``rw_var`` (particles adapts it as the chain runs), a bootstrap filter of ``particles`` (Nx)
inside, ``niter`` iterations; one chain per entry of ``seeds`` (np.random.seed before each).

IN.npz: ``z`` (K,), ``dt``, ``a``, ``noise_var`` (R), ``prior_mean``, ``prior_var``, ``obs_poly``, ``lo``,
``hi``, ``theta0``, ``rw_var``, ``particles``, ``niter``, ``seeds`` (C,).
OUT.npz: ``chains`` (C, niter) the θ chains, ``seconds`` (C,) CPU time of each ``PMMH.run`` (one BLAS
thread), ``acceptance`` (C,), ``filter_seconds`` (CPU time of one bootstrap filter at theta0, after a
warm-up), ``loglik_sd`` (the spread of its log-likelihood estimate over 10 runs at theta0), ``version``.
"""

from __future__ import annotations

import os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import math  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402


def run(args: dict) -> dict:
    import particles
    from particles import distributions as dists
    from particles import mcmc
    from particles import state_space_models as ssm

    z, dt, a = np.asarray(args["z"], dtype=float), float(args["dt"]), float(args["a"])
    noise_sd = math.sqrt(float(args["noise_var"]))
    prior_mean, prior_sd = float(args["prior_mean"]), math.sqrt(float(args["prior_var"]))
    obs_poly = np.asarray(args["obs_poly"], dtype=float)
    lo, hi, theta0 = float(args["lo"]), float(args["hi"]), float(args["theta0"])
    N, niter = int(args["particles"]), int(args["niter"])

    class Moved(dists.ProbDist):
        """x(t + dt) given x(t) = xp under the exact OU law (only ``rvs``: all a bootstrap filter draws)."""

        def __init__(self, xp, theta):
            self.xp, self.theta = xp, theta

        def rvs(self, size=None):
            decay = math.exp(-self.theta * dt)
            sd = math.sqrt(a * -math.expm1(-2.0 * self.theta * dt) / (2.0 * self.theta))
            xp = (prior_mean + prior_sd * np.random.standard_normal(size) if self.xp is None
                  else np.asarray(self.xp, dtype=float))
            return decay * xp + sd * np.random.standard_normal(xp.shape)

    class OUSensor(ssm.StateSpaceModel):
        default_params = {"theta": theta0}

        def PX0(self):
            return Moved(None, self.theta)

        def PX(self, t, xp):
            return Moved(xp, self.theta)

        def PY(self, t, xp, x):
            return dists.Normal(loc=np.polyval(obs_poly, x), scale=noise_sd)

    # warm-up (imports, numba's compilation of the resampling), then one filter's cost and the spread
    # of its log-likelihood estimate at theta0
    particles.SMC(fk=ssm.Bootstrap(ssm=OUSensor(theta=theta0), data=z[:20]), N=N).run()
    logliks, spent = [], []
    np.random.seed(12345)
    for _ in range(10):
        pf = particles.SMC(fk=ssm.Bootstrap(ssm=OUSensor(theta=theta0), data=z), N=N)
        began = time.process_time()
        pf.run()
        spent.append(time.process_time() - began)
        logliks.append(pf.logLt)
    prior = dists.StructDist({"theta": dists.Uniform(a=lo, b=hi)})
    chains, seconds, acceptance = [], [], []
    for seed in np.asarray(args["seeds"]).tolist():
        start = np.zeros(1, dtype=[("theta", float)])  # its own: the sampler proposes into it in place
        start["theta"] = theta0
        np.random.seed(int(seed))
        alg = mcmc.PMMH(ssm_cls=OUSensor, prior=prior, data=z, Nx=N, niter=niter, theta0=start,
                        adaptive=True, rw_cov=np.array([[float(args["rw_var"])]]))
        began = time.process_time()
        alg.run()
        seconds.append(time.process_time() - began)
        chains.append(np.array(alg.chain.theta["theta"], dtype=float))
        acceptance.append(float(alg.acc_rate))
    try:
        from importlib.metadata import version

        installed = version("particles")
    except ImportError:
        installed = str(getattr(particles, "__version__", "?"))
    return {"chains": np.array(chains), "seconds": np.array(seconds), "acceptance": np.array(acceptance),
            "filter_seconds": float(np.median(spent)), "loglik_sd": float(np.std(logliks, ddof=1)),
            "version": installed}


def main(argv: list[str]) -> int:
    if len(argv) != 2:
        print(__doc__.splitlines()[3].strip(), file=sys.stderr)
        return 2
    with np.load(argv[0]) as data:
        args = {key: data[key] for key in data.files}
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:  # one thread through the environment variables above
        out = run(args)
    else:
        with threadpool_limits(1):
            out = run(args)
    np.savez(argv[1], **out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
