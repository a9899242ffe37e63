"""Error against run time for every solver: ``python -m soft_tissue_sim.bench solvers``.

One trajectory per solver on the same scene (the beam clamped at one end, swinging down):

* ``cg``: plain CG (the paper's CGM), ``jacobi``: block-Jacobi PCG,
* ``ldlt``: PCG with the asynchronous LDL^T factor rotated by the nodal rotations (eq. 2),
* ``ldlt_norot``: the same factor without the rotation,
* ``direct``: a fresh CHOLMOD factorization every step (the reference trajectory).

Outputs (JSON + PNG under benchmarks/results/):

(a) error against wall time per step, sweeping the CG tolerance from 1e-3 to 1e-10, with
    both the relative residual reached and the displacement error against the reference;
(b) iterations per step over the trajectory at tolerance 1e-7;
(c) the paper's table (Nodes, Method, Build, Iterations, Solve, Total) for the three beams.
"""

from __future__ import annotations

import time

import numpy as np

from ..report import Progress
from ..scene import load_scene
from .common import figure, parser, publish, resolved_device, save_figure

METHODS = {
    "cg": {"preconditioner": "none"},
    "jacobi": {"preconditioner": "jacobi"},
    "ldlt": {"preconditioner": "async_ldlt", "ldlt": {"rotate": True}},
    "ldlt_norot": {"preconditioner": "async_ldlt", "ldlt": {"rotate": False}},
    "direct": {"preconditioner": "direct"},
}
TOLERANCES = [1e-3, 1e-4, 1e-5, 1e-6, 1e-7, 1e-8, 1e-9, 1e-10]


def run_trajectory(scene: str, method: str, steps: int, tolerance: float, device, max_iterations=5000,
                   deterministic=False):
    solver = {**METHODS[method], "tolerance": tolerance, "max_iterations": max_iterations}
    if "ldlt" in solver and deterministic:
        solver["ldlt"] = {**solver["ldlt"], "deterministic": True, "refresh_every": 4}
    sim = load_scene(scene, device=device, overrides={"solver": solver})
    stats, traj = [], []
    try:
        sim.step()  # warm-up: kernel compilation and the first (synchronous) factorization
        sim.reset()
        for _ in range(steps):
            stats.append(sim.step().as_dict())
            traj.append(sim.positions())
        nodes = sim.mesh.n_nodes
        rest = sim.mesh.points.copy()
    finally:
        sim.close()
    return stats, np.array(traj), nodes, rest


def _mean(stats, key):
    return float(np.mean([s[key] for s in stats]))


def sweep(scene, steps, device, methods, tolerances, progress=None):
    """(a): per method and tolerance, mean step time, residual and error vs the direct reference."""
    ref_stats, ref, _, rest = run_trajectory(scene, "direct", steps, 1e-12, device)
    scale = np.abs(ref - rest).max()
    out = []
    for m in methods:
        for tol in tolerances:
            stats, traj, nodes, _ = run_trajectory(scene, m, steps, tol, device)
            err = np.abs(traj - ref).max(axis=(1, 2)) / scale
            out.append({
                "method": m, "tolerance": tol, "nodes": nodes,
                "total_ms": _mean(stats, "total_ms"), "solve_ms": _mean(stats, "solve_ms"),
                "iterations": _mean(stats, "iterations"),
                "residual_mean": _mean(stats, "residual"), "residual_max": float(max(s["residual"] for s in stats)),
                "displacement_error_max": float(err.max()), "displacement_error_final": float(err[-1]),
                "refresh_interval": _mean(stats, "refresh_interval"),
            })
            if progress:
                progress.update(len(out), f"{m} tol {tol:.0e}")
    return out


def paper_table(scenes, steps, device, methods, progress=None):
    """(c) and (b): one trajectory per beam and method at tolerance 1e-7."""
    rows, iters = [], {}
    for scene in scenes:
        for m in methods:
            stats, _, nodes, _ = run_trajectory(scene, m, steps, 1e-7, device)
            rows.append({
                "nodes": nodes, "method": m, "build_ms": _mean(stats, "build_ms"),
                "iterations": _mean(stats, "iterations"), "solve_ms": _mean(stats, "solve_ms"),
                "total_ms": _mean(stats, "total_ms"), "precond_ms": _mean(stats, "precond_ms"),
                "factorization_ms": _mean([s for s in stats if s["factorization_ms"] > 0] or stats,
                                          "factorization_ms"),
                "refresh_interval": stats[-1]["refresh_interval"],
                "factor_age_mean": _mean(stats, "factor_age"),
                "converged_fraction": float(np.mean([s["converged"] for s in stats])),
            })
            iters[f"{nodes}/{m}"] = [s["iterations"] for s in stats]
            if progress:
                progress.update(len(rows), f"{scene} {m}")
    return rows, iters


def plot(result, path_prefix):
    fig, axes = figure(1, 3, figsize=(17, 5))
    for m in dict.fromkeys(r["method"] for r in result["sweep"]):
        rs = [r for r in result["sweep"] if r["method"] == m]
        t = [r["total_ms"] for r in rs]
        axes[0].loglog(t, [max(r["residual_max"], 1e-16) for r in rs], "o-", label=m)
        axes[1].loglog(t, [max(r["displacement_error_max"], 1e-16) for r in rs], "o-", label=m)
    axes[0].set(xlabel="wall time per step (ms)", ylabel="max relative residual",
                title=f"(a) residual vs time, {result['sweep'][0]['nodes']} nodes")
    axes[1].set(xlabel="wall time per step (ms)", ylabel="max displacement error / max displacement",
                title="(a) error vs direct solve")
    for k, v in result["iterations"].items():
        axes[2].semilogy(v, label=k)
    axes[2].set(xlabel="step", ylabel="PCG iterations (tol 1e-7)", title="(b) iterations per step")
    for ax in axes:
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7)
    save_figure(fig, path_prefix, f"solvers on {result['device']}")


def main(argv=None) -> int:
    ap = parser("solvers", __doc__)
    ap.add_argument("--scene", default="beam_2000.yaml", help="scene for the tolerance sweep (a)")
    ap.add_argument("--table-scenes", nargs="*", default=["beam_1200.yaml", "beam_1600.yaml", "beam_2000.yaml"])
    ap.add_argument("--steps", type=int, default=60, help="steps per trajectory (table)")
    ap.add_argument("--sweep-steps", type=int, default=25, help="steps per trajectory (sweep)")
    ap.add_argument("--methods", nargs="*", default=list(METHODS))
    ap.add_argument("--tolerances", nargs="*", type=float, default=TOLERANCES)
    args = ap.parse_args(argv)
    device = resolved_device(args)
    sweep_methods = [m for m in args.methods if m != "direct"]
    prog = Progress(len(sweep_methods) * len(args.tolerances) + len(args.table_scenes) * len(args.methods))
    t0 = time.perf_counter()
    rows, iters = paper_table(args.table_scenes, args.steps, device, args.methods, prog)
    sw = sweep(args.scene, args.sweep_steps, device, sweep_methods, args.tolerances, prog)
    result = {"table": rows, "iterations": iters, "sweep": sw, "steps": args.steps, "sweep_steps": args.sweep_steps,
              "wall_s": time.perf_counter() - t0}
    for nodes in sorted({r["nodes"] for r in rows}):
        cg = next((r for r in rows if r["nodes"] == nodes and r["method"] == "cg"), None)
        ld = next((r for r in rows if r["nodes"] == nodes and r["method"] == "ldlt"), None)
        if cg and ld:
            result.setdefault("speedup_ldlt_vs_cg", {})[str(nodes)] = cg["total_ms"] / ld["total_ms"]
    publish("solvers", device, result, args, plot)
    hdr = f"{'Nodes':>6} {'Method':<11} {'Build(ms)':>9} {'Iter':>8} {'Solve(ms)':>9} {'Total(ms)':>9} {'Refresh':>7}"
    print(hdr)
    for r in rows:
        print(f"{r['nodes']:>6} {r['method']:<11} {r['build_ms']:9.2f} {r['iterations']:8.2f} {r['solve_ms']:9.2f} "
              f"{r['total_ms']:9.2f} {r['refresh_interval']:7.2f}")
    print(f"speed-up of async LDL^T over CG: {result.get('speedup_ldlt_vs_cg')}")
    return 0
