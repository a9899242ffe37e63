"""The node built in-process (no launch): markers, services, diagnostics, parameters, namespaces,
instrument input hardening, the scripted instrument, and (with the contact and cutting modules)
wrenches and cuts seen through ROS."""

import math
import time

import numpy as np
import pytest
import rclpy
import yaml
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from geometry_msgs.msg import PoseStamped, TwistStamped, WrenchStamped
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter
from rclpy.qos import qos_profile_sensor_data
from std_srvs.srv import SetBool, Trigger
from visualization_msgs.msg import Marker, MarkerArray

from soft_tissue_sim.contact.records import ContactResponse
from soft_tissue_sim.paths import SCENES_DIR
from soft_tissue_sim.ros.node import SimNode
from soft_tissue_sim.ros.scripted_instrument import Script, ScriptedInstrument, path, sample, script_over_surface
from soft_tissue_sim.scene import load_scene
from soft_tissue_sim.stats import ContactStats, CutStats


@pytest.fixture
def ros():
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    ex = SingleThreadedExecutor(context=ctx)
    yield ctx, ex
    ex.shutdown()
    rclpy.shutdown(context=ctx)


FAST = [Parameter("device", value="cpu"), Parameter("realtime", value=False)]


def make_node(ctx, namespace=""):
    return SimNode(context=ctx, namespace=namespace,
                   parameter_overrides=[Parameter("scene", value="test_small.yaml")] + FAST)


def spin_until(ex, cond, timeout=20.0):
    end = time.time() + timeout
    while time.time() < end and not cond():
        ex.spin_once(timeout_sec=0.05)
    return cond()


def call(ex, node, srv_type, name, req):
    cli = node.create_client(srv_type, name)
    assert spin_until(ex, cli.service_is_ready)
    fut = cli.call_async(req)
    assert spin_until(ex, fut.done)
    return fut.result()


def status(diag_msgs, suffix):
    """The key/value dict and level of the newest status whose name ends with ``suffix``."""
    for msg in reversed(diag_msgs):
        for st in msg.status:
            if st.name.endswith(suffix):
                return {v.key: v.value for v in st.values}, st.level
    return None, None


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

    def step(self, body):
        return ContactResponse(None, ContactStats(contacts=2))

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


def node_with_recording_instruments(ctx, *params):
    sim = load_scene("test_small.yaml", device="cpu")
    sim.contact = RecordingInstruments()
    return SimNode(context=ctx, sim=sim, parameter_overrides=FAST + list(params)), sim


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


def send(ex, node, pub, msg, kind="pose"):
    """Publish one message and spin until the node has accepted or rejected it."""
    seen = lambda: node.accepted[kind] + sum(node.rejected[kind].values())  # noqa: E731
    before = seen()
    pub.publish(msg)
    assert spin_until(ex, lambda: seen() > before, timeout=30.0), f"{kind} never arrived"


# --------------------------------------------------------------------------- node basics
def test_markers_reset_pause_diagnostics_and_graceful_failures(ros):
    ctx, ex = ros
    sim_node = make_node(ctx)
    probe = rclpy.create_node("probe", context=ctx)
    ex.add_node(sim_node)
    ex.add_node(probe)
    markers, diags, arrays = [], [], []
    probe.create_subscription(Marker, "/soft_tissue_sim/surface", markers.append, 10)
    probe.create_subscription(DiagnosticArray, "/diagnostics", diags.append, 10)
    probe.create_subscription(MarkerArray, "/soft_tissue_sim/markers", arrays.append, 10)
    assert spin_until(ex, lambda: len(markers) >= 3 and len(diags) >= 2)
    n_tri = len(sim_node.sim.surface_triangles())
    assert markers[-1].type == Marker.TRIANGLE_LIST and len(markers[-1].points) == 3 * n_tri
    first_z = markers[0].points[-1].z
    assert spin_until(ex, lambda: sim_node.sim.step_count > 20)
    assert abs(markers[-1].points[-1].z - first_z) > 0  # the beam sags under gravity
    kv, level = status(diags, ": solver")
    assert int(kv["step"]) > 0 and float(kv["residual"]) <= 1e-7 and kv["rejected_poses"] == "0"
    assert level == DiagnosticStatus.OK and int(kv["surface_triangles"]) == n_tri
    kv, level = status(diags, ": instrument input")
    assert kv["instruments"] == "" and kv["rejected_poses"] == "0" and level == DiagnosticStatus.OK
    assert arrays == []  # no instruments, no contact: nothing to draw

    assert call(ex, probe, SetBool, "/soft_tissue_sim/pause", SetBool.Request(data=True)).success
    steps = sim_node.sim.step_count
    spin_until(ex, lambda: False, timeout=0.5)
    assert sim_node.sim.step_count == steps

    markers.clear()
    r = call(ex, probe, Trigger, "/soft_tissue_sim/reset", Trigger.Request())
    assert r.success and sim_node.sim.step_count == 0
    assert spin_until(ex, lambda: markers)
    assert markers[0].points[-1].z == pytest.approx(float(sim_node.sim.mesh.points[
        sim_node.sim.surface_triangles().reshape(-1)[-1], 2]))

    # a scene without cutting answers the cut services with a failure, and the node lives on
    r = call(ex, probe, Trigger, "/soft_tissue_sim/cut", Trigger.Request())
    assert not r.success and "no cutting" in r.message
    r = call(ex, probe, SetBool, "/soft_tissue_sim/set_cutting", SetBool.Request(data=True))
    assert not r.success
    assert call(ex, probe, SetBool, "/soft_tissue_sim/pause", SetBool.Request(data=False)).success
    assert spin_until(ex, lambda: sim_node.sim.step_count > 3)
    sim_node.destroy_node()
    probe.destroy_node()


def test_two_nodes_in_two_namespaces_run_side_by_side(ros):
    ctx, ex = ros
    a, b = make_node(ctx, "left"), make_node(ctx, "right")
    probe = rclpy.create_node("probe2", context=ctx)
    for n in (a, b, probe):
        ex.add_node(n)
    seen = {"left": 0, "right": 0}
    for ns in seen:
        probe.create_subscription(Marker, f"/{ns}/soft_tissue_sim/surface",
                                  lambda m, ns=ns: seen.__setitem__(ns, seen[ns] + 1), 10)
    assert spin_until(ex, lambda: min(seen.values()) >= 2)
    assert call(ex, probe, Trigger, "/left/soft_tissue_sim/reset", Trigger.Request()).success
    assert a.sim.step_count == 0 or a.sim.step_count < b.sim.step_count
    for n in (a, b, probe):
        n.destroy_node()


def test_parameters_load_from_the_yaml_file(ros, tmp_path):
    ctx, ex = ros
    params = tmp_path / "p.yaml"
    text = open("config/sim_node.yaml").read().replace("rate_hz: 50.0", "rate_hz: 25.0")
    params.write_text(text.replace("scene: default.yaml", "scene: test_small.yaml"))
    node = SimNode(context=ctx, cli_args=["--ros-args", "--params-file", str(params)])
    assert node.get_parameter("rate_hz").value == 25.0
    assert node.get_parameter("scene").value == "test_small.yaml"
    assert node.sim.name == "test_small" and node.get_parameter("frame_id").value == "world"
    assert node.get_parameter("pose_timeout_s").value == 0.5
    assert node.get_parameter("publish_clock").value is False
    node.destroy_node()
    # the file's key matches the node in any namespace (sim.launch.py's namespace argument)
    node = SimNode(context=ctx, namespace="left", cli_args=["--ros-args", "--params-file", str(params)])
    assert node.get_parameter("rate_hz").value == 25.0 and node.sim.name == "test_small"
    node.destroy_node()


# ------------------------------------------------------------------ instrument input hardening
def test_bad_poses_are_rejected_per_reason_and_counted_in_diagnostics(ros):
    ctx, ex = ros
    node, sim = node_with_recording_instruments(ctx, Parameter("pose_timeout_s", value=0.5))
    probe = rclpy.create_node("pose_source", context=ctx)
    ex.add_node(node)
    ex.add_node(probe)
    diags, arrays = [], []
    probe.create_subscription(DiagnosticArray, "/diagnostics", diags.append, 10)
    probe.create_subscription(MarkerArray, "/soft_tissue_sim/markers", arrays.append, 10)
    pub = probe.create_publisher(PoseStamped, "/soft_tissue_sim/instruments/probe/pose", qos_profile_sensor_data)
    assert spin_until(ex, lambda: pub.get_subscription_count() > 0)
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
        (lambda: pose_msg(probe, (0.05, 0.0, 0.03), age_s=2.0), False),  # stale
        (lambda: pose_msg(probe, (0.05, 0.0, 0.03), age_s=-2.0), False),  # stale (from the future)
        (lambda: pose_msg(probe, (0.06, 0.0, 0.03), frame=""), True),  # empty frame = the node's frame
        (lambda: pose_msg(probe, (0.07, 0.0, 0.03), zero_stamp=True), True),  # zero stamp = now
        (lambda: pose_msg(probe, (1.5, 0.0, 0.03)), False),  # invalid: the simulation's ValueError
        (lambda: pose_msg(probe, (2.5, 0.0, 0.03)), False),  # error: any other exception of the simulation
    ]
    for msg, _ok in cases:
        send(ex, node, pub, msg())
    assert len(rec.calls) == sum(ok for _m, ok in cases) == 3, (node.rejected, node.last_rejection)
    # only finite, unit quaternions reach the simulation; the near-unit one is normalised
    np.testing.assert_allclose(rec.calls[0]["quaternion"], [0.0, s2, 0.0, s2], atol=1e-12)
    assert [c["position"][0] for c in rec.calls] == [0.05, 0.06, 0.07]
    assert all(c["linear"] is None for c in rec.calls)  # no twist sent: no velocity

    assert spin_until(ex, lambda: status(diags, ": instrument input")[0]["rejected_poses"] == "9")
    kv, level = status(diags, ": instrument input")
    assert level == DiagnosticStatus.WARN and "error" in kv["last_rejection"]
    assert kv["instruments"] == "probe" and kv["accepted_poses"] == "3" and kv["rejected_poses"] == "9"
    expect = {"non_finite": 2, "bad_quaternion": 2, "unknown_frame": 1, "stale": 2, "invalid": 1, "error": 1}
    assert {r: int(kv[f"rejected_poses.{r}"]) for r in expect} == expect
    assert status(diags, ": solver")[0]["rejected_poses"] == "9"
    assert float(status(diags, ": solver")[0]["force_N.probe"]) == pytest.approx(0.5)

    # markers: the capsule at the last accepted pose (identity: shaft along +z from the tip), contacts
    assert spin_until(ex, lambda: arrays and any(m.ns == "contacts" for m in arrays[-1].markers))
    by = {(m.ns, m.type): m for m in arrays[-1].markers}
    shaft = by[("instrument/probe", Marker.CYLINDER)]
    caps = by[("instrument/probe", Marker.SPHERE_LIST)]
    assert (shaft.pose.position.x, shaft.pose.position.z) == pytest.approx((0.07, 0.03 + 0.025))
    assert (shaft.scale.x, shaft.scale.z) == pytest.approx((0.008, 0.05))
    assert [(p.x, p.z) for p in caps.points] == [pytest.approx((0.07, 0.03)), pytest.approx((0.07, 0.08))]
    assert [(p.x, p.z) for p in by[("contacts", Marker.SPHERE_LIST)].points] == [
        pytest.approx((0.05, 0.01)), pytest.approx((0.06, 0.01))]

    # the pose turned +z onto +x: the shaft lies along x
    send(ex, node, pub, pose_msg(probe, (0.05, 0.0, 0.03), (0.0, s2, 0.0, s2)))
    shaft = lambda: {(m.ns, m.type): m for m in arrays[-1].markers}[("instrument/probe", Marker.CYLINDER)]  # noqa
    assert spin_until(ex, lambda: shaft().pose.position.x != 0.07)
    assert (shaft().pose.position.x, shaft().pose.position.y, shaft().pose.position.z) == pytest.approx(
        (0.075, 0.0, 0.03))
    o = shaft().pose.orientation
    assert abs(o.x * 0 + o.y * s2 + o.z * 0 + o.w * s2) == pytest.approx(1.0)  # the pose's own rotation
    node.destroy_node()
    probe.destroy_node()


def test_twist_gives_the_velocity_of_the_pose_and_bad_twists_are_rejected(ros):
    ctx, ex = ros
    node, sim = node_with_recording_instruments(ctx)
    probe = rclpy.create_node("twist_source", context=ctx)
    ex.add_node(node)
    ex.add_node(probe)
    pose_pub = probe.create_publisher(PoseStamped, "/soft_tissue_sim/instruments/probe/pose",
                                      qos_profile_sensor_data)
    twist_pub = probe.create_publisher(TwistStamped, "/soft_tissue_sim/instruments/probe/twist",
                                       qos_profile_sensor_data)
    assert spin_until(ex, lambda: pose_pub.get_subscription_count() > 0 and twist_pub.get_subscription_count() > 0)
    rec = sim.contact
    send(ex, node, twist_pub, twist_msg(probe, (0.0, 0.0, -0.02), (0.0, 0.1, 0.0)), "twist")
    assert rec.calls == []  # no pose yet: the velocity waits for one
    send(ex, node, pose_pub, pose_msg(probe, (0.05, 0.0, 0.03)))
    assert len(rec.calls) == 1
    np.testing.assert_allclose(rec.calls[0]["linear"], [0.0, 0.0, -0.02])
    np.testing.assert_allclose(rec.calls[0]["angular"], [0.0, 0.1, 0.0])
    # a twist after the pose: the same pose again, with the new velocity
    send(ex, node, twist_pub, twist_msg(probe, (0.01, 0.0, 0.0)), "twist")
    assert len(rec.calls) == 2
    np.testing.assert_allclose(rec.calls[1]["position"], [0.05, 0.0, 0.03])
    np.testing.assert_allclose(rec.calls[1]["linear"], [0.01, 0.0, 0.0])
    send(ex, node, twist_pub, twist_msg(probe, (float("nan"), 0.0, 0.0)), "twist")
    send(ex, node, twist_pub, twist_msg(probe, (0.0, 0.0, 1.0), frame="tool0"), "twist")
    assert len(rec.calls) == 2 and node.accepted["twist"] == 2
    assert dict(node.rejected["twist"]) == {"non_finite": 1, "unknown_frame": 1}
    send(ex, node, pose_pub, pose_msg(probe, (0.06, 0.0, 0.03)))  # keeps the last good twist
    np.testing.assert_allclose(rec.calls[2]["linear"], [0.01, 0.0, 0.0])
    node.destroy_node()
    probe.destroy_node()


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


def test_scripted_instrument_drives_the_node_on_simulation_time(ros):
    ctx, ex = ros
    node, sim = node_with_recording_instruments(ctx, Parameter("publish_clock", value=True),
                                                Parameter("use_sim_time", value=True))
    sim.cutting = RecordingBlade(sim.contact)
    sc = dict(start=[0.06, 0.0, 0.01], end=[0.09, 0.0, 0.01], approach_height=0.02, press_depth=0.003,
              approach_s=0.08, press_s=0.06, sweep_s=0.16, retract_s=0.2)
    scripted = ScriptedInstrument(context=ctx, parameter_overrides=[
        Parameter("use_sim_time", value=True), Parameter("instrument", value="probe")] + [
        Parameter(k, value=v) for k, v in sc.items()])
    ex.add_node(node)
    ex.add_node(scripted)
    retracted = lambda: abs(sim.contact.calls[-1]["position"][2] - 0.03) < 1e-12  # noqa: E731
    assert spin_until(ex, lambda: scripted.finished and len(sim.cutting.switches) >= 3 and retracted(), timeout=30.0)
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
    assert sim.time < 1.0  # the script took 0.5 s of simulation time, not of wall time
    scripted.destroy_node()
    node.destroy_node()


# ------------------------------------------------ with the real contact and cutting components
def probe_scene():
    cfg = yaml.safe_load(open(SCENES_DIR / "test_small.yaml"))
    cfg["gravity"] = [0.0, 0.0, 0.0]  # the beam at rest: only the probe deforms it
    cfg["instruments"] = [{"name": "probe", "shape": "capsule", "radius": 0.004, "length": 0.05,
                           "pose": {"position": [0.08, 0.0, 0.06]}, "blade": [[0.0, 0.0, 0.0], [0.0, 0.0, 0.03]]}]
    return cfg


def test_wrench_responds_to_pressing_the_tissue(ros):
    ctx, ex = ros
    node = SimNode(context=ctx, sim=load_scene(probe_scene(), device="cpu"), parameter_overrides=FAST)
    probe = rclpy.create_node("presser", context=ctx)
    ex.add_node(node)
    ex.add_node(probe)
    wrenches, arrays = [], []
    probe.create_subscription(WrenchStamped, "/soft_tissue_sim/instruments/probe/wrench", wrenches.append, 50)
    probe.create_subscription(MarkerArray, "/soft_tissue_sim/markers", arrays.append, 10)
    pub = probe.create_publisher(PoseStamped, "/soft_tissue_sim/instruments/probe/pose", qos_profile_sensor_data)
    assert spin_until(ex, lambda: pub.get_subscription_count() > 0)

    def hold(z, steps):
        send(ex, node, pub, pose_msg(probe, (0.08, 0.0, z)))
        n = node.sim.step_count
        assert spin_until(ex, lambda: node.sim.step_count >= n + steps)
        k = len(wrenches)
        assert spin_until(ex, lambda: len(wrenches) > k)
        return np.array([wrenches[-1].wrench.force.x, wrenches[-1].wrench.force.y, wrenches[-1].wrench.force.z])

    top = float(node.sim.positions()[:, 2].max())  # a surface node right below the tip at (0.08, 0)
    free = hold(top + 0.04, 2)
    assert np.linalg.norm(free) == 0.0  # 4 cm above the tissue: no contact
    pressed = hold(top + 0.004 - 0.003, 4)  # the tip sphere (r = 4 mm) 3 mm into the surface
    assert pressed[2] > 1e-3 and pressed[2] > 3 * np.hypot(pressed[0], pressed[1])  # the tissue pushes it up
    assert wrenches[-1].header.frame_id == "world"
    # the markers: the contact component's capsule at the pressed pose, its blade, the contact points
    tip = top + 0.001
    assert spin_until(ex, lambda: arrays and any(m.ns == "contacts" and m.points for m in arrays[-1].markers))
    by = {(m.ns, m.type): m for m in arrays[-1].markers}
    shaft = by[("instrument/probe", Marker.CYLINDER)]
    assert (shaft.pose.position.x, shaft.pose.position.z, shaft.scale.z) == pytest.approx((0.08, tip + 0.025, 0.05))
    blade = by[("instrument/probe", Marker.LINE_LIST)]
    assert [(p.x, p.z) for p in blade.points] == [pytest.approx((0.08, tip)), pytest.approx((0.08, tip + 0.03))]
    contacts = by[("contacts", Marker.SPHERE_LIST)].points
    assert all(abs(p.x - 0.08) < 0.01 and abs(p.z - tip) < 0.005 for p in contacts)
    node.destroy_node()
    probe.destroy_node()


def test_cut_service_changes_the_surface_markers_triangle_count(ros):
    ctx, ex = ros
    cfg = probe_scene()
    cfg["cutting"] = {"instrument": "probe"}
    node = SimNode(context=ctx, sim=load_scene(cfg, device="cpu"), parameter_overrides=FAST)
    probe = rclpy.create_node("cutter", context=ctx)
    ex.add_node(node)
    ex.add_node(probe)
    markers = []
    probe.create_subscription(Marker, "/soft_tissue_sim/surface", markers.append, 10)
    pub = probe.create_publisher(PoseStamped, "/soft_tissue_sim/instruments/probe/pose", qos_profile_sensor_data)
    assert spin_until(ex, lambda: pub.get_subscription_count() > 0 and markers)
    n_before = len(markers[-1].points) // 3
    assert call(ex, probe, SetBool, "/soft_tissue_sim/pause", SetBool.Request(data=True)).success
    bottom = float(node.sim.positions()[:, 2].min())
    send(ex, node, pub, pose_msg(probe, (0.035, -0.03, bottom - 0.005)))  # beside the beam, blade spanning it
    r = call(ex, probe, Trigger, "/soft_tissue_sim/cut", Trigger.Request())
    assert r.success and r.message.startswith("0 tets changed")  # the first cut only records the blade
    send(ex, node, pub, pose_msg(probe, (0.035, 0.03, bottom - 0.005)))  # to the other side: across the beam
    markers.clear()
    r = call(ex, probe, Trigger, "/soft_tissue_sim/cut", Trigger.Request())
    assert r.success and int(r.message.split()[0]) > 0, r.message
    assert spin_until(ex, lambda: markers)
    n_after = len(markers[-1].points) // 3
    assert n_after > n_before and n_after == len(node.sim.surface_triangles())
    node.destroy_node()
    probe.destroy_node()

