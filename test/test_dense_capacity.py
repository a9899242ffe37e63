"""The dense inverse keeps its address and leading dimension across size changes within its
capacity (soft_tissue_sim.dense_inverse): installs, folds and regrows of any size up to the
capacity leave ``inv.ptr``, ``ld`` and ``graph_key()`` as they were, ``apply`` reads the size on
the device (a graph captured before a regrow replays right after it), and a size beyond the
capacity reallocates (a new key).

Runs on Warp's CPU backend by default (NumPy and SciPy's LAPACK); ``STS_TEST_DEVICE=cuda:0``
runs the same tests on a GPU.
"""

import ctypes
import os
import types

import numpy as np
import pytest
import warp as wp

from soft_tissue_sim import dense_inverse as DI
from soft_tissue_sim.buffers import GrowArray
from soft_tissue_sim.sherman_morrison import woodbury_q

DEVICE = os.environ.get("STS_TEST_DEVICE", "cpu")
CUDA = DEVICE.startswith("cuda")
if CUDA and wp.get_cuda_device_count() == 0:
    raise RuntimeError(f"STS_TEST_DEVICE={DEVICE} but Warp sees no CUDA device")


def _spd(n3, rng):
    B = rng.standard_normal((n3, n3))
    return B @ B.T / n3 + 0.5 * np.eye(n3)


def _factor_into(D, A):
    """A^-1 made in D's work buffer and installed."""
    D.work = wp.array(A, dtype=wp.float64, device=DEVICE)
    if D.device.is_cuda:
        D._prepare_gpu(A.shape[0], None)
    D.factorize()
    assert D.install() is None


def _installed(A, precision="float64"):
    """A DenseInverse with A^-1 installed (and the reference inverse it holds, checked against A)."""
    n3 = A.shape[0]
    D = DI.DenseInverse(DEVICE, precision)
    _factor_into(D, A)
    P = D.inv.numpy().copy()
    np.testing.assert_allclose(P @ A, np.eye(n3), atol=1e-9)
    return D, P


def _rotations(n, rng):
    Q, R = np.linalg.qr(rng.standard_normal((n, 3, 3)))
    return Q * np.sign(np.diagonal(R, axis1=1, axis2=2))[:, None, :]


def _reference(P, dR, r):
    """dR P dR^T r in NumPy (node blocks of 3)."""
    s = np.einsum("nba,nb->na", dR, r).reshape(-1)
    return np.einsum("nab,nb->na", dR, (P @ s).reshape(-1, 3))


def _regrown(P, keep, added):
    n = len(keep) + added
    out = np.eye(n)
    out[: len(keep), : len(keep)] = P[np.ix_(keep, keep)]
    return out


def _folded(P, rows, N):
    U = P[:, rows]
    return P - U @ woodbury_q(N, U[rows]) @ U.T


class _Vectors:
    """r, z and dR as views of kept allocations (addresses held across sizes, as the PCG's are)."""

    def __init__(self):
        self.bufs = {k: GrowArray(t, DEVICE) for k, t in (("r", wp.vec3d), ("z", wp.vec3d), ("dR", wp.mat33d))}

    def set(self, r, dR):
        n = len(r)
        v = {k: b.view(n) for k, b in self.bufs.items()}
        v["r"].assign(r)
        v["dR"].assign(dR)
        v["z"].zero_()
        return v["r"], v["z"], v["dR"]


def _apply(D, r, dR):
    n = len(r)
    z = wp.zeros(n, dtype=wp.vec3d, device=DEVICE)
    D.apply(wp.array(r, dtype=wp.vec3d, device=DEVICE), z, wp.array(dR, dtype=wp.mat33d, device=DEVICE))
    return z.numpy()


def lower_symmetric(P):
    """The symmetric matrix of P's lower triangle (what the packed single-precision copy holds,
    before rounding)."""
    return np.tril(P) + np.tril(P, -1).T


def _check(D, P, rng, tol=1e-12):
    """D's apply equals NumPy's dR P dR^T r, the size on the device is P's, the view is P."""
    n3 = P.shape[0]
    assert D.n3 == n3 and int(D._count.numpy()[0]) == n3
    np.testing.assert_allclose(D.inv.numpy(), P, rtol=0, atol=tol * np.abs(P).max())
    Pa = D.single().astype(np.float64) if D.precision == "float32" else P
    if D.precision == "float32":
        assert np.array_equal(D.single(), lower_symmetric(D.inv.numpy()).astype(np.float32))
    n = n3 // 3
    r, dR = rng.standard_normal((n, 3)), _rotations(n, rng)
    ref = _reference(Pa, dR, r)
    assert np.abs(_apply(D, r, dR) - ref).max() <= tol * np.abs(ref).max()


@pytest.mark.parametrize("precision", ["float64", "float32"])
def test_install_fold_and_regrows_within_the_capacity_keep_the_address(precision):
    """After an install, a fold, regrows to a smaller size (a gather: nodes dropped and permuted)
    and to larger ones (appended identity rows, in place and with a gather), the inverse stays at
    its address with its leading dimension (and so does the single-precision copy), the key holds,
    and apply equals NumPy's to 1e-12."""
    rng = np.random.default_rng(1)
    nodes = 40
    A = _spd(3 * nodes, rng)
    D, P = _installed(A, precision)
    ld = D.ld
    assert ld % DI.LD_MULTIPLE == 0 and ld >= 3 * nodes + 3 * 8
    assert D.inv.strides == (8 * ld, 8) and not D.inv.is_contiguous
    ptr, key = D.inv.ptr, D.graph_key()
    _check(D, P, rng)

    rows = np.arange(9, 15)  # nodes 3 and 4
    N = 0.05 * rng.standard_normal((6, 6))
    N = N + N.T
    D.fold(rows, N)
    P = _folded(P, rows, N)
    _check(D, P, rng)

    # smaller: drop nodes 5 and 17, the others permuted (a gather through the second store)
    kept = rng.permutation(np.setdiff1d(np.arange(nodes), [5, 17]))
    keep = (3 * kept[:, None] + np.arange(3)).ravel()
    D.regrow(keep, 0)
    P = _regrown(P, keep, 0)
    _check(D, P, rng)

    # larger, in place: all kept in order, two nodes appended
    D.regrow(np.arange(P.shape[0]), 6)
    P = _regrown(P, np.arange(P.shape[0]), 6)
    _check(D, P, rng)

    # larger with a gather: a node dropped, four appended; then a fold on the new rows
    keep = np.arange(3, P.shape[0])
    D.regrow(keep, 12)
    P = _regrown(P, keep, 12)
    _check(D, P, rng)
    rows = np.arange(P.shape[0] - 6, P.shape[0])
    D.fold(rows, N)
    P = _folded(P, rows, N)
    _check(D, P, rng)

    # a smaller prefix: no data moves
    D.regrow(np.arange(P.shape[0] - 9), 0)
    P = P[:-9, :-9]
    _check(D, P, rng)

    assert (D.inv.ptr, D.ld, D.graph_key()) == (ptr, ld, key)
    assert D._store[0].allocations == 1 and D._store[1].allocations == 1
    if precision == "float32":
        assert D._packed_buf.allocations == 1
    D.close()


def test_installs_of_other_sizes_within_the_capacity_keep_the_address():
    """Factors of other sizes up to the capacity are copied into the same strided store."""
    rng = np.random.default_rng(2)
    D, P = _installed(_spd(120, rng))
    ptr, ld, key = D.inv.ptr, D.ld, D.graph_key()
    for n3 in (108, ld - ld % 3, 126):
        A = _spd(n3, rng)
        _factor_into(D, A)
        np.testing.assert_allclose(D.inv.numpy() @ A, np.eye(n3), atol=1e-9)
        _check(D, D.inv.numpy().copy(), rng)
        assert (D.inv.ptr, D.ld, D.graph_key()) == (ptr, ld, key)
    D.close()


def test_a_graph_captured_before_a_regrow_replays_after_it():
    """apply captured at one size (vectors of kept addresses, as the PCG's) and replayed after
    regrows to a larger and to a smaller size gives the plain apply's result at the new size."""
    rng = np.random.default_rng(3)
    D, P = _installed(_spd(90, rng))
    vec = _Vectors()
    r, z, dR = vec.set(rng.standard_normal((30, 3)), _rotations(30, rng))
    D.apply(r, z, dR)  # loads the kernels
    key = D.graph_key()
    with wp.ScopedCapture(device=DEVICE) as cap:
        D.apply(r, z, dR)
    for keep, added in ((np.arange(90), 15), (np.arange(6, 105), 0)):
        D.regrow(keep, added)
        P = _regrown(P, keep, added)
        assert D.graph_key() == key
        n = P.shape[0] // 3
        rn, dRn = rng.standard_normal((n, 3)), _rotations(n, rng)
        r, z, dR = vec.set(rn, dRn)
        wp.capture_launch(cap.graph)
        replayed = z.numpy().copy()
        plain = _apply(D, rn, dRn)
        assert np.array_equal(replayed, plain)
        ref = _reference(P, dRn, rn)
        assert np.abs(replayed - ref).max() <= 1e-12 * np.abs(ref).max()
    D.close()


def test_a_regrow_beyond_the_capacity_reallocates():
    """A regrow (or an install) past the leading dimension reallocates the store with a larger
    one: a new key, the result still right; the next changes within it keep the new address."""
    rng = np.random.default_rng(4)
    D, P = _installed(_spd(60, rng), "float32")
    ld, key = D.ld, D.graph_key()
    added = ld - 60 + 6
    D.regrow(np.arange(3, 60), added)
    P = _regrown(P, np.arange(3, 60), added)
    assert D.ld > ld and D.ld >= P.shape[0] and D.graph_key() != key
    assert D.graph_key()[1] == D.ld
    _check(D, P, rng)
    ptr, key = D.inv.ptr, D.graph_key()
    D.regrow(np.arange(P.shape[0]), 3)
    P = _regrown(P, np.arange(P.shape[0]), 3)
    _check(D, P, rng)
    assert (D.inv.ptr, D.graph_key()) == (ptr, key)
    n3 = D.ld + 3  # an install past the capacity
    _factor_into(D, _spd(n3, rng))
    assert D.ld >= n3 and D.graph_key() != key
    _check(D, D.inv.numpy().copy(), rng)
    D.close()


def test_the_preconditioner_key_holds_across_a_cut():
    """Through the device preconditioner: a cut (a fold, regrows, nodes added) within the
    capacity leaves its graph key (and so the inverse's and dR's addresses) as it was, and the
    corrected inverse is still the modified matrix's."""
    from test_cutting import corrected_vs_fresh, fresh_bound, lengthwise, unrotated_dense_beam

    from soft_tissue_sim import load_scene

    with load_scene(unrotated_dense_beam(DEVICE)) as sim:
        for _ in range(2):
            sim.step()
        sim.fem.update_rotations(sim.integrator.x)
        pre = sim.preconditioner
        pre.refresh(sim.integrator)
        pre.begin_step(sim.integrator)
        key, n = pre.graph_key(), sim.mesh.n_nodes
        assert lengthwise(sim, 0.035, 0.08).changed
        corrected = corrected_vs_fresh(sim, np.random.default_rng(1))
        assert sim.mesh.n_nodes > n and pre.backend.n3 == 3 * sim.mesh.n_nodes
        assert 3 * sim.mesh.n_nodes <= pre.backend.ld
        assert pre.graph_key() == key
        assert corrected < fresh_bound(sim, np.random.default_rng(1))
        assert sim.step().converged


def _colmajor(ptr, rows, cols, ld, ctype=ctypes.c_double):
    """The column-major (rows, cols) matrix with leading dimension ld at the host address ptr."""
    buf = (ctype * (ld * (cols - 1) + rows)).from_address(ptr)
    size = ctypes.sizeof(ctype)
    return np.lib.stride_tricks.as_strided(np.ctypeslib.as_array(buf), (rows, cols), (size, size * ld))


def _fake_bindings():
    """Stand-ins for nvmath's cuBLAS and cuSOLVER bindings on host memory, with the libraries'
    column-major semantics on raw pointers: dgemm (BLAS), dgetrf and dgetrs (LAPACK's, through
    SciPy), so that :class:`LibraryFold`'s calls run on Warp's CPU device."""
    import scipy.linalg as sla

    calls = []

    def dgemm(h, transa, transb, m, n, k, alpha, a, lda, b, ldb, beta, c, ldc):
        calls.append(("dgemm", transa, transb, m, n, k, lda, ldb, ldc))
        A = _colmajor(a, k, m, lda).T if transa == 1 else _colmajor(a, m, k, lda)
        B = _colmajor(b, n, k, ldb).T if transb == 1 else _colmajor(b, k, n, ldb)
        C = _colmajor(c, m, n, ldc)
        al, be = (ctypes.c_double.from_address(p).value for p in (alpha, beta))
        C[...] = al * (A @ B) + (be * C if be != 0.0 else 0.0)  # (BLAS reads no C where beta is 0)

    def dgetrf(h, m, n, a, lda, work, ipiv, info):
        calls.append(("dgetrf", m, n, lda))
        A = _colmajor(a, m, n, lda)
        lu, piv = sla.lu_factor(np.array(A))
        A[...] = lu
        _colmajor(ipiv, min(m, n), 1, min(m, n), ctypes.c_int)[:, 0] = piv + 1
        ctypes.c_int.from_address(info).value = 0

    def dgetrs(h, trans, n, nrhs, a, lda, ipiv, b, ldb, info):
        calls.append(("dgetrs", trans, n, nrhs, lda, ldb))
        piv = _colmajor(ipiv, n, 1, n, ctypes.c_int)[:, 0] - 1
        B = _colmajor(b, n, nrhs, ldb)
        B[...] = sla.lu_solve((np.array(_colmajor(a, n, n, lda)), piv), np.array(B), trans=trans)
        ctypes.c_int.from_address(info).value = 0

    handles = dict(create=lambda: 0, destroy=lambda h: None, set_stream=lambda h, s: None)
    cublas = types.SimpleNamespace(dgemm=dgemm, **handles)
    cusolver = types.SimpleNamespace(dgetrf=dgetrf, dgetrs=dgetrs, dgetrf_buffer_size=lambda h, m, n, a, lda: 1,
                                     **handles)
    return cublas, cusolver, calls


def test_the_library_fold_equals_the_host_fold_on_a_strided_matrix():
    """The GPU's fold (:class:`LibraryFold`: its gathers and symmetrization on Warp's CPU device,
    its dgemm, getrf and getrs by column-major stand-ins of the libraries) against
    :func:`fold_into` (NumPy): P - U Q U^T in the (n, n) view of a store with a larger leading
    dimension, the padding beyond it untouched; twice, the second fold on fewer rows (the
    buffers reused)."""
    cublas, cusolver, calls = _fake_bindings()
    rng = np.random.default_rng(6)
    n, ld = 21, 40
    B = rng.standard_normal((n, n))
    store = np.full((ld, ld), 7.0)
    store[:n, :n] = np.linalg.inv(B @ B.T + n * np.eye(n))
    P = wp.array(store, dtype=wp.float64, device="cpu")
    Pv = DI.strided_square(wp.array(ptr=P.ptr, dtype=wp.float64, shape=(ld * ld,), device="cpu"), n, ld)
    fold = DI.LibraryFold("cpu", cublas, cusolver)
    ref = store.copy()
    for rows in (np.array([3, 4, 5, 12, 13, 14]), np.array([0, 1, 2])):
        k = len(rows)
        C = rng.standard_normal((k, k))
        N = 0.1 * (C + C.T)
        DI.fold_into(np, ref[:n, :n], rows, N)
        fold(Pv, rows.astype(np.int32), N)
        got = P.numpy()
        np.testing.assert_allclose(got[:n, :n], ref[:n, :n], rtol=0, atol=1e-13)
        assert np.all(got[n:] == 7.0) and np.all(got[:, n:] == 7.0)
    assert [c[0] for c in calls] == ["dgemm", "dgetrf", "dgetrs", "dgemm", "dgemm"] * 2
    fold.release()  # (what close does before the handles go): the buffers go, the next fold makes them again
    assert fold._UT.buffer is None and fold.staged.buffer is None
    rows = np.array([6, 7, 8])
    DI.fold_into(np, ref[:n, :n], rows, N[:3, :3])
    fold(Pv, rows.astype(np.int32), N[:3, :3])
    np.testing.assert_allclose(P.numpy()[:n, :n], ref[:n, :n], rtol=0, atol=1e-13)
    assert calls[4] == ("dgemm", 0, 1, n, n, 6, n, n, ld)  # the rank update with P's leading dimension
