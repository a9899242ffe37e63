"""Corotational FEM: invariance, assembly against the matrix-free product, material checks."""

import numpy as np
import pytest
import scipy.sparse.linalg as spla
import warp as wp

from soft_tissue_sim.corotational_fem import CorotationalFEM, rotation_from, rotation_svd
from soft_tissue_sim.material import Material, MaterialTable, ParameterError
from soft_tissue_sim.mesh import beam_mesh


def rotation(axis, angle):
    a = np.asarray(axis, float) / np.linalg.norm(axis)
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K


@pytest.fixture(scope="module")
def fem():
    mesh = beam_mesh(6, n_cross=3, spacing=0.01)
    mat = MaterialTable({0: Material(1e5, 0.3, 1000.0)})
    return CorotationalFEM(mesh, mat, "cpu")


@wp.kernel
def _polar_kernel(F: wp.array(dtype=wp.mat33d), R: wp.array(dtype=wp.mat33d), R_svd: wp.array(dtype=wp.mat33d)):
    i = wp.tid()
    R[i] = rotation_from(F[i])
    R_svd[i] = rotation_svd(F[i])


def test_polar_rotation_by_newton_iteration_equals_the_svd_one():
    """rotation_from (scaled Newton, SVD fallback) = the SVD polar rotation: for stretched and
    sheared elements, exact rotations, inverted (reflected) and nearly flat ones; always a
    proper rotation."""
    rng = np.random.default_rng(0)
    n = 3000
    Q = np.stack([rotation(rng.standard_normal(3), rng.uniform(0, np.pi)) for _ in range(n)])
    S = np.eye(3) + 0.3 * rng.standard_normal((n, 3, 3))
    F = Q @ (0.5 * (S + S.transpose(0, 2, 1)))
    F[:100] = Q[:100] * np.array([1.0, 1.0, -1.0])  # inverted
    F[100:200] = Q[100:200] @ np.diag([1.0, 1.0, 1e-9])  # nearly flat
    F[200:300] = Q[200:300]  # pure rotations
    F[300:400] *= 1e-4  # tiny elements: the tests are scale free
    Fw = wp.array(F, dtype=wp.mat33d, device="cpu")
    R, R_svd = wp.zeros_like(Fw), wp.zeros_like(Fw)
    wp.launch(_polar_kernel, n, [Fw, R, R_svd], device="cpu")
    R, R_svd = R.numpy(), R_svd.numpy()
    np.testing.assert_allclose(R, R_svd, atol=1e-12)
    np.testing.assert_allclose(R[200:300], Q[200:300], atol=1e-13)
    np.testing.assert_allclose(R @ R.transpose(0, 2, 1), np.broadcast_to(np.eye(3), R.shape), atol=1e-12)
    assert np.linalg.det(R).min() > 0.999999
    # the polar factor: R^T F is symmetric (and positive definite where det F > 0)
    S_ = R.transpose(0, 2, 1) @ F
    np.testing.assert_allclose(S_, S_.transpose(0, 2, 1), atol=1e-10 * np.abs(F).max())


def forces(fem, x, rotate=True):
    xw = wp.array(x, dtype=wp.vec3d, device="cpu")
    if rotate:
        fem.update_rotations(xw)
    else:
        fem.rotations.assign(np.tile(np.eye(3), (fem.n_tets, 1, 1)))
    f = wp.zeros_like(xw)
    fem.add_elastic_forces(xw, f)
    return f.numpy()


@pytest.mark.parametrize("axis", [[1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 2, -0.5]])
def test_rigid_rotation_makes_no_elastic_force(fem, axis):
    X = fem.mesh.points
    Q = rotation(axis, np.pi / 2)
    x = (X - X.mean(0)) @ Q.T + np.array([0.3, -0.1, 0.2])
    # Force scale: a 1% stretch along x.
    ref = np.abs(forces(fem, X * np.array([1.01, 1.0, 1.0]))).max()
    f_corot = forces(fem, x, rotate=True)
    f_linear = forces(fem, x, rotate=False)
    assert np.abs(f_corot).max() < 1e-9 * ref
    # Plain linear FEM (R = I) sees the rotation as a huge strain.
    assert np.abs(f_linear).max() > 10 * ref


def test_rotated_stretch_force_is_the_rotated_force(fem):
    X = fem.mesh.points
    stretched = X * np.array([1.02, 0.99, 1.0])
    Q = rotation([0.3, -1.0, 0.4], 1.1)
    f0 = forces(fem, stretched)
    f1 = forces(fem, stretched @ Q.T)
    np.testing.assert_allclose(f1, f0 @ Q.T, atol=1e-9 * np.abs(f0).max())


def test_inverted_element_gets_a_proper_rotation(fem):
    X = fem.mesh.points.copy()
    x = X.copy()
    x[:, 2] *= -1.0  # mirror: every element inverted
    xw = wp.array(x, dtype=wp.vec3d, device="cpu")
    fem.update_rotations(xw)
    R = fem.rotations.numpy()
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-9)
    np.testing.assert_allclose(np.einsum("eji,ejk->eik", R, R), np.broadcast_to(np.eye(3), R.shape), atol=1e-9)
    assert np.all(np.isfinite(forces(fem, x)))


@pytest.mark.parametrize("mass", ["lumped", "consistent"])
def test_assembled_matrix_equals_matrix_free_product(mass):
    mesh = beam_mesh(5, n_cross=3, spacing=0.01)
    mat = MaterialTable({0: Material(2e5, 0.35, 1100.0)})
    fixed = np.flatnonzero(mesh.points[:, 0] <= 1e-12)
    f = CorotationalFEM(mesh, mat, "cpu", mass=mass, fixed_nodes=fixed)
    rng = np.random.default_rng(0)
    x = mesh.points + 0.002 * rng.standard_normal(mesh.points.shape)
    f.update_rotations(wp.array(x, dtype=wp.vec3d))
    m_coef, k_coef = 1.3, 2e-4
    A = f.assemble_scipy(m_coef, k_coef)
    p = rng.standard_normal(mesh.points.shape)
    out = wp.zeros(mesh.n_nodes, dtype=wp.vec3d)
    pw = wp.array(p, dtype=wp.vec3d)
    f.system_product(pw, pw, out, 1.0, 0.0, m_coef, k_coef)
    np.testing.assert_allclose(out.numpy().ravel(), A @ p.ravel(), rtol=1e-12, atol=1e-12 * np.abs(A @ p.ravel()).max())
    # the stiffness buffer is left zero (the next product adds into it without a zeroing launch)
    assert not f._Kp.numpy().any()
    again = wp.zeros_like(out)
    f.system_product(pw, pw, again, 1.0, 0.0, m_coef, k_coef)
    np.testing.assert_array_equal(again.numpy(), out.numpy())
    # symmetric positive definite, fixed rows are identity
    assert spla.norm(A - A.T) < 1e-12 * spla.norm(A)
    dense = A.toarray()
    assert np.linalg.eigvalsh(dense).min() > 0
    for i in fixed:
        np.testing.assert_array_equal(dense[3 * i:3 * i + 3, 3 * i:3 * i + 3], np.eye(3))
    # the Jacobi blocks are the diagonal blocks of A on free nodes
    D = wp.zeros(mesh.n_nodes, dtype=wp.mat33d)
    f.diagonal_blocks(m_coef, k_coef, D)
    free = np.setdiff1d(np.arange(mesh.n_nodes), fixed)
    Dn = D.numpy()
    for i in free[:10]:
        np.testing.assert_allclose(Dn[i], dense[3 * i:3 * i + 3, 3 * i:3 * i + 3], rtol=1e-12)


def test_total_mass_and_gravity_load():
    mesh = beam_mesh(4, n_cross=3, spacing=0.02)
    f = CorotationalFEM(mesh, MaterialTable({0: Material(1e5, 0.3, 900.0)}), "cpu", mass="consistent")
    vol = 0.06 * 0.04 * 0.04
    assert f.total_mass == pytest.approx(900.0 * vol, rel=1e-12)
    ones = wp.array(np.tile([0.0, 0.0, 1.0], (mesh.n_nodes, 1)), dtype=wp.vec3d)
    out = wp.zeros_like(ones)
    f.mass_product(ones, out)  # consistent M applied to a uniform field = total mass
    assert out.numpy()[:, 2].sum() == pytest.approx(900.0 * vol, rel=1e-12)


@pytest.mark.parametrize(
    "kwargs, msg",
    [
        (dict(young=0.0, poisson=0.3, density=1000.0), "Young"),
        (dict(young=-5.0, poisson=0.3, density=1000.0), "Young"),
        (dict(young=1e5, poisson=0.5, density=1000.0), "Poisson"),
        (dict(young=1e5, poisson=0.7, density=1000.0), "Poisson"),
        (dict(young=1e5, poisson=0.3, density=0.0), "density"),
        (dict(young=float("nan"), poisson=0.3, density=1000.0), "finite"),
        (dict(young=1e5, poisson=0.3, density="soft"), "number"),
    ],
)
def test_impossible_material_parameters_are_rejected(kwargs, msg):
    with pytest.raises(ParameterError, match=msg):
        Material(**kwargs)


def test_undefined_material_id_is_named():
    mesh = beam_mesh(3, n_cross=2, spacing=0.01)
    mesh.material_ids[:] = 7
    with pytest.raises(ParameterError, match=r"material ids \[7\]"):
        MaterialTable({0: Material(1e5, 0.3, 1000.0)}).element_arrays(mesh.material_ids)


def _rest_arrays(f):
    return [f.Dm_inv.numpy(), f.volume.numpy(), f.lumped_mass.numpy(), f.free.numpy(), f.tets.numpy()]


def _split_node(mesh, node):
    """``mesh`` with ``node`` split: a copy at the same rest position takes its place in every
    other tet around it (a cut's node split)."""
    from soft_tissue_sim.mesh import TetMesh

    T = mesh.tets.copy()
    at = np.flatnonzero(np.any(T == node, axis=1))[::2]
    T[at] = np.where(T[at] == node, mesh.n_nodes, T[at])
    return TetMesh(np.concatenate([mesh.points, mesh.points[node:node + 1]]), T)


def test_rest_data_taken_over_from_the_source_tets_equal_a_fresh_build():
    """set_mesh with tet_source (a node split, then a removal; also a wrong hint) gives the
    very numbers of a FEM built afresh on the new mesh; a malformed hint is refused and the
    FEM keeps its mesh."""
    from soft_tissue_sim.mesh import TetMesh

    rng = np.random.default_rng(3)
    mesh = beam_mesh(6, n_cross=3, spacing=0.01)
    mesh = TetMesh(mesh.points + 0.002 * rng.uniform(-0.5, 0.5, mesh.points.shape), mesh.tets)  # all shapes differ
    mat = MaterialTable({0: Material(1e5, 0.3, 1000.0)})
    f = CorotationalFEM(mesh, mat, "cpu", fixed_nodes=np.arange(9))
    split = _split_node(mesh, 30)
    removal = TetMesh(split.points, split.tets[5:])
    moved = TetMesh(removal.points.copy(), removal.tets)
    moved.points[40] += 0.001  # same numbering, one node moved: its tets computed, the others taken over
    for new, source in ((split, np.arange(mesh.n_tets)), (removal, np.arange(5, mesh.n_tets)),
                        (moved, np.arange(removal.n_tets)),
                        (removal, np.roll(np.arange(removal.n_tets), 7))):  # the last one wrong: computed
        f.set_mesh(new, np.arange(9), tet_source=source)
        fresh = CorotationalFEM(new, mat, "cpu", fixed_nodes=np.arange(9))
        for a, b in zip(_rest_arrays(f), _rest_arrays(fresh)):
            np.testing.assert_array_equal(a, b)
        assert f.total_mass == fresh.total_mass
    before = _rest_arrays(f)
    with pytest.raises(ValueError, match="tet_source"):
        f.set_mesh(split, np.arange(9), tet_source=np.arange(3))
    with pytest.raises(ValueError, match="tet_source"):
        f.set_mesh(split, np.arange(9), tet_source=np.full(split.n_tets, removal.n_tets))
    assert f.mesh is removal and all(np.array_equal(a, b) for a, b in zip(before, _rest_arrays(f)))


def test_a_split_keeps_the_device_arrays_of_unchanged_element_data():
    """A node split changes no element's rest shape or material: set_mesh keeps those device
    arrays (same objects, same bytes) and sends only the nodes' data and the tets; a removal
    changes them and sends them too (views of the same allocation)."""
    from soft_tissue_sim.mesh import TetMesh

    mesh = beam_mesh(6, n_cross=3, spacing=0.01)
    mat = MaterialTable({0: Material(1e5, 0.3, 1000.0)})
    f = CorotationalFEM(mesh, mat, "cpu", fixed_nodes=np.arange(9))
    split = _split_node(mesh, 30)
    names = ("Dm_inv", "volume", "mu", "lam", "rho", "_all_tets")
    before = {k: getattr(f, k) for k in names}
    f.set_mesh(split, np.arange(9), tet_source=np.arange(mesh.n_tets))
    assert all(getattr(f, k) is before[k] for k in names)
    assert f.tets is not None and np.array_equal(f.tets.numpy(), split.tets)
    assert sorted(f.uploads) == ["counts", "free", "lumped_mass", "rest", "tets"]
    assert f.counts.numpy().tolist() == [split.n_nodes, split.n_tets]  # what the launches read
    f.set_mesh(TetMesh(split.points, split.tets[5:]), np.arange(9), tet_source=np.arange(5, mesh.n_tets))
    assert not any(getattr(f, k) is before[k] for k in names)
    assert {"Dm_inv", "volume", "mu", "lam", "rho"} <= set(f.uploads)
    assert f.Dm_inv.ptr == before["Dm_inv"].ptr  # the same allocation: it fits
    fresh = CorotationalFEM(f.mesh, mat, "cpu", fixed_nodes=np.arange(9))
    for a, b in zip(_rest_arrays(f), _rest_arrays(fresh)):
        np.testing.assert_array_equal(a, b)


def test_same_rest_shape_equals_the_row_wise_comparison_on_random_tets():
    """Whether each tet keeps its source's rest positions, node for node: the same flags as
    comparing the 12 gathered coordinates of each pair of tets row by row."""
    from soft_tissue_sim.corotational_fem import _same_rest_shape

    rng = np.random.default_rng(5)
    for n_old, n_new, k in ((20, 20, 0), (20, 26, 50), (40, 31, 200)):
        X_old = rng.integers(0, 3, (n_old, 3)).astype(np.float64)  # repeated points: equal by value too
        X = np.concatenate([X_old, rng.integers(0, 3, (max(n_new - n_old, 0), 3)).astype(np.float64)])[:n_new]
        X[rng.random(n_new) < 0.2] += 0.5  # moved nodes
        T_old = rng.integers(0, n_old, (k, 4)).astype(np.int32)
        T = np.where(rng.random((k, 4)) < 0.3, rng.integers(0, n_new, (k, 4)), np.minimum(T_old, n_new - 1))
        T = T.astype(np.int32)
        ref = np.array([np.array_equal(X[T[i]], X_old[T_old[i]]) for i in range(k)], bool)
        got = _same_rest_shape(X, T, X_old, T_old)
        np.testing.assert_array_equal(got, ref)
        assert got.shape == (k,) and got.dtype == bool
        assert 0 < ref.sum() < k or k == 0


def test_edge_ownership_equals_a_stable_sort_of_the_edges_on_random_faces():
    """The owner of each undirected edge is its first occurrence in face-major order: the same
    flags as a stable argsort of the edges' keys (random faces, shared and repeated edges)."""
    from soft_tissue_sim.contact.geometry import edge_ownership

    rng = np.random.default_rng(9)
    for n, f in ((3, 1), (6, 10), (50, 400)):
        faces = np.stack([rng.choice(n, 3, replace=False) for _ in range(f)]).astype(np.int32)
        a, b = faces.ravel(), np.roll(faces, -1, axis=1).ravel()
        key = np.minimum(a, b).astype(np.int64) * n + np.maximum(a, b)
        order = np.argsort(key, kind="stable")
        ks = key[order]
        ref = np.zeros(3 * f, np.int32)
        ref[order[np.concatenate(([True], ks[1:] != ks[:-1]))]] = 1
        np.testing.assert_array_equal(edge_ownership(faces), ref.reshape(-1, 3))


def test_the_steps_launches_captured_at_one_mesh_replay_right_after_a_topology_change():
    """The per-step launches read the node and tet counts on the device and cover the
    capacities: a graph of them captured before a node split (more nodes) and before a removal
    (fewer tets) gives, replayed after it, what plain launches at the new mesh give; the launch
    dimensions hold while the allocations do."""
    from soft_tissue_sim.mesh import TetMesh

    mesh = beam_mesh(6, n_cross=3, spacing=0.01)
    mat = MaterialTable({0: Material(1e5, 0.3, 1000.0)})
    f = CorotationalFEM(mesh, mat, "cpu", fixed_nodes=np.arange(9))
    cap = f.node_dim
    rng = np.random.default_rng(3)
    arrays = {k: wp.zeros(cap, dtype=wp.vec3d, device="cpu") for k in ("x", "p", "force", "Ap", "Kp")}

    def launches():
        f.update_rotations(arrays["x"])
        f.add_elastic_forces(arrays["x"], arrays["force"])
        f.system_product(arrays["p"], arrays["p"], arrays["Ap"], 1.0, 0.0, 1.0, 1e-4)
        f.stiffness_product(arrays["p"], arrays["Kp"])
        f.update_node_rotations()

    def fill(n):
        X = f.rest.numpy() + 1e-3 * rng.standard_normal((n, 3))
        for k, v in (("x", X), ("p", rng.standard_normal((n, 3))), ("force", np.zeros((n, 3)))):
            h = arrays[k].numpy()
            h[:n] = v
            arrays[k].assign(h)

    def outputs(n):
        return [arrays[k].numpy()[:n].copy() for k in ("force", "Ap", "Kp")] + [f._node_rot.numpy()[:n].copy(),
                                                                             f.rotations.numpy().copy()]

    fill(mesh.n_nodes)
    with wp.ScopedCapture(device="cpu") as cap_:
        launches()
    split = _split_node(mesh, 30)
    removed = TetMesh(split.points, split.tets[5:])
    for new, src in ((split, np.arange(mesh.n_tets)), (removed, np.arange(5, split.n_tets))):
        dims = (f.node_dim, f.tet_dim)
        f.set_mesh(new, np.arange(9), tet_source=src)
        assert (f.node_dim, f.tet_dim) == dims and f.node_dim >= new.n_nodes
        fill(new.n_nodes)
        state = [arrays[k].numpy().copy() for k in ("x", "p", "force")]
        wp.capture_launch(cap_.graph)
        replayed = outputs(new.n_nodes)
        for k, v in zip(("x", "p", "force"), state):
            arrays[k].assign(v)
        launches()
        for a, b in zip(replayed, outputs(new.n_nodes)):
            np.testing.assert_array_equal(a, b)
        assert not f._Kp.numpy().any()  # left zero by every product, through the change
        assert np.abs(replayed[1]).max() > 0.0 and np.isfinite(replayed[3]).all()
