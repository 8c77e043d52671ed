"""The studio's engine: the model, what it looks like from each camera, observe, solve and save.

Everything numeric is mbcal's library: :func:`mbcal.language.load_model`, the modeler (compiled
once per model and reused for every slider move), :func:`mbcal.api.observe`,
:func:`mbcal.api.calibrate` with random restarts, :func:`mbcal.measurements.io.write_measurements`,
the calibrated-model export and the overlay pictures of :mod:`mbcal.render.overlays`.

No path given by the page is ever opened: photos are referred to by ids the engine made, the
model and measurement files are those named on the command line, and every output goes under
the ``--out`` folder with a fixed name.
"""

from __future__ import annotations

import contextlib
import json
import math
import re
import threading
import time
from collections.abc import Mapping, Sequence
from dataclasses import astuple, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from mbcal._jax import jax, jnp
from mbcal.api import calibrate, observe
from mbcal.errors import MbcalError
from mbcal.geometry.camera import project_camera_points
from mbcal.geometry.raycast import cast_rays
from mbcal.geometry.shapes import get_shape
from mbcal.language import load_model
from mbcal.language.model import Model
from mbcal.measurements.io import read_measurements, write_measurements
from mbcal.measurements.sets import MeasurementSet, measurements_from_records, merge_measurements
from mbcal.modeling import modeler
from mbcal.outputs import all_or_nothing, atomic_write, check_output, check_output_folder, make_output_folder
from mbcal.studio.session import SESSION_FILE, Click, Session, load_session, save_session

__all__ = ["Engine", "Photo", "error_json", "MAX_CLICKS", "MAX_RESTARTS_STUDIO", "STALE_SOLVE"]

MAX_CLICKS = 5000
MAX_RESTARTS_STUDIO = 256
STALE_SOLVE = (
    "the clicks, unknowns or values were edited (or the model reloaded) while the solve ran: its "
    "result is not used (nor saved, nor set on the sliders); solve again"
)
"""What the page says of a solve whose inputs changed before it finished."""
OVERLAYS_MANIFEST = ".studio-overlays.json"
"""In ``--out/overlays``: the pictures the last Save drew (the next one removes those it does not redraw)."""
_OVERLAY_NAME = re.compile(r"[A-Za-z0-9_-]+_(before|after)\.png")
_RENDER_LOCK = threading.Lock()
IMAGE_TYPES = {".png": "image/png", ".jpg": "image/jpeg", ".jpeg": "image/jpeg"}


def error_json(err: MbcalError, what: str = "the model") -> dict[str, Any]:
    """An mbcal error for the page: ``file:line:col: message``, the source line and the column;
    ``what`` is the input to fix ("the model", "the measurement file bad.csv")."""
    text = err.render()
    out: dict[str, Any] = {
        "message": str(err),
        "text": text,
        "location": None,
        "source": None,
        "column": None,
        "what": what,
    }
    if err.span is not None:
        out["location"] = str(err.span)
        out["column"] = err.span.column
        lines = text.splitlines()
        if len(lines) > 1 and lines[1].startswith("    "):
            out["source"] = lines[1][4:]
    return out


@dataclass
class Photo:
    """A photo named on the command line: the page refers to it by ``id`` only."""

    id: str
    camera: str  # as given; resolved against the model when it loads
    config: str
    path: Path
    width: int = 0
    height: int = 0

    @property
    def media_type(self) -> str:
        return IMAGE_TYPES.get(self.path.suffix.lower(), "application/octet-stream")


@dataclass
class _ShapeEdges:
    """A shape's mesh in its own frame and the edges that do not depend on the eye."""

    vertices: np.ndarray  # (v, 3)
    fixed: np.ndarray  # (k, 2) vertex indices: feature edges and borders
    adjacency: np.ndarray  # (a, 2) faces sharing an edge
    adjacency_edges: np.ndarray  # (a, 2) that edge
    normals: np.ndarray  # (f, 3)
    centers: np.ndarray  # (f, 3)
    flat: bool


def _shape_edges(kind_name: str, dims: np.ndarray, mesh_data) -> _ShapeEdges | None:
    import trimesh  # with pyrender: loaded when the first wireframe is drawn

    kind = get_shape(kind_name)
    if not kind.bounded:
        return None
    mesh = kind.trimesh(dims, mesh_data, sections=48, two_sided=False)
    counts = trimesh.grouping.group_rows(mesh.edges_sorted, require_count=1)
    border = mesh.edges_sorted[counts] if len(counts) else np.zeros((0, 2), dtype=np.int64)
    if kind.flat:
        fixed = border
    else:
        sharp = mesh.face_adjacency_edges[mesh.face_adjacency_angles > np.radians(25.0)]
        fixed = np.vstack([sharp, border])
    return _ShapeEdges(
        np.asarray(mesh.vertices, dtype=float),
        np.asarray(fixed, dtype=np.int64).reshape(-1, 2),
        np.asarray(mesh.face_adjacency, dtype=np.int64).reshape(-1, 2),
        np.asarray(mesh.face_adjacency_edges, dtype=np.int64).reshape(-1, 2),
        np.asarray(mesh.face_normals, dtype=float),
        np.asarray(mesh.triangles_center, dtype=float),
        kind.flat,
    )


def _tenths(pixels: np.ndarray) -> list[int]:
    """Pixels (k, m, 2) as a flat list of integers in tenths of a pixel (compact, fast JSON)."""
    return np.round(pixels * 10.0).astype(np.int64).ravel().tolist()


def _object_of(shape_name: str) -> str:
    return shape_name.rsplit(".", 1)[0] if "." in shape_name else shape_name


_MISSING = object()

_UNSAFE_IN_NAMES = re.compile(r"[\x00-\x1f/\\]")
"""What a name that travels in the page's requests may not hold (the server's ``Name`` rule)."""

MAX_EDGE_SETS = 256
"""Edge sets kept per loaded model (one per shape and size seen): a bound on the memory a long
session of slider drags takes."""


@dataclass
class _Loaded:
    """A model that loaded, with its compiled modeler and measurement files."""

    model: Model
    inputs: MeasurementSet | None
    scene_fn: Any
    occlusion_fn: Any = None
    warm: threading.Event = field(default_factory=threading.Event)  # compiled: first calls done
    edges: dict[tuple[int, bytes], _ShapeEdges | None] = field(default_factory=dict)


class Engine:
    """The studio's state and its computations; the server calls it, one request at a time.

    Parameters
    ----------
    model_path : path
        The model (.mdl or .urdf).
    measurement_paths : paths
        Measurement files: their image points become clicks (when no session exists yet), the
        rest (and their known values and configurations) join every solve.
    photos : sequence of (camera, config, path)
    out : path
        The only folder the studio writes into.
    """

    def __init__(
        self,
        model_path: str | Path,
        measurement_paths: Sequence[str | Path] = (),
        photos: Sequence[tuple[str, str, str | Path]] = (),
        out: str | Path = "mbcal-studio",
    ):
        self.model_path = Path(model_path)
        self.measurement_paths = [Path(p) for p in measurement_paths]
        # --out is made last, once everything else is valid: a refused start leaves no folder.
        self.out = check_output_folder(out, "--out")
        self.photos: dict[str, Photo] = {}
        for i, (camera, config, path) in enumerate(photos):
            if not config or _UNSAFE_IN_NAMES.search(config):
                raise MbcalError(f"configuration name {config!r}: a name without '/', '\\' or control characters")
            p = Path(path)
            if not p.is_file():
                raise MbcalError(f"photo not found: {p}")
            if p.suffix.lower() not in IMAGE_TYPES:
                raise MbcalError(f"{p}: photos must be PNG or JPEG")
            from PIL import Image  # pillow: only the photo's size is read here

            try:
                with Image.open(p) as img:
                    width, height = img.size
            except OSError as err:
                raise MbcalError(f"cannot read photo {p}: {err}") from None
            self.photos[f"p{i}"] = Photo(f"p{i}", camera, config, p, width, height)
        self.lock = threading.RLock()
        self._save_lock = threading.Lock()  # one Save at a time: each reads what the last one drew
        self._edges_lock = threading.Lock()
        self.loaded: _Loaded | None = None
        self.error: dict[str, Any] | None = None
        self.notes: list[str] = []
        self.session = Session()
        self.result: Any = None
        # "stale": what the page says when a solve finished after an edit (its result not used)
        self.solve_state: dict[str, Any] = {
            "running": False,
            "messages": [],
            "error": None,
            "done": False,
            "stale": None,
        }
        self._next_id = 1
        model_name = str(self.model_path.resolve())
        for photo in self.photos.values():  # Save draws into out/overlays: never over a photo
            if _inside(photo.path, self.out / "overlays"):
                raise MbcalError(f"photo {photo.path} is inside {self.out / 'overlays'}, which Save writes into")
        restored = load_session(self.session_path)
        if restored is not None and restored.model and restored.model != model_name:
            # Another model's clicks: dropping them here would lose that session (its file is
            # rewritten at once below).
            raise MbcalError(
                f"{self.session_path} holds a session of {restored.model}",
                hint=f"give another --out for {self.model_path.name}, or move that session away",
            )
        self.load(start=True)
        # A start with a broken model or measurement file: the files' clicks are taken at the first
        # Reload that loads them (they were lost: the empty session saved meant 'restored' after).
        self._inputs_pending = restored is None and self.loaded is None
        if restored is not None:
            self.session = restored
            self._keep_valid_clicks("restored from " + str(self.session_path))
        elif self.loaded is not None and self.loaded.inputs is not None:
            self._clicks_from_inputs()
        self.session.model = model_name
        self._next_id = self._max_id() + 1
        with all_or_nothing():  # the folders made are removed again if the session cannot be written
            make_output_folder(self.out)
            if not self._inputs_pending:  # else a restart would restore no clicks, not read the files'
                self.save_session()
        self._start_warm_up()

    # ---- files ---------------------------------------------------------------------------------------

    @property
    def session_path(self) -> Path:
        return self.out / SESSION_FILE

    @property
    def inputs(self) -> list[Path]:
        return [self.model_path, *self.measurement_paths, *(p.path for p in self.photos.values())]

    def save_session(self, session: Session | None = None) -> None:
        try:
            save_session(self.session if session is None else session, self.session_path)
        except OSError as err:
            raise MbcalError(f"cannot save the session to {self.session_path}: {err.strerror or err}") from None

    # ---- the model -----------------------------------------------------------------------------------

    def load(self, *, start: bool = False) -> bool:
        """(Re)load the model and the measurement files; on error keep the message for the page.

        A photo whose camera the model lacks is the model's error on a reload (the camera was
        renamed: fix the model), but the command line's at ``start`` (a wrong ``--image``): raised.
        """
        with self.lock:
            try:
                model = load_model(self.model_path)
            except MbcalError as err:
                self.error = error_json(err)
                return False
            # a measurement file's error is that file's to fix, not the model's
            sets = []
            for path in self.measurement_paths:
                try:
                    sets.append(read_measurements(path, model))
                except MbcalError as err:
                    self.error = error_json(err, f"the measurement file {path}")
                    return False
            try:
                inputs = merge_measurements(sets, model) if sets else None
            except MbcalError as err:
                self.error = error_json(err, "the measurement files")
                return False
            try:
                self._check_photo_cameras(model)
            except MbcalError as err:
                if start:
                    raise
                self.error = error_json(err)
                return False
            scene_fn = jax.jit(lambda X: modeler(model, X))
            self.loaded = _Loaded(model, inputs, scene_fn)
            self.error = None
            self.result = None
        return True

    def _check_photo_cameras(self, model: Model) -> None:
        for photo in self.photos.values():
            try:
                model.resolve("camera", photo.camera)
            except MbcalError as err:  # named as given on the command line
                given = photo.camera + ("" if photo.config == "default" else f"@{photo.config}")
                raise MbcalError(f"--image {given}={photo.path}: {err.message}", hint=err.hint) from None

    def _start_warm_up(self) -> None:
        """Compile the projections while the browser opens the page (the first draw is then quick);
        only once the studio has started (a refused start compiles nothing)."""
        if self.loaded is not None and self.error is None:
            warm_up = threading.Thread(target=self._warm_up, args=(self.loaded,), name="mbcal-studio-warm-up")
            warm_up.daemon = True
            warm_up.start()

    def _warm_up(self, loaded: _Loaded) -> None:
        try:
            for photo_id in list(self.photos)[:1]:
                self.projection(photo_id)
        except Exception:  # a failure shows when the page asks for the overlay; nothing to do here
            pass
        finally:
            loaded.warm.set()

    def reload(self) -> dict[str, Any]:
        """Reload after the model file changed: clicks whose names still exist are kept."""
        ok = self.load()
        if ok and self._inputs_pending:
            assert self.loaded is not None
            try:
                if self.loaded.inputs is not None:
                    self._clicks_from_inputs()
            except MbcalError as err:  # a correlated σ (refused at start): the file's to fix
                self.session.clicks = []
                self.error, self.loaded = error_json(err, "the measurement files"), None
                return {"ok": False, "error": self.error, "notes": self.notes}
            self._inputs_pending = False
            self._next_id = self._max_id() + 1
        if ok:
            self._keep_valid_clicks("kept after reloading")
            self._start_warm_up()
            self.save_session()
        return {"ok": ok, "error": self.error, "notes": self.notes}

    def _keep_valid_clicks(self, why: str) -> None:
        if self.loaded is None:
            return
        model = self.loaded.model
        keep: list[Click] = []
        dropped: list[Click] = []
        for c in self.session.clicks:
            (keep if model.has("point", c.point) and model.has("camera", c.camera) else dropped).append(c)
        self.session.clicks = keep
        self.session.values = {k: v for k, v in self.session.values.items() if model.has("param", k.split("@")[0])}
        self.notes = [f"{len(keep)} click(s) {why}"]
        if dropped:
            names = ", ".join(sorted({c.point for c in dropped}))
            self.notes.append(f"{len(dropped)} click(s) dropped: the model no longer has {names}")

    def _clicks_from_inputs(self) -> None:
        assert self.loaded is not None and self.loaded.inputs is not None
        taken = {m.id for m in self.loaded.inputs}
        for m in self.loaded.inputs:
            if m.kind == "image_point" and m.value is not None:
                if np.any(m.cov != np.diag(np.diag(m.cov))):  # a click holds σ of u and of v, no correlation
                    raise MbcalError(
                        f"image point '{m.id}' has a covariance with correlation ('cov'); the studio's clicks "
                        "hold a σ of u and a σ of v only",
                        span=m.where,
                        hint="give sigma_u and sigma_v instead, or solve that file with mbcal solve",
                    )
                sigma_u, sigma_v = (float(s) for s in m.sigma)
                cid = _UNSAFE_IN_NAMES.sub("_", m.id)  # ids travel in the page's requests: no slashes
                if cid != m.id:  # cleaned: made unique again ('a/1' and 'a_1' are both in the file)
                    base, k = cid, 2
                    while cid in taken:
                        cid, k = f"{base}_{k}", k + 1
                    taken.add(cid)
                self.session.clicks.append(
                    Click(
                        cid,
                        m.refs["camera"],
                        m.config,
                        m.refs["point"],
                        float(m.value[0]),
                        float(m.value[1]),
                        sigma_u,
                        None if sigma_v == sigma_u else sigma_v,
                    )
                )

    def _max_id(self) -> int:
        best = 0
        for c in self.session.clicks:
            if c.id.startswith("c") and c.id[1:].isdigit():
                best = max(best, int(c.id[1:]))
        return best

    def require_model(self) -> _Loaded:
        if self.loaded is None or self.error is not None:
            what = self.error["what"] if self.error else "the model"
            where = self.error["location"] if self.error else str(self.model_path)
            raise MbcalError(f"{what} did not load ({where}); fix it and press Reload")
        return self.loaded

    def configurations(self) -> list[str]:
        names = ["default"]
        if self.loaded is not None and self.loaded.inputs is not None:
            names += list(self.loaded.inputs.configurations) + self.loaded.inputs.config_names
        names += [p.config for p in self.photos.values()]
        names += [c.config for c in self.session.clicks]
        return list(dict.fromkeys(names))

    def state(self) -> dict[str, Any]:
        """What the page needs to draw itself."""
        with self.lock:
            out: dict[str, Any] = {
                "model": self.model_path.name,
                "out": str(self.out),
                "error": self.error,
                "notes": self.notes,
                "session": self.session.to_json(),
                "configurations": self.configurations(),
                "photos": [
                    {"id": p.id, "camera": p.camera, "config": p.config, "width": p.width, "height": p.height}
                    for p in self.photos.values()
                ],
                "next_id": self._next_id,
            }
            if self.loaded is None:
                return out
            model = self.loaded.model
            for photo in out["photos"]:
                try:
                    photo["camera"] = model.resolve("camera", photo["camera"])
                except MbcalError:
                    pass  # the error is already shown (the model that loaded has no such camera)
            out["cameras"] = [
                {"name": c.name, "short": model.short_name("camera", c.name), "width": c.width, "height": c.height}
                for c in model.cameras
            ]
            out["points"] = [{"name": p.name, "short": model.short_name("point", p.name)} for p in model.points]
            out["params"] = [
                {
                    "name": p.name,
                    "unit": p.unit,
                    "nominal": p.nominal,
                    "lower": p.lower,
                    "upper": p.upper,
                    "per_configuration": p.per_configuration,
                }
                for p in model.params
            ]
            out["objects"] = list(dict.fromkeys(_object_of(s.name) for s in model.shapes))
            return out

    # ---- projections ---------------------------------------------------------------------------------

    def _X(self, loaded: _Loaded, config: str, values: Mapping[str, float]) -> np.ndarray:
        model = loaded.model
        X = model.nominal.copy()
        if loaded.inputs is not None:
            for k, v in loaded.inputs.known.items():
                X[model.param_index(k)] = v
            for k, v in loaded.inputs.configurations.get(config, {}).items():
                X[model.param_index(k)] = v
        for k, v in values.items():
            if model.has("param", k):
                X[model.param_index(k)] = float(v)
        suffix = "@" + config
        for k, v in values.items():  # a per-configuration estimate (name@config) for this photo's configuration
            if k.endswith(suffix) and model.has("param", k[: -len(suffix)]):
                X[model.param_index(k[: -len(suffix)])] = float(v)
        return X

    def _scene(self, loaded: _Loaded, X: np.ndarray) -> dict[str, np.ndarray]:
        s = loaded.scene_fn(jnp.asarray(X, dtype=jnp.float64))
        return {
            "frame_poses": np.asarray(s.frame_poses),
            "points": np.asarray(s.points),
            "K": np.asarray(s.camera_intrinsics),
            "dist": np.asarray(s.camera_distortion),
            "shape_poses": np.asarray(s.shape_poses),
            "shape_dims": np.asarray(s.shape_dims),
        }

    def _edges(self, loaded: _Loaded, i: int, dims: np.ndarray) -> _ShapeEdges | None:
        key = (i, np.round(dims, 9).tobytes())
        found = loaded.edges.get(key, _MISSING)
        if found is not _MISSING:
            return found  # type: ignore[return-value]
        shape = loaded.model.shapes[i]
        edges = _shape_edges(shape.kind, dims, shape.mesh)  # outside the lock: overlays run in parallel
        with self._edges_lock:
            while len(loaded.edges) >= MAX_EDGE_SETS:  # a slider dragged through many sizes: the oldest go
                del loaded.edges[next(iter(loaded.edges))]
            loaded.edges[key] = edges
        return edges

    def projection(
        self, photo_id: str, values: Mapping[str, float] | None = None, *, occlusion: bool = True
    ) -> dict[str, Any]:
        """The model as the photo's camera sees it at ``values``: polylines per object, point pixels.

        With ``occlusion`` the edges (and points) that a surface of the model hides from the camera
        are left out (points are marked ``hidden``): a ray is cast from the camera to the middle of
        every piece of edge, with mbcal's differentiable ray caster (compiled once per model).
        """
        with self.lock:
            loaded = self.require_model()
        if not loaded.warm.is_set() and threading.current_thread().name != "mbcal-studio-warm-up":
            loaded.warm.wait(timeout=600)  # the warm-up is compiling: wait for it, not compile twice
        with self.lock:
            photo = self._photo(photo_id)
            model = loaded.model
            cam_name = model.resolve("camera", photo.camera)
            ci = model.camera_index(cam_name)
            X = self._X(loaded, photo.config, self.session.values if values is None else values)
            scene = self._scene(loaded, X)
        T = scene["frame_poses"][model.cameras[ci].frame]
        R, t = T[:3, :3], T[:3, 3]
        K, dist = scene["K"][ci], scene["dist"][ci]
        # The edges of every shape, grouped by object: feature edges and borders, and silhouettes.
        names: list[str] = []
        segs: list[np.ndarray] = []
        owners: list[np.ndarray] = []
        for i, shape in enumerate(model.shapes):
            e = self._edges(loaded, i, scene["shape_dims"][i])
            if e is None:
                continue
            P = scene["shape_poses"][i]
            verts = e.vertices @ P[:3, :3].T + P[:3, 3]
            pairs = e.fixed
            if not e.flat and len(e.adjacency):
                normals = e.normals @ P[:3, :3].T
                centers = e.centers @ P[:3, :3].T + P[:3, 3]
                facing = np.einsum("ij,ij->i", normals, t - centers) > 0
                flip = facing[e.adjacency[:, 0]] != facing[e.adjacency[:, 1]]
                pairs = np.vstack([pairs, e.adjacency_edges[flip]])
            if len(pairs) == 0:
                continue
            obj = _object_of(shape.name)
            if obj not in names:
                names.append(obj)
            segs.append(verts[pairs])
            owners.append(np.full(len(pairs), names.index(obj)))
        a, b, owner = self._pieces(np.concatenate(segs) if segs else np.zeros((0, 2, 3)), owners, R, t, K, dist)
        pts_c = (scene["points"] - t) @ R
        hidden = np.zeros(len(model.points), dtype=bool)
        if occlusion and len(model.shapes):
            mid_world = ((a + b) / 2) @ R.T + t
            seen = self._visible(loaded, scene, t, np.concatenate([mid_world, scene["points"]]))
            hidden = ~seen[len(a) :]
            keep = seen[: len(a)]
            a, b, owner = a[keep], b[keep], owner[keep]
        with np.errstate(all="ignore"):
            pix = project_camera_points(np.stack([a, b], axis=1), K, dist, np)  # (n, 2, 2)
        good = np.all(np.isfinite(pix), axis=(1, 2)) & np.all(np.abs(pix) < 1e5, axis=(1, 2))
        paths = {}
        for k, name in enumerate(names):
            mine = good & (owner == k)
            paths[name] = [[2, _tenths(pix[mine])]] if np.any(mine) else []
        ppix = project_camera_points(np.where(pts_c[:, 2:3] > 1e-6, pts_c, 1.0), K, dist, np)
        points = []
        for p, (u, v), z, h in zip(model.points, ppix, pts_c[:, 2], hidden):
            ok = bool(z > 1e-6 and math.isfinite(u) and math.isfinite(v))
            points.append(
                {
                    "name": p.name,
                    "u": round(float(u), 3) if ok else None,
                    "v": round(float(v), 3) if ok else None,
                    "hidden": bool(h),
                }
            )
        return {"photo": photo.id, "camera": cam_name, "config": photo.config, "points": points, "paths": paths}

    @staticmethod
    def _pieces(segs: np.ndarray, owners: list[np.ndarray], R, t, K, dist):
        """World segments (k, 2, 3) in front of the camera → pieces (camera frame) and their owners.

        Segments longer than 24 px are cut into 8 pieces: with lens distortion a straight edge is a
        curve in the image, and a long edge may be partly hidden.
        """
        owner = np.concatenate(owners) if owners else np.zeros(0, dtype=np.int64)
        c = (segs - t) @ R
        front = (c[:, 0, 2] > 1e-3) & (c[:, 1, 2] > 1e-3)
        c, owner = c[front], owner[front]
        fx, fy = float(K[0]), float(K[1])
        ends = c[..., :2] / c[..., 2:3] if len(c) else np.zeros((0, 2, 2))
        length = np.hypot(fx * (ends[:, 1, 0] - ends[:, 0, 0]), fy * (ends[:, 1, 1] - ends[:, 0, 1]))
        long = length > 24.0
        s = np.linspace(0.0, 1.0, 9)[None, :, None]
        cut = c[long][:, :1] * (1 - s) + c[long][:, 1:] * s  # (k, 9, 3)
        a = np.concatenate([c[~long][:, 0], cut[:, :-1].reshape(-1, 3)])
        b = np.concatenate([c[~long][:, 1], cut[:, 1:].reshape(-1, 3)])
        who = np.concatenate([owner[~long], np.repeat(owner[long], 8)])
        return a, b, who

    def _visible(self, loaded: _Loaded, scene: dict[str, np.ndarray], eye: np.ndarray, points: np.ndarray):
        """Whether each world point is seen from ``eye``: no surface of the model lies before it.

        Rays go to every point through :func:`mbcal.geometry.raycast.cast_rays`, compiled once per
        model and per size bucket.  A shape that holds the camera inside it (a head around its
        eyes: rays in all six axis directions hit it) hides nothing.  Mesh shapes are costly per
        ray, so only the rays that pass through a mesh's bounding sphere are cast against it.
        """
        shapes = loaded.model.shapes
        plain = [i for i, sh in enumerate(shapes) if sh.mesh is None]
        meshes = [i for i, sh in enumerate(shapes) if sh.mesh is not None]
        fns = loaded.occlusion_fn
        if fns is None:
            # Shapes of one kind can be cast together: their poses and sizes become a leading axis
            # of cast_rays (one compiled kernel for the kind, however many shapes it has).
            kinds: dict[str, list[int]] = {}
            for i in plain:
                kinds.setdefault(shapes[i].kind, []).append(i)
            # A few shapes of a kind run faster one by one; many compile faster as one batch.
            groups = [g for idx in kinds.values() for g in ([idx] if len(idx) > 8 else [[i] for i in idx])]

            def by_kind(poses, dims, origins, dirs, group):
                return cast_rays(poses[jnp.array(group)][:, None], dims[jnp.array(group)][:, None],
                                 [shapes[group[0]]], origins, dirs)  # fmt: skip

            def cast(poses, dims, eye, pts, enabled):
                d = pts - eye
                length = jnp.linalg.norm(d, axis=-1)
                dirs = d / jnp.maximum(length, 1e-12)[:, None]
                origins = jnp.broadcast_to(eye, pts.shape)
                t = jnp.full(pts.shape[0], jnp.inf)
                for group in groups:
                    hits = by_kind(poses, dims, origins, dirs, group)  # (k, n)
                    t = jnp.minimum(t, jnp.min(jnp.where(enabled[jnp.array(group)][:, None], hits, jnp.inf), axis=0))
                return t

            def cast_mesh(i):
                def one(pose, dim, eye, pts):
                    d = pts - eye
                    length = jnp.linalg.norm(d, axis=-1)
                    dirs = d / jnp.maximum(length, 1e-12)[:, None]
                    return cast_rays(pose, dim, [shapes[i]], jnp.broadcast_to(eye, pts.shape), dirs)

                return jax.jit(one)

            def around(poses, dims, eye):
                dirs = jnp.concatenate([jnp.eye(3), -jnp.eye(3)])
                origins = jnp.broadcast_to(eye, (6, 3))
                inside = jnp.zeros(len(shapes), dtype=bool)
                for group in groups:
                    hits = by_kind(poses, dims, origins, dirs, group)  # (k, 6)
                    inside = inside.at[jnp.array(group)].set(jnp.all(jnp.isfinite(hits), axis=-1))
                for i in meshes:
                    hits = cast_rays(poses[i : i + 1], dims[i : i + 1], [shapes[i]], origins, dirs)
                    inside = inside.at[i].set(jnp.all(jnp.isfinite(hits)))
                return inside

            fns = loaded.occlusion_fn = {"plain": jax.jit(cast) if plain else None, "around": jax.jit(around)}
            for i in meshes:
                fns[i] = cast_mesh(i)

        def bucket(pts: np.ndarray) -> tuple[np.ndarray, int]:
            n = len(pts)
            size = max(256, 1 << (n - 1).bit_length())  # a few sizes only: a few compilations
            pad = np.broadcast_to(eye + np.array([0.0, 0.0, 1.0]), (size - n, 3))
            return np.concatenate([pts, pad]), n

        poses, dims = scene["shape_poses"], scene["shape_dims"]
        enabled = ~np.asarray(fns["around"](poses, dims, eye))
        length = np.linalg.norm(points - eye, axis=-1)
        t = np.full(len(points), np.inf)
        if plain:
            padded, n = bucket(points)
            t = np.array(fns["plain"](poses, dims, eye, padded, enabled))[:n]
        for i in meshes:
            mesh = shapes[i].mesh
            if not enabled[i] or mesh is None:
                continue
            local = np.asarray(mesh.vertices, dtype=float) * dims[i]
            center_local = 0.5 * (local.min(axis=0) + local.max(axis=0))
            radius = float(np.linalg.norm(local - center_local, axis=-1).max()) + 1e-6
            center = poses[i][:3, :3] @ center_local + poses[i][:3, 3]
            d = points - eye
            s = np.clip(((center - eye) @ d.T) / np.maximum(length**2, 1e-24), 0.0, 1.0)
            near = np.linalg.norm(eye + s[:, None] * d - center, axis=-1) <= radius
            if not np.any(near):
                continue
            padded, n = bucket(points[near])
            t_mesh = np.asarray(fns[i](poses[i : i + 1], dims[i : i + 1], eye, padded))[:n]
            t[near] = np.minimum(t[near], t_mesh)
        return t >= length - (2e-3 + 0.01 * length)

    def solid(self, photo_id: str, values: Mapping[str, float] | None = None) -> bytes:
        """The model rendered from the photo's camera (pyrender) as an RGBA PNG: transparent where
        no surface is seen, so the page lays it over the photo as a translucent solid."""
        import io

        from PIL import Image  # pillow: loaded when a picture is made

        from mbcal.render.views import render_view  # rendering: loaded when the solid is first drawn

        with self.lock:
            loaded = self.require_model()
            photo = self._photo(photo_id)
            cam_name = loaded.model.resolve("camera", photo.camera)
            X = self._X(loaded, photo.config, self.session.values if values is None else values)
            scene = loaded.scene_fn(jnp.asarray(X, dtype=jnp.float64))
        with _RENDER_LOCK:  # one OpenGL context at a time: pyrender's EGL contexts are not thread-safe
            view = render_view(scene, cam_name)
        alpha = np.where(view.shape_index >= 0, 255, 0).astype(np.uint8)
        rgba = np.dstack([view.color, alpha])
        buf = io.BytesIO()
        Image.fromarray(rgba, "RGBA").save(buf, format="PNG")
        return buf.getvalue()

    def _photo(self, photo_id: str) -> Photo:
        photo = self.photos.get(photo_id)
        if photo is None:
            raise MbcalError(f"no photo '{photo_id}'")
        return photo

    # ---- edits ---------------------------------------------------------------------------------------

    def set_session(
        self, clicks: Sequence[Mapping[str, Any]], estimate: Sequence[str], values: Mapping[str, float], hidden
    ) -> dict[str, Any]:
        """Replace the clicks, unknowns and values (the page sends its whole state); saved at once."""
        with self.lock:
            loaded = self.require_model()
            model = loaded.model
            if len(clicks) > MAX_CLICKS:
                raise MbcalError(f"at most {MAX_CLICKS} clicks")
            configs = set(self.configurations())
            new = []
            seen = set()
            for c in clicks:
                if not model.has("point", c["point"]):
                    raise MbcalError(f"the model has no point '{c['point']}'")
                if not model.has("camera", c["camera"]):
                    raise MbcalError(f"the model has no camera '{c['camera']}'")
                if c["config"] not in configs:
                    raise MbcalError(f"no configuration '{c['config']}'")
                if c["id"] in seen:
                    raise MbcalError(f"duplicate click id '{c['id']}'")
                seen.add(c["id"])
                new.append(
                    Click(c["id"], c["camera"], c["config"], c["point"], c["u"], c["v"], c["sigma"], c.get("sigma_v"))
                )
            for pattern in estimate:
                if not model.match_params(pattern):
                    raise MbcalError(f"no parameter matches '{pattern}'")
            for name in values:
                if not model.has("param", name.split("@")[0]):
                    raise MbcalError(f"the model has no parameter '{name.split('@')[0]}'")
            stale = new != self.session.clicks or list(estimate) != self.session.estimate
            session = Session(new, list(estimate), dict(values), list(hidden), self.session.model)
            self.save_session(session)  # written first: a refused write leaves the engine as it was
            self.session = session
            if stale:
                self.result = None  # the solve was of other clicks: Save must not write it beside these
            self._next_id = max(self._next_id, self._max_id() + 1)
            return {"saved": len(new), "next_id": self._next_id}

    # ---- observe, solve, save ------------------------------------------------------------------------

    def _unknowns(self, model: Model) -> list[str]:
        names: list[str] = []
        for pattern in self.session.estimate:
            names += model.match_params(pattern)
        if not names:
            raise MbcalError("choose the unknowns first (names or globs, e.g. room.*)")
        return list(dict.fromkeys(names))

    def measurements(self) -> MeasurementSet:
        """The clicks (and the other measurements of the input files) as one measurement set."""
        loaded = self.require_model()
        inputs = loaded.inputs
        records = [
            {
                "id": c.id,
                "kind": "image_point",
                "config": c.config,
                "camera": c.camera,
                "point": c.point,
                "u": c.u,
                "v": c.v,
                **({"sigma": c.sigma} if c.sigma_v is None else {"sigma_u": c.sigma, "sigma_v": c.sigma_v}),
            }
            for c in self.session.clicks
        ]
        if not records:
            raise MbcalError("no clicked points yet: pick a model point, then click where it is in the photo")
        clicked = measurements_from_records(
            records,
            loaded.model,
            known=inputs.known if inputs else None,
            configurations=inputs.configurations if inputs else None,
        )
        if inputs is None:
            return clicked
        others = inputs.subset([m.kind != "image_point" for m in inputs.measurements])
        return merge_measurements([clicked, others], loaded.model) if len(others) else clicked

    def _start_values(self, model: Model, names: list[str]) -> dict[str, float]:
        out = {}
        for k, v in self.session.values.items():
            base = k.split("@")[0]
            if base in names and (("@" in k) == model.param(base).per_configuration):
                out[k] = v
        return out

    def observe(self) -> dict[str, Any]:
        """Rank, σ, unobservable combinations and the suggested next clicks, at the current values."""
        with self.lock:
            loaded = self.require_model()
            model = loaded.model
            names = self._unknowns(model)
            data = self.measurements()
            at = self._start_values(model, names)
        analysis = observe(model, data, names, at=at or None)
        obs = analysis.observability
        suggestions = []
        for s in obs.suggestions or []:
            rec = s.record
            suggestions.append(
                {
                    "kind": rec.get("kind"),
                    "camera": rec.get("camera"),
                    "point": rec.get("point"),
                    "config": rec.get("config", "default"),
                    "text": s.text,
                }
            )
        return {
            "rank": int(obs.rank),
            "unknowns": len(names),
            "observable": bool(obs.observable),
            "verdict": obs.verdict(),
            "combinations": [c.describe() for c in obs.unobservable],
            "weak": [c.describe() for c in obs.weak],
            "std": {k: _num(v) for k, v in analysis.std.items()},
            "suggestions": suggestions,
            "summary": analysis.summary(),
        }

    def start_solve(self, restarts: int, seed: int = 0) -> None:
        """Solve in a background thread; :meth:`solve_status` reports progress and the result."""
        with self.lock:
            if self.solve_state["running"]:
                raise MbcalError("a solve is already running")
            loaded = self.require_model()
            model = loaded.model
            names = self._unknowns(model)
            data = self.measurements()
            start = self._start_values(model, names)
            asked = self._solve_inputs()
            self.solve_state = {
                "running": True,
                "messages": [],
                "error": None,
                "done": False,
                "stale": None,
                "started": time.time(),
            }

        def say(message: str) -> None:
            self.solve_state["messages"].append(message)

        def work() -> None:
            try:
                result = calibrate(
                    model, data, names, restarts=restarts, seed=seed, initial=start or None, progress=say
                )
                with self.lock:
                    if self.loaded is not loaded or self._solve_inputs() != asked:
                        # Edited while it ran: its result is of other clicks (or unknowns, or start
                        # values, or model), so it is neither saved beside these nor written over
                        # the values the operator set meanwhile.
                        self.solve_state["stale"] = STALE_SOLVE
                        return
                    self.result = result
                    for k, v in result.values.items():
                        self.session.values[k] = float(v)
                    self.save_session()
                    self.solve_state["report"] = self._report(result)
            except MbcalError as err:
                self.solve_state["error"] = error_json(err)
            except Exception as err:  # the server must stay up; the page shows what happened
                self.solve_state["error"] = {"message": f"{type(err).__name__}: {err}", "location": None}
            finally:
                self.solve_state["running"] = False
                self.solve_state["done"] = True

        threading.Thread(target=work, name="mbcal-studio-solve", daemon=True).start()

    def _solve_inputs(self) -> tuple:
        """What a solve is of: the clicks, the unknowns and the values it starts from (a copy)."""
        return (
            [astuple(c) for c in self.session.clicks],
            list(self.session.estimate),
            dict(self.session.values),
        )

    def solve_status(self) -> dict[str, Any]:
        with self.lock:
            return dict(self.solve_state)

    def _report(self, result) -> dict[str, Any]:
        model = result.problem.model
        params = []
        for name in result.names:
            info = model.param(name.split("@")[0])
            params.append(
                {
                    "name": name,
                    "unit": info.unit,
                    "value": result.values[name],
                    "std": _num(result.std[name]),
                    "initial": result.initial[name],
                    "display": info.display(result.values[name]),
                    "display_std": _num(info.display(result.std[name])),
                }
            )
        residuals = {
            r.id: {"predicted": [float(x) for x in r.predicted], "measured": [float(x) for x in r.measured]}
            for r in result.residuals
            if r.kind == "image_point"
        }
        points = [p.to_json() for p in result.points]
        return {
            "ok": bool(result.ok),
            "status": str(result.status),
            "params": params,
            "residuals": residuals,
            "points": points,
            "rms": {k: _num(v) for k, v in result.rms.items()},
            "summary": result.summary(max_residuals=10),
        }

    def save(self, fmt: str = "csv") -> dict[str, Any]:
        """Write the measurements, the calibrated model, the report and the overlays into ``--out``.

        All or nothing: every target is checked before any is written, and they are renamed into
        place together (:func:`mbcal.outputs.all_or_nothing`) -- a refused or failed Save leaves
        the earlier files as they were.  Overlays an earlier Save drew that this one does not
        (a camera or configuration without clicks now) are removed: none is left beside a report
        it does not belong to.  The overlays alone may fail (said in the notes): the rest is saved.
        """
        from mbcal.render.overlays import planned_overlays  # rendering: loaded when pictures are made

        if fmt not in ("csv", "json"):
            raise MbcalError("format must be csv or json")
        with self.lock:
            loaded = self.require_model()
            data = self.measurements()
            result = self.result
            inputs = self.inputs
        with self._save_lock:
            meas = self._target(f"measurements.{fmt}", inputs)
            # the other format's file, from an earlier Save: left as it is, and named in the answer
            other = "measurements.json" if fmt == "csv" else "measurements.csv"
            suffix = ".urdf" if self.model_path.suffix.lower() == ".urdf" else ".mdl"
            if result is None:
                with all_or_nothing():
                    write_measurements(data, meas)
                # An earlier Save's report, model and overlays stay (nothing is removed unasked), but
                # they are of other clicks: said, so that no one reads them as these measurements' fit.
                names = (other, f"{self.model_path.stem}_calibrated{suffix}", "report.json", "overlays")
                earlier = [name for name in names if (self.out / name).exists()]
                notes = list(self.notes)
                if earlier:
                    notes.append(
                        f"{', '.join(earlier)} in {self.out} are from an earlier Save, of other clicks: "
                        "Solve, then Save, to replace them"
                    )
                return {"written": [meas.name], "removed": [], "earlier": earlier, "out": str(self.out), "notes": notes}
            model_out = self._target(f"{self.model_path.stem}_calibrated{suffix}", inputs)
            report = self._target("report.json", inputs)
            folder = self._target_path("overlays")
            if folder.exists() and not folder.is_dir():
                raise MbcalError(f"{folder} is a file: Save draws its overlays into a folder of that name")
            for picture in planned_overlays(loaded.model, result.residuals, folder):
                self._target(f"overlays/{picture.name}", inputs)
            manifest = self._target(f"overlays/{OVERLAYS_MANIFEST}", inputs)
            earlier = self._studio_overlays(manifest)
            with all_or_nothing():
                write_measurements(data, meas)
                result.write_model(model_out)
                atomic_write(report, json.dumps(result.to_json(), indent=1, allow_nan=False) + "\n")
                drawn = self._overlays(loaded.model, result, folder)
                if drawn or folder.is_dir():
                    atomic_write(manifest, json.dumps(drawn, indent=1) + "\n")
            removed = []
            for name in sorted(set(earlier) - set(drawn)):
                stale = folder / name
                if stale.is_file() and not stale.is_symlink() and stale.resolve() not in {p.resolve() for p in inputs}:
                    with contextlib.suppress(OSError):
                        stale.unlink()
                        removed.append(f"overlays/{name}")
        written = [meas.name, model_out.name, report.name, *(f"overlays/{name}" for name in drawn)]
        notes = list(self.notes)
        earlier = [other] if (self.out / other).exists() else []
        if earlier:
            notes.append(f"{other} in {self.out} is from an earlier Save: {meas.name} holds these clicks")
        return {"written": written, "removed": removed, "earlier": earlier, "out": str(self.out), "notes": notes}

    def _target(self, name: str, inputs: Sequence[Path]) -> Path:
        """An output of Save: under ``--out`` itself, not through a link to elsewhere, not an input."""
        path = self._target_path(name)
        if not path.parent.exists():  # overlays/ on the first Save: made when they are drawn
            return path
        return check_output(path, inputs)

    def _target_path(self, name: str) -> Path:
        path = self.out / name
        if path.is_symlink() or not _inside(path, self.out):
            raise MbcalError(f"{path} leads outside {self.out} (a link): the studio writes only under --out")
        return path

    @staticmethod
    def _studio_overlays(manifest: Path) -> list[str]:
        """The overlays the last Save drew (their names, as it recorded them in ``manifest``)."""
        try:
            names = json.loads(manifest.read_text(encoding="utf-8"))
        except (OSError, UnicodeDecodeError, json.JSONDecodeError):
            return []
        if not isinstance(names, list):
            return []
        # Only plain names of pictures in the folder: a hand-edited list cannot point elsewhere.
        return [n for n in names if isinstance(n, str) and _OVERLAY_NAME.fullmatch(n)]

    def _overlays(self, model: Model, result, folder: Path) -> list[str]:
        """Draw the overlays into ``folder``: their names, or none (said in the notes) when they fail."""
        from mbcal.render.overlays import calibration_overlays  # rendering: loaded when pictures are made
        from mbcal.render.views import load_image  # as above

        # Each photo is of one camera in one configuration: drawn under that configuration's overlays only.
        backgrounds: dict[tuple[str, str], np.ndarray] = {}
        for photo in self.photos.values():
            backgrounds[(model.resolve("camera", photo.camera), photo.config)] = load_image(photo.path)
        try:
            with _RENDER_LOCK, all_or_nothing():  # failed: none of them (the rest of the Save stands)
                paths = calibration_overlays(result, folder, backgrounds=backgrounds)
        except MbcalError as err:
            self.notes.append(f"overlays not drawn: {err}")
            return []
        return [p.name for p in paths]


def _inside(path: Path, folder: Path) -> bool:
    """Whether ``path`` (links followed) lies in ``folder`` (links followed)."""
    return path.resolve().is_relative_to(folder.resolve())


def _num(v: float) -> float | None:
    v = float(v)
    return v if math.isfinite(v) else None
