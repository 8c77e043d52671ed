"""Mesh files named by ``shape mesh("part.stl")`` (and URDF visuals): read and validated."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from mbcal.errors import MeshError, SourceSpan
from mbcal.language.model import MeshData

__all__ = ["load_mesh", "MESH_SUFFIXES"]

# The formats trimesh reads that carry triangles.
MESH_SUFFIXES = (".stl", ".obj", ".ply", ".glb", ".gltf", ".off", ".dae")


def load_mesh(path: Path, span: SourceSpan | None) -> MeshData:
    """Read an STL/OBJ/PLY/glTF file with trimesh; a :class:`MeshError` when it is unusable."""
    import trimesh  # loaded with the first mesh: keeps `mbcal check` of plain models fast

    suffix = path.suffix.lower()
    if suffix not in MESH_SUFFIXES:
        raise MeshError(f"unsupported mesh format '{suffix}' (use .stl, .obj, .ply, .glb or .gltf)", span)
    if not path.is_file():
        raise MeshError(f"mesh file not found: {path}", span, hint="mesh paths are relative to the model file")
    if path.stat().st_size == 0:
        raise MeshError(f"mesh file is empty: {path}", span)
    try:
        loaded = trimesh.load(str(path), force="mesh", process=False)
    except Exception as err:  # trimesh raises many types for corrupt files
        raise MeshError(f"cannot read mesh {path}: {type(err).__name__}: {err}", span) from None
    vertices = np.asarray(getattr(loaded, "vertices", np.zeros((0, 3))), dtype=float)
    faces = np.asarray(getattr(loaded, "faces", np.zeros((0, 3))), dtype=np.int64)
    if faces.ndim != 2 or faces.shape[0] == 0 or faces.shape[1] != 3:
        raise MeshError(f"mesh {path} has no triangles", span)
    if vertices.ndim != 2 or vertices.shape[1] != 3 or not np.all(np.isfinite(vertices)):
        raise MeshError(f"mesh {path} has invalid vertices", span)
    if faces.min() < 0 or faces.max() >= len(vertices):
        raise MeshError(f"mesh {path} has faces that refer to missing vertices", span)
    return MeshData(str(path), vertices, faces)
