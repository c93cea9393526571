"""The SymPy-free numpy builder of solver/expressions.py against SymPy's own evaluation.

Truth: SymPy's exact expression of the same text, lambdified (a different route: exact rationals,
simplification, generated code); the two agree to rounding on random points of the ball.  And a
stored model filters without importing SymPy at all (the start-up of `yauyau filter`).
"""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
from helpers import ROOT
from yauyau.solver.errors import SpecError
from yauyau.solver.expressions import (
    numeric_expression,
    numeric_many,
    parse_expression,
    state_symbols,
    vectorize,
)

CASES = [
    "x**3", "-0.2*x + y", "x*y**2 - 3.5*sin(x) + cos(y)/2", "tanh(x) + sech(y)", "atan2(y, x) + atan(x)",
    "exp(-x**2/2) / sqrt(2*pi)", "log(1 + x**2) * e", "abs(x) + sign(y) + min(x, y) - max(x, 0.5)",
    "theta*x - kappa**2*y", "(x + y + 1)**4", "sinh(x)*cosh(y) - asinh(x)",
    "-(-x)", "+x - 1e-3*y**5", "x / (1 + y**2)", "asin(x/10) + acos(y/10) + atanh(x/10)", "acosh(2 + x**2)",
]


@pytest.mark.parametrize("text", CASES)
def test_numeric_builder_agrees_with_sympy(text):
    params = {"theta": 0.7, "kappa": -1.3}
    numeric = numeric_expression(text, {"x": 0, "y": 1}, params, "f")
    symbols = state_symbols(2)
    names = {"x": symbols[0], "y": symbols[1], **{k: __import__("sympy").Rational(repr(v))
                                                    for k, v in params.items()}}
    exact = vectorize(parse_expression(text, names, "f"), symbols)
    X = np.random.default_rng(0).uniform(-3, 3, size=(500, 2))
    a, b = numeric(X), exact(X)
    assert a.shape == (500,) and np.allclose(a, b, rtol=1e-12, atol=1e-12), np.max(np.abs(a - b))


@pytest.mark.parametrize("n", [2, 9])
def test_many_expressions_on_points_or_on_coordinate_rows_agree_with_sympy(n):
    """numeric_many's two layouts: points (P, n) -> (P, m), and coordinate rows (n, P) -> (m, P) (the
    coupled Yau–Niu rows' ``rows``: each row written once), Fortran- or C-ordered, against SymPy; a
    constant expression fills its row."""
    import sympy

    texts = [*CASES[:6], "2.5"]
    states = {"x": 0, "y": 1, **{f"z{i}": i for i in range(2, n)}}
    params = {"theta": 0.7, "kappa": -1.3}
    many = numeric_many([numeric_expression(t, states, params, f"f[{i}]") for i, t in enumerate(texts)])
    symbols = state_symbols(n)
    names = {"x": symbols[0], "y": symbols[1], **{k: sympy.Rational(repr(v)) for k, v in params.items()}}
    X = np.random.default_rng(1).uniform(-3, 3, size=(400, n))
    exact = np.stack([np.broadcast_to(vectorize(parse_expression(t, names, "f"), symbols)(X), (400,))
                      for t in texts], axis=1)
    for points in (X, np.asfortranarray(X)):
        on_points, on_rows = many(points), many.rows(points.T)
        assert on_points.shape == (400, len(texts)) and on_rows.shape == (len(texts), 400)
        assert on_rows.flags.c_contiguous
        assert np.allclose(on_points, exact, rtol=1e-12, atol=1e-12)
        assert np.allclose(on_rows.T, exact, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("shape", ["{x}**3", "-0.5*{x}", "{x}", "theta*sin({x}) - {x}/(1 + {x}**2)", "kappa"])
@pytest.mark.parametrize("order", ["own", "shifted"])
def test_expressions_of_one_shape_on_their_own_coordinates_agree_with_sympy(shape, order):
    """Twelve expressions of one shape, each in its own coordinate (a hundred ``x_i**3`` sensors), are
    evaluated as one array operation (numeric_many's template): against SymPy on points in both orders
    and on coordinate rows, the same numbers as each expression alone, and never a view of the points
    (the identity ``x_i`` is copied).  A constant (no coordinate) has no template and still fills its
    rows."""
    import sympy

    n = 12
    states = {f"z{i}": i for i in range(n)}
    params = {"theta": 0.7, "kappa": -1.3}
    coordinate = (lambda i: i) if order == "own" else (lambda i: (i + 5) % n)
    texts = [shape.format(x=f"z{coordinate(i)}") for i in range(n)]
    functions = [numeric_expression(t, states, params, f"f[{i}]") for i, t in enumerate(texts)]
    assert all((f.template is not None) == ("{x}" in shape) for f in functions)
    many = numeric_many(functions)
    symbols = state_symbols(n)
    names = {**{f"z{i}": s for i, s in enumerate(symbols)},
             **{k: sympy.Rational(repr(v)) for k, v in params.items()}}
    X = np.random.default_rng(2).uniform(-3, 3, size=(300, n))
    exact = np.stack([np.broadcast_to(vectorize(parse_expression(t, names, "f"), symbols)(X), (300,))
                      for t in texts], axis=1)
    alone = np.stack([f(X) for f in functions], axis=1)
    for points in (X, np.asfortranarray(X)):
        on_points, on_rows = many(points), many.rows(np.ascontiguousarray(points.T))
        assert np.allclose(on_points, exact, rtol=1e-12, atol=1e-12)
        assert np.array_equal(on_points, alone) and np.array_equal(on_rows, alone.T)
        assert not np.may_share_memory(on_points, points) and not np.may_share_memory(on_rows, points)


@pytest.mark.parametrize("text, message", [
    ("__import__('os')", "unknown function"), ("x.real", "not allowed"), ("foo(x)", "unknown function"),
    ("z + 1", "unknown name 'z'"), ("x**100", "exponent"), ("10.0**60*1e10**60", "floating-point range"),
    ("x**x", "positive constant base"), ("1/0", "undefined"), ("log(0)*x", "undefined"),
    ("sqrt(-1)*x", "not real|undefined"), ("sin(x, x)", "exactly 1"), ("True*x", "real numbers"),
    ("x*1e308*1e308*1e308", None),
])
def test_numeric_builder_refuses_what_sympy_refuses(text, message):
    if message is None:  # folds to an infinite constant only at evaluation: inf values, not a crash
        values = numeric_expression(text, {"x": 0}, {}, "drift[0]")(np.array([[1.0]]))
        assert not np.isfinite(values).all()
        return
    with pytest.raises(SpecError, match=message) as err:
        numeric_expression(text, {"x": 0}, {}, "drift[0]")
    assert err.value.field == "drift[0]"


@pytest.mark.slow
def test_a_stored_model_filters_without_sympy(tmp_path):
    import yauyau

    store = tmp_path / "store"
    mid = yauyau.precompute(ROOT / "examples" / "cubic_sensor.toml", store)
    code = (f"import sys, yauyau; f = yauyau.open_filter({str(store)!r}, {mid!r}); f.run([[0.01], [0.02]]); "
            "print(sorted(m for m in ('sympy', 'skfem', 'yauyau.solver.analysis') "
            "if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                         env={"PYTHONPATH": str(ROOT), "PATH": "/usr/bin:/bin", "OPENBLAS_NUM_THREADS": "1"})
    assert out.stdout.strip().splitlines()[-1] == "[]"
