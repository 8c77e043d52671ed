"""Bundle Adjustment in the Large (BAL) problems (Agarwal, Snavely, Seitz & Szeliski, 2010).

A BAL file (https://grail.cs.washington.edu/projects/bal/) holds, as whitespace-separated text:

    <cameras> <points> <observations>
    <camera> <point> <x> <y>                  one line per observation
    <9 numbers per camera>                     R (rotation vector), t, f, k1, k2
    <3 numbers per point>                      X, Y, Z

A camera maps a world point X to P = R X + t, p = −P / P_z, and the pixel
f · (1 + k1 ‖p‖² + k2 ‖p‖⁴) · p (the image centre is the origin; the file's own convention).
:func:`read_bal` reads a file with located errors; :func:`bal_residual` is the reprojection
error in JAX (:func:`mbcal.structured.bal_structure` gives the block structure the
Schur-complement solver uses: each point is a block, each camera a group of shared unknowns).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from mbcal._jax import jnp
from mbcal.errors import MbcalError

__all__ = ["BalProblem", "read_bal", "bal_residual", "BalFileError"]

Array = Any


class BalFileError(MbcalError):
    """A BAL file that cannot be read (the message is ``file:line:col: what``)."""


@dataclass(frozen=True)
class BalProblem:
    """A bundle-adjustment problem.

    Attributes
    ----------
    cameras : (C, 9) rotation vector, translation, f, k1, k2
    points : (N, 3)
    camera_index, point_index : (M,) int
    observed : (M, 2) pixels
    """

    cameras: np.ndarray
    points: np.ndarray
    camera_index: np.ndarray
    point_index: np.ndarray
    observed: np.ndarray

    @property
    def x0(self) -> np.ndarray:
        """The unknowns from the file: every camera's 9 numbers, then every point's 3."""
        return np.concatenate([self.cameras.ravel(), self.points.ravel()])

    @property
    def n_cameras(self) -> int:
        return len(self.cameras)

    @property
    def n_points(self) -> int:
        return len(self.points)

    def split(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        c = 9 * self.n_cameras
        return x[:c].reshape(-1, 9), x[c:].reshape(-1, 3)


def _tokens(text: str):
    """Yield (token, line, column) of every whitespace-separated token (1-based)."""
    for lineno, line in enumerate(text.splitlines(), start=1):
        col = 0
        for part in line.split():
            col = line.index(part, col)
            yield part, lineno, col + 1
            col += len(part)


def read_bal(path: str | Path) -> BalProblem:
    """Read a BAL text file; a malformed file raises :class:`BalFileError` located at the token."""
    path = Path(path)
    try:
        text = path.read_text(encoding="ascii")
    except (OSError, UnicodeDecodeError) as e:
        raise BalFileError(f"{path}: cannot read: {e}") from None
    tokens = _tokens(text)
    last = [1, 1]

    def take(kind: type, what: str):
        try:
            tok, line, col = next(tokens)
        except StopIteration:
            raise BalFileError(f"{path}:{last[0]}:{last[1]}: the file ends where {what} was expected") from None
        last[:] = [line, col + len(tok)]  # where the file ends, if it ends after this token
        try:
            value = kind(tok)
        except ValueError:
            word = "an integer" if kind is int else "a number"
            raise BalFileError(f"{path}:{line}:{col}: expected {word} ({what}), found '{tok}'") from None
        if kind is float and not np.isfinite(value):
            raise BalFileError(f"{path}:{line}:{col}: {what} is not finite ('{tok}')")
        return value, line, col

    counts = []
    for what in ("the number of cameras", "the number of points", "the number of observations"):
        v, line, col = take(int, what)
        if v < 0:
            raise BalFileError(f"{path}:{line}:{col}: {what} must not be negative, found {v}")
        counts.append(v)
    n_cam, n_pt, n_obs = counts
    cam = np.zeros(n_obs, dtype=np.int64)
    pt = np.zeros(n_obs, dtype=np.int64)
    obs = np.zeros((n_obs, 2))
    for i in range(n_obs):
        c, line, col = take(int, f"the camera of observation {i + 1}")
        if not 0 <= c < n_cam:
            raise BalFileError(f"{path}:{line}:{col}: camera {c} is not one of the {n_cam} cameras (0 … {n_cam - 1})")
        p, line, col = take(int, f"the point of observation {i + 1}")
        if not 0 <= p < n_pt:
            raise BalFileError(f"{path}:{line}:{col}: point {p} is not one of the {n_pt} points (0 … {n_pt - 1})")
        cam[i], pt[i] = c, p
        obs[i, 0] = take(float, f"x of observation {i + 1}")[0]
        obs[i, 1] = take(float, f"y of observation {i + 1}")[0]
    cameras = np.array([take(float, f"parameter {k % 9 + 1} of camera {k // 9}")[0] for k in range(9 * n_cam)])
    points = np.array([take(float, f"coordinate {k % 3 + 1} of point {k // 3}")[0] for k in range(3 * n_pt)])
    extra = next(tokens, None)
    if extra is not None:
        raise BalFileError(f"{path}:{extra[1]}:{extra[2]}: unexpected '{extra[0]}' after the last point")
    return BalProblem(cameras.reshape(n_cam, 9), points.reshape(n_pt, 3), cam, pt, obs)


def _rotate(w: Array, X: Array) -> Array:
    """Rodrigues' rotation of points X (M, 3) by rotation vectors w (M, 3), smooth at w = 0."""
    theta2 = jnp.sum(w * w, axis=1, keepdims=True)
    small = theta2 < 1e-20
    theta = jnp.sqrt(jnp.where(small, 1.0, theta2))
    # sin θ / θ and (1 − cos θ) / θ² with their series where θ is tiny (keeps derivatives finite).
    a = jnp.where(small, 1.0 - theta2 / 6.0, jnp.sin(theta) / theta)
    b = jnp.where(small, 0.5 - theta2 / 24.0, (1.0 - jnp.cos(theta)) / jnp.where(small, 1.0, theta2))
    cross = jnp.cross(w, X)
    return X + a * cross + b * jnp.cross(w, cross)


def bal_residual(x: Array, camera_index: Array, point_index: Array, observed: Array, n_cameras: int) -> Array:
    """(2M,) reprojection errors in pixels, x = every camera's 9 numbers then every point's 3."""
    cams = jnp.reshape(x[: 9 * n_cameras], (-1, 9))[camera_index]
    pts = jnp.reshape(x[9 * n_cameras :], (-1, 3))[point_index]
    P = _rotate(cams[:, :3], pts) + cams[:, 3:6]
    p = -P[:, :2] / P[:, 2:3]
    r2 = jnp.sum(p * p, axis=1, keepdims=True)
    scale = cams[:, 6:7] * (1.0 + cams[:, 7:8] * r2 + cams[:, 8:9] * r2 * r2)
    return jnp.reshape(scale * p - observed, (-1,))
