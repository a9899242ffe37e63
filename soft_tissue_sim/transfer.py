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
