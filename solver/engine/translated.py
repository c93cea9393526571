"""The offline arrays of the home ball seen on a translated ball (a ball that follows the state).

Where the Fokker–Planck operator does not change under the move (f independent of the moved
coordinates), B_R(c₀ + shift) has the home ball's basis, projector and propagators: only the nodes
move (solver/engine/follow.py).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

from ..offline.pipeline import check_points

if TYPE_CHECKING:  # types only
    from numpy.typing import ArrayLike

    from ..offline.pipeline import OfflineModel


class TranslatedOffline:
    """The offline arrays of B_R(c₀) seen on B_R(c₀ + shift): nodes moved, everything else shared."""

    weights: np.ndarray  # the home's (set in __init__, with the rest of OfflineArrays)
    basis: np.ndarray
    projector: np.ndarray
    propagator_fp: np.ndarray
    propagator_k: np.ndarray

    def __init__(self, home: OfflineModel, shift: np.ndarray, home_center: np.ndarray):
        self.home, self.shift = home, np.asarray(shift, dtype=float)
        self.home_center = np.asarray(home_center, dtype=float)
        self.nodes = np.asarray(home.nodes) + self.shift
        for name in ("weights", "basis", "projector", "propagator_fp", "propagator_k"):
            setattr(self, name, getattr(home, name))

    @property
    def size(self) -> int:
        return self.basis.shape[1]

    def _points(self, points: ArrayLike) -> np.ndarray:
        return check_points(points, self.nodes.shape[1]) - self.shift

    def evaluate_basis(self, points: ArrayLike) -> np.ndarray:
        return self.home.evaluate_basis(self._points(points))

    def interpolate(self, nodal: np.ndarray, points: ArrayLike) -> np.ndarray:
        return self.home.interpolate(nodal, self._points(points))

    def interpolation_matrix(self, points: ArrayLike) -> Any:
        return self.home.interpolation_matrix(self._points(points))

    def fokker_planck_generator(self) -> np.ndarray:
        return self.home.fokker_planck_generator()
