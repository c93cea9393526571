"""Model analysis: Wong matrix, η, the structural conditions, the estimation algebra and the
recommended exact or general filter, split along its seams:

* :mod:`.budget`: the deadline and expression-size cap every step checks (BoundReached);
* :mod:`.operators`: differential operators, composition, Lie bracket, zero tests, display;
* :mod:`.algebra`: the estimation algebra by rounds of brackets (closure, dimension, linear rank);
* :mod:`.conditions`: Wong matrix, η, (C1)/(C'1), (C2), (C3), the linear case, the seed 004 class;
* :mod:`.report`: :func:`analyze`, the report, :func:`recommend_method`, text/JSON rendering.

The papers are named in :mod:`yauyau.solver.papers` (docs/papers.md).
"""

from .algebra import (
    DEFAULT_MAX_DEPTH,
    DEFAULT_MAX_DIMENSION,
    EstimationAlgebra,
    bounded_algebra,
    estimation_algebra,
)
from .budget import DEFAULT_MAX_SIZE, DEFAULT_TIME_LIMIT, BoundReached, Budget, bounded, expression_size
from .conditions import (
    Condition,
    constant_value,
    eta,
    is_constant,
    observed_coordinate,
    polynomial_degree_at_most,
    seed004_structure,
    whitened_wong_matrix,
    wong_matrix,
)
from .operators import (
    Operator,
    add,
    bracket,
    compose,
    derivative,
    exact_matrix,
    is_identity,
    is_zero,
    kolmogorov_operator,
    multiplication,
    observation_energy,
    order,
    show,
    show_operator,
    tidy,
)
from .report import AnalysisReport, analyze, recommend_method, recommend_method_from

__all__ = [
    "DEFAULT_MAX_DEPTH", "DEFAULT_MAX_DIMENSION", "DEFAULT_MAX_SIZE", "DEFAULT_TIME_LIMIT",
    "AnalysisReport", "BoundReached", "Budget", "Condition", "EstimationAlgebra", "Operator",
    "add", "analyze", "bounded", "bounded_algebra", "bracket", "compose", "constant_value", "derivative",
    "estimation_algebra", "eta", "exact_matrix", "expression_size", "is_constant", "is_identity", "is_zero",
    "kolmogorov_operator", "multiplication", "observation_energy", "observed_coordinate", "order",
    "polynomial_degree_at_most", "recommend_method", "recommend_method_from", "seed004_structure", "show",
    "show_operator", "tidy", "whitened_wong_matrix", "wong_matrix",
]
