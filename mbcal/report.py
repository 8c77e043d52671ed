"""Readable text: terminal tables and model summaries.

Plain text tables with box-drawing rules — no third-party dependency — that read well in a
terminal, a log file and a CI transcript alike.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from mbcal.language.model import Model

__all__ = ["table", "fmt", "model_summary"]


def fmt(value: Any, digits: int = 6) -> str:
    """A number with ``digits`` significant digits; other values as str."""
    if value is None:
        return "—"
    if isinstance(value, (bool, np.bool_)):
        return "yes" if value else "no"
    if isinstance(value, (int, np.integer)):
        return str(int(value))
    if isinstance(value, (float, np.floating)):
        v = float(value)
        if np.isnan(v):
            return "—"
        if np.isinf(v):
            return "∞" if v > 0 else "-∞"
        if v == 0:
            return "0"
        return f"{v:.{digits}g}"
    return str(value)


def table(
    headers: Sequence[str],
    rows: Sequence[Sequence[Any]],
    *,
    title: str | None = None,
    align: str | None = None,
    max_rows: int | None = None,
) -> str:
    """A text table.

    Parameters
    ----------
    headers : sequence of str
    rows : sequence of rows; cells are formatted with :func:`fmt`
    title : str, optional
        A line above the table.
    align : str, optional
        One letter per column, ``l`` or ``r``; numbers are right-aligned by default.
    max_rows : int, optional
        Show at most this many rows and say how many were left out.
    """
    shown = list(rows if max_rows is None else rows[:max_rows])
    cells = [[c if isinstance(c, str) else fmt(c) for c in row] for row in shown]
    if align is None:
        align = "".join(
            "r" if shown and all(isinstance(r[i], (int, float, np.number)) for r in shown if i < len(r)) else "l"
            for i in range(len(headers))
        )
    widths = [len(h) for h in headers]
    for row in cells:
        for i, c in enumerate(row):
            widths[i] = max(widths[i], len(c))

    def line(values: Sequence[str]) -> str:
        parts = []
        for i, v in enumerate(values):
            parts.append(v.rjust(widths[i]) if align[i] == "r" else v.ljust(widths[i]))
        return "  ".join(parts).rstrip()

    out = []
    if title:
        out.append(title)
    out.append(line(list(headers)))
    out.append("  ".join("─" * w for w in widths).rstrip())
    out.extend(line(r) for r in cells)
    if max_rows is not None and len(rows) > max_rows:
        out.append(f"… {len(rows) - max_rows} more rows")
    return "\n".join(out)


def _value_with_unit(info, value: float | None) -> str:
    if value is None:
        return "—"
    unit = info.unit
    return f"{fmt(info.display(value), 6)} {unit}".rstrip()


def model_summary(model: Model) -> str:
    """Parameters, frames, points, sensors and shapes of a model, as text."""
    from mbcal.language.ir import Const

    out = [f"model {model.path}"]
    if len(model.files) > 1:
        out.append("includes " + ", ".join(model.files[1:]))
    counts = (
        f"{len(model.params)} parameters, {len(model.frames)} frames, {len(model.points)} points, "
        f"{len(model.cameras)} cameras, {len(model.ranges)} range sensors, {len(model.shapes)} shapes"
    )
    out.append(counts)
    if model.params:
        rows = []
        for p in model.params:
            rng = "—"
            if p.lower is not None and p.upper is not None:
                rng = f"[{fmt(p.display(p.lower), 4)}, {fmt(p.display(p.upper), 4)}] {p.unit}".rstrip()
            rows.append(
                [
                    p.name,
                    _value_with_unit(p, p.nominal),
                    rng,
                    _value_with_unit(p, p.sigma),
                    "per configuration" if p.per_configuration else "",
                ]
            )
        out.append("")
        out.append(table(["parameter", "nominal", "search range", "prior σ", ""], rows, align="lllll"))
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
