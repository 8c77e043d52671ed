"""Range data in: point clouds (PLY, OBJ, PCD, XYZ/CSV, .npy) and depth images (16-bit PNG,
float TIFF, .npy), read into float64 numpy arrays with located errors.

Every reader checks a file's own claims (a header's point count, a row size) against the bytes
that are really there *before* allocating anything, so a truncated file or a header that claims
2 GB of points is a :class:`~mbcal.errors.MeasurementFileError` naming the file (and the line,
for text), never a traceback or a 2 GB allocation.

Formats
-------
* PLY (ASCII and binary) and OBJ: read with trimesh (vertices; faces are ignored).
* PCD (Point Cloud Library): ``DATA ascii`` and ``DATA binary``, any field order, fields x, y, z
  required; ``binary_compressed`` is refused with a clear message (convert it with
  ``pcl_convert_pcd_ascii_binary``).  NaN points (organised clouds mark missing returns so) are
  dropped — as every cloud reader drops a point with a coordinate that is not finite (NaN, inf),
  counted in :attr:`PointCloud.dropped`; the scan and the fit report state the count.
* XYZ / CSV / TXT: one point per line, three or more numbers separated by white space or
  commas; a first line of column names (``x,y,z``) is allowed; ``#`` starts a comment.
* ``.npy``: an (N, 3) (or (N, ≥3), first three columns) array of points in metres.
* Depth images: 16-bit PNG (counts × the sensor's depth scale, 1 mm by default; 0 = no return),
  32-bit float TIFF or ``.npy`` in metres (0, NaN or inf = no return), as RealSense, Kinect and
  ROS tools write them.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mbcal.errors import MeasurementFileError, SourceSpan
from mbcal.outputs import atomic_writer

__all__ = [
    "CLOUD_SUFFIXES",
    "DEPTH_SUFFIXES",
    "PointCloud",
    "read_cloud",
    "read_depth",
    "read_npy",
    "not_a_scan",
    "write_ply",
    "write_pcd",
    "write_xyz",
    "write_depth_png",
]

CLOUD_SUFFIXES = (".ply", ".obj", ".pcd", ".xyz", ".csv", ".txt", ".pts", ".npy")
DEPTH_SUFFIXES = (".png", ".tif", ".tiff", ".npy")
MAX_POINTS = 200_000_000  # 4.8 GB of float64 points: refuse claims beyond this outright


@dataclass(frozen=True)
class PointCloud:
    """Points read from a file: (N, 3) float64 in metres, and how many were dropped (a coordinate
    NaN or infinite; every format)."""

    points: np.ndarray
    path: str
    dropped: int = 0


def _fail(path: str | os.PathLike, message: str, line: int | None = None, hint: str | None = None):
    if line is not None:
        return MeasurementFileError(message, SourceSpan(str(path), line, 1), hint=hint)
    return MeasurementFileError(f"{path}: {message}", hint=hint)


def _finite_points(points: np.ndarray, path) -> PointCloud:
    points = np.asarray(points, dtype=float)
    keep = np.all(np.isfinite(points), axis=1)
    if not keep.any():
        raise _fail(path, "no finite points in the file")
    return PointCloud(np.ascontiguousarray(points[keep]), str(path), int((~keep).sum()))


def read_cloud(path: str | os.PathLike) -> PointCloud:
    """Read a point cloud (metres) from PLY, OBJ, PCD, XYZ/CSV/TXT or .npy (by the suffix)."""
    p = Path(path)
    if not p.is_file():
        raise _fail(p, "no such file")
    suffix = p.suffix.lower()
    if suffix == ".pcd":
        return _read_pcd(p)
    if suffix == ".ply":
        _check_ply_header(p)
        return _read_trimesh(p, "ply")
    if suffix == ".obj":
        return _read_trimesh(p, "obj")
    if suffix in (".xyz", ".csv", ".txt", ".pts"):
        return _read_text(p)
    if suffix == ".npy":
        arr = read_npy(p)
        if arr.ndim != 2 or arr.shape[1] < 3:
            raise _fail(p, f"a point cloud .npy holds an (N, 3) array; this one is {arr.shape}")
        return _finite_points(arr[:, :3], p)
    raise _fail(p, f"unknown point-cloud format '{suffix}' (read: {', '.join(CLOUD_SUFFIXES)})")


# ---- PLY and OBJ (trimesh) ---------------------------------------------------------------------------

_PLY_TYPES = {
    "char": 1, "int8": 1, "uchar": 1, "uint8": 1, "short": 2, "int16": 2, "ushort": 2, "uint16": 2,
    "int": 4, "int32": 4, "uint": 4, "uint32": 4, "float": 4, "float32": 4, "double": 8, "float64": 8,
}  # fmt: skip


def _check_ply_header(p: Path) -> None:
    """Validate a PLY header's claims against the file size before trimesh allocates anything."""
    with open(p, "rb") as f:
        head = f.read(65536)
    if not head.startswith(b"ply"):
        raise _fail(p, "not a PLY file: it must start with 'ply'", 1)
    end = head.find(b"end_header")
    if end < 0:
        raise _fail(p, "the PLY header has no 'end_header' line (within its first 64 KiB)", 1)
    lines = head[:end].decode("ascii", "replace").splitlines()
    body_start = end + len(b"end_header") + (2 if head[end + 10 : end + 12] == b"\r\n" else 1)
    fmt = None
    row = 0
    fixed = True
    vertices = None
    current = None
    for i, line in enumerate(lines, start=1):
        words = line.split()
        if not words:
            continue
        if words[0] == "format" and len(words) >= 2:
            fmt = words[1]
            if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
                raise _fail(p, f"unknown PLY format '{fmt}'", i)
        elif words[0] == "element" and len(words) == 3:
            current = words[1]
            if not words[2].isdigit():
                raise _fail(p, f"element count '{words[2]}' is not a whole number", i)
            if current == "vertex":
                vertices = int(words[2])
                if vertices > MAX_POINTS:
                    raise _fail(p, f"the header claims {vertices} vertices, more than mbcal reads ({MAX_POINTS})", i)
        elif words[0] == "property" and current == "vertex":
            if words[1] == "list":
                fixed = False
            elif words[1] not in _PLY_TYPES:
                raise _fail(p, f"unknown PLY property type '{words[1]}'", i)
            else:
                row += _PLY_TYPES[words[1]]
    if fmt is None:
        raise _fail(p, "the PLY header has no 'format' line", 1)
    if vertices is None:
        raise _fail(p, "the PLY header declares no 'element vertex'", 1)
    size = p.stat().st_size - body_start
    if fmt != "ascii" and fixed and vertices * row > size:
        raise _fail(
            p,
            f"truncated: the header claims {vertices} vertices of {row} bytes ({vertices * row} bytes), "
            f"the file holds {max(size, 0)} bytes of data",
        )
    if fmt == "ascii" and vertices > size // 2 + 1:
        raise _fail(p, f"truncated: the header claims {vertices} vertices, the file is too short to hold them")


def _read_trimesh(p: Path, kind: str) -> PointCloud:
    import trimesh  # optional at import time: point-cloud files load it when read

    try:
        loaded = trimesh.load(str(p), file_type=kind, process=False, force=None)
    except Exception as err:  # trimesh raises many kinds on malformed files
        raise _fail(p, f"cannot read {kind.upper()}: {type(err).__name__}: {err}") from None
    if isinstance(loaded, trimesh.Scene):
        parts = [np.asarray(getattr(g, "vertices", np.zeros((0, 3)))) for g in loaded.dump()] if loaded.geometry else []
        vertices = np.concatenate(parts) if parts else np.zeros((0, 3))
    else:
        vertices = np.asarray(getattr(loaded, "vertices", np.zeros((0, 3))))
    if len(vertices) == 0:
        raise _fail(p, f"the {kind.upper()} file holds no vertices")
    return _finite_points(vertices, p)


# ---- PCD ------------------------------------------------------------------------------------------------

_PCD_TYPES = {("F", 4): "f4", ("F", 8): "f8", ("I", 1): "i1", ("I", 2): "i2", ("I", 4): "i4", ("I", 8): "i8",
              ("U", 1): "u1", ("U", 2): "u2", ("U", 4): "u4", ("U", 8): "u8"}  # fmt: skip
_PCD_KEYS = ("VERSION", "FIELDS", "SIZE", "TYPE", "COUNT", "WIDTH", "HEIGHT", "VIEWPOINT", "POINTS", "DATA")


def _read_pcd(p: Path) -> PointCloud:
    with open(p, "rb") as f:
        raw = f.read(65536)
    header: dict[str, tuple[list[str], int]] = {}
    offset = 0
    line_no = 0
    data_line = None
    while offset < len(raw):
        nl = raw.find(b"\n", offset)
        if nl < 0:
            break
        line = raw[offset:nl].decode("ascii", "replace").strip()
        offset = nl + 1
        line_no += 1
        if not line or line.startswith("#"):
            continue
        words = line.split()
        key = words[0].upper()
        if key not in _PCD_KEYS:
            raise _fail(p, f"'{words[0]}' is not a PCD header field (expected one of {', '.join(_PCD_KEYS)})", line_no)
        header[key] = (words[1:], line_no)
        if key == "DATA":
            data_line = line_no
            break
    if data_line is None:
        raise _fail(p, "not a PCD file: no 'DATA' line in the header", 1)
    for key in ("FIELDS", "SIZE", "TYPE", "WIDTH", "HEIGHT"):
        if key not in header:
            raise _fail(p, f"the PCD header has no '{key}' line", data_line)
    fields, fl = header["FIELDS"]
    n_fields = len(fields)

    def ints(key: str, count: int | None) -> list[int]:
        words, ln = header[key]
        if count is not None and len(words) != count:
            raise _fail(p, f"{key} gives {len(words)} values for {count} fields", ln)
        try:
            out = [int(w) for w in words]
        except ValueError:
            raise _fail(p, f"{key} must give whole numbers, got '{' '.join(words)}'", ln) from None
        if any(v < 0 for v in out):
            raise _fail(p, f"{key} must not be negative", ln)
        return out

    sizes = ints("SIZE", n_fields)
    counts = ints("COUNT", n_fields) if "COUNT" in header else [1] * n_fields
    types, tl = header["TYPE"]
    if len(types) != n_fields:
        raise _fail(p, f"TYPE gives {len(types)} values for {n_fields} fields", tl)
    width, height = ints("WIDTH", 1)[0], ints("HEIGHT", 1)[0]
    n = ints("POINTS", 1)[0] if "POINTS" in header else width * height
    ln_points = header.get("POINTS", header["WIDTH"])[1]
    if n != width * height:
        raise _fail(p, f"POINTS {n} is not WIDTH × HEIGHT = {width * height}", ln_points)
    if n > MAX_POINTS:
        raise _fail(p, f"the header claims {n} points, more than mbcal reads ({MAX_POINTS})", ln_points)
    for axis in ("x", "y", "z"):
        if axis not in fields:
            raise _fail(p, f"the PCD has no '{axis}' field (fields: {' '.join(fields)})", fl)
    dtype_fields: list[tuple] = []
    for name, size, t, c in zip(fields, sizes, types, counts):
        code = _PCD_TYPES.get((t.upper(), size))
        if code is None:
            raise _fail(p, f"field '{name}': unsupported TYPE {t} with SIZE {size}", tl)
        dtype_fields.append((name, "<" + code, (c,)) if c != 1 else (name, "<" + code))
    names = [f[0] for f in dtype_fields]
    if len(set(names)) != len(names):
        dtype_fields = [(f"{f[0]}_{k}", *f[1:]) for k, f in enumerate(dtype_fields)]  # e.g. several '_' pads
        names = [f[0] for f in dtype_fields]
    dtype = np.dtype(dtype_fields)  # type: ignore[arg-type]
    mode_words, _ = header["DATA"]
    mode = mode_words[0].lower() if mode_words else ""
    with open(p, "rb") as f:
        f.seek(offset)
        if mode == "binary":
            available = p.stat().st_size - offset
            need = n * dtype.itemsize
            if need > available:
                raise _fail(
                    p,
                    f"truncated binary PCD: the header claims {n} points × {dtype.itemsize} bytes = {need} bytes, "
                    f"the file holds {available} bytes of data",
                )
            data = np.frombuffer(f.read(need), dtype=dtype, count=n)
            xyz = np.stack([data[names[fields.index(a)]].astype(float) for a in "xyz"], axis=1)
        elif mode == "ascii":
            xyz = _pcd_ascii(
                p, f.read().decode("ascii", "replace"), n, [fields.index(a) for a in "xyz"], counts, data_line
            )
        elif mode == "binary_compressed":
            raise _fail(
                p,
                "DATA binary_compressed (LZF) is not supported",
                data_line,
                hint="convert it to binary or ascii, e.g. pcl_convert_pcd_ascii_binary IN OUT 1",
            )
        else:
            raise _fail(p, f"DATA must be ascii, binary or binary_compressed, got '{' '.join(mode_words)}'", data_line)
    if n == 0:
        raise _fail(p, "the PCD holds no points")
    return _finite_points(xyz, p)


def _pcd_ascii(p: Path, text: str, n: int, xyz_fields: list[int], counts: list[int], data_line: int) -> np.ndarray:
    columns = [sum(counts[:i]) for i in xyz_fields]
    width = sum(counts)
    out = np.empty((n, 3))
    k = 0
    for j, line in enumerate(text.splitlines(), start=data_line + 1):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        if k >= n:
            raise _fail(p, f"more data lines than the header's {n} points", j)
        words = s.split()
        if len(words) != width:
            raise _fail(p, f"expected {width} values, got {len(words)}", j)
        try:
            out[k] = [float(words[c]) for c in columns]
        except ValueError:
            raise _fail(p, f"not a number in '{s[:60]}'", j) from None
        k += 1
    if k < n:
        raise _fail(p, f"truncated: the header claims {n} points, the file holds {k}", data_line)
    return out


# ---- XYZ / CSV -------------------------------------------------------------------------------------------

_SPLIT = re.compile(r"[,;\s]+")


def _read_text(p: Path) -> PointCloud:
    try:
        text = p.read_text(encoding="utf-8")
    except UnicodeDecodeError:
        raise _fail(p, "not a text file (XYZ/CSV files hold one point per line as text)") from None
    rows: list[list[float]] = []
    header_seen = False
    columns = (0, 1, 2)
    for j, line in enumerate(text.splitlines(), start=1):
        s = line.split("#", 1)[0].strip()
        if not s:
            continue
        words = [w for w in _SPLIT.split(s) if w]
        try:
            values = [float(w) for w in words]
        except ValueError:
            if not rows and not header_seen:
                names = [w.strip().lower() for w in words]
                header_seen = True
                if all(a in names for a in "xyz"):
                    columns = (names.index("x"), names.index("y"), names.index("z"))
                continue
            raise _fail(p, f"not a number in '{s[:60]}'", j) from None
        if len(values) <= max(columns):
            raise _fail(p, f"expected at least {max(columns) + 1} numbers (x y z), got {len(values)}", j)
        rows.append([values[c] for c in columns])
    if not rows:
        raise _fail(p, "the file holds no points")
    return _finite_points(np.asarray(rows), p)


def not_a_scan(path: str | os.PathLike) -> str | None:
    """Why a file of a scan's suffix cannot be a scan by its *kind*, or None: an 8-bit (colour or
    grey) image, which is a photo and never a depth image (those are 16-bit or 32-bit float), or a
    text file of which no line of its first 64 KB starts with three numbers (a README, a log).  A
    file of a scan's kind that is broken (a truncated PNG, a cloud with a bad line) is not named
    here: reading it gives the located error.  For a watched folder, where unrelated files lie."""
    p = Path(path)
    suffix = p.suffix.lower()
    if suffix in (".png", ".tif", ".tiff"):
        try:
            from PIL import Image  # optional at import time

            with Image.open(p) as im:  # the header only
                mode = im.mode
        except Exception:
            return None  # not readable as an image: a broken depth image, the reader says why
        if mode in ("1", "L", "LA", "P", "PA", "RGB", "RGBA", "RGBX", "CMYK", "YCbCr", "LAB", "HSV"):
            return f"an 8-bit image (mode {mode}), not a depth image (16-bit counts or 32-bit float metres)"
        return None
    if suffix in (".xyz", ".csv", ".txt", ".pts"):
        try:
            with open(p, "rb") as f:
                head = f.read(65536)
            text = head.decode("utf-8")
        except (OSError, UnicodeDecodeError):
            return None  # the reader gives the located error
        lines = text.splitlines()
        if len(head) == 65536 and lines:
            lines = lines[:-1]  # the last line may be cut short
        for line in lines:
            words = [w for w in _SPLIT.split(line.split("#", 1)[0].strip()) if w]
            try:
                [float(w) for w in words[:3]]
            except ValueError:
                continue
            if len(words) >= 3:
                return None
        if not text.strip():
            return None  # empty: a file still being made, or an empty scan (the reader says so)
        return "text with no line of three numbers (x y z) in it: not a point cloud"
    return None


# ---- .npy ------------------------------------------------------------------------------------------------


def read_npy(p: Path) -> np.ndarray:
    """np.load with the header's shape checked against the file size first (object arrays refused)."""
    with open(p, "rb") as f:
        try:
            version = np.lib.format.read_magic(f)
            if version == (1, 0):
                shape, fortran, dtype = np.lib.format.read_array_header_1_0(f)
            else:
                shape, fortran, dtype = np.lib.format.read_array_header_2_0(f)
        except Exception as err:
            raise _fail(p, f"not a valid .npy file ({err})") from None
        start = f.tell()
    if dtype.hasobject:
        raise _fail(p, "the .npy holds Python objects; mbcal reads numeric arrays only")
    count = int(np.prod(shape)) if shape else 1
    need = count * dtype.itemsize
    available = p.stat().st_size - start
    if need > available:
        raise _fail(p, f"truncated: the header claims shape {shape} ({need} bytes), the file holds {available} bytes")
    if dtype.kind not in "fiu":
        raise _fail(p, f"the .npy holds {dtype}, not numbers")
    return np.load(p, allow_pickle=False)


# ---- depth images ----------------------------------------------------------------------------------------


def read_depth(path: str | os.PathLike, depth_scale: float = 1e-3) -> np.ndarray:
    """A depth image in metres (H, W) float64, NaN where there is no return.

    16-bit PNG/TIFF counts are multiplied by ``depth_scale`` (m per count; 0 counts = no return);
    float TIFF and .npy hold metres (0, NaN, ±inf = no return).  Negative depths are an error.
    """
    p = Path(path)
    if not p.is_file():
        raise _fail(p, "no such file")
    suffix = p.suffix.lower()
    if suffix == ".npy":
        arr = read_npy(p)
        if arr.ndim != 2:
            raise _fail(p, f"a depth image .npy holds an (H, W) array; this one is {arr.shape}")
        depth = arr.astype(float) * (depth_scale if arr.dtype.kind in "iu" else 1.0)
    elif suffix in (".png", ".tif", ".tiff"):
        depth = _read_image(p, depth_scale)
    else:
        raise _fail(p, f"unknown depth-image format '{suffix}' (read: {', '.join(DEPTH_SUFFIXES)})")
    depth = np.where(np.isfinite(depth) & (depth != 0), depth, np.nan)
    bad = depth < 0
    if bad.any():
        r, c = np.argwhere(bad)[0]
        raise _fail(p, f"negative depth {depth[r, c]:g} m at pixel (row {r}, column {c})")
    if not np.isfinite(depth).any():
        raise _fail(p, "the depth image has no valid pixel (all zero, NaN or infinite)")
    return depth


def _read_image(p: Path, depth_scale: float) -> np.ndarray:
    from PIL import Image  # optional at import time: depth images load Pillow when read

    Image.MAX_IMAGE_PIXELS = 64_000_000
    try:
        with Image.open(p) as im:
            mode = im.mode
            w, h = im.size
            if w * h > 64_000_000:
                raise _fail(p, f"the image claims {w} × {h} pixels, more than a depth image mbcal reads")
            arr = np.asarray(im)
    except MeasurementFileError:
        raise
    except Exception as err:
        raise _fail(p, f"cannot read the image: {type(err).__name__}: {err}") from None
    if mode in ("I;16", "I;16B", "I;16L", "I;16N") or (mode == "I" and arr.dtype.kind in "iu"):
        return arr.astype(float) * depth_scale
    if mode == "F":
        return arr.astype(float)
    raise _fail(
        p,
        f"not a depth image: mode {mode} ({arr.dtype}); depth images are 16-bit (counts of the depth scale) "
        "or 32-bit float (metres)",
    )


# ---- writers (for tests, examples and outlier files) ------------------------------------------------------


def write_ply(path: str | os.PathLike, points: np.ndarray, colors: np.ndarray | None = None) -> None:
    """Write points (N, 3) (and optional uint8 colours (N, 3)) as a binary little-endian PLY, atomically."""
    pts = np.asarray(points, dtype="<f4").reshape(-1, 3)
    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    head = ["ply", "format binary_little_endian 1.0", f"element vertex {len(pts)}"]
    head += ["property float x", "property float y", "property float z"]
    if colors is not None:
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
        head += ["property uchar red", "property uchar green", "property uchar blue"]
    head.append("end_header")
    data = np.empty(len(pts), dtype=fields)
    data["x"], data["y"], data["z"] = pts[:, 0], pts[:, 1], pts[:, 2]
    if colors is not None:
        c = np.asarray(colors, dtype=np.uint8).reshape(-1, 3)
        data["red"], data["green"], data["blue"] = c[:, 0], c[:, 1], c[:, 2]
    with atomic_writer(path, "wb") as f:
        f.write(("\n".join(head) + "\n").encode("ascii"))
        f.write(data.tobytes())


def write_pcd(path: str | os.PathLike, points: np.ndarray, binary: bool = True) -> None:
    """Write points (N, 3) as a PCD (``DATA binary`` float32 or ``DATA ascii``), atomically."""
    pts = np.asarray(points, dtype="<f4").reshape(-1, 3)
    head = [
        "# .PCD v0.7 - Point Cloud Data file format (written by mbcal)",
        "VERSION 0.7", "FIELDS x y z", "SIZE 4 4 4", "TYPE F F F", "COUNT 1 1 1",
        f"WIDTH {len(pts)}", "HEIGHT 1", "VIEWPOINT 0 0 0 1 0 0 0", f"POINTS {len(pts)}",
        f"DATA {'binary' if binary else 'ascii'}",
    ]  # fmt: skip
    with atomic_writer(path, "wb") as f:
        f.write(("\n".join(head) + "\n").encode("ascii"))
        if binary:
            f.write(pts.tobytes())
        else:
            f.write("".join(f"{x:.9g} {y:.9g} {z:.9g}\n" for x, y, z in pts.astype(float)).encode("ascii"))


def write_xyz(path: str | os.PathLike, points: np.ndarray, delimiter: str = " ") -> None:
    """Write points (N, 3) as text, one per line (``.csv``: with an ``x,y,z`` header), atomically."""
    pts = np.asarray(points, dtype=float).reshape(-1, 3)
    lines = ["x,y,z"] if delimiter == "," else []
    lines += [delimiter.join(f"{v:.17g}" for v in row) for row in pts]
    with atomic_writer(path, "w") as f:
        f.write("\n".join(lines) + "\n")


def write_depth_png(path: str | os.PathLike, depth_m: np.ndarray, depth_scale: float = 1e-3) -> None:
    """Write a depth image (metres, NaN = no return) as a 16-bit PNG of counts, atomically."""
    from PIL import Image  # optional at import time: see _read_image

    counts = np.where(np.isfinite(depth_m), np.round(np.asarray(depth_m) / depth_scale), 0)
    if np.any(counts > 65535) or np.any(counts < 0):
        raise MeasurementFileError(f"{path}: depths beyond 0..{65535 * depth_scale:g} m do not fit 16 bits")
    with atomic_writer(path, "wb") as f:
        Image.fromarray(counts.astype(np.uint16)).save(f, format="PNG")
