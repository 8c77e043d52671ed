"""URDF out: a calibrated copy of the URDF a model was read from.

:func:`write_urdf` writes a calibrated copy of a URDF: it edits the input's XML tree with lxml
(everything else — comments, inertials, collisions, materials, formatting — is kept) and sets
each joint's ``<origin xyz rpy>`` from the estimated ``J.x`` ... ``J.yaw``.  Encoder offsets
are **folded into the origin**, exactly: a revolute joint's origin becomes
``origin · Rot(axis, offset)`` and a prismatic joint's ``origin · Trans(axis · offset)``, so the
same readings ``q`` give the calibrated kinematics in any URDF consumer.  Each edited joint
gets an XML comment with the offset and the previous origin; joints without estimates are
left untouched.  Relative mesh file names are rewritten when the output is in another folder.
The input is never overwritten; the output is written atomically.
"""

from __future__ import annotations

import datetime as _dt
import math
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from mbcal.language.urdf import MOVING, ORIGIN_FIELDS, pose_matrix, read_robot, xyz_rpy
from mbcal.outputs import atomic_write, check_output

__all__ = ["write_urdf"]


def _format(value: float) -> str:
    value = float(value)
    if abs(value) < 1e-15:
        return "0"
    return repr(value)


def _relocated_mesh(name: str, source: Path, out: Path) -> str | None:
    if "://" in name or Path(name).is_absolute():
        return None
    target = (source.parent / name).resolve()
    try:
        return Path(os.path.relpath(target, out.parent)).as_posix()
    except ValueError:  # another drive
        return target.as_posix()


def write_urdf(
    result_or_values: Any,
    urdf_in: str | os.PathLike[str],
    urdf_out: str | os.PathLike[str],
    *,
    overwrite: bool = True,
) -> dict[str, dict[str, Any]]:
    """Write ``urdf_in`` with calibrated joint origins to ``urdf_out`` (see the module doc).

    Parameters
    ----------
    result_or_values : CalibrationResult or mapping
        The estimates: a calibration result (its ``values``) or ``{name: SI value}`` with the
        parameter names of the generated model (``J.x`` ... ``J.yaw``, ``J.offset``).  Readings
        (``J.q``), per-configuration copies (``name@config``) and names that are not joint
        parameters of this URDF are ignored.
    urdf_in, urdf_out : path
        The URDF the model was made from, and the file to write (never ``urdf_in``).
    overwrite : bool
        Replace ``urdf_out`` if it exists.

    Returns
    -------
    dict
        For every edited joint (URDF name): ``xyz``, ``rpy`` (the new origin) and ``offset``
        (the folded offset, m or rad).
    """
    from lxml import etree  # heavy: lxml (yourdfpy's dependency), loaded only when a URDF is written

    values = result_or_values if isinstance(result_or_values, Mapping) else result_or_values.values
    source = Path(urdf_in)
    out = check_output(urdf_out, [source], overwrite=overwrite)
    robot = read_robot(source)
    tree = robot.tree
    root = tree.getroot()
    mdl_to_joint = {mdl: name for name, mdl in robot.joints.items()}
    wanted: dict[str, dict[str, float]] = {}
    for key, value in values.items():
        if "@" in key or "." not in key:
            continue
        prefix, _, name = key.rpartition(".")
        if prefix in mdl_to_joint and name in (*ORIGIN_FIELDS, "offset"):
            wanted.setdefault(mdl_to_joint[prefix], {})[name] = float(value)
    joints = {j.name: j for j in robot.urdf.robot.joints}
    elements = {e.get("name"): e for e in root.iterchildren("joint")}
    changed: dict[str, dict[str, Any]] = {}
    for name, estimates in wanted.items():
        joint = joints[name]
        offset = estimates.get("offset", 0.0) if joint.type in MOVING else 0.0
        if offset == 0.0 and not any(f in estimates for f in ORIGIN_FIELDS):
            continue
        element = elements[name]
        origin = element.find("origin")
        xyz0, rpy0 = xyz_rpy(joint.origin)
        xyz = np.array([estimates.get(f, v) for f, v in zip(ORIGIN_FIELDS[:3], xyz0)])
        rpy = np.array([estimates.get(f, v) for f, v in zip(ORIGIN_FIELDS[3:], rpy0)])
        # Components that keep their value keep their text (when it is the value mbcal read).
        written = {}
        if offset == 0.0 and origin is not None:
            for attribute, fields, nominal in (("xyz", ORIGIN_FIELDS[:3], xyz0), ("rpy", ORIGIN_FIELDS[3:], rpy0)):
                tokens = (origin.get(attribute) or "").replace(",", " ").split()
                if len(tokens) == 3:
                    for f, token, value in zip(fields, tokens, nominal):
                        if f not in estimates and _same(token, value):
                            written[f] = token
        if offset != 0.0:
            import trimesh.transformations as tra  # heavy: trimesh, loaded only for a joint offset

            axis = np.asarray(joint.axis, dtype=float)
            axis = axis / np.linalg.norm(axis)
            matrix = pose_matrix(xyz, rpy)
            if joint.type == "prismatic":
                matrix = matrix @ tra.translation_matrix(axis * offset)
            else:
                matrix = matrix @ tra.rotation_matrix(offset, axis)
            xyz, rpy = xyz_rpy(matrix)
        before = "none" if origin is None else f'xyz="{origin.get("xyz", "0 0 0")}" rpy="{origin.get("rpy", "0 0 0")}"'
        if origin is None:
            origin = etree.Element("origin")
            anchor = element.find("child")
            if anchor is None:
                element.insert(0, origin)
            else:
                anchor.addnext(origin)
                origin.tail = anchor.tail
        origin.set("xyz", " ".join(written.get(f, _format(v)) for f, v in zip(ORIGIN_FIELDS[:3], xyz)))
        origin.set("rpy", " ".join(written.get(f, _format(v)) for f, v in zip(ORIGIN_FIELDS[3:], rpy)))
        if joint.type == "prismatic":
            folded = f"{offset * 1000:.9g} mm"
        else:
            folded = f"{math.degrees(offset):.9g} deg"
        note = f" mbcal: calibrated origin; was {before}"
        if "offset" in estimates and joint.type in MOVING:
            note += f"; encoder offset {folded} folded in (readings unchanged)"
        comment = etree.Comment(note.replace("--", "- -") + " ")
        previous = origin.getprevious()
        indent = previous.tail if previous is not None else element.text
        origin.addprevious(comment)
        comment.tail = indent if indent is not None and not indent.strip() else None
        changed[name] = {"xyz": xyz.tolist(), "rpy": rpy.tolist(), "offset": offset}
    if out.resolve().parent != source.resolve().parent:
        for mesh in root.iter("mesh"):
            name = mesh.get("filename")
            new = _relocated_mesh(name, source, out) if name else None
            if new is not None:
                mesh.set("filename", new)

    stamp = _dt.datetime.now().strftime("%Y-%m-%d %H:%M")
    header = f" Calibrated by mbcal on {stamp} from {source.name}: {len(changed)} joint origin(s) edited "
    root.addprevious(etree.Comment(header.replace("--", "- -")))
    atomic_write(out, _serialize(tree))
    return changed


def _serialize(tree) -> bytes:
    """The document, with the nodes around the root element on lines of their own."""
    from lxml import etree  # heavy: lxml, loaded only when a URDF is written

    encoding = tree.docinfo.encoding or "UTF-8"
    version = tree.docinfo.xml_version or "1.0"
    root = tree.getroot()
    parts = [f'<?xml version="{version}" encoding="{encoding}"?>'.encode(encoding)]
    if tree.docinfo.doctype:
        parts.append(tree.docinfo.doctype.encode(encoding))
    nodes = [*reversed(list(root.itersiblings(preceding=True))), root, *root.itersiblings()]
    for node in nodes:
        parts.append(etree.tostring(node, encoding=encoding, xml_declaration=False, with_tail=False))
    return b"\n".join(parts) + b"\n"


def _same(token: str, value: float) -> bool:
    try:
        return abs(float(token) - float(value)) <= 1e-12
    except ValueError:
        return False
