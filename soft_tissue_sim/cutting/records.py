"""What cutting reads and returns: the tissue it plans on, the change the simulation applies,
and the result a caller sees.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..mesh import TetMesh
from ..sherman_morrison import Modification, modification_from_blocks


@dataclass
class CutResult:
    """What one mesh modification did."""

    changed: bool
    message: str
    tets_changed: int = 0  # removed + re-added (cut) or removed (ablation)
    nodes_added: int = 0
    nodes_removed: int = 0
    affected_nodes: int = 0  # nodes this modification changes (its own term's G)
    perturbation_nodes: int = 0  # nodes of N against the factor in use after it (paper's measure)
    faces_cut: int = 0
    debris_tets: int = 0  # tets of fragments below `min_fragment` removed after the change
    ms: float = 0.0  # whole modification, correction included
    smf_u_ms: float = 0.0  # U = P^-1 G (batched triangular solves)
    smf_q_ms: float = 0.0  # Q = (I + N S)^-1 N


@dataclass
class Tissue:
    """What cutting reads of the body: the rest mesh and the state on it (copies)."""

    mesh: TetMesh
    x: np.ndarray  # (n, 3) current positions
    v: np.ndarray  # (n, 3) velocities
    node_uids: np.ndarray  # (n,) identities that survive topology changes
    free: np.ndarray  # (n,) 1.0 free, 0.0 fixed


@dataclass
class TopologyChange:
    """A change of the mesh for the simulation to apply (paper section 3.1): the new mesh and
    the state on it, and what the preconditioner's correction needs to know of it.

    New nodes come after the old ones (a node on an edge, or a copy of a node: its rest and
    current position and its velocity follow the displacement field exactly); a removal
    compacts the numbering. ``removed_tets`` (old numbering) and ``added_tets`` (new
    numbering) are the elements whose blocks leave and enter A."""

    mesh: TetMesh
    x: np.ndarray
    v: np.ndarray
    node_uids: np.ndarray
    free: np.ndarray
    removed_tets: np.ndarray
    added_tets: np.ndarray
    created: np.ndarray  # uids of the new nodes
    removed: np.ndarray  # uids of the deleted nodes
    rotation_source: np.ndarray  # per new node, the old node (index) whose rotation it takes
    old_uids: np.ndarray  # the numbering before
    old_free: np.ndarray

    @property
    def fixed(self) -> np.ndarray:
        return np.flatnonzero(self.free == 0.0)

    def modification(self, version: int, old_blocks, new_blocks, R_nodes: np.ndarray) -> Modification:
        """The change of A (eq. 5-7) from the removed tets' element blocks (old numbering) and the
        added ones' (new numbering), with the old nodes' rotations ``R_nodes`` (a new node takes
        its source's)."""
        R_index = dict(zip(self.old_uids.tolist(), range(len(self.old_uids))))
        R_index.update((int(u), R_index[int(self.old_uids[s])]) for u, s in zip(self.created, self.rotation_source))
        free = dict(zip(self.node_uids.tolist(), self.free.tolist()))
        free.update(zip(self.old_uids.tolist(), self.old_free.tolist()))
        return modification_from_blocks(version, old_blocks, new_blocks, self.old_uids, self.node_uids,
                                        lambda uids: np.stack([R_nodes[R_index[u]] for u in uids.tolist()]),
                                        lambda uids: np.array([free[u] for u in uids.tolist()]),
                                        created=self.created, removed=self.removed)


@dataclass
class CutPlan:
    """What a cutting request asks for: a result, and the change to apply (None: nothing to do,
    the result says why). The result's correction figures and message are completed by
    :meth:`Cutter.record` once the change is applied."""

    result: CutResult
    change: TopologyChange | None = None
    note: str = ""  # appended to the message once applied
    t0: float = 0.0  # perf_counter() when the request began (the result's ms count from it)
