"""Range-only tracking in 4-D: the Yau–Jia filter against the peers users would pick, side by side.

    .venv/bin/python -m bench.yau_jia            # 5 seeds x 100 steps (~5 min)
    .venv/bin/python -m bench.yau_jia --quick    # 2 seeds x 50 steps
    .venv/bin/python -m bench.measurements --setup-peers   # once: the peers' venv

On the same simulated increments of examples/range_only_4d.toml: yau-jia at 8/16/32/64 components
(32 is the default from 3-D on), the `particles` library's bootstrap filter (N. Chopin) with 10k
particles and FilterPy's UKF; the reference is a 10⁶-particle bootstrap filter with exact
constant-velocity transitions written here (its Monte Carlo error is measured by a second run).
The peers run in their own venv (bench/out/peers-venv: particles pins numpy < 2) through
bench/peer_range_only.py, one subprocess per seed, interleaved with our runs so that both see the
same machine load.  Gap: |E[x] − E_ref[x]| averaged over steps, coordinates and seeds.  Cost: ms per
observation, median over seeds, one BLAS thread.  Then the dimension: n = 2, 4, 6 (1-, 2-, 3-D
constant velocity with a range sensor √(1 + |p|²) / |p| / |p|), cost per observation and gap to a
10⁵-particle reference.  Last, the 2-D ring posterior of tests/solver/exact/test_yau_jia.py: gap to the
point-mass reference and cost by the number of components and the splits allowed per step.  Writes
bench/results/yau-jia.md.
"""

from __future__ import annotations

import argparse
import math
import subprocess
import tempfile
import time
from pathlib import Path

import numpy as np
from scipy.linalg import expm
from threadpoolctl import threadpool_limits
from yauyau.solver.exact.yau_jia import YauJiaFilter, default_components
from yauyau.solver.model import compile_model
from yauyau.solver.simulate import simulate
from yauyau.solver.spec import load_spec, spec_from_dict

ROOT = Path(__file__).resolve().parent.parent
RESULTS = ROOT / "bench" / "results"


def _cv_matrices(model, d):
    n = model.n
    half = n // 2
    F = np.zeros((n, n))
    F[:half, half:] = np.eye(half)
    Phi = expm(F * d)
    E = expm(np.block([[-F, model.a], [np.zeros((n, n)), F.T]]) * d)
    Qd = E[n:, n:].T @ E[:n, n:]
    return Phi, 0.5 * (Qd + Qd.T)


def reference_pf(model, increments, N, rng, substeps=2):
    """Bootstrap filter with exact Gaussian transitions over dt/substeps, ∫h by the trapezoid rule."""
    n, dt = model.n, model.dt
    Phi, Qd = _cv_matrices(model, dt / substeps)
    lam, U = np.linalg.eigh(Qd)
    G = U * np.sqrt(np.clip(lam, 0, None))
    prior = model.spec.initial
    x = rng.multivariate_normal(prior.mean, prior.cov, size=N)
    logw, r, means = np.zeros(N), float(model.R[0, 0]), []
    for dy in increments:
        integral = np.zeros(N)
        for _ in range(substeps):
            before = model.h(x)[:, 0]
            x = x @ Phi.T + rng.standard_normal((N, n)) @ G.T
            integral += 0.5 * (before + model.h(x)[:, 0]) * dt / substeps
        logw += -0.5 * (dy[0] - integral) ** 2 / (r * dt)
        w = np.exp(logw - logw.max())
        w /= w.sum()
        means.append(w @ x)
        if 1.0 / (w @ w) < N / 2:
            idx = np.minimum(np.searchsorted(np.cumsum(w), (rng.random() + np.arange(N)) / N), N - 1)
            x, logw = x[idx], np.zeros(N)
    return np.array(means)


PEER_PYTHON = ROOT / "bench" / "out" / "peers-venv" / "bin" / "python"
PEER_SCRIPT = Path(__file__).resolve().parent / "peer_range_only.py"


def peers(model, increments, seed: int, N: int = 10**4) -> dict | None:
    """particles' bootstrap filter (N particles) and FilterPy's UKF on one seed's increments, in the
    peers' venv; None when that venv is missing."""
    if not PEER_PYTHON.exists():
        return None
    Phi, Qd = _cv_matrices(model, model.dt)
    prior = model.spec.initial
    with tempfile.TemporaryDirectory() as tmp:
        src, dst = Path(tmp) / "in.npz", Path(tmp) / "out.npz"
        np.savez(src, increments=increments[None, :, 0], seeds=np.array([seed]), Phi=Phi, Q=Qd,
                 prior_mean=np.array(prior.mean, float), prior_cov=np.array(prior.cov, float),
                 dt=model.dt, noise_var=float(model.R[0, 0]), offset=0.0, particles=N)
        subprocess.run([str(PEER_PYTHON), str(PEER_SCRIPT), str(src), str(dst)], check=True)
        out = np.load(dst)
        return {k: out[k] for k in out.files}


def ours(model, increments, components):
    flt = YauJiaFilter(model, max_components=components)
    state = flt.initial_state()
    start = time.perf_counter()
    _, result = flt.run_arrays(state, increments)
    return result.mean, time.perf_counter() - start


def cv_model(dims: int):
    """Constant velocity in `dims` dimensions (state 2·dims), range sensor."""
    pos = [f"p{i}" for i in range(1, dims + 1)]
    vel = [f"v{i}" for i in range(1, dims + 1)]
    n = 2 * dims
    diffusion = np.zeros((n, n))
    diffusion[dims:, dims:] = 0.25 * np.eye(dims)
    mean = [10.0] + [0.0] * (dims - 1) + [0.0] * (dims - 1) + [1.0]
    cov = np.diag([0.25] + [1.0] * (dims - 1) + [0.25] * dims)
    inside = " + ".join(f"{p}**2" for p in pos)
    sensor = f"sqrt(1 + {inside})" if dims == 1 else f"sqrt({inside})"
    doc = {"name": f"cv-{n}d", "state": pos + vel, "drift": vel + ["0"] * dims, "observation": [sensor],
           "diffusion": diffusion.tolist(), "observation_noise": [[0.25]], "method": "yau-jia",
           "initial": {"kind": "gaussian", "mean": mean, "cov": cov.tolist()},
           "domain": {"radius": 30.0}, "discretization": {"dt": 0.02, "basis": 2}}
    return compile_model(spec_from_dict(doc))


def ring_model():
    """The 2-D model of tests/solver/exact/test_yau_jia.py: a damped rotation seen through the range
    √(1 + |x|²)."""
    doc = {"name": "ring-2d", "state": ["x1", "x2"], "drift": ["-0.5*x1 + x2", "-x1 - 0.5*x2"],
           "observation": ["sqrt(1 + x1**2 + x2**2)"], "method": "yau-jia",
           "initial": {"kind": "gaussian", "mean": [1.0, 0.5], "cov": [[0.5, 0.0], [0.0, 0.5]]},
           "domain": {"radius": 5.0}, "discretization": {"dt": 0.01, "basis": 64}}
    return compile_model(spec_from_dict(doc))


def ring_rows(seeds: int, steps: int) -> list[tuple[int, int, float, float, float]]:
    """2-D: (components, split budget, worst and mean over seeds of the max gap to the point-mass
    reference, ms per observation) for caps 32, 64, 128 (default) and, for contrast, 128 with the
    former one split per step."""
    from yauyau.solver.reference.pointmass import PointMassFilter

    model = ring_model()
    data, refs = [], []
    for seed in range(seeds):
        dy = simulate(model, steps, np.random.default_rng(100 + seed)).increments
        ref = PointMassFilter(model)
        _, estimates = ref.run(ref.initial_state(), dy)
        data.append(dy)
        refs.append(np.array([e.mean for e in estimates]))
    out = []
    for cap, budget in ((32, None), (64, None), (128, None), (128, 1)):
        gaps, costs = [], []
        for dy, ref in zip(data, refs, strict=True):
            flt = YauJiaFilter(model, max_components=cap, split_budget=budget)
            state = flt.initial_state()
            start = time.perf_counter()
            _, result = flt.run_arrays(state, dy)
            costs.append((time.perf_counter() - start) / steps)
            gaps.append(float(np.abs(result.mean - ref).max()))
        out.append((cap, flt.split_budget, max(gaps), float(np.mean(gaps)), float(np.median(costs)) * 1e3))
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.yau_jia", description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true")
    args = parser.parse_args(argv)
    seeds, steps = (2, 50) if args.quick else (5, 100)
    model = compile_model(load_spec(ROOT / "examples" / "range_only_4d.toml"))
    rows: dict[str, list[tuple[float, float]]] = {}
    mc, versions = [], None
    with threadpool_limits(1):
        for seed in range(seeds):
            dy = simulate(model, steps, np.random.default_rng(seed)).increments
            ref = reference_pf(model, dy, 10**6, np.random.default_rng(1000 + seed))
            if seed == 0:
                mc.append(np.abs(reference_pf(model, dy, 10**6, np.random.default_rng(7)) - ref).mean())
            ours(model, dy[:5], 32)  # warm-up: the sensor's generated code, the flows
            peer = peers(model, dy, seed)
            for J in (8, 16, 32, 64):
                mean, sec = ours(model, dy, J)
                gap = np.abs(mean - ref).mean()
                rows.setdefault(f"yau-jia, {J} components", []).append((gap, sec / steps))
            if peer is not None:
                versions = ", ".join(str(v) for v in peer["versions"])
                rows.setdefault("particles bootstrap, 10k", []).append(
                    (np.abs(peer["pf_means"][0] - ref).mean(), float(peer["pf_seconds"][0]) / steps))
                rows.setdefault("FilterPy UKF", []).append(
                    (np.abs(peer["ukf_means"][0] - ref).mean(), float(peer["ukf_seconds"][0]) / steps))
        ring = ring_rows(2 if args.quick else 5, 300 if args.quick else 1000)
        dims = []
        for d in (1, 2, 3):
            m = cv_model(d)
            dy = simulate(m, steps, np.random.default_rng(11)).increments
            ref = reference_pf(m, dy, 10**5, np.random.default_rng(12))
            mean, sec = ours(m, dy, 32)
            dims.append((m.n, np.abs(mean - ref).mean(), sec / steps * 1e3))
    pf = rows.get("particles bootstrap, 10k")
    pf_cost = float(np.median([c for _, c in pf])) if pf else math.nan
    lines = ["## Yau-Jia filter: 4-D range-only tracking", "",
             f"`python -m bench.yau_jia{' --quick' if args.quick else ''}`: examples/range_only_4d.toml, "
             f"{seeds} seed(s) x {steps} steps (dt = 0.02); reference: 10^6-particle bootstrap filter "
             f"(Monte Carlo error, measured by a second run: {np.mean(mc):.4f}). One BLAS thread. Peers: "
             + (versions or "not run (no bench/out/peers-venv: `python -m bench.measurements --setup-peers`)")
             + ".", "",
             "| filter | mean gap to 10^6 particles | ms per observation | speed vs particles 10k |",
             "|---|---|---|---|"]
    for name, values in rows.items():
        gap = float(np.mean([g for g, _ in values]))
        cost = float(np.median([c for _, c in values]))
        speed = f"{pf_cost / cost:.1f}x" if math.isfinite(pf_cost) else "—"
        lines.append(f"| {name} | {gap:.4f} | {cost * 1e3:.3f} | {speed} |")
    lines += ["", "Dimension (constant velocity in 1, 2, 3 dimensions with a range sensor; yau-jia with 32 "
              "components; reference 10^5 particles):", "", "| n | mean gap | ms per observation |",
              "|---|---|---|"]
    lines += [f"| {n} | {gap:.4f} | {ms:.3f} |" for n, gap, ms in dims]
    cap = default_components(4)
    default = rows.get(f"yau-jia, {cap} components")
    if pf and default:
        ratios = {k: pf_cost / float(np.median([c for _, c in v])) for k, v in rows.items()}
        speed, best = ratios[f"yau-jia, {cap} components"], max(v for k, v in ratios.items() if "yau" in k)
        verdict = "met" if speed >= 10 else (f"missed: {speed:.1f}x at the default {cap} components, "
                                             f"{best:.1f}x at best")
        gaps = {k: float(np.mean([g for g, _ in v])) for k, v in rows.items()}
        smaller = all(g < gaps["particles bootstrap, 10k"] for k, g in gaps.items() if "yau" in k)
        lines += ["", "Target (issue 13): at least 10x faster than the 10k-particle filter with a smaller "
                  f"gap: {verdict}.  The gap is {'smaller' if smaller else 'NOT smaller'} at every component "
                  "count.  Why the speed is missed: a yau-jia step makes about 1 800 Python function "
                  "calls (cProfile, 32 components), mostly numpy's wrappers around small (J, 4, 4) stacks "
                  "(two cubatures with derivatives, the exact flow at 8 Gauss nodes, the split check, the "
                  "merges), each a few microseconds of overhead, while the particle filter's step is a "
                  "few dozen calls vectorised over 10^4 particles; below 8 components the fixed part "
                  "(about 0.45 ms) dominates.  Closing it needs a fused (compiled) step, not fewer "
                  "components."]
    lines += ["", "2-D ring posterior (tests/solver/exact/test_yau_jia.py's model, "
              f"{2 if args.quick else 5} seeds x "
              f"{300 if args.quick else 1000} steps): max gap of the mean to the point-mass reference "
              "(worst seed, and mean over seeds) and cost, by the cap on components and the splits "
              "allowed per step:", "", "| components | splits per step | worst gap | mean gap | "
              "ms per observation |", "|---|---|---|---|---|"]
    lines += [f"| {cap} | {budget} | {worst:.4f} | {mean:.4f} | {ms:.3f} |"
              for cap, budget, worst, mean, ms in ring]
    out = RESULTS / "yau-jia.md"
    out.write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
