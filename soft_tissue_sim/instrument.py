"""Rigid instruments posed from outside each step, and static rigid obstacles.

Instrument geometry (tool frame): a sphere-tipped capsule whose shaft is the segment from
the tip centre, the tool frame's origin, to ``length`` along the tool's +z axis, thickened
by ``radius``. A ``length`` of 0 gives a sphere. An optional blade is a segment given by two
points in the tool frame; the cutter reads it in world coordinates with
:meth:`Instrument.blade_world` (pose of the last step, or the latest pose set) and
:meth:`Instrument.previous_blade_world` (pose before the last step), so the blade's sweep
during the last step is the quad between the two.

A pose is a position and a unit quaternion (x, y, z, w) (the ROS order), world frame,
optionally with linear [m/s] and angular [rad/s] velocity (world frame, angular velocity
about the tool frame's origin). The velocities only say how the tool surface moved during
the step (friction needs the relative tangential motion); without them the motion is taken
from the pose change since the previous step. Bad input raises ``ValueError`` with a
message, and the previous pose is kept.

Obstacles are static: an infinite plane (a point and the outward normal) or a triangle mesh
(``vertices`` and ``triangles``, or a ``file`` meshio can read, its triangle cells). Both may
carry their own Coulomb ``friction`` coefficient (else the scene's ``contact.friction``).

Scene entries (see :mod:`soft_tissue_sim.contact.options` for the ``contact`` options)::

    instruments:
      - {name: grasper, shape: capsule, radius: 0.004, length: 0.1,
         pose: {position: [0, 0, 0.05], orientation: [0, 0, 0, 1]},   # optional
         blade: [[0, 0, 0], [0, 0, 0.02]], friction: 0.2}              # optional
    obstacles:
      - {type: plane, name: table, point: [0, 0, 0], normal: [0, 0, 1], friction: 0.3}
      - {type: mesh, name: skull, file: meshes/skull.stl}       # or vertices: [..], triangles: [..]
"""

from __future__ import annotations

import math

import numpy as np
import warp as wp

from .material import ParameterError
from .paths import resolve_path

QUATERNION_TOLERANCE = 1e-3  # |  |q| - 1 | accepted (then normalised); beyond that a pose is rejected
_INSTRUMENT_KEYS = {"name", "shape", "radius", "length", "pose", "blade", "friction"}
_PLANE_KEYS = {"type", "name", "point", "normal", "friction"}
_MESH_KEYS = {"type", "name", "vertices", "triangles", "file", "friction", "scale", "translate"}


# ----------------------------------------------------------------------------- validation
def finite_number(name: str, value, *, minimum: float | None = None, strict: bool = False,
                  error=ParameterError) -> float:
    """``value`` as a finite float, optionally >= (or >, ``strict``) ``minimum``. Raises ``error``."""
    if isinstance(value, bool):
        raise error(f"{name} must be a number, got {value!r}")
    try:
        x = float(value)  # YAML 1.1 reads "1.0e-3" as a string
    except (TypeError, ValueError):
        raise error(f"{name} must be a number, got {value!r}") from None
    if not math.isfinite(x):
        raise error(f"{name} must be finite, got {value!r}")
    if minimum is not None and (x <= minimum if strict else x < minimum):
        raise error(f"{name} must be {'>' if strict else '>='} {minimum}, got {x}")
    return x


def finite_vector(name: str, value, n: int = 3, error=ParameterError) -> np.ndarray:
    """``value`` as a float64 array of ``n`` finite numbers. Raises ``error``."""
    try:
        a = np.array(value, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        raise error(f"{name} must be {n} numbers, got {value!r}") from None
    if a.shape != (n,):
        raise error(f"{name} must be {n} numbers, got {value!r}")
    if not np.all(np.isfinite(a)):
        raise error(f"{name} must be finite, got {a.tolist()}")
    return a


def unit_quaternion(name: str, q, error=ParameterError) -> np.ndarray:
    """A quaternion (x, y, z, w) of norm 1 within :data:`QUATERNION_TOLERANCE`, normalised."""
    a = finite_vector(name, q, 4, error)
    norm = float(np.linalg.norm(a))
    if abs(norm - 1.0) > QUATERNION_TOLERANCE:
        raise error(f"{name} must be a unit quaternion (x, y, z, w), got {a.tolist()} of norm {norm:.6g}")
    return a / norm


def quaternion_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrix of a unit quaternion (x, y, z, w)."""
    x, y, z, w = q
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def _check_keys(what: str, cfg: dict, allowed: set) -> None:
    unknown = set(cfg) - allowed
    if unknown:
        raise ParameterError(f"{what}: unknown keys {sorted(unknown)} (allowed: {sorted(allowed)})")


def _optional_friction(what: str, cfg: dict) -> float | None:
    if cfg.get("friction") is None:
        return None
    return finite_number(f"{what} friction", cfg["friction"], minimum=0.0)


class Pose:
    """A rigid transform: world = R @ local + position."""

    __slots__ = ("position", "quaternion", "R")

    def __init__(self, position, quaternion):
        self.position = np.array(position, dtype=np.float64)
        self.quaternion = np.array(quaternion, dtype=np.float64)
        self.R = quaternion_matrix(self.quaternion)

    def apply(self, local: np.ndarray) -> np.ndarray:
        """Tool-frame points (k, 3) or (3,) to world."""
        return np.asarray(local) @ self.R.T + self.position

    def inverse_apply(self, world: np.ndarray) -> np.ndarray:
        return (np.asarray(world) - self.position) @ self.R

    def copy(self) -> "Pose":
        p = Pose.__new__(Pose)
        p.position, p.quaternion, p.R = self.position.copy(), self.quaternion.copy(), self.R.copy()
        return p


# ----------------------------------------------------------------------------- instruments
class Instrument:
    """A rigid sphere-tipped capsule tool (optionally with a blade), posed from outside.

    Poses: ``pose`` is the latest one set (used by the next step); ``step_pose`` the one the
    last step used; ``previous_step_pose`` the one of the step before. ``force``/``torque``
    hold the last step's contact wrench ON the tool (world frame, torque about the tool
    frame's origin at ``step_pose``) [N, N m].
    """

    kind = "instrument"

    def __init__(self, name: str, radius: float, length: float, pose: Pose, blade: np.ndarray | None = None,
                 friction: float | None = None):
        self.name = name
        self.radius = float(radius)
        self.length = float(length)
        self.blade = None if blade is None else np.array(blade, dtype=np.float64).reshape(2, 3)
        self.friction = friction
        self.initial_pose = pose.copy()
        self.reset()

    @classmethod
    def from_config(cls, cfg, index: int, default_position=(0.0, 0.0, 0.0)) -> "Instrument":
        if not isinstance(cfg, dict):
            raise ParameterError(f"instruments[{index}] must be a mapping, got {cfg!r}")
        name = cfg.get("name")
        if not isinstance(name, str) or not name.strip() or not name.replace("_", "").isalnum():
            raise ParameterError(f"instruments[{index}] needs a name of letters, digits and '_' "
                                 f"(it becomes a ROS topic name), got {name!r}")
        what = f"instrument {name!r}"
        _check_keys(what, cfg, _INSTRUMENT_KEYS)
        shape = cfg.get("shape", "capsule")
        if shape not in ("capsule", "sphere"):
            raise ParameterError(f"{what}: shape must be 'capsule' or 'sphere', got {shape!r}")
        if "radius" not in cfg:
            raise ParameterError(f"{what} needs a radius [m]")
        radius = finite_number(f"{what} radius", cfg["radius"], minimum=0.0, strict=True)
        length = 0.0 if shape == "sphere" else finite_number(f"{what} length", cfg.get("length", 0.0), minimum=0.0)
        pose_cfg = cfg.get("pose") or {}
        if not isinstance(pose_cfg, dict):
            raise ParameterError(f"{what} pose must be a mapping {{position, orientation}}, got {pose_cfg!r}")
        _check_keys(f"{what} pose", pose_cfg, {"position", "orientation"})
        position = finite_vector(f"{what} pose position", pose_cfg.get("position", default_position))
        quat = unit_quaternion(f"{what} pose orientation", pose_cfg.get("orientation", [0.0, 0.0, 0.0, 1.0]))
        blade = None
        if cfg.get("blade") is not None:
            b = cfg["blade"]
            if not (isinstance(b, (list, tuple)) and len(b) == 2):
                raise ParameterError(f"{what} blade must be two points [[x, y, z], [x, y, z]] in the tool frame, got {b!r}")
            blade = np.stack([finite_vector(f"{what} blade point {k}", b[k]) for k in range(2)])
            if np.linalg.norm(blade[1] - blade[0]) <= 0.0:
                raise ParameterError(f"{what} blade has zero length")
        return cls(name, radius, length, Pose(position, quat), blade, _optional_friction(what, cfg))

    # ------------------------------------------------------------------ poses
    def reset(self) -> None:
        self.pose = self.initial_pose.copy()
        self.step_pose = self.initial_pose.copy()
        self.previous_step_pose = self.initial_pose.copy()
        self.linear_velocity = None
        self.angular_velocity = None
        self._step_velocity = (None, None)
        self.force = np.zeros(3)
        self.torque = np.zeros(3)

    def set_pose(self, position, quaternion_xyzw, linear_velocity=None, angular_velocity=None) -> None:
        """Pose for the next step (world frame). Raises ValueError on NaN/inf, a non-unit
        quaternion or wrong sizes; the previous pose is then kept."""
        what = f"instrument {self.name!r}"
        p = finite_vector(f"{what} position", position, error=ValueError)
        q = unit_quaternion(f"{what} orientation", quaternion_xyzw, error=ValueError)
        lv = None if linear_velocity is None else finite_vector(f"{what} linear velocity", linear_velocity,
                                                                error=ValueError)
        av = None if angular_velocity is None else finite_vector(f"{what} angular velocity", angular_velocity,
                                                                 error=ValueError)
        self.pose = Pose(p, q)
        self.linear_velocity, self.angular_velocity = lv, av

    def begin_step(self) -> None:
        """The step about to be solved uses ``pose``; remember the one before it. Velocities
        given with a pose describe the step that follows it only (then the pose change does)."""
        self.previous_step_pose = self.step_pose
        self.step_pose = self.pose.copy()
        self._step_velocity = (self.linear_velocity, self.angular_velocity)
        self.linear_velocity = self.angular_velocity = None

    def displacement_map(self, dt: float) -> tuple[np.ndarray, np.ndarray]:
        """(M, c): the displacement during the last step of the tool's material point now at p is
        M p + c (from the step's velocities where they were given, else from the pose change:
        p - (R_prev R^T (p - x) + x_prev))."""
        lv, av = self._step_velocity
        if lv is not None or av is not None:
            lv = np.zeros(3) if lv is None else np.asarray(lv, dtype=np.float64)
            av = np.zeros(3) if av is None else np.asarray(av, dtype=np.float64)
            S = dt * np.array([[0.0, -av[2], av[1]], [av[2], 0.0, -av[0]], [-av[1], av[0], 0.0]])
            return S, dt * lv - S @ self.step_pose.position
        A = self.previous_step_pose.R @ self.step_pose.R.T
        return np.eye(3) - A, A @ self.step_pose.position - self.previous_step_pose.position

    def point_displacement(self, points: np.ndarray, dt: float) -> np.ndarray:
        """Displacement during the last step of the tool's material points now at ``points`` (k, 3)
        (:meth:`displacement_map`)."""
        points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        M, c = self.displacement_map(dt)
        return points @ M.T + c

    # --------------------------------------------------------------- geometry
    def segment_world(self, pose: Pose | None = None) -> tuple[np.ndarray, np.ndarray]:
        """The capsule's axis segment (tip centre, end of the shaft) in world coordinates."""
        pose = self.step_pose if pose is None else pose
        return pose.position.copy(), pose.position + self.length * pose.R[:, 2]  # R e_z: the tool's axis

    @property
    def has_blade(self) -> bool:
        return self.blade is not None

    def blade_world(self):
        """(p0, p1) world points of the blade at the latest pose, or None without a blade."""
        if self.blade is None:
            return None
        p = self.pose.apply(self.blade)
        return p[0], p[1]

    def previous_blade_world(self):
        """(p0, p1) world points of the blade at the pose before the last step, or None."""
        if self.blade is None:
            return None
        p = self.previous_step_pose.apply(self.blade)
        return p[0], p[1]

    @property
    def origin(self) -> np.ndarray:
        """Where torques are taken: the tool frame's origin at the last step."""
        return self.step_pose.position


# ----------------------------------------------------------------------------- obstacles
class PlaneObstacle:
    """The half-space on the normal's side of a plane is free; the other side is solid."""

    kind = "plane"

    def __init__(self, name: str, point, normal, friction: float | None = None):
        self.name = name
        self.point = np.asarray(point, dtype=np.float64)
        n = np.asarray(normal, dtype=np.float64)
        self.normal = n / np.linalg.norm(n)
        self.friction = friction
        self.force = np.zeros(3)
        self.torque = np.zeros(3)

    @property
    def origin(self) -> np.ndarray:
        return self.point

    def displacement_map(self, dt: float) -> tuple[np.ndarray, np.ndarray]:
        return np.zeros((3, 3)), np.zeros(3)  # static

    def point_displacement(self, points, dt) -> np.ndarray:
        return np.zeros((len(points), 3))


class MeshObstacle:
    """A static triangle mesh. Closed meshes have an inside (the solid); for open ones the
    side opposite the triangles' right-hand normals counts as inside."""

    kind = "mesh"

    def __init__(self, name: str, vertices: np.ndarray, triangles: np.ndarray, friction: float | None = None):
        self.name = name
        self.vertices = np.ascontiguousarray(vertices, dtype=np.float64)
        self.triangles = np.ascontiguousarray(triangles, dtype=np.int32)
        self.friction = friction
        self.force = np.zeros(3)
        self.torque = np.zeros(3)
        self._wp = None  # (device, wp.Mesh, float64 vertices, vec3i triangles), built on first use

    @property
    def origin(self) -> np.ndarray:
        return np.zeros(3)

    def displacement_map(self, dt: float) -> tuple[np.ndarray, np.ndarray]:
        return np.zeros((3, 3)), np.zeros(3)  # static

    def point_displacement(self, points, dt) -> np.ndarray:
        return np.zeros((len(points), 3))

    def warp_mesh(self, device):
        """(wp.Mesh (float32 BVH), float64 vertices, vec3i triangles) on ``device``."""
        if self._wp is None or self._wp[0] != device:
            dev = wp.get_device(device)
            mesh = wp.Mesh(points=wp.array(self.vertices.astype(np.float32), dtype=wp.vec3, device=dev),
                           indices=wp.array(self.triangles.reshape(-1), dtype=wp.int32, device=dev))
            self._wp = (device, mesh, wp.array(self.vertices, dtype=wp.vec3d, device=dev),
                        wp.array(self.triangles, dtype=wp.vec3i, device=dev))
        return self._wp[1:]


def _mesh_arrays(what: str, cfg: dict) -> tuple[np.ndarray, np.ndarray]:
    if "file" in cfg:
        import meshio

        path = resolve_path(cfg["file"])
        try:
            raw = meshio.read(str(path))
        except (Exception, SystemExit) as e:  # noqa: BLE001 - meshio raises many kinds
            raise ParameterError(f"{what}: cannot read {path}: {type(e).__name__}: {e}") from None
        tris = [b.data for b in raw.cells if b.type == "triangle"]
        if not tris:
            raise ParameterError(f"{what}: {path} has no triangle cells ({[b.type for b in raw.cells]})")
        vertices, triangles = np.asarray(raw.points, dtype=np.float64), np.concatenate(tris)
    else:
        if "vertices" not in cfg or "triangles" not in cfg:
            raise ParameterError(f"{what} needs 'file' or both 'vertices' and 'triangles'")
        try:
            vertices = np.array(cfg["vertices"], dtype=np.float64)
            triangles = np.array(cfg["triangles"])
        except (TypeError, ValueError):
            raise ParameterError(f"{what}: vertices and triangles must be numeric lists") from None
    if vertices.ndim != 2 or vertices.shape[1] != 3 or len(vertices) < 3:
        raise ParameterError(f"{what}: vertices must be a list of at least 3 [x, y, z], got shape {vertices.shape}")
    if not np.all(np.isfinite(vertices)):
        raise ParameterError(f"{what}: vertices must be finite")
    if triangles.ndim != 2 or triangles.shape[1] != 3 or len(triangles) == 0:
        raise ParameterError(f"{what}: triangles must be a list of [i, j, k], got shape {triangles.shape}")
    if triangles.dtype.kind not in "iu" and not np.all(triangles == np.round(triangles)):
        raise ParameterError(f"{what}: triangle indices must be integers")
    triangles = triangles.astype(np.int64)
    if triangles.min() < 0 or triangles.max() >= len(vertices):
        raise ParameterError(f"{what}: triangle index out of range 0..{len(vertices) - 1}")
    v = vertices[triangles]
    area2 = np.linalg.norm(np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]), axis=1)
    bad = np.flatnonzero(area2 <= 1e-12 * max(float(np.ptp(vertices, axis=0).max()), 1e-300) ** 2)
    if bad.size:
        raise ParameterError(f"{what}: degenerate (zero-area) triangles {bad[:10].tolist()}")
    scale = finite_number(f"{what} scale", cfg.get("scale", 1.0), minimum=0.0, strict=True)
    shift = finite_vector(f"{what} translate", cfg.get("translate", [0.0, 0.0, 0.0]))
    return vertices * scale + shift, triangles.astype(np.int32)


def obstacle_from_config(cfg, index: int):
    """A :class:`PlaneObstacle` or :class:`MeshObstacle` from a scene's ``obstacles`` entry."""
    if not isinstance(cfg, dict):
        raise ParameterError(f"obstacles[{index}] must be a mapping, got {cfg!r}")
    kind = cfg.get("type")
    name = cfg.get("name", f"{kind}{index}")
    if not isinstance(name, str) or not name.strip():
        raise ParameterError(f"obstacles[{index}] name must be a non-empty string, got {name!r}")
    what = f"obstacle {name!r}"
    if kind == "plane":
        _check_keys(what, cfg, _PLANE_KEYS)
        point = finite_vector(f"{what} point", cfg.get("point", [0.0, 0.0, 0.0]))
        normal = finite_vector(f"{what} normal", cfg.get("normal", [0.0, 0.0, 1.0]))
        if np.linalg.norm(normal) < 1e-12:
            raise ParameterError(f"{what} normal must be non-zero")
        return PlaneObstacle(name, point, normal, _optional_friction(what, cfg))
    if kind == "mesh":
        _check_keys(what, cfg, _MESH_KEYS)
        vertices, triangles = _mesh_arrays(what, cfg)
        return MeshObstacle(name, vertices, triangles, _optional_friction(what, cfg))
    raise ParameterError(f"obstacles[{index}] type must be 'plane' or 'mesh', got {kind!r}")
