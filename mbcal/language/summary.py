"""A model's summary as text: what ``mbcal check`` prints."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from mbcal.language.graph import Const
from mbcal.text import fmt, table

if TYPE_CHECKING:
    from mbcal.language.model import Model

__all__ = ["model_summary"]


def _value_with_unit(info, value: float | None) -> str:
    if value is None:
        return "—"
    unit = info.unit
    return f"{fmt(info.display(value), 6)} {unit}".rstrip()


def _limits(info) -> str:
    if not info.limited:
        return "—"
    lo = "-∞" if info.limit_lower is None else fmt(info.display(info.limit_lower), 4)
    hi = "∞" if info.limit_upper is None else fmt(info.display(info.limit_upper), 4)
    return f"[{lo}, {hi}] {info.unit}".rstrip()


def _count(n: int, noun: str) -> str:
    """``1 camera``, ``2 cameras``, ``0 cameras``."""
    return f"{n} {noun}" if n == 1 else f"{n} {noun}s"


def model_summary(model: Model) -> str:
    """Parameters, frames, points, sensors and shapes of a model, as text."""
    out = [f"model {model.path}"]
    if len(model.files) > 1:
        out.append("includes " + ", ".join(model.files[1:]))
    counts = ", ".join(
        _count(len(items), noun)
        for items, noun in (
            (model.params, "parameter"),
            (model.frames, "frame"),
            (model.points, "point"),
            (model.cameras, "camera"),
            (model.ranges, "range sensor"),
            (model.shapes, "shape"),
        )
    )
    out.append(counts)
    rows: list[list[Any]]
    if model.params:
        rows = []
        limited = any(p.limited for p in model.params)  # the limits column only when a model has some
        for p in model.params:
            rng = "—"
            if p.lower is not None and p.upper is not None:
                rng = f"[{fmt(p.display(p.lower), 4)}, {fmt(p.display(p.upper), 4)}] {p.unit}".rstrip()
            row = [p.name, _value_with_unit(p, p.nominal), rng]
            if limited:
                row.append(_limits(p))
            row += [_value_with_unit(p, p.sigma), "per configuration" if p.per_configuration else ""]
            rows.append(row)
        head = ["parameter", "nominal", "search range"] + (["limits"] if limited else []) + ["prior σ", ""]
        out.append("")
        out.append(table(head, rows, align="l" * len(head)))
    if model.frames:
        rows = []
        for f in model.frames:
            parent = model.frames[f.parent].name if f.parent >= 0 else "world"
            joint = f"{f.joint.kind}" if f.joint else ""
            rows.append([f.name, f.keyword, parent, joint])
        out.append("")
        out.append(table(["frame", "kind", "parent", "joint"], rows, align="llll", max_rows=60))
    if model.points:
        out.append("")
        names = [p.name for p in model.points]
        shown = ", ".join(names[:40]) + (f", … ({len(names) - 40} more)" if len(names) > 40 else "")
        out.append(f"points ({len(names)}): {shown}")
    if model.cameras:
        rows = []
        for c in model.cameras:
            vals = [float(n.value) if isinstance(n, Const) else "param" for n in c.intrinsics[:4]]
            dist = any(not (isinstance(n, Const) and float(n.value) == 0.0) for n in c.distortion)
            rows.append([c.name, f"{c.width}×{c.height}", *vals, "yes" if dist else "no"])
        out.append("")
        out.append(table(["camera", "size", "fx", "fy", "cx", "cy", "distortion"], rows, align="llrrrrl"))
    if model.ranges:
        rows = [[r.name, len(r.directions), r.max_range] for r in model.ranges]
        out.append("")
        out.append(table(["range sensor", "rays", "max range (m)"], rows))
    if model.shapes:
        kinds: dict[str, int] = {}
        for s in model.shapes:
            kinds[s.kind] = kinds.get(s.kind, 0) + 1
        out.append("")
        out.append("shapes: " + ", ".join(f"{n} {k}" for k, n in kinds.items()))
    if model.measures:
        out.append("measurement models: " + ", ".join(model.measures))
    for w in model.warnings:
        out.append(f"warning: {w}")
    return "\n".join(out)
