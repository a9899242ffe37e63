"""The simulation node's parameters: names, defaults, ranges, which may change at run time.

Every parameter is declared with a ParameterDescriptor carrying its description and, for
numbers, its range (FloatingPointRange / IntegerRange), so rclpy refuses an out-of-range value
with a reason (at start-up: the node does not start; at run time: the set is refused). A
parameter marked read-only is used once at start-up (a run-time change is refused: "Trying to
set a read-only parameter"). Integers are accepted where a float is meant (``rate_hz:=100``):
they are turned into doubles before rclpy's type check, at start-up (the overrides) and at
run time (a pre-set callback).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from rcl_interfaces.msg import FloatingPointRange, ParameterDescriptor
from rclpy.parameter import Parameter


@dataclass(frozen=True)
class Spec:
    """One parameter: default value, description, inclusive range (numbers), read-only."""

    name: str
    default: object
    description: str
    lo: float | None = None
    hi: float | None = None
    read_only: bool = False

    def descriptor(self) -> ParameterDescriptor:
        d = ParameterDescriptor(description=self.description, read_only=self.read_only)
        if self.lo is not None and isinstance(self.default, float):
            d.floating_point_range = [FloatingPointRange(from_value=float(self.lo), to_value=float(self.hi), step=0.0)]
        return d


SPECS = (
    Spec("scene", "default.yaml", "scene YAML: a path or a name in config/scenes (read-only)", read_only=True),
    Spec("device", "auto", "auto | cpu | cuda | cuda:N (read-only)", read_only=True),
    Spec("frame_id", "world", "frame of the tissue, the instrument poses and the wrenches (read-only)",
         read_only=True),
    Spec("publish_clock", False, "publish the simulation time on /clock, for use_sim_time nodes (read-only)",
         read_only=True),
    Spec("rate_hz", 50.0, "steps per second of the physics loop with realtime (steady clock)", 0.1, 10000.0),
    Spec("realtime", True, "true: step at rate_hz; false: step as fast as possible"),
    Spec("display_rate_hz", 30.0, "surface and instrument markers per second (0: only after a reset or a cut)",
         0.0, 1000.0),
    Spec("diagnostics_rate_hz", 1.0, "diagnostics messages per second", 0.1, 100.0),
    Spec("pose_timeout_s", 0.5, "poses/twists stamped further than this from now are rejected (0: off)", 0.0, 3600.0),
    Spec("quaternion_tolerance", 0.1, "|norm - 1| up to which a pose quaternion is normalised, else rejected",
         0.0, 1.0),
    Spec("workspace_center", [0.0, 0.0, 0.0], "centre of the instrument workspace, world frame [m]"),
    Spec("workspace_radius", 1.0, "poses further than this from workspace_center are rejected [m]", 1e-3, 1e6),
    Spec("max_speed", 10.0, "twists with a linear speed above this are rejected [m/s]", 0.0, 1e6),
    Spec("max_angular_speed", 100.0, "twists with an angular speed above this are rejected [rad/s]", 0.0, 1e6),
    Spec("service_timeout_s", 5.0, "a service request not served within this (waiting for the step in "
                                   "progress) is answered with success false", 0.01, 600.0),
)
BY_NAME = {s.name: s for s in SPECS}
READ_ONLY = tuple(s.name for s in SPECS if s.read_only)


def _as_double(p: Parameter) -> Parameter:
    """``p`` with integer values turned into doubles where the parameter is a double (array)."""
    spec = BY_NAME.get(p.name)
    if spec is None:
        return p
    if isinstance(spec.default, float) and p.type_ == Parameter.Type.INTEGER:
        return Parameter(p.name, Parameter.Type.DOUBLE, float(p.value))
    if isinstance(spec.default, list) and p.type_ == Parameter.Type.INTEGER_ARRAY:
        return Parameter(p.name, Parameter.Type.DOUBLE_ARRAY, [float(v) for v in p.value])
    return p


def coerce(parameters: list[Parameter]) -> list[Parameter]:
    """Pre-set callback: integers where doubles are meant become doubles."""
    return [_as_double(p) for p in parameters]


def declare(node) -> None:
    """Declare every parameter of :data:`SPECS` on ``node`` (overrides given as integers where
    doubles are meant are accepted) and check what the descriptors cannot express."""
    overrides = getattr(node, "_parameter_overrides", None)  # rclpy keeps the start-up values here
    if isinstance(overrides, dict):
        for name in list(overrides):
            overrides[name] = _as_double(overrides[name])
    for s in SPECS:
        node.declare_parameter(s.name, s.default, s.descriptor())
    reason = check({s.name: node.get_parameter(s.name).value for s in SPECS})
    if reason:
        raise ValueError(reason)
    node.add_pre_set_parameters_callback(coerce)


def check(values: dict) -> str | None:
    """Why a set of parameter values is not acceptable beyond the descriptors, or None."""
    if "workspace_center" in values:
        c = list(values["workspace_center"])
        if len(c) != 3 or not all(math.isfinite(float(v)) for v in c):
            return f"workspace_center must be 3 finite numbers [m], got {c}"
    if "rate_hz" in values and not float(values["rate_hz"]) > 0.0:
        return f"rate_hz must be > 0, got {values['rate_hz']}"
    return None
