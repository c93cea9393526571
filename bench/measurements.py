"""Real sensor streams: observations at irregular times and discrete readings, cost and accuracy.

    .venv/bin/python -m bench.measurements                  # full (about 1 minute, offline stages cached)
    .venv/bin/python -m bench.measurements --quick          # smoke test (< 30 s)
    .venv/bin/python -m bench.measurements --setup-peers    # once: bench/out/peers-venv with particles

1. Cost (issue "Real sensor streams", Performance): ``run_arrays`` per observation on chunks of
   1000 rows for examples/cubic_sensor.toml (1-D) and examples/range_2d.toml (2-D, N = 850, single
   precision): rows one dt apart (the stored propagator) against the same number of rows at
   irregular times (the spectral flow of solver/engine/semigroup.py; exponential gaps of mean dt, 5% of them
   10× longer), for continuous increments and for discrete readings (``measurement = {kind =
   "discrete"}`` added to the spec).  Zero rows (every timed step a full step, as in
   bench/engine_speed.py), the four configurations interleaved (at least 9 repeats, more within a
   time budget where a chunk is cheap), medians; ratios are medians of the ratios of consecutive
   runs.  One BLAS thread.  The one-off cost of building the flow (eigen-decomposition of the
   Galerkin generator, the two modal matrices) is timed apart, and the irregular path's own work
   (flow.scales, the per-step modal products) alone.  Each chunk also runs once on a simulated path,
   to say where the engine could not resolve it.
2. Accuracy at irregular times (1-D cubic sensor, continuous and discrete, 5 seeds × 500 steps): the
   gap |E[x] − E_ref[x]| to a fine-grid point-mass filter exact in time (tests/helpers/irregular_refs.py
   ``GridReference``: 1024 cells, e^{τL} per gap, increments over long gaps in the engine's pieces),
   for the example's discretization and one twice as fine.
3. Discrete readings against the `particles` library's bootstrap filter (N. Chopin, 10k particles) on
   the same data (mean gaps dt and 10 dt): speed ratio and the gap of each to the reference.
   particles pins numpy < 2, so it runs in its own venv (bench/out/peers-venv) as a subprocess
   (bench/peer_particles.py --serve: filters one seed per request, interleaved with the engine's
   runs); this process never imports it.  Without the venv that part is skipped and the fragment
   says so.

The offline stage is cached in bench/out/ (keyed by the spec and the solver's offline sources;
``--fresh`` recomputes it).  Writes bench/results/measurements.md.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import math
import os
import subprocess
import sys
import tempfile
import time
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from threadpoolctl import threadpool_limits
from yauyau.solver.engine.filter import YauYauFilter
from yauyau.solver.engine.pieces import PIECE
from yauyau.solver.model import Model, compile_model
from yauyau.solver.offline.pipeline import OfflineModel, precompute
from yauyau.solver.simulate import simulate
from yauyau.solver.spec import spec_from_dict

ROOT = Path(__file__).resolve().parent.parent
EXAMPLES = ROOT / "examples"
OUT = ROOT / "bench" / "out"
FRAGMENT = ROOT / "bench" / "results" / "measurements.md"
PEER_VENV = OUT / "peers-venv"
PEER_PYTHON = PEER_VENV / "bin" / "python"
PEER_SCRIPT = Path(__file__).resolve().parent / "peer_particles.py"
# the sources whose change invalidates a cached offline stage
OFFLINE_SOURCES = ("offline.py", "fem.py", "basis.py", "propagator.py", "semigroup.py", "model.py",
                   "expressions.py")
CHUNK = 1000
TARGET_RATIO = 1.5
LONG_FRACTION, LONG_FACTOR = 0.05, 10.0
PF_PARTICLES = 10_000
MAX_REPEATS = 201


@dataclass(frozen=True)
class Case:
    key: str
    title: str
    example: str


CASES = [Case("cubic", "1-D cubic sensor (f = −0.2x, h = x³)", "cubic_sensor.toml"),
         Case("range2d", "2-D damped rotation, h = x1³ (N = 850, single precision)", "range_2d.toml")]
KINDS = ("continuous", "discrete")


# -- models, offline stage, data ---------------------------------------------------------------
def spec_doc(example: str, kind: str = "continuous", discretization: dict | None = None) -> dict:
    """The example's spec as a dict; ``kind = "discrete"`` adds ``measurement = {kind = "discrete"}``."""
    doc = tomllib.loads((EXAMPLES / example).read_text())
    if kind != "continuous":
        doc["measurement"] = {"kind": kind}
    if discretization:
        doc["discretization"] = {**doc["discretization"], **discretization}
    return doc


def _cache_key(doc: dict) -> str:
    """The offline arrays depend on the problem and its discretisation, not on the measurement kind."""
    problem = {k: v for k, v in doc.items() if k != "measurement"}
    digest = hashlib.sha256(json.dumps(problem, sort_keys=True).encode())
    for name in OFFLINE_SOURCES:
        path = ROOT / "solver" / name
        if path.exists():
            digest.update(path.read_bytes())
    return digest.hexdigest()[:16]


def offline_stage(doc: dict, model: Model, fresh: bool = False) -> tuple[OfflineModel, float, bool]:
    """(offline arrays, seconds of the precompute, from the cache?) — precomputed once (one BLAS thread
    as everything here), then read from bench/out/."""
    path = OUT / f"offline-{doc['name']}-{_cache_key(doc)}.npz"
    if path.exists() and not fresh:
        with np.load(path) as data:
            arrays = {key: data[key] for key in data.files}
        seconds = float(arrays.pop("precompute_seconds", math.nan))
        return OfflineModel.from_arrays(model, arrays), seconds, True
    began = time.perf_counter()
    offline = precompute(model)
    seconds = time.perf_counter() - began
    OUT.mkdir(parents=True, exist_ok=True)
    with tempfile.NamedTemporaryFile(dir=OUT, suffix=".npz", delete=False) as tmp:
        np.savez(tmp, precompute_seconds=seconds, **offline.to_arrays())
    os.replace(tmp.name, path)  # atomic: other benches may read the cache meanwhile
    return offline, seconds, False


def irregular_times(steps: int, mean_gap: float, rng: np.random.Generator) -> np.ndarray:
    """Exponential gaps, 5% of them (at random) 10× longer, scaled so that the mean gap is ``mean_gap``."""
    n_long = int(round(LONG_FRACTION * steps))
    phi = n_long / steps
    gaps = rng.exponential(mean_gap / (1.0 - phi + phi * LONG_FACTOR), steps)
    gaps[rng.choice(steps, n_long, replace=False)] *= LONG_FACTOR
    return np.cumsum(np.maximum(gaps, 1e-6 * mean_gap))


def _engine(model: Model, offline, **kw) -> YauYauFilter:
    return YauYauFilter(model, offline, precision=model.spec.discretization.precision, **kw)


# -- 1. cost ----------------------------------------------------------------------------------------
def measure_cost(case: Case, repeats: int, tries: int, budget: float, fresh: bool) -> dict[str, Any]:
    """µs/observation of regular and irregular chunks, both kinds, interleaved; the flow's one-off cost."""
    models, data, filters, simulated = {}, {}, {}, {}
    pre = None
    for kind in KINDS:
        doc = spec_doc(case.example, kind)
        model = compile_model(spec_from_dict(doc))
        offline, seconds, cached = offline_stage(doc, model, fresh)
        pre = pre or (seconds, cached, offline.basis.shape)
        models[kind] = (model, offline)
        filters[kind] = _engine(model, offline)
        # The cost of a step does not depend on the data (bench/engine_speed.py): zero rows keep every
        # timed step a full step.  Simulated rows of the same length are run once, to say where the
        # engine could not resolve a real path (discrete readings with R = 1 are sharp).
        zeros = np.zeros((CHUNK, model.m))
        rng = np.random.default_rng(2)
        times = irregular_times(CHUNK, model.dt, rng)
        data[("regular", kind)] = (filters[kind], zeros, None)
        data[("irregular", kind)] = (filters[kind], zeros, times)
        simulated[("regular", kind)] = (simulate(model, CHUNK, np.random.default_rng(1)).rows, None)
        simulated[("irregular", kind)] = (simulate(model, CHUNK, rng, times=times).rows, times)
    # one-off (median over fresh filters): building the spectral flow (eigen-decomposition, modal
    # matrices), and the first irregular / regular chunk of a fresh filter
    model, offline = models["continuous"]
    zeros, times = data[("irregular", "continuous")][1:]
    build, first_irregular, first_regular = [], [], []
    for _ in range(tries):
        fresh_filter = _engine(model, offline)
        began = time.perf_counter()
        flow = fresh_filter.flow
        if not flow.exact:
            _ = (flow.B, flow.C)  # cached properties: built here
        build.append(time.perf_counter() - began)
        for sample, when in ((first_irregular, times), (first_regular, None)):
            flt = _engine(model, offline)
            state = flt.initial_state()
            began = time.perf_counter()
            flt.run_arrays(state, zeros, when)
            sample.append(time.perf_counter() - began)
    # warm-up (the flow of every filter, caches), then the interleaved repeats
    checks = {}
    for key, (flt, rows, times) in data.items():
        _, res = flt.run_arrays(flt.initial_state(), rows, times)
        assert not res.degenerate.any(), f"{key}: a timed step is degenerate"
        _, res = flt.run_arrays(flt.initial_state(), *simulated[key])
        first = int(np.argmax(res.degenerate)) + 1 if res.degenerate.any() else None
        checks[key] = (first, res.reason)
    starts = {key: flt.initial_state() for key, (flt, _, _) in data.items()}
    samples: dict = {key: [] for key in data}
    # at least ``repeats``, more where a chunk is cheap: about ``budget`` seconds of interleaved runs,
    # so that a burst of load from the other users of the machine hits few of them
    began = time.perf_counter()
    for flt, rows, times in data.values():
        flt.run_arrays(flt.initial_state(), rows, times)
    round_s = time.perf_counter() - began
    repeats = int(min(max(repeats, budget / max(round_s, 1e-9)), MAX_REPEATS))
    for _ in range(repeats):
        for key, (flt, rows, times) in data.items():
            began = time.perf_counter()
            flt.run_arrays(starts[key], rows, times)
            samples[key].append(1e6 * (time.perf_counter() - began) / CHUNK)
    us = {key: float(np.median(v)) for key, v in samples.items()}
    spread = {key: (float(np.min(v)), float(np.max(v))) for key, v in samples.items()}
    # ratios of runs made one after the other (same repeat), then their median: a load that drifts over
    # the seconds of the measurement cancels in each pair
    paired = {(key, base): float(np.median(np.array(samples[key]) / np.array(samples[base])))
              for key in samples for base in (("regular", "continuous"), ("regular", key[1]))}
    steady = us[("irregular", "continuous")] * CHUNK * 1e-6
    return {"case": case, "us": us, "spread": spread, "paired": paired, "checks": checks, "repeats": repeats,
            "precompute": pre, "build_s": float(np.median(build)), "tries": tries, "steady_s": steady,
            "first_s": float(np.median(first_irregular)), "first_regular_s": float(np.median(first_regular)),
            "exact_flow": flow.exact, "condition": flow.condition,
            "breakdown": _breakdown(filters["continuous"], data[("irregular", "continuous")][2])}


def _breakdown(flt: YauYauFilter, times: np.ndarray) -> dict[str, float]:
    """µs/observation of the irregular path's extra work: the modal factors e^{τΛ} of the chunk
    (flow.scales, before the loop) and, per step, the two in-place products that apply them (real
    modes, complex pairs: as in the engine's hot loop, replayed alone)."""
    flow = flt.flow
    if flow.exact:
        return {}
    taus = np.diff(times, prepend=0.0)
    K, out = len(taus), {}
    began = time.perf_counter()
    for _ in range(5):
        real, pairs = flow.scales(taus)
    out["scales"] = 1e6 * (time.perf_counter() - began) / (5 * K)
    buffer = np.zeros(flow.N + 1, dtype=flow.dtype)
    cdtype = np.complex64 if flow.dtype == np.float32 else np.complex128
    real_view = buffer[:flow.r]
    pair_view = buffer[flow.r:flow.N].view(cdtype) if pairs.shape[1] else None
    multiply, real_rows, pair_rows = np.multiply, list(real), list(pairs)
    began = time.perf_counter()
    for k in range(K):
        multiply(real_view, real_rows[k], out=real_view)
        if pair_view is not None:
            multiply(pair_view, pair_rows[k], out=pair_view)
    out["multiply"] = 1e6 * (time.perf_counter() - began) / K
    return out


# -- 2./3. accuracy and the particles peer ---------------------------------------------------------
def grid_reference(model: Model):
    """tests/helpers/irregular_refs.py's GridReference (1024 cells, exact in time over each gap)."""
    tests = str(ROOT / "tests")
    if tests not in sys.path:
        sys.path.insert(0, tests)
    from helpers.irregular_refs import GridReference

    return GridReference(model), "GridReference (tests/helpers/irregular_refs.py, 1024 cells)"


def _datasets(case: Case, kind: str, seeds: int, steps: int, mean_gap: float):
    doc = spec_doc(case.example, kind)
    model = compile_model(spec_from_dict(doc))
    out = []
    for seed in range(seeds):
        rng = np.random.default_rng(100 + seed)
        times = irregular_times(steps, mean_gap, rng)
        sim = simulate(model, steps, rng, times=times)
        out.append((seed, sim.rows, times))
    return doc, model, out


EXAMPLE_ENGINE = "Yau–Yau (example: N = 128, mesh 40)"
REFINED_ENGINE = "Yau–Yau (refined: N = 256, mesh 80)"


def measure_accuracy(case: Case, kind: str, seeds: int, steps: int, mean_gap: float, repeats: int,
                     fresh: bool, peer: bool) -> dict[str, Any]:
    """Gap of the engine (and, for discrete readings, of particles' bootstrap filter) to the grid; the
    filters' runs on each seed interleaved (``repeats`` times) for their cost."""
    doc, model, sets = _datasets(case, kind, seeds, steps, mean_gap)
    reference, ref_name = grid_reference(model)
    # increments over gaps longer than 2.25 dt: the engine's pieces of about 2 dt (engine/filter.py PIECE)
    piece = PIECE * float(model.dt) if kind == "continuous" else None
    runs = [reference.run(rows, times, kind, max_piece=piece) for _, rows, times in sets]
    refs = [r.mean for r in runs]
    ref_min_sd = float(min(np.sqrt(np.min(r.cov[:, 0, 0])) for r in runs))
    # the reference's own error: 2× finer grid on the first seed
    fine = type(reference)(model, cells=2 * reference.cells)
    ref_error = float(np.abs(fine.run(sets[0][1], sets[0][2], kind, max_piece=piece).mean - refs[0]).mean())
    refined = spec_doc(case.example, kind, {"basis": 256, "mesh": 80})
    engines = {}
    for name, edoc in ((EXAMPLE_ENGINE, doc), (REFINED_ENGINE, refined)):
        emodel = compile_model(spec_from_dict(edoc))
        flt = _engine(emodel, offline_stage(edoc, emodel, fresh)[0])
        flt.run_arrays(flt.initial_state(), sets[0][1], sets[0][2])  # warm-up: builds the flow
        engines[name] = flt
    pf, pf_note = None, None
    if kind == "discrete":
        pf, pf_note = ParticlesPeer.start(model, sets) if peer else (None, "not run: --no-peer")
    tally = {name: {"gaps": [], "good": [], "secs": [[] for _ in sets], "reason": None} for name in engines}
    pf_secs: list[list[float]] = [[] for _ in sets]
    try:
        for rep in range(repeats):
            for i, (_, rows, times) in enumerate(sets):
                for name, flt in engines.items():
                    began = time.perf_counter()
                    _, res = flt.run_arrays(flt.initial_state(), rows, times)
                    tally[name]["secs"][i].append(time.perf_counter() - began)
                    if rep == 0:
                        tally[name]["gaps"].append(np.abs(res.mean - refs[i]).max(axis=1))
                        tally[name]["good"].append(~res.degenerate)
                        tally[name]["reason"] = tally[name]["reason"] or res.reason
                if pf is not None:
                    pf_secs[i].append(pf.run(i))
    finally:
        result = pf.close() if pf is not None else None
    rows_out = {name: _row(t["gaps"], t["good"], t["secs"], t["reason"]) for name, t in tally.items()}
    if result is not None:
        gaps = [np.abs(result["means"][i][:, None] - ref).max(axis=1) for i, ref in enumerate(refs)]
        good = [np.ones(steps, dtype=bool) for _ in sets]
        rows_out[f"particles {result['version']}, bootstrap {PF_PARTICLES // 1000}k "
                 f"({result['transition']})"] = _row(gaps, good, pf_secs, None)
    elif pf_note is None and kind == "discrete":
        pf_note = "not run: the peer failed"
    return {"case": case, "kind": kind, "mean_gap": mean_gap, "seeds": seeds, "steps": steps,
            "repeats": repeats, "rows": rows_out, "reference": ref_name, "ref_error": ref_error,
            "pf_note": pf_note, "ref_min_sd": ref_min_sd,
            "spacing": {name: flt.node_spacing for name, flt in engines.items()}}


def _row(gaps, good, secs, reason) -> dict[str, Any]:
    """Gaps over all steps and over the good (non-degenerate) ones; µs per filtered observation (the
    engine stops at its first degenerate step): median over seeds of the median over repeats."""
    g, ok = np.concatenate(gaps), np.concatenate(good)
    us = [1e6 * float(np.median(t)) / max(int(k.sum()), 1) for t, k in zip(secs, good, strict=True)]
    return {"gap": float(g.mean()), "gap_good": float(g[ok].mean()) if ok.any() else math.nan,
            "gap_max": float(g.max()), "us": float(np.median(us)), "degenerate": 1.0 - ok.mean(),
            "seeds_degenerate": sum(int(not k.all()) for k in good), "reason": reason}


# -- the particles peer (its own venv, a subprocess) ------------------------------------------------
def _polynomial(expr, symbol) -> np.ndarray | None:
    import sympy as sp

    try:
        return np.array([float(c) for c in sp.Poly(expr, symbol).all_coeffs()])
    except (sp.PolynomialError, TypeError, ValueError):
        return None


class ParticlesPeer:
    """bench/peer_particles.py --serve under the peer venv's python: ``run(i)`` filters data set i there
    and returns its seconds, so that its runs interleave with the engine's; ``close()`` its results."""

    def __init__(self, process: subprocess.Popen, tmp: tempfile.TemporaryDirectory, out: Path, log):
        self.process, self.tmp, self.out, self.log = process, tmp, out, log

    @classmethod
    def start(cls, model: Model, sets,
              increments_dt: float | None = None) -> tuple[ParticlesPeer | None, str | None]:
        """The running peer, or None and why it cannot run.  ``increments_dt``: the rows are increments
        dy = h dt + dw over regular steps dt, read by the peer as z = dy/dt with noise variance R/dt."""
        if not PEER_PYTHON.exists():
            return None, (f"not run: no peer venv at {PEER_VENV.relative_to(ROOT)} "
                          "(create it with `python -m bench.measurements --setup-peers`)")
        prior = model.spec.initial
        x = model.symbols[0]
        drift, sensor = _polynomial(model.drift[0], x), _polynomial(model.observation[0], x)
        if model.n != 1 or drift is None or sensor is None or getattr(prior, "kind", None) != "gaussian":
            return None, "not run: the peer script takes 1-D polynomial models with a Gaussian prior"
        OUT.mkdir(parents=True, exist_ok=True)
        tmp = tempfile.TemporaryDirectory(dir=OUT)
        src, dst = Path(tmp.name) / "in.npz", Path(tmp.name) / "out.npz"
        scale = 1.0 if increments_dt is None else 1.0 / increments_dt
        np.savez(src, observations=np.array([rows[:, 0] * scale for _, rows, _ in sets]),
                 times=np.array([t for _, _, t in sets]), seeds=np.array([1000 + s for s, _, _ in sets]),
                 drift_poly=drift, obs_poly=sensor, diffusion=float(model.a[0, 0]),
                 noise_var=float(model.R[0, 0]) * scale, prior_mean=float(prior.mean[0]),
                 prior_var=float(prior.cov[0][0]), particles=PF_PARTICLES, substeps=4)
        env = {**os.environ, "OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "NUMBA_NUM_THREADS": "1"}
        log = open(Path(tmp.name) / "stderr.txt", "w+")  # closed by close()
        process = subprocess.Popen([str(PEER_PYTHON), str(PEER_SCRIPT), str(src), str(dst), "--serve"],
                                   stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=log, text=True,
                                   env=env)
        peer = cls(process, tmp, dst, log)
        if process.stdout.readline().strip() != "ready":
            peer.close()
            return None, f"not run: the peer failed to start ({peer.error()})"
        return peer, None

    def run(self, i: int) -> float:
        self.process.stdin.write(f"{i}\n")
        self.process.stdin.flush()
        answer = self.process.stdout.readline()
        if not answer:
            raise RuntimeError(f"the particles peer stopped: {self.error()}")
        return float(answer)

    def error(self) -> str:
        self.log.seek(0)
        lines = self.log.read().strip().splitlines()
        return lines[-1] if lines else f"exit status {self.process.poll()}"

    def close(self) -> dict[str, Any] | None:
        """Its results (None if it failed); ends the process and removes its files."""
        try:
            if self.process.stdin and not self.process.stdin.closed:
                self.process.stdin.close()
            self.process.wait(timeout=600)
            if self.process.returncode != 0 or not self.out.exists():
                return None
            with np.load(self.out) as out:
                return {k: (out[k].item() if out[k].ndim == 0 else out[k]) for k in out.files}
        finally:
            if self.process.poll() is None:
                self.process.kill()
            self.log.close()
            self.tmp.cleanup()


def setup_peers() -> int:
    """Create bench/out/peers-venv and install the peers, particles and FilterPy (particles pulls numba
    and scikit-learn: minutes, once).  bench/yau_jia.py uses the same venv."""
    OUT.mkdir(parents=True, exist_ok=True)
    subprocess.run(["python3", "-m", "venv", str(PEER_VENV)], check=True)
    subprocess.run([str(PEER_PYTHON), "-m", "pip", "install", "--quiet", "particles", "filterpy"], check=True)
    print(f"peer venv ready: {PEER_PYTHON}")
    return 0


# -- report -------------------------------------------------------------------------------------------
def _fmt(value: float, digits: int = 3) -> str:
    return "—" if value is None or not math.isfinite(value) else f"{value:.{digits}g}"


def _check(label: str, value: float, limit: float, smaller: bool = True) -> str:
    if value is None or not math.isfinite(value):
        return f"- {label}: not measured"
    met = value <= limit if smaller else value >= limit
    factor = limit / value if smaller else value / limit
    return (f"- {label}: {_fmt(value)} vs target {'≤' if smaller else '≥'} {_fmt(limit)} — "
            f"{'**met**' if met else '**missed**'} ({factor:.3g}× {'margin' if met else 'short'})")


def targets(costs: list[dict], accuracy: list[dict]) -> list[str]:
    out = []
    for res in costs:
        base = ("regular", "continuous")
        for kind in KINDS:
            out.append(_check(f"{res['case'].title}: irregular {kind} / regular continuous, µs/obs",
                              res["paired"][(("irregular", kind), base)], TARGET_RATIO))
    for acc in accuracy:
        where = f"1-D cubic sensor, {acc['kind']} rows at irregular times (mean gap {acc['mean_gap']:g})"
        pf = next((r for name, r in acc["rows"].items() if name.startswith("particles")), None)
        for name in (EXAMPLE_ENGINE, REFINED_ENGINE):
            engine = acc["rows"][name]
            label = f"{where}, {name}"
            out.append(_check(f"{label}: mean gap to the fine grid", engine["gap"], 0.01))
            if acc["kind"] != "discrete":
                continue
            if pf is None:
                out.append(f"- {label}: against particles 10k — {acc['pf_note']}")
                continue
            out.append(_check(f"{label}: speed-up over particles 10k", pf["us"] / engine["us"], 100.0, False))
            out.append(_check(f"{label}: gap of particles 10k / gap of the engine", pf["gap"] / engine["gap"],
                              1.0, False))
    return out


def cost_table(res: dict) -> list[str]:
    pre_s, cached, shape = res["precompute"]
    us = res["us"]
    origin = " (read from bench/out/)" if cached else ""
    lines = [f"**{res['case'].title}** (`examples/{res['case'].example}`, Q = {shape[0]} nodes, "
             f"N = {shape[1]}; offline stage {_fmt(pre_s)} s{origin}; chunks of {CHUNK} rows, median of "
             f"{res['repeats']} interleaved repeats; the ratios are medians over the repeats of the ratio "
             "of runs made one after the other)", "",
             "| rows | kind | µs / obs (median) | min – max | / regular, same kind | / regular continuous "
             "| simulated path: first degenerate step |", "|---|---|---:|---:|---:|---:|---|"]
    base = ("regular", "continuous")
    reasons = []
    for (when, kind), value in us.items():
        lo, hi = res["spread"][(when, kind)]
        first, reason = res["checks"][(when, kind)]
        label = f"every dt = {_model_dt(res)}" if when == "regular" else "irregular (mean gap dt)"
        if reason and reason not in reasons:
            reasons.append(reason)
        flag = "none" if first is None else f"{first} of {CHUNK} ({'†' * (reasons.index(reason) + 1)})"
        lines.append(f"| {label} | {kind} | {value:.1f} | {lo:.1f} – {hi:.1f} | "
                     f"{res['paired'][((when, kind), ('regular', kind))]:.2f} | "
                     f"{res['paired'][((when, kind), base)]:.2f} | {flag} |")
    if reasons:
        lines += [""] + [f"{'†' * (i + 1)} {reason}." for i, reason in enumerate(reasons)]
    flow = ("expm per distinct gap (ill-conditioned eigenvectors)" if res["exact_flow"]
            else f"eigen-decomposition, cond(V) = {res['condition']:.3g}")
    worth = res["build_s"] / res["steady_s"] * CHUNK
    extra = res["breakdown"].get("scales")
    lines += ["", f"One-off, irregular times (median of {res['tries']} fresh filter(s)): building the "
              f"spectral flow ({flow}) {1e3 * res['build_s']:.1f} ms (≈ {worth:.0f} irregular observations' "
              f"worth); the first irregular chunk of a fresh filter {1e3 * res['first_s']:.1f} ms, the first "
              f"regular chunk of a fresh filter {1e3 * res['first_regular_s']:.1f} ms, the next irregular "
              f"chunks {1e3 * res['steady_s']:.1f} ms."
              + (f" The irregular path's own work, timed alone: the modal factors e^{{τΛ}} of the chunk "
                 f"(flow.scales) {extra:.2f} µs/obs, applying them in the loop (two in-place products "
                 f"per step) {res['breakdown']['multiply']:.2f} µs/obs." if extra is not None else ""), ""]
    return lines


def _model_dt(res: dict) -> str:
    return f"{spec_doc(res['case'].example)['discretization']['dt']:g}"


def accuracy_table(acc: dict) -> list[str]:
    lines = [f"**{acc['case'].title}, {acc['kind']} rows, irregular times with mean gap "
             f"{acc['mean_gap']:g}** ({acc['seeds']} seeds × {acc['steps']} steps, the filters' runs "
             f"interleaved per seed, {acc['repeats']} repeat(s); reference: {acc['reference']}, its own "
             f"error against a 2× finer grid {_fmt(acc['ref_error'])} on seed 0)", "",
             "| filter | mean gap to ref | on good steps | max gap | µs / obs | time / engine "
             "| degenerate steps (seeds) |", "|---|---:|---:|---:|---:|---:|---|"]
    engine = acc["rows"][EXAMPLE_ENGINE]["us"]
    reasons = []
    for name, r in acc["rows"].items():
        flag = f"{r['degenerate']:.1%} ({r['seeds_degenerate']})"
        if r["reason"]:
            if r["reason"] not in reasons:
                reasons.append(r["reason"])
            flag += " " + "†" * (reasons.index(r["reason"]) + 1)
        lines.append(f"| {name} | {_fmt(r['gap'])} | {_fmt(r['gap_good'])} | {_fmt(r['gap_max'])} | "
                     f"{_fmt(r['us'])} | {_fmt(r['us'] / engine)}× | {flag} |")
    if reasons:
        lines += [""] + [f"{'†' * (i + 1)} {reason}." for i, reason in enumerate(reasons)]
    spacing = ", ".join(f"{name.split('(')[1].split(':')[0]} {_fmt(h)}" for name, h in acc["spacing"].items())
    lines += ["", f"Node spacing of the engines: {spacing}; the reference's smallest posterior standard "
              f"deviation: {_fmt(acc['ref_min_sd'])}."]
    if acc["pf_note"]:
        lines += ["", f"particles 10k: {acc['pf_note']}."]
    return lines + [""]


def reading(costs: list[dict], accuracy: list[dict]) -> list[str]:
    """What the figures say (the parts that do not change from run to run, with this run's numbers)."""
    out = ["### Reading the figures", ""]
    for res in costs:
        if "multiply" not in res["breakdown"]:
            continue
        us, b = res["us"], res["breakdown"]
        base = us[("regular", "continuous")]
        extra = (res["paired"][(("irregular", "continuous"), ("regular", "continuous"))] - 1.0) * base
        parts = b["scales"] + b["multiply"]
        rest = ""
        if extra > 1.3 * parts:
            rest = "; more than the two parts: the rest is the modal branch of the loop, per step in Python"
        elif extra < 0.7 * parts:
            rest = "; less than the two parts: within the noise of this machine"
        out.append(" ".join([
            f"- {res['case'].title}: an irregular step does the same two BLAS products as a regular",
            "one (the modal matrices Φ V and V⁻¹ Φᵀ W have the shapes of the stored propagator and",
            f"projector); its own work is e^{{τΛ}} for the chunk ({b['scales']:.2f} µs/obs) and two small",
            f"in-place products per step ({b['multiply']:.2f} µs/obs); the measured excess is",
            f"{extra:.1f} µs/obs (paired ratio − 1, times the regular cost{rest}). The one-off",
            "eigen-decomposition is paid once per filter object."]))
    discrete = [a for a in accuracy if a["kind"] == "discrete"]
    if discrete:
        worst = max(a["rows"][EXAMPLE_ENGINE]["degenerate"] for a in discrete)
        refined_ok = all(a["rows"][REFINED_ENGINE]["degenerate"] == 0 for a in discrete)
        if worst > 0:
            out.append(" ".join([
                "- Discrete readings z = x³ + v with R = 1 make the posterior far narrower than continuous",
                "increments over the same gaps do (the reference's standard deviation drops to",
                f"{_fmt(min(a['ref_min_sd'] for a in discrete))}, against a node spacing of",
                f"{_fmt(discrete[0]['spacing'][EXAMPLE_ENGINE])} in the example's discretization). Where it",
                "cannot resolve the posterior the engine flags the step degenerate (it does not return a",
                f"wrong estimate silently) and stops: up to {worst:.0%} of the steps here; the mean gap over",
                "all steps counts them with the last good estimate, the gap on good steps does not.",
                ("A basis and mesh twice as fine resolve every step, at 2–3× the cost." if refined_ok else
                 "Even a basis and mesh twice as fine leave degenerate steps."),
                *[f"The {res['case'].title.split(' ')[0]} example's simulated discrete paths degenerate too "
                  "(cost tables)." for res in costs[1:]
                  if any(res["checks"][(when, "discrete")][0] for when in ("regular", "irregular"))]]))
        out.append(" ".join([
            "- particles' bootstrap filter draws one Gaussian per particle per gap (the transition is",
            "exact here), so it is leaner than the bench's own particle filter of bench/results/filters.md",
            "(two Euler–Maruyama substeps per dt): the speed-up target of the continuous form (≥ 100× over",
            "a 10k-particle filter), applied here to particles, is a harder bar."]))
    return out + [""]


def write_markdown(costs, accuracy, command: str, wall: float, load: float) -> Path:
    parts = ["## Real sensor streams: irregular times and discrete readings", "",
             f"Command: `{command}` (wall time {wall:.0f} s; load average {load:.1f} on {os.cpu_count()} "
             "cores at the start: the machine is shared with other developers, so single figures are "
             "noisy — the configurations are interleaved and the ratios are what to read). One BLAS "
             "thread. Rows at irregular times: exponential gaps of mean dt, 5% of them 10× longer (mean "
             "kept at dt); discrete readings: the example with `measurement = {kind = \"discrete\"}` "
             "(z = h(x) + v, R as in the example: 1). Regular rows use the stored propagator over dt, "
             "irregular rows the spectral flow e^{τA} (engine/semigroup.py). Cost: µs per observation of "
             f"`run_arrays` on chunks of {CHUNK} zero rows (as in bench/engine_speed.py: the cost of a step "
             "does not depend on the data, and every timed step is a full step); the same chunk is also run "
             "once on a simulated path, and the table says where the engine flagged a step it could not "
             "resolve there.", "", "### Targets", "",
             "The cost ratios are the issue's targets; the accuracy and particles lines apply the targets "
             "of the continuous form (bench/results/filters.md: mean gap ≤ 0.01, ≥ 100× faster than a "
             "10k-particle filter, a smaller gap than it) to these runs.", ""]
    parts += targets(costs, accuracy)
    parts += ["", "### Cost per observation: regular vs irregular times", ""]
    for res in costs:
        parts += cost_table(res)
    parts += ["### Accuracy at irregular times, and the discrete form against particles", "",
              "Gap: |E[x] − E_ref[x]| averaged over steps and seeds (max: its maximum; degenerate steps "
              "count with the last good estimate the engine repeats; *on good steps*: without them). "
              "µs / obs: per filtered observation (the engine stops at its first degenerate step), median "
              "over seeds of the median over repeats; the engine's is `run_arrays` over the whole path, "
              "particles' the wall time of `SMC.run`. The refined engine is the example with "
              "`discretization = {basis = 256, mesh = 80}` (basis and mesh twice as fine). particles runs "
              "in its own venv (bench/peer_particles.py: a custom StateSpaceModel, the exact "
              "Ornstein–Uhlenbeck transition over each gap since the drift is linear, M0 = the prior moved "
              "over the first gap, default systematic resampling at ESS < N/2), in a process that filters "
              "each seed on request, so that its runs interleave with the engine's.", ""]
    for acc in accuracy:
        parts += accuracy_table(acc)
    parts += reading(costs, accuracy)
    FRAGMENT.write_text("\n".join(parts).rstrip() + "\n")
    return FRAGMENT


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.measurements", description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="3 repeats, 2 seeds x 200 steps")
    parser.add_argument("--fresh", action="store_true", help="recompute the cached offline stages")
    parser.add_argument("--no-peer", action="store_true", help="skip the particles peer")
    parser.add_argument("--setup-peers", action="store_true", help="create bench/out/peers-venv and exit")
    args = parser.parse_args(argv)
    if args.setup_peers:
        return setup_peers()
    repeats, tries, seeds, steps, budget = (3, 1, 2, 200, 1.0) if args.quick else (9, 3, 5, 500, 15.0)
    load = os.getloadavg()[0]
    started = time.perf_counter()
    costs, accuracy = [], []
    with threadpool_limits(1):
        for case in CASES:
            t0 = time.perf_counter()
            costs.append(measure_cost(case, repeats, tries, budget, args.fresh))
            print("\n".join(cost_table(costs[-1])) + f"({time.perf_counter() - t0:.0f} s)\n", flush=True)
        cubic = CASES[0]
        dt = float(spec_doc(cubic.example)["discretization"]["dt"])
        gaps = [("continuous", dt), ("discrete", dt)] + ([] if args.quick else [("discrete", 10 * dt)])
        for kind, mean_gap in gaps:
            t0 = time.perf_counter()
            accuracy.append(measure_accuracy(cubic, kind, seeds, steps, mean_gap, tries, args.fresh,
                                             not args.no_peer))
            print("\n".join(accuracy_table(accuracy[-1])) + f"({time.perf_counter() - t0:.0f} s)\n",
                  flush=True)
    command = ".venv/bin/python -m bench.measurements" + (" --quick" if args.quick else "")
    out = write_markdown(costs, accuracy, command, time.perf_counter() - started, load)
    print("\n".join(targets(costs, accuracy)))
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
