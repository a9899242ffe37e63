"""The rclpy node ``soft_tissue_sim``: a thin adapter over :class:`soft_tissue_sim.Simulation`.

Topics (all relative names, remappable):
  ~/surface                          visualization_msgs/Marker (TRIANGLE_LIST, rebuilt when cuts change it)
  ~/markers                          visualization_msgs/MarkerArray (contact points)
  ~/instruments/<name>/pose   (sub)  geometry_msgs/PoseStamped, sensor-data QoS
  ~/instruments/<name>/wrench        geometry_msgs/WrenchStamped (force ON the tool, world frame)
  /diagnostics                       diagnostic_msgs/DiagnosticArray (step statistics, rejected poses)
Services (std_srvs): ~/reset (Trigger), ~/cut (Trigger), ~/set_cutting (SetBool), ~/pause (SetBool).
A failed request is answered with success=False and a message; the node never dies of one.
The node does not touch ROS_AUTOMATIC_DISCOVERY_RANGE: real users discover across machines.
"""

from __future__ import annotations

import math

import rclpy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import Point, PoseStamped, WrenchStamped
from rcl_interfaces.msg import ParameterDescriptor
from rclpy.node import Node
from rclpy.qos import qos_profile_sensor_data
from std_srvs.srv import SetBool, Trigger
from visualization_msgs.msg import Marker, MarkerArray

from ..scene import load_scene


def _desc(text):
    return ParameterDescriptor(description=text)


class SimNode(Node):
    def __init__(self, node_name="soft_tissue_sim", **kwargs):
        super().__init__(node_name, **kwargs)
        p = self.declare_parameter
        p("scene", "default.yaml", _desc("scene YAML: a path or a name in config/scenes"))
        p("device", "auto", _desc("auto | cpu | cuda | cuda:N"))
        p("rate_hz", 50.0, _desc("simulation step timer rate"))
        p("realtime", True, _desc("true: one step per timer tick; false: as fast as possible"))
        p("frame_id", "world", _desc("frame of the tissue and of instrument poses"))
        p("surface_publish_every", 1, _desc("publish the surface marker every N steps"))
        p("pose_timeout_s", 0.5, _desc("instrument poses older than this are rejected"))
        self.frame_id = self.get_parameter("frame_id").value
        dev = self.get_parameter("device").value
        self.sim = load_scene(self.get_parameter("scene").value, device=None if dev == "auto" else dev)
        self.paused = False
        self.rejected_poses = 0
        self.last_stats = None
        self._tri_count = -1
        self.surface_pub = self.create_publisher(Marker, "~/surface", 1)
        self.markers_pub = self.create_publisher(MarkerArray, "~/markers", 1)
        self.diag_pub = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self.wrench_pubs = {}
        for name in self.sim.instrument_names():
            self.create_subscription(PoseStamped, f"~/instruments/{name}/pose",
                                     lambda msg, n=name: self._on_pose(n, msg), qos_profile_sensor_data)
            self.wrench_pubs[name] = self.create_publisher(WrenchStamped, f"~/instruments/{name}/wrench", 10)
        self.create_service(Trigger, "~/reset", self._on_reset)
        self.create_service(Trigger, "~/cut", self._on_cut)
        self.create_service(SetBool, "~/set_cutting", self._on_set_cutting)
        self.create_service(SetBool, "~/pause", self._on_pause)
        rate = float(self.get_parameter("rate_hz").value)
        period = 1.0 / rate if self.get_parameter("realtime").value and rate > 0 else 0.0
        self.timer = self.create_timer(period, self._on_timer)
        self.publish_surface(force=True)

    # ------------------------------------------------------------ inputs
    def _reject(self, why):
        self.rejected_poses += 1
        self.get_logger().warn(f"instrument pose rejected: {why}", throttle_duration_sec=1.0)

    def _on_pose(self, name, msg: PoseStamped):
        if msg.header.frame_id not in ("", self.frame_id):
            return self._reject(f"frame '{msg.header.frame_id}' is not '{self.frame_id}'")
        stamp = msg.header.stamp.sec + 1e-9 * msg.header.stamp.nanosec
        now = self.get_clock().now().nanoseconds * 1e-9
        if stamp > 0 and now - stamp > float(self.get_parameter("pose_timeout_s").value):
            return self._reject(f"pose is {now - stamp:.2f} s old")
        pos = msg.pose.position
        q = msg.pose.orientation
        try:
            self.sim.set_instrument_pose(name, [pos.x, pos.y, pos.z], [q.x, q.y, q.z, q.w])
        except ValueError as exc:
            self._reject(str(exc))

    # ---------------------------------------------------------- services
    def _on_reset(self, req, resp):
        try:
            self.sim.reset()
            self.publish_surface(force=True)
            resp.success, resp.message = True, "simulation reset to its initial state"
        except Exception as exc:  # noqa: BLE001 - answered, never fatal
            resp.success, resp.message = False, f"reset failed: {exc}"
        return resp

    def _on_cut(self, req, resp):
        try:
            res = self.sim.cut()
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
        every = max(1, int(self.get_parameter("surface_publish_every").value))
        self.publish_surface(force=self.last_stats.step % every == 0)
        self.publish_wrenches()
        self.publish_diagnostics()

    def surface_marker(self) -> Marker:
        m = Marker()
        m.header.frame_id = self.frame_id
        m.header.stamp = self.get_clock().now().to_msg()
        m.ns, m.id, m.type, m.action = "tissue", 0, Marker.TRIANGLE_LIST, Marker.ADD
        m.pose.orientation.w = 1.0
        m.scale.x = m.scale.y = m.scale.z = 1.0
        m.color.r, m.color.g, m.color.b, m.color.a = 0.9, 0.55, 0.55, 1.0
        x = self.sim.positions()
        tris = self.sim.surface_triangles()
        m.points = [Point(x=float(a), y=float(b), z=float(c)) for a, b, c in x[tris.reshape(-1)]]
        return m

    def publish_surface(self, force=False):
        if force:
            m = self.surface_marker()
            self._tri_count = len(m.points) // 3
            self.surface_pub.publish(m)

    def publish_wrenches(self):
        for name, pub in self.wrench_pubs.items():
            try:
                f, t = self.sim.instrument_wrench(name)
            except ValueError:
                continue
            msg = WrenchStamped()
            msg.header.frame_id = self.frame_id
            msg.header.stamp = self.get_clock().now().to_msg()
            msg.wrench.force.x, msg.wrench.force.y, msg.wrench.force.z = map(float, f)
            msg.wrench.torque.x, msg.wrench.torque.y, msg.wrench.torque.z = map(float, t)
            pub.publish(msg)
        if self.sim.has_contact:
            arr = MarkerArray()
            pts = self.sim.contact_points()
            m = Marker()
            m.header.frame_id = self.frame_id
            m.ns, m.id, m.type = "contacts", 0, Marker.SPHERE_LIST
            m.scale.x = m.scale.y = m.scale.z = 0.002
            m.color.g, m.color.a = 1.0, 1.0
            m.points = [Point(x=float(a), y=float(b), z=float(c)) for a, b, c in pts]
            arr.markers.append(m)
            self.markers_pub.publish(arr)

    def publish_diagnostics(self):
        s = self.last_stats.as_dict() if self.last_stats else {}
        st = DiagnosticStatus(name=f"{self.get_name()}: solver", hardware_id=str(self.sim.device))
        bad = (not s.get("converged", True)) or any(
            isinstance(v, float) and not math.isfinite(v) for v in s.values())
        st.level = DiagnosticStatus.WARN if bad else DiagnosticStatus.OK
        st.message = "not converged" if bad else "ok"
        keys = ["step", "total_ms", "iterations", "residual", "factor_age", "preconditioner", "contacts", "cuts"]
        st.values = [KeyValue(key=k, value=str(s[k])) for k in keys if k in s]
        st.values.append(KeyValue(key="rejected_poses", value=str(self.rejected_poses)))
        st.values.append(KeyValue(key="surface_triangles", value=str(self._tri_count)))
        msg = DiagnosticArray(status=[st])
        msg.header.stamp = self.get_clock().now().to_msg()
        self.diag_pub.publish(msg)

    def destroy_node(self):
        self.sim.close()
        return super().destroy_node()


def main(args=None):
    rclpy.init(args=args)
    node = SimNode()
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, rclpy.executors.ExternalShutdownException):
        pass
    finally:
        node.destroy_node()
        if rclpy.ok():
            rclpy.shutdown()


if __name__ == "__main__":
    main()
