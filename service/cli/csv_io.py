"""The CSV files of ``yauyau filter`` and ``yauyau simulate``: the rows read (--increments as CSV or
.npy, --observations with their times), the estimates written (column by column from a chunk's
arrays), every file written atomically.

A bad file is an InputError naming the row (``increments[k]``, ``observations[k][j]``, ``times[k]``)
and its line.  numpy, orjson and the solver's checks are imported inside the functions, as in every
command module: ``yauyau -h`` and ``yauyau filter -h`` import this module and stay cheap.
"""

from __future__ import annotations

import math
import os
from pathlib import Path

from yauyau.solver.errors import InputError
from yauyau.storage.files import temporary_beside


class Source:
    """The rows read from --increments or --observations: ``rows`` (K, m) (NaN: missing), ``times``
    (K,) or None (regular), the prior's time ``t0``, and ``field``/``lines`` to name a row at fault."""
    def __init__(self, rows, times, t0: float, field: str, lines=None):
        self.rows = rows
        self.times = times
        self.t0 = t0
        self.field = field
        self.lines = lines  # the file's line number of each row (CSV), else None

    def where(self, k: int) -> str:
        """``field[k]`` with the line number when the rows came from a CSV."""
        line = f" (line {self.lines[k]})" if self.lines is not None and k < len(self.lines) else ""
        return f"{self.field}[{k}]{line}"


def read_increments(path: str, m: int, numbers: list[int] | None = None):
    """(K, m) floats from .npy or CSV; NaN is a missing component, a NaN row a missing observation.
    ``numbers`` (a list) receives each row's line number in a CSV."""
    import numpy as np
    from yauyau.solver.measurement import check_rows

    if Path(path).suffix.lower() == ".npy":
        try:
            data = np.load(path, allow_pickle=False)
        except (OSError, ValueError) as exc:
            raise InputError("increments", f"cannot read {path}: {exc}") from None
        if data.dtype.kind not in "iuf":
            raise InputError("increments", f"{path} must hold numbers, not {data.dtype}")
        return check_rows(data, m)
    try:
        text = Path(path).read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError("increments", f"cannot read {path}: {exc}") from None
    check_untimed(text, path)
    return check_rows(parse_csv(text, m, numbers), m)


def check_untimed(text: str, path: str) -> None:
    """InputError naming --observations when the CSV given to --increments is a timed one (a header whose
    first column is t, the format --observations reads): its times would be read as increments."""
    first = text.partition("\n")[0].split(",")
    if first[0].strip().strip('"').strip().lower() == "t":
        raise InputError("increments", f"{path} has a time column (header {first[0].strip()!r}, ...): "
                                       f"rows with their own times go to --observations {path} (add --t0 0 "
                                       "for the files of yauyau simulate); --increments reads regular rows, "
                                       "m numbers each")


def parse_csv(text: str, m: int, numbers: list[int] | None = None) -> list[list[float]]:
    """Rows of m fields; an empty field is a missing component (NaN), a blank line a missing
    observation (a NaN row); the first line is a header when none of its fields is a number (a first
    line with some numbers is data, and a bad field in it an error: never silently shift every step
    by one); blank lines at the end are ignored.  ``numbers`` receives each row's line number."""
    fast = parse_plain(text, m, numbers)
    if fast is not None:
        return fast
    lines = text.splitlines()
    while lines and not lines[-1].strip():
        lines.pop()
    rows: list[list[float]] = []
    nan = math.nan
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
                raise InputError(f"{where}[{j}]", f"line {number}: {field[:40]!r} is not a finite number "
                                                  "(leave the field empty for a missing value)")
        rows.append([nan if v == "" else v for v in values])
        if numbers is not None:
            numbers.append(number)
    return rows


def parse_plain(text: str, m: int, numbers: list[int] | None):
    """The usual file — m finite numbers on every line, an optional header of names — parsed by numpy
    at C speed: a (K, m) array, or None for anything else (blank lines, empty fields, a bad field),
    which :func:`parse_csv` then reads line by line, naming what is wrong."""
    import numpy as np

    body = text.rstrip()
    first, _, rest = body.partition("\n")
    skip = 0
    if first and all(_number(f.strip()) is None for f in first.split(",")):
        body, skip = rest, 1  # a header
    if not body or "\n\n" in body or "\r" in body:
        return None
    fields = body.replace("\n", ",").split(",")
    if len(fields) % m:
        return None
    try:
        values = np.array(fields, dtype=float).reshape(-1, m)
    except ValueError:
        return None
    if not np.isfinite(values).all() or values.shape[0] != body.count("\n") + 1:
        return None  # nan/inf spelled out, or a line with the wrong number of fields
    if numbers is not None:
        numbers.extend(range(1 + skip, 1 + skip + len(values)))
    return values


def read_observations(path: str, m: int, kind: str, t0: float | None) -> Source:
    """The rows and times of an --observations CSV (EPILOG); InputError names the row (observations[k],
    times[k], with the line number) or the file at fault."""
    import numpy as np

    if Path(path).suffix.lower() == ".npy":
        raise InputError("observations", f"{path}: --observations reads a CSV with a header t,<one column "
                                          "per component>; a .npy array of regular rows goes to --increments")
    try:
        text = Path(path).read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError("observations", f"cannot read {path}: {exc}") from None
    lines = text.splitlines()
    while lines and not lines[-1].strip():
        lines.pop()
    example = "t," + ",".join(f"z_{j + 1}" for j in range(m))
    if not lines:
        raise InputError("observations", f"{path} is empty: expected a header {example!r} and one row per "
                                          "time")
    names = [f.strip().strip('"').strip() for f in lines[0].split(",")]
    if names[0].lower() != "t":
        got = "a row of numbers" if _number(names[0]) not in (None, "") else f"{names[0][:40]!r}"
        raise InputError("observations", f"{path} line 1: the header must start with the time column t "
                                          f"(then one column per component, e.g. {example!r}); its first "
                                          f"field is {got}")
    if len(names) - 1 != m:
        raise InputError("observations", f"{path} has {len(names) - 1} column(s) after t "
                                          f"({','.join(names[1:]) or 'none'}); the model has m = {m} "
                                          f"observation component(s): expected t and {m} column(s), e.g. "
                                          f"{example!r}")
    width = m + 1
    times: list[float] = []
    rows: list[list[float]] = []
    numbers: list[int] = []
    nan = math.nan
    previous = -math.inf
    for number, line in enumerate(lines[1:], start=2):
        k = len(rows)
        if not line.strip():
            raise InputError(f"times[{k}]", f"{path} line {number}: a blank line has no time t; a row with "
                                            "its time and empty fields (e.g. '1.5,') is a time with nothing "
                                            "observed")
        fields = [f.strip() for f in line.split(",")]
        if len(fields) != width:
            raise InputError(f"observations[{k}]", f"{path} line {number}: expected {width} fields (t and "
                                                   f"{m} component(s)), got {len(fields)}")
        t = _number(fields[0])
        if t is None or t == "":
            raise InputError(f"times[{k}]", f"{path} line {number}: t = {fields[0][:40]!r} is not a finite "
                                            "number (every row needs its time)")
        if t <= previous:
            raise InputError(f"times[{k}]", f"{path} line {number}: t = {t!r} is not after t = {previous!r} "
                                            f"(line {number - 1}): times must increase strictly")
        if previous > -math.inf:
            _check_gap(path, number, k, previous, t)
        values = [_number(f) for f in fields[1:]]
        for j, (field, value) in enumerate(zip(fields[1:], values, strict=True)):
            if value is None:
                raise InputError(f"observations[{k}][{j}]", f"{path} line {number}: {field[:40]!r} is not "
                                                            "a finite number (leave the field empty for a "
                                                            "missing component)")
        previous = t
        times.append(t)
        rows.append([nan if v == "" else v for v in values])
        numbers.append(number)
    if not rows:
        raise InputError("observations", f"{path} has a header and no rows: one row per observation time")
    start = times[0] if t0 is None else float(t0)
    if times[0] > start:
        _check_gap(path, 2, 0, start, times[0], "--t0")
    if times[0] < start:
        raise InputError("times[0]", f"{path} line 2: t = {times[0]!r} is before --t0 {start!r}: the first "
                                     "row must be at or after the time of the prior")
    data = np.array(rows, dtype=float).reshape(len(rows), m)
    if kind == "continuous" and times[0] == start:
        raise InputError("observations[0]", f"{path} line 2: an increment of a continuous model covers "
                                            f"[t_(k-1), t_k], and the first row's t = {times[0]!r} is the "
                                            "prior's time, an empty interval: give --t0 (the start of the "
                                            "first interval, e.g. --t0 0 for the files of yauyau simulate)")
    return Source(data, np.array(times, dtype=float), start, "observations", numbers)


def _check_gap(path: str, number: int, k: int, before: float, t: float, what: str | None = None) -> None:
    """InputError naming times[k] (line ``number``) when t is too close to the time before it to keep the
    gap's precision (yauyau.solver.measurement.check_spacing)."""
    from yauyau.solver.measurement import check_spacing

    try:
        check_spacing(max(abs(before), abs(t)), t - before, f"times[{k}]", "t")
    except InputError as exc:
        after = what or f"t = {before!r} (line {number - 1})"
        raise InputError(exc.field, f"{path} line {number}: t = {t!r} is {t - before:.3g} after {after}: "
                                    f"{exc.message}") from None


def _number(field: str):
    """A finite float, "" for an empty field, None for anything else (nan/inf included)."""
    if field == "":
        return ""
    try:
        value = float(field)
    except ValueError:
        return None
    return value if math.isfinite(value) else None


def csv_lines(result, extras: list[list] | None = None, monitor: bool = False) -> list[str]:
    """The CSV lines of a chunk's result, column by column from its arrays (``extras``: the mode and
    quantile fields of each row, between the covariances and loglik; ``monitor``: with the innovation
    monitor's alarm and statistic after reinitialised)."""
    import numpy as np

    n = result.mean.shape[1]
    i, j = np.triu_indices(n)
    if extras is None and not np.isinf(result.predictive_loglik).any() and not np.isinf(result.loglik).any():
        return fast_lines(result, i, j, monitor)  # (orjson would write an infinity as an empty field)
    head = zip(result.step.tolist(), result.t.tolist(), *result.mean.T.tolist(),
               *result.cov[:, i, j].T.tolist(), strict=True)
    pll = ["" if v != v else repr(v) for v in result.predictive_loglik.tolist()]
    follow = ([] if result.center is None
              else [*result.center.T.tolist(), result.recentred.astype(int).tolist()])
    statistic = ["" if v != v else repr(v) for v in result.monitor.tolist()] if monitor else []
    watched = [result.alarm.astype(int).tolist(), statistic] if monitor else []
    tail = zip(result.loglik.tolist(), result.degenerate.astype(int).tolist(),
               result.gated.astype(int).tolist(), pll, result.reinitialised.astype(int).tolist(), *watched,
               *follow, strict=True)
    if extras is None:
        return [",".join(map(_field, (*a, *b))) for a, b in zip(head, tail, strict=True)]
    return [",".join(map(_field, (*a, *x, *b))) for a, x, b in zip(head, extras, tail, strict=True)]


def fast_lines(result, i, j, monitor: bool = False) -> list[str]:
    """:func:`csv_lines` without extras, formatted by orjson in one call (shortest round-trip floats,
    as repr gives them; NaN, i.e. not known, as an empty field)."""
    import numpy as np
    import orjson

    K = len(result.step)
    if not K:
        return []
    columns = [result.step.astype(float), result.t, *result.mean.T, *result.cov[:, i, j].T, result.loglik,
               result.degenerate.astype(float), result.gated.astype(float), result.predictive_loglik,
               result.reinitialised.astype(float)]
    flags = [0, len(columns) - 4, len(columns) - 3, len(columns) - 1]  # integers: step and the flags
    if monitor:  # the innovation monitor's alarm (an integer) and statistic
        columns += [result.alarm.astype(float), result.monitor]
        flags.append(len(columns) - 2)
    if result.center is not None:  # a following ball: its centre after the row, and whether it moved
        columns += [*result.center.T, result.recentred.astype(float)]
        flags.append(len(columns) - 1)
    table = np.column_stack(columns)
    rows = table.tolist()
    for row in rows:
        for c in flags:
            row[c] = int(row[c])
    text = orjson.dumps(rows).decode()
    return text[2:-2].replace("null", "").split("],[")


def _field(value) -> str:
    """A CSV field: NaN (not known) as an empty field, everything else as Python writes it."""
    return "" if value != value else str(value)


def write_lines(path: str, columns: list[str], lines: list[str], field: str = "out") -> None:
    """Write the header and the lines atomically (temporary file in the same directory, then rename); the
    file gets the user's umask (storage.files)."""
    target = Path(path)
    try:
        tmp = temporary_beside(target, ".csv")
    except OSError as exc:
        raise InputError(field, f"cannot write {path}: {exc}") from None
    try:
        with open(tmp, "w", encoding="utf-8", newline="") as out:
            out.write(",".join(columns) + "\n")
            for start in range(0, len(lines), 10_000):
                out.write("\n".join(lines[start:start + 10_000]) + "\n")
        os.replace(tmp, target)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def write_csv(path: str, columns: list[str], rows: list[list], field: str = "out") -> None:
    """Rows of values (floats as repr, NaN as an empty field), written atomically."""
    lines = [",".join("" if isinstance(v, float) and v != v else str(v) for v in row) for row in rows]
    write_lines(path, columns, lines, field)
