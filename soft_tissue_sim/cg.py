"""Preconditioned conjugate gradient on Warp arrays, and the simple preconditioners.

We keep our own PCG rather than ``warp.optim.linear.cg``: Warp's variant applies the
preconditioner twice per iteration (to r and to A p), and with the LDL^T preconditioner
of the paper the triangular solves are the dominant cost, so that would double it. Ours is
the textbook PCG: one product with A and one preconditioner application per iteration,
iterating until the recursively updated residual r ~ b - A x is below the tolerance
(||r|| / ||b||). In floating point that recursion drifts from the true residual (far, on
stiff, badly conditioned systems), so the solve ends with one more product: convergence is
judged on the true relative residual ||b - A x|| / ||b||, which is what ``residual`` reports.
With ``warm_start`` the iteration starts from the x it is given (the previous step's solution,
left in place by the caller) instead of zero: r = b - A x, one product more, and zero after all
where that residual is not below ||b|| (or not finite), so a guess never costs more than a
cold start; the stopping test stays relative to ||b||.
Float64 cannot make that residual much smaller than eps ||A|| ||x|| / ||b|| (the rounding of
the product itself); ``residual_floor`` is that estimate (||A|| by a few power iterations,
cached while the operator's key holds) and ``tolerance_unreachable`` says when the tolerance
asked is below it.

Vectors are ``wp.array(dtype=wp.vec3d)`` (node-major). The operator is a callable
``matvec(p, out)`` computing ``out = A p``; a preconditioner has
``apply(r, z)`` computing ``z = P^-1 r``.

:class:`DevicePCG` is the same iteration with every scalar (r.z, p.Ap, alpha, beta, the
residual, the iteration count and the "go on" flag) in device arrays, computed by kernels,
and the loop a ``wp.capture_while`` on that flag: no host synchronisation until the end of
the solve. Its launches read the node count from a device array and run over a grid set by
the capacity of its work vectors, so with ``graph=True`` the solve is captured once as a graph
(per work-vector capacity, operator, preconditioner pattern and coefficients) and replayed each
step, across node counts within that capacity. It needs a preconditioner whose ``apply``
only launches (``device_capable()``): none, jacobi, or a device factor
(:mod:`soft_tissue_sim.device_preconditioner`); otherwise it runs the host-scalar :meth:`PCG.solve`.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import warp as wp

from . import graphs
from .buffers import GrowArray

wp.set_module_options({"enable_backward": False})  # no gradients are taken


@wp.kernel
def _axpy2_kernel(
    alpha: wp.float64,
    p: wp.array(dtype=wp.vec3d),
    Ap: wp.array(dtype=wp.vec3d),
    x: wp.array(dtype=wp.vec3d),
    r: wp.array(dtype=wp.vec3d),
):
    i = wp.tid()
    x[i] = x[i] + alpha * p[i]
    r[i] = r[i] - alpha * Ap[i]


@wp.kernel
def _xpby_kernel(z: wp.array(dtype=wp.vec3d), beta: wp.float64, p: wp.array(dtype=wp.vec3d)):
    i = wp.tid()
    p[i] = z[i] + beta * p[i]


@wp.kernel
def _block_apply_kernel(count: wp.array(dtype=wp.int32), Dinv: wp.array(dtype=wp.mat33d),
                        r: wp.array(dtype=wp.vec3d), z: wp.array(dtype=wp.vec3d)):
    """z = Dinv r on the first count[0] blocks (launched over a capacity)."""
    i = wp.tid()
    if i < count[0]:
        z[i] = Dinv[i] * r[i]


@wp.kernel
def _invert_blocks_kernel(D: wp.array(dtype=wp.mat33d), free: wp.array(dtype=wp.float64),
                          Dinv: wp.array(dtype=wp.mat33d)):
    i = wp.tid()
    if free[i] > wp.float64(0.0):
        Dinv[i] = wp.inverse(D[i])
    else:
        Dinv[i] = wp.identity(n=3, dtype=wp.float64)


@dataclass
class CGResult:
    iterations: int
    residual: float  # final true relative residual ||b - A x|| / ||b|| (one product after the loop)
    converged: bool  # residual <= tolerance
    precond_ms: float
    recursive_residual: float = float("nan")  # ||r|| / ||b|| of the recursion where the loop stopped
    residual_floor: float = 0.0  # eps ||A|| ||x|| / ||b||: about the smallest residual float64 reaches
    tolerance_unreachable: bool = False  # the tolerance asked is below residual_floor


_EPS = float(np.finfo(np.float64).eps)
_POWER_ITERATIONS = 12  # power iterations of the ||A|| estimate (a lower bound, within tens of percent)


@wp.kernel
def _residual_kernel(b: wp.array(dtype=wp.vec3d), Ax: wp.array(dtype=wp.vec3d), r: wp.array(dtype=wp.vec3d)):
    i = wp.tid()
    r[i] = b[i] - Ax[i]


@wp.kernel
def _scale_kernel(a: wp.array(dtype=wp.vec3d), s: wp.float64, out: wp.array(dtype=wp.vec3d)):
    i = wp.tid()
    out[i] = s * a[i]


@wp.kernel
def set_count_kernel(count: wp.array(dtype=wp.int32), n: int):
    """count[0] = n (a device count written in stream order)."""
    count[0] = n


@wp.kernel
def copy_count_kernel(count: wp.array(dtype=wp.int32), src: wp.array(dtype=wp.vec3d), dst: wp.array(dtype=wp.vec3d)):
    """dst = src over the first count[0] entries (launched over a capacity)."""
    i = wp.tid()
    if i < count[0]:
        dst[i] = src[i]


class IdentityPreconditioner:
    """No preconditioning: plain CG (the paper's "CGM"). ``apply`` copies the FEM's node count
    of vectors (read on the device, launched over its capacity: see
    :class:`~soft_tissue_sim.corotational_fem.CorotationalFEM`), so that a captured ``apply``
    holds across topology changes."""

    name = "none"

    def __init__(self):
        self._count = None
        self._dim = 0

    def begin_step(self, system) -> None:
        fem = system.fem
        self._count, self._dim = fem.n_nodes_dev, fem.node_dim

    def apply(self, r: wp.array, z: wp.array) -> None:
        wp.launch(copy_count_kernel, self._dim, [self._count, r, z], device=r.device)

    def stats(self) -> dict:
        return {}

    def invalidate(self) -> None:
        pass

    def close(self) -> None:
        pass

    def device_capable(self) -> bool:
        return self._count is not None

    def graph_key(self) -> tuple:
        return (self._count.ptr, self._dim)


class BlockJacobiPreconditioner:
    """Inverse of the 3x3 diagonal blocks of A, rebuilt every step (cheap). The blocks are views
    of kept allocations (:class:`soft_tissue_sim.buffers.GrowArray`) and ``apply`` reads the
    FEM's node count on the device, launched over its capacity (as
    :class:`IdentityPreconditioner`): a captured ``apply`` holds across topology changes
    (``graph_key``)."""

    name = "jacobi"

    def __init__(self):
        self._D = self._Dinv = None
        self._bufs = None
        self._count = None
        self._dim = 0

    def begin_step(self, system) -> None:
        fem = system.fem
        n = fem.n_nodes
        if self._bufs is None or self._bufs[0].device != wp.get_device(fem.device):
            self._bufs = (GrowArray(wp.mat33d, fem.device), GrowArray(wp.mat33d, fem.device))
        self._D, self._Dinv = (b.view(n) for b in self._bufs)
        self._count, self._dim = fem.n_nodes_dev, fem.node_dim
        fem.diagonal_blocks(system.m_coef, system.k_coef, self._D)
        wp.launch(_invert_blocks_kernel, n, [self._D, fem.free, self._Dinv], device=fem.device)

    def apply(self, r: wp.array, z: wp.array) -> None:
        wp.launch(_block_apply_kernel, self._dim, [self._count, self._Dinv, r, z], device=r.device)

    def stats(self) -> dict:
        return {}

    def invalidate(self) -> None:
        self._D = None

    def close(self) -> None:
        pass

    def device_capable(self) -> bool:
        return self._Dinv is not None

    def graph_key(self) -> tuple:
        return (self._Dinv.ptr, self._dim, self._count.ptr)


class PCG:
    """Preconditioned conjugate gradient with preallocated work vectors."""

    def __init__(self, n: int, device, tolerance: float = 1e-7, max_iterations: int = 1000, warm_start: bool = False):
        if not (tolerance > 0.0):
            raise ValueError(f"CG tolerance must be > 0, got {tolerance}")
        if int(max_iterations) < 1:
            raise ValueError(f"CG max_iterations must be >= 1, got {max_iterations}")
        self.tolerance = float(tolerance)
        self.max_iterations = int(max_iterations)
        self.warm_start = bool(warm_start)  # start from the x given (see the module docstring)
        self.device = wp.get_device(device)
        self._norm_key = None  # what the cached ||A|| estimate was made for (kept across resizes)
        self.norm_estimate = float("nan")
        self.resize(n)

    def resize(self, n: int) -> None:
        """Work vectors for ``n`` nodes, zeroed: views of allocations kept across resizes
        (:class:`soft_tissue_sim.buffers.GrowArray`)."""
        d = self.device
        self.n = n
        if getattr(self, "_bufs", None) is None:
            self._bufs = [GrowArray(wp.vec3d, d) for _ in range(4)]
            self._dot = wp.zeros(1, dtype=wp.float64, device=d)
        self.r, self.z, self.p, self.Ap = (b.view(n) for b in self._bufs)
        for a in (self.r, self.z, self.p, self.Ap, self._dot):
            a.zero_()

    def _inner(self, a: wp.array, b: wp.array) -> float:
        wp.utils.array_inner(a, b, out=self._dot)
        return float(self._dot.numpy()[0])

    def operator_norm(self, matvec) -> float:
        """Estimate of ||A||_2 (a lower bound) by power iterations from a fixed start vector,
        cached while the operator's ``norm_key()`` (found on a bound method's owner: the
        integrator's coefficients, as ||A|| hardly moves with the state or a cut) holds; an
        operator without one is estimated at every call. Uses ``p`` and ``Ap`` as scratch and
        reads scalars on the host: call it outside a solve (and outside a graph capture)."""
        owner = getattr(matvec, "__self__", None)
        mk = getattr(owner, "norm_key", None)
        key = mk() if mk is not None else None
        if key is not None and key == self._norm_key:
            return self.norm_estimate
        start = np.random.default_rng(12345).standard_normal((self.n, 3))
        self.p.assign(start / np.linalg.norm(start))
        est = 0.0
        for _ in range(_POWER_ITERATIONS):
            matvec(self.p, self.Ap)
            est = float(np.sqrt(self._inner(self.Ap, self.Ap)))
            if not (est > 0.0 and np.isfinite(est)):
                break
            wp.launch(_scale_kernel, self.n, [self.Ap, 1.0 / est, self.p], device=self.device)
        self.norm_estimate, self._norm_key = est, key
        return est

    def _finish(self, matvec, b, x, b_norm, it, recursive, t_pre, norm_a) -> CGResult:
        """The true residual ||b - A x|| / ||b|| (one product), the float64 floor, the result."""
        matvec(x, self.Ap)
        wp.launch(_residual_kernel, self.n, [b, self.Ap, self.r], device=self.device)
        rel = float(np.sqrt(self._inner(self.r, self.r)) / b_norm)
        floor = _EPS * norm_a * float(np.sqrt(self._inner(x, x))) / b_norm
        return CGResult(it, rel, bool(rel <= self.tolerance), 1000.0 * t_pre, float(recursive), float(floor),
                        bool(self.tolerance < floor))

    def solve(self, matvec, b: wp.array, x: wp.array, preconditioner) -> CGResult:
        """Solve A x = b from x = 0 (``warm_start``: from the x given, where its residual is
        below ||b||). Returns iterations, the final true relative residual (converged when it
        is within the tolerance) and the float64 floor estimate."""
        if b.shape[0] != self.n:
            self.resize(b.shape[0])
        dev = self.device
        r, z, p, Ap = self.r, self.z, self.p, self.Ap
        b_norm = np.sqrt(self._inner(b, b))
        if b_norm == 0.0 or not np.isfinite(b_norm):
            x.zero_()
            nan = float("nan")
            return CGResult(0, 0.0 if b_norm == 0.0 else nan, b_norm == 0.0, 0.0, 0.0 if b_norm == 0.0 else nan)
        norm_a = self.operator_norm(matvec)
        cold = True
        if self.warm_start:
            matvec(x, Ap)
            wp.launch(_residual_kernel, self.n, [b, Ap, r], device=dev)
            cold = not (np.sqrt(self._inner(r, r)) < b_norm)  # NaN: cold too
        if cold:
            x.zero_()
            wp.copy(r, b)
        t_pre = 0.0
        t0 = time.perf_counter()
        preconditioner.apply(r, z)
        t_pre += time.perf_counter() - t0
        wp.copy(p, z)
        rz = self._inner(r, z)
        rel = 1.0
        it = 0
        n = self.n
        while it < self.max_iterations:
            matvec(p, Ap)
            pAp = self._inner(p, Ap)
            if not (pAp > 0.0):  # breakdown: A not SPD along p, or NaN
                rel = float("nan") if not np.isfinite(pAp) else rel
                break
            alpha = rz / pAp
            wp.launch(_axpy2_kernel, n, [alpha, p, Ap, x, r], device=dev)
            it += 1
            rel = np.sqrt(self._inner(r, r)) / b_norm
            if rel <= self.tolerance or not np.isfinite(rel):
                break
            t0 = time.perf_counter()
            preconditioner.apply(r, z)
            t_pre += time.perf_counter() - t0
            rz_new = self._inner(r, z)
            beta = rz_new / rz
            rz = rz_new
            wp.launch(_xpby_kernel, n, [z, beta, p], device=dev)
        return self._finish(matvec, b, x, b_norm, it, rel, t_pre, norm_a)


# Device scalars of DevicePCG (one float64 array, read once at the end of a solve).
_BB, _RZ, _RZN, _PAP, _ALPHA, _BETA, _RR, _REL, _BROKE, _IT, _RTRUE, _XX = range(12)
_NSCAL = 12
_RED_BLOCK = 256  # threads per block of the dot-product kernels on CUDA


# block_sum(v): the sum of v over a thread block, in every thread of it (on the CPU, a block is
# one thread: v); the warps' sums added in warp order by thread 0, then shared
@wp.func_native("""
#if defined(__CUDA_ARCH__)
__shared__ double red[33];
for (int o = 16; o > 0; o >>= 1) v += __shfl_down_sync(0xffffffff, v, o);
int w = threadIdx.x >> 5;
if ((threadIdx.x & 31) == 0) red[w] = v;
__syncthreads();
if (threadIdx.x == 0) {
    double s = 0.0;
    int nw = (blockDim.x + 31) >> 5;
    for (int k = 0; k < nw; ++k) s += red[k];
    red[32] = s;
}
__syncthreads();
v = red[32];
__syncthreads();
#endif
return v;
""")
def block_sum(v: wp.float64) -> wp.float64: ...


@wp.kernel
def _dot_partial_kernel(a: wp.array(dtype=wp.vec3d), b: wp.array(dtype=wp.vec3d), count: wp.array(dtype=wp.int32),
                        partials: wp.array(dtype=wp.float64)):
    """partials[block] = the block's share of a.b over the first count[0] entries (grid-stride);
    deterministic order."""
    t = wp.tid()
    nt = wp.block_dim()
    n = count[0]
    total = partials.shape[0] * nt
    acc = wp.float64(0.0)
    for i in range(t, n, total):
        ai = a[i]
        bi = b[i]
        acc += ai[0] * bi[0]
        acc += ai[1] * bi[1]
        acc += ai[2] * bi[2]
    acc = block_sum(acc)
    if t % nt == 0:
        partials[t // nt] = acc


@wp.func
def _sum_partials(partials: wp.array(dtype=wp.float64), t: int, nt: int):
    acc = wp.float64(0.0)
    for k in range(t, partials.shape[0], nt):
        acc += partials[k]
    return block_sum(acc)


@wp.kernel
def _pcg_residual_kernel(count: wp.array(dtype=wp.int32), b: wp.array(dtype=wp.vec3d),
                         Ax: wp.array(dtype=wp.vec3d), r: wp.array(dtype=wp.vec3d), blocks: int):
    """r = b - Ax over the first count[0] entries (grid-stride over ``blocks`` blocks)."""
    t = wp.tid()
    n = count[0]
    for i in range(t, n, blocks * wp.block_dim()):
        r[i] = b[i] - Ax[i]


@wp.kernel
def _pcg_start_kernel(count: wp.array(dtype=wp.int32), b: wp.array(dtype=wp.vec3d),
                      x: wp.array(dtype=wp.vec3d), r: wp.array(dtype=wp.vec3d), blocks: int):
    """The cold start: x = 0, r = b over the first count[0] entries (grid-stride over ``blocks``
    blocks)."""
    t = wp.tid()
    n = count[0]
    for i in range(t, n, blocks * wp.block_dim()):
        x[i] = wp.vec3d()
        r[i] = b[i]


@wp.kernel
def _pcg_store_kernel(partials: wp.array(dtype=wp.float64), s: wp.array(dtype=wp.float64), slot: int):
    t = wp.tid()
    v = _sum_partials(partials, t, wp.block_dim())
    if t == 0:
        s[slot] = v


@wp.kernel
def _pcg_init_kernel(s: wp.array(dtype=wp.float64), flag: wp.array(dtype=wp.int32)):
    bb = s[_BB]
    s[_IT] = wp.float64(0.0)
    s[_BROKE] = wp.float64(0.0)
    if bb == wp.float64(0.0):
        s[_REL] = wp.float64(0.0)
    elif wp.isfinite(bb):
        s[_REL] = wp.float64(1.0)
    else:
        s[_REL] = wp.float64(wp.nan)
    flag[0] = 1


@wp.kernel
def _pcg_warm_kernel(partials: wp.array(dtype=wp.float64), s: wp.array(dtype=wp.float64),
                     b: wp.array(dtype=wp.vec3d), x: wp.array(dtype=wp.vec3d), r: wp.array(dtype=wp.vec3d),
                     count: wp.array(dtype=wp.int32), blocks: int):
    """The warm start kept or dropped: r.r of the guess (the sum of ``partials``, added up by
    every block) against b.b (slot BB); unless it is smaller, x = 0 and r = b over the first
    count[0] entries (grid-stride over ``blocks`` blocks)."""
    t = wp.tid()
    nt = wp.block_dim()
    n = count[0]
    rr = _sum_partials(partials, t % nt, nt)
    if not (rr < s[_BB]):
        for i in range(t, n, blocks * nt):
            x[i] = wp.vec3d()
            r[i] = b[i]


@wp.kernel
def _pcg_alpha_axpy2_kernel(
    partials: wp.array(dtype=wp.float64),
    s: wp.array(dtype=wp.float64),
    p: wp.array(dtype=wp.vec3d),
    Ap: wp.array(dtype=wp.vec3d),
    x: wp.array(dtype=wp.vec3d),
    r: wp.array(dtype=wp.vec3d),
    count: wp.array(dtype=wp.int32),
    rr_partials: wp.array(dtype=wp.float64),
):
    """alpha = r.z / p.Ap (p.Ap the sum of ``partials``, added up by every block), x += alpha p,
    r -= alpha A p over the first count[0] entries and each block's share of the new r.r into
    ``rr_partials`` (grid-stride over ``rr_partials.shape[0]`` blocks, the order of
    :func:`_dot_partial_kernel`). r.z is read from
    the slot RZN, where the first iteration and the beta kernel put it; block 0 records p.Ap,
    alpha and r.z (RZ, the denominator of the next beta). A breakdown (p.Ap <= 0: A not SPD
    along p, b = 0, or NaN) leaves x and r as they are and stops the loop (the check)."""
    t = wp.tid()
    nt = wp.block_dim()
    lane = t % nt
    n = count[0]
    pAp = _sum_partials(partials, lane, nt)
    rz = s[_RZN]
    alpha = wp.float64(0.0)
    if pAp > wp.float64(0.0):
        alpha = rz / pAp
    if t == 0:
        s[_PAP] = pAp
        s[_ALPHA] = alpha
        s[_RZ] = rz
        if not (pAp > wp.float64(0.0)):
            s[_BROKE] = wp.float64(1.0)
            if not wp.isfinite(pAp):
                s[_REL] = wp.float64(wp.nan)
    total = rr_partials.shape[0] * nt
    acc = wp.float64(0.0)
    for i in range(t, n, total):
        x[i] = x[i] + alpha * p[i]
        ri = r[i] - alpha * Ap[i]
        r[i] = ri
        acc += ri[0] * ri[0]
        acc += ri[1] * ri[1]
        acc += ri[2] * ri[2]
    acc = block_sum(acc)
    if lane == 0:
        rr_partials[t // nt] = acc


@wp.kernel
def _pcg_check_kernel(partials: wp.array(dtype=wp.float64), s: wp.array(dtype=wp.float64),
                      flag: wp.array(dtype=wp.int32), tol: wp.float64, max_it: wp.float64):
    t = wp.tid()
    rr = _sum_partials(partials, t, wp.block_dim())
    if t == 0:
        s[_RR] = rr
        if s[_BROKE] != wp.float64(0.0):
            flag[0] = 0
        else:
            it = s[_IT] + wp.float64(1.0)
            s[_IT] = it
            rel = wp.sqrt(rr) / wp.sqrt(s[_BB])
            s[_REL] = rel
            if rel <= tol or not wp.isfinite(rel) or it >= max_it:
                flag[0] = 0
            else:
                flag[0] = 1


@wp.kernel
def _pcg_beta_xpby_kernel(partials: wp.array(dtype=wp.float64), s: wp.array(dtype=wp.float64),
                          z: wp.array(dtype=wp.vec3d), p: wp.array(dtype=wp.vec3d), count: wp.array(dtype=wp.int32),
                          blocks: int):
    """beta = r.z (the sum of ``partials``, added up by every block) / the previous r.z (slot RZ,
    left as it is here), p = z + beta p over the first count[0] entries (grid-stride over
    ``blocks`` blocks); block 0 records the new r.z (slot RZN, read by the alpha kernel) and beta."""
    t = wp.tid()
    nt = wp.block_dim()
    n = count[0]
    rzn = _sum_partials(partials, t % nt, nt)
    beta = rzn / s[_RZ]
    if t == 0:
        s[_RZN] = rzn
        s[_BETA] = beta
    for i in range(t, n, blocks * nt):
        p[i] = z[i] + beta * p[i]


MAX_CAPTURE_FAILURES = 3


class DevicePCG(PCG):
    """:class:`PCG` with its scalars on the device and the loop a ``wp.capture_while``.

    Same iteration and stopping test as :meth:`PCG.solve` (the first iteration is peeled so
    that the loop body starts with the preconditioner: no application is wasted after
    convergence), and the same end: after the loop one product A x, the true residual and
    ||x|| by device reductions (still no host read until the solve is over; the ||A||
    estimate is made before, outside any capture). Every launch of the solve reads the node
    count from the device array :attr:`count` (written by :meth:`resize`) and runs over a grid
    fixed by the capacity of the work vectors, so the launches hold for every count up to that
    capacity. ``graph=True`` captures the whole solve (CUDA graph with a conditional while
    node; Warp's API capture on the CPU) on the second solve with the same key -- the launch
    geometry (the work vectors' capacity and addresses), the addresses of b and x, the
    operator's ``graph_key()`` (found on a bound method's owner) and the preconditioner's --
    and replays it afterwards, for any count within the capacity: the operator and the
    preconditioner must then read the count on the device too (their keys hold no count), and
    the kernels never take it from the shape of b or x (views captured at an older count);
    once a capture has succeeded (its kernels are loaded), a new key (a cut, a new factor
    pattern, a changed dt) is captured at its first solve (:class:`soft_tissue_sim.graphs.Replayer`,
    ``eager``; a replaced graph is released where no factorization runs). A capture that fails
    (work another thread enqueues meanwhile can invalidate it) runs that solve uncaptured and
    is tried again with the next solves; graphs are given up after ``MAX_CAPTURE_FAILURES``
    failures in a row. Without a graph the
    loop still needs no host read of dot products: on CUDA ``capture_while`` reads the flag
    (one small copy per iteration), on the CPU it reads it in place.

    The preconditioner time is not measured per application on this path (it would need a
    synchronisation): ``CGResult.precond_ms`` is NaN (``bench haptic`` times applications
    separately).
    """

    def __init__(self, n: int, device, tolerance: float = 1e-7, max_iterations: int = 1000, graph: bool = False,
                 warm_start: bool = False):
        dev = wp.get_device(device)
        # a CUDA graph needs conditional nodes (CUDA 12.4+ driver and toolkit) for the while loop
        self.graph_unsupported = bool(graph and dev.is_cuda and not wp.is_conditional_graph_supported())
        self.replay = graphs.Replayer(dev, "DevicePCG", eager=True, max_failures=MAX_CAPTURE_FAILURES)
        self.replay.enabled = bool(graph) and not self.graph_unsupported
        self.host_solves = 0
        super().__init__(n, device, tolerance, max_iterations, warm_start)

    # the capture's state, as the replayer keeps it
    graph = property(lambda self: self.replay.enabled, doc="Whether solves are captured (off after failures).")
    graph_error = property(lambda self: self.replay.error, doc="The last capture failure, or None.")
    capture_failures = property(lambda self: self.replay.failures, doc="Captures failed in a row.")
    captures = property(lambda self: self.replay.captures)
    replays = property(lambda self: self.replay.replays)

    def resize(self, n: int) -> None:
        """Work vectors for ``n`` nodes (zeroed), ``n`` written to :attr:`count` on the device (a
        launch: stream-ordered). The captured graphs are dropped only where the launch geometry
        changes (the work vectors outgrew their capacity), not for a new ``n`` within it."""
        super().resize(n)
        d = self.device
        if getattr(self, "_s", None) is None:
            self._s = wp.zeros(_NSCAL, dtype=wp.float64, device=d)
            self._flag = wp.zeros(1, dtype=wp.int32, device=d)
            self.count = wp.zeros(1, dtype=wp.int32, device=d)
            self._partials_buf = GrowArray(wp.float64, d)
            self._rr_partials_buf = GrowArray(wp.float64, d)
            self._geometry = None
        wp.launch(set_count_kernel, 1, [self.count, int(n)], device=d)
        # dot products: a block per chunk, then one block adds the partial sums (no allocation,
        # deterministic; Warp's array_inner allocates scratch, which a conditional graph body forbids);
        # as many blocks for every count within the work vectors' common capacity
        cap = min(b.capacity for b in self._bufs)
        self._block = _RED_BLOCK if d.is_cuda else 1
        nb = min(128, max(1, -(-cap // (2 * _RED_BLOCK)))) if d.is_cuda else 1
        self._partials = self._partials_buf.view(nb)
        self._rr_partials = self._rr_partials_buf.view(nb)  # r.r by the alpha kernel, while others read _partials
        for a in (self._s, self._flag, self._partials, self._rr_partials):
            a.zero_()
        geometry = (cap, nb, self._block, self.r.ptr, self.z.ptr, self.p.ptr, self.Ap.ptr,
                    self._partials.ptr, self._rr_partials.ptr)
        self._capacity = cap
        if geometry != self._geometry:
            self._geometry = geometry
            self.replay.clear()  # graphs of the old buffers are released where no factorization runs

    # ------------------------------------------------------------------ pieces
    def _blocks(self, kernel, args):
        """``kernel`` over as many blocks as the partial sums (grid-stride over the vectors)."""
        wp.launch(kernel, self._partials.shape[0] * self._block, args, device=self.device, block_dim=self._block)

    def _ddot(self, a, b):
        self._blocks(_dot_partial_kernel, [a, b, self.count, self._partials])

    def _scalar(self, kernel, args, partials=None):
        """``kernel`` on one block, adding up ``partials`` (default: the dot products')."""
        wp.launch(kernel, self._block, [self._partials if partials is None else partials] + args,
                  device=self.device, block_dim=self._block)

    def _residual(self, b):
        """r = b - A x with A x in ``Ap``."""
        self._blocks(_pcg_residual_kernel, [self.count, b, self.Ap, self.r, self._partials.shape[0]])

    def _tail(self, matvec, x):
        """A p, p.Ap, alpha, x += alpha p, r -= alpha A p, r.r, stopping test."""
        matvec(self.p, self.Ap)
        self._ddot(self.p, self.Ap)
        self._blocks(_pcg_alpha_axpy2_kernel,
                     [self._partials, self._s, self.p, self.Ap, x, self.r, self.count, self._rr_partials])
        self._scalar(_pcg_check_kernel, [self._s, self._flag, self.tolerance, float(self.max_iterations)],
                     self._rr_partials)

    def _run(self, matvec, b, x, preconditioner):
        dev, nb = self.device, self._partials.shape[0]
        self._ddot(b, b)
        self._scalar(_pcg_store_kernel, [self._s, _BB])
        if self.warm_start:  # r = b - A x, or x = 0 and r = b where that is not smaller than b
            matvec(x, self.Ap)
            self._residual(b)
            self._ddot(self.r, self.r)
            self._blocks(_pcg_warm_kernel, [self._partials, self._s, b, x, self.r, self.count, nb])
        else:
            self._blocks(_pcg_start_kernel, [self.count, b, x, self.r, nb])
        wp.launch(_pcg_init_kernel, 1, [self._s, self._flag], device=dev)
        preconditioner.apply(self.r, self.z)
        wp.launch(copy_count_kernel, self._capacity, [self.count, self.z, self.p], device=dev)
        self._ddot(self.r, self.z)
        self._scalar(_pcg_store_kernel, [self._s, _RZN])
        self._tail(matvec, x)

        def body():
            preconditioner.apply(self.r, self.z)
            self._ddot(self.r, self.z)
            self._blocks(_pcg_beta_xpby_kernel, [self._partials, self._s, self.z, self.p, self.count, nb])
            self._tail(matvec, x)

        wp.capture_while(self._flag, body)
        # the true residual b - A x and ||x|| (convergence is judged on them)
        matvec(x, self.Ap)
        self._residual(b)
        self._ddot(self.r, self.r)
        self._scalar(_pcg_store_kernel, [self._s, _RTRUE])
        self._ddot(x, x)
        self._scalar(_pcg_store_kernel, [self._s, _XX])

    def _key(self, matvec, b, x, preconditioner):
        owner = getattr(matvec, "__self__", None)
        mk = getattr(owner, "graph_key", None)
        pk = getattr(preconditioner, "graph_key", None)
        if mk is None or pk is None:
            return None
        pkey = pk()
        if pkey is None:  # an apply that cannot be captured (cuDSS's solve allocates)
            return None
        return (self._geometry, b.ptr, x.ptr, mk(), pkey, self.tolerance, self.max_iterations, self.warm_start)

    def solve(self, matvec, b: wp.array, x: wp.array, preconditioner) -> CGResult:
        done = self.launch(matvec, b, x, preconditioner)
        return done if done is not None else self.result(self.scalars.numpy())

    @property
    def scalars(self) -> wp.array:
        """The device scalars a launched solve leaves (read them for :meth:`result`)."""
        return self._s

    def launch(self, matvec, b: wp.array, x: wp.array, preconditioner) -> CGResult | None:
        """Enqueue the solve without waiting for it: None, then :meth:`result` of
        :attr:`scalars` read to the host (with whatever else the caller reads in that wait);
        or, where the preconditioner cannot apply on the device, the host solve's result."""
        capable = getattr(preconditioner, "device_capable", None)
        if capable is None or not capable():
            self.host_solves += 1
            return super().solve(matvec, b, x, preconditioner)
        if b.shape[0] != self.n:
            self.resize(b.shape[0])
        self._norm_a = self.operator_norm(matvec)  # cached; host reads, so before any capture
        key = self._key(matvec, b, x, preconditioner) if self.graph else None
        self.replay.run(key, lambda: self._run(matvec, b, x, preconditioner))
        return None

    def result(self, s: np.ndarray) -> CGResult:
        """The result of the launched solve from its :attr:`scalars` read to the host."""
        norm_a = self._norm_a
        bb = float(s[_BB])
        if bb == 0.0 or not np.isfinite(bb):
            rel = 0.0 if bb == 0.0 else float("nan")
            return CGResult(0, rel, bb == 0.0, float("nan"), rel)
        rel = float(np.sqrt(s[_RTRUE] / bb))
        floor = _EPS * norm_a * float(np.sqrt(s[_XX] / bb))
        return CGResult(int(s[_IT]), rel, bool(rel <= self.tolerance), float("nan"), float(s[_REL]), floor,
                        bool(self.tolerance < floor))
