"""Scans: points with the sensor frame they were taken in and the configuration they belong to.

A :class:`Scan` holds points in the coordinates of one frame of the model (``world`` for a
registered point cloud, the depth camera's frame for points from a depth image) and the name of
the configuration (robot attitude, time) it was taken in.  :func:`load_scan` reads any file of
:mod:`mbcal.range.readers`; depth images become points through the depth camera's pinhole
intrinsics, after the **edge rule**:

    A depth pixel is dropped when a 4-neighbour has no return, or when the depth of a
    4-neighbour differs from its own by more than ``edge`` × its depth (default 10 %: 10 cm at 1 m).

Such pixels lie on a silhouette (a depth discontinuity) or on a surface seen at a grazing angle.
Real sensors report mixed depths there ("flying pixels"), and the range along such a ray is a
discontinuous function of the model's parameters, the cause of the biased estimates of plain
ray-range fits; point-to-surface residuals of the remaining pixels are smooth in the parameters.
The threshold is far above the noise on purpose: a rule that noise can flip selects pixels by
their noise (a 2 % threshold, near the depth step of a 45° surface between neighbouring pixels of
a 106-pixel-wide camera, biased a rendered-room fit by 5σ); at 10 % only true discontinuities
and very grazing surfaces are cut.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from mbcal.errors import MbcalError, MeasurementFileError
from mbcal.language.model import Model, RangeInfo
from mbcal.params import DEFAULT_CONFIGURATION
from mbcal.range.readers import CLOUD_SUFFIXES, read_cloud, read_depth, read_npy
from mbcal.units import at_least

__all__ = ["Scan", "load_scan", "depth_to_points", "edge_mask", "voxel_downsample", "depth_camera", "EDGE_DEFAULT"]

EDGE_DEFAULT = 0.10


@dataclass(frozen=True)
class Scan:
    """Points (N, 3) in metres in ``frame`` (a model frame's name or ``world``), taken in ``config``.

    A point's σ (m, of its distance to its surface) is ``sigma + sigma_rel · z``, z its depth in
    the sensor frame (a depth camera's noise grows with the range); ``source`` is the file it came
    from; ``dropped`` how many points the reader or the edge rule left out.
    """

    points: np.ndarray
    frame: str = "world"
    config: str = DEFAULT_CONFIGURATION
    sigma: float = 2e-3
    source: str = ""
    dropped: int = 0
    notes: tuple[str, ...] = field(default=())
    sigma_rel: float = 0.0
    pixels: np.ndarray | None = None  # (N, 2) row, column of each point of a depth image
    focal: float = 0.0  # the depth camera's focal length (pixels), for down-sampling on its grid
    nonfinite: int = 0
    """Of ``dropped``: points left out because a coordinate is not a finite number (NaN, inf), by
    the reader (a cloud's NaN points) or here; the fit report states them."""

    def __post_init__(self) -> None:
        if not at_least(self.sigma, 0.0, strict=True):
            raise MbcalError(
                f"scan {self.source or self.frame}: sigma must be a positive number of metres, got {self.sigma!r}"
            )
        if not at_least(self.sigma_rel, 0.0):
            raise MbcalError(f"scan {self.source or self.frame}: sigma_rel must be ≥ 0, got {self.sigma_rel!r}")
        object.__setattr__(self, "points", np.asarray(self.points, dtype=float))  # a list, float32: (N, 3) float64
        shape = self.points.shape
        if len(shape) != 2 or shape[1] != 3:
            raise MbcalError(f"scan {self.source or self.frame}: points must be an (N, 3) array, got shape {shape}")
        finite = np.all(np.isfinite(self.points), axis=1)
        if not finite.all():
            # as the readers leave them out: a NaN went into the voxel keys and lost ~99 % of the rest
            if not finite.any():
                raise MbcalError(f"scan {self.source or self.frame}: no point has finite coordinates")
            lost = int((~finite).sum())
            object.__setattr__(self, "points", np.ascontiguousarray(self.points[finite]))
            if self.pixels is not None and len(self.pixels) == len(finite):
                object.__setattr__(self, "pixels", np.asarray(self.pixels)[finite])
            object.__setattr__(self, "dropped", self.dropped + lost)
            object.__setattr__(self, "nonfinite", self.nonfinite + lost)
            note = f"{lost} point(s) with a coordinate that is not a finite number left out"
            object.__setattr__(self, "notes", (*self.notes, note))

    def __len__(self) -> int:
        return int(self.points.shape[0])

    def downsampled(self, size: float) -> np.ndarray:
        """The points kept for a voxel size (m): a depth image's on a pixel grid whose step is the
        voxel size at the median depth; a cloud's a random subset (seeded) as large as the number
        of cubes of side ``size`` its points occupy.  Which point is kept never depends on its
        noise: one point per cube (:func:`voxel_downsample`), whose membership the noisy position
        decides, biased a cloud's fit of the room by 4–5 σ in yaw with a verdict of ok (0.3 σ
        with every point)."""
        if size <= 0:
            return self.points
        if self.pixels is not None and self.focal > 0 and len(self.points):
            k = max(1, int(round(size * self.focal / float(np.median(self.points[:, 2])))))
            keep = (self.pixels[:, 0] % k == 0) & (self.pixels[:, 1] % k == 0)
            return self.points[keep]
        count = len(voxel_downsample(self.points, size))
        if count >= len(self.points):
            return self.points
        chosen = np.random.default_rng(0).choice(len(self.points), count, replace=False)
        return self.points[np.sort(chosen)]

    def sigmas(self, points: np.ndarray | None = None) -> np.ndarray:
        """σ (m) of each point (of ``points``, default this scan's, in the sensor frame)."""
        p = self.points if points is None else points
        return self.sigma + self.sigma_rel * np.abs(p[:, 2])

    def with_points(self, points: np.ndarray, note: str | None = None) -> Scan:
        return replace(
            self, points=np.ascontiguousarray(points, dtype=float), notes=self.notes + ((note,) if note else ())
        )


def depth_camera(model: Model, name: str | None = None, where: str = "") -> RangeInfo:
    """The model's depth camera ``name`` (a unique suffix), or its only one."""
    cams = [r for r in model.ranges if r.is_depth_camera]
    if name is not None:
        info = model.ranges[model.range_index(name)]
        if not info.is_depth_camera:
            raise MeasurementFileError(
                f"{where}range sensor '{info.name}' is not a depth camera (it has no width, height and f)"
            )
        return info
    if len(cams) != 1:
        listing = ", ".join(c.name for c in cams) or "none"
        raise MeasurementFileError(
            f"{where}a depth image needs the model's depth camera: the model has {len(cams)} ({listing})",
            hint="name it with --sensor NAME, or declare one: range NAME(width = ..., height = ..., f = ...)",
        )
    return cams[0]


def edge_mask(depth: np.ndarray, edge: float = EDGE_DEFAULT) -> np.ndarray:
    """Pixels that pass the edge rule (see the module doc): a return, every 4-neighbour a return,
    and no 4-neighbour's depth farther than ``edge`` × the depth from its own."""
    valid = np.isfinite(depth)
    d = np.where(valid, depth, 0.0)
    ok = valid.copy()
    H, W = depth.shape
    ok[0, :] = ok[-1, :] = False
    ok[:, 0] = ok[:, -1] = False
    for dr, dc in ((1, 0), (-1, 0), (0, 1), (0, -1)):
        nb_valid = np.zeros_like(valid)
        nb = np.zeros_like(d)
        rs, re_ = max(dr, 0), H + min(dr, 0)
        cs, ce = max(dc, 0), W + min(dc, 0)
        nb_valid[rs - dr : re_ - dr, cs - dc : ce - dc] = valid[rs:re_, cs:ce]
        nb[rs - dr : re_ - dr, cs - dc : ce - dc] = d[rs:re_, cs:ce]
        ok &= nb_valid & (np.abs(nb - d) <= edge * d)
    return ok


def depth_to_points(
    depth: np.ndarray, sensor: RangeInfo, edge: float | None = EDGE_DEFAULT, where: str = ""
) -> tuple[np.ndarray, np.ndarray, int]:
    """Points (N, 3) in the depth camera's frame (OpenCV axes) from a depth image in metres, the
    (N, 2) pixel (row, column) of each, and how many returns were dropped (valid range, edge rule)."""
    if depth.shape != (sensor.height, sensor.width):
        raise MeasurementFileError(
            f"{where}the depth image is {depth.shape[1]} × {depth.shape[0]} pixels; depth camera "
            f"'{sensor.name}' is {sensor.width} × {sensor.height}"
        )
    assert sensor.intrinsics is not None
    fx, fy, cx, cy = sensor.intrinsics
    returns = np.isfinite(depth)
    keep = returns & (depth >= sensor.min_range) & (depth <= sensor.max_range)
    if edge is not None:
        keep &= edge_mask(np.where(keep, depth, np.nan), edge)
    rows, cols = np.nonzero(keep)
    z = depth[rows, cols]
    pts = np.stack([(cols - cx) / fx * z, (rows - cy) / fy * z, z], axis=1)
    return pts, np.stack([rows, cols], axis=1), int(returns.sum() - keep.sum())


def voxel_downsample(points: np.ndarray, size: float) -> np.ndarray:
    """One point per occupied cube of side ``size`` (m): the first of its points in the scan's order
    (a measured point, chosen without looking at its noise: averaging would flatten curved
    surfaces, and picking the point nearest to the centroid prefers points whose noise pushes them
    towards it, into solids at edges); ``size <= 0``: every point."""
    if size <= 0 or len(points) == 0:
        return points
    keys = np.floor(points / size).astype(np.int64)
    keys -= keys.min(axis=0)
    span = keys.max(axis=0) + 1
    if float(np.prod(span.astype(float))) < 2.0**62:
        # One integer per cube (a 1-D sort is several times faster than unique rows).
        flat = (keys[:, 0] * span[1] + keys[:, 1]) * span[2] + keys[:, 2]
        _, first = np.unique(flat, return_index=True)
    else:
        _, first = np.unique(keys, axis=0, return_index=True)
    return points[np.sort(first)]


def load_scan(
    path: str | os.PathLike,
    model: Model,
    *,
    sensor: str | None = None,
    frame: str | None = None,
    config: str = DEFAULT_CONFIGURATION,
    sigma: float | None = None,
    edge: float | None = EDGE_DEFAULT,
) -> Scan:
    """Read a scan file: a point cloud (in ``frame``, default ``world``) or a depth image (through
    the model's depth camera ``sensor``: its frame, intrinsics, depth scale and valid range).

    ``sigma`` (m) defaults to 2 mm for clouds; for depth images a point's σ defaults to
    1 mm + 0.1 % of its depth (a structured-light camera's noise; ``sigma`` given: that, constant).
    """
    p = Path(path)
    suffix = p.suffix.lower()
    is_image = suffix in (".png", ".tif", ".tiff")
    if suffix == ".npy" and p.is_file():
        arr = read_npy(p)
        is_image = arr.ndim == 2 and arr.shape[1] > 3  # (H, W) depth, else (N, 3) points
    if is_image:
        info = depth_camera(model, sensor, where=f"{p}: ")
        depth = read_depth(p, info.depth_scale)
        pts, pix, dropped = depth_to_points(depth, info, edge, where=f"{p}: ")
        if len(pts) == 0:
            raise MeasurementFileError(f"{p}: no depth pixel is inside the valid range and away from edges")
        if frame is not None and model.frame_index(frame) != info.frame:
            raise MeasurementFileError(f"{p}: a depth image is taken in its camera's frame, not '{frame}'")
        s, rel = (sigma, 0.0) if sigma is not None else (1e-3, 1e-3)
        name = model.frames[info.frame].name
        assert info.intrinsics is not None  # a depth camera has them
        return Scan(pts, name, config, s, str(p), dropped, sigma_rel=rel, pixels=pix, focal=min(info.intrinsics[:2]))
    if suffix not in CLOUD_SUFFIXES:
        raise MeasurementFileError(f"{p}: unknown scan format '{suffix}' (clouds: {', '.join(CLOUD_SUFFIXES)}; "
                                   "depth images: .png, .tif, .tiff, .npy)")  # fmt: skip
    cloud = read_cloud(p)
    name = "world"
    if frame is not None and frame != "world":
        name = model.frames[model.frame_index(frame)].name
    notes = (
        (f"{cloud.dropped} point(s) with a coordinate that is not a finite number left out",) if cloud.dropped else ()
    )
    s = sigma if sigma is not None else 2e-3
    return Scan(cloud.points, name, config, s, str(p), cloud.dropped, notes, nonfinite=cloud.dropped)
