"""The checked model description D: parameters, frames, points, sensors and shapes.

A :class:`Model` is what :func:`mbcal.load_model` returns.  It is immutable once built and
is hashed by identity, so it can be a static argument of jitted functions.  Expressions are
held as :mod:`mbcal.language.ir` graphs; :func:`mbcal.modeling.modeler` evaluates them.
"""

from __future__ import annotations

import fnmatch
import math
from dataclasses import dataclass, field

import numpy as np

from mbcal.errors import ParameterError, SourceSpan, UnknownNameError, suggest
from mbcal.language.graph import Node
from mbcal.language.summary import model_summary
from mbcal.units import ANGLE, LENGTH, Dim, describe, to_display, within

__all__ = [
    "ParamInfo",
    "JointInfo",
    "FrameInfo",
    "PointInfo",
    "CameraInfo",
    "RangeInfo",
    "ShapeInfo",
    "MeshData",
    "TargetInfo",
    "Model",
]


@dataclass(frozen=True, eq=False)
class ParamInfo:
    """A declared parameter.

    Attributes
    ----------
    name : str
        Full dotted name (``room.x``); templates and frames prefix the names declared in them.
    index : int
        Position in the model's parameter vector X.
    nominal : float
        Nominal (design) value in SI units.
    lower, upper : float or None
        Search range for random initial values.
    sigma : float or None
        Prior standard deviation around ``nominal`` (a soft constraint when estimated).
    per_configuration : bool
        Each configuration of a measurement set has its own copy.
    dim : Dim or None
        Physical dimension (None: given without a unit).
    limit_lower, limit_upper : float or None
        Hard limits (``limits [a, b]``, or ``in [lo, hi] bounded``): the estimate never leaves
        them.  None: no limit on that side.
    """

    name: str
    index: int
    nominal: float
    lower: float | None
    upper: float | None
    sigma: float | None
    per_configuration: bool
    dim: Dim | None
    span: SourceSpan | None = field(default=None, repr=False)
    value_span: SourceSpan | None = field(default=None, repr=False)
    value_unit: str | None = None  # the unit the value was written in ("cm"), None for SI
    editable: bool = False  # one statement declares it alone (no template, no index range)
    overridden: bool = False  # an ``override`` gave its value (value_span is that statement's)
    limit_lower: float | None = None
    limit_upper: float | None = None
    used_as: tuple[Dim, ...] = ()
    """Declared without a unit (``dim`` None): the dimensions the places it stands in require (a box's
    size: length; a camera's f: a plain number), which a value given with a unit must fit."""

    @property
    def limited(self) -> bool:
        """Whether the parameter has a hard limit on either side."""
        return self.limit_lower is not None or self.limit_upper is not None

    @property
    def unit(self) -> str:
        """The unit values are shown in: ``m``, ``deg`` or empty."""
        if self.dim == LENGTH:
            return "m"
        if self.dim == ANGLE:
            return "deg"
        return ""

    def display(self, value: float) -> float:
        """``value`` (SI) in the display unit (degrees for angles)."""
        return to_display(self.unit, value)

    def from_display(self, value: float) -> float:
        """A display-unit value back to SI."""
        return float(np.radians(value)) if self.unit == "deg" else float(value)

    def describe(self) -> str:
        return describe(self.dim)

    @property
    def given_dim(self) -> Dim | None:
        """The dimension a value given for it with a unit (``--set``, a file's known value) must have:
        its own, else the one dimension its places require; None when that is not one (never used
        where a dimension is required, or used as two): then a plain number only."""
        if self.dim is not None:
            return self.dim
        return self.used_as[0] if len(self.used_as) == 1 else None

    def outside_limits(self, value: float) -> str | None:
        """None when ``value`` (SI) lies within the hard limits, else what is wrong, in the display
        unit: ``45 cm`` → "0.45 m is outside the hard limits of lever.length [0.1, 0.4] m".  Every
        way a value is given (``--set``, a measurement file's known value, ``known=``) is checked
        by this one rule."""
        low = -math.inf if self.limit_lower is None else self.limit_lower
        high = math.inf if self.limit_upper is None else self.limit_upper
        if within(value, low, high):  # (a few ulps of slack: 35 cm against a limit of 0.35 m)
            return None
        suffix = f" {self.unit}" if self.unit else ""
        ends = ", ".join(f"{self.display(v):.12g}" for v in (low, high))
        return f"{self.display(value):.12g}{suffix} is outside the hard limits of {self.name} [{ends}]{suffix}"


@dataclass(frozen=True, eq=False)
class JointInfo:
    """A joint moving its frame relative to the frame's ``at`` pose."""

    kind: str  # revolute | prismatic
    axis: Node  # unit 3-vector in the frame
    q: Node
    offset: Node | None
    lower: float | None
    upper: float | None
    span: SourceSpan | None = field(default=None, repr=False)


@dataclass(frozen=True, eq=False)
class FrameInfo:
    """A coordinate frame: an object, a link, a sensor or a target."""

    name: str
    parent: int  # index into Model.frames, -1 for the world
    pose: Node | None  # T_parent_frame before the joint; None is the identity
    joint: JointInfo | None
    keyword: str
    span: SourceSpan | None = field(default=None, repr=False)


@dataclass(frozen=True, eq=False)
class PointInfo:
    """A named point, fixed in its frame."""

    name: str
    frame: int
    position: Node  # (3,) in the frame
    span: SourceSpan | None = field(default=None, repr=False)


@dataclass(frozen=True, eq=False)
class CameraInfo:
    """A pinhole camera with OpenCV's axes (x right, y down, z forward) and distortion model."""

    name: str
    frame: int  # the camera's own frame
    width: int
    height: int
    intrinsics: tuple[Node, Node, Node, Node, Node]  # fx, fy, cx, cy, skew (pixels)
    distortion: tuple[Node, Node, Node, Node, Node]  # k1, k2, p1, p2, k3 (OpenCV order)
    span: SourceSpan | None = field(default=None, repr=False)


@dataclass(frozen=True, eq=False)
class RangeInfo:
    """A range sensor: rays from its frame's origin along fixed directions."""

    name: str
    frame: int
    directions: np.ndarray  # (n, 3) unit vectors in the sensor frame
    max_range: float
    span: SourceSpan | None = field(default=None, repr=False)
    # A depth camera (``range NAME(width = ..., height = ..., f = ...)``): pinhole intrinsics
    # (fx, fy, cx, cy; OpenCV axes), image size, the depth unit of its images (m per count) and
    # the valid range [min_range, max_range]; rays through the pixel centres, row by row.
    intrinsics: tuple[float, float, float, float] | None = None
    width: int = 0
    height: int = 0
    depth_scale: float = 1e-3
    min_range: float = 0.0

    @property
    def is_depth_camera(self) -> bool:
        """Whether the sensor is a depth camera (pinhole intrinsics and an image size)."""
        return self.intrinsics is not None


@dataclass(frozen=True, eq=False)
class TargetInfo:
    """A calibration target: its kind, layout and the names of its points (in detection order)."""

    name: str
    kind: str  # chessboard | grid | squares | points
    frame: int
    rows: int
    cols: int
    points: tuple[str, ...]
    size_ratio: float = 0.0  # squares: size / pitch
    span: SourceSpan | None = field(default=None, repr=False)


@dataclass(frozen=True, eq=False)
class MeshData:
    """Triangles of a mesh file, in the file's own units (before ``scale``)."""

    path: str
    vertices: np.ndarray  # (v, 3)
    faces: np.ndarray  # (f, 3) int
    buffers: tuple[str, ...] = ()  # the other files it reads (a .gltf's buffers)


@dataclass(frozen=True, eq=False)
class ShapeInfo:
    """A solid or surface attached to a frame; every primitive is centred on its origin."""

    name: str
    frame: int
    kind: str
    dims: tuple[Node, ...]  # the kind's dimensions (mbcal.geometry.shapes)
    pose: Node | None  # T_frame_shape
    mesh: MeshData | None = None
    span: SourceSpan | None = field(default=None, repr=False)


@dataclass(frozen=True, eq=False)
class Model:
    """A checked model description (D in the seed paper).

    Build one with :func:`mbcal.load_model` or :func:`mbcal.load_model_text`.
    """

    path: str
    params: tuple[ParamInfo, ...]
    frames: tuple[FrameInfo, ...]
    points: tuple[PointInfo, ...]
    cameras: tuple[CameraInfo, ...]
    ranges: tuple[RangeInfo, ...]
    shapes: tuple[ShapeInfo, ...]
    measures: tuple[str, ...] = ()
    targets: tuple[TargetInfo, ...] = ()
    # Where each of ``measures`` is named (its 'measure' statement), for the error of a kind no
    # installed measurement model provides (mbcal.measurements.registry.declared_models).
    measure_spans: tuple[SourceSpan, ...] = field(default=(), repr=False)
    templates: tuple[str, ...] = ()
    files: tuple[str, ...] = ()
    data_files: tuple[str, ...] = ()
    """The other files it reads (meshes, point files): with :attr:`files`, what an output must not replace."""
    warnings: tuple[str, ...] = ()
    # SHA-256 of the text a model was checked from when it was not read from a file
    # (load_model_text): the text is part of the model's identity for the compiled-program cache.
    text_digest: str = ""
    # SHA-256 of each of :attr:`files` and :attr:`data_files` as it was when the model was read
    # (path, digest; "" unreadable): the compiled-program cache keys on these, not on the files as
    # they are when a problem is built later (one saved in between keyed the program of the old
    # content under the new one's name).
    file_digests: tuple[tuple[str, str], ...] = ()
    # The text itself when it was not read from a file (load_model_text): a calibrated model is
    # written from it — the file at ``path`` may say something else (a text edited in memory).
    source_text: str | None = field(default=None, repr=False, compare=False)
    _index: dict[str, dict[str, int]] = field(default_factory=dict, repr=False)
    _suffixes: dict[str, dict[str, list[str]]] = field(default_factory=dict, repr=False)

    def __post_init__(self) -> None:
        index = {
            "param": {p.name: i for i, p in enumerate(self.params)},
            "frame": {f.name: i for i, f in enumerate(self.frames)},
            "point": {p.name: i for i, p in enumerate(self.points)},
            "camera": {c.name: i for i, c in enumerate(self.cameras)},
            "range": {r.name: i for i, r in enumerate(self.ranges)},
            "shape": {s.name: i for i, s in enumerate(self.shapes)},
        }
        object.__setattr__(self, "_index", index)

    # ---- look-ups by name --------------------------------------------------------------------

    def _lookup(self, what: str, name: str) -> int:
        table = self._index[what]
        if name in table:
            return table[name]
        if what != "param":
            matches = self._suffix_table(what).get(name, [])
            if len(matches) == 1:
                return table[matches[0]]
            if len(matches) > 1:
                shown = ", ".join(f"'{m}'" for m in matches[:5]) + (", ..." if len(matches) > 5 else "")
                raise UnknownNameError(
                    f"'{name}' is ambiguous: it could be the {what} {shown}", hint="give more of the dotted path"
                )
        hint = suggest(name, table)
        names = list(table)
        if hint or not names:
            available = "" if hint else f" (the model has no {what})"
        else:
            shown = ", ".join(names[:8]) + (f", ... ({len(names)} in all)" if len(names) > 8 else "")
            available = f" (the model's {what}s: {shown})"
        error = ParameterError if what == "param" else UnknownNameError
        raise error(f"the model has no {what} named '{name}'{available}", hint=hint)

    def _suffix_table(self, what: str) -> dict[str, list[str]]:
        """Every dotted suffix of every name (``hand.tip`` for ``base.arm.hand.tip``)."""
        if what not in self._suffixes:
            table: dict[str, list[str]] = {}
            for full in self._index[what]:
                parts = full.split(".")
                for k in range(1, len(parts)):
                    table.setdefault(".".join(parts[k:]), []).append(full)
            self._suffixes[what] = table
        return self._suffixes[what]

    def short_name(self, what: str, full: str) -> str:
        """The shortest dotted suffix of ``full``, of two components at least, that still names
        it uniquely (for reports: ``lever.tip``, ``eyes.left``)."""
        if what == "frame" and full == "world":
            return full
        parts = full.split(".")
        table = self._suffix_table(what)
        for k in range(len(parts) - 2, 0, -1):
            suffix = ".".join(parts[k:])
            if table.get(suffix) == [full] and suffix not in self._index[what]:
                return suffix
        return full

    def resolve(self, what: str, name: str) -> str:
        """The full name of a frame, point, camera, range sensor or shape given by a unique suffix."""
        if what == "frame" and name == "world":
            return name
        return self.names(what)[self._lookup(what, name)]

    def param_index(self, name: str) -> int:
        """Position of a parameter in X; a :class:`ParameterError` with suggestions if unknown."""
        return self._lookup("param", name)

    def frame_index(self, name: str) -> int:
        """Position of a frame (full name or unique dotted suffix); ``world`` is -1."""
        if name == "world":
            return -1
        return self._lookup("frame", name)

    def point_index(self, name: str) -> int:
        return self._lookup("point", name)

    def camera_index(self, name: str) -> int:
        return self._lookup("camera", name)

    def range_index(self, name: str) -> int:
        return self._lookup("range", name)

    def shape_index(self, name: str) -> int:
        return self._lookup("shape", name)

    def target(self, name: str | None = None) -> TargetInfo:
        """A target by name (a unique suffix is enough); the only one when ``name`` is None."""
        if name is None:
            if not self.targets:
                raise UnknownNameError(
                    "the model has no calibration target",
                    hint="describe the target: target NAME = chessboard(...) or squares(...) (docs/language.md)",
                )
            if len(self.targets) > 1:
                listing = ", ".join(t.name for t in self.targets)
                raise UnknownNameError(f"the model has {len(self.targets)} targets ({listing}); name one")
            return self.targets[0]
        full = self.resolve("frame", name)
        for t in self.targets:
            if t.name == full:
                return t
        raise UnknownNameError(f"'{name}' is not a target", hint=suggest(name, [t.name for t in self.targets]))

    def param(self, name: str) -> ParamInfo:
        return self.params[self.param_index(name)]

    def has(self, what: str, name: str) -> bool:
        return name in self._index[what]

    def names(self, what: str) -> list[str]:
        """All names of one kind: ``param``, ``frame``, ``point``, ``camera``, ``range``, ``shape``."""
        return list(self._index[what])

    def match_params(self, pattern: str) -> list[str]:
        """Parameter names matching a name or a glob pattern (``room.*``)."""
        if pattern in self._index["param"]:
            return [pattern]
        return [p.name for p in self.params if fnmatch.fnmatchcase(p.name, pattern)]

    def shapes_of(self, frame: str, *, recursive: bool = True) -> list[int]:
        """Indices of the shapes attached to ``frame`` (and, by default, to its descendants)."""
        root = self.frame_index(frame)
        out = []
        for i, s in enumerate(self.shapes):
            f = s.frame
            while f >= 0:
                if f == root:
                    out.append(i)
                    break
                if not recursive:
                    break
                f = self.frames[f].parent
        return out

    @property
    def nominal(self) -> np.ndarray:
        """The nominal parameter vector X (SI units)."""
        return np.array([p.nominal for p in self.params], dtype=float)

    @property
    def per_configuration(self) -> list[str]:
        """Names of the parameters declared ``per configuration``."""
        return [p.name for p in self.params if p.per_configuration]

    def summary(self) -> str:
        """A readable overview: parameters, frames, points, sensors, shapes."""
        return model_summary(self)
