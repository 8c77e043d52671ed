"""URDF in: robot descriptions as mbcal models.

Reading
-------
:func:`urdf_to_mdl` reads a URDF with `yourdfpy <https://github.com/clemense/yourdfpy>`_
(kinematics only: meshes are neither loaded nor required by yourdfpy) and writes the equivalent
``.mdl`` text; :func:`load_urdf` checks that text into a :class:`~mbcal.language.model.Model`
(``mbcal.load_model`` calls it for ``*.urdf`` files).  What the text holds:

* the link tree as nested ``link`` frames, the root link at the top level.  URDF names are
  turned into identifiers (``[A-Za-z_][A-Za-z0-9_]*``): other characters become ``_``, a
  leading digit gets a ``_`` in front, reserved words (and ``origin`` for links) get a ``_``
  behind, clashes get ``_2``, ``_3``, ...  :func:`urdf_names` returns the mapping; every frame
  and parameter block names its URDF original in a comment.
* for every joint ``J`` (mdl name) its origin as six parameters ``J.x``, ``J.y``, ``J.z`` (m,
  search range ±2 cm) and ``J.roll``, ``J.pitch``, ``J.yaw`` (deg, ±2 deg), the URDF values being
  the nominal ones, and the child frame ``at pose(J.x, J.y, J.z, J.roll, J.pitch, J.yaw)``.  The
  angles are recovered from yourdfpy's origin matrix (fixed-axis x-y-z, as URDF), so an
  ``rpy`` written outside (-180°, 180°] comes back as the equivalent triple.
* revolute, continuous and prismatic joints: ``param J.q = 0 deg per configuration`` (m for
  prismatic) — the joint reading, given per configuration in a measurement file — and
  ``param J.offset = 0 deg in [-5 deg, 5 deg]`` (±5 mm for prismatic), the encoder's unknown
  zero; inside the child frame ``joint revolute(AXIS, J.q, offset = J.offset, lower = ...,
  upper = ...)`` with the URDF axis and limits (a ``<limit>`` without ``lower`` or ``upper``
  has 0 there, URDF's default, said in a comment).  A ``<mimic>`` joint moves by
  ``multiplier · (the other joint's reading) + offset`` and has an ``offset`` parameter but no
  reading.  Fixed joints have origin parameters but no joint statement; floating and planar
  joints are refused (:class:`UrdfError` naming the joint), and so is a revolute or prismatic
  joint without ``<limit>`` (URDF requires one; urdfdom refuses the file too).
* every ``<visual>`` as a ``shape`` (box, cylinder, sphere, mesh) at its constant origin.
  URDF cylinders are centred with their axis along z, as mbcal's.  What cannot be shown (a
  mesh file that cannot be found or read, a non-positive size) is left out with a comment:
  the kinematics still load.  ``<collision>`` and ``<inertial>`` elements are ignored.
* a point ``origin`` at every link's origin (``<link>.origin``, so links can be measured), and
  ``measure image_point, point3d, distance, angle``.

Mesh file names are resolved here, not by yourdfpy: ``file://PATH`` is PATH; a relative name
is relative to the URDF's folder; ``package://PKG/REST`` is looked up, first hit wins, in
every ancestor folder of the URDF named ``PKG`` (nearest first), then in ``D/PKG/REST`` for
``D`` the URDF's folder and each of its ancestors, then as ``REST`` relative to the URDF's
folder.  The ``.mdl`` text names meshes relative to the URDF's folder (or ``mesh_base``).

Calibrated URDFs are written by :mod:`mbcal.export.urdf`.
"""

from __future__ import annotations

import io
import json
import math
import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from mbcal.errors import MeshError, SourceSpan, UrdfError, suggest
from mbcal.geometry.shapes import get_shape, shape_kinds
from mbcal.language import files
from mbcal.language.meshes import MESH_SUFFIXES, load_mesh
from mbcal.language.parse import RESERVED

__all__ = ["urdf_to_mdl", "urdf_names", "resolve_mesh", "read_robot", "xyz_rpy", "pose_matrix", "UrdfError"]

MOVING = ("revolute", "continuous", "prismatic")
ORIGIN_FIELDS = ("x", "y", "z", "roll", "pitch", "yaw")
MEASURES = "image_point, point3d, distance, angle"


# ---- reading ------------------------------------------------------------------------------------


@dataclass
class _Robot:
    """A URDF as yourdfpy reads it, with mbcal names and the tree structure."""

    path: Path
    urdf: Any  # yourdfpy.URDF
    tree: Any  # lxml ElementTree (comments kept), to locate lines and to edit
    elements: dict[tuple[str, str], Any]  # (kind, name) → its first <link> or <joint> element
    links: dict[str, str] = field(default_factory=dict)  # URDF name → mdl name
    joints: dict[str, str] = field(default_factory=dict)
    root: str = ""
    children: dict[str, list[Any]] = field(default_factory=dict)  # link → joints whose parent it is

    def span(self, kind: str, name: str, part: str | None = None) -> SourceSpan | None:
        """Where the element is written (its ``<tag``), or its child ``part`` (``origin``, ``axis``,
        ``limit``) where it has one; a start tag split over lines is found at its ``<`` (lxml
        knows the line where the tag ends)."""
        element = self.elements.get((kind, name))
        if element is None or not element.sourceline:
            return None
        fallback = SourceSpan(str(self.path), element.sourceline, 1)
        text = _source_text(self.path)
        tag = re.compile(rf"<{kind}\b[^>]*?\bname\s*=\s*[\"']{re.escape(name)}[\"']")
        found = tag.search(text)
        if found is None:
            return fallback
        offset = found.start()
        if part is not None and next(element.iterchildren(part), None) is not None:
            child = re.compile(rf"<{part}\b").search(text, found.end())  # the first after the tag: its own
            offset = child.start() if child else offset
        return SourceSpan.at_offset(str(self.path), text, offset)

    def error(
        self,
        message: str,
        kind: str | None = None,
        name: str | None = None,
        part: str | None = None,
        hint: str | None = None,
    ) -> UrdfError:
        span = self.span(kind, name, part) if kind and name is not None else None
        return UrdfError(message if span else f"{self.path}: {message}", span, hint)


def _source_text(path: Path) -> str:
    try:
        return path.read_text(encoding="utf-8", errors="replace")
    except OSError:
        return ""


def _identifier(name: str, taken: set[str], avoid: frozenset[str] | set[str] = frozenset()) -> str:
    text = re.sub(r"[^A-Za-z0-9_]", "_", name) or "_"
    if text[0].isdigit():
        text = "_" + text
    if text in RESERVED or text in avoid:
        text += "_"
    candidate, k = text, 2
    while candidate in taken:
        candidate = f"{text}_{k}"
        k += 1
    taken.add(candidate)
    return candidate


def _value_in_attributes(path: Path, root: Any, message: str) -> SourceSpan | None:
    """Where the value a URDF reader could not take (``could not convert string to float: 'abc'``)
    is written: the first attribute holding it as one of its words (lxml knows the element's
    line; the column is found on that line)."""
    quoted = re.search(r"'([^']+)'", message)
    if quoted is None:
        return None
    bad = quoted.group(1)
    for element in root.iter():
        for name, value in element.attrib.items():
            if bad in str(value).split() and element.sourceline:
                line = element.sourceline
                try:
                    text = path.read_text(errors="replace").splitlines()[line - 1]
                except (OSError, IndexError):
                    return SourceSpan(str(path), line, 1)
                at = re.search(rf"{re.escape(name)}\s*=\s*[\"'][^\"']*?(?<![^\s\"']){re.escape(bad)}", text)
                column = at.end() - len(bad) + 1 if at else 1
                return SourceSpan(str(path), line, column, line, column + len(bad))
    return None


def read_robot(path: str | os.PathLike[str]) -> _Robot:
    """Parse a URDF (strict XML first, for line numbers), then with yourdfpy; check the tree."""
    from lxml import etree  # heavy: loaded with the first URDF, so that `mbcal check` of .mdl files stays fast

    path = Path(path)
    if not path.is_file():
        raise UrdfError(f"{path}: URDF file not found")
    try:
        # Read once: the bytes digested for the programs' key are the bytes both parsers read
        # (yourdfpy read the file again, and a save in between went unnoticed).
        data = files.read_bytes(path)
        parser = etree.XMLParser(remove_blank_text=False, resolve_entities=False)
        tree = etree.parse(io.BytesIO(data), parser, base_url=str(path))
    except etree.XMLSyntaxError as err:
        line, column = err.position or (err.lineno, 1)
        message = f"malformed XML: {err.msg}"
        if line:
            raise UrdfError(message, SourceSpan(str(path), int(line), max(int(column or 1), 1))) from None
        raise UrdfError(f"{path}: {message}") from None
    except OSError as err:
        raise UrdfError(f"{path}: cannot read: {err}") from None
    root = tree.getroot()
    if root.tag != "robot":
        raise UrdfError(
            f"the root element is <{root.tag}>, not <robot>", SourceSpan(str(path), root.sourceline or 1, 1)
        )
    elements: dict[tuple[str, str], Any] = {}
    for kind in ("link", "joint"):
        for element in root.iterchildren(kind):
            name = element.get("name")
            if name is not None:
                elements.setdefault((kind, name), element)

    import yourdfpy  # heavy (trimesh and more): loaded with the first URDF

    try:
        urdf = yourdfpy.URDF.load(
            io.BytesIO(data),
            build_scene_graph=False,
            load_meshes=False,
            filename_handler=lambda name: name,
            mesh_dir=str(path.parent),
        )
    except Exception as err:  # yourdfpy raises KeyError, ValueError, AttributeError, ... on bad input
        detail = f"'{err.args[0]}' is missing" if isinstance(err, KeyError) else str(err)
        where = _value_in_attributes(path, root, detail) if isinstance(err, ValueError) else None
        if where is not None:
            raise UrdfError(f"not a valid URDF ({detail})", where) from None
        raise UrdfError(f"{path}: not a valid URDF ({type(err).__name__}: {detail})") from None

    robot = _Robot(path, urdf, tree, elements)
    links = [link.name for link in urdf.robot.links]
    if not links:
        raise robot.error("the robot has no links")
    seen: set[str] = set()
    for name in links:
        if name in seen:
            raise robot.error(f"link '{name}' is declared twice", "link", name)
        seen.add(name)
    parent_of: dict[str, str] = {}
    joint_seen: set[str] = set()
    for joint in urdf.robot.joints:
        if joint.name in joint_seen:
            raise robot.error(f"joint '{joint.name}' is declared twice", "joint", joint.name)
        joint_seen.add(joint.name)
        for role, link in (("parent", joint.parent), ("child", joint.child)):
            if not link:
                raise robot.error(f"joint '{joint.name}' has no {role} link", "joint", joint.name)
            if link not in seen:
                raise robot.error(f"joint '{joint.name}' refers to a missing {role} link '{link}'", "joint", joint.name)
        if joint.type in ("floating", "planar"):
            raise robot.error(
                f"joint '{joint.name}' is {joint.type}: mbcal models revolute, continuous, prismatic "
                "and fixed joints only",
                "joint",
                joint.name,
            )
        if joint.type not in (*MOVING, "fixed"):
            raise robot.error(f"joint '{joint.name}' has an unknown type '{joint.type}'", "joint", joint.name)
        # checked here, at the joint's line: in the .mdl written from it they were errors at a line of
        # a file that does not exist ('robot.urdf.mdl:6:17: unexpected m ... nan m')
        if joint.origin is not None and not np.all(np.isfinite(np.asarray(joint.origin, dtype=float))):
            raise robot.error(
                f"joint '{joint.name}': its <origin> is not finite numbers", "joint", joint.name, "origin"
            )
        if joint.type in MOVING:
            axis = np.asarray(joint.axis if joint.axis is not None else (1.0, 0.0, 0.0), dtype=float)
            if not (np.all(np.isfinite(axis)) and np.linalg.norm(axis) > 0):
                raise robot.error(
                    f"joint '{joint.name}': its <axis> must be a finite, non-zero vector", "joint", joint.name, "axis"
                )
        limit = joint.limit
        if limit is None and joint.type in ("revolute", "prismatic"):
            # URDF requires it (urdfdom refuses the file); read as no limits, IK went anywhere
            raise robot.error(
                f"joint '{joint.name}' is {joint.type} but has no <limit> (URDF requires one for revolute and "
                "prismatic joints)",
                "joint",
                joint.name,
                hint='add <limit lower="..." upper="..." effort="..." velocity="..."/>'
                + (', or make it type="continuous" if it turns without limits' if joint.type == "revolute" else ""),
            )
        if limit is not None and joint.type in ("revolute", "prismatic"):
            low, high = _limit_values(limit)
            if not (np.isfinite(low) and np.isfinite(high) and low <= high):
                raise robot.error(
                    f"joint '{joint.name}': its <limit> must have lower ≤ upper, got lower={low:g} upper={high:g}",
                    "joint",
                    joint.name,
                    "limit",
                )
        if joint.child in parent_of:
            raise robot.error(
                f"link '{joint.child}' is the child of two joints ('{parent_of[joint.child]}' and '{joint.name}')",
                "joint",
                joint.name,
            )
        parent_of[joint.child] = joint.name
        robot.children.setdefault(joint.parent, []).append(joint)
    roots = [name for name in links if name not in parent_of]
    if not roots:
        # every link has a parent: follow parents from the first link until one repeats, and name a
        # joint of that cycle at its line (the message had no line to go to)
        joints = {j.name: j for j in urdf.robot.joints}
        walked: list[str] = []
        link = next(iter(links))
        while link not in walked:
            walked.append(link)
            link = joints[parent_of[link]].parent
        cycle = [parent_of[name] for name in walked[walked.index(link) :]]
        raise robot.error(
            f"the links do not form one tree: the joints {', '.join(repr(j) for j in cycle)} form a cycle",
            "joint",
            cycle[0],
        )
    if len(roots) != 1:
        raise robot.error(f"the links do not form one tree: several root links: {', '.join(roots)}", "link", roots[1])
    robot.root = roots[0]
    order = []
    stack = [robot.root]
    while stack:
        link = stack.pop()
        order.append(link)
        stack.extend(reversed([j.child for j in robot.children.get(link, [])]))
    if len(order) != len(links):
        lost = [name for name in links if name not in set(order)]
        raise robot.error(f"the joints form a cycle through the links {', '.join(lost)}")
    joints_by_name = {j.name: j for j in urdf.robot.joints}
    for joint in urdf.robot.joints:
        if joint.mimic is not None:
            other = joints_by_name.get(joint.mimic.joint)
            if other is None:
                raise robot.error(
                    f"joint '{joint.name}' mimics '{joint.mimic.joint}', which does not exist",
                    "joint",
                    joint.name,
                    "mimic",
                    hint=suggest(str(joint.mimic.joint), [j for j in joints_by_name if j != joint.name])
                    or f"the robot's joints: {', '.join(joints_by_name)}",
                )
            if other.type not in MOVING or other.mimic is not None:
                why = f"is {other.type}" if other.type not in MOVING else f"mimics '{other.mimic.joint}' itself"
                raise robot.error(
                    f"joint '{joint.name}' mimics '{other.name}', which {why}: a mimic joint follows a moving joint "
                    "without <mimic>",
                    "joint",
                    joint.name,
                    "mimic",
                )
            if joint.type not in MOVING:
                raise robot.error(f"joint '{joint.name}' is {joint.type} but has <mimic>", "joint", joint.name)
    taken: set[str] = set()
    for name in order:
        robot.links[name] = _identifier(name, taken, {"origin"})
    taken = set()
    for joint in urdf.robot.joints:
        robot.joints[joint.name] = _identifier(joint.name, taken)
    return robot


def urdf_names(path: str | os.PathLike[str]) -> dict[str, dict[str, str]]:
    """The URDF → mdl name mapping: ``{"link": {...}, "joint": {...}}``."""
    robot = read_robot(path)
    return {"link": dict(robot.links), "joint": dict(robot.joints)}


def resolve_mesh(filename: str, urdf_path: str | os.PathLike[str]) -> Path | None:
    """The file a URDF mesh name refers to, or None when none exists (see the module doc)."""
    base = Path(urdf_path).resolve().parent
    if filename.startswith("file://"):
        candidates = [Path(filename[len("file://") :])]
    elif filename.startswith("package://"):
        package, _, rest = filename[len("package://") :].partition("/")
        folders = [base, *base.parents]
        candidates = [d / rest for d in folders if d.name == package]
        candidates += [d / package / rest for d in folders]
        candidates.append(base / rest)
    elif "://" in filename:
        return None
    else:
        candidates = [base / filename]
    for candidate in candidates:
        if candidate.is_file():
            return candidate.resolve()
    return None


# ---- .mdl text ------------------------------------------------------------------------------------


def _num(value: float) -> str:
    value = float(value)
    if value == 0.0:
        return "0"
    return f"{value:.15g}"


def _length(value: float) -> str:
    return f"{_num(value)} m"


def _angle(value: float) -> str:
    return f"{_num(math.degrees(value))} deg"


def xyz_rpy(matrix: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """Translation and URDF roll-pitch-yaw of a 4×4 origin (None: the identity)."""
    import trimesh.transformations as tra  # heavy: trimesh is loaded only for URDFs and meshes

    if matrix is None:
        return np.zeros(3), np.zeros(3)
    matrix = np.asarray(matrix, dtype=float)
    return matrix[:3, 3].copy(), np.array(tra.euler_from_matrix(matrix, "sxyz"), dtype=float)


def pose_matrix(xyz, rpy) -> np.ndarray:
    import trimesh.transformations as tra  # heavy: trimesh is loaded only for URDFs and meshes

    matrix = tra.euler_matrix(float(rpy[0]), float(rpy[1]), float(rpy[2]), "sxyz")
    matrix[:3, 3] = np.asarray(xyz, dtype=float)
    return matrix


def _constant_pose(matrix: np.ndarray | None) -> str:
    """`` at pose(...)`` for a constant origin, or nothing for the identity."""
    if matrix is None or np.allclose(matrix, np.eye(4), rtol=0.0, atol=1e-15):
        return ""
    xyz, rpy = xyz_rpy(matrix)
    return " at pose(" + ", ".join([*map(_length, xyz), *map(_angle, rpy)]) + ")"


def _axis(axis: np.ndarray) -> str:
    axis = np.asarray(axis, dtype=float)
    for i, letter in enumerate("xyz"):
        unit = np.zeros(3)
        unit[i] = 1.0
        if np.array_equal(axis, unit):
            return letter
        if np.array_equal(axis, -unit):
            return "-" + letter
    return "(" + ", ".join(_num(v) for v in axis) + ")"


def _comment(text: object) -> str:
    return " ".join(str(text).split())


def _urdf_primitive(geometry) -> tuple[str, np.ndarray] | None:
    """The shape kind a URDF ``<geometry>`` stands for (from the shape registry) and its sizes."""
    for kind in shape_kinds().values():
        if kind.urdf is None:
            continue
        tag, attributes = kind.urdf
        element = getattr(geometry, tag, None)
        if element is not None:
            values = [np.ravel(np.asarray(getattr(element, a, np.nan), dtype=float)) for a in attributes]
            return kind.name, np.concatenate(values) if values else np.zeros(0)
    return None


def _visual(visual, index: int, robot: _Robot, taken: set[str], base: Path) -> str:
    """One ``shape`` statement, or a comment saying why a visual is left out."""
    geometry = visual.geometry
    label = f"visual {index}" + (f" '{visual.name}'" if visual.name else "")
    if geometry is None:
        return f"# {label}: no geometry, left out"
    primitive = _urdf_primitive(geometry)
    if primitive is not None:
        kind, size = primitive
        dims = [_length(v) for v in size]
        ok = size.shape == (len(get_shape(kind).dims),) and get_shape(kind).invalid(size.tolist()) is None
    elif geometry.mesh is not None:
        filename = geometry.mesh.filename
        if not filename:
            return f"# {label}: a mesh without a file name, left out"
        found = resolve_mesh(filename, robot.path)
        if found is None:
            return f"# {label}: mesh file not found, left out: {_comment(filename)}"
        if found.suffix.lower() not in MESH_SUFFIXES:
            return f"# {label}: mesh format '{found.suffix}' is not supported, left out: {_comment(filename)}"
        try:
            load_mesh(found, None)
        except MeshError as err:
            return f"# {label}: mesh cannot be read, left out: {_comment(err.message)}"
        scale = np.ones(3) if geometry.mesh.scale is None else np.asarray(geometry.mesh.scale, dtype=float).ravel()
        if scale.size == 1:
            scale = np.repeat(scale, 3)
        if scale.size != 3 or not np.all(scale > 0):
            return f"# {label}: mesh scale {_comment(scale)} is not positive, left out"
        try:
            shown = Path(os.path.relpath(found, base)).as_posix()
        except ValueError:  # another drive
            shown = found.as_posix()
        kind = "mesh"
        dims = [json.dumps(shown, ensure_ascii=False), "scale = (" + ", ".join(_num(v) for v in scale) + ")"]
        ok = True
    else:
        return f"# {label}: geometry not supported, left out"
    if not ok:
        return f"# {label}: a {kind} with an invalid size (not positive), left out"
    name = _identifier(visual.name, taken) if visual.name else _identifier(f"visual{index}", taken)
    note = f"  # URDF visual '{_comment(visual.name)}'" if visual.name and visual.name != name else ""
    return f"shape {name} = {kind}({', '.join(dims)}){_constant_pose(visual.origin)}{note}"


def _joint_params(robot: _Robot, joint, ranges: dict[str, float]) -> list[str]:
    j = robot.joints[joint.name]
    xyz, rpy = xyz_rpy(joint.origin)
    dl, da = ranges["origin_length"], ranges["origin_angle"]
    renamed = f" (mdl name '{j}')" if j != joint.name else ""
    lines = [
        f"# joint '{_comment(joint.name)}'{renamed}: {joint.type}, "
        f"'{_comment(joint.parent)}' -> '{_comment(joint.child)}'"
    ]
    for name, value in zip(ORIGIN_FIELDS[:3], xyz):
        lines.append(f"param {j}.{name} = {_length(value)} in [{_length(value - dl)}, {_length(value + dl)}]")
    for name, value in zip(ORIGIN_FIELDS[3:], rpy):
        lines.append(f"param {j}.{name} = {_angle(value)} in [{_angle(value - da)}, {_angle(value + da)}]")
    if joint.type in MOVING:
        if joint.type == "prismatic":
            zero, d = "0 m", ranges["offset_length"]
            limits = f"[{_length(-d)}, {_length(d)}]"
        else:
            zero, d = "0 deg", ranges["offset_angle"]
            limits = f"[{_angle(-d)}, {_angle(d)}]"
        if joint.mimic is None:
            lines.append(f"param {j}.q = {zero} per configuration")
        lines.append(f"param {j}.offset = {zero} in {limits}")
    return lines


def _joint_statement(robot: _Robot, joint, by_name: dict[str, Any]) -> str:
    j = robot.joints[joint.name]
    unit = "m" if joint.type == "prismatic" else "rad"
    if joint.mimic is None:
        q = f"{j}.q"
    else:
        other = by_name[joint.mimic.joint]
        source = "m" if other.type == "prismatic" else "rad"
        multiplier = 1.0 if joint.mimic.multiplier is None else float(joint.mimic.multiplier)
        shift = 0.0 if joint.mimic.offset is None else float(joint.mimic.offset)
        q = f"{_num(multiplier)} * ({robot.joints[other.name]}.q / (1 {source})) * (1 {unit}) + {_num(shift)} {unit}"
    args = [_axis(joint.axis), q, f"offset = {j}.offset"]
    limit = joint.limit
    note = ""
    if joint.type != "continuous" and limit is not None:
        show = _length if joint.type == "prismatic" else _angle
        low, high = _limit_values(limit)
        args += [f"lower = {show(low)}", f"upper = {show(high)}"]
        missing = [side for side in ("lower", "upper") if getattr(limit, side, None) is None]
        if missing:
            note = f"  # <limit> has no {' or '.join(missing)}: 0, URDF's default"
            if low == high:
                note += " (the joint cannot move)"
    return f"joint {joint.type}({', '.join(args)}){note}"


def _limit_values(limit) -> tuple[float, float]:
    """A ``<limit>``'s lower and upper values, each 0 where the element leaves it out: URDF's
    default (wiki.ros.org/urdf/XML/joint: "lower (optional, defaults to 0)", the same for
    upper; urdfdom reads them so, hence every consumer built on it).  Until now a missing side
    was read as no limit at all."""
    low, high = (getattr(limit, side, None) for side in ("lower", "upper"))
    return (0.0 if low is None else float(low), 0.0 if high is None else float(high))


def urdf_to_mdl(
    path: str | os.PathLike[str],
    *,
    mesh_base: str | os.PathLike[str] | None = None,
    origin_length: float = 0.02,
    origin_angle: float = math.radians(2.0),
    offset_angle: float = math.radians(5.0),
    offset_length: float = 0.005,
) -> str:
    """The ``.mdl`` text of a URDF file (see the module doc for what it holds).

    Parameters
    ----------
    path : path
        The URDF file.
    mesh_base : path, optional
        The folder mesh paths are written relative to (default: the URDF's folder; the text
        then works as a model file saved beside the URDF).
    origin_length, origin_angle : float
        Half-widths (m, rad) of the search ranges of the joint origins around their URDF values.
    offset_angle, offset_length : float
        Half-widths (rad, m) of the search ranges of the revolute and prismatic joint offsets.

    Raises
    ------
    UrdfError
        The file is not well-formed XML, not a valid URDF, not one tree of links, or has a
        floating or planar joint; with the file and, where known, the line.
    """
    robot = read_robot(path)
    ranges = {
        "origin_length": origin_length,
        "origin_angle": origin_angle,
        "offset_angle": offset_angle,
        "offset_length": offset_length,
    }
    base = Path(mesh_base).resolve() if mesh_base is not None else robot.path.resolve().parent
    urdf = robot.urdf
    by_name = {j.name: j for j in urdf.robot.joints}
    link_map = {link.name: link for link in urdf.robot.links}
    out = [
        f"# Generated by mbcal from {robot.path.name} (robot '{_comment(urdf.robot.name)}').",
        "# Lengths in m, angles in deg.  Per joint J: J.x J.y J.z J.roll J.pitch J.yaw (the origin),",
        "# J.q (the reading, per configuration) and J.offset (the encoder's zero).",
    ]
    renamed = [
        (kind, a, b) for kind, table in (("link", robot.links), ("joint", robot.joints)) for a, b in table.items()
    ]
    renamed = [item for item in renamed if item[1] != item[2]]
    if renamed:
        out.append("# Renamed (URDF -> mdl):")
        out.extend(f"#   {kind} '{_comment(a)}' -> {b}" for kind, a, b in renamed)
    out.append("")
    order: list[Any] = []
    stack = list(reversed(robot.children.get(robot.root, [])))
    while stack:
        joint = stack.pop()
        order.append(joint)
        stack.extend(reversed(robot.children.get(joint.child, [])))
    for joint in order:
        out.extend(_joint_params(robot, joint, ranges))
        out.append("")

    def frame(name: str, joint, depth: int) -> None:
        pad = "  " * depth
        mdl = robot.links[name]
        note = f"URDF link '{_comment(name)}'"
        if joint is None:
            out.append(f"{pad}link {mdl} {{  # {note}, the root")
        else:
            j = robot.joints[joint.name]
            pose = ", ".join(f"{j}.{f}" for f in ORIGIN_FIELDS)
            out.append(f"{pad}link {mdl} at pose({pose}) {{  # {note}, joint '{_comment(joint.name)}' ({joint.type})")
        inner = pad + "  "
        if joint is not None and joint.type in MOVING:
            out.append(inner + _joint_statement(robot, joint, by_name))
        out.append(f"{inner}point origin = (0, 0, 0)")
        taken = {"origin", *(robot.links[j.child] for j in robot.children.get(name, []))}
        for i, visual in enumerate(link_map[name].visuals):
            out.append(inner + _visual(visual, i, robot, taken, base))
        for child in robot.children.get(name, []):
            frame(child.child, child, depth + 1)
        out.append(pad + "}")

    frame(robot.root, None, 0)
    out.append("")
    out.append(f"measure {MEASURES}")
    return "\n".join(out) + "\n"
