"""precompute / OfflineModel: array contract of docs/architecture.md, round trip, workers,
evaluation at arbitrary points (against closed-form eigenfunctions), and bad input."""

import numpy as np
import pytest
from yauyau.solver import compile_model, load_spec, spec_from_dict
from yauyau.solver.errors import InputError, SpecError
from yauyau.solver.offline.pipeline import ARRAY_NAMES, OPTIONAL_ARRAYS, OfflineModel, precompute


def make_model(n, radius=3.0, basis=24, mesh=None, order=2, dt=0.02, center=None):
    state = ["x", "y", "z"][:n]
    drift = ["-x + 0.3*y", "-y - 0.3*x", "-z"][:n] if n > 1 else ["-0.5*x"]
    return compile_model(spec_from_dict(dict(
        name="o", state=state, drift=drift, observation=["x**3"] if n == 1 else ["x", "y**2"],
        initial=dict(kind="gaussian", mean=[0.0] * n, cov=np.eye(n).tolist()),
        domain=dict(radius=radius, center=center),
        discretization=dict(dt=dt, basis=basis, mesh=mesh, order=order, substeps=4))))


@pytest.fixture(scope="module")
def disk():
    return precompute(make_model(2, basis=40, mesh=6))


def test_array_contract(disk):
    arrays = disk.to_arrays()
    assert set(arrays) == set(ARRAY_NAMES) | {"generator"}  # "frame" only for a moving frame (test_frame)
    assert set(OPTIONAL_ARRAYS) == {"generator", "frame"}
    q, n = arrays["nodes"].shape
    size = disk.size
    assert (n, size) == (2, 40)
    assert arrays["basis"].shape == arrays["propagator_fp"].shape == arrays["propagator_k"].shape == (q, size)
    assert arrays["projector"].shape == (size, q)
    assert arrays["mesh_points"].shape[0] == 2 and arrays["mesh_cells"].shape[0] == 3
    assert np.all(arrays["weights"] > 0)
    # quadrature of a function vanishing on ∂B_R: ∫(R² − |x|²) = πR⁴/2 (O(h²) lumping error)
    r2 = (arrays["nodes"] ** 2).sum(axis=1)
    assert arrays["weights"] @ (9.0 - r2) == pytest.approx(np.pi * 81 / 2, rel=0.03)
    np.testing.assert_allclose(arrays["projector"] @ arrays["basis"], np.eye(size), atol=1e-10)
    assert all(np.all(np.isfinite(v)) for v in arrays.values())
    # nodes are interior: strictly inside the ball
    assert np.linalg.norm(arrays["nodes"], axis=1).max() < 3.0


def test_round_trip(disk):
    arrays = {k: np.array(v, copy=True) for k, v in disk.to_arrays().items()}
    again = OfflineModel.from_arrays(disk.model, arrays)
    for name in ARRAY_NAMES:
        np.testing.assert_array_equal(getattr(again, name), getattr(disk, name))
    pts = np.random.default_rng(1).uniform(-3, 3, size=(50, 2))
    np.testing.assert_array_equal(again.evaluate_basis(pts), disk.evaluate_basis(pts))


@pytest.mark.slow
def test_workers_give_the_same_arrays(disk):
    progress = []
    two = precompute(disk.model, workers=2, progress=lambda done, total: progress.append((done, total)))
    for name in ARRAY_NAMES:
        np.testing.assert_allclose(getattr(two, name), getattr(disk, name), rtol=0, atol=1e-12)
    assert progress[-1] == (40, 40)
    assert [d for d, _ in progress] == sorted(d for d, _ in progress)


def test_evaluate_basis_at_nodes_and_outside(disk):
    np.testing.assert_allclose(disk.evaluate_basis(disk.nodes), disk.basis, atol=1e-12)
    outside = np.array([[3.5, 0.0], [0.0, -10.0], [2.2, 2.2]])
    np.testing.assert_array_equal(disk.evaluate_basis(outside), 0.0)


def test_evaluate_basis_is_the_linear_interpolant_in_2d(disk):
    """Between nodes a P1 function is linear: at an edge midpoint it is the mean of the ends."""
    cells = disk.mesh_cells
    p = disk.mesh_points
    nodal = np.zeros((p.shape[1], disk.size))
    nodal[disk.node_index] = disk.basis
    mid = 0.5 * (p[:, cells[0]] + p[:, cells[1]]).T
    expected = 0.5 * (nodal[cells[0]] + nodal[cells[1]])
    np.testing.assert_allclose(disk.evaluate_basis(mid), expected, atol=1e-12)


def test_evaluate_basis_matches_sines_in_1d():
    """Interval (c − R, c + R): φ_k = sin(kπ(x − c + R)/2R)/√R up to the FE error, signs fixed."""
    radius, center = 2.0, 0.5
    off = precompute(make_model(1, radius=radius, basis=6, mesh=48, center=[center]))
    x = np.linspace(center - radius - 1, center + radius + 1, 301)[:, None]
    values = off.evaluate_basis(x)
    k = np.arange(1, 7)
    inside = np.abs(x[:, 0] - center) <= radius
    exact = np.sin(np.outer(x[:, 0] - center + radius, k) * np.pi / (2 * radius)) / np.sqrt(radius)
    exact[~inside] = 0.0
    signs = np.sign((values * exact).sum(axis=0))
    np.testing.assert_allclose(values * signs, exact, atol=2e-4)


def test_default_mesh_sizes():
    """About two interior nodes per basis function (1-D P2: Q = 4·mesh − 1; 2-D rings)."""
    spec = load_spec("examples/cubic_sensor.toml")  # the example sets mesh; here the default
    spec = spec.model_copy(update={"discretization": spec.discretization.model_copy(update={"mesh": None})})
    off = precompute(compile_model(spec))
    assert 2 * off.size <= off.nodes.shape[0] < 2 * off.size + 4
    assert int(off.element_order) == 2
    q = precompute(make_model(2, basis=50)).nodes.shape[0]
    assert 100 <= q <= 140


def test_off_centre_disk():
    """B_R(c) with c ≠ 0: nodes inside, the first mode is the Bessel mode J0(j₀,₁|x − c|/R) (up to scale)."""
    from scipy.special import j0, jn_zeros

    centre = np.array([1.5, -2.0])
    off = precompute(make_model(2, radius=2.0, basis=6, mesh=16, center=centre.tolist()))
    r = np.linalg.norm(off.nodes - centre, axis=1)
    assert r.max() < 2.0
    profile = j0(jn_zeros(0, 1)[0] * r / 2.0)
    first = off.basis[:, 0] / np.sqrt(off.weights @ off.basis[:, 0] ** 2)
    profile /= np.sqrt(off.weights @ profile**2)
    assert np.sqrt(off.weights @ (first - profile) ** 2) < 0.02
    assert np.all(off.evaluate_basis(np.array([[0.0, 0.0], [3.6, -2.0]])) == 0.0)


def test_small_3d():
    off = precompute(make_model(3, radius=2.0, basis=20, mesh=2))
    np.testing.assert_allclose(off.projector @ off.basis, np.eye(20), atol=1e-10)
    np.testing.assert_allclose(off.evaluate_basis(off.nodes), off.basis, atol=1e-12)
    assert np.all(np.isfinite(off.propagator_k))


def test_bad_input(disk):
    arrays = disk.to_arrays()
    with pytest.raises(InputError) as err:
        OfflineModel.from_arrays(disk.model, {k: v for k, v in arrays.items() if k != "projector"})
    assert err.value.field == "arrays.projector"
    with pytest.raises(InputError) as err:
        OfflineModel.from_arrays(disk.model, {**arrays, "weights": arrays["weights"][:-1]})
    assert err.value.field == "arrays.weights"
    bad = arrays["propagator_fp"].copy()
    bad[0, 0] = np.nan
    with pytest.raises(InputError) as err:
        OfflineModel.from_arrays(disk.model, {**arrays, "propagator_fp": bad})
    assert err.value.field == "arrays.propagator_fp"
    with pytest.raises(InputError) as err:
        disk.evaluate_basis(np.zeros((3, 3)))
    assert err.value.field == "points"
    with pytest.raises(InputError):
        disk.evaluate_basis([[np.inf, 0.0]])
    with pytest.raises(InputError):
        precompute(disk.model, workers=0)
    with pytest.raises(SpecError) as err:
        precompute(make_model(1, basis=100, mesh=4))
    assert err.value.field == "discretization.basis"
    with pytest.raises(SpecError) as err:  # rejected before any mesh is built
        precompute(make_model(2, basis=10, mesh=4000))
    assert err.value.field == "discretization.mesh"
    with pytest.raises(SpecError) as err:  # five refinements (41727 nodes, Lanczos) is the finest ball
        precompute(make_model(3, basis=10, mesh=6))
    assert err.value.field == "discretization.mesh" and "at most 5" in str(err.value)
