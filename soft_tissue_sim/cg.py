"""Preconditioned conjugate gradient on Warp arrays, and the simple preconditioners.

We keep our own PCG rather than ``warp.optim.linear.cg``: Warp's variant applies the
preconditioner twice per iteration (to r and to A p), and with the LDL^T preconditioner
of the paper the triangular solves are the dominant cost, so that would double it. Ours is
the textbook PCG: one product with A and one preconditioner application per iteration,
stopping on the true relative residual ||b - A x|| / ||b|| of the recursion.

Vectors are ``wp.array(dtype=wp.vec3d)`` (node-major). The operator is a callable
``matvec(p, out)`` computing ``out = A p``; a preconditioner has
``apply(r, z)`` computing ``z = P^-1 r``.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import warp as wp


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
def _block_apply_kernel(Dinv: wp.array(dtype=wp.mat33d), r: wp.array(dtype=wp.vec3d), z: wp.array(dtype=wp.vec3d)):
    i = wp.tid()
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
    residual: float  # final relative residual ||b - A x|| / ||b|| (recursive)
    converged: bool
    precond_ms: float


class IdentityPreconditioner:
    """No preconditioning: plain CG (the paper's "CGM")."""

    name = "none"

    def begin_step(self, system) -> None:
        pass

    def apply(self, r: wp.array, z: wp.array) -> None:
        wp.copy(z, r)

    def stats(self) -> dict:
        return {}

    def invalidate(self) -> None:
        pass

    def close(self) -> None:
        pass


class BlockJacobiPreconditioner:
    """Inverse of the 3x3 diagonal blocks of A, rebuilt every step (cheap)."""

    name = "jacobi"

    def __init__(self):
        self._D = self._Dinv = None

    def begin_step(self, system) -> None:
        fem = system.fem
        if self._D is None or self._D.shape[0] != fem.n_nodes:
            self._D = wp.zeros(fem.n_nodes, dtype=wp.mat33d, device=fem.device)
            self._Dinv = wp.zeros_like(self._D)
        fem.diagonal_blocks(system.m_coef, system.k_coef, self._D)
        wp.launch(_invert_blocks_kernel, fem.n_nodes, [self._D, fem.free, self._Dinv], device=fem.device)

    def apply(self, r: wp.array, z: wp.array) -> None:
        wp.launch(_block_apply_kernel, r.shape[0], [self._Dinv, r, z], device=r.device)

    def stats(self) -> dict:
        return {}

    def invalidate(self) -> None:
        self._D = None

    def close(self) -> None:
        pass


class HostPreconditioner:
    """Adapter for a host (numpy) preconditioner such as the CHOLMOD LDL^T one.

    On the CPU device the Warp arrays are viewed in place; on CUDA they are copied
    to the host and back (the device-side triangular solves are issue #8's work).
    """

    def __init__(self, inner):
        self.inner = inner
        self.name = inner.name
        self._host_r = None

    def begin_step(self, system) -> None:
        self.inner.begin_step(system.step_index, system.fem.node_rotations())

    def apply(self, r: wp.array, z: wp.array) -> None:
        if r.device.is_cpu:
            self.inner.apply(r.numpy().reshape(-1), z.numpy().reshape(-1))
        else:
            out = np.empty(3 * r.shape[0])
            self.inner.apply(r.numpy().reshape(-1), out)
            z.assign(out.reshape(-1, 3))

    def stats(self) -> dict:
        return self.inner.stats()

    def invalidate(self) -> None:
        self.inner.invalidate()

    def close(self) -> None:
        self.inner.close()


class PCG:
    """Preconditioned conjugate gradient with preallocated work vectors."""

    def __init__(self, n: int, device, tolerance: float = 1e-7, max_iterations: int = 1000):
        if not (tolerance > 0.0):
            raise ValueError(f"CG tolerance must be > 0, got {tolerance}")
        if int(max_iterations) < 1:
            raise ValueError(f"CG max_iterations must be >= 1, got {max_iterations}")
        self.tolerance = float(tolerance)
        self.max_iterations = int(max_iterations)
        self.device = wp.get_device(device)
        self.resize(n)

    def resize(self, n: int) -> None:
        d = self.device
        self.n = n
        self.r = wp.zeros(n, dtype=wp.vec3d, device=d)
        self.z = wp.zeros(n, dtype=wp.vec3d, device=d)
        self.p = wp.zeros(n, dtype=wp.vec3d, device=d)
        self.Ap = wp.zeros(n, dtype=wp.vec3d, device=d)
        self._dot = wp.zeros(1, dtype=wp.float64, device=d)

    def _inner(self, a: wp.array, b: wp.array) -> float:
        wp.utils.array_inner(a, b, out=self._dot)
        return float(self._dot.numpy()[0])

    def solve(self, matvec, b: wp.array, x: wp.array, preconditioner) -> CGResult:
        """Solve A x = b from x = 0. Returns iterations and the final relative residual."""
        if b.shape[0] != self.n:
            self.resize(b.shape[0])
        dev = self.device
        r, z, p, Ap = self.r, self.z, self.p, self.Ap
        x.zero_()
        wp.copy(r, b)
        b_norm = np.sqrt(self._inner(b, b))
        if b_norm == 0.0 or not np.isfinite(b_norm):
            return CGResult(0, 0.0 if b_norm == 0.0 else float("nan"), b_norm == 0.0, 0.0)
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
        return CGResult(it, float(rel), bool(rel <= self.tolerance), 1000.0 * t_pre)
