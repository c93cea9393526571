"""A ball that follows the state (solver/engine/follow.py) against the fixed ball, and precompute on Dask.

    python -m bench.follow [--quick]     # writes bench/results/follow.md

* Cost per observation with ``[domain] follow`` (a random walk with trend f = 1, which travels far
  beyond the ball) against the fixed ball of the same Q and N (an OU drift −x/2 that stays in it),
  chunks of 1000 rows, one BLAS thread, medians; 1-D (N = 48) and 2-D (f = (1, 0.5), P1 at N = 300,
  P2 + bubble at N = 300 and 600).
* A re-centre's cost (``FollowingFilter.recentre``) in steps of the fixed ball.
* Accuracy of the following ball against the exact Kalman filter of the sampled model.
* The offline solves on Dask: one process, a local cluster of 1 and of 2 workers (2-D, N = 600).
* An atlas (``[domain] region``, solver/engine/atlas.py) for f = 0.8 + 0.3 sin x (1-D) and
  f = (0.8 + 0.3 sin x, 0.5) (2-D: a lattice along x, translation along y): precompute in one process
  and on a running local cluster of 1 and 2 workers, file size per centre, cost per observation
  against the fixed ball and the shift-invariant following ball, centres read.
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import numpy as np
from threadpoolctl import threadpool_limits
from yauyau.solver import compile_model, spec_from_dict
from yauyau.solver.engine.filter import build
from yauyau.solver.exact.kalman_bucy import KalmanBucyFilter
from yauyau.solver.offline.pipeline import precompute
from yauyau.solver.simulate import simulate

from .fragments import write_fragment

ROOT = Path(__file__).resolve().parent.parent
FRAGMENT = ROOT / "bench" / "results" / "follow.md"
CHUNK = 1000


def _doc(n: int, drift: list[str], follow: bool, basis: int, element: str = "lagrange") -> dict:
    names = ["x", "y"][:n]
    return {"name": "follow-bench", "state": names, "drift": drift, "observation": names, "method": "yau-yau",
            "initial": {"kind": "gaussian", "mean": [0.0] * n, "cov": np.eye(n).tolist()},
            "domain": {"radius": 6.0, "follow": follow},
            "discretization": {"dt": 0.01, "basis": basis, "element": element}}


CASES = [("1-D", 1, ["1.0"], ["-0.5*x"], 48, "lagrange"),
         ("2-D P1", 2, ["1.0", "0.5"], ["-0.5*x", "-0.5*y"], 300, "lagrange"),
         ("2-D bubble", 2, ["1.0", "0.5"], ["-0.5*x", "-0.5*y"], 300, "bubble"),
         ("2-D bubble", 2, ["1.0", "0.5"], ["-0.5*x", "-0.5*y"], 600, "bubble")]


def _time_run(flt, rows, repeats: int, chunk: int = CHUNK) -> float:
    """Median seconds per observation over ``repeats`` runs of ``rows`` in chunks."""
    times = []
    for _ in range(repeats):
        state = flt.initial_state()
        start = time.perf_counter()
        for c in range(0, len(rows), chunk):
            state, _ = flt.run_arrays(state, rows[c:c + chunk])
        times.append(time.perf_counter() - start)
    return statistics.median(times) / len(rows)


def _engine(doc: dict):
    model = compile_model(spec_from_dict(doc))
    return model, build(model, precompute(model))


def follow_rows(steps: int, repeats: int) -> list[str]:
    out = []
    for label, n, trend, ou, basis, element in CASES:
        model, follow = _engine(_doc(n, trend, True, basis, element))
        fixed_model, fixed = _engine(_doc(n, ou, False, basis, element))
        moving = simulate(model, steps, np.random.default_rng(3)).increments
        staying = simulate(fixed_model, steps, np.random.default_rng(3)).increments
        with threadpool_limits(1, user_api="blas"):
            t_follow, t_fixed, t_blocks = [], [], []
            for _ in range(3):  # interleaved
                t_follow.append(_time_run(follow, moving, repeats))
                t_fixed.append(_time_run(fixed, staying, repeats))
                follow.moves_in_loop = False  # the previous revision: moves between blocks only
                t_blocks.append(_time_run(follow, moving, repeats))
                follow.moves_in_loop = True
            per_follow, per_fixed = statistics.median(t_follow), statistics.median(t_fixed)
            per_blocks = statistics.median(t_blocks)
            state, result = follow.run_arrays(follow.initial_state(), moving)
            target = follow.snapped(state.center, state.center + 0.9)  # an offset of the table
            beyond = max((float(np.linalg.norm(k)) for k in follow._table), default=0.0)  # in steps
            far = follow.snapped(state.center, state.center + (beyond + 2) * follow._lattice)
            moves, firsts, tables = [], [], []
            for _ in range(20):
                start = time.perf_counter()  # the table, as the filter builds it when it is made
                follow._carry_table()
                tables.append(time.perf_counter() - start)
                follow._carries.clear()  # a move by an offset beyond the table: its carry is built then
                start = time.perf_counter()
                follow.recentre(state, far)
                firsts.append(time.perf_counter() - start)
                follow.recentre(state, target)  # (warm: the calls above evicted the caches)
                start = time.perf_counter()
                follow.recentre(state, target)
                moves.append(time.perf_counter() - start)
            move, first, table = (statistics.median(t) for t in (moves, firsts, tables))
        kalman = KalmanBucyFilter(model, kind="discrete")
        _, exact = kalman.run_arrays(kalman.initial_state(), moving)
        gap = float(np.abs(result.mean - exact.mean).max())
        _, still = fixed.run_arrays(fixed.initial_state(), staying)
        kalman_fixed = KalmanBucyFilter(fixed_model, kind="discrete")
        _, exact_fixed = kalman_fixed.run_arrays(kalman_fixed.initial_state(), staying)
        fixed_gap = float(np.abs(still.mean - exact_fixed.mean).max())
        var = float(np.max(np.abs(np.diagonal(result.cov, axis1=1, axis2=2)
                                  / np.diagonal(exact.cov, axis1=1, axis2=2) - 1)))
        cells = [label, len(follow.nodes), follow.N, f"{per_fixed * 1e6:.1f}", f"{per_follow * 1e6:.1f}",
                 f"{per_follow / per_fixed:.2f}×", f"{per_blocks * 1e6:.1f} ({per_blocks / per_fixed:.2f}×)",
                 int(result.recentred.sum()),
                 f"{move * 1e6:.0f} ({move / per_fixed:.0f} steps)",
                 f"{first * 1e6:.0f} ({first / per_fixed:.0f} steps)",
                 f"{len(follow._table)} in {table * 1e3:.1f} ms", f"{gap:.1e}", f"{fixed_gap:.1e}",
                 f"{var:.1e}",
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
            from yauyau.solver.offline import jobs as off

            job = off.Job(*_job_parts(model), token="bench")
            fp = np.empty_like(job.initial)
            from yauyau.solver.offline.distributed import run_blocks

            def store(_, result, fp=fp):
                fp[:, result[0]:result[1]] = result[2]
            blocks = [(0, b) for b in off.column_blocks(job.initial.shape[1])]
            run_blocks([job], blocks, store, off.dask_block, workers=1)
            arrays = fp
        else:
            arrays = precompute(model, **kwargs).propagator_fp
        seconds = time.perf_counter() - start
        reference = arrays if reference is None else reference
        rows.append(f"| {label} | {seconds:.1f} | {np.array_equal(arrays, reference)} |")
        print(rows[-1])
    return rows


def _job_parts(model):
    from yauyau.solver.offline.pipeline import dirichlet_eigenbasis, finite_element_space

    disc = finite_element_space(model)
    phi = dirichlet_eigenbasis(disc, model.spec.discretization.basis)
    return (disc.fokker_planck, disc.kolmogorov, disc.weights, model.dt, model.spec.discretization.substeps,
            phi.values)


FRAME_CASES = [  # affine drifts: the ball rides the frame ċ = Ac + b (engine/frame.py) and follows in it
    ("1-D linear growth", {"state": ["x"], "drift": ["0.1*x + 0.2"], "observation": ["x"],
                           "initial": {"kind": "gaussian", "mean": [2.0], "cov": [[1.0]]},
                           "domain": {"radius": 6.0}, "discretization": {"dt": 0.01, "basis": 120}}, 3000),
    ("2-D constant velocity", {"state": ["p", "v"], "drift": ["v", "-0.2*v"], "observation": ["p"],
                               "diffusion": [[0.0, 0.0], [0.0, 1.0]],
                               "initial": {"kind": "gaussian", "mean": [0.0, 0.0], "cov": np.eye(2).tolist()},
                               "domain": {"radius": 8.0},
                               "discretization": {"dt": 0.01, "basis": 1000}}, 2000)]
FRAME_CHUNK = 100


def frame_rows(repeats: int) -> list[str]:
    """Cost per observation in a moving frame with follow against the fixed ball of the same spec
    (follow off: its own propagator) on the first 300 rows of the path, which stay inside it; chunks
    of 100 rows."""
    out = []
    for label, doc, steps in FRAME_CASES:
        engines = {}
        for follow in (True, False):
            spec = dict(doc, name="frame-bench", method="yau-yau", domain=dict(doc["domain"], follow=follow))
            engines[follow] = _engine(spec)
        model, moving = engines[True]
        rows = simulate(model, steps, np.random.default_rng(4)).increments
        with threadpool_limits(1, user_api="blas"):
            t_follow, t_fixed, t_blocks = [], [], []
            for _ in range(3):  # interleaved
                t_follow.append(_time_run(moving, rows, repeats, FRAME_CHUNK))
                t_fixed.append(_time_run(engines[False][1], rows[:300], repeats, FRAME_CHUNK))
                moving.moves_in_loop = False  # the previous revision: moves between blocks only
                t_blocks.append(_time_run(moving, rows, repeats, FRAME_CHUNK))
                moving.moves_in_loop = True
        per_follow, per_fixed = statistics.median(t_follow), statistics.median(t_fixed)
        per_blocks = statistics.median(t_blocks)
        _, result = moving.run_arrays(moving.initial_state(), rows)
        cells = [label, len(moving.nodes), moving.N, steps, f"{per_fixed * 1e6:.1f}",
                 f"{per_follow * 1e6:.1f}", f"{per_follow / per_fixed:.2f}×",
                 f"{per_blocks * 1e6:.1f} ({per_blocks / per_fixed:.2f}×)", int(result.recentred.sum())]
        out.append("| " + " | ".join(map(str, cells)) + " |")
        print(out[-1])
    return out


ATLAS_CASES = [("1-D", ["x"], ["0.8 + 0.3*sin(x)"], [[-5.0, 60.0]], 48, 0.02),
               ("2-D", ["x", "y"], ["0.8 + 0.3*sin(x)", "0.5"], [[-5.0, 25.0], [-5.0, 25.0]], 300, 0.01)]


HOWS = (("one process", 0), ("local cluster, 1 worker", 1), ("local cluster, 2 workers", 2))


def _atlas_doc(names, drift, region, basis, dt) -> dict:
    n = len(names)
    return {"name": "atlas-bench", "state": names, "drift": drift, "observation": names, "method": "yau-yau",
            "initial": {"kind": "gaussian", "mean": [0.0] * n, "cov": np.eye(n).tolist()},
            "domain": {"radius": 6.0, "follow": True, "region": region},
            "discretization": {"dt": dt, "basis": basis}}


def atlas_rows(steps: int, repeats: int, workers_2d: bool = True) -> tuple[list[str], list[str]]:
    """(precompute rows, online rows) of the atlas cases."""
    import tempfile

    from distributed import LocalCluster

    import yauyau

    pre, online = [], []
    for label, names, drift, region, basis, dt in ATLAS_CASES:
        doc = _atlas_doc(names, drift, region, basis, dt)
        model = compile_model(spec_from_dict(doc))
        timings, reference = [], None
        for how, workers in HOWS:
            cluster = None
            if workers:
                started = time.perf_counter()
                cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                                       dashboard_address=None, silence_logs=40)
                boot = time.perf_counter() - started
            start = time.perf_counter()
            offline = precompute(model, scheduler=None if cluster is None else cluster.scheduler_address)
            seconds = time.perf_counter() - start
            if cluster is not None:
                cluster.close()
            solved = offline.atlas.solved
            arrays = (solved.propagator_fp, solved.generator)
            reference = arrays if reference is None else reference
            same = all(np.array_equal(a, b) for a, b in zip(arrays, reference, strict=True))
            timings.append((how, seconds, None if cluster is None else boot, same))
        with tempfile.TemporaryDirectory() as directory:
            mid = yauyau.precompute(spec_from_dict(doc), directory)
            size = (Path(directory) / f"{mid}.h5").stat().st_size
        K = offline.atlas.size
        per_centre = (solved.propagator_fp[0].nbytes + solved.generator[0].nbytes) / 1e6
        for how, seconds, boot, same in timings:
            cells = [label, K, f"{len(offline.nodes)} × {basis}", how, f"{seconds:.1f}",
                     "—" if boot is None else f"{boot:.1f}", f"{seconds / K:.2f}", same,
                     f"{size / 1e6:.1f}", f"{per_centre:.3f}"]
            pre.append("| " + " | ".join(map(str, cells)) + " |")
            print(pre[-1])
        follow = build(model, offline)
        fixed_doc = _doc(len(names), [f"-0.5*{v}" for v in names], False, basis)
        fixed_doc["discretization"]["dt"] = dt
        fixed_model, fixed = _engine(fixed_doc)
        trend_doc = _doc(len(names), ["1.0"] * len(names), True, basis)
        trend_doc["discretization"]["dt"] = dt
        trend_model, trend = _engine(trend_doc)
        k = steps if label == "1-D" else steps // 2
        moving = simulate(model, k, np.random.default_rng(2)).increments
        staying = simulate(fixed_model, k, np.random.default_rng(2)).increments
        travelling = simulate(trend_model, k, np.random.default_rng(2)).increments
        with threadpool_limits(1, user_api="blas"):
            t = {"atlas": [], "fixed": [], "trend": []}
            for _ in range(3):  # interleaved
                t["atlas"].append(_time_run(build(model, offline), moving, repeats))  # engines built anew
                t["fixed"].append(_time_run(fixed, staying, repeats))
                t["trend"].append(_time_run(trend, travelling, repeats))
        per = {key: statistics.median(v) for key, v in t.items()}
        offline.atlas.clear()
        before = offline.atlas.loads
        state, result = follow.run_arrays(follow.initial_state(), moving)
        read = offline.atlas.loads - before  # centres built from the arrays in this one run
        cells = [label, f"{k} (t = {k * dt:g})", f"{per['fixed'] * 1e6:.1f}", f"{per['trend'] * 1e6:.1f}",
                 f"{per['atlas'] * 1e6:.1f}", f"{per['atlas'] / per['fixed']:.2f}×",
                 int(result.recentred.sum()), f"{read} of {K}", bool(result.degenerate.any())]
        online.append("| " + " | ".join(map(str, cells)) + " |")
        print(online[-1])
    return pre, online


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
             "chunks of 1000 rows, one BLAS thread, medians, interleaved. *follow*: moves inside the "
             "engine's loop (solver/engine/recentring.py); *between blocks*: the same filter with moves "
             "between blocks only (the previous revision). *move*: one re-centre between blocks (carry + "
             "projection), in µs and in steps of the fixed ball, by an offset of the table of carries "
             "built with the filter (every offset in whole mesh steps no longer than (1.5·follow_distance "
             "+ 0.1)·R: the moves' usual reach); *untabled move*: a move by an offset beyond the table, "
             "whose carry is built then (once per offset, then kept); *table*: its offsets and the time "
             "to build them, once when the filter is made. "
             "Gaps: against the exact Kalman filter of "
             "the sampled model (*fixed gap*: the fixed ball's on its OU path, the engine's own error at "
             "this Q and N).", "",
             "| model | Q | N | fixed µs/obs | follow µs/obs | ratio | between blocks µs/obs | moves "
             "| move µs | untabled move µs | table | mean gap | fixed gap | var error | degenerate |",
             "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|"]
    lines += follow_rows(steps, repeats)
    lines += ["", "### In a moving frame (an affine drift, solver/engine/frame.py)", "",
              "The ball rides ċ = Ac + b and follows the posterior in that frame; the fixed ball is the same "
              "spec without follow (the propagator of f itself) on the path's first 300 rows, which stay "
              "inside it. Chunks of 100 rows, one BLAS thread, medians of interleaved runs, µs per "
              "observation; *between blocks*: moves between blocks only (the previous revision).", "",
              "| model | Q | N | steps | fixed | frame + follow | ratio | between blocks | moves |",
              "|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
    lines += frame_rows(repeats)
    lines += ["", f"### Precompute on Dask (2-D OU, basis {basis})", "",
              "Seconds for the whole propagator solve; *identical*: the arrays equal the one-process run's "
              "bit for bit.", "", "| how | seconds | identical |", "|---|---:|---|"]
    lines += dask_rows(basis)
    pre, online = atlas_rows(steps // 2 if args.quick else 3000, repeats)
    lines += ["", "### An atlas for a drift that is not shift-invariant (`[domain] region`)", "",
              "f = 0.8 + 0.3 sin x (1-D, region [-5, 60]) and f = (0.8 + 0.3 sin x, 0.5) (2-D, region "
              "[-5, 25]²: the lattice runs along x only, y moves by translation); radius 6, "
              "follow_distance 0.15. Precompute: seconds for the home ball and every centre "
              "(*cluster start*: the local cluster's start-up, not included), per centre, *identical*: "
              "the atlas equals the one-process run's bit for bit; the file and one centre's "
              "propagator + generator in MB.", "",
              "| model | centres | Q × N | how | seconds | cluster start | s/centre | identical | file MB "
              "| MB/centre |", "|---|---:|---|---|---:|---:|---:|---|---:|---:|"]
    lines += pre
    lines += ["", "Online: µs per observation, chunks of 1000, one BLAS thread, medians of interleaved "
              "runs: the fixed ball (OU path inside it), the shift-invariant following ball (trend f = 1), "
              "and the atlas (a new filter each run: its centres' engines are built as the state reaches "
              "them).", "",
              "| model | steps | fixed | follow (trend) | atlas | atlas / fixed | moves | centres read "
              "| degenerate |", "|---|---|---:|---:|---:|---:|---:|---|---|"]
    lines += online
    write_fragment(FRAGMENT, lines)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
