"""The Delassus operator W = H P^-1 H^T from the factor's forward solves (eq. 4, 11-12)."""

import numpy as np
import pytest
import scipy.sparse as sps
from sksparse.cholmod import analyze

from soft_tissue_sim import load_scene
from soft_tissue_sim.delassus import GROUP, LowerFactor
from soft_tissue_sim.ldlt_preconditioner import _drop_decoupled

from test_cutting import beam_scene, lengthwise


def constraint_columns(rng, n_nodes, m, nodes=None):
    """m columns like contact rows of H^T: a unit normal spread over 1 to 4 nodes by weights."""
    pool = np.arange(n_nodes) if nodes is None else np.asarray(nodes)
    B = np.zeros((3 * n_nodes, m))
    for c in range(m):
        k = rng.integers(1, 5)
        nd = rng.choice(pool, k, replace=False)
        nrm = rng.standard_normal(3)
        nrm /= np.linalg.norm(nrm)
        w = rng.random(k) * (1.0 if k == 1 else -1.0) ** np.arange(k)
        for i, j in enumerate(nd):
            B[3 * j:3 * j + 3, c] = w[i] * nrm
    return B


def beam_matrix():
    with load_scene(beam_scene(n_long=10, n_cross=3)) as sim:
        for _ in range(3):
            sim.step()
        A = sim._snapshot()[0].csc()  # the snapshot holds the state; the worker assembles it
        n = sim.fem.n_nodes
    A = _drop_decoupled(A)
    A.sort_indices()
    return A, n


@pytest.mark.parametrize("mode", ["simplicial", "supernodal"])
def test_quadratic_form_of_the_forward_solves_equals_the_full_solves(mode):
    rng = np.random.default_rng(1)
    A, n = beam_matrix()
    f = analyze(A, mode=mode)
    f.cholesky_inplace(A)
    B = constraint_columns(rng, n, 2 * GROUP + 5)  # three groups, the last one padded
    B[:, 7] = 0.0  # a column that touches nothing
    ref = B.T @ f(B)
    lower = LowerFactor.from_cholmod(f)  # a supernodal factor turns simplicial, its solves keep working
    W = lower.quadratic(B)
    assert np.abs(W - ref).max() <= 1e-12 * np.abs(ref).max()
    np.testing.assert_array_equal(W, W.T)
    assert np.all(W[7] == 0.0)
    Yt = lower.forward(B)  # L^-1 P B itself, row by row
    Lref = f.solve_L(f.apply_P(B), use_LDLt_decomposition=True)
    assert np.abs(Yt.T - Lref).max() <= 1e-12 * np.abs(Lref).max()
    np.testing.assert_allclose(B.T @ f(B), ref)  # the factor still solves after the conversion
    assert lower.quadratic(np.zeros((3 * n, 0))).shape == (0, 0)
    with pytest.raises(ValueError, match="DOFs"):
        lower.quadratic(B[:-3])


@pytest.mark.parametrize("worker", ["thread", "process"])
def test_preconditioner_delassus_equals_its_columns_rotated_and_corrected(worker):
    """inner.delassus(B) = B^T P^-1 B as apply_columns computes it: with the rotations of
    eq. (2) and the Sherman-Morrison correction and identity padding after a cut (eq. 11-12);
    with worker=process both are computed in the process holding the factor."""
    rng = np.random.default_rng(2)
    cfg = beam_scene(n_long=10, n_cross=3, worker=worker)
    cfg["obstacles"] = [{"type": "plane", "point": [0, 0, -1.0], "normal": [0, 0, 1]}]  # contact: far below
    with load_scene(cfg) as sim:
        inner = sim.preconditioner.inner
        for _ in range(6):  # the beam sags and swings: rotations, a factor of step 0
            sim.step()

        def check(expect_correction):
            sim.fem.update_rotations(sim.integrator.x)
            inner.begin_step(sim.step_count, sim.fem.node_rotations())
            assert (inner.correction is not None and inner.correction.active) == expect_correction
            B = constraint_columns(rng, sim.fem.n_nodes, 21)
            ref = B.T @ inner.apply_columns(B)
            W = inner.delassus(B)
            assert np.abs(W - ref).max() <= 1e-10 * np.abs(ref).max()
            return ref

        ref = check(False)
        assert inner.dR is not None and np.abs(inner.dR - np.eye(3)).max() > 1e-4  # really rotated
        res = lengthwise(sim, 0.045, 0.09)  # node splitting: added DOFs, padded and corrected
        assert res.changed and res.nodes_added > 0
        check(True)
        corner = int(np.argmax(sim.mesh.points.sum(axis=1)))  # the tets around a corner: a node vanishes
        r2 = sim.remove_tets(np.flatnonzero(np.any(sim.mesh.tets == corner, axis=1)))
        assert r2.changed and r2.nodes_removed > 0
        check(True)
        assert len(inner.correction.terms) == 2
        assert np.isfinite(ref).all()


def test_no_lower_factor_without_contact():
    with load_scene(beam_scene()) as sim:  # cutting, no contact: not needed
        sim.step()
        assert sim.preconditioner.inner.lower is None and sim.preconditioner.inner.delassus(np.zeros((3, 1))) is None


def test_dense_delassus_equals_its_columns_rotated_and_corrected():
    """The dense backend gathers W from its inverse (a kernel per entry): it equals B^T P^-1 B
    from its applications (the matrix-vector kernel), rotated, and after a cut and a removal
    folded into the inverse; and it equals CHOLMOD's W for the same state."""
    rng = np.random.default_rng(5)
    cfg = beam_scene(n_long=10, n_cross=3, backend="dense")
    cfg["obstacles"] = [{"type": "plane", "point": [0, 0, -1.0], "normal": [0, 0, 1]}]
    with load_scene(cfg) as sim:
        pre = sim.preconditioner
        for _ in range(6):
            sim.step()

        def check():
            sim.fem.update_rotations(sim.integrator.x)
            pre.begin_step(sim.integrator)
            B = constraint_columns(rng, sim.fem.n_nodes, 17)
            ref = B.T @ pre.apply_columns(B)
            W = pre.delassus(sps.csc_matrix(B))
            assert np.abs(W - ref).max() <= 1e-10 * np.abs(ref).max()
            return B, W

        B, W = check()
        assert np.abs(pre.dR.numpy() - np.eye(3)).max() > 1e-4  # really rotated
        host_cfg = beam_scene(n_long=10, n_cross=3)
        host_cfg["obstacles"] = cfg["obstacles"]
        with load_scene(host_cfg) as host:  # same scene, same deterministic schedule: the same factor
            for _ in range(6):
                host.step()
            host.fem.update_rotations(host.integrator.x)
            host.preconditioner.begin_step(host.integrator)
            Wh = host.preconditioner.inner.delassus(B)
        assert np.abs(W - Wh).max() <= 1e-8 * np.abs(Wh).max()
        assert lengthwise(sim, 0.045, 0.09).changed
        check()
        corner = int(np.argmax(sim.mesh.points.sum(axis=1)))
        assert sim.remove_tets(np.flatnonzero(np.any(sim.mesh.tets == corner, axis=1))).changed
        check()
        with pytest.raises(ValueError, match="more than 4 nodes"):
            pre.delassus(np.ones((3 * sim.fem.n_nodes, 1)))
