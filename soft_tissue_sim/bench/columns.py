"""Blocks of columns solved with the LDL^T factor: ``python -m soft_tissue_sim.bench columns``.

The Sherman-Morrison correction needs U = P^-1 G for the 3k columns of the k affected nodes
of every cut (eq. 6), and contact needs P^-1 H^T for one column per contact every step
(eq. 4). This measures one block solve X = A^-1 B against the number of columns, on the
factor of the 2,000-node beam and of the brain at rest:

* ``cholmod``: CHOLMOD's solve on the host (one call for the whole block, numpy in and out),
* ``device_lanesL``: :meth:`soft_tissue_sim.ldlt_device.DeviceLDLT.solve_columns`, every
  level of the level-scheduled triangular solves one launch for all the columns, ``L``
  threads per (row group, column) pair; host in and out, copies included (what the
  correction and the contact solver pay). CUDA only (on the CPU backend it is a check, not a
  contender).

Each time is the median of ``--repeat`` calls after a warm-up. The error of every device
result against CHOLMOD is recorded. Writes ``columns_<cpu|gpu>.json`` and ``.png``.
"""

from __future__ import annotations

import time

import numpy as np
import scipy.sparse as sps
import warp as wp
from sksparse.cholmod import analyze

from ..ldlt_device import DeviceLDLT, StructureCache, factor_values
from ..paths import resolve_path
from ..report import Progress
from ..scene import load_scene, read_scene
from .common import figure, parser, publish, resolved_device, save_figure

COLUMNS = (1, 3, 6, 12, 24, 48, 96, 192, 384)


def _scene_matrix(name: str):
    cfg, base = read_scene(name)
    for k in ("instruments", "contact", "cutting", "obstacles"):
        cfg.pop(k, None)
    if "file" in (cfg.get("mesh") or {}):
        cfg["mesh"] = {"file": str(resolve_path(cfg["mesh"]["file"], base))}
    cfg["solver"] = {"preconditioner": "none"}
    with load_scene(cfg, device="cpu") as sim:
        A = sps.csc_matrix(sim._snapshot()[0])
    A.sort_indices()
    return A


def _median_ms(fn, repeat: int) -> float:
    fn()
    t = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        t.append(1000.0 * (time.perf_counter() - t0))
    return float(np.median(t))


def run(scene: str, device: str, columns, lanes, repeat: int):
    A = _scene_matrix(scene)
    f = analyze(A, mode="simplicial", ordering_method="metis")
    f.cholesky_inplace(A)
    vals = factor_values(f, StructureCache())
    rng = np.random.default_rng(0)
    rows = []
    devs = {L: DeviceLDLT(device, cols_lanes=L) for L in lanes}
    for d in devs.values():
        d.set_factor(vals)
    for c in columns:
        B = rng.standard_normal((A.shape[0], c))
        ref = f(B)
        row = {"scene": scene, "dofs": A.shape[0], "columns": c,
               "cholmod_ms": _median_ms(lambda: f(B), repeat)}
        for L, d in devs.items():
            X = d.solve_columns(B)
            row[f"device_lanes{L}_ms"] = _median_ms(lambda: d.solve_columns(B), repeat)
            row[f"device_lanes{L}_err"] = float(np.linalg.norm(X - ref) / np.linalg.norm(ref))
            row[f"device_lanes{L}_launches"] = d.column_launches(c)
        rows.append(row)
    s = vals.structure
    return rows, {"dofs": s.n, "fwd_levels": s.fwd_levels, "bwd_levels": s.bwd_levels, "nnz_L": s.nnz_offdiag}


def plot(result, prefix):
    scenes = list(dict.fromkeys(r["scene"] for r in result["rows"]))
    fig, axes = figure(1, len(scenes), figsize=(6.5 * len(scenes), 4.8), squeeze=False)
    for ax, sc in zip(axes[0], scenes):
        rs = [r for r in result["rows"] if r["scene"] == sc]
        c = [r["columns"] for r in rs]
        ax.loglog(c, [r["cholmod_ms"] for r in rs], "o-", label="CHOLMOD (host)")
        for k in rs[0]:
            if k.startswith("device_lanes") and k.endswith("_ms"):
                ax.loglog(c, [r[k] for r in rs], "s-", label=k[:-3].replace("_", " ") + " (with copies)")
        ax.set(xlabel="columns", ylabel="ms per block solve", title=f"{sc} ({rs[0]['dofs']} DOFs)")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8)
    save_figure(fig, prefix, f"A^-1 B for a block of columns on {result['device']}")


def main(argv=None) -> int:
    ap = parser("columns", __doc__)
    ap.add_argument("--scenes", nargs="*", default=["beam_2000.yaml", "brain_resection.yaml"])
    ap.add_argument("--columns", nargs="*", type=int, default=list(COLUMNS))
    ap.add_argument("--lanes", nargs="*", type=int, default=None, help="cols_lanes variants (CUDA: 4 8 32)")
    ap.add_argument("--repeat", type=int, default=20)
    args = ap.parse_args(argv)
    device = resolved_device(args)
    wp.init()
    cuda = wp.get_device(device).is_cuda
    lanes = args.lanes or ([4, 8, 32] if cuda else [1])
    prog = Progress(len(args.scenes))
    t0 = time.perf_counter()
    rows, factors = [], {}
    for i, sc in enumerate(args.scenes):
        r, fs = run(sc, device, args.columns, lanes, args.repeat)
        rows += r
        factors[sc] = fs
        best = min((k for k in r[-1] if k.startswith("device_lanes") and k.endswith("_ms")), key=lambda k: r[-1][k])
        prog.update(i + 1, f"{sc}: {r[-1]['columns']} columns CHOLMOD {r[-1]['cholmod_ms']:.2f} ms, "
                           f"{best} {r[-1][best]:.2f} ms")
    result = {"rows": rows, "factors": factors, "repeat": args.repeat, "wall_s": time.perf_counter() - t0}
    publish("columns", device, result, args, plot)
    keys = [k for k in rows[0] if k.endswith("_ms")]
    print(f"{'scene':<22} {'cols':>5} " + " ".join(f"{k[:-3]:>15}" for k in keys))
    for r in rows:
        print(f"{r['scene']:<22} {r['columns']:>5} " + " ".join(f"{r[k]:15.3f}" for k in keys))
    return 0
