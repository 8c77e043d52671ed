"""The built-in measurement models.

They are registered through the ``mbcal.measurements`` entry-point group in mbcal's own
``pyproject.toml``, exactly as a third-party plugin registers its models.

========================  ===========================  ===================  ==========================
kind                      refers to                    values               meaning
========================  ===========================  ===================  ==========================
``image_point``           camera, point                u, v (pixels)        projection (pinhole + OpenCV distortion)
``point3d``               point, frame (world)         x, y, z (m)          a point's position in a frame
``distance``              a, b (points)                value (m)            distance between two points
``angle``                 a, b, c, d (points)          value (rad)          angle between a→b and c→d
``range``                 sensor (range), data: ray    value (m)            distance along a ray to the first surface
``point_to_surface``      object, frame; data: x y z   (0 implied, m)       distance of a measured point to a surface
========================  ===========================  ===================  ==========================
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np

from mbcal._jax import jax, jnp
from mbcal.geometry.camera import project_camera_points
from mbcal.geometry.raycast import cast_rays, distance_to_shapes
from mbcal.language import soa_math as sm
from mbcal.language.ir import Const
from mbcal.measurements.protocol import Batch, MeasurementModel, Role, frame_poses_with_world
from mbcal.modeling import Needs

if TYPE_CHECKING:
    from mbcal.scene import Scene

Array = Any

__all__ = ["ImagePoint", "Point3D", "Distance", "Angle", "Range", "PointToSurface", "BUILTINS"]


def rotate_t(R: Array, v: Array) -> Array:
    """Rᵀ·v for stacks (n, 3, 3) and (n, 3), as a broadcast product and a sum.

    An einsum or matmul here becomes thousands of 3×3 dot products under vmap and jacfwd, which
    XLA runs slowly on a CPU; the elementwise form fuses into one kernel.
    """
    return jnp.sum(R * v[:, :, None], axis=1)


def rotate(R: Array, v: Array) -> Array:
    """R·v for stacks (n, 3, 3) and (n, 3) (see :func:`rotate_t`)."""
    return jnp.sum(R * v[:, None, :], axis=2)


def _is_zero(node) -> bool:
    return isinstance(node, Const) and float(node.value) == 0.0


def _points(scenes: Scene, batch: Batch, role: str) -> Array:
    return scenes.points[batch.config, batch.refs[role]]


def _frame_poses(scenes: Scene, batch: Batch, role: str) -> Array:
    poses, world = frame_poses_with_world(scenes)
    index = np.where(batch.refs[role] < 0, world, batch.refs[role])
    return poses[batch.config, index]


def _distinct(index: np.ndarray) -> list[int]:
    """The distinct entries of an index array, as Python ints (thousands of rows, a few values)."""
    return np.unique(index).tolist()


def _point_needs(batch: Batch, roles: tuple[str, ...], frames: tuple[str, ...] = ()) -> Needs:
    points = frozenset(i for r in roles for i in _distinct(batch.refs[r]))
    framed = frozenset(i for r in frames for i in _distinct(batch.refs[r]) if i >= 0)
    return Needs(frames=framed, points=points)


def _norm(v: Array) -> Array:
    """Row norms of (n, 3) with a finite derivative at zero."""
    sq = jnp.sum(v * v, axis=1)
    return jnp.where(sq > 0, jnp.sqrt(jnp.where(sq > 0, sq, 1.0)), 0.0)


def _to_camera(scenes: Scene, batch: Batch) -> tuple[Array, np.ndarray]:
    cams = batch.refs["camera"]
    frames = np.array([scenes.model.cameras[i].frame for i in cams], dtype=np.int64)
    T = scenes.frame_poses[batch.config, frames]
    p = _points(scenes, batch, "point")
    return rotate_t(T[:, :3, :3], p - T[:, :3, 3]), cams


GRID_MIN_FILL = 0.5
"""``image_point`` measurements are projected on the grid (configuration × point) of each camera
when they fill at least this fraction of it, else one by one (see :func:`_grids`)."""


def _constant_pose(model, frame: int) -> np.ndarray | None:
    """The world pose (4, 4) of a frame whose chain to the world holds only constant poses (no
    joint, no parameter), else None."""
    T = np.eye(4)
    while frame >= 0:
        info = model.frames[frame]
        if info.joint is not None or not (info.pose is None or isinstance(info.pose, Const)):
            return None
        if info.pose is not None:
            T = np.asarray(info.pose.value, dtype=float) @ T
        frame = info.parent
    return T


class _Grid(NamedTuple):
    """The measurements of one camera laid out on the grid (configuration × point) of the scenes."""

    members: np.ndarray  # (k,) positions in the batch
    points: np.ndarray  # (P,) the points they read, each once
    column: np.ndarray  # (k,) each measurement's column in ``points``


def _grids(scenes: Scene, batch: Batch) -> list[_Grid] | None:
    """Per camera, the (configuration × point) grid that holds its measurements — or None when the
    measurements fill less than :data:`GRID_MIN_FILL` of the grids.

    Projecting on the grid and picking the measurements' pixels at the end makes the per-point
    work one array kernel over the scenes' own layout (each camera's pose, intrinsics and
    distortion broadcast over its points), instead of gathering the point, the camera's pose,
    intrinsics and distortion — and under ``jacfwd`` all their derivatives — for every
    measurement: ~2× faster residual and Jacobian for a camera seen in many views (issue 15).
    """
    cams, points = batch.refs["camera"], batch.refs["point"]
    C = int(scenes.points.shape[0])
    grids = []
    for k in np.unique(cams):
        members = np.nonzero(cams == k)[0]
        used, column = np.unique(points[members], return_inverse=True)
        grids.append(_Grid(members, used, column.reshape(-1)))
    if len(batch) < GRID_MIN_FILL * sum(C * len(g.points) for g in grids):
        return None
    return grids


class ImagePoint(MeasurementModel):
    """Pixel coordinates of a named point in a camera (OpenCV's pinhole and distortion model)."""

    kind = "image_point"
    roles = (Role("camera", "camera"), Role("point", "point"))
    values = ("u", "v")
    value_dimension = "pixel"
    default_sigma = 1.0
    description = "pixel coordinates (u, v) of a named point in a camera image"

    def predict(self, scenes: Scene, batch: Batch) -> Array:
        grids = _grids(scenes, batch)
        if grids is None:  # sparse: per measurement
            pc, cams = _to_camera(scenes, batch)
            return self._project(scenes, pc, cams, lambda a: a[batch.config, cams])
        parts = []
        index = np.zeros(len(batch), dtype=np.int64)  # each measurement's row in the grids, flattened
        offset = 0
        for g in grids:
            k = int(batch.refs["camera"][g.members[0]])
            frame = scenes.model.cameras[k].frame
            every = np.array_equal(g.points, np.arange(scenes.points.shape[1]))
            points = scenes.points if every else scenes.points[:, g.points]  # (C, P, 3)
            fixed = _constant_pose(scenes.model, frame)
            if fixed is not None:  # a camera fixed in the world: Rᵀ (p − t) with constants
                d = [sm.sub(points[..., i], float(fixed[i, 3])) for i in range(3)]
                pc = jnp.stack([sm.total(sm.mul(float(fixed[i, j]), d[i]) for i in range(3)) for j in range(3)], -1)
            else:
                T = scenes.frame_poses[:, frame]  # (C, 4, 4)
                pc = jnp.sum(T[:, None, :3, :3] * (points - T[:, None, :3, 3])[:, :, :, None], axis=2)  # Rᵀ (p − t)
            uv = self._project(scenes, pc, [k], lambda a, k=k: a[:, k][:, None])
            parts.append(jnp.reshape(uv, (-1, 2)))
            index[g.members] = offset + batch.config[g.members] * len(g.points) + g.column
            offset += int(uv.shape[0]) * len(g.points)
        return (parts[0] if len(parts) == 1 else jnp.concatenate(parts))[index]

    @staticmethod
    def _project(scenes: Scene, pc: Array, cams: Any, take: Any) -> Array:
        """Pixels of points ``pc`` (..., 3) in the camera frame of cameras ``cams``; ``take`` picks
        the rows of the scenes' intrinsics and distortion that go with them (broadcasting
        against pc's leading axes)."""
        model = scenes.model
        used = sorted(set(np.asarray(cams).tolist()))
        if all(_is_zero(n) for k in used for n in model.cameras[k].distortion):
            # No camera distorts: skip the polynomial (and its derivatives) altogether.
            xy = pc[..., :2] / pc[..., 2:3]
            if all(_is_zero(model.cameras[k].intrinsics[4]) for k in used):
                if len(used) == 1 and all(isinstance(n, Const) for n in model.cameras[used[0]].intrinsics[:4]):
                    fx, fy, cx, cy = (float(n.value) for n in model.cameras[used[0]].intrinsics[:4])
                    return jnp.stack([fx * xy[..., 0] + cx, fy * xy[..., 1] + cy], axis=-1)
                K = take(scenes.camera_intrinsics)
                return jnp.stack([K[..., 0] * xy[..., 0] + K[..., 2], K[..., 1] * xy[..., 1] + K[..., 3]], axis=-1)
        return project_camera_points(pc, take(scenes.camera_intrinsics), take(scenes.camera_distortion))

    def candidates(self, model, configurations):
        return [
            {"kind": self.kind, "camera": c.name, "point": p.name, "config": cfg}
            for cfg in configurations
            for c in model.cameras
            for p in model.points
        ]

    def needs(self, model, batch: Batch) -> Needs:
        return Needs(
            points=frozenset(_distinct(batch.refs["point"])),
            cameras=frozenset(_distinct(batch.refs["camera"])),
        )

    def visible(self, scenes: Scene, batch: Batch) -> Array:
        pc, cams = _to_camera(scenes, batch)
        uv = self.predict(scenes, batch)
        size = np.array([[scenes.model.cameras[i].width, scenes.model.cameras[i].height] for i in cams], dtype=float)
        inside = (uv >= -0.5) & (uv <= size - 0.5)
        return (pc[:, 2] > 1e-6) & jnp.all(inside, axis=1)


class Point3D(MeasurementModel):
    """A named point's position, in the world or in a given frame."""

    kind = "point3d"
    roles = (Role("point", "point"), Role("frame", "frame", default="world"))
    values = ("x", "y", "z")
    value_dimension = "length"
    default_sigma = 1e-3
    description = "3-D position (x, y, z) of a named point in a frame (default: world)"

    def predict(self, scenes: Scene, batch: Batch) -> Array:
        T = _frame_poses(scenes, batch, "frame")
        p = _points(scenes, batch, "point")
        return rotate_t(T[:, :3, :3], p - T[:, :3, 3])

    def needs(self, model, batch: Batch) -> Needs:
        return _point_needs(batch, ("point",), ("frame",))

    def candidates(self, model, configurations):
        return [{"kind": self.kind, "point": p.name, "config": cfg} for cfg in configurations for p in model.points]


class Distance(MeasurementModel):
    """The distance between two named points."""

    kind = "distance"
    roles = (Role("a", "point"), Role("b", "point"))
    values = ("value",)
    value_dimension = "length"
    default_sigma = 1e-3
    description = "distance between points a and b"

    def predict(self, scenes: Scene, batch: Batch) -> Array:
        return _norm(_points(scenes, batch, "a") - _points(scenes, batch, "b"))[:, None]

    def needs(self, model, batch: Batch) -> Needs:
        return _point_needs(batch, ("a", "b"))

    def candidates(self, model, configurations):
        names = [p.name for p in model.points]
        if len(names) > 40:  # n² pairs: only for small models
            return []
        return [
            {"kind": self.kind, "a": a, "b": b, "config": cfg}
            for cfg in configurations
            for i, a in enumerate(names)
            for b in names[i + 1 :]
        ]


class Angle(MeasurementModel):
    """The angle between the directions a→b and c→d."""

    kind = "angle"
    roles = (Role("a", "point"), Role("b", "point"), Role("c", "point"), Role("d", "point"))
    values = ("value",)
    value_dimension = "angle"
    default_sigma = 1e-3
    description = "angle between the directions a→b and c→d"

    def predict(self, scenes: Scene, batch: Batch) -> Array:
        u = _points(scenes, batch, "b") - _points(scenes, batch, "a")
        v = _points(scenes, batch, "d") - _points(scenes, batch, "c")
        return jnp.arctan2(_norm(jnp.cross(u, v)), jnp.sum(u * v, axis=1))[:, None]

    def needs(self, model, batch: Batch) -> Needs:
        return _point_needs(batch, ("a", "b", "c", "d"))


class Range(MeasurementModel):
    """Distance along one ray of a range sensor to the first surface of the scene."""

    kind = "range"
    roles = (Role("sensor", "range"),)
    values = ("value",)
    data = ("ray",)
    integer_data = ("ray",)
    value_dimension = "length"
    default_sigma = 1e-3
    description = "distance along ray number 'ray' of a range sensor to the first surface it hits"

    def needs(self, model, batch: Batch) -> Needs:
        frames = frozenset(model.ranges[s].frame for s in _distinct(batch.refs["sensor"]))
        return Needs(frames=frames, shapes=None)

    def check(self, model, refs, data):
        n = len(model.ranges[refs["sensor"]].directions)
        ray = int(data["ray"])
        if not 0 <= ray < n:
            return f"ray {ray} does not exist: range sensor '{model.ranges[refs['sensor']].name}' has rays 0..{n - 1}"
        return None

    def candidates(self, model, configurations):
        out = []
        for cfg in configurations:
            for r in model.ranges:
                step = max(1, len(r.directions) // 64)  # a sample of a dense grid is enough to rank
                out.extend(
                    {"kind": self.kind, "sensor": r.name, "ray": k, "config": cfg}
                    for k in range(0, len(r.directions), step)
                )
        return out

    def _rays(self, scenes: Scene, batch: Batch) -> tuple[Array, Array, np.ndarray]:
        model = scenes.model
        sensors = batch.refs["sensor"]
        rays = batch.data[:, 0].astype(np.int64)
        frames = np.array([model.ranges[s].frame for s in sensors], dtype=np.int64)
        local = (
            np.stack([model.ranges[s].directions[r] for s, r in zip(sensors, rays)]) if len(batch) else np.zeros((0, 3))
        )
        T = scenes.frame_poses[batch.config, frames]
        directions = rotate(T[:, :3, :3], jnp.asarray(local))
        max_range = np.array([model.ranges[s].max_range for s in sensors], dtype=float)
        return T[:, :3, 3], directions, max_range

    def predict(self, scenes: Scene, batch: Batch) -> Array:
        origins, directions, max_range = self._rays(scenes, batch)
        shapes = scenes.model.shapes
        poses = scenes.shape_poses[batch.config]
        dims = scenes.shape_dims[batch.config]

        def one(P, D, o, d):
            return cast_rays(P, D, shapes, o[None], d[None])[0]

        t = jax.vmap(one)(poses, dims, origins, directions)
        return jnp.where(t < max_range, t, max_range)[:, None]  # a miss reads the maximum range

    def visible(self, scenes: Scene, batch: Batch) -> Array:
        origins, directions, max_range = self._rays(scenes, batch)
        shapes = scenes.model.shapes
        t = jax.vmap(lambda P, D, o, d: cast_rays(P, D, shapes, o[None], d[None])[0])(
            scenes.shape_poses[batch.config], scenes.shape_dims[batch.config], origins, directions
        )
        return t < max_range


class PointToSurface(MeasurementModel):
    """Distance of a measured 3-D point (a range sensor's point cloud) to a named object's surface.

    The measured point (x, y, z) is given in ``frame`` (default: world); the object is a frame
    whose shapes — and those of the frames under it — make the surface.  The measured value is
    0: the point lies on the surface.
    """

    kind = "point_to_surface"
    roles = (Role("object", "object"), Role("frame", "frame", default="world"))
    values = ("distance",)
    data = ("x", "y", "z")
    unit_data = ("x", "y", "z")
    value_dimension = "length"
    implicit_value = 0.0
    default_sigma = 1e-3
    description = "distance of a measured point (x, y, z in 'frame') to the surface of 'object' (0 when it fits)"

    def needs(self, model, batch: Batch) -> Needs:
        shapes = frozenset(
            i for obj in set(batch.refs["object"].tolist()) for i in model.shapes_of(model.frames[obj].name)
        )
        frames = frozenset(i for i in _distinct(batch.refs["frame"]) if i >= 0)
        return Needs(frames=frames, shapes=shapes)

    def check(self, model, refs, data):
        if not model.shapes_of(model.frames[refs["object"]].name):
            return f"object '{model.frames[refs['object']].name}' has no shapes to measure a distance to"
        return None

    def predict(self, scenes: Scene, batch: Batch) -> Array:
        model = scenes.model
        T = _frame_poses(scenes, batch, "frame")
        p = rotate(T[:, :3, :3], jnp.asarray(batch.data)) + T[:, :3, 3]
        out = jnp.zeros(len(batch))
        objects = batch.refs["object"]
        for obj in np.unique(objects):
            rows = np.nonzero(objects == obj)[0]
            idx = np.asarray(model.shapes_of(model.frames[obj].name), dtype=np.int64)
            shapes = [model.shapes[i] for i in idx]
            poses = scenes.shape_poses[batch.config[rows]][:, idx]
            dims = scenes.shape_dims[batch.config[rows]][:, idx]
            d = jax.vmap(lambda P, D, q, s=shapes: distance_to_shapes(P, D, s, q[None])[0])(poses, dims, p[rows])
            out = out.at[rows].set(d)
        return out[:, None]


BUILTINS: tuple[type[MeasurementModel], ...] = (ImagePoint, Point3D, Distance, Angle, Range, PointToSurface)
