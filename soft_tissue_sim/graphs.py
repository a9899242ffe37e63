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

:class:`Replayer` is the capture-and-replay a component uses for launches whose arguments hold
for many steps (it retires the graphs it replaces here).
"""

from __future__ import annotations

import warnings
from collections import OrderedDict

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


class Replayer:
    """A component's launches captured as a graph per key and replayed.

    :meth:`run` runs ``launches`` (a callable that only launches: no host reads, no host logic
    that could differ between calls) plainly the first time ``key`` is seen (its kernels load
    then), captures them at the second time and replays the graph from then on while the key
    holds. The key names everything the launches depend on (array addresses, sizes, scalar
    arguments). Up to ``slots`` keys keep a graph (for a component that alternates between
    argument sets); beyond that the least recently used is retired (:func:`retire`), as are all
    on :meth:`clear`. ``eager``: once a capture has succeeded (the kernels are loaded), a new key
    is captured at its first use (for launches whose key changes every few calls, or after every
    cut: a plain first run and a capture at the second would pay for the launches twice); if that
    capture fails, the launches run plainly and the key is captured at its next use, as without
    ``eager`` (the failure is not counted). Only for launches that allocate nothing: memory
    allocated inside a capture belongs to the graph. Another capture that fails runs the
    launches plainly and forgets the key; ``max_failures`` failures in a row turn capturing off
    for this replayer, with a warning. ``None`` as a key, ``enabled`` False, or a capture
    already under way (a replayer's launches inside another's): plain launches."""

    def __init__(self, device, name: str, slots: int = 1, eager: bool = False, max_failures: int = 1):
        self.device = wp.get_device(device)
        self.name = name
        self.slots = int(slots)
        self.eager = bool(eager)
        self.max_failures = int(max_failures)
        self.enabled = True
        self.error: str | None = None
        self.failures = 0  # captures failed in a row
        self.captures = 0
        self.replays = 0
        self.plain = 0  # runs of plain launches (not inside another replayer's capture)
        self._graphs: OrderedDict = OrderedDict()
        self._seen: OrderedDict = OrderedDict()

    def counts(self) -> dict:
        """{captures, replays, plain}: how its launches have run so far."""
        return {"captures": self.captures, "replays": self.replays, "plain": self.plain}

    def graph(self, key):
        """The graph kept for ``key``, or None."""
        return self._graphs.get(key)

    def latest(self):
        """The graph launched last among those kept, or None."""
        return next(reversed(self._graphs.values()), None)

    def run(self, key, launches) -> bool:
        """Run ``launches`` for ``key`` (see the class); True where a graph was launched."""
        if self.device.is_capturing:  # part of the outer graph
            launches()
            return False
        if key is None or not self.enabled:
            return self._plain(launches)
        graph = self._graphs.get(key)
        if graph is None:
            if key not in self._seen and not (self.eager and self.captures > 0):
                self._see(key)
                return self._plain(launches)
            first = key not in self._seen  # an eager capture at the key's first use
            try:
                with wp.ScopedCapture(device=self.device) as cap:
                    launches()
            except Exception as exc:  # noqa: BLE001 - these launches run plainly; captured again later
                self.error = f"{type(exc).__name__}: {exc}"
                if first:  # (it may have met what a first run does: an allocation) as if not eager
                    self._see(key)
                    return self._plain(launches)
                self.failures += 1
                self._seen.pop(key, None)
                if self.failures >= self.max_failures:
                    self.enabled = False
                    times = f" {self.failures} times in a row" if self.max_failures > 1 else ""
                    warnings.warn(f"{self.name}: graph capture failed{times} ({self.error}); launching directly",
                                  RuntimeWarning, stacklevel=3)
                return self._plain(launches)
            graph = cap.graph
            self._graphs[key] = graph
            self.failures = 0
            self.captures += 1
            while len(self._graphs) > self.slots:
                retire(self._graphs.popitem(last=False)[1])
        else:
            self._graphs.move_to_end(key)
        wp.capture_launch(graph)
        self.replays += 1
        return True

    def _plain(self, launches) -> bool:
        """Run ``launches`` plainly (counted in :attr:`plain`); False: no graph launched."""
        self.plain += 1
        launches()
        return False

    def _see(self, key) -> None:
        """Remember ``key`` as seen (the last 2 slots keys)."""
        self._seen[key] = True
        while len(self._seen) > 2 * self.slots:
            self._seen.popitem(last=False)

    def clear(self) -> None:
        """Retire every kept graph and forget the keys seen."""
        retire_all(self._graphs.values())
        self._graphs.clear()
        self._seen.clear()
