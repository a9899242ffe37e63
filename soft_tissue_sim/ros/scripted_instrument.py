"""A scripted instrument: a second rclpy node that drives one instrument of the simulation node.

The script (pure functions, no ROS needed: :class:`Script`, :func:`sample`): approach from
``approach_height`` above ``start`` down to ``start`` (a point on the tissue surface), press
``press_depth`` into the tissue, switch the blade on and sweep (still pressed) to ``end``,
switch the blade off and retract ``approach_height`` above ``end``, then hold there. Each
segment is a quintic ease (zero velocity and acceleration at both ends), so position and
velocity are continuous everywhere.

The node ``scripted_instrument`` publishes, at ``rate_hz`` on its own clock (use_sim_time with
the simulation node's ``publish_clock`` makes it follow simulation time):
  <sim_node>/instruments/<instrument>/pose    geometry_msgs/PoseStamped (sensor-data QoS)
  <sim_node>/instruments/<instrument>/twist   geometry_msgs/TwistStamped (sensor-data QoS)
and calls <sim_node>/set_cutting (std_srvs/SetBool) when the blade should change state; a
simulation without cutting answers with a failure, which is logged once and the script goes on.

Parameters: instrument, sim_node, frame_id, start, end, down, approach_height, press_depth,
approach_s, press_s, sweep_s, retract_s, orientation (x, y, z, w), rate_hz, loop, use_cutting.
A scene may carry the same keys (those of :class:`Script` and ``instrument``) under ``script:``.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, fields

import numpy as np
import rclpy
from geometry_msgs.msg import PoseStamped, TwistStamped
from rcl_interfaces.msg import ParameterDescriptor
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.qos import qos_profile_sensor_data
from std_srvs.srv import SetBool

PHASES = ("approach", "press", "sweep", "retract", "done")


@dataclass(frozen=True)
class Script:
    """The scripted cut. Points in the world frame [m], durations [s]."""

    start: tuple = (0.12, 0.0, 0.02)  # surface point where the blade goes in
    end: tuple = (0.28, 0.0, 0.02)  # surface point where the sweep ends
    down: tuple = (0.0, 0.0, -1.0)  # direction into the tissue
    approach_height: float = 0.03
    press_depth: float = 0.004
    approach_s: float = 0.5
    press_s: float = 0.4
    sweep_s: float = 1.2
    retract_s: float = 0.5

    def __post_init__(self):
        for k in ("start", "end", "down"):
            v = np.asarray(getattr(self, k), dtype=float)
            if v.shape != (3,) or not np.all(np.isfinite(v)):
                raise ValueError(f"script {k} must be 3 finite numbers, got {getattr(self, k)!r}")
            object.__setattr__(self, k, tuple(float(c) for c in v))
        if not np.linalg.norm(self.down) > 0:
            raise ValueError("script down must not be the zero vector")
        for k in ("approach_height", "press_depth"):
            v = float(getattr(self, k))
            if not (math.isfinite(v) and v >= 0):
                raise ValueError(f"script {k} must be >= 0, got {v!r}")
            object.__setattr__(self, k, v)
        for k in ("approach_s", "press_s", "sweep_s", "retract_s"):
            v = float(getattr(self, k))
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"script {k} must be > 0, got {v!r}")
            object.__setattr__(self, k, v)

    @classmethod
    def from_dict(cls, d: dict) -> Script:
        names = {f.name for f in fields(cls)}
        unknown = set(d) - names
        if unknown:
            raise ValueError(f"unknown script keys: {sorted(unknown)} (known: {sorted(names)})")
        return cls(**d)

    @property
    def unit_down(self) -> np.ndarray:
        d = np.asarray(self.down)
        return d / np.linalg.norm(d)

    def segments(self):
        """[(phase, p0, p1, duration, blade_on)] in order."""
        s, e, dn = np.asarray(self.start), np.asarray(self.end), self.unit_down
        above_s, above_e = s - self.approach_height * dn, e - self.approach_height * dn
        in_s, in_e = s + self.press_depth * dn, e + self.press_depth * dn
        return [
            ("approach", above_s, s, self.approach_s, False),
            ("press", s, in_s, self.press_s, False),
            ("sweep", in_s, in_e, self.sweep_s, True),
            ("retract", in_e, above_e, self.retract_s, False),
        ]

    @property
    def total_s(self) -> float:
        return self.approach_s + self.press_s + self.sweep_s + self.retract_s


@dataclass
class Sample:
    position: np.ndarray
    velocity: np.ndarray
    phase: str
    blade: bool


def ease(u: float) -> tuple[float, float]:
    """Quintic ease 10u^3 - 15u^4 + 6u^5 on [0, 1] and its derivative (both clamped)."""
    u = min(max(float(u), 0.0), 1.0)
    return u * u * u * (10.0 + u * (-15.0 + 6.0 * u)), 30.0 * u * u * (1.0 - u) ** 2


def sample(script: Script, t: float) -> Sample:
    """Where the instrument is at time ``t`` [s] after the script started, how fast, in which phase."""
    t = max(float(t), 0.0)
    t0 = 0.0
    for phase, p0, p1, dur, blade in script.segments():
        if t < t0 + dur:
            s, ds = ease((t - t0) / dur)
            return Sample(p0 + s * (p1 - p0), (ds / dur) * (p1 - p0), phase, blade)
        t0 += dur
    last = script.segments()[-1][2]
    return Sample(last.copy(), np.zeros(3), "done", False)


def path(script: Script, n: int = 200) -> tuple[np.ndarray, np.ndarray]:
    """(times, positions) of ``n`` evenly spaced samples over the whole script."""
    ts = np.linspace(0.0, script.total_s, n)
    return ts, np.array([sample(script, t).position for t in ts])


def script_over_surface(points: np.ndarray, up_axis: int = 2, long_axis: int | None = None,
                        fractions=(0.15, 0.35), clearance: float = 0.0, near: int = 8, **kw) -> Script:
    """A script whose sweep runs along the top of a point cloud (e.g. the tissue's rest positions):
    along its longest horizontal axis from ``fractions[0]`` to ``fractions[1]`` of its extent,
    ``clearance`` above the top there (the highest of the ``near`` points horizontally nearest to
    the start, and to the end: on a domed body the tip sphere's surface then just touches at both),
    near the middle of the other horizontal axis but halfway between two node coordinates: a
    structured mesh often has a node plane in the middle, and a blade sweeping in it cuts no element."""
    pts = np.asarray(points, dtype=float)
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    horiz = [a for a in range(3) if a != up_axis]
    if long_axis is None:
        long_axis = max(horiz, key=lambda a: hi[a] - lo[a])
    start, end = 0.5 * (lo + hi), 0.5 * (lo + hi)
    start[up_axis] = end[up_axis] = hi[up_axis] + float(clearance)
    side = next(a for a in horiz if a != long_axis)
    vals = np.unique(np.round(pts[:, side], 9))
    if len(vals) > 1:
        mids = 0.5 * (vals[1:] + vals[:-1])
        start[side] = end[side] = mids[np.argmin(np.abs(mids - start[side]))]
    start[long_axis] = lo[long_axis] + fractions[0] * (hi[long_axis] - lo[long_axis])
    end[long_axis] = lo[long_axis] + fractions[1] * (hi[long_axis] - lo[long_axis])
    for p in (start, end):
        d = np.linalg.norm(pts[:, horiz] - p[horiz], axis=1)
        closest = np.argsort(d)[:max(1, int(near))]
        p[up_axis] = pts[closest, up_axis].max() + float(clearance)
    down = np.zeros(3)
    down[up_axis] = -1.0
    return Script(start=tuple(start), end=tuple(end), down=tuple(down), **kw)


def script_for_scene(sim, instrument: str | None = None) -> tuple[str, Script, list[str]]:
    """(instrument name, script, notes) for a simulation with instruments: the scene's ``script:``
    keys (``instrument`` and those of :class:`Script`) over a sweep along the top of the tissue
    (:func:`script_over_surface`, cleared by the instrument's radius). Unknown keys are left out
    and named in the notes."""
    names = sim.instrument_names()
    if not names:
        raise ValueError("this scene has no instruments to script")
    cfg = dict((getattr(sim, "config", None) or {}).get("script") or {})
    name = instrument or cfg.pop("instrument", None) or names[0]
    cfg.pop("instrument", None)
    if name not in names:
        raise ValueError(f"unknown instrument {name!r}; this scene has {names}")
    known = {f.name for f in fields(Script)}
    notes = [f"scene script key {k!r} is not a scripted-instrument key: left out" for k in sorted(set(cfg) - known)]
    radius = 0.0
    for it in (sim.config.get("instruments") or []):
        if isinstance(it, dict) and it.get("name") == name:
            radius = float(it.get("radius", 0.0) or 0.0)
    base = script_over_surface(sim.mesh.points, clearance=radius)
    merged = {f.name: getattr(base, f.name) for f in fields(Script)}
    merged.update({k: v for k, v in cfg.items() if k in known})
    return name, Script(**merged), notes


def script_parameters(script: Script) -> list[tuple[str, object]]:
    """(parameter name, value) pairs that give a ScriptedInstrument node this script."""
    out = []
    for f in fields(Script):
        v = getattr(script, f.name)
        out.append((f.name, [float(c) for c in v] if isinstance(v, tuple) else float(v)))
    return out


def _desc(text):
    return ParameterDescriptor(description=text)


class ScriptedInstrument(Node):
    """Publishes one instrument's pose and twist along a :class:`Script`; toggles the blade."""

    def __init__(self, node_name="scripted_instrument", **kwargs):
        super().__init__(node_name, **kwargs)
        d = Script()
        p = self.declare_parameter
        p("instrument", "probe", _desc("the scene's instrument name"))
        p("sim_node", "/soft_tissue_sim", _desc("fully qualified name of the simulation node"))
        p("frame_id", "world", _desc("frame of the published poses (the simulation node's frame_id)"))
        for k in ("start", "end", "down"):
            p(k, list(getattr(d, k)), _desc(f"script {k} [m], world frame"))
        for k in ("approach_height", "press_depth", "approach_s", "press_s", "sweep_s", "retract_s"):
            p(k, getattr(d, k), _desc(f"script {k}"))
        p("orientation", [0.0, 0.0, 0.0, 1.0], _desc("instrument orientation quaternion (x, y, z, w)"))
        p("rate_hz", 100.0, _desc("publication rate on the node clock"))
        p("loop", False, _desc("start the script again once it is done"))
        p("use_cutting", True, _desc("call <sim_node>/set_cutting around the sweep"))
        p("wait_for_sim_s", 10.0, _desc("the script starts once the simulation node subscribes to the pose "
                                        "and offers set_cutting, or after this long with only the subscription"))
        g = lambda k: self.get_parameter(k).value  # noqa: E731
        self.script = Script(**{f.name: g(f.name) for f in fields(Script)})
        q = np.asarray(g("orientation"), dtype=float)
        if q.shape != (4,) or not np.isfinite(q).all() or np.linalg.norm(q) < 1e-6:
            raise ValueError(f"orientation must be a non-zero quaternion (x, y, z, w), got {g('orientation')}")
        self.orientation = q / np.linalg.norm(q)
        self.instrument = g("instrument")
        self.frame_id = g("frame_id")
        self.loop = bool(g("loop"))
        self.use_cutting = bool(g("use_cutting"))
        base = g("sim_node").rstrip("/")
        topic = f"{base}/instruments/{self.instrument}"
        self.pose_pub = self.create_publisher(PoseStamped, f"{topic}/pose", qos_profile_sensor_data)
        self.twist_pub = self.create_publisher(TwistStamped, f"{topic}/twist", qos_profile_sensor_data)
        self.cutting_client = self.create_client(SetBool, f"{base}/set_cutting")
        self.t0_ns = None
        self.phase = None
        self.published = 0
        self.blade_requested = None  # the state last asked of the simulation
        self.blade_state = None  # the state the simulation confirmed
        self.cutting_error = ""
        self.finished = False
        self.wait_for_sim_s = float(g("wait_for_sim_s"))
        self._created = time.monotonic()
        self.timer = self.create_timer(1.0 / float(g("rate_hz")), self._on_timer)

    def sim_ready(self) -> bool:
        """The simulation node is there: it subscribes to the pose and (unless it has taken too
        long, or the blade is not used) offers set_cutting."""
        if self.pose_pub.get_subscription_count() == 0:
            self.get_logger().info("waiting for the simulation node to subscribe to the pose",
                                   throttle_duration_sec=5.0)
            return False
        return (not self.use_cutting or self.cutting_client.service_is_ready()
                or time.monotonic() - self._created > self.wait_for_sim_s)

    def elapsed(self) -> float | None:
        now = self.get_clock().now().nanoseconds
        if now == 0:  # a simulated clock that has not started yet
            return None
        if self.t0_ns is None and not self.sim_ready():
            return None
        if self.t0_ns is None or now < self.t0_ns:  # first tick, or the clock jumped back (a reset)
            self.t0_ns, self.blade_requested, self.finished = now, None, False
        return (now - self.t0_ns) * 1e-9

    def _on_timer(self):
        t = self.elapsed()
        if t is None:
            return
        if self.loop and t >= self.script.total_s:
            self.t0_ns += int(self.script.total_s * 1e9)
            t -= self.script.total_s
        s = sample(self.script, t)
        self.phase = s.phase
        self.finished = s.phase == "done"
        stamp = self.get_clock().now().to_msg()
        pose = PoseStamped()
        pose.header.frame_id, pose.header.stamp = self.frame_id, stamp
        pose.pose.position.x, pose.pose.position.y, pose.pose.position.z = map(float, s.position)
        o = pose.pose.orientation
        o.x, o.y, o.z, o.w = map(float, self.orientation)
        twist = TwistStamped()
        twist.header.frame_id, twist.header.stamp = self.frame_id, stamp
        twist.twist.linear.x, twist.twist.linear.y, twist.twist.linear.z = map(float, s.velocity)
        self.twist_pub.publish(twist)  # first: the pose then goes in with this velocity
        self.pose_pub.publish(pose)
        self.published += 1
        if self.use_cutting:
            self._blade(s.blade)

    def _blade(self, on: bool):
        if on == self.blade_requested:
            return
        if not self.cutting_client.service_is_ready():
            self.get_logger().warning("set_cutting service not available yet", throttle_duration_sec=2.0)
            return
        self.blade_requested = on
        self.cutting_client.call_async(SetBool.Request(data=on)).add_done_callback(
            lambda fut, on=on: self._blade_done(on, fut))

    def _blade_done(self, on, fut):
        try:
            resp = fut.result()
        except Exception as exc:  # noqa: BLE001
            resp = SetBool.Response(success=False, message=str(exc))
        if resp.success:
            self.blade_state = on
            self.get_logger().info(f"blade {'on' if on else 'off'}")
        elif not self.cutting_error:
            self.cutting_error = resp.message
            self.get_logger().warning(f"set_cutting({on}) refused: {resp.message}; the script goes on")


def main(args=None):
    rclpy.init(args=args)
    node = ScriptedInstrument()
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        node.destroy_node()
        if rclpy.ok():
            rclpy.shutdown()


if __name__ == "__main__":
    main()
