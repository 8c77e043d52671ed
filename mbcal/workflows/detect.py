"""Automatic measurement (meas_r) from images: calibration-target corners with OpenCV.

OpenCV is optional (``pip install 'mbcal[vision]'``); without it, detection says how to get it.

* ``chessboard`` targets: ``cv2.findChessboardCorners`` for the pattern size (cols, rows), then
  ``cv2.cornerSubPix``.  The corners come row by row, as the target's points are named.  Use a
  board with one odd and one even count: a symmetric board can be reported from either end.
* ``squares`` targets (separated dark squares, like Zhang's pattern): the squares are found as
  dark quadrilaterals (Otsu threshold, contours, polygon approximation), ordered into the grid
  by a homography fitted to their centres, their corners matched to the target's corner
  numbering, then refined with ``cv2.cornerSubPix``.  The labelling is right-handed as seen from
  the camera (columns to the right, rows downwards in the image): the target's z axis points away
  from the camera, as for OpenCV's chessboards.

Each image becomes one configuration (named after the file) of the measurement file.
"""

from __future__ import annotations

import hashlib
import re
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mbcal.errors import MbcalError
from mbcal.language.targets import SQUARE_CORNERS
from mbcal.measurements.sets import measurements_from_records
from mbcal.render.views import check_image_path, load_image
from mbcal.workflows.cameras import homography

__all__ = ["require_opencv", "detect_chessboard", "detect_squares", "detect_images", "Detection"]


def require_opencv():
    """Import OpenCV or explain how to install it."""
    try:
        import cv2  # optional: OpenCV (mbcal[vision])
    except ImportError:
        raise MbcalError(
            "corner detection needs OpenCV, which is not installed",
            hint="pip install 'mbcal[vision]'  (or: pip install opencv-python-headless)",
        ) from None
    return cv2


def _gray(image: np.ndarray) -> np.ndarray:
    cv2 = require_opencv()
    if image.ndim == 3:
        return cv2.cvtColor(np.ascontiguousarray(image[..., :3]), cv2.COLOR_RGB2GRAY)
    return np.ascontiguousarray(image)


def _refine(gray: np.ndarray, corners: np.ndarray, window: int) -> np.ndarray:
    cv2 = require_opencv()
    criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 100, 1e-4)
    pts = corners.reshape(-1, 1, 2).astype(np.float32)
    cv2.cornerSubPix(gray, pts, (window, window), (-1, -1), criteria)
    return pts.reshape(-1, 2).astype(float)


def detect_chessboard(image: np.ndarray, rows: int, cols: int) -> np.ndarray | None:
    """Inner corners (rows·cols, 2) of a chessboard, row by row; None if it is not found."""
    cv2 = require_opencv()
    gray = _gray(image)
    flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
    found, corners = cv2.findChessboardCorners(gray, (cols, rows), flags=flags)
    if not found or corners is None:
        return None
    corners = corners.reshape(-1, 2)
    spacing = np.median(np.linalg.norm(np.diff(corners.reshape(rows, cols, 2), axis=1), axis=2))
    return _refine(gray, corners, int(np.clip(spacing / 4, 3, 11)))


def _quads(gray: np.ndarray) -> list[np.ndarray]:
    """Dark convex quadrilaterals of an image, as (4, 2) vertex arrays."""
    cv2 = require_opencv()
    blur = cv2.GaussianBlur(gray, (3, 3), 0)
    _, bw = cv2.threshold(blur, 0, 255, cv2.THRESH_BINARY_INV + cv2.THRESH_OTSU)
    contours, _ = cv2.findContours(bw, cv2.RETR_LIST, cv2.CHAIN_APPROX_SIMPLE)
    out = []
    for c in contours:
        area = cv2.contourArea(c)
        if area < 30:
            continue
        approx = cv2.approxPolyDP(c, 0.06 * cv2.arcLength(c, True), True)
        if len(approx) == 4 and cv2.isContourConvex(approx):
            out.append(approx.reshape(4, 2).astype(float))
    return out


def _apply(H: np.ndarray, p: np.ndarray) -> np.ndarray:
    q = np.c_[p, np.ones(len(p))] @ H.T
    return q[:, :2] / q[:, 2:3]


def detect_squares(image: np.ndarray, rows: int, cols: int, size_ratio: float) -> np.ndarray | None:
    """Corners (rows·cols·4, 2) of a grid of dark squares in the target's point order; or None.

    ``size_ratio`` is the squares' side over their pitch.
    """
    gray = _gray(image)
    quads = _quads(gray)
    n = rows * cols
    if len(quads) < n:
        return None
    # |a × b| of the two edges from the first corner, written out (NumPy 2 deprecates cross of 2-vectors)
    a = np.array([q[1] - q[0] for q in quads], dtype=float)
    b = np.array([q[3] - q[0] for q in quads], dtype=float)
    areas = np.abs(a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0])
    # The n quadrilaterals of most similar size: the grid's squares.
    order = np.argsort(areas)
    best, best_spread = None, np.inf
    for start in range(len(order) - n + 1):
        window = areas[order[start : start + n]]
        spread = window[-1] / window[0]
        if spread < best_spread:
            best, best_spread = order[start : start + n], spread
    if best is None or best_spread > 4.0:
        return None
    squares = [quads[i] for i in best]
    centers = np.array([q.mean(axis=0) for q in squares])
    half = size_ratio / 2.0
    s, d = centers.sum(axis=1), centers[:, 0] - centers[:, 1]
    tl, br, tr, bl = centers[np.argmin(s)], centers[np.argmax(s)], centers[np.argmax(d)], centers[np.argmin(d)]
    # Which image direction holds the columns: compare side lengths with the grid's shape.
    horizontal = (np.linalg.norm(tr - tl) + np.linalg.norm(br - bl)) / 2
    vertical = (np.linalg.norm(bl - tl) + np.linalg.norm(br - tr)) / 2
    if rows != cols and (horizontal > vertical) != (cols > rows):
        return None  # the board is turned by about 90°: ambiguous for this simple ordering
    grid = np.array(
        [[half, half], [cols - 1 + half, half], [cols - 1 + half, rows - 1 + half], [half, rows - 1 + half]]
    )
    H = homography(grid, np.array([tl, tr, br, bl]))
    expected = np.array([[c + half, r + half] for r in range(rows) for c in range(cols)])
    for _ in range(2):
        predicted = _apply(H, expected)
        distance = np.linalg.norm(predicted[:, None, :] - centers[None, :, :], axis=2)
        match = np.argmin(distance, axis=1)
        if len(set(match.tolist())) != n:
            return None
        H = homography(expected, centers[match])
    Hinv = np.linalg.inv(H)
    corners = np.zeros((n, 4, 2))
    for g, sq in enumerate(match):
        r, c = divmod(g, cols)
        in_grid = _apply(Hinv, squares[sq])
        targets = np.array([[c + a * size_ratio, r + b * size_ratio] for a, b in SQUARE_CORNERS])
        assign = np.argmin(np.linalg.norm(targets[:, None, :] - in_grid[None, :, :], axis=2), axis=1)
        if len(set(assign.tolist())) != 4:
            return None
        corners[g] = squares[sq][assign]
    side = np.median([np.linalg.norm(q[1] - q[0]) for q in squares])
    return _refine(gray, corners.reshape(-1, 2), int(np.clip(side / 6, 2, 7)))


@dataclass
class Detection:
    """What was found in one image."""

    image: str
    config: str
    corners: np.ndarray | None
    same_as: str | None = None
    """An earlier image of the call with the very same bytes (a copy under another name): its
    corners would count twice, as two views, and make σ too small."""

    @property
    def found(self) -> bool:
        return self.corners is not None


def _digest(path: Path) -> str | None:
    """The file's SHA-256 (None when it cannot be read again: it was just read as an image)."""
    try:
        return hashlib.sha256(path.read_bytes()).hexdigest()
    except OSError:
        return None


def _config_name(path: Path, taken: set[str]) -> str:
    base = re.sub(r"[^A-Za-z0-9_.-]", "_", path.stem) or "image"
    name, k = base, 2
    while name in taken:
        name, k = f"{base}_{k}", k + 1
    taken.add(name)
    return name


def detect_images(
    model, images: Sequence[str], *, target: str | None = None, camera: str | None = None, sigma: float = 0.5
):
    """Detect a model's target in images; returns (MeasurementSet, list of Detection).

    Raises
    ------
    MbcalError
        The target cannot be detected automatically (a ``points`` target), an image is
        unreadable, a folder, named twice (the same resolved path) or has another size than the
        camera, or the target is found in no image.  A copy under another name (the same bytes) is
        detected, and named in its :attr:`Detection.same_as`.
    """
    require_opencv()
    info = model.target(target)
    if info.kind == "points":
        raise MbcalError(
            f"target '{info.name}' is a list of points: there is no pattern to detect automatically",
            hint="describe the target as chessboard(...) or squares(...) to detect it",
        )
    if not model.cameras:
        raise MbcalError("the model has no camera for the image points")
    cam = model.cameras[model.camera_index(camera)] if camera else model.cameras[0]
    seen: dict[Path, str] = {}
    for item in images:  # a folder, or an image named twice, is refused before any image is searched
        check_image_path(item)
        key = Path(item).resolve()
        if key in seen:  # it would become a second view (CalibIm1_2) of the same corners: σ too small
            also = f" (as {seen[key]})" if seen[key] != str(item) else ""
            raise MbcalError(f"{item} is given twice{also}", hint="each image is one view: give it once")
        seen[key] = str(item)
    records, detections = [], []
    taken: set[str] = set()
    digests: dict[str, str] = {}  # content → the first image with it
    for item in images:
        path = Path(item)
        image = load_image(path)
        digest = _digest(path)
        same_as = digests.setdefault(digest, str(path)) if digest else None
        if image.shape[:2] != (cam.height, cam.width):
            raise MbcalError(
                f"{path} is {image.shape[1]}×{image.shape[0]} pixels but camera '{cam.name}' is "
                f"{cam.width}×{cam.height}"
            )
        config = _config_name(path, taken)
        if info.kind in ("chessboard", "grid"):
            corners = detect_chessboard(image, info.rows, info.cols)
        else:
            corners = detect_squares(image, info.rows, info.cols, info.size_ratio)
        detections.append(Detection(str(path), config, corners, same_as if same_as != str(path) else None))
        if corners is None:
            continue
        for name, (u, v) in zip(info.points, corners):
            records.append(
                {
                    "id": f"{config}:{cam.name.rsplit('.', 1)[-1]}:{name.rsplit('.', 1)[-1]}",
                    "kind": "image_point",
                    "config": config,
                    "camera": cam.name,
                    "point": name,
                    "u": float(u),
                    "v": float(v),
                    "sigma": sigma,
                }
            )
    if not records:
        raise MbcalError(
            f"target '{info.name}' ({info.kind} {info.rows}×{info.cols}) was found in none of the {len(images)} images"
        )
    data = measurements_from_records(records, model)
    data.images = {d.config: str(Path(d.image).resolve()) for d in detections if d.found}
    return data, detections
