"""The node built in-process (no launch), driven by the robot-stack client of the node benchmark
(:class:`soft_tissue_sim.ros.client.RobotClient`): the physics thread (the newest pose every
step, a wrench every step), services (bursts all answered, failures with a reason), parameters
(ranges, integers for doubles, run-time changes, read-only), diagnostics, namespaces, instrument
input hardening, the pre-serialized surface, the single-call cut, the scripted instrument, and
bad configuration ending the process with a FATAL line and exit code 1.

No timing assertions: counts, values, levels and messages only."""

import math
import os
import subprocess
import sys
import time

import numpy as np
import pytest
import rclpy
import yaml
from diagnostic_msgs.msg import DiagnosticStatus
from geometry_msgs.msg import PoseStamped, TwistStamped, WrenchStamped
from rclpy.parameter import Parameter
from rclpy.serialization import deserialize_message, serialize_message
from std_srvs.srv import SetBool, Trigger
from visualization_msgs.msg import Marker, MarkerArray

from soft_tissue_sim.contact.records import ContactResponse
from soft_tissue_sim.paths import SCENES_DIR
from soft_tissue_sim.ros.client import RobotClient, Spinner, wait_for
from soft_tissue_sim.ros.node import InputRejected, SimNode, read_stamped
from soft_tissue_sim.ros.scripted_instrument import Script, ScriptedInstrument, path, sample, script_over_surface
from soft_tissue_sim.ros.surface_marker import SurfaceMarkerEncoder, surface_template
from soft_tissue_sim.ros.wrench_message import WrenchEncoder
from soft_tissue_sim.scene import load_scene
from soft_tissue_sim.stats import ContactStats, CutStats

# A DDS domain of this test process: other developers' nodes on this machine stay out of it.
os.environ.setdefault("ROS_DOMAIN_ID", str(1 + os.getpid() % 100))


@pytest.fixture
def ros():
    """(context, spinner): nodes added to the spinner run in a background MultiThreadedExecutor."""
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    spinner = Spinner(context=ctx)
    nodes = []
    yield ctx, spinner, nodes
    spinner.close()  # first: no callback runs on an entity being destroyed
    for n in reversed(nodes):
        n.destroy_node()
    rclpy.shutdown(context=ctx)


FAST = [Parameter("device", value="cpu"), Parameter("realtime", value=False),
        Parameter("diagnostics_rate_hz", value=20.0)]


def add(ros_fixture, *new):
    _ctx, spinner, nodes = ros_fixture
    for n in new:
        nodes.append(n)
        spinner.add(n)
    return new[0] if len(new) == 1 else new


def make_node(ctx, namespace="", params=(), **kw):
    return SimNode(context=ctx, namespace=namespace,
                   parameter_overrides=[Parameter("scene", value="test_small.yaml")] + FAST + list(params), **kw)


def status(client, suffix):
    """The key/value dict and level of the newest status whose name ends with ``suffix``."""
    d = client.diag(suffix)
    return (d[0], d[1]) if d is not None else (None, None)


class RecordingInstruments:
    """Stands in for the contact component in the adapter tests: one instrument 'probe' and a
    record of exactly what the node hands the simulation. ValueError past x = 1 m (the
    simulation refusing a pose), RuntimeError past x = 2 m (the simulation failing)."""

    instruments = [{"name": "probe", "shape": "capsule", "radius": 0.004, "length": 0.05}]

    def __init__(self):
        self.calls = []

    def instrument_names(self):
        return ["probe"]

    def set_instrument_pose(self, name, position, quaternion, linear_velocity=None, angular_velocity=None):
        if position[0] > 2.0:
            raise RuntimeError("solver exploded")
        if name != "probe" or position[0] > 1.0:
            raise ValueError(f"instrument {name!r} pose outside the workspace")
        self.calls.append(dict(position=np.array(position), quaternion=np.array(quaternion),
                               linear=None if linear_velocity is None else np.array(linear_velocity),
                               angular=None if angular_velocity is None else np.array(angular_velocity)))

    def instrument_wrench(self, name):
        return np.array([0.0, 0.0, 0.5]), np.zeros(3)

    def contact_points(self):
        return np.array([[0.05, 0.0, 0.01], [0.06, 0.0, 0.01]])

    def step(self, body, host=None, begin=True, device_lcp=True):
        return ContactResponse(None, ContactStats(contacts=2))

    def launch_penetration(self, body):
        return None  # no measurement of the penetration left

    def reset(self):
        self.calls.clear()


class RecordingBlade:
    """Stands in for the cutting component: records set_active calls with the instrument's pose."""

    def __init__(self, instruments):
        self.active, self.switches, self.instruments = False, [], instruments

    def set_active(self, active):
        self.active = bool(active)
        self.switches.append((self.active, self.instruments.calls[-1]["position"].copy()))

    def step(self, step_count, instruments):
        return []

    def step_stats(self, results):
        return CutStats()

    def reset(self):
        self.active = False


def node_with_recording_instruments(ctx, *params, **kw):
    sim = load_scene("test_small.yaml", device="cpu")
    sim.contact = RecordingInstruments()
    return SimNode(context=ctx, sim=sim, parameter_overrides=FAST + list(params), **kw), sim


def pose_msg(node, pos, quat=(0.0, 0.0, 0.0, 1.0), frame="world", age_s=0.0, zero_stamp=False):
    m = PoseStamped()
    m.header.frame_id = frame
    if not zero_stamp:
        m.header.stamp = (node.get_clock().now() - rclpy.duration.Duration(seconds=age_s)).to_msg()
    m.pose.position.x, m.pose.position.y, m.pose.position.z = map(float, pos)
    o = m.pose.orientation
    o.x, o.y, o.z, o.w = map(float, quat)
    return m


def twist_msg(node, lin, ang=(0.0, 0.0, 0.0), frame="world"):
    m = TwistStamped()
    m.header.frame_id, m.header.stamp = frame, node.get_clock().now().to_msg()
    m.twist.linear.x, m.twist.linear.y, m.twist.linear.z = map(float, lin)
    m.twist.angular.x, m.twist.angular.y, m.twist.angular.z = map(float, ang)
    return m


def send(node, pub, msg, kind="pose", applied=True):
    """Publish one message and wait until the node accepted or rejected it and, when it was
    accepted (and ``applied``), until a step handed it to the simulation (or it refused it)."""
    seen = lambda: node.accepted[kind] + sum(node.rejected[kind].values())  # noqa: E731
    before, acc = seen(), node.accepted[kind]
    rej_sim = node.rejected["pose"]["invalid"] + node.rejected["pose"]["error"]
    pub.publish(msg)
    assert wait_for(lambda: seen() > before, 30.0), f"{kind} never arrived"
    if applied and node.accepted[kind] > acc:
        steps = node.loop.steps
        assert wait_for(lambda: node.loop.steps >= steps + 2 or node.loop.paused, 30.0)
        assert wait_for(lambda: node._inputs["probe"].pose is None or (
            node._inputs["probe"].used_pose_seq == node._inputs["probe"].pose_seq
            and node._inputs["probe"].used_twist_seq == node._inputs["probe"].twist_seq)
            or node.rejected["pose"]["invalid"] + node.rejected["pose"]["error"] > rej_sim, 30.0)


# --------------------------------------------------------------------------- surface marker
def test_pre_serialized_surface_marker_reads_back_as_the_marker():
    enc = SurfaceMarkerEncoder(surface_template("world"))
    rng = np.random.default_rng(0)
    for k in (0, 3, 3 * 517):
        v = rng.normal(size=(k, 3))
        m = deserialize_message(enc.encode(v, 1_234_567_890_123), Marker)
        assert [(p.x, p.y, p.z) for p in m.points] == [tuple(r) for r in v.tolist()]
        assert (m.header.stamp.sec, m.header.stamp.nanosec) == (1234, 567_890_123)
        assert (m.header.frame_id, m.ns, m.id, m.type) == ("world", "tissue", 0, Marker.TRIANGLE_LIST)
        assert m.color.a == pytest.approx(1.0) and m.pose.orientation.w == 1.0 and m.colors == [] and m.text == ""
    other = SurfaceMarkerEncoder(surface_template("a_much_longer_frame_name"))  # other string lengths, alignment
    m = deserialize_message(other.encode(np.ones((6, 3)), 0), Marker)
    assert m.header.frame_id == "a_much_longer_frame_name" and [p.z for p in m.points] == [1.0] * 6
    with pytest.raises(ValueError, match="vertices"):
        enc.encode(np.zeros((4, 2)))


def test_pre_serialized_wrench_reads_back_as_the_wrench():
    for frame in ("world", "w", "a_much_longer_frame_name"):  # other string lengths, alignment
        enc = WrenchEncoder(frame)
        for force, torque, stamp in (((1.5, -2.0, 3e-9), (0.0, -1e-300, 7.0), 1_234_567_890_123),
                                     (np.array([-0.25, 4.0, 1e6]), np.array([2.0, 3.0, -4.0]), 0)):
            m = deserialize_message(enc.encode(force, torque, stamp), WrenchStamped)
            assert m.header.frame_id == frame
            assert (m.header.stamp.sec, m.header.stamp.nanosec) == divmod(stamp, 1_000_000_000)
            f, t = m.wrench.force, m.wrench.torque
            assert (f.x, f.y, f.z) == tuple(float(c) for c in force)
            assert (t.x, t.y, t.z) == tuple(float(c) for c in torque)


def test_instrument_messages_are_read_from_their_serialized_bytes():
    """read_stamped gives a PoseStamped's and a TwistStamped's frame, stamp and values as the
    message has them, for frame ids of every length modulo 8 (the doubles' alignment); bytes
    that are not such a message are rejected with the reason "error"."""
    for k in range(10):
        frame = "f" * k
        p = PoseStamped()
        p.header.frame_id, p.header.stamp.sec, p.header.stamp.nanosec = frame, 1_700_000_000 + k, 999_999_999 - k
        p.pose.position.x, p.pose.position.y, p.pose.position.z = 0.1 * k, -2.5, float("nan")
        p.pose.orientation.x, p.pose.orientation.y, p.pose.orientation.z, p.pose.orientation.w = 0.0, 0.6, 0.0, 0.8
        got = read_stamped(serialize_message(p), PoseStamped)
        assert got[:2] == (frame, (1_700_000_000 + k) * 1_000_000_000 + 999_999_999 - k)
        np.testing.assert_array_equal(got[2], [0.1 * k, -2.5, float("nan"), 0.0, 0.6, 0.0, 0.8])
        t = TwistStamped()
        t.header.frame_id = frame
        t.twist.linear.x, t.twist.angular.z = 1e-3 * k, -4.0
        got = read_stamped(serialize_message(t), TwistStamped)
        assert got[:2] == (frame, 0) and got[2] == (1e-3 * k, 0.0, 0.0, 0.0, 0.0, -4.0)
    raw = serialize_message(PoseStamped())
    for bad in (raw[:20], raw[:12] + b"\xff\xff\x00\x00" + raw[16:]):
        with pytest.raises(InputRejected) as err:
            read_stamped(bad, PoseStamped)
        assert err.value.reason == "error"


# --------------------------------------------------------------------------- node basics
def test_markers_reset_pause_diagnostics_and_graceful_failures(ros):
    ctx = ros[0]
    sim_node = make_node(ctx)
    probe = RobotClient(context=ctx, node_name="probe")
    markers, arrays = [], []
    probe.create_subscription(Marker, "/soft_tissue_sim/surface", markers.append, 10)
    probe.create_subscription(MarkerArray, "/soft_tissue_sim/markers", arrays.append, 10)
    add(ros, sim_node, probe)
    assert wait_for(lambda: len(markers) >= 3 and probe.diag(": solver") and probe.diag(": rate"))
    n_tri = len(sim_node.sim.surface_triangles())
    assert markers[-1].type == Marker.TRIANGLE_LIST and len(markers[-1].points) == 3 * n_tri
    first_z = markers[0].points[-1].z
    assert wait_for(lambda: sim_node.sim.step_count > 20)
    k = len(markers)
    assert wait_for(lambda: len(markers) > k)
    assert abs(markers[-1].points[-1].z - first_z) > 0  # the beam sags under gravity
    assert wait_for(lambda: int(probe.diag(": solver")[0].get("step", 0)) > 0)
    kv, level = status(probe, ": solver")
    assert float(kv["residual"]) <= 1e-7 and kv["rejected_poses"] == "0"
    assert level == DiagnosticStatus.OK and int(kv["surface_triangles"]) == n_tri
    kv, level = status(probe, ": instrument input")
    assert kv["instruments"] == "" and kv["rejected_poses"] == "0" and level == DiagnosticStatus.OK
    kv, level = status(probe, ": rate")
    assert kv["realtime"] == "false" and level == DiagnosticStatus.OK and int(kv["steps_total"]) > 0
    assert arrays == []  # no instruments, no contact: nothing to draw

    assert probe.call(SetBool, "pause", SetBool.Request(data=True)).success
    steps = sim_node.sim.step_count  # answered after it took effect: no step from now on
    time.sleep(0.5)
    assert sim_node.sim.step_count == steps
    assert wait_for(lambda: probe.diag(": rate")[2] == "paused")

    rest_z = float(sim_node.sim.mesh.points[sim_node.sim.surface_triangles().reshape(-1)[-1], 2])
    assert markers[-1].points[-1].z != pytest.approx(rest_z)  # sagged
    r = probe.call(Trigger, "reset")
    assert r.success and sim_node.sim.step_count == 0
    assert wait_for(lambda: markers[-1].points[-1].z == pytest.approx(rest_z))  # paused: the reset state stays

    # a scene without cutting answers the cut services with a failure and the reason; the node lives on
    r = probe.call(Trigger, "cut")
    assert not r.success and "no cutting" in r.message
    r = probe.call(SetBool, "set_cutting", SetBool.Request(data=True))
    assert not r.success and "no cutting" in r.message
    assert probe.call(SetBool, "pause", SetBool.Request(data=False)).success
    assert wait_for(lambda: sim_node.sim.step_count > 3)


def test_the_node_builds_every_kernel_at_start_up(ros, monkeypatch):
    """All of the package's Warp modules are built for the scene's device before the physics
    thread starts (a fresh machine compiles them then, not at the first contact step)."""
    import soft_tissue_sim.ros.node as node_module

    calls = []

    def build_all(device):
        calls.append(device)
        return 0.25

    monkeypatch.setattr(node_module, "build_all", build_all)
    ctx, _spinner, nodes = ros
    node = make_node(ctx, start=False)
    nodes.append(node)
    assert calls == [node.sim.device]
    assert node.kernels_s == 0.25


def test_two_nodes_in_two_namespaces_run_side_by_side(ros):
    ctx = ros[0]
    a, b = make_node(ctx, "left"), make_node(ctx, "right")
    probe = rclpy.create_node("probe2", context=ctx)
    seen = {"left": 0, "right": 0}
    for ns in seen:
        probe.create_subscription(Marker, f"/{ns}/soft_tissue_sim/surface",
                                  lambda m, ns=ns: seen.__setitem__(ns, seen[ns] + 1), 10)
    client = RobotClient("/left/soft_tissue_sim", context=ctx, node_name="left_client")
    add(ros, a, b, probe, client)
    assert wait_for(lambda: min(seen.values()) >= 2)
    assert wait_for(lambda: b.sim.step_count > 5)
    assert client.call(Trigger, "reset").success
    assert a.sim.step_count < b.sim.step_count


def test_parameters_load_from_the_yaml_file(ros, tmp_path):
    ctx = ros[0]
    params = tmp_path / "p.yaml"
    text = open("config/sim_node.yaml").read().replace("rate_hz: 50.0", "rate_hz: 25.0")
    params.write_text(text.replace("scene: default.yaml", "scene: test_small.yaml"))
    node = SimNode(context=ctx, cli_args=["--ros-args", "--params-file", str(params)], start=False)
    assert node.get_parameter("rate_hz").value == 25.0 and node.loop.rate_hz == 25.0
    assert node.get_parameter("scene").value == "test_small.yaml"
    assert node.sim.name == "test_small" and node.get_parameter("frame_id").value == "world"
    assert node.get_parameter("pose_timeout_s").value == 0.5
    assert node.get_parameter("display_rate_hz").value == 30.0
    assert node.get_parameter("publish_clock").value is False
    node.destroy_node()
    # the file's key matches the node in any namespace (sim.launch.py's namespace argument)
    node = SimNode(context=ctx, namespace="left", cli_args=["--ros-args", "--params-file", str(params)], start=False)
    assert node.get_parameter("rate_hz").value == 25.0 and node.sim.name == "test_small"
    node.destroy_node()


def test_parameters_ranges_integers_and_changes_at_run_time(ros):
    ctx = ros[0]
    node = make_node(ctx, params=[Parameter("rate_hz", value=100)])  # an integer where a double is meant
    assert node.get_parameter("rate_hz").value == 100.0 and node.loop.rate_hz == 100.0
    client = RobotClient(context=ctx)
    add(ros, node, client)
    assert client.set_parameters(rate_hz=20, realtime=True) == [(True, "")] * 2
    assert node.loop.rate_hz == 20.0 and node.loop.realtime and node.get_parameter("rate_hz").value == 20.0
    for bad in (0.0, -10, 1e9, float("nan")):
        (ok, reason), = client.set_parameters(rate_hz=bad)
        assert not ok and "rate_hz" in reason
    assert node.loop.rate_hz == 20.0
    assert client.set_parameters(realtime=False) == [(True, "")] and not node.loop.realtime
    assert client.set_parameters(display_rate_hz=5) == [(True, "")]
    assert node.display_timer.timer_period_ns == 200_000_000
    assert client.set_parameters(display_rate_hz=0.0) == [(True, "")] and node.display_timer is None
    assert client.set_parameters(display_rate_hz=40.0) == [(True, "")] and node.display_timer is not None
    assert client.set_parameters(diagnostics_rate_hz=4) == [(True, "")]
    assert node.diag_timer.timer_period_ns == 250_000_000
    assert client.set_parameters(pose_timeout_s=2, workspace_radius=0.5, max_speed=3) == [(True, "")] * 3
    assert node._settings["pose_timeout_s"] == 2.0 and node._workspace() == ((0.0, 0.0, 0.0), 0.5)
    assert client.set_parameters(workspace_center=[1, 2, 3]) == [(True, "")]  # integers again
    assert node._workspace()[0] == (1.0, 2.0, 3.0)
    (ok, reason), = client.set_parameters(workspace_center=[1.0, 2.0])
    assert not ok and "workspace_center" in reason
    for name, value in (("scene", "beam_2000.yaml"), ("device", "cuda"), ("frame_id", "map"),
                        ("publish_clock", True)):
        (ok, reason), = client.set_parameters(**{name: value})
        assert not ok and "read-only" in reason and name in reason
    assert node.frame_id == "world"
    # bad values at start-up: the node does not start
    with pytest.raises(Exception, match="rate_hz"):
        make_node(ctx, params=[Parameter("rate_hz", value=0.0)])
    with pytest.raises(ValueError, match="workspace_center"):
        make_node(ctx, params=[Parameter("workspace_center", value=[0.0])])


def test_bad_configuration_ends_with_a_fatal_line_and_exit_code_1(tmp_path):
    bad_scene = tmp_path / "bad.yaml"
    bad_scene.write_text("name: bad\nmesh: {generator: beam, n_long: 4, n_cross: 2, spacing: 0.01}\nfloor: 3\n")
    env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    cases = {"no such scene": ["-p", "scene:=no_such_scene.yaml"], "unknown scene keys": ["-p", f"scene:={bad_scene}"],
             "rate_hz": ["-p", "rate_hz:=0"], "frame_id": ["-p", "frame_id:=3"]}
    procs = {k: subprocess.Popen([sys.executable, "-m", "soft_tissue_sim.ros", "--ros-args", "-p", "device:=cpu"] + a,
                                 stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
             for k, a in cases.items()}
    for what, p in procs.items():
        out, err = p.communicate(timeout=120)
        assert p.returncode == 1, (what, out, err)
        fatal = [line for line in (out + err).splitlines() if "[FATAL]" in line]
        assert len(fatal) == 1 and "Traceback" not in out + err, (what, out, err)
        assert (what if what != "no such scene" else "no_such_scene.yaml") in fatal[0], fatal


def test_the_node_process_keeps_its_long_lived_objects_out_of_full_collections(ros):
    """``python -m soft_tissue_sim.ros`` freezes what it made before spinning (the scene, its
    buffers and kernels), so that Python's full collections, which walked them all, no longer
    stall a step; its rate diagnostics say how many objects that is."""
    ctx = ros[0]
    from diagnostic_msgs.msg import DiagnosticArray

    ns = f"gc_{os.getpid()}"
    env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    proc = subprocess.Popen([sys.executable, "-m", "soft_tissue_sim.ros", "--ros-args", "-r", f"__ns:=/{ns}",
                             "-p", "device:=cpu", "-p", "scene:=test_small.yaml", "-p", "diagnostics_rate_hz:=5.0"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    frozen = []
    listener = rclpy.create_node("gc_listener", context=ctx)

    def on_diag(msg):
        for st in msg.status:
            if st.name.startswith("soft_tissue_sim: rate") and st.hardware_id == "cpu":
                frozen.extend(int(kv.value) for kv in st.values if kv.key == "gc_frozen_objects")

    listener.create_subscription(DiagnosticArray, "/diagnostics", on_diag, 10)
    add(ros, listener)
    try:
        assert wait_for(lambda: frozen or proc.poll() is not None, timeout=120.0)
        assert proc.poll() is None, proc.communicate()[1][-2000:]
        assert frozen[-1] > 1000  # the scene's objects at least (tens of thousands)
    finally:
        proc.terminate()
        proc.communicate(timeout=30)


# ------------------------------------------------------------------ the physics thread
def test_each_step_uses_the_newest_pose_and_publishes_a_wrench(ros):
    ctx = ros[0]
    node, sim = node_with_recording_instruments(ctx, start=False)
    client = RobotClient(instrument="probe", context=ctx)
    add(ros, node, client)
    assert wait_for(lambda: client.pose_pub.get_subscription_count() > 0
                    and node.wrench_pubs["probe"].get_subscription_count() > 0)
    node.loop.set_paused(True)
    node.start()
    stamps = []
    for k in range(1, 6):  # one at a time, so that the node receives all five
        stamps.append(client.publish_pose((0.01 * k, 0.0, 0.03)))
        assert wait_for(lambda: node.accepted["pose"] == k)
    assert node.superseded == 4 and sim.contact.calls == []  # paused: kept, not applied
    assert client.call(SetBool, "pause", SetBool.Request(data=False)).success
    assert wait_for(lambda: node.loop.steps >= 5)
    # the first step took the newest pose only, and no step took it again
    assert [c["position"][0] for c in sim.contact.calls] == [0.05]
    assert client.call(SetBool, "pause", SetBool.Request(data=True)).success
    steps = node.loop.steps
    assert wait_for(lambda: client.wrenches == steps)  # one wrench per step, all received
    assert node.wrenches_published == steps
    assert client.stamps_used == 1 and client.latency_summary()["count"] == 1  # stamped with the pose used
    assert stamps[-1] in client._sent_stamps
    assert client.last_force == pytest.approx((0.0, 0.0, 0.5))
    # a stream of poses faster than the steps: each step takes the newest, in order, none twice
    assert client.call(SetBool, "pause", SetBool.Request(data=False)).success
    client.reset_counters()
    n0 = len(sim.contact.calls)
    client.start_stream(lambda t: (0.01 + 0.01 * t, 0.0, 0.03), rate_hz=400.0)
    assert wait_for(lambda: client.stamps_used >= 10)
    client.stop_stream()
    xs = [c["position"][0] for c in sim.contact.calls[n0:]]
    assert len(xs) >= 10 and all(b > a for a, b in zip(xs, xs[1:]))
    assert node.superseded > 4 and node.rejected_poses == 0


def test_service_bursts_are_all_answered(ros):
    ctx = ros[0]
    node = make_node(ctx)
    client = RobotClient(context=ctx)
    add(ros, node, client)
    for name, data in (("pause", True), ("pause", False), ("reset", None), ("set_cutting", True), ("cut", None)):
        r = client.burst(name, 100, data=data)
        assert r["answered"] == 100, r
        expect = 0 if name in ("set_cutting", "cut") else 100  # no cutting in this scene: refused, with why
        assert r["succeeded"] == expect, r
        if not expect:
            assert all("no cutting" in m for m in r["messages"]), r
    assert wait_for(lambda: node.sim.step_count > 3)


def test_requests_queued_during_a_step_are_served_together_after_it():
    """The physics loop: requests made during a step run after it, in order; a run of the same
    key runs once and every caller gets its answer; an exception is an answer too."""
    import threading

    from soft_tissue_sim.ros.physics_loop import PhysicsLoop

    in_step, runs = threading.Event(), []

    def step():
        in_step.set()
        time.sleep(0.3)
        return 0.01

    loop = PhysicsLoop(step, rate_hz=1.0, realtime=False)
    loop.start()
    try:
        assert in_step.wait(10.0)
        answers = [None] * 40

        def ask(i):
            if i == 39:
                answers[i] = loop.call(lambda: 1 / 0, 10.0)
            else:
                answers[i] = loop.call(lambda: runs.append(i) or "reset done", 10.0, key="reset")
        threads = [threading.Thread(target=ask, args=(i,)) for i in range(40)]
        for t in threads:
            t.start()
            time.sleep(0.001)
        for t in threads:
            t.join(20.0)
        assert answers[:39] == [(True, "reset done")] * 39 and len(runs) == 1
        assert answers[39][0] is False and "ZeroDivisionError" in answers[39][1]
        assert loop.call(lambda: loop.steps, 10.0)[0]
    finally:
        loop.stop()
    assert loop.call(lambda: "stopped: runs at once", 1.0) == (True, "stopped: runs at once")


def test_a_request_not_served_in_time_is_answered_with_the_reason(ros):
    ctx = ros[0]
    sim = load_scene("test_small.yaml", device="cpu")
    step = sim.step
    sim.step = lambda: (time.sleep(0.3), step())[1]  # a step far longer than the service timeout
    node = SimNode(context=ctx, sim=sim, parameter_overrides=FAST + [Parameter("service_timeout_s", value=0.02)])
    client = RobotClient(context=ctx)
    add(ros, node, client)
    assert wait_for(lambda: node.loop.steps >= 1)
    answers = [client.call(Trigger, "reset") for _ in range(3)]
    assert all(r is not None for r in answers)
    assert any(not r.success and "not served within" in r.message for r in answers), answers
    assert client.set_parameters(service_timeout_s=5.0) == [(True, "")]
    assert client.call(Trigger, "reset").success


def test_rate_diagnostics_warn_when_the_rate_is_not_reached(ros):
    ctx = ros[0]
    node = make_node(ctx, params=[Parameter("realtime", value=True), Parameter("rate_hz", value=10000.0)])
    client = RobotClient(context=ctx)
    add(ros, node, client)
    t = time.monotonic()
    stepping = lambda: (d := client.diag(": rate", newer_than=t + 1.0)) is not None and float(  # noqa: E731
        d[0]["achieved_rate_hz"]) > 0.0  # (a loaded machine's first steps can take seconds)
    assert wait_for(stepping)
    kv, level, message = client.diag(": rate")
    assert level == DiagnosticStatus.WARN and "achieved" in message and "10000" in message
    assert 0.0 < float(kv["achieved_rate_hz"]) < 10000.0 and float(kv["real_time_factor"]) > 0.0
    assert int(kv["wrenches_published"]) == 0  # no instruments
    assert client.set_parameters(realtime=False) == [(True, "")]
    t = time.monotonic()
    assert wait_for(lambda: client.diag(": rate", newer_than=t + 0.5) is not None)
    _kv, level, message = client.diag(": rate")
    assert level == DiagnosticStatus.OK and "as fast as possible" in message


# ------------------------------------------------------------------ instrument input hardening
def test_bad_poses_are_rejected_per_reason_and_counted_in_diagnostics(ros):
    ctx = ros[0]
    # stale past 1.5 s: the good poses have that long to be taken while the physics thread runs
    # as fast as it can (0.5 s was exceeded now and then on a loaded 2-core machine)
    node, sim = node_with_recording_instruments(ctx, Parameter("pose_timeout_s", value=1.5),
                                                Parameter("workspace_radius", value=10.0))
    probe = RobotClient(context=ctx, node_name="pose_source")
    arrays = []
    probe.create_subscription(MarkerArray, "/soft_tissue_sim/markers", arrays.append, 10)
    pub = probe.create_publisher(PoseStamped, "/soft_tissue_sim/instruments/probe/pose", 10)
    add(ros, node, probe)
    assert wait_for(lambda: pub.get_subscription_count() > 0)
    rec = sim.contact
    nan, inf = float("nan"), float("inf")
    s2 = math.sqrt(0.5)
    cases = [  # (message, accepted?): stamped when sent
        (lambda: pose_msg(probe, (0.05, 0.0, 0.03), (0.0, s2 * 1.04, 0.0, s2 * 1.04)), True),  # |q| = 1.04: normalised
        (lambda: pose_msg(probe, (nan, 0.0, 0.03)), False),  # non_finite
        (lambda: pose_msg(probe, (0.05, 0.0, 0.03), (0.0, 0.0, inf, 1.0)), False),  # non_finite
        (lambda: pose_msg(probe, (0.05, 0.0, 0.03), (0.0, 0.0, 0.0, 0.0)), False),  # bad_quaternion (~0)
        (lambda: pose_msg(probe, (0.05, 0.0, 0.03), (0.0, 0.0, 0.0, 2.0)), False),  # bad_quaternion (|q| = 2)
        (lambda: pose_msg(probe, (0.05, 0.0, 0.03), frame="camera_link"), False),  # unknown_frame
        (lambda: pose_msg(probe, (0.05, 0.0, 0.03), age_s=3.0), False),  # stale
        (lambda: pose_msg(probe, (0.05, 0.0, 0.03), age_s=-3.0), False),  # stale (from the future)
        (lambda: pose_msg(probe, (0.06, 0.0, 0.03), frame=""), True),  # empty frame = the node's frame
        (lambda: pose_msg(probe, (0.07, 0.0, 0.03), zero_stamp=True), True),  # zero stamp = now
        (lambda: pose_msg(probe, (1e6, 0.0, 0.03)), False),  # outside_workspace
        (lambda: pose_msg(probe, (0.0, 1e300, 0.0)), False),  # outside_workspace
        (lambda: pose_msg(probe, (1.5, 0.0, 0.03)), False),  # invalid: the simulation's ValueError
        (lambda: pose_msg(probe, (2.5, 0.0, 0.03)), False),  # error: any other exception of the simulation
    ]
    for msg, _ok in cases:
        send(node, pub, msg())
    assert len(rec.calls) == sum(ok for _m, ok in cases) == 3, (node.rejected, node.last_rejection)
    # only finite, unit quaternions reach the simulation; the near-unit one is normalised
    np.testing.assert_allclose(rec.calls[0]["quaternion"], [0.0, s2, 0.0, s2], atol=1e-12)
    assert [c["position"][0] for c in rec.calls] == [0.05, 0.06, 0.07]
    assert all(c["linear"] is None for c in rec.calls)  # no twist sent: no velocity

    assert wait_for(lambda: probe.diag(": instrument input") and
                    probe.diag(": instrument input")[0]["rejected_poses"] == "11")
    kv, level = status(probe, ": instrument input")
    assert level == DiagnosticStatus.WARN and "error" in kv["last_rejection"]
    assert kv["instruments"] == "probe" and kv["accepted_poses"] == "5" and kv["rejected_poses"] == "11"
    expect = {"non_finite": 2, "bad_quaternion": 2, "unknown_frame": 1, "stale": 2, "outside_workspace": 2,
              "invalid": 1, "error": 1}
    assert {r: int(kv[f"rejected_poses.{r}"]) for r in expect} == expect
    assert float(kv["pose_to_step_ms.max"]) >= 0.0
    assert wait_for(lambda: probe.diag(": solver")[0]["rejected_poses"] == "11")
    assert float(status(probe, ": solver")[0]["force_N.probe"]) == pytest.approx(0.5)

    # markers: the capsule at the last applied pose (identity: shaft along +z from the tip), contacts
    assert wait_for(lambda: arrays and any(m.ns == "contacts" for m in arrays[-1].markers))
    assert wait_for(lambda: {(m.ns, m.type): m for m in arrays[-1].markers}[
        ("instrument/probe", Marker.CYLINDER)].pose.position.x == pytest.approx(0.07))
    by = {(m.ns, m.type): m for m in arrays[-1].markers}
    shaft = by[("instrument/probe", Marker.CYLINDER)]
    caps = by[("instrument/probe", Marker.SPHERE_LIST)]
    assert (shaft.pose.position.x, shaft.pose.position.z) == pytest.approx((0.07, 0.03 + 0.025))
    assert (shaft.scale.x, shaft.scale.z) == pytest.approx((0.008, 0.05))
    assert [(p.x, p.z) for p in caps.points] == [pytest.approx((0.07, 0.03)), pytest.approx((0.07, 0.08))]
    assert [(p.x, p.z) for p in by[("contacts", Marker.SPHERE_LIST)].points] == [
        pytest.approx((0.05, 0.01)), pytest.approx((0.06, 0.01))]

    # the pose turned +z onto +x: the shaft lies along x
    send(node, pub, pose_msg(probe, (0.05, 0.0, 0.03), (0.0, s2, 0.0, s2)))
    shaft = lambda: {(m.ns, m.type): m for m in arrays[-1].markers}[("instrument/probe", Marker.CYLINDER)]  # noqa
    assert wait_for(lambda: shaft().pose.position.x != pytest.approx(0.07))
    assert (shaft().pose.position.x, shaft().pose.position.y, shaft().pose.position.z) == pytest.approx(
        (0.075, 0.0, 0.03))
    o = shaft().pose.orientation
    assert abs(o.x * 0 + o.y * s2 + o.z * 0 + o.w * s2) == pytest.approx(1.0)  # the pose's own rotation


def test_twist_gives_the_velocity_of_the_pose_and_bad_twists_are_rejected(ros):
    ctx = ros[0]
    node, sim = node_with_recording_instruments(ctx, Parameter("pose_timeout_s", value=30.0))  # a busy CPU: twists stay fresh
    probe = rclpy.create_node("twist_source", context=ctx)
    pose_pub = probe.create_publisher(PoseStamped, "/soft_tissue_sim/instruments/probe/pose", 10)
    twist_pub = probe.create_publisher(TwistStamped, "/soft_tissue_sim/instruments/probe/twist", 10)
    add(ros, node, probe)
    assert wait_for(lambda: pose_pub.get_subscription_count() > 0 and twist_pub.get_subscription_count() > 0)
    rec = sim.contact
    send(node, twist_pub, twist_msg(probe, (0.0, 0.0, -0.02), (0.0, 0.1, 0.0)), "twist")
    steps = node.loop.steps
    assert wait_for(lambda: node.loop.steps > steps + 3)
    assert rec.calls == []  # no pose yet: the velocity waits for one
    send(node, pose_pub, pose_msg(probe, (0.05, 0.0, 0.03)))
    assert len(rec.calls) == 1
    np.testing.assert_allclose(rec.calls[0]["linear"], [0.0, 0.0, -0.02])
    np.testing.assert_allclose(rec.calls[0]["angular"], [0.0, 0.1, 0.0])
    # a twist after the pose: the same pose again, with the new velocity
    send(node, twist_pub, twist_msg(probe, (0.01, 0.0, 0.0)), "twist")
    assert len(rec.calls) == 2
    np.testing.assert_allclose(rec.calls[1]["position"], [0.05, 0.0, 0.03])
    np.testing.assert_allclose(rec.calls[1]["linear"], [0.01, 0.0, 0.0])
    send(node, twist_pub, twist_msg(probe, (float("nan"), 0.0, 0.0)), "twist")
    send(node, twist_pub, twist_msg(probe, (0.0, 0.0, 1.0), frame="tool0"), "twist")
    send(node, twist_pub, twist_msg(probe, (0.0, 0.0, -20.0)), "twist")  # over max_speed (10 m/s)
    send(node, twist_pub, twist_msg(probe, (0.0, 0.0, 0.0), (500.0, 0.0, 0.0)), "twist")  # over max_angular_speed
    assert len(rec.calls) == 2 and node.accepted["twist"] == 2
    assert dict(node.rejected["twist"]) == {"non_finite": 1, "unknown_frame": 1, "too_fast": 2}
    send(node, pose_pub, pose_msg(probe, (0.06, 0.0, 0.03)))  # keeps the last good twist
    np.testing.assert_allclose(rec.calls[2]["linear"], [0.01, 0.0, 0.0])


# --------------------------------------------------------------------------- scripted instrument
def test_scripted_trajectory_is_continuous_presses_sweeps_and_retracts():
    sc = Script(start=(0.1, 0.0, 0.02), end=(0.3, 0.01, 0.02), approach_height=0.03, press_depth=0.004,
                approach_s=0.5, press_s=0.4, sweep_s=1.2, retract_s=0.5)
    ts, xs = path(sc, 4001)
    dt = ts[1] - ts[0]
    vel = np.array([sample(sc, t).velocity for t in ts])
    vmax = np.abs(vel).max()
    # continuous: no jump bigger than the fastest speed allows, and the velocity is the derivative
    assert np.abs(np.diff(xs, axis=0)).max() <= vmax * dt * 1.01
    np.testing.assert_allclose(np.diff(xs, axis=0) / dt, 0.5 * (vel[1:] + vel[:-1]), atol=2e-3 * vmax)
    assert np.abs(np.diff(vel, axis=0)).max() < 0.05 * vmax  # no velocity jump either
    # starts above the start point, reaches the press depth, sweeps at it with the blade on
    np.testing.assert_allclose(xs[0], [0.1, 0.0, 0.05])
    assert xs[:, 2].min() == pytest.approx(0.016, abs=1e-12)
    phases = [sample(sc, t) for t in ts]
    sweep = np.array([s.position for s in phases if s.phase == "sweep"])
    assert len(sweep) > 100 and np.allclose(sweep[:, 2], 0.016)
    assert all(s.blade == (s.phase == "sweep") for s in phases)
    assert [p for i, p in enumerate(s.phase for s in phases) if i == 0 or phases[i - 1].phase != p] == [
        "approach", "press", "sweep", "retract", "done"]
    # ends retracted above the end point, at rest
    end = sample(sc, sc.total_s + 1.0)
    np.testing.assert_allclose(end.position, [0.3, 0.01, 0.05])
    assert end.phase == "done" and not end.blade and not end.velocity.any()
    with pytest.raises(ValueError, match="sweep_s"):
        Script(sweep_s=0.0)
    with pytest.raises(ValueError, match="start"):
        Script(start=(0.0, float("nan"), 0.0))
    with pytest.raises(ValueError, match="unknown script keys"):
        Script.from_dict({"start": [0, 0, 0], "depth": 0.01})
    # a sweep along the top of the beam, from 15 % to 35 % of its length
    pts = load_scene("test_small.yaml", device="cpu").mesh.points
    s = script_over_surface(pts)
    assert s.start == pytest.approx((0.0165, -0.005, 0.01)) and s.end == pytest.approx((0.0385, -0.005, 0.01))
    assert script_over_surface(pts, clearance=0.004).start[2] == pytest.approx(0.014)
    # on a dome z = 1 - x^2 (grid spacing 0.1) the sweep starts and ends on the top there: the
    # highest of the 8 nearest points, one grid step up the slope (x = -0.6 and -0.2), plus the
    # clearance; not at the summit (1.01)
    g = np.linspace(-1.0, 1.0, 21)
    x, y = (a.ravel() for a in np.meshgrid(g, 0.5 * g))
    dome = np.column_stack([x, y, 1.0 - x * x])
    d = script_over_surface(dome, clearance=0.01)
    assert d.start == pytest.approx((-0.7, -0.025, 1.0 - 0.6 ** 2 + 0.01))
    assert d.end == pytest.approx((-0.3, -0.025, 1.0 - 0.2 ** 2 + 0.01))


def test_scripted_instrument_drives_the_node_on_simulation_time(ros):
    ctx = ros[0]
    # 40 steps/s of 10 ms steps (dt 0.01: 0.4 of real time): the physics thread leaves the
    # executor's threads time for the clock, the script's timer and the set_cutting calls, as a
    # node running at a rate it keeps does. At a rate the CPU barely keeps (100 Hz on the CI
    # machine) the blade's calls were served late or the script starved.
    node, sim = node_with_recording_instruments(ctx, Parameter("publish_clock", value=True),
                                                Parameter("use_sim_time", value=True),
                                                Parameter("realtime", value=True), Parameter("rate_hz", value=40.0))
    sim.cutting = RecordingBlade(sim.contact)
    sc = dict(start=[0.06, 0.0, 0.01], end=[0.09, 0.0, 0.01], approach_height=0.02, press_depth=0.003,
              approach_s=0.08, press_s=0.06, sweep_s=0.16, retract_s=0.2)
    scripted = ScriptedInstrument(context=ctx, parameter_overrides=[
        Parameter("use_sim_time", value=True), Parameter("instrument", value="probe")] + [
        Parameter(k, value=v) for k, v in sc.items()])
    add(ros, node, scripted)
    retracted = lambda: sim.contact.calls and abs(sim.contact.calls[-1]["position"][2] - 0.03) < 1e-12  # noqa
    assert wait_for(lambda: scripted.finished and len(sim.cutting.switches) >= 3 and retracted(), timeout=30.0)
    # poses follow the script in simulation time: from above the start to retracted above the end
    first, last = sim.contact.calls[0]["position"], sim.contact.calls[-1]["position"]
    assert first[2] > 0.025 and abs(first[0] - 0.06) < 1e-6
    np.testing.assert_allclose(last, [0.09, 0.0, 0.03], atol=1e-9)
    assert min(c["position"][2] for c in sim.contact.calls) == pytest.approx(0.007, abs=1e-9)
    assert sum(c["linear"] is None for c in sim.contact.calls) <= 1  # poses come with their twist
    assert node.rejected_poses == 0  # stamped in simulation time, none stale
    # the blade: off at the start, on at the start of the sweep (pressed in), off at its end
    (off0, _), (on, p_on), (off, p_off) = sim.cutting.switches[:3]
    assert (off0, on, off) == (False, True, False)
    assert p_on[2] == pytest.approx(0.007, abs=1e-12) and 0.06 <= p_on[0] < 0.075  # pressed, early in the sweep
    assert p_off[0] == pytest.approx(0.09, abs=1e-3) and p_off[2] < 0.012  # at the end, before it has retracted
    assert scripted.blade_state is False and scripted.cutting_error == ""
    assert scripted.get_clock().ros_time_is_active and sim.time >= 0.5  # the script ran on simulation time


# ------------------------------------------------ with the real contact and cutting components
def probe_scene():
    cfg = yaml.safe_load(open(SCENES_DIR / "test_small.yaml"))
    cfg["gravity"] = [0.0, 0.0, 0.0]  # the beam at rest: only the probe deforms it
    cfg["instruments"] = [{"name": "probe", "shape": "capsule", "radius": 0.004, "length": 0.05,
                           "pose": {"position": [0.08, 0.0, 0.06]}, "blade": [[0.0, 0.0, 0.0], [0.0, 0.0, 0.03]]}]
    return cfg


def test_wrench_responds_to_pressing_the_tissue(ros):
    ctx = ros[0]
    node = SimNode(context=ctx, sim=load_scene(probe_scene(), device="cpu"), parameter_overrides=FAST)
    client = RobotClient(instrument="probe", context=ctx, node_name="presser")
    arrays = []
    client.create_subscription(MarkerArray, "/soft_tissue_sim/markers", arrays.append, 10)
    add(ros, node, client)
    assert wait_for(lambda: client.pose_pub.get_subscription_count() > 0)

    def hold(z, steps):
        client.publish_pose((0.08, 0.0, z))
        used = client.stamps_used
        assert wait_for(lambda: client.stamps_used > used)  # a wrench answers this pose
        n = node.sim.step_count
        assert wait_for(lambda: node.sim.step_count >= n + steps)
        k = client.wrenches
        assert wait_for(lambda: client.wrenches > k)
        return np.array(client.last_force)

    top = float(node.sim.positions()[:, 2].max())  # a surface node right below the tip at (0.08, 0)
    free = hold(top + 0.04, 2)
    assert np.linalg.norm(free) == 0.0  # 4 cm above the tissue: no contact
    pressed = hold(top + 0.004 - 0.003, 4)  # the tip sphere (r = 4 mm) 3 mm into the surface
    assert pressed[2] > 1e-3 and pressed[2] > 3 * np.hypot(pressed[0], pressed[1])  # the tissue pushes it up
    # the markers: the contact component's capsule at the pressed pose, its blade, the contact points
    tip = top + 0.001
    assert wait_for(lambda: arrays and any(m.ns == "contacts" and m.points for m in arrays[-1].markers))
    by = {(m.ns, m.type): m for m in arrays[-1].markers}
    shaft = by[("instrument/probe", Marker.CYLINDER)]
    assert (shaft.pose.position.x, shaft.pose.position.z, shaft.scale.z) == pytest.approx((0.08, tip + 0.025, 0.05))
    blade = by[("instrument/probe", Marker.LINE_LIST)]
    assert [(p.x, p.z) for p in blade.points] == [pytest.approx((0.08, tip)), pytest.approx((0.08, tip + 0.03))]
    contacts = by[("contacts", Marker.SPHERE_LIST)].points
    assert all(abs(p.x - 0.08) < 0.01 and abs(p.z - tip) < 0.005 for p in contacts)


def test_blade_triangles_and_a_cut_where_the_blade_is(ros):
    """The cutter's single cut (library): the blade's segment widened by the radius along the
    tool's x axis; a cut there separates tets when the blade is in the tissue, none when not."""
    cfg = probe_scene()
    cfg["cutting"] = {"instrument": "probe"}
    sim = load_scene(cfg, device="cpu")
    bottom = float(sim.positions()[:, 2].min())
    sim.set_instrument_pose("probe", [0.035, 0.0, bottom - 0.005], [0.0, 0.0, 0.0, 1.0])
    tris = sim.blade_triangles()
    corners = np.unique(tris.reshape(-1, 3).round(12), axis=0)
    np.testing.assert_allclose(corners[:, 1], 0.0)  # the flat of the blade: the tool's x-z plane
    assert sorted(set(corners[:, 0].round(9))) == [0.031, 0.039]  # +- the radius along x
    assert sorted(set(corners[:, 2].round(9))) == [round(bottom - 0.005, 9), round(bottom + 0.025, 9)]
    c, s = math.cos(math.pi / 4), math.sin(math.pi / 4)  # a quarter turn about z: the blade's flat along y
    sim.set_instrument_pose("probe", [0.035, 0.0, bottom - 0.005], [0.0, 0.0, s, c])
    corners = sim.blade_triangles().reshape(-1, 3)
    np.testing.assert_allclose(corners[:, 0], 0.035, atol=1e-12)
    n_tri = len(sim.surface_triangles())
    res = sim.cut_at_blade()
    assert res.changed and res.tets_changed > 0 and len(sim.surface_triangles()) > n_tri
    sim.set_instrument_pose("probe", [0.035, 0.0, bottom + 0.2], [0.0, 0.0, 0.0, 1.0])  # far above the beam
    assert not sim.cut_at_blade().changed
    sim.close()


def test_one_cut_call_cuts_where_the_blade_is(ros):
    ctx = ros[0]
    cfg = probe_scene()
    cfg["cutting"] = {"instrument": "probe"}
    node = SimNode(context=ctx, sim=load_scene(cfg, device="cpu"), parameter_overrides=FAST)
    client = RobotClient(instrument="probe", context=ctx, node_name="cutter")
    markers = []
    client.create_subscription(Marker, "/soft_tissue_sim/surface", markers.append, 10)
    add(ros, node, client)
    assert wait_for(lambda: client.pose_pub.get_subscription_count() > 0 and markers)
    n_before = len(markers[-1].points) // 3
    assert client.call(SetBool, "pause", SetBool.Request(data=True)).success
    bottom = float(node.sim.positions()[:, 2].min())
    c, s = math.cos(math.pi / 4), math.sin(math.pi / 4)  # a quarter turn about z: across the beam
    client.publish_pose((0.035, 0.0, bottom - 0.005), (0.0, 0.0, s, c))  # the blade upright through the beam
    assert wait_for(lambda: node.accepted["pose"] == 1)
    markers.clear()
    r = client.call(Trigger, "cut")  # one call: the cut where the blade is now (the newest pose)
    assert r.success and int(r.message.split()[0]) > 0, r.message
    # the surface after the cut (a periodic display of the old one may come first)
    assert wait_for(lambda: markers and len(markers[-1].points) // 3 == len(node.sim.surface_triangles()))
    n_after = len(markers[-1].points) // 3
    assert n_after > n_before
    client.publish_pose((0.035, 0.0, bottom + 0.2))  # far above the tissue
    assert wait_for(lambda: node.accepted["pose"] == 2)
    r = client.call(Trigger, "cut")
    assert not r.success and "nothing cut" in r.message
