"""Noise on some coordinates only (a positive semi-definite diffusion): the three schemes side by side.

    python -m bench.psd [--quick]     # writes bench/results/psd.md

Constant-velocity tracking, f = (v, −0.2v), a = diag(0, 1), 2-D P1 on the default mesh:
``scheme = "galerkin"`` (lumped mass), ``"consistent"`` (Galerkin, consistent mass) and ``"supg"``
(streamline-upwind Petrov–Galerkin with the recovered second derivatives, the default for such a
diffusion; solver/offline/fem.py).

* Prediction: the prior N((−2, 1), 0.2 I) moved over t = 1 without data (radius 6), against the
  exact moments of the linear SDE; *ring*: the density's most negative value over its peak, *negative
  mass*: −∫min(σ, 0)/∫σ (the oscillations along the drift).
* Filtering: h = p, R = 1, dt = 0.01, t = 0..50 on a following ball (radius 8, N = 1000) against the
  exact Kalman filter of the sampled model: the target travels ~50 units.
* Cost: precompute seconds and µs per observation (chunks of 1000 rows, one BLAS thread, medians of
  interleaved runs) of each scheme on the same mesh.
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import numpy as np
import scipy.linalg as sla
from threadpoolctl import threadpool_limits
from yauyau.solver import compile_model, spec_from_dict
from yauyau.solver.engine.filter import build
from yauyau.solver.exact.kalman_bucy import KalmanBucyFilter
from yauyau.solver.offline.pipeline import precompute
from yauyau.solver.simulate import simulate

from .fragments import write_fragment

ROOT = Path(__file__).resolve().parent.parent
FRAGMENT = ROOT / "bench" / "results" / "psd.md"
SCHEMES = ("galerkin", "consistent", "supg")
A = np.array([[0.0, 1.0], [0.0, -0.2]])
NOISE = np.diag([0.0, 1.0])


def _doc(scheme: str, basis: int, radius: float, follow: bool, mean, cov) -> dict:
    return {"name": "cv", "state": ["p", "v"], "drift": ["v", "-0.2*v"], "observation": ["p"],
            "diffusion": NOISE.tolist(), "method": "yau-yau",
            "initial": {"kind": "gaussian", "mean": list(mean), "cov": cov},
            "domain": {"radius": radius, "follow": follow},
            "discretization": {"dt": 0.01, "basis": basis, "scheme": scheme}}


def exact_moments(mean0: np.ndarray, cov0: np.ndarray, t: float) -> tuple[np.ndarray, np.ndarray]:
    """Mean and covariance of dx = Ax dt + dW (Van Loan's exponential for the noise integral)."""
    E = sla.expm(A * t)
    G = sla.expm(np.block([[-A, NOISE], [np.zeros((2, 2)), A.T]]) * t)
    return E @ mean0, E @ cov0 @ E.T + G[2:, 2:].T @ G[:2, 2:]


def prediction_rows(sizes: tuple[int, ...]) -> list[str]:
    mean0, cov0 = np.array([-2.0, 1.0]), 0.2 * np.eye(2)
    mean_x, cov_x = exact_moments(mean0, cov0, 1.0)
    rows = []
    for basis in sizes:
        for scheme in SCHEMES:
            model = compile_model(spec_from_dict(_doc(scheme, basis, 6.0, False, mean0, cov0.tolist())))
            flt = build(model, precompute(model))
            state, result = flt.run_arrays(flt.initial_state(), np.full((100, 1), np.nan))
            sigma, w = flt.nodal_density(state), flt.weights
            mean, cov, mass = result.mean[-1], result.cov[-1], w @ sigma
            cells = [basis, len(w), scheme, f"{np.abs(mean - mean_x).max():.1e}",
                     f"{np.abs(np.diag(cov) / np.diag(cov_x) - 1).max():.1%}",
                     f"{sigma.min() / sigma.max():.1e}", f"{-(w * np.minimum(sigma, 0)).sum() / mass:.1e}"]
            rows.append("| " + " | ".join(map(str, cells)) + " |")
            print(rows[-1])
    return rows


def _per_obs(flt, rows: np.ndarray, repeats: int) -> list[float]:
    out = []
    for _ in range(repeats):
        state = flt.initial_state()
        start = time.perf_counter()
        for c in range(0, len(rows), 1000):
            state, _ = flt.run_arrays(state, rows[c:c + 1000])
        out.append((time.perf_counter() - start) / len(rows))
    return out


def filtering_rows(steps: int, basis: int, repeats: int) -> list[str]:
    filters, accuracy, seconds = {}, {}, {}
    sim = None
    for scheme in SCHEMES:
        model = compile_model(spec_from_dict(_doc(scheme, basis, 8.0, True, [0.0, 0.0], np.eye(2).tolist())))
        start = time.perf_counter()
        offline = precompute(model)
        seconds[scheme] = time.perf_counter() - start
        flt = build(model, offline)
        if sim is None:
            sim = simulate(model, steps, np.random.default_rng(1))
            kalman = KalmanBucyFilter(model, kind="discrete")
            _, exact = kalman.run_arrays(kalman.initial_state(), sim.increments)
        _, result = flt.run_arrays(flt.initial_state(), sim.increments)
        gap = np.abs(result.mean - exact.mean).max(axis=1)
        var = np.abs(np.diagonal(result.cov, axis1=1, axis2=2) / np.diagonal(exact.cov, axis1=1, axis2=2) - 1)
        accuracy[scheme] = (len(offline.weights), np.median(gap), gap.max(), var.max(),
                            abs(result.loglik[-1] - exact.loglik[-1]), int(result.recentred.sum()),
                            bool(result.degenerate.any()))
        filters[scheme] = flt
    times = {scheme: [] for scheme in SCHEMES}
    with threadpool_limits(limits=1, user_api="blas"):
        for _ in range(repeats):  # interleaved
            for scheme in SCHEMES:
                times[scheme] += _per_obs(filters[scheme], sim.increments, 1)
    base = statistics.median(times["galerkin"])
    rows = []
    for scheme in SCHEMES:
        q, median, worst, var, loglik, moves, degenerate = accuracy[scheme]
        per = statistics.median(times[scheme])
        cells = [scheme, q, basis, f"{median:.1e}", f"{worst:.1e}", f"{var:.1%}", f"{loglik:.1e}", moves,
                 f"{seconds[scheme]:.1f}", f"{per * 1e6:.0f}", f"{per / base:.2f}×", degenerate]
        rows.append("| " + " | ".join(map(str, cells)) + " |")
        print(rows[-1])
    return rows


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.psd", description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="smaller bases, a shorter path")
    args = parser.parse_args(argv)
    sizes, steps, basis, repeats = ((300,), 1000, 400, 1) if args.quick else ((300, 600, 1200), 5000, 1000, 3)
    lines = ["## Noise on some coordinates only (`scheme`, a semi-definite diffusion)", "",
             "`python -m bench.psd" + (" --quick" if args.quick else "") + "`", "",
             "Constant-velocity tracking f = (v, −0.2v), a = diag(0, 1), 2-D P1 on the default mesh. "
             "Prediction of N((−2, 1), 0.2 I) over t = 1 without data (radius 6) against the exact "
             "moments of the linear SDE; *ring*: the density's most negative value over its peak; "
             "*negative mass*: −∫min(σ, 0)/∫σ.", "",
             "| N | Q | scheme | mean error | variance error | ring | negative mass |",
             "|---:|---:|---|---:|---:|---:|---:|"]
    lines += prediction_rows(sizes)
    lines += ["", f"Filtering h = p, R = 1, dt = 0.01, {steps} steps (the target travels ~{steps // 100} "
              "units) on a following ball of radius 8 against the exact Kalman filter of the sampled model; "
              "precompute seconds; µs per observation in chunks of 1000, one BLAS thread, medians of "
              "interleaved runs, and the ratio to plain Galerkin.", "",
              "| scheme | Q | N | gap median | gap max | variance error | loglik gap | moves | precompute s "
              "| µs/obs | vs galerkin | degenerate |",
              "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|"]
    lines += filtering_rows(steps, basis, repeats)
    write_fragment(FRAGMENT, lines)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
