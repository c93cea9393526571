"""`yauyau filter MODEL_ID --store DIR (--increments IN | --observations IN.csv) --out OUT.csv`.

The input and output formats are in EPILOG (what ``yauyau filter -h`` prints).  The stored model
(storage.model_store) is filtered with the method of --method (default: the one chosen at precompute
and stored with the model; no analysis runs here) in chunks of --chunk rows, with --blas-threads
BLAS threads (default 1: bench/results/blas.md).  Rows are the spec's ``[measurement]`` kind: increments
dy (continuous) or measurements z (discrete); --increments reads regular rows (t_k = t0 + k·dt),
--observations rows with their own times.  --gate overrides the spec's outlier gate, --on-degenerate
says what a degenerate density does (solver/recovery.py), --lost-track when a filter that keeps gating
or restarting has lost track and --monitor the innovation monitor (solver/watch.py).  --quantiles,
--mode and --density add what the density says beyond mean and covariance (yauyau.solver.summaries;
storage.density_file): the rows are then run one at a time (solver/summarised.py, the path the
service takes for a chunk that asks for them).  All input is validated before anything is written;
OUT (and the density file) appear atomically.  The output columns are built from the chunks' arrays
(ChunkResult), not per-row objects; the files are read and written by service/cli/csv_io.py.  The
solver's modules are imported inside the functions: ``yauyau -h`` imports this module (start-up).
Exit status: 0 done, 2 bad input (nothing written), 3 the filter degenerated under --on-degenerate
stop, or lost track (OUT is written, the steps from the first degenerate one on are flagged; stderr
says from which step and why).
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

from yauyau.solver.blas import blas_threads
from yauyau.solver.errors import InputError
from yauyau.solver.registry import AUTO, DEFAULT_POLICY, FORMS, METHODS, POLICIES, PRECISIONS

from .csv_io import Source, csv_lines, read_increments, read_observations, write_lines
from .precompute import store_argument

DEFAULT_CHUNK = 1000
EXIT_DEGENERATE = 3
DENSITY_POINTS = {1: 401, 2: 101, 3: 61}

EPILOG = """\
input, one of:
  --increments IN   regular rows, t_k = t0 + k*dt (dt of the spec; t0 = --t0, default 0): CSV of
                    m comma-separated numbers per row, an optional header line (any names), or a
                    .npy array (K, m). Continuous models only ([measurement] kind = "continuous"):
                    the rows are the increments dy_k = y(t_k) - y(t_(k-1)), not the cumulative y.
  --observations IN.csv
                    rows with their own times: a header whose first column is t, then one column
                    per observation component (any names; m of them), e.g. "t,z_1"; one row per
                    time, times finite and strictly increasing (they need not be regular). For a
                    discrete model ([measurement] kind = "discrete") a row holds the measurements
                    z = h(x(t)) + v at t; for a continuous one the increments dy of y over
                    [t_(k-1), t_k], t_0 = --t0. A discrete model reads only --observations.
  In both, an empty field is a missing component (only the others update) and a row of empty
  fields no observation at that time (the filter only predicts). `yauyau simulate SPEC --out DIR`
  writes DIR/increments.csv or DIR/observations.csv.

time of the prior (--t0 T): the model's prior holds at t = T. With --observations the default is
  the first row's time: the prior holds at the first observation, which is an update with no
  propagation before it (for a continuous model that first row covers no interval: leave its
  values empty or give --t0, e.g. --t0 0 for the files of yauyau simulate, whose paths start at 0).
  An earlier T propagates the prior from T to the first row. With --increments the default is 0.

outliers (--gate K): a row whose predictive standard score exceeds K is not used (the step only
  predicts) and is flagged gated = 1; default: the spec's [measurement] gate (6 unless set); 0
  turns the gate off. A method that cannot gate (wei-norman: its path integrals need every row)
  takes every row and leaves gated = 0.

degenerate density (--on-degenerate): stop (default): the rows from the first degenerate one on
  are flagged degenerate = 1 (their estimates repeat the last good one) and the exit status is 3;
  reinitialise: the filter starts again there from a prior broadened around the last good
  estimate (that row's observation is not used, the row is flagged reinitialised = 1) and goes on;
  the exit status is then 0. stderr says how many rows were gated and re-initialised, and why.

lost track (--lost-track GATED,RESTARTS,WINDOW, default 20,3,100; 0 turns a rule off): a filter
  that gated GATED consecutive rows, or restarted RESTARTS times within WINDOW rows, no longer
  follows the state (on a fixed ball: the state left it): from that row on the rows are
  degenerate = 1, with the reason and the fix on stderr (domain.follow = true, a larger
  domain.radius), whatever --on-degenerate says; the exit status is 3.

innovation monitor (--monitor N): a sustained bias of the observations against their predictions
  (a drifting sensor) raises alarm = 1 on a row; N is the mean number of healthy rows per false
  alarm (1e9 is a good choice; default: the spec's [measurement] monitor, off unless set; 0 turns
  it off). stderr says how many alarms were raised and where the first was.

output (--out OUT.csv), one row per input row:
  step, t                 step k (1, 2, ...) and its time t_k
  mean_<var>              conditional mean E[x(t) | observations up to t], one column per variable
  cov_<var>_<var>         conditional covariance (upper triangle)
  mode_<var>              with --mode: the MAP point (tallest node, refined)
  q<p>_<var>              with --quantiles p1,p2,...: marginal quantiles, e.g. q0.05_x
  loglik                  cumulative log-likelihood of the observations used (discrete: the sum
                          of their predictive_loglik; continuous: relative to pure noise, dy = dw)
  degenerate              1 from the step the density lost its mass on (see stderr), else 0
  gated                   1 when the gate rejected this row's observation, else 0
  predictive_loglik       log p(this row | the rows before) (-inf: impossible under the model);
                          empty when the row has no observation (or the method does not compute it)
  reinitialised           1 when the filter started again at this row (--on-degenerate), else 0
  alarm                   (--monitor) 1 when the innovation monitor raised its alarm at this row
  monitor                 (--monitor) its statistic after this row (+-1: an alarm; +: the
                          observations above their predictions)
  center_<var>            ([domain] follow = true) the centre of the ball after this row
  recentred               ([domain] follow = true) 1 when the ball moved after this row, else 0

density (--density OUT.h5): the density every --density-every steps on a grid over the ball
  (--density-points per axis): joint density for 1-D and 2-D, each marginal always; CF-style
  HDF5 (time, step, one coordinate per variable); `yauyau plot` draws it.

exit status: 0 done; 2 bad input (one line on stderr naming the field or row, nothing written);
  3 the filter degenerated under --on-degenerate stop, or lost track (OUT written, rows flagged).
"""


def blas_threads_argument(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--blas-threads", type=int, default=None, metavar="N",
                        help="BLAS threads of the online products (default: $YAUYAU_BLAS_THREADS or 1; one "
                             "thread per process is faster on a busy machine, bench/results/blas.md)")


def record_arguments(parser: argparse.ArgumentParser, out_help: str) -> None:
    """A stored model and a record of rows: what `filter` and `smooth` both read."""
    parser.add_argument("model_id", help="id of a stored model (yauyau models lists them)")
    store_argument(parser)
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument("--increments", metavar="IN",
                        help="regular rows (continuous models): observation increments, .csv or .npy")
    source.add_argument("--observations", metavar="IN.csv",
                        help="rows with their times: CSV with a header t,<one column per component>")
    parser.add_argument("--out", required=True, help=out_help)
    parser.add_argument("--t0", type=float, default=None, metavar="T",
                        help="time of the prior (default: the first row's time with --observations, "
                             "0 with --increments)")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    record_arguments(parser, "output CSV of the estimates")
    parser.add_argument("--gate", type=float, default=None, metavar="K",
                        help="outlier gate in predictive standard deviations (default: the spec's "
                             "[measurement] gate; 0: off)")
    parser.add_argument("--on-degenerate", choices=POLICIES, default=DEFAULT_POLICY,
                        help="stop (default: flag the rest, exit 3) or reinitialise (start again from a "
                             "broadened prior and go on)")
    parser.add_argument("--lost-track", default=None, metavar="GATED,RESTARTS,WINDOW",
                        help="lost track after GATED consecutive gated rows or RESTARTS restarts within "
                             "WINDOW rows (default 20,3,100; 0 turns a rule off)")
    parser.add_argument("--monitor", type=float, default=None, metavar="N",
                        help="innovation monitor: mean healthy rows per false alarm, e.g. 1e9 (default: the "
                             "spec's [measurement] monitor, off unless set; 0: off)")
    parser.add_argument("--method", choices=[m for m in METHODS if m != AUTO], default=None,
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
    from yauyau.solver import jit

    with jit.one_shot():  # the kernel chosen for this input's length ends with the command
        return _run(args)


def _run(args: argparse.Namespace) -> int:
    from yauyau.solver import jit
    from yauyau.solver.blas import limited_blas
    from yauyau.solver.filtering import check_t0, cumulative_hint
    from yauyau.solver.measurement import check_gate
    from yauyau.solver.methods import make_filter
    from yauyau.solver.watch import check_monitor, parse_lost_track, settings_for

    from yauyau.api import OnlineFilter, load_model

    if args.chunk < 1:
        raise InputError("chunk", "must be a positive integer")
    if args.t0 is not None and not math.isfinite(args.t0):
        raise InputError("t0", "must be a finite number (the time at which the model's prior holds)")
    gate = check_gate(args.gate)
    lost_track = None if args.lost_track is None else parse_lost_track(args.lost_track)
    monitor = check_monitor(args.monitor, "--monitor")
    outputs = Outputs.from_args(args)
    threads = blas_threads(args.blas_threads)
    stored = load_model(args.store, args.model_id)
    model = stored.model
    outputs.check(model)
    kind = model.spec.measurement.kind
    if args.observations is not None:
        source = read_observations(args.observations, model.m, kind, args.t0)
    else:
        if kind == "discrete":
            raise InputError("increments", f"model {stored.id} has discrete measurements ([measurement] "
                                           'kind = "discrete"): give them with their times, --observations '
                                           "IN.csv (a header t,<one column per component>)")
        if args.t0 is not None:  # regular rows step by dt from t0: that must still be a step
            check_t0(float(args.t0), "t0", float(model.dt), "--t0")
        numbers: list[int] = []
        source = Source(read_increments(args.increments, model.m, numbers), None,
                        0.0 if args.t0 is None else float(args.t0), "increments", numbers or None)
    method = args.method or stored.method
    flt = make_filter(model, stored.offline, method, form=args.form, precision=args.precision, gate=gate)
    # short inputs: numba's start-up costs more than its compiled rows save
    jit.choose_for_rows(len(source.rows), getattr(flt, "compiled_min_rows", jit.COMPILED_MIN_ROWS))
    state = OnlineFilter(flt, t0=source.t0).state if source.times is None else _at(flt, source.t0)
    watch = settings_for(flt, lost_track, monitor)
    preflight(flt, state, source, args.method is None)
    why = "--method" if args.method else f"stored at precompute: {stored.method_reason}"
    print(f"yauyau filter: method {method} ({why})", file=sys.stderr)
    hint = cumulative_hint(source.rows, model) if source.times is None else None
    if hint:
        print(f"yauyau filter: warning: {hint}", file=sys.stderr)
    writer = outputs.density_writer(flt, stored, method)
    try:
        bar = progress_bar(args.progress, len(source.rows))
        with limited_blas(threads), bar:
            lines, report = filter_rows(flt, source.rows, args.chunk, outputs, writer, bar,
                                        times=source.times, state=state, policy=args.on_degenerate,
                                        watch=watch)
        write_lines(args.out, header(model, outputs, follow=hasattr(flt, "directions"),
                                     monitor=watch.monitor > 0), lines)
    except BaseException:
        if writer is not None:
            writer.abort()
        raise
    if writer is not None:
        writer.close()
    report.print(len(source.rows), flt.gate if hasattr(flt, "gate") else None, watch.monitor)
    if report.degenerate is not None:
        step, t, reason = report.degenerate
        instead = ("" if (reason or "").startswith("lost track") else
                   " (--on-degenerate reinitialise starts again instead)")
        print(f"yauyau filter: degenerate from step {step} (t = {t:g}): {reason}; the rows from there on are "
              f"flagged degenerate = 1{instead}" + (f". {hint}" if hint else ""), file=sys.stderr)
        return EXIT_DEGENERATE
    return 0


def _at(flt, t0: float):
    """The filter's initial state at ``t0`` (rows with their own times: their gaps were checked)."""
    from yauyau.solver.filtering import at_time

    return at_time(flt.initial_state(), t0)


def preflight(flt, state, source: Source, stored_method: bool) -> None:
    """One step of the row a method is likeliest to refuse (the first partly missing row, else the
    first) before anything runs: a method that cannot take these rows (irregular times, discrete
    measurements, a partly missing row) says so now, naming the row and the fix; the step is
    discarded (a filter's state is a value)."""
    import numpy as np

    rows = source.rows
    if not len(rows):
        return
    missing = np.isnan(rows)
    partial = missing.any(axis=1) & ~missing.all(axis=1)
    k = int(np.argmax(partial)) if partial.any() else 0
    times = None if source.times is None else source.times[k:k + 1]
    try:
        flt.run_arrays(state, rows[k:k + 1], times)
    except InputError as exc:
        field = exc.field  # about the probe's one row k (increments[0], increments) or the whole input
        if field.startswith("increments[0]"):
            field = source.where(k) + field[len("increments[0]"):]
        elif field == "increments":
            field = source.where(k)
        elif field.startswith("times[0]") and source.times is not None:
            field = source.where(k).replace(source.field, "times", 1) + field[len("times[0]"):]
        message = exc.message
        if "(the general engine) takes it" in message:
            stored_with = f" (the model was stored with {flt.method})" if stored_method else ""
            message += f"; use --method yau-yau{stored_with}"
        raise InputError(field, message) from None


class Report:
    """What a run flagged: gated and re-initialised rows (count and the first with its reason), the
    first degenerate row (step, t, reason) or None."""
    def __init__(self):
        self.gated = 0
        self.reinitialised = 0
        self.first_gated = None
        self.first_reinitialised = None
        self.degenerate = None
        self.alarms = 0
        self.first_alarm = None

    def add(self, result, gate) -> None:
        import numpy as np

        if result.alarm.any():
            if self.first_alarm is None:
                k = int(np.argmax(result.alarm))
                self.first_alarm = (int(result.step[k]), float(result.t[k]), float(result.monitor[k]))
            self.alarms += int(result.alarm.sum())
        if self.degenerate is None and result.degenerate.any():
            k = int(np.argmax(result.degenerate))
            self.degenerate = (int(result.step[k]), float(result.t[k]), result.row_reason(k, gate))
        for name in ("gated", "reinitialised"):
            flags = getattr(result, name)
            count = int(flags.sum())
            if count:
                if getattr(self, f"first_{name}") is None:
                    k = int(np.argmax(flags))
                    setattr(self, f"first_{name}", (int(result.step[k]), float(result.t[k]),
                                                    result.row_reason(k, gate)))
                setattr(self, name, getattr(self, name) + count)

    def print(self, rows: int, gate, monitor: float = 0.0) -> None:
        gate_text = "gate off" if not gate else f"gate {gate:g} sd"
        print(f"yauyau filter: {rows} row(s), {self.gated} gated ({gate_text}), {self.reinitialised} "
              "re-initialised", file=sys.stderr)
        for what, first in (("gated", self.first_gated), ("re-initialised", self.first_reinitialised)):
            if first is not None:
                step, t, reason = first
                print(f"yauyau filter: first {what} row: step {step} (t = {t:g}): {reason}", file=sys.stderr)
        if self.first_alarm is not None:
            step, t, value = self.first_alarm
            side = "above" if value > 0 else "below"
            print(f"yauyau filter: innovation monitor: {self.alarms} alarm(s), the first at step {step} "
                  f"(t = {t:g}): the observations have drifted {side} their predictions (a sensor bias, or a "
                  "model that does not fit): columns alarm and monitor", file=sys.stderr)
        elif monitor > 0:
            print(f"yauyau filter: innovation monitor: no alarm ({monitor:,.0f} healthy rows per false "
                  "alarm)", file=sys.stderr)


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
        if self.density is not None and Path(self.density).suffix.lower() not in (".h5", ".hdf5"):
            raise InputError("density", f"{self.density}: the density file is HDF5, name it *.h5")
        if self.density is not None and model.spec.domain.follow:
            raise InputError("density", "the ball follows the state ([domain] follow = true), so no fixed "
                                        "grid holds the density; leave --density out (the mean, covariance "
                                        "and --quantiles columns follow it)")
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


def filter_rows(flt, increments, chunk: int, outputs: Outputs | None = None, writer=None, bar=None, *,
                times=None, state=None, policy: str = "stop", watch=None):
    """The output lines (CSV text, one per row: step, t, means, upper-triangle covariances[, modes,
    quantiles], loglik, degenerate, gated, predictive_loglik, reinitialised, alarm, monitor) and the
    :class:`Report` of the run.  ``times`` (K,) or None (regular), from ``state`` (default: the filter's
    initial state), under the ``on_degenerate`` ``policy`` and the ``watch`` settings (solver/watch.py;
    None: the defaults and the spec's monitor)."""
    from yauyau.solver.summarised import summarised_rows
    from yauyau.solver.watch import Watch, settings_for, watched_run

    outputs = outputs or Outputs()
    state = flt.initial_state() if state is None else state
    settings = settings_for(flt) if watch is None else watch
    monitored = settings.monitor > 0  # its two columns only when it is on
    seen = Watch()
    gate = getattr(flt, "gate", None)
    lines: list[str] = []
    report = Report()
    if writer is not None:
        snapshot(flt, state, flt.estimate(state), outputs, writer)  # the prior, at t0
    for start in range(0, len(increments), chunk):
        stop = min(start + chunk, len(increments))
        if outputs.per_step:  # one row at a time: the density after each is summarised (or drawn)
            for row in summarised_rows(flt, state, seen, increments[start:stop],
                                       None if times is None else times[start:stop], policy, settings,
                                       mode=outputs.mode, probs=outputs.probs):
                state, seen = row.state, row.watch
                lines += csv_lines(row.result, [summary_columns(flt, row, outputs, writer)], monitored)
                report.add(row.result, gate)
        else:
            state, seen, result = watched_run(flt, state, seen, increments[start:stop],
                                              None if times is None else times[start:stop], policy, settings)
            lines += csv_lines(result, monitor=monitored)
            report.add(result, gate)
        if bar is not None:
            bar.update(stop - start)
    return lines, report


def summary_columns(flt, row, outputs: Outputs, writer) -> list:
    """Mode and quantile columns of one step (a :class:`yauyau.solver.summarised.SummarisedRow`; empty
    fields when degenerate); a density snapshot every ``outputs.every`` steps."""
    n = flt.model.n
    extra: list = []
    if outputs.mode:
        extra += [float(v) for v in row.mode] if row.mode is not None else [""] * n
    if outputs.probs is not None:
        q, blank = row.quantiles, [""] * len(outputs.probs)
        for i in range(n):
            extra += [float(v) if v == v else "" for v in q[i]] if q is not None else blank
    estimate = row.estimate
    if writer is not None and not estimate.degenerate and int(estimate.step) % outputs.every == 0:
        snapshot(flt, row.state, estimate, outputs, writer)
    return extra


def snapshot(flt, state, estimate, outputs: Outputs, writer) -> None:
    """The marginals (and the joint density in 1-D and 2-D) on the output grid, into the file."""
    from yauyau.solver import summaries

    marginals = summaries.marginals_on_grid(flt, state, outputs.axes, estimate)
    joint = summaries.joint_on_grid(flt, state, outputs.axes) if flt.model.n <= 2 else None
    writer.append(int(estimate.step), float(estimate.t), marginals, joint)


def header(model, outputs: Outputs | None = None, follow: bool = False, monitor: bool = False) -> list[str]:
    """The CSV columns; ``follow`` (a ball that follows the state): center_<var> and recentred last."""
    outputs = outputs or Outputs()
    names = model.spec.state
    n = len(names)
    cov = [f"cov_{names[i]}_{names[j]}" for i in range(n) for j in range(i, n)]
    extra = [f"mode_{v}" for v in names] if outputs.mode else []
    if outputs.probs is not None:
        extra += [f"q{p}_{v}" for v in names for p in outputs.probs_text]
    tail = [*[f"center_{v}" for v in names], "recentred"] if follow else []
    watched = ["alarm", "monitor"] if monitor else []
    return ["step", "t", *[f"mean_{v}" for v in names], *cov, *extra, "loglik", "degenerate", "gated",
            "predictive_loglik", "reinitialised", *watched, *tail]


