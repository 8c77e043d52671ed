"""What the benchmark scripts share: timing, the machine's description, and writing a script's own
section of a page in docs/ (between its markers) without touching the rest."""

from __future__ import annotations

import os
import platform
import time
from collections.abc import Callable
from pathlib import Path

from mbcal.outputs import atomic_write


def best_of(fn: Callable[[], object], repeats: int) -> float:
    """The shortest of ``repeats`` timed calls (seconds): the least disturbed by the machine."""
    out = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        out.append(time.perf_counter() - t0)
    return min(out)


def cpu_name() -> str:
    """The processor's model name (from /proc/cpuinfo where there is one)."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def cores_and_system() -> str:
    return f"{os.cpu_count()} cores, {platform.system()} {platform.release()}"


def replace_section(path: Path, text: str, begin: str, end: str, *, append: bool = True) -> None:
    """Write ``text`` (which starts with ``begin`` and ends with ``end``) over that section of
    ``path``; where the page has no such section, append it (or refuse, if not ``append``)."""
    old = path.read_text(encoding="utf-8") if path.exists() else ""
    start, stop = old.find(begin), old.find(end)
    if start >= 0 and stop > start:
        new = old[:start] + text + old[stop + len(end) :]
    elif append:
        new = old.rstrip("\n") + ("\n\n" if old else "") + text + "\n"
    else:
        raise SystemExit(f"{path} has no '{begin}' … '{end}' section to replace")
    atomic_write(path, new)
