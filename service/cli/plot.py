"""`yauyau plot OUT.csv [--smoothed S.csv] [--truth TRUTH.csv] [--density D.h5] --out FIG.png`: look at a run
(`yauyau plot FIT.json --out FIG.png`: a fit's profile log-likelihood, service/cli/plot_fit.py).

One row of panels per state variable: the conditional mean against time with a 95% band (the
marginal quantiles q0.025/q0.975 when OUT.csv has them, else mean ± 1.96 sd), the truth overlaid
(`yauyau simulate` writes it), rows the outlier gate rejected marked x on the mean (column gated),
re-initialisations as dotted vertical lines (column reinitialised), degenerate rows shaded, and
with --density the marginal density as a heat map over time with the mean and truth on top.  With
--smoothed S.csv (`yauyau smooth --out S.csv` over the same rows) the smoothed mean and its 95% band are
drawn on the same panels, in red beside the filtered blue, each labelled; its rows must be OUT.csv's
(same count, same t) and its variables the same.  PNG or SVG by the suffix of --out (matplotlib, no
screen needed).
"""

from __future__ import annotations

import argparse
import csv
import math
from pathlib import Path

FORMATS = (".png", ".svg")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("estimates", metavar="OUT.csv",
                        help="output of yauyau filter, or FIT.json of yauyau fit --profile NAME --json (its "
                             "profile is drawn)")
    parser.add_argument("--smoothed", default=None, metavar="S.csv",
                        help="output of yauyau smooth over the same rows: its mean and 95%% band drawn "
                             "beside the filtered ones")
    parser.add_argument("--truth", default=None, metavar="TRUTH.csv", help="truth.csv of yauyau simulate")
    parser.add_argument("--density", default=None, metavar="D.h5",
                        help="density file of yauyau filter --density")
    parser.add_argument("--out", required=True, metavar="FIG.png", help="figure file (.png or .svg)")
    parser.add_argument("--title", default=None, help="figure title (default: the file names)")


def read_table(path: str, field: str) -> dict[str, list[float]]:
    """Columns of a CSV with a header; empty fields are NaN."""
    from yauyau.solver.errors import InputError

    try:
        with open(path, encoding="utf-8", newline="") as fh:
            rows = list(csv.reader(fh))
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(field, f"cannot read {path}: {exc}") from None
    if len(rows) < 2:
        raise InputError(field, f"{path}: a header and at least one row are needed")
    header = [h.strip() for h in rows[0]]
    columns: dict[str, list[float]] = {h: [] for h in header}
    for number, row in enumerate(rows[1:], start=2):
        if len(row) != len(header):
            raise InputError(field, f"{path} line {number}: expected {len(header)} fields, got {len(row)}")
        for name, text in zip(header, row, strict=True):
            try:
                columns[name].append(float(text) if text.strip() else math.nan)
            except ValueError:
                raise InputError(field, f"{path} line {number}, column {name}: {text[:40]!r} is not a "
                                        "number") from None
    return columns


def variables(columns: dict[str, list[float]], path: str, field: str = "estimates") -> list[str]:
    from yauyau.solver.errors import InputError

    names = [c[len("mean_"):] for c in columns if c.startswith("mean_")]
    if not names or "t" not in columns:
        command = "smooth" if field == "smoothed" else "filter"
        raise InputError(field, f"{path} has no t and mean_<var> columns: is it the output of "
                                f"yauyau {command}?")
    for var in names:
        quantiles = f"q0.025_{var}" in columns and f"q0.975_{var}" in columns
        has_band = f"cov_{var}_{var}" in columns or quantiles
        if not has_band:
            raise InputError(field, f"{path} has mean_{var} but neither cov_{var}_{var} nor q0.025_{var} and "
                                    f"q0.975_{var}: no band to draw")
    return names


def check_smoothed(estimates: dict, names: list[str], smoothed: dict, path: str) -> None:
    """The smoothed file must cover the filtered file's rows: same variables, same row count, same t."""
    import numpy as np
    from yauyau.solver.errors import InputError

    theirs = variables(smoothed, path, "smoothed")
    if theirs != names:
        raise InputError("smoothed", f"{path} has the variables {theirs}, the filtered file {names}")
    if len(smoothed["t"]) != len(estimates["t"]):
        raise InputError("smoothed", f"{path} has {len(smoothed['t'])} rows, the filtered file "
                                     f"{len(estimates['t'])}: smooth the same rows")
    a, b = np.array(estimates["t"]), np.array(smoothed["t"])
    differ = ~np.isclose(a, b, rtol=1e-9, atol=1e-12)
    if differ.any():
        k = int(np.argmax(differ))
        raise InputError("smoothed", f"{path} row {k + 1}: t = {b[k]!r}, the filtered file's t = {a[k]!r}: "
                                     "smooth the same rows")


def band(columns: dict[str, list[float]], var: str):
    """(low, high, label) of the 95% band of ``var``."""
    import numpy as np

    lo, hi = columns.get(f"q0.025_{var}"), columns.get(f"q0.975_{var}")
    if lo is not None and hi is not None:
        return np.array(lo), np.array(hi), "95% band (quantiles)"
    mean = np.array(columns[f"mean_{var}"])
    sd = np.sqrt(np.clip(np.array(columns[f"cov_{var}_{var}"]), 0.0, None))
    return mean - 1.96 * sd, mean + 1.96 * sd, "mean ± 1.96 sd"


def draw(estimates: dict, names: list[str], truth: dict | None, density, title: str,
         smoothed: dict | None = None):
    """The figure (matplotlib Figure, Agg canvas); ``smoothed`` (checked by check_smoothed) adds the
    smoothed mean and band in red."""
    import numpy as np
    from matplotlib.figure import Figure

    n = len(names)
    ncols = 2 if density is not None else 1
    fig = Figure(figsize=(6.4 * ncols, 2.6 * n + 0.6), layout="constrained")
    axes = np.atleast_2d(fig.subplots(n, ncols, squeeze=False))
    t = np.array(estimates["t"])
    bad = _flags(estimates, "degenerate", len(t))
    gated = _flags(estimates, "gated", len(t))  # yauyau filter's outlier gate: marked x
    again = _flags(estimates, "reinitialised", len(t))  # --on-degenerate reinitialise: a dotted line
    for i, var in enumerate(names):
        ax = axes[i, 0]
        mean = np.array(estimates[f"mean_{var}"])
        low, high, label = band(estimates, var)
        which = "filtered " if smoothed is not None else ""
        ax.fill_between(t, low, high, color="tab:blue", alpha=0.25, linewidth=0, label=which + label)
        ax.plot(t, mean, color="tab:blue", linewidth=1.2, label=which + "conditional mean")
        if smoothed is not None:
            s_low, s_high, s_label = band(smoothed, var)
            ax.fill_between(t, s_low, s_high, color="tab:red", alpha=0.2, linewidth=0,
                            label="smoothed " + s_label)
            ax.plot(t, smoothed[f"mean_{var}"], color="tab:red", linewidth=1.2, label="smoothed mean")
        if f"mode_{var}" in estimates:
            ax.plot(t, estimates[f"mode_{var}"], color="tab:green", linewidth=0.8, label="mode")
        if truth is not None and var in truth:
            ax.plot(truth["t"], truth[var], color="black", linewidth=0.9, label="truth")
        if bad.any():
            ax.axvspan(t[np.argmax(bad)], t[-1], color="tab:red", alpha=0.12, label="degenerate")
        if gated.any():
            ax.plot(t[gated], mean[gated], linestyle="none", marker="x", markersize=5, color="tab:orange",
                    label=f"gated ({int(gated.sum())})")
        for k, when in enumerate(t[again]):
            ax.axvline(when, color="tab:purple", linewidth=0.8, linestyle=":",
                       label=f"re-initialised ({int(again.sum())})" if k == 0 else None)
        ax.set_ylabel(var)
        ax.legend(loc="upper right", fontsize="small", ncols=2)
        if density is not None:
            _heat_map(axes[i, 1], density, var, t, mean, truth)
    for ax in axes[-1]:
        ax.set_xlabel("t")
    fig.suptitle(title, fontsize="medium")
    return fig


def _flags(columns: dict[str, list[float]], name: str, count: int):
    """A 0/1 column as booleans (all False when the file has no such column: older outputs)."""
    import numpy as np

    values = np.array(columns.get(name, [0.0] * count))
    return np.nan_to_num(values) > 0


def _edges(times):
    """Cell edges around the snapshot times (midpoints: the times may be irregular)."""
    import numpy as np

    if len(times) == 1:
        return np.array([times[0] - 0.5, times[0] + 0.5])
    middle = 0.5 * (times[1:] + times[:-1])
    return np.concatenate([[times[0] - (middle[0] - times[0])], middle,
                           [times[-1] + (times[-1] - middle[-1])]])


def _heat_map(ax, density, var, t, mean, truth) -> None:
    import numpy as np
    from yauyau.solver.errors import InputError

    if var not in density.state:
        raise InputError("density", f"the density file has no variable {var!r} (it has {density.state})")
    k = density.state.index(var)
    grid, values = density.axes[k], density.marginals[k]
    edges_t = _edges(np.asarray(density.time, dtype=float))
    dx = grid[1] - grid[0]
    edges_x = np.concatenate([grid - dx / 2, [grid[-1] + dx / 2]])
    mesh = ax.pcolormesh(edges_t, edges_x, values.T, shading="flat", cmap="magma", rasterized=True)
    ax.figure.colorbar(mesh, ax=ax, label=f"p({var} | y)")
    ax.plot(t, mean, color="tab:cyan", linewidth=0.9, label="mean")
    if truth is not None and var in truth:
        ax.plot(truth["t"], truth[var], color="white", linewidth=0.8, linestyle="--", label="truth")
    ax.set_ylabel(var)
    ax.set_ylim(_focus(grid, values))
    ax.legend(loc="upper right", fontsize="small")


def _focus(grid, values):
    """The part of the grid that holds the density (quantiles 1e-4 .. 1 − 1e-4 of the time-summed
    marginal, padded), so that a narrow posterior in a wide ball is visible."""
    import numpy as np

    total = values.sum(axis=0)
    cdf = np.cumsum(total)
    if not cdf[-1] > 0:
        return grid[0], grid[-1]
    cdf /= cdf[-1]
    lo, hi = grid[np.searchsorted(cdf, 1e-4)], grid[min(np.searchsorted(cdf, 1 - 1e-4), len(grid) - 1)]
    pad = 0.1 * (hi - lo) + (grid[1] - grid[0])
    return max(grid[0], lo - pad), min(grid[-1], hi + pad)


def run(args: argparse.Namespace) -> int:
    import matplotlib

    matplotlib.use("Agg")
    from yauyau.solver.errors import InputError

    out = Path(args.out)
    if out.suffix.lower() not in FORMATS:
        raise InputError("out", f"{out.name}: give a .png or .svg file name")
    if Path(args.estimates).suffix.lower() == ".json":  # yauyau fit --profile NAME --json: its profile
        from .plot_fit import run as plot_fit

        return plot_fit(args, out)
    estimates = read_table(args.estimates, "estimates")
    names = variables(estimates, args.estimates)
    smoothed = None
    if args.smoothed:
        smoothed = read_table(args.smoothed, "smoothed")
        check_smoothed(estimates, names, smoothed, args.smoothed)
    truth = read_table(args.truth, "truth") if args.truth else None
    if truth is not None and "t" not in truth:
        raise InputError("truth", f"{args.truth} has no t column: is it the truth.csv of yauyau simulate?")
    density = None
    if args.density:
        from yauyau.storage.density_file import read_density

        density = read_density(args.density)
    title = args.title or " · ".join(Path(p).name for p in (args.estimates, args.smoothed, args.truth,
                                                           args.density) if p)
    from .plot_fit import save

    return save(draw(estimates, names, truth, density, title, smoothed), out)
