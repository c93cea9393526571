"""`yauyau fit SPEC (--increments IN | --observations IN.csv) --free NAME=LO:HI [--free ...] [--t0 T]
[--json] [--out FITTED.toml] [--profile NAME] [--workers K | --scheduler ADDR]`: maximum-likelihood
estimates of a spec's parameters from a record (yauyau.solver.fitting, issue 39).

Free names are entries of the spec's ``parameters`` table and ``observation_noise[i][i]`` /
``diffusion[i][i]``; the spec's values start.  Exit 0 when the optimiser converged, 1 when not (the
reason on stderr: the optimiser stopped, the likelihood is flat in a name or not finite somewhere), 2
for bad input naming the field (nothing written).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys

from yauyau.solver.errors import InputError

from .csv_io import Source, read_increments, read_observations

EPILOG = """\
input as for `yauyau filter`: --increments IN (regular rows, continuous models) or --observations
  IN.csv (header t,<components>). --free NAME=LO:HI, once per free name: a parameter of the spec's
  parameters table, observation_noise[i][i] or diffusion[i][i] (a variance: LO > 0); the spec's
  value must lie in [LO, HI].

output: a table (estimate, standard error from the observed information, bounds hit, log-likelihood,
  evaluations, time), or with --json exactly {"estimates", "stderr", "loglik", "evaluations",
  "converged", "method"}, plus "profile": {"name", "grid", "loglik"} only with --profile NAME (the
  profile log-likelihood of NAME on 21 points of its box, the other free names re-maximised; `yauyau
  plot FIT.json --out FIG.png` draws it); --out FITTED.toml (or .json) writes the spec with the fitted
  values (only when converged).

parallel: a free name entering the drift or the diffusion recomputes the offline stage at every
  evaluation; with --workers K (> 1: a local Dask cluster of K processes) or --scheduler tcp://HOST:PORT
  the evaluations that do not wait on each other (the finite-difference gradient's points, the
  Hessian's, the profile's grid) run on Dask, as `yauyau precompute --workers` does; the optimiser and
  its answer are the same. Other fits (milliseconds per evaluation) stay in this process.

exit status: 0 converged; 1 not converged, saying why on stderr: the optimiser stopped, the likelihood
  is flat in a free name at the optimum (the record does not determine it there: the name is given),
  or not finite / refused by the filter somewhere the optimiser went; 2 bad input (the field named,
  nothing written): a free name not in the spec or used by no expression, LO >= HI, a variance bound
  <= 0, the spec's value outside the box, too few rows for the free names.
"""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("spec", help="model spec (.toml or .json)")
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument("--increments", metavar="IN", help="regular rows (continuous models), .csv or .npy")
    source.add_argument("--observations", metavar="IN.csv",
                        help="rows with their times: header t,<components>")
    parser.add_argument("--free", action="append", required=True, metavar="NAME=LO:HI",
                        help="a free name and its box (repeat for each)")
    parser.add_argument("--t0", type=float, default=None, metavar="T",
                        help="time of the prior (default: as yauyau filter)")
    parser.add_argument("--json", action="store_true", help="print the result as JSON")
    parser.add_argument("--out", default=None, metavar="FITTED.toml", help="write the fitted spec")
    parser.add_argument("--profile", default=None, metavar="NAME",
                        help="also compute the profile log-likelihood of this free name (adds \"profile\" to "
                             "--json; draw it with yauyau plot FIT.json)")
    parser.add_argument("--workers", type=int, default=None, metavar="K",
                        help="local Dask worker processes for the evaluations of a fit that recomputes the "
                             "offline stage (default 1: in this process)")
    parser.add_argument("--scheduler", default=None, metavar="tcp://HOST:PORT",
                        help="run those evaluations on this running Dask cluster instead")
    parser.epilog = EPILOG
    parser.formatter_class = argparse.RawDescriptionHelpFormatter


def parse_free(items: list[str]) -> dict[str, tuple[float, float]]:
    """--free NAME=LO:HI, each; InputError('free.NAME' or 'free')."""
    out: dict[str, tuple[float, float]] = {}
    for item in items:
        name, eq, box = item.partition("=")
        name = name.strip()
        if not eq or not name:
            raise InputError("free", f"must be NAME=LO:HI, got {item!r}")
        lo, colon, hi = box.partition(":")
        try:
            bounds = (float(lo), float(hi))
        except ValueError:
            bounds = None
        if not colon or bounds is None or not all(math.isfinite(b) for b in bounds):
            raise InputError(f"free.{name}", f"must be NAME=LO:HI with finite numbers, got {item!r}")
        if name in out:
            raise InputError(f"free.{name}", "is given twice")
        out[name] = bounds
    return out


def run(args: argparse.Namespace) -> int:
    from yauyau.solver.filtering import check_t0
    from yauyau.solver.fitting import fit
    from yauyau.solver.spec import load_spec

    free = parse_free(args.free)
    if args.t0 is not None and not math.isfinite(args.t0):
        raise InputError("t0", "must be a finite number (the time at which the model's prior holds)")
    spec = load_spec(args.spec)
    kind = spec.measurement.kind
    if args.observations is not None:
        source = read_observations(args.observations, spec.m, kind, args.t0)
    else:
        if kind == "discrete":
            raise InputError("increments", "the spec has discrete measurements: give them with their times, "
                                           "--observations IN.csv")
        t0 = 0.0 if args.t0 is None else check_t0(float(args.t0), "t0", float(spec.discretization.dt), "--t0")
        source = Source(read_increments(args.increments, spec.m), None, t0, "increments")
    if args.workers is not None and args.workers < 1:
        raise InputError("workers", "must be a positive integer")
    result = fit(spec, source.rows, source.times, free, args.profile, t0=source.t0, workers=args.workers,
                 scheduler=args.scheduler)
    if result.note:
        print(f"yauyau fit: {result.note}", file=sys.stderr)
    if args.out is not None and result.spec is not None and result.converged:
        write_spec(args.out, result.spec)
    if args.json:
        print(json.dumps(result.as_json(profile=args.profile is not None)))
    else:
        print(f"{'name':<24} {'estimate':>14} {'stderr':>12}  bound")
        for name, value in result.estimates.items():
            hit = "hit" if name in result.bounds_hit else ""
            print(f"{name:<24} {value:>14.6g} {result.stderr[name]:>12.4g}  {hit}")
        print(f"loglik {result.loglik:.6f}; {result.evaluations} evaluations; method {result.method}; "
              f"{result.seconds:.1f} s")
    if not result.converged:
        print(f"yauyau fit: not converged: {result.reason}", file=sys.stderr)
        return 1
    return 0


def write_spec(path: str, spec) -> None:
    """The spec as TOML (or JSON for a .json path), checked to read back as the same spec, written
    atomically."""
    from pathlib import Path

    from yauyau.solver.spec import parse_spec_text
    from yauyau.storage.files import temporary_beside

    data = spec.model_dump(mode="json", exclude_none=True)
    is_json = Path(path).suffix.lower() == ".json"
    text = json.dumps(data, indent=2) + "\n" if is_json else toml_text(data)
    if parse_spec_text(text, "json" if is_json else "toml").canonical_json() != spec.canonical_json():
        raise InputError("out", "the fitted spec does not read back as written (please report)")
    try:
        tmp = temporary_beside(path, ".toml")
        try:
            tmp.write_text(text, encoding="utf-8")
            os.replace(tmp, path)
        finally:
            tmp.unlink(missing_ok=True)
    except OSError as exc:
        raise InputError("out", f"cannot write {path}: {exc}") from None


def _value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, float)):
        return repr(v)
    if isinstance(v, str):
        return json.dumps(v)  # JSON's escapes are TOML basic-string escapes
    if isinstance(v, list):
        return "[" + ", ".join(_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{ " + ", ".join(f"{json.dumps(k)} = {_value(x)}" for k, x in v.items()) + " }"
    raise InputError("out", f"cannot write {type(v).__name__} as TOML")


def toml_text(data: dict, prefix: str = "") -> str:
    """TOML of a spec's dict: scalars, arrays and the parameters as inline values, other tables as
    [tables]."""
    lines, tables = [], []
    for key, value in data.items():
        if isinstance(value, dict) and key != "parameters":
            tables.append((key, value))
        else:
            lines.append(f"{json.dumps(key)} = {_value(value)}")
    text = "\n".join(lines) + ("\n" if lines else "")
    for key, value in tables:
        name = f"{prefix}{json.dumps(key)}"
        text += f"\n[{name}]\n" + toml_text(value, name + ".")
    return text
