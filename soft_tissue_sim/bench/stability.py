"""Stability on stiff and extreme cases, for every solver: ``python -m soft_tissue_sim.bench stability``.

Cases (a beam of 3 x 3 x 16 nodes, 1.5 cm x 2 cm x 2 cm... scaled by ``--n-long``, clamped at x = 0):

* ``ratio_R``: the far half of the beam R times stiffer than the near half (R = 1, 20, 1e3, 1e6);
* ``dt_T``: time step T from 1e-3 to 0.1 s;
* ``undamped_dt_0.1``: a soft beam (E = 1e5 Pa) without damping at dt = 0.1 s, where the
  single linearisation of eq. (1) creates energy;
* ``poisson_P``: Poisson ratio up to 0.499 (near incompressible);
* ``twist_360``: the beam twisted by 360 degrees about its axis, then released;
* ``instrument_1ms``: a capsule driven at 1 m/s into a block resting on its fixed base (contact);
* ``cuts_1000``: 1,000 successive random cuts, one per step (cutting + SMF where the solver has a factor).

Solvers: plain CG, block-Jacobi PCG, the asynchronous LDL^T and a direct factorization per
step, all with the paper's single linearisation per step; ``ldlt_newton`` and
``direct_newton`` are the same with ``solver: {newton_iterations: 3}`` (re-linearised twice,
see :mod:`soft_tissue_sim.implicit_integration`; ``--newton`` sets the count).

Each case and solver reports: finite or not, energy growth (max over the run of E(t) - E(0),
over the energy scale m g L; E includes the elastic energy, so the strain a once-linearized
step stores in a stiff body that rotates counts as growth) and the drift at the end (E(end) -
E(0) over m g L), mean and max PCG iterations (summed over a step's linearisations), final
residual (the true one), converged fraction, steps whose tolerance was below float64's floor,
max penetration (contact case), rollbacks of the divergence guard, wall time. JSON and a
heat-map PNG under benchmarks/results/.
"""

from __future__ import annotations

import time

import numpy as np

from ..report import Progress
from ..scene import load_scene
from .common import figure, parser, publish, resolved_device, save_figure

SOLVERS = {
    "cg": {"preconditioner": "none"},
    "jacobi": {"preconditioner": "jacobi"},
    "ldlt": {"preconditioner": "async_ldlt", "ldlt": {"rotate": True, "refresh_every": 4}},
    "direct": {"preconditioner": "direct"},
    "ldlt_newton": {"preconditioner": "async_ldlt", "ldlt": {"rotate": True, "refresh_every": 4}, "newton_iterations": 3},
    "direct_newton": {"preconditioner": "direct", "newton_iterations": 3},
}


def beam(n_long=16, young=1e5, poisson=0.3, ratio=1.0, dt=0.01, max_iterations=1000):
    L = 0.01 * (n_long - 1)
    return {
        "name": "stability_beam",
        "mesh": {"generator": "beam", "n_long": n_long, "n_cross": 3, "spacing": 0.01,
                 "regions": [{"box": {"min": [L / 2, -1, -1], "max": [1, 1, 1]}, "material": 1}]},
        "materials": [{"id": 0, "young": young, "poisson": poisson, "density": 1000.0},
                      {"id": 1, "young": young * ratio, "poisson": poisson, "density": 1000.0}],
        "damping": {"mass": 0.1, "stiffness": 0.002},
        "fixed": {"axis": "x", "below": 0.0},
        "time": {"dt": dt},
        "solver": {"tolerance": 1e-7, "max_iterations": max_iterations},
    }


def cases(n_long):
    out = {}
    for r in (1.0, 20.0, 1e3, 1e6):
        out[f"ratio_{r:g}"] = {"scene": beam(n_long, ratio=r)}
    for dt in (1e-3, 1e-2, 0.05, 0.1):
        out[f"dt_{dt:g}"] = {"scene": beam(n_long, dt=dt)}
    soft = beam(n_long, young=1e5, dt=0.1)
    soft["damping"] = {"mass": 0.0, "stiffness": 0.0}
    out["undamped_dt_0.1"] = {"scene": soft}
    for nu in (0.3, 0.45, 0.49, 0.499):
        out[f"poisson_{nu:g}"] = {"scene": beam(n_long, poisson=nu)}
    out["twist_360"] = {"scene": beam(n_long, young=3e5), "twist": 2 * np.pi}
    blk = beam(6, young=3e4)
    blk["mesh"] = {"generator": "beam", "n_long": 6, "n_cross": 6, "spacing": 0.01}
    blk["fixed"] = {"axis": "z", "below": -0.025 + 1e-6}
    blk["instruments"] = [{"name": "probe", "shape": "capsule", "radius": 0.004, "length": 0.05}]
    out["instrument_1ms"] = {"scene": blk, "instrument_speed": 1.0}
    cut = beam(n_long)
    cut["cutting"] = {"correction": "sherman_morrison"}
    out["cuts_1000"] = {"scene": cut, "cuts": 1000}
    return out


def twist_positions(points, angle):
    """Rotate each cross-section about the beam axis (through its centre) by angle * x / L."""
    x = points[:, 0]
    L = x.max() - x.min()
    c = points[:, 1:].mean(axis=0)
    a = angle * (x - x.min()) / L
    y, z = points[:, 1] - c[0], points[:, 2] - c[1]
    out = points.copy()
    out[:, 1] = c[0] + np.cos(a) * y - np.sin(a) * z
    out[:, 2] = c[1] + np.sin(a) * y + np.cos(a) * z
    return out


def run_case(name, case, solver, steps, device, rng, newton=3):
    cfg = dict(case["scene"])
    cfg["solver"] = {**cfg["solver"], **SOLVERS[solver]}
    if "newton_iterations" in cfg["solver"]:
        cfg["solver"]["newton_iterations"] = newton
    n_steps = case.get("cuts", steps)
    row = {"case": name, "solver": solver, "steps": n_steps}
    t0 = time.perf_counter()
    try:
        sim = load_scene(cfg, device=device)
    except Exception as exc:  # noqa: BLE001 - a case a solver cannot even build is a result
        return {**row, "finite": False, "error": f"{type(exc).__name__}: {exc}"}
    its, res, conv, pen, floor = [], [], [], [], []
    try:
        if "twist" in case:
            sim.integrator.set_state(twist_positions(sim.mesh.points, case["twist"]), np.zeros_like(sim.mesh.points))
        e0 = sim.energy()["total"]
        scale = sim.fem.total_mass * 9.81 * float(np.ptp(sim.mesh.points, axis=0).max())
        growth = 0.0
        top = float(sim.mesh.points[:, 2].max())
        cx, cy = sim.mesh.points[:, :2].mean(axis=0)
        for k in range(n_steps):
            if "instrument_speed" in case:  # straight down at 1 m/s from 1 cm above, then held
                z = top + 0.01 + 0.004 - min(case["instrument_speed"] * sim.time, 0.02)
                sim.set_instrument_pose("probe", [cx, cy, z], [0, 0, 0, 1], [0, 0, -case["instrument_speed"]])
            if "cuts" in case:
                P = sim.positions()
                c = P[rng.integers(len(P))]
                d = rng.standard_normal((2, 3)) * 0.006
                sim.cut_triangles([np.array([c - d[0] - d[1], c + d[0], c + d[1]])])
            s = sim.step()
            its.append(s.iterations)
            res.append(s.residual)
            conv.append(s.converged)
            floor.append(s.tolerance_unreachable)
            if s.contact is not None and s.contact.max_penetration is not None:
                pen.append(s.contact.max_penetration)
            if k % 5 == 0 or k == n_steps - 1:
                e = sim.energy()["total"]
                if not np.isfinite(e):
                    growth = float("inf")
                    break
                growth = max(growth, (e - e0) / scale)
        finite = bool(np.isfinite(sim.positions()).all())
        e_end = sim.energy()["total"]
        row.update(finite=finite, energy_growth=growth, energy_final=float((e_end - e0) / scale), iterations_mean=float(np.mean(its)),
                   iterations_max=int(np.max(its)), residual_final=float(res[-1]),
                   converged_fraction=float(np.mean(conv)), below_floor_steps=int(np.sum(floor)),
                   rollbacks=sim.rollbacks,
                   max_penetration=float(max(pen)) if pen else None, nodes=sim.mesh.n_nodes)
    except Exception as exc:  # noqa: BLE001
        row.update(finite=False, error=f"{type(exc).__name__}: {exc}")
    finally:
        sim.close()
    row["wall_s"] = time.perf_counter() - t0
    return row


def plot(result, prefix):
    rows = result["rows"]
    cs = list(dict.fromkeys(r["case"] for r in rows))
    ss = list(dict.fromkeys(r["solver"] for r in rows))
    fig, axes = figure(1, 2, figsize=(13, 0.45 * len(cs) + 2))
    for ax, key, title in ((axes[0], "iterations_mean", "mean PCG iterations (log10)"),
                           (axes[1], "energy_growth", "energy growth / (m g L)")):
        M = np.full((len(cs), len(ss)), np.nan)
        for r in rows:
            v = r.get(key)
            if v is not None and r.get("finite"):
                M[cs.index(r["case"]), ss.index(r["solver"])] = np.log10(max(v, 1e-3)) if key == "iterations_mean" else v
        im = ax.imshow(M, aspect="auto", cmap="viridis" if key == "iterations_mean" else "coolwarm")
        for r in rows:
            i, j = cs.index(r["case"]), ss.index(r["solver"])
            if not r.get("finite"):
                txt = "NaN"
            elif key == "iterations_mean":
                txt = f"{r['iterations_mean']:.3g}" + ("" if r["converged_fraction"] == 1.0 else "*")
            else:
                txt = f"{r['energy_growth']:.2g}"
            ax.text(j, i, txt, ha="center", va="center", fontsize=7, color="w" if key == "iterations_mean" else "k")
        ax.set_xticks(range(len(ss)), ss)
        ax.set_yticks(range(len(cs)), cs)
        ax.set_title(title + ("  (* = not always converged)" if key == "iterations_mean" else ""))
        fig.colorbar(im, ax=ax)
    save_figure(fig, prefix, f"stability on {result['device']}")


def main(argv=None) -> int:
    ap = parser("stability", __doc__)
    ap.add_argument("--steps", type=int, default=100)
    ap.add_argument("--n-long", type=int, default=16)
    ap.add_argument("--solvers", nargs="*", default=list(SOLVERS))
    ap.add_argument("--cases", nargs="*", default=None, help="subset of case names")
    ap.add_argument("--newton", type=int, default=3, help="linearisations per step of the *_newton solvers")
    args = ap.parse_args(argv)
    device = resolved_device(args)
    all_cases = cases(args.n_long)
    names = args.cases or list(all_cases)
    prog = Progress(len(names) * len(args.solvers))
    rows = []
    t0 = time.perf_counter()
    for name in names:
        for solver in args.solvers:
            r = run_case(name, all_cases[name], solver, args.steps, device, np.random.default_rng(7), args.newton)
            rows.append(r)
            prog.update(len(rows), f"{name} {solver}: finite={r.get('finite')} it={r.get('iterations_mean', float('nan')):.1f}")
    result = {"rows": rows, "steps": args.steps, "newton_iterations": args.newton, "wall_s": time.perf_counter() - t0}
    publish("stability", device, result, args, plot)
    print(f"{'case':<16} {'solver':<13} {'finite':>6} {'E growth':>9} {'E drift':>9} {'it mean':>8} {'it max':>6} "
          f"{'resid':>9} {'conv':>5} {'floor':>5} {'pen':>9} {'wall s':>7}")
    for r in rows:
        pen = r.get("max_penetration")
        print(f"{r['case']:<16} {r['solver']:<13} {str(r.get('finite')):>6} {r.get('energy_growth', float('nan')):9.3g} "
              f"{r.get('energy_final', float('nan')):9.3g} "
              f"{r.get('iterations_mean', float('nan')):8.1f} {r.get('iterations_max', 0):6d} "
              f"{r.get('residual_final', float('nan')):9.2e} {r.get('converged_fraction', 0):5.2f} "
              f"{r.get('below_floor_steps', 0):5d} "
              f"{'' if pen is None else f'{pen:9.2e}':>9} {r['wall_s']:7.1f}" + (f"  {r['error']}" if "error" in r else ""))
    return 0
