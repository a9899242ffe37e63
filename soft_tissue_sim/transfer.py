"""Device-to-host reads with one synchronisation for many arrays.

``array.numpy()`` of a CUDA array allocates a host array, copies into it from pageable memory
and waits, every time. :func:`to_host` copies several arrays into pinned host mirrors kept per
source array, waits once, and returns NumPy views of the mirrors. A view is overwritten by the
next read of the same source: index or copy it before that. On the CPU device the views are
the arrays' own memory, as ``numpy()`` gives them.

Page-locked host memory comes from :class:`PinnedPool` and goes back to it, never to the driver:
``cudaFreeHost`` waits for the whole device (a background factorization included), and a mesh
change replaces many of the arrays these mirrors and stagings are kept for.
"""

from __future__ import annotations

import threading
from collections import OrderedDict, defaultdict

import numpy as np
import warp as wp


class PinnedPool:
    """Page-locked host blocks of power-of-two sizes, handed out as Warp arrays and taken back
    when such an array is deleted (its deleter), to be handed out again; none is ever freed.
    What it holds is at most twice the largest set of page-locked arrays alive at once.
    ``pinned=False`` pools ordinary host memory the same way (a machine without CUDA)."""

    MIN_BYTES = 256

    def __init__(self, pinned: bool = True):
        self.pinned = bool(pinned)
        self._lock = threading.Lock()
        self._free: dict[int, list] = defaultdict(list)  # block size -> idle blocks
        self._lent: dict[int, wp.array] = {}  # ptr -> its block
        self.allocated = 0  # blocks asked of the driver

    def empty(self, shape, dtype) -> wp.array:
        """An uninitialised page-locked CPU array of ``shape`` and ``dtype``."""
        shape = (shape,) if isinstance(shape, int) else tuple(shape)
        nbytes = int(np.prod(shape)) * wp.types.type_size_in_bytes(dtype)
        size = 1 << max(self.MIN_BYTES.bit_length() - 1, (max(nbytes, 1) - 1).bit_length())
        with self._lock:
            idle = self._free[size]
            block = idle.pop() if idle else None
        if block is None:
            block = wp.empty(size, dtype=wp.uint8, device="cpu", pinned=self.pinned)
            self.allocated += 1
        with self._lock:
            self._lent[block.ptr] = block
        return wp.array(ptr=block.ptr, dtype=dtype, shape=shape, capacity=size, device="cpu", pinned=self.pinned,
                        deleter=self._take_back)

    def zeros(self, shape, dtype) -> wp.array:
        a = self.empty(shape, dtype)
        a.numpy().view(np.uint8)[...] = 0
        return a

    def _take_back(self, ptr: int, _size: int) -> None:
        with self._lock:
            block = self._lent.pop(ptr, None)
            if block is not None:
                self._free[block.shape[0]].append(block)


PINNED = PinnedPool()

_MIRRORS: OrderedDict = OrderedDict()  # (device, ptr, dtype) -> pinned host array
_MAX_MIRRORS = 256


def _mirror(a: wp.array, pool: PinnedPool | None = None) -> wp.array:
    """The pinned mirror kept for the device array ``a`` (one per address and dtype). Where the
    source at that address changed its shape (a view of a kept allocation after a mesh change),
    the old mirror goes back to the pool before the new one is taken, so that the same block
    serves again within its size class instead of a new page-locked allocation."""
    key = (str(a.device), a.ptr, a.dtype)
    m = _MIRRORS.get(key)
    if m is not None and m.shape != a.shape:
        del _MIRRORS[key]
        m = None  # the last reference: its block is idle again (unless a NumPy view of it is alive)
    if m is None:
        m = (pool or PINNED).empty(a.shape, a.dtype)
        _MIRRORS[key] = m
        while len(_MIRRORS) > _MAX_MIRRORS:  # arrays of earlier meshes
            _MIRRORS.popitem(last=False)
    else:
        _MIRRORS.move_to_end(key)
    return m


def to_host(*arrays: wp.array) -> list[np.ndarray]:
    """NumPy views of ``arrays`` on the host, after one wait for the device (see the module)."""
    if all(a.device.is_cpu for a in arrays):
        return [a.numpy() for a in arrays]
    mirrors = []
    for a in arrays:
        m = _mirror(a)
        wp.copy(m, a)
        mirrors.append(m)
    wp.synchronize_stream(wp.get_stream(arrays[0].device))
    return [m.numpy() for m in mirrors]


class Staged:
    """A device array filled from the host without a wait: write :meth:`view` (NumPy), then
    :meth:`send`. On the CPU device the view is the array itself and nothing is sent; on a GPU it
    is a pinned mirror copied asynchronously on the current stream, and :meth:`view` first waits
    for the last copy out of it to have left (so a refill never races a copy in flight)."""

    def __init__(self, shape, dtype, device):
        self.array = wp.zeros(shape, dtype=dtype, device=device)
        self._host = self.array if self.array.device.is_cpu else PINNED.zeros(shape, dtype)
        self._np = self._host.numpy()
        self._sent = None  # the event after the last copy

    def view(self) -> np.ndarray:
        """The host side to fill (the whole buffer)."""
        if self._sent is not None:
            wp.synchronize_event(self._sent)
        return self._np

    def send(self, count: int = 0) -> wp.array:
        """Copy the first ``count`` elements (0: all) to the device; returns :attr:`array`."""
        if self._host is not self.array:
            wp.copy(self.array, self._host, count=count)
            self._sent = wp.get_stream(self.array.device).record_event(self._sent)
        return self.array


class Readback:
    """Host buffers kept for a fixed list of device arrays: :meth:`copy` enqueues their copies
    (plain launches, which a graph may capture: the buffers stay where they are while the
    arrays keep their shapes), :meth:`read` waits for the stream once and returns NumPy views
    (overwritten by the next copy). Page-locked on a GPU; on the CPU device the views are the
    arrays' own memory, as :func:`to_host` gives them (nothing is copied)."""

    def __init__(self):
        self._bufs: list[wp.array] = []
        self._views: list[np.ndarray] = []  # their NumPy views, made once per buffer

    def copy(self, *arrays: wp.array) -> None:
        for i, a in enumerate(arrays):
            if i == len(self._bufs):
                self._bufs.append(None)
                self._views.append(None)
            b = self._bufs[i]
            if a.device.is_cpu:
                if b is not a:
                    self._bufs[i], self._views[i] = a, a.numpy()
                continue
            if b is None or b.shape != a.shape or b.dtype != a.dtype:
                b = self._bufs[i] = PINNED.empty(a.shape, a.dtype)
                self._views[i] = b.numpy()
            wp.copy(b, a)
        del self._bufs[len(arrays):]
        del self._views[len(arrays):]

    def key(self) -> tuple:
        """The buffers' addresses (a graph that captured :meth:`copy` writes there)."""
        return tuple(b.ptr for b in self._bufs)

    def read(self, device) -> list[np.ndarray]:
        """Views of the buffers after one wait for ``device``'s current stream."""
        dev = wp.get_device(device)
        if dev.is_cuda:
            wp.synchronize_stream(wp.get_stream(dev))
        return list(self._views)
