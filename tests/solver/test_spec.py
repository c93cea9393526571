"""Model specs and safe expressions: hostile and malformed input is refused, naming the field."""

import numpy as np
import pytest
import sympy as sp
from yauyau.solver import SpecError, compile_model, load_spec, spec_from_dict
from yauyau.solver.expressions import numeric_expression, parse_expression

X = sp.Symbol("x_0", real=True)


def base(**over):
    spec = {
        "name": "t", "state": ["x"], "drift": ["-0.2*x"], "observation": ["x**3"],
        "initial": {"kind": "gaussian", "mean": [0.5], "cov": [[1.0]]},
        "domain": {"radius": 7.0}, "discretization": {"dt": 0.01, "basis": 16},
    }
    spec.update(over)
    return spec


@pytest.mark.parametrize("text", [
    "__import__('os').system('x')", "(1).__class__", "lambda: 0", "9**9**9", "x.real",
    "[x]", "x if x else 1", "open('f')", "x[0]", "{}", "f'{x}'", "1 < x", "x and 1",
    "exp(x, x)", "exp(x=1)", "exp(*x)", "'abc'", "True", "1j", "y", "__builtins__",
    "(" * 300 + "x" + ")" * 300,
    "x+" * 500 + "x", "2**x**x", "1/0", "log(-1)", "", "   ",
])
def test_hostile_expression_refused(text):
    with pytest.raises(SpecError) as err:
        parse_expression(text, {"x": X}, "drift[0]")
    assert err.value.field == "drift[0]"


@pytest.mark.parametrize("text, expected", [
    ("-0.2*x", -X / 5), ("x**3", X**3), ("tanh(x)", sp.tanh(X)), ("exp(-x**2/2)", sp.exp(-X**2 / 2)),
    ("abs(x) + sqrt(4)", sp.Abs(X) + 2), ("-(x - 1)**2", -(X - 1) ** 2), ("2**x", 2**X),
])
def test_expression_builds_exact_sympy(text, expected):
    assert sp.simplify(parse_expression(text, {"x": X}) - expected) == 0


@pytest.mark.parametrize("over, field", [
    ({"state": ["x", "x"]}, "state"),
    ({"state": ["exp"]}, "state"),
    ({"state": []}, "state"),
    ({"state": ["a", "b", "c", "d", "e", "f", "g"]}, "state"),  # at most 6 (the general engine: 3)
    ({"drift": ["x", "x"]}, "drift"),
    ({"drift": ["q*x"]}, "drift[0]"),
    ({"observation": ["__import__('os')"]}, "observation[0]"),
    ({"diffusion": [[1.0, 0.0]]}, "diffusion"),
    ({"diffusion": [[-1.0]]}, "diffusion"),
    ({"observation_noise": [[0.0]]}, "observation_noise"),
    ({"domain": {"radius": 0.0}}, "domain.radius"),
    ({"domain": {"radius": -1.0}}, "domain.radius"),
    ({"domain": {"radius": 2.0, "center": [0.0, 1.0]}}, "domain.center"),
    ({"discretization": {"dt": 0.0, "basis": 8}}, "discretization.dt"),
    ({"discretization": {"dt": 0.1}}, "discretization.basis"),
    ({"initial": {"kind": "gaussian", "mean": [0.0, 1.0], "cov": [[1.0]]}}, "initial.mean"),
    ({"initial": {"kind": "gaussian", "mean": [0.0], "cov": [[0.0]]}}, "initial.cov"),
    ({"initial": {"kind": "wishful"}}, "initial"),
    ({"initial": {"kind": "density", "expression": "exp(-x**2)+lambda: 0"}}, "initial.expression"),
    ({"drift": ["log(x)"]}, "drift[0]"),
    ({"parameters": {"x": 1.0}}, "parameters"),
    ({"colour": "red"}, "colour"),
])
def test_bad_spec_names_field(over, field):
    with pytest.raises(SpecError) as err:
        spec_from_dict(base(**over))
    assert err.value.field == field, str(err.value)


@pytest.mark.parametrize("over, field, hint", [
    ({"domain": {"radius": 7.0, "folow": True}}, "domain.folow", "did you mean 'follow'?"),
    ({"diffusoin": [[1.0]]}, "diffusoin", "did you mean 'diffusion'?"),
    ({"initial": {"kind": "gaussian", "mean": [0.5], "covariance": [[1.0]]}}, "initial.covariance",
     "did you mean 'cov'?"),
    ({"initial": {"kind": "mixture", "weights": [1.0], "means": [[0.5]], "covs": [[[1.0]]], "cov": 1}},
     "initial.cov", "did you mean 'covs'?"),
    ({"discretization": {"dt": 0.01, "basis": 16, "zzz": 1}}, "discretization.zzz",
     "this table accepts basis, dt, element, mesh, order, points, precision, scheme, substeps"),
])
def test_unknown_key_names_the_nearest_accepted_one(over, field, hint):
    """A misspelt key is named with the key it most likely meant and the keys its table accepts
    (pydantic alone says "Extra inputs are not permitted")."""
    with pytest.raises(SpecError) as err:
        spec_from_dict(base(**over))
    assert err.value.field == field
    assert hint in str(err.value)
    assert f"unknown key '{field.rsplit('.', 1)[-1]}'" in str(err.value)


def test_diffusion_error_shows_its_eigenvalues():
    with pytest.raises(SpecError) as err:
        spec_from_dict(base(state=["x", "y"], drift=["-x", "-y"], observation=["x"],
                            initial={"kind": "gaussian", "mean": [0.0, 0.0], "cov": [[1.0, 0.0], [0.0, 1.0]]},
                            diffusion=[[1.0, 2.0], [2.0, 1.0]]))
    assert err.value.field == "diffusion"
    assert "its eigenvalues are -1, 3" in str(err.value)  # (1 1; 1 1)·… : 1 ∓ 2, computed by hand


def test_parameters_are_exact_numbers():
    model = compile_model(spec_from_dict(base(drift=["-theta*x"], parameters={"theta": 0.2})))
    assert model.drift[0] == -X / 5
    assert model.div_drift == sp.Rational(-1, 5)
    assert model.potential == X**6 / 2


def test_examples_load():
    for name in ("cubic_sensor", "ou", "benes", "range_2d"):
        model = compile_model(load_spec(f"examples/{name}.toml"))
        pts = np.zeros((3, model.n))
        assert model.f(pts).shape == (3, model.n)
        assert model.h(pts).shape == (3, model.m)


def test_mixture_prior_is_normalised_density():
    model = compile_model(load_spec("examples/benes.toml"))
    x = np.linspace(-12, 12, 20001)[:, None]
    p = model.prior_density(x)
    assert abs(np.trapezoid(p, x[:, 0]) - 1) < 1e-10
    # cosh(x) N(x; 0, 1) normalised: cosh(x) e^{-x²/2} / (sqrt(2π) e^{1/2})
    exact = np.cosh(x[:, 0]) * np.exp(-x[:, 0] ** 2 / 2) / np.sqrt(2 * np.pi * np.e)
    assert np.max(np.abs(p - exact)) < 1e-12


@pytest.mark.parametrize("over, field", [({"observation": ["x^3"]}, "observation[0]"),
                                         ({"drift": ["-0.2*(x - 1)^2"]}, "drift[0]")])
def test_caret_is_not_a_power_and_says_so(over, field):
    """x^3 is Python's exclusive or: the spec is refused with the fix, both by SymPy's parser and by the
    numeric one a stored model is filtered with."""
    with pytest.raises(SpecError) as err:
        spec_from_dict(base(**over))
    assert err.value.field == field and "use ** for powers" in err.value.message, str(err.value)
    with pytest.raises(SpecError, match=r"use \*\* for powers"):
        numeric_expression("x^3", {"x": 0}, {}, "observation[0]")
