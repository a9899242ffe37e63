"""The paper's cut beam (section 4, table and fig. 3-4): ``python -m soft_tissue_sim.bench cut-beam``.

A beam clamped at x = 0 swings down under gravity while a blade cuts it lengthwise, in its
mid-plane, from the free end towards the clamp: one element layer per cut, a cut every
``--cut-every`` steps (paper: 3.4), the factor refreshed every ``--refresh-every`` steps
(paper: 4.3). Methods:

* ``cg``: plain CG, which needs no preconditioner update (the paper's CGM),
* ``smf``: PCG with the asynchronous rotated LDL^T factor and the Sherman-Morrison
  correction of every cut (eq. 5-10),
* ``padded``: the same factor without the correction, only the identity padding of new
  degrees of freedom (eq. 10): what the correction buys.

Reported per beam and method (means over the trajectory): affected nodes per cut (its own
nodes, and the nodes of the perturbation N against the factor in use: the paper's measure), build ms
(right-hand side, rotations and the preconditioner's snapshot), iterations, solve ms, cut ms
(mesh change + U and Q), total ms per step; and, per cut, the cost of U and Q against the
number of affected nodes (fig. 4). JSON and PNG under benchmarks/results/.
"""

from __future__ import annotations

import time

import numpy as np

from ..report import Progress
from ..cutting import sweep_triangles
from ..scene import load_scene
from .common import figure, parser, publish, resolved_device, save_figure

METHODS = {
    "cg": ({"preconditioner": "none"}, "none"),
    "smf": ({"preconditioner": "async_ldlt"}, "sherman_morrison"),
    "padded": ({"preconditioner": "async_ldlt"}, "none"),
}


def cut_script(points, cut_every, count, start_step=2):
    """A vertical blade in the mid-plane y = (min+max)/2, advancing one layer per cut from the free end."""
    lo, hi = points.min(axis=0), points.max(axis=0)
    xs = np.unique(np.round(points[:, 0], 9))
    layer = float(np.median(np.diff(xs)))
    ymid = 0.5 * (lo[1] + hi[1])
    pad = 0.05 * (hi[2] - lo[2])
    return {"frame": "rest", "start_step": start_step, "every": cut_every, "count": count,
            "origin": [float(hi[0] + 0.5 * layer), ymid, float(lo[2] - pad)],
            "edge": [0.0, 0.0, float(hi[2] - lo[2] + 2 * pad)], "direction": [-1.0, 0.0, 0.0], "advance": layer}


def run(scene, method, steps, cut_every, refresh_every, device, tolerance=1e-7, backend="auto"):
    solver, corr = METHODS[method]
    solver = {**solver, "tolerance": tolerance, "max_iterations": 5000}
    if solver["preconditioner"] == "async_ldlt":
        solver["ldlt"] = {"rotate": True, "refresh_every": refresh_every, "deterministic": False,
                          "backend": backend}
    probe = load_scene(scene, device=device, overrides={"solver": {"preconditioner": "none"}})
    pts = probe.mesh.points.copy()
    probe.close()
    count = max(1, (steps - 2) // cut_every + 1)
    sim = load_scene(scene, device=device, overrides={
        "solver": solver, "cutting": {"correction": corr, "script": cut_script(pts, cut_every, count)}})
    stats, cuts = [], []
    try:
        sim.step()  # warm-up: kernel compilation and the first (synchronous) factorization
        sim.reset()
        for _ in range(steps):
            s = sim.step().as_dict()
            stats.append(s)
        cuts = [{"affected_nodes": r.affected_nodes, "perturbation_nodes": r.perturbation_nodes, "u_ms": r.smf_u_ms, "q_ms": r.smf_q_ms, "cut_ms": r.ms,
                 "nodes_added": r.nodes_added} for r in sim.cutting.history]
        nodes0 = len(pts)
        nodes1 = sim.mesh.n_nodes
    finally:
        sim.close()
    return stats, cuts, nodes0, nodes1


def summarize(stats, cuts, nodes0, nodes1, method):
    def m(k):
        return float(np.mean([s.get(k, 0.0) for s in stats]))

    total = [s["total_ms"] + s.get("cut_ms", 0.0) for s in stats]
    return {
        "nodes": nodes0, "nodes_after": nodes1, "method": method,
        "cuts": len(cuts), "affected_nodes": float(np.mean([c["affected_nodes"] for c in cuts])) if cuts else 0.0,
        # the paper's "Affected Nodes": nodes of N against the factor in use (eq. 5)
        "perturbation_nodes": float(np.mean([c["perturbation_nodes"] for c in cuts])) if cuts else 0.0,
        "build_ms": m("build_ms"), "iterations": m("iterations"), "iterations_max": int(max(s["iterations"] for s in stats)),
        "solve_ms": m("solve_ms"), "cut_ms": m("cut_ms"), "total_ms": float(np.mean(total)),
        "total_ms_median": float(np.median(total)),
        "refresh_interval": stats[-1]["refresh_interval"],
        "cut_interval": float(np.mean(np.diff([i for i, s in enumerate(stats) if s.get("tets_changed", 0) > 0])))
        if sum(1 for s in stats if s.get("tets_changed", 0) > 0) > 1 else 0.0,
        "converged_fraction": float(np.mean([s["converged"] for s in stats])),
    }


def plot(result, prefix):
    fig, axes = figure(1, 3, figsize=(17, 5))
    for key, its in result["iterations"].items():
        if "/cg" in key:
            continue
        axes[0].plot(its, label=key, lw=1)
    axes[0].set(xlabel="step", ylabel="PCG iterations (tol 1e-7)", title="(fig. 3) iterations while cutting")
    rows = result["table"]
    for meth in dict.fromkeys(r["method"] for r in rows):
        rs = [r for r in rows if r["method"] == meth]
        axes[1].plot([r["nodes"] for r in rs], [r["total_ms"] for r in rs], "o-", label=meth)
    axes[1].set(xlabel="nodes", ylabel="total ms per step", title="step time")
    ov = result["overhead"]
    if ov:
        host = np.array([o.get("backend") != "dense" for o in ov])
        a = np.array([o["affected_nodes"] for o in ov])
        u = np.array([o["u_ms"] for o in ov])
        axes[2].scatter(a[host], u[host], s=8, label="U = P^-1 G (CHOLMOD, all columns in one call)")
        if (~host).any():
            axes[2].scatter(a[~host], u[~host], s=8, label="U = P^-1 G and the update of the dense inverse")
        axes[2].scatter(a, [o["q_ms"] for o in ov], s=8, label="Q = (I + N S)^-1 N")
    axes[2].set(xlabel="affected nodes", ylabel="ms", title="(fig. 4) overhead of the correction")
    for ax in axes:
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=7)
    save_figure(fig, prefix, f"cut beam on {result['device']}")


def overhead_sweep(scene, device, sizes=(4, 8, 16, 32, 64, 128), backend="auto"):
    """U and Q cost against affected nodes (fig. 4): cuts of growing length on a fresh factor."""
    out = []
    sim = load_scene(scene, device=device, overrides={
        "solver": {"preconditioner": "async_ldlt", "ldlt": {"deterministic": True, "refresh_every": 10**6,
                                                             "backend": backend}},
        "cutting": {"correction": "sherman_morrison"}})
    try:
        pts = sim.mesh.points.copy()
        sim.step()
        lo, hi = pts.min(axis=0), pts.max(axis=0)
        layer = float(np.median(np.diff(np.unique(np.round(pts[:, 0], 9)))))
        ymid = 0.5 * (lo[1] + hi[1])
        x = hi[0] + 0.5 * layer
        for n_layers in sizes:
            sim.reset()
            sim.step()
            x1 = max(lo[0] + layer, x - n_layers * layer)
            r = sim.cut_triangles(sweep_triangles([x, ymid, lo[2] - 1e-3], [x, ymid, hi[2] + 1e-3],
                                                  [x1, ymid, lo[2] - 1e-3], [x1, ymid, hi[2] + 1e-3]), frame="rest")
            if r.changed:
                out.append({"affected_nodes": r.affected_nodes, "u_ms": r.smf_u_ms, "q_ms": r.smf_q_ms,
                            "cut_ms": r.ms, "layers": n_layers, "backend": backend})
    finally:
        sim.close()
    return out


def main(argv=None) -> int:
    ap = parser("cut-beam", __doc__)
    ap.add_argument("--scenes", nargs="*", default=["beam_1200.yaml", "beam_1600.yaml", "beam_2000.yaml"])
    ap.add_argument("--methods", nargs="*", default=list(METHODS))
    ap.add_argument("--steps", type=int, default=90)
    ap.add_argument("--cut-every", type=int, default=3, help="steps between cuts (paper: 3.4)")
    ap.add_argument("--refresh-every", type=int, default=4, help="steps between factorizations (paper: 4.3)")
    ap.add_argument("--backend", default="auto", choices=["auto", "cholmod", "dense"],
                    help="the factor's backend (solver.ldlt.backend; auto: dense on CUDA)")
    args = ap.parse_args(argv)
    device = resolved_device(args)
    prog = Progress(len(args.scenes) * len(args.methods) + 1)
    t0 = time.perf_counter()
    rows, iters, per_cut = [], {}, []
    for scene in args.scenes:
        for meth in args.methods:
            stats, cuts, n0, n1 = run(scene, meth, args.steps, args.cut_every, args.refresh_every, device,
                                      backend=args.backend)
            rows.append(summarize(stats, cuts, n0, n1, meth))
            iters[f"{n0}/{meth}"] = [s["iterations"] for s in stats]
            if meth == "smf":
                per_cut += [{**c, "nodes": n0} for c in cuts]
            prog.update(len(rows), f"{scene} {meth}: {rows[-1]['iterations']:.2f} it, {rows[-1]['total_ms']:.1f} ms")
    if str(device).startswith("cuda"):  # fig. 4 for both backends (CHOLMOD's chained terms, the folded dense inverse)
        overhead = [o for b in ("cholmod", "dense") for o in overhead_sweep(args.scenes[-1], device, backend=b)]
    else:
        overhead = overhead_sweep(args.scenes[-1], device, backend=args.backend)
    prog.update(len(rows) + 1, "overhead sweep")
    result = {"table": rows, "iterations": iters, "overhead": per_cut + [{**o, "sweep": True} for o in overhead],
              "steps": args.steps, "cut_every": args.cut_every, "refresh_every": args.refresh_every,
              "backend": args.backend,
              "wall_s": time.perf_counter() - t0}
    speed = {}
    for n in sorted({r["nodes"] for r in rows}):
        cg = next((r for r in rows if r["nodes"] == n and r["method"] == "cg"), None)
        sm = next((r for r in rows if r["nodes"] == n and r["method"] == "smf"), None)
        if cg and sm:
            speed[str(n)] = cg["total_ms"] / sm["total_ms"]
    result["speedup_smf_vs_cg"] = speed
    publish("cut_beam", device, result, args, plot)
    print(f"{'Nodes':>6} {'Method':<7} {'Affected':>8} {'N nodes':>7} {'Build':>7} {'Iter':>7} {'Solve':>7} {'Cut':>6} {'Total':>7}"
          f" {'Refresh':>7} {'CutEvery':>8}")
    for r in rows:
        print(f"{r['nodes']:>6} {r['method']:<7} {r['affected_nodes']:8.2f} {r['perturbation_nodes']:7.2f} {r['build_ms']:7.2f} {r['iterations']:7.2f} "
              f"{r['solve_ms']:7.2f} {r['cut_ms']:6.2f} {r['total_ms']:7.2f} {r['refresh_interval']:7.2f} "
              f"{r['cut_interval']:8.2f}")
    print(f"speed-up of SMF over CG (total step time): {speed}")
    return 0
