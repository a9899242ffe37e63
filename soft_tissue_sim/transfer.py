"""Device-to-host reads with one synchronisation for many arrays.

``array.numpy()`` of a CUDA array allocates a host array, copies into it from pageable memory
and waits, every time. :func:`to_host` copies several arrays into pinned host mirrors kept per
source array, waits once, and returns NumPy views of the mirrors. A view is overwritten by the
next read of the same source: index or copy it before that. On the CPU device the views are
the arrays' own memory, as ``numpy()`` gives them.
"""

from __future__ import annotations

from collections import OrderedDict

import numpy as np
import warp as wp

_MIRRORS: OrderedDict = OrderedDict()  # (device, ptr, shape, dtype) -> pinned host array
_MAX_MIRRORS = 256


def _mirror(a: wp.array) -> wp.array:
    key = (str(a.device), a.ptr, a.shape, a.dtype)
    m = _MIRRORS.get(key)
    if m is None:
        m = wp.empty(a.shape, dtype=a.dtype, device="cpu", pinned=True)
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
        self._host = self.array if self.array.device.is_cpu else wp.zeros(shape, dtype=dtype, device="cpu",
                                                                         pinned=True)
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
