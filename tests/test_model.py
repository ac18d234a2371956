"""The model object: transition, analytic Jacobians, measurement, covariances (Eqs. 19-22, 31-34)."""
import numpy as np
import pytest
from helpers import random_block_mesh, random_material, small_model
from hypothesis import given, settings
from hypothesis import strategies as st

from sfem_filters.fem.material import Material, Parameterisation
from sfem_filters.model import SFEMModel


def _state(model, rng):
    n = model.dim_x // 2
    x = np.concatenate([rng.standard_normal(n) * 1e-4, rng.standard_normal(n) * 1e-3])
    return np.concatenate([x, model.x0[model.dim_x:]])


def _fd_jacobian(model, z, t, h=1e-2):
    """Central differences of fx in the material parameters (h in log E / logit 2 nu)."""
    nx = model.dim_x
    cols = []
    for j in range(model.dim_theta):
        zp, zm = z.copy(), z.copy()
        zp[nx + j] += h
        zm[nx + j] -= h
        cols.append((model.fx(zp, t)[:nx] - model.fx(zm, t)[:nx]) / (2 * h))
    return np.array(cols).T


@settings(max_examples=8, deadline=None)
@given(seed=st.integers(0, 10_000))
def test_F_jacobian_against_finite_differences(seed):
    """The theta block M_t of F agrees with central differences (O(h^2) with h = 1e-2)."""
    rng = np.random.default_rng(seed)
    model = small_model(rng)
    z = _state(model, rng)
    F = model.F_jacobian(z, 1)
    fd = _fd_jacobian(model, z, 1)
    Mt = F[:model.dim_x, model.dim_x:]
    assert np.abs(Mt - fd).max() <= 2e-3 * np.abs(fd).max()
    # and with a smaller step the agreement improves (the error is truncation, not a bug)
    fd2 = _fd_jacobian(model, z, 1, h=2.5e-3)
    assert np.abs(Mt - fd2).max() < np.abs(Mt - fd).max()


def test_F_jacobian_kinematic_block_is_A_and_theta_block_identity():
    rng = np.random.default_rng(5)
    model = small_model(rng)
    z = _state(model, rng)
    F = model.F_jacobian(z, 0)
    nx = model.dim_x
    # independent reference: the block exponential of Eqs. (14)-(16) at z's material
    from helpers import reduced_matrices

    from sfem_filters.fem.statespace import continuous_matrices, discretize_zoh
    M, K = reduced_matrices(model, model.material_of(z))
    A, _ = discretize_zoh(*continuous_matrices(M, K, model.alpha * M + model.beta * K), model.frame_interval)
    np.testing.assert_allclose(F[:nx, :nx], A, atol=1e-10 * np.abs(A).max())
    np.testing.assert_array_equal(F[nx:, nx:], np.eye(model.dim_theta))
    np.testing.assert_array_equal(F[nx:, :nx], 0.0)
    # fx is linear in x: the x block of F is its exact derivative
    dx = np.zeros_like(z)
    dx[:nx] = rng.standard_normal(nx) * 1e-5
    np.testing.assert_allclose(model.fx(z + dx, 0) - model.fx(z, 0), F @ dx, atol=1e-12 * np.abs(F @ dx).max())


def test_modal_M_t_equals_expm_frechet_reference():
    """The fast Jacobian and the reference one (expm_frechet per parameter) agree tightly."""
    rng = np.random.default_rng(11)
    mesh = random_block_mesh(rng)
    mat = random_material(rng, mesh.n_elements)
    fast = small_model(np.random.default_rng(1), mesh=mesh, material=mat)
    ref = small_model(np.random.default_rng(1), mesh=mesh, material=mat, jacobian="expm_frechet")
    z = _state(fast, rng)
    a, b = fast.F_jacobian(z, 2), ref.F_jacobian(z, 2)
    assert np.abs(a - b).max() <= 1e-8 * np.abs(b).max()


def test_region_parameterisation_chain_rule():
    """With one region per half of the mesh, M_t is the sum of the per-element columns of each region."""
    rng = np.random.default_rng(7)
    mesh = random_block_mesh(rng)
    labels = (mesh.centroids[:, 0] > 0.01).astype(int)
    mat = Material(np.where(labels, 9e4, 6e4), np.where(labels, 0.45, 0.35))
    per_el = small_model(np.random.default_rng(2), mesh=mesh, material=mat)
    per_reg = small_model(np.random.default_rng(2), mesh=mesh, material=mat,
                          parameterisation=Parameterisation.per_region(labels))
    assert per_reg.dim_theta == 4
    np.testing.assert_allclose(per_reg.material_of().E, mat.E)
    z_el = _state(per_el, rng)
    z_reg = np.concatenate([z_el[:per_el.dim_x], per_reg.x0[per_reg.dim_x:]])
    Mt_el = per_el.F_jacobian(z_el, 1)[:per_el.dim_x, per_el.dim_x:]
    Mt_reg = per_reg.F_jacobian(z_reg, 1)[:per_reg.dim_x, per_reg.dim_x:]
    n = mesh.n_elements
    for r in range(2):
        np.testing.assert_allclose(Mt_reg[:, r], Mt_el[:, :n][:, labels == r].sum(axis=1),
                                   atol=1e-12 * np.abs(Mt_el).max())
        np.testing.assert_allclose(Mt_reg[:, 2 + r], Mt_el[:, n:][:, labels == r].sum(axis=1),
                                   atol=1e-12 * np.abs(Mt_el).max())


def test_basis_parameterisation_against_finite_differences():
    rng = np.random.default_rng(9)
    mesh = random_block_mesh(rng)
    c = mesh.centroids / 0.02
    basis = np.column_stack([np.ones(mesh.n_elements), c[:, 0] - 0.5, c[:, 1] - 0.5])
    model = small_model(rng, mesh=mesh, parameterisation=Parameterisation.from_basis(basis),
                        material=Material.uniform(mesh.n_elements, 8e4, 0.4))
    z = _state(model, rng)
    z[model.dim_x:] += rng.standard_normal(model.dim_theta) * 0.1
    Mt = model.F_jacobian(z, 0)[:model.dim_x, model.dim_x:]
    fd = _fd_jacobian(model, z, 0, h=1e-3)
    assert np.abs(Mt - fd).max() <= 1e-4 * np.abs(fd).max()


@pytest.mark.parametrize("kind", ["element", "relative_regions", "basis_with_level"])
def test_physical_jacobian_against_finite_differences(kind):
    """d(E, nu)/d theta of the stop rule's rows equals central differences of
    physical_parameters, for an element, a relative-region and a levelled basis map."""
    rng = np.random.default_rng(11)
    mesh = random_block_mesh(rng)
    n = mesh.n_elements
    if kind == "element":
        param = Parameterisation.per_element(n)
    elif kind == "relative_regions":
        param = Parameterisation.relative_regions(np.arange(n) % 3, 1e4)
    else:
        c = mesh.centroids / 0.02
        param = Parameterisation.from_basis(np.column_stack([c[:, 0] - 0.5, c[:, 1] - 0.5])).with_level(1e4)
    model = small_model(rng, mesh=mesh, parameterisation=param, material=Material.uniform(n, 1e4, 0.4))
    theta = 0.3 * rng.standard_normal(param.n_params)
    J = model.physical_jacobian(theta).toarray()
    assert J.shape == (2 * n, param.n_params)
    h = 1e-6
    fd = np.column_stack([(model.physical_parameters(theta + h * e) - model.physical_parameters(theta - h * e)) / (2 * h)
                          for e in np.eye(param.n_params)])
    scale = np.abs(fd).max(axis=1, keepdims=True) + 1e-300
    assert np.abs((J - fd) / scale).max() < 1e-6


@given(theta=st.lists(st.floats(-36.0, 36.0), min_size=8, max_size=8))
def test_estimates_stay_admissible_for_any_theta(theta):
    """Every representable theta maps to E > 0 and 0 < nu < 0.5: nothing to clip."""
    mat = Parameterisation.per_element(4).material(np.array(theta))
    assert np.all(mat.E > 0)
    assert np.all((mat.nu > 0) & (mat.nu < 0.5))


def test_diverged_theta_is_an_error_not_a_boundary_value():
    """Where double precision would round nu to 0.5 (or E to inf), say so instead of clipping."""
    p = Parameterisation.per_element(2)
    with pytest.raises(FloatingPointError, match="theta: .* the estimate diverged"):
        p.material(np.array([11.0, 11.0, 0.0, 40.0]))
    with pytest.raises(FloatingPointError, match="theta: .* the estimate diverged"):
        p.material(np.array([800.0, 11.0, 0.0, 0.0]))
    with pytest.raises(FloatingPointError, match="theta: expected finite"):
        p.material(np.array([np.nan, 11.0, 0.0, 0.0]))


def test_measurement_function_and_covariances():
    rng = np.random.default_rng(4)
    model = small_model(rng)
    z = _state(model, rng)
    H = model.H_jacobian(z, 0)
    np.testing.assert_array_equal(model.hx(z, 0), H @ z)
    assert model.hx(z.reshape(-1, 1), 0).shape == (model.dim_obs, 1)
    np.testing.assert_array_equal(H[:, model.dim_x // 2:], 0.0)       # velocities and theta unobserved
    # P0 of Eq. (34): block diagonal, P2 (kinematics-material cross-covariance) zero
    nx = model.dim_x
    np.testing.assert_array_equal(model.P0[:nx, nx:], 0.0)
    for M in (model.P0, model.Q, model.R):
        np.testing.assert_array_equal(M, M.T)
        assert np.linalg.eigvalsh(M).min() >= 0
    np.testing.assert_allclose(model.material_of(model.x0).E, model.material.E)
    np.testing.assert_allclose(model.material_of(model.x0).nu, model.material.nu)


def test_fixed_material_model_is_linear_kf():
    rng = np.random.default_rng(6)
    model = small_model(rng, parameterisation=None)
    assert model.dim_state == model.dim_x and model.dim_theta == 0
    z = _state(model, rng)
    F = model.F_jacobian(z, 0)
    w = model.system().input_matrix() @ model.dofmap.restrict(model.loads[1])
    np.testing.assert_allclose(model.fx(z, 0), F @ z + w, atol=1e-12 * np.abs(F @ z).max())


def test_bad_arguments_are_named():
    rng = np.random.default_rng(0)
    model = small_model(rng)
    with pytest.raises(ValueError, match="z: expected a state of length"):
        model.fx(np.zeros(3), 0)
    with pytest.raises(ValueError, match=r"t: expected a frame index in \[0, 3\]"):
        model.fx(model.x0, 4)
    mesh = model.mesh
    with pytest.raises(ValueError, match="loads: expected shape"):
        SFEMModel(mesh, model.material, np.zeros((5, 3)), model.observation_operator, 0.01, model.dofmap.fixed)
    with pytest.raises(ValueError, match="frame_interval: expected a positive"):
        SFEMModel(mesh, model.material, model.loads, model.observation_operator, -1.0, model.dofmap.fixed)
    with pytest.raises(ValueError, match="measurement_std: expected standard deviations > 0"):
        SFEMModel(mesh, model.material, model.loads, model.observation_operator, 0.01, model.dofmap.fixed,
                  measurement_std=0.0)
    with pytest.raises(ValueError, match="nu: expected Poisson's ratios"):
        Material(np.ones(2), np.array([0.3, 0.5]))
    with pytest.raises(ValueError, match="E: expected Young's moduli > 0"):
        Material(np.array([1.0, -1.0]), np.array([0.3, 0.3]))


def test_relative_region_parameterisation_keeps_the_mean_log_E():
    """Contrasts move E between regions but never the mean log E (not identifiable without force)."""
    labels = np.repeat(np.arange(4), 3)
    p = Parameterisation.relative_regions(labels, 1e4)
    assert p.n_E == 3 and p.n_params == 7
    rng = np.random.default_rng(0)
    for _ in range(5):
        mat = p.material(rng.standard_normal(7))
        assert np.mean(np.log(mat.E)) == pytest.approx(np.log(1e4), abs=1e-12)
    start = Material.uniform(12, 1e4, 0.45)
    np.testing.assert_allclose(p.material(p.theta_of(start)).E, start.E)
    np.testing.assert_allclose(p.theta_of(start)[:3], 0.0, atol=1e-12)


def test_correlated_prior_is_spd_and_correlates_neighbours():
    from sfem_filters.fem.material import correlated_prior
    rng = np.random.default_rng(3)
    mesh = random_block_mesh(rng)
    p = Parameterisation.per_element(mesh.n_elements)
    C = correlated_prior(p, mesh.centroids, length=0.005, std_E=0.3, std_nu=1.0) + 1e-9 * np.eye(p.n_params)
    np.testing.assert_allclose(C, C.T)
    assert np.linalg.eigvalsh(C).min() > 0
    np.testing.assert_allclose(np.diag(C)[: mesh.n_elements], 0.09 + 1e-9)
    d = np.linalg.norm(mesh.centroids[:, None] - mesh.centroids[None], axis=2)
    i, j = np.unravel_index(np.argmin(d + np.eye(len(d)) * 1e9), d.shape)
    k = np.argmax(d[i])
    assert C[i, j] > C[i, k]                                      # nearer elements correlate more
    assert np.all(C[: mesh.n_elements, mesh.n_elements:] == 0)    # E and nu independent
    model = small_model(rng, mesh=mesh, parameterisation=p)
    m2 = SFEMModel(mesh, model.material, model.loads, model.observation_operator, 0.01, model.dofmap.fixed,
                   parameterisation=p, prior_cov=C)
    np.testing.assert_allclose(m2.P0[m2.dim_x:, m2.dim_x:], C)
    with pytest.raises(ValueError, match="prior_cov: expected a symmetric positive definite"):
        SFEMModel(mesh, model.material, model.loads, model.observation_operator, 0.01, model.dofmap.fixed,
                  parameterisation=p, prior_cov=-C)


def test_velocity_rows_observe_the_velocity_state():
    """H = [D 0; 0 D_v] (Eq. 13): velocity rows read U', displacement rows read U, at any point."""
    from sfem_filters.fem.observation import point_observation_matrix
    rng = np.random.default_rng(8)
    base = small_model(rng, parameterisation=None)
    mesh = base.mesh
    pts = mesh.centroids[:3]                                   # points that are not nodes
    Dp = point_observation_matrix(mesh, pts)
    m = SFEMModel(mesh, base.material, base.loads, Dp, 0.01, base.dofmap.fixed, velocity_operator=Dp,
                  measurement_std=np.r_[np.full(6, 1e-5), np.full(6, 1e-3)])
    assert m.dim_obs == 12
    z = rng.standard_normal(m.dim_state)
    U, V = m.displacements(z), m.velocities(z)
    y = m.hx(z, 0)
    np.testing.assert_allclose(y[:6], Dp @ U, atol=1e-14)
    np.testing.assert_allclose(y[6:], Dp @ V, atol=1e-14)
    # barycentric interpolation: a point at a centroid reads the mean of its triangle's nodes
    e = 0
    np.testing.assert_allclose(y[0], U[2 * mesh.elements[e]].mean(), atol=1e-14)


def test_per_frame_measurement_noise_is_used_frame_by_frame():
    """A 2D measurement_std gives R_at(t) per frame; the filter engines use it (same x, P
    as a model whose constant R equals that frame's, on a frame where they coincide)."""
    from sfem_filters.filtering import ENGINES, measurement_cov

    def build(noise):
        rng = np.random.default_rng(3)               # same mesh, loads and material each time
        return small_model(rng, noise=noise)

    base = build(1e-4)
    F, m = base.loads.shape[0], base.dim_obs
    sd = np.full((F, m), 1e-4)
    sd[1] = 3e-4
    model = build(sd)
    assert np.allclose(model.R_at(1), np.diag(np.full(m, 9e-8)))
    assert np.allclose(model.R_at(0), np.diag(np.full(m, 1e-8)))
    assert np.allclose(measurement_cov(model, 1), model.R_at(1))
    assert model.fingerprint() != build(np.full((F, m), 1e-4)).fingerprint()
    with pytest.raises(ValueError, match=r"measurement_std: expected shape"):
        build(np.ones((F + 1, m)))
    with pytest.raises(ValueError, match="measurement_std: expected standard deviations > 0"):
        build(np.zeros((F, m)))
    y = np.random.default_rng(0).standard_normal((F, m)) * 1e-4
    mask = np.ones(m, bool)
    results = []
    for mdl in (model, build(3e-4)):
        eng = ENGINES["structured"](mdl)
        eng.predict(0)
        eng.update(y[1], 1, mask)
        results.append((eng.x.copy(), eng.P.copy()))
    assert np.allclose(results[0][0], results[1][0], rtol=1e-12, atol=1e-18)
    assert np.allclose(results[0][1], results[1][1], rtol=1e-12, atol=1e-20)


@settings(max_examples=15, deadline=None)
@given(seed=st.integers(0, 10_000), kE=st.integers(1, 4), knu=st.integers(1, 4),
       length=st.floats(0.002, 0.05), relative=st.booleans())
def test_smooth_basis_is_the_kernels_leading_modes(seed, kE, knu, length, relative):
    """Parameterisation.smooth: the columns are eigenvectors of the (centred, if relative)
    squared-exponential kernel with its largest eigenvalues, unit RMS and mutually
    orthogonal; relative E modes keep the mean log E at the reference."""
    rng = np.random.default_rng(seed)
    mesh = random_block_mesh(rng, n_interior=int(rng.integers(3, 9)))
    c, n = mesh.centroids, mesh.n_elements
    p = Parameterisation.smooth(c, length, kE, knu, E_reference=7e4 if relative else None)
    kernel = np.exp(-np.sum((c[:, None] - c[None]) ** 2, axis=2) / (2 * length ** 2))
    C = np.eye(n) - 1.0 / n if relative else np.eye(n)
    for B, Kmat, k in ((p.basis_E.toarray(), C @ kernel @ C, kE), (p.basis_nu.toarray(), kernel, knu)):
        assert B.shape == (n, k)
        np.testing.assert_allclose(B.T @ B / n, np.eye(k), atol=1e-10)
        lam = np.linalg.eigvalsh(Kmat)[::-1]
        rayleigh = np.diag(B.T @ Kmat @ B) / n
        np.testing.assert_allclose(rayleigh, lam[:k], rtol=1e-8, atol=1e-10 * lam[0])
    theta = rng.standard_normal(p.n_params)
    mat = p.material(theta)
    if relative:
        np.testing.assert_allclose(np.mean(np.log(mat.E)), np.log(7e4), rtol=1e-12)


def test_smooth_basis_errors_are_named():
    mesh = random_block_mesh(np.random.default_rng(0))
    c, n = mesh.centroids, mesh.n_elements
    with pytest.raises(ValueError, match="length: expected"):
        Parameterisation.smooth(c, 0.0, 2, 1)
    with pytest.raises(ValueError, match="modes_E, modes_nu: expected at most"):
        Parameterisation.smooth(c, 0.01, n, 1, E_reference=7e4)
    with pytest.raises(ValueError, match="centroids: expected"):
        Parameterisation.smooth(c[:, :1], 0.01, 2, 1)
    with pytest.raises(ValueError, match="modes_nu"):
        Parameterisation.smooth(c, 0.01, 2, 0)
