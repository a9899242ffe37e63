"""The ``dense`` factor backend: A(t_u)^-1 held as a dense matrix on the device.

For the bodies of the paper (a few thousand nodes) the inverse of A = M + dt^2 K fits in
device memory (8 n3^2 bytes: 216 MB for the 1,734-node brain), and what the method needs of
its factor becomes dense linear algebra that a GPU does at memory speed:

* the factor is cuSOLVER's Cholesky factorization and the inverse from it (``potrf``, then
  cuBLAS's ``trsm`` against the identity and ``trmm``, through nvmath-python's bindings, by
  column blocks so that the zeros of the triangular X = L^-1 are neither solved for nor
  multiplied: :meth:`DenseInverse._inverse_from_factor`; SciPy's LAPACK ``potrf`` and
  ``potri`` on the CPU);
* an application of eq. (2), z = dR A^-1 dR^T r, is one matrix-vector product between two
  rotations (:func:`dense_apply_kernel`: a block of threads per node, its three rows against
  the rotated vector). It reads the whole matrix once, so its time is the matrix's size over
  the memory bandwidth: with ``precision="float32"`` it reads a single-precision copy of the
  inverse's lower triangle (made after each install, fold and regrow), packed in 96 x 96
  tiles, each tile read once for its own product and its transpose's (:func:`sym_tile`,
  products summed in double precision, then each node's partial sums in a fixed order): a
  quarter of the double-precision matrix's bytes. The preconditioner then differs from
  A(t_u)^-1 by about 1e-7 relatively, far less than a factor a few steps old does; the
  corrections, W and the columns U keep using the double-precision inverse;
* the Sherman-Morrison-Woodbury correction of eq. (5)-(7) is exact and folded into the
  inverse: U = P^-1 G is a gather of columns, Q = (I + N S)^-1 N a small solve on the device
  (S = G^T U; cuSOLVER's ``getrf`` and ``getrs``, nothing read back), and P^-1 - U Q U^T
  replaces P^-1 (a rank-3k update, cuBLAS ``gemm``): :class:`LibraryFold`, nine calls into
  kept buffers;
* the Delassus operator W = H P^-1 H^T of eq. (4) gathers the 3x3 blocks of the contact
  nodes (:func:`delassus_kernel`, an entry of W per thread; :func:`delassus_matrix_kernel`
  for a row count read on the device, the contact LCP solved there), and the response
  P^-1 H^T lambda reads the contact nodes' columns (:func:`rows_apply`).

The matrix is symmetric and stored row-major (C order); LAPACK and cuSOLVER see it as its
column-major transpose, the same matrix. On the CPU ``potri`` fills one triangle, which
:func:`symmetrize_kernel` mirrors. Arrays are Warp arrays, handed to cuSOLVER and cuBLAS by
address (GPU) or viewed by NumPy without copies (CPU: the fold's arithmetic, :func:`fold_into`).

Capacity. The inverse in use is an (n3, n3) view with a fixed row stride L (the leading
dimension, :func:`leading_dimension`: n3 with headroom, a multiple of 96) into a store whose
address holds while n3 <= L; its size n3 is also kept in a one-element device array, written by
a launch on the stream of the change. :meth:`DenseInverse.apply` is launched over the capacity
(L / 3 nodes) and reads the size from that array, so that a graph captured with it stays valid
across the size changes of cuts (:meth:`DenseInverse.graph_key` holds no size).
"""

from __future__ import annotations

import contextlib
import sys

import numpy as np
import warp as wp

from .buffers import GrowArray, PackedArrays, capacity_for, typed_view
from .cg import block_sum, set_count_kernel
from .transfer import PINNED, to_host

wp.set_module_options({"enable_backward": False})  # no gradients are taken

BLOCK = 256  # threads per node in the double-precision matrix-vector product on CUDA
LD_MULTIPLE = 96  # leading dimensions are multiples of this: whole nodes, rows 128-byte aligned in float32


def leading_dimension(n3: int) -> int:
    """The leading dimension of a store made for n3 DOFs: n3 with headroom
    (:func:`~soft_tissue_sim.buffers.capacity_for`), rounded up to a multiple of ``LD_MULTIPLE``."""
    return -(-capacity_for(int(n3)) // LD_MULTIPLE) * LD_MULTIPLE


@wp.kernel
def scatter_dense_kernel(rows: wp.array(dtype=wp.int32), cols: wp.array(dtype=wp.int32),
                         vals: wp.array(dtype=wp.mat33d), A: wp.array2d(dtype=wp.float64)):
    """A += the 3x3 block triplets (rows, cols, vals) (duplicates add up)."""
    t = wp.tid()
    r = 3 * rows[t]
    c = 3 * cols[t]
    v = vals[t]
    for a in range(3):
        for b in range(3):
            if v[a, b] != wp.float64(0.0):
                wp.atomic_add(A, r + a, c + b, v[a, b])


@wp.kernel
def symmetrize_kernel(A: wp.array2d(dtype=wp.float64)):
    """A[i, j] = A[j, i] below the diagonal: the row-major upper triangle (LAPACK's column-major
    lower one, which ``potri`` with ``lower`` fills) mirrored."""
    i, j = wp.tid()
    if i > j:
        A[i, j] = A[j, i]


@wp.kernel
def zero_matrix_kernel(A: wp.array2d(dtype=wp.float64)):
    i, j = wp.tid()
    A[i, j] = wp.float64(0.0)


@wp.kernel
def identity_matrix_kernel(A: wp.array2d(dtype=wp.float64)):
    i, j = wp.tid()
    A[i, j] = wp.where(i == j, wp.float64(1.0), wp.float64(0.0))


@wp.kernel
def regrow_kernel(old: wp.array2d(dtype=wp.float64), keep: wp.array(dtype=wp.int32),
                  out: wp.array2d(dtype=wp.float64)):
    """out = old[keep][:, keep] padded with identity rows and columns (eq. 10)."""
    i, j = wp.tid()
    k = keep.shape[0]
    if i < k and j < k:
        out[i, j] = old[keep[i], keep[j]]
    elif i == j:
        out[i, j] = wp.float64(1.0)
    else:
        out[i, j] = wp.float64(0.0)


@wp.kernel
def pad_identity_kernel(P: wp.array2d(dtype=wp.float64), k: int):
    """P[i, j] = P[j, i] = the identity's entry for j = k + t, launched over (i, t) in
    (n, added): rows and columns k .. n - 1 of the (n, n) P made identity rows in place (eq. 10's
    padding)."""
    i, t = wp.tid()
    j = k + t
    v = wp.where(i == j, wp.float64(1.0), wp.float64(0.0))
    P[i, j] = v
    P[j, i] = v


@wp.kernel
def fold_columns_kernel(P: wp.array2d(dtype=wp.float64), rows: wp.array(dtype=wp.int32),
                        UT: wp.array2d(dtype=wp.float64)):
    """UT[c, i] = P[rows[c], i]: the columns U = P G of the symmetric P, written as rows (reads
    and writes contiguous); UT row-major is U column-major (n x k, leading dimension n)."""
    c, i = wp.tid()
    UT[c, i] = P[rows[c], i]


@wp.kernel
def fold_small_kernel(UT: wp.array2d(dtype=wp.float64), rows: wp.array(dtype=wp.int32),
                      S: wp.array2d(dtype=wp.float64), M: wp.array2d(dtype=wp.float64)):
    """S = G^T P G (the rows of U at the affected DOFs) and M = I, the two k x k inputs of
    M := I + N S."""
    a, b = wp.tid()
    S[a, b] = UT[b, rows[a]]
    M[a, b] = wp.where(a == b, wp.float64(1.0), wp.float64(0.0))


@wp.kernel
def symmetrize_small_kernel(Q: wp.array2d(dtype=wp.float64)):
    """Q := (Q + Q^T) / 2 in place (each pair once)."""
    a, b = wp.tid()
    if a < b:
        v = wp.float64(0.5) * (Q[a, b] + Q[b, a])
        Q[a, b] = v
        Q[b, a] = v


@wp.kernel
def rotate_in_kernel(dR: wp.array(dtype=wp.mat33d), r: wp.array(dtype=wp.vec3d), s: wp.array(dtype=wp.float64),
                     count: wp.array(dtype=wp.int32)):
    """s = dR^T r, node by node, flattened (the right rotation of eq. 2), for the nodes i with
    3 i < count[0] (launched over a capacity; :func:`~soft_tissue_sim.buffers.unbounded_count`
    where launched over the nodes)."""
    i = wp.tid()
    if 3 * i < count[0]:
        v = wp.transpose(dR[i]) * r[i]
        s[3 * i] = v[0]
        s[3 * i + 1] = v[1]
        s[3 * i + 2] = v[2]


@wp.func
def block_node(t: int):
    """Thread t in blocks of wp.block_dim() threads an item (a node, a tile): (item, lane,
    threads a block)."""
    nt = wp.block_dim()
    i = t // nt
    return i, t - i * nt, nt


@wp.func
def store_rotated(a0: wp.float64, a1: wp.float64, a2: wp.float64, lane: int, i: int,
                  dR: wp.array(dtype=wp.mat33d), z: wp.array(dtype=wp.vec3d)):
    """z_i = dR_i (the block's sums of its lanes' a0, a1, a2: node i's three rows), written by
    lane 0 (the left rotation of eq. 2)."""
    s0 = block_sum(a0)
    s1 = block_sum(a1)
    s2 = block_sum(a2)
    if lane == 0:
        z[i] = dR[i] * wp.vec3d(s0, s1, s2)


@wp.kernel
def dense_apply_kernel(P: wp.array2d(dtype=wp.float64), s: wp.array(dtype=wp.float64),
                       dR: wp.array(dtype=wp.mat33d), z: wp.array(dtype=wp.vec3d),
                       count: wp.array(dtype=wp.int32)):
    """z_i = dR_i (P s)_i for the nodes i with 3 i < n3 = count[0] (launched over a capacity; P
    read through its strides, its first n3 rows and columns): a block of threads per node i, its
    three rows of P against s (the lanes over the columns), the left rotation of eq. (2) applied
    to the result."""
    i, lane, nt = block_node(wp.tid())
    n3 = count[0]
    r = 3 * i
    if r >= n3:  # the whole block (one node) leaves
        return
    a0 = wp.float64(0.0)
    a1 = wp.float64(0.0)
    a2 = wp.float64(0.0)
    for j in range(lane, n3, nt):
        sj = s[j]
        a0 += P[r, j] * sj
        a1 += P[r + 1, j] * sj
        a2 += P[r + 2, j] * sj
    store_rotated(a0, a1, a2, lane, i, dR, z)


# The single-precision copy: the lower triangle of the inverse in TILE x TILE tiles (32 nodes a
# side), packed by rows of tiles -- tile (i, j), j <= i, is the b-th with b = i (i + 1) / 2 + j,
# row-major inside -- so that the apply reads each symmetric pair of entries once: half the bytes
# of the whole matrix. Entries past the size n3 are zero.
TILE = wp.constant(96)
TILE_BLOCK = 192  # CUDA threads a tile: 96 rows of its own product, 96 columns of its transpose's
GATHER_BLOCK = 32  # CUDA threads a node adding up its partial sums


def tile_count(tiles: int) -> int:
    """Packed tiles of a lower triangle ``tiles`` tiles a side."""
    return tiles * (tiles + 1) // 2


@wp.func
def tile_of(b: int) -> wp.vec2i:
    """(i, j), j <= i: the b-th tile of a lower triangle packed by rows of tiles."""
    i = int((wp.sqrt(wp.float64(8.0) * wp.float64(b) + wp.float64(1.0)) - wp.float64(1.0)) * wp.float64(0.5))
    while (i + 1) * (i + 2) // 2 <= b:
        i += 1
    while i * (i + 1) // 2 > b:
        i -= 1
    return wp.vec2i(i, b - i * (i + 1) // 2)


@wp.kernel
def pack_lower_kernel(src: wp.array2d(dtype=wp.float64), n3: int, dst: wp.array(dtype=wp.float32)):
    """dst = the lower triangle of src's first n3 rows and columns, rounded to single precision,
    packed in tiles (one entry a thread; zero past n3), launched over the tiles of n3."""
    t = wp.tid()
    b = t // (TILE * TILE)
    e = t - b * (TILE * TILE)
    ij = tile_of(b)
    r = e // TILE
    row = ij[0] * TILE + r
    col = ij[1] * TILE + e - r * TILE
    v = wp.float32(0.0)
    if row < n3 and col < n3:  # the lower triangle's entry in the diagonal tiles too: exactly symmetric
        v = wp.float32(src[wp.max(row, col), wp.min(row, col)])
    dst[t] = v


# One tile (i, j) of the packed copy against the rotated vector s = dR^T r (eq. 2): its product
# with s's segment j into the partial sums of row block i, and (off the diagonal) its transpose's
# with segment i into those of row block j; part[(I ntc + K) TILE + k] holds row k of block I's
# sum over block K. On CUDA the block of TILE_BLOCK threads loads the whole tile into registers
# (16-byte loads, all issued before the rotation of its 64 nodes), then passes it through shared
# memory half by half (48 rows: more blocks resident; rows padded to 100 floats: both reads free
# of bank conflicts), 48 threads summing its rows and 96 its columns in double precision; on the
# CPU the one thread does all of it.
@wp.func_native("""
const float* tile = Pk.data + (size_t)b * 9216;
double* out = part.data;
// x[0..2] = dR_node^T r_node, zero past n3
auto rotated = [&](int node, double* x) {
    double a0 = 0.0, a1 = 0.0, a2 = 0.0;
    if (3 * node < n3) {
        const wp::mat_t<3, 3, double>& R = dR.data[node];
        const wp::vec_t<3, double>& v = r.data[node];
        a0 = R.data[0][0] * v.c[0] + R.data[1][0] * v.c[1] + R.data[2][0] * v.c[2];
        a1 = R.data[0][1] * v.c[0] + R.data[1][1] * v.c[1] + R.data[2][1] * v.c[2];
        a2 = R.data[0][2] * v.c[0] + R.data[1][2] * v.c[1] + R.data[2][2] * v.c[2];
    }
    x[0] = a0;
    x[1] = a1;
    x[2] = a2;
};
#if defined(__CUDA_ARCH__)
__shared__ __align__(16) float sh[48 * 100];
__shared__ __align__(16) double xi[96];
__shared__ __align__(16) double xj[96];
// the whole tile's loads issued at once, into registers (6 + 6 16-byte loads a thread of the
// 192: the launch's block is TILE_BLOCK), before the rotation's
const float4* src = (const float4*)tile;
float4 held[12];
#pragma unroll
for (int m = 0; m < 12; ++m)
    held[m] = __ldg(src + lane + 192 * m);
if (lane < 64) {
    int k = lane < 32 ? lane : lane - 32;
    rotated(32 * (lane < 32 ? i : j) + k, (lane < 32 ? xi : xj) + 3 * k);
}
double col = 0.0;
for (int h = 0; h < 2; ++h) {  // the tile's two halves of 48 rows in turn through shared memory
    if (h)
        __syncthreads();
#pragma unroll
    for (int m = 0; m < 6; ++m) {
        int q = lane + 192 * m;
        int row = q / 24;
        *(float4*)(sh + row * 100 + 4 * (q - 24 * row)) = held[6 * h + m];
    }
    __syncthreads();
    if (lane < 48) {
        const float4* row = (const float4*)(sh + lane * 100);
        const double2* x2 = (const double2*)xj;
        double a = 0.0;
        for (int q = 0; q < 24; ++q) {
            float4 v = row[q];
            double2 x = x2[2 * q], y = x2[2 * q + 1];
            a += (double)v.x * x.x + (double)v.y * x.y + (double)v.z * y.x + (double)v.w * y.y;
        }
        out[((size_t)i * ntc + j) * 96 + 48 * h + lane] = a;
    } else if (lane >= 96 && lane < 192 && i != j) {
        const float* t = sh + lane - 96;
        const double* x = xi + 48 * h;
        for (int q = 0; q < 48; ++q)
            col += (double)t[100 * q] * x[q];
    }
}
if (lane >= 96 && lane < 192 && i != j)
    out[((size_t)j * ntc + i) * 96 + lane - 96] = col;
#else
double xi[96], xj[96];
for (int k = 0; k < 32; ++k) {
    rotated(32 * i + k, xi + 3 * k);
    rotated(32 * j + k, xj + 3 * k);
}
for (int k = 0; k < 96; ++k) {
    double a = 0.0;
    for (int c = 0; c < 96; ++c)
        a += (double)tile[k * 96 + c] * xj[c];
    out[((size_t)i * ntc + j) * 96 + k] = a;
}
if (i != j) {
    for (int c = 0; c < 96; ++c) {
        double a = 0.0;
        for (int k = 0; k < 96; ++k)
            a += (double)tile[k * 96 + c] * xi[k];
        out[((size_t)j * ntc + i) * 96 + c] = a;
    }
}
#endif
""")
def sym_tile(Pk: wp.array(dtype=wp.float32), r: wp.array(dtype=wp.vec3d), dR: wp.array(dtype=wp.mat33d),
             part: wp.array(dtype=wp.float64), b: int, i: int, j: int, lane: int, nt: int, n3: int, ntc: int): ...


@wp.kernel
def sym_tiles_kernel(Pk: wp.array(dtype=wp.float32), r: wp.array(dtype=wp.vec3d), dR: wp.array(dtype=wp.mat33d),
                     part: wp.array(dtype=wp.float64), count: wp.array(dtype=wp.int32), ntc: int):
    """The packed copy's tiles against dR^T r (:func:`sym_tile`), a block of threads a tile,
    launched over the tiles of the capacity (``ntc`` a side); the tiles past n3 = count[0] leave."""
    b, lane, nt = block_node(wp.tid())
    n3 = count[0]
    ij = tile_of(b)
    if ij[0] * TILE >= n3:  # the whole block leaves
        return
    sym_tile(Pk, r, dR, part, b, ij[0], ij[1], lane, nt, n3, ntc)


@wp.kernel
def sym_gather_kernel(part: wp.array(dtype=wp.float64), dR: wp.array(dtype=wp.mat33d), z: wp.array(dtype=wp.vec3d),
                      count: wp.array(dtype=wp.int32), ntc: int):
    """z_i = dR_i (the partial sums of node i's rows over the tile columns below n3 = count[0]),
    a block of threads a node (lanes over the tile columns, then a block sum: a fixed order),
    launched over a capacity."""
    i, lane, nt = block_node(wp.tid())
    n3 = count[0]
    r = 3 * i
    if r >= n3:  # the whole block (one node) leaves
        return
    blocks = (n3 + TILE - 1) // TILE
    row_block = r // TILE
    k = r - row_block * TILE
    a0 = wp.float64(0.0)
    a1 = wp.float64(0.0)
    a2 = wp.float64(0.0)
    for c in range(lane, blocks, nt):
        at = (row_block * ntc + c) * TILE + k
        a0 += part[at]
        a1 += part[at + 1]
        a2 += part[at + 2]
    store_rotated(a0, a1, a2, lane, i, dR, z)


def unpack_lower(packed: np.ndarray, n3: int) -> np.ndarray:
    """The (n3, n3) symmetric matrix of a packed copy (host arrays)."""
    tiles = -(-n3 // TILE)
    out = np.zeros((tiles * TILE, tiles * TILE), packed.dtype)
    T = packed[: tile_count(tiles) * TILE * TILE].reshape(-1, TILE, TILE)
    b = 0
    for i in range(tiles):
        for j in range(i + 1):
            out[i * TILE:(i + 1) * TILE, j * TILE:(j + 1) * TILE] = T[b]
            if i != j:
                out[j * TILE:(j + 1) * TILE, i * TILE:(i + 1) * TILE] = T[b].T
            b += 1
    return out[:n3, :n3]


@wp.func
def delassus_entry(P: wp.array2d(dtype=wp.float64), nodes: wp.array2d(dtype=wp.int32),
                   coef: wp.array2d(dtype=wp.vec3d), dR: wp.array(dtype=wp.mat33d), a: int, b: int):
    """h_a^T dR P dR^T h_b for constraint rows a and b given as up to 4 (node, 3-vector) pairs
    each (node -1: none): each pair rotated into the factor's frame by dR_n^T, then 3x3 blocks
    of P gathered."""
    acc = wp.float64(0.0)
    for k in range(4):
        i = nodes[a, k]
        if i >= 0:
            ca = wp.transpose(dR[i]) * coef[a, k]
            for l in range(4):
                j = nodes[b, l]
                if j >= 0:
                    cb = wp.transpose(dR[j]) * coef[b, l]
                    for p in range(3):
                        for q in range(3):
                            acc += ca[p] * P[3 * i + p, 3 * j + q] * cb[q]
    return acc


@wp.kernel
def delassus_kernel(P: wp.array2d(dtype=wp.float64), nodes: wp.array2d(dtype=wp.int32),
                    coef: wp.array2d(dtype=wp.vec3d), dR: wp.array(dtype=wp.mat33d), m: int,
                    W: wp.array(dtype=wp.float64)):
    """W[a m + b] = h_a^T dR P dR^T h_b (:func:`delassus_entry`) for the first m constraint rows,
    one entry per thread (W row-major with row length m)."""
    a, b = wp.tid()
    W[a * m + b] = delassus_entry(P, nodes, coef, dR, a, b)


@wp.kernel
def delassus_matrix_kernel(P: wp.array2d(dtype=wp.float64), nodes: wp.array2d(dtype=wp.int32),
                           coef: wp.array2d(dtype=wp.vec3d), dR: wp.array(dtype=wp.mat33d),
                           sizes: wp.array(dtype=wp.int32), scale: wp.float64, W: wp.array2d(dtype=wp.float64)):
    """W[a, b] = scale (W_ab + W_ba) / 2 (:func:`delassus_entry`, symmetric by construction) for
    a, b < sizes[0], the number of rows read on the device: launched over W's whole capacity,
    so that a captured launch serves every row count."""
    a, b = wp.tid()
    m = sizes[0]
    if a < m and b < m:
        W[a, b] = scale * wp.float64(0.5) * (delassus_entry(P, nodes, coef, dR, a, b)
                                             + delassus_entry(P, nodes, coef, dR, b, a))


@wp.kernel
def rows_part_kernel(P: wp.array2d(dtype=wp.float64), nodes: wp.array2d(dtype=wp.int32),
                     coef: wp.array2d(dtype=wp.vec3d), lam: wp.array(dtype=wp.float64),
                     sizes: wp.array(dtype=wp.int32), dR: wp.array(dtype=wp.mat33d),
                     count: wp.array(dtype=wp.int32), part: wp.array2d(dtype=wp.vec3d)):
    """part[c, i] = sum_r lam_r sum_s P_(i, n_rs) dR_(n_rs)^T c_rs over the rows r = c, c + S,
    c + 2 S, ... < sizes[0] (S = part.shape[0]; nodes n_rs, coefficients c_rs): node i's share
    of P^-1 H^T lambda from every S-th row, H^T lambda never formed. P is symmetric: node i's
    block is read from the rows' nodes' rows, contiguous across threads. The nodes i with
    3 i < count[0] (launched over a capacity: thread (c, i))."""
    c, i = wp.tid()
    if 3 * i >= count[0]:
        return
    acc = wp.vec3d(wp.float64(0.0), wp.float64(0.0), wp.float64(0.0))
    r = c
    while r < sizes[0]:
        lr = lam[r]
        if lr != wp.float64(0.0):
            for k in range(4):
                j = nodes[r, k]
                if j >= 0:
                    v = lr * (wp.transpose(dR[j]) * coef[r, k])
                    for q in range(3):
                        row = 3 * j + q
                        acc += v[q] * wp.vec3d(P[row, 3 * i], P[row, 3 * i + 1], P[row, 3 * i + 2])
        r += part.shape[0]
    part[c, i] = acc


@wp.kernel
def rows_sum_kernel(part: wp.array2d(dtype=wp.vec3d), dR: wp.array(dtype=wp.mat33d), scale: wp.float64,
                    free: wp.array(dtype=wp.float64), count: wp.array(dtype=wp.int32),
                    out: wp.array(dtype=wp.vec3d)):
    """out_i = scale free_i dR_i sum_c part[c, i] (in the order of c) for the nodes i with
    3 i < count[0]: :func:`rows_part_kernel`'s shares added, the rotation of eq. (2) applied."""
    i = wp.tid()
    if 3 * i >= count[0]:
        return
    acc = wp.vec3d(wp.float64(0.0), wp.float64(0.0), wp.float64(0.0))
    for c in range(part.shape[0]):
        acc += part[c, i]
    out[i] = (scale * free[i]) * (dR[i] * acc)


ROWS_SPLIT = 16  # CUDA: the threads a node in rows_apply, each summing every ROWS_SPLIT-th row


def rows_part(device, nodes: int, split: int | None = None) -> wp.array:
    """The partial sums :func:`rows_apply` needs for ``nodes`` nodes, ``split`` shares a node
    (default: ROWS_SPLIT on a GPU, the rows' loop spread over more threads; one on the CPU)."""
    if split is None:
        split = ROWS_SPLIT if wp.get_device(device).is_cuda else 1
    return wp.empty((split, nodes), dtype=wp.vec3d, device=device)


def rows_apply(P: wp.array, nodes: wp.array, coef: wp.array, lam: wp.array, sizes: wp.array, dR: wp.array,
               scale: float, free: wp.array, count: wp.array, part: wp.array, out: wp.array, device) -> None:
    """out_i = scale free_i dR_i sum_r lam_r sum_s P_(i, n_rs) dR_(n_rs)^T c_rs for the first
    sizes[0] constraint rows (nodes n_rs, coefficients c_rs): scale dR P^-1 dR^T H^T lambda (eq. 2)
    on the free nodes from the columns of the rows' nodes only. Launched over ``part``'s nodes
    (:func:`rows_part`: the capacity), for the nodes i with 3 i < count[0] (read on the device)."""
    wp.launch(rows_part_kernel, part.shape, [P, nodes, coef, lam, sizes, dR, count, part], device=device)
    wp.launch(rows_sum_kernel, part.shape[1], [part, dR, float(scale), free, count, out], device=device)


def _matrix_view(buf: GrowArray, rows: int, cols: int) -> wp.array:
    """A (rows, cols) row-major view of ``buf``'s first rows * cols values (reallocated, contents
    lost, only when it outgrows the allocation)."""
    return typed_view(buf.view(rows * cols), 0, buf.dtype, (rows, cols))


def strided_square(buf: wp.array, n: int, ld: int) -> wp.array:
    """An (n, n) row-major view of the flat array ``buf`` with row stride ``ld`` elements (keeps it
    alive)."""
    size = wp.types.type_size_in_bytes(buf.dtype)
    a = wp.array(ptr=buf.ptr, dtype=buf.dtype, shape=(n, n), strides=(ld * size, size), device=buf.device)
    a._ref = buf
    return a


def fold_into(xp, P, rows, N) -> None:
    """P <- P - U Q U^T in place (``xp`` arrays; P may have a row stride), U = P[:, rows],
    Q = (I + N S)^-1 N with S = U[rows] (:func:`~soft_tissue_sim.sherman_morrison.woodbury_q`):
    :meth:`DenseInverse.fold`'s arithmetic on the CPU (and the reference of :class:`LibraryFold`,
    the GPU's)."""
    from .sherman_morrison import woodbury_q

    r = xp.asarray(rows)
    U = xp.ascontiguousarray(P[r].T)  # columns of the symmetric P: rows are contiguous
    Q = woodbury_q(xp.asarray(N), U[r], xp)
    V = xp.ascontiguousarray(U @ Q)
    P -= U @ V.T


_MINUS_ONE = np.array([-1.0])
_ONE = np.array([1.0])
_ZERO = np.array([0.0])


class LibraryFold:
    """The fold P <- P - U Q U^T of :meth:`DenseInverse.fold` on the inverse's device from its
    own kept buffers: the affected DOFs and N sent in one page-locked copy, U and S = G^T U
    gathered by two launches, M = I + N S by cuBLAS's ``dgemm``, Q = M^-1 N by cuSOLVER's
    ``getrf`` and ``getrs``, symmetrized by a launch, V = U Q and P - V U^T by two ``dgemm``
    (P's leading dimension): nine calls in all, nothing allocated while the buffers hold, nothing
    read back. The same arithmetic as :func:`fold_into` (``getrf``'s pivoting for NumPy's
    ``solve``). It owns a cuBLAS and a cuSOLVER handle (not the factorization's, which another
    thread may be using on another stream) until :meth:`close`. ``cublas`` and ``cusolver``:
    nvmath-python's binding modules by default (or stand-ins with their signatures on host
    memory, for a test on the CPU device)."""

    def __init__(self, device, cublas=None, cusolver=None):
        if cublas is None:
            from nvmath.bindings import cublas
        if cusolver is None:
            from nvmath.bindings import cusolverDn as cusolver
        self.cublas, self.cusolver = cublas, cusolver
        self.blas, self.solver = cublas.create(), cusolver.create()
        self.device = wp.get_device(device)
        self.staged = PackedArrays({"rows": wp.int32, "N": wp.float64, "Q": wp.float64}, self.device)
        f64 = (GrowArray(wp.float64, self.device) for _ in range(5))
        self._UT, self._V, self._S, self._M, self._work = f64
        self._ipiv = GrowArray(wp.int32, self.device)
        self.info = wp.zeros(1, dtype=wp.int32, device=self.device)  # getrf's and getrs's (not read)
        self._lwork: dict[int, int] = {}

    def release(self) -> None:
        """Let the buffers go (allocates nothing; the next fold makes them again)."""
        self.staged = PackedArrays(dict(self.staged.fields), self.device)
        for buf in (self._UT, self._V, self._S, self._M, self._work, self._ipiv):
            buf.release()
        self._lwork.clear()

    def close(self) -> None:
        """The buffers (:meth:`release`) and the handles go."""
        self.release()
        if self.blas is not None:
            self.cublas.destroy(self.blas)
            self.cusolver.destroy(self.solver)
            self.blas = self.solver = None

    def __call__(self, P: wp.array, rows: np.ndarray, N: np.ndarray, stream: int = 0) -> None:
        """P <- P - U Q U^T (P an (n, n) float64 view with unit column stride, its row stride the
        leading dimension) for the DOFs ``rows`` and the perturbation N, on the raw CUDA stream
        ``stream``."""
        cublas, cusolver, blas, solver = self.cublas, self.cusolver, self.blas, self.solver
        k, n, ld = len(rows), int(P.shape[0]), P.strides[0] // P.strides[1]
        if k == 0 or n == 0:
            return
        st = self.staged
        st.reserve({"rows": k, "N": k * k, "Q": k * k})
        st.host("rows")[...] = rows
        st.host("N")[...] = np.asarray(N, np.float64).ravel()
        st.host("Q")[...] = st.host("N")  # getrs's right-hand side, overwritten by Q
        st.send(("rows", "N", "Q"))
        r, Nd, Q = st.array("rows"), st.array("N"), st.alias("Q", wp.float64, (k, k))
        UT = _matrix_view(self._UT, k, n)
        S, M = _matrix_view(self._S, k, k), _matrix_view(self._M, k, k)
        V = self._V.view(k * n)
        ipiv = self._ipiv.view(k)
        wp.launch(fold_columns_kernel, (k, n), [P, r, UT], device=self.device)
        wp.launch(fold_small_kernel, (k, k), [UT, r, S, M], device=self.device)
        cublas.set_stream(blas, stream)
        cusolver.set_stream(solver, stream)
        one, zero, minus = _ONE.ctypes.data, _ZERO.ctypes.data, _MINUS_ONE.ctypes.data
        # column-major views: N and S symmetric are themselves, so M_cm = I + N S
        cublas.dgemm(blas, 0, 0, k, k, k, one, Nd.ptr, k, S.ptr, k, one, M.ptr, k)
        lwork = self._lwork.get(k)
        if lwork is None:
            lwork = self._lwork[k] = int(cusolver.dgetrf_buffer_size(solver, k, k, M.ptr, k))
        work = self._work.view(max(1, lwork))
        cusolver.dgetrf(solver, k, k, M.ptr, k, work.ptr, ipiv.ptr, self.info.ptr)
        cusolver.dgetrs(solver, 0, k, k, M.ptr, k, ipiv.ptr, Q.ptr, k, self.info.ptr)  # Q_cm = M^-1 N
        wp.launch(symmetrize_small_kernel, (k, k), [Q], device=self.device)
        # U_cm (n x k, ld n) is UT row-major; V_cm = U Q; P_cm (ld) -= V U^T
        cublas.dgemm(blas, 0, 0, n, k, k, one, UT.ptr, n, Q.ptr, k, zero, V.ptr, n)
        cublas.dgemm(blas, 0, 1, n, n, k, minus, V.ptr, n, UT.ptr, n, one, P.ptr, ld)


def array_module(device):
    """CuPy for a CUDA device, NumPy for the CPU: the array library the backends call."""
    if wp.get_device(device).is_cuda:
        import cupy

        return cupy
    return np


def xp_view(xp, a: wp.array):
    """``a`` as an ``xp`` array, sharing its memory."""
    return a.numpy() if xp is np else xp.asarray(a)


class DenseInverse:
    """A dense inverse of A on one device, with a second buffer in which the next one is made.

    ``request(triplets, n3, stream)`` assembles A into the work buffer on ``stream`` (the
    simulation's); ``factorize(stream)`` turns it into A^-1 in place on another stream (the
    factor's: this is what runs beside the steps); ``install(stream)`` copies it into the
    store in use and reports failure (A not positive definite). Between installs, :meth:`fold`
    applies corrections and :meth:`regrow` changes the node set of the inverse in use.

    The inverse in use :attr:`inv` is an (n3, n3) view with row stride :attr:`ld` into a store
    whose address holds while n3 <= ld (installs and regrows of any such size included; a larger
    one reallocates it with a new leading dimension); its size is also in a device array that
    :meth:`apply` reads, so that a captured :meth:`apply` serves every size up to the capacity
    (see the module docstring).

    ``precision``: of the matrix :meth:`apply` reads, ``"float64"`` (the inverse in use) or
    ``"float32"`` (a single-precision copy of it, kept up to date; see the module docstring).
    """

    name = "dense"
    PRECISIONS = ("float64", "float32")
    inverse_block = 2048  # GPU: the inverse by column blocks of this many DOFs (0: whole; see _inverse_from_factor)

    def __init__(self, device, precision: str = "float64"):
        if precision not in self.PRECISIONS:
            raise ValueError(f"dense precision must be one of {', '.join(self.PRECISIONS)}, got {precision!r}")
        self.device = wp.get_device(device)
        self.precision = precision
        self.xp = array_module(self.device)
        self.inv: wp.array | None = None  # (n3, n3) the inverse in use: a view of store 0, row stride ld
        self.packed: wp.array | None = None  # precision float32: its single-precision copy, packed tiles
        self.work: wp.array | None = None  # (n3, n3) the next one (contiguous)
        self._ld = 0  # the stores' leading dimension (0: none yet)
        # (ld^2 each) the inverse in use, and a regrow's gather target; the single-precision copy
        # (the lower triangle's tiles of the capacity) and the apply's partial sums; kept across
        # node-count changes while n3 <= ld (a cut allocates nothing)
        self._store = self._empty_stores()
        self._packed_buf = GrowArray(wp.float32, self.device, headroom=1.0)
        self._part_buf = GrowArray(wp.float64, self.device, headroom=1.0)
        self._part: wp.array | None = None
        # (ld, ld) view of store 0: the matrix apply reads (its first count[0] rows and columns)
        self._full: wp.array | None = None
        self._s: wp.array | None = None  # (ld,) the rotated vector of apply
        self._rows_part: wp.array | None = None  # apply_rows' partial sums (rows_part, ld / 3 nodes)
        self._count = wp.zeros(1, dtype=wp.int32, device=self.device)  # n3, as apply reads it
        self._keep_in = PackedArrays({"keep": wp.int32}, self.device)  # a regrow's indices (page-locked)
        # the work buffer and the GPU's second buffer as views of allocations kept across
        # node-count changes (a request after a cut allocates nothing while they hold)
        self._work_buf = GrowArray(wp.float64, self.device)
        self._rhs_buf = GrowArray(wp.float64, self.device)
        self._info = wp.zeros(2, dtype=wp.int32, device=self.device)
        # GPU: the info copied to page-locked memory at the end of a factorization, on its stream,
        # so that an install (after the factorization's last event) reads it without a wait
        self._info_host = PINNED.zeros(2, wp.int32) if self.device.is_cuda else None
        self._handle = None  # cuSOLVER
        if self.device.is_cuda:  # loaded here, not first in the thread that enqueues factorizations
            wp.load_module(sys.modules[__name__], device=self.device)
        self._rhs = None  # GPU: the identity, then the inverse
        self._triplets = None  # GPU: the assembly factorize launches first (see assemble)
        self._result = None  # the buffer holding the finished inverse
        self._lwork = 0
        self._workspace = None
        self._blas = None  # cuBLAS (the factorization's)
        self._library_fold: LibraryFold | None = None  # GPU: the folds (made with the first factor)
        self._W = None  # delassus: W on the device (grown to the largest m x m seen)
        self._deferred = 0  # the depth of changing() scopes open
        self._stale = False  # the single-precision copy is to be made again (changing())

    # ----------------------------------------------------------- making one
    @property
    def n3(self) -> int:
        return 0 if self.inv is None else self.inv.shape[0]

    @property
    def ld(self) -> int:
        """The leading dimension (row stride) of the inverse in use and its copy: the capacity in
        DOFs (0 before the first install)."""
        return self._ld

    def assemble(self, triplets, n3: int, stream=None, topology=None) -> None:
        """The work buffer = A (n3 x n3) from 3x3 block triplets: on the CPU now, on ``stream``;
        on a GPU the zeroing and the scatter are launched by :meth:`factorize`, on the
        factorization's stream (the triplets must then hold until the factorization has begun:
        the caller orders it after them), so that none of that work waits on the simulation's
        stream."""
        rows, cols, vals = triplets
        if self.work is None or self.work.shape[0] != n3:
            self.work = _matrix_view(self._work_buf, n3, n3)
        if self.device.is_cuda:
            self._prepare_gpu(n3, stream)
            self._triplets = triplets
            return
        self.work.zero_()
        wp.launch(scatter_dense_kernel, rows.shape[0], [rows, cols, vals, self.work], device=self.device,
                  stream=stream)

    def _prepare_gpu(self, n: int, stream) -> None:
        """What the GPU factorization needs, made on the caller's thread before it is enqueued
        (possibly by another thread, which then allocates nothing and loads no module): the
        cuSOLVER and cuBLAS handles, the workspace, the second buffer (:meth:`factorize` writes
        the identity into it, the right-hand side of ``trsm``); the fold's handles."""
        from nvmath.bindings import cusolverDn

        if self._handle is None:
            self._handle = cusolverDn.create()
        lower = 0  # CUBLAS_FILL_MODE_LOWER
        lwork = cusolverDn.dpotrf_buffer_size(self._handle, lower, n, self.work.ptr, n)
        if self._workspace is None or self._lwork < lwork:
            self._workspace = wp.empty(lwork, dtype=wp.float64, device=self.device)
            self._lwork = lwork
        if self._rhs is None or self._rhs.shape[0] != n:
            self._rhs = _matrix_view(self._rhs_buf, n, n)
        if self._blas is None:
            from nvmath.bindings import cublas

            self._blas = cublas.create()
        if self._library_fold is None:  # the folds, and their calls made once on a 6 x 6 matrix:
            self._library_fold = LibraryFold(self.device)  # the libraries' kernels loaded now, not
            P = wp.array(np.eye(6), dtype=wp.float64, device=self.device)  # at the first cut
            self._library_fold(P, np.arange(3, dtype=np.int32), 0.5 * np.eye(3),
                               stream.cuda_stream if stream is not None else 0)

    def factorize(self, stream=None) -> None:
        """Work buffer A -> A^-1, on ``stream``: cuSOLVER and cuBLAS calls and, by column
        blocks, one launch of this module's :func:`symmetrize_kernel` (loaded at construction;
        nothing is allocated: see :meth:`assemble`). GPU: Cholesky A = L L^T (``potrf``), then
        X = L^-1 against the identity in the second buffer (``trsm``: X's upper triangle comes
        out exactly zero) and A^-1 = X^T X into the work buffer (``trmm``), by column blocks
        (:meth:`_inverse_from_factor`): one triangular solve fewer than ``potrs`` against the
        identity; before them, on the same stream, the assembly :meth:`assemble` left (the work
        buffer zeroed, the triplets scattered) and the identity in the second buffer.
        CPU: LAPACK's ``potrf`` and ``potri`` in place, the missing triangle mirrored."""
        n = self.work.shape[0]
        if self.xp is np:
            from scipy.linalg import lapack

            At = self.work.numpy().T  # column-major view of the symmetric matrix
            c, info = lapack.dpotrf(At, lower=1, clean=0, overwrite_a=1)
            if info == 0:
                c, info = lapack.dpotri(c, lower=1, overwrite_c=1)
            if not np.shares_memory(c, At):
                At[...] = c
            self._info.assign(np.array([info, 0], dtype=np.int32))
            wp.launch(symmetrize_kernel, (n, n), [self.work], device=self.device, stream=stream)
            self._result = self.work
            return
        from nvmath.bindings import cusolverDn

        if self._triplets is not None:  # the assembly (see assemble), on this stream
            rows, cols, vals = self._triplets
            self._triplets = None
            wp.launch(zero_matrix_kernel, (n, n), [self.work], device=self.device, stream=stream)
            wp.launch(scatter_dense_kernel, rows.shape[0], [rows, cols, vals, self.work], device=self.device,
                      stream=stream)
        wp.launch(identity_matrix_kernel, (n, n), [self._rhs], device=self.device, stream=stream)
        cusolverDn.set_stream(self._handle, stream.cuda_stream if stream is not None else 0)
        lower = 0  # CUBLAS_FILL_MODE_LOWER
        info = self._info.ptr
        cusolverDn.dpotrf(self._handle, lower, n, self.work.ptr, n, self._workspace.ptr, self._lwork, info)
        from nvmath.bindings import cublas

        h = self._blas
        cublas.set_stream(h, stream.cuda_stream if stream is not None else 0)
        self._inverse_from_factor(h, n, stream)
        rt = self.xp.cuda.runtime
        if stream is not None:
            rt.memcpyAsync(self._info_host.ptr, self._info.ptr, 8, rt.memcpyDeviceToHost, stream.cuda_stream)
        else:  # the legacy stream: copied before returning
            rt.memcpy(self._info_host.ptr, self._info.ptr, 8, rt.memcpyDeviceToHost)
        self._result = self.work

    def _inverse_from_factor(self, h, n: int, stream) -> None:
        """A^-1 = X^T X into the work buffer from L (the work buffer's lower triangle), X = L^-1
        made in the second buffer (which holds the identity). With ``inverse_block`` b > 0, by
        column blocks of b: X's block J solves L[j:, j:] X[j:, J] = I[j:, J] (rows above j stay
        zero), and the lower triangle of A^-1 is X[j:, j:]^T X[j:, J], its upper one mirrored
        after; else whole (``trsm`` against the identity, ``trmm``)."""
        from nvmath.bindings import cublas

        one, L, X, C = _ONE.ctypes.data, self.work.ptr, self._rhs.ptr, self.work.ptr
        b = int(self.inverse_block)
        if b <= 0 or b >= n:  # (side left, lower, op, non-unit diagonal)
            cublas.dtrsm(h, 0, 0, 0, 0, n, n, one, L, n, X, n)
            cublas.dtrmm(h, 0, 0, 1, 0, n, n, one, X, n, X, n, C, n)
            return

        def at(base, i, j):  # element (i, j) of a column-major n x n matrix
            return base + 8 * (j * n + i)

        starts = range(0, n, b)
        for j in starts:
            cublas.dtrsm(h, 0, 0, 0, 0, n - j, min(b, n - j), one, at(L, j, j), n, at(X, j, j), n)
        for j in starts:
            cublas.dtrmm(h, 0, 0, 1, 0, n - j, min(b, n - j), one, at(X, j, j), n, at(X, j, j), n, at(C, j, j), n)
        wp.launch(symmetrize_kernel, (n, n), [self.work], device=self.device, stream=stream)

    def install(self, stream=None) -> str | None:
        """The finished work buffer (contiguous n x n) becomes the inverse in use, copied on
        ``stream`` into the strided store (same address and leading dimension while n <= ld; the
        size array written on ``stream`` where n changes); returns why not, or None. Call it once
        the factorization's stream has passed its end (on a GPU the info is then read from
        page-locked memory without a wait)."""
        info = self._info_host.numpy() if self._info_host is not None else self._info.numpy()
        if info[0] != 0 or info[1] != 0:
            return (f"dense factorization failed (potrf info {info[0]}, inverse info {info[1]}): "
                    "A is not positive definite")
        n = self._result.shape[0]
        if self.inv is None or self.inv.shape[0] != n:
            if n > self._ld:
                self.inv = self.packed = None  # its contents are not needed: the old store goes first
            self._reserve(n)
            self._resize(n, stream)
        self._copy_in(self._result, stream)
        self._pack(stream)
        return None

    def _copy_in(self, src: wp.array, stream=None) -> None:
        """The inverse in use (row stride ld) := ``src`` (contiguous n x n), on ``stream``: on a
        GPU one pitched copy of the runtime (Warp's copy of a strided view is a generic kernel
        moving a byte at a time)."""
        n = src.shape[0]
        if not self.device.is_cuda:
            wp.copy(self.inv, src, stream=stream)
            return
        assert src.strides == (8 * n, 8) and self.inv.strides == (8 * self._ld, 8)
        rt = self.xp.cuda.runtime
        stream = stream if stream is not None else wp.get_stream(self.device)
        with wp.ScopedDevice(self.device):  # the runtime call in the device's context
            rt.memcpy2DAsync(self.inv.ptr, 8 * self._ld, src.ptr, 8 * n, 8 * n, n, rt.memcpyDeviceToDevice,
                             stream.cuda_stream)

    def _empty_stores(self) -> tuple:
        return GrowArray(wp.float64, self.device, headroom=1.0), GrowArray(wp.float64, self.device, headroom=1.0)

    def _reserve(self, n: int) -> None:
        """Store 0 and the rotated vector for n DOFs: where n > ld, reallocated with a new leading
        dimension (:func:`leading_dimension`; contents lost, the inverse in use still readable
        through :attr:`inv` until it is replaced; the second store and the single-precision copy
        follow at their next use)."""
        if n <= self._ld:
            return
        ld = leading_dimension(n)
        self._store[1].release()
        self._full = self.packed = self._part = None
        self._ld = ld
        self._full = strided_square(self._store[0].view(ld * ld), ld, ld)
        self._s = wp.empty(ld, dtype=wp.float64, device=self.device)
        self._rows_part = rows_part(self.device, ld // 3)

    def _view(self, k: int, n: int) -> wp.array:
        """The (n, n) view of store ``k`` with row stride ld."""
        return strided_square(self._store[k].view(self._ld * self._ld), n, self._ld)

    def _resize(self, n: int, stream=None) -> None:
        """The inverse in use := the (n, n) view of store 0; the size array := n, on ``stream``."""
        self.inv = self._view(0, n)
        wp.launch(set_count_kernel, 1, [self._count, n], device=self.device, stream=stream)

    @contextlib.contextmanager
    def changing(self):
        """A series of changes of the inverse in use (an install, folds, regrows) after which
        the single-precision copy is made once, at the end, instead of after each."""
        self._deferred += 1
        try:
            yield self
        finally:
            self._deferred -= 1
            if not self._deferred and self._stale and self.inv is not None:
                self._pack()

    def _pack(self, stream=None) -> None:
        """precision float32: the single-precision copy := the inverse in use's lower triangle,
        packed in tiles (same address while the capacity holds); inside :meth:`changing`, marked
        to be made at its end."""
        if self.precision != "float32":
            return
        if self._deferred:
            self._stale = True
            return
        self._stale = False
        n, ntc = self.inv.shape[0], self._ld // TILE
        if self.packed is None:
            self.packed = self._packed_buf.view(tile_count(ntc) * TILE * TILE)
            self._part = self._part_buf.view(ntc * ntc * TILE)
        size = tile_count(-(-n // TILE)) * TILE * TILE
        wp.launch(pack_lower_kernel, size, [self._full, n, self.packed], device=self.device, stream=stream)

    def single(self) -> np.ndarray:
        """The (n3, n3) single-precision matrix the apply reads (precision float32), on the host."""
        return unpack_lower(self.packed.numpy(), self.n3)

    @property
    def applied(self) -> wp.array:
        """The matrix :meth:`apply` reads: the inverse in use ((n3, n3) view, row stride ld), or
        its packed single-precision copy (the capacity's tiles)."""
        return self.packed if self.precision == "float32" else self.inv

    def _applied_full(self) -> wp.array | None:
        """What a captured apply holds: the inverse's store as an (ld, ld) view, or the packed copy."""
        return self.packed if self.precision == "float32" else self._full

    # ------------------------------------------------------------- using it
    def apply(self, r: wp.array, z: wp.array, dR: wp.array) -> None:
        """z = dR A^-1 dR^T r (eq. 2) for the current size n3 (read on the device): launches only,
        over the capacity (ld / 3 nodes), so that a captured one serves every n3 <= ld. r, z and
        dR need n3 / 3 entries; their shapes are not read."""
        nodes = self._ld // 3
        if self.precision == "float32":  # the packed tiles, then each node's partial sums
            ntc = self._ld // TILE
            block = TILE_BLOCK if self.device.is_cuda else 1
            wp.launch(sym_tiles_kernel, tile_count(ntc) * block, [self.packed, r, dR, self._part, self._count, ntc],
                      device=self.device, block_dim=block)
            block = GATHER_BLOCK if self.device.is_cuda else 1
            wp.launch(sym_gather_kernel, nodes * block, [self._part, dR, z, self._count, ntc], device=self.device,
                      block_dim=block)
            return
        wp.launch(rotate_in_kernel, nodes, [dR, r, self._s, self._count], device=self.device)
        block = BLOCK if self.device.is_cuda else 1
        wp.launch(dense_apply_kernel, nodes * block, [self._full, self._s, dR, z, self._count],
                  device=self.device, block_dim=block)

    def graph_key(self) -> tuple | None:
        """What a captured :meth:`apply` depends on besides its arguments (no size: see
        :meth:`apply`); None before an install."""
        P = self._applied_full()
        if self.inv is None or P is None:
            return None
        return (P.ptr, self._ld, self._s.ptr, self._count.ptr, self._part.ptr if self._part is not None else 0)

    def matrix(self):
        """The inverse in use as an ``xp`` array (a view, row stride ld)."""
        return xp_view(self.xp, self.inv)

    def delassus(self, nodes: wp.array, coef: wp.array, dR: wp.array, m: int | None = None) -> np.ndarray:
        """W = H dR A^-1 dR^T H^T (m x m, host) for the first ``m`` (default: all) constraint rows
        in node form (arrays (>= m, 4)). W is gathered into a buffer kept between calls and read
        with :func:`~soft_tissue_sim.transfer.to_host`; the result is a view, valid until the
        next call."""
        m = nodes.shape[0] if m is None else int(m)
        if self._W is None or self._W.shape[0] < m * m:
            self._W = wp.empty(m * m, dtype=wp.float64, device=self.device)
        wp.launch(delassus_kernel, (m, m), [self.inv, nodes, coef, dR, m, self._W], device=self.device)
        return to_host(self._W)[0][: m * m].reshape(m, m)

    def delassus_matrix(self, nodes: wp.array, coef: wp.array, dR: wp.array, sizes: wp.array, scale: float,
                        W: wp.array) -> None:
        """W[:m, :m] = scale H dR A^-1 dR^T H^T, symmetric, for the first m = sizes[0] rows (read
        on the device: launches only, over W's capacity)."""
        wp.launch(delassus_matrix_kernel, W.shape, [self._full, nodes, coef, dR, sizes, float(scale), W],
                  device=self.device)

    def apply_rows(self, nodes: wp.array, coef: wp.array, lam: wp.array, sizes: wp.array, dR: wp.array,
                   scale: float, free: wp.array, out: wp.array) -> None:
        """out = scale dR A^-1 dR^T H^T lambda on the free nodes (zero on the fixed ones) for the
        first sizes[0] constraint rows in node form, lambda on the device (launches only; the
        inverse in use, in double precision, as :meth:`delassus_matrix` reads it), launched over
        the capacity (ld / 3 nodes) with the size read on the device, as :meth:`apply` is. ``out``
        holds at least the node count."""
        rows_apply(self._full, nodes, coef, lam, sizes, dR, scale, free, self._count, self._rows_part, out,
                   self.device)

    # ----------------------------------------------------------- changing it
    def fold(self, rows: np.ndarray, N: np.ndarray) -> None:
        """P^-1 <- P^-1 - U Q U^T with U = P^-1 G (G selecting ``rows``) and Q = (I + N S)^-1 N,
        S = G^T P^-1 G (:func:`~soft_tissue_sim.sherman_morrison.woodbury_q`): the exact
        corrected inverse of eq. (5)-(7) for the perturbation N (host). Runs on the
        simulation's stream, Q included: nothing is read back."""
        if self.device.is_cuda:
            self._library_fold(self.inv, np.asarray(rows, np.int32), N, wp.get_stream(self.device).cuda_stream)
        else:
            fold_into(self.xp, self.matrix(), rows, N)
        self._pack()

    def regrow(self, keep: np.ndarray, added: int) -> None:
        """Change the node set of the inverse in use: keep the DOFs ``keep`` (in that order),
        then append ``added`` DOFs as identity rows (eq. 10's padding), on the simulation's stream.
        The result stays in store 0 (same address and leading dimension) while the new size is
        <= ld: in place where ``keep`` is a prefix 0..k-1 (the padding written, nothing moved),
        else gathered into the second store and copied back (its first rows, one contiguous
        copy). A larger size gathers into a reallocated store 0. Nothing is allocated while the
        stores hold; the indices go up from page-locked memory."""
        keep = np.asarray(keep)
        k, added = int(len(keep)), int(added)
        n = k + added
        old, ld = self.inv, self._ld
        if n <= ld and np.array_equal(keep, np.arange(k)):
            if n != old.shape[0]:
                self._resize(n)
            if added:
                wp.launch(pad_identity_kernel, (n, added), [self.inv, k], device=self.device)
            self._pack()
            return
        staged = self._keep_in
        staged.reserve({"keep": k})
        staged.host("keep")[...] = keep
        staged.send(("keep",))
        if n > ld:  # outgrown: straight into the new store (the old one is read through old)
            self._reserve(n)
            self._resize(n)
            wp.launch(regrow_kernel, (n, n), [old, staged.array("keep"), self.inv], device=self.device)
        else:
            ld = self._ld
            wp.launch(regrow_kernel, (n, n), [old, staged.array("keep"), self._view(1, n)], device=self.device)
            wp.copy(self._store[0].buffer, self._store[1].buffer, count=(n - 1) * ld + n)
            if n != old.shape[0]:
                self._resize(n)
        self._pack()

    def reset(self) -> None:
        """Forget the inverse in use (a new one must be installed before the next apply; the
        stores are kept)."""
        self.inv = self.packed = None

    def close(self) -> None:
        if self._handle is not None:
            from nvmath.bindings import cusolverDn

            cusolverDn.destroy(self._handle)
            self._handle = None
        if self._blas is not None:
            from nvmath.bindings import cublas

            cublas.destroy(self._blas)
            self._blas = None
        if self._library_fold is not None:
            self._library_fold.close()
            self._library_fold = None
        self.inv = self.packed = self.work = self._workspace = self._rhs = self._result = self._triplets = None
        self._full = self._s = self._part = self._rows_part = None
        self._ld = 0
        self._store = self._empty_stores()
        self._packed_buf = GrowArray(wp.float32, self.device, headroom=1.0)
        self._part_buf = GrowArray(wp.float64, self.device, headroom=1.0)
        self._work_buf, self._rhs_buf = (GrowArray(b.dtype, self.device) for b in (self._work_buf, self._rhs_buf))

