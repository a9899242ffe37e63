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
    # finding the debris it would leave and planning their removal into it (one change),
    # applying it to the FEM, the state and the node identities, and the preconditioner's
    # correction (its U and Q in ``smf_*``)
    plan_ms: float = 0.0
    apply_ms: float = 0.0
    correction_ms: float = 0.0
    debris_ms: float = 0.0


class Tissue:
    """What cutting reads of the body: the rest mesh, the node identities and the state on the
    nodes (copies): positions ``x``, velocities ``v``, ``free`` (1.0 free, 0.0 fixed) and ``dv``
    (the last step's velocity change, the solver's next guess, or None).

    The state is given as arrays, or as ``read``, a function returning (x, v, free, dv) that the
    first access of any of them calls: a plan that never looks at the state (a sweep screened
    on the device that cuts nothing) costs no read of it. ``read`` gives the state at the time
    of that first access: look before the body steps again. ``positions`` and ``device_tets``:
    the current positions and the mesh's tets where the body keeps them (Warp arrays on its
    device: vec3d, and vec4i in ``mesh.tets``' order), for :class:`.screen.SweepScreen`; or None."""

    def __init__(self, mesh: TetMesh, x=None, v=None, node_uids=None, free=None, dv=None, *, read=None,
                 positions=None, device_tets=None):
        self.mesh, self.node_uids, self.positions, self.device_tets = mesh, node_uids, positions, device_tets
        self._read = read
        self._state = None if read is not None else (x, v, free, dv)

    @property
    def loaded(self) -> bool:
        """Whether the state is at hand (given, or read)."""
        return self._state is not None

    def _part(self, i: int):
        if self._state is None:
            self._state = tuple(self._read())
            self._read = None
        return self._state[i]

    x = property(lambda self: self._part(0), doc="(n, 3) current positions")
    v = property(lambda self: self._part(1), doc="(n, 3) velocities")
    free = property(lambda self: self._part(2), doc="(n,) 1.0 free, 0.0 fixed")
    dv = property(lambda self: self._part(3), doc="(n, 3) the last step's velocity change, or None")


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

    def then(self, after: TopologyChange) -> TopologyChange:
        """This change followed by ``after`` (a change of this one's result) as one change of
        this one's mesh: what the simulation applies once instead of twice (the removal of the
        debris a cut leaves). Its removed tets are this one's and the original tets ``after``
        removes; its added tets, those of the final mesh that come from this one's added tets; a
        node this one creates and ``after`` removes is neither created nor removed."""
        if self.tet_source is None or after.tet_source is None:
            raise ValueError("composing topology changes needs both changes' tet sources")
        mid_added = np.zeros(self.mesh.n_tets, bool)
        mid_added[self.added_tets] = True
        gone = np.asarray(after.removed_tets, np.int64)
        kept_gone = gone[~mid_added[gone]]  # original tets (kept by this change) that ``after`` removes
        removed_tets = np.union1d(self.removed_tets, self.tet_source[kept_gone]).astype(np.int64)
        src = np.asarray(after.tet_source, np.int64)
        from_added = np.zeros(after.mesh.n_tets, bool)
        has = src >= 0
        from_added[has] = mid_added[src[has]]
        from_added[np.asarray(after.added_tets, np.int64)] = True
        added_tets = np.flatnonzero(from_added)
        tet_source = np.where(has, self.tet_source[np.maximum(src, 0)], -1)
        # the nodes created by either that the final mesh keeps, each with the original node whose
        # rotation it takes (for ``after``'s, through its source in this change's result)
        alive = np.isin(self.created, after.node_uids)
        n_old, rot = len(self.old_uids), np.asarray(self.rotation_source, np.int64)
        mid_rot = np.concatenate([np.arange(n_old), rot])[_positions(np.concatenate([self.old_uids, self.created]),
                                                                     self.node_uids)]
        created = np.concatenate([self.created[alive], after.created]).astype(np.int64)
        rotation_source = np.concatenate([rot[alive], mid_rot[np.asarray(after.rotation_source, np.int64)]])
        removed = np.union1d(self.removed, np.setdiff1d(after.removed, self.created)).astype(np.int64)
        return TopologyChange(after.mesh, after.x, after.v, after.node_uids, after.free, removed_tets, added_tets,
                              created, removed, rotation_source, self.old_uids, self.old_free, tet_source, after.dv)

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
