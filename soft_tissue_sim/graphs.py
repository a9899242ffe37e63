"""Where replaced CUDA graphs wait to be released.

Releasing an executable CUDA graph (``cudaGraphExecDestroy``, what dropping the last reference
to a ``wp.Graph`` does) waits until the whole device is idle, work on other streams included.
The simulation replaces graphs when the mesh changes (a cut: new array sizes and addresses)
while a factorization may be running beside the steps on a stream of its own; released there,
each one would make the cut wait for that factorization. So a component that replaces a graph
hands the old one to :func:`retire` instead of dropping it, and the graphs are released by
:func:`release` where the device has nothing long in flight: the device preconditioner calls it
between installing a factor and requesting the next one, and the simulation at the end of a
step where no factorization is running. Invariants: a retired graph is never launched again;
at most :data:`MAX_PARKED` wait (beyond that they are released at once, whatever is running).
"""

from __future__ import annotations

import warp as wp

MAX_PARKED = 256

_parked: list = []


def retire(graph) -> None:
    """Keep ``graph`` (a ``wp.Graph``; anything else is ignored) until the next :func:`release`."""
    if isinstance(graph, wp.Graph):
        _parked.append(graph)
        if len(_parked) > MAX_PARKED:
            release()


def retire_all(graphs) -> None:
    """:func:`retire` every graph among ``graphs`` (an iterable; other values are ignored)."""
    for g in graphs:
        retire(g)


def parked() -> int:
    """How many retired graphs wait to be released."""
    return len(_parked)


def release() -> int:
    """Release every retired graph now (each release waits for the device to be idle); returns
    how many."""
    n = len(_parked)
    _parked.clear()
    return n
