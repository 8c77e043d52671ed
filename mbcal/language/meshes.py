"""Mesh files named by ``shape mesh("part.stl")`` (and URDF visuals): read and validated.

The triangles read from a file are kept in the cache folder (``meshes/`` of
:func:`mbcal.cache.cache_dir`), keyed by the file's bytes, its format and the installed trimesh:
``import trimesh`` alone takes ~0.6 s (it loads SciPy's spatial and optimisation modules and
networkx), a third of a warm ``mbcal solve`` of the seed's room, while the arrays load in a
millisecond (issue 16).  A changed file is a new key; an unreadable entry is read again with
trimesh.  Only formats whose triangles are all in the one file are kept (:data:`CACHED_SUFFIXES`:
a ``.gltf`` keeps its vertices in separate buffer files, which the key would not see), and an
entry is written only when the file was not changed while trimesh read it.
"""

from __future__ import annotations

import functools
import importlib.metadata
import importlib.util
import io
import os
from pathlib import Path

import numpy as np

from mbcal.cache import Hasher, cache_dir
from mbcal.errors import MeshError, SourceSpan
from mbcal.language import files
from mbcal.language.model import MeshData
from mbcal.outputs import atomic_write

__all__ = ["load_mesh", "MESH_SUFFIXES"]

# The formats trimesh reads that carry triangles.
MESH_SUFFIXES = (".stl", ".obj", ".ply", ".glb", ".gltf", ".off", ".dae")

# The formats whose triangles the cache folder keeps: every one but .gltf, whose buffers are files
# of their own.  (An .obj's materials file holds no geometry.)
CACHED_SUFFIXES = (".stl", ".obj", ".ply", ".glb", ".off", ".dae")

# Bump when what is stored changes (the arrays, their dtypes, the reading options).
_ENTRY_VERSION = 1


def load_mesh(path: Path, span: SourceSpan | None) -> MeshData:
    """Read an STL/OBJ/PLY/glTF file with trimesh (or its triangles from the cache folder); a
    :class:`MeshError` when it is unusable."""
    suffix = path.suffix.lower()
    if suffix not in MESH_SUFFIXES:
        raise MeshError(f"unsupported mesh format '{suffix}' (use .stl, .obj, .ply, .glb or .gltf)", span)
    if not path.is_file():
        raise MeshError(f"mesh file not found: {path}", span, hint="mesh paths are relative to the model file")
    if path.stat().st_size == 0:
        raise MeshError(f"mesh file is empty: {path}", span)
    key = _entry(path, suffix)
    entry, content = key if key is not None else (None, b"")
    if key is None:  # not read for the cache: read for the digest of what the model is built from
        try:
            content = path.read_bytes()
        except OSError:
            content = b""  # trimesh will say what is wrong with it
    files.note(path, content)
    arrays = _read_entry(entry) if entry is not None else None
    if arrays is None:
        vertices, faces = _read_with_trimesh(path, span)
    else:
        vertices, faces = arrays
    if faces.ndim != 2 or faces.shape[0] == 0 or faces.shape[1] != 3:
        raise MeshError(f"mesh {path} has no triangles", span)
    if vertices.ndim != 2 or vertices.shape[1] != 3 or not np.all(np.isfinite(vertices)):
        raise MeshError(f"mesh {path} has invalid vertices", span)
    if faces.min() < 0 or faces.max() >= len(vertices):
        raise MeshError(f"mesh {path} has faces that refer to missing vertices", span)
    if arrays is None and entry is not None and _unchanged(path, content):  # only a valid mesh is kept
        _write_entry(entry, vertices, faces)
    return MeshData(str(path), vertices, faces, _gltf_buffers(path, content) if suffix == ".gltf" else ())


def _gltf_buffers(path: Path, content: bytes) -> tuple[str, ...]:
    """The files a .gltf reads its vertices from (its buffers that are not data: URIs): the model's
    data files too, so that an edited buffer is a changed model."""
    import json
    from urllib.parse import unquote

    try:
        buffers = json.loads(content.decode("utf-8")).get("buffers", [])
    except (ValueError, AttributeError):
        return ()
    found = []
    for buffer in buffers if isinstance(buffers, list) else []:
        uri = buffer.get("uri") if isinstance(buffer, dict) else None
        if isinstance(uri, str) and uri and not uri.startswith("data:"):
            found.append(str((path.parent / unquote(uri)).resolve()))
    return tuple(found)


def _read_with_trimesh(path: Path, span: SourceSpan | None) -> tuple[np.ndarray, np.ndarray]:
    import trimesh  # heavy (~0.6 s): loaded only for a mesh the cache folder does not hold

    try:
        loaded = trimesh.load(str(path), force="mesh", process=False)
    except Exception as err:  # trimesh raises many types for corrupt files
        raise MeshError(f"cannot read mesh {path}: {type(err).__name__}: {err}", span) from None
    vertices = np.asarray(getattr(loaded, "vertices", np.zeros((0, 3))), dtype=float)
    faces = np.asarray(getattr(loaded, "faces", np.zeros((0, 3))), dtype=np.int64)
    return vertices, faces


@functools.lru_cache(maxsize=1)
def _reader() -> str:
    """Which trimesh would read the files, found without importing it: its version (from the
    installed package's metadata) and its ``__init__.py``'s location, size and time (an editable
    checkout changed in place)."""
    spec = importlib.util.find_spec("trimesh")
    if spec is None or spec.origin is None:
        return "no trimesh"
    try:
        version = importlib.metadata.version("trimesh")
    except importlib.metadata.PackageNotFoundError:
        version = "unknown"
    st = os.stat(spec.origin)
    return f"{version}:{spec.origin}:{st.st_size}:{st.st_mtime_ns}"


def _entry(path: Path, suffix: str) -> tuple[Path, bytes] | None:
    """The cache file for this mesh file's content and the content itself, or None when caching is
    off or the format is not kept (:data:`CACHED_SUFFIXES`)."""
    folder = cache_dir()
    if folder is None or suffix not in CACHED_SUFFIXES:
        return None
    try:
        content = path.read_bytes()
    except OSError:
        return None  # trimesh will say what is wrong with it
    key = Hasher().add("mesh", _ENTRY_VERSION, suffix, _reader(), content).hexdigest()
    return folder / "meshes" / f"{key}.npz", content


def _unchanged(path: Path, content: bytes) -> bool:
    """Whether the file still holds ``content`` (it may have been saved again while trimesh read it:
    its triangles must not be kept under the old content's key)."""
    try:
        return path.read_bytes() == content
    except OSError:
        return False


def _read_entry(entry: Path) -> tuple[np.ndarray, np.ndarray] | None:
    try:
        with np.load(io.BytesIO(entry.read_bytes()), allow_pickle=False) as stored:
            vertices, faces = stored["vertices"], stored["faces"]
    except Exception:  # missing, truncated or foreign: read the mesh file again
        return None
    if vertices.dtype != np.float64 or faces.dtype != np.int64:
        return None
    return vertices, faces


def _write_entry(entry: Path, vertices: np.ndarray, faces: np.ndarray) -> None:
    buf = io.BytesIO()
    np.savez(buf, vertices=vertices, faces=faces)
    try:
        entry.parent.mkdir(parents=True, exist_ok=True)
        atomic_write(entry, buf.getvalue(), at_once=True)
    except OSError:
        pass  # a read-only cache: still correct, only slower next time
