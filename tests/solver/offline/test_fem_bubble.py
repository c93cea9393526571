"""``element = "bubble"``: P2 plus bubbles with a lumped mass (solver/offline/fem.py), against exact truth.

Truth, 2-D: the element's nodal quadrature |T|/20 (vertices), 2|T|/15 (edge midpoints), 9|T|/20
(centroid), which integrates cubics exactly (checked here on x³ and x²y over the triangles); the Dirichlet
eigenvalues of the unit disk, j_{k,1}² (Bessel zeros); a quadratic, which the element reproduces exactly;
and the exact Kalman filter of a 2-D OU model.  3-D: the 15-node tetrahedron's weights derived here with
SymPy from its nodal basis (17/840, 4/105, 27/280, 32/105 of |T|) and their exactness for cubics; a
quadratic reproduced exactly; the exact Kalman filter of tests/solver/engine/test_engine_3d.py's model.
"""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sps
from scipy.special import jn_zeros
from skfem import Basis, ElementTetCCR, ElementTetP1, ElementTriP1, LinearForm, asm
from yauyau.solver import compile_model, spec_from_dict
from yauyau.solver.engine.filter import build
from yauyau.solver.exact.kalman_bucy import KalmanBucyFilter
from yauyau.solver.offline import fem
from yauyau.solver.offline.pipeline import precompute
from yauyau.solver.simulate import simulate

OU = {"name": "ou2", "state": ["x", "y"], "drift": ["-0.5*x", "-0.5*y"], "observation": ["x", "y"],
      "method": "yau-yau",
      "initial": {"kind": "gaussian", "mean": [0.0, 0.0], "cov": [[1.0, 0.0], [0.0, 1.0]]},
      "domain": {"radius": 6.0}}


def _triangle_areas(space):
    p, t = space.mesh.p, space.mesh.t
    a, b, c = p[:, t[0]], p[:, t[1]], p[:, t[2]]
    return 0.5 * np.abs((b - a)[0] * (c - a)[1] - (b - a)[1] * (c - a)[0])


def test_the_lumped_weights_are_the_positive_nodal_quadrature_exact_for_cubics():
    space = fem.build(2, np.zeros(2), 1.0, 6, 2)
    weights = fem.lumped_mass(space.basis, space)
    areas = _triangle_areas(space)
    bubbles = space.basis.element_dofs[-1]
    assert np.all(weights > 0)
    assert np.allclose(weights[bubbles], 9 * areas / 20, rtol=1e-12)  # the centroid's weight
    assert np.isclose(weights.sum(), areas.sum(), rtol=1e-12)  # the polygon's area
    # exact for cubics: Σ w_i g(x_i) = ∫ g over the polygon (scikit-fem's Gauss rule of order 4)
    x = space.basis.doflocs.T
    for g in (lambda P: P[:, 0] ** 3, lambda P: P[:, 0] ** 2 * P[:, 1] + P[:, 1] ** 2):
        form = LinearForm(lambda v, w, g=g: g(np.stack([w.x[0].ravel(), w.x[1].ravel()], 1))
                          .reshape(w.x[0].shape) * v)
        gauss = asm(form, Basis(space.mesh, ElementTriP1(), intorder=4)).sum()  # Σ of P1 functions = 1
        assert np.isclose(weights @ g(x), gauss, rtol=1e-11, atol=1e-13)


def test_interpolation_reproduces_quadratics_and_the_basis_is_orthonormal():
    doc = {**OU, "discretization": {"dt": 0.01, "basis": 120, "element": "bubble"}}
    offline = precompute(compile_model(spec_from_dict(doc)))
    assert int(offline.element_order) == 2
    q = lambda P: 1 + P[:, 0] - 2 * P[:, 1] + 0.3 * P[:, 0] ** 2 + 0.2 * P[:, 0] * P[:, 1]  # noqa: E731
    points = np.random.default_rng(0).uniform(-3, 3, (300, 2))  # in triangles off the boundary (q = 0 there)
    assert np.abs(offline.interpolate(q(offline.nodes), points) - q(points)).max() < 1e-11
    gram = offline.basis.T @ (offline.weights[:, None] * offline.basis)
    assert np.abs(gram - np.eye(offline.size)).max() < 1e-10


def _eigen_error(order: int, rings: int) -> float:
    space = fem.build(2, np.zeros(2), 1.0, rings, order)
    idx = space.interior
    K = space.nodal(fem.stiffness(space.basis, np.eye(2)))[idx][:, idx]
    w = fem.lumped_mass(space.basis, space)[idx]
    scale = sps.diags(1 / np.sqrt(w))
    lam = np.sort(np.linalg.eigvalsh((scale @ K @ scale).toarray()))[:4]
    exact = np.array(sorted([jn_zeros(0, 1)[0] ** 2, jn_zeros(1, 1)[0] ** 2, jn_zeros(1, 1)[0] ** 2,
                             jn_zeros(2, 1)[0] ** 2]))
    return float(np.abs(lam / exact - 1).max())


@pytest.mark.slow
def test_disk_eigenvalues_converge_and_beat_p1_on_the_same_mesh():
    """The polygonal boundary keeps both elements second order in h; the bubble element's constant is
    ~10x smaller (measured 0.0122, 0.0029 at 4, 8 rings; P1 0.111, 0.029)."""
    coarse, fine = _eigen_error(2, 4), _eigen_error(2, 8)
    assert fine < 0.004 and 3.5 < coarse / fine < 4.6
    assert _eigen_error(1, 8) > 5 * fine


@pytest.mark.slow
@pytest.mark.parametrize("order, bound", [(2, 0.015), (1, 0.08)])  # 2: bubble, 1: the P1 default
def test_a_2d_ou_filter_against_kalman_at_the_default_basis(order, bound):
    """Basis 300, the default mesh: P2+bubble 0.011 from Kalman (Q = 613), P1 0.058 (Q = 631)."""
    doc = {**OU, "discretization": {"dt": 0.01, "basis": 300, "order": 2,
                                    "element": "bubble" if order == 2 else "lagrange"}}
    model = compile_model(spec_from_dict(doc))
    flt = build(model, precompute(model))
    increments = simulate(model, 3000, np.random.default_rng(3)).increments
    _, result = flt.run_arrays(flt.initial_state(), increments)
    kalman = KalmanBucyFilter(model, kind="discrete")
    _, exact = kalman.run_arrays(kalman.initial_state(), increments)
    gap = float(np.abs(result.mean - exact.mean).max())
    print(f"order {order}: Q = {len(flt.nodes)}, gap {gap:.2e}")
    assert 550 < len(flt.nodes) < 700 and gap <= bound
    if order == 1:
        assert gap > 3 * 0.015  # the bubble element is several times closer at the same cost


def test_bubble_is_refused_in_1d_and_at_order_1_and_leaves_other_ids_alone():
    from yauyau.solver.errors import SpecError

    with pytest.raises(SpecError) as caught:
        spec_from_dict({**OU, "discretization": {"dt": 0.01, "basis": 50, "order": 1, "element": "bubble"}})
    assert caught.value.field == "discretization.element"
    one = {"name": "ou1", "state": ["x"], "drift": ["-x"], "observation": ["x"], "domain": {"radius": 5.0},
           "initial": {"kind": "gaussian", "mean": [0.0], "cov": [[1.0]]},
           "discretization": {"dt": 0.01, "basis": 20, "element": "bubble"}}
    with pytest.raises(SpecError) as caught:
        spec_from_dict(one)
    assert caught.value.field == "discretization.element" and "2 or 3 state variables" in str(caught.value)
    plain = spec_from_dict({**OU, "discretization": {"dt": 0.01, "basis": 50}})
    assert "element" not in plain.canonical_json()
    assert "bubble" in spec_from_dict({**OU, "discretization": {"dt": 0.01, "basis": 50,
                                                                 "element": "bubble"}}).canonical_json()


# -- 3-D: P2 plus four cubic face bubbles and the quartic interior bubble (scikit-fem's ElementTetCCR) --
def _tet_weights_by_sympy() -> list:
    """∫ψ_i / |T| of the nodal basis of P2 + λ_iλ_jλ_k (faces) + λ₀λ₁λ₂λ₃ on the reference tetrahedron,
    nodes in scikit-fem's order (4 vertices, 6 edge midpoints, 4 face centroids, the centroid)."""
    import itertools

    import sympy as sp

    x, y, z = sp.symbols("x y z")
    lam = [1 - x - y - z, x, y, z]
    space = [sp.Integer(1), x, y, z, x * x, y * y, z * z, x * y, y * z, x * z]
    space += [lam[i] * lam[j] * lam[k] for i, j, k in itertools.combinations(range(4), 3)]
    space.append(lam[0] * lam[1] * lam[2] * lam[3])
    nodes = [[sp.nsimplify(c, tolerance=1e-12, rational=True) for c in v] for v in ElementTetCCR().doflocs]
    values = sp.Matrix([[f.subs({x: p[0], y: p[1], z: p[2]}) for f in space] for p in nodes])
    integral = sp.Matrix([sp.integrate(f, (z, 0, 1 - x - y), (y, 0, 1 - x), (x, 0, 1)) for f in space])
    return list(6 * values.inv().T * integral)  # ψ = (values⁻¹)ᵀ-combination of the space; |T| = 1/6


def _volumes(space):
    p, t = space.mesh.p, space.mesh.t
    a = p[:, t[0]]
    return np.abs(np.einsum("ij,ij->j", p[:, t[1]] - a, np.cross(p[:, t[2]] - a, p[:, t[3]] - a, axis=0))) / 6


def test_tetrahedron_lumped_weights_are_mulders_positive_quadrature_exact_for_cubics():
    import sympy as sp

    derived = _tet_weights_by_sympy()
    expected = [sp.Rational(17, 840)] * 4 + [sp.Rational(4, 105)] * 6 + [sp.Rational(27, 280)] * 4 + [
        sp.Rational(32, 105)]
    assert [sp.nsimplify(w) for w in derived] == expected and sum(expected) == 1
    space = fem.build(3, np.array([0.3, -0.2, 0.1]), 2.0, 2, 2)
    weights = fem.lumped_mass(space.basis, space)
    volumes = _volumes(space)
    assert np.all(weights > 0)
    interior = space.basis.element_dofs[-1]  # one centroid DOF per tetrahedron
    assert np.allclose(weights[interior], 32 * volumes / 105, rtol=1e-12)
    assert np.isclose(weights.sum(), volumes.sum(), rtol=1e-12)
    x = space.basis.doflocs.T
    cubics = (lambda P: P[:, 0] ** 3 + 2 * P[:, 1],
              lambda P: P[:, 0] ** 2 * P[:, 1] + P[:, 2] ** 2 + P[:, 1] * P[:, 2],
              lambda P: P[:, 0] * P[:, 1] * P[:, 2] + 1)
    for g in cubics:
        form = LinearForm(lambda v, w, g=g: g(np.stack([c.ravel() for c in w.x], 1))
                          .reshape(w.x[0].shape) * v)
        gauss = asm(form, Basis(space.mesh, ElementTetP1(), intorder=4)).sum()
        assert np.isclose(weights @ g(x), gauss, rtol=1e-11, atol=1e-12)
    quartic = lambda P: P[:, 0] ** 4  # noqa: E731 -- beyond the rule's degree: not exact
    form = LinearForm(lambda v, w: quartic(np.stack([c.ravel() for c in w.x], 1)).reshape(w.x[0].shape) * v)
    gauss = asm(form, Basis(space.mesh, ElementTetP1(), intorder=5)).sum()
    assert not np.isclose(weights @ quartic(x), gauss, rtol=1e-8)


@pytest.mark.slow
def test_3d_bubble_interpolation_reproduces_quadratics_and_the_basis_is_orthonormal():
    doc = {"name": "ou3", "state": ["x", "y", "z"], "drift": ["-x", "-y", "-z"], "observation": ["x"],
           "method": "yau-yau", "domain": {"radius": 3.0},
           "initial": {"kind": "gaussian", "mean": [0.0, 0.0, 0.0], "cov": np.eye(3).tolist()},
           "discretization": {"dt": 0.02, "basis": 150, "mesh": 2, "element": "bubble"}}
    offline = precompute(compile_model(spec_from_dict(doc)))
    assert int(offline.element_order) == 2 and len(offline.nodes) == fem.BALL_INTERIOR_BUBBLE[2]
    q = lambda P: 1 + P[:, 0] - 2 * P[:, 2] + 0.3 * P[:, 0] ** 2 + 0.2 * P[:, 1] * P[:, 2]  # noqa: E731
    points = np.random.default_rng(0).uniform(-0.8, 0.8, (400, 3))  # in tetrahedra off the boundary
    assert np.abs(offline.interpolate(q(offline.nodes), points) - q(points)).max() < 1e-11
    # anywhere inside (near the sphere too, where the boundary DOFs are 0), as scikit-fem's own element
    # finder and basis evaluate the same nodal values
    full = np.zeros(offline.space.basis.N)
    full[offline.node_index] = q(offline.nodes)
    anywhere = np.random.default_rng(1).uniform(-1.6, 1.6, (400, 3))
    assert np.allclose(offline.interpolate(q(offline.nodes), anywhere),
                       offline.space.basis.probes(anywhere.T) @ full, atol=1e-11)
    gram = offline.basis.T @ (offline.weights[:, None] * offline.basis)
    assert np.abs(gram - np.eye(offline.size)).max() < 1e-10


def test_3d_bubble_beyond_three_refinements_is_refused_by_name_before_any_mesh():
    from yauyau.solver.errors import SpecError

    doc = {"name": "ou3", "state": ["x", "y", "z"], "drift": ["-x", "-y", "-z"], "observation": ["x"],
           "method": "yau-yau", "domain": {"radius": 3.0},
           "initial": {"kind": "gaussian", "mean": [0.0, 0.0, 0.0], "cov": np.eye(3).tolist()},
           "discretization": {"dt": 0.02, "basis": 150, "mesh": 4, "element": "bubble"}}
    spec = spec_from_dict(doc)
    assert fem.planned_nodes(spec) == 139007 > fem.MAX_NODES  # what a service checks before a precompute
    with pytest.raises(SpecError) as caught:
        fem.discretise(compile_model(spec))
    assert caught.value.field == "discretization.mesh" and "at most 3" in str(caught.value)
    doc["discretization"]["mesh"] = None
    assert fem.planned_nodes(spec_from_dict(doc)) == fem.BALL_INTERIOR_BUBBLE[2]  # the first with ≥ 2N nodes


@pytest.mark.slow
@pytest.mark.parametrize("n, element", [(2, "lagrange"), (2, "bubble"), (3, "lagrange"), (3, "bubble")])
def test_the_interpolation_matrix_is_scikit_fems_own_evaluation(n, element):
    """``OfflineModel.interpolation_matrix`` (what a move carries with) against scikit-fem's element
    finder and basis on the same nodal values (through P⁻¹ for the hierarchical triangle), and 0 outside
    the ball."""
    state = ["x", "y", "z"][:n]
    doc = {"name": "ou", "state": state, "drift": [f"-{s}" for s in state], "observation": [state[0]],
           "method": "yau-yau", "domain": {"radius": 3.0},
           "initial": {"kind": "gaussian", "mean": [0.0] * n, "cov": np.eye(n).tolist()},
           "discretization": {"dt": 0.02, "basis": 40, "mesh": 2 if n == 3 else 5, "element": element}}
    offline = precompute(compile_model(spec_from_dict(doc)))
    nodal = np.random.default_rng(2).standard_normal(len(offline.nodes))
    points = np.random.default_rng(3).uniform(-3.5, 3.5, (500, n))
    points[:5] = offline.nodes[:5]  # at nodes: the nodal values themselves
    ours = offline.interpolation_matrix(points) @ nodal
    assert np.allclose(ours[:5], nodal[:5], atol=1e-12)
    space = offline.space
    full = np.zeros(space.basis.N)
    full[offline.node_index] = nodal
    coefficients = full if space.to_nodal is None else space.to_nodal @ full
    within = np.linalg.norm(points, axis=1) < 0.8 * 3.0  # inside the meshed polygon / polyhedron
    assert within.sum() > 50
    assert np.allclose(ours[within], space.basis.probes(points[within].T) @ coefficients, atol=1e-12)
    outside = np.linalg.norm(points, axis=1) >= 3.0
    assert outside.sum() > 50 and np.all(ours[outside] == 0.0)


@pytest.mark.parametrize("n", [1, 2, 3])
def test_barycentric_coordinates_rebuild_the_point(n):
    """fem.barycentric (Cramer's rule in 2-D and 3-D, a solve otherwise) against the definition:
    Σ λ_i v_i = X and Σ λ_i = 1, for random simplices, each point against several candidates."""
    rng = np.random.default_rng(n)
    points = rng.normal(size=(n, 40))
    cells = np.array([rng.choice(40, n + 1, replace=False) for _ in range(25)]).T
    elem = rng.integers(0, 25, size=(30, 6))
    X = rng.normal(size=(30, n))
    lam = fem.barycentric(points, cells, elem, X)
    assert lam.shape == (30, 6, n + 1)
    vertices = points[:, cells[:, elem]]  # (n, n+1, P, k)
    rebuilt = np.einsum("cvpk,pkv->pkc", vertices, lam)
    assert np.abs(rebuilt - X[:, None, :]).max() < 1e-9
    assert np.abs(lam.sum(axis=-1) - 1.0).max() < 1e-12
    if n > 1:  # a cell of zero area or volume: no coordinates, no warning, and no point found in it
        flat = np.zeros((n, n + 1))
        flat[0] = np.arange(n + 1)
        import warnings

        with warnings.catch_warnings():
            warnings.simplefilter("error")
            lam = fem.barycentric(flat, np.arange(n + 1)[:, None], np.zeros((1, 1), dtype=int), X[:1])
        assert not np.isfinite(lam).all()
