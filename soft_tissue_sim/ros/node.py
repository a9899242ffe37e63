"""The rclpy node ``soft_tissue_sim``: a thin adapter over :class:`soft_tissue_sim.Simulation`.

Threads and callback groups: the physics steps on its own thread (:mod:`.physics_loop`) at
``rate_hz`` (``realtime``) or back to back, and is the only thread that touches the
simulation: requests (services, a snapshot for display) run on it between two steps. Every
step uses the newest accepted pose (and twist) of each instrument, kept per instrument
(keep-last 1: a newer pose replaces one no step has used yet, counted as superseded), and
publishes every instrument's wrench (pre-serialized, :mod:`.wrench_message`). Instrument input
is taken by a thread of its own (:mod:`.input_thread`) as serialized bytes
(:func:`read_stamped`); services, display and diagnostics are executor callbacks in their own
callback groups (``main`` spins a MultiThreadedExecutor); the
display asks the physics thread for a snapshot (positions, mesh, instrument geometry) at
``display_rate_hz`` and builds and publishes from it, so it never holds up a step. The
surface goes out pre-serialized (:mod:`.surface_marker`).

Topics (all relative names, remappable):
  ~/surface                          visualization_msgs/Marker (TRIANGLE_LIST) at display_rate_hz,
                                     and after every reset and cut
  ~/markers                          visualization_msgs/MarkerArray at display_rate_hz: per instrument a
                                     CYLINDER (shaft), a SPHERE_LIST (its two end caps: a capsule) and a
                                     LINE_LIST (its blade); contact points as one SPHERE_LIST (ns "contacts")
  ~/instruments/<name>/pose   (sub)  geometry_msgs/PoseStamped, best effort, keep-last 1
  ~/instruments/<name>/twist  (sub)  geometry_msgs/TwistStamped, best effort, keep-last 1 (optional):
                                     the velocity handed to the simulation with the pose
  ~/instruments/<name>/wrench        geometry_msgs/WrenchStamped, every step (force ON the tool, world
                                     frame). Its stamp is the stamp of the pose the step used (so a
                                     controller can match a wrench to its command); before any stamped
                                     pose, the time of the step
  /diagnostics                       diagnostic_msgs/DiagnosticArray at diagnostics_rate_hz:
                                     "<node>: rate" (achieved step rate, real-time factor, step time;
                                     WARN when realtime and the rate is under rate_hz), "<node>: solver"
                                     (step statistics), "<node>: instrument input" (accepted, rejected per
                                     reason, superseded poses, pose-to-step age)
  /clock                             rosgraph_msgs/Clock, the simulation time, every step, only with
                                     publish_clock
Services (std_srvs; own callback group, request queues of SERVICE_QUEUE_DEPTH; each is served
between two steps and answered after it took effect; one that cannot be served is answered
success false with the reason): ~/reset (Trigger), ~/cut (Trigger: one cut where the blade is
now, :meth:`soft_tissue_sim.scene.Simulation.cut_at_blade`), ~/set_cutting (SetBool: the pedal),
~/pause (SetBool).

Parameters: :mod:`.parameters` (ranges in the descriptors; rate_hz, realtime, display_rate_hz,
diagnostics_rate_hz, the input limits and service_timeout_s apply at run time; scene, device,
frame_id and publish_clock are read-only).

Input hardening: a pose or twist is rejected, with a throttled warning and a count per reason
in the diagnostics, when it holds NaN/inf ("non_finite"), when its quaternion is ~0 or further
than quaternion_tolerance from unit length ("bad_quaternion"; a near-unit one is normalised),
when its frame_id is neither empty nor the node's frame_id ("unknown_frame"), when its stamp is
more than pose_timeout_s away from the node clock ("stale"; a zero stamp means "now"; 0 turns
the check off), when its position is further than workspace_radius from workspace_center
("outside_workspace"), when a twist is faster than max_speed / max_angular_speed
("too_fast"), when the simulation refuses it ("invalid") or fails on it ("error").
No callback or service lets an exception out: the node never dies of a message or a request.

Instrument markers: the capsule's axis segment comes from the contact component
(``instruments[...].segment_world()``, world points, tip first); without one, from the last
applied pose with the convention of :mod:`soft_tissue_sim.instrument`: the tip at the tool
frame's origin and the shaft ``length`` along the tool's +z axis. A blade
(``blade_world()``) is drawn as a line, red while cutting is active.

Bad configuration (a scene that does not load, a parameter out of range) ends ``main`` with
one FATAL log line naming the problem and exit code 1. The node does not touch
ROS_AUTOMATIC_DISCOVERY_RANGE: real users discover across machines.
"""

from __future__ import annotations

import gc
import math
import struct
import sys
import threading
import time
from collections import Counter, deque
from dataclasses import dataclass

import numpy as np
import rclpy
from builtin_interfaces.msg import Time as TimeMsg
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import Point, PoseStamped, TwistStamped, WrenchStamped
from rcl_interfaces.msg import SetParametersResult
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup, ReentrantCallbackGroup
from rclpy.clock import Clock, ClockType
from rclpy.executors import ExternalShutdownException, MultiThreadedExecutor
from rclpy.logging import get_logger
from rclpy.node import Node
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.serialization import deserialize_message
from rosgraph_msgs.msg import Clock as ClockMsg
from std_srvs.srv import SetBool, Trigger
from visualization_msgs.msg import Marker, MarkerArray

from ..realtime import freeze_long_lived
from ..scene import load_scene
from ..warp_modules import build_all
from . import parameters
from .input_thread import InputThread, ThreadServedGroup
from .physics_loop import PhysicsLoop
from .surface_marker import CDR_LE, SurfaceMarkerEncoder, surface_template
from .wrench_message import WrenchEncoder

REJECT_REASONS = ("non_finite", "bad_quaternion", "unknown_frame", "stale", "outside_workspace", "too_fast",
                  "invalid", "error")
SERVICE_QUEUE_DEPTH = 1000  # requests (and, for our clients, responses) a burst may queue
EXECUTOR_THREADS = 8  # main(): services wait for a step boundary in their thread
RATE_WARN_FRACTION = 0.95  # diagnostics WARN under this fraction of rate_hz (realtime)
INPUT_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1, reliability=ReliabilityPolicy.BEST_EFFORT)
SERVICE_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=SERVICE_QUEUE_DEPTH,
                         reliability=ReliabilityPolicy.RELIABLE)


class InputRejected(ValueError):
    """An instrument message the node will not pass on; ``reason`` is one of REJECT_REASONS."""

    def __init__(self, reason: str, text: str):
        super().__init__(text)
        self.reason = reason


_HEAD = struct.Struct("<iII")  # header.stamp.sec, .nanosec, the frame id's length (with its NUL)
_DOUBLES = {6: struct.Struct("<6d"), 7: struct.Struct("<7d")}


def read_stamped(raw: bytes, msg_type) -> tuple[str, int, tuple]:
    """(frame id, stamp [ns], the float64 fields) of a serialized PoseStamped (7: position,
    orientation xyzw) or TwistStamped (6: linear, angular): a std_msgs/Header and then only
    float64. Read from the CDR bytes as they came (little endian; other encodings through
    ``deserialize_message``): taking a message as a Python object costs tens of microseconds,
    at kHz rates on the thread the physics needs. InputRejected ("error") for bytes that are
    not such a message."""
    n = 7 if msg_type is PoseStamped else 6
    try:
        if raw[:2] != CDR_LE:
            m = deserialize_message(raw, msg_type)
            v = ((m.pose.position.x, m.pose.position.y, m.pose.position.z, m.pose.orientation.x,
                  m.pose.orientation.y, m.pose.orientation.z, m.pose.orientation.w) if n == 7 else
                 (m.twist.linear.x, m.twist.linear.y, m.twist.linear.z, m.twist.angular.x, m.twist.angular.y,
                  m.twist.angular.z))
            return m.header.frame_id, _stamp_ns(m.header), v
        sec, nsec, length = _HEAD.unpack_from(raw, 4)
        end = 16 + length
        if length < 1 or raw[end - 1] != 0:
            raise ValueError("frame id not terminated")
        frame = raw[16:end - 1].decode()
        at = end + (-(end - 4)) % 8  # float64 aligned to 8 from the encapsulation's end
        return frame, sec * 1_000_000_000 + nsec, _DOUBLES[n].unpack_from(raw, at)
    except Exception as exc:  # noqa: BLE001 - too short, bad string...: not this message type
        raise InputRejected("error", f"unreadable {msg_type.__name__}: {type(exc).__name__}: {exc}") from None


def check_header(frame: str, stamp_ns: int, frame_id: str, now_ns: int, timeout_s: float) -> None:
    """Raise InputRejected when a header's frame is foreign or its stamp too far from ``now_ns``.

    An empty frame_id means the node's frame. A zero stamp means "now". ``now_ns == 0`` (a
    simulated clock that has not started) or ``timeout_s <= 0`` turns the age check off.
    """
    if frame not in ("", frame_id):
        raise InputRejected("unknown_frame", f"frame '{frame}' is not '{frame_id}'")
    if stamp_ns == 0 or now_ns == 0 or not timeout_s > 0:
        return
    age = (now_ns - stamp_ns) * 1e-9
    if age > timeout_s:
        raise InputRejected("stale", f"stamp is {age:.3f} s old (pose_timeout_s {timeout_s:g})")
    if -age > timeout_s:
        raise InputRejected("stale", f"stamp is {-age:.3f} s in the future (pose_timeout_s {timeout_s:g})")


def check_pose(raw: bytes, frame_id: str, now_ns: int, timeout_s: float, quaternion_tolerance: float = 0.1,
               workspace=None):
    """(position, unit quaternion xyzw, stamp [ns]) of a serialized PoseStamped, or InputRejected
    naming what is wrong. ``workspace``: (centre, radius) of the sphere the position must lie
    in, or None. Plain floats until the end: this runs for every message, up to kHz rates."""
    frame, stamp_ns, v = read_stamped(raw, PoseStamped)
    pos, quat = v[:3], v[3:]
    if not all(map(math.isfinite, v)):
        raise InputRejected("non_finite", f"NaN or inf in pose: position {list(pos)}, orientation {list(quat)}")
    check_header(frame, stamp_ns, frame_id, now_ns, timeout_s)
    if workspace is not None:
        dist = math.dist(pos, workspace[0])
        if not dist <= workspace[1]:
            raise InputRejected("outside_workspace", f"position {list(pos)} is {dist:.4g} m from the workspace "
                                                     f"centre (workspace_radius {workspace[1]:g} m)")
    norm = math.hypot(*quat)
    if norm < 1e-6:
        raise InputRejected("bad_quaternion", f"orientation quaternion is ~0 (norm {norm:.3g})")
    if abs(norm - 1.0) > quaternion_tolerance:
        raise InputRejected("bad_quaternion", f"orientation quaternion norm {norm:.4g} is not ~1 "
                                              f"(tolerance {quaternion_tolerance:g})")
    return np.array(pos), np.array(quat) / norm, stamp_ns


def check_twist(raw: bytes, frame_id: str, now_ns: int, timeout_s: float,
                max_speed: float = math.inf, max_angular_speed: float = math.inf):
    """(linear, angular) velocity of a serialized TwistStamped (world frame), or InputRejected."""
    frame, stamp_ns, v = read_stamped(raw, TwistStamped)
    lin, ang = v[:3], v[3:]
    if not all(map(math.isfinite, v)):
        raise InputRejected("non_finite", f"NaN or inf in twist: linear {list(lin)}, angular {list(ang)}")
    check_header(frame, stamp_ns, frame_id, now_ns, timeout_s)
    v, w = math.hypot(*lin), math.hypot(*ang)
    if v > max_speed:
        raise InputRejected("too_fast", f"linear speed {v:.4g} m/s is over max_speed {max_speed:g} m/s")
    if w > max_angular_speed:
        raise InputRejected("too_fast", f"angular speed {w:.4g} rad/s is over max_angular_speed "
                                        f"{max_angular_speed:g} rad/s")
    return np.array(lin), np.array(ang)


def quat_rotate(q_xyzw, v) -> np.ndarray:
    """Rotate vector v by the unit quaternion q (x, y, z, w)."""
    x, y, z, w = (float(c) for c in q_xyzw)
    u = np.array([x, y, z])
    v = np.asarray(v, dtype=np.float64)
    return v + 2.0 * np.cross(u, np.cross(u, v) + w * v)


def quat_z_to(direction) -> tuple[float, float, float, float]:
    """A unit quaternion (x, y, z, w) turning +z onto ``direction``."""
    d = np.asarray(direction, dtype=np.float64)
    d = d / np.linalg.norm(d)
    c = float(d[2])
    if c < -1.0 + 1e-12:
        return 1.0, 0.0, 0.0, 0.0  # half a turn about x
    axis = np.cross([0.0, 0.0, 1.0], d)
    w = 1.0 + c
    n = math.sqrt(w * w + float(axis @ axis))
    return float(axis[0] / n), float(axis[1] / n), float(axis[2] / n), float(w / n)


def _field(obj, key, default=None):
    if isinstance(obj, dict):
        return obj.get(key, default)
    return getattr(obj, key, default)


def _stamp_ns(header) -> int:
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


def _time_msg(ns: int) -> TimeMsg:
    return TimeMsg(sec=int(ns // 1_000_000_000), nanosec=int(ns % 1_000_000_000))


class _Input:
    """The newest accepted pose and twist of one instrument (keep-last 1) and what a step used."""

    __slots__ = ("pose", "pose_seq", "twist", "twist_seq", "used_pose_seq", "used_twist_seq")

    def __init__(self):
        self.pose = None  # (position, quaternion, stamp ns, monotonic time received)
        self.twist = None  # (linear, angular, monotonic time received)
        self.pose_seq = self.twist_seq = self.used_pose_seq = self.used_twist_seq = 0


@dataclass
class Snapshot:
    """What the display needs, taken between two steps."""

    stamp_ns: int
    positions: np.ndarray
    mesh: object
    mesh_version: int
    instruments: list  # (name, (tip, end, radius, shape) or None, blade (p0, p1) or None)
    contact_points: np.ndarray
    cutting_on: bool


class SimNode(Node):
    def __init__(self, node_name="soft_tissue_sim", sim=None, start=True, **kwargs):
        """``sim``: an already built Simulation (in-process use); it is then not closed with the node.
        ``start``: start the physics thread now (else call :meth:`start`)."""
        super().__init__(node_name, **kwargs)
        parameters.declare(self)
        gp = lambda name: self.get_parameter(name).value  # noqa: E731
        self.frame_id = gp("frame_id")
        self._settings = {s.name: gp(s.name) for s in parameters.SPECS}
        self._owns_sim = sim is None
        if sim is None:
            dev = gp("device")
            sim = load_scene(gp("scene"), device=None if dev == "auto" else dev)
        self.sim = sim
        # every kernel built now, not at its first launch: on a machine without the kernel cache
        # a GPU's contact modules compile for tens of seconds, which would stall the first steps
        self.kernels_s = build_all(sim.device)
        self.get_logger().info(f"kernels ready on {sim.device} in {self.kernels_s:.1f} s")
        self.names = list(sim.instrument_names())
        self.on_step = None  # optional callable(StepStats), called on the physics thread after each step
        self._closing = False
        self.last_stats = None
        # instrument input (executor threads) -> the physics thread
        self._in_lock = threading.Lock()
        self._inputs = {name: _Input() for name in self.names}
        self.rejected = {"pose": Counter(), "twist": Counter()}
        self.accepted = {"pose": 0, "twist": 0}
        self.superseded = 0
        self.last_rejection = ""
        self._last_rejection_t = -math.inf
        self._pose_ages = deque(maxlen=2000)  # ms from a pose's receipt to the step that used it
        self._stamp_ages = deque(maxlen=2000)  # ms from a pose's stamp to the step that used it
        # outputs of the physics thread
        self.last_wrench = {}  # name -> (force, torque)
        self.wrenches_published = 0
        self._applied = {}  # name -> (position, quaternion) last applied
        self._used_stamp = {name: 0 for name in self.names}
        self._wrench_encoder = WrenchEncoder(self.frame_id)
        # display
        self._snapshot_wanted = False
        self._snapshot = None
        self._tri_key = None
        self._tris = None
        self._tri_count = -1
        self.surface_encoder = SurfaceMarkerEncoder(surface_template(self.frame_id))

        steady = Clock(clock_type=ClockType.STEADY_TIME)  # with use_sim_time the node clock follows /clock
        self._input_group = ThreadServedGroup()  # taken by self.input_thread, not by an executor
        self._service_group = ReentrantCallbackGroup()
        self._display_group = MutuallyExclusiveCallbackGroup()
        self.surface_pub = self.create_publisher(Marker, "~/surface", 1)
        self.markers_pub = self.create_publisher(MarkerArray, "~/markers", 1)
        self.diag_pub = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self.clock_pub = self.create_publisher(ClockMsg, "/clock", 10) if gp("publish_clock") else None
        self.wrench_pubs = {}
        inputs = []
        for name in self.names:
            # the twist first: when both wait, the input thread takes them in this order
            # taken as serialized bytes (read_stamped)
            inputs.append(self.create_subscription(TwistStamped, f"~/instruments/{name}/twist",
                                                   lambda msg, n=name: self._on_twist(n, msg), INPUT_QOS,
                                                   callback_group=self._input_group, raw=True))
            inputs.append(self.create_subscription(PoseStamped, f"~/instruments/{name}/pose",
                                                   lambda msg, n=name: self._on_pose(n, msg), INPUT_QOS,
                                                   callback_group=self._input_group, raw=True))
            self.wrench_pubs[name] = self.create_publisher(WrenchStamped, f"~/instruments/{name}/wrench", 100)
        self.input_thread = InputThread(self.context, inputs, name=f"{node_name} input",
                                        on_error=lambda t: self.get_logger().error(t, throttle_duration_sec=1.0))
        for srv_type, name, cb in ((Trigger, "~/reset", self._on_reset), (Trigger, "~/cut", self._on_cut),
                                   (SetBool, "~/set_cutting", self._on_set_cutting),
                                   (SetBool, "~/pause", self._on_pause)):
            self.create_service(srv_type, name, cb, qos_profile=SERVICE_QOS, callback_group=self._service_group)
        self._display_guard = self.create_guard_condition(self._on_snapshot, callback_group=self._display_group)
        self.display_timer = None
        self._set_display_rate(self._settings["display_rate_hz"], steady)
        self.diag_timer = self.create_timer(1.0 / self._settings["diagnostics_rate_hz"], self.publish_diagnostics,
                                            callback_group=self._display_group, clock=steady)
        self._steady = steady
        self.add_on_set_parameters_callback(self._check_parameters)
        self.add_post_set_parameters_callback(self._apply_parameters)

        self.loop = PhysicsLoop(self._step_once, self._settings["rate_hz"], self._settings["realtime"],
                                between=self._between_steps, on_error=self._step_failed,
                                name=f"{node_name} physics")
        self._snapshot_wanted = True  # the surface once at start-up
        self._between_steps()
        self._on_snapshot()
        if start:
            self.start()

    def start(self) -> None:
        """Start the input and physics threads."""
        self.input_thread.start()
        self.loop.start()

    # -------------------------------------------------------------- parameters
    def _check_parameters(self, params):
        reason = parameters.check({p.name: p.value for p in params})
        return SetParametersResult(successful=reason is None, reason=reason or "")

    def _apply_parameters(self, params):
        for p in params:
            if p.name in self._settings:
                self._settings[p.name] = p.value
        names = {p.name for p in params}
        if names & {"rate_hz", "realtime"}:
            self.loop.set_rate(self._settings["rate_hz"], self._settings["realtime"])
        if "display_rate_hz" in names:
            self._set_display_rate(self._settings["display_rate_hz"], self._steady)
        if "diagnostics_rate_hz" in names:
            self.diag_timer.timer_period_ns = int(1e9 / self._settings["diagnostics_rate_hz"])

    def _set_display_rate(self, rate_hz: float, clock) -> None:
        if rate_hz > 0 and self.display_timer is not None:
            self.display_timer.timer_period_ns = int(1e9 / rate_hz)
            self.display_timer.reset()
        elif rate_hz > 0:
            self.display_timer = self.create_timer(1.0 / rate_hz, self._on_display_tick,
                                                   callback_group=self._display_group, clock=clock)
        elif self.display_timer is not None:
            self.destroy_timer(self.display_timer)
            self.display_timer = None

    # ------------------------------------------------------------------ inputs
    @property
    def rejected_poses(self) -> int:
        return sum(self.rejected["pose"].values())

    def _now_ns(self) -> int:
        return self.get_clock().now().nanoseconds

    def _reject(self, kind, name, reason, text):
        with self._in_lock:
            self.rejected[kind][reason] += 1
            self.last_rejection = f"{kind} of '{name}' ({reason}): {text}"
            self._last_rejection_t = time.monotonic()
        self.get_logger().warning(f"instrument {kind} of '{name}' ({reason}): {text}", throttle_duration_sec=1.0)

    def _workspace(self):
        s = self._settings
        return tuple(float(c) for c in s["workspace_center"]), float(s["workspace_radius"])

    def _on_pose(self, name, msg: bytes):
        s = self._settings
        try:
            pos, quat, stamp_ns = check_pose(msg, self.frame_id, self._now_ns(), s["pose_timeout_s"],
                                             s["quaternion_tolerance"], self._workspace())
        except InputRejected as exc:
            return self._reject("pose", name, exc.reason, str(exc))
        except Exception as exc:  # noqa: BLE001
            return self._reject("pose", name, "error", f"{type(exc).__name__}: {exc}")
        entry = (pos, quat, stamp_ns, time.monotonic())
        with self._in_lock:
            slot = self._inputs[name]
            if slot.pose is not None and slot.pose_seq != slot.used_pose_seq:
                self.superseded += 1
            slot.pose = entry
            slot.pose_seq += 1
            self.accepted["pose"] += 1

    def _on_twist(self, name, msg: bytes):
        s = self._settings
        try:
            lin, ang = check_twist(msg, self.frame_id, self._now_ns(), s["pose_timeout_s"], s["max_speed"],
                                   s["max_angular_speed"])
        except InputRejected as exc:
            return self._reject("twist", name, exc.reason, str(exc))
        except Exception as exc:  # noqa: BLE001
            return self._reject("twist", name, "error", f"{type(exc).__name__}: {exc}")
        with self._in_lock:
            slot = self._inputs[name]
            slot.twist = (lin, ang, time.monotonic())
            slot.twist_seq += 1
            self.accepted["twist"] += 1

    def _take_inputs(self, now_mono: float) -> list:
        """(name, pose entry, (linear, angular) or None, new pose?) per instrument with a pose or
        twist no step has used yet. A twist older than pose_timeout_s is not used."""
        timeout = self._settings["pose_timeout_s"]
        out = []
        with self._in_lock:
            for name, slot in self._inputs.items():
                if slot.pose is None or (slot.pose_seq == slot.used_pose_seq and slot.twist_seq == slot.used_twist_seq):
                    continue
                tw = slot.twist
                if tw is not None and timeout > 0 and now_mono - tw[2] > timeout:
                    tw = None
                out.append((name, slot.pose, None if tw is None else tw[:2], slot.pose_seq != slot.used_pose_seq))
                slot.used_pose_seq, slot.used_twist_seq = slot.pose_seq, slot.twist_seq
        return out

    # ---------------------------------------------------------- physics thread
    def _step_once(self) -> float:
        """One step (on the physics thread): the newest inputs, the step, the wrenches. Returns
        the simulated time it advanced."""
        sim = self.sim
        self._apply_inputs()
        t_before = sim.time
        stats = sim.step()
        self.last_stats = stats
        self._publish_wrenches()
        self.publish_clock()
        if self.on_step is not None:
            self.on_step(stats)
        return max(0.0, sim.time - t_before)

    def _apply_inputs(self) -> None:
        """Hand the simulation the newest pose (and twist) of every instrument no step has used."""
        sim = self.sim
        mono, now_ns = time.monotonic(), self._now_ns()
        for name, (pos, quat, stamp_ns, t_rx), vel, new_pose in self._take_inputs(mono):
            lin, ang = vel if vel is not None else (None, None)
            try:
                sim.set_instrument_pose(name, pos, quat, linear_velocity=lin, angular_velocity=ang)
            except ValueError as exc:
                self._reject("pose", name, "invalid", str(exc))
                continue
            except Exception as exc:  # noqa: BLE001 - counted and logged, never fatal
                self._reject("pose", name, "error", f"{type(exc).__name__}: {exc}")
                continue
            self._applied[name] = (pos, quat)
            if new_pose:
                self._used_stamp[name] = stamp_ns
                with self._in_lock:
                    self._pose_ages.append(1000.0 * (mono - t_rx))
                    if stamp_ns and now_ns:
                        self._stamp_ages.append(1e-6 * (now_ns - stamp_ns))

    def _publish_wrenches(self):
        now = None
        for name, pub in self.wrench_pubs.items():
            try:
                f, t = self.sim.instrument_wrench(name)
                f, t = np.asarray(f, dtype=float).reshape(3), np.asarray(t, dtype=float).reshape(3)
            except Exception as exc:  # noqa: BLE001
                self.get_logger().warning(f"no wrench for '{name}': {exc}", throttle_duration_sec=1.0)
                continue
            self.last_wrench[name] = (f, t)
            stamp = self._used_stamp[name]
            if not stamp:
                now = self._now_ns() if now is None else now
                stamp = now
            pub.publish(self._wrench_encoder.encode(f, t, stamp))
            self.wrenches_published += 1

    def publish_clock(self):
        if self.clock_pub is not None:
            self.clock_pub.publish(ClockMsg(clock=_time_msg(int(round(self.sim.time * 1e9)))))

    def _step_failed(self, text: str) -> None:
        if self.context.ok():  # else: shutting down, nothing to say
            self.get_logger().error(f"step failed: {text}", throttle_duration_sec=1.0)

    def _between_steps(self) -> None:
        """On the physics thread between two steps: the snapshot the display asked for."""
        if not self._snapshot_wanted:
            return
        self._snapshot_wanted = False
        sim = self.sim
        insts = []
        for name in self.names:
            try:
                insts.append((name, self.instrument_segment(name), self.instrument_blade(name)))
            except Exception as exc:  # noqa: BLE001
                self.get_logger().warning(f"instrument '{name}' geometry failed: {exc}", throttle_duration_sec=1.0)
                insts.append((name, None, None))
        try:
            contacts = np.asarray(sim.contact_points(), dtype=float).reshape(-1, 3)
        except Exception as exc:  # noqa: BLE001
            self.get_logger().warning(f"contact points failed: {exc}", throttle_duration_sec=1.0)
            contacts = np.zeros((0, 3))
        snap = Snapshot(self._now_ns(), sim.positions(), sim.mesh, getattr(sim, "mesh_version", 0), insts, contacts,
                        bool(getattr(getattr(sim, "cutting", None), "active", False)))
        with self._in_lock:
            self._snapshot = snap
        if self.loop.running:
            self._display_guard.trigger()

    # ---------------------------------------------------------------- services
    def _serve(self, fn, key=None):
        """(success, message) of ``fn`` run between two steps."""
        ok, result = self.loop.call(fn, self._settings["service_timeout_s"], key=key)
        return ok, result

    def _redisplay(self):
        self._snapshot_wanted = True

    def _do_reset(self):
        self.sim.reset()
        with self._in_lock:
            for slot in self._inputs.values():
                slot.pose = slot.twist = None
                slot.used_pose_seq, slot.used_twist_seq = slot.pose_seq, slot.twist_seq
        self._applied.clear()
        self.last_wrench.clear()
        self._used_stamp = {name: 0 for name in self.names}
        self.last_stats = None
        self._redisplay()
        self.publish_clock()
        return "simulation reset to its initial state"

    def _do_cut(self):
        cutter = getattr(self.sim, "cutting", None)
        if cutter is None:
            raise ValueError("this scene has no cutting")
        self.input_thread.drain()  # where the blade is now: the newest pose received
        self._apply_inputs()
        res = self.sim.cut_at_blade()
        self._redisplay()
        if not res.changed:
            raise ValueError(f"nothing cut: {res.message}")
        return f"{res.tets_changed} tets changed: {res.message}"

    def _do_set_cutting(self, on: bool):
        self.input_thread.drain()  # the pedal acts at the newest pose received
        self._apply_inputs()
        self.sim.set_cutting(on)
        return f"cutting {'on' if on else 'off'}"

    def _do_pause(self, paused: bool):
        self.loop.set_paused(paused)
        return "paused" if paused else "running"

    def _answer(self, resp, fn, what, key=None):
        try:
            ok, result = self._serve(fn, key)
            resp.success, resp.message = bool(ok), str(result) if ok else f"{what} failed: {result}"
        except Exception as exc:  # noqa: BLE001 - answered, never fatal
            resp.success, resp.message = False, f"{what} failed: {type(exc).__name__}: {exc}"
        return resp

    def _on_reset(self, req, resp):
        return self._answer(resp, self._do_reset, "reset", key="reset")

    def _on_cut(self, req, resp):
        return self._answer(resp, self._do_cut, "cut")

    def _on_set_cutting(self, req, resp):
        on = bool(req.data)
        return self._answer(resp, lambda: self._do_set_cutting(on), "set_cutting", key=("set_cutting", on))

    def _on_pause(self, req, resp):
        paused = bool(req.data)
        return self._answer(resp, lambda: self._do_pause(paused), "pause", key=("pause", paused))

    # ----------------------------------------------------------------- display
    def _on_display_tick(self):
        self._snapshot_wanted = True
        self.loop.wake()

    def _on_snapshot(self):
        if self._closing:
            return
        with self._in_lock:
            snap, self._snapshot = self._snapshot, None
        if snap is None:
            return
        try:
            self.publish_surface(snap)
            self.publish_markers(snap)
        except Exception as exc:  # noqa: BLE001
            if self.context.ok():
                self.get_logger().error(f"publishing the display failed: {type(exc).__name__}: {exc}",
                                        throttle_duration_sec=1.0)

    def surface_triangles(self, snap: Snapshot) -> np.ndarray:
        """The surface triangles of the snapshot's mesh, recomputed only when the topology changed."""
        mesh = snap.mesh  # a cut replaces the mesh object and bumps mesh_version
        key = (id(mesh), snap.mesh_version, mesh.n_tets, mesh.n_nodes)
        if key != self._tri_key or self._tris is None:
            self._tri_key, self._tris = key, mesh.boundary_faces()
            self._tri_count = len(self._tris)
        return self._tris

    def surface_bytes(self, snap: Snapshot) -> bytes:
        """The serialized surface Marker of a snapshot."""
        tris = self.surface_triangles(snap)
        return self.surface_encoder.encode(snap.positions[tris.reshape(-1)], snap.stamp_ns)

    def publish_surface(self, snap: Snapshot):
        if self.surface_pub.get_subscription_count() > 0:
            self.surface_pub.publish(self.surface_bytes(snap))
        else:
            self.surface_triangles(snap)  # keep the count in the diagnostics current

    def _instrument_info(self, name):
        """The contact component's record of an instrument, else the scene's entry, else None."""
        insts = getattr(getattr(self.sim, "contact", None), "instruments", None)
        if isinstance(insts, dict):
            if name in insts:
                return insts[name]
        elif insts is not None:
            try:
                for it in insts:
                    if _field(it, "name") == name:
                        return it
            except TypeError:
                pass
        for it in (getattr(self.sim, "config", None) or {}).get("instruments") or []:
            if _field(it, "name") == name:
                return it
        return None

    def instrument_segment(self, name):
        """(tip, end, radius, shape) of an instrument in world coordinates, or None if unknown yet."""
        info = self._instrument_info(name)
        radius = float(_field(info, "radius", 0.002) or 0.002)
        length = float(_field(info, "length", 0.0) or 0.0)
        shape = str(_field(info, "shape", "capsule"))
        seg = None
        for key in ("segment_world", "segment", "endpoints"):  # the contact component's own geometry
            seg = _field(info, key)
            seg = seg() if callable(seg) else seg
            if seg is not None:
                break
        if seg is not None:
            a, b = (np.asarray(v, dtype=float).reshape(3) for v in seg)
            return a, b, radius, shape
        if name not in self._applied:
            return None
        pos, quat = self._applied[name]
        return pos, pos + quat_rotate(quat, [0.0, 0.0, length]), radius, shape

    def instrument_blade(self, name):
        """(p0, p1) world end points of an instrument's blade, or None."""
        blade = _field(self._instrument_info(name), "blade_world")
        blade = blade() if callable(blade) else None
        return None if blade is None else tuple(np.asarray(p, dtype=float).reshape(3) for p in blade)

    def instrument_markers(self, snap: Snapshot) -> list[Marker]:
        """Per instrument (ns "instrument/<name>", ids 3i..3i+2): the shaft (CYLINDER), the two end
        caps (SPHERE_LIST) and, with a blade, the blade (LINE_LIST, red while cutting is active)."""
        out = []
        stamp = _time_msg(snap.stamp_ns)
        pt = lambda v: Point(x=float(v[0]), y=float(v[1]), z=float(v[2]))  # noqa: E731
        for i, (name, seg, blade) in enumerate(snap.instruments):
            shaft, caps, line = Marker(), Marker(), Marker()
            for k, (m, kind) in enumerate(((shaft, Marker.CYLINDER), (caps, Marker.SPHERE_LIST),
                                           (line, Marker.LINE_LIST))):
                m.header.frame_id = self.frame_id
                m.header.stamp = stamp
                m.ns, m.id, m.type = f"instrument/{name}", 3 * i + k, kind
                m.pose.orientation.w = 1.0
                m.color.r, m.color.g, m.color.b, m.color.a = 0.7, 0.75, 0.85, 1.0
            if seg is None or not all(np.all(np.isfinite(v)) for v in seg[:2]):
                shaft.action = caps.action = line.action = Marker.DELETE
                out += [shaft, caps, line]
                continue
            a, b, r, _shape = seg
            d = b - a
            length = float(np.linalg.norm(d))
            caps.scale.x = caps.scale.y = caps.scale.z = 2.0 * r
            caps.points = [pt(a), pt(b)] if length > 0 else [pt(a)]
            if length > 0:
                shaft.pose.position = pt(0.5 * (a + b))
                o = shaft.pose.orientation
                o.x, o.y, o.z, o.w = quat_z_to(d)
                shaft.scale.x = shaft.scale.y = 2.0 * r
                shaft.scale.z = length
            else:  # a sphere: the cap is all there is
                shaft.action = Marker.DELETE
            if blade is not None:
                line.scale.x = 0.5 * r
                line.color.r, line.color.g, line.color.b = (1.0, 0.1, 0.1) if snap.cutting_on else (0.3, 0.3, 0.3)
                line.points = [pt(v) for v in blade]
            else:
                line.action = Marker.DELETE
            out += [shaft, caps, line]
        return out

    def contact_marker(self, snap: Snapshot) -> Marker:
        m = Marker()
        m.header.frame_id = self.frame_id
        m.header.stamp = _time_msg(snap.stamp_ns)
        m.ns, m.id, m.type = "contacts", 0, Marker.SPHERE_LIST
        m.pose.orientation.w = 1.0
        m.scale.x = m.scale.y = m.scale.z = 0.002
        m.color.g, m.color.a = 1.0, 1.0
        pts = snap.contact_points[np.all(np.isfinite(snap.contact_points), axis=1)]
        m.points = [Point(x=a, y=b, z=c) for a, b, c in pts.tolist()]
        return m

    def publish_markers(self, snap: Snapshot):
        if not (self.sim.has_contact or self.names) or self.markers_pub.get_subscription_count() == 0:
            return
        arr = MarkerArray()
        arr.markers = self.instrument_markers(snap) + [self.contact_marker(snap)]
        self.markers_pub.publish(arr)

    # ------------------------------------------------------------- diagnostics
    def rate_status(self) -> DiagnosticStatus:
        r = self.loop.rates()
        s = self._settings
        st = DiagnosticStatus(name=f"{self.get_name()}: rate", hardware_id=str(self.sim.device))
        target = float(s["rate_hz"])
        values = {"achieved_rate_hz": f"{r['rate_hz']:.2f}", "rate_hz": f"{target:g}",
                  "realtime": str(bool(s["realtime"])).lower(), "real_time_factor": f"{r['real_time_factor']:.3f}",
                  "step_ms_mean": f"{r['step_ms_mean']:.3f}", "step_ms_max": f"{r['step_ms_max']:.3f}",
                  "steps_total": str(self.loop.steps), "late_steps": str(self.loop.late_steps),
                  "wrenches_published": str(self.wrenches_published), "paused": str(self.loop.paused).lower(),
                  "display_rate_hz": f"{float(s['display_rate_hz']):g}", "dt": f"{self.sim.dt:g}",
                  "gc_frozen_objects": str(gc.get_freeze_count())}
        st.values = [KeyValue(key=k, value=v) for k, v in values.items()]
        if self.loop.paused:
            st.level, st.message = DiagnosticStatus.OK, "paused"
        elif s["realtime"] and r["rate_hz"] < RATE_WARN_FRACTION * target:
            st.level = DiagnosticStatus.WARN
            st.message = (f"achieved {r['rate_hz']:.1f} of {target:g} steps/s (real-time factor "
                          f"{r['real_time_factor']:.2f}, step {r['step_ms_mean']:.1f} ms)")
            self.get_logger().warning(st.message, throttle_duration_sec=10.0)
        else:
            st.level = DiagnosticStatus.OK
            st.message = (f"{r['rate_hz']:.1f} steps/s" + ("" if s["realtime"] else " (as fast as possible)")
                          + f", real-time factor {r['real_time_factor']:.2f}")
        return st

    def input_status(self) -> DiagnosticStatus:
        st = DiagnosticStatus(name=f"{self.get_name()}: instrument input", hardware_id=str(self.sim.device))
        values = [KeyValue(key="instruments", value=",".join(self.names))]
        with self._in_lock:
            rejected = {k: Counter(v) for k, v in self.rejected.items()}
            accepted = dict(self.accepted)
            superseded, last = self.superseded, self.last_rejection
            ages, stamp_ages = np.array(self._pose_ages), np.array(self._stamp_ages)
            recent = time.monotonic() - self._last_rejection_t < 1.0
        for kind in ("pose", "twist"):
            cnt = rejected[kind]
            values.append(KeyValue(key=f"accepted_{kind}s", value=str(accepted[kind])))
            values.append(KeyValue(key=f"rejected_{kind}s", value=str(sum(cnt.values()))))
            values += [KeyValue(key=f"rejected_{kind}s.{r}", value=str(cnt[r])) for r in REJECT_REASONS]
        values.append(KeyValue(key="superseded_poses", value=str(superseded)))
        for key, a in (("pose_to_step_ms", ages), ("pose_stamp_to_step_ms", stamp_ages)):
            if len(a):
                values.append(KeyValue(key=f"{key}.median", value=f"{float(np.median(a)):.3f}"))
                values.append(KeyValue(key=f"{key}.max", value=f"{float(a.max()):.3f}"))
        values.append(KeyValue(key="last_rejection", value=last))
        st.values = values
        st.level = DiagnosticStatus.WARN if recent else DiagnosticStatus.OK
        st.message = f"rejecting input: {last}" if recent else "ok"
        return st

    def solver_status(self) -> DiagnosticStatus:
        stats = self.last_stats
        s = stats.as_dict() if stats is not None else {}
        st = DiagnosticStatus(name=f"{self.get_name()}: solver", hardware_id=str(self.sim.device))
        bad = (not s.get("converged", True)) or any(
            isinstance(v, float) and not math.isfinite(v) for v in s.values())
        st.level = DiagnosticStatus.WARN if bad else DiagnosticStatus.OK
        st.message = "not converged" if bad else "ok"
        keys = ["step", "total_ms", "iterations", "residual", "factor_age", "preconditioner", "contacts", "cuts",
                "rollbacks"]
        st.values = [KeyValue(key=k, value=str(s[k])) for k in keys if k in s]
        st.values.append(KeyValue(key="rejected_poses", value=str(self.rejected_poses)))
        st.values.append(KeyValue(key="surface_triangles", value=str(self._tri_count)))
        for name, (f, _t) in list(self.last_wrench.items()):
            st.values.append(KeyValue(key=f"force_N.{name}", value=f"{float(np.linalg.norm(f)):.6g}"))
        return st

    def publish_diagnostics(self):
        if self._closing:
            return
        try:
            msg = DiagnosticArray(status=[self.rate_status(), self.solver_status(), self.input_status()])
            msg.header.stamp = self.get_clock().now().to_msg()
            self.diag_pub.publish(msg)
        except Exception as exc:  # noqa: BLE001
            if self.context.ok():
                self.get_logger().error(f"diagnostics failed: {type(exc).__name__}: {exc}", throttle_duration_sec=1.0)

    def destroy_node(self):
        self._closing = True
        self.input_thread.stop()
        self.loop.stop()
        if self._owns_sim:
            self.sim.close()
        return super().destroy_node()


def main(args=None) -> int:
    """Run the node in a MultiThreadedExecutor until Ctrl-C. Exit code 1, after one FATAL log
    line naming the problem, when the configuration is bad (scene, parameters)."""
    logger = get_logger("soft_tissue_sim")
    try:
        rclpy.init(args=args)
    except Exception as exc:  # noqa: BLE001 - e.g. malformed --ros-args
        logger.fatal(f"cannot start: {type(exc).__name__}: {exc}")
        return 1
    node = ex = None
    try:
        try:
            node = SimNode()
        except (KeyboardInterrupt, ExternalShutdownException):
            return 0
        except Exception as exc:  # noqa: BLE001 - bad scene or parameters: one line, no traceback
            logger.fatal(f"cannot start the simulation node: {type(exc).__name__}: {exc}")
            return 1
        freeze_long_lived()
        ex = MultiThreadedExecutor(num_threads=EXECUTOR_THREADS)
        ex.add_node(node)
        try:
            ex.spin()
        except (KeyboardInterrupt, ExternalShutdownException):
            pass
        return 0
    finally:
        if node is not None:
            node.loop.stop()  # answers the requests still waiting
        if ex is not None:
            ex.shutdown(timeout_sec=5.0)
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()


if __name__ == "__main__":
    sys.exit(main())
