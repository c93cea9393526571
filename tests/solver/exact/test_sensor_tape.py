"""The sensor tape (solver/exact/sensor_tape.py) run by its compiled interpreter
(solver/exact/sensor_kernel.py) against SymPy's own arbitrary-precision evaluation of the same
expressions and of their derivatives, every whitelisted function; the domain edges as numpy gives
them (the numpy path's conventions: NaN outside a domain, ±inf at a pole)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import sympy as sp
from yauyau.solver.exact.sensor_tape import Uncompilable, build_tape, sensor_tapes
from yauyau.solver.expressions import FUNCTIONS, parse_expression, state_symbols

X0, X1 = state_symbols(2)
NAMES = {"x": X0, "y": X1}
# each whitelisted function of a smooth argument inside its domain, at the points below
TEXTS = {"exp": "exp(x - y)", "log": "log(2 + x**2)", "sqrt": "sqrt(1 + x**2 + y**2)", "sin": "sin(3*x)",
         "cos": "cos(x*y)", "tan": "tan(x/3)", "tanh": "tanh(2*y)", "sinh": "sinh(x)", "cosh": "cosh(y)",
         "atan": "atan(x + y)", "asin": "asin(x/3)", "acos": "acos(y/3)", "asinh": "asinh(x*y)",
         "acosh": "acosh(2 + y**2)", "atanh": "atanh(x/3)", "abs": "abs(x - 0.25)", "sech": "sech(x)",
         "sign": "sign(y - 0.1)", "atan2": "atan2(y, x + 3)", "min": "min(x, y**2)", "max": "max(x, 2*y)"}
POINTS = np.array([[0.3, -0.7], [-1.1, 0.45], [1.7, 1.2], [-0.2, -1.5]])


def _run(tape, X):
    from yauyau.solver.exact.sensor_kernel import run_tape

    F = np.empty((len(X), len(tape.outputs)))
    run_tape(tape.code, tape.constants, tape.outputs, X, np.empty((tape.registers, len(X))), F)
    return F


def _truth(expr, X):
    return np.array([float(expr.evalf(30, subs={X0: sp.Float(x, 30), X1: sp.Float(y, 30)})) for x, y in X])


def test_every_function_and_its_derivatives_as_sympy_evaluates_them():
    assert set(TEXTS) == set(FUNCTIONS)
    for name, text in TEXTS.items():
        expr = parse_expression(text, NAMES)
        full, values = sensor_tapes([expr], (X0, X1))
        F = _run(full, POINTS)
        derivatives = [expr] + [sp.diff(expr, s) for s in (X0, X1)] + [sp.diff(expr, s, t) for s in (X0, X1)
                                                                       for t in (X0, X1)]
        for column, d in enumerate(derivatives):
            truth = _truth(d.replace(sp.DiracDelta, lambda *a: sp.S.Zero), POINTS)
            np.testing.assert_allclose(F[:, column], truth, rtol=1e-13, atol=1e-14, err_msg=f"{name}: {d}")
        np.testing.assert_array_equal(_run(values, POINTS)[:, 0], F[:, 0])


def test_powers_products_and_quotients():
    expr = parse_expression("(x**3 - 2*y)/(1 + x**2)**1.5 - x**-2 + 2**y * (x*y)**0.5 / 7 - e**x + pi", NAMES)
    X = np.abs(POINTS) + 0.1
    np.testing.assert_allclose(_run(build_tape((expr,), (X0, X1)), X)[:, 0], _truth(expr, X), rtol=1e-13)


def test_domain_edges_as_numpy():
    texts = ["sqrt(x)", "log(x)", "acosh(x)", "atanh(x)", "asin(x)", "acos(x)", "x**0.5", "1/x", "sign(x)",
             "min(x, y)", "max(x, y)"]
    X = np.array([[-1.0, 0.0], [0.0, 1.0], [1.0, np.nan], [2.0, -1.0], [np.nan, 0.5]])
    for text in texts:
        expr = parse_expression(text, NAMES)
        with np.errstate(all="ignore"):
            expected = sp.lambdify((X0, X1), expr, modules="numpy")(X[:, 0], X[:, 1])
        # the same NaNs and infinities where numpy gives them; finite values to an ulp or two (numba's
        # acosh is not numpy's libm call on every machine: 1 ulp apart on an AVX-512 one)
        np.testing.assert_allclose(_run(build_tape((expr,), (X0, X1)), X)[:, 0],
                                   np.broadcast_to(expected, len(X)), rtol=1e-15, atol=0, err_msg=text)


def test_a_node_without_an_instruction_is_refused_by_name():
    with pytest.raises(Uncompilable, match="gamma"):
        build_tape((sp.gamma(X0),), (X0, X1))
    assert math.isnan(_run(build_tape((sp.sqrt(X0 - 2),), (X0, X1)), POINTS[:1])[0, 0])
