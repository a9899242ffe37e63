"""Cost against mesh size: ``python -m soft_tissue_sim.bench scaling``.

Beams (a square cross-section of c x c nodes, 1 cm spacing, clamped at x = 0, swinging under
gravity) and brain-like bodies (the brain mesh, uniformly refined by splitting every tet
into 8) from about 1,000 to 200,000 nodes. For each size and solver (CG, block-Jacobi PCG,
async rotated LDL^T): median and mean step time, iterations, factorization time, and memory
(growth of device memory in use for CUDA, of the process's resident memory for the CPU), after a
warm-up step. JSON and a log-log plot under benchmarks/results/.
"""

from __future__ import annotations

import json
import resource
import time

import numpy as np
import warp as wp

from ..mesh import TetMesh, brain_mesh, validate_mesh
from ..report import Progress
from ..scene import Simulation
from .common import figure, parser, publish, resolved_device, save_figure

SOLVERS = {
    "cg": {"preconditioner": "none"},
    "jacobi": {"preconditioner": "jacobi"},
    "ldlt": {"preconditioner": "async_ldlt", "ldlt": {"rotate": True, "refresh_every": 4}},
}
BEAMS = [(40, 5), (80, 5), (100, 8), (160, 10), (250, 14), (330, 20), (500, 20)]  # (n_long, n_cross)


def refine(mesh: TetMesh) -> TetMesh:
    """Split every tet into 8 (edge midpoints; the inner octahedron cut along one diagonal)."""
    P, T = mesh.points, mesh.tets.astype(np.int64)
    E = np.sort(T[:, [[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]]].reshape(-1, 2), axis=1)
    uniq, inv = np.unique(E, axis=0, return_inverse=True)
    mid = P.shape[0] + inv.reshape(-1, 6)
    pts = np.concatenate([P, 0.5 * (P[uniq[:, 0]] + P[uniq[:, 1]])])
    a, b, c, d = T.T
    m01, m02, m03, m12, m13, m23 = mid.T
    kids = np.stack([
        [a, m01, m02, m03], [m01, b, m12, m13], [m02, m12, c, m23], [m03, m13, m23, d],
        [m01, m02, m03, m13], [m01, m02, m13, m12], [m02, m03, m13, m23], [m02, m13, m12, m23],
    ], axis=0).transpose(2, 0, 1).reshape(-1, 4)
    vol = np.einsum("ij,ij->i", pts[kids[:, 1]] - pts[kids[:, 0]],
                    np.cross(pts[kids[:, 2]] - pts[kids[:, 0]], pts[kids[:, 3]] - pts[kids[:, 0]]))
    kids[vol < 0] = kids[vol < 0][:, [0, 2, 1, 3]]
    return validate_mesh(pts, kids, np.repeat(mesh.material_ids, 8))


def body_configs():
    out = []
    for n_long, c in BEAMS:
        out.append(("beam", n_long * c * c, {"generator": "beam", "n_long": n_long, "n_cross": c, "spacing": 0.01}))
    m = brain_mesh()
    for level in range(3):
        out.append(("brain", m.n_nodes, m))
        if level < 2:
            m = refine(m)
    return out


def scene_for(kind, mesh_spec, solver):
    cfg = {
        "name": f"scaling_{kind}",
        "materials": [{"id": 0, "young": 1e5, "poisson": 0.3, "density": 1000.0},
                      {"id": 1, "young": 2e6, "poisson": 0.3, "density": 1000.0}],
        "damping": {"mass": 0.1, "stiffness": 0.005},
        "time": {"dt": 0.01},
        "solver": {**SOLVERS[solver], "tolerance": 1e-6, "max_iterations": 3000},
    }
    if kind == "beam":
        cfg["mesh"] = mesh_spec
        cfg["fixed"] = {"axis": "x", "below": 0.0}
    else:
        zmin = float(mesh_spec.points[:, 2].min())
        cfg["mesh"] = {"generator": "brain"}  # replaced below by the refined mesh
        cfg["fixed"] = {"axis": "z", "below": zmin + 0.15 * float(np.ptp(mesh_spec.points[:, 2]))}
    return cfg


def memory_mb(device) -> float:
    d = wp.get_device(device)
    if d.is_cuda:
        return (d.total_memory - d.free_memory) / 2**20
    try:  # current resident set size of the process
        with open("/proc/self/statm") as fh:
            return int(fh.read().split()[1]) * resource.getpagesize() / 2**20
    except OSError:
        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def run(kind, mesh_spec, solver, steps, device):
    cfg = scene_for(kind, mesh_spec, solver)
    mem0 = memory_mb(device)
    if kind == "brain":
        import soft_tissue_sim.scene as scene_mod

        orig = scene_mod.build_mesh
        scene_mod.build_mesh = lambda spec, base: mesh_spec
        try:
            sim = Simulation(cfg, None, device)
        finally:
            scene_mod.build_mesh = orig
    else:
        sim = Simulation(cfg, None, device)
    try:
        sim.step()  # warm-up: compile, first synchronous factorization
        stats = [sim.step() for _ in range(steps)]
        mem = memory_mb(device) - mem0
        tot = [s.total_ms for s in stats]
        return {
            "kind": kind, "nodes": sim.mesh.n_nodes, "dofs": 3 * sim.mesh.n_nodes, "tets": sim.mesh.n_tets,
            "solver": solver, "steps": steps,
            "step_ms_median": float(np.median(tot)), "step_ms_mean": float(np.mean(tot)),
            "iterations": float(np.mean([s.iterations for s in stats])),
            "converged_fraction": float(np.mean([s.converged for s in stats])),
            "factorization_ms": float(max(s.factorization_ms for s in stats)),
            "memory_mb": float(mem), "steps_per_s": 1000.0 / float(np.median(tot)),
        }
    finally:
        sim.close()


def plot(result, prefix):
    rows = result["rows"]
    fig, axes = figure(1, 3, figsize=(17, 5))
    for kind, mk in (("beam", "o-"), ("brain", "s--")):
        for solver in dict.fromkeys(r["solver"] for r in rows):
            rs = sorted([r for r in rows if r["kind"] == kind and r["solver"] == solver], key=lambda r: r["dofs"])
            if not rs:
                continue
            d = [r["dofs"] for r in rs]
            axes[0].loglog(d, [r["step_ms_median"] for r in rs], mk, label=f"{kind} {solver}")
            axes[1].loglog(d, [max(r["iterations"], 0.5) for r in rs], mk, label=f"{kind} {solver}")
            axes[2].loglog(d, [max(r["memory_mb"], 1e-1) for r in rs], mk, label=f"{kind} {solver}")
    axes[0].axhline(1000.0 / 60.0, color="k", lw=0.8, ls=":", label="60 steps/s")
    axes[0].set(xlabel="degrees of freedom", ylabel="median step (ms)", title="step time")
    axes[1].set(xlabel="degrees of freedom", ylabel="PCG iterations per step (tol 1e-6)", title="iterations")
    axes[2].set(xlabel="degrees of freedom", ylabel="MB", title="memory growth (device in use / process RSS)")
    for ax in axes:
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7)
    save_figure(fig, prefix, f"scaling on {result['device']}")


def main(argv=None) -> int:
    ap = parser("scaling", __doc__)
    ap.add_argument("--steps", type=int, default=8)
    ap.add_argument("--max-nodes", type=int, default=200_000)
    ap.add_argument("--min-nodes", type=int, default=0, help="only bodies of at least this many nodes")
    ap.add_argument("--solvers", nargs="*", default=list(SOLVERS))
    ap.add_argument("--budget-s", type=float, default=480.0, help="stop starting new runs after this")
    args = ap.parse_args(argv)
    device = resolved_device(args)
    bodies = [b for b in body_configs() if args.min_nodes <= b[1] <= args.max_nodes]
    prog = Progress(len(bodies) * len(args.solvers))
    rows, t0 = [], time.perf_counter()
    skipped = []
    for kind, n, spec in sorted(bodies, key=lambda b: b[1]):
        for solver in args.solvers:
            if time.perf_counter() - t0 > args.budget_s:
                skipped.append(f"{kind} {n} {solver}")
                continue
            try:
                rows.append(run(kind, spec, solver, args.steps, device))
                r = rows[-1]
                msg = f"{kind} {r['nodes']} {solver}: {r['step_ms_median']:.2f} ms, {r['iterations']:.1f} it"
            except Exception as exc:  # noqa: BLE001 - out of memory etc. is a result
                rows.append({"kind": kind, "nodes": n, "dofs": 3 * n, "solver": solver, "error": str(exc)})
                msg = f"{kind} {n} {solver}: {exc}"
            prog.update(len(rows), msg)
            json.dumps(rows[-1])
    ok = [r for r in rows if "error" not in r]
    result = {"rows": ok, "failed": [r for r in rows if "error" in r], "skipped_for_time": skipped,
              "wall_s": time.perf_counter() - t0}
    publish("scaling", device, result, args, plot)
    for r in ok:
        print(f"{r['kind']:<6} {r['nodes']:>7} {r['solver']:<7} {r['step_ms_median']:9.2f} ms {r['iterations']:8.1f} it "
              f"{r['memory_mb']:8.1f} MB {r['steps_per_s']:8.1f} steps/s")
    return 0
