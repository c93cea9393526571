"""The typed seams of the public API (issue 36, item 4).

1. ``mypy`` with the project's configuration (pyproject.toml's ``[tool.mypy]``: strict on the folder
   ``yauyau/``, the solver's, the store's and the service's signatures used) finds no error.
2. Every public property and field of the public API's classes has a docstring (``help`` and the
   editors show it): read from the source with ``ast``, as attribute docstrings.
3. What typing the seam found: ``OnlineFilter.step`` asked every filter for a ``gate``, which the
   Wei–Norman filter (it never gates) does not have; it now steps it, and the estimate is the exact
   Kalman–Bucy one, in closed form below.
"""

from __future__ import annotations

import ast
import importlib.util
import inspect
import subprocess
import sys
import textwrap

import numpy as np
import pytest
from helpers import ROOT
from yauyau.solver.exact.wei_norman import WeiNormanFilter
from yauyau.solver.filtering import ChunkedFilter, ChunkResult, Estimate, Filter, FilterState, MarginalFilter
from yauyau.solver.model import compile_model
from yauyau.solver.spec import spec_from_dict

from yauyau.api import OnlineFilter, Solved, StoredFilterModel


@pytest.mark.slow
def test_mypy_passes_on_the_public_api():
    if importlib.util.find_spec("mypy") is None:
        pytest.skip("mypy is not installed (it comes with the test extra: pip install -e '.[test]')")
    done = subprocess.run([sys.executable, "-m", "mypy", "--config-file", str(ROOT / "pyproject.toml")],
                          cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, f"mypy failed (exit {done.returncode}):\n{done.stdout}\n{done.stderr}"


PUBLIC_CLASSES = [OnlineFilter, Solved, StoredFilterModel, Estimate, ChunkResult, Filter, FilterState,
                  MarginalFilter, ChunkedFilter]


def undocumented(cls: type) -> list[str]:
    """The public fields (annotated names in the class body) without a string right after them, and
    the public properties without a docstring."""
    body = ast.parse(textwrap.dedent(inspect.getsource(cls))).body[0]
    assert isinstance(body, ast.ClassDef)
    missing = []
    for statement, following in zip(body.body, [*body.body[1:], None], strict=True):
        if isinstance(statement, ast.AnnAssign) and isinstance(statement.target, ast.Name):
            name = statement.target.id
            documented = (isinstance(following, ast.Expr) and isinstance(following.value, ast.Constant)
                          and isinstance(following.value.value, str) and following.value.value.strip())
        elif isinstance(statement, ast.FunctionDef) and any(
                isinstance(d, ast.Name) and d.id == "property" for d in statement.decorator_list):
            name = statement.name
            documented = bool(ast.get_docstring(statement))
        else:
            continue
        if not name.startswith("_") and not documented:
            missing.append(f"{cls.__name__}.{name}")
    return missing


def test_every_public_property_has_a_docstring():
    missing = [name for cls in PUBLIC_CLASSES for name in undocumented(cls)]
    assert not missing, f"public properties without a docstring: {missing}"


def test_the_docstring_check_sees_a_missing_one():
    class Bare:
        documented: int
        """Yes."""
        bare: float

        @property
        def plain(self) -> int:
            return 1

    assert undocumented(Bare) == ["Bare.bare", "Bare.plain"]


def test_online_filter_steps_a_filter_that_never_gates():
    """dx = dw, dy = x dt + dv (R = 1), x(0) ~ N(0, 1): the Kalman–Bucy covariance P' = 1 − P² stays
    at P = 1, and over one step whose observation path is linear (ẏ = c, what the Wei–Norman
    representation assumes) the mean solves m' = c − m: m(dt) = c (1 − e^{−dt}); the log-likelihood
    is ∫ m c − ½ (m² + P) dt.  The Wei–Norman filter gets its flow e^{tL0}σ0 in closed form:
    L0 w = ½ w'' − ½ x² w keeps σ0 = N(0, 1) Gaussian with variance 1 and log-mass −t/2."""
    dt, dy = 0.05, 0.3
    spec = {"name": "wn", "state": ["x"], "drift": ["0"], "observation": ["x"],
            "initial": {"kind": "gaussian", "mean": [0.0], "cov": [[1.0]]},
            "domain": {"radius": 10.0}, "discretization": {"dt": dt, "basis": 10}}
    model = compile_model(spec_from_dict(spec))

    def log_flow(t: float, points: np.ndarray) -> np.ndarray:
        return -0.5 * t - 0.5 * points[:, 0] ** 2 - 0.5 * np.log(2 * np.pi)

    flt = WeiNormanFilter(model, log_flow, log_flow=True)
    assert not hasattr(flt, "gate")
    estimate = OnlineFilter(flt).step([dy])
    c = dy / dt
    grows = dt - (1 - np.exp(-dt))  # ∫ (1 − e^{−t}) dt
    squares = dt - 2 * (1 - np.exp(-dt)) + (1 - np.exp(-2 * dt)) / 2  # ∫ (1 − e^{−t})² dt
    assert estimate.mean[0] == pytest.approx(c * (1 - np.exp(-dt)), abs=1e-9)
    assert estimate.cov[0, 0] == pytest.approx(1.0, abs=1e-9)
    assert estimate.loglik == pytest.approx(c * c * grows - 0.5 * c * c * squares - 0.5 * dt, abs=1e-9)
    assert not estimate.gated and estimate.reason is None
