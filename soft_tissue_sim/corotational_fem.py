"""Corotational linear tetrahedral FEM (Mueller & Gross 2004) in Warp kernels, float64.

For a linear tetrahedron with rest shape-function gradients g_0..g_3 (g_0 = -g_1-g_2-g_3),
the deformation gradient is F = sum_i x_i g_i^T. Its polar decomposition F = R S gives
the element rotation R. The corotated elastic force and the corotated stiffness are

    f_i   = -V R sigma(eps) g_i,        eps = sym(R^T F - I)
    (K p)_i = V R sigma(sym(sum_j (R^T p_j) g_j^T)) g_i

with sigma(eps) = 2 mu eps + lambda tr(eps) I. A rigid rotation of the rest shape gives
F = Q, R = Q, eps = 0: no force (plain linear FEM would give one). K is the positive
semidefinite stiffness (K = -df/dx with R frozen), so the system matrix of eq. (1) is

    A = M - dt B - dt^2 (df/dx) = (1 + dt alpha) M + (dt beta + dt^2) K

with Rayleigh damping B = -(alpha M + beta K). Nodes marked fixed are filtered out
(their rows and columns replaced by the identity) so that A stays symmetric positive
definite and CG never moves them.

Host code (:class:`CorotationalFEM`) owns the arrays and launches; the kernels hold the
arithmetic. The matrix-free product with A, the COO triplets of A (the device factors) and
the host assembly of A as scipy CSC for CHOLMOD (:mod:`soft_tissue_sim.host_assembly`, NumPy,
from a copy of the state) use the same element formulas.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sps
import warp as wp

from .buffers import GrowArray, PackedArrays, unbounded_count
from .host_assembly import AssemblyState
from .material import MaterialTable
from .mesh import TetMesh, all_four
from .transfer import to_host

wp.set_module_options({"enable_backward": False})  # no gradients are taken

_F64 = wp.float64


@wp.func
def shape_gradients(Dm_inv: wp.mat33d, k: int):
    """Gradient of the linear shape function of local node k (rows of Dm^-1; g_0 = -sum)."""
    if k == 0:
        return -wp.vec3d(
            Dm_inv[0, 0] + Dm_inv[1, 0] + Dm_inv[2, 0],
            Dm_inv[0, 1] + Dm_inv[1, 1] + Dm_inv[2, 1],
            Dm_inv[0, 2] + Dm_inv[1, 2] + Dm_inv[2, 2],
        )
    return wp.vec3d(Dm_inv[k - 1, 0], Dm_inv[k - 1, 1], Dm_inv[k - 1, 2])


@wp.func
def stress(eps: wp.mat33d, mu: wp.float64, lam: wp.float64):
    tr = eps[0, 0] + eps[1, 1] + eps[2, 2]
    return _F64(2.0) * mu * eps + lam * tr * wp.identity(n=3, dtype=wp.float64)


@wp.func
def _frob2(A: wp.mat33d):
    return wp.ddot(A, A)


@wp.func
def rotation_svd(F: wp.mat33d):
    """Rotation of the polar decomposition from the SVD F = U S V^T: R = U D V^T with
    D = diag(1, 1, det(U V^T)) applied on the smallest singular value, so R is a proper
    rotation even when det F <= 0 (inverted elements)."""
    U = wp.mat33d()
    s = wp.vec3d()
    V = wp.mat33d()
    wp.svd3(F, U, s, V)
    R = U * wp.transpose(V)
    if wp.determinant(R) < _F64(0.0):
        k = 0
        if s[1] < s[k]:
            k = 1
        if s[2] < s[k]:
            k = 2
        for r in range(3):
            U[r, k] = -U[r, k]
        R = U * wp.transpose(V)
    return R


@wp.func
def rotation_from(F: wp.mat33d):
    """Rotation of the polar decomposition F = R S, robust to inverted elements.

    Where F is safely invertible with det F > 0 (almost every element, almost always) the
    polar factor is unique and Higham's scaled Newton iteration X <- (g X + X^-T / g) / 2,
    g = (|X^-1|_F / |X|_F)^(1/2), converges to it quadratically from X = F: a few 3x3
    inversions instead of an SVD (about 5x cheaper on the CPU backend, same R to rounding).
    Otherwise (inverted, nearly flat, or no convergence in 30 steps) the SVD of
    :func:`rotation_svd`."""
    n2 = _frob2(F)
    det = wp.determinant(F)
    if det > _F64(1.0e-6) * n2 * wp.sqrt(n2) / _F64(5.196152422706632):  # det > 1e-6 (|F|_F / sqrt 3)^3
        X = F
        for _it in range(30):
            Xi = wp.transpose(wp.inverse(X))
            g = wp.sqrt(wp.sqrt(_frob2(Xi) / _frob2(X)))
            Xn = _F64(0.5) * (g * X + Xi / g)
            d = _frob2(Xn - X)
            X = Xn
            if d < _F64(1.0e-30):
                return X
    return rotation_svd(F)


@wp.kernel
def element_rotations_kernel(
    count: wp.array(dtype=wp.int32),
    x: wp.array(dtype=wp.vec3d),
    tets: wp.array(dtype=wp.vec4i),
    Dm_inv: wp.array(dtype=wp.mat33d),
    R_out: wp.array(dtype=wp.mat33d),
):
    e = wp.tid()
    if e >= count[0]:
        return
    t = tets[e]
    x0 = x[t[0]]
    Ds = wp.matrix_from_cols(x[t[1]] - x0, x[t[2]] - x0, x[t[3]] - x0)
    R_out[e] = rotation_from(Ds * Dm_inv[e])


@wp.kernel
def elastic_force_kernel(
    count: wp.array(dtype=wp.int32),
    x: wp.array(dtype=wp.vec3d),
    tets: wp.array(dtype=wp.vec4i),
    Dm_inv: wp.array(dtype=wp.mat33d),
    volume: wp.array(dtype=wp.float64),
    mu: wp.array(dtype=wp.float64),
    lam: wp.array(dtype=wp.float64),
    R: wp.array(dtype=wp.mat33d),
    f: wp.array(dtype=wp.vec3d),
):
    """f += -V R sigma(sym(R^T F - I)) g_i (accumulated; f must be initialised)."""
    e = wp.tid()
    if e >= count[0]:
        return
    t = tets[e]
    x0 = x[t[0]]
    Ds = wp.matrix_from_cols(x[t[1]] - x0, x[t[2]] - x0, x[t[3]] - x0)
    Re = R[e]
    G = wp.transpose(Re) * (Ds * Dm_inv[e]) - wp.identity(n=3, dtype=wp.float64)
    eps = _F64(0.5) * (G + wp.transpose(G))
    P = -volume[e] * (Re * stress(eps, mu[e], lam[e]))
    for k in range(4):
        wp.atomic_add(f, t[k], P * shape_gradients(Dm_inv[e], k))


@wp.kernel
def stiffness_product_kernel(
    count: wp.array(dtype=wp.int32),
    p: wp.array(dtype=wp.vec3d),
    free: wp.array(dtype=wp.float64),
    tets: wp.array(dtype=wp.vec4i),
    Dm_inv: wp.array(dtype=wp.mat33d),
    volume: wp.array(dtype=wp.float64),
    mu: wp.array(dtype=wp.float64),
    lam: wp.array(dtype=wp.float64),
    rho: wp.array(dtype=wp.float64),
    R: wp.array(dtype=wp.mat33d),
    k_coef: wp.float64,
    m_coef: wp.float64,
    out: wp.array(dtype=wp.vec3d),
):
    """out += k_coef K (free*p) + m_coef M_consistent (free*p), K corotated (accumulated)."""
    e = wp.tid()
    if e >= count[0]:
        return
    t = tets[e]
    Dinv = Dm_inv[e]
    Re = R[e]
    Rt = wp.transpose(Re)
    G = wp.mat33d()
    psum = wp.vec3d()
    for j in range(4):
        pj = p[t[j]] * free[t[j]]
        psum += pj
        G += wp.outer(Rt * pj, shape_gradients(Dinv, j))
    eps = _F64(0.5) * (G + wp.transpose(G))
    P = (k_coef * volume[e]) * (Re * stress(eps, mu[e], lam[e]))
    mc = m_coef * rho[e] * volume[e] / _F64(20.0)
    for i in range(4):
        pi = p[t[i]] * free[t[i]]
        wp.atomic_add(out, t[i], P * shape_gradients(Dinv, i) + mc * (psum + pi))


@wp.kernel
def combine_kernel(
    count: wp.array(dtype=wp.int32),
    p: wp.array(dtype=wp.vec3d),
    free: wp.array(dtype=wp.float64),
    lumped_mass: wp.array(dtype=wp.float64),
    m_coef: wp.float64,
    Kp: wp.array(dtype=wp.vec3d),
    alpha: wp.float64,
    y: wp.array(dtype=wp.vec3d),
    beta: wp.float64,
    z: wp.array(dtype=wp.vec3d),
    reset: int,
):
    """z = alpha * (filtered A p) + beta * y, with A p = m_coef m_i p_i + Kp_i on free nodes, p_i on fixed;
    with ``reset``, Kp_i = 0 once read (Kp is then zero for the next product: no zeroing launch)."""
    i = wp.tid()
    if i >= count[0]:
        return
    Ap = p[i]
    if free[i] > _F64(0.0):
        Ap = m_coef * lumped_mass[i] * p[i] + Kp[i]
    if reset != 0:
        Kp[i] = wp.vec3d()
    z[i] = alpha * Ap + beta * y[i]


@wp.func
def element_block(
    Dinv: wp.mat33d, Re: wp.mat33d, V: wp.float64, mu: wp.float64, lam: wp.float64, rho: wp.float64,
    i: int, j: int, k_coef: wp.float64, m_coef: wp.float64, consistent: int,
):
    """Block (i, j) of one element's contribution to A = m_coef M + k_coef K (unfiltered).

    K_ij = V R (mu (g_i.g_j) I + mu g_j g_i^T + lambda g_i g_j^T) R^T; mass m_coef rho V/20 (1+d_ij) I
    (consistent) or m_coef rho V/4 I on the diagonal (lumped).
    """
    I3 = wp.identity(n=3, dtype=wp.float64)
    gi = shape_gradients(Dinv, i)
    gj = shape_gradients(Dinv, j)
    K0 = mu * wp.dot(gi, gj) * I3 + mu * wp.outer(gj, gi) + lam * wp.outer(gi, gj)
    blk = (k_coef * V) * (Re * K0 * wp.transpose(Re))
    if consistent != 0:
        w = _F64(1.0)
        if i == j:
            w = _F64(2.0)
        blk += (m_coef * rho * V / _F64(20.0) * w) * I3
    elif i == j:
        blk += (m_coef * rho * V / _F64(4.0)) * I3
    return blk


@wp.kernel
def element_blocks_subset_kernel(
    ids: wp.array(dtype=wp.int32),
    tets: wp.array(dtype=wp.vec4i),
    free: wp.array(dtype=wp.float64),
    Dm_inv: wp.array(dtype=wp.mat33d),
    volume: wp.array(dtype=wp.float64),
    mu: wp.array(dtype=wp.float64),
    lam: wp.array(dtype=wp.float64),
    rho: wp.array(dtype=wp.float64),
    R: wp.array(dtype=wp.mat33d),
    k_coef: wp.float64,
    m_coef: wp.float64,
    consistent: int,
    rows: wp.array(dtype=wp.int32),
    cols: wp.array(dtype=wp.int32),
    values: wp.array(dtype=wp.mat33d),
):
    """The 16 3x3 blocks of the elements ids[0..]'s contributions to the filtered A, as COO
    triplets (blocks touching a fixed node are zero): all elements for the assembly, or those
    a cut removes or adds (the perturbation N of the Sherman-Morrison correction, eq. 5)."""
    s = wp.tid()
    e = ids[s]
    t = tets[e]
    for i in range(4):
        for j in range(4):
            blk = element_block(Dm_inv[e], R[e], volume[e], mu[e], lam[e], rho[e], i, j, k_coef, m_coef, consistent)
            k = s * 16 + i * 4 + j
            rows[k] = t[i]
            cols[k] = t[j]
            values[k] = blk * (free[t[i]] * free[t[j]])


@wp.kernel
def fixed_identity_kernel(
    free: wp.array(dtype=wp.float64),
    offset: int,
    rows: wp.array(dtype=wp.int32),
    cols: wp.array(dtype=wp.int32),
    values: wp.array(dtype=wp.mat33d),
):
    i = wp.tid()
    rows[offset + i] = i
    cols[offset + i] = i
    values[offset + i] = (_F64(1.0) - free[i]) * wp.identity(n=3, dtype=wp.float64)


@wp.kernel
def diagonal_blocks_kernel(
    tets: wp.array(dtype=wp.vec4i),
    Dm_inv: wp.array(dtype=wp.mat33d),
    volume: wp.array(dtype=wp.float64),
    mu: wp.array(dtype=wp.float64),
    lam: wp.array(dtype=wp.float64),
    rho: wp.array(dtype=wp.float64),
    R: wp.array(dtype=wp.mat33d),
    k_coef: wp.float64,
    m_coef: wp.float64,
    consistent: int,
    diag: wp.array(dtype=wp.mat33d),
):
    """diag_i += the (i, i) 3x3 blocks of A = m_coef M + k_coef K (unfiltered)."""
    e = wp.tid()
    t = tets[e]
    Re = R[e]
    I3 = wp.identity(n=3, dtype=wp.float64)
    mfac = _F64(0.25)
    if consistent != 0:
        mfac = _F64(0.1)
    for i in range(4):
        g = shape_gradients(Dm_inv[e], i)
        K0 = mu[e] * wp.dot(g, g) * I3 + (mu[e] + lam[e]) * wp.outer(g, g)
        blk = (k_coef * volume[e]) * (Re * K0 * wp.transpose(Re)) + (m_coef * rho[e] * volume[e] * mfac) * I3
        wp.atomic_add(diag, t[i], blk)


@wp.kernel
def node_rotation_accumulate_kernel(
    count: wp.array(dtype=wp.int32),
    tets: wp.array(dtype=wp.vec4i),
    volume: wp.array(dtype=wp.float64),
    R: wp.array(dtype=wp.mat33d),
    acc: wp.array(dtype=wp.mat33d),
):
    e = wp.tid()
    if e >= count[0]:
        return
    t = tets[e]
    for k in range(4):
        wp.atomic_add(acc, t[k], volume[e] * R[e])


@wp.kernel
def orthonormalize_kernel(count: wp.array(dtype=wp.int32), acc: wp.array(dtype=wp.mat33d),
                          out: wp.array(dtype=wp.mat33d)):
    i = wp.tid()
    if i < count[0]:
        out[i] = rotation_from(acc[i])


@wp.kernel
def zero_vectors_kernel(count: wp.array(dtype=wp.int32), out: wp.array(dtype=wp.vec3d)):
    """out[i] = 0 for i < count[0]."""
    i = wp.tid()
    if i < count[0]:
        out[i] = wp.vec3d()


@wp.kernel
def zero_matrices_kernel(count: wp.array(dtype=wp.int32), out: wp.array(dtype=wp.mat33d)):
    """out[i] = 0 for i < count[0]."""
    i = wp.tid()
    if i < count[0]:
        out[i] = wp.mat33d()


@wp.kernel
def _orthonormalize_subset_kernel(nodes: wp.array(dtype=wp.int32), acc: wp.array(dtype=wp.mat33d),
                                  out: wp.array(dtype=wp.mat33d)):
    """out[s] = the rotation of acc[nodes[s]] (:func:`orthonormalize_kernel` on those nodes)."""
    s = wp.tid()
    out[s] = rotation_from(acc[nodes[s]])


@wp.kernel
def _gather_rotations_kernel(src: wp.array(dtype=wp.int32), old: wp.array(dtype=wp.mat33d),
                             R: wp.array(dtype=wp.mat33d)):
    """R[e] = old[src[e]] where src[e] >= 0 (a tet taking over its source's rotation)."""
    e = wp.tid()
    s = src[e]
    if s >= 0:
        R[e] = old[s]


@wp.kernel
def _scatter_rotations_kernel(ids: wp.array(dtype=wp.int32), R_sub: wp.array(dtype=wp.mat33d),
                              R: wp.array(dtype=wp.mat33d)):
    s = wp.tid()
    R[ids[s]] = R_sub[s]


def _same_rest_shape(X, T, X_old, T_old) -> np.ndarray:
    """(k,) whether the tets T (k, 4) of points X have the rest positions of the tets T_old of
    points X_old, node for node (float equality of all 12 coordinates). A node that keeps its
    index and its position (most of them, across a topology change) is settled by comparing
    indices; only the other corners' positions are gathered and compared. The coordinates are
    compared column by column and a tet's 4 flags read together (:func:`..mesh.all_four`)."""
    n = min(len(X), len(X_old))
    kept_common = _same_points(X[:n], X_old[:n])  # nodes with the same index and rest position
    if kept_common.all():  # an index both tets hold is below n (T_old's are): a kept node
        same = np.equal(T, T_old).reshape(-1, 4)
    else:
        kept = np.zeros(len(X), bool)
        kept[:n] = kept_common
        same = np.ascontiguousarray((T == T_old) & kept[T], dtype=bool).reshape(-1, 4)
    other = ~same
    if other.any():
        same[other] = _same_points(np.take(X, T[other], axis=0), np.take(X_old, T_old[other], axis=0))
    return all_four(same)


def _bucket(k: int) -> int:
    """The count a scratch array of ``k`` entries is reserved with: the next power of two (at
    least 16), so that calls of similar sizes share one set of views."""
    return max(16, 1 << (int(k) - 1).bit_length())


def _same_points(P, Q) -> np.ndarray:
    """(k,) whether the points P (k, 3) and Q (k, 3) are equal (all three coordinates)."""
    return (P[:, 0] == Q[:, 0]) & (P[:, 1] == Q[:, 1]) & (P[:, 2] == Q[:, 2])


class CorotationalFEM:
    """Rest-state data and per-step corotational operators of one tetrahedral body.

    The per-step launches (rotations, forces, products, node rotations) cover the arrays'
    capacities (:attr:`node_dim`, :attr:`tet_dim`) and read the node and tet counts from the
    device (:attr:`counts`), never from the arrays' shapes: a graph captured of them stays valid
    across topology changes while the allocations hold (the :meth:`graph_key` of an operator
    names the addresses and these dimensions, not the counts)."""

    def __init__(
        self,
        mesh: TetMesh,
        materials: MaterialTable,
        device,
        *,
        mass: str = "lumped",
        fixed_nodes: np.ndarray | None = None,
    ):
        if mass not in ("lumped", "consistent"):
            raise ValueError(f"mass must be 'lumped' or 'consistent', got {mass!r}")
        self.device = wp.get_device(device)
        self.materials = materials
        self.consistent_mass = mass == "consistent"
        self.set_mesh(mesh, fixed_nodes)

    # ----------------------------------------------------------------- set-up
    def set_mesh(self, mesh: TetMesh, fixed_nodes: np.ndarray | None = None, tet_source=None) -> None:
        """(Re)build all rest-state arrays for ``mesh`` (also after a topology change).

        ``tet_source`` (m,): for each tet, the tet of the previous mesh it comes from, or -1
        (a topology change keeps most tets as they were). A tet whose four rest positions equal
        its source's, bit for bit, takes the source's Dm^-1 and volume; the others are computed.
        Both ways give the same numbers (each tet's are a function of its rest positions). Such
        a tet also takes its source's element rotation; :meth:`update_rotations` with
        ``changed_only`` then computes the others' (where the previous rotations were of the
        same positions, node for node). Without ``tet_source`` the rotations are the identity.

        The arrays are views into allocations kept across changes (:mod:`soft_tissue_sim.
        buffers`); the data that changed is sent in one copy per run of fields. Bad input
        raises ValueError and leaves the FEM as it was."""
        n, m = mesh.n_nodes, mesh.n_tets
        X = mesh.points.astype(np.float64)
        T = mesh.tets.astype(np.int32)
        prev = getattr(self, "_rest_tets", None)
        reuse, src, in_place = np.zeros(m, bool), None, False
        if tet_source is not None and prev is not None:
            src = np.asarray(tet_source, dtype=np.int64)
            lo, hi = (int(src.min()), int(src.max())) if m and src.shape == (m,) else (0, -1)
            if src.shape != (m,) or lo < -1 or hi >= len(prev[1]):
                raise ValueError(f"tet_source must hold one index in [-1, {len(prev[1])}) per tet ({m}), got "
                                 f"shape {src.shape}")
            in_place = len(prev[1]) == m and np.array_equal(src, np.arange(m))  # each tet its source's index
            if in_place:
                reuse = _same_rest_shape(X, T, prev[0], prev[1])
            else:
                k = np.flatnonzero(src >= 0)
                reuse[k] = _same_rest_shape(X, np.take(T, k, axis=0), prev[0], np.take(prev[1], src[k], axis=0))
        host = self.__dict__.setdefault("_element_host", {})  # the element data on the device, as sent
        # every tet in place with its source's shape (a node split): the rest data is the old one
        same_place = bool(m and in_place and reuse.all())
        kept = set()  # the element fields known unchanged (not sent again)
        if same_place:
            Dm_inv, vol = host["Dm_inv"], host["volume"]
            kept |= {"Dm_inv", "volume"}
        else:
            if reuse.any():  # every tet's from its source, then the computed ones overwritten
                take = np.where(reuse, src, 0)
                Dm_inv, vol = np.take(host["Dm_inv"], take, axis=0), np.take(host["volume"], take)
            else:
                Dm_inv, vol = np.empty((m, 3, 3)), np.empty(m)
            new = np.flatnonzero(~reuse)
            Xn = np.take(X, np.take(T, new, axis=0), axis=0)  # (k, 4, 3) the computed tets' rest positions
            Dm = np.stack([Xn[:, 1] - Xn[:, 0], Xn[:, 2] - Xn[:, 0], Xn[:, 3] - Xn[:, 0]], axis=2)
            vol[new] = np.linalg.det(Dm) / 6.0
            if np.any(vol <= 0.0):
                bad = np.flatnonzero(vol <= 0.0)
                raise ValueError(f"{len(bad)} tets with non-positive rest volume, e.g. {bad[:10].tolist()}")
            Dm_inv[new] = np.linalg.inv(Dm)
        mats = mesh.material_ids
        old_mats = host.get("material_ids")
        if (src is not None and old_mats is not None and (m == 0 or lo >= 0)
                and np.array_equal(mats, old_mats if same_place else np.take(old_mats, src))):
            if same_place:  # each tet's material as its source's: the same (mu, lambda, rho)
                mu, lam, rho = host["mu"], host["lam"], host["rho"]
                kept |= {"mu", "lam", "rho"}
            else:
                mu, lam, rho = (np.take(host[k], src) for k in ("mu", "lam", "rho"))
        else:
            mu, lam, rho = self.materials.element_arrays(mats)
        lumped = np.bincount(T.ravel(), weights=np.repeat(rho * vol / 4.0, 4), minlength=n)  # in order, as add.at
        free = np.ones(n)
        if fixed_nodes is not None and len(fixed_nodes):
            free[np.asarray(fixed_nodes, dtype=np.int64)] = 0.0
        d = self.device
        if getattr(self, "_packed", None) is None:
            # rest data: the fields that change with every mesh first (one run), then the element
            # data, which a node split leaves as it was; src: the tets' rotation sources (a gather)
            self._packed = PackedArrays({"counts": wp.int32, "rest": wp.vec3d, "lumped_mass": wp.float64,
                                         "free": wp.float64, "tets": wp.vec4i, "src": wp.int32, "Dm_inv": wp.mat33d,
                                         "volume": wp.float64, "mu": wp.float64, "lam": wp.float64,
                                         "rho": wp.float64}, d)
            self._sub = PackedArrays({"ids": wp.int32, "tets": wp.vec4i, "Dm_inv": wp.mat33d, "volume": wp.float64,
                                      "nodes": wp.int32}, d)
            self._grow = {name: GrowArray(dtype, d, fill) for name, dtype, fill in (
                ("rotations", wp.mat33d, None), ("_rot_old", wp.mat33d, None),
                ("_Kp", wp.vec3d, lambda cap: np.zeros((cap, 3))),  # zero between products: see system_product
                ("_rot_acc", wp.mat33d, None), ("_node_rot", wp.mat33d, None), ("_ones", wp.float64, 1.0),
                ("_all_tets", wp.int32, lambda cap: np.arange(cap, dtype=np.int32)), ("_rows", wp.int32, None),
                ("_cols", wp.int32, None), ("_vals", wp.mat33d, None), ("_sub_R", wp.mat33d, None),
                ("_sub_node_R", wp.mat33d, None))}
        packed, grow = self._packed, self._grow
        # the element rotations the new tets take over from their sources: in place where each
        # keeps its source's index (a node split), else gathered from a copy of the old ones
        carry = src is not None and reuse.any() and getattr(self, "rotations", None) is not None
        gather = carry and (m > grow["rotations"].capacity
                            or not (in_place or np.array_equal(np.flatnonzero(reuse), src[reuse])))
        if gather:
            old = grow["_rot_old"].view(self.n_tets)
            wp.copy(old, self.rotations)
        data = {"counts": np.array([n, m], np.int32), "rest": X, "lumped_mass": lumped, "free": free, "tets": T,
                "Dm_inv": Dm_inv, "volume": vol, "mu": mu, "lam": lam, "rho": rho}
        if gather:
            data["src"] = np.where(reuse, src, -1).astype(np.int32)
        realloc = packed.reserve({k: len(data[k]) if k in data else m for k in packed.fields})
        changed = []
        for name, a in data.items():
            if realloc or name not in kept:
                h = packed.host(name)
                h[...] = a.reshape(h.shape)
                if name != "src":
                    host[name] = a
                changed.append(name)
        host["material_ids"] = mats.copy()
        packed.send(changed)
        self.uploads = changed  # the fields this change sent (tests, statistics)
        self.mesh = mesh
        self.n_nodes, self.n_tets = n, m
        for name in data:
            if name != "src":
                setattr(self, name, packed.array(name))
        # the counts on the device (node, tet) and the launches' dimensions (the capacities)
        self.n_nodes_dev, self.n_tets_dev = self.counts[0:1], self.counts[1:2]
        self.node_dim, self.tet_dim = packed.capacity["rest"], packed.capacity["tets"]
        self.fixed_nodes = np.flatnonzero(free == 0.0)
        self.rotations = grow["rotations"].view(m)
        self._carried = None
        if carry:  # the others' rotations are left undefined: update_rotations(changed_only) computes them
            if gather:
                wp.launch(_gather_rotations_kernel, m, [packed.array("src"), old, self.rotations], device=d)
            self._carried = np.flatnonzero(~reuse)
        else:
            self.rotations.fill_(wp.mat33d(*np.eye(3).ravel()))
        self._Kp = grow["_Kp"].view(n)
        self.node_rotations_current = False  # update_node_rotations ran after the last update_rotations
        self._rot_acc = grow["_rot_acc"].view(n)
        self._node_rot = grow["_node_rot"].view(n)
        self.total_mass = float(lumped.sum())
        self._rest_tets = (X, T)  # with _element_host: what the next set_mesh may take over (tet_source)

    # COO triplets of A (assemble_triplets writes every entry): 16 blocks per element + one
    # diagonal block per node; views of the kept allocations, made when first read after a change
    @property
    def _all_tets(self) -> wp.array:
        return self._grow["_all_tets"].view(self.n_tets)

    def _triplet_view(self, name: str) -> wp.array:
        return self._grow[name].view(16 * self.n_tets + self.n_nodes)

    _rows = property(lambda self: self._triplet_view("_rows"))
    _cols = property(lambda self: self._triplet_view("_cols"))
    _vals = property(lambda self: self._triplet_view("_vals"))

    def set_fixed_nodes(self, fixed_nodes) -> None:
        free = np.ones(self.n_nodes)
        free[np.asarray(fixed_nodes, dtype=np.int64)] = 0.0
        self.free.assign(free)
        self.fixed_nodes = np.flatnonzero(free == 0.0)

    # -------------------------------------------------------------- per step
    def update_rotations(self, x: wp.array, changed_only: bool = False, tets=None) -> None:
        """The element rotations at positions ``x``: of all tets, or of ``tets`` (indices; the
        others keep theirs). ``changed_only``: right after a :meth:`set_mesh` with
        ``tet_source``, whose rotations before it were of the same positions node for node (a
        topology change: the state unchanged), compute only the tets that did not take over
        their source's (the others' would come out the same)."""
        self.node_rotations_current = False
        ids = self._carried if changed_only else (None if tets is None else np.asarray(tets, np.int64))
        self._carried = None
        if ids is None:
            wp.launch(element_rotations_kernel, self.tet_dim, [self.n_tets_dev, x, self.tets, self.Dm_inv,
                                                               self.rotations], device=self.device)
        elif len(ids):
            self._subset_rotations(x, ids)

    def _subset_rotations(self, x: wp.array, ids: np.ndarray, nodes=None) -> wp.array:
        """The rotations at ``x`` of the tets ``ids`` (ascending), into the element rotations
        (the same kernel as for all tets, on those: the same numbers); with ``nodes``, also the
        node rotations of those nodes from these tets alone. Returns the tets' rotations."""
        k, d = len(ids), self.device
        sub = self._sub
        # the fields hold their first k (nodes: len(nodes)) entries; their counts are rounded up
        # (_bucket) and the launches cover those entries alone
        b = _bucket(k)
        sub.reserve({"ids": b, "tets": b, "Dm_inv": b, "volume": b,
                     "nodes": sub.counts["nodes"] if nodes is None else _bucket(len(nodes))})
        sub.host("ids")[:k] = ids
        np.take(self._rest_tets[1], ids, axis=0, out=sub.host("tets")[:k])
        np.take(self._element_host["Dm_inv"], ids, axis=0, out=sub.host("Dm_inv")[:k])
        fields = ["ids", "tets", "Dm_inv"]
        if nodes is not None:
            np.take(self._element_host["volume"], ids, out=sub.host("volume")[:k])
            sub.host("nodes")[:len(nodes)] = nodes
            fields += ["volume", "nodes"]
        sub.send(fields)
        R = self._grow["_sub_R"].view(b)
        wp.launch(element_rotations_kernel, k, [unbounded_count(d), x, sub.array("tets"), sub.array("Dm_inv"), R],
                  device=d)
        wp.launch(_scatter_rotations_kernel, k, [sub.array("ids"), R, self.rotations], device=d)
        return R

    def node_rotations_around(self, x: wp.array, tets, nodes) -> np.ndarray:
        """The node rotations (eq. 2) of ``nodes`` at positions ``x``, from the element
        rotations of ``tets`` alone, which must hold every tet of those nodes (ascending, so
        that each node's volume-weighted sum adds up in the order of :meth:`update_node_rotations`:
        the same numbers). The tets' rotations at ``x`` go into the element rotations too (the
        others keep theirs). Returns (n, 3, 3) on the host, NaN outside ``nodes``."""
        ids, nodes = np.asarray(tets, np.int64), np.asarray(nodes, np.int32)
        out = np.full((self.n_nodes, 3, 3), np.nan)
        self.node_rotations_current = False
        if not len(nodes):
            return out
        R = self._subset_rotations(x, ids, nodes)
        d, sub, g = self.device, self._sub, self._grow
        self._rot_acc.zero_()
        wp.launch(node_rotation_accumulate_kernel, len(ids),
                  [unbounded_count(d), sub.array("tets"), sub.array("volume"), R, self._rot_acc], device=d)
        R_nodes = g["_sub_node_R"].view(sub.counts["nodes"])
        wp.launch(_orthonormalize_subset_kernel, len(nodes), [sub.array("nodes"), self._rot_acc, R_nodes], device=d)
        out[nodes] = to_host(R_nodes)[0][:len(nodes)]
        return out

    def add_elastic_forces(self, x: wp.array, f: wp.array) -> None:
        """f += elastic forces at positions x, with the current element rotations."""
        wp.launch(
            elastic_force_kernel,
            self.tet_dim,
            [self.n_tets_dev, x, self.tets, self.Dm_inv, self.volume, self.mu, self.lam, self.rotations, f],
            device=self.device,
        )

    def system_product(self, p, y, z, alpha, beta, m_coef, k_coef) -> None:
        """z = alpha * A p + beta * y with A = m_coef M + k_coef K, filtered on fixed nodes. The
        stiffness product goes into ``_Kp``, which is zero before (allocated zeroed) and after
        (the combination zeroes each entry it reads; the product writes only the current nodes)."""
        self._stiffness(p, self.free, k_coef, m_coef if self.consistent_mass else 0.0, self._Kp)
        wp.launch(
            combine_kernel,
            self.node_dim,
            [self.n_nodes_dev, p, self.free, self.lumped_mass, 0.0 if self.consistent_mass else float(m_coef), self._Kp,
             float(alpha), y, float(beta), z, 1],
            device=self.device,
        )

    def stiffness_product(self, p: wp.array, out: wp.array) -> None:
        """out = K p (unfiltered corotated stiffness, no mass): used for b and damping."""
        self.zero_nodes(out)
        self._stiffness(p, self._ones(), 1.0, 0.0, out)

    def _stiffness(self, p: wp.array, free: wp.array, k_coef: float, m_coef: float, out: wp.array) -> None:
        """out += k_coef K (free p) + m_coef M_consistent (free p): :func:`stiffness_product_kernel`
        over the tets' capacity."""
        wp.launch(stiffness_product_kernel, self.tet_dim,
                  [self.n_tets_dev, p, free, self.tets, self.Dm_inv, self.volume, self.mu, self.lam, self.rho,
                   self.rotations, float(k_coef), float(m_coef), out], device=self.device)

    def zero_nodes(self, out: wp.array) -> None:
        """out[i] = 0 for the current nodes (a launch reading the count: capturable across sizes)."""
        wp.launch(zero_vectors_kernel, self.node_dim, [self.n_nodes_dev, out], device=self.device)

    def _ones(self) -> wp.array:
        return self._grow["_ones"].view(self.n_nodes)

    def mass_product(self, p: wp.array, out: wp.array) -> None:
        """out = M p (lumped or consistent, unfiltered)."""
        self.zero_nodes(out)
        if self.consistent_mass:
            self._stiffness(p, self._ones(), 0.0, 1.0, out)
        else:
            wp.launch(
                combine_kernel,
                self.node_dim,
                [self.n_nodes_dev, p, self._ones(), self.lumped_mass, 1.0, out, 1.0, out, 0.0, out, 0],
                device=self.device,
            )

    def diagonal_blocks(self, m_coef: float, k_coef: float, out: wp.array) -> None:
        """out = the 3x3 diagonal blocks of A = m_coef M + k_coef K (fixed nodes: identity)."""
        out.zero_()
        wp.launch(
            diagonal_blocks_kernel,
            self.n_tets,
            [self.tets, self.Dm_inv, self.volume, self.mu, self.lam, self.rho, self.rotations,
             float(k_coef), float(m_coef), int(self.consistent_mass), out],
            device=self.device,
        )

    # ------------------------------------------------------------- assembly
    def assemble_triplets(self, m_coef: float, k_coef: float):
        """The filtered A = m_coef M + k_coef K as COO triplets of 3x3 blocks on the device:
        (rows, cols, values), 16 blocks per element (zero where they touch a fixed node) and one
        per node (the identity on fixed nodes, zero elsewhere). Duplicates add up."""
        rows, cols, vals = self._rows, self._cols, self._vals
        wp.launch(
            element_blocks_subset_kernel,
            self.n_tets,
            [self._all_tets, self.tets, self.free, self.Dm_inv, self.volume, self.mu, self.lam, self.rho,
             self.rotations, float(k_coef), float(m_coef), int(self.consistent_mass), rows, cols, vals],
            device=self.device,
        )
        wp.launch(
            fixed_identity_kernel, self.n_nodes, [self.free, 16 * self.n_tets, rows, cols, vals],
            device=self.device,
        )
        return rows, cols, vals

    def element_blocks(self, tet_ids, m_coef: float, k_coef: float):
        """The filtered 3x3 blocks of A = m_coef M + k_coef K contributed by the elements ``tet_ids``,
        with the current element rotations: (rows, cols, values) numpy arrays of 16 blocks each."""
        ids = np.asarray(tet_ids, dtype=np.int32)
        k = 16 * len(ids)
        if k == 0:
            return np.zeros(0, np.int32), np.zeros(0, np.int32), np.zeros((0, 3, 3))
        # rows and cols are the tets' nodes (block (i, j) of tet t at (t_i, t_j)): from the host's
        # copy of the tets; the values come from the device, in one read
        T = np.take(self._rest_tets[1], ids, axis=0)
        rows, cols = np.repeat(T, 4, axis=1).reshape(-1), np.tile(T, (1, 4)).reshape(-1)
        d, g = self.device, self._grow
        if getattr(self, "_block_ids", None) is None:
            self._block_ids = PackedArrays({"ids": wp.int32}, d)
            g["_block_rows"], g["_block_cols"] = GrowArray(wp.int32, d), GrowArray(wp.int32, d)
            g["_block_vals"] = GrowArray(wp.mat33d, d)
        # the buffers' counts rounded up (_bucket): the launch writes the first k blocks
        sent, b = self._block_ids, _bucket(len(ids))
        sent.reserve({"ids": b})
        sent.host("ids")[:len(ids)] = ids
        sent.send(("ids",))
        vals = g["_block_vals"].view(16 * b)
        wp.launch(
            element_blocks_subset_kernel,
            len(ids),
            [sent.array("ids"), self.tets, self.free, self.Dm_inv, self.volume, self.mu, self.lam, self.rho,
             self.rotations, float(k_coef), float(m_coef), int(self.consistent_mass), g["_block_rows"].view(16 * b),
             g["_block_cols"].view(16 * b), vals],
            device=d,
        )
        return rows, cols, to_host(vals)[0][:k].copy()  # a copy: the buffers serve the next call

    def assembly_state(self, m_coef: float, k_coef: float) -> AssemblyState:
        """Host copies of what the filtered A = m_coef M + k_coef K depends on now (the element
        rotations of the last :meth:`update_rotations`, topology, rest gradients, material,
        fixed flags): :meth:`AssemblyState.csc` assembles A from them on any thread, with NumPy."""
        host = (lambda a: a.numpy().copy()) if self.device.is_cpu else (lambda a: a.numpy())
        return AssemblyState(self.n_nodes, host(self.tets), host(self.Dm_inv), host(self.volume), host(self.mu),
                             host(self.lam), host(self.rho), host(self.free), host(self.rotations), float(m_coef),
                             float(k_coef), self.consistent_mass)

    def assemble_scipy(self, m_coef: float, k_coef: float) -> sps.csc_matrix:
        """The filtered A as a scipy CSC matrix (for CHOLMOD and direct solves)."""
        return self.assembly_state(m_coef, k_coef).csc()

    # ------------------------------------------------------------ rotations
    def update_node_rotations(self) -> wp.array:
        """Per-node rotations (n, mat33d, on the device): the volume-weighted average of the
        element rotations around each node, projected back onto SO(3) (the rotations of eq. 2).
        Launches only; uses the element rotations of the last :meth:`update_rotations`."""
        wp.launch(zero_matrices_kernel, self.node_dim, [self.n_nodes_dev, self._rot_acc], device=self.device)
        wp.launch(node_rotation_accumulate_kernel, self.tet_dim,
                  [self.n_tets_dev, self.tets, self.volume, self.rotations, self._rot_acc], device=self.device)
        wp.launch(orthonormalize_kernel, self.node_dim, [self.n_nodes_dev, self._rot_acc, self._node_rot],
                  device=self.device)
        self.node_rotations_current = True
        return self._node_rot

    def current_node_rotations(self) -> wp.array:
        """The node rotations of the current element rotations: those the last
        :meth:`update_node_rotations` launched if no :meth:`update_rotations` came after it,
        else launched now."""
        return self._node_rot if self.node_rotations_current else self.update_node_rotations()

    def node_rotations(self) -> np.ndarray:
        """:meth:`update_node_rotations` read back to the host, (n, 3, 3) (a copy)."""
        return to_host(self.update_node_rotations())[0].copy()
