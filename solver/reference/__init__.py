"""Reference filters (pure numpy/scipy) against which the Yau–Yau engine is measured.

``DiscreteKalmanFilter`` (exact for the sampled linear model), ``BenesFilter`` (exact for
f = tanh x, h = x), ``PointMassFilter`` (fine finite-volume grid, n = 1, 2),
``BootstrapParticleFilter``, ``ExtendedKalmanFilter`` and ``UnscentedKalmanFilter``.
"""

from ..expressions import affine_coefficients
from .benes import BenesFilter
from .gaussian_approx import ExtendedKalmanFilter, UnscentedKalmanFilter
from .kalman import DiscreteKalmanFilter, van_loan
from .particle import BootstrapParticleFilter
from .pointmass import PointMassFilter

__all__ = ["BenesFilter", "BootstrapParticleFilter", "DiscreteKalmanFilter", "ExtendedKalmanFilter",
           "PointMassFilter", "UnscentedKalmanFilter", "affine_coefficients", "van_loan"]
