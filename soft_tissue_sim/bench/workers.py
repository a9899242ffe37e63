"""Where the asynchronous factorization runs: ``python -m soft_tissue_sim.bench workers``.

The async LDL^T preconditioner factorizes in the background with CHOLMOD. Workers:

* ``thread``: a thread, CHOLMOD called through :mod:`soft_tissue_sim.cholmod_nogil`, which
  frees the GIL while it factorizes: the factorization runs beside the step;
* ``thread-gil``: the same thread through scikit-sparse, which holds the GIL while it
  factorizes (``ldlt.release_gil: false``): the step waits through every factorization;
* ``process``: two factorization processes swap roles (one solves with the installed
  factor, the other factorizes the next snapshot) and nothing is shared but a socket.

Per scene and worker, over ``--steps`` steps after ``--warmup``: the step time
(``Simulation.step``: median, mean, p99, max), PCG iterations, the factors installed and the
last factorization time. Scenes (CPU by default), all without instruments, contact or
cutting so that the step is the solver and the refresh only:

* ``brain``: config/scenes/brain_resection.yaml settling under gravity (1,734 nodes, a
  factor requested every 3 steps here, whatever the scene says);
* ``beam_2000``: config/scenes/beam_2000.yaml swinging under gravity (refresh every 4).

The full resection with either worker: ``python -m soft_tissue_sim.bench brain --worker ...``.
Writes ``workers_<cpu|gpu>.json`` and ``.png`` (step-time distributions).
"""

from __future__ import annotations

import time

import numpy as np

from ..report import Progress
from ..scene import load_scene, read_scene
from .common import figure, parser, publish, resolved_device, rounded, save_figure

SCENES = {"brain": "brain_resection.yaml", "beam_2000": "beam_2000.yaml"}
WORKERS = ("thread", "thread-gil", "process")
REFRESH = {"brain": 3}  # fixed here, so that results stay comparable when a scene's setting changes


def scene_config(name: str) -> dict:
    """The scene without instruments, obstacles, contact or cutting (its mesh is found in the
    package, as for any scene given as a dict)."""
    cfg, _ = read_scene(SCENES[name])
    for key in ("instruments", "obstacles", "contact", "cutting", "script"):
        cfg.pop(key, None)
    return cfg


def run(name: str, worker: str, device: str, steps: int, warmup: int) -> dict:
    cfg = scene_config(name)
    solver = dict(cfg.get("solver") or {})
    solver["ldlt"] = {**(solver.get("ldlt") or {}), "worker": worker.split("-")[0], "deterministic": False,
                      "release_gil": worker != "thread-gil"}
    if name in REFRESH:
        solver["ldlt"]["refresh_every"] = REFRESH[name]
    cfg["solver"] = solver
    with load_scene(cfg, device=device) as sim:
        for _ in range(warmup):
            sim.step()
        ms, its = [], []
        for _ in range(steps):
            t0 = time.perf_counter()
            s = sim.step()
            ms.append(1000.0 * (time.perf_counter() - t0))
            its.append(s.iterations)
        st = sim.preconditioner.stats()
        ms = np.array(ms)
        return {"scene": name, "worker": worker, "nodes": sim.fem.n_nodes, "steps": steps,
                "refresh_every": int(solver["ldlt"].get("refresh_every", 1)),
                "step_ms_median": float(np.median(ms)), "step_ms_mean": float(ms.mean()),
                "step_ms_p99": float(np.percentile(ms, 99)), "step_ms_max": float(ms.max()),
                "iterations_mean": float(np.mean(its)), "factors_installed": int(st["factor_count"]),
                "factorization_ms_last": float(st["factorization_ms"]), "worker_error": st.get("worker_error"),
                "step_ms": rounded(ms.tolist())}


def plot(result: dict, prefix: str) -> None:
    rows = result["runs"]
    scenes = list(dict.fromkeys(r["scene"] for r in rows))
    fig, axes = figure(1, len(scenes), figsize=(6.5 * len(scenes), 4.5), squeeze=False)
    for ax, sc in zip(axes[0], scenes):
        for r in rows:
            if r["scene"] == sc:
                ax.plot(np.sort(r["step_ms"]), np.linspace(0, 1, len(r["step_ms"])), drawstyle="steps-post",
                        label=f"{r['worker']}: median {r['step_ms_median']:.1f}, p99 {r['step_ms_p99']:.0f} ms")
        ax.set(xscale="log", xlabel="step time (ms)", ylabel="fraction of steps", title=f"{sc} ({rows[0]['steps']} steps)")
        ax.grid(True, alpha=0.3)
        ax.legend()
    save_figure(fig, prefix, f"async LDL^T factorization in a thread or in worker processes, {result['device']}")


def main(argv=None) -> int:
    ap = parser("workers", __doc__, device="cpu")
    ap.add_argument("--scenes", nargs="*", default=list(SCENES), choices=list(SCENES))
    ap.add_argument("--workers", nargs="*", default=list(WORKERS), choices=list(WORKERS))
    ap.add_argument("--steps", type=int, default=200)
    ap.add_argument("--warmup", type=int, default=10)
    ap.add_argument("--repeat", type=int, default=2, help="runs per scene and worker (alternating)")
    args = ap.parse_args(argv)
    device = resolved_device(args)
    jobs = [(sc, w) for sc in args.scenes for _ in range(args.repeat) for w in args.workers]
    prog = Progress(len(jobs))
    rows = []
    for sc, w in jobs:
        rows.append(run(sc, w, device, args.steps, args.warmup))
        r = rows[-1]
        prog.update(len(rows), f"{sc} {w}: median {r['step_ms_median']:.1f} ms, mean {r['step_ms_mean']:.1f}, "
                               f"p99 {r['step_ms_p99']:.0f}")
    result = {"runs": rows, "steps": args.steps, "warmup": args.warmup, "repeat": args.repeat}
    publish("workers", device, result, args, plot)
    print(f"{'scene':>10} {'worker':>10} {'median':>8} {'mean':>8} {'p99':>8} {'iter':>6} {'factors':>8}")
    for r in rows:
        print(f"{r['scene']:>10} {r['worker']:>10} {r['step_ms_median']:8.1f} {r['step_ms_mean']:8.1f} "
              f"{r['step_ms_p99']:8.1f} {r['iterations_mean']:6.2f} {r['factors_installed']:8d}")
    return 0
