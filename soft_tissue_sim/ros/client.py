"""A robot-stack client of the simulation node, for the node benchmark and the launch-free tests.

:class:`RobotClient` (an rclpy node) does what an integrator's stack does: streams one
instrument's poses at a fixed rate from its own thread (stamped with the system clock),
listens to that instrument's wrench, optionally subscribes to the surface and markers (raw:
counted, not deserialized), reads the node's diagnostics, sends bursts of concurrent
service calls and sets the node's parameters. It measures what the node promises:

- wrenches received, and per pose the latency to the first wrench that answers it (the node
  stamps a wrench with the stamp of the pose its step used): ``now - stamp`` on the same clock;
- poses sent, and how many a step used (distinct stamps seen on wrenches);
- per burst, how many calls were answered and how many succeeded.

Its wrench subscription is served by a thread of its own (:class:`InputThread`, as the node
serves its poses): a wrench a step at 1 kHz is more than rclpy's executors deliver (the
MultiThreadedExecutor falls to a few messages a second and starves the pose stream). Everything
else (diagnostics, surface, service responses) needs an executor running in another thread
(:class:`Spinner`); one thread is enough for the client alone.
"""

from __future__ import annotations

import threading
import time

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped, WrenchStamped
from rcl_interfaces.srv import SetParameters
from rclpy.executors import MultiThreadedExecutor, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from std_srvs.srv import SetBool, Trigger
from visualization_msgs.msg import Marker, MarkerArray

from .input_thread import InputThread, ThreadServedGroup

BURST_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1000, reliability=ReliabilityPolicy.RELIABLE)
POSE_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1, reliability=ReliabilityPolicy.BEST_EFFORT)
WRENCH_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1000, reliability=ReliabilityPolicy.RELIABLE)


class Spinner:
    """An executor spinning the given nodes in a background thread until :meth:`close`; a
    SingleThreadedExecutor for ``threads=1``, else a MultiThreadedExecutor (nodes whose callbacks
    wait, such as the simulation node's services)."""

    def __init__(self, *nodes, context=None, threads: int = 4):
        self.executor = (SingleThreadedExecutor(context=context) if threads == 1
                         else MultiThreadedExecutor(num_threads=threads, context=context))
        for n in nodes:
            self.executor.add_node(n)
        self._thread = threading.Thread(target=self._spin, daemon=True, name="spinner")
        self._thread.start()

    def _spin(self):
        try:
            self.executor.spin()
        except Exception:  # noqa: BLE001 - the context shut down under it
            pass

    def add(self, node):
        self.executor.add_node(node)

    def close(self):
        for n in list(self.executor.get_nodes()):  # no new callbacks; those running finish first
            self.executor.remove_node(n)
        time.sleep(0.1)
        self.executor.shutdown(timeout_sec=5.0)
        self._thread.join(5.0)


def wait_for(cond, timeout: float = 20.0, period: float = 0.01) -> bool:
    """Poll ``cond()`` until true or ``timeout`` seconds passed; its last value."""
    end = time.monotonic() + timeout
    while not cond() and time.monotonic() < end:
        time.sleep(period)
    return bool(cond())


class RobotClient(Node):
    """Drives instrument ``instrument`` of the simulation node ``sim_node`` (fully qualified name)."""

    def __init__(self, sim_node: str = "/soft_tissue_sim", instrument: str | None = None, frame_id: str = "world",
                 node_name: str = "robot_client", **kwargs):
        super().__init__(node_name, **kwargs)
        self.sim_node = sim_node.rstrip("/")
        self.instrument = instrument
        self.frame_id = frame_id
        self._lock = threading.Lock()
        self._stream = None
        self.diagnostics = {}  # status name -> (values, level, message, monotonic time received)
        self._sent_stamps = set()
        self.reset_counters()
        if instrument is not None:
            base = f"{self.sim_node}/instruments/{instrument}"
            self.pose_pub = self.create_publisher(PoseStamped, f"{base}/pose", POSE_QOS)
            sub = self.create_subscription(WrenchStamped, f"{base}/wrench", self._on_wrench, WRENCH_QOS,
                                           callback_group=ThreadServedGroup())
            self._wrench_input = InputThread(self.context, [sub], name=f"{node_name} wrenches")
            self._wrench_input.start()
        self.create_subscription(DiagnosticArray, "/diagnostics", self._on_diagnostics, 50)
        self._surface_sub = self._markers_sub = None
        self._service_clients = {}

    def destroy_node(self):
        self.stop_stream()
        if getattr(self, "_wrench_input", None) is not None:
            self._wrench_input.stop()
        return super().destroy_node()

    # ------------------------------------------------------------ counters
    def reset_counters(self):
        """Forget what was measured so far (a new measurement window)."""
        with self._lock:
            self.poses_sent = 0
            self.wrenches = 0
            self.latencies_ms = []  # per pose a step used: its stamp to the first wrench answering it
            self.stamps_used = 0
            self._last_stamp = None
            self.last_force = None
            self.surfaces = 0
            self.surface_bytes = 0
            self.marker_arrays = 0
            self.window_start = time.monotonic()

    def _on_wrench(self, msg: WrenchStamped):
        now = time.time_ns()
        stamp = int(msg.header.stamp.sec) * 1_000_000_000 + int(msg.header.stamp.nanosec)
        with self._lock:
            self.wrenches += 1
            self.last_force = (msg.wrench.force.x, msg.wrench.force.y, msg.wrench.force.z)
            if stamp != self._last_stamp:
                self._last_stamp = stamp
                if stamp in self._sent_stamps:
                    self.stamps_used += 1
                    self.latencies_ms.append(1e-6 * (now - stamp))

    def _on_diagnostics(self, msg: DiagnosticArray):
        with self._lock:
            for st in msg.status:
                self.diagnostics[st.name] = ({v.key: v.value for v in st.values}, st.level, st.message,
                                             time.monotonic())

    def diag(self, suffix: str, newer_than: float | None = None):
        """(values, level, message) of the newest status whose name ends with ``suffix`` (and was
        received after the monotonic time ``newer_than``), or None."""
        with self._lock:
            for name, (values, level, message, t) in self.diagnostics.items():
                if name.endswith(suffix) and (newer_than is None or t > newer_than):
                    return values, level, message
        return None

    # ------------------------------------------------------------- surface
    def subscribe_display(self, on: bool = True):
        """Subscribe (raw bytes, counted) to the node's surface and markers, or unsubscribe."""
        if on and self._surface_sub is None:
            self._surface_sub = self.create_subscription(Marker, f"{self.sim_node}/surface", self._on_surface, 1,
                                                         raw=True)
            self._markers_sub = self.create_subscription(MarkerArray, f"{self.sim_node}/markers", self._on_markers,
                                                         1, raw=True)
        elif not on and self._surface_sub is not None:
            self.destroy_subscription(self._surface_sub)
            self.destroy_subscription(self._markers_sub)
            self._surface_sub = self._markers_sub = None

    def _on_surface(self, raw: bytes):
        with self._lock:
            self.surfaces += 1
            self.surface_bytes += len(raw)

    def _on_markers(self, raw: bytes):
        with self._lock:
            self.marker_arrays += 1

    # --------------------------------------------------------------- poses
    def publish_pose(self, position, quaternion=(0.0, 0.0, 0.0, 1.0)) -> int:
        """Publish one pose stamped now (system clock); returns the stamp [ns]."""
        m = PoseStamped()
        m.header.frame_id = self.frame_id
        stamp = time.time_ns()
        m.header.stamp.sec, m.header.stamp.nanosec = stamp // 1_000_000_000, stamp % 1_000_000_000
        p = m.pose.position
        p.x, p.y, p.z = (float(c) for c in position)
        o = m.pose.orientation
        o.x, o.y, o.z, o.w = (float(c) for c in quaternion)
        with self._lock:
            self._sent_stamps.add(stamp)
            self.poses_sent += 1
        self.pose_pub.publish(m)
        return stamp

    def start_stream(self, trajectory, rate_hz: float = 1000.0):
        """Publish ``trajectory(t)`` -> position (or (position, quaternion)) at ``rate_hz`` from a
        thread, t in seconds since the start, on absolute deadlines."""
        self.stop_stream()
        self._sent_stamps = set()
        stop = threading.Event()

        def run():
            t0 = time.monotonic()
            k = 0
            while not stop.is_set():
                t = time.monotonic() - t0
                pose = trajectory(t)
                if isinstance(pose, tuple) and len(pose) == 2:
                    self.publish_pose(*pose)
                else:
                    self.publish_pose(pose)
                k += 1
                wait = t0 + k / rate_hz - time.monotonic()
                if wait > 0:
                    stop.wait(wait)
                elif wait < -0.1:  # far behind (the machine is busy): skip ahead, no burst
                    k = int((time.monotonic() - t0) * rate_hz)

        self._stream = (stop, threading.Thread(target=run, daemon=True, name="pose stream"))
        self._stream[1].start()

    def stop_stream(self):
        if self._stream is not None:
            self._stream[0].set()
            self._stream[1].join(5.0)
            self._stream = None

    # ------------------------------------------------------------ services
    def _client(self, srv_type, name):
        key = (srv_type, name)
        if key not in self._service_clients:
            self._service_clients[key] = self.create_client(srv_type, f"{self.sim_node}/{name}", qos_profile=BURST_QOS)
        return self._service_clients[key]

    def call(self, srv_type, name: str, request=None, timeout: float = 20.0):
        """One call; the response, or None when none came within ``timeout``."""
        cli = self._client(srv_type, name)
        if not cli.wait_for_service(timeout_sec=timeout):
            return None
        fut = cli.call_async(request if request is not None else srv_type.Request())
        wait_for(fut.done, timeout)
        return fut.result() if fut.done() else None

    def burst(self, name: str, n: int = 100, data: bool | None = None, timeout: float = 60.0) -> dict:
        """``n`` concurrent calls of the node's service ``name`` (Trigger, or SetBool with ``data``):
        how many were answered, how many succeeded, in how long."""
        srv_type = Trigger if data is None else SetBool
        cli = self._client(srv_type, name)
        if not cli.wait_for_service(timeout_sec=20.0):
            return {"calls": n, "answered": 0, "succeeded": 0, "seconds": None, "error": "service not available"}
        t0 = time.monotonic()
        futs = []
        for _ in range(n):
            req = srv_type.Request() if data is None else SetBool.Request(data=bool(data))
            futs.append(cli.call_async(req))
        wait_for(lambda: all(f.done() for f in futs), timeout)
        done = [f for f in futs if f.done() and f.result() is not None]
        seconds = time.monotonic() - t0
        for f in futs:
            if not f.done():
                cli.remove_pending_request(f)
        return {"calls": n, "answered": len(done), "succeeded": sum(bool(f.result().success) for f in done),
                "seconds": seconds, "messages": sorted({f.result().message for f in done})[:3]}

    def set_parameters(self, timeout: float = 20.0, **values):
        """Set parameters of the node; the list of (successful, reason) per parameter, or None."""
        req = SetParameters.Request(parameters=[Parameter(k, value=v).to_parameter_msg() for k, v in values.items()])
        res = self.call(SetParameters, "set_parameters", req, timeout)
        return None if res is None else [(r.successful, r.reason) for r in res.results]

    # ------------------------------------------------------------- figures
    def latency_summary(self) -> dict:
        with self._lock:
            a = np.array(self.latencies_ms)
        if not len(a):
            return {"count": 0}
        return {"count": int(len(a)), "median_ms": float(np.median(a)), "p99_ms": float(np.percentile(a, 99)),
                "max_ms": float(a.max())}
