"""Haptic-rate figures of the solvers: ``python -m soft_tissue_sim.bench haptic``.

Per-step time distribution (median, p99, mean of ``Simulation.step``, which includes the
divergence guard's copies; and of the integrator step alone), PCG iterations and
preconditioner cost for

(a) the brain (config/scenes/brain_resection.yaml) settling under gravity, no instrument
    motion: without instruments, contact and cutting (``brain``), and optionally
    (``--contact``) with the instruments parked 1 m away while contact and self-collision
    stay on (``brain_contact``, best variants only);
(b) the 2,000-node beam (config/scenes/beam_2000.yaml) swinging under gravity,

for these solvers (all PCG at the scene's tolerance):

* ``cg``: plain CG, host scalars (three dot products read per iteration),
* ``cg_graph``: plain CG with device scalars, captured as a graph,
* ``cholmod``: the async rotated LDL^T of CHOLMOD on the host (on CUDA r and z are copied
  each application),
* ``dense``: the async rotated dense inverse on the device, PCG with device scalars captured
  as a graph (:mod:`soft_tissue_sim.dense_inverse`),
* ``cudss`` (CUDA): cuDSS's factor on the device, PCG with device scalars, no graph.

Also the time of one preconditioner application at the end of each run: through the
preconditioner's ``apply`` (launches from Python, synchronised) and, where it can be
captured, replayed as a graph. With device scalars the per-step preconditioner time is not
measured (that would need a synchronisation); ``precond_ms_est`` = iterations x the graph
apply time.

Targets (measured, never asserted; ``bench targets`` gathers them): on the GPU the device
factor 20x faster than plain CG on the beam (median step), and the brain's median step <= 1 ms.

Writes ``haptic_<cpu|gpu>.json`` and ``.png`` (``--out``). ``--commit-note`` is stored as
``commit_note`` (the device copy's git HEAD may be stale); ``source_digest`` hashes the
package sources that ran. ``--plot JSON`` only redraws the PNG of an existing result.
"""

from __future__ import annotations

import hashlib
import json
import time
from pathlib import Path

import numpy as np
import warp as wp

from ..paths import resolve_path
from ..scene import load_scene, read_scene
from .common import device_description, figure, parser, resolved_device, save_figure, write_result
from .timing import apply_timing

VARIANTS = {
    "cg": {"preconditioner": "none", "graph": False},
    "cg_graph": {"preconditioner": "none", "graph": True},
    "cholmod": {"preconditioner": "async_ldlt", "graph": False, "ldlt": {"backend": "cholmod"}},
    "dense": {"preconditioner": "async_ldlt", "graph": "auto", "ldlt": {"backend": "dense"}},
    "cudss": {"preconditioner": "async_ldlt", "graph": "auto", "ldlt": {"backend": "cudss"}},
}
CUDA_ONLY = {"cudss"}
CONTACT_VARIANTS = ("cholmod", "dense")


def scene_config(name: str) -> dict:
    """The scene dicts of the benchmark: brain without instruments, brain with them parked, beam."""
    if name == "beam":
        cfg, base = read_scene("beam_2000.yaml")
    else:
        cfg, base = read_scene("brain_resection.yaml")
        if name == "brain":
            for k in ("instruments", "contact", "cutting"):
                cfg.pop(k, None)
        else:  # parked 1 m above the tissue: contact and self-collision run, nothing touches
            cfg.pop("cutting", None)
            for i, ins in enumerate(cfg.get("instruments") or []):
                ins["pose"] = {"position": [0.0, 0.1 * i, 1.0], "orientation": [0, 0, 0, 1]}
    cfg["mesh"] = dict(cfg["mesh"])
    if "file" in cfg["mesh"]:
        cfg["mesh"]["file"] = str(resolve_path(cfg["mesh"]["file"], base))
    return cfg


def _dist(a) -> dict:
    a = np.asarray(a, dtype=np.float64)
    if a.size == 0 or not np.isfinite(a).any():
        return {"median": float("nan"), "p99": float("nan"), "mean": float("nan"), "max": float("nan")}
    a = a[np.isfinite(a)]
    return {"median": float(np.median(a)), "p99": float(np.percentile(a, 99)), "mean": float(a.mean()),
            "max": float(a.max())}


def run_variant(cfg: dict, variant: str, device: str, steps: int, warmup: int, reps: int) -> dict:
    solver = dict(cfg.get("solver") or {})
    v = VARIANTS[variant]
    solver.update({k: val for k, val in v.items() if k != "ldlt"})
    solver["ldlt"] = {**(solver.get("ldlt") or {}), **v.get("ldlt", {})}
    c = dict(cfg, solver=solver)
    t_load = time.perf_counter()
    sim = load_scene(c, device=device)
    try:
        for _ in range(warmup):  # compilation, first factorization, graph capture
            sim.step()
        load_s = time.perf_counter() - t_load
        wall, rows = [], []
        for _ in range(steps):
            t0 = time.perf_counter()
            st = sim.step()
            wall.append(1000.0 * (time.perf_counter() - t0))
            rows.append(st.as_dict())
        ps = sim.preconditioner.stats()
        cg = sim.integrator.cg
        applies = apply_timing(sim, reps) if hasattr(sim.preconditioner, "inner") else {}
        finite = bool(np.isfinite(sim.positions()).all())
        nodes = sim.mesh.n_nodes
    finally:
        sim.close()
    its = np.array([r["iterations"] for r in rows])
    pre_ms = np.array([r["precond_ms"] for r in rows], dtype=np.float64)
    res = {
        "steps": steps, "warmup": warmup, "nodes": nodes, "load_and_warmup_s": load_s,
        "step_ms": _dist(wall),
        "integrator_ms": _dist([r["total_ms"] for r in rows]),
        "solve_ms": _dist([r["solve_ms"] for r in rows]),
        "build_ms": _dist([r["build_ms"] for r in rows]),
        "iterations": {"mean": float(its.mean()), "median": float(np.median(its)), "max": int(its.max())},
        "converged_fraction": float(np.mean([r["converged"] for r in rows])),
        "precond_ms_per_step": _dist(pre_ms) if np.isfinite(pre_ms).any() else None,
        "apply": applies,
        "backend": ps.get("backend", "n/a"),
        "factor_count": ps.get("factor_count"), "refresh_interval": ps.get("refresh_interval"),
        "factorization_ms_last": ps.get("factorization_ms"), "factor_age_last": ps.get("factor_age"),
        "pcg": type(cg).__name__, "graph": bool(getattr(cg, "graph", False)),
        "captures": getattr(cg, "captures", 0), "replays": getattr(cg, "replays", 0),
        "host_solves": getattr(cg, "host_solves", None),
        "finite": finite,
        "step_ms_series": [round(w, 4) for w in wall],
        "iterations_series": its.tolist(),
    }
    g = applies.get("graph_apply_ms")
    res["precond_ms_est"] = float(its.mean() * g) if g is not None else None
    return res


def source_digest() -> str:
    root = Path(__file__).resolve().parents[1]
    h = hashlib.sha1()
    for p in sorted(root.rglob("*.py")):
        h.update(p.relative_to(root).as_posix().encode())
        h.update(p.read_bytes())
    return h.hexdigest()[:12]


def plot(result: dict, prefix: str) -> None:
    scenes = result["scenes"]
    fig, axes = figure(2, len(scenes), figsize=(6.5 * len(scenes), 8.5), squeeze=False)
    for j, (sname, sc) in enumerate(scenes.items()):
        names = [k for k, v in sc["variants"].items() if "error" not in v]
        data = [sc["variants"][k]["step_ms_series"] for k in names]
        ax = axes[0][j]
        if data:
            ax.boxplot(data, whis=(1, 99), showfliers=True, flierprops={"markersize": 2})
            ax.set_xticks(range(1, len(names) + 1), names, rotation=30, ha="right", fontsize=8)
        ax.set_yscale("log")
        ax.axhline(1.0, color="r", lw=0.8, ls="--")
        ax.set(ylabel="ms per step (Simulation.step)", title=f"{sname}: step time (whiskers p1-p99; red: 1 ms)")
        ax.grid(True, alpha=0.3, which="both")
        ax = axes[1][j]
        its = [sc["variants"][k]["iterations"]["mean"] for k in names]
        ax.bar(range(len(names)), its, color="C1")
        for i, k in enumerate(names):
            ap = sc["variants"][k].get("apply") or {}
            lab = ap.get("graph_apply_ms", ap.get("apply_ms"))
            if lab is not None:
                ax.text(i, its[i], f"{lab:.3g} ms/apply", ha="center", va="bottom", fontsize=7)
        ax.set_xticks(range(len(names)), names, rotation=30, ha="right", fontsize=8)
        ax.set_yscale("log")
        ax.set(ylabel="PCG iterations per step (mean)", title=f"{sname}: iterations, preconditioner apply ms")
        ax.grid(True, alpha=0.3, which="both")
    save_figure(fig, prefix, f"haptic step times on {result.get('device', '?')}")


def main(argv=None) -> int:
    ap = parser("haptic", __doc__)
    ap.add_argument("--steps", type=int, default=200, help="measured steps per variant")
    ap.add_argument("--cg-steps", type=int, default=None, help="measured steps of the plain CG variants (default --steps)")
    ap.add_argument("--warmup", type=int, default=20)
    ap.add_argument("--reps", type=int, default=50, help="preconditioner applications timed")
    ap.add_argument("--scenes", default="brain,beam", help="comma list of brain, beam")
    ap.add_argument("--variants", default=None, help=f"comma list of {', '.join(VARIANTS)} (default: all that apply)")
    ap.add_argument("--contact", action="store_true", help="also the brain with parked instruments (contact on)")
    ap.add_argument("--commit-note", default="", help="stored as commit_note (what code ran)")
    ap.add_argument("--plot", default=None, metavar="JSON", help="only redraw the PNG of this result file")
    args = ap.parse_args(argv)
    if args.plot:
        doc = json.load(open(args.plot))
        plot(doc["figures"] | {"device": doc["device"]}, str(Path(args.plot).with_suffix("")))
        return 0
    device = resolved_device(args)
    cuda = wp.get_device(device).is_cuda
    variants = args.variants.split(",") if args.variants else [v for v in VARIANTS if cuda or v not in CUDA_ONLY]
    for v in variants:
        if v not in VARIANTS:
            ap.error(f"unknown variant {v!r}")
    scenes = [s.strip() for s in args.scenes.split(",") if s.strip()]
    if args.contact and "brain" in scenes:
        scenes.append("brain_contact")
    figures = {"scenes": {}, "commit_note": args.commit_note, "source_digest": source_digest(),
               "conditional_graphs": bool(cuda and wp.is_conditional_graph_supported()),
               "settings": {"steps": args.steps, "cg_steps": args.cg_steps or args.steps, "warmup": args.warmup,
                            "reps": args.reps}}
    t_all = time.perf_counter()
    for sname in scenes:
        cfg = scene_config(sname)
        sc = {"scene": "brain_resection.yaml" if sname.startswith("brain") else "beam_2000.yaml",
              "variants": {}}
        for v in variants if sname != "brain_contact" else [v for v in variants if v in CONTACT_VARIANTS]:
            t0 = time.perf_counter()
            try:
                n_steps = args.cg_steps if (v.startswith("cg") and args.cg_steps) else args.steps
                sc["variants"][v] = run_variant(cfg, v, device, n_steps, args.warmup, args.reps)
            except Exception as exc:  # noqa: BLE001 - recorded, the other variants still run
                sc["variants"][v] = {"error": f"{type(exc).__name__}: {exc}"}
            r = sc["variants"][v]
            if "error" in r:
                print(f"{sname:>13} {v:<26} ERROR {r['error']}", flush=True)
            else:
                a = r["apply"]
                print(f"{sname:>13} {v:<26} step median {r['step_ms']['median']:8.3f} p99 {r['step_ms']['p99']:8.3f} "
                      f"mean {r['step_ms']['mean']:8.3f} ms | integ median {r['integrator_ms']['median']:8.3f} | "
                      f"it {r['iterations']['mean']:7.2f} | apply graph {a.get('graph_apply_ms', float('nan')):.4f} "
                      f"launched {a.get('apply_ms', float('nan')):.4f} ms"
                      f" [{time.perf_counter() - t0:.1f} s]", flush=True)
        figures["scenes"][sname] = sc
    summ = {}
    for sname in ("beam", "brain"):
        vs = (figures["scenes"].get(sname) or {}).get("variants", {})
        base, best = vs.get("cg", {}), vs.get("dense", {})
        if "step_ms" in base and "step_ms" in best:
            summ[f"{sname}_speedup_dense_over_cg_median_step"] = base["step_ms"]["median"] / best["step_ms"]["median"]
            summ[f"{sname}_speedup_dense_over_cg_mean_step"] = base["step_ms"]["mean"] / best["step_ms"]["mean"]
        for other in ("cg_graph", "cholmod"):
            o = vs.get(other, {})
            if "step_ms" in o and "step_ms" in best:
                summ[f"{sname}_speedup_dense_over_{other}_median_step"] = o["step_ms"]["median"] / best["step_ms"]["median"]
        if "step_ms" in best:
            summ[f"{sname}_dense_median_step_ms"] = best["step_ms"]["median"]
            summ[f"{sname}_dense_p99_step_ms"] = best["step_ms"]["p99"]
    if not cuda:
        summ["note"] = "targets are for the GPU; this run is on the CPU backend"
    figures["summary"] = summ
    figures["wall_s"] = time.perf_counter() - t_all
    path = write_result("haptic", device, figures, args.out)
    try:
        plot(figures | {"device": device_description(device)}, str(path.with_suffix("")))
        print(f"wrote {path} and {path.with_suffix('.png')}")
    except ImportError as exc:
        print(f"wrote {path} (no PNG: {exc}; redraw with --plot {path})")
    for k, v in summ.items():
        print(f"  {k}: {v}")
    return 0
