"""Fine-grid (point-mass) reference filter for n = 1, 2, independent of the finite elements.

The Fokker–Planck equation of the signal,

    ∂p/∂t = ½ Σ a_ij ∂_i∂_j p − Σ ∂_i (f_i p),

is discretised by finite volumes on a uniform cell-centred grid of the box [c − R, c + R]ⁿ that
contains the ball: the flux through a face is f·(p_L + p_R)/2 − ½a_ii (p_R − p_L)/h (central,
second order), no flux through the box's boundary (mass is conserved), and cross-diffusion
a_ij (i ≠ j) by central differences.  Time: TR-BDF2 (L-stable, second order) with γ = 2 − √2,
for which both implicit stages share the matrix I − (γ/2)δL — one sparse LU, factored once.
After the flow over dt the density is multiplied by exp(hᵀR⁻¹Δy − ½hᵀR⁻¹h dt) in log scale
and renormalised.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
import scipy.sparse as sps
from scipy.interpolate import RegularGridInterpolator
from scipy.sparse.linalg import splu

from ..errors import InputError, SpecError
from ..filtering import Estimate
from ..model import Model
from ._base import ReferenceFilter, StepState, advance, log_sum_exp

DEFAULT_CELLS = {1: 2048, 2: 128}
_GAMMA = 2.0 - np.sqrt(2.0)  # TR-BDF2: both stages then use I − (γ/2) δ L


@dataclass(frozen=True)
class GridState(StepState):
    """Normalised density on the cells, flattened in 'ij' order."""

    density: np.ndarray = field(default_factory=lambda: np.zeros(0))

    def to_dict(self) -> dict[str, Any]:
        out = asdict(self)
        out["density"] = self.density.tolist()
        return out


def cell_axes(model: Model, cells: int, box: float) -> list[np.ndarray]:
    """Cell centres along each axis of the box c ± box·R."""
    half = box * model.radius
    width = 2.0 * half / cells
    return [model.center[d] - half + width * (np.arange(cells) + 0.5) for d in range(model.n)]


def fokker_planck_matrix(model: Model, axes: list[np.ndarray]) -> sps.csr_matrix:
    """Sparse finite-volume matrix L of the Fokker–Planck operator on the cells (no-flux box)."""
    shape = tuple(len(ax) for ax in axes)
    index = np.arange(int(np.prod(shape))).reshape(shape)
    points = np.stack([g.ravel() for g in np.meshgrid(*axes, indexing="ij")], axis=1)
    rows, cols, vals = [], [], []
    for d, ax in enumerate(axes):
        width = ax[1] - ax[0]
        left = np.take(index, np.arange(shape[d] - 1), axis=d).ravel()
        right = np.take(index, np.arange(1, shape[d]), axis=d).ravel()
        drift = model.f(0.5 * (points[left] + points[right]))[:, d]
        diffusion = 0.5 * model.a[d, d] / width
        alpha, beta = 0.5 * drift + diffusion, 0.5 * drift - diffusion  # flux = α p_L + β p_R
        rows += [left, left, right, right]
        cols += [left, right, left, right]
        vals += [-alpha / width, -beta / width, alpha / width, beta / width]
    size = index.size
    L = sps.coo_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                       shape=(size, size)).tocsr()
    if len(axes) == 2 and model.a[0, 1] != 0.0:
        L = L + model.a[0, 1] * sps.kron(_central_difference(axes[0]), _central_difference(axes[1]))
    return L.tocsr()


def _central_difference(ax: np.ndarray) -> sps.csr_matrix:
    width = ax[1] - ax[0]
    k = len(ax)
    return sps.diags([np.full(k - 1, 0.5 / width), np.full(k - 1, -0.5 / width)], [1, -1]).tocsr()


class PointMassFilter(ReferenceFilter):
    """Fine-grid reference: finite-volume Fokker–Planck flow + exact pointwise update."""

    method = "point-mass"

    def __init__(self, model: Model, cells: int | None = None, substeps: int | None = None, box: float = 1.0):
        super().__init__(model)
        if model.n not in DEFAULT_CELLS:
            raise SpecError("state", "the point-mass reference supports n = 1 or 2")
        cells = DEFAULT_CELLS[model.n] if cells is None else cells
        if not isinstance(cells, (int, np.integer)) or cells < 8:
            raise InputError("cells", "must be an integer >= 8")
        substeps = (4 if model.n == 1 else 2) if substeps is None else substeps
        if not isinstance(substeps, (int, np.integer)) or substeps < 1:
            raise InputError("substeps", "must be an integer >= 1")
        self.axes = cell_axes(model, int(cells), box)
        self.shape = (int(cells),) * model.n
        self.points = np.stack([g.ravel() for g in np.meshgrid(*self.axes, indexing="ij")], axis=1)
        self.volume = float(np.prod([ax[1] - ax[0] for ax in self.axes]))
        self.substeps = int(substeps)
        delta = model.dt / self.substeps
        L = fokker_planck_matrix(model, self.axes)
        eye = sps.identity(L.shape[0], format="csc")
        # minimum degree on AᵀA+A keeps the 2-D fill-in (and the solve) several times smaller than COLAMD
        self._lu = splu((eye - 0.5 * _GAMMA * delta * L).tocsc(), permc_spec="MMD_AT_PLUS_A")
        self._explicit = (eye + 0.5 * _GAMMA * delta * L).tocsr()
        # h R⁻¹ and ½hᵀR⁻¹h dt at the cells, once: log e = (hR⁻¹)Δy − ½hᵀR⁻¹h dt
        self._hR = model.h(self.points) @ model.R_inv
        self._penalty = model.half_hRh(self.points) * model.dt

    def initial_state(self, prior: Any | None = None) -> GridState:
        if prior is not None:
            raise InputError("prior", "the point-mass reference uses the model's prior")
        log_p = self.model.log_prior(self.points)
        weight = np.exp(log_p - np.max(log_p))
        return GridState(density=weight / (weight.sum() * self.volume))

    def flow(self, density: np.ndarray) -> np.ndarray:
        """Fokker–Planck flow over dt: ``substeps`` TR-BDF2 steps."""
        g = _GAMMA
        u = density
        for _ in range(self.substeps):
            half = self._lu.solve(self._explicit @ u)  # trapezoidal stage to t + γδ
            u = self._lu.solve((half - (1 - g) ** 2 * u) / (g * (2 - g)))  # BDF2 stage to t + δ
        return np.clip(u, 0.0, None)

    def _advance(self, state: GridState, increment: np.ndarray | None) -> GridState:
        p = self.flow(state.density)
        p = p / (p.sum() * self.volume)
        if increment is None:
            return advance(state, self.model.dt, 0.0, density=p)
        with np.errstate(divide="ignore"):
            log_w = np.log(p) + (self._hR @ increment - self._penalty)
        log_z = log_sum_exp(log_w) + np.log(self.volume)
        if not np.isfinite(log_z):
            return advance(state, self.model.dt, 0.0, density=p, degenerate=True,
                           reason="the update factor vanished wherever the density lives")
        return advance(state, self.model.dt, log_z, density=np.exp(log_w - log_z))

    def estimate(self, state: GridState) -> Estimate:
        w = state.density * self.volume
        mean = w @ self.points
        d = self.points - mean
        cov = (d * w[:, None]).T @ d
        return Estimate(step=state.step, t=state.t, mean=mean, cov=cov, loglik=state.loglik,
                        loglik_increment=state.loglik_increment, degenerate=state.degenerate,
                        reason=state.reason, mode=self.points[int(np.argmax(state.density))].copy())

    def density(self, state: GridState, points: np.ndarray) -> np.ndarray:
        """Linear interpolation of the cell values (zero outside the box)."""
        table = RegularGridInterpolator(self.axes, state.density.reshape(self.shape),
                                        bounds_error=False, fill_value=0.0)
        return table(np.atleast_2d(np.asarray(points, float)))
