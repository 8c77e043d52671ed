"""Headless rendering and overlays: what a model's camera sees, drawn over a real image.

Rendering uses pyrender off screen (EGL by default; set ``PYOPENGL_PLATFORM=osmesa`` for
OSMesa).  pyrender renders pinhole cameras only: lens distortion is not rendered, but every
line and point that mbcal *draws* (wireframes, measured points, residuals) is projected with
the camera's full model, distortion included.

Depth and occlusion come from a separate pass with multisampling off (pyrender's segmentation
mode): multisampled depth mixes the values of the surfaces that meet at an edge.
"""

from __future__ import annotations

import atexit
import contextlib
import io
import os
import shlex
import threading
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from mbcal.errors import MbcalError, RenderError
from mbcal.geometry.camera import project_camera_points
from mbcal.geometry.shapes import get_shape, shape_mesh
from mbcal.outputs import atomic_write

__all__ = [
    "RenderError",
    "View",
    "render_view",
    "shared_context",
    "wireframe_segments",
    "draw_overlay",
    "save_png",
    "plot_figure",
    "save_figure",
]

# OpenCV camera axes (x right, y down, z forward) → OpenGL's (x right, y up, z backward).
_CV_TO_GL = np.diag([1.0, -1.0, -1.0, 1.0])


def _headless() -> None:
    if "PYOPENGL_PLATFORM" not in os.environ:
        os.environ["PYOPENGL_PLATFORM"] = "egl"


def _pyrender():
    _headless()
    try:
        import pyrender  # optional: needs EGL/OSMesa, loaded when a view is rendered
    except Exception as err:  # missing GL libraries surface here
        raise RenderError(
            f"pyrender cannot start ({type(err).__name__}: {err})",
            hint="install Mesa's EGL (Debian: libegl1 libegl-mesa0 libgl1-mesa-dri) or set PYOPENGL_PLATFORM=osmesa",
        ) from None
    return pyrender


@dataclass
class View:
    """A rendered camera view.

    Attributes
    ----------
    color : (H, W, 3) uint8
        Shaded image (pinhole, no distortion).
    depth : (H, W) float
        Distance along the optical axis (m) of the nearest surface; 0 where there is none.
    shape_index : (H, W) int
        Index of the shape seen at each pixel (in ``model.shapes``), −1 for background.
    """

    color: np.ndarray
    depth: np.ndarray
    shape_index: np.ndarray


def _palette(n: int) -> np.ndarray:
    """Distinct, lightly shaded colours for n shapes."""
    rng = np.random.default_rng(7)
    hues = (np.arange(n) * 0.61803398875) % 1.0
    out = []
    for h in hues:
        i = int(h * 6)
        f = h * 6 - i
        v, s = 0.85, 0.35 + 0.2 * rng.random()
        p, q, t = v * (1 - s), v * (1 - s * f), v * (1 - s * (1 - f))
        out.append([(v, t, p), (q, v, p), (p, v, t), (p, q, v), (t, p, v), (v, p, q)][i % 6])
    return np.asarray(out)


def render_view(
    scene,
    camera: str,
    *,
    points: bool = False,
    point_radius: float = 0.004,
    background: tuple[float, float, float] = (0.92, 0.93, 0.95),
    color: bool = True,
    depth: bool = True,
) -> View:
    """Render a single scene (not a batch) from a model camera.

    Parameters
    ----------
    scene : Scene
    camera : str
        Camera name (a unique suffix is enough).
    points : bool
        Add small spheres at the named points.
    color, depth : bool
        Which passes to render: the shaded image, and the depth with the shape index.  A pass
        left out costs nothing and its arrays are empty (shape (0, 0, 3) and (0, 0)), so that a
        use of them fails rather than draws something wrong.
    """
    pyrender = _pyrender()
    import trimesh  # with pyrender: rendering's optional dependencies load on first use

    model = scene.model
    cam = scene.camera(camera)
    fx, fy, cx, cy, skew = (float(v) for v in np.asarray(cam.intrinsics))
    if abs(skew) > 1e-9:
        raise RenderError(f"camera '{camera}' has skew {skew:g}; rendering supports skew = 0 only")
    poses = np.asarray(scene.shape_poses, dtype=float)
    dims = np.asarray(scene.shape_dims, dtype=float)
    colors = _palette(len(model.shapes))
    for i, shape in enumerate(model.shapes):
        if get_shape(shape.kind).flat:
            colors[i] = (0.82, 0.82, 0.80)  # walls and floors in a neutral grey
    pr_scene = pyrender.Scene(bg_color=[*background, 1.0], ambient_light=[0.35, 0.35, 0.35])
    seg_map = {}
    for i, shape in enumerate(model.shapes):
        mesh = shape_mesh(shape.kind, dims[i], shape.mesh, two_sided=False)
        material = pyrender.MetallicRoughnessMaterial(
            baseColorFactor=[*colors[i], 1.0], metallicFactor=0.1, roughnessFactor=0.8, doubleSided=True
        )
        node = pr_scene.add(pyrender.Mesh.from_trimesh(mesh, material=material, smooth=False), pose=poses[i])
        seg_map[node] = _index_color(i)
    if points:
        pts = np.asarray(scene.points, dtype=float)
        marker = trimesh.creation.icosphere(subdivisions=2, radius=point_radius)
        material = pyrender.MetallicRoughnessMaterial(baseColorFactor=[0.9, 0.1, 0.1, 1.0])
        for k, p in enumerate(pts):
            T = np.eye(4)
            T[:3, 3] = p
            node = pr_scene.add(pyrender.Mesh.from_trimesh(marker, material=material), pose=T)
            seg_map[node] = _index_color(len(model.shapes) + k)
    znear = 0.01
    camera_node = pyrender.IntrinsicsCamera(fx=fx, fy=fy, cx=cx + 0.5, cy=cy + 0.5, znear=znear, zfar=100.0)
    T_gl = np.asarray(cam.T_world_camera, dtype=float) @ _CV_TO_GL
    pr_scene.add(camera_node, pose=T_gl)
    light = pyrender.DirectionalLight(color=np.ones(3), intensity=3.0)
    pr_scene.add(light, pose=T_gl)
    with _RENDERER.lock:
        renderer = _RENDERER.get(pyrender, cam.width, cam.height)
        try:
            image = renderer.render(pr_scene)[0][..., :3] if color else np.zeros((0, 0, 3), np.uint8)
            if depth:
                seg, z = renderer.render(pr_scene, flags=pyrender.RenderFlags.SEG, seg_node_map=seg_map)
            else:
                seg, z = np.zeros((0, 0, 3), np.uint8), np.zeros((0, 0))
        except Exception as err:
            _RENDERER.close()  # a context in an unknown state: the next view opens a new one
            # A driver's refusal (an image larger than its renderbuffers, out of memory) was a
            # traceback, read by the command line as a fit verdict (status 1): a RenderError is
            # bad input (status 2), naming the camera and its size.
            detail = " ".join(f"{type(err).__name__}: {err}".split())
            raise RenderError(
                f"cannot render camera '{camera}' ({cam.width}×{cam.height} px): "
                + (detail if len(detail) <= 300 else detail[:300] + " ..."),
                hint="a smaller image, or another OpenGL driver (PYOPENGL_PLATFORM=osmesa), may render",
            ) from err
        except BaseException:
            _RENDERER.close()
            raise
        if not _RENDERER.scopes:
            _RENDERER.close()
    index = seg[..., 0].astype(np.int64) * 65536 + seg[..., 1].astype(np.int64) * 256 + seg[..., 2]
    return View(color=np.ascontiguousarray(image), depth=np.asarray(z, dtype=float), shape_index=index - 1)


@contextlib.contextmanager
def shared_context() -> Iterator[None]:
    """Render every view inside the block with one off-screen OpenGL context.

    Opening a context (~60 ms with Mesa) and closing one (pyrender's ``delete`` runs a full
    garbage collection: ~50 ms in a process that holds JAX's programs) cost more than a view
    itself: ``mbcal demo`` draws six (issue 16).  Outside such a block each view opens and closes
    its own, because closing any pyrender context terminates the EGL display that every context
    of the process shares (a depth simulation between two views would break a kept context).
    Blocks nest; the context is closed when the outermost one ends.
    """
    with _RENDERER.lock:
        _RENDERER.scopes += 1
    try:
        yield
    finally:
        with _RENDERER.lock:
            _RENDERER.scopes -= 1
            if not _RENDERER.scopes:
                _RENDERER.close()


class _SharedRenderer:
    """The context of :func:`render_view`, used under a lock and kept while a
    :func:`shared_context` block is open.  pyrender makes it current for each render, resizes it
    when a view's size differs, and drops the previous scene's meshes from it when the next scene
    is drawn."""

    def __init__(self) -> None:
        self.lock = threading.RLock()
        self.scopes = 0
        self._renderer: Any = None
        atexit.register(self.close)

    def get(self, pyrender: Any, width: int, height: int) -> Any:
        if self._renderer is None:
            try:
                self._renderer = pyrender.OffscreenRenderer(width, height)
            except Exception as err:
                raise RenderError(
                    f"cannot open an off-screen OpenGL context ({type(err).__name__}: {err})",
                    hint="install Mesa's EGL (libegl1 libegl-mesa0 libgl1-mesa-dri) or set PYOPENGL_PLATFORM=osmesa",
                ) from None
        self._renderer.viewport_width, self._renderer.viewport_height = width, height
        return self._renderer

    def close(self) -> None:
        renderer, self._renderer = self._renderer, None
        if renderer is not None:
            try:
                renderer.delete()
            except Exception:  # a context that is already gone: nothing to free
                pass


_RENDERER = _SharedRenderer()


def _index_color(i: int) -> np.ndarray:
    """A segmentation colour encoding i + 1 (0 is the background)."""
    k = i + 1
    return np.array([(k >> 16) & 255, (k >> 8) & 255, k & 255], dtype=np.uint8)


# ---- wireframes -----------------------------------------------------------------------------------------


def _feature_edges(mesh, angle_deg: float = 25.0) -> np.ndarray:
    """Edges (k, 2) of a mesh where its faces bend by more than ``angle_deg``, and its borders."""
    import trimesh  # with pyrender: rendering's dependencies load on first use

    sharp = mesh.face_adjacency_edges[mesh.face_adjacency_angles > np.radians(angle_deg)]
    counts = trimesh.grouping.group_rows(mesh.edges_sorted, require_count=1)
    border = mesh.edges_sorted[counts] if len(counts) else np.zeros((0, 2), dtype=np.int64)
    return np.vstack([sharp, border]) if len(border) else sharp


def _silhouette_edges(mesh, eye: np.ndarray) -> np.ndarray:
    """Edges between a face turned towards ``eye`` and one turned away."""
    normals = mesh.face_normals
    centers = mesh.triangles_center
    facing = np.einsum("ij,ij->i", normals, eye - centers) > 0
    adj = mesh.face_adjacency
    flip = facing[adj[:, 0]] != facing[adj[:, 1]]
    return mesh.face_adjacency_edges[flip]


def _border_edges(mesh) -> np.ndarray:
    """Edges that belong to one face only: the outline of a one-sided flat shape."""
    import trimesh  # as above

    return mesh.edges_sorted[trimesh.grouping.group_rows(mesh.edges_sorted, require_count=1)]


def wireframe_segments(scene, camera: str) -> np.ndarray:
    """World-space edges (k, 2, 3) of every shape as seen from ``camera``: feature edges,
    silhouettes and borders (occlusion is not applied here)."""
    model = scene.model
    eye = np.asarray(scene.camera(camera).center, dtype=float)
    poses = np.asarray(scene.shape_poses, dtype=float)
    dims = np.asarray(scene.shape_dims, dtype=float)
    out = []
    for i, shape in enumerate(model.shapes):
        kind = get_shape(shape.kind)
        if not kind.bounded:
            continue  # an infinite surface has no edges
        mesh = kind.trimesh(dims[i], shape.mesh, sections=64, two_sided=not kind.flat)
        mesh.apply_transform(poses[i])
        if kind.flat:
            edges = _border_edges(mesh)
        else:
            edges = np.vstack([_feature_edges(mesh), _silhouette_edges(mesh, eye)])
        out.append(mesh.vertices[edges])
    return np.concatenate(out) if out else np.zeros((0, 2, 3))


def _visible_samples(scene, camera: str, view: View, segments: np.ndarray, step_px: float = 1.0) -> list:
    """For every world segment, its pixels along its length and whether each is visible.

    All segments are sampled and projected at once (numpy); a sample is visible when no
    surface of the rendered depth lies in front of it.
    """
    if len(segments) == 0:
        return []
    cam = scene.camera(camera)
    T = np.asarray(cam.T_world_camera, dtype=float)
    R, t = T[:3, :3], T[:3, 3]
    K = np.asarray(cam.intrinsics, dtype=float)
    dist = np.asarray(cam.distortion, dtype=float)
    fx, fy, cx, cy, _ = K
    c = (segments - t) @ R  # (k, 2, 3) camera frame
    z = np.maximum(c[..., 2], 1e-3)
    pin = np.stack([fx * c[..., 0] / z + cx, fy * c[..., 1] / z + cy], axis=-1)
    length = np.linalg.norm(pin[:, 1] - pin[:, 0], axis=-1)
    counts = np.clip(np.nan_to_num(length / step_px, nan=2.0), 2, 4000).astype(int)
    seg_id = np.repeat(np.arange(len(segments)), counts)
    offsets = np.concatenate([[0], np.cumsum(counts)[:-1]])
    s = (np.arange(counts.sum()) - np.repeat(offsets, counts)) / np.repeat(counts - 1, counts)
    pts = c[seg_id, 0] * (1 - s[:, None]) + c[seg_id, 1] * s[:, None]
    front = pts[:, 2] > 1e-3
    zz = np.where(front, pts[:, 2], 1.0)
    u, v = fx * pts[:, 0] / zz + cx, fy * pts[:, 1] / zz + cy
    H, W = view.depth.shape
    iu, iv = np.round(u).astype(int), np.round(v).astype(int)
    inside = front & (iu >= 0) & (iu < W) & (iv >= 0) & (iv < H)
    iu_c, iv_c = np.clip(iu, 1, W - 2), np.clip(iv, 1, H - 2)
    # The deepest surface in a 3×3 neighbourhood: an edge lies on the surfaces it bounds.
    hood = np.stack([view.depth[iv_c + dv, iu_c + du] for dv in (-1, 0, 1) for du in (-1, 0, 1)])
    empty = np.any(hood == 0.0, axis=0)
    tol = 2e-3 + 0.01 * pts[:, 2]
    visible = inside & (empty | (pts[:, 2] <= hood.max(axis=0) + tol))
    with np.errstate(all="ignore"):
        pixels = project_camera_points(pts, K, dist, np)
    bounds = np.cumsum(counts)[:-1]
    return list(zip(np.split(pixels, bounds), np.split(visible, bounds)))


# ---- drawing ----------------------------------------------------------------------------------------------


@dataclass
class Layer:
    """Something to draw over an image."""

    kind: str  # "wireframe" | "points" | "vectors" | "labels"
    data: Any
    color: tuple[int, int, int]
    width: float = 1.5
    label: str | None = None


def _font(size: int):
    """DejaVu Sans (shipped with matplotlib) for legends; Pillow's bitmap font if it is missing."""
    from PIL import ImageFont  # pillow: loaded when a picture is drawn

    try:
        return ImageFont.truetype(_font_file(), size)
    except Exception:  # no matplotlib font: the default font lacks some symbols but works
        return ImageFont.load_default()


def _font_file() -> str:
    """matplotlib's copy of DejaVu Sans, found without importing matplotlib (~0.25 s, issue 16)."""
    import importlib.util  # only to find the file

    spec = importlib.util.find_spec("matplotlib")
    for folder in (spec.submodule_search_locations or []) if spec is not None else []:
        path = os.path.join(folder, "mpl-data", "fonts", "ttf", "DejaVuSans.ttf")
        if os.path.isfile(path):
            return path
    from matplotlib import font_manager  # heavy: a matplotlib laid out differently

    return font_manager.findfont("DejaVu Sans", fallback_to_default=True)


def draw_overlay(image: np.ndarray, layers: Sequence[Layer], *, supersample: int = 2, legend: bool = True):
    """Draw layers over an RGB image; returns a PIL image.

    Wireframe data: a list of (pixels (k, 2), visible (k,)) runs; points: (n, 2) pixels;
    vectors: (n, 2, 2) pixel pairs (from, to); labels: list of (pixel, text).
    """
    from PIL import Image, ImageDraw  # pillow: loaded when a picture is drawn

    base = Image.fromarray(np.asarray(image, dtype=np.uint8)).convert("RGB")
    W, H = base.size
    k = supersample
    big = base.resize((W * k, H * k), Image.Resampling.BICUBIC)
    draw = ImageDraw.Draw(big)
    for layer in layers:
        lw = max(1, int(round(layer.width * k)))
        if layer.kind == "wireframe":
            for pixels, visible in layer.data:
                # Which samples to draw, for the whole run at once (per sample: 0.15 s a demo).
                xy = np.asarray(pixels, dtype=float).reshape(-1, 2)
                shown = np.asarray(visible, dtype=bool).reshape(-1)[: len(xy)]
                xy = xy[: len(shown)]
                good = (shown & np.isfinite(xy).all(axis=1)).tolist()
                run = []
                for p, ok in zip(((xy + 0.5) * k).tolist(), good):
                    if ok:
                        run.append((p[0], p[1]))
                    elif len(run) > 1:
                        draw.line(run, fill=layer.color, width=lw)
                        run = []
                    else:
                        run = []
                if len(run) > 1:
                    draw.line(run, fill=layer.color, width=lw)
        elif layer.kind == "points":
            r = 4 * k
            for p in np.asarray(layer.data).reshape(-1, 2):
                if np.all(np.isfinite(p)):
                    x, y = (p[0] + 0.5) * k, (p[1] + 0.5) * k
                    draw.ellipse([x - r, y - r, x + r, y + r], outline=layer.color, width=lw)
        elif layer.kind == "vectors":
            for a, b in np.asarray(layer.data).reshape(-1, 2, 2):
                if np.all(np.isfinite(a)) and np.all(np.isfinite(b)):
                    draw.line(
                        [((a[0] + 0.5) * k, (a[1] + 0.5) * k), ((b[0] + 0.5) * k, (b[1] + 0.5) * k)],
                        fill=layer.color,
                        width=lw,
                    )
                    tip = 1.5 * k
                    draw.ellipse(
                        [
                            (b[0] + 0.5) * k - tip,
                            (b[1] + 0.5) * k - tip,
                            (b[0] + 0.5) * k + tip,
                            (b[1] + 0.5) * k + tip,
                        ],
                        fill=layer.color,
                    )
        elif layer.kind == "labels":
            font = _font(11 * k)
            for p, text in layer.data:
                draw.text(((p[0] + 6) * k, (p[1] - 6) * k), text, fill=layer.color, font=font)
    out = big.resize((W, H), Image.Resampling.LANCZOS)
    if legend:
        entries = [(lay.label, lay.color) for lay in layers if lay.label]
        if entries:
            d = ImageDraw.Draw(out)
            font = _font(12)
            width = max(d.textlength(text, font=font) for text, _ in entries)
            d.rectangle([2, 2, 30 + width, 6 + 16 * len(entries)], fill=(255, 255, 255))
            y = 5
            for text, color in entries:
                d.rectangle([6, y + 4, 20, y + 10], fill=color)
                d.text((26, y), text, fill=(20, 20, 20), font=font)
                y += 16
    return out


def wireframe_layer(scene, camera: str, view: View, color, label: str | None = None, width: float = 1.5) -> Layer:
    """The model's visible edges as seen by ``camera`` (occlusion from ``view``'s depth)."""
    return Layer(
        "wireframe", _visible_samples(scene, camera, view, wireframe_segments(scene, camera)), color, width, label
    )


def save_png(image, path) -> None:
    """Write a PIL image or an array as PNG, atomically."""
    from PIL import Image  # pillow: loaded when a picture is written

    if not isinstance(image, Image.Image):
        image = Image.fromarray(np.asarray(image, dtype=np.uint8))
    buf = io.BytesIO()
    image.save(buf, format="PNG")
    atomic_write(path, buf.getvalue())


def plot_figure(nrows: int = 1, ncols: int = 1, *, figsize: tuple[float, float], layout: Any = None, **subplots: Any):
    """(figure, axes (nrows, ncols)): a matplotlib figure drawn by the Agg renderer, made without
    pyplot — so a plot never switches the caller's backend (a notebook's inline one, say) and
    leaves nothing in pyplot's list of open figures to close."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg  # heavy: loaded when a plot is made
    from matplotlib.figure import Figure

    fig = Figure(figsize=figsize, layout=layout)
    FigureCanvasAgg(fig)
    return fig, fig.subplots(nrows, ncols, squeeze=False, **subplots)  # layout: None or "constrained"


def save_figure(fig, path, *, dpi: int = 110) -> None:
    """Write a figure of :func:`plot_figure` as PNG, atomically."""
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi)
    atomic_write(path, buf.getvalue())


def check_image_path(path) -> None:
    """Refuse a folder given where an image is expected, with the glob that was likely meant
    (``mbcal detect DIR`` said only "[Errno 21] Is a directory")."""
    if Path(path).is_dir():
        pattern = shlex.quote(str(Path(path))) + "/*.png"  # the glob outside the quotes: the shell expands it
        raise MbcalError(f"{path} is a folder, not an image", hint=f"give the images, e.g. {pattern}")


def _wide_grey(img) -> bool:
    """A greyscale image of more than 8 bits a pixel: 16-bit (``I;16``, ``I;16B``…, a mono
    machine-vision camera's PNG or TIFF), 32-bit integer (``I``) or floating point (``F``)."""
    return img.mode in ("I", "F") or img.mode.startswith("I;16")


def _to_8_bits(values: np.ndarray) -> np.ndarray:
    """A wide greyscale image as (H, W, 3) uint8, scaled linearly from its own range (its darkest
    pixel 0, its brightest 255): a 10- or 12-bit sensor's values in a 16-bit file, or a float
    image, have no fixed full scale.  Pillow's convert("RGB") clipped every value above 255 to
    white, and a 16-bit image of a target became a white page ("board not found").  Pixels that
    are not finite (a float image's NaN) become 0; an image of one value is black."""
    a = np.asarray(values, dtype=np.float64)
    finite = np.isfinite(a)
    out = np.zeros(a.shape, dtype=np.uint8)
    if finite.any():
        lo, hi = float(a[finite].min()), float(a[finite].max())
        if hi > lo:
            out[finite] = np.clip(np.rint((a[finite] - lo) * (255.0 / (hi - lo))), 0, 255).astype(np.uint8)
    return np.repeat(out[..., None], 3, axis=2)


def load_image(path) -> np.ndarray:
    """An RGB image from a file, as (H, W, 3) uint8.  A greyscale image of more than 8 bits a
    pixel (16-bit, 32-bit, float) is scaled from its own darkest to its brightest value
    (:func:`_to_8_bits`)."""
    from PIL import Image, UnidentifiedImageError  # pillow: loaded when a picture is read

    check_image_path(path)
    try:
        with Image.open(path) as img:
            if _wide_grey(img):
                return _to_8_bits(np.asarray(img))
            return np.asarray(img.convert("RGB"))
    except FileNotFoundError:
        raise MbcalError(f"image not found: {path}") from None
    except (UnidentifiedImageError, OSError) as err:
        raise MbcalError(f"cannot read image {path}: {err}") from None
