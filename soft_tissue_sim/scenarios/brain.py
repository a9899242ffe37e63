"""The scripted surgeon of the brain tumour resection (paper fig. 5; scene
``config/scenes/brain_resection.yaml``): the plan of actions, one per step, and the closed
loop that finishes it. Used by ``bench brain`` and the tests.

The plan (:func:`plan`): the probe presses 6 mm into the cortex above the tumour and retracts;
the scalpel (a 12 mm vertical blade) spirals down around the tumour with the pedal down;
the tissue under the tumour is aspirated in tumour-sparing bites (:func:`spare_tumour_bite`)
in two layers above the floor of the cut, which stays; the brain settles. With a margin (the
long session), an outer spiral comes first, and radial cuts part the ring between the two
spirals into wedges. The closed loop (:class:`Surgeon`): while the tumour is attached to the
fixed base, bite on the tet of the fewest healthy tets that hold it (:func:`attachment_cut`)
closest to the tumour, one bite a step; once free, the specimen is lifted out.

Invariants: a bite never takes a tumour tet (its sphere shrinks to spare every tumour
centroid); the blade enters the tissue only through a cut already made (each stroke starts
with the pedal up and the blade above the brain); :func:`attachment_cut` is topological
(max-flow on nodes and tets) and never cuts a tumour tet.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sps
from scipy.sparse.csgraph import breadth_first_order, maximum_flow

IDENTITY = [0.0, 0.0, 0.0, 1.0]
BLADE = 0.012  # the scalpel's blade length in brain_resection.yaml [m]
PASS = 0.010  # the most a radial cut's pass goes below the last (less than the blade: passes overlap) [m]


def tumour_geometry(mesh):
    cen = mesh.centroids()[mesh.material_ids == 1]
    c = cen.mean(axis=0)
    r = float(np.max(np.linalg.norm(cen[:, :2] - c[:2], axis=1)))
    return c, r, float(cen[:, 2].min()), float(cen[:, 2].max())


def plan(mesh, turns=4, step_len=0.0012, layers=2, bite=0.0045, margin=0.0, radial=0):
    """The scripted surgeon: a list of per-step actions.

    ``margin`` > 0 adds a margin (the long session): an outer spiral cut ``margin`` outside the
    inner one before it, and after it ``radial`` radial cuts that part the ring between the
    two into wedges. Each radial cut is one stroke in its vertical plane: the blade comes in
    from above along the outer cut, then goes back and forth between the two cuts, each pass
    at most 10 mm lower (the blade is 12 mm). The blade only ever enters the tissue through a
    cut, so it is never thrust into intact tissue (a scripted pose may jump; a blade does not).
    """
    c, r, zlo, zhi = tumour_geometry(mesh)
    top = float(mesh.points[:, 2].max())
    R = r + 0.006  # cut 6 mm outside the tumour centroids
    acts = []
    probe_home = np.array([c[0] + R + 0.012, c[1], top + 0.04])
    scal_home = np.array([c[0] + R, c[1], top + 0.04])
    probe_park = probe_home + [0.03, 0, 0]
    # 1. push
    for k in range(60):
        depth = 0.006 * min(1.0, k / 20.0) if k < 40 else 0.006 * max(0.0, 1.0 - (k - 40) / 15.0)
        p = np.array([c[0], c[1], top + 0.004 - depth])
        acts.append({"probe": p if k < 58 else probe_home, "scalpel": scal_home, "cutting": False})
    # 2. spiral cut: blade from z to z + 12 mm, z from top - 10 mm down to below the tumour
    z0, z1 = top - 0.010, max(0.003, zlo - 0.014)

    def spiral(radius, out):
        n = int(np.ceil(turns * 2 * np.pi * radius / step_len))
        for k in range(n + 1):
            s = k / n
            a = 2 * np.pi * turns * s
            p = np.array([c[0] + radius * np.cos(a), c[1] + radius * np.sin(a), z0 + (z1 - z0) * s])
            acts.append({"probe": probe_park, "scalpel": p, "cutting": True})
        if out:  # pedal up, blade out (in the standard session the aspiration does it)
            acts.append({"probe": probe_park, "scalpel": scal_home, "cutting": False})

    if margin <= 0:
        spiral(R, False)
    else:  # the long session: an outer cut first, the inner one, then the margin parted into wedges
        R2 = R + margin
        spiral(R2, True)
        spiral(R, True)
        levels = np.linspace(z0, z1, int(np.ceil((z0 - z1) / PASS)) + 1)
        for j in range(int(radial)):
            u = np.array([np.cos(2 * np.pi * (j + 0.5) / radial), np.sin(2 * np.pi * (j + 0.5) / radial), 0.0])
            at = lambda rad, z: np.array([c[0], c[1], z]) + rad * u  # noqa: E731
            # in from above along the outer cut, then back and forth between the two cuts, one
            # level lower each time (the vertical moves lie in a cut already made)
            corners = [at(R2, z0 + BLADE)]
            for i, z in enumerate(levels):
                a, b = (R2, R) if i % 2 == 0 else (R, R2)
                corners += [at(a, z), at(b, z)]
            for p in polyline(corners, step_len):
                acts.append({"probe": probe_park, "scalpel": p, "cutting": True})
            acts.append({"probe": probe_park, "scalpel": scal_home, "cutting": False})
    # 3. aspiration under the tumour: bites on a disc, ring by ring, in layers (the elements are
    #    about 1 cm: one layer of bites does not part them), the lowest one layer above the
    #    cut's floor: the floor stays, and the specimen rests on it (self-contact) as it comes free
    bites = [(0.0, 0.0)]
    for ring in np.arange(0.004, R + 1e-9, 0.004):
        m = max(6, int(2 * np.pi * ring / 0.004))
        bites += [(ring * np.cos(2 * np.pi * j / m), ring * np.sin(2 * np.pi * j / m)) for j in range(m)]
    for zb in z1 + 0.003 + 0.0045 * np.arange(1, layers + 1):
        for bx, by in bites:
            acts.append({"probe": probe_park, "scalpel": scal_home, "cutting": False,
                         "remove": (np.array([c[0] + bx, c[1] + by, zb]), bite)})
    # 4. settle
    for _ in range(40):
        acts.append({"probe": probe_park, "scalpel": scal_home, "cutting": False, "phase": "settle"})
    return acts


def polyline(corners, step: float) -> list:
    """Points along a polyline, at most ``step`` apart, the corners included (not the first)."""
    out = []
    for a, b in zip(corners[:-1], corners[1:]):
        n = max(1, int(np.ceil(np.linalg.norm(b - a) / step)))
        out += [a + (b - a) * (k / n) for k in range(1, n + 1)]
    return out


def tumour_freed(sim) -> bool:
    m = sim.mesh
    T = m.tets
    lab = m.node_components()
    fixed = sim.fem.fixed_nodes
    base = set(np.unique(lab[fixed]).tolist())
    tum_nodes = np.unique(T[m.material_ids == 1])
    return not any(l in base for l in np.unique(lab[tum_nodes]).tolist())


def attachment_cut(sim) -> np.ndarray:
    """The fewest non-tumour tets whose removal parts the tumour from the fixed base.

    A minimum cut (max-flow) between the tumour's nodes and the fixed nodes in the graph of
    nodes and tets: each tet is split into an in and an out vertex joined by an arc of
    capacity 1 (healthy tissue) or "infinite" (tumour: never cut); nodes join the tets that
    hold them with infinite arcs. Returns the indices of the cut tets (empty when the tumour
    is already free). Purely topological: the bites are placed on these tets' current
    centroids.
    """
    m = sim.mesh
    T = m.tets.astype(np.int64)
    n, nt = m.n_nodes, m.n_tets
    tum = m.material_ids == 1
    tum_nodes = np.unique(T[tum])
    fixed = np.asarray(sim.fem.fixed_nodes, np.int64)
    big = 4 * nt + 1  # larger than any cut made of tets
    tin, tout = n + np.arange(nt), n + nt + np.arange(nt)
    src, snk = n + 2 * nt, n + 2 * nt + 1
    node_of = T.ravel()
    tet_of = np.repeat(np.arange(nt), 4)
    rows = np.concatenate([node_of, tout[tet_of], tin, np.full(len(tum_nodes), src), fixed])
    cols = np.concatenate([tin[tet_of], node_of, tout, tum_nodes, np.full(len(fixed), snk)])
    cap = np.concatenate([np.full(8 * nt, big), np.where(tum, big, 1), np.full(len(tum_nodes) + len(fixed), big)])
    N = n + 2 * nt + 2
    C = sps.csr_matrix((cap.astype(np.int32), (rows, cols)), shape=(N, N))
    C.sum_duplicates()
    res = maximum_flow(C, src, snk)
    if res.flow_value == 0:
        return np.zeros(0, np.int64)
    R = (C - res.flow).tocsr()
    R.data = (R.data > 0).astype(np.int8)
    R.eliminate_zeros()
    reach = np.zeros(N, bool)
    reach[breadth_first_order(R, src, directed=True, return_predecessors=False)] = True
    return np.flatnonzero(reach[tin] & ~reach[tout] & ~tum)


def specimen_tets(sim) -> np.ndarray:
    """Mask of the tets in the parts that hold tumour and no fixed node: the freed specimen."""
    m = sim.mesh
    T = m.tets
    lab = m.node_components()
    base = np.unique(lab[sim.fem.fixed_nodes])
    tum = np.unique(lab[np.unique(T[m.material_ids == 1])])
    parts = np.setdiff1d(tum, base)
    return np.isin(lab[T[:, 0]], parts)


def tumour_drop(sim) -> float:
    """How far the tumour's nodes have moved down from their rest position, on average [m]."""
    m = sim.mesh
    tn = np.unique(m.tets[m.material_ids == 1])
    return float(np.mean(m.points[tn, 2] - sim.positions()[tn, 2]))


def inverted_tets(sim) -> int:
    """Tets whose current signed volume has the opposite sign of their rest volume."""
    def vol(p):
        e = p[sim.mesh.tets][:, 1:] - p[sim.mesh.tets][:, :1]
        return np.einsum("ij,ij->i", e[:, 0], np.cross(e[:, 1], e[:, 2]))
    return int(np.sum(vol(sim.positions()) * vol(sim.mesh.points) < 0))


def spare_tumour_bite(sim, center, radius: float):
    """An aspiration bite (``remove_elements``) on a sphere, shrunk where needed so that no
    tumour tet's current centroid lies inside: the surgeon aspirates tissue, never the tumour.
    Returns the removal result and the radius used."""
    m = sim.mesh
    cen = sim.positions()[m.tets].mean(axis=1)[m.material_ids == 1]
    c = np.asarray(center, np.float64)
    r = float(radius)
    if len(cen):
        r = min(r, 0.999 * float(np.linalg.norm(cen - c, axis=1).min()))
    return sim.remove_elements(c, max(r, 1e-9)), r



class Surgeon:
    """The whole session on ``sim``: the planned actions, the closed loop, the extraction and
    the settling. An action is a dict: the probe's and the scalpel's positions (identity
    orientation), the pedal (``cutting``), and at most one removal: ``remove`` (center,
    radius) a tumour-sparing bite, ``cleanup_tet`` a bite of ``cleanup_radius`` on that tet's
    current centroid, ``extract`` the specimen lifted out; ``phase`` "settle" for the last 40
    steps. :meth:`act` carries one out before the caller's step."""

    def __init__(self, sim, turns=4, step_len=0.0012, margin=0.0, radial=0, max_cleanup=60, cleanup_radius=0.005):
        self.sim = sim
        self.acts = plan(sim.mesh, turns, step_len, margin=margin, radial=radial)
        self.max_cleanup, self.cleanup_radius = max_cleanup, cleanup_radius
        self.cleanup_bites = 0
        self.cut_sizes: list[int] = []  # the attachment cut's size before each closed-loop bite

    def planned(self) -> list[dict]:
        return [a for a in self.acts if a.get("phase") != "settle"]

    def cleanup(self) -> dict | None:
        """The next closed-loop action: while the tumour still hangs on (and bites are left), a
        bite on the tet of the attachment cut closest to the tumour, working in from it; None
        when it is free or nothing holds it."""
        sim = self.sim
        if tumour_freed(sim) or self.cleanup_bites >= self.max_cleanup:
            return None
        cut = attachment_cut(sim)
        self.cut_sizes.append(len(cut))
        if len(cut) == 0:
            return None
        x, m = sim.positions(), sim.mesh
        cen = x[m.tets[cut]].mean(axis=1)
        tc = x[np.unique(m.tets[m.material_ids == 1])].mean(axis=0)
        self.cleanup_bites += 1
        park = {k: v for k, v in self.acts[-1].items() if k != "phase"}  # instruments parked, pedal up
        return {**park, "cleanup_tet": int(cut[np.argmin(np.linalg.norm(cen - tc, axis=1))])}

    def settle(self, freed: bool) -> list[dict]:
        """The settling steps; the first lifts the specimen out if the tumour is free."""
        settle = [a for a in self.acts if a.get("phase") == "settle"]
        if freed:
            settle[0] = {**settle[0], "extract": True}
        return settle

    def act(self, a: dict):
        """Pose the instruments, set the pedal and make the action's removal. Returns its
        CutResult (None without one) and, for a closed-loop bite, (center, radius used)."""
        sim = self.sim
        sim.set_instrument_pose("probe", a["probe"], IDENTITY)
        sim.set_instrument_pose("scalpel", a["scalpel"], IDENTITY)
        sim.set_cutting(a["cutting"])
        if "remove" in a:
            return spare_tumour_bite(sim, *a["remove"])[0], None
        if "extract" in a:
            return sim.remove_tets(specimen_tets(sim)), None
        if "cleanup_tet" in a:
            c = sim.positions()[sim.mesh.tets[a["cleanup_tet"]]].mean(axis=0)  # that tet's centroid
            r, rad = spare_tumour_bite(sim, c, self.cleanup_radius)
            return r, (c, rad)
        return None, None
