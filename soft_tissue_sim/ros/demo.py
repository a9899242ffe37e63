"""The main job of ``make run``: a scene inside the ROS 2 node, headless.

Runs the simulation node in-process (its physics thread stepping as fast as it can) and, when
the scene has instruments, the scripted instrument node
(:mod:`soft_tissue_sim.ros.scripted_instrument`) in an executor beside it: approach, press,
blade on and sweep, blade off, retract. The script runs on simulation time (the simulation
node publishes /clock), so it takes about the same number of steps on any machine (it follows
the clock it receives: a pose may reach the simulation a step later on a busy machine). A live
line shows steps/s, solver iterations, contacts, cuts and the instrument force; a summary table
closes the run.

Discovery is kept on this machine (ROS_AUTOMATIC_DISCOVERY_RANGE is set to LOCALHOST here if
unset; the node itself never sets it).
"""

import argparse
import collections
import os
import sys
import time


def main(argv=None) -> int:
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    import numpy as np
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.parameter import Parameter

    from ..report import Progress, summarize, table
    from ..realtime import freeze_long_lived
    from .node import SimNode
    from .scripted_instrument import ScriptedInstrument, script_for_scene, script_parameters

    ap = argparse.ArgumentParser(prog="python -m soft_tissue_sim.ros.demo")
    ap.add_argument("--scene", default="default.yaml")
    ap.add_argument("--steps", type=int, default=300)
    ap.add_argument("--device", default="auto")
    ap.add_argument("--instrument", default=None, help="instrument to script (default: the scene's script or first)")
    ap.add_argument("--no-script", action="store_true", help="do not start the scripted instrument")
    args = ap.parse_args(argv)
    rclpy.init()
    node = scripted = None
    try:
        node = SimNode(parameter_overrides=[
            Parameter("scene", value=args.scene), Parameter("device", value=args.device),
            Parameter("realtime", value=False), Parameter("publish_clock", value=True),
            Parameter("use_sim_time", value=True)], start=False)
        sim = node.sim
        done = collections.deque()  # step statistics, appended by the node's physics thread
        node.on_step = done.append
        ex = SingleThreadedExecutor()
        ex.add_node(node)
        print(f"node /{node.get_name()}: scene {sim.name}, {sim.mesh.n_nodes} nodes, {sim.mesh.n_tets} tets, "
              f"device {sim.device}, preconditioner {sim.preconditioner.name}, "
              f"instruments {sim.instrument_names() or 'none'}, cutting {'yes' if sim.has_cutting else 'no'}",
              flush=True)
        if sim.instrument_names() and not args.no_script:
            name, script, notes = script_for_scene(sim, args.instrument)
            for n in notes:
                print(f"note: {n}", flush=True)
            scripted = ScriptedInstrument(parameter_overrides=[
                Parameter("use_sim_time", value=True), Parameter("instrument", value=name),
                Parameter("sim_node", value=node.get_fully_qualified_name()),
                Parameter("frame_id", value=node.frame_id)] + [Parameter(k, value=v) for k, v in
                                                               script_parameters(script)])
            ex.add_node(scripted)
            print(f"scripted instrument '{name}': {np.round(script.start, 4).tolist()} -> "
                  f"{np.round(script.end, 4).tolist()}, press {script.press_depth * 1000:.1f} mm, "
                  f"{script.total_s:.2f} s of simulation time ({script.total_s / sim.dt:.0f} steps)", flush=True)
        tri0 = len(sim.surface_triangles())
        freeze_long_lived()
        prog, stats = Progress(args.steps), []
        window = []  # wall times of recent steps, for steps/s
        force_max, phases = 0.0, []
        node.start()
        while len(stats) < args.steps:
            ex.spin_once(timeout_sec=0.02)
            if not done:
                continue
            s = done.popleft()
            d = s.as_dict()
            stats.append(d)
            now = time.perf_counter()
            window = [t for t in window if now - t < 2.0] + [now]
            sps = (len(window) - 1) / (window[-1] - window[0]) if len(window) > 1 else 0.0
            force = max((float(np.linalg.norm(f)) for f, _t in node.last_wrench.values()), default=0.0)
            force_max = max(force_max, force)
            phase = scripted.phase if scripted is not None else None
            if phase and (not phases or phases[-1] != phase):
                phases.append(phase)
            text = f"{sps:5.1f} steps/s  it {s.iterations:4d}  res {s.residual:.1e}"
            if sim.has_contact:
                text += f"  contacts {d.get('contacts', 0):3d}  |F| {force:7.3f} N"
            if sim.has_cutting:
                text += f"  cuts {d.get('cuts', 0)}"
            if phase:
                text += f"  [{phase}]"
            prog.update(len(stats), text)
    finally:
        for n in (scripted, node):
            if n is not None:
                n.destroy_node()
        rclpy.shutdown()
    summary = summarize(stats)
    summary.update({"scene": sim.name, "device": sim.device, "nodes": sim.mesh.n_nodes,
                    "surface_triangles": f"{tri0} -> {len(sim.surface_triangles())}",
                    "poses_accepted": node.accepted["pose"], "poses_rejected": node.rejected_poses})
    if sim.has_contact:
        summary["force_max_N"] = force_max
    if sim.has_cutting and stats:
        summary["cuts_total"] = int(stats[-1].get("cuts", 0))  # the cutter's running count of modifications
    if scripted is not None:
        summary["script_phases"] = " > ".join(phases)
        summary["blade"] = scripted.cutting_error or ("used" if scripted.blade_state is not None else "not used")
    print(table(list(summary.items()), f"summary: {sim.name} in the ROS 2 node"))
    return 0


if __name__ == "__main__":
    sys.exit(main())
