"""Camera calibration from a planar target: intrinsics, distortion and the target's pose per view.

The workflow is mbcal's general calibration with a good start.  Before the Marquardt refinement,
Zhang's closed-form method (Z. Zhang, "A flexible new technique for camera calibration", IEEE
PAMI 22(11), 2000, section 3.1) gives initial values:

1. a homography from the target plane to the image in every view (normalised DLT);
2. the camera matrix from the homographies (two constraints per view on B = K⁻ᵀK⁻¹; with the
   skew fixed at 0 when it is not estimated);
3. the target's pose in every view from K⁻¹H.

These initialise the model's parameters: camera intrinsics written as plain parameters
(``fx = cam.fx``), target frames posed by ``pose(x, y, z, roll, pitch, yaw)`` of
per-configuration parameters, and the pose of further cameras relative to the first (a stereo
rig) from the views both see.  Distortion starts at zero.  Then every unknown is refined
together, and the report gives what OpenCV users expect: RMS reprojection error, RMS per view,
σ of every intrinsic (scaled by the residual variance, as OpenCV does).
"""

from __future__ import annotations

import math
import weakref
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from mbcal._jax import release_memory
from mbcal.api import calibrate, simulate
from mbcal.errors import MbcalError
from mbcal.geometry import transforms as geo
from mbcal.geometry.camera import distort
from mbcal.geometry.transforms import rpy_from_matrix
from mbcal.language import ir
from mbcal.language.model import Model
from mbcal.measurements.sets import MeasurementSet, measurements_from_records
from mbcal.modeling import Needs, modeler, parameter_vector
from mbcal.outputs import finite_or_null, make_output_folder
from mbcal.params import ParameterSet
from mbcal.render.views import Layer, draw_overlay, load_image, save_png
from mbcal.solver import SolverConfig
from mbcal.text import fmt, table

__all__ = [
    "homography",
    "homographies",
    "poses_from_homographies",
    "intrinsics_from_homographies",
    "pose_from_homography",
    "rpy_from_matrix",
    "initial_values",
    "zhang_start",
    "calibrate_cameras",
    "CameraCalibration",
    "plan_views",
    "simulate_views",
    "synthesize_images",
    "INTRINSIC_NAMES",
    "DISTORTION_NAMES",
]

INTRINSIC_NAMES = ("fx", "fy", "cx", "cy", "skew")
AUTO_RESTARTS = 4  # starts of calibrate_cameras(restarts=None) when Zhang's start alone is not enough
CLOSED_FORM_LAMBDA = 1e-6
"""Marquardt's initial λ (relative to the scaled diagonal of JᵀJ) when the solve starts from
Zhang's closed-form solution alone: a start believed close to the minimum gets a small damping
(Madsen, Nielsen & Tingleff, *Methods for non-linear least squares problems*, 2004, §3.2:
τ = 10⁻⁶ then, 10⁻³ otherwise).  The default 10⁻³ damped the weak distortion directions for
the first iterations: 13 views 14 → 10 iterations, 100 views 12 → 7 (issue 16)."""
DISTORTION_NAMES = ("k1", "k2", "p1", "p2", "k3")


# ---- Zhang's closed form ------------------------------------------------------------------------


def _normalizers(p: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Hartley's similarity (V, 3, 3) per view of padded points (V, L, 2) with a mask (V, L):
    centroid to the origin, mean distance √2."""
    count = np.maximum(mask.sum(axis=1), 1)
    mean = np.sum(p * mask[..., None], axis=1) / count[:, None]
    spread = np.sum(np.linalg.norm(p - mean[:, None, :], axis=2) * mask, axis=1) / count
    scale = math.sqrt(2.0) / np.maximum(spread, 1e-12)
    T = np.zeros((len(p), 3, 3))
    T[:, 0, 0] = T[:, 1, 1] = scale
    T[:, :2, 2] = -scale[:, None] * mean
    T[:, 2, 2] = 1.0
    return T


def homographies(src: np.ndarray, dst: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    """H (V, 3, 3) with dst ~ H·src for V views at once (normalised DLT, Hartley's scaling).

    ``src``, ``dst``: (V, L, 2) point sets padded to a common length L; ``mask`` (V, L) marks the
    real points (default: all).  Padded points give zero rows of the DLT system, which change
    neither its singular values nor its null vector: every view gets exactly the homography of its
    own points, all from one stacked SVD."""
    src, dst = np.asarray(src, float), np.asarray(dst, float)
    mask = np.ones(src.shape[:2], dtype=bool) if mask is None else np.asarray(mask, dtype=bool)
    if np.any(mask.sum(axis=1) < 4):
        raise MbcalError("a homography needs at least 4 points")
    Ts, Td = _normalizers(src, mask), _normalizers(dst, mask)
    s = np.einsum("vij,vlj->vli", Ts[:, :2, :2], src) + Ts[:, None, :2, 2]
    d = np.einsum("vij,vlj->vli", Td[:, :2, :2], dst) + Td[:, None, :2, 2]
    V, L = mask.shape
    x, y, u, v = s[..., 0], s[..., 1], d[..., 0], d[..., 1]
    one, zero = np.ones_like(x), np.zeros_like(x)
    rows = np.empty((V, L, 2, 9))
    rows[:, :, 0] = np.stack([-x, -y, -one, zero, zero, zero, u * x, u * y, u], axis=-1)
    rows[:, :, 1] = np.stack([zero, zero, zero, -x, -y, -one, v * x, v * y, v], axis=-1)
    rows *= mask[:, :, None, None]
    A = rows.reshape(V, 2 * L, 9)
    if 2 * L < 9:  # 4 points (8 rows): pad to 9 rows so that the thin SVD holds the null vector
        A = np.concatenate([A, np.zeros((V, 9 - 2 * L, 9))], axis=1)
    # All of V but not the 2L × 2L U (issue 15): the thin SVD of each (2L, 9) system.
    _, _, Vt = np.linalg.svd(A, full_matrices=False)
    Hn = Vt[:, -1].reshape(V, 3, 3)
    H = np.linalg.solve(Td, Hn) @ Ts
    return H / H[:, 2:3, 2:3]


SPAN_TOLERANCE = 1e-9
"""A view's points span their plane when the smaller principal axis of their scatter is more than
this fraction of the larger (points on a target are exact, their pixels measured to ~10⁻³ of the
image): below, they lie on a line and give no homography."""


def _spans_plane(p: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Per view (V,) of padded points (V, L, 2): whether the real points span the plane (not all
    on one line, not all at one place); a non-finite point never does."""
    count = np.maximum(mask.sum(axis=1), 1)
    q = np.where(mask[..., None], p, 0.0)
    mean = q.sum(axis=1) / count[:, None]
    d = np.where(mask[..., None], q - mean[:, None, :], 0.0)
    scatter = np.einsum("vli,vlj->vij", d, d) / count[:, None, None]
    with np.errstate(invalid="ignore", over="ignore"):
        small, large = np.linalg.eigvalsh(np.nan_to_num(scatter, nan=0.0, posinf=0.0, neginf=0.0)).T
        spans = small > SPAN_TOLERANCE**2 * large
    return spans & np.all(np.isfinite(q), axis=(1, 2))


def homography(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """H (3, 3) with dst ~ H·src for (n ≥ 4, 2) point sets (normalised DLT, Hartley's scaling)."""
    src, dst = np.asarray(src, float), np.asarray(dst, float)
    if len(src) < 4:
        raise MbcalError("a homography needs at least 4 points")
    return homographies(src[None], dst[None])[0]


def _v(H: np.ndarray, i: int, j: int) -> np.ndarray:
    """Zhang's v_ij (…, 6) of homographies (…, 3, 3): h_iᵀ B h_j = v_ijᵀ b."""
    hi, hj = H[..., :, i], H[..., :, j]  # columns i and j
    return np.stack(
        [
            hi[..., 0] * hj[..., 0],
            hi[..., 0] * hj[..., 1] + hi[..., 1] * hj[..., 0],
            hi[..., 1] * hj[..., 1],
            hi[..., 2] * hj[..., 0] + hi[..., 0] * hj[..., 2],
            hi[..., 2] * hj[..., 1] + hi[..., 1] * hj[..., 2],
            hi[..., 2] * hj[..., 2],
        ],
        axis=-1,
    )


def intrinsics_from_homographies(Hs: Sequence[np.ndarray] | np.ndarray, *, skew: bool = True) -> np.ndarray:
    """The camera matrix K from ≥ 3 plane homographies (≥ 2 with ``skew=False``)."""
    H = np.asarray(Hs, dtype=float).reshape(-1, 3, 3)
    if not np.all(np.isfinite(H)):
        raise MbcalError("the camera matrix needs finite homographies")
    rows = np.stack([_v(H, 0, 1), _v(H, 0, 0) - _v(H, 1, 1)], axis=1).reshape(-1, 6)
    if not skew:
        rows = np.vstack([rows, [0, 1, 0, 0, 0, 0]])  # B12 = 0  ⇔  γ = 0
    if len(rows) < 5:
        raise MbcalError(f"{len(H)} views are too few to initialise the camera matrix (3 needed, 2 without skew)")
    _, _, Vt = np.linalg.svd(rows, full_matrices=len(rows) < 6)  # V only: not the (2V)² U
    b = Vt[-1]
    if b[0] < 0:
        b = -b
    B11, B12, B22, B13, B23, B33 = b
    den = B11 * B22 - B12 * B12
    v0 = (B12 * B13 - B11 * B23) / den
    lam = B33 - (B13 * B13 + v0 * (B12 * B13 - B11 * B23)) / B11
    alpha = math.sqrt(abs(lam / B11))
    beta = math.sqrt(abs(lam * B11 / den))
    gamma = -B12 * alpha * alpha * beta / lam
    u0 = gamma * v0 / beta - B13 * alpha * alpha / lam
    return np.array([[alpha, gamma, u0], [0.0, beta, v0], [0.0, 0.0, 1.0]])


def poses_from_homographies(K: np.ndarray, Hs: np.ndarray) -> np.ndarray:
    """T (V, 4, 4): the pose of a plane z = 0 in the camera frame from each of V homographies."""
    A = np.linalg.solve(K, np.asarray(Hs, dtype=float).reshape(-1, 3, 3))
    lam = 1.0 / np.linalg.norm(A[:, :, 0], axis=1)
    lam = np.where(lam * A[:, 2, 2] < 0, -lam, lam)  # the target is in front of the camera
    r1, r2, t = lam[:, None] * A[:, :, 0], lam[:, None] * A[:, :, 1], lam[:, None] * A[:, :, 2]
    R = np.stack([r1, r2, np.cross(r1, r2)], axis=2)
    U, _, Vt = np.linalg.svd(R)  # the nearest rotation
    flip = np.linalg.det(U @ Vt) < 0
    U[flip, :, 2] *= -1
    T = np.zeros((len(A), 4, 4))
    T[:, :3, :3] = U @ Vt
    T[:, :3, 3] = t
    T[:, 3, 3] = 1.0
    return T


def pose_from_homography(K: np.ndarray, H: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """R (3, 3) and t (3,) of a plane z = 0 in the camera frame from its homography."""
    T = poses_from_homographies(K, H[None])[0]
    return T[:3, :3], T[:3, 3]


def _T(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T


# ---- mapping onto the model's parameters -----------------------------------------------------------


def _param(node) -> str | None:
    return node.name if isinstance(node, ir.ParamRef) else None


def _pose_params(node) -> list[str] | None:
    """The six parameter names of a ``pose(x, y, z, roll, pitch, yaw)`` of plain parameters."""
    if not (isinstance(node, ir.Op) and node.op == "compose" and len(node.args) == 2):
        return None
    t, r = node.args
    if not (isinstance(t, ir.Op) and t.op == "translate" and isinstance(t.args[0], ir.Op) and t.args[0].op == "vec"):
        return None
    if not (isinstance(r, ir.Op) and r.op == "rpy"):
        return None
    names = [_param(a) for a in (*t.args[0].args, *r.args)]
    return [n for n in names if n] if all(names) else None


def _frame_world(model: Model, X: np.ndarray, frame: int) -> np.ndarray:
    if frame < 0:
        return np.eye(4)
    return np.asarray(modeler(model, X).frame_poses[frame], dtype=float)


def _set_pose(values: dict, names: list[str], T_local: np.ndarray, suffix: str = "") -> None:
    roll, pitch, yaw = rpy_from_matrix(T_local[:3, :3])
    for name, v in zip(names, (*T_local[:3, 3], roll, pitch, yaw)):
        values[name + suffix] = float(v)


def _average_pose(Ts: list[np.ndarray]) -> np.ndarray:
    """A mean rigid transform (chordal mean of the rotations, mean translation)."""
    R = sum(T[:3, :3] for T in Ts)
    U, _, Vt = np.linalg.svd(R)
    Rm = U @ Vt
    if np.linalg.det(Rm) < 0:
        Rm = U @ np.diag([1, 1, -1]) @ Vt
    return _T(Rm, np.mean([T[:3, 3] for T in Ts], axis=0))


def _rpy_many(R: np.ndarray) -> np.ndarray:
    """(V, 3) roll, pitch, yaw of rotations (V, 3, 3): :func:`rpy_from_matrix` for many at once."""
    pitch = np.arctan2(-R[:, 2, 0], np.hypot(R[:, 0, 0], R[:, 1, 0]))
    return np.stack([np.arctan2(R[:, 2, 1], R[:, 2, 2]), pitch, np.arctan2(R[:, 1, 0], R[:, 0, 0])], axis=1)


class _Nominal:
    """What Zhang's start reads of a model at its nominal values, once per model (issue 16: the
    modeler and a point-by-point evaluation were ~2 ms of a warm 13-view calibration): every
    frame's pose, and for the points asked for so far whether each lies on its frame's z = 0
    plane (its frame, else −1) and where (x, y in that frame)."""

    def __init__(self, model: Model):
        self.model = model
        self.X0 = model.nominal
        # every frame's pose (no points, cameras or shapes)
        self.frame_poses = np.asarray(modeler(model, self.X0, Needs(frames=None)).frame_poses, dtype=float)
        self.plane_frame = np.full(len(model.points), -1, dtype=np.int64)
        self.plane_xy = np.zeros((len(model.points), 2))
        self.done = np.zeros(len(model.points), dtype=bool)

    def planes(self, which: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(frame, xy) of the points ``which`` (model point indices)."""
        for j in np.unique(which[~self.done[which]]).tolist():
            p = self.model.points[j]
            if p.frame >= 0:
                local = np.asarray(ir.evaluate(p.position, self.X0, {}, np), dtype=float)
                if abs(local[2]) <= 1e-9:
                    self.plane_frame[j], self.plane_xy[j] = p.frame, local[:2]
            self.done[j] = True
        return self.plane_frame[which], self.plane_xy[which]


_NOMINALS: weakref.WeakKeyDictionary[Model, _Nominal] = weakref.WeakKeyDictionary()


def _nominal(model: Model) -> _Nominal:
    found = _NOMINALS.get(model)
    if found is None:
        found = _NOMINALS[model] = _Nominal(model)
    return found


class _PlanarPoints:
    """The image points of planar targets in a measurement set, as arrays: per measurement its
    camera, configuration and target frame, the point on the target plane (xy, from the point's
    position evaluated once per point) and the pixels; grouped by (camera, configuration, frame)
    in order of first appearance."""

    def __init__(self, model: Model, data: MeasurementSet):
        columns = data.columns()  # arrays, not a walk over thousands of measurements (issue 15)
        self.configs = columns.config_names
        col = columns.kinds.get("image_point")
        if col is None:
            key, self.xy, self.uv = np.zeros((0, 3), dtype=np.int64), np.zeros((0, 2)), np.zeros((0, 2))
        else:
            # each distinct point once: its target frame and its xy on the target's z = 0 plane
            point_names, point_code = col.refs["point"]
            which = np.array([model.point_index(name) for name in point_names], dtype=np.int64)
            frame, plane_xy = _nominal(model).planes(which)
            camera_names, camera_code = col.refs["camera"]
            camera = np.array([model.camera_index(c) for c in camera_names], dtype=np.int64)[camera_code]
            use = np.nonzero(col.has_value & (frame[point_code] >= 0))[0]
            key = np.stack([camera[use], col.config[use], frame[point_code[use]]], axis=1)
            self.xy = plane_xy[point_code[use]]
            self.uv = col.values[use]
        # one integer per (camera, configuration, frame): np.unique(axis=0) sorts rows far slower
        span = np.max(key, axis=0) + 1 if len(key) else np.ones(3, dtype=np.int64)
        packed = (key[:, 0] * span[1] + key[:, 1]) * span[2] + key[:, 2]
        _unique, first, inverse = np.unique(packed, return_index=True, return_inverse=True)
        order = np.argsort(first, kind="stable")  # groups in order of first appearance
        rank = np.empty(len(order), dtype=np.int64)
        rank[order] = np.arange(len(order))
        self.keys = key[first[order]]  # (K, 3): camera, configuration, frame
        self.group = rank[np.ravel(inverse)] if len(key) else np.zeros(0, dtype=np.int64)
        self.count = np.bincount(self.group, minlength=len(self.keys))

    def padded(self, groups: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Target-plane points, pixels (len(groups), L, 2) and the mask (len(groups), L) of some groups."""
        slot = np.full(len(self.keys), -1, dtype=np.int64)
        slot[groups] = np.arange(len(groups))
        rows = np.nonzero(slot[self.group] >= 0)[0]
        g = slot[self.group[rows]]
        order = np.argsort(g, kind="stable")
        rows, g = rows[order], g[order]
        start = np.concatenate([[0], np.cumsum(np.bincount(g, minlength=len(groups)))])
        within = np.arange(len(rows)) - start[g]
        L = int(self.count[groups].max())
        src, dst = np.zeros((len(groups), L, 2)), np.zeros((len(groups), L, 2))
        mask = np.zeros((len(groups), L), dtype=bool)
        src[g, within], dst[g, within], mask[g, within] = self.xy[rows], self.uv[rows], True
        return src, dst, mask


def initial_values(model: Model, data: MeasurementSet, unknown: Sequence[str]) -> dict[str, float]:
    """Initial values of a camera calibration's unknowns by Zhang's method (see the module doc).

    Returns ``{unknown name: value}`` for the unknowns it can initialise; the rest keep their
    nominal values.  ``unknown`` are the expanded unknown names (``board.x@view3``).  Vectorised
    over the views (issue 15): each point's position is evaluated once, the homographies of all
    views come from one stacked SVD, the poses from batched products.  A view whose points give no
    homography (fewer than 4, all on one line, not finite) is left out: its target's pose keeps
    its nominal value unless another camera saw it (:func:`zhang_start` says which).
    """
    return zhang_start(model, data, unknown)[0]


def zhang_start(model: Model, data: MeasurementSet, unknown: Sequence[str]) -> tuple[dict[str, float], list[str]]:
    """:func:`initial_values`, and a note for each view left out whose target's estimated pose
    therefore starts at its nominal value (the view, the camera, why)."""
    unknown_set = set(unknown)
    X0 = model.nominal
    frame_poses0 = _nominal(model).frame_poses
    values: dict[str, float] = {}
    obs = _PlanarPoints(model, data)
    cameras = sorted({int(c) for c in obs.keys[:, 0]})
    poses: dict[tuple[int, int, int], np.ndarray] = {}  # T_camera_target per (camera, config, frame)
    left_out: dict[int, str] = {}  # group → why it gives no homography
    for ci in cameras:
        mine = obs.keys[:, 0] == ci
        for g in np.nonzero(mine & (obs.count < 4))[0].tolist():
            left_out[g] = f"only {obs.count[g]} point(s) of the target (a homography needs 4)"
        groups = np.nonzero(mine & (obs.count >= 4))[0]
        if not len(groups):
            continue
        src, dst, mask = obs.padded(groups)
        on_target, in_image = _spans_plane(src, mask), _spans_plane(dst, mask)
        for g, a, b in zip(groups.tolist(), on_target.tolist(), in_image.tolist()):
            if not (a and b):
                where = "on the target" if not a else "in the image"
                left_out[g] = f"its {obs.count[g]} points lie on one line {where} (no homography)"
        usable = on_target & in_image
        groups, src, dst, mask = groups[usable], src[usable], dst[usable], mask[usable]
        if not len(groups):
            continue
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):  # a non-finite one is left out
            Hs = homographies(src, dst, mask)
        finite = np.all(np.isfinite(Hs), axis=(1, 2))
        for g in groups[~finite].tolist():
            left_out[g] = f"its {obs.count[g]} points give no finite homography"
        groups, Hs = groups[finite], Hs[finite]
        if not len(groups):
            continue
        info = model.cameras[ci]
        intrinsic_names = [_param(n) for n in info.intrinsics]
        skew = intrinsic_names[4] is not None and intrinsic_names[4] in unknown_set
        fitted = [n for n in intrinsic_names[:4] if n is not None and n in unknown_set]
        K = None
        if fitted and len(Hs) >= (3 if skew else 2):
            with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
                K = intrinsics_from_homographies(Hs, skew=skew)
            if not np.all(np.isfinite(K)):  # views that do not determine it (all parallel)
                K = None
        if K is not None:
            numbers = {
                intrinsic_names[0]: [K[0, 0]],
                intrinsic_names[1]: [K[1, 1]],
                intrinsic_names[2]: [K[0, 2]],
                intrinsic_names[3]: [K[1, 2]],
            }
            if skew:
                numbers[intrinsic_names[4]] = [K[0, 1]]
            merged: dict[str, list[float]] = {}
            for name, v in numbers.items():
                if name is not None:
                    merged.setdefault(name, []).extend(v)
            for name, v in merged.items():
                if name in unknown_set:
                    values[name] = float(np.mean(v))  # f = fx = fy: the mean
        if K is None:
            fx, fy, cx, cy, s = (float(ir.evaluate(n, X0, {}, np)) for n in info.intrinsics)
            K = np.array([[fx, s, cx], [0, fy, cy], [0, 0, 1.0]])
        for g, T in zip(groups, poses_from_homographies(K, Hs)):
            poses[tuple(int(k) for k in obs.keys[g])] = T  # type: ignore[index]
    if not poses:
        return values, _left_out_notes(model, obs, left_out, set(), unknown_set)
    reference = cameras[0]
    T_world_ref = frame_poses0[model.cameras[reference].frame]
    parents: dict[int, np.ndarray] = {}

    def parent_inverse(frame) -> np.ndarray:
        if frame.parent not in parents:
            parents[frame.parent] = np.eye(4) if frame.parent < 0 else np.linalg.inv(frame_poses0[frame.parent])
        return parents[frame.parent]

    # Further cameras: their pose relative to the reference from the views both see.
    T_ref_cam = {reference: np.eye(4)}
    for ci in cameras[1:]:
        shared = [(k, poses[(reference, k[1], k[2])]) for k in poses if k[0] == ci and (reference, k[1], k[2]) in poses]
        if not shared:
            continue
        T_ref_cam[ci] = _average_pose([T_ref_t @ np.linalg.inv(poses[k]) for k, T_ref_t in shared])
        frame = model.frames[model.cameras[ci].frame]
        names = _pose_params(frame.pose) if frame.pose is not None else None
        if names and all(n in unknown_set for n in names):
            _set_pose(values, names, parent_inverse(frame) @ T_world_ref @ T_ref_cam[ci])
    # Target poses per view, from the reference camera when it saw the view, else another one.
    chosen: dict[tuple[int, int], tuple[int, int, int]] = {}
    for k in sorted(poses, key=lambda k: k[0] != reference):
        if (k[1], k[2]) not in chosen and k[0] in T_ref_cam:
            chosen[(k[1], k[2])] = k
    by_frame: dict[int, list[tuple[int, int, int]]] = {}
    for k in chosen.values():
        by_frame.setdefault(k[2], []).append(k)
    for target, ks in by_frame.items():
        frame = model.frames[target]
        names = _pose_params(frame.pose) if frame.pose is not None else None
        if not names:
            continue
        T_cam = np.stack([T_world_ref @ T_ref_cam[k[0]] for k in ks])
        T_local = parent_inverse(frame) @ T_cam @ np.stack([poses[k] for k in ks])
        pose_numbers = np.concatenate([T_local[:, :3, 3], _rpy_many(T_local[:, :3, :3])], axis=1)
        for k, row in zip(ks, pose_numbers):
            config = obs.configs[k[1]]
            suffix = f"@{config}" if any(f"{n}@{config}" in unknown_set for n in names) else ""
            if all((n + suffix) in unknown_set for n in names):
                for name, v in zip(names, row):
                    values[name + suffix] = float(v)
    release_memory(20 * obs.uv.nbytes)  # the stacked DLT systems and their SVD's work space
    return values, _left_out_notes(model, obs, left_out, set(chosen), unknown_set)


def _left_out_notes(
    model: Model, obs: _PlanarPoints, left_out: dict[int, str], posed: set[tuple[int, int]], unknown: set[str]
) -> list[str]:
    """A note for each view left out of Zhang's start whose target's pose is estimated and came
    from no other camera: it starts at the nominal pose."""
    notes = []
    for g, why in sorted(left_out.items()):
        ci, config_index, target = (int(k) for k in obs.keys[g])
        frame = model.frames[target]
        names = _pose_params(frame.pose) if frame.pose is not None else None
        config = obs.configs[config_index]
        if (config_index, target) in posed or not names:
            continue
        if not (all(f"{n}@{config}" in unknown for n in names) or all(n in unknown for n in names)):
            continue
        camera = model.short_name("camera", model.cameras[ci].name)
        notes.append(
            f"{config} (camera {camera}): {why}; Zhang's start left it out: the pose of "
            f"'{model.short_name('frame', frame.name)}' there starts at the model's nominal values"
        )
    return notes


# ---- the workflow --------------------------------------------------------------------------------------


@dataclass
class CameraCalibration:
    """The outcome of :func:`calibrate_cameras`: the general result plus camera-level numbers."""

    result: Any  # CalibrationResult
    initial: dict[str, float]
    cameras: list[str]
    intrinsics: dict[str, dict[str, tuple[float, float | None]]] = field(default_factory=dict)
    """Per camera, per intrinsic (``fx`` … ``k3``): (value, σ); σ None when the intrinsic is fixed,
    ∞ when it is estimated but the views do not determine it; for an intrinsic given by an
    expression, the σ propagated from the unknowns it reads (None when it reads none)."""
    views: list[dict[str, Any]] = field(default_factory=list)
    rms: float = float("nan")
    notes: list[str] = field(default_factory=list)
    """Views that Zhang's start left out (:func:`zhang_start`): their targets' poses started at the
    nominal values."""

    @property
    def ok(self) -> bool:
        return self.result.ok

    def to_json(self) -> dict[str, Any]:
        data = self.result.to_json()
        # std null: fixed (estimated false) or not determined by the views (estimated true, σ = ∞)
        data["cameras"] = {
            cam: {k: {"value": v, "std": finite_or_null(s), "estimated": s is not None} for k, (v, s) in values.items()}
            for cam, values in self.intrinsics.items()
        }
        data["views"] = self.views
        data["rms_reprojection"] = self.rms
        data["notes"] = self.notes
        return data

    def summary(self) -> str:
        model = self.result.problem.model
        out = [
            f"camera calibration: {len(self.views)} views, "
            f"{sum(v['points'] for v in self.views)} points, RMS reprojection error {self.rms:.4f} px"
        ]
        out.extend(f"note: {note}" for note in self.notes)
        at_bound = set(self.result.observability.active_bounds)
        for cam, values in self.intrinsics.items():
            info = model.cameras[model.camera_index(cam)]
            names = [_param(node) for node in info.intrinsics + info.distortion]

            def sigma(s: float | None, name: str | None) -> str:
                if s is None:
                    return "fixed"
                if name in at_bound:
                    return "0 (at bound)"
                return fmt(s, 3) if np.isfinite(s) else "∞ (unobservable)"

            rows = [[k, fmt(v, 8), sigma(s, name)] for (k, (v, s)), name in zip(values.items(), names)]
            out.append("")
            out.append(table(["", "value", "σ"], rows, align="lrr", title=f"camera {model.short_name('camera', cam)}:"))
        rows = [
            [v["config"], model.short_name("camera", v["camera"]), v["points"], f"{v['rms']:.4f}"] for v in self.views
        ]
        out.append("")
        out.append(table(["view", "camera", "points", "RMS (px)"], rows, align="llrr", title="per view:"))
        out.append("")
        out.append(self.result.summary(max_residuals=8))
        return "\n".join(out)


def _expression_std(result: Any, node: ir.Node, X: np.ndarray) -> float | None:
    """σ of a camera's intrinsic given by an expression of parameters (``fy = f * aspect``), in
    the first configuration: gᵀ C g with g its gradient (JAX autodiff) in the unknowns it reads
    and C their covariance; None when it reads no unknown (fixed), ∞ when one of them is not
    determined by the views."""
    slots = result.problem.params.slots(0)
    if all(slots[p] < 0 for p in ir.depends_on(node)):
        return None
    from mbcal._jax import jax, jnp

    gradient = np.asarray(jax.grad(lambda P: ir.evaluate(node, P, {}, jnp))(jnp.asarray(X, dtype=float)))
    g = np.zeros(result.problem.params.size)  # in the unknowns: chain rule through X = X(x)
    np.add.at(g, slots[slots >= 0], gradient[slots >= 0])
    idx = np.nonzero(g)[0]
    if idx.size == 0:
        return 0.0
    if not np.all(np.isfinite(result.observability.std[idx])):
        return math.inf
    C = np.asarray(result.covariance[np.ix_(idx, idx)], dtype=float)
    return float(math.sqrt(max(float(g[idx] @ C @ g[idx]), 0.0)))


def default_unknowns(model: Model, data: MeasurementSet) -> list[str]:
    """Parameters with a search range, and per-configuration ones the measurements do not give."""
    given = set(data.known)
    for values in data.configurations.values():
        given.update(values)
    out = []
    for p in model.params:
        if p.name in given:
            continue
        if (p.lower is not None and p.upper is not None) or p.per_configuration:
            out.append(p.name)
    return out


def calibrate_cameras(
    model: Model,
    data: MeasurementSet,
    estimate: Sequence[str] | None = None,
    *,
    initialize: bool = True,
    restarts: int | None = None,
    seed: int | None = 0,
    config=None,
    initial: Mapping[str, float] | None = None,
    scale_covariance: bool = True,
    progress=None,
    fit=None,
    accept_poor_fit: bool = False,
    analysis: str = "auto",
) -> CameraCalibration:
    """Calibrate cameras from image points of planar targets (see the module doc).

    Parameters
    ----------
    estimate : sequence of str, optional
        Unknowns (default: :func:`default_unknowns`).
    initialize : bool
        Start from Zhang's closed-form solution (otherwise from the nominal values).
    restarts : int, optional
        Starting points: the first is the start above, the others random within the search
        ranges.  None (the default, *auto*): with Zhang's start, that start alone, and
        :data:`AUTO_RESTARTS` starts again only when it did not converge or its fit is not
        consistent with the stated σ (the χ² test of the fit verdict) — a closed-form start seldom
        needs random company, a doubtful fit always gets it; without initialisation,
        :data:`AUTO_RESTARTS` starts.  A number always runs that many.
    config : SolverConfig, optional
        The solver's settings.  None (the default): the defaults, except that Zhang's start alone
        starts with a small damping (:data:`CLOSED_FORM_LAMBDA`).
    scale_covariance : bool
        Scale σ by the reduced χ² (OpenCV's convention); the residuals then set the noise level.
    fit, accept_poor_fit
        The fit verdict's thresholds (:class:`mbcal.fit.FitConfig`) and whether to accept a poor fit
        (see :class:`mbcal.api.CalibrateOptions`).
    analysis : str
        ``auto``, ``dense`` or ``structured``: how the report of a many-view calibration is
        computed (:attr:`mbcal.api.CalibrateOptions.analysis`; from the blocks beyond about 250 views).
    """
    estimate = list(estimate) if estimate else default_unknowns(model, data)
    params = ParameterSet(model, estimate, configurations=data.config_names, per_configuration=data.configurations)
    start, notes = zhang_start(model, data, params.names) if initialize else ({}, [])
    if progress is not None:
        for note in notes:
            progress(note)
    start.update(initial or {})
    auto = restarts is None
    first = (1 if initialize else AUTO_RESTARTS) if restarts is None else restarts

    def run(n: int):
        # a closed-form start alone: Marquardt's λ starts small (CLOSED_FORM_LAMBDA), unless the
        # caller chose the solver's settings
        close = config is None and initialize and n == 1
        return calibrate(
            model,
            data,
            estimate,
            restarts=n,
            seed=seed,
            config=SolverConfig(lambda_init=CLOSED_FORM_LAMBDA) if close else config,
            initial=start,
            scale_covariance=scale_covariance,
            progress=progress,
            fit=fit,
            accept_poor_fit=accept_poor_fit,
            analysis=analysis,
        )

    result = run(first)
    if auto and first < AUTO_RESTARTS:
        verdict = result.verdict
        settled = result.solver.status_best.converged and verdict is not None and verdict.tested and verdict.consistent
        if settled:  # a weak direction (k2 against k3) is no local minimum: restarts would not help it
            result.run = replace(result.run, note="auto: Zhang's start alone (converged, consistent with the stated σ)")
        else:  # the same first start and random ones beside it: never worse than the first run
            if progress is not None:
                progress(f"the fit from Zhang's start is not consistent with the stated σ: {AUTO_RESTARTS} starts")
            result = run(AUTO_RESTARTS)
            note = f"auto: {AUTO_RESTARTS} starts (from Zhang's start alone: not converged or not consistent with σ)"
            result.run = replace(result.run, note=note)
    cams = sorted({m.refs["camera"] for m in data if m.kind == "image_point"}, key=model.camera_index)
    values = result.values
    std = result.std
    intrinsics: dict[str, dict[str, tuple[float, float | None]]] = {}
    X = result.problem.params.X(result.x)[0]
    for cam in cams:
        info = model.cameras[model.camera_index(cam)]
        entry: dict[str, tuple[float, float | None]] = {}
        for label, node in zip(INTRINSIC_NAMES + DISTORTION_NAMES, info.intrinsics + info.distortion):
            name = _param(node)
            v = float(ir.evaluate(node, X, {}, np))
            if name is not None:
                s = std.get(name) if name in values else None
            else:  # an expression: its σ propagated from the unknowns it reads (None when it reads none)
                s = _expression_std(result, node, X)
            entry[label] = (v, None if s is None else float(s))  # None: fixed; ∞: estimated, not determined
        intrinsics[cam] = entry
    views = []
    rms = float("nan")
    columns = result.problem.measurements.columns()
    col = columns.kinds.get("image_point")
    if col is not None:  # per (view, camera) in order of first appearance, from the set's columns
        _members, measured, predicted = result.residuals.kind("image_point")  # the rows of col, in order
        e2 = np.sum((measured - predicted) ** 2, axis=1)
        camera_names, camera_code = col.refs["camera"]
        key = col.config * len(camera_names) + camera_code
        distinct, first_row, which = np.unique(key, return_index=True, return_inverse=True)
        count = np.bincount(which, minlength=len(distinct))
        total = np.bincount(which, weights=e2, minlength=len(distinct))
        for k in np.argsort(first_row, kind="stable").tolist():
            row = int(first_row[k])
            config, cam = columns.config_names[int(col.config[row])], camera_names[int(camera_code[row])]
            views.append(
                {"config": config, "camera": cam, "points": int(count[k]), "rms": float(np.sqrt(total[k] / count[k]))}
            )
        rms = float(np.sqrt(np.mean(e2)))
    return CameraCalibration(result, start, cams, intrinsics, views, rms, notes)


def _view_image(images: Mapping[str, str], config: str, cam: str) -> str | None:
    """The image given for a view: by ``CONFIG@CAMERA``, else by ``CONFIG``."""
    return images.get(f"{config}@{cam}") or images.get(config)


def _reprojection_file(model, config: str, cam: str, out_dir) -> Path:
    return Path(out_dir) / f"{config}_{model.short_name('camera', cam).replace('.', '_')}_reprojection.png"


def planned_reprojections(model, measurements, images: Mapping[str, str], out_dir) -> list[Path]:
    """The files :func:`reprojection_images` will write for these measurements and images: known
    before the solve, so that a name that is taken (an input image in the same folder) is refused
    before it."""
    views = dict.fromkeys((m.config, m.refs["camera"]) for m in measurements if m.kind == "image_point")
    return [
        _reprojection_file(model, config, cam, out_dir) for config, cam in views if _view_image(images, config, cam)
    ]


def reprojection_images(cc: CameraCalibration, images: Mapping[str, str], out_dir, *, vector_scale: float = 10.0):
    """Write each view's image with its measured (blue) and reprojected (red) corners."""
    out_dir = make_output_folder(out_dir)
    model = cc.result.problem.model
    written = []
    groups: dict[tuple[str, str], list] = {}
    for r in cc.result.residuals:
        if r.kind == "image_point":
            groups.setdefault((r.config, r.refs["camera"]), []).append(r)
    for (config, cam), rows in groups.items():
        path = _view_image(images, config, cam)
        if path is None:
            continue
        image = load_image(path)
        measured = np.array([r.measured for r in rows])
        predicted = np.array([r.predicted for r in rows])
        layers = [
            Layer("points", measured, (30, 80, 220), 1.2, "detected corners"),
            Layer(
                "vectors",
                np.stack([predicted, predicted + vector_scale * (measured - predicted)], axis=1),
                (230, 130, 0),
                1.2,
                f"reprojection error × {vector_scale:g}",
            ),
            Layer("points", predicted, (220, 30, 30), 0.8, "reprojected corners"),
        ]
        target = _reprojection_file(model, config, cam, out_dir)
        save_png(draw_overlay(image, layers), target)
        written.append(target)
    return written


# ---- synthetic images of targets ------------------------------------------------------------------------


def _undistort(xy: np.ndarray, distortion: np.ndarray, iterations: int = 20) -> np.ndarray:
    """Normalised coordinates whose distortion is ``xy`` (fixed-point iteration, as OpenCV does)."""
    if not np.any(distortion):
        return xy
    guess = xy.copy()
    for _ in range(iterations):
        guess = guess - (distort(guess, distortion, np) - xy)
    return guess


def target_image(scene, camera: str, target, *, supersample: int = 3, background: int = 90) -> np.ndarray:
    """A synthetic grey image (H, W) uint8 of a chessboard or squares target seen by a camera.

    The image is made by casting every (sub)pixel through the camera's model — distortion
    included — onto the target plane and painting the pattern found there.  It is what
    detection is tested on, and it lets a calibration be planned and rehearsed without a camera.
    """
    cam = scene.camera(camera)
    info = target
    if info.kind not in ("chessboard", "grid", "squares"):
        raise MbcalError(f"cannot draw a '{info.kind}' target")
    K = np.asarray(cam.intrinsics, dtype=float)
    fx, fy, cx, cy, skew = K
    T_cam = np.asarray(cam.T_world_camera, dtype=float)
    T_target = np.asarray(scene.frame_poses[info.frame], dtype=float)
    T = np.linalg.inv(T_cam) @ T_target  # target → camera
    pts = np.asarray(scene.points, dtype=float)
    first = scene.model.point_index(info.points[0])
    local = (pts[first + np.arange(len(info.points))] - T_target[:3, 3]) @ T_target[:3, :3]
    W, H = cam.width, cam.height
    k = supersample
    u, v = np.meshgrid((np.arange(W * k) + 0.5) / k - 0.5, (np.arange(H * k) + 0.5) / k - 0.5)
    distortion = np.asarray(cam.distortion, dtype=float)

    def normalised(uu, vv):
        yd = (vv - cy) / fy
        return np.stack([(uu - cx - skew * yd) / fx, yd], axis=-1)

    if np.any(distortion):
        from scipy.ndimage import map_coordinates  # only here: ~0.1 s of every command's start-up (issue 16)

        # Undistortion is smooth: solve it on a coarse grid and interpolate (cubic) in between.
        step = 4.0
        gu = np.arange(-step, W + 2 * step, step)
        gv = np.arange(-step, H + 2 * step, step)
        GU, GV = np.meshgrid(gu, gv)
        coarse = _undistort(normalised(GU, GV).reshape(-1, 2), distortion).reshape(len(gv), len(gu), 2)
        coords = np.stack([(v.ravel() - gv[0]) / step, (u.ravel() - gu[0]) / step])
        xy = np.stack([map_coordinates(coarse[..., i], coords, order=3, mode="nearest") for i in range(2)], axis=-1)
    else:
        xy = normalised(u, v).reshape(-1, 2)
    rays = np.c_[xy, np.ones(len(xy))] @ T[:3, :3]  # ray directions in the target frame
    origin = -T[:3, :3].T @ T[:3, 3]  # camera centre in the target frame
    with np.errstate(divide="ignore", invalid="ignore"):
        s = -origin[2] / rays[:, 2]
    hit = origin[None, :2] + s[:, None] * rays[:, :2]
    valid = np.isfinite(s) & (s > 0)
    if info.kind == "squares":
        pitch = np.linalg.norm(local[4] - local[0]) if info.cols > 1 else np.linalg.norm(local[1] - local[0]) / 0.5
        size = info.size_ratio * pitch
        gx, gy = hit[:, 0] / pitch, hit[:, 1] / pitch
        inside = (
            (gx >= -0.5)
            & (gx <= info.cols + 0.5 - (1 - info.size_ratio))
            & (gy >= -0.5)
            & (gy <= info.rows + 0.5 - (1 - info.size_ratio))
        )
        fx_, fy_ = gx - np.floor(gx), gy - np.floor(gy)
        in_grid = (gx >= 0) & (gx < info.cols) & (gy >= 0) & (gy < info.rows)
        dark = in_grid & (fx_ < size / pitch) & (fy_ < size / pitch)
        value = np.where(inside, np.where(dark, 20, 235), background)
    else:
        dx = np.linalg.norm(local[1] - local[0]) if info.cols > 1 else 0.025
        dy = np.linalg.norm(local[info.cols] - local[0]) if info.rows > 1 else dx
        gx, gy = hit[:, 0] / dx, hit[:, 1] / dy
        on_board = (gx >= -1) & (gx < info.cols) & (gy >= -1) & (gy < info.rows)
        margin = (gx >= -2) & (gx < info.cols + 1) & (gy >= -2) & (gy < info.rows + 1)
        parity = (np.floor(gx) + np.floor(gy)) % 2 == 0
        value = np.where(on_board, np.where(parity, 20, 235), np.where(margin, 235, background))
    value = np.where(valid, value, background).astype(float).reshape(H * k, W * k)
    image = value.reshape(H, k, W, k).mean(axis=(1, 3))
    return np.clip(np.round(image), 0, 255).astype(np.uint8)


def plan_views(
    model: Model,
    n: int,
    *,
    seed: int = 0,
    target: str | None = None,
    camera: str | None = None,
    distance: tuple[float, float] = (0.35, 0.6),
    tilt_deg: float = 35.0,
) -> dict[str, dict[str, float]]:
    """Random poses of a target in front of a camera: ``{view: {pose parameter: value}}``.

    The target frame must be posed by ``pose(x, y, z, roll, pitch, yaw)`` of per-configuration
    parameters (as in models/camera_calibration.mdl).  Its centre is put on a random ray within
    the middle of the image at a random distance, tilted by up to ``tilt_deg``, with its z axis
    pointing away from the camera.
    """
    info = model.target(target)
    frame = model.frames[info.frame]
    names = _pose_params(frame.pose) if frame.pose is not None else None
    if not names:
        raise MbcalError(f"target '{info.name}' is not posed by pose(x, y, z, roll, pitch, yaw) of parameters")
    cam = model.cameras[model.camera_index(camera)] if camera else model.cameras[0]
    X0 = model.nominal
    scene = modeler(model, X0)
    T_world_cam = np.asarray(scene.frame_poses[cam.frame], dtype=float)
    T_world_parent = _frame_world(model, X0, frame.parent)
    first = model.point_index(info.points[0])
    T_target0 = np.asarray(scene.frame_poses[info.frame], dtype=float)
    local = (np.asarray(scene.points, float)[first : first + len(info.points)] - T_target0[:3, 3]) @ T_target0[:3, :3]
    centre = local.mean(axis=0)
    fx, fy, cx, cy, _ = (float(ir.evaluate(nd, X0, {}, np)) for nd in cam.intrinsics)
    rng = np.random.default_rng(seed)
    views = {}
    for k in range(n):
        u = rng.uniform(0.35, 0.65) * cam.width
        v = rng.uniform(0.35, 0.65) * cam.height
        z = rng.uniform(*distance)
        c_cam = np.array([(u - cx) / fx * z, (v - cy) / fy * z, z])
        a, b, g = np.radians(rng.uniform(-tilt_deg, tilt_deg, 3) * np.array([1, 1, 0.5]))
        R = geo.rpy(np, a, b, g)[:3, :3]  # z away from the camera: the board faces it
        T_cam_target = _T(R, c_cam - R @ centre)
        T_local = np.linalg.inv(T_world_parent) @ T_world_cam @ T_cam_target
        values: dict[str, float] = {}
        _set_pose(values, names, T_local)
        views[f"view{k + 1:02d}"] = values
    return views


def simulate_views(
    model: Model,
    n: int,
    known: Mapping[str, float],
    *,
    seed: int = 0,
    sigma: float = 0.5,
    target: str | None = None,
    camera: str | None = None,
    distance: tuple[float, float] = (0.35, 0.6),
    tilt_deg: float = 35.0,
) -> tuple[MeasurementSet, dict[str, float]]:
    """Simulated corner measurements of a target in ``n`` random views (:func:`plan_views`).

    ``known`` holds the true values of the shared unknowns (the intrinsics); each view's pose is
    drawn by :func:`plan_views`.  Every corner is measured with σ = ``sigma`` px and Gaussian noise of
    that σ; corners outside the image are left out.  Returns the measurements and the complete truth
    (``known`` plus ``board.x@view01`` …), for checking an estimate or planning a calibration
    before a board is printed.
    """
    poses = plan_views(model, n, seed=seed, target=target, camera=camera, distance=distance, tilt_deg=tilt_deg)
    truth = dict(known)
    for view, pose in poses.items():
        truth.update({f"{name}@{view}": value for name, value in pose.items()})
    cam = model.cameras[model.camera_index(camera)] if camera else model.cameras[0]
    records = [
        {"kind": "image_point", "config": view, "camera": cam.name, "point": p, "u": 0.0, "v": 0.0, "sigma": sigma}
        for view in poses
        for p in model.target(target).points
    ]
    plan = measurements_from_records(records, model)
    del records
    data = simulate(model, plan, truth, noise=1.0, seed=seed, drop_invisible=True)
    del plan  # the plan's measurements, next to the data's (2,000 views: ~50 MB each, issue 15)
    release_memory(500 * len(data), collect=True)
    return data, truth


def synthesize_images(
    model: Model,
    views: Mapping[str, Mapping[str, float]],
    out_dir,
    *,
    truth: Mapping[str, float] | None = None,
    target: str | None = None,
    camera: str | None = None,
    noise: float = 2.0,
    seed: int = 0,
) -> dict[str, str]:
    """Draw the target in every view as a camera would see it (PNG files); ``{view: path}``.

    ``truth`` sets the camera's true parameters (intrinsics, distortion, a rig's pose);
    ``noise`` is the σ of Gaussian pixel noise (grey levels).
    """
    out_dir = make_output_folder(out_dir)
    info = model.target(target)
    cam = model.cameras[model.camera_index(camera)] if camera else model.cameras[0]
    rng = np.random.default_rng(seed)
    paths = {}
    for view, pose in views.items():
        scene = modeler(model, parameter_vector(model, {**(truth or {}), **pose}))
        image = target_image(scene, cam.name, info).astype(float)
        image = np.clip(image + rng.normal(0, noise, image.shape), 0, 255).astype(np.uint8)
        path = out_dir / f"{view}.png"
        save_png(np.repeat(image[..., None], 3, axis=2), path)
        paths[view] = str(path)
    return paths
