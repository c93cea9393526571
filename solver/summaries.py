"""What a conditional density says beyond its mean and covariance: marginal quantiles, the mode, and
the density on a grid.

For the x² sensor the mean is 0 and useless (the posterior has two peaks at ±|x|); the mode and the
quantiles of each marginal p_i(x_i) = ∫ p(x) dx_{≠i} are what a user reads.

* Quantile q_p of x_i: the root of F_i(q) = p, F_i the marginal's distribution function.  A filter
  whose density is Gaussian (Kalman–Bucy, EKF/UKF) answers in closed form, m_i + √P_ii Φ⁻¹(p).
  Otherwise the marginal is evaluated on a grid over its support (the ball for the engine, ±12
  standard deviations around the mean for the others), F_i accumulated with the trapezoidal rule,
  and inverted; a second grid over the bracket [q_min, q_max] the first pass found resolves
  posteriors much narrower than the support (errors O(h²) of the finer spacing h).
* Mode (MAP): the engine's density is known at its nodes; the tallest node is refined by a quadratic
  fit of log σ at the nearby nodes (the vertex, kept when it is a maximum inside the neighbourhood:
  the sub-mesh peak of the smooth density the nodes sample).  Another filter's mode is the best
  point of a grid search refined by Nelder–Mead on −log p; a Gaussian filter's is its mean.
* Densities on a grid (for plots and for ``yauyau filter --density``): the joint density in 1-D and
  2-D, and each variable's marginal in every dimension.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

from .errors import InputError

if TYPE_CHECKING:  # types only
    from .filtering import Estimate, Filter, FilterState

FIRST_PASS_POINTS = {1: 513, 2: 257, 3: 129}  # per dimension n: the grid over the support
SECOND_PASS_POINTS = 257  # over the bracket, when the first grid is coarse for the posterior
# A second pass only when the posterior's bracket [q(1e-4), q(1-1e-4)] spans fewer first-pass cells:
# it needs a new marginal operator (cheap in 1-D, ~0.2 s in 2-D), the cached first grid does not.
SPAN_CELLS = 32
RESOLUTION = {2: 64, 3: 32}  # quadrature points per integrated direction
GAUSSIAN_SUPPORT_SD = 12.0


def check_probabilities(probs: Any, field: str = "quantiles") -> np.ndarray:
    """Probabilities strictly between 0 and 1 (a list, or text like '0.05,0.5,0.95')."""
    if isinstance(probs, str):
        parts = [p.strip() for p in probs.split(",") if p.strip()]
        try:
            probs = [float(p) for p in parts]
        except ValueError:
            raise InputError(field, f"must be comma-separated probabilities, got {probs[:60]!r}") from None
    try:
        arr = np.asarray(probs, dtype=float).reshape(-1)
    except (TypeError, ValueError):
        raise InputError(field, "must be a list of probabilities") from None
    if arr.size == 0:
        raise InputError(field, "give at least one probability, e.g. 0.05,0.5,0.95")
    if arr.size > 99:
        raise InputError(field, f"at most 99 probabilities, got {arr.size}")
    if not np.all(np.isfinite(arr)) or np.any(arr <= 0.0) or np.any(arr >= 1.0):
        raise InputError(field, "probabilities must lie strictly between 0 and 1 (e.g. 0.05,0.5,0.95)")
    return arr


def is_gaussian(flt: Filter) -> bool:
    """Whether the filter's density is exactly N(mean, cov)."""
    from .gaussian import GaussianFilter

    return isinstance(flt, GaussianFilter)


def quantiles_from_marginal(grid: np.ndarray, values: np.ndarray, probs: np.ndarray) -> np.ndarray:
    """Quantiles of the density with ``values`` at the increasing ``grid`` (trapezoidal F, inverted
    piecewise linearly).  NaN where the marginal has no positive mass."""
    values = np.clip(np.nan_to_num(np.asarray(values, float), nan=0.0, posinf=0.0), 0.0, None)
    cells = 0.5 * (values[1:] + values[:-1]) * np.diff(grid)
    cdf = np.concatenate([[0.0], np.cumsum(cells)])
    total = cdf[-1]
    if not total > 0.0 or not np.isfinite(total):
        return np.full(len(probs), np.nan)
    cdf /= total
    # F is flat where the density is 0: interpolate on the strictly increasing part.
    keep = np.concatenate([[True], np.diff(cdf) > 0.0])
    return np.interp(probs, cdf[keep], grid[keep])


def support(flt: Filter, state: FilterState, estimate: Estimate, variable: int) -> tuple[float, float]:
    """An interval holding the marginal of ``variable``: the engine's ball, else ±12 sd."""
    model = flt.model
    if getattr(flt, "method", None) == "yau-yau":
        c, r = float(flt.ball_center(state)[variable]), float(model.half_widths[variable])
        return c - r, c + r
    mean = float(estimate.mean[variable])
    sd = float(np.sqrt(max(float(estimate.cov[variable][variable]), 0.0)))
    sd = max(sd, 1e-9 * max(1.0, abs(mean)))
    return mean - GAUSSIAN_SUPPORT_SD * sd, mean + GAUSSIAN_SUPPORT_SD * sd


def marginal(flt: Filter, state: FilterState, variable: int, grid: np.ndarray,
             estimate: Estimate | None = None) -> np.ndarray:
    """The marginal density of ``variable`` at ``grid``: the filter's own, or by quadrature over a
    box of ±12 sd around the mean."""
    from .filtering import marginal_by_quadrature

    if hasattr(flt, "marginal"):
        return np.asarray(flt.marginal(state, variable, grid, RESOLUTION.get(flt.model.n, 16)), dtype=float)
    estimate = flt.estimate(state) if estimate is None else estimate
    n = flt.model.n
    bounds = np.array([support(flt, state, estimate, i) for i in range(n)])
    return marginal_by_quadrature(lambda points: flt.density(state, points), n, variable, grid,
                                  bounds[:, 0], bounds[:, 1], resolution=48)


def quantiles(flt: Filter, state: FilterState, probs: Sequence[float] | np.ndarray,
              estimate: Estimate | None = None) -> np.ndarray:
    """Marginal quantiles (n, len(probs)) of the filter's density in ``state``."""
    from scipy.special import ndtri

    probs = check_probabilities(probs)
    estimate = flt.estimate(state) if estimate is None else estimate
    n = flt.model.n
    if bool(getattr(state, "degenerate", False)):
        return np.full((n, len(probs)), np.nan)
    if is_gaussian(flt):
        mean = np.asarray(estimate.mean, float)
        sd = np.sqrt(np.clip(np.diag(np.asarray(estimate.cov, float)), 0.0, None))
        return mean[:, None] + sd[:, None] * ndtri(probs)[None, :]
    out = np.empty((n, len(probs)))
    for i in range(n):
        lo, hi = support(flt, state, estimate, i)
        grid = np.linspace(lo, hi, FIRST_PASS_POINTS.get(n, 65))
        values = marginal(flt, state, i, grid, estimate)
        ends = np.array([min(probs.min(), 1e-4), max(probs.max(), 1 - 1e-4)])
        found = quantiles_from_marginal(grid, values, np.concatenate([probs, ends]))  # one CDF, both uses
        first, bracket = found[:len(probs)], found[len(probs):]
        if not np.all(np.isfinite(first)):
            out[i] = np.nan
            continue
        h = grid[1] - grid[0]
        a, b = max(lo, bracket[0] - 2 * h), min(hi, bracket[1] + 2 * h)
        if b - a > SPAN_CELLS * h:  # the first grid resolves this posterior: O(h²) is already small
            out[i] = first
            continue
        fine = np.linspace(a, b, SECOND_PASS_POINTS)
        fine_values = marginal(flt, state, i, fine, estimate)
        # F on the fine grid, anchored by the coarse grid's mass outside [a, b].
        coarse_cdf = np.concatenate([[0.0], np.cumsum(0.5 * (values[1:] + values[:-1]) * np.diff(grid))])
        left, inside_b = np.interp([a, b], grid, coarse_cdf) / coarse_cdf[-1]
        span = inside_b - left
        out[i] = quantiles_from_marginal(fine, fine_values, np.clip((probs - left) / span, 0.0, 1.0))
    return out


def summarise(flt: Filter, state: FilterState, estimate: Estimate, want_mode: bool = False,
              probs: np.ndarray | None = None) -> tuple[np.ndarray | None, np.ndarray | None]:
    """(mode (n,), marginal quantiles (n, len(probs))) of the density in ``state`` whose estimate is
    ``estimate``: each None when not asked for (``want_mode`` false, ``probs`` None) or when the
    density is degenerate."""
    healthy = not estimate.degenerate and not bool(getattr(state, "degenerate", False))
    point = mode(flt, state, estimate) if want_mode and healthy else None
    q = quantiles(flt, state, probs, estimate) if probs is not None and healthy else None
    return point, q


# -- the mode -------------------------------------------------------------------------------------
def mode(flt: Filter, state: FilterState, estimate: Estimate | None = None) -> np.ndarray | None:
    """The MAP point of the filter's density in ``state`` (None when degenerate)."""
    estimate = flt.estimate(state) if estimate is None else estimate
    if bool(getattr(state, "degenerate", False)):
        return None
    if is_gaussian(flt):
        return np.asarray(estimate.mean, float).copy()
    if hasattr(flt, "nodal_density"):
        centred = getattr(flt, "centred", None)  # a ball that follows the state: its nodes where it is
        return _refine_on_nodes(flt if centred is None else centred(state), state)
    return _search_mode(flt, state, estimate)


def _refine_on_nodes(flt: Filter, state: FilterState) -> np.ndarray:
    """The tallest node, moved to the vertex of a quadratic fitted to log σ at its nearest nodes."""
    from scipy.spatial import cKDTree

    nodes = flt.nodes
    sigma = flt.nodal_density(state)
    top = int(np.argmax(sigma))
    n = nodes.shape[1]
    tree = flt.node_tree if hasattr(flt, "node_tree") else cKDTree(nodes)
    terms = 1 + n + n * (n + 1) // 2
    _, near = tree.query(nodes[top], k=min(len(nodes), 2 * terms + 1))
    near = np.atleast_1d(near)
    values = sigma[near]
    if len(near) < terms + 1 or np.any(values <= 0.0):
        return nodes[top].copy()
    d = nodes[near] - nodes[top]
    pairs = [(i, j) for i in range(n) for j in range(i, n)]
    design = np.column_stack([np.ones(len(near)), d, *[d[:, i] * d[:, j] for i, j in pairs]])
    coef, *_ = np.linalg.lstsq(design, np.log(values), rcond=None)
    g = coef[1:1 + n]
    H = np.zeros((n, n))
    for (i, j), c in zip(pairs, coef[1 + n:], strict=True):
        H[i, j] += c if i != j else 2 * c
        if i != j:
            H[j, i] += c
    if np.any(np.linalg.eigvalsh(H) >= 0.0):
        return nodes[top].copy()
    step = -np.linalg.solve(H, g)
    reach = np.max(np.linalg.norm(d, axis=1))
    if not np.all(np.isfinite(step)) or np.linalg.norm(step) > reach:
        return nodes[top].copy()
    return nodes[top] + step


def _search_mode(flt: Filter, state: FilterState, estimate: Estimate) -> np.ndarray:
    """Grid search over ±6 sd, then Nelder–Mead on −log p from the best grid point."""
    from scipy.optimize import minimize

    n = flt.model.n
    mean = np.asarray(estimate.mean, float)
    sd = np.sqrt(np.clip(np.diag(np.asarray(estimate.cov, float)), 1e-18, None))
    per_axis = {1: 401, 2: 81, 3: 25}.get(n, 9)
    iterations = 400 * n
    if hasattr(flt, "point_mode"):  # a point cloud: start from its densest point, no grid
        start = flt.point_mode(state)
        # each step is a kernel density over every point (10-D, 8 192 points: 18 s a row at 400n
        # steps, 7 s at 50n): refined up to 4-D, past that the densest heavy point is the mode
        if n > 4:
            return start
        iterations = 50 * n
    else:
        axes = [np.linspace(mean[i] - 6 * sd[i], mean[i] + 6 * sd[i], per_axis) for i in range(n)]
        points = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, n)
        values = np.asarray(flt.density(state, points), dtype=float)
        start = points[int(np.argmax(np.nan_to_num(values, nan=-np.inf)))]

    density = getattr(flt, "mode_density", flt.density)  # a point cloud's: smoothed for its gradient

    def neg_log(x: np.ndarray) -> float:
        value = float(np.asarray(density(state, x[None, :]), dtype=float)[0])
        return -np.log(value) if value > 0.0 and np.isfinite(value) else np.inf

    result = minimize(neg_log, start, method="Nelder-Mead",
                      options={"xatol": 1e-6 * float(sd.max()), "fatol": 1e-10, "maxiter": iterations,
                               "initial_simplex": _simplex(start, sd * 6 / (per_axis - 1))})
    return result.x if np.isfinite(result.fun) and result.fun <= neg_log(start) else start


def _simplex(start: np.ndarray, step: np.ndarray) -> np.ndarray:
    return np.vstack([start, start + np.diag(step)])


# -- densities on grids -----------------------------------------------------------------------------
def density_axes(flt: Filter, state: FilterState, points: int,
                 estimate: Estimate | None = None) -> list[np.ndarray]:
    """One grid per state variable over the density's support (the ball for the engine)."""
    estimate = flt.estimate(state) if estimate is None else estimate
    return [np.linspace(*support(flt, state, estimate, i), points) for i in range(flt.model.n)]


def joint_on_grid(flt: Filter, state: FilterState, axes: list[np.ndarray]) -> np.ndarray:
    """The normalised joint density on the product grid of ``axes`` (shape (len(a) for a in axes))."""
    mesh = np.meshgrid(*axes, indexing="ij")
    points = np.stack([m.ravel() for m in mesh], axis=1)
    values = np.asarray(flt.density(state, points), dtype=float)
    return np.where(np.isfinite(values), np.maximum(values, 0.0), 0.0).reshape(mesh[0].shape)


def marginals_on_grid(flt: Filter, state: FilterState, axes: list[np.ndarray],
                      estimate: Estimate | None = None) -> list[np.ndarray]:
    """Each variable's marginal density on its own axis."""
    out = []
    for i, axis in enumerate(axes):
        values = marginal(flt, state, i, axis, estimate)
        out.append(np.where(np.isfinite(values), np.maximum(values, 0.0), 0.0))
    return out
