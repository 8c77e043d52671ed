"""mbcal's fixed overhead (issue 16): a warm call against OpenCV, a cold start, the command line.

Run from the repository root (not part of the test suite)::

    python bench/overhead.py                     # about two minutes on 2 CPU cores
    python bench/overhead.py --views 3 --no-demo --out /tmp/overhead.md   # a quick look

It measures, in one run on one machine:

* **warm**: ``calibrate_cameras`` (Zhang's initialisation, the Marquardt solve, the whole
  post-solve analysis) on N simulated views of models/camera_calibration.mdl's 9 × 6 board,
  beside ``cv2.calibrateCamera`` (the same 5-term distortion model) on the same corners, and the
  JAX tracing and compiling a warm call still does (goal: none);
* **cold**: the same calibration as the first call of a fresh process with an empty cache
  (imports, model loading, trace + compile), and in a second process that finds the caches;
* **command line**: wall time of ``mbcal calibrate-camera`` on the same corners (empty cache,
  then warm caches) and of ``mbcal demo`` with warm caches, and the start-up of
  ``mbcal --help`` and ``mbcal check``.

It writes its own section of docs/performance.md (``--out`` to write elsewhere).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))
from common import CAMERA_TRUTH, best_of, cores_and_system, cpu_name, replace_section  # noqa: E402

BEGIN, END = "<!-- bench/overhead.py: begin -->", "<!-- bench/overhead.py: end -->"
MODEL = ROOT / "models" / "camera_calibration.mdl"
GOALS = {"warm_ratio": 1.0, "first_s": 1.0, "second_s": 0.3, "cli_s": 1.0, "demo_s": 4.0}
TRUTH = CAMERA_TRUTH


def say(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def camera_data(views: int, seed: int = 3):
    """(model, measurements): simulated corners (σ 0.5 px) of the board in ``views`` random poses."""
    import mbcal
    from mbcal.workflows.cameras import simulate_views

    model = mbcal.load_model(MODEL)
    return model, simulate_views(model, views, TRUTH, seed=seed, distance=(0.45, 0.7))[0]


def opencv_inputs(model, data):
    """The board's corners (z = 0 in the board's frame) and the image points per view, for OpenCV."""
    from mbcal.modeling import modeler

    scene = modeler(model, model.nominal)
    info = model.target(None)
    first = model.point_index(info.points[0])
    T = np.asarray(scene.frame_poses[info.frame], dtype=float)
    world = np.asarray(scene.points, dtype=float)[first : first + len(info.points)]
    local = (world - T[:3, 3]) @ T[:3, :3]
    index = {p: k for k, p in enumerate(info.points)}
    views: dict[str, list[tuple[int, np.ndarray]]] = {}
    for m in data:
        views.setdefault(m.config, []).append((index[m.refs["point"]], np.asarray(m.value)))
    objects, images = [], []
    for items in views.values():
        order = [k for k, _ in items]
        objects.append(local[order].astype(np.float32))
        images.append(np.array([uv for _, uv in items], dtype=np.float32))
    return objects, images


def trace_counts(fn) -> dict[str, int]:
    """How many times JAX traced, lowered and compiled while ``fn()`` ran."""
    from mbcal._jax import jax

    names = {
        "/jax/core/compile/jaxpr_trace_duration": "traces",
        "/jax/core/compile/jaxpr_to_mlir_module_duration": "lowerings",
        "/jax/core/compile/backend_compile_duration": "compiles",
    }
    counts = dict.fromkeys(names.values(), 0)

    def listener(event: str, duration: float, **_kw) -> None:
        if event in names:
            counts[names[event]] += 1

    jax.monitoring.register_event_duration_secs_listener(listener)
    try:
        fn()
    finally:
        jax.monitoring.unregister_event_duration_listener(listener)
    return counts


def bench_warm(views: int, repeats: int) -> dict:
    import cv2

    from mbcal.workflows.cameras import calibrate_cameras

    say(f"warm: {views} views")
    model, data = camera_data(views)
    objects, images = opencv_inputs(model, data)
    first = calibrate_cameras(model, data)  # trace and compile
    counts = trace_counts(lambda: calibrate_cameras(model, data))
    t_ours = best_of(lambda: calibrate_cameras(model, data), repeats)
    cc = calibrate_cameras(model, data)
    calibrate_cameras(model, data, restarts=4)  # the former default, beside it
    t_four = best_of(lambda: calibrate_cameras(model, data, restarts=4), repeats)
    out: dict = {}

    def opencv():
        out["cv"] = cv2.calibrateCamera(objects, images, (640, 480), None, None)

    t_cv = best_of(opencv, repeats)
    rms_cv, K, dist = out["cv"][:3]
    got = {k: v for k, (v, _) in cc.intrinsics["cam"].items()}
    return {
        "views": views,
        "points": len(data),
        "unknowns": cc.result.problem.params.size,
        "mbcal_s": t_ours,
        "chosen": cc.result.run.note,
        "four_s": t_four,
        "opencv_s": t_cv,
        "ratio": t_ours / t_cv,
        "solve_s": first.result.elapsed,
        **counts,
        "rms": cc.rms,
        "rms_opencv": float(rms_cv),
        "fx": got["fx"],
        "fx_opencv": float(K[0, 0]),
        "k1": got["k1"],
        "k1_opencv": float(np.ravel(dist)[0]),
    }


CHILD = """
import json, sys, time
t0 = time.perf_counter()
sys.path.insert(0, {root!r}); sys.path.insert(0, {bench!r})
from overhead import camera_data
from mbcal.workflows.cameras import calibrate_cameras
t1 = time.perf_counter()
model, data = camera_data({views})
t2 = time.perf_counter()
from overhead import trace_counts
box = {{}}
counts = trace_counts(lambda: box.setdefault("cc", calibrate_cameras(model, data)))
t3 = time.perf_counter()
calibrate_cameras(model, data)
t4 = time.perf_counter()
print(json.dumps({{"imports_s": t1 - t0, "data_s": t2 - t1, "first_s": t3 - t2, "warm_s": t4 - t3,
                  "rms": box["cc"].rms, **counts}}))
"""


def child(views: int, cache: Path) -> dict:
    env = {**os.environ, "MBCAL_CACHE_DIR": str(cache)}
    env.pop("MBCAL_CACHE", None)
    code = CHILD.format(root=str(ROOT), bench=str(ROOT / "bench"), views=views)
    proc = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, cwd=ROOT)
    if proc.returncode:
        raise RuntimeError(f"benchmark child failed:\n{proc.stderr}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def bench_cold(views: int) -> dict:
    say("cold: first and second process")
    with tempfile.TemporaryDirectory() as tmp:
        first = child(views, Path(tmp))
        second = child(views, Path(tmp))
    return {"first": first, "second": second}


def wall(argv: list[str], cache: Path, **extra: str) -> float:
    """Wall time of one run of the command line (a fresh process, as a user starts it)."""
    env = {**os.environ, "MBCAL_CACHE_DIR": str(cache), **extra}
    env.pop("MBCAL_CACHE", None)
    t0 = time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", "mbcal", *argv], env=env, capture_output=True, text=True, cwd=ROOT)
    elapsed = time.perf_counter() - t0
    if proc.returncode not in (0, 1):  # 1: a poor fit is still a finished run
        raise RuntimeError(f"mbcal {' '.join(argv)} failed ({proc.returncode}):\n{proc.stderr}")
    return elapsed


def bench_cli(views: int, demo: bool, repeats: int) -> dict:
    from mbcal.measurements.io import write_measurements

    say("command line")
    out: dict = {"no_bytecode_env": os.environ.get("PYTHONDONTWRITEBYTECODE", "")}
    # mbcal's modules as bytecode, as an installed package has them (pip compiles them; an editable
    # install writes them on its first import unless PYTHONDONTWRITEBYTECODE is set, as on the
    # machines this project is measured on: then every process compiled mbcal's ~60 modules from
    # source, ~0.1-0.2 s of each command).  __pycache__ is ignored by git.
    compiled = subprocess.run([sys.executable, "-m", "compileall", "-q", str(ROOT / "mbcal")], capture_output=True)
    out["bytecode"] = compiled.returncode == 0  # a read-only checkout: measured without it, and said so
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        cache = folder / "cache"
        _, data = camera_data(views)
        corners = folder / "corners.json"
        write_measurements(data, corners)
        argv = ["calibrate-camera", str(MODEL), str(corners), "--quiet"]
        out["calibrate_cold_s"] = wall(argv, cache)
        out["calibrate_warm_s"] = min(wall(argv, cache) for _ in range(repeats))
        # The same with one BLAS thread (NumPy's SVDs of the analysis beside XLA's threads).
        out["calibrate_warm_1blas_s"] = min(wall(argv, cache, OPENBLAS_NUM_THREADS="1") for _ in range(repeats))
        out["help_s"] = min(wall(["--help"], cache) for _ in range(repeats))
        out["check_s"] = min(wall(["check", str(MODEL)], cache) for _ in range(repeats))
        if demo:
            wall(["demo", "-o", str(folder / "demo")], cache)  # fills the caches
            out["demo_warm_s"] = wall(["demo", "-o", str(folder / "demo2")], cache)
    return out


def verdict(value: float, goal: float) -> str:
    return "met" if value <= goal else "**missed**"


def report(results: dict) -> str:
    import jax

    w, cold, cli = results["warm"], results["cold"], results["cli"]
    lines = [
        BEGIN,
        "## Fixed overhead: warm calls, cold start, the command line",
        "",
        "Written by `python bench/overhead.py` (do not edit by hand; run it again).  Every ratio is",
        "measured in the same run on the same machine; times are the best of several runs.",
        "",
        f"- machine: {cpu_name()}, {cores_and_system()}",
        f"- Python {sys.version.split()[0]}, JAX {jax.__version__}, NumPy {np.__version__}, "
        f"OpenCV {results.get('opencv', '?')}",
        f"- run on {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}",
        "",
        f"### Warm `calibrate_cameras`, {w['views']} views of a 9 × 6 board ({w['points']} corners, "
        f"{w['unknowns']} unknowns)",
        "",
        "| program | time (ms) | ratio to OpenCV (goal ≤ 1×) | JAX traces / compiles in the call |",
        "|---|--:|--:|--:|",
        f"| mbcal `calibrate_cameras` (restarts chosen — {w['chosen']}; analysis, fit verdict) | "
        f"{w['mbcal_s'] * 1e3:.1f} | {w['ratio']:.1f}× ({verdict(w['ratio'], GOALS['warm_ratio'])}) | "
        f"{w['traces']} / {w['compiles']} |",
        f"| mbcal `calibrate_cameras(restarts=4)` (the default until 2026-11-25) | {w['four_s'] * 1e3:.1f} | "
        f"{w['four_s'] / w['opencv_s']:.1f}× | — |",
        f"| `cv2.calibrateCamera` (k1, k2, p1, p2, k3) | {w['opencv_s'] * 1e3:.1f} | 1× | — |",
        "",
        f"Same estimates: RMS reprojection {w['rms']:.6f} px (OpenCV {w['rms_opencv']:.6f}), "
        f"fx {w['fx']:.4f} (OpenCV {w['fx_opencv']:.4f}), k1 {w['k1']:.6f} (OpenCV {w['k1_opencv']:.6f}).",
        "",
        "### Cold start (fresh processes, the same calibration)",
        "",
        "| process | imports (s) | simulate the data (s) | first `calibrate_cameras` (s, goal ≤ "
        f"{GOALS['first_s']:g} / ≤ {GOALS['second_s']:g}) | JAX traces / compiles in it | the next call (s) |",
        "|---|--:|--:|--:|--:|--:|",
    ]
    for label, key, goal in (
        ("first, empty cache", "first", GOALS["first_s"]),
        ("second, caches from the first", "second", GOALS["second_s"]),
    ):
        c = cold[key]
        lines.append(
            f"| {label} | {c['imports_s']:.2f} | {c['data_s']:.2f} | {c['first_s']:.2f} "
            f"({verdict(c['first_s'], goal)}) | {c['traces']} / {c['compiles']} | {c['warm_s']:.2f} |"
        )
    lines += [
        "",
        "### The command line (wall time of a fresh process)",
        "",
        (
            "mbcal's modules were compiled to bytecode first (`python -m compileall mbcal`), as an "
            "installed package has them"
            if cli.get("bytecode", True)
            else "mbcal's modules could not be compiled to bytecode here (`python -m compileall mbcal` "
            "failed: a read-only checkout?), so these rows include compiling them from source"
        )
        + (
            f"; this machine's environment sets `PYTHONDONTWRITEBYTECODE={cli['no_bytecode_env']}`, under "
            "which a checkout never writes them and every process compiles mbcal's ~60 modules from "
            "source (measured by hand: ~0.1–0.2 s of each command)."
            if cli.get("no_bytecode_env")
            else "."
        ),
        "",
        "| command | wall (s) | goal |",
        "|---|--:|--:|",
        f"| `mbcal --help` | {cli['help_s']:.2f} | — |",
        f"| `mbcal check models/camera_calibration.mdl` | {cli['check_s']:.2f} | — |",
        f"| `mbcal calibrate-camera` ({w['views']} views), empty cache | {cli['calibrate_cold_s']:.2f} | — |",
        f"| `mbcal calibrate-camera` ({w['views']} views), warm caches | {cli['calibrate_warm_s']:.2f} | "
        f"≤ {GOALS['cli_s']:g} s ({verdict(cli['calibrate_warm_s'], GOALS['cli_s'])}) |",
        f"| the same with `OPENBLAS_NUM_THREADS=1` | {cli['calibrate_warm_1blas_s']:.2f} | — |",
    ]
    if "demo_warm_s" in cli:
        lines.append(
            f"| `mbcal demo`, warm caches | {cli['demo_warm_s']:.2f} | ≤ {GOALS['demo_s']:g} s "
            f"({verdict(cli['demo_warm_s'], GOALS['demo_s'])}) |"
        )
    lines += ["", *PROFILE, END]
    return "\n".join(lines)


# What the profiles showed (cProfile of warm calls and of the command line; JAX's trace and compile
# events; CPU time of XLA's compile), before and after issue 16's changes.  Measured by hand on the
# 2-core machine while other work ran (load 6–9): read the ratios, not the absolute times.
PROFILE = [
    "### Profile before and after",
    "",
    "What dominated a warm `calibrate_cameras` (13 views) before: 590–760 ms, of which the solve",
    "was ~190–260 ms.  Every call built a new `Problem` and with it new jitted functions, so the",
    "residual table, the Jacobian, the visibility test, the point uncertainties and the frame",
    "origins were traced, lowered and compiled (from the compilation cache) again: 6 traces per",
    "call, ~0.35 s of tracing and ~0.17 s of lowering.  Without a cache folder the solver was",
    "traced again too.  In a second process (the command line) each of them was traced again,",
    "and every `jnp.asarray` of a NumPy array ran a small compiled program (one per new shape:",
    "~80 ms the first time, ~20 ms from the compilation cache; 34 of them in one",
    "`mbcal calibrate-camera`).  XLA's compile of the room's solver took 3.4 s of CPU, 1.7 s of it",
    "the solver's own loop (a trivial model), of which the unrolled Cholesky was half.",
    "",
    "What changed:",
    "",
    "- A problem's jitted functions are shared by every later problem of the same structure",
    "  (same fingerprint — model files and text, measurement structure and σ, unknowns, priors,",
    "  mbcal's code — and the same model and measurement-model objects) through a bounded LRU",
    "  (`mbcal.cache.PROGRAMS`, 8 structures): a warm call neither traces nor compiles (0 / 0",
    "  above; `tests/test_overhead.py` counts JAX's events).  The residual and Jacobian at the",
    "  solution come from one forward pass; h, the visibility flags and the frame origins from",
    "  one program.",
    "- The post-solve programs are exported to the cache folder like the solver (and the",
    "  structured solver of issue 15 now too), so a second process loads them instead of",
    "  tracing; arrays reach JAX by `jax.device_put` (`mbcal._jax.to_device`), which compiles",
    "  nothing.  `mbcal.fit` takes its χ² tails from `scipy.special` instead of importing",
    "  `scipy.stats` (0.35 s of every command's start-up).  User CPU of a warm",
    "  `mbcal calibrate-camera` on 13 views: 3.1 s → 1.8 s.",
    "- The dense solver's damped system is solved by LAPACK's Cholesky instead of the unrolled",
    "  one: the same speed for 6–7 unknowns × 64 restarts, and the solver's own compile",
    "  1.7 → 0.9 s of CPU (room's whole solver 3.4 → 2.9 s).",
    "- Memory maps: every compiled XLA:CPU program holds a few hundred (338 for the room's",
    "  solver).  After `tests/test_calibrate.py` in one process 19,532 maps were held (the limit",
    "  is 65,530; beyond it XLA:CPU crashes): 6,100 by the programs cache, 11,800 by the solvers'",
    "  compiled-code caches (64 dense + 32 structured entries).  The dense solver now keeps 8.",
    "- `mbcal demo` and `solve --overlay` drew their before/after images from scenes built by the",
    "  modeler op by op (~0.65 s each, 4 per demo): `Problem.whole_scenes` is one compiled,",
    "  exported program.",
    "- The command line runs NumPy with one BLAS thread unless `OPENBLAS_NUM_THREADS` is set:",
    "  on a busy machine OpenBLAS threads spinning beside XLA's made the analysis's two SVDs",
    "  (1,404 × 87) take 2.6 s instead of ~20 ms.  Library users' processes are not changed.",
    "- The process's own costs (profiled with `-X importtime`, cProfile of the whole `main`, JAX's",
    "  compile log, `perf`): Python's exit took ~0.15 s after every command (JAX's and XLA's",
    "  clean-up, a collection of every module, freeing each executable); the command line now",
    "  flushes its output and ends at once (`mbcal.cli.exit_now`; `MBCAL_FAST_EXIT=0`, a tracer",
    "  or a profiler get the ordinary exit).  `mbcal demo` rendered 12 OpenGL passes in 6 new",
    "  contexts (pyrender closes one with a full garbage collection, ~50 ms in a process holding",
    "  JAX's programs): one context now serves a set of pictures (`render.views.shared_context`;",
    "  not beyond it: closing any pyrender context ends the EGL display all of them share), and",
    "  only the passes used are drawn (the true images: colour; before/after over a photo:",
    "  depth), 6 in all.  The demo's true,",
    "  nominal and calibrated scenes come from the problem's compiled program instead of three",
    "  modeler runs op by op (18 small XLA compiles), and the overlays' legend finds its font",
    "  without importing matplotlib.  Measured under load 4–7 on the 2 cores, user + sys CPU of",
    "  a warm `mbcal calibrate-camera` (13 views) 1.39 → 1.21 s, of `mbcal demo` 4.8 → 2.9 s",
    "  (best wall 2.65 → 2.42 s and 7.4 → 4.3 s at that load).  Tried and left out: configuring",
    "  the compilation cache before the first small eager compile (the cache hits cost more than",
    "  the compiles), and saving the exported programs' executables with",
    "  `jax.experimental.serialize_executable` to skip their lowering (0.35 → 0.15 s of CPU for a",
    "  solver's load, but XLA:CPU's reloaded executable failed at run time: `Function",
    "  bitcast_gather_fusion.4 not found`).",
    "- The compiled model's residual and Jacobian (issues 15 and 16).  XLA:CPU fuses whatever a",
    "  point's value depends on into the kernel over all points (and all Jacobian columns), so",
    "  per-configuration work is recomputed for every point: the solver's rotation step about the",
    "  current orientation is now I + [δ]× (exact in value and first derivative at δ = 0, all the",
    "  Jacobian reads) instead of exp([δ]×) with its square root, sines and branches; image points",
    "  are projected on each camera's grid (configuration × point, intrinsics and distortion",
    "  broadcast, the pose of a camera fixed in the world applied as constants) and picked at the",
    "  end, instead of gathering the point, the camera's pose,",
    "  intrinsics and distortion with all their derivatives for every measurement; the points of",
    "  all frames that move together (one rigid object) are placed as one array operation.",
    "  Measured at load ~1 on the 2 cores (wall, before → after): the 15-column Jacobian at",
    "  13 / 500 / 2,000 views 0.87 → 0.16 ms, 19.8 → 4.6 ms, 97 → 18.5 ms (a hand-written JAX",
    "  version of the same residual at 500 views, in `jacfwd`: 5.8 ms), the residual at 500 views",
    "  0.78 → 0.30 ms (hand-written 0.35 ms); the structured solve at 13 / 500 / 2,000 views",
    "  10.9 → 5.8 ms, 254 → 104 ms, 1.32 → 0.43 s; a warm `calibrate_cameras` (13 views)",
    "  67 → 40 ms (these two with the other changes of the same round); the seed's arm, 64",
    "  restarts, r + J 2.0 → 1.3 ms and the solve 27 → 18 ms (the",
    "  room unchanged: 0.4 ms and 4.5 ms); the room's compiled solver 6,496 → 3,058 lines of",
    "  optimised HLO, its XLA compile 2.0 → 1.5 s.  Tried and dropped: the",
    "  points as a matrix product with the frame's rotation (forces the transform to be computed",
    "  once, but XLA then recomputed the kinematic chain once per matrix entry: the arm 2.5×",
    "  slower), the grid rotation written out by components (arm 2× slower), optimisation",
    "  barriers (XLA:CPU removes them).",
    "- The last round (warm `calibrate_cameras`, 13 views; CPU time beside wall time to see",
    "  through a load of 2–4 from other work): (1) restarts are chosen (`restarts=None`, the",
    "  default): Zhang's start alone, and 4 starts only when that fit does not converge or is",
    "  not consistent with the stated σ — each vmapped start cost ~9 ms, and a weak k2/k3",
    "  direction is no local minimum that random starts would cure (the table shows",
    "  `restarts=4` beside it); (2) the measurement set as arrays (`MeasurementSet.columns`, built",
    "  once per set): the problem, Zhang's start, the residual table, the RMS and the point",
    "  uncertainties read columns instead of walking 702 objects several times; (3) the points'",
    "  equal Jacobian patterns grouped by packed 64-bit words (`np.unique(axis=0)` took 7 ms for",
    "  702 rows of 87); (4) NumPy arrays handed straight to compiled programs (`jax.device_put`",
    "  cost ~30 µs each, 33 per call; a compiled call takes NumPy arguments for ~3 µs); (5) the",
    "  nominal frame poses computed once in Zhang's start (it ran the modeler 2–3 times);",
    "  (6) a block-structured problem's point uncertainties from each point's compressed",
    "  Jacobian (its view's 6 unknowns and the 9 intrinsics) and its block's joint covariance",
    "  instead of k × 3 × n (100 views: 79 MB and ~70 ms).  Wall 45 → ~17 ms at 13 views.",
    "  (7) XLA:CPU's MLIR fusion emitters took half of every compile: mbcal's programs are",
    "  compiled with the classic emitter (`mbcal._jax.jit`, options passed per program, never",
    "  `XLA_FLAGS`; `MBCAL_XLA_OPTIONS=off` turns it off): the first `calibrate_cameras`",
    "  3.6 → 2.1 s and `mbcal calibrate-camera` with an empty cache 6.4 → 4.0 s (load 2.5–4.5),",
    "  the structured solver ~4 % slower warm.",
    "- The round after (16.3 → ~10 ms wall for the warm call, quiet machine; timed by wrapping each",
    "  step): the solve was ~4.5 ms (14 iterations of ~0.29 ms and ~0.4 ms fixed), the rest ~11 ms",
    "  of NumPy and Python.  (1) Zhang's start alone starts Marquardt's damping at 10⁻⁶ of the",
    "  scaled diagonal instead of 10⁻³ (Madsen, Nielsen and Tingleff 2004, §3.2, for a start",
    "  believed close to the minimum): the weak distortion directions were held back for the first",
    "  iterations, 14 → 10 iterations here, 12 → 7 at 100 views, the same minimum.  (2) The residual",
    "  table and the point uncertainties are arrays, each row made when read (`ResidualRows`,",
    "  `PointUncertainties`: 702 objects each were ~1 ms), and the predicted values come from the",
    "  residual instead of running the model again.  (3) The point uncertainties are computed when",
    "  first read (`result.points`: by the report, its JSON, the studio; ~1.2 ms, which OpenCV does",
    "  not compute either).  (4) After a structured solve the m × n Jacobian is scattered from the",
    "  compressed one only when the fit is not consistent or candidates are ranked, and the fit",
    "  verdict builds its per-measurement row blocks only then.  (5) σ⟂ of a point from its 2 × 2",
    "  restriction in closed form (a batched 3 × 3 eigvalsh was 0.45 ms).  (6) Zhang's start reads",
    "  the model's nominal frame poses and target-plane points once per model (the modeler and a",
    "  point-by-point evaluation, ~1 ms), its groups by one packed integer key.  (7) `ParameterSet`",
    "  keeps its bounds, names and index arrays instead of rebuilding them on every access (read",
    "  ~10 times per call), and a problem's block structure is found once.",
    "- This round (the seed's problems; XLA's own per-kernel profile, `jax.profiler`): the",
    "  four costliest kernels of the room's loop were YNNPACK calls (`__ynn_fusion`) that jaxlib",
    "  0.10 makes of fused reductions — the rotation of 24 points written as a broadcast product",
    "  summed over an axis of 3, for 6 tangents of 64 restarts — and one materialised broadcast",
    "  feeding them.  mbcal's programs now keep reductions and elementwise work in XLA's own loops",
    "  and leave only single large matrix products to YNNPACK (`mbcal._jax.compiler_options`):",
    "  the room's 64 restarts 4.2 → 2.8 ms, the arm's 17.4 → 14.5 ms, the hand-written floor's",
    "  loop 3.6 → 2.2 ms (medians of 30 warm runs, side by side); with no YNNPACK at all the",
    "  dense solver's 100-view JᵀJ ran ~15 % slower, so large products keep it.  The camera",
    "  calibration (structured solver) and the first calls are unchanged within the noise.",
    "  Then the dense solver's loop carried the m × n weighted Jacobian and selected and copied it",
    "  every iteration (three kernels over 64 × 96 × 6 values, a third of the room's loop); it now",
    "  carries JᵀJ and Jᵀr, as the structured solver already did: the room 2.9 → 2.4 ms, the arm",
    "  13.7 → 12.7 ms.  Moving the products changed XLA's rounding and showed that the step rule",
    "  (take a step when S decreases) decided by the sign of a rounding error near the minimum; a",
    "  step whose predicted and computed changes are both within float64's resolution of S is now",
    "  taken and ends the restart as converged (a tight linear fit: 1e-10 → 1e-14 from the",
    "  solution).  The seed's table now reports medians of 20 warm runs after 0.3 s of untimed",
    "  runs (the notes' measure) instead of the best of 5, which caught the processor before it",
    "  had settled.  Tried without gain: binding `jax.lax` primitives directly instead of",
    "  `jax.numpy`'s operators while tracing the model (the arm's trace 0.64 → 0.68 s).",
    "- The stop after (the arm's first call, 1.07–1.12 s; XLA's per-module compile log): XLA's",
    "  tree-reduction rewrite made a reduce-window kernel of every sum over more than 32 terms",
    "  (Σr² over 168 residuals, the finiteness test of JᵀJ), each ~30 ms of LLVM's CPU; mbcal's",
    "  programs are now compiled without it (`mbcal._jax.compiler_options`): the arm's compile",
    "  0.64 → 0.56 s; the room's 0.54 → 0.51 s; and with one LLVM module per usable core instead",
    "  of XLA's 32 (a fixed cost each): 0.56 → 0.53 s and 0.53 → 0.50 s; the first",
    "  `calibrate_cameras` 2.1 → 2.0 s; warm solves, the structured solver at 30 and 1,000 views",
    "  and BAL unchanged (A/B).  What stays (bench/run.py's notes): ~0.23 s of the arm's trace",
    "  and lowering is once per process (JAX's first trace of its own `jax.numpy` operations;",
    "  jaxlib importing `scipy.linalg` for LAPACK, ~0.07 s), and over 40 % of the arm's warm iteration",
    "  is the kinematic chain recomputed for each coordinate of each point by XLA:CPU's classic",
    "  emitter.",
    "",
    "- This stop (AMD EPYC, 2 cores; wall times wander by up to 2× within minutes here): a quiet",
    "  command no longer computes the report it does not print (a calibration's summary reads",
    "  every point's σ: ~40 ms of `mbcal calibrate-camera --quiet`); the fit verdict takes its",
    "  weak directions from the observability analysis's SVD instead of a second 87 × 87",
    "  eigen-decomposition (~0.7 ms of the warm call); a model's mesh files are read with trimesh",
    "  once and then from the cache folder (`import trimesh` alone was ~0.6 s: a warm `mbcal solve`",
    "  of the seed's room 2.0 → 1.23 s; not in this table: the camera model has no mesh).  Tried",
    "  and dropped: drawing the demo's residual plot in a thread beside the rendering (no gain:",
    "  both hold the GIL most of the time).",
    "- The stop after (the same machine; `-X importtime`, cProfile of the whole command, `perf`",
    "  of the executable's load): jaxlib read LAPACK's function tables from SciPy's Cython modules",
    "  by importing `scipy.linalg` (~0.11 s) when the first exported program was lowered; the two",
    "  modules are now loaded from their files (`mbcal._jax.prepare_lapack`, ~0.02 s): a warm",
    "  `mbcal calibrate-camera` 1.18 → 1.03 s, the second process's first `calibrate_cameras`",
    "  0.32 → 0.26 s.  A model file's statements are kept in the cache folder (`syntax/`, JSON,",
    "  keyed by its text): Lark's import, tables and parse were ~0.05 s of every command (the",
    "  camera model 52 → 4 ms to load); the measurement file's records counted their line from",
    "  the start of the file (quadratic: 702 corners 46 → 20 ms).  `mbcal demo` parsed the model",
    "  again with Lark to relocate the calibrated model's paths (now through the same cache),",
    "  and its residual plot drew the figure twice (the placeholder layout engine that",
    "  `tight_layout` leaves makes `savefig` draw once more) with a patch per bar: 3.95–4.05 →",
    "  3.72–3.85 s, the pictures byte for byte the same.  XLA reads, compiles and runs a program",
    "  without holding Python's lock (a Python thread ran at 95 % of its speed beside a load): the",
    "  analysis's programs (the compressed Jacobian, the visibility) now load in a thread while",
    "  the solver's does, the first time a structure is analysed in a process",
    "  (`mbcal.api._load_analysis_programs`): a warm `mbcal calibrate-camera` 0.97–1.01 →",
    "  0.93–0.97 s, with an empty cache 4.16 → 3.85 s (alternating A/B runs).  Measured and left: the structured",
    "  solver's executable takes ~0.12–0.15 s to load from the compilation cache — XLA rebuilding",
    "  its 4,700-instruction HLO module (~45 % of the load) and linking its 50 object files; without",
    "  JAX's location metadata 10 % smaller and no faster, and neither one LLVM module nor 32",
    "  changed it.",
    "- This stop (the same machine; alternating A/B runs, `perf` of XLA's compile): the structured",
    "  solver inverted its 6 × 6 blocks with an unrolled Cholesky factorisation, a third of the",
    "  13-view program (5,732 → 3,742 HLO instructions after XLA's passes); up to 32 blocks they now",
    "  come from LAPACK's batched Cholesky (`mbcal.structured.LAPACK_BLOCKS`; beyond it the",
    "  unrolled one stays, LAPACK's loop over blocks being slower there: a warm 1,000-view",
    "  calibration ~10 % longer): the first `calibrate_cameras` of an empty cache 2.6–2.9 →",
    "  2.1–2.2 s, the second process's 0.22 → 0.17–0.19 s, a warm `mbcal calibrate-camera`",
    "  0.97–1.00 → 0.91–0.94 s (its executable loads faster), warm calls unchanged.  Python's",
    "  garbage collector walked every object of the process (~200,000 with JAX imported) now and",
    "  then, set off by the allocations of tracing, of reading the corners and of loading the",
    "  programs: it is paused while mbcal's programs trace and compile, and the `mbcal` command",
    "  runs without collections from its start to its first program, then freezes what start-up",
    "  built (`mbcal._collector`; a library caller's process is never frozen): a warm",
    "  `mbcal calibrate-camera` 0.86–0.94 → 0.81–0.90 s (A/B), the seed room's trace + lower",
    "  0.57 → 0.48 s (bench/run.py).  The warm call with the collector off: no change (it",
    "  allocates little).",
    "- The stop of 2026-11-25 (08:00–10:00 UTC) made the warm call ~2 ms longer (A/B against",
    "  565f706, alternating processes: 15.0–16.2 → 17.8 ms medians) for two checks a wrong fit",
    "  needed: the fit verdict's test for systematic residuals (`mbcal.fit.systematic_residuals`,",
    "  each corner's 4 nearest in its view: ~1.1 ms, distances, a partition and dense pair sums",
    "  over 13 × 54 × 54) and Zhang's start leaving out views whose corners lie on a line (~0.5 ms,",
    "  a 2 × 2 eigenvalue problem per view): the warm call now sits at the goal's limit — 1.2×,",
    "  1.1×, 0.9× and 1.0× over OpenCV in four runs of this page within an hour (the table is the",
    "  last: the machine's speed wanders more than the change).",
    "- The stop of 2026-11-25 (10:15–13:00 UTC) added to the fit verdict (other solutions as good,",
    "  unknowns held at a limit, untested measurements, 3-D systematic residuals); none runs for",
    "  Zhang's start alone on full views (one restart; no configuration with few corners), and an",
    "  A/B of the stop's first and last commits (alternating processes, 6 runs each) gave the same",
    "  times within the noise (medians ~18 ms both, on a machine ~15 % slower than in the morning:",
    "  OpenCV 15–18 ms).  Three runs of this page at its end: 1.1×, 1.0× (1.02) and the table's.",
    "- The stop of 2026-11-25 (13:15–16:15 UTC): the fit verdict's rows of each measurement as",
    "  arrays (`Problem.row_blocks`: start and size) instead of a NumPy range per measurement (702",
    "  `arange` calls and their stacking, ~0.5 ms), the untested-measurement selection on them",
    "  (0.43 → 0.07 ms) and the systematic-residual test summing over the neighbour pairs only",
    "  (1.05 → 0.81 ms, alone).  A/B against c635d45 (alternating processes, 5 each, best of 20",
    "  calls): medians 15.4 → 14.7 ms beside OpenCV's 13.2–14.0 ms — ratio 1.10× (0.99–1.23):",
    "  the goal still missed.  Tried and dropped: the analysis without the SVD's vectors (the",
    "  covariance as R⁻¹R⁻ᵀ, 0.35 ms instead of ~1 ms): this problem has a weakly observable",
    "  direction (k3 with k2), whose vector the report names, so the vectors are needed anyway;",
    "  one BLAS thread (`OPENBLAS_NUM_THREADS=1`) for the library's call: no difference in the",
    "  best times.  Added: the check that the estimate keeps the model valid (a focal length > 0;",
    "  signs only, ~10 µs).",
    "",
    "What remains (measured this stop, by hand):",
    "",
    "- The warm call, ~16–18 ms when called back to back: the structured solve is ~3.7 ms run",
    "  alone back to back but ~6 ms inside the call — the same program after ~10 ms of Python",
    "  work (a 10 ms sleep before it: 3.6 → 6.1 ms, with XLA on one thread too: the processor's",
    "  caches and clocks, not XLA's threads); ~10 ms of NumPy and Python around it: the problem",
    "  and its two `ParameterSet`s (~3 ms), Zhang's start (~2 ms), the analysis's SVD of the",
    "  87 × 87 square-root information (~1.8 ms inside the call, 0.9 ms alone), the compressed",
    "  Jacobian at the solution (~0.75 ms of XLA), the fit verdict (~0.5 ms).",
    "- A warm `mbcal calibrate-camera`, 0.81–0.90 s by hand this stop (0.92–1.10 s at the last,",
    "  on a machine whose speed wanders by 10–20 %): imports ~0.5 s (JAX alone ~0.45 s, NumPy",
    "  0.08 s), the solver's program: its first lowering in the process (~0.06 s, of which JAX's",
    "  import of its MLIR dialects' Python classes is most) and its executable read from the",
    "  compilation cache (~0.12 s, was ~0.16 s with the unrolled block inverses), the model and",
    "  the 702 corners (~0.03 s), the calibration's own work (~0.03 s).",
    "- `mbcal demo`, 3.7–3.9 s warm here: ~1.9 s of imports (JAX, trimesh — pyrender imports",
    "  it, and it imports `scipy.spatial` —, pyrender, matplotlib), five executables from the",
    "  cache (~0.25 s), rendering and overlays ~1.3 s, the residual plot ~0.2 s.",
    "- The seed's problems (`bench/run.py`): the arm's warm solve is bound by XLA:CPU's classic",
    "  emitter recomputing the kinematic chain for every coordinate of the hand points.  XLA's",
    "  newer fusion emitters avoid that (measured again this stop, fresh processes: arm",
    "  18.6–23.7 → 9.4–11.2 ms warm, first call +0.5–0.7 s; the room 2.5–3.3 → 4.0–4.5 ms,",
    "  slower): a tiered compile — the classic program first, the other compiled in the",
    "  background and kept where it runs faster — would take the arm's gain without the first",
    "  call's cost; not built: which program answers a call would depend on timing, and the two",
    "  round differently (bench/run.py's notes).",
]


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--views", type=int, default=13)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--no-demo", action="store_true", help="skip `mbcal demo` (slow)")
    parser.add_argument("--out", type=Path, default=ROOT / "docs" / "performance.md")
    args = parser.parse_args(argv)
    import cv2

    results = {
        "opencv": cv2.__version__,
        "warm": bench_warm(args.views, args.repeats),
        "cold": bench_cold(args.views),
        "cli": bench_cli(args.views, not args.no_demo, max(1, args.repeats // 2)),
    }
    text = report(results)
    replace_section(args.out, text, BEGIN, END)
    print(json.dumps(results, indent=1))
    say(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
