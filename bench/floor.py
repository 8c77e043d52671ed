"""Hand-written JAX residuals of the seed's two problems, in the style of the hand-written floor of
../shared/PERFORMANCE-NOTES.md (issue 16): the room's pose and the arm's joint offsets written out
directly, with every constant read once from the model — the points, the cameras' poses and
intrinsics, the arm's link offsets and joint axes, each attitude's joint readings — and the same
whitening as mbcal's problem.  ``bench/run.py`` runs the same minimal Marquardt loop on these and
on mbcal's generic residual, so the floor is measured in the same run instead of quoted.

Each builder checks its function against mbcal's residual at a few points and refuses to return
one that differs (a floor of a different problem would mean nothing).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from mbcal._jax import jax, jnp
from mbcal.problem import Problem

Residual = Callable[..., jax.Array]


def _only_image_points(problem: Problem):
    if len(problem.groups) != 1 or problem.groups[0].model.kind != "image_point" or len(problem.prior_index):
        raise ValueError("the hand-written residuals cover image points only, without priors")
    group = problem.groups[0]
    if not group.diagonal:
        raise ValueError("the hand-written residuals take a diagonal covariance")
    return group


def _project(K: np.ndarray, pc: jax.Array) -> jax.Array:
    """Pinhole projection (no distortion: both seed models have none) of camera-frame points (m, 3)."""
    return jnp.stack([K[:, 0] * pc[:, 0] / pc[:, 2] + K[:, 2], K[:, 1] * pc[:, 1] / pc[:, 2] + K[:, 3]], axis=-1)


def _rotation(axis: np.ndarray, angle: jax.Array) -> jax.Array:
    """Rotations (C, 3, 3) about a constant unit axis by angles (C,) (Rodrigues)."""
    a = np.asarray(axis, dtype=float)
    cross = np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])
    c, s = jnp.cos(angle)[:, None, None], jnp.sin(angle)[:, None, None]
    return np.eye(3) * c + cross * s + np.outer(a, a) * (1.0 - c)


def _rpy(roll: jax.Array, pitch: jax.Array, yaw: jax.Array) -> jax.Array:
    cr, sr, cp, sp, cy, sy = (jnp.cos(roll), jnp.sin(roll), jnp.cos(pitch), jnp.sin(pitch), jnp.cos(yaw), jnp.sin(yaw))
    return jnp.array(
        [
            [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
            [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
            [-sp, cp * sr, cp * cr],
        ]
    )


def _checked(problem: Problem, fun: Residual, name: str) -> Residual:
    rng = np.random.default_rng(0)
    lo, hi = problem.params.lower, problem.params.upper
    y, known = problem.y, problem.params.known
    for _ in range(3):
        x = np.where(np.isfinite(lo) & np.isfinite(hi), rng.uniform(lo, hi), problem.params.x0)
        ours, theirs = np.asarray(fun(x, y, known)), np.asarray(problem.residual_function(x, y, known))
        if ours.shape != theirs.shape or not np.allclose(ours, theirs, rtol=1e-9, atol=1e-9):
            raise AssertionError(f"the hand-written {name} residual differs from mbcal's")
    return fun


def room(problem: Problem) -> Residual:
    """r(x) of the room's pose (teleexistence.mdl, x = room.x, y, z, roll, pitch, yaw): the 24
    points moved by the pose, seen by the two fixed cameras."""
    group = _only_image_points(problem)
    model = problem.model
    scene = problem.whole_scenes(problem.params.x0)  # room pose 0: the points where the room's frame is the world's
    names = problem.params.names
    order = np.array([names.index(f"room.{k}") for k in ("x", "y", "z", "roll", "pitch", "yaw")])
    if not np.allclose(problem.params.x0[order], 0.0):
        raise ValueError("the room's nominal pose must be the identity")
    cams, pts = group.batch.refs["camera"], group.batch.refs["point"]
    P0 = np.asarray(scene.points)[0][pts]  # (m, 3)
    Tc = np.asarray(scene.frame_poses)[0][[model.cameras[c].frame for c in cams]]  # (m, 4, 4)
    K = np.asarray(scene.camera_intrinsics)[0][cams]
    w = np.asarray(group.whiten).reshape(-1)
    m = problem.size

    def fun(x, y, known):
        p = x[order]
        pw = P0 @ _rpy(p[3], p[4], p[5]).T + p[:3]
        pc = jnp.sum(Tc[:, :3, :3] * (pw - Tc[:, :3, 3])[:, :, None], axis=1)  # Rᵀ (p − t)
        return (_project(K, pc).reshape(-1) - y[:m]) * w

    return _checked(problem, fun, "room")


def arm(problem: Problem) -> Residual:
    """r(x) of the arm's seven joint offsets (arm7.mdl): in each attitude the chain from the
    shoulder to the hand with the known encoder readings plus the offsets, the hand's points
    seen by the stereo head (whose pose each attitude's neck readings fix)."""
    group = _only_image_points(problem)
    model = problem.model
    names = problem.params.names
    chain = [i for i, f in enumerate(model.frames) if f.name.startswith("base.torso.shoulder_flexion")]
    joints = [model.frames[i].joint for i in chain]
    offsets = np.array([names.index(j.offset.name) for j in joints])  # type: ignore[union-attr]
    scene = problem.whole_scenes(problem.params.x0)
    X = problem.params.X(problem.params.x0)  # (C, n_params): every attitude's readings
    q = np.stack([X[:, j.q.index] for j in joints], axis=1)  # type: ignore[union-attr]  # (C, 7)
    parent = np.asarray(scene.frame_poses)[:, model.frames[chain[0]].parent]  # torso, per attitude
    poses = [np.eye(4) if model.frames[i].pose is None else np.asarray(model.frames[i].pose.value) for i in chain]
    axes = [np.asarray(j.axis.value, dtype=float) for j in joints]  # type: ignore[union-attr]
    hand = chain[-1]
    local = np.array([np.asarray(p.position.value, dtype=float) for p in model.points])
    if any(p.frame != hand for p in model.points):
        raise ValueError("the arm's points must all be on the hand")
    cfg, cams, pts = group.batch.config, group.batch.refs["camera"], group.batch.refs["point"]
    Tc = np.asarray(scene.frame_poses)[cfg, [model.cameras[c].frame for c in cams]]  # (m, 4, 4)
    K = np.asarray(scene.camera_intrinsics)[cfg, cams]
    w = np.asarray(group.whiten).reshape(-1)
    m = problem.size

    # Tried, slower under jacfwd and vmap on XLA:CPU: the 3 × 3 products as broadcasts and sums
    # (3×), every camera and point on a grid picked at the end (1.6×), the joints' sines and
    # cosines by angle addition (1.05×).
    def fun(x, y, known):
        R, t = jnp.asarray(parent[:, :3, :3]), jnp.asarray(parent[:, :3, 3])
        for k, (pose, axis) in enumerate(zip(poses, axes)):
            t = t + jnp.einsum("cij,j->ci", R, pose[:3, 3])
            R = jnp.einsum("cij,jk->cik", R, pose[:3, :3])
            R = jnp.einsum("cij,cjk->cik", R, _rotation(axis, q[:, k] + x[offsets[k]]))
        pw = jnp.einsum("cij,pj->cpi", R, local) + t[:, None, :]  # (C, P, 3)
        p = pw[cfg, pts]
        pc = jnp.sum(Tc[:, :3, :3] * (p - Tc[:, :3, 3])[:, :, None], axis=1)
        return (_project(K, pc).reshape(-1) - y[:m]) * w

    return _checked(problem, fun, "arm")


BUILDERS = {"room": room, "arm": arm}
