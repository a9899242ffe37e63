"""The preconditioner interface of the PCG solve of eq. (1), and the factory that builds one
from a scene's ``solver`` options.

A preconditioner is used by :class:`soft_tissue_sim.implicit_integration.BackwardEuler`
(``begin_step`` once per step, then ``apply`` in every PCG iteration) and, where it holds a
factorization, by contact and cutting (``inner``):

* ``name``; ``begin_step(system)``: prepare for a step (``system`` has ``fem``, ``m_coef``,
  ``k_coef``, ``step_index``); ``apply(r, z)``: z = P^-1 r on Warp vec3d arrays;
* ``refresh(system)`` (factor-based ones): a factor of the current state, made and installed now;
* ``stats()`` (a dict merged into the step statistics), ``invalidate()`` (the mesh or the
  coefficients changed: start afresh), ``close()`` (return at once, whatever runs behind);
* ``device_capable()``: ``apply`` only launches device work (PCG may keep its scalars on the
  device); ``graph_key()``: what a captured ``apply`` depends on, or None when it cannot be
  captured in a CUDA graph;
* ``inner``: the factor's services, or absent: ``delassus(B)`` (B^T P^-1 B, the Delassus
  operator of eq. 4), ``apply_columns(B)``, ``make_correction(enabled, rotate)`` (the object a
  cutter feeds topological changes, eq. 5-12), ``rotate``.

Kinds (``solver.preconditioner``): ``none`` (plain CG), ``jacobi`` (3x3 block diagonal),
``async_ldlt`` (the paper's asynchronous, rotated exact factorization) and ``direct`` (an
exact factor every step, unrotated: the reference). The factor's backend (``ldlt.backend``):

* ``cholmod``: CHOLMOD's sparse LDL^T on the host, in a background worker
  (:mod:`soft_tissue_sim.ldlt_preconditioner`), applied on the host;
* ``dense``: the dense inverse on the device (:mod:`soft_tissue_sim.dense_inverse`;
  cuSOLVER on a GPU, LAPACK on Warp's CPU backend), applied from a single-precision copy
  (``apply_precision``: auto = float32 on a GPU for ``async_ldlt``, float64 otherwise);
* ``cudss``: cuDSS's sparse factor on the GPU (:mod:`soft_tissue_sim.cudss_factor`; no
  cutting, no contact);
* ``auto``: CHOLMOD on the CPU; on a GPU the dense inverse up to ``dense_max_dofs`` degrees of
  freedom, cuDSS above for scenes without contact and cutting, else CHOLMOD.
"""

from __future__ import annotations

import warnings

import numpy as np
import warp as wp

from .cg import BlockJacobiPreconditioner, IdentityPreconditioner
from .material import ParameterError

PRECONDITIONERS = ("none", "jacobi", "async_ldlt", "direct")
BACKENDS = ("auto", "cholmod", "dense", "cudss")
DENSE_MAX_DOFS = 12_000  # auto: the dense inverse up to this size on a GPU (bench backends, docs/benchmarks.md)
_RETIRED = {"apply_on", "columns_on", "lanes", "tail_width", "tail_block", "cols_lanes", "min_device_columns"}
_LDLT_KEYS = {"backend", "rotate", "refresh_every", "device_refresh_every", "device_refresh_iterations",
              "deterministic", "lag", "mode",
              "ordering", "worker", "release_gil", "dense_max_dofs", "reserve_sms", "apply_precision"}
RESERVE_SMS = 16  # auto: SMs a GPU factorization leaves to the steps (sm_partition; docs/benchmarks.md)


class HostPreconditioner:
    """Adapter of a host (NumPy) preconditioner, such as the CHOLMOD LDL^T one, to Warp arrays:
    on the CPU device the arrays are viewed in place, on CUDA copied to the host and back."""

    def __init__(self, inner):
        self.inner = inner
        self.name = inner.name

    def begin_step(self, system) -> None:
        self.inner.begin_step(system.step_index, system.fem.node_rotations())

    def apply(self, r: wp.array, z: wp.array) -> None:
        if r.device.is_cpu:
            self.inner.apply(r.numpy().reshape(-1), z.numpy().reshape(-1))
        else:
            out = np.empty(3 * r.shape[0])
            self.inner.apply(r.numpy().reshape(-1), out)
            z.assign(out.reshape(-1, 3))

    def refresh(self, system) -> None:
        """A factor of the current state, made and installed now."""
        self.inner.refresh(system.step_index)

    def stats(self) -> dict:
        return self.inner.stats()

    def invalidate(self) -> None:
        self.inner.invalidate()

    def close(self) -> None:
        self.inner.close()

    def device_capable(self) -> bool:
        return False

    def graph_key(self):
        return None


def _gpu_libraries() -> str | None:
    """Why the GPU backends cannot be used here, or None."""
    try:
        import cupy  # noqa: F401
        import nvmath.bindings.cusolverDn  # noqa: F401
    except Exception as exc:  # noqa: BLE001 - any import failure means: not available
        return f"{type(exc).__name__}: {exc} (install the GPU extra: pip install .[cuda])"
    return None


def choose_backend(backend: str, device, n_dofs: int, contact: bool, cutting: bool, dense_max: int) -> str:
    """The backend ``auto`` stands for, or the one asked for once checked against the device."""
    cuda = wp.get_device(device).is_cuda
    if backend == "auto":
        if not cuda:
            return "cholmod"
        missing = _gpu_libraries()
        if missing is not None:
            warnings.warn(f"ldlt backend auto: the GPU backends are not available ({missing}); using CHOLMOD "
                          "on the host", RuntimeWarning, stacklevel=3)
            return "cholmod"
        if n_dofs <= dense_max:
            return "dense"
        return "cholmod" if (contact or cutting) else "cudss"
    if backend == "cudss":
        if not cuda:
            raise ParameterError("ldlt backend cudss needs a CUDA device (cuDSS runs on the GPU)")
        if contact or cutting:
            raise ParameterError("ldlt backend cudss supports neither contact nor cutting: use dense or cholmod")
    if backend in ("dense", "cudss") and cuda:
        missing = _gpu_libraries()
        if missing is not None:
            raise ParameterError(f"ldlt backend {backend} needs CuPy and nvmath-python: {missing}")
    return backend


def make_preconditioner(kind: str, options: dict, snapshot_fn, meta_fn=None, device="cpu", n_dofs: int = 0,
                        contact: bool = False, cutting: bool = False):
    """The preconditioner a scene's ``solver`` names (see the module docstring). ``snapshot_fn``
    gives (A or a state that assembles it, node rotations, topology) for the host factorization;
    ``meta_fn`` the topology alone ({"uids", "version"}) for the device backends."""
    if kind == "none":
        return IdentityPreconditioner()
    if kind == "jacobi":
        return BlockJacobiPreconditioner()
    if kind not in ("async_ldlt", "direct"):
        raise ParameterError(f"unknown preconditioner {kind!r}: use one of {', '.join(PRECONDITIONERS)}")
    retired = _RETIRED & set(options)
    if retired:
        raise ParameterError(f"ldlt options {sorted(retired)} were retired with the level-scheduled device solves: "
                             "use ldlt.backend (auto, cholmod, dense or cudss)")
    unknown = set(options) - _LDLT_KEYS
    if unknown:
        raise ParameterError(f"unknown ldlt options {sorted(unknown)}: use {sorted(_LDLT_KEYS)}")
    backend = str(options.get("backend", "auto"))
    if backend not in BACKENDS:
        raise ParameterError(f"ldlt backend must be one of {', '.join(BACKENDS)}, got {backend!r}")
    dense_max = options.get("dense_max_dofs", DENSE_MAX_DOFS)
    if isinstance(dense_max, bool) or not isinstance(dense_max, int) or dense_max < 0:
        raise ParameterError(f"ldlt dense_max_dofs must be a whole number >= 0, got {dense_max!r}")
    backend = choose_backend(backend, device, n_dofs, contact, cutting, dense_max)
    direct = kind == "direct"  # a fresh exact factor every step: the reference solution
    sched = dict(rotate=False, refresh_every=1, deterministic=True, lag=0) if direct else dict(
        rotate=bool(options.get("rotate", True)), refresh_every=int(options.get("refresh_every", 1)),
        deterministic=bool(options.get("deterministic", False)), lag=options.get("lag", 0))
    if backend == "cholmod":
        from .ldlt_preconditioner import ORDERINGS, AsyncLDLTPreconditioner

        ordering = str(options.get("ordering", "default"))
        if ordering == "auto":
            ordering = "default"
        if ordering not in ORDERINGS:
            raise ParameterError(f"ldlt ordering must be one of {', '.join(ORDERINGS)}, got {ordering!r}")
        try:
            inner = AsyncLDLTPreconditioner(
                snapshot_fn, mode=str(options.get("mode", "auto")), ordering=ordering,
                lower_factor=contact, worker=str(options.get("worker", "thread")),
                release_gil=bool(options.get("release_gil", True)), **sched)
        except ValueError as exc:
            raise ParameterError(f"ldlt options: {exc}") from None
        if direct:
            inner.name = "direct"
        return HostPreconditioner(inner)
    from .device_preconditioner import AsyncDevicePreconditioner

    if not direct and "device_refresh_every" in options:  # a GPU factorization shares the device with the steps
        every = options["device_refresh_every"]
        if isinstance(every, bool) or not isinstance(every, int) or every < 1:
            raise ParameterError(f"ldlt device_refresh_every must be a whole number >= 1, got {every!r}")
        sched["refresh_every"] = every
    if not direct:  # and only where the steps need it (a factorization in flight slows the steps beside it)
        its = options.get("device_refresh_iterations", 0)
        if isinstance(its, bool) or not isinstance(its, int) or its < 0:
            raise ParameterError(f"ldlt device_refresh_iterations must be a whole number >= 0, got {its!r}")
        sched["refresh_iterations"] = its
    reserve = options.get("reserve_sms", "auto")
    if reserve == "auto":
        reserve = RESERVE_SMS
    if isinstance(reserve, bool) or not isinstance(reserve, int) or reserve < 0:
        raise ParameterError(f"ldlt reserve_sms must be auto or a whole number >= 0, got {reserve!r}")
    sched["reserve_sms"] = reserve
    precision = str(options.get("apply_precision", "auto"))
    if precision not in ("auto", "float64", "float32"):
        raise ParameterError(f"ldlt apply_precision must be auto, float64 or float32, got {precision!r}")
    if backend == "dense":
        from .dense_inverse import DenseInverse

        if precision == "auto":  # single precision where the apply is bandwidth-bound: a GPU's async factor
            precision = "float32" if wp.get_device(device).is_cuda and not direct else "float64"
        factor = DenseInverse(device, precision)
    else:
        from .cudss_factor import CuDSSFactor

        factor = CuDSSFactor(device)
    try:
        return AsyncDevicePreconditioner(factor, meta_fn, device, name=kind, **sched)
    except ValueError as exc:
        factor.close()
        raise ParameterError(f"ldlt options: {exc}") from None
