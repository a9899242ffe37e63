"""The contact LCP's solvers on recorded problems: ``python -m soft_tissue_sim.bench lcp``.

Records the LCPs the host solves (:meth:`soft_tissue_sim.contact.pgs.PGS.solve`) in scenes run
on Warp's CPU backend, then solves each again, timed:

* ``default``: the default scene along the node benchmark's trajectory (``--steps`` steps: the
  scalpel lowered, pressed and swayed; friction, about 15 rows), every ``--every``-th set, as
  the sweeps alone leave them (the warm starts of a run without the friction finish);
* ``resection``: the shipped scripted resection (``bench brain``'s session; frictionless, self
  contacts of the cut's faces), its sets of more than 32 rows, ``--large`` of them at random
  (0: not run).

Each set is solved by the host's :class:`~soft_tissue_sim.contact.pgs.PGS` and, on
``--device``, by :func:`~soft_tissue_sim.contact.device_lcp.device_pgs_kernel` in buffers of 32
rows (the default limit) or, for the large sets, 256 (each solve launched and waited for, so
the device's times include a launch). Reported per set kind: sets, rows (median), sweeps and
face solves (mean, the host's; the device makes the same), the sets left above the tolerance,
time per solve (mean and median) of each, and the largest difference of the device's lambda
from the host's relative to the largest force; for the sets with friction, both solves with
``contact.friction_active_set`` too (iterations, sets above the tolerance, times, and the
largest difference of the contact displacement W lambda between them).

``trajectory``: the default scene along the same trajectory run on ``--device`` for
``--trajectory`` steps with the LCP converged (1e-9 m, up to 5,000 iterations), by the sweeps
alone, and with the friction finish (a factor made in the step that asks for it, so that the runs are
comparable): per setting the iterations a step, the steps above the tolerance, the step's wall
time, and the scalpel's force (median and p99, relative) and the positions (largest) against
the converged run: error against run time for the contact LCP.

Writes ``lcp_<cpu|gpu>.json``. Not a target row: a measuring tool for the device LCP's
kernels (docs/benchmarks.md).
"""

from __future__ import annotations

import contextlib
import time

import numpy as np
import warp as wp

from .common import parser, publish, resolved_device


@contextlib.contextmanager
def recording(keep):
    """Within it, every host LCP solve appends (W, d0, row_start, rows, mu, lam0, tolerance,
    pyramid, max_iterations) to the list it yields, where ``keep(m)`` for its row count m."""
    from ..contact.pgs import PGS

    sets, solve = [], PGS.solve

    def recorded(self, W, d0, row_start, rows, mu, max_iterations, tolerance, pyramid, lam0):
        if keep(len(d0)):
            sets.append((np.array(W), np.array(d0), np.array(row_start), np.array(rows), np.array(mu),
                         np.array(lam0), float(tolerance), bool(pyramid), int(max_iterations)))
        return solve(self, W, d0, row_start, rows, mu, max_iterations, tolerance, pyramid, lam0)

    PGS.solve = recorded
    try:
        yield sets
    finally:
        PGS.solve = solve


def along_trajectory(sim, steps: int):
    """Steps ``sim`` (the default scene) along the node benchmark's trajectory (the scalpel
    lowered, pressed and swayed), closing it at the end; yields (step index, the scalpel's name,
    the step's statistics, its wall time in ms) after each step."""
    from .node import _trajectory

    try:
        name = sim.instrument_names()[0]
        at, _script = _trajectory(sim, name)
        for i in range(steps):
            sim.set_instrument_pose(name, at(i * sim.dt), (0.0, 0.0, 0.0, 1.0))
            t0 = time.perf_counter()
            stats = sim.step()
            yield i, name, stats, 1e3 * (time.perf_counter() - t0)
    finally:
        sim.close()


def default_sets(steps: int, every: int) -> list:
    """The default scene's LCPs along the node benchmark's trajectory (CPU), every ``every``-th,
    as the sweeps alone leave them (the device's default, ``friction_active_set`` false: each
    set's warm start is the last step's swept forces)."""
    from ..scene import load_scene

    sim = load_scene("default.yaml", device="cpu", overrides={"contact": {"friction_active_set": False}})
    with recording(lambda m: m > 0) as sets:
        for _ in along_trajectory(sim, steps):
            pass
    return sets[::every]


def resection_sets(count: int, seed: int = 0) -> list:
    """``count`` of the shipped resection's LCPs beyond 32 rows (CPU), at random."""
    from .brain import run

    with recording(lambda m: m > 32) as sets:
        run("cpu")
    rng = np.random.default_rng(seed)
    pick = sorted(rng.choice(len(sets), size=min(count, len(sets)), replace=False)) if sets else []
    return [sets[i] for i in pick]


def host_solve(problem, friction_active_set: bool = False) -> tuple[np.ndarray, int, float, float]:
    """The host's solve of a recorded set (``friction_active_set``: with that finish, as the
    scene option asks): (lambda, sweeps and active-set steps, residual, seconds)."""
    from ..contact.pgs import PGS

    W, d0, row_start, rows, mu, lam0, tol, pyramid, max_it = problem
    pgs = PGS(friction_active_set=friction_active_set)
    pgs.solve(W, d0, row_start, rows, mu, max_it, tol, pyramid, lam0)  # its buffers and launch made
    t0 = time.perf_counter()
    lam, its, res = pgs.solve(W, d0, row_start, rows, mu, max_it, tol, pyramid, lam0)
    return lam, its, res, time.perf_counter() - t0


def device_solve(problem, cap: int, device, reps: int = 3, friction_finish: bool = False) -> tuple[np.ndarray, int,
                                                                                                   float]:
    """The device's solve of a recorded set (:meth:`~soft_tissue_sim.contact.device_lcp.DeviceLCP.
    solve` in buffers of ``cap`` rows, the set's W written in; ``friction_finish``: with the
    friction finish): (lambda, sweeps and face solves, seconds a solve, launch and wait included)."""
    from ..contact.device_lcp import DeviceLCP
    from ..contact.pgs import FIRST_SWEEPS

    W, d0, row_start, rows, mu, lam0, tol, pyramid, max_it = problem
    m = len(d0)
    lcp = DeviceLCP(cap, device)
    lcp.stage_problem(W, d0, lam0, row_start, rows, mu)
    lcp.solve(max_it, tol, pyramid, FIRST_SWEEPS, friction_finish)  # loaded
    wp.synchronize_device(device)
    t0 = time.perf_counter()
    for _ in range(reps):
        lcp.solve(max_it, tol, pyramid, FIRST_SWEEPS, friction_finish)
    wp.synchronize_device(device)
    return lcp.lam.numpy()[:m], int(lcp.info.numpy()[0]), (time.perf_counter() - t0) / reps


def compare(sets: list, cap: int, device) -> dict:
    """The host's and the device's solves of ``sets``, summarized."""
    if not sets:
        return {"sets": 0}
    host_t, dev_t, its, diff, capped = [], [], [], [], 0
    fin_t, fin_its, fin_capped, fin_dev_t, fin_diff = [], [], 0, [], []  # the frictional sets with the friction finish
    for p in sets:
        lam_h, it, res, th = host_solve(p)
        lam_d, it_d, td = device_solve(p, cap, device)
        host_t.append(th)
        dev_t.append(td)
        its.append(it)
        capped += res > p[6]
        scale = max(float(np.abs(lam_h).max()), 1e-300)
        diff.append(float(np.abs(lam_d - lam_h).max()) / scale)
        if len(p[2]) < len(p[1]):
            lam_f, it_f, res_f, tf = host_solve(p, friction_active_set=True)
            fin_t.append(tf)
            fin_its.append(it_f)
            fin_capped += res_f > p[6]
            lam_fd, _it, tfd = device_solve(p, cap, device, friction_finish=True)
            fin_dev_t.append(tfd)
            # the contact displacement W lambda: where nearly repeated contacts share a force,
            # rounding can split it otherwise
            fin_diff.append(float(np.abs(p[0] @ (lam_fd - lam_f)).max()))
    ms = lambda t: (1e3 * float(np.mean(t)), 1e3 * float(np.median(t)))  # noqa: E731
    out = {"sets": len(sets), "rows_median": float(np.median([len(p[1]) for p in sets])),
           "frictional": int(sum(len(p[2]) < len(p[1]) for p in sets)), "iterations_mean": float(np.mean(its)),
           "above_tolerance": int(capped), "host_ms_mean": ms(host_t)[0], "host_ms_median": ms(host_t)[1],
           "device_ms_mean": ms(dev_t)[0], "device_ms_median": ms(dev_t)[1],
           "device_buffer_rows": cap, "lambda_max_relative_difference": float(max(diff))}
    if fin_t:  # the host with contact.friction_active_set, on the frictional sets
        out["friction_finish"] = {"iterations_mean": float(np.mean(fin_its)), "above_tolerance": int(fin_capped),
                                  "host_ms_mean": ms(fin_t)[0], "host_ms_median": ms(fin_t)[1],
                                  "device_ms_mean": ms(fin_dev_t)[0], "device_ms_median": ms(fin_dev_t)[1],
                                  "displacement_max_difference_m": float(max(fin_diff))}
    return out


TRAJECTORY_SETTINGS = {  # name -> contact options over the scene's (the reference first)
    "converged": {"tolerance": 1e-9, "max_iterations": 5000},
    "sweeps": {"friction_active_set": False},
    "friction_finish": {"friction_active_set": True},
}


def trajectory_run(device, steps: int, contact: dict) -> dict:
    """The default scene along the node benchmark's trajectory on ``device`` (a factor made in
    the step that asks for it, so that runs are comparable) with ``contact`` options: per step the
    scalpel's force, the LCP's iterations and residual, the wall time; positions every 10th step."""
    from ..scene import load_scene

    sim = load_scene("default.yaml", device=device, overrides={"contact": contact,
                                                                  "solver": {"ldlt": {"deterministic": True}}})
    tol = sim.contact.options["tolerance"]
    force, its, above, wall, x = [], [], 0, [], []
    for i, name, stats, ms in along_trajectory(sim, steps):
        d = stats.as_dict()
        wall.append(ms)
        force.append(sim.instrument_wrench(name)[0].copy())
        its.append(d.get("gs_iterations", 0) or 0)
        above += (d.get("lcp_residual", 0.0) or 0.0) > tol
        if i % 10 == 0:
            x.append(sim.positions())
    return {"force": np.array(force), "iterations": np.array(its), "above": above, "wall": np.array(wall),
            "x": np.array(x)}


def trajectory(device, steps: int) -> dict:
    """The default scene's trajectory with each of :data:`TRAJECTORY_SETTINGS`, each against the
    converged one: iterations a step, steps above the tolerance, step time, the scalpel's force
    against the converged run's (relative, over the steps it is pressed) and the positions'
    largest difference."""
    runs = {k: trajectory_run(device, steps, c) for k, c in TRAJECTORY_SETTINGS.items()}
    ref = runs["converged"]
    nref = np.linalg.norm(ref["force"], axis=1)
    on = nref > 1e-6 * nref.max() if len(nref) else nref > 0
    out = {"steps": int(steps)}
    for k, r in runs.items():
        rel = np.linalg.norm(r["force"] - ref["force"], axis=1)[on] / nref[on] if on.any() else np.zeros(1)
        out[k] = {"iterations_mean": float(r["iterations"].mean()), "above_tolerance_fraction": r["above"] / steps,
                  "step_ms_median": float(np.median(r["wall"])), "step_ms_mean": float(r["wall"].mean()),
                  "wrench_error_median": float(np.median(rel)), "wrench_error_p99": float(np.percentile(rel, 99)),
                  "positions_max_error_m": float(np.abs(r["x"] - ref["x"]).max())}
    return out


def main(argv=None) -> int:
    ap = parser("lcp", __doc__)
    ap.add_argument("--steps", type=int, default=1200, help="steps of the default scene's trajectory")
    ap.add_argument("--every", type=int, default=4, help="keep every n-th of the default scene's sets")
    ap.add_argument("--large", type=int, default=120, help="resection sets beyond 32 rows (0: none)")
    ap.add_argument("--trajectory", type=int, default=1500,
                    help="steps of the default scene's trajectory run on --device with each LCP setting (0: none)")
    args = ap.parse_args(argv)
    device = resolved_device(args)
    from ..contact.device_lcp import BIG, SMALL

    figures = {"default": compare(default_sets(args.steps, args.every), SMALL, device)}
    if args.large > 0:
        figures["resection"] = compare(resection_sets(args.large), BIG, device)
    if args.trajectory > 0:
        figures["trajectory"] = trajectory(device, args.trajectory)
    publish("lcp", device, figures, args)
    print(f"LCP solves on {device} (host: this machine's CPU)")
    for kind, f in figures.items():
        if kind == "trajectory":
            print(f"  the default scene's trajectory on {device}, {f['steps']} steps, against the converged LCPs:")
            for name in TRAJECTORY_SETTINGS:
                g = f[name]
                print(f"  {name:16s} {g['iterations_mean']:6.1f} iterations a step, "
                      f"{100 * g['above_tolerance_fraction']:4.1f} % above the tolerance, step "
                      f"{g['step_ms_median']:.2f} / {g['step_ms_mean']:.2f} ms, wrench {g['wrench_error_median']:.1e} / "
                      f"{g['wrench_error_p99']:.1e}, positions {1e6 * g['positions_max_error_m']:.1f} um")
            continue
        if not f["sets"]:
            print(f"  {kind:10s} no sets")
            continue
        print(f"  {kind:10s} {f['sets']:4d} sets, {f['rows_median']:.0f} rows median, {f['iterations_mean']:.1f} "
              f"sweeps/face solves; host {f['host_ms_mean']:.3f} / {f['host_ms_median']:.3f} ms, device "
              f"{f['device_ms_mean']:.3f} / {f['device_ms_median']:.3f} ms (mean / median); lambda within "
              f"{f['lambda_max_relative_difference']:.1e}; {f['above_tolerance']} above the tolerance")
        if "friction_finish" in f:
            g = f["friction_finish"]
            print(f"  {'':10s} with the friction finish: {g['iterations_mean']:.1f} sweeps/steps, host "
                  f"{g['host_ms_mean']:.3f} / {g['host_ms_median']:.3f} ms, device {g['device_ms_mean']:.3f} / "
                  f"{g['device_ms_median']:.3f} ms, {g['above_tolerance']} above the tolerance, W lambda within "
                  f"{g['displacement_max_difference_m']:.1e} m")
    return 0
