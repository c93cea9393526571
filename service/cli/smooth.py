"""`yauyau smooth MODEL_ID --store DIR (--increments IN | --observations IN.csv) --out OUT.csv [--t0 T]
[--lag L] [--quantiles P,...] [--mode]`:
the optimal smoother over a recorded file (yauyau.solver.smoothing, issue 38).

The input is read as `yauyau filter` reads it (service/cli/csv_io.py) and the output has its columns
(``filter.header``): ``mean_<var>`` and ``cov_<var>_<var>`` are the smoothed moments, given every row
of the file (``--lag L``: given the rows up to L after each row, fixed-lag); loglik, gated and
predictive_loglik are the forward pass's.  Methods yau-yau (the general engine's forward–backward
smoother of its discretised model, also on a ball that follows the state), kalman-bucy and yau-hu
(exact: solver/smoothing.py); another method, a filter that degenerates, a bad --lag or a file longer
than the memory budget (--memory) exit 2 naming the field, with nothing written.
"""

from __future__ import annotations

import argparse
import math
import sys

from yauyau.solver.errors import InputError
from yauyau.solver.registry import AUTO, FORMS, METHODS, PRECISIONS

from .csv_io import Source, csv_lines, read_increments, read_observations, write_lines
from .filter import Outputs, blas_threads_argument, header, record_arguments, snapshot

DEFAULT_MEMORY_GB = 2.0  # what the rows of a smoothing run may take (check_memory)

EPILOG = """\
input and output as for `yauyau filter` (yauyau filter -h): --increments IN (regular rows) or
  --observations IN.csv (rows with their times, header t,<components>); an empty field is missing,
  a row of empty fields no observation. OUT.csv has filter's columns: step, t, mean_<var>,
  cov_<var>_<var>, loglik, degenerate, gated, predictive_loglik, reinitialised (and center_<var>,
  recentred on a ball that follows the state); the means and
  covariances are the smoothed ones (given every row; with --lag L, given the rows up to L after);
  --quantiles P,... and --mode add q<p>_<var> and mode_<var> of the smoothed density (with --lag L, of
  each row's density given the L rows after it), --density D.h5 writes it on a grid as filter --density
  does (yau-yau).

exit status: 0 done; 2 bad input, a method that cannot smooth, a filter that degenerates or a file
  over the memory budget (one line on stderr naming the field, nothing written).
"""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    record_arguments(parser, "output CSV of the smoothed estimates")
    parser.add_argument("--lag", default=None, metavar="L",
                        help="fixed-lag smoothing: each row given the L rows after it (default: every row)")
    parser.add_argument("--method", choices=[m for m in METHODS if m != AUTO], default=None,
                        help="method (default: the one chosen at precompute); yau-yau, kalman-bucy or yau-hu "
                             "smooth")
    parser.add_argument("--form", choices=FORMS, default="stable", help="yau-yau step: stable or literal")
    parser.add_argument("--precision", choices=PRECISIONS, default=None,
                        help="yau-yau products in double or single precision")
    parser.add_argument("--gate", type=float, default=None, metavar="K",
                        help="outlier gate in predictive standard deviations (default: the spec's; 0: off)")
    parser.add_argument("--quantiles", default=None, metavar="P,P,...",
                        help="marginal quantiles of each row's smoothed density, e.g. 0.05,0.5,0.95 "
                             "(columns q<p>_<var>, as filter writes them)")
    parser.add_argument("--mode", action="store_true",
                        help="the smoothed density's mode (columns mode_<var>)")
    parser.add_argument("--density", default=None, metavar="OUT.h5",
                        help="write the smoothed density on a grid every --density-every steps (HDF5, as "
                             "filter --density writes it; yau-yau)")
    parser.add_argument("--density-every", type=int, default=10, metavar="K",
                        help="steps between density snapshots (default %(default)s)")
    parser.add_argument("--density-points", type=int, default=None, metavar="G",
                        help="grid points per axis (default 401 in 1-D, 101 in 2-D, 61 in 3-D)")
    parser.add_argument("--memory", type=float, default=DEFAULT_MEMORY_GB, metavar="GB",
                        help="memory budget of the smoother's stored rows (default %(default)s GB)")
    blas_threads_argument(parser)
    parser.epilog = EPILOG
    parser.formatter_class = argparse.RawDescriptionHelpFormatter


def parse_lag(text: str | None) -> int | None:
    """--lag: a non-negative whole number of rows (InputError('lag'))."""
    if text is None:
        return None
    try:
        value = int(text.strip())
    except ValueError:
        raise InputError("lag", f"must be a non-negative whole number of rows, got {text!r}") from None
    if value < 0:
        raise InputError("lag", f"must be a non-negative whole number of rows, got {text!r}")
    return value


def check_memory(flt, rows: int, budget_gb: float, field: str) -> None:
    """Refuse a file whose rows do not fit the budget: the engine keeps its whole forward pass where the
    K×Q nodal values fit KEEP, else works in checkpointed blocks of max(256, √K, KEEP / Q) rows (3 doubles a
    node a row: σ, the factors and their exponents; solver/engine/smoother.py), and every row keeps its
    result (mean, covariance, flags) and its line of output (about 200 bytes)."""
    from yauyau.solver.engine.smoother import BLOCK, KEEP

    if not (math.isfinite(budget_gb) and budget_gb > 0):
        raise InputError("memory", "must be a positive number of GB")
    n, nodes = flt.model.n, len(getattr(flt, "weights", ()))
    per_row = 8 * (3 * n + n * n + 12) + 200 + 8 * (nodes + 1) // BLOCK  # + a checkpoint per block
    kept = rows * nodes <= KEEP
    block = 24 * nodes * (rows if kept else max(BLOCK, math.isqrt(max(rows, 1)) + 1, KEEP // max(nodes, 1)))
    budget = budget_gb * 1e9
    fits = max(0, int((budget - block) // per_row))
    if rows > fits:
        raise InputError(field, f"{rows} rows need about {(rows * per_row + block) / 1e9:.3g} GB to smooth, "
                                f"over the budget of {budget_gb:g} GB (--memory): at most {fits} rows fit; "
                                "split the file or raise --memory")


def check_summaries(flt, outputs) -> None:
    """--mode, --quantiles and --density read each row's smoothed density: the engine's (yau-yau) or a
    Gaussian's (kalman-bucy); another smoother (yau-hu's mixture) gives its moments only — refused by
    the option's name before any work (its mode is not its mean)."""
    from yauyau.solver.smoothed_summaries import offers_densities

    if offers_densities(flt):
        return
    for wanted, field in ((outputs.mode, "mode"), (outputs.probs is not None, "quantiles"),
                          (outputs.density is not None, "density")):
        if wanted:
            raise InputError(field, f"method {flt.method}: its smoother gives the smoothed mean and "
                                    f"covariance only; drop --{field}, or smooth with --method yau-yau (the "
                                    "engine's smoothed density)")


def run(args: argparse.Namespace) -> int:
    from yauyau.solver import jit

    with jit.one_shot():  # the kernel chosen for this input's length ends with the command (as filter's)
        return _run(args)


def _run(args: argparse.Namespace) -> int:
    from yauyau.solver import jit
    from yauyau.solver.blas import blas_threads, limited_blas
    from yauyau.solver.filtering import at_time, check_t0
    from yauyau.solver.measurement import check_gate
    from yauyau.solver.methods import make_filter
    from yauyau.solver.smoothed_summaries import smooth_lag_with_quantiles, smooth_with_quantiles

    from yauyau.api import load_model

    lag = parse_lag(args.lag)
    outputs = Outputs.from_args(args)
    if args.t0 is not None and not math.isfinite(args.t0):
        raise InputError("t0", "must be a finite number (the time at which the model's prior holds)")
    gate = check_gate(args.gate)
    stored = load_model(args.store, args.model_id)
    model = stored.model
    kind = model.spec.measurement.kind
    if args.observations is not None:
        source = read_observations(args.observations, model.m, kind, args.t0)
    else:
        if kind == "discrete":
            raise InputError("increments", f"model {stored.id} has discrete measurements: give them with "
                                           "their times, --observations IN.csv")
        t0 = 0.0 if args.t0 is None else check_t0(float(args.t0), "t0", float(model.dt), "--t0")
        numbers: list[int] = []
        source = Source(read_increments(args.increments, model.m, numbers), None, t0, "increments",
                        numbers or None)
    method = args.method or stored.method
    flt = make_filter(model, stored.offline, method, form=args.form, precision=args.precision, gate=gate)
    check_memory(flt, len(source.rows), args.memory, source.field)
    check_summaries(flt, outputs)
    threads = blas_threads(args.blas_threads)
    jit.choose_for_rows(len(source.rows), getattr(flt, "compiled_min_rows", jit.COMPILED_MIN_ROWS))
    state = at_time(flt.initial_state(), source.t0)
    snapshots: dict[int, object] = {}  # --density: the smoothed states of every --density-every-th step

    def keep(k: int, smoothed) -> None:
        if int(smoothed.step) % outputs.every == 0:
            snapshots[int(smoothed.step)] = smoothed
    each = None if outputs.density is None else keep
    try:
        with limited_blas(threads):  # one by default (blas.md)
            if lag is None:
                _, result, table = smooth_with_quantiles(flt, state, source.rows, source.times, outputs.probs,
                                                         each)
            else:
                _, result, table = smooth_lag_with_quantiles(flt, state, source.rows, source.times, lag,
                                                             outputs.probs, each)
    except InputError as exc:
        raise InputError(_in_file(exc.field, source), exc.message) from None
    extras = None
    if outputs.mode or outputs.probs is not None:
        mode = result.mean if result.mode is None else result.mode
        K = len(result.step)
        extras = [[*(mode[k].tolist() if outputs.mode else []),
                   *(table[k].ravel().tolist() if table is not None else [])] for k in range(K)]
    writer = outputs.density_writer(flt, stored, method)
    try:
        for step in sorted(snapshots):
            snapshot(flt, snapshots[step], snapshots[step].last, outputs, writer)
        write_lines(args.out, header(model, outputs, follow=result.center is not None),  # a following ball
                    csv_lines(result, extras))
    except BaseException:
        if writer is not None:
            writer.abort()
        raise
    if writer is not None:
        writer.close()
    what = "fixed-interval" if lag is None else f"fixed-lag (L = {lag})"
    print(f"yauyau smooth: method {method}, {what}, {len(source.rows)} row(s), {int(result.gated.sum())} "
          "gated", file=sys.stderr)
    return 0


def _in_file(field: str, source: Source) -> str:
    """A smoother's ``increments[k]``/``observations[k]`` as the file's row (with its line)."""
    for name in ("increments", "observations"):
        if field.startswith(f"{name}[") and "]" in field:
            index, rest = field[len(name) + 1:].split("]", 1)
            if index.isdigit():
                return source.where(int(index)) + rest
    return field
