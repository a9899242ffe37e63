"""A stream for background GPU work that leaves some of the device's SMs to the steps.

The factorization that refreshes the preconditioner (paper section 2.2) runs beside the
simulation on a stream of its own. Dense factorizations fill every SM with long blocks, and
stream priorities only order blocks waiting for an SM: a step's small kernels, launched one
after the other, each wait for a factorization block to finish, and a 2 ms step takes as long
as the factorization (20 ms). A CUDA green context confines the factorization's stream to a
subset of the SMs; the simulation's own stream (the primary context) keeps all of them, so
``reserve`` SMs are always free for it.

:func:`partitioned_stream` makes one through the CUDA driver's green-context API (the
``cuda-bindings`` package that nvmath-python brings; CUDA 12.4+ driver) or says why it cannot.
"""

from __future__ import annotations

import warp as wp


class PartitionedStream:
    """A non-blocking stream of a green context holding all but ``reserved`` of the device's
    SMs (rounded to the architecture's partition granularity). ``stream``: a Warp view of it;
    ``sms``: the SMs its work may use; ``total``: the device's."""

    def __init__(self, device, reserve: int):
        from cuda.bindings import driver as cu

        self.device = wp.get_device(device)
        self._gctx = None
        self._handle = None

        def check(result):
            err, *out = result
            if err != cu.CUresult.CUDA_SUCCESS:
                raise RuntimeError(f"CUDA driver: {err.name if hasattr(err, 'name') else err}")
            return out[0] if len(out) == 1 else out

        check(cu.cuInit(0))
        dev = check(cu.cuDeviceGet(self.device.ordinal))
        res = check(cu.cuDeviceGetDevResource(dev, cu.CUdevResourceType.CU_DEV_RESOURCE_TYPE_SM))
        self.total = int(res.sm.smCount)
        want = self.total - int(reserve)
        if want < int(res.sm.minSmPartitionSize):
            raise ValueError(f"cannot leave {reserve} of {self.total} SMs free: the factorization needs at least "
                             f"{res.sm.minSmPartitionSize}")
        # a group of at least `want` SMs, rounded down to the granularity so that `reserve` stay free
        align = max(1, int(res.sm.smCoscheduledAlignment))
        want = max(int(res.sm.minSmPartitionSize), want - want % align)
        groups, _nb, _rest = check(cu.cuDevSmResourceSplitByCount(1, res, 0, want))
        group = groups[0]
        self.sms = int(group.sm.smCount)
        desc = check(cu.cuDevResourceGenerateDesc([group], 1))
        self._gctx = check(cu.cuGreenCtxCreate(desc, dev, cu.CUgreenCtxCreate_flags.CU_GREEN_CTX_DEFAULT_STREAM))
        self._handle = check(cu.cuGreenCtxStreamCreate(self._gctx, cu.CUstream_flags.CU_STREAM_NON_BLOCKING, 0))
        self.stream = wp.Stream(self.device, cuda_stream=int(self._handle))
        # events of the simulation's context must order work on it (the factor waits for its
        # assembly; the simulation for the factor): check that once here
        probe = wp.Event(self.device)
        self.stream.record_event(probe)
        wp.get_stream(self.device).wait_event(probe)
        wp.synchronize_event(probe)

    @property
    def reserved(self) -> int:
        return self.total - self.sms


_MADE: dict = {}  # (device ordinal, reserve) -> (stream or None, why not): one per process, kept


def partitioned_stream(device, reserve: int) -> tuple[PartitionedStream | None, str | None]:
    """(a :class:`PartitionedStream` leaving ``reserve`` SMs free, None), or (None, why not).
    One green context per device and size, made on first use and kept for the process (the
    simulations of a process share it: their factorizations queue on one stream)."""
    dev = wp.get_device(device)
    if not dev.is_cuda:
        return None, "not a CUDA device"
    if reserve <= 0:
        return None, "no SMs reserved"
    key = (dev.ordinal, int(reserve))
    if key not in _MADE:
        try:
            _MADE[key] = (PartitionedStream(dev, reserve), None)
        except Exception as exc:  # noqa: BLE001 - no driver support, no bindings, a bad size: a plain stream then
            _MADE[key] = (None, f"{type(exc).__name__}: {exc}")
    return _MADE[key]
