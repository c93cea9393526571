"""Parsing the points of a density request: an explicit list or a product grid."""

from __future__ import annotations

import math

import numpy as np
from yauyau.solver.errors import InputError


def _number(text: str, field: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise InputError(field, f"{text.strip()[:40]!r} is not a number") from None
    if not math.isfinite(value):
        raise InputError(field, "coordinates must be finite")
    return value


def _explicit(points: str) -> np.ndarray:
    rows = [[_number(c, "points") for c in p.split(",")] for p in points.split(";") if p.strip()]
    if not rows:
        raise InputError("points", "no points given")
    if len({len(r) for r in rows}) != 1:
        raise InputError("points", "every point needs the same number of coordinates")
    return np.asarray(rows, dtype=float)


def _grid(grid: str, max_points: int) -> np.ndarray:
    axes = []
    for i, part in enumerate(grid.split(",")):
        bits = part.split(":")
        if len(bits) != 3:
            raise InputError("grid", f"axis {i}: expected 'lo:hi:count', got {part.strip()[:40]!r}")
        lo, hi = _number(bits[0], "grid"), _number(bits[1], "grid")
        count = _number(bits[2], "grid")
        if count != int(count) or not 1 <= count <= max_points:
            raise InputError("grid", f"axis {i}: count must be an integer in 1..{max_points}")
        axes.append(np.linspace(lo, hi, int(count)))
    total = math.prod(len(a) for a in axes)
    if total > max_points:
        raise InputError("grid", f"{total} points, at most {max_points}")
    mesh = np.meshgrid(*axes, indexing="ij")
    return np.stack([m.ravel() for m in mesh], axis=1)


def parse_points(points: str | None, grid: str | None, max_points: int) -> np.ndarray:
    """(P, d) points from ``points='x,y;x,y'`` or ``grid='lo:hi:count,...'`` (exactly one of them)."""
    if (points is None) == (grid is None):
        raise InputError("points", "give exactly one of 'points' or 'grid'")
    return _explicit(points) if points is not None else _grid(grid, max_points)
