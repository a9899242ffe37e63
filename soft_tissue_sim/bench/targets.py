"""Every speed and fidelity target in one run: ``python -m soft_tissue_sim.bench targets``.

Measures each target row of the GPU preconditioner and GPU step issues on the device given
(``--device cuda:0`` for the GPU rows; the CPU rows on the CPU), prints a table and writes
``targets_<cpu|gpu>.json``: a list ``targets`` of ``{name, value, unit, goal, met}`` with the
device, date and commit. Rows that do not apply to the device are listed with ``value``
None and the reason. The README's and docs/benchmarks.md's targets tables are made from it.

Rows (scenes of ``config/scenes``):

* ``precond_apply_ms``: one application of the brain's preconditioner (eq. 2), replayed in a
  CUDA graph (GPU) or called from Python (CPU);
* ``precond_factor_ms``: wall time of one new factor of the brain (assembly, factorization,
  install), median of 5;
* ``beam2000_smf_*``: the paper's cut beam at 2,000 nodes (a cut every 3 steps, a refresh
  every 4, 90 steps): the PCG solve with the corrections (``solve``), the whole step with
  the cuts (``step``), its mean iterations, and plain CG's step over the SMF step;
* ``beam100k_step_ms``: a 100,000-node beam (20 x 20 x 250 nodes) swinging under gravity,
  median step (GPU only);
* ``brain_contact_step_*``: the brain with both instruments pressed into it, no cutting;
* ``brain_resection_*``: the shipped scripted resection (``bench brain``): step time,
  iterations, the tumour freed, rollbacks, inverted tets; on the CPU its frame rate;
* ``brain_cut_ms_*``: from the same run, the host cost of the steps with a modification
  (median and p99): the wall time of the step's cutting phase (the state's read, planning,
  mesh change, FEM and state arrays, the preconditioner's correction, the contact surface's
  rebuild) plus a removal asked before the step (the surgeon's bites), the same parts;
* ``close_s``: ``Simulation.close()`` of the brain while a factorization is in flight.

``--ldlt KEY=VALUE`` (repeatable) lays a ``solver.ldlt`` setting over the brain scene's in every
brain row (e.g. ``--ldlt reserve_sms=48``), to measure the targets under another factor policy;
the settings are recorded in the result (``ldlt_overrides``).
"""

from __future__ import annotations

import argparse
import gc
import json
import sys
import time

import numpy as np
import warp as wp

from ..scene import load_scene, read_scene, resolve_device, resolve_path
from ..stats import CUT_PARTS
from . import RESULTS_DIR, write_result
from .timing import apply_timing, refresh_timing, timed_steps


def _row(name, value, unit, goal, better="<=", note=None):
    if value is None:
        met = None
    elif better == "<=":
        met = bool(value <= goal)
    elif better == ">=":
        met = bool(value >= goal)
    else:  # "==": a boolean or a count that must equal the goal
        met = bool(value == goal)
    r = {"name": name, "value": value, "unit": unit, "goal": goal, "goal_relation": better, "met": met}
    if note:
        r["note"] = note
    return r


# solver.ldlt settings laid over the brain scene's in every brain row (``--ldlt KEY=VALUE``)
LDLT: dict = {}


def parse_ldlt(items) -> dict:
    """``KEY=VALUE`` strings as a dict, each value read as JSON where it parses (numbers,
    booleans), else kept as a string."""
    out = {}
    for item in items or ():
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise ValueError(f"--ldlt takes KEY=VALUE, got {item!r}")
        try:
            out[key] = json.loads(value)
        except json.JSONDecodeError:
            out[key] = value
    return out


def _brain(contact=False):
    cfg, base = read_scene("brain_resection.yaml")
    if LDLT:
        cfg["solver"] = {**cfg["solver"], "ldlt": {**cfg["solver"].get("ldlt", {}), **LDLT}}
    cfg.pop("cutting", None)
    if not contact:
        cfg.pop("instruments", None)
        cfg.pop("contact", None)
    cfg["mesh"] = {"file": str(resolve_path(cfg["mesh"]["file"], base))}
    return cfg


def precond_rows(device, reps=100):
    """precond_apply_ms and precond_factor_ms on the brain, with the scene's preconditioner."""
    with load_scene(_brain(), device=device) as sim:
        for _ in range(5):
            sim.step()
        pre, integ = sim.preconditioner, sim.integrator
        backend = pre.stats().get("backend")
        integ.build()
        pre.begin_step(integ)
        t = apply_timing(sim, reps)
        apply_ms = t.get("graph_apply_ms", t["apply_ms"])
        factor_ms = refresh_timing(sim, 5)
    note = f"brain, 5,202 DOFs, backend {backend}"
    return [_row("precond_apply_ms", apply_ms, "ms", 0.1, note=note),
            _row("precond_factor_ms", factor_ms, "ms", 25.0, note=note)]


def cut_beam_rows(device, steps=90):
    from .cut_beam import run, summarize

    smf_stats, cuts, n0, n1 = run("beam_2000.yaml", "smf", steps, 3, 4, device)
    smf = summarize(smf_stats, cuts, n0, n1, "smf")
    cg_stats, cg_cuts, _, _ = run("beam_2000.yaml", "cg", max(12, steps // 3), 3, 4, device)
    cg_step = float(np.mean([s["total_ms"] + s.get("cut_ms", 0.0) for s in cg_stats]))
    corr_ms = sum(c["u_ms"] + c["q_ms"] for c in cuts) / len(smf_stats)
    solve = float(np.mean([s["solve_ms"] for s in smf_stats])) + corr_ms
    note = f"{smf['cuts']} cuts in {steps} steps, the scene's backend (auto)"
    return [_row("beam2000_smf_solve_ms", solve, "ms", 1.0, note=note + "; PCG solve + corrections, mean"),
            _row("beam2000_smf_step_ms", smf["total_ms"], "ms", 3.4,
                 note=note + "; whole step with the cuts, mean; " + beam_split(smf_stats)),
            _row("beam2000_smf_iterations_mean", smf["iterations"], "iterations", 8.0, note=note),
            _row("beam2000_smf_over_cg", cg_step / smf["total_ms"], "x", 20.0, ">=",
                 note=f"plain CG {cg_step:.1f} ms a step (mean of {len(cg_stats)}) on the same device")]


def beam_split(stats) -> str:
    """Where the cut beam's step goes (its step records): the steps between cuts, a cut's step
    (its cutting phase and the phase's parts) and the step after a cut, means in ms."""
    cut = [i for i, s in enumerate(stats) if s.get("tets_changed", 0) > 0]
    after = [i + 1 for i in cut if i + 1 < len(stats) and i + 1 not in cut]
    between = [i for i in range(len(stats)) if i not in cut and i not in after]

    def mean(idx, f):
        return float(np.mean([f(stats[i]) for i in idx])) if idx else float("nan")

    whole = lambda s: s["total_ms"] + s.get("cut_ms", 0.0)  # noqa: E731
    parts = ", ".join(f"{name} {mean(cut, lambda s, k=k: s.get(k, 0.0)):.2f}" for k, name in CUT_PARTS.items())
    return (f"steps between cuts {mean(between, whole):.2f} (solve {mean(between, lambda s: s['solve_ms']):.2f}), "
            f"a cut's step {mean(cut, whole):.2f} of which its cutting phase {mean(cut, lambda s: s['cut_ms']):.2f} "
            f"({parts}), the step after a cut {mean(after, whole):.2f} (solve {mean(after, lambda s: s['solve_ms']):.2f})")


def beam100k_rows(device, steps=40, warmup=8):
    if not wp.get_device(device).is_cuda:
        return [_row("beam100k_step_ms", None, "ms", 16.7, note="GPU only (the CPU takes seconds a step)")]
    cfg = {"name": "beam100k", "mesh": {"generator": "beam", "n_long": 250, "n_cross": 20, "spacing": 0.01},
           "materials": [{"id": 0, "young": 5.0e4, "poisson": 0.3, "density": 1000.0}],
           "damping": {"mass": 0.1, "stiffness": 0.01}, "fixed": {"axis": "x", "below": 0.0},
           "time": {"dt": 0.01}, "solver": {"tolerance": 1.0e-6, "preconditioner": "async_ldlt",
                                           "ldlt": {"refresh_every": 4}}}
    with load_scene(cfg, device=device) as sim:
        for _ in range(warmup):
            sim.step()
        walls, stats = timed_steps(sim, steps)
        its = [st.iterations for st in stats]
        ps = sim.preconditioner.stats()
        n = sim.mesh.n_nodes
    return [_row("beam100k_step_ms", float(np.median(walls)), "ms", 16.7,
                 note=f"{n} nodes, backend {ps.get('backend')}, {np.mean(its):.2f} iterations, "
                      f"p99 {np.percentile(walls, 99):.1f} ms, factorization {ps.get('factorization_ms', 0):.1f} ms")]


def brain_contact_rows(device, steps=200, ramp=20):
    """Both instruments pressed into the brain (the probe 6 mm over the tumour, the scalpel's
    shaft 3 mm beside it, pedal up), held; the held steps are timed."""
    cfg = _brain(contact=True)
    with load_scene(cfg, device=device) as sim:
        P = sim.mesh.points
        cen = sim.mesh.centroids()[sim.mesh.material_ids == 1].mean(axis=0)

        def top(x, y):
            near = np.hypot(P[:, 0] - x, P[:, 1] - y) < 0.01
            return float(P[near, 2].max())

        spots = {"probe": (cen[0], cen[1], 0.006), "scalpel": (cen[0] + 0.025, cen[1], 0.003)}
        walls, its, contacts = [], [], []
        for k in range(ramp + steps):
            s = min(1.0, k / ramp)
            for name, (x, y, depth) in spots.items():
                sim.set_instrument_pose(name, [x, y, top(x, y) + 0.01 - s * (0.01 + depth)], [0, 0, 0, 1])
            t0 = time.perf_counter()
            st = sim.step()
            w = 1000.0 * (time.perf_counter() - t0)
            if k >= ramp:
                walls.append(w)
                its.append(st.iterations)
                contacts.append(st.as_dict().get("contacts", 0))
        backend = sim.preconditioner.stats().get("backend")
    note = (f"{steps} held steps, {np.mean(contacts):.0f} contacts, {np.mean(its):.2f} iterations, "
            f"backend {backend}")
    return [_row("brain_contact_step_median_ms", float(np.median(walls)), "ms", 1.0, note=note),
            _row("brain_contact_step_p99_ms", float(np.percentile(walls, 99)), "ms", 2.0, note=note)]


def brain_resection_rows(device):
    from .brain import run

    rows, mods, freed, finite, _, _, info = run(device, progress=True, ldlt=LDLT)
    wall = np.array([r["wall_ms"] for r in rows])
    its = np.array([r["iterations"] for r in rows])
    g = info["step_graphs"]["after the solve"]
    note = (f"{len(rows)} steps, {len(mods)} modifications; {resection_split(rows)}; the launches after the solve "
            f"captured {g['captures']}, replayed {g['replays']}, plain {g['plain']}")
    out = [_row("brain_resection_step_median_ms", float(np.median(wall)), "ms", 2.0, note=note),
           _row("brain_resection_step_p99_ms", float(np.percentile(wall, 99)), "ms", 20.0, note=note),
           _row("brain_resection_iterations_mean", float(its.mean()), "iterations", 5.7, note=note),
           _row("brain_resection_tumour_freed", bool(freed and finite), "", True, "=="),
           _row("brain_resection_rollbacks", int(sum(r["rolled_back"] for r in rows)), "", 0, "=="),
           _row("brain_resection_inverted_tets", int(info["inverted_tets_end"]), "", 0, "==")]
    if not wp.get_device(device).is_cuda:
        out.append(_row("brain_resection_fps", float(1000.0 / wall.mean()), "FPS", 20.0, ">=", note=note))
    return out + cut_rows(rows)


def resection_split(rows, many: int = 32) -> str:
    """Where the resection's step time is: the wall time's median and p99 (steps) over the
    steps with a modification, the steps right after one (a new surface, the launches sized by
    the counts captured again), the other steps with more than ``many`` contacts (the LCP on
    the host), and the rest."""
    wall = np.array([r["wall_ms"] for r in rows])
    mod = np.array([bool(r.get("modified")) for r in rows])
    after = np.zeros_like(mod)
    after[1:] = mod[:-1] & ~mod[1:]
    large = ~mod & ~after & (np.array([r.get("contacts", 0) for r in rows]) > many)
    parts = []
    for name, m in (("with a modification", mod), ("right after one", after),
                    (f"other steps of more than {many} contacts", large), ("the others", ~(mod | after | large))):
        if m.any():
            parts.append(f"{name} {np.median(wall[m]):.2f} / {np.percentile(wall[m], 99):.2f} ({int(m.sum())})")
    return "step wall ms median / p99 (steps): " + ", ".join(parts)


def cut_rows(rows) -> list:
    """brain_cut_ms_median and brain_cut_ms_p99 from the resection's step rows (``bench brain``'s:
    ``modified``, ``cut_ms`` and its parts): over the steps with a modification."""
    mod = [r for r in rows if r.get("modified")]
    if not mod:
        return [_row(n, None, "ms", g, note="no step with a modification") for n, g in
                (("brain_cut_ms_median", 5.0), ("brain_cut_ms_p99", 20.0))]
    cut = np.array([r["cut_ms"] for r in mod])
    names = {**CUT_PARTS, "surface_ms": "contact surface"}
    parts = {k: np.array([r.get(k, 0.0) for r in mod]) for k in names}
    rest = cut - sum(parts.values())
    note = (f"{len(mod)} steps with a modification; wall time of the host's cutting phase, medians: "
            + ", ".join(f"{names[k]} {np.median(v):.2f}" for k, v in parts.items())
            + f", the rest (the state's reads, plans that changed nothing) {np.median(rest):.2f} ms")
    return [_row("brain_cut_ms_median", float(np.median(cut)), "ms", 5.0, note=note),
            _row("brain_cut_ms_p99", float(np.percentile(cut, 99)), "ms", 20.0, note=note)]


def close_rows(device):
    sim = load_scene(_brain(), device=device, overrides={"solver": {"ldlt": {"refresh_every": 1}}})
    sim.step()
    sim.step()  # a factorization requested and (on a GPU or in the worker thread) in flight
    t0 = time.perf_counter()
    sim.close()
    return [_row("close_s", time.perf_counter() - t0, "s", 1.0, note="brain, a factorization in flight")]


# the 100,000-node beam after the brain's rows: what it leaves behind (gigabytes of device memory
# in CUDA's pool, cuDSS's state) is not the brain's to pay
GROUPS = {"precond": precond_rows, "cut_beam": cut_beam_rows, "brain_contact": brain_contact_rows,
          "brain_resection": brain_resection_rows, "beam100k": beam100k_rows, "close": close_rows}


def markdown(paths) -> str:
    """The targets table (one row per target, one column per device) from targets JSON files."""
    docs = [json.load(open(p)) for p in paths]
    names = list(dict.fromkeys(t["name"] for d in docs for t in d["targets"]))
    head = "| target | goal | " + " | ".join(d["device"].split(" (")[0] for d in docs) + " |"
    lines = [head, "| --- | --- | " + " | ".join("---" for _ in docs) + " |"]
    for n in names:
        goal = next(f"{t['goal_relation']} {t['goal']} {t['unit']}".strip() for d in docs for t in d["targets"]
                    if t["name"] == n)
        cells = []
        for d in docs:
            t = next((t for t in d["targets"] if t["name"] == n), None)
            if t is None or t["value"] is None:
                cells.append("")
                continue
            v = t["value"]
            vs = f"{v:.3g}" if isinstance(v, float) else str(v)
            cells.append(f"{vs} ({'met' if t['met'] else 'not met'})")
        lines.append(f"| `{n}` | {goal.replace('<=', 'at most').replace('>=', 'at least').replace('==', '')} | "
                     + " | ".join(cells) + " |")
    dates = "; ".join(f"{d['device']}: {d['date'][:10]}, commit {d['commit']}" for d in docs)
    return "\n".join(lines) + f"\n\n({dates})"


def _compile_kernels(device) -> None:
    """Build every kernel module of the package for ``device`` first, so that no row times a
    compilation (a fresh machine has no kernel cache)."""
    from ..warp_modules import build_all

    print(f"  [kernels built in {build_all(device):.1f} s]", file=sys.stderr, flush=True)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m soft_tissue_sim.bench targets", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default=None)
    ap.add_argument("--only", default=None, help=f"comma list of {', '.join(GROUPS)} (default: all)")
    ap.add_argument("--out", default=str(RESULTS_DIR))
    ap.add_argument("--markdown", nargs="+", metavar="JSON", help="only print the table of these result files")
    ap.add_argument("--ldlt", action="append", metavar="KEY=VALUE",
                    help="a solver.ldlt setting for the brain's rows (repeatable; recorded in the result)")
    args = ap.parse_args(argv)
    if args.markdown:
        print(markdown(args.markdown))
        return 0
    try:
        LDLT.clear()
        LDLT.update(parse_ldlt(args.ldlt))
    except ValueError as exc:
        ap.error(str(exc))
    device = resolve_device(args.device)
    _compile_kernels(device)
    groups = args.only.split(",") if args.only else list(GROUPS)
    for g in groups:
        if g not in GROUPS:
            ap.error(f"unknown group {g!r}")
    targets, t_all = [], time.perf_counter()
    for g in groups:
        t0 = time.perf_counter()
        try:
            rows = GROUPS[g](device)
        except Exception as exc:  # noqa: BLE001 - recorded as rows without a value; the others still run
            rows = [_row(g, None, "", None, note=f"failed: {type(exc).__name__}: {exc}")]
        gc.collect()  # the group's scenes closed and gone before the next group
        for r in rows:
            v = r["value"]
            vs = "-" if v is None else (f"{v:.4g}" if isinstance(v, float) else str(v))
            flag = {True: "met", False: "NOT met", None: "n/a"}[r["met"]]
            print(f"{r['name']:<34} {vs:>10} {r['unit']:<10} goal {r['goal_relation']} {r['goal']!s:<6} {flag:<8}"
                  f" {r.get('note', '')}", flush=True)
        print(f"  [{g}: {time.perf_counter() - t0:.1f} s]", file=sys.stderr, flush=True)
        targets += rows
    figures = {"targets": targets, "wall_s": time.perf_counter() - t_all}
    if LDLT:
        figures["ldlt_overrides"] = dict(LDLT)
    path = write_result("targets", device, figures, args.out)
    doc = json.load(open(path))
    doc["targets"] = doc["figures"].pop("targets")
    with open(path, "w") as fh:
        json.dump(doc, fh, indent=1, default=float)
    print(f"wrote {path}")
    return 0
