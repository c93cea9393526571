"""Maximum likelihood of one drift parameter beside `particles`' PMMH (issue 39's benchmark).

    .venv/bin/python -m bench.fit [--quick]     # writes bench/results/fit.md

The model: examples/cubic_sensor.toml with its drift rate free, dx = −θ x dt + dv, dy = x³ dt + dw,
θ = 0.2; 1 000 rows (dt = 0.01) simulated by ``yauyau.simulate`` (seed 3).  ``yauyau.fit`` maximises
the record's log-likelihood over θ ∈ [0.02, 2] from the spec's value (θ enters the drift: every
evaluation recomputes the offline stage).  The peer, in its own venv (bench/out/peers-venv) as a
subprocess (bench/peer_pmmh.py), runs particles' PMMH on the same rows read as discrete readings
z = dy/dt with noise variance R/dt, the exact OU transition, a bootstrap filter of N particles inside,
a flat prior on the same box and the same start, for a few independent chains.  CPU time:
``time.process_time`` here, the children's ``os.times`` and each chain's ``process_time`` there; one
BLAS thread.
"""

from __future__ import annotations

import argparse
import os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import subprocess  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
import tomllib  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
from yauyau.solver import spec_from_dict  # noqa: E402

import yauyau  # noqa: E402

from .fragments import RESULTS, ROOT, write_fragment  # noqa: E402

PEER_PYTHON = ROOT / "bench" / "out" / "peers-venv" / "bin" / "python"
PEER_SCRIPT = ROOT / "bench" / "peer_pmmh.py"
THETA, LO, HI, ROWS, SEED, TARGET = 0.2, 0.02, 2.0, 1_000, 3, 30.0


def cubic_spec():
    doc = tomllib.loads((ROOT / "examples" / "cubic_sensor.toml").read_text())
    doc["parameters"], doc["drift"] = {"theta": THETA}, ["-theta*x"]
    return spec_from_dict(doc)


def pmmh(rows: np.ndarray, dt: float, spec, particles: int, niter: int, chains: int) -> dict | str:
    if not PEER_PYTHON.exists():
        return "not run: no bench/out/peers-venv (python -m bench.measurements --setup-peers)"
    prior = spec.initial
    with tempfile.TemporaryDirectory() as tmp:
        src, dst = Path(tmp) / "in.npz", Path(tmp) / "out.npz"
        np.savez(src, z=rows[:, 0] / dt, dt=dt, a=float(spec.diffusion_matrix()[0, 0]),
                 noise_var=float(spec.noise_matrix()[0, 0]) / dt, prior_mean=float(prior.mean[0]),
                 prior_var=float(prior.cov[0][0]), obs_poly=[1.0, 0.0, 0.0, 0.0], lo=LO, hi=HI, theta0=THETA,
                 rw_var=(0.1 * (HI - LO)) ** 2, particles=particles, niter=niter,
                 seeds=np.arange(1, chains + 1))
        before = os.times()
        done = subprocess.run([str(PEER_PYTHON), str(PEER_SCRIPT), str(src), str(dst)], capture_output=True,
                              text=True)
        after = os.times()
        if done.returncode != 0:
            return "failed: " + done.stderr.strip().splitlines()[-1]
        out = {k: v.item() if v.ndim == 0 else v for k, v in np.load(dst).items()}
    out["child_seconds"] = (after.children_user - before.children_user
                            + after.children_system - before.children_system)
    return out


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m bench.fit", description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true")
    args = parser.parse_args(argv)
    particles, niter, chains = (100, 60, 2) if args.quick else (200, 500, 3)
    burn = niter // 5
    wall, load = time.time(), os.getloadavg()
    spec = cubic_spec()
    dt = spec.discretization.dt
    rows = np.asarray(yauyau.simulate(spec, ROWS, seed=SEED).rows, dtype=float)
    began, before = time.process_time(), os.times()
    found = yauyau.fit(spec, rows, free={"theta": (LO, HI)})
    after = os.times()  # this process and any children it waited for
    cpu = time.process_time() - began + (after.children_user - before.children_user
                                         + after.children_system - before.children_system)
    est, se = found.estimates["theta"], found.stderr["theta"]
    met = "met" if cpu < TARGET and found.converged else "missed"
    peer = pmmh(rows, dt, spec, particles, niter, chains)
    if isinstance(peer, dict):
        kept = peer["chains"][:, burn:]
        means, sds = kept.mean(axis=1), kept.std(axis=1, ddof=1)
        pooled = kept.ravel()
        chain_rows = [f"| chain {c + 1} | {niter:,} | {peer['seconds'][c]:.0f} | {means[c]:.3f} | "
                      f"{sds[c]:.3f} | {peer['acceptance'][c]:.2f} |" for c in range(len(means))]
        peer_lines = [
            f"particles {peer['version']} PMMH on the same rows (z = dy/dt, noise variance R/dt = "
            f"{1 / dt:.0f}, the exact OU transition), a bootstrap filter of N = {particles} inside (one "
            f"filter: {peer['filter_seconds']:.2f} s CPU; its log-likelihood's spread at θ = {THETA}: "
            f"{peer['loglik_sd']:.2f}), flat prior on [{LO}, {HI}], start θ = {THETA}, particles' adaptive "
            f"random walk; {chains} independent chains of {niter} iterations, the first {burn} dropped. "
            f"N and the iterations are chosen to keep the peer under ~10 min of CPU on this loaded machine.",
            "",
            "| PMMH | iterations | CPU s | posterior mean θ | posterior sd | acceptance |",
            "|---|---:|---:|---:|---:|---:|", *chain_rows,
            f"| all chains | {chains * niter:,} | {peer['seconds'].sum():.0f} "
            f"(process {peer['child_seconds']:.0f}) "
            f"| {pooled.mean():.3f} | {pooled.std(ddof=1):.3f} | — |", "",
            f"Spread of PMMH's estimate (the posterior mean) over the {chains} chains: sd "
            f"{means.std(ddof=1):.3f}, range {means.min():.3f}–{means.max():.3f}; its posterior sd "
            f"{pooled.std(ddof=1):.3f} against yauyau's standard error {se:.3f}. PMMH took "
            f"{peer['seconds'].sum() / cpu:.0f}× yauyau's CPU time over its {chains} chains "
            f"({peer['seconds'].mean() / cpu:.0f}× a chain)."]
    else:
        peer_lines = [f"PMMH: {peer}"]
    lines = [
        "## Fitting a drift parameter", "",
        f"Generated by `python -m bench.fit{' --quick' if args.quick else ''}` (bench/fit.py, peer "
        f"bench/peer_pmmh.py): CPU time, one BLAS thread; 2 shared cores, load average "
        f"{load[0]:.1f} / {load[1]:.1f} / {load[2]:.1f} (1, 5, 15 min) at the start; "
        f"{time.time() - wall:.0f} s wall.", "",
        f"examples/cubic_sensor.toml with its drift rate free (dx = −θ x dt + dv, dy = x³ dt + dw, "
        f"θ = {THETA}), {ROWS:,} rows (dt = {dt}) simulated by `yauyau.simulate` (seed {SEED}); "
        f"`yauyau.fit(spec, rows, free={{\"theta\": ({LO}, {HI})}})` from the spec's value (θ enters the "
        "drift: each evaluation recomputes the offline stage).", "",
        "| fit | method | θ̂ | standard error | log-likelihood | evaluations | converged | CPU s | wall s |",
        "|---|---|---:|---:|---:|---:|---|---:|---:|",
        f"| yauyau.fit | {found.method} | {est:.3f} | {se:.3f} | {found.loglik:.2f} | {found.evaluations} | "
        f"{found.converged} | {cpu:.1f} | {found.seconds:.1f} |", "",
        "(A fresh process; numba's on-disk cache of the compiled kernels is warm, as after any first run.)",
        "",
        f"Target (issue 39): under {TARGET:.0f} s — **{met}** ({cpu:.1f} s CPU).", "", *peer_lines, ""]
    print("\n".join(lines))
    print(f"wrote {write_fragment(RESULTS / 'fit.md', lines)}")


if __name__ == "__main__":
    main()
