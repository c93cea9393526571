"""The 2-D example (damped rotation, h = x1³) against the peers, and cheaper discretisations of it.

    .venv/bin/python -m bench.range_2d            # 5 seeds x 1000 steps, CLI on 20 000 rows (~10 min)
    .venv/bin/python -m bench.range_2d --quick    # 2 seeds x 300 steps, CLI on 5 000 rows
    .venv/bin/python -m bench.measurements --setup-peers   # once: the peers' venv

On the same simulated paths of examples/range_2d.toml (solver/simulate.py): the Yau–Yau engine at the
example's discretisation and at the candidate ones of CANDIDATES (fewer basis functions, the P2 +
bubble element, a smaller ball, double precision), the `particles` library's bootstrap filter
(N. Chopin; N = 10 000, the EXACT Gaussian transition of the linear drift over dt: Φ = expm(A dt), Q by
Van Loan; the sensor written x1*x1*x1) and FilterPy's UKF, both in their own venv
(bench/out/peers-venv, numpy < 2) through bench/peer_range_only.py, one subprocess per seed,
interleaved with our runs.  The reference is the optimal filter computed on a fine point-mass grid
(bench/filters.py's reference for its case "range2d", on the example's problem with a ball of radius
at least REFERENCE_RADIUS whatever the candidate).  Gap: |E[x] − E_ref[x]|∞ averaged over steps and
seeds (as bench/filters.py).  Cost: CPU time per row, one BLAS thread, medians over seeds —
``run_arrays`` in chunks of 1000 in this process, and `yauyau filter` on a CSV (the run on the file
minus the run on one row, which holds the start-up and the model load; bench/cli_speed.py), the CLI
choosing its kernel as it does by default.  Writes bench/results/range-2d.md.

Target (issue 37): per row ≥ 15× faster than particles 10k, at most the UKF's cost, with a mean gap
≤ 1/10 of the UKF's.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
import tomllib
from pathlib import Path

import numpy as np
from scipy.linalg import expm
from threadpoolctl import threadpool_limits

from .fragments import write_fragment

ROOT = Path(__file__).resolve().parent.parent
EXAMPLE = ROOT / "examples" / "range_2d.toml"
FRAGMENT = ROOT / "bench" / "results" / "range-2d.md"
PEER_PYTHON = ROOT / "bench" / "out" / "peers-venv" / "bin" / "python"
PEER_SCRIPT = Path(__file__).resolve().parent / "peer_range_only.py"
REFERENCE_RADIUS = 4.5  # the reference grid's ball, whatever ball a candidate uses
PARTICLES = 10_000
PF_ROW, UKF_ROW = f"particles bootstrap, {PARTICLES // 1000}k", "FilterPy UKF"
TARGET_PF, TARGET_UKF_COST, TARGET_UKF_GAP = 15.0, 1.0, 0.1
# (label, [discretization] overrides, [domain] overrides); the first row is the example as it stands, the
# others say every field they change from it (mesh None: the default mesh for the basis)
DEFAULT = {"mesh": None, "element": None, "precision": "single"}
CANDIDATES = [
    ("the example as it stands", {}, {}),
    ("basis 600", {**DEFAULT, "basis": 600}, {}),
    ("basis 500", {**DEFAULT, "basis": 500}, {}),
    ("basis 400", {**DEFAULT, "basis": 400}, {}),
    ("basis 500, mesh 16", {**DEFAULT, "basis": 500, "mesh": 16}, {}),
    ("basis 450, mesh 16", {**DEFAULT, "basis": 450, "mesh": 16}, {}),
    ("bubble element, basis 300", {**DEFAULT, "basis": 300, "element": "bubble"}, {}),
    ("following ball, radius 3.5, basis 400", {**DEFAULT, "basis": 400}, {"radius": 3.5, "follow": True}),
]


def example_doc() -> dict:
    return tomllib.loads(EXAMPLE.read_text())


def candidate_spec(discretization: dict, domain: dict):
    from yauyau.solver.spec import spec_from_dict

    doc = example_doc()
    merged = {**doc["discretization"], **discretization}
    doc["discretization"] = {k: v for k, v in merged.items() if v is not None}
    doc["domain"] = {**doc["domain"], **domain}
    return spec_from_dict(doc)


def reference_means(increments: np.ndarray) -> np.ndarray:
    """The optimal filter's means on a fine point-mass grid: bench/filters.py's reference for "range2d"."""
    from yauyau.solver.model import compile_model

    from .filters import CASES, _reference, _run

    case = next(c for c in CASES if c.key == "range2d")
    radius = max(REFERENCE_RADIUS, float(example_doc()["domain"]["radius"]))
    model = compile_model(candidate_spec({}, {"radius": radius}))
    means, _, _, _, _ = _run(_reference(model, case), increments)
    return means


def exact_transition(model) -> tuple[np.ndarray, np.ndarray]:
    """Φ = expm(A dt) and Q = ∫₀^dt e^{As} a e^{Aᵀs} ds (Van Loan) of the linear drift f = Ax."""
    affine = model.affine_drift
    if affine is None or np.any(affine[1]):
        raise SystemExit("the peers' exact transition needs a linear drift f = Ax")
    A, n, dt = np.asarray(affine[0], float), model.n, model.dt
    E = expm(np.block([[-A, model.a], [np.zeros((n, n)), A.T]]) * dt)
    Phi = E[n:, n:].T
    Q = Phi @ E[:n, n:]
    return Phi, 0.5 * (Q + Q.T)


def peers(model, increments: np.ndarray, seed: int) -> dict | None:
    """particles' bootstrap filter (10k) and FilterPy's UKF on one seed, in the peers' venv."""
    if not PEER_PYTHON.exists():
        return None
    Phi, Q = exact_transition(model)
    prior = model.spec.initial
    with tempfile.TemporaryDirectory() as tmp:
        src, dst = Path(tmp) / "in.npz", Path(tmp) / "out.npz"
        np.savez(src, increments=increments[None, :, 0], seeds=np.array([seed]), Phi=Phi, Q=Q,
                 prior_mean=np.array(prior.mean, float), prior_cov=np.array(prior.cov, float),
                 dt=model.dt, noise_var=float(model.R[0, 0]), offset=0.0, particles=PARTICLES,
                 sensor="cube1")
        subprocess.run([str(PEER_PYTHON), str(PEER_SCRIPT), str(src), str(dst)], check=True)
        with np.load(dst) as out:
            return {k: out[k] for k in out.files}


def _engine(flt, increments: np.ndarray) -> tuple[np.ndarray, float, int]:
    """(means, CPU seconds, rows flagged degenerate) of ``run_arrays`` in chunks of 1000."""
    state, means, flagged = flt.initial_state(), [], 0
    start = time.process_time()
    for k in range(0, len(increments), 1000):
        state, result = flt.run_arrays(state, increments[k:k + 1000])
        means.append(result.mean)
        flagged += int(np.sum(result.degenerate))
    return np.concatenate(means), time.process_time() - start, flagged


def _cli(model_id: str, store: Path, rows: Path, out: Path) -> tuple[float, int]:
    """(CPU seconds (user + system) of `yauyau filter` on ``rows``, one BLAS thread; its rows flagged
    degenerate).  Exit 3 (some rows degenerate) is a result here, not a failure."""
    yauyau = Path(sys.executable).with_name("yauyau")
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1")
    command = [str(yauyau), "filter", model_id, "--store", str(store), "--increments", str(rows),
               "--out", str(out)]
    before = os.times()
    done = subprocess.run(command, capture_output=True, text=True, env=env)
    after = os.times()
    if done.returncode not in (0, 3):
        raise SystemExit(f"yauyau filter failed ({done.returncode}): {done.stderr[-2000:]}")
    with out.open() as fh:
        header = fh.readline().strip().split(",")
        column = header.index("degenerate")
        flagged = sum(line.strip().split(",")[column] == "1" for line in fh)
    seconds = (after.children_user - before.children_user) + (after.children_system - before.children_system)
    return seconds, flagged


def _load() -> str:
    one, five, fifteen = os.getloadavg()
    return f"{one:.2f}, {five:.2f}, {fifteen:.2f} on {os.cpu_count()} cores"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.range_2d", description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="2 seeds x 300 steps, CLI on 5 000 rows")
    parser.add_argument("--only", default="", help="comma-separated candidate numbers (0: the example)")
    args = parser.parse_args(argv)
    seeds, steps, cli_rows, repeats = (2, 300, 5000, 2) if args.quick else (5, 1000, 20_000, 3)
    wanted = [int(i) for i in args.only.split(",") if i] or list(range(len(CANDIDATES)))
    from yauyau.solver.methods import make_filter
    from yauyau.solver.model import compile_model
    from yauyau.solver.simulate import simulate

    import yauyau

    load_start, began = _load(), time.perf_counter()
    base = compile_model(candidate_spec({}, {}))
    paths = [simulate(base, steps, np.random.default_rng(seed)).increments for seed in range(seeds)]
    long_rows = simulate(base, cli_rows, np.random.default_rng(1000)).increments
    rows: dict[str, dict] = {}
    versions = None
    with tempfile.TemporaryDirectory() as tmp, threadpool_limits(1, user_api="blas"):
        tmp = Path(tmp)
        data, one = tmp / "rows.csv", tmp / "one.csv"
        data.write_text("dy\n" + "\n".join(repr(v) for v in long_rows[:, 0].tolist()) + "\n")
        one.write_text("dy\n" + repr(float(long_rows[0, 0])) + "\n")
        refs = [reference_means(dy) for dy in paths]
        filters = {}
        for i in wanted:
            label, disc, dom = CANDIDATES[i]
            spec = candidate_spec(disc, dom)
            t0 = time.perf_counter()
            mid = yauyau.precompute(spec, tmp / "store")
            pre = time.perf_counter() - t0
            loaded = yauyau.api.load_model(tmp / "store", mid)
            flt = make_filter(loaded.model, loaded.offline, loaded.method)
            _engine(flt, paths[0][:50])  # warm-up: the kernels' first call
            filters[label] = (mid, flt)
            rows[label] = {"Q": len(flt.nodes), "N": flt.offline.basis.shape[1], "pre": pre, "gaps": [],
                           "us": [], "cli": [], "degenerate": 0, "cli_degenerate": 0.0}
        for seed, (dy, ref) in enumerate(zip(paths, refs, strict=True)):
            peer = peers(base, dy, seed)  # interleaved with our runs: the same load on both
            if peer is not None:
                versions = ", ".join(str(v) for v in peer["versions"])
                for key, name in (("pf", PF_ROW), ("ukf", UKF_ROW)):
                    r = rows.setdefault(name, {"gaps": [], "us": [], "cli": []})
                    r["gaps"].append(np.abs(peer[f"{key}_means"][0] - ref).max(axis=1))
                    r["us"].append(1e6 * float(peer[f"{key}_seconds"][0]) / steps)
            for label, (_, flt) in filters.items():
                means, seconds, flagged = _engine(flt, dy)
                rows[label]["degenerate"] += flagged
                rows[label]["gaps"].append(np.abs(means - ref).max(axis=1))
                rows[label]["us"].append(1e6 * seconds / steps)
            print(f"seed {seed} done ({time.perf_counter() - began:.0f} s)", flush=True)
        for _ in range(repeats):
            for label, (mid, _) in filters.items():
                full, flagged = _cli(mid, tmp / "store", data, tmp / "out.csv")
                first, _ = _cli(mid, tmp / "store", one, tmp / "out1.csv")
                rows[label]["cli"].append(1e6 * (full - first) / (cli_rows - 1))
                rows[label]["cli_degenerate"] = flagged / cli_rows
    load_end = _load()
    pf, ukf = rows.get(PF_ROW), rows.get(UKF_ROW)
    table = _table(rows, pf, ukf)
    command = "python -m bench.range_2d" + (" --quick" if args.quick else "") + (
        f" --only {args.only}" if args.only else "")
    lines = ["## 2-D rotation with a cubic sensor against particles and the UKF", "",
             f"`{command}` (wall {time.perf_counter() - began:.0f} s): examples/range_2d.toml (damped "
             "rotation, h = x1³, dt = 0.01), "
             f"{seeds} seeds × {steps} steps; reference: point-mass grid (bench/filters.py's, 128² cells, "
             f"radius {REFERENCE_RADIUS:g}). CPU time per row, one BLAS thread, medians over seeds; "
             f"`yauyau filter` on a CSV of {cli_rows} rows minus one row, median of {repeats}. Peers: "
             + (versions or "not run (no bench/out/peers-venv: `python -m bench.measurements --setup-peers`)")
             + " (exact transition, sensor x1*x1*x1). Load average (1, 5, 15 min) at the start "
             f"{load_start}, at the end {load_end}.", "", *table, "",
             f"Target (issue 37): ≥ {TARGET_PF:g}× faster per row than particles 10k, at most the UKF's cost "
             f"per row, mean gap ≤ {TARGET_UKF_GAP:g} × the UKF's (in-process `run_arrays` cost)."]
    write_fragment(FRAGMENT, lines)
    print("\n".join(lines))
    return 0


def _table(rows: dict, pf: dict | None, ukf: dict | None) -> list[str]:
    def us(r: dict) -> float:
        return float(np.median(r["us"]))

    def gap(r: dict) -> float:
        return float(np.concatenate(r["gaps"]).mean())

    out = ["| filter | Q | N | precompute s | µs/row `run_arrays` | µs/row CLI | mean gap | max gap "
           "| degenerate rows (paths; CLI file) | particles / ours | ours / UKF | gap / UKF gap | target |",
           "|---|---:|---:|---:|---:|---:|---:|---:|---|---:|---:|---:|---|"]
    for label, r in rows.items():
        ours = "Q" in r
        cli = float(np.median(r["cli"])) if r["cli"] else float("nan")
        speed = us(pf) / us(r) if pf and ours else float("nan")
        cost = us(r) / us(ukf) if ukf and ours else float("nan")
        rel = gap(r) / gap(ukf) if ukf and ours else float("nan")
        met = "—"
        if ours and pf and ukf:
            ok = speed >= TARGET_PF and cost <= TARGET_UKF_COST and rel <= TARGET_UKF_GAP
            met = "met" if ok else "missed"
        cells = [f"{r['Q']}", f"{r['N']}", f"{r['pre']:.1f}"] if ours else ["—", "—", "—"]
        out.append(f"| {label} | " + " | ".join(cells) + f" | {us(r):.0f} | "
                   + (f"{cli:.0f}" if ours else "—") + f" | {gap(r):.4f} | "
                   f"{float(np.concatenate(r['gaps']).max()):.3f} | "
                   + (f"{r['degenerate'] / sum(map(len, r['gaps'])):.1%}; {r['cli_degenerate']:.1%} | "
                      if ours else "— | ")
                   + (f"{speed:.1f}× | {cost:.2f}× | {rel:.3f} | {met} |" if ours else "— | — | — | — |"))
    return out


if __name__ == "__main__":
    raise SystemExit(main())
