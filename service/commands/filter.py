"""`yauyau filter MODEL_ID --store DIR --increments IN --out OUT.csv`: run a filter over a file.

The input and output formats are in EPILOG (what ``yauyau filter -h`` prints).  The stored model
(storage.model_store) is filtered with the method of --method (default: the one chosen at precompute
and stored with the model; no analysis runs here) in chunks of --chunk rows, with --blas-threads
BLAS threads (default 1: docs/bench-blas.md).  --quantiles, --mode and --density add what the
density says beyond mean and covariance (yauyau.solver.summaries; storage.density_file).  All
input is validated before anything is written; OUT (and the density file) appear atomically.
Exit status: 0 done, 2 bad input (nothing written), 3 the filter degenerated (OUT is written, the
steps from the first degenerate one on are flagged; stderr says from which step and why).
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import tempfile
from pathlib import Path

from .precompute import store_argument

DEFAULT_CHUNK = 1000
EXIT_DEGENERATE = 3
DENSITY_POINTS = {1: 401, 2: 101, 3: 61}

EPILOG = """\
input (--increments IN):
  CSV: one row per step tau_k = k*dt, m comma-separated numbers (the observation increments
  dy_k = y(tau_k) - y(tau_(k-1)), not the cumulative y); an optional header line (any names);
  a row of empty fields is a missing observation (the filter only predicts). Or a .npy array
  of shape (K, m), NaN rows missing. `yauyau simulate SPEC --out DIR` writes such a file.

output (--out OUT.csv), one row per step:
  step, t                 step k and time t = k*dt
  mean_<var>              conditional mean E[x(t) | y], one column per state variable
  cov_<var>_<var>         conditional covariance (upper triangle)
  mode_<var>              with --mode: the MAP point (tallest node, refined)
  q<p>_<var>              with --quantiles p1,p2,...: marginal quantiles, e.g. q0.05_x
  loglik                  cumulative log-likelihood of the observations
  degenerate              1 from the step the density lost its mass on (see stderr), else 0

density (--density OUT.h5): the density every --density-every steps on a grid over the ball
  (--density-points per axis): joint density for 1-D and 2-D, each marginal always; CF-style
  HDF5 (time, step, one coordinate per variable); `yauyau plot` draws it.

exit status: 0 done; 2 bad input (nothing written); 3 the filter degenerated (OUT written).
"""


FORMS = ("stable", "literal")  # yauyau.solver.engine.FORMS (not imported here: start-up cost)
PRECISIONS = ("double", "single")


def blas_threads_argument(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--blas-threads", type=int, default=None, metavar="N",
                        help="BLAS threads of the online products (default: $YAUYAU_BLAS_THREADS or 1; one "
                             "thread per process is faster on a busy machine, docs/bench-blas.md)")


def blas_threads(requested: int | None) -> int:
    """The BLAS thread count: the flag, else $YAUYAU_BLAS_THREADS, else 1."""
    from yauyau.solver.errors import InputError

    if requested is None:
        text = os.environ.get("YAUYAU_BLAS_THREADS", "1")
        try:
            requested = int(text)
        except ValueError:
            raise InputError("YAUYAU_BLAS_THREADS", f"must be a positive integer, got {text!r}") from None
    if requested < 1 or requested > 1024:
        raise InputError("blas_threads", "must be a positive integer (at most 1024)")
    return requested


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from yauyau.solver.registry import METHODS

    parser.add_argument("model_id", help="id of a stored model (yauyau models lists them)")
    store_argument(parser)
    parser.add_argument("--increments", required=True, help="observation increments: .csv or .npy")
    parser.add_argument("--out", required=True, help="output CSV of the estimates")
    parser.add_argument("--method", choices=[m for m in METHODS if m != "auto"], default=None,
                        help="filter (default: the method chosen at precompute, stored with the model)")
    parser.add_argument("--form", choices=FORMS, default="stable",
                        help="yau-yau step: stable (default) or literal: Yau (2008) (5.35)")
    parser.add_argument("--precision", choices=PRECISIONS, default=None,
                        help="yau-yau matrix-vector products in double or single precision "
                             "(default: the spec's discretization.precision)")
    parser.add_argument("--chunk", type=int, default=DEFAULT_CHUNK,
                        help="rows per chunk (default %(default)s)")
    parser.add_argument("--quantiles", default=None, metavar="P,P,...",
                        help="marginal quantiles per variable, e.g. 0.05,0.5,0.95 (columns q<p>_<var>)")
    parser.add_argument("--mode", action="store_true", help="add the MAP point (columns mode_<var>)")
    parser.add_argument("--density", default=None, metavar="OUT.h5",
                        help="write the density on a grid every --density-every steps (HDF5)")
    parser.add_argument("--density-every", type=int, default=10, metavar="K",
                        help="steps between density snapshots (default %(default)s)")
    parser.add_argument("--density-points", type=int, default=None, metavar="G",
                        help="grid points per axis (default 401 in 1-D, 101 in 2-D, 61 in 3-D)")
    parser.add_argument("--progress", choices=("auto", "on", "off"), default="auto",
                        help="progress bar on stderr (auto: only when stderr is a terminal)")
    blas_threads_argument(parser)
    parser.epilog = EPILOG
    parser.formatter_class = argparse.RawDescriptionHelpFormatter


def run(args: argparse.Namespace) -> int:
    from threadpoolctl import threadpool_limits
    from yauyau.solver.errors import InputError
    from yauyau.solver.filtering import cumulative_hint
    from yauyau.solver.methods import make_filter

    from yauyau.api import load_model

    if args.chunk < 1:
        raise InputError("chunk", "must be a positive integer")
    outputs = Outputs.from_args(args)
    threads = blas_threads(args.blas_threads)
    stored = load_model(args.store, args.model_id)
    model = stored.model
    outputs.check(model)
    increments = read_increments(args.increments, model.m)
    method = args.method or stored.method
    why = "--method" if args.method else f"stored at precompute: {stored.method_reason}"
    print(f"yauyau filter: method {method} ({why})", file=sys.stderr)
    hint = cumulative_hint(increments, model)
    if hint:
        print(f"yauyau filter: warning: {hint}", file=sys.stderr)
    flt = make_filter(model, stored.offline, method, form=args.form, precision=args.precision)
    writer = outputs.density_writer(flt, stored, method)
    try:
        bar = progress_bar(args.progress, len(increments))
        with threadpool_limits(limits=threads, user_api="blas"), bar:
            rows, first_degenerate = filter_rows(flt, increments, args.chunk, outputs, writer, bar)
        write_csv(args.out, header(model, outputs), rows)
    except BaseException:
        if writer is not None:
            writer.abort()
        raise
    if writer is not None:
        writer.close()
    if first_degenerate is not None:
        print(f"yauyau filter: degenerate from step {first_degenerate.step} (t = {first_degenerate.t:g}): "
              f"{first_degenerate.reason}; the rows from there on are flagged degenerate = 1"
              + (f". {hint}" if hint else ""), file=sys.stderr)
        return EXIT_DEGENERATE
    return 0


class Outputs:
    """What to compute per step besides mean and covariance (from the command line)."""

    def __init__(self, probs=None, probs_text=(), mode=False, density=None, every=10, points=None):
        self.probs = probs
        self.probs_text = list(probs_text)
        self.mode = mode
        self.density = density
        self.every = every
        self.points = points

    @classmethod
    def from_args(cls, args: argparse.Namespace) -> "Outputs":
        from yauyau.solver.errors import InputError
        from yauyau.solver.summaries import check_probabilities

        probs, texts = None, []
        if args.quantiles is not None:
            probs = check_probabilities(args.quantiles)
            texts = [p.strip() for p in args.quantiles.split(",") if p.strip()]
            if len(set(probs.tolist())) != len(probs):
                raise InputError("quantiles", "each probability once")
        if args.density_every < 1:
            raise InputError("density_every", "must be a positive integer")
        if args.density_points is not None and not 2 <= args.density_points <= 2001:
            raise InputError("density_points", "must be an integer in 2..2001")
        return cls(probs, texts, args.mode, args.density, args.density_every, args.density_points)

    @property
    def per_step(self) -> bool:
        return self.probs is not None or self.mode or self.density is not None

    def check(self, model) -> None:
        from yauyau.solver.errors import InputError

        if self.density is not None and Path(self.density).suffix.lower() not in (".h5", ".hdf5"):
            raise InputError("density", f"{self.density}: the density file is HDF5, name it *.h5")
        if self.points is not None and model.n == 3 and self.points > 201:
            raise InputError("density_points", "at most 201 per axis in 3-D")

    def density_writer(self, flt, stored, method):
        if self.density is None:
            return None
        import numpy as np
        from yauyau.storage.density_file import DensityWriter

        model = flt.model
        points = self.points or DENSITY_POINTS.get(model.n, 41)
        c, r = model.center, model.radius
        self.axes = [np.linspace(c[i] - r, c[i] + r, points) for i in range(model.n)]
        return DensityWriter(self.density, list(model.spec.state), self.axes, joint=model.n <= 2,
                             attrs={"model_id": stored.id, "model_name": model.spec.name, "method": method,
                                    "dt": float(model.dt)})


def progress_bar(mode: str, total: int):
    """tqdm over the rows on stderr: only on a terminal unless --progress on."""
    from tqdm import tqdm

    disable = mode == "off" or (mode == "auto" and not sys.stderr.isatty())
    return tqdm(total=total, disable=disable, unit="obs", file=sys.stderr, desc="yauyau filter",
                mininterval=0.5, dynamic_ncols=True)


def read_increments(path: str, m: int):
    """(K, m) floats from .npy or CSV; NaN rows are missing observations."""
    import numpy as np
    from yauyau.solver.errors import InputError
    from yauyau.solver.filtering import check_increments

    if Path(path).suffix.lower() == ".npy":
        try:
            data = np.load(path, allow_pickle=False)
        except (OSError, ValueError) as exc:
            raise InputError("increments", f"cannot read {path}: {exc}") from None
        if data.dtype.kind not in "iuf":
            raise InputError("increments", f"{path} must hold numbers, not {data.dtype}")
        return check_increments(data, m)
    try:
        text = Path(path).read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError("increments", f"cannot read {path}: {exc}") from None
    return check_increments(parse_csv(text, m), m)


def parse_csv(text: str, m: int) -> list[list[float]]:
    """Rows of m fields; empty fields (or a blank line) are a missing observation (NaN row); the
    first line is a header when none of its fields is a number (a first line with some numbers is
    data, and a bad field in it an error: never silently shift every step by one); blank lines at
    the end are ignored."""
    from yauyau.solver.errors import InputError

    lines = text.splitlines()
    while lines and not lines[-1].strip():
        lines.pop()
    rows: list[list[float]] = []
    for number, line in enumerate(lines, start=1):
        fields = [f.strip() for f in line.split(",")] if line.strip() else [""] * m
        values = [_number(f) for f in fields]
        if number == 1 and line.strip() and all(v is None for v in values):
            continue  # a header: text in every field
        where = f"increments[{len(rows)}]"
        if len(fields) != m:
            raise InputError(where, f"line {number}: expected {m} field(s), got {len(fields)}")
        for j, (field, value) in enumerate(zip(fields, values, strict=True)):
            if value is None:
                raise InputError(f"{where}[{j}]", f"line {number}: {field[:40]!r} is not a finite number")
        rows.append([math.nan if v == "" else v for v in values])
    return rows


def _number(field: str):
    """A finite float, "" for an empty field, None for anything else (nan/inf included)."""
    if field == "":
        return ""
    try:
        value = float(field)
    except ValueError:
        return None
    return value if math.isfinite(value) else None


def filter_rows(flt, increments, chunk: int, outputs: Outputs | None = None, writer=None, bar=None):
    """One output row per step (step, t, means, upper-triangle covariances[, modes, quantiles],
    loglik, degenerate) and the first degenerate estimate (or None)."""
    outputs = outputs or Outputs()
    state = flt.initial_state()
    rows: list[list] = []
    first_degenerate = None
    if writer is not None:
        snapshot(flt, state, flt.estimate(state), outputs, writer)  # the prior, t = 0
    for start in range(0, len(increments), chunk):
        block = increments[start:start + chunk]
        if outputs.per_step:
            estimates = []
            for row in block:
                state, estimate = flt.step(state, row)
                estimates.append((estimate, summary_columns(flt, state, estimate, outputs, writer)))
        else:
            state, result = flt.run(state, block)
            estimates = [(e, []) for e in result]
        for e, extra in estimates:
            n = len(e.mean)
            cov = [float(e.cov[i][j]) for i in range(n) for j in range(i, n)]
            mean = [float(v) for v in e.mean]
            rows.append([int(e.step), float(e.t), *mean, *cov, *extra, float(e.loglik), int(e.degenerate)])
            if e.degenerate and first_degenerate is None:
                first_degenerate = e
        if bar is not None:
            bar.update(len(block))
    return rows, first_degenerate


def summary_columns(flt, state, estimate, outputs: Outputs, writer) -> list:
    """Mode and quantile columns of one step (empty fields when degenerate); a density snapshot
    every ``outputs.every`` steps."""
    from yauyau.solver import summaries

    n = flt.model.n
    extra: list = []
    healthy = not estimate.degenerate
    if outputs.mode:
        point = summaries.mode(flt, state, estimate) if healthy else None
        extra += [float(v) for v in point] if point is not None else [""] * n
    if outputs.probs is not None:
        q = summaries.quantiles(flt, state, outputs.probs, estimate) if healthy else None
        blank = [""] * len(outputs.probs)
        for i in range(n):
            extra += [float(v) if v == v else "" for v in q[i]] if q is not None else blank
    if writer is not None and healthy and int(estimate.step) % outputs.every == 0:
        snapshot(flt, state, estimate, outputs, writer)
    return extra


def snapshot(flt, state, estimate, outputs: Outputs, writer) -> None:
    """The marginals (and the joint density in 1-D and 2-D) on the output grid, into the file."""
    from yauyau.solver import summaries

    marginals = summaries.marginals_on_grid(flt, state, outputs.axes, estimate)
    joint = summaries.joint_on_grid(flt, state, outputs.axes) if flt.model.n <= 2 else None
    writer.append(int(estimate.step), float(estimate.t), marginals, joint)


def header(model, outputs: Outputs | None = None) -> list[str]:
    outputs = outputs or Outputs()
    names = model.spec.state
    n = len(names)
    cov = [f"cov_{names[i]}_{names[j]}" for i in range(n) for j in range(i, n)]
    extra = [f"mode_{v}" for v in names] if outputs.mode else []
    if outputs.probs is not None:
        extra += [f"q{p}_{v}" for v in names for p in outputs.probs_text]
    return ["step", "t", *[f"mean_{v}" for v in names], *cov, *extra, "loglik", "degenerate"]


def write_csv(path: str, columns: list[str], rows: list[list]) -> None:
    """Write atomically (temporary file in the same directory, then rename)."""
    from yauyau.solver.errors import InputError

    target = Path(path)
    try:
        handle, tmp = tempfile.mkstemp(prefix=".tmp-", suffix=".csv", dir=target.parent)
    except OSError as exc:
        raise InputError("out", f"cannot write {path}: {exc}") from None
    try:
        with os.fdopen(handle, "w", encoding="utf-8", newline="") as out:
            out.write(",".join(columns) + "\n")
            for row in rows:
                out.write(",".join(repr(v) if isinstance(v, float) else str(v) for v in row) + "\n")
        os.replace(tmp, target)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
