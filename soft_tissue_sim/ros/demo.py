"""The main job of ``make run``: the default scene inside the ROS 2 node, headless.

Spins the node in-process as fast as it steps, with a live progress line and a summary
table at the end. Discovery is kept on this machine (ROS_AUTOMATIC_DISCOVERY_RANGE is set
to LOCALHOST here if unset; the node itself never sets it).
"""

import argparse
import os
import sys


def main(argv=None) -> int:
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.parameter import Parameter

    from ..report import Progress, summarize, table
    from .node import SimNode

    ap = argparse.ArgumentParser(prog="python -m soft_tissue_sim.ros.demo")
    ap.add_argument("--scene", default="default.yaml")
    ap.add_argument("--steps", type=int, default=300)
    ap.add_argument("--device", default="auto")
    args = ap.parse_args(argv)
    rclpy.init()
    node = SimNode(parameter_overrides=[Parameter("scene", value=args.scene), Parameter("device", value=args.device),
                                        Parameter("realtime", value=False)])
    ex = SingleThreadedExecutor()
    ex.add_node(node)
    sim = node.sim
    print(f"node /{node.get_name()}: scene {sim.name}, {sim.mesh.n_nodes} nodes, {sim.mesh.n_tets} tets, "
          f"device {sim.device}, preconditioner {sim.preconditioner.name}", flush=True)
    prog, stats, last = Progress(args.steps), [], None
    try:
        while len(stats) < args.steps:
            ex.spin_once(timeout_sec=0.1)
            s = node.last_stats
            if s is not None and s is not last:
                last = s
                stats.append(s.as_dict())
                prog.update(len(stats), f"{s.total_ms:7.2f} ms/step  it {s.iterations:4d}  res {s.residual:.1e}")
    finally:
        node.destroy_node()
        rclpy.shutdown()
    summary = summarize(stats)
    summary.update({"scene": sim.name, "device": sim.device, "nodes": sim.mesh.n_nodes, "rejected_poses":
                    node.rejected_poses})
    print(table(list(summary.items()), f"summary: {sim.name} in the ROS 2 node"))
    return 0


if __name__ == "__main__":
    sys.exit(main())
