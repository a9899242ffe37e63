"""The contacts of one step as a record of arrays (one row per contact).

A row is a tissue node against an object (``tri`` -1), a tissue node against a tissue
triangle (self-collision: ``obj`` -1, the node and the triangle's nodes), or a tissue triangle
against an instrument (``node`` -1, the tissue point sum_i bary_i x[tri_i]). Invariants:
every array has the same number of rows; ``normal`` is a unit vector pointing the way the
tissue is pushed; ``gap`` < 0 is a penetration; ``bary`` sums to 1 on rows with a triangle.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Any

import numpy as np
import warp as wp

from ..stats import ContactStats

DETECTED = ("node", "obj", "gap", "normal", "point", "tri", "bary")  # the fields detection fills


@dataclass
class Contacts:
    """Contacts, one row per contact. ``lambda_n`` and ``force`` are set by the response."""

    node: np.ndarray  # (k,) int64: the tissue node, -1 on a tissue triangle's row
    obj: np.ndarray  # (k,) int64: index of the object in ContactSolver.objects, -1 for self-collision
    gap: np.ndarray  # (k,) delta^0 [m]
    normal: np.ndarray  # (k, 3)
    point: np.ndarray  # (k, 3) on the other surface [m]
    tri: np.ndarray  # (k, 3) int64: the triangle's nodes, -1 where none
    bary: np.ndarray  # (k, 3) the barycentric weights on ``tri``
    lambda_n: np.ndarray | None = None  # (k,) normal force [N]
    force: np.ndarray | None = None  # (k, 3) force ON THE TISSUE [N], world frame

    @classmethod
    def empty(cls, responded: bool = False) -> Contacts:
        """No contacts (with empty ``lambda_n`` and ``force`` where ``responded``)."""
        z3 = np.zeros((0, 3))
        return cls(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0), z3, z3.copy(),
                   np.zeros((0, 3), np.int64), z3.copy(), *((np.zeros(0), z3.copy()) if responded else ()))

    @classmethod
    def concat(cls, parts: list[Contacts]) -> Contacts:
        """The rows of ``parts`` in order (detection results: no response yet)."""
        if not parts:
            return cls.empty()
        return cls(**{name: np.concatenate([getattr(p, name) for p in parts]) for name in DETECTED})

    def take(self, rows) -> Contacts:
        """The contacts selected by a boolean mask or indices."""
        ln, f = self.lambda_n, self.force
        return Contacts(self.node[rows], self.obj[rows], self.gap[rows], self.normal[rows], self.point[rows],
                        self.tri[rows], self.bary[rows], None if ln is None else ln[rows],
                        None if f is None else f[rows])

    def responded(self, lambda_n: np.ndarray, force: np.ndarray) -> Contacts:
        """These contacts (the same arrays) with the response's normal forces and forces on the tissue."""
        return Contacts(self.node, self.obj, self.gap, self.normal, self.point, self.tri, self.bary, lambda_n, force)

    def __len__(self) -> int:
        return len(self.node)

    def items(self):
        """(name, array) of the fields that are set, the way the earlier dicts were read."""
        return [(name, getattr(self, name)) for name in _FIELDS if getattr(self, name) is not None]

    def __getitem__(self, name: str) -> np.ndarray:
        """A field by name (read access for code written against the earlier dicts)."""
        if name not in _FIELDS:
            raise KeyError(name)
        return getattr(self, name)


_FIELDS = tuple(f.name for f in fields(Contacts))


@dataclass
class ContactResponse:
    """What one contact step changes: the correction of the free motion, which the caller
    applies as x += dx, v += dx / dt (None: no contact), and its statistics."""

    dx: np.ndarray | wp.array | None  # (n, 3) [m] (a (n,) vec3d device array on a GPU), zero on fixed nodes
    stats: ContactStats
    device: Any = None  # a contact.device_lcp.PendingLCP where the LCP is solved with the correction (dx None)
