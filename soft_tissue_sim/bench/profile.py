"""Profile of one step: ``python -m soft_tissue_sim.bench profile [--scene default.yaml]``.

After warm-up, ``--steps`` steps are run under Warp's CUDA activity timing (kernels, memory
copies and sets, per name; CUDA devices only) and under cProfile (host time per function).
Writes ``profile_<cpu|gpu>.json``: per-step totals, kernels and copies grouped by name with
their count and total ms, and the host functions with the largest cumulative time.
"""

from __future__ import annotations

import cProfile
import pstats
import time
from collections import defaultdict

import numpy as np
import warp as wp

from ..scene import load_scene
from .common import parser, publish, resolved_device


def main(argv=None) -> int:
    ap = parser("profile", __doc__)
    ap.add_argument("--scene", default="beam_2000.yaml")
    ap.add_argument("--steps", type=int, default=20)
    args = ap.parse_args(argv)
    device = resolved_device(args)
    sim = load_scene(args.scene, device=device)
    try:
        for _ in range(5):  # warm-up: compilation, first factorization
            sim.step()
        cuda = wp.get_device(device).is_cuda
        if cuda:
            wp.timing_begin(cuda_filter=wp.TIMING_ALL)
        prof = cProfile.Profile()
        t0 = time.perf_counter()
        prof.enable()
        stats = [sim.step() for _ in range(args.steps)]
        prof.disable()
        wall = 1000.0 * (time.perf_counter() - t0) / args.steps
        activity = wp.timing_end() if cuda else []
    finally:
        sim.close()
    groups = defaultdict(lambda: {"count": 0, "ms": 0.0, "kind": ""})
    for r in activity:
        g = groups[r.name]
        g["count"] += 1
        g["ms"] += r.elapsed
        g["kind"] = {wp.TIMING_KERNEL: "kernel", wp.TIMING_KERNEL_BUILTIN: "kernel (builtin)",
                     wp.TIMING_MEMCPY: "memcpy", wp.TIMING_MEMSET: "memset",
                     wp.TIMING_GRAPH: "graph"}.get(r.filter, str(r.filter))
    per_kind = defaultdict(lambda: {"count": 0, "ms": 0.0})
    for g in groups.values():
        per_kind[g["kind"]]["count"] += g["count"]
        per_kind[g["kind"]]["ms"] += g["ms"]
    st = pstats.Stats(prof)
    host = []
    for (fn, line, name), (cc, nc, tt, ct, _callers) in st.stats.items():
        host.append({"function": f"{fn.split('site-packages/')[-1].split('soft_tissue_sim/')[-1]}:{line}({name})",
                     "calls": nc, "own_ms": 1000.0 * tt / args.steps, "cumulative_ms": 1000.0 * ct / args.steps})
    host.sort(key=lambda h: -h["cumulative_ms"])
    n = args.steps
    figures = {
        "scene": args.scene, "steps": n, "wall_ms_per_step_profiled": wall,
        "iterations_mean": float(np.mean([s.iterations for s in stats])),
        "solve_ms_mean": float(np.mean([s.solve_ms for s in stats])),
        "precond_ms_mean": float(np.mean([s.precond_ms for s in stats])),
        "device_activity_per_step": {k: {"count": v["count"] / n, "ms": v["ms"] / n} for k, v in per_kind.items()},
        "device_by_name_per_step": sorted(({"name": k, "kind": v["kind"], "count": v["count"] / n, "ms": v["ms"] / n}
                                           for k, v in groups.items()), key=lambda g: -g["ms"])[:40],
        "host_top_per_step": host[:40],
        "note": "cProfile adds overhead to the host time; the device figures are CUDA event timings",
    }
    publish("profile", device, figures, args)
    print(f"{args.scene}: {wall:.2f} ms/step under the profilers, {figures['iterations_mean']:.2f} iterations")
    for k, v in figures["device_activity_per_step"].items():
        print(f"  device {k:<18} {v['count']:8.1f} per step {v['ms']:8.3f} ms")
    for h in host[:15]:
        print(f"  host {h['cumulative_ms']:8.2f} ms cum {h['own_ms']:8.2f} own  {h['calls'] / n:7.1f}x  {h['function']}")
    return 0
