"""A ball that follows the state (solver/follow.py) against the fixed ball, and precompute on Dask.

    python -m bench.follow [--quick]     # writes docs/bench-follow.md

* Cost per observation with ``[domain] follow`` (a random walk with trend f = 1, which travels far
  beyond the ball) against the fixed ball of the same Q and N (an OU drift −x/2 that stays in it),
  chunks of 1000 rows, one BLAS thread, medians; 1-D (N = 48) and 2-D (f = (1, 0.5), N = 300).
* A re-centre's cost (``FollowingFilter.recentre``) in steps of the fixed ball.
* Accuracy of the following ball against the exact Kalman filter of the sampled model.
* The offline solves on Dask: one process, a local cluster of 1 and of 2 workers (2-D, N = 600).
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import numpy as np
from threadpoolctl import threadpool_limits
from yauyau.solver import compile_model, spec_from_dict
from yauyau.solver.engine import build
from yauyau.solver.exact.kalman_bucy import KalmanBucyFilter
from yauyau.solver.offline import precompute
from yauyau.solver.simulate import simulate

from .fragments import write_fragment

ROOT = Path(__file__).resolve().parent.parent
FRAGMENT = ROOT / "docs" / "bench-follow.md"
CHUNK = 1000


def _doc(n: int, drift: list[str], follow: bool, basis: int) -> dict:
    names = ["x", "y"][:n]
    return {"name": "follow-bench", "state": names, "drift": drift, "observation": names, "method": "yau-yau",
            "initial": {"kind": "gaussian", "mean": [0.0] * n, "cov": np.eye(n).tolist()},
            "domain": {"radius": 6.0, "follow": follow}, "discretization": {"dt": 0.01, "basis": basis}}


CASES = [("1-D", 1, ["1.0"], ["-0.5*x"], 48), ("2-D", 2, ["1.0", "0.5"], ["-0.5*x", "-0.5*y"], 300)]


def _time_run(flt, rows, repeats: int) -> float:
    """Median seconds per observation over ``repeats`` runs of ``rows`` in chunks."""
    times = []
    for _ in range(repeats):
        state = flt.initial_state()
        start = time.perf_counter()
        for c in range(0, len(rows), CHUNK):
            state, _ = flt.run_arrays(state, rows[c:c + CHUNK])
        times.append(time.perf_counter() - start)
    return statistics.median(times) / len(rows)


def _engine(doc: dict):
    model = compile_model(spec_from_dict(doc))
    return model, build(model, precompute(model))


def follow_rows(steps: int, repeats: int) -> list[str]:
    out = []
    for label, n, trend, ou, basis in CASES:
        model, follow = _engine(_doc(n, trend, True, basis))
        fixed_model, fixed = _engine(_doc(n, ou, False, basis))
        moving = simulate(model, steps, np.random.default_rng(3)).increments
        staying = simulate(fixed_model, steps, np.random.default_rng(3)).increments
        with threadpool_limits(1, user_api="blas"):
            t_follow, t_fixed = [], []
            for _ in range(3):  # interleaved
                t_follow.append(_time_run(follow, moving, repeats))
                t_fixed.append(_time_run(fixed, staying, repeats))
            per_follow, per_fixed = statistics.median(t_follow), statistics.median(t_fixed)
            state, result = follow.run_arrays(follow.initial_state(), moving)
            target = follow.snapped(state.center, state.center + 0.9)
            moves = []
            for _ in range(20):
                start = time.perf_counter()
                follow.recentre(state, target)
                moves.append(time.perf_counter() - start)
            move = statistics.median(moves)
        kalman = KalmanBucyFilter(model, kind="discrete")
        _, exact = kalman.run_arrays(kalman.initial_state(), moving)
        gap = float(np.abs(result.mean - exact.mean).max())
        var = float(np.max(np.abs(np.diagonal(result.cov, axis1=1, axis2=2)
                                  / np.diagonal(exact.cov, axis1=1, axis2=2) - 1)))
        cells = [label, len(follow.nodes), follow.N, f"{per_fixed * 1e6:.1f}", f"{per_follow * 1e6:.1f}",
                 f"{per_follow / per_fixed:.2f}×", int(result.recentred.sum()),
                 f"{move * 1e6:.0f} ({move / per_fixed:.0f} steps)", f"{gap:.1e}", f"{var:.1e}",
                 bool(result.degenerate.any())]
        out.append("| " + " | ".join(map(str, cells)) + " |")
        print(out[-1])
    return out


def dask_rows(basis: int) -> list[str]:
    doc = _doc(2, ["-x", "-0.5*y"], False, basis)
    model = compile_model(spec_from_dict(doc))
    rows, reference = [], None
    for label, kwargs in (("one process, no cluster", {"workers": 1}), ("local cluster, 1 worker", None),
                          ("local cluster, 2 workers", {"workers": 2})):
        start = time.perf_counter()
        if kwargs is None:  # a one-worker cluster: the Dask path with a single worker
            from yauyau.solver import offline as off

            job = off._Job(*_job_parts(model), token="bench")
            fp = np.empty_like(job.initial)
            from yauyau.solver.distributed import run_blocks

            def store(result, fp=fp):
                fp[:, result[0]:result[1]] = result[2]
            run_blocks(job, off.column_blocks(job.initial.shape[1]), store, workers=1)
            arrays = fp
        else:
            arrays = precompute(model, **kwargs).propagator_fp
        seconds = time.perf_counter() - start
        reference = arrays if reference is None else reference
        rows.append(f"| {label} | {seconds:.1f} | {np.array_equal(arrays, reference)} |")
        print(rows[-1])
    return rows


def _job_parts(model):
    from yauyau.solver.offline import dirichlet_eigenbasis, finite_element_space

    disc = finite_element_space(model)
    phi = dirichlet_eigenbasis(disc, model.spec.discretization.basis)
    return (disc.fokker_planck, disc.kolmogorov, disc.weights, model.dt, model.spec.discretization.substeps,
            phi.values)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.follow", description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="shorter paths, fewer repeats")
    args = parser.parse_args(argv)
    steps, repeats, basis = (2000, 1, 300) if args.quick else (10_000, 3, 600)
    lines = ["## A ball that follows the state (`[domain] follow`)", "",
             "`python -m bench.follow" + (" --quick" if args.quick else "") + "`", "",
             f"Random walk with trend (f = 1 in 1-D, (1, 0.5) in 2-D; h = x, a = I, radius 6, "
             f"dt = 0.01, {steps} steps: the state travels ~{steps // 100} units) on a following ball, "
             "against the fixed ball of the same nodes Q and basis N on an OU path that stays inside it; "
             "chunks of 1000 rows, one BLAS thread, medians, interleaved. *move*: one re-centre (carry + "
             "projection), in µs and in steps of the fixed ball. Gaps: against the exact Kalman filter of "
             "the sampled model.", "",
             "| model | Q | N | fixed µs/obs | follow µs/obs | ratio | moves | move µs | mean gap "
             "| var error | degenerate |", "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|"]
    lines += follow_rows(steps, repeats)
    lines += ["", f"### Precompute on Dask (2-D OU, basis {basis})", "",
              "Seconds for the whole propagator solve; *identical*: the arrays equal the one-process run's "
              "bit for bit.", "", "| how | seconds | identical |", "|---|---:|---|"]
    lines += dask_rows(basis)
    write_fragment(FRAGMENT, lines)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
