"""The rclpy node ``soft_tissue_sim``: a thin adapter over :class:`soft_tissue_sim.Simulation`.

Topics (all relative names, remappable):
  ~/surface                          visualization_msgs/Marker (TRIANGLE_LIST, rebuilt when cuts change it)
  ~/markers                          visualization_msgs/MarkerArray: per instrument a CYLINDER (shaft)
                                     and a SPHERE_LIST (its two end caps: a capsule); contact points
                                     as one SPHERE_LIST (ns "contacts")
  ~/instruments/<name>/pose   (sub)  geometry_msgs/PoseStamped, sensor-data QoS
  ~/instruments/<name>/twist  (sub)  geometry_msgs/TwistStamped, sensor-data QoS (optional): the
                                     velocity handed to the simulation with the pose
  ~/instruments/<name>/wrench        geometry_msgs/WrenchStamped (force ON the tool, world frame)
  /diagnostics                       diagnostic_msgs/DiagnosticArray: "<node>: solver" (step statistics)
                                     and "<node>: instrument input" (accepted/rejected inputs per reason)
  /clock                             rosgraph_msgs/Clock, the simulation time, only with publish_clock
Services (std_srvs): ~/reset (Trigger), ~/cut (Trigger), ~/set_cutting (SetBool), ~/pause (SetBool).

Input hardening: a pose or twist is rejected, with a throttled warning and a count per reason
in the diagnostics, when it holds NaN/inf ("non_finite"), when its quaternion is ~0 or further
than quaternion_tolerance from unit length ("bad_quaternion"; a near-unit one is normalised),
when its frame_id is neither empty nor the node's frame_id ("unknown_frame"), when its stamp is
more than pose_timeout_s away from the node clock ("stale"; a zero stamp means "now"; 0 turns
the check off), when the simulation refuses it ("invalid") or fails on it ("error").
No callback or service lets an exception out: the node never dies of a message or a request.

Instrument markers: the capsule's axis segment comes from the contact component
(``instruments[...].segment_world()``, world points, tip first); without one, from the last
accepted pose with the convention of :mod:`soft_tissue_sim.instrument`: the tip at the tool
frame's origin and the shaft ``length`` along the tool's +z axis. A blade
(``blade_world()``) is drawn as a line, red while cutting is active.

The node does not touch ROS_AUTOMATIC_DISCOVERY_RANGE: real users discover across machines.
"""

from __future__ import annotations

import math
import time
from collections import Counter

import numpy as np
import rclpy
from builtin_interfaces.msg import Time as TimeMsg
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import Point, PoseStamped, TwistStamped, WrenchStamped
from rcl_interfaces.msg import ParameterDescriptor
from rclpy.clock import Clock, ClockType
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.qos import qos_profile_sensor_data
from rosgraph_msgs.msg import Clock as ClockMsg
from std_srvs.srv import SetBool, Trigger
from visualization_msgs.msg import Marker, MarkerArray

from ..scene import load_scene

REJECT_REASONS = ("non_finite", "bad_quaternion", "unknown_frame", "stale", "invalid", "error")


class InputRejected(ValueError):
    """An instrument message the node will not pass on; ``reason`` is one of REJECT_REASONS."""

    def __init__(self, reason: str, text: str):
        super().__init__(text)
        self.reason = reason


def _desc(text):
    return ParameterDescriptor(description=text)


def check_header(header, frame_id: str, now_ns: int, timeout_s: float) -> None:
    """Raise InputRejected when a header's frame is foreign or its stamp too far from ``now_ns``.

    An empty frame_id means the node's frame. A zero stamp means "now". ``now_ns == 0`` (a
    simulated clock that has not started) or ``timeout_s <= 0`` turns the age check off.
    """
    if header.frame_id not in ("", frame_id):
        raise InputRejected("unknown_frame", f"frame '{header.frame_id}' is not '{frame_id}'")
    stamp_ns = int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)
    if stamp_ns == 0 or now_ns == 0 or not timeout_s > 0:
        return
    age = (now_ns - stamp_ns) * 1e-9
    if age > timeout_s:
        raise InputRejected("stale", f"stamp is {age:.3f} s old (pose_timeout_s {timeout_s:g})")
    if -age > timeout_s:
        raise InputRejected("stale", f"stamp is {-age:.3f} s in the future (pose_timeout_s {timeout_s:g})")


def check_pose(msg: PoseStamped, frame_id: str, now_ns: int, timeout_s: float, quaternion_tolerance: float = 0.1):
    """(position, unit quaternion xyzw) of a PoseStamped, or InputRejected naming what is wrong."""
    p, q = msg.pose.position, msg.pose.orientation
    pos = np.array([p.x, p.y, p.z], dtype=np.float64)
    quat = np.array([q.x, q.y, q.z, q.w], dtype=np.float64)
    if not (np.all(np.isfinite(pos)) and np.all(np.isfinite(quat))):
        raise InputRejected("non_finite", f"NaN or inf in pose: position {pos.tolist()}, orientation {quat.tolist()}")
    check_header(msg.header, frame_id, now_ns, timeout_s)
    norm = float(np.linalg.norm(quat))
    if norm < 1e-6:
        raise InputRejected("bad_quaternion", f"orientation quaternion is ~0 (norm {norm:.3g})")
    if abs(norm - 1.0) > quaternion_tolerance:
        raise InputRejected("bad_quaternion", f"orientation quaternion norm {norm:.4g} is not ~1 "
                                              f"(tolerance {quaternion_tolerance:g})")
    return pos, quat / norm


def check_twist(msg: TwistStamped, frame_id: str, now_ns: int, timeout_s: float):
    """(linear, angular) velocity of a TwistStamped (world frame), or InputRejected."""
    lin = np.array([msg.twist.linear.x, msg.twist.linear.y, msg.twist.linear.z], dtype=np.float64)
    ang = np.array([msg.twist.angular.x, msg.twist.angular.y, msg.twist.angular.z], dtype=np.float64)
    if not (np.all(np.isfinite(lin)) and np.all(np.isfinite(ang))):
        raise InputRejected("non_finite", f"NaN or inf in twist: linear {lin.tolist()}, angular {ang.tolist()}")
    check_header(msg.header, frame_id, now_ns, timeout_s)
    return lin, ang


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


class SimNode(Node):
    def __init__(self, node_name="soft_tissue_sim", sim=None, **kwargs):
        """``sim``: an already built Simulation (in-process use); it is then not closed with the node."""
        super().__init__(node_name, **kwargs)
        p = self.declare_parameter
        p("scene", "default.yaml", _desc("scene YAML: a path or a name in config/scenes"))
        p("device", "auto", _desc("auto | cpu | cuda | cuda:N"))
        p("rate_hz", 50.0, _desc("simulation step timer rate (steady clock)"))
        p("realtime", True, _desc("true: one step per timer tick; false: as fast as possible"))
        p("frame_id", "world", _desc("frame of the tissue and of instrument poses"))
        p("surface_publish_every", 1, _desc("publish the surface marker every N steps"))
        p("pose_timeout_s", 0.5, _desc("instrument poses/twists further than this from now are rejected; 0: off"))
        p("quaternion_tolerance", 0.1, _desc("|norm-1| up to which a pose quaternion is normalised, else rejected"))
        p("publish_clock", False, _desc("publish the simulation time on /clock (for use_sim_time nodes)"))
        self.frame_id = self.get_parameter("frame_id").value
        self._owns_sim = sim is None
        if sim is None:
            dev = self.get_parameter("device").value
            sim = load_scene(self.get_parameter("scene").value, device=None if dev == "auto" else dev)
        self.sim = sim
        self.paused = False
        self.last_stats = None
        self.rejected = {"pose": Counter(), "twist": Counter()}
        self.accepted = {"pose": 0, "twist": 0}
        self.last_rejection = ""
        self._last_rejection_t = -math.inf
        self.last_wrench = {}  # name -> (force, torque) numpy arrays
        self._poses = {}  # name -> (position, unit quaternion xyzw) last accepted
        self._twists = {}  # name -> (linear, angular, steady time received)
        self._tri_count = -1
        self._topology = None  # (mesh, mesh_version, n_tets, n_nodes) of the cached surface
        self._tris = None
        self.surface_pub = self.create_publisher(Marker, "~/surface", 1)
        self.markers_pub = self.create_publisher(MarkerArray, "~/markers", 1)
        self.diag_pub = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self.clock_pub = self.create_publisher(ClockMsg, "/clock", 10) if self.get_parameter(
            "publish_clock").value else None
        self.wrench_pubs = {}
        for name in self.sim.instrument_names():
            # the twist first: when both wait, the executor takes them in this order
            self.create_subscription(TwistStamped, f"~/instruments/{name}/twist",
                                     lambda msg, n=name: self._on_twist(n, msg), qos_profile_sensor_data)
            self.create_subscription(PoseStamped, f"~/instruments/{name}/pose",
                                     lambda msg, n=name: self._on_pose(n, msg), qos_profile_sensor_data)
            self.wrench_pubs[name] = self.create_publisher(WrenchStamped, f"~/instruments/{name}/wrench", 10)
        self.create_service(Trigger, "~/reset", self._on_reset)
        self.create_service(Trigger, "~/cut", self._on_cut)
        self.create_service(SetBool, "~/set_cutting", self._on_set_cutting)
        self.create_service(SetBool, "~/pause", self._on_pause)
        rate = float(self.get_parameter("rate_hz").value)
        period = 1.0 / rate if self.get_parameter("realtime").value and rate > 0 else 0.0
        # A steady clock: with use_sim_time the node clock follows /clock, which only this timer advances.
        self.timer = self.create_timer(period, self._on_timer, clock=Clock(clock_type=ClockType.STEADY_TIME))
        self.publish_surface(force=True)

    # ------------------------------------------------------------ inputs
    @property
    def rejected_poses(self) -> int:
        return sum(self.rejected["pose"].values())

    def _now_ns(self) -> int:
        return self.get_clock().now().nanoseconds

    def _reject(self, kind, name, reason, text):
        self.rejected[kind][reason] += 1
        self.last_rejection = f"{kind} of '{name}' ({reason}): {text}"
        self._last_rejection_t = time.monotonic()
        self.get_logger().warning(f"instrument {self.last_rejection}", throttle_duration_sec=1.0)

    def _apply(self, kind, name, pos, quat, lin=None, ang=None) -> bool:
        try:
            self.sim.set_instrument_pose(name, pos, quat, linear_velocity=lin, angular_velocity=ang)
            return True
        except ValueError as exc:
            self._reject(kind, name, "invalid", str(exc))
        except Exception as exc:  # noqa: BLE001 - counted and logged, never fatal
            self._reject(kind, name, "error", f"{type(exc).__name__}: {exc}")
        return False

    def _fresh_twist(self, name):
        tw = self._twists.get(name)
        timeout = float(self.get_parameter("pose_timeout_s").value)
        if tw is None or (timeout > 0 and time.monotonic() - tw[2] > timeout):
            return None, None
        return tw[0], tw[1]

    def _on_pose(self, name, msg: PoseStamped):
        try:
            pos, quat = check_pose(msg, self.frame_id, self._now_ns(),
                                   float(self.get_parameter("pose_timeout_s").value),
                                   float(self.get_parameter("quaternion_tolerance").value))
        except InputRejected as exc:
            return self._reject("pose", name, exc.reason, str(exc))
        except Exception as exc:  # noqa: BLE001
            return self._reject("pose", name, "error", f"{type(exc).__name__}: {exc}")
        lin, ang = self._fresh_twist(name)
        if self._apply("pose", name, pos, quat, lin, ang):
            self._poses[name] = (pos, quat)
            self.accepted["pose"] += 1

    def _on_twist(self, name, msg: TwistStamped):
        try:
            lin, ang = check_twist(msg, self.frame_id, self._now_ns(),
                                   float(self.get_parameter("pose_timeout_s").value))
        except InputRejected as exc:
            return self._reject("twist", name, exc.reason, str(exc))
        except Exception as exc:  # noqa: BLE001
            return self._reject("twist", name, "error", f"{type(exc).__name__}: {exc}")
        self._twists[name] = (lin, ang, time.monotonic())
        self.accepted["twist"] += 1
        if name in self._poses:  # the pose the instrument already has, with the new velocity
            self._apply("twist", name, *self._poses[name], lin, ang)

    # ---------------------------------------------------------- services
    def _on_reset(self, req, resp):
        try:
            self.sim.reset()
            self._poses.clear()
            self._twists.clear()
            self.last_wrench.clear()
            self.publish_surface(force=True)
            self.publish_clock()
            resp.success, resp.message = True, "simulation reset to its initial state"
        except Exception as exc:  # noqa: BLE001 - answered, never fatal
            resp.success, resp.message = False, f"reset failed: {exc}"
        return resp

    def _on_cut(self, req, resp):
        try:
            res = self.sim.cut()
            self.publish_surface(force=True)
            resp.success, resp.message = True, f"{res.tets_changed} tets changed: {res.message}"
        except Exception as exc:  # noqa: BLE001
            resp.success, resp.message = False, f"cut failed: {exc}"
        return resp

    def _on_set_cutting(self, req, resp):
        try:
            self.sim.set_cutting(req.data)
            resp.success, resp.message = True, f"cutting {'on' if req.data else 'off'}"
        except Exception as exc:  # noqa: BLE001
            resp.success, resp.message = False, f"set_cutting failed: {exc}"
        return resp

    def _on_pause(self, req, resp):
        self.paused = bool(req.data)
        resp.success, resp.message = True, "paused" if self.paused else "running"
        return resp

    # ------------------------------------------------------------ output
    def _on_timer(self):
        if self.paused:
            return
        try:
            self.last_stats = self.sim.step()
        except Exception as exc:  # noqa: BLE001 - keep the node alive and say why
            self.get_logger().error(f"step failed: {exc}", throttle_duration_sec=1.0)
            return
        try:
            self.publish_clock()
            every = max(1, int(self.get_parameter("surface_publish_every").value))
            self.publish_surface(force=self.last_stats.step % every == 0)
            self.publish_wrenches()
            self.publish_markers()
            self.publish_diagnostics()
        except Exception as exc:  # noqa: BLE001
            if self.context.ok():  # else: shutting down (Ctrl-C while stepping), nothing to say
                self.get_logger().error(f"publishing failed: {type(exc).__name__}: {exc}",
                                        throttle_duration_sec=1.0)

    def publish_clock(self):
        if self.clock_pub is not None:
            ns = int(round(self.sim.time * 1e9))
            self.clock_pub.publish(ClockMsg(clock=TimeMsg(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)))

    def _stamp(self):
        return self.get_clock().now().to_msg()

    def surface_marker(self) -> Marker:
        m = Marker()
        m.header.frame_id = self.frame_id
        m.header.stamp = self._stamp()
        m.ns, m.id, m.type, m.action = "tissue", 0, Marker.TRIANGLE_LIST, Marker.ADD
        m.pose.orientation.w = 1.0
        m.scale.x = m.scale.y = m.scale.z = 1.0
        m.color.r, m.color.g, m.color.b, m.color.a = 0.9, 0.55, 0.55, 1.0
        x = self.sim.positions()
        tris = self._surface_triangles()
        m.points = [Point(x=a, y=b, z=c) for a, b, c in x[tris.reshape(-1)].tolist()]  # tolist: 2x faster
        return m

    def _topology_key(self):
        mesh = self.sim.mesh  # a cut replaces the mesh object and bumps mesh_version
        return mesh, getattr(self.sim, "mesh_version", 0), mesh.n_tets, mesh.n_nodes

    def _topology_changed(self) -> bool:
        key, old = self._topology_key(), self._topology
        return old is None or key[0] is not old[0] or key[1:] != old[1:]

    def _surface_triangles(self):
        """The surface triangles, recomputed only when the topology changed (a cut or a reset)."""
        if self._topology_changed() or self._tris is None:
            self._topology, self._tris = self._topology_key(), self.sim.surface_triangles()
        return self._tris

    def publish_surface(self, force=False):
        if force or self._topology_changed():  # a cut changed the mesh: publish now
            m = self.surface_marker()
            self._tri_count = len(m.points) // 3
            self.surface_pub.publish(m)

    def publish_wrenches(self):
        for name, pub in self.wrench_pubs.items():
            try:
                f, t = self.sim.instrument_wrench(name)
                f, t = np.asarray(f, dtype=float).reshape(3), np.asarray(t, dtype=float).reshape(3)
            except Exception as exc:  # noqa: BLE001
                self.get_logger().warning(f"no wrench for '{name}': {exc}", throttle_duration_sec=1.0)
                continue
            self.last_wrench[name] = (f, t)
            msg = WrenchStamped()
            msg.header.frame_id = self.frame_id
            msg.header.stamp = self._stamp()
            msg.wrench.force.x, msg.wrench.force.y, msg.wrench.force.z = map(float, f)
            msg.wrench.torque.x, msg.wrench.torque.y, msg.wrench.torque.z = map(float, t)
            pub.publish(msg)

    # ---------------------------------------------------------- markers
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
        if name not in self._poses:
            return None
        pos, quat = self._poses[name]
        return pos, pos + quat_rotate(quat, [0.0, 0.0, length]), radius, shape

    def instrument_markers(self) -> list[Marker]:
        """Per instrument (ns "instrument/<name>", ids 3i..3i+2): the shaft (CYLINDER), the two end
        caps (SPHERE_LIST) and, with a blade, the blade (LINE_LIST, red while cutting is active)."""
        out = []
        cutting_on = bool(getattr(getattr(self.sim, "cutting", None), "active", False))
        pt = lambda v: Point(x=float(v[0]), y=float(v[1]), z=float(v[2]))  # noqa: E731
        for i, name in enumerate(self.sim.instrument_names()):
            shaft, caps, line = Marker(), Marker(), Marker()
            for k, (m, kind) in enumerate(((shaft, Marker.CYLINDER), (caps, Marker.SPHERE_LIST),
                                           (line, Marker.LINE_LIST))):
                m.header.frame_id = self.frame_id
                m.header.stamp = self._stamp()
                m.ns, m.id, m.type = f"instrument/{name}", 3 * i + k, kind
                m.pose.orientation.w = 1.0
                m.color.r, m.color.g, m.color.b, m.color.a = 0.7, 0.75, 0.85, 1.0
            seg = self.instrument_segment(name)
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
            blade = _field(self._instrument_info(name), "blade_world")
            blade = blade() if callable(blade) else None
            if blade is not None:
                line.scale.x = 0.5 * r
                line.color.r, line.color.g, line.color.b = (1.0, 0.1, 0.1) if cutting_on else (0.3, 0.3, 0.3)
                line.points = [pt(v) for v in blade]
            else:
                line.action = Marker.DELETE
            out += [shaft, caps, line]
        return out

    def contact_marker(self) -> Marker:
        m = Marker()
        m.header.frame_id = self.frame_id
        m.header.stamp = self._stamp()
        m.ns, m.id, m.type = "contacts", 0, Marker.SPHERE_LIST
        m.pose.orientation.w = 1.0
        m.scale.x = m.scale.y = m.scale.z = 0.002
        m.color.g, m.color.a = 1.0, 1.0
        pts = np.asarray(self.sim.contact_points(), dtype=float).reshape(-1, 3)
        m.points = [Point(x=float(a), y=float(b), z=float(c)) for a, b, c in pts if np.isfinite([a, b, c]).all()]
        return m

    def publish_markers(self):
        if not (self.sim.has_contact or self.wrench_pubs):
            return
        arr = MarkerArray()
        try:
            arr.markers += self.instrument_markers()
        except Exception as exc:  # noqa: BLE001
            self.get_logger().warning(f"instrument markers failed: {exc}", throttle_duration_sec=1.0)
        try:
            arr.markers.append(self.contact_marker())
        except Exception as exc:  # noqa: BLE001
            self.get_logger().warning(f"contact points failed: {exc}", throttle_duration_sec=1.0)
        self.markers_pub.publish(arr)

    # ------------------------------------------------------ diagnostics
    def input_status(self) -> DiagnosticStatus:
        st = DiagnosticStatus(name=f"{self.get_name()}: instrument input", hardware_id=str(self.sim.device))
        values = [KeyValue(key="instruments", value=",".join(self.sim.instrument_names()))]
        for kind in ("pose", "twist"):
            cnt = self.rejected[kind]
            values.append(KeyValue(key=f"accepted_{kind}s", value=str(self.accepted[kind])))
            values.append(KeyValue(key=f"rejected_{kind}s", value=str(sum(cnt.values()))))
            values += [KeyValue(key=f"rejected_{kind}s.{r}", value=str(cnt[r])) for r in REJECT_REASONS]
        values.append(KeyValue(key="last_rejection", value=self.last_rejection))
        st.values = values
        recent = time.monotonic() - self._last_rejection_t < 1.0
        st.level = DiagnosticStatus.WARN if recent else DiagnosticStatus.OK
        st.message = f"rejecting input: {self.last_rejection}" if recent else "ok"
        return st

    def publish_diagnostics(self):
        s = self.last_stats.as_dict() if self.last_stats else {}
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
        for name, (f, _t) in self.last_wrench.items():
            st.values.append(KeyValue(key=f"force_N.{name}", value=f"{float(np.linalg.norm(f)):.6g}"))
        msg = DiagnosticArray(status=[st, self.input_status()])
        msg.header.stamp = self._stamp()
        self.diag_pub.publish(msg)

    def destroy_node(self):
        if self._owns_sim:
            self.sim.close()
        return super().destroy_node()


def main(args=None):
    rclpy.init(args=args)
    node = SimNode()
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
