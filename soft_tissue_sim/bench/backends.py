"""The factor backends against body size: ``python -m soft_tissue_sim.bench backends``.

For beams of growing length (5 x 5 cross-section, 1 cm spacing) and the brain, and each
backend (``cholmod`` on the host, ``dense`` and ``cudss`` on a GPU): one application of the
preconditioner (replayed in a CUDA graph where it can be, else launched and synchronised),
the wall time of one new factor (assembly, factorization, install), and the median step and
mean iterations of a beam swinging under gravity with a factor requested every 4 steps.
This is the measurement behind ``ldlt.dense_max_dofs``: the size up to which ``auto``
chooses the dense inverse. Writes ``backends_<cpu|gpu>.json`` and ``.png``.
"""

from __future__ import annotations

import argparse
import json

import numpy as np
import warp as wp

from ..scene import load_scene, read_scene, resolve_device, resolve_path
from . import RESULTS_DIR, write_result
from .timing import apply_timing, refresh_timing, timed_steps


def body(kind: str, n_long: int = 0) -> dict:
    if kind == "brain":
        cfg, base = read_scene("brain_resection.yaml")
        for k in ("instruments", "contact", "cutting"):
            cfg.pop(k, None)
        cfg["mesh"] = {"file": str(resolve_path(cfg["mesh"]["file"], base))}
        return cfg
    return {"name": f"beam_{25 * n_long}", "mesh": {"generator": "beam", "n_long": n_long, "n_cross": 5, "spacing": 0.01},
            "materials": [{"id": 0, "young": 5.0e4, "poisson": 0.3, "density": 1000.0}],
            "damping": {"mass": 0.1, "stiffness": 0.01}, "fixed": {"axis": "x", "below": 0.0}, "time": {"dt": 0.01}}


def measure(cfg: dict, backend: str, device: str, steps: int, reps: int = 50) -> dict:
    solver = {"preconditioner": "async_ldlt", "tolerance": 1e-6, "max_iterations": 2000,
              "ldlt": {"backend": backend, "refresh_every": 4}}
    with load_scene(cfg, device=device, overrides={"solver": solver}) as sim:
        for _ in range(3):
            sim.step()
        walls, stats = timed_steps(sim, steps)
        pre, integ = sim.preconditioner, sim.integrator
        integ.build()
        pre.begin_step(integ)
        t = apply_timing(sim, reps)
        graph = "graph_apply_ms" in t
        apply_ms = t["graph_apply_ms"] if graph else t["apply_ms"]
        factor_ms = refresh_timing(sim, 3)
        n = sim.mesh.n_nodes
        return {"nodes": n, "dofs": 3 * n, "backend": backend, "apply_ms": apply_ms, "apply_in_graph": graph,
                "factor_ms": factor_ms, "step_ms_median": float(np.median(walls)),
                "iterations_mean": float(np.mean([st.iterations for st in stats]))}


def plot(result, prefix):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(16, 4.5))
    for b in dict.fromkeys(r["backend"] for r in result["rows"]):
        rs = sorted((r for r in result["rows"] if r["backend"] == b and "error" not in r), key=lambda r: r["dofs"])
        x = [r["dofs"] for r in rs]
        for ax, key in zip(axes, ("apply_ms", "factor_ms", "step_ms_median")):
            ax.plot(x, [r[key] for r in rs], "o-", label=b)
    for ax, t in zip(axes, ("one application (ms)", "one new factor, wall (ms)", "median step (ms)")):
        ax.set(xscale="log", yscale="log", xlabel="degrees of freedom", title=t)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend()
    fig.suptitle(f"factor backends on {result['device']}")
    fig.tight_layout()
    fig.savefig(f"{prefix}.png", dpi=100)
    plt.close(fig)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m soft_tissue_sim.bench backends", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default=None)
    ap.add_argument("--lengths", default="40,80,128,192,256", help="beam lengths in nodes (x 25 nodes)")
    ap.add_argument("--backends", default=None, help="comma list (default: cholmod, and dense, cudss on a GPU)")
    ap.add_argument("--steps", type=int, default=40)
    ap.add_argument("--out", default=str(RESULTS_DIR))
    args = ap.parse_args(argv)
    device = resolve_device(args.device)
    cuda = wp.get_device(device).is_cuda
    backends = args.backends.split(",") if args.backends else (["cholmod", "dense", "cudss"] if cuda else ["cholmod",
                                                                                                       "dense"])
    bodies = [("brain", 0)] + [("beam", int(n)) for n in args.lengths.split(",")]
    rows = []
    for kind, n_long in bodies:
        for b in backends:
            try:
                r = measure(body(kind, n_long), b, device, args.steps)
            except Exception as exc:  # noqa: BLE001 - recorded; the other rows still run
                r = {"backend": b, "dofs": 0, "error": f"{type(exc).__name__}: {exc}"}
            r["body"] = kind if kind == "brain" else f"beam 5x5x{n_long}"
            rows.append(r)
            print(json.dumps(r), flush=True)
    path = write_result("backends", device, {"rows": rows}, args.out)
    doc = json.load(open(path))
    plot({"rows": rows, "device": doc["device"]}, str(path.with_suffix("")))
    print(f"wrote {path}")
    return 0
