"""Command line: ``python -m soft_tissue_sim run|mesh ...``."""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from .report import Progress, summarize, table


def _run(args) -> int:
    from .scene import load_scene

    sim = load_scene(args.scene, device=args.device)
    print(f"scene {sim.name}: {sim.mesh.n_nodes} nodes, {sim.mesh.n_tets} tets, device {sim.device}, "
          f"dt {sim.dt} s, preconditioner {sim.preconditioner.name}", flush=True)
    progress = Progress(args.steps)
    stats = []
    t0 = time.perf_counter()
    try:
        for k in range(args.steps):
            s = sim.step().as_dict()
            stats.append(s)
            progress.update(k + 1, f"{s['total_ms']:7.2f} ms/step  it {s['iterations']:4d}  res {s['residual']:.1e}")
    finally:
        sim.close()
    wall = time.perf_counter() - t0
    summary = summarize(stats)
    summary.update({"scene": sim.name, "device": sim.device, "nodes": sim.mesh.n_nodes, "tets": sim.mesh.n_tets,
                    "wall_s": wall})
    print(table(list(summary.items()), f"summary: {sim.name}"))
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        with open(args.json, "w") as fh:
            json.dump({"summary": summary, "steps": stats}, fh, indent=1, default=str)
        print(f"wrote {args.json}")
    return 0


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv and argv[0] == "mesh":
        from .mesh import cli

        return cli(argv[1:]) or 0
    ap = argparse.ArgumentParser(prog="python -m soft_tissue_sim", description=__doc__)
    sub = ap.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("run", help="run a scene headless and print a summary")
    r.add_argument("--scene", default="default.yaml", help="scene YAML (path or name in config/scenes)")
    r.add_argument("--steps", type=int, default=200)
    r.add_argument("--device", default=None, help="cpu | cuda | cuda:N (default: the scene's, auto)")
    r.add_argument("--json", default=None, help="write per-step statistics and the summary here")
    sub.add_parser("mesh", help="generate or inspect meshes (python -m soft_tissue_sim mesh --help)")
    args = ap.parse_args(argv)
    if args.cmd == "run":
        return _run(args)
    return 1


if __name__ == "__main__":
    sys.exit(main())
