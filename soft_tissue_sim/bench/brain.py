"""Brain tumour resection end to end (paper fig. 5): ``python -m soft_tissue_sim.bench brain``.

Scene ``config/scenes/brain_resection.yaml``, driven by a scripted surgeon:

1. push: the probe presses 6 mm into the cortex above the tumour, holds, and retracts;
2. circumferential cut: the scalpel (a 12 mm vertical blade) spirals down around the tumour
   with the pedal down (4 turns, to 14 mm under the tumour), one small cut per step
   (continuous cutting);
3. aspiration: the tissue under the tumour is removed in small bites (element removal) in
   three layers (the elements are about 1 cm), meant to free the tumour with a cuff of tissue
   (in the rest frame this plan frees it; in the simulation, strands near the base where the
   tumour sinks as its support goes hold it: see the README);
4. everything settles (40 steps).

Reported: modifications (cuts and removals) with their affected nodes, PCG iterations
(mean and max), step time (mean, median, p99) and frame rate, contacts, LCP residual, max
penetration, rollbacks, and whether the tumour ended in a part no longer attached to the
fixed base. JSON and PNG under benchmarks/results/.
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np
import scipy.sparse as sps
from scipy.sparse.csgraph import connected_components

from ..report import Progress
from ..scene import load_scene, resolve_device
from . import RESULTS_DIR, write_result

IDENTITY = [0.0, 0.0, 0.0, 1.0]


def tumour_geometry(mesh):
    cen = mesh.centroids()[mesh.material_ids == 1]
    c = cen.mean(axis=0)
    r = float(np.max(np.linalg.norm(cen[:, :2] - c[:2], axis=1)))
    return c, r, float(cen[:, 2].min()), float(cen[:, 2].max())


def plan(mesh, turns=4, step_len=0.0012, layers=3, bite=0.0045):
    """The scripted surgeon: a list of per-step actions."""
    c, r, zlo, zhi = tumour_geometry(mesh)
    top = float(mesh.points[:, 2].max())
    R = r + 0.006  # cut 6 mm outside the tumour centroids
    acts = []
    probe_home = np.array([c[0] + R + 0.012, c[1], top + 0.04])
    scal_home = np.array([c[0] + R, c[1], top + 0.04])
    # 1. push
    for k in range(60):
        depth = 0.006 * min(1.0, k / 20.0) if k < 40 else 0.006 * max(0.0, 1.0 - (k - 40) / 15.0)
        p = np.array([c[0], c[1], top + 0.004 - depth])
        acts.append({"probe": p if k < 58 else probe_home, "scalpel": scal_home, "cutting": False})
    # 2. spiral cut: blade from z to z + 12 mm, z from top - 10 mm down to below the tumour
    z0, z1 = top - 0.010, max(0.003, zlo - 0.014)
    n = int(np.ceil(turns * 2 * np.pi * R / step_len))
    for k in range(n + 1):
        s = k / n
        a = 2 * np.pi * turns * s
        p = np.array([c[0] + R * np.cos(a), c[1] + R * np.sin(a), z0 + (z1 - z0) * s])
        acts.append({"probe": probe_home + [0.03, 0, 0], "scalpel": p, "cutting": True})
    # 3. aspiration under the tumour: bites on a disc, ring by ring, in layers from the cut's
    #    floor up (the elements are about 1 cm: one layer of bites does not part them)
    bites = [(0.0, 0.0)]
    for ring in np.arange(0.004, R + 1e-9, 0.004):
        m = max(6, int(2 * np.pi * ring / 0.004))
        bites += [(ring * np.cos(2 * np.pi * j / m), ring * np.sin(2 * np.pi * j / m)) for j in range(m)]
    for zb in z1 + 0.003 + 0.0045 * np.arange(layers):
        for bx, by in bites:
            acts.append({"probe": probe_home + [0.03, 0, 0], "scalpel": scal_home, "cutting": False,
                         "remove": (np.array([c[0] + bx, c[1] + by, zb]), bite)})
    # 4. settle
    for _ in range(40):
        acts.append({"probe": probe_home + [0.03, 0, 0], "scalpel": scal_home, "cutting": False})
    return acts


def tumour_freed(sim) -> bool:
    m = sim.mesh
    T = m.tets
    rows = np.repeat(T, 4, axis=1).ravel()
    cols = np.tile(T, (1, 4)).ravel()
    g = sps.coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(m.n_nodes, m.n_nodes))
    _, lab = connected_components(g, directed=False)
    fixed = sim.fem.fixed_nodes
    base = set(np.unique(lab[fixed]).tolist())
    tum_nodes = np.unique(T[m.material_ids == 1])
    return not any(l in base for l in np.unique(lab[tum_nodes]).tolist())


def run(device, scene="brain_resection.yaml", turns=4, step_len=0.0012):
    sim = load_scene(scene, device=device)
    rows, mods = [], []
    try:
        sim.step()  # warm-up: compile, first factorization
        sim.reset()
        acts = plan(sim.mesh, turns, step_len)
        for a in acts:
            sim.set_instrument_pose("probe", a["probe"], IDENTITY)
            sim.set_instrument_pose("scalpel", a["scalpel"], IDENTITY)
            sim.set_cutting(a["cutting"])
            t0 = time.perf_counter()
            extra_ms = 0.0
            if "remove" in a:
                r = sim.remove_elements(*a["remove"])
                extra_ms = r.ms
                if r.changed:
                    mods.append({"kind": "removal", "affected_nodes": r.affected_nodes, "ms": r.ms,
                                 "u_ms": r.smf_u_ms, "q_ms": r.smf_q_ms, "step": sim.step_count})
            n_before = len(sim.cutting.history)
            s = sim.step()
            wall = 1000.0 * (time.perf_counter() - t0)
            for r in sim.cutting.history[n_before:]:
                if r.changed and r.message.startswith("cut"):
                    mods.append({"kind": "cut", "affected_nodes": r.affected_nodes, "ms": r.ms, "u_ms": r.smf_u_ms,
                                 "q_ms": r.smf_q_ms, "step": sim.step_count})
            d = s.as_dict()
            rows.append({"step": sim.step_count, "wall_ms": wall, "total_ms": d["total_ms"] + d.get("cut_ms", 0.0)
                         + d.get("contact_ms", 0.0) + extra_ms, "iterations": d["iterations"],
                         "residual": d["residual"], "converged": d["converged"], "contacts": d.get("contacts", 0),
                         "max_penetration": d.get("max_penetration", 0.0), "lcp_residual": d.get("lcp_residual", 0.0),
                         "factor_age": d["factor_age"], "refresh_interval": d["refresh_interval"],
                         "rolled_back": bool(d.get("rolled_back", False)),
                         "wrench_probe_N": float(np.linalg.norm(sim.instrument_wrench("probe")[0]))})
        freed = tumour_freed(sim)
        finite = bool(np.isfinite(sim.positions()).all())
        nodes_end, tets_end = sim.mesh.n_nodes, sim.mesh.n_tets
    finally:
        sim.close()
    return rows, mods, freed, finite, nodes_end, tets_end


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
    ap.add_argument("--device", default=None)
    ap.add_argument("--out", default=str(RESULTS_DIR))
    args = ap.parse_args(argv)
    device = resolve_device(args.device)
    prog = Progress(1)
    t0 = time.perf_counter()
    rows, mods, freed, finite, n_end, t_end = run(device, args.scene, args.turns, args.step_len)
    wall = np.array([r["wall_ms"] for r in rows])
    its = np.array([r["iterations"] for r in rows])
    summary = {
        "steps": len(rows), "modifications": len(mods),
        "cuts": sum(m["kind"] == "cut" for m in mods), "removals": sum(m["kind"] == "removal" for m in mods),
        "affected_nodes_mean": float(np.mean([m["affected_nodes"] for m in mods])) if mods else 0.0,
        "modification_every_steps": len(rows) / max(1, len(mods)),
        "iterations_mean": float(its.mean()), "iterations_max": int(its.max()),
        "converged_fraction": float(np.mean([r["converged"] for r in rows])),
        "step_ms_mean": float(wall.mean()), "step_ms_median": float(np.median(wall)),
        "step_ms_p99": float(np.percentile(wall, 99)), "fps_mean": float(1000.0 / wall.mean()),
        "contacts_mean": float(np.mean([r["contacts"] for r in rows])),
        "max_penetration": float(max(r["max_penetration"] for r in rows)),
        "refresh_interval": rows[-1]["refresh_interval"], "rollbacks": int(sum(r["rolled_back"] for r in rows)),
        "tumour_freed": bool(freed), "finite": finite, "nodes_end": n_end, "tets_end": t_end,
        "wall_s": time.perf_counter() - t0,
    }
    prog.update(1, f"{summary['modifications']} modifications, {summary['iterations_mean']:.2f} it, "
                   f"{summary['fps_mean']:.1f} FPS")
    result = {"summary": summary, "modifications": mods, "steps_detail": rows}
    path = write_result("brain", device, result, args.out)
    result["device"] = json.load(open(path))["device"]
    plot(result, str(path.with_suffix("")))
    for k, v in summary.items():
        print(f"{k:>26}: {v}")
    print(f"wrote {path} and {path.with_suffix('.png')}")
    return 0
