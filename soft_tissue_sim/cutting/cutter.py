"""The cutting component of a scene (:class:`Cutter`): its options, the blade's strokes,
scripted cuts and element removal, planned on a :class:`~.records.Tissue` and returned as
:class:`~.records.CutPlan`; the simulation applies the change and the cutter records it in the
Sherman-Morrison correction of the preconditioner (eq. 5-12).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from functools import partial

import numpy as np

from ..material import ParameterError
from ..mesh import (TetMesh, all_four, centroids, edge_table_after_change, extent, interior_faces_after_removal,
                    interior_faces_after_split, tet_quality)
from ..sherman_morrison import Modification
from ..stats import CUT_PARTS, CutStats
from .geometry import _path_planes, faces_cut_by_triangles, load_kernels, sweep_triangles, tets_near_box
from .records import CutPlan, CutResult, Tissue, TopologyChange
from .screen import SweepScreen
from .subdivision import CutState, faces_on_cut, subdivide_for_cut
from .topology import split_along_faces

CORRECTIONS = ("sherman_morrison", "none")
SCHEMES = ("split", "subdivide")
DEFAULT_SNAP = 0.35  # subdivide: a crossing within this fraction of its edge snaps to the end


@dataclass
class _Stroke:
    """What a stroke (successive sweeps) remembers: the uids of the nodes on its cut with their
    state, and the last sweep's mean normal (to orient the next one)."""

    uids: np.ndarray
    state: CutState
    last: np.ndarray | None


def _vec3(v, what):
    a = np.asarray(v, dtype=np.float64)
    if a.shape != (3,) or not np.all(np.isfinite(a)):
        raise ParameterError(f"{what} must be 3 finite numbers, got {v!r}")
    return a


def _carry_tables(mesh: TetMesh, new_mesh: TetMesh, removed_tets, added_tets, node_id, kept=None,
                  copies=None) -> None:
    """Give ``new_mesh`` the connectivity tables derived from ``mesh``'s, where those are at
    hand: its interior faces (the split scheme reads them) where the change is one their
    derivation covers, an element removal (``kept``: the kept tets' mask and the kept nodes)
    or a node split (``copies``: the old node each appended node copies); its edge table (the
    contact surface and the fragment check read it) for any change, from the tets taken out
    (``removed_tets``, old numbering), the node renumbering ``node_id`` and the tets put in
    (``added_tets``). Otherwise the new mesh computes a table when first asked."""
    faces = mesh.cached_interior_faces()
    derived = None
    if faces is not None and kept is not None:
        derived = interior_faces_after_removal(faces, kept[0], kept[1], mesh.n_nodes)
    elif faces is not None and copies is not None:
        derived = interior_faces_after_split(faces, mesh.tets, new_mesh.tets,
                                             np.concatenate([np.arange(mesh.n_nodes), copies]))
    if derived is not None:
        new_mesh.set_interior_faces(derived)
    table = mesh.cached_edge_table()
    if table is not None:
        table = edge_table_after_change(table, removed_tets, added_tets, node_id, new_mesh.n_nodes)
    if table is not None:
        new_mesh.set_edge_table(table)


class Cutter:
    """Cutting machinery of a scene: blade cuts, element removal, scripted cuts, and the
    preconditioner correction. Scene keys (all optional)::

        cutting:
          instrument: scalpel              # the instrument whose blade cuts (contact's instruments)
          correction: sherman_morrison     # sherman_morrison | none (only identity padding, eq. 10)
          min_quality: 0.01                # quality floor of the tets a cut creates (1 = regular)
          tolerance: 1.0e-9                # geometric tolerance [m]
          min_fragment: 5                  # a free fragment of fewer tets that a change leaves is
                                           # removed as debris (0: keep every fragment)
          scheme: split                    # split: separate along existing faces (node splitting);
                                           # subdivide: split the crossed edges first (Mor-Kanade)
          snap: 0.35                       # subdivide: a crossing closer than this fraction of
                                           # its edge to an end snaps to that end (no slivers)
          lead: 0.001                      # subdivide: a sweep cuts this far ahead of the blade's
                                           # axis [m] (default: twice the instrument's radius)
          script:                          # planned cuts: a plane patch that advances every few steps
            {frame: rest, start_step: 1, every: 3, count: 40,
             origin: [x, y, z], edge: [ex, ey, ez], direction: [dx, dy, dz], advance: 0.01}
    """

    def __init__(self, cfg, preconditioner=None):
        """``preconditioner``: the scene's; a factor that takes a correction (the asynchronous
        LDL^T) gets this cutter's Sherman-Morrison correction installed. Raises ParameterError."""
        cfg = dict(cfg) if isinstance(cfg, dict) else {}
        unknown = set(cfg) - {"instrument", "correction", "min_quality", "tolerance", "script", "enabled",
                            "min_fragment", "scheme", "snap", "lead"}
        if unknown:
            raise ParameterError(f"unknown cutting keys: {sorted(unknown)}")
        self.instrument = cfg.get("instrument")
        self.correction_mode = str(cfg.get("correction", "sherman_morrison"))
        if self.correction_mode not in CORRECTIONS:
            raise ParameterError(f"cutting correction must be one of {CORRECTIONS}, got {self.correction_mode!r}")
        self.min_quality = float(cfg.get("min_quality", 0.01))
        if not 0.0 < self.min_quality < 1.0:
            raise ParameterError(f"cutting min_quality must be in (0, 1), got {self.min_quality}")
        self.tolerance = float(cfg.get("tolerance", 1e-9))
        if not (self.tolerance >= 0.0 and np.isfinite(self.tolerance)):
            raise ParameterError(f"cutting tolerance must be >= 0, got {self.tolerance}")
        mf = cfg.get("min_fragment", 5)
        if isinstance(mf, bool) or not isinstance(mf, int) or mf < 0:
            raise ParameterError(f"cutting min_fragment must be an integer >= 0, got {mf!r}")
        self.min_fragment = mf
        self.scheme = str(cfg.get("scheme", "split"))
        if self.scheme not in SCHEMES:
            raise ParameterError(f"cutting scheme must be one of {SCHEMES}, got {self.scheme!r}")
        self.snap = float(cfg.get("snap", DEFAULT_SNAP))
        if not 0.0 < self.snap < 0.5:
            raise ParameterError(f"cutting snap must be in (0, 0.5), got {self.snap}")
        lead = cfg.get("lead")
        if lead is not None and not (isinstance(lead, (int, float)) and np.isfinite(lead) and lead >= 0.0):
            raise ParameterError(f"cutting lead must be a distance >= 0 [m], got {lead!r}")
        self.lead = None if lead is None else float(lead)
        self.script = self._parse_script(cfg.get("script"))
        if self.scheme == "split":  # the faces a sweep cuts are found by a kernel on the CPU (first cut mid-run)
            load_kernels()
        self.active = False
        self.screen = None  # screen the blade's sweeps on the body's device: None on a GPU, True also on the CPU
        self._sweep_screen = None  # the sweep screen of the body's device (made at the first sweep there)
        self.correction = None
        inner = getattr(preconditioner, "inner", None)
        if inner is not None and hasattr(inner, "make_correction"):
            self.correction = inner.make_correction(enabled=self.correction_mode == "sherman_morrison",
                                                    rotate=bool(getattr(inner, "rotate", True)))
        self._reset_counters()

    def _reset_counters(self):
        self._strokes: dict[str, _Stroke] = {}  # subdivide: each stroke's cut state
        self.modifications = 0
        self.history: list[CutResult] = []
        self._blade_at_last_cut = None
        self._script_done = 0

    @staticmethod
    def _parse_script(s):
        if not s:
            return None
        if not isinstance(s, dict):
            raise ParameterError(f"cutting script must be a mapping, got {s!r}")
        out = {
            "frame": str(s.get("frame", "rest")),
            "start_step": int(s.get("start_step", 1)),
            "every": int(s.get("every", 3)),
            "count": int(s.get("count", 10)),
            "origin": _vec3(s.get("origin"), "cutting script origin"),
            "edge": _vec3(s.get("edge"), "cutting script edge"),
            "direction": _vec3(s.get("direction"), "cutting script direction"),
            "advance": float(s.get("advance", 0.01)),
        }
        if out["frame"] not in ("rest", "world"):
            raise ParameterError(f"cutting script frame must be rest or world, got {out['frame']!r}")
        if out["every"] < 1 or out["count"] < 0 or not out["advance"] > 0.0:
            raise ParameterError("cutting script needs every >= 1, count >= 0 and advance > 0")
        nrm = np.linalg.norm(out["direction"])
        if not nrm > 0.0:
            raise ParameterError("cutting script direction must be non-zero")
        out["direction"] = out["direction"] / nrm
        return out

    def scripted_triangles(self, k: int) -> np.ndarray:
        """Blade triangles of the k-th scripted cut: the patch from k*advance to (k+1)*advance,
        reaching back a little over the previous one so consecutive cuts join."""
        s = self.script
        d, e = s["direction"], s["edge"]
        a = max(0.0, (k - 0.25) * s["advance"])
        b = (k + 1) * s["advance"]
        p0 = s["origin"] + a * d
        q0 = s["origin"] + b * d
        return sweep_triangles(p0, p0 + e, q0, q0 + e)

    def _screen(self, tissue: Tissue):
        """The sweep screen of the device where ``tissue`` keeps its positions and tets
        (:attr:`screen`: None, a GPU's; True, any device's; False, none), or None: the plan then
        reads the state and tests on the host."""
        pos = tissue.positions
        if pos is None or tissue.device_tets is None or self.screen is False or (
                self.screen is None and not pos.device.is_cuda):
            return None
        if self._sweep_screen is None or self._sweep_screen.device != pos.device:
            self._sweep_screen = SweepScreen(pos.device)
        return self._sweep_screen

    # ----------------------------------------------------------------- API
    def set_active(self, active: bool) -> None:
        self.active = bool(active)

    def reset(self) -> None:
        self._reset_counters()
        self.active = False
        if self.correction is not None:
            self.correction.clear()

    @staticmethod
    def _state_of(st: _Stroke | None, node_uids) -> CutState:
        """A stroke's cut state over the current nodes (by uid; nodes it never met are off it)."""
        state = CutState.empty(len(node_uids))
        if st is not None and len(st.uids):
            order = np.argsort(st.uids)
            k = np.minimum(np.searchsorted(st.uids, node_uids, sorter=order), len(order) - 1)
            hit = st.uids[order[k]] == node_uids
            src = order[k[hit]]
            state.on[hit], state.normals[hit], state.offsets[hit] = True, st.state.normals[src], st.state.offsets[src]
        return state

    def _lead(self, inst) -> float:
        """How far ahead of its axis a sweep of the blade cuts (subdivide): the blade's capsule
        pushes the tissue it meets, so an edge ahead of a slow blade slides along in front of it
        and is never crossed. Default: twice the capsule's radius."""
        if self.lead is not None:
            return self.lead
        if self.scheme != "subdivide":
            return 0.0
        return 2.0 * float(getattr(inst, "radius", 0.0))

    def _instrument(self, instruments):
        """The cutting instrument and its blade's world end points: the (named) instrument of
        ``instruments`` (a mapping name -> instrument) that has a blade, as (instrument,
        (p0, p1)), or None."""
        for inst in (instruments or {}).values():
            if self.instrument is None or getattr(inst, "name", None) == self.instrument:
                fn = getattr(inst, "blade_world", None)
                blade = fn() if fn is not None else None
                if blade is not None:
                    return inst, tuple(np.asarray(p, dtype=np.float64) for p in blade)
        return None

    def cut(self, tissue: Tissue, instruments) -> CutPlan:
        """Cut along the blade's path since the last cut (or since the blade was first seen)."""
        found = self._instrument(instruments)
        if found is None:
            return CutPlan(CutResult(False, "no instrument with a blade in this scene: nothing to cut with"))
        inst, blade = found
        prev = self._blade_at_last_cut
        self._blade_at_last_cut = blade
        if prev is None:
            self._strokes.pop("blade", None)  # a new stroke of the blade
            return CutPlan(CutResult(False, "blade position recorded; the next cut follows its path from here"))
        q0, q1 = blade
        d = 0.5 * ((q0 - prev[0]) + (q1 - prev[1]))
        lead, dn = self._lead(inst), float(np.linalg.norm(d))
        if lead > 0.0 and dn > 0.0:  # cut what the blade's capsule reaches ahead of its axis
            q0, q1 = q0 + lead * d / dn, q1 + lead * d / dn
        return self.cut_triangles(tissue, sweep_triangles(prev[0], prev[1], q0, q1), frame="world", stroke="blade")

    def blade_triangles(self, instruments) -> np.ndarray | None:
        """The blade where it is now, as two triangles (2, 3, 3), world frame, or None without a
        blade: its segment widened by the instrument's radius to both sides along the tool's x
        axis (the flat of the blade is the tool's x-z plane; the tool's y axis for a blade along x)."""
        found = self._instrument(instruments)
        if found is None:
            return None
        inst, (p0, p1) = found
        axis = p1 - p0
        axis = axis / np.linalg.norm(axis)
        pose = getattr(inst, "pose", None)
        R = np.eye(3) if pose is None else np.asarray(pose.R, dtype=np.float64)
        side = R[:, 0] - (R[:, 0] @ axis) * axis
        if np.linalg.norm(side) < 1e-6:  # blade along the tool's x axis
            side = R[:, 1] - (R[:, 1] @ axis) * axis
        side *= float(getattr(inst, "radius", 0.0)) / np.linalg.norm(side)
        return sweep_triangles(p0 - side, p1 - side, p0 + side, p1 + side)

    def cut_at_blade(self, tissue: Tissue, instruments) -> CutPlan:
        """One cut where the blade is now (:meth:`blade_triangles`), not a sweep: a stab incision
        as wide as the instrument, through the tissue the blade is in."""
        tris = self.blade_triangles(instruments)
        if tris is None:
            return CutPlan(CutResult(False, "no instrument with a blade in this scene: nothing to cut with"))
        return self.cut_triangles(tissue, tris, frame="world")

    def step(self, step_count: int, instruments) -> list:
        """The modifications due at step ``step_count``, in order: the scripted cut due now, then
        the blade's sweep while cutting is active. Each is a function of the tissue (planned on
        the tissue the previous one left) returning a :class:`CutPlan`."""
        ops = []
        s = self.script
        if s is not None and self._script_done < s["count"]:
            k = step_count - s["start_step"]
            if k >= 0 and k % s["every"] == 0:
                ops.append(partial(self.cut_triangles, triangles=self.scripted_triangles(self._script_done),
                                   frame=s["frame"], stroke="script"))
                self._script_done += 1
        if self.active:
            ops.append(partial(self.cut, instruments=instruments))
        else:
            self._blade_at_last_cut = None  # a pedal press starts a new path
        return ops

    def step_stats(self, results: list[CutResult]) -> CutStats:
        """The statistics of one step's modifications (their results once applied)."""
        done = [r for r in results if r.changed]
        return CutStats(cuts=self.modifications, tets_changed=sum(r.tets_changed for r in done),
                        affected_nodes=sum(r.affected_nodes for r in done), cut_ms=sum(r.ms for r in results),
                        smf_u_ms=sum(r.smf_u_ms for r in done), smf_q_ms=sum(r.smf_q_ms for r in done),
                        **{k: sum(getattr(r, k) for r in done) for k in CUT_PARTS})

    # ------------------------------------------------------------- cutting
    def cut_triangles(self, tissue: Tissue, triangles, frame: str = "world", stroke: str | None = None) -> CutPlan:
        """Cut along blade triangles (k, 3, 3), given in the current (world) or rest frame.

        ``subdivide``: first the crossed edges are split and their tets bisected
        (:func:`subdivide_for_cut`); then, on that mesh, the faces whose nodes are all on the
        cut are split as in the ``split`` scheme (:func:`faces_on_cut`,
        :func:`split_along_faces`). Where the blade is still inside an element the refinement
        alone is the modification: the crack opens once the blade has passed a whole face.
        ``stroke`` names a cut made of successive sweeps (the blade while the pedal is down, a
        script): the nodes on its cut are remembered between sweeps (the per-element cut state
        of progressive cutting); None: this call alone."""
        t0 = time.perf_counter()
        tris = np.asarray(triangles, dtype=np.float64).reshape(-1, 3, 3)
        if not np.all(np.isfinite(tris)):
            return CutPlan(CutResult(False, "blade has non-finite coordinates: no cut"))
        if frame not in ("world", "rest"):
            raise ValueError(f"frame must be 'world' or 'rest', got {frame!r}")

        def ms():
            return 1000.0 * (time.perf_counter() - t0)

        tris, tri_n = _path_planes(tris)  # the non-degenerate triangles and their normals
        if not len(tris):
            return CutPlan(CutResult(False, "the blade swept no area: no cut", ms=ms()))
        mesh = tissue.mesh
        n = mesh.n_nodes
        tets = mesh.tets.astype(np.int64)
        tol = self.tolerance + 1e-9 * extent(mesh.points)
        if self.scheme == "subdivide":
            pts = tissue.x if frame == "world" else mesh.points
            st = self._strokes.get(stroke) if stroke is not None else None
            ref = st.last if st is not None else (tri_n[0] if len(tri_n) else None)
            if ref is not None:  # orient the blade's normals along the stroke (the motion may reverse)
                tri_n = tri_n * np.where(tri_n @ ref < 0.0, -1.0, 1.0)[:, None]
            work, parent, fresh, ea, eb, et, state = subdivide_for_cut(
                pts, tets, tris, self.snap, tol, self._state_of(st, tissue.node_uids), tri_n)
            P = np.concatenate([pts, (1.0 - et)[:, None] * pts[ea] + et[:, None] * pts[eb]])
            pairs, fnodes, cut = faces_on_cut(P, work, state)
            if stroke is not None:  # the old nodes on the cut, whatever happens below (new ones added on commit)
                m = tri_n.sum(axis=0)
                on_old = state.on[:n]
                self._strokes[stroke] = _Stroke(tissue.node_uids[on_old], state.take(np.flatnonzero(on_old)),
                                                m / np.linalg.norm(m) if np.linalg.norm(m) > 0 else ref)
        else:
            work, parent, fresh = tets, np.arange(len(tets)), np.zeros(len(tets), bool)
            ea, eb, et = np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0)
            screen = self._screen(tissue) if frame == "world" else None
            cut = None
            if screen is not None:
                cut = screen.faces_cut(tissue.positions, tissue.device_tets, mesh, tris, tri_n, tol)
            if cut is None:
                pairs, fnodes, cut = faces_cut_by_triangles(tissue.x if frame == "world" else mesh.points, work, tris,
                                                            tol, faces=mesh.interior_faces(), normals=tri_n)
            else:
                pairs, fnodes = mesh.interior_faces()[:2]
        new_tets, dup = work, np.zeros(0, np.int64)
        if cut.any():
            new_tets, dup = split_along_faces(work, pairs[cut], fnodes[cut], pairs, fnodes, n + len(ea), cut=cut)
        if not len(ea) and not len(dup):
            if not cut.any():
                return CutPlan(CutResult(False, "the blade crossed no tissue (no uncut face on its path): nothing "
                                         "changed", ms=ms()))
            return CutPlan(CutResult(False, "the cut faces do not separate anything yet (the blade only grazed the "
                                     "tissue): nothing changed", faces_cut=int(cut.sum()), ms=ms()))
        # new nodes: the edge nodes, then the copies (of old or of edge nodes), as (a, b, t) of old nodes
        ext_a, ext_b = np.concatenate([np.arange(n), ea]), np.concatenate([np.arange(n), eb])
        ext_t = np.concatenate([np.zeros(n), et])
        a, b, t = (np.concatenate([ea, ext_a[dup]]), np.concatenate([eb, ext_b[dup]]),
                   np.concatenate([et, ext_t[dup]]))
        same = ~fresh & all_four(np.equal(new_tets, tets if self.scheme == "split" else tets[parent]))
        kept = np.zeros(len(tets), bool)
        kept[parent[same]] = True
        removed_ids = np.flatnonzero(~kept)
        what = "cut (subdivision)" if len(ea) else "cut"
        note = " (refined inside the elements the blade is crossing, not separated yet)" if len(ea) and not len(dup) else ""
        plan = self._change(tissue, new_tets, (a, b, t), removed_ids, np.flatnonzero(~same), keep=np.arange(n),
                            mats=mesh.material_ids[parent], what=what, note=note, t0=t0,
                            tet_source=np.where(fresh, -1, parent))
        plan.result.faces_cut = int(cut.sum())
        if plan.change is not None and stroke is not None and self.scheme == "subdivide":
            # every new node is on the cut: the crossings and the copies of nodes of cut faces
            st = self._strokes[stroke]
            added = state.take(np.concatenate([np.arange(n, n + len(ea)), dup]))  # edge nodes, then copies
            st.uids = np.concatenate([st.uids, plan.change.node_uids[n:]])  # (debris is removed after)
            st.state = st.state.extended(added)
        return plan

    def remove_elements(self, tissue: Tissue, center, radius: float, frame: str = "world") -> CutPlan:
        """Ablation / aspiration: delete the tets whose centroid lies within ``radius`` of ``center``."""
        t0 = time.perf_counter()
        c = np.asarray(center, dtype=np.float64)
        if c.shape != (3,) or not np.all(np.isfinite(c)) or not (float(radius) > 0.0):
            return CutPlan(CutResult(False, f"element removal needs a finite center and radius > 0, got {center!r}, "
                                     f"{radius!r}"))
        mesh = tissue.mesh
        pts = tissue.x if frame == "world" else mesh.points
        # a centroid lies in its tet's box: only the tets whose nodes are not all beyond one
        # face of the sphere's box (a little widened against rounding) can have it inside
        r = float(radius)
        widen = 1e-9 * (r + float(np.abs(c).max()))
        cand = tets_near_box(pts, mesh.tets, c - r - widen, c + r + widen)
        gone = np.zeros(mesh.n_tets, bool)
        gone[cand[np.linalg.norm(centroids(pts, mesh.tets[cand]) - c, axis=1) <= r]] = True
        if not gone.any():
            return CutPlan(CutResult(False, "no element within the removal sphere: nothing changed"))
        return self._removal(tissue, gone, t0)

    def remove_tets(self, tissue: Tissue, tets) -> CutPlan:
        """Delete given tets (a boolean mask over the tets or their indices): the extraction of
        a part cut free (a resected specimen), or any removal decided outside."""
        t0 = time.perf_counter()
        n = tissue.mesh.n_tets
        sel = np.asarray(tets)
        if sel.dtype == bool:
            if sel.shape != (n,):
                return CutPlan(CutResult(False, f"tet mask must have one entry per tet ({n}), got shape {sel.shape}"))
            gone = sel.copy()
        else:
            if sel.size and (not np.issubdtype(sel.dtype, np.integer) or sel.min() < 0 or sel.max() >= n):
                return CutPlan(CutResult(False, f"tet indices must be integers in [0, {n}), got {tets!r}"))
            gone = np.zeros(n, bool)
            gone[sel.astype(np.int64).ravel()] = True
        if not gone.any():
            return CutPlan(CutResult(False, "no tet given: nothing changed"))
        return self._removal(tissue, gone, t0)

    def _removal(self, tissue: Tissue, gone: np.ndarray, t0: float) -> CutPlan:
        if gone.all():
            return CutPlan(CutResult(False, "refused: the removal would delete every element of the body"))
        kept_tets = ~gone
        used = np.zeros(tissue.mesh.n_nodes, bool)
        used[np.compress(kept_tets, tissue.mesh.tets, axis=0)] = True
        return self._change(tissue, None, np.zeros(0, np.int64), np.flatnonzero(gone), np.zeros(0, np.int64),
                            keep=np.flatnonzero(used), kept_tets=kept_tets, what="removal", t0=t0)

    def small_fragments(self, mesh, free: np.ndarray) -> np.ndarray:
        """Mask of the tets in free fragments (no fixed node) of fewer than ``min_fragment`` tets."""
        if self.min_fragment <= 0 or mesh.n_tets == 0:
            return np.zeros(mesh.n_tets, bool)
        lab = mesh.node_components()
        tet_lab = lab[mesh.tets[:, 0]]
        count = np.bincount(tet_lab, minlength=lab.max() + 1)
        anchored = np.zeros(len(count), bool)
        anchored[lab[free == 0.0]] = True
        small = (count < self.min_fragment) & ~anchored
        return small[tet_lab]

    def join_debris(self, plan: CutPlan) -> None:
        """Make the removal of the small free fragments ``plan``'s change would leave (a lone tet
        shaved off by the blade would otherwise tumble through the cut at free-fall speed) part
        of that change: one change for the simulation to apply, its result counting both. Read
        from the planned change itself (no read of the body)."""
        tissue = plan.change.tissue()
        gone = self.small_fragments(tissue.mesh, tissue.free)
        if not gone.any() or gone.all():
            return
        debris = self._removal(tissue, gone, time.perf_counter())
        if debris.change is None:
            return
        res = plan.result
        plan.change = plan.change.then(debris.change)
        res.debris_tets = debris.result.tets_changed
        res.nodes_removed += debris.result.nodes_removed
        plan.note += f"; {res.debris_tets} debris tets of fragments under {self.min_fragment} tets removed"

    # ------------------------------------------------------------- planning
    def _change(self, tissue: Tissue, new_tets, source, removed_ids, added_ids, keep, kept_tets=None, mats=None,
                what: str = "cut", note: str = "", t0: float = 0.0, tet_source=None) -> CutPlan:
        """A topology change of ``tissue``, or a refusal (the mesh unchanged).

        ``new_tets``: the new tets (None: element removal, ``keep`` the nodes kept, ``kept_tets``
        the tets). New nodes are appended after the old ones, node k at (1 - t) a + t b of old
        nodes ``source = (a, b, t)`` (a copy of node a: b = a, t = 0), for its rest and current
        position, its velocity and its dv (the solver's guess, where the tissue has it): a node
        on an edge follows the displacement field exactly.
        ``mats``: the new tets' material ids (default: unchanged); ``tet_source``: the old tet
        each new one comes from (-1: none; removal: the kept ones)."""
        mesh, old_uids, free_old = tissue.mesh, tissue.node_uids, tissue.free
        x, v, dv = tissue.x, tissue.v, tissue.dv
        if new_tets is None:  # element removal with compaction
            remap = np.full(mesh.n_nodes, -1, np.int64)
            remap[keep] = np.arange(len(keep))
            tets_new = np.take(remap, np.compress(kept_tets, mesh.tets, axis=0))
            pts_new, x_new, v_new = (np.take(a, keep, axis=0) for a in (mesh.points, x, v))
            dv_new = None if dv is None else np.take(dv, keep, axis=0)
            uids_new = np.take(old_uids, keep)
            free_new = np.take(free_old, keep)
            mats = np.compress(kept_tets, mesh.material_ids)
            created = np.zeros(0, np.int64)
            gone = np.ones(mesh.n_nodes, bool)
            gone[keep] = False
            removed = np.sort(old_uids[gone])
            source = np.zeros(0, np.int64)
            tet_source = np.flatnonzero(kept_tets)
        else:  # node splitting and subdivision: new nodes appended
            a, b, t = source
            t = np.asarray(t, dtype=np.float64)[:, None]

            def along(arr):
                return np.concatenate([arr, (1.0 - t) * arr[a] + t * arr[b]])

            tets_new = new_tets
            pts_new, x_new, v_new = along(mesh.points), along(x), along(v)
            dv_new = None if dv is None else along(dv)
            first = int(old_uids.max()) + 1 if len(old_uids) else 0
            created = np.arange(first, first + len(a), dtype=np.int64)
            uids_new = np.concatenate([old_uids, created])
            free_new = np.concatenate([free_old, np.maximum(free_old[a], free_old[b])])  # fixed if both ends are
            mats = mesh.material_ids if mats is None else mats
            removed = np.zeros(0, np.int64)
            source = np.where(t[:, 0] <= 0.5, a, b)  # the old node whose rotation a new one takes
        # the quality floor (node splitting keeps shapes; this guards the invariant) and no orphan node
        q = tet_quality(pts_new, tets_new[added_ids]) if len(added_ids) else np.ones(1)
        used = np.zeros(len(pts_new), bool)
        used[tets_new.ravel()] = True
        if q.min() < self.min_quality or not used.all():
            return CutPlan(CutResult(False, f"refused: the change would create a tet of quality {q.min():.3g} < "
                                     f"{self.min_quality} or a node without a tet; mesh unchanged",
                                     ms=1000.0 * (time.perf_counter() - t0)))
        new_mesh = TetMesh(pts_new, tets_new, mats)
        removed_tets = np.take(mesh.tets, removed_ids, axis=0)
        if new_tets is None:
            _carry_tables(mesh, new_mesh, removed_tets, np.zeros((0, 4), np.int64), remap, kept=(kept_tets, keep))
        else:
            _carry_tables(mesh, new_mesh, removed_tets, np.take(tets_new, added_ids, axis=0), np.arange(mesh.n_nodes),
                          copies=a if np.array_equal(a, b) else None)
        change = TopologyChange(new_mesh, x_new, v_new, uids_new, free_new, removed_ids,
                                added_ids, created, removed, source, old_uids, free_old, tet_source, dv_new)
        return CutPlan(CutResult(True, what, tets_changed=int(len(removed_ids)), nodes_added=int(len(created)),
                                 nodes_removed=int(len(removed))), change, note, t0)

    # ------------------------------------------------------------- applied
    def record(self, plan: CutPlan, mod: Modification) -> bool:
        """Account for ``plan`` once its change is applied, ``mod`` being the modification of A
        it made: count it, give it to the Sherman-Morrison correction (eq. 5-12), and say what
        it did in ``plan.result``. False where there is no correction: the preconditioner must
        then be rebuilt from the new mesh."""
        res, change = plan.result, plan.change
        self.modifications += 1
        res.affected_nodes = int(len(mod.uids))
        if self.correction is not None:
            self.correction.u_ms = self.correction.q_ms = 0.0
            self.correction.add(mod, change.node_uids)
            res.smf_u_ms, res.smf_q_ms = self.correction.u_ms, self.correction.q_ms
            res.perturbation_nodes = self.correction.perturbation_nodes()
        res.message = (f"{res.message}: {len(change.removed_tets)} tets changed, {len(change.created)} nodes added, "
                       f"{len(change.removed)} removed, {len(mod.uids)} affected{plan.note}")
        self.history.append(res)
        return self.correction is not None
