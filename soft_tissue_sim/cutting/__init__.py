"""Cutting and element removal by incremental mesh change (paper section 3.1, fig. 1).

Two schemes (``cutting: {scheme: split | subdivide}``); both remove the tets a cut touches,
re-create them with new connectivity and add them back (the paper's three steps), and end by
node splitting: at each node of a separated face, every group of its tets still connected
through uncut faces beyond the first gets its own copy of the node.

- ``split`` (default): the blade's triangles (the quad its segment swept, or a scripted plane
  patch) separate the existing interior faces between tets on opposite sides of their plane,
  one of them crossed. No tet is subdivided; the cut follows faces within an element.
- ``subdivide`` (progressive, after Mor & Kanade): every mesh edge the blade crosses gets a
  node at the crossing and the tets around it are bisected there (conforming); a crossing
  within ``snap`` of an end snaps to it. A stroke remembers its nodes on the cut; a face is
  separated once its three nodes are on the cut and its two tets lie on opposite sides.

Element removal (ablation, aspiration, extraction) deletes tets; nodes left without a tet go.

The :class:`Cutter` (:mod:`.cutter`) plans on a :class:`Tissue` snapshot and returns a :class:`CutPlan`: a
:class:`TopologyChange` that the simulation applies, or a refusal. Once applied, the change
of A goes to the Sherman-Morrison correction of the preconditioner (eq. 5-12,
:mod:`soft_tissue_sim.sherman_morrison`). Invariants: a change is applied whole or not at all;
no tet below ``min_quality`` and no node without a tet is created; new nodes come after the
old ones at an interpolated rest and current position and velocity (the displacement field,
mass and momentum are unchanged), and node uids survive every change.
"""

from .cutter import CORRECTIONS, DEFAULT_SNAP, SCHEMES, Cutter
from .geometry import sweep_triangles, tets_cut_by_triangle
from .records import CutPlan, CutResult, Tissue, TopologyChange

__all__ = ["CORRECTIONS", "DEFAULT_SNAP", "SCHEMES", "Cutter", "CutPlan", "CutResult", "Tissue", "TopologyChange",
           "sweep_triangles", "tets_cut_by_triangle"]
