"""The node built in-process (no launch): markers, services, diagnostics, parameters, namespaces."""

import time

import pytest
import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter
from std_srvs.srv import SetBool, Trigger
from visualization_msgs.msg import Marker

from soft_tissue_sim.ros.node import SimNode


@pytest.fixture
def ros():
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    ex = SingleThreadedExecutor(context=ctx)
    yield ctx, ex
    ex.shutdown()
    rclpy.shutdown(context=ctx)


def make_node(ctx, namespace=""):
    return SimNode(context=ctx, namespace=namespace, parameter_overrides=[
        Parameter("scene", value="test_small.yaml"), Parameter("device", value="cpu"),
        Parameter("realtime", value=False)])


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


def test_markers_reset_pause_diagnostics_and_graceful_failures(ros):
    ctx, ex = ros
    sim_node = make_node(ctx)
    probe = rclpy.create_node("probe", context=ctx)
    ex.add_node(sim_node)
    ex.add_node(probe)
    markers, diags = [], []
    probe.create_subscription(Marker, "/soft_tissue_sim/surface", markers.append, 10)
    probe.create_subscription(DiagnosticArray, "/diagnostics", diags.append, 10)
    assert spin_until(ex, lambda: len(markers) >= 3 and len(diags) >= 2)
    n_tri = len(sim_node.sim.surface_triangles())
    assert markers[-1].type == Marker.TRIANGLE_LIST and len(markers[-1].points) == 3 * n_tri
    first_z = markers[0].points[-1].z
    assert spin_until(ex, lambda: sim_node.sim.step_count > 20)
    assert abs(markers[-1].points[-1].z - first_z) > 0  # the beam sags under gravity
    kv = {v.key: v.value for v in diags[-1].status[0].values}
    assert int(kv["step"]) > 0 and float(kv["residual"]) <= 1e-7 and kv["rejected_poses"] == "0"

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
    node.destroy_node()
