"""`yauyau filter MODEL_ID --store DIR --increments IN --out OUT.csv`: run a filter over a file.

The observation increments Δy_k = y(τ_k) − y(τ_{k−1}), one row per step τ_k = k·dt, are read from
a CSV file (m comma-separated numbers per row; an optional header line; a row of empty fields is a
missing observation, the filter then only predicts) or a .npy array (K, m) (NaN rows missing).
The stored model (storage.model_store) is filtered with the method of --method (default: the one
chosen at precompute and stored with the model; no analysis runs here) in chunks of --chunk rows, with
--blas-threads BLAS threads (default 1: docs/bench-blas.md), and OUT gets one
row per step: step, t, mean_<var>…, cov_<var>_<var>… (upper triangle), loglik (cumulative),
degenerate.  All input is validated before anything is written; OUT appears atomically.
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
    blas_threads_argument(parser)


def run(args: argparse.Namespace) -> int:
    from threadpoolctl import threadpool_limits
    from yauyau.solver.errors import InputError
    from yauyau.solver.methods import make_filter

    from yauyau.api import load_model

    if args.chunk < 1:
        raise InputError("chunk", "must be a positive integer")
    threads = blas_threads(args.blas_threads)
    stored = load_model(args.store, args.model_id)
    model = stored.model
    increments = read_increments(args.increments, model.m)
    method = args.method or stored.method
    why = "--method" if args.method else f"stored at precompute: {stored.method_reason}"
    print(f"yauyau filter: method {method} ({why})", file=sys.stderr)
    flt = make_filter(model, stored.offline, method, form=args.form, precision=args.precision)
    with threadpool_limits(limits=threads, user_api="blas"):
        rows, first_degenerate = filter_rows(flt, increments, args.chunk)
    write_csv(args.out, header(model), rows)
    if first_degenerate is not None:
        print(f"yauyau filter: degenerate from step {first_degenerate.step}: {first_degenerate.reason}",
              file=sys.stderr)
    return 0


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


def filter_rows(flt, increments, chunk: int):
    """One output row per step (step, t, means, upper-triangle covariances, loglik, degenerate) and
    the first degenerate estimate (or None)."""
    state = flt.initial_state()
    rows: list[list] = []
    first_degenerate = None
    for start in range(0, len(increments), chunk):
        state, estimates = flt.run(state, increments[start:start + chunk])
        for e in estimates:
            n = len(e.mean)
            cov = [float(e.cov[i][j]) for i in range(n) for j in range(i, n)]
            mean = [float(v) for v in e.mean]
            rows.append([int(e.step), float(e.t), *mean, *cov, float(e.loglik), int(e.degenerate)])
            if e.degenerate and first_degenerate is None:
                first_degenerate = e
    return rows, first_degenerate


def header(model) -> list[str]:
    names = model.spec.state
    n = len(names)
    cov = [f"cov_{names[i]}_{names[j]}" for i in range(n) for j in range(i, n)]
    return ["step", "t", *[f"mean_{v}" for v in names], *cov, "loglik", "degenerate"]


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
