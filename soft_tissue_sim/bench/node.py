"""The simulation node in a robot stack: ``python -m soft_tissue_sim.bench node``.

Starts the node as a separate process (``python -m soft_tissue_sim.ros``, the scene's
parameters on the command line, its own namespace) and drives it from this process with
:class:`soft_tissue_sim.ros.client.RobotClient`, as an integrator's stack would: the first
instrument's poses at ``--pose-rate-hz`` (1 kHz) from a thread, lowered onto the tissue and
pressed in (then moved sideways a little, in contact all along); its wrench subscribed; the
surface and markers subscribed or not; bursts of concurrent service calls. Measured:

1. ``realtime``: the node at ``rate_hz`` (``--rate-hz``): achieved step rate (the node's step
   counter over the window), wrench rate (wrenches received), pose-to-wrench latency (a pose's
   stamp to the first wrench stamped with it: median, p99), poses sent / taken by the node /
   used by a step / superseded (keep-last 1) / dropped on the way, the node's own pose-to-step
   age, real-time factor, late steps;
2. ``max_rate``: ``realtime`` false (set at run time through the parameter service), with
   nothing subscribed and with the surface and markers subscribed, alternately ``--repeats``
   times: steps per second, and the ratio of the two;
3. ``bursts``: ``--burst`` concurrent ``~/pause`` (true, then false) and ``~/reset`` calls:
   answered, succeeded, seconds until the last answer.

Targets (reported, never asserted): wrench rate = step rate; latency median <= two step periods
+ 2 ms; step rate with the surface subscribed >= 90 % of the rate with nothing subscribed;
100 of 100 burst calls answered. Writes ``node_<cpu|gpu>.json`` (summaries only) to
``benchmarks/results/`` (``--out``). The machine's load average is recorded: on a shared CPU
the rates move with it.
"""

from __future__ import annotations

import argparse
import math
import os
import signal
import subprocess
import sys
import tempfile
import time

import numpy as np


def _trajectory(sim, instrument: str):
    """t -> (position, quaternion): 1 s down from above onto the start of the scene's scripted
    sweep, pressed in by the script's depth, then a slow sideways sway of 5 mm along the sweep."""
    from ..ros.scripted_instrument import ease, script_for_scene

    _name, script, _notes = script_for_scene(sim, instrument)
    start = np.array(script.start)
    down = script.unit_down
    above = start - script.approach_height * down
    pressed = start + script.press_depth * down
    along = np.array(script.end) - start
    along = along / max(np.linalg.norm(along), 1e-12)

    def at(t):
        if t < 1.0:
            u, _du = ease(t)
            return above + u * (pressed - above)
        return pressed + 0.005 * math.sin(math.pi * (t - 1.0)) * along

    return at, script


class _Window:
    """Counters of the node (from its diagnostics) and of the client over one measurement."""

    def __init__(self, client, wait_s: float = 10.0):
        from ..ros.client import wait_for

        self.client = client
        t = time.monotonic()
        if not wait_for(lambda: client.diag(": rate", newer_than=t) is not None, wait_s):
            raise RuntimeError("no diagnostics from the node")
        self.rate0 = client.diag(": rate")[0]
        self.input0 = client.diag(": instrument input")[0]
        client.reset_counters()
        self.t0 = time.monotonic()

    def close(self, wait_s: float = 10.0) -> dict:
        from ..ros.client import wait_for

        c = self.client
        t = time.monotonic()
        if not wait_for(lambda: c.diag(": rate", newer_than=t) is not None, wait_s):
            raise RuntimeError("no diagnostics from the node")
        seconds = time.monotonic() - self.t0
        rate1, input1 = c.diag(": rate")[0], c.diag(": instrument input")[0]
        d = lambda kv0, kv1, k: int(kv1.get(k, 0)) - int(kv0.get(k, 0))  # noqa: E731
        steps = d(self.rate0, rate1, "steps_total")
        taken = (d(self.input0, input1, "accepted_poses") + d(self.input0, input1, "rejected_poses")
                 - d(self.input0, input1, "rejected_poses.invalid") - d(self.input0, input1, "rejected_poses.error"))
        lat = c.latency_summary()
        out = {
            "seconds": seconds,
            "steps": steps,
            "step_rate_hz": steps / seconds,
            "wrenches_received": c.wrenches,
            "wrench_rate_hz": c.wrenches / seconds,
            "wrenches_published_by_node": d(self.rate0, rate1, "wrenches_published"),
            "latency_pose_to_wrench_ms": {k: v for k, v in lat.items() if k != "count"},
            "poses_sent": c.poses_sent,
            "poses_taken_by_node": taken,
            "poses_dropped_on_the_way": max(0, c.poses_sent - taken),
            "poses_used_by_a_step": c.stamps_used,
            "poses_superseded": d(self.input0, input1, "superseded_poses"),
            "poses_rejected": d(self.input0, input1, "rejected_poses"),
            "node_pose_to_step_ms_median": float(input1.get("pose_to_step_ms.median", "nan")),
            "node_real_time_factor": float(rate1.get("real_time_factor", "nan")),
            "node_achieved_rate_hz": float(rate1.get("achieved_rate_hz", "nan")),
            "node_step_ms_mean": float(rate1.get("step_ms_mean", "nan")),
            "late_steps": d(self.rate0, rate1, "late_steps"),
            "surfaces_received": c.surfaces,
            "surface_bytes_mean": c.surface_bytes / c.surfaces if c.surfaces else 0,
            "marker_arrays_received": c.marker_arrays,
        }
        return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m soft_tissue_sim.bench node", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", default="default.yaml")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--rate-hz", type=float, default=50.0, help="the node's rate_hz (realtime)")
    ap.add_argument("--pose-rate-hz", type=float, default=1000.0)
    ap.add_argument("--seconds", type=float, default=8.0, help="length of each measurement window")
    ap.add_argument("--warmup", type=float, default=3.0, help="seconds before the first window (contact, kernels)")
    ap.add_argument("--repeats", type=int, default=2, help="alternations of the max-rate pair")
    ap.add_argument("--burst", type=int, default=100)
    ap.add_argument("--out", default=None, help="results directory (default benchmarks/results)")
    args = ap.parse_args(argv)

    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    os.environ.setdefault("ROS_DOMAIN_ID", str(1 + os.getpid() % 100))  # away from other runs on this machine
    import rclpy

    from ..report import table
    from ..ros.client import RobotClient, Spinner, wait_for
    from ..scene import load_scene
    from . import write_result

    probe = load_scene(args.scene, device="cpu")  # geometry for the trajectory (no step taken)
    names = probe.instrument_names()
    if not names:
        print(f"scene {args.scene} has no instrument to drive", file=sys.stderr)
        return 2
    instrument = names[0]
    trajectory, script = _trajectory(probe, instrument)
    scene_name, dt = probe.name, probe.dt
    probe.close()

    ns = f"bench_node_{os.getpid()}"
    log = tempfile.NamedTemporaryFile("w+", prefix="bench_node_", suffix=".log", delete=False)
    pkg_root = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(filter(None, [pkg_root, os.environ.get("PYTHONPATH")])))
    cmd = [sys.executable, "-m", "soft_tissue_sim.ros", "--ros-args", "-r", f"__ns:=/{ns}",
           "-p", f"scene:={args.scene}", "-p", f"device:={args.device}", "-p", f"rate_hz:={args.rate_hz}",
           "-p", "diagnostics_rate_hz:=4.0"]
    load0 = os.getloadavg()
    proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, env=env)
    rclpy.init()
    client = RobotClient(f"/{ns}/soft_tissue_sim", instrument=instrument, node_name="bench_robot")
    spinner = Spinner(client, threads=1)
    figures = {"scene": scene_name, "dt": dt, "instrument": instrument, "rate_hz": args.rate_hz,
               "pose_rate_hz": args.pose_rate_hz, "window_s": args.seconds, "load_average_start": list(load0)}
    rc = 1
    try:
        print(f"node: {' '.join(cmd)}", flush=True)
        ok = wait_for(lambda: client.diag(": rate") is not None and client.pose_pub.get_subscription_count() > 0
                      and proc.poll() is None, 120.0)
        if not ok:
            raise RuntimeError(f"the node did not come up (exit code {proc.poll()})")
        client.start_stream(lambda t: (trajectory(t), (0.0, 0.0, 0.0, 1.0)), args.pose_rate_hz)
        time.sleep(args.warmup)

        print(f"realtime at {args.rate_hz:g} Hz, poses at {args.pose_rate_hz:g} Hz ({args.seconds:g} s)...", flush=True)
        w = _Window(client)
        time.sleep(args.seconds)
        rt = w.close()
        period_ms = 1000.0 / rt["step_rate_hz"] if rt["step_rate_hz"] > 0 else float("nan")
        rt["latency_target_ms"] = 2.0 * period_ms + 2.0
        figures["realtime"] = rt

        print("bursts...", flush=True)
        bursts = {}
        for key, name, data in (("pause_true", "pause", True), ("pause_false", "pause", False),
                                ("reset", "reset", None)):
            b = client.burst(name, args.burst, data=data)
            bursts[key] = {k: b[k] for k in ("calls", "answered", "succeeded", "seconds")}
        figures["bursts"] = bursts
        client.start_stream(lambda t: (trajectory(t), (0.0, 0.0, 0.0, 1.0)), args.pose_rate_hz)  # down again
        time.sleep(args.warmup)

        res = client.set_parameters(realtime=False)
        if res != [(True, "")]:
            raise RuntimeError(f"realtime false refused: {res}")
        pairs = {"nothing_subscribed": [], "surface_subscribed": []}
        for k in range(args.repeats):
            for key, on in (("nothing_subscribed", False), ("surface_subscribed", True)):
                print(f"as fast as possible, {key.replace('_', ' ')} ({k + 1}/{args.repeats})...", flush=True)
                client.subscribe_display(on)
                time.sleep(2.0)
                w = _Window(client)
                time.sleep(args.seconds)
                pairs[key].append(w.close())
        client.subscribe_display(False)
        mr = {}
        for key, runs in pairs.items():
            mr[key] = {"step_rate_hz": [r["step_rate_hz"] for r in runs],
                       "step_rate_hz_mean": float(np.mean([r["step_rate_hz"] for r in runs])),
                       "wrench_rate_hz_mean": float(np.mean([r["wrench_rate_hz"] for r in runs])),
                       "surfaces_per_s_mean": float(np.mean([r["surfaces_received"] / r["seconds"] for r in runs])),
                       "surface_bytes_mean": float(np.mean([r["surface_bytes_mean"] for r in runs])),
                       "latency_median_ms_mean": float(np.mean([r["latency_pose_to_wrench_ms"].get("median_ms",
                                                                                                  np.nan)
                                                                for r in runs]))}
        mr["ratio_surface_to_nothing"] = mr["surface_subscribed"]["step_rate_hz_mean"] / max(
            mr["nothing_subscribed"]["step_rate_hz_mean"], 1e-12)
        figures["max_rate"] = mr
    finally:
        client.stop_stream()
        figures["load_average_end"] = list(os.getloadavg())
        if proc.poll() is None:
            proc.send_signal(signal.SIGINT)
            try:
                proc.wait(30)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
        figures["node_exit_code"] = proc.returncode
        spinner.close()
        client.destroy_node()
        rclpy.try_shutdown()
        log.seek(0)
        tail = log.read().splitlines()[-15:]
        log.close()
        os.unlink(log.name)
        if proc.returncode not in (0, -signal.SIGINT):
            print("node output (tail):\n" + "\n".join(tail), file=sys.stderr)
    if "max_rate" not in figures:
        return rc

    rt, b, mr = figures["realtime"], figures["bursts"], figures["max_rate"]
    lat = rt["latency_pose_to_wrench_ms"]
    rows = [("step rate (realtime) [1/s]", rt["step_rate_hz"]), ("wrench rate [1/s]", rt["wrench_rate_hz"]),
            ("latency median / p99 [ms]", f"{lat.get('median_ms', float('nan')):.1f} / "
                                         f"{lat.get('p99_ms', float('nan')):.1f}"),
            ("latency target [ms]", rt["latency_target_ms"]),
            ("poses sent / taken / used", f"{rt['poses_sent']} / {rt['poses_taken_by_node']} / "
                                          f"{rt['poses_used_by_a_step']}"),
            ("poses dropped on the way", rt["poses_dropped_on_the_way"]),
            ("real-time factor", rt["node_real_time_factor"]),
            ("max rate, nothing subscribed [1/s]", mr["nothing_subscribed"]["step_rate_hz_mean"]),
            ("max rate, surface subscribed [1/s]", mr["surface_subscribed"]["step_rate_hz_mean"]),
            ("ratio (target >= 0.9)", mr["ratio_surface_to_nothing"]),
            ("surfaces received [1/s]", mr["surface_subscribed"]["surfaces_per_s_mean"])]
    rows += [(f"burst {k}: answered / succeeded", f"{v['answered']} / {v['succeeded']} of {v['calls']} "
                                                   f"in {v['seconds']:.2f} s") for k, v in b.items()]
    rows += [("load average start / end", f"{figures['load_average_start'][0]:.2f} / "
                                          f"{figures['load_average_end'][0]:.2f}"),
             ("node exit code", figures["node_exit_code"])]
    print(table(rows, f"node benchmark: {scene_name}, {args.device}"))
    path = write_result("node", args.device, figures, args.out)
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
