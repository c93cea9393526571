"""The offline arrays of the home ball seen on a translated ball (a ball that follows the state).

Where the Fokker–Planck operator does not change under the move (f independent of the moved
coordinates), B_R(c₀ + shift) has the home ball's basis, projector and propagators: only the nodes
move (solver/engine/follow.py).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ..offline.pipeline import check_points


class TranslatedOffline:
    """The offline arrays of B_R(c₀) seen on B_R(c₀ + shift): nodes moved, everything else shared."""

    def __init__(self, home: Any, shift: np.ndarray, home_center: np.ndarray):
        self.home, self.shift = home, np.asarray(shift, dtype=float)
        self.home_center = np.asarray(home_center, dtype=float)
        self.nodes = np.asarray(home.nodes) + self.shift
        for name in ("weights", "basis", "projector", "propagator_fp", "propagator_k"):
            setattr(self, name, getattr(home, name))

    @property
    def size(self) -> int:
        return self.basis.shape[1]

    def _points(self, points: Any) -> np.ndarray:
        return check_points(points, self.nodes.shape[1]) - self.shift

    def evaluate_basis(self, points: Any) -> np.ndarray:
        return self.home.evaluate_basis(self._points(points))

    def interpolate(self, nodal: np.ndarray, points: Any) -> np.ndarray:
        return self.home.interpolate(nodal, self._points(points))

    def interpolation_matrix(self, points: Any) -> Any:
        return self.home.interpolation_matrix(self._points(points))

    def fokker_planck_generator(self) -> np.ndarray:
        return self.home.fokker_planck_generator()
