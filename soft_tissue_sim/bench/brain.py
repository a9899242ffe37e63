"""Brain tumour resection end to end (paper fig. 5): ``python -m soft_tissue_sim.bench brain``.

Scene ``config/scenes/brain_resection.yaml``, driven by the scripted surgeon of
:mod:`soft_tissue_sim.scenarios.brain`: the probe presses the cortex; the scalpel spirals
down around the tumour with the pedal down (continuous cutting); the tissue under the tumour
is aspirated in tumour-sparing bites (element removal); a closed loop bites what still holds
the tumour to the fixed base (a minimum cut of healthy tets), one bite a step, at most
``--max-cleanup``; the freed specimen is lifted out and the brain settles. The long session
(``--margin 0.01 --radial 16``) adds an outer spiral and radial cuts that part the margin into
wedges.

Reported: modifications (cuts and removals) with their affected nodes and the nodes of N (the
paper's measure), PCG iterations (mean and max), step time (mean, median, p99) and frame rate,
the host cost of the steps with a modification (``cut_ms_*``: the step's cutting phase and a
removal asked before it, contact surface rebuild included),
contacts, LCP residual, max penetration, rollbacks, whether the tumour ended in a part no
longer attached to the fixed base (``tumour_freed``), whether the planned bites alone did it
(``freed_by_plan``), that no tumour tet was removed before it was freed
(``tumour_tets_intact``), the step it was freed at, how far the tumour had sunk then, the tets
lifted out (``extracted_tets``), the tumour tets left at the end (``tumour_left_end``: 0 when
the resection is complete) and the inverted tets at the end. With ``--detail`` the JSON also
holds every step's and every modification's record.
"""

from __future__ import annotations

import sys
import time

import numpy as np

from ..cutting import DEFAULT_SNAP
from ..report import Progress
from ..scenarios.brain import Surgeon, inverted_tets, tumour_drop, tumour_freed
from ..scene import load_scene, read_scene
from ..stats import CUT_PARTS
from .common import columns, figure, parser, publish, resolved_device, save_figure


def run(device, scene="brain_resection.yaml", turns=4, step_len=0.0012, max_cleanup=60, cleanup_radius=0.005,
        backend="auto", scheme=None, worker=None, synchronous=False, refresh_every=None, snap=None,
        margin=0.0, radial=0, progress=False, lag=0, reserve_sms=None, ldlt=None):
    cfg = read_scene(scene)[0]
    solver = dict(cfg.get("solver") or {})
    solver["ldlt"] = {**(solver.get("ldlt") or {}), "backend": backend, **(ldlt or {})}
    if worker is not None:
        solver["ldlt"]["worker"] = worker
    if refresh_every is not None:  # on every device
        solver["ldlt"]["refresh_every"] = int(refresh_every)
        solver["ldlt"].pop("device_refresh_every", None)
    if reserve_sms is not None:  # SMs a GPU factorization leaves to the steps
        solver["ldlt"]["reserve_sms"] = int(reserve_sms)
    if synchronous or lag:  # the factor made in the step that requests it (no background worker)
        solver["ldlt"]["deterministic"] = True
    if lag:  # ... and installed lag steps later (the paper's background factorization took about 5.6)
        solver["ldlt"]["lag"] = int(lag)
    overrides = {"solver": solver}
    if scheme is not None:
        overrides["cutting"] = {"scheme": scheme}
    if snap is not None:
        overrides.setdefault("cutting", {})["snap"] = float(snap)
    sim = load_scene(scene, device=device, overrides=overrides)
    rows, mods, bites, extracted = [], [], [], []
    try:
        sim.step()  # warm-up: compile, first factorization
        sim.reset()
        surgeon = Surgeon(sim, turns, step_len, margin, radial, max_cleanup, cleanup_radius)
        prog = Progress(len(surgeon.acts)) if progress else None  # the closed loop's bites come on top
        n_tum = int((sim.mesh.material_ids == 1).sum())
        its_sum = [0]  # iterations so far, for the progress line

        def record(kind, r, **extra):
            """One modification's statistics (its own nodes and the nodes of N, the paper's measure)."""
            return {"kind": kind, "affected_nodes": r.affected_nodes, "perturbation_nodes": r.perturbation_nodes,
                    "ms": r.ms, "u_ms": r.smf_u_ms, "q_ms": r.smf_q_ms, "step": sim.step_count, **extra}

        def do(a):
            t0 = time.perf_counter()
            r, bite = surgeon.act(a)
            asked = r if r is not None and r.changed else None  # a removal asked before the step
            extra_ms = r.ms if r is not None else 0.0
            if bite is not None:
                bites.append({"step": sim.step_count, "center": bite[0].tolist(), "radius": bite[1],
                              "tets": r.tets_changed, "changed": bool(r.changed)})
            if "extract" in a:
                extracted.append(int(r.tets_changed) if r.changed else 0)
            if r is not None and r.changed:
                kind = "extraction" if "extract" in a else "removal"
                mods.append(record(kind, r, **({} if kind == "extraction" else {"cleanup": "cleanup_tet" in a})))
            n_before, mods_before = len(sim.cutting.history), sim.cutting.modifications
            s = sim.step()
            wall = 1000.0 * (time.perf_counter() - t0)
            for h in sim.cutting.history[n_before:]:
                if h.changed and h.message.startswith("cut"):
                    mods.append(record("cut", h))
            d = s.as_dict()
            rows.append({"step": sim.step_count, "wall_ms": wall, "total_ms": d["total_ms"] + d.get("cut_ms", 0.0)
                         + d.get("contact_ms", 0.0) + extra_ms, "iterations": d["iterations"],
                         "residual": d["residual"], "converged": d["converged"], "contacts": d.get("contacts", 0),
                         "max_penetration": d.get("max_penetration"), "lcp_residual": d.get("lcp_residual", 0.0),
                         "factor_age": d["factor_age"], "refresh_interval": d["refresh_interval"],
                         "rolled_back": bool(d.get("rolled_back", False)),
                         # the host cost of this step's modifications: the step's cutting phase and
                         # the request made before it (the surgeon's removal), each with its surface
                         "modified": asked is not None or sim.cutting.modifications > mods_before,
                         "cut_ms": d.get("cut_ms", 0.0) + extra_ms,
                         "surface_ms": d.get("surface_ms", 0.0) + (asked.surface_ms if asked is not None else 0.0),
                         "smf_ms": d.get("smf_u_ms", 0.0) + d.get("smf_q_ms", 0.0)
                         + (asked.smf_u_ms + asked.smf_q_ms if asked is not None else 0.0),
                         **{k: d.get(k, 0.0) + (getattr(asked, k) if asked is not None else 0.0)
                            for k in CUT_PARTS},
                         "wrench_probe_N": float(np.linalg.norm(sim.instrument_wrench("probe")[0]))})
            its_sum[0] += d["iterations"]
            if prog is not None:
                prog.update(min(len(rows), prog.total - 1),
                            f"step {sim.step_count}: {len(mods)} modifications, {its_sum[0] / len(rows):.2f} it")

        for a in surgeon.planned():
            do(a)
        freed_planned = tumour_freed(sim)
        while (a := surgeon.cleanup()) is not None:  # closed loop: aspirate what holds the tumour
            do(a)
        freed = tumour_freed(sim)
        freed_step = sim.step_count if freed else None
        z_freed = tumour_drop(sim)
        tumour_intact = int((sim.mesh.material_ids == 1).sum()) == n_tum
        for a in surgeon.settle(freed):  # the surgeon lifts a freed specimen out, the brain settles
            do(a)
        inverted = inverted_tets(sim)
        tumour_left = int((sim.mesh.material_ids == 1).sum())
        finite = bool(np.isfinite(sim.positions()).all())
        nodes_end, tets_end = sim.mesh.n_nodes, sim.mesh.n_tets
        step_graphs = {name: rep.counts() for name, rep in sim.integrator.replayers().items()}
    finally:
        sim.close()
    info = {"freed_by_plan": bool(freed_planned), "cleanup_bites": len(bites), "cut_sizes": surgeon.cut_sizes,
            "tumour_tets_intact": tumour_intact, "bites": bites, "freed_at_step": freed_step,
            "tumour_drop_when_freed_m": z_freed, "extracted_tets": int(sum(extracted)),
            "tumour_left_end": tumour_left, "inverted_tets_end": inverted, "step_graphs": step_graphs}
    return rows, mods, freed, finite, nodes_end, tets_end, info


def plot(result, prefix):
    st, mods = result["plot"]["steps"], result["plot"]["modifications"]
    fig, axes = figure(1, 3, figsize=(17, 4.5))
    axes[0].plot(st["step"], st["iterations"], lw=0.8)
    for k in mods["step"]:
        axes[0].axvline(k, color="r", alpha=0.05)
    axes[0].set(xlabel="step", ylabel="PCG iterations", title="iterations (red: modifications)")
    axes[1].plot(st["step"], st["wall_ms"], lw=0.8)
    axes[1].set(xlabel="step", ylabel="ms", title="wall time per step (cut, contact, solve)")
    axes[2].hist(mods["affected_nodes"], bins=30)
    axes[2].set(xlabel="affected nodes per modification", ylabel="count", title="modifications")
    for ax in axes:
        ax.grid(True, alpha=0.3)
    save_figure(fig, prefix, f"brain tumour resection on {result['device']}")


def main(argv=None) -> int:
    ap = parser("brain", __doc__)
    ap.add_argument("--scene", default="brain_resection.yaml")
    ap.add_argument("--turns", type=float, default=4)
    ap.add_argument("--step-len", type=float, default=0.0012, help="scalpel advance per step [m]")
    ap.add_argument("--margin", type=float, default=0.0,
                    help="the long session: an outer spiral cut this far outside the inner one [m] (0: none)")
    ap.add_argument("--radial", type=int, default=0,
                    help="the long session: radial cuts dividing the margin into wedges")
    ap.add_argument("--max-cleanup", type=int, default=60, help="most extra (closed-loop) bites")
    ap.add_argument("--cleanup-radius", type=float, default=0.005, help="radius of a closed-loop bite [m]")
    ap.add_argument("--backend", default="auto", choices=["auto", "cholmod", "dense"],
                    help="the factor's backend (solver.ldlt.backend)")
    ap.add_argument("--scheme", default=None, choices=["split", "subdivide"],
                    help="cutting scheme (default: the scene's)")
    ap.add_argument("--snap", type=float, default=None,
                    help="subdivide: snap a crossing to an edge's end within this fraction (default: the scene's)")
    ap.add_argument("--worker", default=None, choices=["thread", "process"],
                    help="where the async factorization runs (default: the scene's)")
    ap.add_argument("--refresh-every", type=int, default=None,
                    help="request a factor every this many steps (default: the scene's)")
    ap.add_argument("--synchronous", action="store_true",
                    help="factorize in the step that requests the factor (ldlt.deterministic), not in the background")
    ap.add_argument("--lag", type=int, default=0,
                    help="factorize in the step that requests the factor and install it this many steps later: "
                         "the schedule of a background factorization that takes that long, reproducibly")
    ap.add_argument("--reserve-sms", type=int, default=None,
                    help="GPU: SMs the factorization leaves to the steps (ldlt.reserve_sms; default: the scene's)")
    args = ap.parse_args(argv)
    if args.reserve_sms is not None and args.reserve_sms < 0:
        ap.error("--reserve-sms is a number of SMs >= 0")
    if args.lag < 0:
        ap.error("--lag is a number of steps >= 0")
    if args.margin < 0 or (args.radial > 0) != (args.margin > 0) or args.radial < 0:
        ap.error("--margin and --radial come together (a margin > 0 and at least one radial cut), or neither")
    device = resolved_device(args)
    t0 = time.perf_counter()
    rows, mods, freed, finite, n_end, t_end, info = run(device, args.scene, args.turns, args.step_len,
                                                        args.max_cleanup, args.cleanup_radius, args.backend,
                                                        args.scheme, args.worker, args.synchronous,
                                                        args.refresh_every, args.snap, args.margin, args.radial,
                                                        progress=True, lag=args.lag, reserve_sms=args.reserve_sms)
    wall = np.array([r["wall_ms"] for r in rows])
    its = np.array([r["iterations"] for r in rows])
    cut = np.array([r["cut_ms"] for r in rows if r["modified"]])
    summary = {
        "steps": len(rows), "modifications": len(mods),
        "cuts": sum(m["kind"] == "cut" for m in mods), "removals": sum(m["kind"] == "removal" for m in mods),
        "cleanup_bites": info["cleanup_bites"], "cleanup_removals": sum(bool(m.get("cleanup")) for m in mods),
        "affected_nodes_mean": float(np.mean([m["affected_nodes"] for m in mods])) if mods else 0.0,
        **{f"affected_nodes_{k}s_mean": float(np.mean([m["affected_nodes"] for m in mods if m["kind"] == k]))
           for k in ("cut", "removal") if any(m["kind"] == k for m in mods)},
        # the paper's "affecting 24 nodes": the nodes of N against the factor in use (eq. 5)
        "perturbation_nodes_mean": float(np.mean([m["perturbation_nodes"] for m in mods])) if mods else 0.0,
        "perturbation_nodes_median": float(np.median([m["perturbation_nodes"] for m in mods])) if mods else 0.0,
        "modification_every_steps": len(rows) / max(1, len(mods)),
        "iterations_mean": float(its.mean()), "iterations_max": int(its.max()),
        "converged_fraction": float(np.mean([r["converged"] for r in rows])),
        "step_ms_mean": float(wall.mean()), "step_ms_median": float(np.median(wall)),
        "step_ms_p99": float(np.percentile(wall, 99)), "fps_mean": float(1000.0 / wall.mean()),
        # the host cost of the steps with a modification (cutting phase and removals asked before the step)
        "cut_steps": len(cut), "cut_ms_median": float(np.median(cut)) if len(cut) else 0.0,
        "cut_ms_p99": float(np.percentile(cut, 99)) if len(cut) else 0.0,
        **{f"{k[:-3]}_ms_median": float(np.median([r[k] for r in rows if r["modified"]])) if len(cut) else 0.0
           for k in ("surface_ms", *CUT_PARTS)},
        "contacts_mean": float(np.mean([r["contacts"] for r in rows])),
        "max_penetration": max((r["max_penetration"] for r in rows if r["max_penetration"] is not None),
                               default=None),  # over the steps that measured it (contact penetration_every)
        "refresh_interval": rows[-1]["refresh_interval"], "rollbacks": int(sum(r["rolled_back"] for r in rows)),
        "tumour_freed": bool(freed), "freed_by_plan": info["freed_by_plan"],
        "tumour_tets_intact": info["tumour_tets_intact"], "cut_sizes": info["cut_sizes"],
        "freed_at_step": info["freed_at_step"], "tumour_drop_when_freed_m": info["tumour_drop_when_freed_m"],
        "extracted_tets": info["extracted_tets"], "tumour_left_end": info["tumour_left_end"],
        "inverted_tets_end": info["inverted_tets_end"], "step_graphs": info["step_graphs"],
        "finite": finite, "nodes_end": n_end, "tets_end": t_end,
        "wall_s": time.perf_counter() - t0,
    }
    print(f"done: {summary['modifications']} modifications, {summary['iterations_mean']:.2f} it, "
          f"{summary['fps_mean']:.1f} FPS", file=sys.stderr)
    cfg = read_scene(args.scene)[0]
    ldlt = (cfg.get("solver") or {}).get("ldlt") or {}
    summary["backend"] = args.backend
    summary["ldlt_worker"] = args.worker or str(ldlt.get("worker", "thread"))
    summary["ldlt_synchronous"] = bool(args.synchronous or args.lag)
    summary["ldlt_lag"] = args.lag
    summary["refresh_every"] = args.refresh_every or int(ldlt.get("refresh_every", 0))
    summary["step_len_m"] = args.step_len
    summary["margin_m"] = args.margin
    summary["radial_cuts"] = args.radial
    summary["cutting_scheme"] = args.scheme or str((cfg.get("cutting") or {}).get("scheme", "split"))
    summary["snap"] = args.snap if args.snap is not None else float((cfg.get("cutting") or {}).get("snap", DEFAULT_SNAP))
    result = {"summary": summary, "cleanup_bites": info["bites"],
              "plot": {"steps": columns(rows, ("step", "iterations", "wall_ms")),
                       "modifications": columns(mods, ("step", "affected_nodes"))}}
    publish("brain", device, result, args, plot, detail={"modifications": mods, "steps_detail": rows})
    for k, v in summary.items():
        print(f"{k:>26}: {v}")
    return 0
