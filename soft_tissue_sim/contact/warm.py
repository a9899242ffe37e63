"""Warm start of the contact LCP: the last step's forces, found again by the contact's name.

A contact is named by its object and the tissue nodes it involves, by their uids (stable
across cuts): (object, node) for a node's contact, (object, the triangle's three nodes sorted)
for a triangle's. Names are rows of four integers, (obj, uid, -1, -1) or (obj, u0, u1, u2)
(uids are >= 0, so the two kinds never meet), matched as whole rows through a sorted byte view
rather than one Python dict look-up per contact.
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

    def __init__(self, names: np.ndarray | None = None, forces: np.ndarray | None = None):
        """``names`` (k, 4) and ``forces`` (k, 3) of the contacts to remember (none by default);
        where a name repeats, the last row's force is the one kept (as a dict built in row order)."""
        names = np.zeros((0, 4), np.int64) if names is None else names
        rows = _rows(names)
        order = np.argsort(rows, kind="stable")
        self._sorted = rows[order]
        self._forces = (np.zeros((0, 3)) if forces is None else np.asarray(forces, np.float64))[order]

    def __len__(self) -> int:
        return len(self._sorted)

    def lookup(self, names: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(found, forces): which of the contacts ``names`` (k, 4) were remembered, and their
        forces (found rows only, in order)."""
        if not len(self._sorted) or not len(names):
            return np.zeros(len(names), bool), np.zeros((0, 3))
        rows = _rows(names)
        at = np.searchsorted(self._sorted, rows, side="right") - 1  # the last of equal names
        at = np.maximum(at, 0)
        found = self._sorted[at] == rows
        return found, self._forces[at[found]]
