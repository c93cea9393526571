"""Irregular rows against regular rows on every bundled model the general engine runs and on a double well.

    python -m bench.irregular_cost [--quick]     # writes bench/results/irregular.md

Per model: cond(V) of the Galerkin generator's eigenbasis, the flow's form for irregular rows
(solver/engine/semigroup.py: modal where cond(V) ≤ MAX_CONDITION, else the Schur form's tables of
solver/engine/powers.py), and the µs per regular row and per irregular row (gaps 0.5–1.5 dt) measured
by solver/engine/rowcost.py (chunks of zero increments, CPU time, one BLAS thread, medians) — with the
form the engine picks, with the Schur form forced (its cost where the modal form would do), and with
the former fallback forced, expm(τA) per gap (fewer rows: O(N³) each).  Also the error of each form
against scipy.linalg.expm(τA) on random coefficient vectors, τ in [0.1 dt, 100 dt], and what a
block-diagonal form (Bavely–Stewart: real Schur form, then Sylvester equations whose solutions stay
under 1e3) would leave: the size of its largest block.
"""

from __future__ import annotations

import argparse
import contextlib
import os
from pathlib import Path

import numpy as np
import scipy.linalg as sla
from threadpoolctl import threadpool_limits
from yauyau.solver import compile_model, load_spec, spec_from_dict
from yauyau.solver.engine import powers, semigroup
from yauyau.solver.engine.rowcost import row_costs
from yauyau.solver.methods import make_filter
from yauyau.solver.offline.pipeline import precompute

from .fragments import write_fragment

ROOT = Path(__file__).resolve().parent.parent
FRAGMENT = ROOT / "bench" / "results" / "irregular.md"
# range_only_4d: yau-jia, 4-D (no general engine)
EXAMPLES = ["benes", "cubic_sensor", "ou", "power_meter", "random_walk_trend", "sin_drift_atlas",
            "yau_jia_1d", "range_2d", "constant_velocity"]


def double_well(basis: int, radius: float) -> dict:
    """dx = (x − x³) dt + dv, dy = x² dt + dw: its generator's eigenbasis is ill-conditioned on a wide
    ball."""
    return {"name": f"double-well-{basis}", "state": ["x"], "drift": ["x - x**3"],
            "observation": ["x**2"],
            "initial": {"kind": "gaussian", "mean": [0.5], "cov": [[1.0]]},
            "domain": {"radius": radius}, "discretization": {"dt": 0.01, "basis": basis}}


DOUBLE_WELLS = {"double well, R 3.5, basis 96": double_well(96, 3.5),
                "double well, R 3.5, basis 128": double_well(128, 3.5)}


@contextlib.contextmanager
def forced(form: str | None):
    """The flow's form forced by its thresholds (None: the engine's own choice)."""
    saved = semigroup.MAX_CONDITION, powers.MAX_TABLE_BYTES
    if form in ("schur", "expm"):
        semigroup.MAX_CONDITION = 0.0
    if form == "expm":
        powers.MAX_TABLE_BYTES = 0
    try:
        yield
    finally:
        semigroup.MAX_CONDITION, powers.MAX_TABLE_BYTES = saved


def largest_block(A: np.ndarray, bound: float = 1e3) -> int:
    """Bavely–Stewart block diagonalisation (real Schur form, then Sylvester equations T11 X − X T22 = −T12,
    the nearest eigenvalue moved into a block while ‖X‖∞ > bound): the size of the largest block."""
    from scipy.linalg.lapack import dtrexc, dtrsyl

    T, Y = (np.asfortranarray(m) for m in sla.schur(A, output="real"))
    N, i, largest = A.shape[0], 0, 0

    def size(p: int) -> int:
        return 2 if p + 1 < N and T[p + 1, p] != 0.0 else 1

    def starts(a: int, b: int) -> list[int]:
        out = []
        while a < b:
            out.append(a)
            a += size(a)
        return out

    while i < N:
        j = i + size(i)
        while j < N:
            X, scale, info = dtrsyl(T[i:j, i:j], T[j:, j:], -T[i:j, j:], isgn=-1)
            if info == 0 and np.abs(X / scale).sum(axis=1).max() <= bound:
                T[i:j, j:] = 0.0
                break
            mine = np.concatenate([np.linalg.eigvals(T[p:p + size(p), p:p + size(p)]) for p in starts(i, j)])
            best = min(starts(j, N), key=lambda p: np.min(np.abs(
                np.linalg.eigvals(T[p:p + size(p), p:p + size(p)])[:, None] - mine[None, :])))
            T, Y, _ = dtrexc(T, Y, best + 1, j + 1)
            j += size(j)
        largest = max(largest, j - i)
        i = j
    return largest


def accuracy(flow, dt: float, rng: np.random.Generator) -> float:
    """The largest relative error of the flow against scipy.linalg.expm(τA) on random vectors."""
    worst = 0.0
    drawn = np.exp(rng.uniform(np.log(0.1 * dt), np.log(100 * dt), 4))
    for tau in np.concatenate([[0.1 * dt, 100 * dt], drawn]):
        c = rng.standard_normal(flow.N)
        truth = sla.expm(tau * flow.generator) @ c
        worst = max(worst, float(np.linalg.norm(flow.apply(tau, c) - truth) / np.linalg.norm(truth)))
    return worst


def measure(title: str, model, rows: int, repeats: int) -> dict:
    offline = precompute(model)
    out: dict = {"Q": offline.basis.shape[0], "N": offline.basis.shape[1]}
    big = out["N"] > 400
    for form in (None, "schur", "expm"):
        if form == "schur" and big:
            continue  # the tables would not fit (the form falls back to expm)
        with forced(form):
            flt = make_filter(model, offline, "yau-yau")
            flow = flt.flow
            cost = row_costs(flt, rows=(5 if big else 30) if form == "expm" else rows,
                             repeats=1 if form == "expm" else repeats)
            key = "auto" if form is None else form
            out[key] = cost
            if form is None:
                out["condition"] = flow.condition
                out["error"] = accuracy(flow, model.dt, np.random.default_rng(0)) if not big else float("nan")
                out["block"] = largest_block(flow.generator) if not big else None
    print(title, out, flush=True)
    return out


def render(results: dict, load: float, rows: int) -> list[str]:
    lines = ["## Irregular rows against regular rows", "",
             "`python -m bench.irregular_cost`", "",
             f"µs per row of `run_arrays` (solver/engine/rowcost.py: chunks of {rows} rows of zero "
             "increments; "
             "irregular: gaps 0.5–1.5 dt), CPU time, one BLAS thread, medians, compiled loops; load average "
             f"{load:.1f} on {os.cpu_count()} cores at the start.  *form*: the flow the engine picks for "
             f"irregular rows (modal: cond(V) ≤ {semigroup.MAX_CONDITION:.0e} in double precision; schur: "
             "solver/engine/powers.py); *schur forced*: that "
             "form where the modal one would do; *expm*: the fallback before the Schur form, "
             "expm(τA) per gap (a few rows).  *error*: the flow against scipy.linalg.expm(τA) on random "
             "vectors, τ in [0.1 dt, 100 dt].  *block*: the largest block a Bavely–Stewart block "
             "diagonalisation (Sylvester solutions ≤ 1e3) leaves.", "",
             "| model | Q | N | cond(V) | block | form | error | regular µs | irregular µs "
             "| irregular / regular | schur forced µs (ratio) | expm µs (ratio) |",
             "|---|---:|---:|---:|---:|---|---:|---:|---:|---:|---:|---:|"]
    for title, r in results.items():
        auto = r["auto"]
        schur = r.get("schur")
        schur_text = (f"{schur.irregular_us:.1f} ({schur.irregular_us / auto.regular_us:.2f}×)" if schur
                      else "–")
        expm = r["expm"]
        block = "–" if r["block"] is None else str(r["block"])
        error = "–" if np.isnan(r["error"]) else f"{r['error']:.1e}"
        lines.append(f"| {title} | {r['Q']} | {r['N']} | {r['condition']:.1e} | {block} | {auto.flow} "
                     f"| {error} | {auto.regular_us:.1f} | {auto.irregular_us:.1f} | {auto.ratio:.2f}× "
                     f"| {schur_text} | {expm.irregular_us:.0f} "
                     f"({expm.irregular_us / auto.regular_us:.0f}×) |")
    return lines + [""]


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m bench.irregular_cost",
                                     description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="fewer rows and repeats, 1-D models only")
    args = parser.parse_args(argv)
    rows, repeats = (200, 3) if args.quick else (300, 5)
    load = os.getloadavg()[0]
    models = {name: compile_model(load_spec(ROOT / "examples" / f"{name}.toml")) for name in EXAMPLES
              if not (args.quick and name in ("range_2d", "constant_velocity"))}
    models.update({title: compile_model(spec_from_dict(doc)) for title, doc in DOUBLE_WELLS.items()})
    with threadpool_limits(1):
        results = {title: measure(title, model, rows, repeats) for title, model in models.items()}
    lines = render(results, load, rows)
    write_fragment(FRAGMENT, lines)
    print("\n".join(lines))


if __name__ == "__main__":
    main()
