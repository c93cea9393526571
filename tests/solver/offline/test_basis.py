"""The L²(B_R)-orthonormal basis: orthonormality in the FE mass inner product, exact left
inverse, and eigenvalues against the closed-form Dirichlet spectrum of −½Δ on the ball:

    interval (−R, R):  λ_k = ½ (kπ / 2R)²,   disk:  λ_1 = ½ (j₀,₁ / R)²,   ball:  λ_1 = ½ (π / R)².
"""

import numpy as np
import pytest
from scipy.special import jn_zeros
from skfem import BilinearForm, asm
from yauyau.solver import compile_model, spec_from_dict
from yauyau.solver.offline import fem
from yauyau.solver.offline.basis import eigenbasis


def make_model(n, radius, basis, mesh=None, order=2, center=None):
    state = ["x", "y", "z"][:n]
    return compile_model(spec_from_dict(dict(
        name="b", state=state, drift=["0"] * n, observation=["x"],
        initial=dict(kind="gaussian", mean=[0.0] * n, cov=np.eye(n).tolist()),
        domain=dict(radius=radius, center=center),
        discretization=dict(dt=0.01, basis=basis, mesh=mesh, order=order))))


def consistent_mass(space):
    """The FE mass matrix ∫φ_iφ_j (all DOFs, assembled here, independently)."""
    return asm(BilinearForm(lambda u, v, w: u * v), space.basis).tocsr()


def basis_of(model):
    space = fem.discretise(model)
    ops = fem.assemble(model, space)
    return space, ops, eigenbasis(ops.half_stiffness, ops.weights, model.spec.discretization.basis)


@pytest.mark.parametrize("n, radius, size, mesh, order", [
    (1, 3.0, 40, 32, 2), (1, 3.0, 40, 64, 1), (2, 2.0, 60, 8, 1), (3, 1.5, 30, 3, 1)])
def test_gram_is_identity_and_projector_inverts(n, radius, size, mesh, order):
    model = make_model(n, radius, size, mesh, order)
    space, ops, basis = basis_of(model)
    mass = consistent_mass(space)
    idx = space.interior
    # the FE inner product of the method is the lumped mass: row sums of the consistent one
    lumped = np.asarray(mass.sum(axis=1)).ravel()[idx]
    np.testing.assert_allclose(ops.weights, lumped, rtol=1e-12)
    gram = basis.values.T @ (lumped[:, None] * basis.values)
    np.testing.assert_allclose(gram, np.eye(size), atol=1e-10)
    # and the consistent mass agrees on the smooth low modes up to the O(h²) lumping error
    # (the 3-D ball here has only 8 cells across the radius)
    low = basis.values[:, :3]
    gram_consistent = low.T @ (mass[idx][:, idx] @ low)
    np.testing.assert_allclose(gram_consistent, np.eye(3), atol={1: 0.01, 2: 0.05, 3: 0.15}[n])
    np.testing.assert_allclose(basis.projector @ basis.values, np.eye(size), atol=1e-10)
    assert np.all(ops.weights > 0)
    assert np.all(np.diff(basis.eigenvalues) >= -1e-12)


def test_lumped_mass_integrates_polynomials():
    """Σ w_i p(x_i) = ∫ p for the interval P2 (Simpson: exact to degree 3; p = 0 on ∂B_R)."""
    model = make_model(1, 2.0, 10, mesh=8, order=2)
    space, ops, _ = basis_of(model)
    x = space.nodes[:, 0]
    assert ops.weights @ ((4.0 - x**2) * (x + 1.0)) == pytest.approx(32 / 3, rel=1e-12)


def test_interval_spectrum_and_eigenfunctions():
    radius, size = 3.0, 12
    model = make_model(1, radius, size, mesh=64, order=2, center=[1.0])
    space, _, basis = basis_of(model)
    k = np.arange(1, size + 1)
    exact = 0.5 * (k * np.pi / (2 * radius)) ** 2
    np.testing.assert_allclose(basis.eigenvalues, exact, rtol=1e-5)
    # the first eigenfunction is sin(π(x − c + R)/2R)/√R, positive (sign convention)
    x = space.nodes[:, 0]
    phi1 = np.sin(np.pi * (x - 1.0 + radius) / (2 * radius)) / np.sqrt(radius)
    np.testing.assert_allclose(basis.values[:, 0], phi1, atol=1e-6)


def test_interval_eigenvalues_converge_p1_rate_two():
    errors = []
    for mesh in (16, 32, 64):
        _, _, basis = basis_of(make_model(1, 1.0, 4, mesh=mesh, order=1))
        errors.append(abs(basis.eigenvalues[3] - 0.5 * (4 * np.pi / 2) ** 2))
    ratio = np.array(errors[:-1]) / np.array(errors[1:])
    assert np.all((ratio > 3.7) & (ratio < 4.3)), ratio


def test_disk_first_eigenvalue_bessel_zero():
    radius = 2.0
    exact = 0.5 * (jn_zeros(0, 1)[0] / radius) ** 2
    errors = [abs(basis_of(make_model(2, radius, 3, mesh=m, order=1))[2].eigenvalues[0] - exact)
              for m in (8, 16)]
    assert errors[1] < 0.01 * exact
    assert errors[0] / errors[1] > 3.0, errors


def test_ball_first_eigenvalue():
    radius = 1.5
    exact = 0.5 * (np.pi / radius) ** 2
    _, _, basis = basis_of(make_model(3, radius, 3, mesh=3, order=1))
    assert basis.eigenvalues[0] == pytest.approx(exact, rel=0.03)


def test_too_many_basis_functions_is_a_spec_error():
    from yauyau.solver.errors import SpecError

    model = make_model(1, 1.0, 40, mesh=4, order=1)
    with pytest.raises(SpecError) as err:
        fem.discretise(model)
    assert err.value.field == "discretization.basis"


def ball_dirichlet_spectrum(radius, count):
    """The lowest eigenvalues of −½Δ on the ball with u = 0 on the sphere: ½ (z/R)² for every zero z
    of the spherical Bessel function j_l, with multiplicity 2l + 1 (found here by bracketing)."""
    from scipy.optimize import brentq
    from scipy.special import spherical_jn

    values = []
    grid = np.linspace(0.1, 20.0, 4000)
    for ell in range(8):
        f = spherical_jn(ell, grid)
        for i in np.flatnonzero(np.sign(f[:-1]) != np.sign(f[1:])):
            zero = brentq(lambda z, degree: spherical_jn(degree, z), grid[i], grid[i + 1], args=(ell,))
            values += [0.5 * (zero / radius) ** 2] * (2 * ell + 1)
    return np.sort(values)[:count]


@pytest.mark.slow
def test_lanczos_ball_spectrum_converges_and_matches_the_dense_solve(monkeypatch):
    """Above DENSE_NODES the basis comes from shift-invert Lanczos: forced here on meshes the dense
    solve also handles.  The 17 lowest eigenvalues (full multiplets l = 0, 1, 2, 3 and the second
    l = 0) converge to the closed form at the P1 rate, the Gram matrix is I, and the result is the
    same on a second run (a fixed start vector)."""
    import yauyau.solver.offline.basis as basis_module

    radius, size = 2.0, 17
    exact = ball_dirichlet_spectrum(radius, size)
    dense = basis_of(make_model(3, radius, size, mesh=3, order=1))[2]
    monkeypatch.setattr(basis_module, "DENSE_NODES", 0)
    errors = []
    for mesh in (3, 4):
        _, ops, basis = basis_of(make_model(3, radius, size, mesh=mesh, order=1))
        gram = basis.values.T @ (ops.weights[:, None] * basis.values)
        np.testing.assert_allclose(gram, np.eye(size), atol=1e-9)
        np.testing.assert_allclose(basis.projector @ basis.values, np.eye(size), atol=1e-9)
        # the mesh splits each multiplet slightly: compare the multiplets' means
        groups = np.unique(np.round(exact, 9), return_inverse=True)[1]
        means = np.bincount(groups, basis.eigenvalues) / np.bincount(groups)
        errors.append(np.abs(means / (np.bincount(groups, exact) / np.bincount(groups)) - 1.0))
        if mesh == 3:
            np.testing.assert_allclose(basis.eigenvalues, dense.eigenvalues, rtol=1e-9)
            again = basis_of(make_model(3, radius, size, mesh=mesh, order=1))[2]
            np.testing.assert_array_equal(again.values, basis.values)
    assert errors[1].max() < 0.02, errors[1]
    assert np.all(errors[0] / errors[1] > 3.0), errors[0] / errors[1]


@pytest.mark.slow
def test_node_counts_of_the_refined_balls_are_those_built():
    """The node table a service checks before it accepts a precompute (fem.planned_nodes) against
    the meshes themselves, up to the finest 3-D ball (beyond the dense eigensolver)."""
    for resolution in (1, 2, 3, 4, 5):
        built = fem.build(3, np.zeros(3), 1.0, resolution, 1)
        assert fem.interior_count(3, 1, resolution) == len(built.interior)
