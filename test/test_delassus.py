"""The Delassus operator W = H P^-1 H^T from the factor's forward solves (eq. 4, 11-12)."""

import numpy as np
import pytest
import scipy.sparse as sps
from sksparse.cholmod import analyze

from soft_tissue_sim import blas_threads, delassus, load_scene
from soft_tissue_sim.delassus import GROUP, LowerFactor, rotate_columns
from soft_tissue_sim.device_preconditioner import constraint_rows
from soft_tissue_sim.ldlt_preconditioner import BLOCK_COLUMNS, _drop_decoupled, block_solver, rotate_nodes

from test_cutting import beam_scene, crosswise, lengthwise


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
    assert len(lower.snodes) > 0  # the top separator by BLAS, the rest by the kernel
    W = lower.quadratic(B)
    assert np.abs(W - ref).max() <= 1e-12 * np.abs(ref).max()
    np.testing.assert_array_equal(W, W.T)
    assert np.all(W[7] == 0.0)
    np.testing.assert_allclose(lower.quadratic(sps.csc_matrix(B)), W, rtol=0, atol=1e-14 * np.abs(ref).max())
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
            # the same columns given in node form (as the contact step gives them)
            Wn = pre.delassus_rows(*constraint_rows(sps.csc_matrix(B), sim.fem.n_nodes))
            assert np.abs(Wn - ref).max() <= 1e-10 * np.abs(ref).max()
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


def dense_reference(A, B):
    """B^T A^-1 B by a dense solve."""
    return B.T @ np.linalg.solve(A.toarray() if sps.issparse(A) else A, B)


def beam_factors(monkeypatch, blas_from):
    """The beam's matrix, its simplicial CHOLMOD factor and that factor's LowerFactor with the
    supernodes of at least ``blas_from`` columns solved by BLAS: (A, n nodes, factor, lower)."""
    monkeypatch.setattr(delassus, "SNODE_BLAS", blas_from)
    A, n = beam_matrix()
    f = analyze(A, mode="simplicial")
    f.cholesky_inplace(A)
    return A, n, f, LowerFactor.from_cholmod(f)


@pytest.mark.parametrize("blas_from", [2, 10**9])
def test_kernel_and_blas_supernodes_give_the_dense_inverse(monkeypatch, blas_from):
    """W by the kernel alone (no supernode large enough for BLAS) and with BLAS on nearly
    every supernode: both B^T A^-1 B of the dense inverse, whatever the columns (one to 4
    nodes, several in the same place, a column given twice, an empty one)."""
    rng = np.random.default_rng(3)
    A, n, f, lower = beam_factors(monkeypatch, blas_from)
    assert (len(lower.snodes) == 0) == (blas_from > n)
    for m in (1, 3, GROUP, 3 * GROUP + 1):
        B = constraint_columns(rng, n, m, nodes=rng.choice(n, max(4, m // 3), replace=False))
        if m > 3:
            B[:, 1] = B[:, 0]
            B[:, 2] = 0.0
        ref = dense_reference(A, B)
        W = lower.quadratic(sps.coo_matrix(B))
        assert np.abs(W - ref).max() <= 1e-10 * np.abs(ref).max()
        np.testing.assert_array_equal(W, W.T)


@pytest.mark.parametrize("blas_from", [2, delassus.SNODE_BLAS, 10**9])
def test_block_solve_equals_the_factors_solve(monkeypatch, blas_from):
    """solve_block(B) = A^-1 B as CHOLMOD solves it, by the kernel alone, with the default
    supernodes by BLAS and with BLAS on nearly every supernode: unit columns (a cut's G, one
    node's three DOFs after another, the last group padded), constraint columns with a column
    given twice and an empty one, dense and sparse."""
    rng = np.random.default_rng(5)
    A, n, f, lower = beam_factors(monkeypatch, blas_from)
    for c in (1, GROUP, 2 * GROUP + 5):
        dofs = (3 * rng.choice(n, -(-c // 3), replace=False)[:, None] + np.arange(3)).ravel()[:c]
        G = np.zeros((3 * n, c))
        G[dofs, np.arange(c)] = 1.0
        B = constraint_columns(rng, n, c)
        if c > 3:
            B[:, 1] = B[:, 0]
            B[:, 2] = 0.0
        for M in (G, B, sps.csc_matrix(B)):
            ref = f(M.toarray() if sps.issparse(M) else M)
            X = lower.solve_block(M)
            assert X.shape == (3 * n, c)
            assert np.abs(X - ref).max() <= 1e-12 * np.abs(ref).max()
    assert lower.solve_block(np.zeros((3 * n, 0))).shape == (3 * n, 0)
    with pytest.raises(ValueError, match="DOFs"):
        lower.solve_block(np.zeros((3 * n - 3, 2)))


def test_a_block_goes_to_the_lower_factor_and_a_few_columns_to_the_factor():
    """The installed factor's solve: a block of BLOCK_COLUMNS columns or more by the lower
    factor's block solve, fewer (and single vectors) by the factor itself; without a lower
    factor, always the factor."""
    calls = []
    factor = lambda B: calls.append(("factor", np.shape(B))) or np.asarray(B)  # noqa: E731

    class Lower:
        def solve_block(self, B):
            calls.append(("block", B.shape))
            return B

    solve = block_solver(factor, Lower())
    k = BLOCK_COLUMNS
    for shape in ((30,), (30, 1), (30, k - 1), (30, k), (30, 3 * k)):
        solve(np.zeros(shape))
    assert [c[0] for c in calls] == ["factor", "factor", "factor", "block", "block"]
    assert block_solver(factor, None) is factor


def test_a_cuts_columns_come_from_the_block_solve(monkeypatch):
    """After a cut of a body with contact (the lower factor kept), the Sherman-Morrison
    columns U = P^-1 G of eq. (6) are solved as one block by the lower factor."""
    blocks = []
    solve_block = LowerFactor.solve_block
    monkeypatch.setattr(LowerFactor, "solve_block", lambda self, B: blocks.append(B.shape[1]) or solve_block(self, B))
    cfg = beam_scene(n_long=10, n_cross=3, rotate=False)
    cfg["obstacles"] = [{"type": "plane", "point": [0, 0, -1.0], "normal": [0, 0, 1]}]
    with load_scene(cfg) as sim:
        for _ in range(3):
            sim.step()
        sim.preconditioner.refresh(sim.integrator)
        blocks.clear()
        res = lengthwise(sim, 0.035, 0.08)
        assert res.changed and res.affected_nodes * 3 >= BLOCK_COLUMNS
        assert blocks == [3 * res.affected_nodes]


def test_a_factor_with_negative_pivots_gives_its_own_inverse():
    """An LDL^T with some D < 0 (an indefinite matrix): no D^-1/2, the signed D^-1 instead;
    W is still B^T (P^T L D L^T P)^-1 B."""
    rng = np.random.default_rng(4)
    A, n = beam_matrix()
    f = analyze(A, mode="simplicial")
    f.cholesky_inplace(A)
    LD = f.LD().tocsc()
    first = LD.indptr[:-1]
    LD.data[first[::7]] *= -1.0  # flip some pivots

    class Factor:
        def LD(self):
            return LD.copy()

        def P(self):
            return f.P()

    lower = LowerFactor.from_cholmod(Factor())
    assert lower.sqrt_dinv is None
    L = sps.tril(LD, -1).tocsc() + sps.eye(3 * n)
    Ap = (L @ sps.diags(LD.diagonal()) @ L.T).toarray()  # the permuted matrix
    inv_p = np.empty_like(f.P())
    inv_p[f.P()] = np.arange(3 * n)
    A_neg = Ap[np.ix_(inv_p, inv_p)]
    B = constraint_columns(rng, n, 2 * GROUP + 3)
    ref = dense_reference(A_neg, B)
    W = lower.quadratic(B)
    assert np.abs(W - ref).max() <= 1e-10 * np.abs(ref).max()
    X_ref = np.linalg.solve(A_neg, B)
    assert np.abs(lower.solve_block(B) - X_ref).max() <= 1e-10 * np.abs(X_ref).max()


def test_rotate_columns_equals_the_dense_rotation():
    """The sparse rotation of constraint columns into a factor's frame (node map and dR^T)
    equals the dense one of the preconditioner (rotate_nodes on the scattered block)."""
    rng = np.random.default_rng(6)
    n, n_ext = 30, 41
    B = constraint_columns(rng, n, 12)
    q = rng.standard_normal((n_ext, 3, 3))
    dR = np.linalg.qr(q)[0]
    nodes = rng.choice(n_ext, n, replace=False)
    Be = np.zeros((n_ext, 3, 12))
    Be[nodes] = B.reshape(n, 3, 12)
    ref = rotate_nodes(dR, Be.reshape(-1, 12), transpose=True)
    out = rotate_columns(sps.csc_matrix(B), dR, nodes, n_ext)
    assert out.shape == (3 * n_ext, 12)
    np.testing.assert_allclose(out.toarray(), ref, rtol=0, atol=1e-15)
    np.testing.assert_allclose(rotate_columns(B).toarray(), B, rtol=0, atol=0)


def test_delassus_equals_the_dense_inverse_after_cuts():
    """inner.delassus(H^T) = H A^-1 H^T of the dense inverse of the current A: with the factor
    just made, then after a cut that splits nodes, a second cut (two chained corrections) and
    an element removal (nodes vanish): the corrected factor is the new A's (eq. 5-12; not
    rotated, as in test_cutting's exactness test), and W follows it, on random column sets of
    several sizes (the kernel's groups, BLAS's supernodes)."""
    rng = np.random.default_rng(8)
    cfg = beam_scene(n_long=10, n_cross=3, rotate=False)
    cfg["obstacles"] = [{"type": "plane", "point": [0, 0, -1.0], "normal": [0, 0, 1]}]  # contact: far below
    with load_scene(cfg) as sim:
        integ, pre = sim.integrator, sim.preconditioner
        inner = pre.inner
        for _ in range(3):
            sim.step()
        sim.fem.update_rotations(integ.x)
        pre.refresh(integ)
        assert inner.lower is not None and len(inner.lower.snodes) > 0

        def check(corrected):
            sim.fem.update_rotations(integ.x)
            pre.begin_step(integ)
            assert (inner.correction is not None and inner.correction.active) == corrected
            A = sim.fem.assemble_scipy(integ.m_coef, integ.k_coef)
            n = sim.fem.n_nodes
            for m in (1, 7, 2 * GROUP + 5, 70):
                B = constraint_columns(rng, n, m)
                ref = dense_reference(A, B)
                W = inner.delassus(sps.csc_matrix(B))
                assert np.abs(W - ref).max() <= 1e-10 * np.abs(ref).max()

        check(False)
        res = lengthwise(sim, 0.035, 0.08)
        assert res.changed and res.nodes_added > 0
        check(True)
        assert crosswise(sim, 0.055).changed
        assert len(inner.correction.terms) == 2
        check(True)
        res3 = sim.remove_elements(sim.positions()[-1], 0.012)
        assert res3.changed and res3.nodes_removed > 0
        check(True)
        with pytest.raises(ValueError, match="DOFs"):  # a block for another numbering
            inner.delassus(sps.csc_matrix(constraint_columns(rng, sim.fem.n_nodes + 1, 3)))


def test_one_blas_thread_inside_the_block_and_the_number_restored():
    blas = np.show_config(mode="dicts")["Build Dependencies"]["blas"]
    version = tuple(int(p) for p in str(blas.get("version", "0")).split(".")[:3] if p.isdigit())
    if "openblas" not in str(blas.get("name", "")).lower() or version < (0, 3, 27):
        # another BLAS (or an OpenBLAS without the call): the block is a no-op that still nests
        assert not blas_threads.available()
        with blas_threads.one_thread():
            assert blas_threads._inside == 1
        assert blas_threads._inside == 0
        return
    assert blas_threads.available()  # NumPy's own OpenBLAS offers the call: it must be found
    setters = blas_threads._find_setters()

    def numbers():
        now = [f(1) for f in setters]  # each returns the number it had
        for f, k in zip(setters, now):
            f(k)
        return now

    before = numbers()
    for f in setters:
        f(2)
    with blas_threads.one_thread():
        assert numbers() == [1] * len(setters)
        with blas_threads.one_thread():  # nested (or another thread's): the outer one restores
            pass
        assert numbers() == [1] * len(setters)
    assert numbers() == [2] * len(setters)
    for f, n in zip(setters, before):
        f(n)
