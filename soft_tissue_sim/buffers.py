"""Device arrays kept across mesh changes.

A topology change (a cut, a removal) changes the sizes of many per-node and per-element
arrays by a few entries. Making new arrays for it costs an allocation each, and an upload
from NumPy (``wp.array(numpy)``) costs a synchronous copy from pageable memory each (on a
GPU it waits for the stream). The arrays here are allocated with headroom and kept: a
change takes a prefix view of the size it needs, and the allocation is replaced only when a
size outgrows it.

* :class:`GrowArray`: one array (scratch, state) of changing length.
* :class:`PackedArrays`: several typed arrays in one allocation, filled on the host side (a
  pinned staging buffer on a GPU; on the CPU device the arrays' own memory) and sent with
  one copy per run of adjacent fields that changed, without a wait.

Invariant: a view is valid until the next :meth:`GrowArray.view` / :meth:`PackedArrays.reserve`
that reallocates; views hold a reference to their allocation (a stale view reads the old
memory, never freed memory). Code that keeps an array across a change must copy it.
"""

from __future__ import annotations

import math

import numpy as np
import warp as wp

from .transfer import PINNED

HEADROOM = 1.25  # capacity over the size that made an allocation
MIN_CAPACITY = 16
ALIGN = 64  # bytes: where each field of a PackedArrays starts


def capacity_for(n: int, headroom: float = HEADROOM) -> int:
    return max(MIN_CAPACITY, int(math.ceil(n * headroom)))


_UNBOUNDED: dict = {}


def unbounded_count(device) -> wp.array:
    """A device count (int32, one element) no index reaches: for a kernel that reads its count
    on the device (launched over a capacity) launched over exactly the elements it is to cover."""
    d = wp.get_device(device)
    if d.alias not in _UNBOUNDED:
        _UNBOUNDED[d.alias] = wp.array([np.iinfo(np.int32).max], dtype=wp.int32, device=d)
    return _UNBOUNDED[d.alias]


def typed_view(buffer: wp.array, offset_bytes: int, dtype, shape) -> wp.array:
    """A typed array of ``shape`` (a length, or a tuple) at ``offset_bytes`` into ``buffer``
    (keeps it alive)."""
    shape = (int(shape),) if np.isscalar(shape) else tuple(shape)
    a = wp.array(ptr=buffer.ptr + offset_bytes, dtype=dtype, shape=shape, device=buffer.device,
                 pinned=buffer.pinned)
    a._ref = buffer
    return a


class GrowArray:
    """One device array whose length changes with the mesh: :meth:`view` (n) is its first n
    elements; the allocation (``headroom`` over the n that made it) is replaced only when n
    outgrows it, and then its contents are not carried over (the old one is let go first).
    ``fill``: a value every newly allocated element gets (e.g. 1.0, or an index ramp given as a
    callable of the capacity)."""

    def __init__(self, dtype, device, fill=None, headroom: float = HEADROOM):
        self.dtype = dtype
        self.device = wp.get_device(device)
        self.fill = fill
        self.headroom = float(headroom)
        self.buffer: wp.array | None = None
        self.allocations = 0
        self._view: wp.array | None = None

    @property
    def capacity(self) -> int:
        return 0 if self.buffer is None else int(self.buffer.shape[0])

    def view(self, n: int) -> wp.array:
        """The first ``n`` elements (the same object while n and the allocation hold)."""
        n = int(n)
        if self.buffer is None or n > self.buffer.shape[0]:
            cap = capacity_for(n, self.headroom)
            self.buffer = self._view = None  # where no other view holds it, freed before the next is made
            if callable(self.fill):
                self.buffer = wp.array(self.fill(cap), dtype=self.dtype, device=self.device)
            elif self.fill is not None:
                self.buffer = wp.full(cap, self.fill, dtype=self.dtype, device=self.device)
            else:
                self.buffer = wp.empty(cap, dtype=self.dtype, device=self.device)
            self.allocations += 1
        if self._view is None or self._view.shape[0] != n:
            self._view = typed_view(self.buffer, 0, self.dtype, n)
        return self._view

    def release(self) -> None:
        """Let the allocation go (the next :meth:`view` makes a new one)."""
        self.buffer = self._view = None


def _numpy_layout(dtype) -> tuple:
    """(NumPy scalar type, element shape) of a Warp dtype."""
    scalar = getattr(dtype, "_wp_scalar_type_", dtype)
    return wp.dtype_to_numpy(scalar), tuple(getattr(dtype, "_shape_", ()))


def field_runs(order: list, names) -> list[tuple]:
    """The fields ``names`` (of the fields in layout ``order``) as runs of adjacent fields:
    [(first, last), ...] in layout order."""
    runs: list[list[int]] = []
    for i in sorted(order.index(k) for k in set(names)):
        if runs and runs[-1][-1] == i - 1:
            runs[-1][-1] = i
        else:
            runs.append([i, i])
    return [(order[a], order[b]) for a, b in runs]


class PackedArrays:
    """Typed device arrays (``fields``: name -> Warp dtype, in layout order) in one allocation.

    Per change: :meth:`reserve` the element counts (True where it reallocated: every field must
    then be written again), write the fields that changed into :meth:`host` (NumPy views),
    :meth:`send` them (one copy per run of adjacent fields, asynchronous), and take the device
    arrays from :meth:`array`. Fields that change together should be adjacent. On the CPU
    device :meth:`host` is the device memory itself and :meth:`send` copies nothing; on a GPU
    it is a page-locked staging buffer, and :meth:`host` first waits until the last copy out
    of it has left."""

    def __init__(self, fields: dict, device):
        self.fields = dict(fields)
        self.device = wp.get_device(device)
        self.counts = {k: 0 for k in self.fields}
        self.capacity = {k: 0 for k in self.fields}
        self.offsets: dict[str, int] = {}
        self.buffer: wp.array | None = None
        self.staging: wp.array | None = None
        self.allocations = 0
        self.copies = 0
        self._sent = None  # the event after the last copy out of the staging buffer
        self._arrays: dict[str, wp.array] = {}
        self._host: dict[str, np.ndarray] = {}
        self._runs: dict[frozenset, list] = {}  # send's runs of adjacent fields, by the set of names

    def _size(self, name: str) -> int:
        return wp.types.type_size_in_bytes(self.fields[name])

    def reserve(self, counts: dict) -> bool:
        """Set the element counts; reallocate (with headroom for every field) where one exceeds
        its capacity. Returns whether it reallocated."""
        grow = self.buffer is None or any(int(counts[k]) > self.capacity[k] for k in self.fields)
        if grow:
            if self._sent is not None:  # the old staging buffer goes back to the pool: no copy out of it in flight
                wp.synchronize_event(self._sent)
            off = 0
            for k in self.fields:
                self.capacity[k] = capacity_for(int(counts[k]))
                self.offsets[k] = off
                off += -(-self.capacity[k] * self._size(k) // ALIGN) * ALIGN
            self.buffer = wp.empty(off, dtype=wp.uint8, device=self.device)
            if self.device.is_cuda:
                self.staging = PINNED.empty(off, wp.uint8)
            else:
                self.staging = self.buffer
            self._sent = None
            self.allocations += 1
            self._arrays.clear()
            self._host.clear()
        for k in self.fields:
            c = int(counts[k])
            if c != self.counts[k]:
                self.counts[k] = c
                self._arrays.pop(k, None)
                self._host.pop(k, None)
        return grow

    def writable(self) -> None:
        """Wait until the last :meth:`send` has left the staging buffer (its host views may then
        be filled again)."""
        if self._sent is not None:
            wp.synchronize_event(self._sent)
            self._sent = None

    def host(self, name: str) -> np.ndarray:
        """The host side of field ``name`` (its current count), to fill before :meth:`send`
        (:meth:`writable` first)."""
        self.writable()
        h = self._host.get(name)
        if h is None:
            scalar, shape = _numpy_layout(self.fields[name])
            n, off = self.counts[name], self.offsets[name]
            raw = self.staging.numpy()[off: off + n * self._size(name)]
            h = self._host[name] = raw.view(scalar).reshape((n, *shape))
        return h

    def send(self, names) -> None:
        """Copy the fields ``names`` to the device (runs of adjacent fields in one copy each)."""
        if self.staging is self.buffer:
            return
        key = frozenset(names)
        runs = self._runs.get(key)
        if runs is None:
            runs = self._runs[key] = field_runs(list(self.fields), key)
        for first, last in runs:
            start = self.offsets[first]
            end = self.offsets[last] + self.counts[last] * self._size(last)
            if end > start:
                wp.copy(self.buffer, self.staging, dest_offset=start, src_offset=start, count=end - start)
                self.copies += 1
        if runs:
            self._sent = wp.get_stream(self.device).record_event()

    def alias(self, name: str, dtype, shape) -> wp.array:
        """Field ``name``'s device memory as an array of ``dtype`` and ``shape`` (a length or a
        tuple: e.g. vec3i rows as a flat int32 index list)."""
        return typed_view(self.buffer, self.offsets[name], dtype, shape)

    def array(self, name: str) -> wp.array:
        """The device array of field ``name`` (the same object while its count and the
        allocation hold)."""
        a = self._arrays.get(name)
        if a is None:
            a = self._arrays[name] = typed_view(self.buffer, self.offsets[name], self.fields[name], self.counts[name])
        return a
