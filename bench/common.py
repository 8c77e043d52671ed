"""What the benchmark scripts share: timing, the machine's description, and writing a script's own
section of a page in docs/ (between its markers) without touching the rest."""

from __future__ import annotations

import os
import platform
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path

from mbcal.outputs import atomic_write

# The true intrinsics (OpenCV's 5-term model) of the simulated 9 × 6 board camera of
# models/camera_calibration.mdl, shared by the benchmarks that simulate its views.
CAMERA_TRUTH = {
    "cam.fx": 812.0,
    "cam.fy": 806.5,
    "cam.cx": 327.0,
    "cam.cy": 236.0,
    "cam.k1": -0.21,
    "cam.k2": 0.08,
    "cam.p1": 0.001,
    "cam.p2": -0.0007,
    "cam.k3": 0.0,
}


def _times(fn: Callable[[], object], repeats: int) -> list[float]:
    """Wall times (seconds) of ``repeats`` calls of ``fn``."""
    out = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        out.append(time.perf_counter() - t0)
    return out


def best_of(fn: Callable[[], object], repeats: int) -> float:
    """The shortest of ``repeats`` timed calls (seconds): the least disturbed by the machine."""
    return min(_times(fn, repeats))


def median_of(fn: Callable[[], object], repeats: int, warmup_s: float = 0.3) -> float:
    """The median of ``repeats`` timed calls (seconds): the measure of ../shared/PERFORMANCE-NOTES.md
    ("medians of 20 warm runs"), where a number is compared with the notes' own.  Untimed calls
    for ``warmup_s`` first (at least 3): the first calls after a compile ran ~15 % slower than
    the steady state (the room's 64 restarts: median 2.8 ms over the first 20, 2.45 after)."""
    start = time.perf_counter()
    calls = 0
    while calls < 3 or time.perf_counter() - start < warmup_s:
        fn()
        calls += 1
    return statistics.median(_times(fn, repeats))


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
    """Cores and system, with the load average of the last minute: a number measured while other
    work kept the machine busy says so on the page."""
    load = f"; load average {os.getloadavg()[0]:.1f} when it ran" if hasattr(os, "getloadavg") else ""
    return f"{os.cpu_count()} cores, {platform.system()} {platform.release()}{load}"


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


def publish(text: str, out: str, begin: str, end: str) -> None:
    """Print a bench's section; unless ``out`` is ``-``, also write it over its section of the
    page ``out`` (the rest of the page untouched)."""
    print(text)
    if out != "-":
        replace_section(Path(out), text, begin, end)
        print(f"\nwrote {out}", file=sys.stderr)


def save_figure(fig, path: Path, dpi: int = 110) -> None:
    """Write a matplotlib figure as a PNG atomically (a temporary file, then a rename)."""
    tmp = path.with_suffix(".tmp.png")
    fig.savefig(tmp, dpi=dpi)
    os.replace(tmp, path)


def growth_exponent(sizes, seconds) -> float:
    """The exponent b of seconds ∝ size^b, fitted over the larger half of the sizes (the asymptote)."""
    import numpy as np

    xs = np.log(np.asarray(sizes, dtype=float))[len(sizes) // 2 :]
    ys = np.log(np.asarray(seconds, dtype=float))[len(sizes) // 2 :]
    return float(np.polyfit(xs, ys, 1)[0]) if len(xs) > 1 else float("nan")
