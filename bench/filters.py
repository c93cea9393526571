"""Accuracy and speed of the Yau–Yau engine against reference filters, side by side (issue 3).

    .venv/bin/python -m bench.filters            # full: 20 seeds x 1000 steps per model (~15 min)
    .venv/bin/python -m bench.filters --quick    # 3 seeds x 300 steps (~2 min)

On the same simulated paths (solver/simulate.py) every filter runs over the same increments:
the engine (stable and literal forms), the fine-grid point-mass reference, bootstrap particle
filters (1k/10k/100k), EKF and UKF; the oracle is the exact sampled Kalman filter (OU), the exact
Beneš filter (Beneš) or the point-mass grid (cubic sensor, 2-D).  Accuracy: RMSE of the
conditional mean against the true state over all seeds and steps, and the gap
|E[x] − E_ref[x]| (∞-norm over components) averaged over steps and seeds, and its maximum.
Speed: µs per observation amortised over a chunk of 1000 (median over seeds) and over 100
chunks of 1, in the same process, so that ratios are meaningful on a noisy machine.
Writes bench/results/filters.md and docs/img/filters-*.png.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np
from yauyau.solver.model import Model, compile_model
from yauyau.solver.reference import (
    BenesFilter,
    BootstrapParticleFilter,
    DiscreteKalmanFilter,
    ExtendedKalmanFilter,
    PointMassFilter,
    UnscentedKalmanFilter,
)
from yauyau.solver.simulate import simulate
from yauyau.solver.spec import load_spec

ROOT = Path(__file__).resolve().parent.parent
DOCS = ROOT / "docs"
IMG = DOCS / "img"
CHUNK1_STEPS = 100


@dataclass
class Case:
    key: str
    title: str
    spec: str
    reference: str  # "kalman" | "benes" | "point-mass"
    pf_100k_seeds: int = 0  # the 100k-particle PF is run on this many seeds only (full run)
    max_steps: int | None = None  # horizon cap, where the signal would leave the ball B_R


CASES = [
    Case("cubic", "1-D cubic sensor (f = −0.2x, h = x³)", "examples/cubic_sensor.toml", "point-mass", 2),
    Case("ou", "1-D Ornstein–Uhlenbeck (h = x)", "examples/ou.toml", "kalman"),
    # tanh drift pushes |x| up at rate ~1: by t = 10 paths reach the rim of B_10, where every
    # bounded-domain filter (engine and grid alike) breaks down, so the horizon is t = 3.
    Case("benes", "1-D Beneš (f = tanh x, h = x)", "examples/benes.toml", "benes", max_steps=300),
    Case("range2d", "2-D damped rotation, h = x1³", "examples/range_2d.toml", "point-mass"),
]


@dataclass
class Tally:
    """Accumulated accuracy and speed of one filter on one model."""

    sq_error: float = 0.0
    count: int = 0
    gaps: list[np.ndarray] = field(default_factory=list)
    var_ratio_err: float = 0.0
    us_chunk: list[float] = field(default_factory=list)
    us_single: float | None = None
    degenerate: int = 0
    steps: int = 0

    def add(self, means, covs, truth, ref_means, ref_covs, seconds, degenerate):
        self.sq_error += float(np.sum((means - truth) ** 2))
        self.count += truth.size
        self.gaps.append(np.abs(means - ref_means).max(axis=1))
        var, ref_var = np.diagonal(covs, axis1=1, axis2=2), np.diagonal(ref_covs, axis1=1, axis2=2)
        self.var_ratio_err = max(self.var_ratio_err, float(np.max(np.abs(var / ref_var - 1))))
        self.us_chunk.append(1e6 * seconds / len(means))
        self.degenerate += degenerate
        self.steps += len(means)

    def row(self) -> dict[str, float]:
        gaps = np.concatenate(self.gaps)
        return {"rmse": np.sqrt(self.sq_error / self.count), "gap": float(gaps.mean()),
                "gap_max": float(gaps.max()), "var": self.var_ratio_err,
                "us1000": float(np.median(self.us_chunk)), "us1": self.us_single,
                "degenerate": self.degenerate / max(self.steps, 1), "seeds": len(self.gaps)}


# -- running a filter -----------------------------------------------------------------------------
def _run(filt, increments) -> tuple[np.ndarray, np.ndarray, float, int, Any]:
    """(means (K, n), covs (K, n, n), seconds, degenerate steps, final state)."""
    state = filt.initial_state()
    if hasattr(filt, "run_arrays"):  # the engine's array fast path
        start = time.perf_counter()
        state, res = filt.run_arrays(state, increments)
        seconds = time.perf_counter() - start
        return res.mean, res.cov, seconds, int(np.sum(res.degenerate)), state
    start = time.perf_counter()
    state, est = filt.run(state, increments)
    seconds = time.perf_counter() - start
    means = np.array([e.mean for e in est])
    covs = np.array([e.cov for e in est])
    return means, covs, seconds, sum(e.degenerate for e in est), state


# the particle filters here are this module's own; a ratio against the peer library is quoted from the
# benchmarks that run it (bench/peer_particles.py)
OWN_PF = ("this module's PF 10k (Euler, 2 substeps; the `particles` library: bench/results/cli.md, "
          "measurements.md)")

def _single_step_us(filt, increments) -> float:
    """µs per observation when each observation is its own chunk (the service's worst case)."""
    state = filt.initial_state()
    rows = increments[:CHUNK1_STEPS]
    go = filt.run_arrays if hasattr(filt, "run_arrays") else filt.run
    start = time.perf_counter()
    for k in range(len(rows)):
        state, _ = go(state, rows[k:k + 1])
    return 1e6 * (time.perf_counter() - start) / len(rows)


# -- the filters of one case ----------------------------------------------------------------------
def _engine(model: Model, form: str, offline):
    from yauyau.solver.engine.filter import YauYauFilter

    return YauYauFilter(model, offline, form=form, precision=model.spec.discretization.precision)


def _filters(model: Model, offline, seed: int, with_100k: bool) -> dict[str, Callable[[], Any]]:
    out: dict[str, Callable[[], Any]] = {}
    if offline is not None:
        out["Yau–Yau (stable)"] = lambda: _engine(model, "stable", offline)
        out["Yau–Yau (literal)"] = lambda: _engine(model, "literal", offline)
    out["point-mass grid"] = lambda: PointMassFilter(model)
    sizes = (1_000, 10_000, 100_000) if with_100k else (1_000, 10_000)
    for size in sizes:
        out[f"PF {size // 1000}k"] = lambda size=size: BootstrapParticleFilter(
            model, size, np.random.default_rng(10_000 + seed), substeps=2)
    out["EKF"] = lambda: ExtendedKalmanFilter(model, substeps=1)  # RK4 over dt = 0.01: error ~ (dt|f'|)⁵
    out["UKF"] = lambda: UnscentedKalmanFilter(model, substeps=1)
    return out


def _reference(model: Model, case: Case):
    if case.reference == "kalman":
        return DiscreteKalmanFilter(model)
    if case.reference == "benes":
        return BenesFilter(model)
    return PointMassFilter(model)


def _precompute(model: Model):
    try:
        from yauyau.solver.offline.pipeline import precompute
    except ImportError:  # the engine not landed: the references still run
        return None, float("nan")
    start = time.perf_counter()
    offline = precompute(model)
    return offline, time.perf_counter() - start


# -- one case ----------------------------------------------------------------------------------------
def run_case(case: Case, seeds: int, steps: int, quick: bool) -> dict[str, Any]:
    model = compile_model(load_spec(ROOT / case.spec))
    offline, pre_s = _precompute(model)
    tallies: dict[str, Tally] = {}
    l1: dict[str, float] = {}
    plot_data: dict[str, Any] = {}
    for seed in range(seeds):
        sim = simulate(model, steps, np.random.default_rng(seed))
        truth = sim.states[1:]
        ref = _reference(model, case)
        ref_means, ref_covs, ref_s, _, ref_state = _run(ref, sim.increments)
        tallies.setdefault(f"reference: {case.reference}", Tally()).add(
            ref_means, ref_covs, truth, ref_means, ref_covs, ref_s, 0)
        with_100k = (not quick) and seed < case.pf_100k_seeds
        for name, make in _filters(model, offline, seed, with_100k).items():
            if name == "point-mass grid" and case.reference == "point-mass":
                continue  # it is the reference
            filt = make()
            means, covs, secs, degenerate, state = _run(filt, sim.increments)
            tallies.setdefault(name, Tally()).add(means, covs, truth, ref_means, ref_covs, secs, degenerate)
            if seed == 0:
                tallies[name].us_single = _single_step_us(make(), sim.increments)
                plot_data[name] = means
                if case.reference == "benes":
                    l1[name] = _benes_l1(model, ref, make, sim.increments)
        if seed == 0:
            tallies[f"reference: {case.reference}"].us_single = _single_step_us(ref, sim.increments)
            plot_data.update(truth=truth, reference=ref_means, times=sim.times[1:], increments=sim.increments,
                             model=model, offline=offline, ref_state=ref_state)
    return {"case": case, "rows": {k: t.row() for k, t in tallies.items()}, "precompute_s": pre_s,
            "l1": l1, "plot": plot_data, "seeds": seeds, "steps": steps}


def _benes_l1(model: Model, exact: BenesFilter, make, increments, every: int = 100) -> float:
    """Max over checkpoints (every 100 steps) of the L1 distance of the density to the exact one."""
    filt = make()
    grid = np.linspace(-model.radius, model.radius, 4001)[:, None]
    s_f, s_e = filt.initial_state(), exact.initial_state()
    worst = 0.0
    for start in range(0, len(increments), every):
        chunk = increments[start:start + every]
        s_f, _ = filt.run(s_f, chunk)
        s_e, _ = exact.run(s_e, chunk)
        diff = np.abs(filt.density(s_f, grid) - exact.density(s_e, grid))
        worst = max(worst, float(np.trapezoid(diff, grid[:, 0])))
    return worst


# -- report --------------------------------------------------------------------------------------------
def _fmt(value: float | None, digits: int = 3) -> str:
    if value is None or not np.isfinite(value):
        return "—"
    return f"{value:.{digits}g}"


def table(result: dict[str, Any]) -> str:
    rows = result["rows"]
    engine = rows.get("Yau–Yau (stable)")
    lines = ["| filter | seeds | RMSE vs truth | mean gap to ref | max gap | max rel. var err "
             "| µs/obs (chunk 1000) | µs/obs (chunk 1) | time / engine | degenerate |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for name, r in rows.items():
        ratio = r["us1000"] / engine["us1000"] if engine else float("nan")
        lines.append(f"| {name} | {r['seeds']} | {_fmt(r['rmse'])} | {_fmt(r['gap'])} | {_fmt(r['gap_max'])} "
                     f"| {_fmt(r['var'])} | {_fmt(r['us1000'])} | {_fmt(r['us1'])} | {_fmt(ratio)}× "
                     f"| {r['degenerate']:.0%} |")
    if result["l1"]:
        lines.append("")
        lines.append("Density L1 distance to the exact Beneš density (max over checkpoints every 100 steps, "
                     "seed 0): " + ", ".join(f"{k} {_fmt(v)}" for k, v in result["l1"].items()))
    return "\n".join(lines)


def targets(results: dict[str, dict[str, Any]]) -> list[str]:
    """Each issue-3 target with the measured value and by how much it is met or missed."""
    out = []

    def check(label: str, value: float, limit: float, smaller: bool = True) -> None:
        if not np.isfinite(value):
            out.append(f"- {label}: not measured (engine missing)")
            return
        met = value <= limit if smaller else value >= limit
        factor = limit / value if smaller else value / limit
        out.append(f"- {label}: {_fmt(value)} vs target {'≤' if smaller else '≥'} {_fmt(limit)} — "
                   f"{'**met**' if met else '**missed**'} ({factor:.3g}× {'margin' if met else 'short'})")

    def engine(key: str, col: str) -> float:
        row = results.get(key, {}).get("rows", {}).get("Yau–Yau (stable)")
        return float("nan") if row is None else row[col]

    def pf(key: str, col: str) -> float:
        return results[key]["rows"]["PF 10k"][col] if key in results else float("nan")

    if "cubic" in results:
        check("cubic sensor: mean gap to the fine grid", engine("cubic", "gap"), 0.01)
        check("cubic sensor: µs/obs (chunk 1000)", engine("cubic", "us1000"), 10.0)
        check(f"cubic sensor: speed-up over {OWN_PF}", pf("cubic", "us1000") / engine("cubic", "us1000"),
              100.0, smaller=False)
        check(f"cubic sensor: gap of {OWN_PF} / gap of engine", pf("cubic", "gap") / engine("cubic", "gap"),
              1.0, smaller=False)
    if "ou" in results:
        check("OU: max |mean − Kalman mean|", engine("ou", "gap_max"), 1e-3)
        check("OU: max relative variance error vs Kalman", engine("ou", "var"), 0.01)
    if "benes" in results:
        l1 = results["benes"]["l1"].get("Yau–Yau (stable)", np.nan)
        check("Beneš: density L1 to the exact filter", l1, 1e-3)
    if "range2d" in results:
        check("2-D: µs/obs (chunk 1000)", engine("range2d", "us1000"), 500.0)
        check("2-D: mean gap to the fine grid", engine("range2d", "gap"), 0.02)
        check(f"2-D: speed-up over {OWN_PF}", pf("range2d", "us1000") / engine("range2d", "us1000"), 1.0,
              smaller=False)
    return out


def plots(result: dict[str, Any]) -> list[str]:
    """Density over time (engine vs reference) and error over time for one case; returns file names."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    key, data = result["case"].key, result["plot"]
    IMG.mkdir(parents=True, exist_ok=True)
    names = []
    times = data["times"]
    fig, ax = plt.subplots(figsize=(8, 4))
    for name, means in data.items():
        if isinstance(means, np.ndarray) and name not in ("truth", "reference", "times", "increments"):
            gap = np.abs(means - data["reference"]).max(axis=1)
            ax.semilogy(times, np.maximum(gap, 1e-12), label=name, lw=1)
    ax.set_xlabel("t")
    ax.set_ylabel("|E[x] − E_ref[x]|")
    ax.set_title(f"{result['case'].title}: gap to the reference over time (seed 0)")
    ax.legend(fontsize=7, ncol=2)
    fig.tight_layout()
    path = IMG / f"filters-{key}-error.png"
    fig.savefig(path, dpi=110)
    plt.close(fig)
    names.append(path.name)
    if data.get("offline") is not None and result["case"].reference != "kalman" and data["model"].n == 1:
        names.append(_density_plot(result, plt))
    return names


def _density_plot(result, plt) -> str:
    data, model = result["plot"], result["plot"]["model"]
    engine = _engine(model, "stable", data["offline"])
    grid = np.linspace(-model.radius, model.radius, 400)[:, None]
    state, columns, every = engine.initial_state(), [], 10
    incs = data["increments"]
    for start in range(0, len(incs), every):
        state, _ = engine.run(state, incs[start:start + every])
        columns.append(engine.density(state, grid))
    image = np.array(columns).T
    fig, ax = plt.subplots(figsize=(8, 4))
    t_end = data["times"][-1]
    extent = (0, t_end, grid[0, 0], grid[-1, 0])
    ax.imshow(image, origin="lower", aspect="auto", extent=extent, cmap="viridis")
    ax.plot(data["times"], data["truth"][:, 0], "w-", lw=0.8, label="true state")
    ax.plot(data["times"], data["reference"][:, 0], "r--", lw=0.8, label="reference mean")
    ax.set_ylim(-4, 4)
    ax.set_xlabel("t")
    ax.set_ylabel("x")
    ax.set_title(f"{result['case'].title}: Yau–Yau conditional density (seed 0)")
    ax.legend(fontsize=7, loc="upper right")
    fig.tight_layout()
    path = IMG / f"filters-{result['case'].key}-density.png"
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path.name


def write_markdown(results: dict[str, dict[str, Any]], images: list[str], command: str, wall: float) -> Path:
    parts = ["## Filters: accuracy and speed against reference filters", "",
             f"Command: `{command}` (wall time {wall:.0f} s). Every filter runs on the same simulated paths "
             "(Euler–Maruyama, 10 substeps per dt); RMSE is of the conditional mean against the true state "
             "over all seeds and steps; *gap* is |E[x] − E_ref[x]|∞ averaged over steps and seeds "
             "(*max gap*: its maximum); *max rel. var err* compares the marginal variances with the "
             "reference. Speed: µs per observation for one chunk of all steps (median over seeds) and for "
             f"{CHUNK1_STEPS} chunks of one observation; *time / engine* is the chunk-1000 ratio to the "
             "stable engine, measured in the same run. The engine is timed through `run_arrays` (its array "
             "fast path); particle filters use 2 Euler–Maruyama substeps per dt, EKF/UKF one RK4 step.",
             "", "### Targets", ""]
    parts += targets(results)
    for res in results.values():
        case = res["case"]
        parts += ["", f"### {case.title}", "",
                  f"`{case.spec}`, {res['seeds']} seeds × {res['steps']} steps, reference: {case.reference}; "
                  f"offline precompute {_fmt(res['precompute_s'])} s.", "", table(res)]
    if images:
        parts += ["", "### Plots", ""] + [f"![{name}](../../docs/img/{name})" for name in images]
    out = ROOT / "bench" / "results" / "filters.md"
    out.write_text("\n".join(parts) + "\n")
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.filters", description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="3 seeds x 300 steps, no 100k-particle PF")
    parser.add_argument("--seeds", type=int, default=None)
    parser.add_argument("--steps", type=int, default=None)
    parser.add_argument("--only", default="", help="comma-separated: " + ",".join(c.key for c in CASES))
    args = parser.parse_args(argv)
    seeds = args.seeds or (3 if args.quick else 20)
    steps = args.steps or (300 if args.quick else 1000)
    wanted = [w for w in args.only.split(",") if w] or [c.key for c in CASES]
    started = time.perf_counter()
    results, images = {}, []
    for case in CASES:
        if case.key not in wanted:
            continue
        t0 = time.perf_counter()
        results[case.key] = run_case(case, seeds, min(steps, case.max_steps or steps), args.quick)
        print(f"## {case.title} ({time.perf_counter() - t0:.0f} s)\n{table(results[case.key])}\n", flush=True)
        images += plots(results[case.key])
    command = ".venv/bin/python -m bench.filters" + (" --quick" if args.quick else "")
    out = write_markdown(results, images, command, time.perf_counter() - started)
    print("\n".join(targets(results)))
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
