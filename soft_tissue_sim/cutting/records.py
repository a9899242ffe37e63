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
    ms: float = 0.0  # whole modification: planning, mesh change, correction (and, asked through the
    # Simulation's API, the state's read and the contact surface's rebuild)
    smf_u_ms: float = 0.0  # U = P^-1 G (batched triangular solves)
    smf_q_ms: float = 0.0  # Q = (I + N S)^-1 N
    surface_ms: float = 0.0  # the contact surface's rebuild (API requests; a step's is in its CutStats)
    # the parts of ``ms`` (a change applied): planning it (geometry, the new mesh and state),
    # applying it to the FEM, the state and the node identities, the preconditioner's
    # correction (its U and Q in ``smf_*``), and finding and removing the debris it left (that
    # removal's correction included; its U and Q are in ``smf_*`` too)
    plan_ms: float = 0.0
    apply_ms: float = 0.0
    correction_ms: float = 0.0
    debris_ms: float = 0.0


@dataclass
class Tissue:
    """What cutting reads of the body: the rest mesh and the state on it (copies)."""

    mesh: TetMesh
    x: np.ndarray  # (n, 3) current positions
    v: np.ndarray  # (n, 3) velocities
    node_uids: np.ndarray  # (n,) identities that survive topology changes
    free: np.ndarray  # (n,) 1.0 free, 0.0 fixed
    dv: np.ndarray | None = None  # (n, 3) the last step's velocity change (the solver's next guess), if read


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
    tet_source: np.ndarray | None = None  # per new tet, the old tet it comes from (-1: a new one)
    dv: np.ndarray | None = None  # the tissue's dv carried like v (None: the tissue had none)

    @property
    def fixed(self) -> np.ndarray:
        return np.flatnonzero(self.free == 0.0)

    def tissue(self) -> Tissue:
        """The body once this change is applied, as cutting reads it (what the simulation
        would read back from the device: the same arrays)."""
        return Tissue(self.mesh, self.x, self.v, self.node_uids, self.free, self.dv)

    def modification(self, version: int, old_blocks, new_blocks, R_nodes: np.ndarray) -> Modification:
        """The change of A (eq. 5-7) from the removed tets' element blocks (old numbering) and the
        added ones' (new numbering), with the old nodes' rotations ``R_nodes`` (a new node takes
        its source's) and free flags (an old node's from before the change)."""
        n_old = len(self.old_uids)
        R_keys = np.concatenate([self.old_uids, self.created])
        R_rows = np.concatenate([np.arange(n_old), np.asarray(self.rotation_source, np.int64)])
        free_keys = np.concatenate([self.old_uids, self.node_uids])  # an old node's flag first
        free_vals = np.concatenate([self.old_free, self.free])
        return modification_from_blocks(version, old_blocks, new_blocks, self.old_uids, self.node_uids,
                                        lambda uids: R_nodes[R_rows[_positions(R_keys, uids)]],
                                        lambda uids: free_vals[_positions(free_keys, uids)],
                                        created=self.created, removed=self.removed)


def _positions(keys: np.ndarray, query: np.ndarray) -> np.ndarray:
    """For each query value, the position of its first occurrence in ``keys``; KeyError where
    it is absent."""
    query = np.asarray(query, np.int64)
    order = np.argsort(keys, kind="stable")
    k = np.minimum(np.searchsorted(keys, query, sorter=order), max(len(keys) - 1, 0))
    if not len(keys) or np.any(keys[order[k]] != query):
        if len(query):
            raise KeyError(f"node uids unknown to the change: {query[~np.isin(query, keys)][:10].tolist()}")
        return np.zeros(0, np.int64)
    return order[k]


@dataclass
class CutPlan:
    """What a cutting request asks for: a result, and the change to apply (None: nothing to do,
    the result says why). The result's correction figures and message are completed by
    :meth:`Cutter.record` once the change is applied."""

    result: CutResult
    change: TopologyChange | None = None
    note: str = ""  # appended to the message once applied
    t0: float = 0.0  # perf_counter() when the request began (the result's ms count from it)
