"""Start-up: what a user waits for before the first estimate, side by side in one run.

    python -m bench.startup [--quick] [--baseline REV]     # writes bench/results/startup.md

* the floor: ``python -c "import numpy, scipy.sparse.linalg, h5py, numba"`` (what any filter needs:
  the hot path is numba's compiled loops, solver/engine/compiled.py), and the same without numba;
* ``yauyau filter`` on a 1-row input of the 1-D cubic sensor (stored model, method chosen at
  precompute), from process start to exit: as it chooses (the numpy kernel for so short an input),
  with the compiled kernel forced and the cache that precompute warmed, and forced with a cold cache
  (a fresh ``YAUYAU_CACHE_DIR`` each run: what the first run on a machine where nothing warmed it pays);
* the kernel's break-even for a one-shot `filter` (solver/jit.py ``COMPILED_MIN_ROWS``): CPU
  seconds of `filter` on 1, 20 000 and 100 000 rows with each kernel forced;
* ``yauyau serve`` from process start to ``/readyz`` answering 200, with 1 and with 9 stored models;
* the same commands of an earlier git revision (``--baseline REV``, default ``ea33e0d``: v0.1, the
  last revision before the package became ``yauyau``; its own store, its file format), which analysed
  the model on every `filter` and every model at `serve`; ``--baseline none`` skips it.

Medians of the repeats, the commands interleaved, one BLAS thread (OPENBLAS_NUM_THREADS=1).
"""

from __future__ import annotations

import argparse
import os
import socket
import subprocess
import sys
import tempfile
import time
import tomllib
import urllib.request
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
FRAGMENT = ROOT / "bench" / "results" / "startup.md"
SPEC = ROOT / "examples" / "cubic_sensor.toml"


def _env(tree: Path, cache: Path | None = None) -> dict[str, str]:
    env = dict(os.environ, PYTHONPATH=str(tree), OPENBLAS_NUM_THREADS="1")
    if cache is not None:  # numba's on-disk cache, warmed by `yauyau precompute` (solver/warm.py)
        env["YAUYAU_CACHE_DIR"] = str(cache)
    return env


def _timed(cmd: list[str], env: dict[str, str], cwd: Path = ROOT) -> float:
    began = time.perf_counter()
    subprocess.run(cmd, env=env, cwd=cwd, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return time.perf_counter() - began


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def _serve_ready(cli: list[str], store: Path, env: dict[str, str], cwd: Path = ROOT) -> float:
    port = _free_port()
    began = time.perf_counter()
    proc = subprocess.Popen([*cli, "serve", "--store", str(store), "--port", str(port), "--log-level",
                             "warning", "--session-db", str(store / "s.sqlite3")], env=env, cwd=cwd,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    try:
        while time.perf_counter() - began < 600:
            if proc.poll() is not None:
                raise RuntimeError(f"serve exited with {proc.returncode}")
            try:
                with urllib.request.urlopen(f"http://127.0.0.1:{port}/readyz", timeout=1) as reply:
                    if reply.status == 200:
                        return time.perf_counter() - began
            except OSError:
                time.sleep(0.02)
        raise RuntimeError("serve never became ready")
    finally:
        os.killpg(proc.pid, 15)
        proc.wait(30)


def _specs(directory: Path, count: int) -> list[Path]:
    """``count`` distinct small 1-D models (the cubic sensor with other basis sizes), method auto."""
    doc = tomllib.loads(SPEC.read_text())
    paths = []
    for i in range(count):
        text = SPEC.read_text().replace(f"basis = {doc['discretization']['basis']}", f"basis = {40 + i}")
        text = text.replace(f'name = "{doc["name"]}"', f'name = "cubic-{i}"')
        path = directory / f"cubic-{i}.toml"
        path.write_text(text)
        paths.append(path)
    return paths


class Tree:
    """A revision's command line: its import name and a store precomputed by it."""

    def __init__(self, label: str, tree: Path, module: str, work: Path, models: int):
        # run from the tree itself: `python -m` puts the working directory first on sys.path
        self.label, self.tree, self.env = label, tree, _env(tree, work / f"{label}-cache")
        self.work = work
        self.cli = [sys.executable, "-m", module]
        self.one, self.many = work / f"{label}-one", work / f"{label}-many"
        specs = _specs(work, models)
        self.model_id = self._precompute(self.one, SPEC)
        for spec in specs:
            self._precompute(self.many, spec)
        self.input = work / "one-row.csv"
        self.input.write_text("0.01\n")

    def _precompute(self, store: Path, spec: Path) -> str:
        out = subprocess.run([*self.cli, "precompute", str(spec), "--store", str(store), "--quiet"],
                             env=self.env, cwd=self.tree, check=True, capture_output=True, text=True)
        return out.stdout.strip().splitlines()[-1]

    def filter_seconds(self, env: dict[str, str] | None = None) -> float:
        out = str(self.input.with_suffix(".out.csv"))
        return _timed([*self.cli, "filter", self.model_id, "--store", str(self.one), "--increments",
                       str(self.input), "--out", out], self.env if env is None else env, self.tree)

    def cold_seconds(self) -> float:
        """`filter` compiled with an empty numba cache: the first run on a machine where nothing warmed it."""
        cache = Path(tempfile.mkdtemp(prefix="cold-", dir=self.work))
        return self.filter_seconds(dict(self.env, YAUYAU_CACHE_DIR=str(cache), YAUYAU_KERNEL="compiled"))

    def compiled_seconds(self) -> float:
        return self.filter_seconds(dict(self.env, YAUYAU_KERNEL="compiled"))

    def cpu_seconds(self, rows: int, kernel: str) -> float:
        """User + system CPU of `filter` on ``rows`` rows with ``kernel`` forced."""
        path = self.work / f"rows-{rows}.csv"
        if not path.exists():
            np.savetxt(path, np.random.default_rng(0).normal(0.0, 0.1, (rows, 1)), fmt="%.6g")
        before = os.times()
        subprocess.run([*self.cli, "filter", self.model_id, "--store", str(self.one), "--increments",
                        str(path), "--out", str(path.with_suffix(".out.csv"))],
                       env=dict(self.env, YAUYAU_KERNEL=kernel), cwd=self.tree, check=True,
                       stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        after = os.times()
        return (after.children_user - before.children_user) + (after.children_system - before.children_system)


BASELINE = "ea33e0d"
BREAK_EVEN_ROWS = (1, 20_000, 100_000)
FLOORS = ("numpy, scipy.sparse.linalg, h5py, numba", "numpy, scipy.sparse.linalg, h5py")


def _known_revision(rev: str) -> bool:
    return subprocess.run(["git", "-C", str(ROOT), "cat-file", "-e", f"{rev}^{{commit}}"],
                          capture_output=True).returncode == 0


def _baseline_tree(rev: str, into: Path) -> tuple[Path, str]:
    archive = subprocess.run(["git", "-C", str(ROOT), "archive", rev], check=True, capture_output=True).stdout
    into.mkdir(parents=True)
    subprocess.run(["tar", "-x", "-C", str(into)], input=archive, check=True)
    module = "yauyau.service.cli" if (into / "yauyau").is_dir() else "service.cli"
    return into, module


def measure(repeats: int, models: int, baseline: str | None) -> dict[str, dict[str, float]]:
    work = Path(tempfile.mkdtemp(prefix="yauyau-startup-"))
    trees = [Tree("this revision", ROOT, "yauyau.service.cli", work, models)]
    if baseline:
        tree, module = _baseline_tree(baseline, work / "baseline")
        trees.append(Tree(f"revision {baseline}", tree, module, work, models))
    floors = {name: [sys.executable, "-c", f"import {name}"] for name in FLOORS}
    samples: dict[str, dict[str, list[float]]] = {t.label: {} for t in trees}
    floor: dict[str, list[float]] = {name: [] for name in floors}
    even: dict[tuple[int, str], list[float]] = {}
    for _ in range(repeats):  # interleaved: the machine's noise hits every command alike
        for name, cmd in floors.items():
            floor[name].append(_timed(cmd, _env(ROOT)))
        for t in trees:
            runs = samples[t.label]
            runs.setdefault("filter, 1 row", []).append(t.filter_seconds())
            if t.tree == ROOT:
                runs.setdefault("filter, 1 row, YAUYAU_KERNEL=compiled", []).append(t.compiled_seconds())
                runs.setdefault("filter, 1 row, compiled, cold numba cache", []).append(t.cold_seconds())
                for rows in BREAK_EVEN_ROWS:
                    for kernel in ("numpy", "compiled"):
                        even.setdefault((rows, kernel), []).append(t.cpu_seconds(rows, kernel))
            runs.setdefault("serve ready, 1 model", []).append(_serve_ready(t.cli, t.one, t.env, t.tree))
            runs.setdefault(f"serve ready, {models} models", []).append(
                _serve_ready(t.cli, t.many, t.env, t.tree))
    out = {"floor": {name: float(np.median(values)) for name, values in floor.items()}}
    for label, runs in samples.items():
        out[label] = {name: float(np.median(values)) for name, values in runs.items()}
    out["break-even"] = {f"{rows} {kernel}": float(np.median(values))
                         for (rows, kernel), values in even.items()}
    return out


def render(results: dict[str, dict[str, float]], repeats: int, baseline: str | None) -> str:
    floor_name, floor = next(iter(results["floor"].items()))
    lean = list(results["floor"].values())[1]
    flag = "" if baseline == BASELINE else f" --baseline {baseline or 'none'}"
    command = "python -m bench.startup" + flag
    lines = ["## Start-up", "", f"`{command}`", "",
             f"Seconds from process start, medians of {repeats} interleaved runs, one BLAS thread; the floor "
             f"is `python -c \"import {floor_name}\"` = {floor:.2f} s where the command runs numba's "
             f"loops (*compiled*), {lean:.2f} s without numba where it does not (`serve` imports numba "
             "after it is ready, in its warm-up thread).  `filter`: "
             "the 1-D cubic sensor on a 1-row input (target ≤ 2× the floor): as `filter` chooses (the numpy "
             "kernel below `COMPILED_MIN_ROWS` rows), and with the compiled kernel forced, with the numba "
             "cache that `yauyau precompute` warmed and with a cold one; `serve`: until "
             "`/readyz` answers (target < 2 s whatever the number of models).", "",
             "| revision | command | seconds | × floor |", "|---|---|---:|---:|"]
    for label, rows in results.items():
        if label in ("floor", "break-even"):
            continue
        for name, value in rows.items():
            base = floor if "compiled" in name else lean
            lines.append(f"| {label} | {name} | {value:.2f} | {value / base:.1f} |")
    even = results["break-even"]
    lines += ["", "The kernel's break-even for a one-shot `filter` (CPU seconds, user + system, each kernel "
              "forced with `YAUYAU_KERNEL`; `filter` itself takes the numpy path below "
              "`COMPILED_MIN_ROWS` rows, solver/jit.py):", "",
              "| rows | numpy kernel s | compiled kernel s | compiled − numpy s |", "|---:|---:|---:|---:|"]
    for rows in BREAK_EVEN_ROWS:
        a, b = even[f"{rows} numpy"], even[f"{rows} compiled"]
        lines.append(f"| {rows:,} | {a:.2f} | {b:.2f} | {b - a:+.2f} |")
    lines += ["", "The method is chosen once, at precompute, and stored with the model; `filter` reads it "
              "and imports neither SymPy nor the analysis (the numeric model is built from the checked "
              "syntax trees), and `serve` lists the models from the files' attributes and loads each on "
              "first use (a bounded cache).  Before, every `filter` ran the symbolic estimation-algebra "
              "analysis and `serve` analysed every stored model before answering.", ""]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m bench.startup", description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="fewer repeats")
    parser.add_argument("--baseline", default=BASELINE, metavar="REV",
                        help="also time this git revision (default %(default)s, v0.1; 'none' to skip)")
    args = parser.parse_args(argv)
    if args.baseline == "none" or not _known_revision(args.baseline):
        args.baseline = None
    repeats = 3 if args.quick else 7
    results = measure(repeats, 9, args.baseline)
    text = render(results, repeats, args.baseline)
    FRAGMENT.write_text(text)
    print(text)


if __name__ == "__main__":
    main()
