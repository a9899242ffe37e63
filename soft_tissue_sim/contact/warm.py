"""Warm start of the contact LCP: the last step's forces, found again by the contact's name.

A contact is named by its object and the tissue nodes it involves, by their uids (stable
across cuts): (object, node) for a node's contact, (object, the triangle's three nodes sorted)
for a triangle's. Names are rows of four integers, (obj, uid, -1, -1) or (obj, u0, u1, u2)
(uids are >= 0, so the two kinds never meet), matched as whole rows through a sorted byte view
rather than one Python dict look-up per contact. A step whose contacts are those of the last
one, in the same order (contacts held still), finds its forces without the search: when
their names are distinct, row i's force is last step's row i's.
"""

from __future__ import annotations

import numpy as np

_ROW = np.dtype((np.void, 4 * 8))  # one name: four int64 compared as bytes


def contact_names(obj: np.ndarray, node: np.ndarray, tri: np.ndarray, uids: np.ndarray) -> np.ndarray:
    """(k, 4) int64 names of contacts with object ``obj``, tissue node ``node`` (-1: a
    triangle's contact) and triangle ``tri`` (k, 3), nodes named by ``uids``."""
    names = np.empty((len(node), 4), np.int64)
    names[:, 0] = obj
    on_tri = (node < 0).nonzero()[0]
    if not len(on_tri):
        names[:, 1] = uids[node]
        names[:, 2:] = -1
        return names
    names[:, 1:] = -1
    on_node = (node >= 0).nonzero()[0]
    names[on_node, 1] = uids[node[on_node]]
    names[on_tri, 1:] = np.sort(uids[tri[on_tri]], axis=1)
    return names


def _rows(names: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(names, dtype=np.int64).view(_ROW).ravel()


class WarmStart:
    """The forces of the last step's contacts by name (see the module docstring)."""

    def __init__(self, names: np.ndarray | None = None, forces: np.ndarray | None = None,
                 kept: np.ndarray | None = None, distinct: bool = False):
        """``names`` (k, 4) and ``forces`` (k, 3) of the contacts, ``kept`` (k,) bool the rows to
        remember (default all; none by default); where a remembered name repeats, the last
        row's force is the one kept (as a dict built in row order). ``distinct``: the names are
        known to be distinct (see :meth:`then`)."""
        self._names = np.zeros((0, 4), np.int64) if names is None else np.array(names, np.int64).reshape(-1, 4)
        self._forces = np.zeros((0, 3)) if forces is None else np.array(forces, np.float64).reshape(-1, 3)
        self._kept = np.ones(len(self._names), bool) if kept is None else np.array(kept, bool)
        self._count = int(np.count_nonzero(self._kept))
        self._bytes = self._names.tobytes()
        self._distinct = True if distinct else None  # None: not known yet
        self._index = None  # (sorted remembered names, their forces), made at the first search
        self._matched = None  # the last query that was this step's list of names, when they are distinct

    def __len__(self) -> int:
        return self._count

    def lookup(self, names: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(found, forces): which of the contacts ``names`` (k, 4) were remembered, and their
        forces (found rows only, in order)."""
        if not self._count or not len(names):
            return np.zeros(len(names), bool), np.zeros((0, 3))
        if names.shape == self._names.shape and names.tobytes() == self._bytes:  # the same contacts, in order
            if self._distinct is None:
                sorted_rows = np.sort(_rows(self._names))
                self._distinct = not np.count_nonzero(sorted_rows[1:] == sorted_rows[:-1])
            if self._distinct:
                self._matched = names
                return self._kept.copy(), self._forces[self._kept]
        if self._index is None:
            rows = _rows(self._names[self._kept])
            order = np.argsort(rows, kind="stable")
            self._index = rows[order], self._forces[self._kept][order]
        stored, forces = self._index
        rows = _rows(names)
        at = np.searchsorted(stored, rows, side="right") - 1  # the last of equal names
        at = np.maximum(at, 0)
        found = stored[at] == rows
        return found, forces[at[found]]

    def then(self, names: np.ndarray, forces: np.ndarray, kept: np.ndarray) -> WarmStart:
        """The next step's warm start, ``WarmStart(names, forces, kept)``, knowing the names
        distinct where they are the array this one's last :meth:`lookup` matched as a whole
        (unchanged since)."""
        return WarmStart(names, forces, kept, distinct=names is self._matched)
