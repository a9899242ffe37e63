"""Error against run time over all solvers and scenes: ``python -m soft_tissue_sim.bench accuracy``.

For a user who has a time budget per step and wants to know which solver and which CG
tolerance to pick. Every (scene, solver, tolerance) runs the same trajectory; the error is
measured against a reference trajectory solved with a fresh CHOLMOD factorization every
step at tolerance 1e-12 (``direct``).

Scenes (each stresses something else):

* ``beam``: the 2,000-node beam clamped at one end swinging down under gravity (large
  rotations: the case the rotation of eq. 2 is for);
* ``brain``: the brain-like body, tumour 20 times stiffer, settling under gravity
  (heterogeneous stiffness), with its contact model built and its instruments parked;
* ``press``: the default scene's bar on its fixed base, its scalpel pressed 6 mm into it
  (contact through the LCP of eq. 3-4 every step); cutting off, so that every solver sees
  the same topology.

Solvers: plain CG, block-Jacobi PCG, PCG with the asynchronous rotated LDL^T factor, and
the same without rotation. Reported per run: mean ms per step (solve + contact), mean
iterations, max relative residual, max displacement error relative to the largest
displacement of the reference. The summary gives, per scene and error level, the fastest
(solver, tolerance) that reaches it. JSON and PNG (one panel per scene).
"""

from __future__ import annotations

import time

import numpy as np

from ..report import Progress
from ..scene import load_scene, read_scene
from .common import figure, parser, publish, resolved_device, save_figure

IDENTITY = [0.0, 0.0, 0.0, 1.0]
SOLVERS = {
    "cg": {"preconditioner": "none"},
    "jacobi": {"preconditioner": "jacobi"},
    "ldlt": {"preconditioner": "async_ldlt", "ldlt": {"rotate": True}},
    "ldlt_norot": {"preconditioner": "async_ldlt", "ldlt": {"rotate": False}},
}
REFERENCE = {"preconditioner": "direct"}
TOLERANCES = [1e-3, 1e-5, 1e-7, 1e-9]
ERROR_LEVELS = [1e-2, 1e-3, 1e-4, 1e-5]


def _press_pose(k: int, steps: int) -> np.ndarray:
    """The scalpel's tip: from 2 cm above the bar's top (z = 0.02) down to 6 mm into it by the
    middle of the run, then held."""
    s = min(1.0, k / max(1, steps // 2))
    z = 0.02 + 0.005 + 0.02 * (1.0 - s) - 0.006 * s
    return np.array([0.4, 0.0, z])


SCENES = {
    "beam": {"scene": "beam_2000.yaml", "overrides": {}, "drive": None},
    "brain": {"scene": "brain_resection.yaml", "overrides": {"cutting": None}, "drive": "park"},
    "press": {"scene": "default.yaml", "overrides": {"cutting": None, "script": None}, "drive": "press"},
}


def trajectory(key: str, solver: dict, tolerance: float, steps: int, device, max_iterations: int = 5000):
    spec = SCENES[key]
    ov = {k: v for k, v in spec["overrides"].items()}
    solver = dict(solver)
    if "ldlt" in solver:  # keep the scene's refresh interval and the like
        scene_ldlt = (read_scene(spec["scene"])[0].get("solver") or {}).get("ldlt") or {}
        solver["ldlt"] = {**scene_ldlt, **solver["ldlt"]}
    ov["solver"] = {**solver, "tolerance": tolerance, "max_iterations": max_iterations}
    sim = load_scene(spec["scene"], device=device, overrides=ov)
    stats, traj = [], []
    try:
        sim.step()  # warm-up: kernel compilation and the first factorization
        sim.reset()
        names = sim.instrument_names()
        for k in range(steps):
            if spec["drive"] == "park":
                for i, name in enumerate(names):
                    sim.set_instrument_pose(name, [0.2 + 0.05 * i, 0.0, 0.2], IDENTITY)
            elif spec["drive"] == "press":
                sim.set_instrument_pose(names[0], _press_pose(k, steps), IDENTITY)
            d = sim.step().as_dict()
            d["step_ms"] = d["total_ms"] + d.get("contact_ms", 0.0)
            stats.append(d)
            traj.append(sim.positions())
        rest = sim.mesh.points.copy()
    finally:
        sim.close()
    return stats, np.array(traj), rest


def sweep(scenes, solvers, tolerances, steps, device, progress=None):
    rows = []
    for key in scenes:
        _, ref, rest = trajectory(key, REFERENCE, 1e-12, steps, device)
        scale = float(np.abs(ref - rest).max())
        for name in solvers:
            for tol in tolerances:
                stats, traj, _ = trajectory(key, SOLVERS[name], tol, steps, device)
                err = np.abs(traj - ref).max(axis=(1, 2)) / scale
                rows.append({
                    "scene": key, "solver": name, "tolerance": tol,
                    "step_ms": float(np.mean([s["step_ms"] for s in stats])),
                    "iterations": float(np.mean([s["iterations"] for s in stats])),
                    "residual_max": float(max(s["residual"] for s in stats)),
                    "converged_fraction": float(np.mean([s["converged"] for s in stats])),
                    "error_max": float(err.max()), "error_final": float(err[-1]),
                    "reference_displacement_m": scale,
                })
                if progress:
                    progress.update(len(rows), f"{key} {name} tol {tol:.0e}: {rows[-1]['step_ms']:.1f} ms, "
                                               f"error {rows[-1]['error_max']:.1e}")
    return rows


def cheapest(rows, levels=ERROR_LEVELS):
    """Per scene and error level, the fastest (solver, tolerance) whose max error is below it."""
    out = {}
    for key in dict.fromkeys(r["scene"] for r in rows):
        out[key] = {}
        for lev in levels:
            ok = [r for r in rows if r["scene"] == key and r["error_max"] <= lev and r["converged_fraction"] == 1.0]
            best = min(ok, key=lambda r: r["step_ms"]) if ok else None
            out[key][f"{lev:.0e}"] = None if best is None else {
                "solver": best["solver"], "tolerance": best["tolerance"], "step_ms": best["step_ms"],
                "error_max": best["error_max"]}
    return out


def plot(result, prefix):
    rows = result["rows"]
    scenes = list(dict.fromkeys(r["scene"] for r in rows))
    fig, axes = figure(1, len(scenes), figsize=(6 * len(scenes), 4.6), squeeze=False)
    for ax, key in zip(axes[0], scenes):
        for name in dict.fromkeys(r["solver"] for r in rows):
            rs = [r for r in rows if r["scene"] == key and r["solver"] == name]
            ax.loglog([r["step_ms"] for r in rs], [max(r["error_max"], 1e-16) for r in rs], "o-", label=name)
            for r in rs:
                ax.annotate(f"{r['tolerance']:.0e}", (r["step_ms"], max(r["error_max"], 1e-16)), fontsize=6)
        ax.set(xlabel="ms per step (solve + contact)", ylabel="max displacement error / max displacement",
               title=key)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7)
    save_figure(fig, prefix, f"error against run time (labels: CG tolerance) on {result['device']}")


def main(argv=None) -> int:
    ap = parser("accuracy", __doc__)
    ap.add_argument("--scenes", nargs="*", default=list(SCENES), choices=list(SCENES))
    ap.add_argument("--solvers", nargs="*", default=list(SOLVERS), choices=list(SOLVERS))
    ap.add_argument("--tolerances", nargs="*", type=float, default=TOLERANCES)
    ap.add_argument("--steps", type=int, default=20)
    args = ap.parse_args(argv)
    device = resolved_device(args)
    prog = Progress(len(args.scenes) * len(args.solvers) * len(args.tolerances))
    t0 = time.perf_counter()
    rows = sweep(args.scenes, args.solvers, args.tolerances, args.steps, device, prog)
    result = {"rows": rows, "cheapest": cheapest(rows), "steps": args.steps, "wall_s": time.perf_counter() - t0}
    publish("accuracy", device, result, args, plot)
    print(f"{'scene':<6} {'error <=':>8}  fastest")
    for key, levels in result["cheapest"].items():
        for lev, best in levels.items():
            what = "none reached it" if best is None else (f"{best['solver']} tol {best['tolerance']:.0e}: "
                                                           f"{best['step_ms']:.1f} ms/step")
            print(f"{key:<6} {lev:>8}  {what}")
    return 0
