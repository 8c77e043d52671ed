"""The pinhole camera with OpenCV's axes and distortion model.

A point (X, Y, Z) in the camera frame (x right, y down, z forward) maps to normalised
coordinates x = X/Z, y = Y/Z, then through OpenCV's distortion (k1, k2, p1, p2, k3 in that
order)::

    r² = x² + y²
    x' = x (1 + k1 r² + k2 r⁴ + k3 r⁶) + 2 p1 x y + p2 (r² + 2x²)
    y' = y (1 + k1 r² + k2 r⁴ + k3 r⁶) + p1 (r² + 2y²) + 2 p2 x y

and to pixels u = fx x' + skew y' + cx, v = fy y' + cy, with pixel (0, 0) the centre of the
top-left pixel (OpenCV's convention).
"""

from __future__ import annotations

from typing import Any

from mbcal._jax import jnp

Array = Any

__all__ = ["project_camera_points", "distort"]


def distort(xy: Array, distortion: Array, xp: Any = jnp) -> Array:
    """Apply OpenCV's radial-tangential distortion to normalised coordinates (..., 2).

    ``xp`` is the array module (``jax.numpy`` by default; ``numpy`` for plain arrays).
    """
    k1, k2, p1, p2, k3 = (distortion[..., i] for i in range(5))
    x, y = xy[..., 0], xy[..., 1]
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    return xp.stack([xd, yd], axis=-1)


def project_camera_points(p_camera: Array, intrinsics: Array, distortion: Array, xp: Any = jnp) -> Array:
    """Pixels (..., 2) of points (..., 3) given in the camera frame.

    ``intrinsics`` is (..., 5) = fx, fy, cx, cy, skew; ``distortion`` (..., 5) = k1, k2, p1, p2, k3.
    Points at or behind the camera give non-finite or meaningless pixels: callers check depth.
    """
    z = p_camera[..., 2]
    xy = p_camera[..., :2] / z[..., None]
    d = distort(xy, distortion, xp)
    fx, fy, cx, cy, skew = (intrinsics[..., i] for i in range(5))
    u = fx * d[..., 0] + skew * d[..., 1] + cx
    v = fy * d[..., 1] + cy
    return xp.stack([u, v], axis=-1)
