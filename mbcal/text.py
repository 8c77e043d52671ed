"""Readable text: terminal tables and number formatting.

Plain text tables with box-drawing rules — no third-party dependency — that read well in a
terminal, a log file and a CI transcript alike.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

__all__ = ["table", "fmt"]


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
