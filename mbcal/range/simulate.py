"""Simulated depth images: what a model's depth camera would measure, rendered by pyrender.

The scene's shapes are tessellated finely (``sections`` around round shapes: 256 by default,
so a 3.5 cm cylinder deviates from its mesh by less than 3 µm) and rendered with pyrender's
depth pass (no multisampling: no mixed depths at edges).  Noise is added along the optical
axis, as structured-light and stereo cameras show it: σ_z = ``noise`` + ``noise_rel`` · z.
"""

from __future__ import annotations

import os
from collections.abc import Mapping

import numpy as np

from mbcal.errors import RenderError
from mbcal.geometry.shapes import shape_mesh
from mbcal.language.model import Model
from mbcal.modeling import Needs, modeler
from mbcal.range.scans import depth_camera

__all__ = ["render_depth", "add_depth_noise"]

_CV_TO_GL = np.diag([1.0, -1.0, -1.0, 1.0])  # OpenCV camera axes → OpenGL's


def render_depth(
    model: Model,
    values: Mapping[str, float] | None = None,
    sensor: str | None = None,
    *,
    sections: int = 256,
    shapes: Mapping[int, object] | None = None,
) -> np.ndarray:
    """Depth (H, W) in metres along the depth camera's optical axis, NaN where nothing is hit
    (or beyond the valid range).  ``shapes`` replaces the mesh of shape index → a trimesh in the
    shape's frame (a "real" scene that differs from the model)."""
    if "PYOPENGL_PLATFORM" not in os.environ:
        os.environ["PYOPENGL_PLATFORM"] = "egl"
    try:
        import pyrender  # optional: needs EGL/OSMesa, loaded when a depth image is rendered
    except Exception as err:
        raise RenderError(f"pyrender cannot start ({type(err).__name__}: {err})") from None
    info = depth_camera(model, sensor)
    assert info.intrinsics is not None
    scene = modeler(model, dict(values or {}), Needs.everything())
    poses = np.asarray(scene.shape_poses, dtype=float)
    dims = np.asarray(scene.shape_dims, dtype=float)
    pr = pyrender.Scene()
    seg = {}
    for i, shape in enumerate(model.shapes):
        mesh = (shapes or {}).get(i)
        if mesh is None:
            mesh = shape_mesh(shape.kind, dims[i], shape.mesh, sections=sections, plane_size=20.0)
        node = pr.add(pyrender.Mesh.from_trimesh(mesh, smooth=False), pose=poses[i])
        seg[node] = np.array([255, 255, 255], dtype=np.uint8)
    fx, fy, cx, cy = info.intrinsics
    cam = pyrender.IntrinsicsCamera(fx=fx, fy=fy, cx=cx + 0.5, cy=cy + 0.5, znear=0.05, zfar=50.0)
    T = np.asarray(scene.frame_poses[info.frame], dtype=float)
    pr.add(cam, pose=T @ _CV_TO_GL)
    try:
        r = pyrender.OffscreenRenderer(info.width, info.height)
    except Exception as err:
        raise RenderError(f"cannot open an off-screen OpenGL context ({type(err).__name__}: {err})") from None
    try:
        # The segmentation pass renders without multisampling: the depth of each pixel is taken at
        # its centre (a multisampled depth pass reads sample 0, off the centre by (-1/8, 3/8) px).
        _, depth = r.render(pr, flags=pyrender.RenderFlags.SEG, seg_node_map=seg)
    finally:
        r.delete()
    depth = np.asarray(depth, dtype=float)
    valid = (depth > 0) & (depth >= info.min_range) & (depth <= info.max_range)
    return np.where(valid, depth, np.nan)


def add_depth_noise(depth: np.ndarray, noise: float = 1e-3, noise_rel: float = 0.0, seed: int = 0) -> np.ndarray:
    """Gaussian noise along the optical axis, σ_z = noise + noise_rel · z (m)."""
    rng = np.random.default_rng(seed)
    return depth + rng.standard_normal(depth.shape) * (noise + noise_rel * np.nan_to_num(depth))
