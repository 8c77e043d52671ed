"""Many configurations: camera calibration with hundreds of views, and a bundle adjustment (issue 15).

1. Camera calibration (models/camera_calibration.mdl: 9 × 6 board, OpenCV's 5-term distortion)
   from 13, 100, 500 and 2,000 synthetic views (0.3 px noise), warm: mbcal's structured solve
   (Zhang's closed-form start, Schur-complement Marquardt, σ of the intrinsics from the reduced
   system) beside ``cv2.calibrateCamera`` on the same points; `calibrate_cameras` (the full
   report, analysed from the blocks beyond the dense analysis' size).  Every size runs in two fresh
   processes (``--camera-row N``), so that its peak memory is its own: the first from an empty
   cache folder (every program compiled), the second loading those programs; the process's peak,
   the part the mbcal solve and analysis added above the simulated data, and the resident memory
   after each step (a table).  Time per iteration and the largest difference of the estimates
   from OpenCV's.
2. BAL Ladybug-49 (``../shared/data/bal/problem-49-7776-pre.txt``: 49 cameras, 7,776 points,
   31,843 observations, 23,769 unknowns) from the file's initial values through the low-level
   structured API: Σr² and wall time, the first call (compile) separately; with ``--scipy`` also
   scipy's ``least_squares(method="trf")`` with the Jacobian's sparsity pattern (SciPy cookbook
   settings: finite differences, ``x_scale="jac"``, ``ftol=1e-4``; about 100 s).

3. Growing unknowns to 10,000: time per iteration of the structured and the dense solver as the
   views of models/camera_calibration.mdl grow (9 shared unknowns + 6 per view), with a plot
   (docs/images/scaling_structured.png).

The section goes into docs/performance.md between its markers (``--out -`` prints it).

    python bench/scale.py                      # 13, 100, 500, 2000 views; Ladybug
    python bench/scale.py --scipy              # and scipy's reference run on Ladybug
    python bench/scale.py --quick --out -      # tiny: 13 views, the 3-camera BAL file
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from common import CAMERA_TRUTH, best_of, cores_and_system, cpu_name, growth_exponent, publish, save_figure  # noqa: E402

import mbcal  # noqa: E402
from mbcal._jax import jax  # noqa: E402
from mbcal.datasets.bal import bal_residual, read_bal  # noqa: E402
from mbcal.modeling import modeler  # noqa: E402
from mbcal.problem import Problem  # noqa: E402
from mbcal.solver import SolverConfig, least_squares  # noqa: E402
from mbcal.structured import (  # noqa: E402
    analyze_structured,
    bal_structure,
    least_squares_structured,
    structure_of,
)
from mbcal.workflows.cameras import (  # noqa: E402
    calibrate_cameras,
    default_unknowns,
    initial_values,
    simulate_views,
)

BEGIN = "<!-- bench/scale.py: begin -->"
END = "<!-- bench/scale.py: end -->"
BAL = ROOT.parent / "shared" / "data" / "bal"
MODEL = ROOT / "models" / "camera_calibration.mdl"
TRUTH = CAMERA_TRUTH
INTRINSICS = list(TRUTH)
JAXLS = {"cost": 26882.0, "seconds": 3.7, "iterations": 30}  # the reference (jaxls, same machine kind)
SCIPY_REFERENCE = {"cost": 26818.0, "seconds": 96.0}


def peak_mb() -> float:
    """The process's peak resident memory so far (MB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def resident_mb() -> float:
    """The process's resident memory now (MB; Linux, else the peak)."""
    try:
        return int(Path("/proc/self/statm").read_text().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20
    except (OSError, ValueError, IndexError):
        return peak_mb()


# Resident memory after each step of a camera row (MB) and the peak so far: where the memory goes.
MEMORY: dict[str, tuple[float, float]] = {}
STEPS = {
    "start": "Python, NumPy, JAX, OpenCV and mbcal imported",
    "data": "the simulated views (simulate_views: the measurement objects, the simulation's programs), or "
    "in the *from a file* process the same corners read from a CSV file (`read_measurements`), as "
    "`mbcal calibrate-camera` reads them",
    "problem": "Problem, structure_of and Zhang's start",
    "solve": "the first structured solve (compiling or loading its program)",
    "analysis": "σ of the shared unknowns from the reduced system (analyze_structured)",
    "warm": "the warm repeats of the whole path",
    "report": "calibrate_cameras, the full report (analysed from the blocks beyond ~250 views)",
}


def mark(step: str) -> None:
    """Record the resident memory after ``step`` (the first time it is reached)."""
    MEMORY.setdefault(step, (resident_mb(), peak_mb()))


def synthetic_views(model: mbcal.Model, n: int, *, seed: int = 1, sigma: float = 0.3) -> mbcal.MeasurementSet:
    """Image points of the model's board in ``n`` random views at TRUTH (:func:`simulate_views`)."""
    return simulate_views(model, n, TRUTH, seed=seed, sigma=sigma)[0]


def board_local(model: mbcal.Model) -> dict[str, np.ndarray]:
    """Each board corner's position in the board's frame (m)."""
    info = model.target("board")
    scene = modeler(model, model.nominal)
    T = np.asarray(scene.frame_poses[info.frame], dtype=float)
    first = model.point_index(info.points[0])
    P = np.asarray(scene.points, dtype=float)[first : first + len(info.points)]
    return dict(zip(info.points, (P - T[:3, 3]) @ T[:3, :3]))


def opencv(model: mbcal.Model, data: mbcal.MeasurementSet, repeats: int):
    """``cv2.calibrateCamera`` on the same points: (seconds, {intrinsic: value}) or None without OpenCV."""
    try:
        import cv2  # optional dependency
    except ImportError:
        return None
    local = board_local(model)
    by_view: dict[str, list] = {}
    for m in data:
        by_view.setdefault(m.config, []).append((local[m.refs["point"]], m.value))
    obj = [np.array([p for p, _ in pts], dtype=np.float32) for pts in by_view.values()]
    img = [np.array([uv for _, uv in pts], dtype=np.float32).reshape(-1, 1, 2) for pts in by_view.values()]
    cam = model.cameras[0]
    out: dict = {}

    def run():
        criteria = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 100, 1e-12)
        out["r"] = cv2.calibrateCamera(obj, img, (cam.width, cam.height), None, None, criteria=criteria)

    seconds = best_of(run, repeats)
    _, K, dist, _, _ = out["r"]
    d = np.ravel(dist)
    values = dict(zip(INTRINSICS, [K[0, 0], K[1, 1], K[0, 2], K[1, 2], d[0], d[1], d[2], d[3], d[4]]))
    return seconds, {k: float(v) for k, v in values.items()}


def mbcal_structured(model: mbcal.Model, data: mbcal.MeasurementSet, repeats: int) -> dict:
    """Zhang's start, the Schur-complement solve and σ of the shared unknowns, timed warm."""
    estimate = default_unknowns(model, data)
    out: dict = {}

    def run():
        for name in ("problem", "structure", "solved", "analysis"):  # a repeat holds one path's objects
            out.pop(name, None)
        problem = Problem(model, data, estimate)
        structure = structure_of(problem)
        assert structure is not None
        x0 = problem.params.from_dict(initial_values(model, data, problem.params.names))
        args = (problem.y, problem.params.known)
        mark("problem")
        t = time.perf_counter()
        solved = least_squares_structured(
            problem.residual_function,
            x0,
            structure,
            args=args,
            config=SolverConfig(),
            local=problem.local,
            cache_key=problem.fingerprint(),  # as calibrate: a new Problem finds the program it traced
        )
        out["solve"] = time.perf_counter() - t
        mark("solve")
        analysis = analyze_structured(problem.residual_function, solved.x_best, structure, args=args)
        mark("analysis")
        out.update(problem=problem, structure=structure, solved=solved, analysis=analysis)

    t0 = time.perf_counter()
    run()
    out["first"] = time.perf_counter() - t0
    out["warm"] = best_of(run, repeats)
    mark("warm")
    names = out["problem"].params.names
    x = out["solved"].x_best
    out["values"] = {k: float(x[names.index(k)]) for k in INTRINSICS}
    shared = [names[j] for j in out["structure"].shared.ravel()]
    out["std"] = {k: float(out["analysis"].shared_std[shared.index(k)]) for k in INTRINSICS}
    out["iterations"] = int(out["solved"].iterations.max())
    out["status"] = out["solved"].status_best.label
    return out


def full_report(model: mbcal.Model, data: mbcal.MeasurementSet, repeats: int) -> tuple[float, str]:
    """Warm ``calibrate_cameras`` (the full report: analysed densely up to
    DENSE_ANALYSIS_ENTRIES, from the blocks beyond) and its fit verdict's headline."""
    verdict = calibrate_cameras(model, data, restarts=1).result.verdict.verdict()  # (not held while timed)
    return best_of(lambda: calibrate_cameras(model, data, restarts=1), repeats), verdict


def camera_row(n: int, repeats: int, compare: bool = True, read: str | None = None, write: str | None = None) -> dict:
    """One size of the camera benchmark, measured in this (fresh) process; ``compare``: also
    OpenCV (the rows that only measure memory leave it out); ``read``: the corners from that
    file instead of simulated here; ``write``: save the simulated corners there at the end."""
    from mbcal.measurements.io import read_measurements, write_measurements

    mark("start")
    model = mbcal.load_model(MODEL)
    data = read_measurements(read, model) if read else synthetic_views(model, n)
    mark("data")
    before = resident_mb()
    ours = mbcal_structured(model, data, repeats)
    peak = peak_mb()
    row = {
        "views": n,
        "points": len(data),
        "unknowns": ours["problem"].params.size,
        **{k: ours[k] for k in ("first", "warm", "solve", "values", "std", "iterations", "status")},
        "peak_mb": peak,
        "data_mb": before,
        "added_mb": max(peak - before, 0.0),
    }
    for name in ("problem", "structure", "solved", "analysis"):  # the report's peak is its own
        ours.pop(name)
    cv = opencv(model, data, repeats) if compare else None
    if cv is not None:
        row["cv_seconds"], row["cv_values"] = cv
        row["differs"] = max(abs(ours["values"][k] - cv[1][k]) / ours["std"][k] for k in INTRINSICS)
    row["report"], row["verdict"] = full_report(model, data, max(1, repeats // 2) if n <= 500 else 1)
    mark("report")
    row["report_peak_mb"] = peak_mb()
    row["memory"] = MEMORY
    if write:  # after every measurement of this process
        write_measurements(data, write)
    return row


def camera_rows(sizes: list[int], repeats: int) -> list[dict]:
    """Each size in two fresh processes, so that a peak memory is its own, not the largest so
    far: the first with an empty cache folder (every program traced and compiled: the timed row),
    the second with the programs it left (loaded, nothing compiled: the memory a later run needs)."""
    rows = []
    for n in sizes:
        with tempfile.TemporaryDirectory(prefix="mbcal-scale-cache-") as cache:
            env = {**os.environ, "MBCAL_CACHE_DIR": cache}

            def run(*extra: str, cache_dir: str = cache) -> dict:
                proc = subprocess.run(
                    [sys.executable, __file__, "--camera-row", str(n), *extra],
                    capture_output=True,
                    text=True,
                    check=False,
                    env={**env, "MBCAL_CACHE_DIR": cache_dir},
                )
                if proc.returncode != 0:
                    raise SystemExit(f"the {n}-view row failed:\n{proc.stderr}")
                return json.loads(proc.stdout.strip().splitlines()[-1])

            corners = str(Path(cache) / "corners.csv")
            row = run("--repeats", str(repeats), "--write-data", corners)
            row["cached"] = run("--repeats", "1", "--memory-only")
            with tempfile.TemporaryDirectory(prefix="mbcal-scale-cache-") as empty:  # a first run: compiles
                row["file"] = run("--repeats", "1", "--memory-only", "--read-data", corners, cache_dir=empty)
        rows.append(row)
        cv_s = row.get("cv_seconds", float("nan"))
        print(
            f"{n} views: mbcal {row['warm']:.3f} s, OpenCV {cv_s:.3f} s, peak {row['peak_mb']:.0f} MB", file=sys.stderr
        )
    return rows


def scaling_rows(views: list[int], dense_up_to: int, repeats: int) -> list[dict]:
    """Time per iteration of the structured and the dense solver from Zhang's start, as the views
    (and the unknowns, 9 + 6 per view) grow; the dense solver up to ``dense_up_to`` unknowns."""
    model = mbcal.load_model(MODEL)
    rows = []
    for n in views:
        data = synthetic_views(model, n)
        problem = Problem(model, data, default_unknowns(model, data))
        structure = structure_of(problem)
        assert structure is not None
        x0 = problem.params.from_dict(initial_values(model, data, problem.params.names))
        args = (problem.y, problem.params.known)
        row: dict = {"views": n, "unknowns": problem.params.size, "residuals": problem.n_residuals}
        solvers = {
            "structured": lambda: least_squares_structured(
                problem.residual_function, x0, structure, args=args, local=problem.local
            )
        }
        if problem.params.size <= dense_up_to:
            solvers["dense"] = lambda: least_squares(
                problem.residual_function, x0, args=args, size=problem.n_residuals, local=problem.local
            )
        for name, solve in solvers.items():
            t = time.perf_counter()
            solved = solve()
            first = time.perf_counter() - t
            warm = best_of(solve, repeats if problem.params.size <= 3000 else 1)
            iterations = max(int(solved.iterations[0]), 1)
            row[name] = {"solve": warm, "first": first, "iterations": iterations, "per_iteration": warm / iterations}
        rows.append(row)
        print(
            f"scaling: {n} views, {row['unknowns']} unknowns: {row['structured']['per_iteration']:.4f} s",
            file=sys.stderr,
        )
    return rows


def scaling_plot(rows: list[dict], path: Path) -> None:
    """Time per iteration against the unknowns, both solvers, log–log."""
    import matplotlib  # optional dependency (the plot only)

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.5, 4.2))
    for name, style in (("structured", "o-"), ("dense", "s--")):
        have = [r for r in rows if name in r]
        if have:
            ax.loglog([r["unknowns"] for r in have], [1e3 * r[name]["per_iteration"] for r in have], style, label=name)
    ax.set_xlabel("unknowns (9 intrinsics + 6 per view)")
    ax.set_ylabel("ms per iteration")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    ax.set_title("camera calibration, one Marquardt solve, warm, CPU")
    fig.tight_layout()
    save_figure(fig, path)


def growth(rows: list[dict], name: str) -> float:
    """The exponent b of time per iteration ∝ unknowns^b over the larger half of the sizes."""
    have = [r for r in rows if name in r]
    return growth_exponent([r["unknowns"] for r in have], [r[name]["per_iteration"] for r in have])


def bal_run(path: Path, iterations: list[int], run_scipy: bool) -> dict:
    bal = read_bal(path)
    structure = bal_structure(bal)
    C = bal.n_cameras

    def fun(x, ci, pi, obs):
        return bal_residual(x, ci, pi, obs, C)

    args = (bal.camera_index, bal.point_index, bal.observed)
    out: dict = {"file": path.name, "cameras": C, "points": bal.n_points, "observations": len(bal.observed)}
    out["n"] = structure.n
    out["cost0"] = float(np.sum(np.asarray(jax.jit(fun)(bal.x0, *args)) ** 2))
    out["runs"] = []
    for cap in iterations:
        config = SolverConfig(max_iterations=cap)
        t = time.perf_counter()
        least_squares_structured(fun, bal.x0, structure, args=args, config=config)
        first = time.perf_counter() - t
        t = time.perf_counter()
        solved = least_squares_structured(fun, bal.x0, structure, args=args, config=config)
        warm = time.perf_counter() - t
        out["runs"].append(
            {
                "cap": cap,
                "first": first,
                "warm": warm,
                "cost": solved.cost_best,
                "iterations": int(solved.iterations[0]),
            }
        )
        print(f"{path.name}: {cap} iterations, Σr² {solved.cost_best:.1f}, {warm:.2f} s warm", file=sys.stderr)
    out["peak_mb"] = peak_mb()
    if run_scipy:
        out["scipy"] = scipy_run(bal, fun, args)
    return out


def scipy_run(bal, fun, args) -> dict:
    """scipy's trf with the sparsity pattern of the Jacobian (finite differences, as the SciPy cookbook)."""
    from scipy.optimize import least_squares as scipy_least_squares  # a reference, only here
    from scipy.sparse import lil_matrix

    m, n = 2 * len(bal.observed), len(bal.x0)
    A = lil_matrix((m, n), dtype=int)
    i = np.arange(len(bal.observed))
    for s in range(9):
        A[2 * i, bal.camera_index * 9 + s] = 1
        A[2 * i + 1, bal.camera_index * 9 + s] = 1
    for s in range(3):
        A[2 * i, bal.n_cameras * 9 + bal.point_index * 3 + s] = 1
        A[2 * i + 1, bal.n_cameras * 9 + bal.point_index * 3 + s] = 1
    f = jax.jit(fun)

    def residual(x):
        return np.asarray(f(x, *args))

    t = time.perf_counter()
    res = scipy_least_squares(residual, bal.x0, jac_sparsity=A, x_scale="jac", ftol=1e-4, method="trf")
    return {"seconds": time.perf_counter() - t, "cost": 2.0 * float(res.cost), "evaluations": int(res.nfev)}


def memory_table(cams: list[dict]) -> list[str]:
    """Where the memory of each camera row goes: resident after each step (the peak so far in
    parentheses), compiling every program and loading them from the cache."""
    lines = [
        "### Memory of the camera rows",
        "",
        "Resident memory (MB) of the process after each step, the peak so far in parentheses; each size "
        "in three fresh processes: *compiling* starts from an empty cache folder (every program traced "
        "and compiled: the timed rows above), *cached* is a second process that loads those programs, "
        "*compiling, from a file* a third, again from an empty cache folder, that reads the same corners "
        "from a CSV file instead of simulating them (a user's first run: no simulation).  "
        "Steps: " + "; ".join(f"*{k}*: {v}" for k, v in STEPS.items()) + ".",
        "",
        "| views | programs | " + " | ".join(STEPS) + " |",
        "|--:|---|" + "--:|" * len(STEPS),
    ]
    for r in cams:
        for label, row in (("compiling", r), ("cached", r.get("cached")), ("compiling, from a file", r.get("file"))):
            if not row or "memory" not in row:
                continue
            cells = [
                f"{row['memory'][k][0]:.0f} ({row['memory'][k][1]:.0f})" if k in row["memory"] else "—" for k in STEPS
            ]
            lines.append(f"| {r['views']} | {label} | " + " | ".join(cells) + " |")
    return [*lines, ""]


def file_peaks(cams: list[dict]) -> list[str]:
    """The peak of the process a user runs the first time: corners read from a file, every program
    compiled (goal at 2,000 views: 500 MB), beside the benchmark's own process that simulated them."""
    rows = [(r["views"], r["file"]["peak_mb"], r["peak_mb"]) for r in cams if "file" in r]
    if not rows:
        return []
    goal = next((f" (goal ≤ 500 MB: {'met' if p <= 500 else '**missed**'})" for v, p, _ in rows if v == 2000), "")
    listed = ", ".join(f"{v} views {p:.0f} MB" for v, p, _ in rows)
    return [
        "Peak memory of the mbcal path in the process a user runs — the corners read from a CSV file, "
        f"every program compiled (an empty cache), no simulation, no OpenCV comparison: {listed}{goal}; "
        "the *peak memory* "
        "column above is the benchmark's own process, which also simulated the views and compiled (it keeps "
        "the simulation's compiled programs, ~50 MB at 2,000 views, for a later simulation of the same plan).  "
        "After every XLA compile and after large structured work mbcal gives the heap that freed "
        "temporaries left in malloc's arenas back to the system (`mbcal._jax.release_memory`, glibc's "
        "`malloc_trim`): without it the process a user runs peaked at 527 MB at 2,000 views.",
        "",
    ]


def section(cams: list[dict], bal: dict, scaling: list[dict], plot: str | None, quick: bool) -> str:
    lines = [
        BEGIN,
        "## Many configurations: the Schur complement (issue 15)",
        "",
        "Written by `python bench/scale.py` (do not edit by hand; run it again)"
        + (" — **a `--quick` run: tiny sizes, not the benchmark**." if quick else "."),
        "Camera calibration from synthetic views of models/camera_calibration.mdl's 9 × 6 board (OpenCV's",
        "5-term distortion, 0.3 px noise, corners outside the image left out), warm, best of several runs.",
        "*mbcal* is the low-level structured path a program with many views uses: Zhang's closed-form start,",
        "Schur-complement Marquardt from it (one start), σ of the intrinsics from the reduced system",
        "(`mbcal.structured`, [scale.md](scale.md)); *calibrate_cameras* is the full report (residual",
        "table, observability, fit verdict; analysed from the blocks beyond `DENSE_ANALYSIS_ENTRIES`,",
        "about 250 views), one start from Zhang's closed form; its point uncertainties are computed when",
        "first read (`result.points`), which this timing does not do.",
        "Each size runs in fresh processes.  *Peak memory, corners from a file*: the peak resident size",
        "of a process that reads the corners from a CSV file and runs the mbcal path with an empty",
        "cache (every program compiled), as a user's first run does — Python, NumPy and JAX included.",
        "*Peak memory, the process that simulated them*: the same in the benchmark's timed process,",
        "which also simulated the views (their plan, the simulation's compiled programs);",
        "*added by mbcal* the part of it above the resident size before the mbcal path (the problem,",
        "the solve's first call with its compilation, the warm calls, the analysis); *report peak* the",
        "peak after calibrate_cameras too.",
        "",
        f"- machine: {cpu_name()}, {cores_and_system()}",
        f"- Python {platform.python_version()}, JAX {jax.__version__}, NumPy {np.__version__}",
        f"- run on {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}",
        "",
        "| views | image points | unknowns | mbcal (ms) | iterations | per iteration (ms) | first call (s) "
        "| OpenCV (ms) | OpenCV ÷ mbcal | largest difference from OpenCV (σ) "
        "| peak memory, corners from a file (MB; goal ≤ 500 at 2,000 views) "
        "| peak memory, the process that simulated them (MB) "
        "| added by mbcal (MB) | calibrate_cameras (ms) | report peak (MB) |",
        "|--:|--:|--:|--:|--:|--:|--:|--:|--:|--:|--:|--:|--:|--:|--:|",
    ]
    for r in cams:
        cv = r.get("cv_seconds")
        cv_ms = "—" if cv is None else f"{1e3 * cv:.0f}"
        ratio = "—" if cv is None else f"{cv / r['warm']:.2f}"
        differs = "—" if cv is None else f"{r['differs']:.1e}"
        per_iteration = 1e3 * r["solve"] / max(r["iterations"], 1)
        from_file = f"{r['file']['peak_mb']:.0f}" if "file" in r else "—"
        if "file" in r and r["views"] == 2000:
            from_file += " (met)" if r["file"]["peak_mb"] <= 500 else " (**missed**)"
        lines.append(
            f"| {r['views']} | {r['points']} | {r['unknowns']} | {1e3 * r['warm']:.0f} | {r['iterations']} "
            f"| {per_iteration:.1f} | {r['first']:.1f} | {cv_ms} | {ratio} | {differs} | {from_file} "
            f"| {r['peak_mb']:.0f} | {r['added_mb']:.0f} | {1e3 * r['report']:.0f} | {r['report_peak_mb']:.0f} |"
        )
    lines += [
        "",
        "The difference from OpenCV is the largest over the nine intrinsics, in units of each one's σ "
        "(both programs stop at their own tolerances; 1e-4 σ is far below any statistical meaning).  "
        f"mbcal's σ of fx at the largest size: {cams[-1]['std']['cam.fx']:.3g} px.  The full report's verdict "
        f"at the largest size: {cams[-1]['verdict']}.",
        "",
        *file_peaks(cams),
        *memory_table(cams),
        f"### Bundle adjustment: {bal['file']} ({bal['cameras']} cameras, {bal['points']:,} points, "
        f"{bal['observations']:,} observations, {bal['n']:,} unknowns)",
        "",
        "From the file's initial values (Σr² = " + f"{bal['cost0']:,.0f}" + "), every point a block of 3, every "
        "camera a group of 9 shared unknowns; the residual is written in JAX (`mbcal.datasets.bal`).",
        "",
        "| program | iteration cap | iterations | Σr² | wall time warm (s) | first call (s) |",
        "|---|--:|--:|--:|--:|--:|",
    ]
    for run in bal["runs"]:
        lines.append(
            f"| mbcal structured | {run['cap']} | {run['iterations']} | {run['cost']:,.1f} | {run['warm']:.2f} "
            f"| {run['first']:.2f} |"
        )
    if "scipy" in bal:
        s = bal["scipy"]
        lines.append(
            f"| scipy trf + sparsity (this run) | — | {s['evaluations']} evaluations | {s['cost']:,.1f} "
            f"| {s['seconds']:.1f} | — |"
        )
    if not quick:
        lines.append(
            f"| scipy trf + sparsity (the issue's measurement) | — | — | {SCIPY_REFERENCE['cost']:,.0f} "
            f"| {SCIPY_REFERENCE['seconds']:.0f} | — |"
        )
        lines.append(
            f"| jaxls, Schur + dense Cholesky (the issue's measurement) | {JAXLS['iterations']} "
            f"| {JAXLS['iterations']} | {JAXLS['cost']:,.0f} | {JAXLS['seconds']} | — |"
        )
    lines.append("")
    if "scipy" in bal:
        fastest = min(bal["runs"], key=lambda run: run["warm"])
        lines.append(
            f"scipy's run took {bal['scipy']['seconds'] / fastest['warm']:.0f}× the wall time of mbcal's "
            f"{fastest['cap']}-iteration run (Σr² {bal['scipy']['cost']:,.1f} against {fastest['cost']:,.1f})."
        )
    lines += [
        f"Peak memory of the process after the bundle adjustment (the camera sizes ran in their own "
        f"processes): {bal['peak_mb']:.0f} MB.",
        "",
        "### Growing unknowns to 10,000: the structured and the dense solver",
        "",
        "One Marquardt solve from Zhang's start, warm, of models/camera_calibration.mdl's views (9 shared "
        "unknowns + 6 per view, 0.3 px noise): the Schur complement beside the dense solver, the dense "
        "one up to a few hundred unknowns (beyond, its n × n system dominates: see *Growing unknowns* "
        "above).",
        "",
        "| views | unknowns | residuals | structured: ms / iteration | iterations | first call (s) "
        "| dense: ms / iteration | iterations | dense ÷ structured |",
        "|--:|--:|--:|--:|--:|--:|--:|--:|--:|",
    ]
    for r in scaling:
        st, de = r["structured"], r.get("dense")
        dense = (
            ("—", "—", "—")
            if de is None
            else (
                f"{1e3 * de['per_iteration']:.2f}",
                de["iterations"],
                f"{de['per_iteration'] / st['per_iteration']:.1f}",
            )
        )
        lines.append(
            f"| {r['views']} | {r['unknowns']:,} | {r['residuals']:,} | {1e3 * st['per_iteration']:.2f} "
            f"| {st['iterations']} | {st['first']:.1f} | {dense[0]} | {dense[1]} | {dense[2]} |"
        )
    b_s, b_d = growth(scaling, "structured"), growth(scaling, "dense")
    if np.isfinite(b_s) and np.isfinite(b_d):
        lines += [
            "",
            f"Time per iteration grows as about n^{b_s:.2f} with the unknowns n on the structured path (over "
            f"the larger half of its sizes) and as n^{b_d:.2f} on the dense one: the Schur complement's cost "
            "per iteration is linear in the views (compressed Jacobian m × 15, a 6 × 6 inverse per view, a "
            "9 × 9 reduced system).",
        ]
    lines.append("")
    if plot:
        lines += [f"![scaling of the structured solver]({plot})", ""]
    lines.append(END)
    return "\n".join(lines)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--views", default="13,100,500,2000", help="numbers of views (comma-separated)")
    parser.add_argument("--repeats", type=int, default=3, help="timed repeats (best of)")
    parser.add_argument("--quick", action="store_true", help="tiny sizes (13 views, the 3-camera BAL file)")
    parser.add_argument("--scipy", action="store_true", help="also run scipy's trf on the BAL problem (slow)")
    parser.add_argument("--out", default=str(ROOT / "docs" / "performance.md"), help="page to write ('-': print)")
    parser.add_argument(
        "--scaling", default="3,10,30,100,300,1000,1667", help="views of the growing-unknowns table (comma-separated)"
    )
    parser.add_argument("--camera-row", type=int, help=argparse.SUPPRESS)  # one size, in a fresh process
    parser.add_argument("--memory-only", action="store_true", help=argparse.SUPPRESS)  # that row without OpenCV
    parser.add_argument("--read-data", help=argparse.SUPPRESS)  # the corners from a file (a user's process)
    parser.add_argument("--write-data", help=argparse.SUPPRESS)  # save the simulated corners for that row
    args = parser.parse_args(argv)
    repeats = 1 if args.quick else args.repeats
    if args.camera_row:
        row = camera_row(args.camera_row, repeats, not args.memory_only, args.read_data, args.write_data)
        print(json.dumps(row))
        return 0
    sizes = [13] if args.quick else [int(v) for v in args.views.split(",")]
    cams = camera_rows(sizes, repeats)
    path = BAL / ("dubrovnik-3-7-pre.txt" if args.quick else "problem-49-7776-pre.txt")
    bal = bal_run(path, [5] if args.quick else [10, 30], args.scipy)
    scaling = scaling_rows([3, 10] if args.quick else [int(v) for v in args.scaling.split(",")], 700, repeats)
    plot = None
    if args.out != "-":
        image = Path(args.out).parent / "images" / "scaling_structured.png"
        if image.parent.is_dir():
            scaling_plot(scaling, image)
            plot = f"images/{image.name}"
    text = section(cams, bal, scaling, plot, args.quick)
    publish(text, args.out, BEGIN, END)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
