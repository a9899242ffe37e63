"""Node splitting: the two sides of the cut faces separate (paper section 3.1).

At each node of a cut face, the node's tets are grouped into the sets that stay connected
through uncut faces; every group beyond the first gets a copy of the node, numbered after
the old nodes. Invariants: no tet changes shape; a node whose tets all stay connected is not
copied; where the cut stops, the tets around its tip stay connected.
"""

from __future__ import annotations

import numpy as np

from ..mesh import edge_components


def split_along_faces(tets: np.ndarray, cut_pairs: np.ndarray, cut_nodes_of_faces: np.ndarray,
                      all_pairs: np.ndarray, all_face_nodes: np.ndarray, n_nodes: int, cut: np.ndarray | None = None):
    """Duplicate the nodes of the cut faces so that the two sides separate.

    ``cut``: where known, the mask of the cut faces among all the interior faces (the cut
    faces are then ``all_pairs[cut]``, ``all_face_nodes[cut]``); else the cut faces are found
    among them by their nodes.

    Returns (new_tets, source) where ``source`` (n_new,) gives, for each added node, the node it
    copies; new nodes are numbered from ``n_nodes`` on. Where no node is copied (the cut faces
    separate nothing yet), ``new_tets`` is ``tets`` itself, not a copy.
    """
    cut_nodes = np.unique(cut_nodes_of_faces)
    if not len(cut_nodes):
        return tets, np.zeros(0, np.int64)
    is_cut_node = np.zeros(n_nodes, bool)
    is_cut_node[cut_nodes] = True
    # incidences (node, tet) at cut nodes: vertices of a graph
    flat = np.flatnonzero(is_cut_node[tets])  # 4 t + k: node k of tet t, in that order
    t_idx, k_idx = flat >> 2, flat & 3
    inc_node = np.take(tets, flat).astype(np.int64)
    m = len(tets)
    keys = inc_node * m + t_idx
    order = np.argsort(keys)
    keys_sorted = keys[order]
    # edges: through each uncut interior face, for each of its cut nodes, (v, a) - (v, b)
    at = is_cut_node[all_face_nodes]
    near = np.flatnonzero(at[:, 0] | at[:, 1] | at[:, 2])  # the faces at a cut node
    cut_set = np.zeros(len(near), bool)
    if cut is not None:
        cut_set = cut[near]
    elif len(cut_pairs):
        # mark faces listed as cut (compare by sorted node triples)
        fn = all_face_nodes[near]
        fk = fn[:, 0] * (n_nodes ** 2) + fn[:, 1] * n_nodes + fn[:, 2]
        ck = cut_nodes_of_faces[:, 0] * (n_nodes ** 2) + cut_nodes_of_faces[:, 1] * n_nodes + cut_nodes_of_faces[:, 2]
        cut_set = np.isin(fk, ck)
    unc = near[~cut_set]
    unc_pairs, unc_nodes = all_pairs[unc], all_face_nodes[unc]
    ea, eb = [], []
    for c in range(3):
        v = unc_nodes[:, c].astype(np.int64)
        sel = is_cut_node[v]
        ka = v[sel] * m + unc_pairs[sel, 0]
        kb = v[sel] * m + unc_pairs[sel, 1]
        ea.append(order[np.searchsorted(keys_sorted, ka)])
        eb.append(order[np.searchsorted(keys_sorted, kb)])
    ea, eb = np.concatenate(ea), np.concatenate(eb)
    nv = len(keys)
    label = edge_components(nv, ea, eb)
    # per node its groups, as (node, part) packed and sorted (parts numbered in the order of
    # their lowest incidence): the first keeps the node, each other one gets a copy (numbered
    # in this order)
    group = inc_node * nv + label
    groups = np.unique(group)
    node = groups // nv
    extra = groups[1:][node[1:] == node[:-1]]
    source = extra // nv
    if not len(extra):
        return tets, source
    # relabel the incidences of the extra groups in a copy
    new_tets = tets.copy()
    pos = np.minimum(np.searchsorted(extra, group), len(extra) - 1)
    hit = extra[pos] == group
    new_tets[t_idx[hit], k_idx[hit]] = n_nodes + pos[hit]
    return new_tets, source
