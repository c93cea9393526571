"""The `particles` library's bootstrap filter (N. Chopin) on discrete readings at irregular times.

    bench/out/peers-venv/bin/python bench/peer_particles.py IN.npz OUT.npz [--serve]

Runs in its OWN virtual environment (bench/out/peers-venv: ``python3 -m venv`` + ``pip install
particles``): particles pins numpy < 2, which yauyau does not support, so bench/measurements.py
calls this script as a subprocess and never imports particles itself.  This file imports nothing
from yauyau.

The model is one-dimensional, given by polynomials (coefficients highest power first, as
numpy.polyval):

    dx = f(x) dt + √a dv,   z_k = h(x(t_k)) + v_k,  v_k ~ N(0, R),   x(0) ~ N(prior_mean, prior_var).

Transition over a gap τ: exact where f is linear (f = c1·x + c0: an Ornstein–Uhlenbeck law), else
Euler–Maruyama with ``substeps`` steps per gap.  The first reading is at t_1 > 0, so M0 draws the
prior at t = 0 and moves it over the first gap.

IN.npz: ``observations`` (S, K), ``times`` (S, K), ``seeds`` (S,), ``drift_poly``, ``obs_poly``,
``diffusion``, ``noise_var``, ``prior_mean``, ``prior_var``, ``particles`` (N), ``substeps``.
OUT.npz: ``means`` (S, K), ``variances`` (S, K), ``seconds`` (S,) (CPU time of ``SMC.run``, one
BLAS thread), ``transition`` ("exact-linear" or "euler-maruyama"), ``version`` (of particles).

Without ``--serve`` every data set is filtered once.  With ``--serve`` the script prints ``ready``
after a warm-up, then filters data set ``s`` for each line ``s`` read from stdin and answers the
seconds of that run (one line), so that the caller can interleave its own runs with these on a noisy
machine; at end of input it writes OUT.npz (``seconds``: the last run of each set).
"""

from __future__ import annotations

import os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import math  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402


def _transition(drift_poly: np.ndarray, a: float, substeps: int):
    """(name, sample(xp, tau) -> x) for the 1-D diffusion dx = f(x) dt + √a dv."""
    poly = np.trim_zeros(np.asarray(drift_poly, dtype=float), "f")
    if poly.size <= 2:  # linear drift: exact Gaussian transition
        c1 = float(poly[-2]) if poly.size == 2 else 0.0
        c0 = float(poly[-1]) if poly.size >= 1 else 0.0

        def exact(xp: np.ndarray, tau: float) -> np.ndarray:
            if abs(c1 * tau) < 1e-12:
                mean, var = xp + c0 * tau, a * tau
            else:
                decay = math.exp(c1 * tau)
                mean = decay * xp + c0 * (decay - 1.0) / c1
                var = a * math.expm1(2.0 * c1 * tau) / (2.0 * c1)
            return mean + math.sqrt(var) * np.random.standard_normal(xp.shape)

        return "exact-linear", exact

    def euler(xp: np.ndarray, tau: float) -> np.ndarray:
        small = tau / substeps
        x = xp
        for _ in range(substeps):
            x = x + np.polyval(poly, x) * small + math.sqrt(a * small) * np.random.standard_normal(x.shape)
        return x

    return "euler-maruyama", euler


class Peer:
    """particles' bootstrap filter on the data sets of IN.npz (imports particles on construction)."""

    def __init__(self, inputs: dict):
        import particles
        from particles import distributions as dists
        from particles import state_space_models as ssm

        self.particles, self.ssm = particles, ssm
        self.transition, sample = _transition(inputs["drift_poly"], float(inputs["diffusion"]),
                                              int(inputs["substeps"]))
        obs_poly = np.asarray(inputs["obs_poly"], dtype=float)
        noise_sd = math.sqrt(float(inputs["noise_var"]))
        prior_mean, prior_sd = float(inputs["prior_mean"]), math.sqrt(float(inputs["prior_var"]))

        class Moved(dists.ProbDist):
            """The law of x(t + τ) given x(t) = xp (only ``rvs``: all a bootstrap filter draws)."""

            def __init__(self, xp, tau):
                self.xp, self.tau = xp, tau

            def rvs(self, size=None):
                if self.xp is None:  # the first gap: from the prior at t = 0
                    return sample(prior_mean + prior_sd * np.random.standard_normal(size), self.tau)
                return sample(np.asarray(self.xp, dtype=float), self.tau)

        class Sensor(ssm.StateSpaceModel):
            """Discrete readings z_k = h(x(t_k)) + N(0, R) at the gaps ``self.gaps``."""

            def PX0(self):
                return Moved(None, self.gaps[0])

            def PX(self, t, xp):
                return Moved(xp, self.gaps[t])

            def PY(self, t, xp, x):
                return dists.Normal(loc=np.polyval(obs_poly, x), scale=noise_sd)

        self.Sensor = Sensor
        self.N = int(inputs["particles"])
        self.observations, self.times, self.seeds = inputs["observations"], inputs["times"], inputs["seeds"]
        S, K = self.observations.shape
        self.means, self.variances, self.seconds = np.empty((S, K)), np.empty((S, K)), np.full(S, np.nan)
        # warm-up outside the timed runs: imports, and numba's compilation of the resampling
        # (ESSrmin = 1: resample at every step)
        warm = Sensor(gaps=np.diff(self.times[0, :5], prepend=0.0))
        particles.SMC(fk=ssm.Bootstrap(ssm=warm, data=self.observations[0, :5]), N=self.N, ESSrmin=1.0,
                      collect=[particles.collectors.Moments()]).run()

    def run(self, s: int) -> float:
        """Filter data set ``s`` (seeded by its seed); the seconds of ``SMC.run``."""
        particles, ssm = self.particles, self.ssm
        gaps = np.diff(self.times[s], prepend=0.0)
        fk = ssm.Bootstrap(ssm=self.Sensor(gaps=gaps), data=self.observations[s])
        np.random.seed(int(self.seeds[s]))
        alg = particles.SMC(fk=fk, N=self.N, collect=[particles.collectors.Moments()])
        began = time.process_time()
        alg.run()
        self.seconds[s] = time.process_time() - began
        self.means[s] = [float(np.squeeze(m["mean"])) for m in alg.summaries.moments]
        self.variances[s] = [float(np.squeeze(m["var"])) for m in alg.summaries.moments]
        return float(self.seconds[s])

    def result(self) -> dict:
        try:  # the installed distribution's version (particles.__version__ lags behind it)
            from importlib.metadata import version

            installed = version("particles")
        except ImportError:  # PackageNotFoundError included: the module's own string
            installed = str(getattr(self.particles, "__version__", "?"))
        return {"means": self.means, "variances": self.variances, "seconds": self.seconds,
                "transition": self.transition, "version": installed}


def _serve(peer: Peer) -> None:
    print("ready", flush=True)
    for line in sys.stdin:
        if line.strip():
            print(repr(peer.run(int(line))), flush=True)


def run(inputs: dict, serve: bool = False) -> dict:
    peer = Peer(inputs)
    if serve:
        _serve(peer)
    else:
        for s in range(len(peer.seeds)):
            peer.run(s)
    return peer.result()


def main(argv: list[str]) -> int:
    serve = "--serve" in argv
    argv = [a for a in argv if a != "--serve"]
    if len(argv) != 2:
        print(__doc__.splitlines()[2].strip(), file=sys.stderr)
        return 2
    with np.load(argv[0]) as data:
        inputs = {key: data[key] for key in data.files}
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:  # one thread through the environment variables above
        out = run(inputs, serve)
    else:
        with threadpool_limits(1):
            out = run(inputs, serve)
    np.savez(argv[1], **out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
