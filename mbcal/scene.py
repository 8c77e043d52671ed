"""The scene E_v = modeler(D, X): world poses, points, sensors and shapes as arrays.

A :class:`Scene` is a JAX pytree: its arrays are leaves (differentiable, batchable with
``vmap`` — a batch of scenes, one per configuration, has a leading axis on every array) and
its model is static metadata.  Names are looked up through the model.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from mbcal._jax import jax, jnp
from mbcal.geometry.camera import project_camera_points
from mbcal.geometry.shapes import shape_mesh
from mbcal.language.model import Model

Array = Any

__all__ = ["Scene", "CameraView"]


@dataclass(frozen=True)
class CameraView:
    """One camera of a scene: pose, intrinsics, distortion and image size."""

    name: str
    T_world_camera: Array  # (4, 4)
    intrinsics: Array  # (5,) fx, fy, cx, cy, skew
    distortion: Array  # (5,) k1, k2, p1, p2, k3
    width: int
    height: int

    @property
    def center(self) -> Array:
        """The optical centre in world coordinates."""
        return self.T_world_camera[:3, 3]

    def to_camera(self, p_world: Array) -> Array:
        """World points (..., 3) in the camera frame."""
        R, t = self.T_world_camera[:3, :3], self.T_world_camera[:3, 3]
        return (p_world - t) @ R

    def project(self, p_world: Array) -> Array:
        """Pixels (..., 2) of world points (..., 3).

        The pinhole projection of any point: one behind the camera (z ≤ 0 in :meth:`to_camera`'s
        frame) gets a pixel too, mirrored through the optical centre, as from OpenCV's
        ``projectPoints``, and a differentiable one.  Whether a point can be seen at all is
        ``to_camera(p)[..., 2] > 0`` and inside the image; a calibration leaves out, and reports,
        measurements that cannot be made (``Problem.visible``)."""
        return project_camera_points(self.to_camera(p_world), self.intrinsics, self.distortion)

    @property
    def K(self) -> np.ndarray:
        """OpenCV's 3×3 camera matrix."""
        fx, fy, cx, cy, skew = np.asarray(self.intrinsics, dtype=float)
        return np.array([[fx, skew, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


@dataclass(frozen=True)
class Scene:
    """World-frame geometry of a model for one parameter vector.

    Attributes
    ----------
    model : Model
        The description the scene was built from (static).
    frame_poses : (F, 4, 4) float
        ``T_world_frame`` of every frame, in ``model.frames`` order.
    points : (P, 3) float
        World position of every named point, in ``model.points`` order.
    camera_intrinsics : (K, 5) float
        fx, fy, cx, cy, skew of every camera.
    camera_distortion : (K, 5) float
        k1, k2, p1, p2, k3 of every camera.
    shape_poses : (S, 4, 4) float
        ``T_world_shape`` of every shape.
    shape_dims : (S, 3) float
        The shape's dimensions (see :mod:`mbcal.geometry.shapes`), padded with zeros.
    """

    model: Model
    frame_poses: Array
    points: Array
    camera_intrinsics: Array
    camera_distortion: Array
    shape_poses: Array
    shape_dims: Array

    # ---- look-ups ------------------------------------------------------------------------------

    def point(self, name: str) -> Array:
        """World position (3,) of a named point (``room.lever.tip``)."""
        return self.points[..., self.model.point_index(name), :]

    def frame(self, name: str) -> Array:
        """``T_world_frame`` (4, 4) of a frame; ``world`` is the identity."""
        i = self.model.frame_index(name)
        if i < 0:
            return jnp.eye(4)
        return self.frame_poses[..., i, :, :]

    def camera(self, name: str) -> CameraView:
        """A camera's pose, intrinsics and distortion."""
        i = self.model.camera_index(name)
        info = self.model.cameras[i]
        return CameraView(
            name,
            self.frame_poses[..., info.frame, :, :],
            self.camera_intrinsics[..., i, :],
            self.camera_distortion[..., i, :],
            info.width,
            info.height,
        )

    def range_rays(self, name: str) -> tuple[Array, Array]:
        """World origins (n, 3) and unit directions (n, 3) of a range sensor's rays."""
        info = self.model.ranges[self.model.range_index(name)]
        T = self.frame_poses[..., info.frame, :, :]
        dirs = jnp.asarray(info.directions) @ jnp.swapaxes(T[..., :3, :3], -1, -2)
        origins = jnp.broadcast_to(T[..., None, :3, 3], dirs.shape)
        return origins, dirs

    def values(self) -> dict[str, np.ndarray]:
        """Every named point's world position as numpy, by name."""
        pts = np.asarray(self.points)
        return {p.name: pts[..., i, :] for i, p in enumerate(self.model.points)}

    # ---- export ----------------------------------------------------------------------------------

    def to_trimesh(self, *, points: bool = False, point_radius: float = 0.01, plane_size: float = 10.0):
        """The scene's shapes as a :class:`trimesh.Scene` (world coordinates, metres).

        Parameters
        ----------
        points : bool
            Add a small sphere at every named point.
        point_radius : float
            Radius of those spheres (m).
        plane_size : float
            Side (m) of the square that stands for an infinite ``plane()``.
        """
        import trimesh  # optional at import time: loaded when a scene is exported

        if np.ndim(self.points) != 2:
            raise ValueError("to_trimesh() needs a single scene, not a batch (index the configuration first)")
        scene = trimesh.Scene()
        poses = np.asarray(self.shape_poses, dtype=float)
        dims = np.asarray(self.shape_dims, dtype=float)
        for i, shape in enumerate(self.model.shapes):
            mesh = shape_mesh(shape.kind, dims[i], shape.mesh, plane_size=plane_size)
            scene.add_geometry(mesh, node_name=shape.name, geom_name=shape.name, transform=poses[i])
        if points:
            pts = np.asarray(self.points, dtype=float)
            for i, p in enumerate(self.model.points):
                marker = trimesh.creation.icosphere(subdivisions=1, radius=point_radius)
                T = np.eye(4)
                T[:3, 3] = pts[i]
                scene.add_geometry(marker, node_name=f"point:{p.name}", geom_name=f"point:{p.name}", transform=T)
        return scene


jax.tree_util.register_dataclass(
    Scene,
    data_fields=["frame_poses", "points", "camera_intrinsics", "camera_distortion", "shape_poses", "shape_dims"],
    meta_fields=["model"],
)
