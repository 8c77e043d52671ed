"""Fixed overhead (issue 16): a warm call neither traces nor compiles; start-up imports only what
a command needs."""

from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import subprocess
import sys
from typing import Any

import numpy as np
import pytest

import mbcal
from mbcal._jax import jax
from mbcal.cache import PROGRAMS, ProgramCache
from mbcal.problem import Problem
from mbcal.workflows.cameras import calibrate_cameras, simulate_views

from conftest import MODELS, ROOT

TRACE = "/jax/core/compile/jaxpr_trace_duration"
LOWER = "/jax/core/compile/jaxpr_to_mlir_module_duration"
COMPILE = "/jax/core/compile/backend_compile_duration"


@contextlib.contextmanager
def jax_events():
    """Count JAX's tracing, lowering and compiling events while the block runs."""
    counts = {TRACE: 0, LOWER: 0, COMPILE: 0}

    def listener(event: str, duration: float, **_kw) -> None:
        if event in counts:
            counts[event] += 1

    jax.monitoring.register_event_duration_secs_listener(listener)
    try:
        yield counts
    finally:
        jax.monitoring.unregister_event_duration_listener(listener)


def camera_data(model: mbcal.Model, views: int, seed: int) -> mbcal.MeasurementSet:
    """Simulated corners of the bundled 9 × 6 board in ``views`` random poses."""
    truth = {"cam.fx": 812.0, "cam.fy": 806.5, "cam.cx": 327.0, "cam.cy": 236.0, "cam.k1": -0.21, "cam.k2": 0.08}
    return simulate_views(model, views, truth, seed=seed, distance=(0.45, 0.7))[0]


@pytest.fixture(scope="module")
def camera():
    return mbcal.load_model(MODELS / "camera_calibration.mdl")


@pytest.mark.slow
def test_a_warm_calibration_neither_traces_nor_compiles_and_gives_the_same_numbers(camera):
    data = camera_data(camera, 4, seed=3)
    first = calibrate_cameras(camera, data)
    again = camera_data(camera, 4, seed=3)  # a new set of the same structure, as a second file would be
    with jax_events() as counts:
        second = calibrate_cameras(camera, again)
    assert counts == {TRACE: 0, LOWER: 0, COMPILE: 0}
    np.testing.assert_array_equal(second.result.x, first.result.x)
    np.testing.assert_array_equal(second.result.observability.covariance, first.result.observability.covariance)
    assert second.rms == first.rms and second.views == first.views
    assert [p.perpendicular for p in second.result.points] == [p.perpendicular for p in first.result.points]
    # Other measured values (the same structure): still no tracing, and a different answer.
    other = camera_data(camera, 4, seed=4)
    with jax_events() as counts:
        third = calibrate_cameras(camera, other)
    assert counts[TRACE] == 0
    assert not np.array_equal(third.result.x, first.result.x)


def test_residual_and_jacobian_from_one_pass_match_the_separate_programs(camera):
    data = camera_data(camera, 2, seed=5)
    problem = Problem(camera, data, ["cam.fx", "cam.fy", "cam.cx", "cam.cy", "board.*"])
    x = problem.params.x0 + 0.01
    r, J = problem.residual_and_jacobian(x)
    np.testing.assert_allclose(r, problem.residual(x), rtol=1e-13, atol=1e-12)
    np.testing.assert_allclose(J, problem.jacobian(x), rtol=1e-13, atol=1e-12)
    # The Jacobian against central finite differences in every unknown.
    h = 1e-6
    for j in range(problem.params.size):
        step = np.zeros_like(x)
        step[j] = h
        fd = (problem.residual(x + step) - problem.residual(x - step)) / (2 * h)
        np.testing.assert_allclose(J[:, j], fd, rtol=1e-5, atol=1e-5 * np.abs(J).max())


def test_problems_of_one_structure_share_their_programs_and_others_do_not(camera):
    data = camera_data(camera, 2, seed=6)
    a = Problem(camera, data, ["cam.fx", "board.*"])
    b = Problem(camera, camera_data(camera, 2, seed=7), ["cam.fx", "board.*"])
    assert b.residual_function is a.residual_function and b.local is a.local
    c = Problem(camera, data, ["cam.fy", "board.*"])  # other unknowns
    assert c.residual_function is not a.residual_function
    reloaded = mbcal.load_model(MODELS / "camera_calibration.mdl")  # an equal model, another object
    d = Problem(reloaded, camera_data(reloaded, 2, seed=6), ["cam.fx", "board.*"])
    assert d.residual_function is not a.residual_function
    # Each problem still sees its own measured values.
    x = a.params.x0
    assert not np.allclose(a.residual(x), b.residual(x))


def test_the_program_cache_is_bounded_and_drops_the_least_recently_used():
    cache = ProgramCache(3)
    built = []
    for key in ("a", "b", "c", "a", "d", "e"):
        cache.get(key, lambda key=key: built.append(key) or key.upper())
    assert built == ["a", "b", "c", "d", "e"]  # "a" was used again before it could be dropped
    assert len(cache) == 3
    assert cache.get("a", lambda: "new") == "A" and cache.get("b", lambda: "rebuilt") == "rebuilt"
    assert PROGRAMS.size <= 16


def run_python(code: str, **env: str) -> Any:
    return run_python_argv(code, **env)


def run_python_argv(code: str, *argv: str, **env: str) -> Any:
    """The JSON that ``code`` prints last, run in a fresh Python with ``argv`` and ``env``."""
    full = {**os.environ, **env}
    proc = subprocess.run([sys.executable, "-c", code, *argv], capture_output=True, text=True, cwd=ROOT, env=full)
    assert proc.returncode == 0, proc.stderr
    return json.loads(proc.stdout.strip().splitlines()[-1])


HEAVY = ("matplotlib", "pyrender", "trimesh", "cv2", "scipy", "OpenGL", "PIL")


def test_import_mbcal_loads_no_heavy_library():
    loaded = run_python(
        "import json, sys; import mbcal; print(json.dumps(sorted(m for m in sys.modules if '.' not in m)))"
    )
    assert not [m for m in HEAVY if m in loaded], loaded


def test_the_calibration_path_does_not_import_scipy_stats_or_plotting():
    # scipy.stats alone took 0.35 s of every solving command's start-up, scipy.special ~0.2 s and
    # scipy.ndimage ~0.1 s (the χ² tail of a consistent fit is computed in plain Python; arrays of
    # them, and image resampling, import those when needed); plotting and rendering load only
    # where a command draws.
    loaded = run_python(
        "import json, sys; import mbcal.api, mbcal.workflows.cameras, mbcal.cli; print(json.dumps(sorted(sys.modules)))"
    )
    late = ("scipy.stats", "scipy.special", "scipy.ndimage")
    assert not [m for m in loaded if m in late or m.split(".")[0] in ("matplotlib", "pyrender", "cv2")]


LAPACK_RUN = """
import json, sys
import numpy as np
import mbcal._jax as mj
from mbcal.workflows.cameras import calibrate_cameras, simulate_views
from mbcal.language import load_model
before = 'scipy.linalg' in sys.modules
model = load_model(sys.argv[1])
truth = {"cam.fx": 812.0, "cam.fy": 806.5, "cam.cx": 327.0, "cam.cy": 236.0, "cam.k1": -0.21, "cam.k2": 0.08}
data = simulate_views(model, 4, truth, seed=2, distance=(0.45, 0.7))[0]
cc = calibrate_cameras(model, data)
during = 'scipy.linalg' in sys.modules
import scipy.linalg
capi = sorted(scipy.linalg.cython_lapack.__pyx_capi__)[:1]
chol = float(scipy.linalg.cholesky(np.eye(2) * 4.0)[0, 0])
print(json.dumps([before, during, mj.prepare_lapack(), capi, chol, list(cc.result.values.values())]))
"""


@pytest.mark.parametrize("cached", [False, True])
def test_jaxlib_gets_lapack_without_importing_scipy_linalg(tmp_path, cached):
    # jaxlib imported scipy.linalg (~0.11 s of every command) only for two Cython modules' tables:
    # the Cholesky steps of a traced solver and every exported program's lowering need them.
    model = str(MODELS / "camera_calibration.mdl")
    cache = {"MBCAL_CACHE_DIR": str(tmp_path / "cache")} if cached else {"MBCAL_CACHE": "off"}
    runs = [run_python_argv(LAPACK_RUN, model, **cache) for _ in range(2 if cached else 1)]
    for before, during, prepared, capi, chol, _ in runs:
        assert (before, during, prepared) == (False, False, True)
        assert capi and chol == 2.0  # the ordinary scipy.linalg afterwards, its Cython tables too
    if cached:  # the second process called the exported programs instead of tracing
        assert list(tmp_path.joinpath("cache", "exports").iterdir())
        np.testing.assert_allclose(runs[0][-1], runs[1][-1], rtol=1e-9)


def test_with_scipy_linalg_already_imported_jaxlib_is_left_to_import_it_itself():
    out = run_python(
        "import json, scipy.linalg, mbcal._jax as mj, jax.numpy as jnp; "
        "print(json.dumps([mj.prepare_lapack(), float(mj.jit(jnp.linalg.cholesky)(jnp.eye(2) * 9.0)[0, 0])]))"
    )
    assert out == [False, 3.0]


def test_a_quiet_command_does_not_compute_the_report_it_does_not_show(camera, tmp_path, monkeypatch, capsys):
    # A calibration's summary reads every point's σ (~40 ms of a 13-view `calibrate-camera`):
    # --quiet shows nothing, so nothing of it is computed; without --quiet it is shown.
    from mbcal.cli import main
    from mbcal.measurements.io import write_measurements
    from mbcal.workflows.cameras import CameraCalibration

    corners = tmp_path / "corners.json"
    write_measurements(camera_data(camera, 3, seed=5), corners)
    argv = ["calibrate-camera", str(MODELS / "camera_calibration.mdl"), str(corners), "--accept-poor-fit"]
    assert main(argv) == 0 and "reprojection" in capsys.readouterr().out.lower()

    def refuse(self):
        raise AssertionError("the summary was computed under --quiet")

    monkeypatch.setattr(CameraCalibration, "summary", refuse)
    assert main([*argv, "--quiet"]) == 0
    assert capsys.readouterr().out == ""


def test_one_chi2_tail_in_plain_python_equals_scipys():
    from scipy import special

    from mbcal.fit import stats

    worst = 0.0
    for df in (1, 2, 5, 9, 10, 11, 30, 87, 1317, 10_000, 216_000, 1_000_000):
        for z in np.linspace(-8.0, 40.0, 97):
            for x in np.array([1.0, 0.5, 2.0, 0.01, 10.0]) * (df + z * np.sqrt(2.0 * df)):
                if x < 0:
                    continue
                expected = special.chdtrc(df, x)
                got = stats.chi2.sf(float(x), df)
                assert isinstance(got, float)
                if expected > 1e-290:
                    worst = max(worst, abs(got - expected) / expected)
                else:
                    assert got < 1e-280
    assert worst < 1e-10
    assert stats.chi2.sf(0.0, 4) == stats.chi2.sf(-3.0, 4) == 1.0
    assert np.isnan(stats.chi2.sf(float("nan"), 5)) and stats.chi2.sf(float("inf"), 5) == 0.0
    for df in (20, 90, 1317, 216_000):  # an exact fit: S far below the degrees of freedom
        for x in (1e-300, 1e-20, 1e-3):
            assert stats.chi2.sf(x, df) == pytest.approx(special.chdtrc(df, x), rel=1e-12)
    # arrays of tails are scipy's own
    np.testing.assert_array_equal(stats.chi2.sf(np.array([1.0, 50.0]), 3), special.chdtrc(3, [1.0, 50.0]))


@pytest.mark.parametrize("argv", [["--help"], ["check", "models/camera_calibration.mdl"], ["cache"]])
def test_the_cli_starts_without_heavy_libraries(argv):
    code = (
        "import json, sys\n"
        "from mbcal.cli import main\n"
        "try:\n"
        f"    code = main({argv!r})\n"
        "except SystemExit as e:\n"
        "    code = e.code\n"
        "print()\n"
        "print(json.dumps({'code': code, 'loaded': sorted(m for m in sys.modules if '.' not in m)}))\n"
    )
    out = run_python(code)
    assert out["code"] in (0, None)
    assert not [m for m in HEAVY + ("jax",) if m in out["loaded"]], out["loaded"]


@pytest.mark.slow
def test_the_overhead_bench_runs_on_a_tiny_size_and_writes_its_section(tmp_path):
    out = tmp_path / "performance.md"
    out.write_text("# Performance\n\nkept\n")
    proc = subprocess.run(
        [sys.executable, "bench/overhead.py", "--views", "3", "--repeats", "1", "--no-demo", "--out", str(out)],
        capture_output=True,
        text=True,
        cwd=ROOT,
        env={**os.environ, "MBCAL_CACHE_DIR": str(tmp_path / "cache")},
    )
    assert proc.returncode == 0, proc.stderr
    text = out.read_text()
    assert text.startswith("# Performance\n\nkept\n")
    assert "<!-- bench/overhead.py: begin -->" in text and "<!-- bench/overhead.py: end -->" in text
    # The warm call neither traced nor compiled, and mbcal agrees with OpenCV on the same corners.
    assert "| 0 / 0 |" in text
    results = json.loads(proc.stdout)
    assert abs(results["warm"]["rms"] - results["warm"]["rms_opencv"]) < 1e-3
    # The second process takes the traced programs from the cache the first one wrote.
    assert results["cold"]["second"]["traces"] < results["cold"]["first"]["traces"]


def test_whole_scenes_from_the_compiled_program_match_the_modeler_run_op_by_op(camera):
    data = camera_data(camera, 2, seed=8)
    problem = Problem(camera, data, ["cam.fx", "board.*"])
    x = problem.params.x0 + 0.02
    compiled = problem.whole_scenes(x)
    from mbcal.modeling import Needs

    eager = problem.scenes(jax.numpy.asarray(x), needs=Needs.everything())
    for name in ("frame_poses", "points", "camera_intrinsics", "camera_distortion", "shape_poses", "shape_dims"):
        np.testing.assert_allclose(getattr(compiled, name), np.asarray(getattr(eager, name)), rtol=1e-13, atol=1e-13)
    np.testing.assert_allclose(problem.frame_origins(x), compiled.frame_poses[..., :3, 3], rtol=1e-13, atol=1e-13)


# ---- the compiled model's residual and Jacobian (issues 15 and 16) ------------------------------


def _image_point_predictions(problem: Problem, x: np.ndarray):
    """h of the problem's image points and ∂h/∂x, straight from the measurement model."""
    from mbcal._jax import jnp

    (group,) = [g for g in problem.groups if g.model.kind == "image_point"]
    known = jnp.asarray(problem.params.known)

    def h(xx):
        return group.model.predict(problem.scenes(xx, known), group.batch)

    both = jax.jit(jax.jacfwd(lambda xx: (lambda v: (v, v))(h(xx)), has_aux=True))
    J, value = both(jnp.asarray(x))
    return np.asarray(value), np.asarray(J)


@pytest.mark.parametrize("case", ["camera", pytest.param("stereo", marks=pytest.mark.slow)])
def test_image_points_on_the_grid_match_them_one_by_one(camera, monkeypatch, case):
    import dataclasses

    from mbcal.measurements import builtin

    if case == "camera":  # some corners left out, the measurements shuffled
        data = camera_data(camera, 3, seed=11)
        model, estimate = camera, ["cam.*", "board.*"]
    else:  # two cameras, their measurements interleaved
        model = mbcal.load_model(MODELS / "teleexistence.mdl")
        plan = mbcal.read_measurements(ROOT / "measurements" / "room_plan.csv", model)
        data = mbcal.simulate(model, plan, {"room.x": 0.05, "room.yaw": 0.1}, noise=0.5, seed=2)
        estimate = ["room.*"]
    order = np.random.default_rng(0).permutation(len(data.measurements))
    if case == "camera":
        order = np.delete(order, np.arange(0, len(order), 7))  # some corners unseen
    data = dataclasses.replace(data, measurements=[data.measurements[i] for i in order])
    problem = Problem(model, data, estimate)
    x = problem.params.x0 + 0.01
    batch = problem.groups[0].batch
    seen = {}
    for fill in (0.0, 2.0):  # always on the grid, never
        monkeypatch.setattr(builtin, "GRID_MIN_FILL", fill)
        scenes = jax.eval_shape(problem.scenes, jax.numpy.asarray(x))
        assert (builtin._grids(scenes, batch) is None) == (fill > 1)
        seen[fill] = _image_point_predictions(problem, x)
    np.testing.assert_allclose(seen[0.0][0], seen[2.0][0], rtol=1e-13, atol=1e-9)
    np.testing.assert_allclose(seen[0.0][1], seen[2.0][1], rtol=1e-12, atol=1e-9 * np.abs(seen[2.0][1]).max())
    if case == "camera":
        assert len(batch) < 3 * 54  # the grid path gathered a partly filled grid


def test_the_local_jacobian_of_many_views_matches_finite_differences_of_the_step(camera):
    """The solver's Jacobian in local coordinates (the rotation step to first order,
    :func:`mbcal.language.soa_math.rotation_step`) against central differences through the exact
    step x ⊞ d (:meth:`mbcal.problem.OrientationSteps.plus`)."""
    from mbcal._jax import jnp

    data = camera_data(camera, 3, seed=12)
    problem = Problem(camera, data, ["cam.*", "board.*"])
    local = problem.local
    assert local is not None and len(problem.orientation_names) == 3
    x = problem.params.x0.copy()
    x[[problem.params.names.index(f"board.{a}@{c}") for a in ("roll", "pitch", "yaw") for c in ("view01",)]] = 0.3
    y, known = jnp.asarray(problem.y), jnp.asarray(problem.params.known)
    n = problem.params.size
    r = np.asarray(local.residual(jnp.asarray(x), jnp.zeros(n), y, known))
    J = np.asarray(jax.jacfwd(lambda d: local.residual(jnp.asarray(x), d, y, known))(jnp.zeros(n)))
    np.testing.assert_allclose(r, problem.residual(x), rtol=1e-12, atol=1e-9)
    plus = jax.jit(local.plus)
    h = 1e-6
    for j in range(n):
        e = np.zeros(n)
        e[j] = h
        fd = (problem.residual(np.asarray(plus(x, e))) - problem.residual(np.asarray(plus(x, -e)))) / (2 * h)
        np.testing.assert_allclose(J[:, j], fd, rtol=1e-5, atol=1e-6 * np.abs(J).max())


def test_plots_leave_the_callers_matplotlib_backend_and_pyplot_alone(camera, tmp_path):
    # A library that plots must not switch its caller's backend (a notebook's inline one) nor
    # leave figures open in pyplot: the figures are made without pyplot and drawn by Agg.
    import matplotlib
    from PIL import Image

    from mbcal.range.manager import Update
    from mbcal.range.pictures import plot_history
    from mbcal.render.overlays import residual_plot

    cc = calibrate_cameras(camera, camera_data(camera, 3, seed=5))
    history = [
        Update(k, float(k), {"a.x": 0.01 * k}, {"a.x": 0.002}, 1.0, 1.0, 10, 0, True, drift=["a.x"] if k == 2 else [])
        for k in range(4)
    ]
    before = matplotlib.get_backend()
    matplotlib.use("svg")
    try:
        residual_plot(cc.result, tmp_path / "residuals.png")
        plot_history(history, ["a.x"], tmp_path / "history.png", units={"a.x": "m"})
        assert matplotlib.get_backend() == "svg"
    finally:
        matplotlib.use(before)
    for name in ("residuals.png", "history.png"):
        with Image.open(tmp_path / name) as img:
            assert img.format == "PNG" and img.size[0] > 500
    if "matplotlib.pyplot" in sys.modules:  # imported by another test of this process: none left open
        assert sys.modules["matplotlib.pyplot"].get_fignums() == []


def test_the_residual_bars_are_red_above_the_outlier_threshold_and_blue_below(camera, tmp_path):
    # The bars are drawn as two filled step outlines (one patch per measurement took ~0.6 s for
    # 702 corners): the worst first, red exactly for the measurements above the threshold.
    from PIL import Image

    from mbcal.render.overlays import residual_plot

    data = camera_data(camera, 3, seed=5)
    cc = calibrate_cameras(camera, data)

    def bar_colours(result, name):
        residual_plot(result, tmp_path / name)
        with Image.open(tmp_path / name) as img:
            left = np.asarray(img.convert("RGB"))[:, : img.size[0] // 2].reshape(-1, 3).astype(int)
        red = np.all(np.abs(left - [0xD6, 0x27, 0x28]) <= 2, axis=1).sum()
        blue = np.all(np.abs(left - [0x1F, 0x77, 0xB4]) <= 2, axis=1).sum()
        return red, blue

    assert max(r.normalized for r in cc.result.residuals) < cc.result.outlier_threshold
    red, blue = bar_colours(cc.result, "clean.png")
    assert blue > 5000 and red < 300  # the threshold's dashed line and its legend are the only red
    measurements = list(data.measurements)
    m = measurements[7]
    moved = dataclasses.replace(m, value=np.asarray(m.value) + [40.0, -40.0])
    measurements[7] = moved
    spoilt = calibrate_cameras(camera, dataclasses.replace(data, measurements=measurements))
    assert sum(r.normalized > spoilt.result.outlier_threshold for r in spoilt.result.residuals) >= 1
    red_out, blue_out = bar_colours(spoilt.result, "outlier.png")
    assert red_out > red + 500 and blue_out > 500  # the outlier stretches the axis: shorter blue bars


def test_the_analysis_programs_load_beside_the_solve_once_per_structure(camera, monkeypatch):
    # XLA reads and compiles programs without Python's lock: the analysis's programs (compressed J,
    # visibility) load in a thread while the solver's does (issue 16), the first time a structure
    # is analysed in the process only, and the thread is done when calibrate returns.
    import threading
    import time

    from mbcal import api

    started, loading = [], []
    load = api._load_analysis_programs
    real = api.compressed_jacobian

    def recording(*a, **kw):
        started.append(load(*a, **kw))
        return started[-1]

    def who_loads(*a, **kw):
        loading.append(threading.current_thread().name)
        if loading[-1] == "mbcal-analysis-programs":
            time.sleep(0.5)  # slower than the solve: calibrate must wait for it
        return real(*a, **kw)

    monkeypatch.setattr(api, "_load_analysis_programs", recording)
    monkeypatch.setattr(api, "compressed_jacobian", who_loads)
    data = camera_data(camera, 11, seed=21)  # a structure no other test analyses
    with jax_events() as events:
        first = calibrate_cameras(camera, data)
    assert isinstance(started[0], threading.Thread) and not started[0].is_alive()  # joined
    assert "mbcal-analysis-programs" in loading and events[COMPILE] > 0
    started.clear()
    again = calibrate_cameras(camera, data)
    assert started and all(isinstance(s, api._Nothing) for s in started)  # loaded already: none started
    assert not [t for t in threading.enumerate() if t.name == "mbcal-analysis-programs"]
    np.testing.assert_array_equal(first.result.x, again.result.x)
    np.testing.assert_array_equal(first.result.residuals.normalized, again.result.residuals.normalized)

    # An error in the thread is the analysis's to report: here only the thread's call fails.
    def failing_in_the_thread(*a, **kw):
        if threading.current_thread().name == "mbcal-analysis-programs":
            raise RuntimeError("not here")
        return real(*a, **kw)

    monkeypatch.setattr(api, "compressed_jacobian", failing_in_the_thread)
    started.clear()
    other = calibrate_cameras(camera, camera_data(camera, 12, seed=22))
    assert isinstance(started[0], threading.Thread) and other.result.rms["image_point"] < 1.0

    # A failed solve joins it too: nothing runs on after the call.
    def failing_solve(*a, **kw):
        raise api.SolverError("the solver failed")

    monkeypatch.setattr(api, "least_squares_structured", failing_solve)
    started.clear()
    with pytest.raises(api.SolverError):
        calibrate_cameras(camera, camera_data(camera, 15, seed=24))
    assert isinstance(started[0], threading.Thread) and not started[0].is_alive()
    monkeypatch.undo()

    monkeypatch.setattr(api, "_load_analysis_programs", recording)
    monkeypatch.setattr(api, "_LOAD_BESIDE_VALUES", 10)  # too large to load beside the solve
    started.clear()
    calibrate_cameras(camera, camera_data(camera, 14, seed=23))
    assert started and isinstance(started[0], api._Nothing)
    monkeypatch.setattr(api, "_LOAD_BESIDE_VALUES", 4_000_000)
    started.clear()
    with jax.default_device(jax.devices("cpu")[0]):  # a setting the thread would not inherit
        calibrate_cameras(camera, camera_data(camera, 16, seed=25))
    assert started and isinstance(started[0], api._Nothing)


def _room_problem(known=None):
    model = mbcal.load_model(MODELS / "teleexistence.mdl")
    plan = mbcal.read_measurements(ROOT / "measurements" / "room_plan.csv", model)
    data = mbcal.simulate(model, plan, {"room.x": 0.02, "room.yaw": 0.01}, noise=0.0)
    return model, data, Problem(model, data, ["room.*"], known=known)


def test_the_models_own_values_are_constants_of_the_program_and_given_values_are_inputs():
    """Known values that only the model gives (its design data) fold into the traced residual:
    the room's 410 operations became 132 (issue 16: trace and compile).  A value given by the
    caller, a file or --set stays an input: the same model with another lever length has another
    fingerprint and other programs, and its residual uses the value given, not the model's."""
    model, data, plain = _room_problem()
    constants = plain.params.model_constants
    names = [p.name for p in model.params]
    assert constants[names.index("lever.length")] and not constants[names.index("room.x")]
    x = plain.params.x0 + 0.001
    jaxpr = jax.make_jaxpr(lambda z: plain.residual_function(z, plain.y, plain.params.known))(x)
    assert len(jaxpr.jaxpr.eqns) < 200, len(jaxpr.jaxpr.eqns)  # 410 with every known value an input

    _, _, longer = _room_problem(known={"lever.length": 0.30})
    assert not longer.params.model_constants[names.index("lever.length")]
    assert longer.fingerprint() != plain.fingerprint()
    assert longer._programs is not plain._programs
    # each residual against the one computed op by op with every value an input (no folding)
    for problem in (plain, longer):
        scenes = jax.vmap(lambda row, needs=problem.needs: mbcal.modeler(model, row, needs))(problem.params.X(x))
        h = np.concatenate([np.reshape(g.model.predict(scenes, g.batch), -1) for g in problem.groups])
        assert np.allclose(problem.predict(x), h, rtol=0, atol=1e-9)
    # 5 cm more lever: its tip and knob move in the image (pixels), nothing off the lever moves
    moved = np.abs(longer.predict(x) - plain.predict(x)).reshape(-1, 2).max(axis=1)
    point = [m.refs["point"] for m in data.measurements]
    lengthwise = [p.endswith(("lever.tip", "lever.knob_front", "lever.middle")) for p in point]
    assert np.all(moved[lengthwise] > 1.0) and np.all(moved[[not k for k in lengthwise]] < 1e-9), moved
