"""Brain tumour resection end to end (paper fig. 5): ``python -m soft_tissue_sim.bench brain``.

Scene ``config/scenes/brain_resection.yaml``, driven by a scripted surgeon:

1. push: the probe presses 6 mm into the cortex above the tumour, holds, and retracts;
2. circumferential cut: the scalpel (a 12 mm vertical blade) spirals down around the tumour
   with the pedal down (4 turns, to 14 mm under the tumour), one small cut per step
   (continuous cutting);
3. aspiration: the tissue under the tumour is removed in small bites (element removal,
   ``remove_elements``: the tets whose current centroid lies in a 4.5 mm sphere) in two
   layers (the elements are about 1 cm) above the floor of the cut, which stays: the
   specimen rests on it as it comes free (aspirating the floor as well, as an earlier plan
   did, let it hang 6-10 cm below the brain, with no skull under it, and cost iterations).
   Every bite spares the tumour: its sphere is shrunk so that no tumour tet's centroid lies
   inside (without this, an earlier plan's top layer, aimed where the tumour was before it
   sank, aspirated 42 of its 116 tets). The bites alone do not free the tumour: it sinks
   as its support goes, and the bites, aimed where the tissue was, miss strands;
4. closed loop (what a surgeon does next): while the tumour is still attached to the fixed
   base (connectivity of the tets), find what holds it: a minimum cut between the tumour's
   nodes and the fixed nodes (max-flow on the graph of nodes and tets, each healthy tet
   cuttable at cost 1, tumour tets never) gives the fewest healthy tets whose removal parts
   them; bite (5 mm, tumour-sparing as above) on the current centroid of the cut tet closest
   to the tumour, step the simulation, and look again; one bite per step, at most 60. Every
   bite is a removal modification in the statistics; ``cleanup_bites`` counts them and
   ``cut_sizes`` lists the size of the cut before each;
5. once free, the specimen (the tumour and its cuff: the parts holding tumour and no fixed
   node) is lifted out (``Simulation.remove_tets``, an "extraction" modification), and the
   brain settles (40 steps). Before the extraction the specimen hangs in the opened base:
   the scene has no skull, and a skull plane (obstacle at z = 0) was tried: the stiff tumour
   then crushes the thin tissue left between it and the plane, which inverts (about 100
   inverted tets), so it is not used.

The long session (``--margin 0.01 --radial 16``) is the same resection with a margin: before
the spiral above, an outer spiral 10 mm outside it; after it, radial cuts that part the ring
between the two into wedges (each one stroke: in from above along the outer cut, then back
and forth between the cuts, each pass at most 10 mm lower, so the blade enters the tissue only
through a cut). It is about four times longer (about 2,700 steps against about 700, the
paper's interactive session about 3,000), and makes the paper's count of modifications.

Reported: modifications (cuts and removals) with their affected nodes, PCG iterations
(mean and max), step time (mean, median, p99) and frame rate, contacts, LCP residual, max
penetration, rollbacks, whether the tumour ended in a part no longer attached to the fixed
base (``tumour_freed``), whether the planned bites alone did it (``freed_by_plan``), that no
tumour tet was removed before it was freed (``tumour_tets_intact``), the step it was freed
at, how far the tumour had sunk then, the tets lifted out (``extracted_tets``), the tumour
tets left in the body at the end (``tumour_left_end``: 0 when the resection is complete) and
the inverted tets at the end. JSON and PNG under
benchmarks/results/.
"""

from __future__ import annotations

import argparse
import json
import sys
import time

import numpy as np
import scipy.sparse as sps
from scipy.sparse.csgraph import breadth_first_order, maximum_flow

from ..cutting import DEFAULT_SNAP
from ..report import Progress
from ..scene import load_scene, read_scene, resolve_device
from . import RESULTS_DIR, write_result

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
    #    cut's floor: the floor stays, and the specimen rests on it (self-contact) as it comes
    #    free. Aspirating the floor too opened a hole through the base, and with no skull under
    #    it the specimen hung 6-10 cm below the brain on strands while the last bites went in:
    #    12-22 PCG iterations a step there with the paper's factor delay (bench --lag 6)
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


def run(device, scene="brain_resection.yaml", turns=4, step_len=0.0012, max_cleanup=60, cleanup_radius=0.005,
        backend="auto", scheme=None, worker=None, synchronous=False, refresh_every=None, snap=None,
        margin=0.0, radial=0, progress=False, lag=0):
    cfg = read_scene(scene)[0]
    solver = dict(cfg.get("solver") or {})
    solver["ldlt"] = {**(solver.get("ldlt") or {}), "backend": backend}
    if worker is not None:
        solver["ldlt"]["worker"] = worker
    if refresh_every is not None:
        solver["ldlt"]["refresh_every"] = int(refresh_every)
    if synchronous or lag:  # the factor made in the step that requests it (no background worker)
        solver["ldlt"]["deterministic"] = True
    if lag:  # ... and installed lag steps later (the paper's background factorization took about 5.6)
        solver["ldlt"]["lag"] = int(lag)
    overrides = {"solver": solver}
    if scheme is not None:
        overrides["cutting"] = {"scheme": scheme}
    if snap is not None:
        overrides.setdefault("cutting", {})["snap"] = float(snap)
    sim = load_scene(scene, device=device, overrides=overrides)
    rows, mods, bites, extracted = [], [], [], []
    try:
        sim.step()  # warm-up: compile, first factorization
        sim.reset()
        acts = plan(sim.mesh, turns, step_len, margin=margin, radial=radial)
        prog = Progress(len(acts)) if progress else None  # the closed loop's bites come on top
        n_tum = int((sim.mesh.material_ids == 1).sum())
        park = {k: v for k, v in acts[-1].items() if k != "phase"}  # instruments parked, pedal up
        its_sum = [0]  # iterations so far, for the progress line

        def record(kind, r, **extra):
            """One modification's statistics (its own nodes and the nodes of N, the paper's measure)."""
            return {"kind": kind, "affected_nodes": r.affected_nodes, "perturbation_nodes": r.perturbation_nodes,
                    "ms": r.ms, "u_ms": r.smf_u_ms, "q_ms": r.smf_q_ms, "step": sim.step_count, **extra}

        def do(a, kind="removal"):
            sim.set_instrument_pose("probe", a["probe"], IDENTITY)
            sim.set_instrument_pose("scalpel", a["scalpel"], IDENTITY)
            sim.set_cutting(a["cutting"])
            t0 = time.perf_counter()
            extra_ms = 0.0
            if "remove" in a:
                r, _ = spare_tumour_bite(sim, *a["remove"])
                extra_ms = r.ms
                if r.changed:
                    mods.append(record("removal", r, cleanup=kind == "cleanup"))
            elif "extract" in a:  # lift the freed specimen out (en bloc resection)
                r = sim.remove_tets(specimen_tets(sim))
                extra_ms = r.ms
                extracted.append(int(r.tets_changed) if r.changed else 0)
                if r.changed:
                    mods.append(record("extraction", r))
            elif "cleanup_tet" in a:
                c = sim.positions()[sim.mesh.tets[a["cleanup_tet"]]].mean(axis=0)  # that tet's centroid
                r, rad = spare_tumour_bite(sim, c, cleanup_radius)
                extra_ms = r.ms
                bites.append({"step": sim.step_count, "center": c.tolist(), "radius": rad,
                              "tets": r.tets_changed, "changed": bool(r.changed)})
                if r.changed:
                    mods.append(record("removal", r, cleanup=True))
            n_before = len(sim.cutting.history)
            s = sim.step()
            wall = 1000.0 * (time.perf_counter() - t0)
            for r in sim.cutting.history[n_before:]:
                if r.changed and r.message.startswith("cut"):
                    mods.append(record("cut", r))
            d = s.as_dict()
            rows.append({"step": sim.step_count, "wall_ms": wall, "total_ms": d["total_ms"] + d.get("cut_ms", 0.0)
                         + d.get("contact_ms", 0.0) + extra_ms, "iterations": d["iterations"],
                         "residual": d["residual"], "converged": d["converged"], "contacts": d.get("contacts", 0),
                         "max_penetration": d.get("max_penetration", 0.0), "lcp_residual": d.get("lcp_residual", 0.0),
                         "factor_age": d["factor_age"], "refresh_interval": d["refresh_interval"],
                         "rolled_back": bool(d.get("rolled_back", False)),
                         "wrench_probe_N": float(np.linalg.norm(sim.instrument_wrench("probe")[0]))})
            its_sum[0] += d["iterations"]
            if prog is not None:
                prog.update(min(len(rows), prog.total - 1),
                            f"step {sim.step_count}: {len(mods)} modifications, {its_sum[0] / len(rows):.2f} it")

        for a in acts:
            if a.get("phase") == "settle":
                continue
            do(a)
        freed_planned = tumour_freed(sim)
        # closed loop: while the tumour still hangs on, aspirate what holds it, one bite a step
        cut_sizes = []
        while not tumour_freed(sim) and len(bites) < max_cleanup:
            cut = attachment_cut(sim)
            cut_sizes.append(len(cut))
            if len(cut) == 0:
                break
            cen = sim.positions()[sim.mesh.tets[cut]].mean(axis=1)
            tc = sim.positions()[np.unique(sim.mesh.tets[sim.mesh.material_ids == 1])].mean(axis=0)
            pick = int(cut[np.argmin(np.linalg.norm(cen - tc, axis=1))])  # work in from the tumour
            do({**park, "cleanup_tet": pick}, "cleanup")
        freed = tumour_freed(sim)
        freed_step = sim.step_count if freed else None
        z_freed = tumour_drop(sim)
        tumour_intact = int((sim.mesh.material_ids == 1).sum()) == n_tum
        settle = [a for a in acts if a.get("phase") == "settle"]
        if freed:  # the surgeon lifts the specimen out, then the brain settles
            settle[0] = {**settle[0], "extract": True}
        for a in settle:
            do(a)
        inverted = inverted_tets(sim)
        tumour_left = int((sim.mesh.material_ids == 1).sum())
        finite = bool(np.isfinite(sim.positions()).all())
        nodes_end, tets_end = sim.mesh.n_nodes, sim.mesh.n_tets
    finally:
        sim.close()
    info = {"freed_by_plan": bool(freed_planned), "cleanup_bites": len(bites), "cut_sizes": cut_sizes,
            "tumour_tets_intact": tumour_intact, "bites": bites, "freed_at_step": freed_step,
            "tumour_drop_when_freed_m": z_freed, "extracted_tets": int(sum(extracted)),
            "tumour_left_end": tumour_left, "inverted_tets_end": inverted}
    return rows, mods, freed, finite, nodes_end, tets_end, info


def plot(result, prefix):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    st = result["steps_detail"]
    fig, axes = plt.subplots(1, 3, figsize=(17, 4.5))
    k = [s["step"] for s in st]
    axes[0].plot(k, [s["iterations"] for s in st], lw=0.8)
    for m in result["modifications"]:
        axes[0].axvline(m["step"], color="r", alpha=0.05)
    axes[0].set(xlabel="step", ylabel="PCG iterations", title="iterations (red: modifications)")
    axes[1].plot(k, [s["wall_ms"] for s in st], lw=0.8)
    axes[1].set(xlabel="step", ylabel="ms", title="wall time per step (cut, contact, solve)")
    axes[2].hist([m["affected_nodes"] for m in result["modifications"]], bins=30)
    axes[2].set(xlabel="affected nodes per modification", ylabel="count", title="modifications")
    for ax in axes:
        ax.grid(True, alpha=0.3)
    fig.suptitle(f"brain tumour resection on {result['device']}")
    fig.tight_layout()
    fig.savefig(f"{prefix}.png", dpi=110)
    plt.close(fig)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m soft_tissue_sim.bench brain", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", default="brain_resection.yaml")
    ap.add_argument("--turns", type=float, default=4)
    ap.add_argument("--step-len", type=float, default=0.0012, help="scalpel advance per step [m]")
    ap.add_argument("--margin", type=float, default=0.0,
                    help="the long session: an outer spiral cut this far outside the inner one [m] (0: none)")
    ap.add_argument("--radial", type=int, default=0,
                    help="the long session: radial cuts dividing the margin into wedges")
    ap.add_argument("--max-cleanup", type=int, default=60, help="most extra (closed-loop) bites")
    ap.add_argument("--cleanup-radius", type=float, default=0.005, help="radius of a closed-loop bite [m]")
    ap.add_argument("--backend", default="auto", choices=["auto", "cholmod", "dense"],
                    help="the factor's backend (solver.ldlt.backend)")
    ap.add_argument("--scheme", default=None, choices=["split", "subdivide"],
                    help="cutting scheme (default: the scene's)")
    ap.add_argument("--snap", type=float, default=None,
                    help="subdivide: snap a crossing to an edge's end within this fraction (default: the scene's)")
    ap.add_argument("--worker", default=None, choices=["thread", "process"],
                    help="where the async factorization runs (default: the scene's)")
    ap.add_argument("--refresh-every", type=int, default=None,
                    help="request a factor every this many steps (default: the scene's)")
    ap.add_argument("--synchronous", action="store_true",
                    help="factorize in the step that requests the factor (ldlt.deterministic), not in the background")
    ap.add_argument("--lag", type=int, default=0,
                    help="factorize in the step that requests the factor and install it this many steps later: "
                         "the schedule of a background factorization that takes that long (the paper's: about 5.6 "
                         "steps), reproducibly")
    ap.add_argument("--device", default=None)
    ap.add_argument("--out", default=str(RESULTS_DIR))
    args = ap.parse_args(argv)
    if args.lag < 0:
        ap.error("--lag is a number of steps >= 0")
    if args.margin < 0 or (args.radial > 0) != (args.margin > 0) or args.radial < 0:
        ap.error("--margin and --radial come together (a margin > 0 and at least one radial cut), or neither")
    device = resolve_device(args.device)
    t0 = time.perf_counter()
    rows, mods, freed, finite, n_end, t_end, info = run(device, args.scene, args.turns, args.step_len,
                                                        args.max_cleanup, args.cleanup_radius, args.backend,
                                                        args.scheme, args.worker, args.synchronous,
                                                        args.refresh_every, args.snap, args.margin, args.radial,
                                                        progress=True, lag=args.lag)
    wall = np.array([r["wall_ms"] for r in rows])
    its = np.array([r["iterations"] for r in rows])
    summary = {
        "steps": len(rows), "modifications": len(mods),
        "cuts": sum(m["kind"] == "cut" for m in mods), "removals": sum(m["kind"] == "removal" for m in mods),
        "cleanup_bites": info["cleanup_bites"], "cleanup_removals": sum(bool(m.get("cleanup")) for m in mods),
        "affected_nodes_mean": float(np.mean([m["affected_nodes"] for m in mods])) if mods else 0.0,
        **{f"affected_nodes_{k}s_mean": float(np.mean([m["affected_nodes"] for m in mods if m["kind"] == k]))
           for k in ("cut", "removal") if any(m["kind"] == k for m in mods)},
        # the paper's "affecting 24 nodes": the nodes of N against the factor in use (eq. 5)
        "perturbation_nodes_mean": float(np.mean([m["perturbation_nodes"] for m in mods])) if mods else 0.0,
        "perturbation_nodes_median": float(np.median([m["perturbation_nodes"] for m in mods])) if mods else 0.0,
        "modification_every_steps": len(rows) / max(1, len(mods)),
        "iterations_mean": float(its.mean()), "iterations_max": int(its.max()),
        "converged_fraction": float(np.mean([r["converged"] for r in rows])),
        "step_ms_mean": float(wall.mean()), "step_ms_median": float(np.median(wall)),
        "step_ms_p99": float(np.percentile(wall, 99)), "fps_mean": float(1000.0 / wall.mean()),
        "contacts_mean": float(np.mean([r["contacts"] for r in rows])),
        "max_penetration": float(max(r["max_penetration"] for r in rows)),
        "refresh_interval": rows[-1]["refresh_interval"], "rollbacks": int(sum(r["rolled_back"] for r in rows)),
        "tumour_freed": bool(freed), "freed_by_plan": info["freed_by_plan"],
        "tumour_tets_intact": info["tumour_tets_intact"], "cut_sizes": info["cut_sizes"],
        "freed_at_step": info["freed_at_step"], "tumour_drop_when_freed_m": info["tumour_drop_when_freed_m"],
        "extracted_tets": info["extracted_tets"], "tumour_left_end": info["tumour_left_end"],
        "inverted_tets_end": info["inverted_tets_end"],
        "finite": finite, "nodes_end": n_end, "tets_end": t_end,
        "wall_s": time.perf_counter() - t0,
    }
    print(f"done: {summary['modifications']} modifications, {summary['iterations_mean']:.2f} it, "
          f"{summary['fps_mean']:.1f} FPS", file=sys.stderr)
    cfg = read_scene(args.scene)[0]
    ldlt = (cfg.get("solver") or {}).get("ldlt") or {}
    summary["backend"] = args.backend
    summary["ldlt_worker"] = args.worker or str(ldlt.get("worker", "thread"))
    summary["ldlt_synchronous"] = bool(args.synchronous or args.lag)
    summary["ldlt_lag"] = args.lag
    summary["refresh_every"] = args.refresh_every or int(ldlt.get("refresh_every", 0))
    summary["step_len_m"] = args.step_len
    summary["margin_m"] = args.margin
    summary["radial_cuts"] = args.radial
    summary["cutting_scheme"] = args.scheme or str((cfg.get("cutting") or {}).get("scheme", "split"))
    summary["snap"] = args.snap if args.snap is not None else float((cfg.get("cutting") or {}).get("snap", DEFAULT_SNAP))
    result = {"summary": summary, "modifications": mods, "cleanup_bites": info["bites"], "steps_detail": rows}
    path = write_result("brain", device, result, args.out)
    result["device"] = json.load(open(path))["device"]
    plot(result, str(path.with_suffix("")))
    for k, v in summary.items():
        print(f"{k:>26}: {v}")
    print(f"wrote {path} and {path.with_suffix('.png')}")
    return 0
