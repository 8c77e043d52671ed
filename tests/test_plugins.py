"""Measurement models are plugins: the example package in tests/plugins is installed and found
through its entry point, exactly as a third-party package would be."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
import warnings

import numpy as np
import pytest

from mbcal.errors import MeasurementFileError
from mbcal.measurements import MeasurementModel, Role, get_model, register, registry

from conftest import ROOT

PLUGIN = ROOT / "tests" / "plugins" / "mbcal_example_plugin"


def test_builtins_are_registered_through_the_entry_point_group():
    from importlib import metadata

    names = {ep.name for ep in metadata.entry_points(group="mbcal.measurements")}
    assert {"image_point", "point3d", "distance", "angle", "range", "point_to_surface"} <= names
    assert set(registry()) >= names


def test_unknown_kind_lists_the_available_ones():
    with pytest.raises(MeasurementFileError) as info:
        get_model("image_pont")
    assert "available:" in str(info.value) and "image_point" in str(info.value)


@pytest.fixture(scope="module")
def installed_plugin(tmp_path_factory):
    target = tmp_path_factory.mktemp("site")
    result = subprocess.run(
        [
            sys.executable,
            "-m",
            "pip",
            "install",
            "--no-deps",
            "--no-build-isolation",
            "--target",
            str(target),
            str(PLUGIN),
        ],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert result.returncode == 0, result.stderr[-3000:]
    return target


def test_example_plugin_is_found_through_its_entry_point_and_calibrates(installed_plugin, tmp_path):
    script = textwrap.dedent(
        """
        import json, math
        import mbcal
        from mbcal.measurements import registry
        assert "height" in registry(), sorted(registry())
        model = mbcal.load_model_text('''
        param shelf.z = 1.0 m in [0.8 m, 1.2 m]
        param shelf.tilt = 0 deg in [-5 deg, 5 deg]
        frame shelf at (0, 0, shelf.z) * rot_x(shelf.tilt) {
          point front = (0, -0.2 m, 0)
          point back = (0, 0.2 m, 0)
        }
        ''')
        plan = mbcal.measurements_from_records(
            [{"kind": "height", "point": p, "sigma": 0.001} for p in ("shelf.front", "shelf.back")], model)
        truth = {"shelf.z": 1.05, "shelf.tilt": math.radians(2)}
        data = mbcal.simulate(model, plan, truth, seed=1)
        result = mbcal.calibrate(model, data, ["shelf.*"], restarts=4)
        print(json.dumps({k: [result.values[k], result.std[k], truth[k]] for k in truth}))
        """
    )
    env = {**os.environ, "PYTHONPATH": str(installed_plugin)}
    out = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, env=env, timeout=600, cwd=tmp_path
    )
    assert out.returncode == 0, out.stderr[-3000:]
    values = json.loads(out.stdout.strip().splitlines()[-1])
    for name, (value, std, true) in values.items():
        assert abs(value - true) <= 3 * std + 1e-9, name


def test_a_broken_plugin_warns_and_the_rest_still_work(tmp_path):
    dist = tmp_path / "broken_plugin-0.1.dist-info"
    dist.mkdir()
    (dist / "METADATA").write_text("Metadata-Version: 2.1\nName: broken-plugin\nVersion: 0.1\n")
    (dist / "entry_points.txt").write_text("[mbcal.measurements]\nbroken = no_such_module:Model\n")
    script = (
        "import warnings\n"
        "with warnings.catch_warnings(record=True) as w:\n"
        "    warnings.simplefilter('always')\n"
        "    from mbcal.measurements import registry\n"
        "    kinds = registry()\n"
        "print('image_point' in kinds, 'broken' in kinds, any('broken' in str(x.message) for x in w))\n"
    )
    env = {**os.environ, "PYTHONPATH": str(tmp_path)}
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, env=env, timeout=300)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["True", "False", "True"]


def test_a_model_can_be_registered_from_python():
    class Zero(MeasurementModel):
        kind = "test_zero"
        roles = ()
        values = ("value",)

        def predict(self, scenes, batch):
            from mbcal._jax import jnp

            return jnp.zeros((len(batch), 1))

    register(Zero)
    assert get_model("test_zero").size == 1
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert "image_point" in registry()
    assert np.isfinite(get_model("image_point").default_sigma)


def test_a_measure_kind_no_installed_model_provides_is_reported_at_the_statement_when_the_model_is_used():
    """'measure image_point, image_pointt' checked fine and solve/observe never mentioned the typo
    (docs/language.md: kinds not installed are reported when the model is used); 'mbcal check'
    loads no measurement model, so it still accepts the model."""
    from mbcal import load_model_text, measurements_from_records
    from mbcal.errors import MdlError
    from mbcal.measurements.sets import MeasurementSet
    from mbcal.problem import Problem

    model = load_model_text("param a = 1 m\npoint p = (a, 0, 0)\nmeasure point3d,\n  image_pointt\n")
    assert model.measures == ("point3d", "image_pointt")
    record = {"kind": "point3d", "point": "p", "x": 1, "y": 0, "z": 0, "sigma": 0.001}
    with pytest.raises(MdlError) as info:
        measurements_from_records([record], model)
    message = "<string>:4:3: no installed measurement model provides 'image_pointt' (installed:"
    assert str(info.value).startswith(message)
    assert "point3d" in info.value.message and info.value.hint == "did you mean 'image_point'?"
    data = measurements_from_records([record], None)  # built without the model: the problem says it
    assert isinstance(data, MeasurementSet)
    with pytest.raises(MdlError, match=r"^<string>:4:3: no installed measurement model provides 'image_pointt'"):
        Problem(model, data, ["a"])
    ok = load_model_text("param a = 1 m\npoint p = (a, 0, 0)\nmeasure point3d\n")
    assert len(Problem(ok, measurements_from_records([record], ok), ["a"]).groups) == 1


# ---- a plugin that breaks the protocol is named, never silently misread --------------------------

SHELF = """
param shelf.z = 1.0 m in [0.8 m, 1.2 m]
frame shelf at (0, 0, shelf.z) {
  point front = (0, -0.2 m, 0)
  point middle = (0, 0, 0)
  point back = (0, 0.2 m, 0)
}
measure point3d, KIND
"""


def _plugin(kind: str, values: tuple[str, ...], predict, visible=None) -> MeasurementModel:
    """A point plugin of ``kind`` registered from Python, with the given predict (and visible)."""
    methods = {"kind": kind, "roles": (Role("point", "point"),), "values": values, "value_dimension": "length"}
    methods["predict"] = lambda self, scenes, batch: predict(scenes.points[batch.config, batch.refs["point"]])
    if visible is not None:
        methods["visible"] = lambda self, scenes, batch: visible(len(batch))
    return register(type(f"Plugin_{kind}", (MeasurementModel,), methods))


def _shelf_plan(kind: str):
    import mbcal

    model = mbcal.load_model_text(SHELF.replace("KIND", kind))
    points = ("shelf.front", "shelf.middle", "shelf.back")
    records = [{"kind": kind, "point": p, "sigma": 0.001} for p in points]
    records += [{"kind": "point3d", "point": p, "sigma": 0.001} for p in points]
    return model, mbcal.measurements_from_records(records, model)


@pytest.mark.parametrize(
    "kind, values, predict, expected",
    [
        ("test_too_wide", ("value",), lambda p: p[:, 1:3], r"\(3, 2\) for 3 measurements; expected \(3, 1\) or \(3,\)"),
        ("test_transposed", ("a", "b"), lambda p: p[:, 1:3].T, r"\(2, 3\) for 3 measurements; expected \(3, 2\):"),
        ("test_scalar", ("value",), lambda p: p[:, 2].sum(), r"shape \(\) for 3 measurements"),
    ],
)
def test_a_plugin_predicting_the_wrong_shape_is_named(kind, values, predict, expected):
    """A plugin of one value that returned (n, 2), or (2, n) for (n, 2), was flattened: every
    later row of h was read against another measurement's value, and the fit could be reported
    trustworthy."""
    import mbcal
    from mbcal.errors import MeasurementModelError

    _plugin(kind, values, predict)
    model, plan = _shelf_plan(kind)
    with pytest.raises(MeasurementModelError, match=f"^measurement model '{kind}': predict returned an array of"):
        mbcal.simulate(model, plan, {"shelf.z": 1.05}, noise=0)
    with pytest.raises(MeasurementModelError, match=expected):
        mbcal.Problem(model, plan, ["shelf.z"]).residual(np.array([1.0]), np.zeros(12 + 3 * (len(values) - 1)))


def test_a_plugin_of_one_value_may_predict_one_flat_value_per_measurement():
    import mbcal

    _plugin("test_flat", ("value",), lambda p: p[:, 2])
    model, plan = _shelf_plan("test_flat")
    data = mbcal.simulate(model, plan, {"shelf.z": 1.05}, noise=0)
    assert [float(m.value[0]) for m in data][:3] == pytest.approx([1.05] * 3)
    result = mbcal.calibrate(model, data, ["shelf.z"], restarts=1)
    assert result.values["shelf.z"] == pytest.approx(1.05)


def test_a_plugin_whose_visible_has_the_wrong_shape_is_named():
    import mbcal
    from mbcal._jax import jnp
    from mbcal.errors import MeasurementModelError

    _plugin("test_visible_half", ("value",), lambda p: p[:, 2:3], visible=lambda n: jnp.ones((2,), bool))
    model, plan = _shelf_plan("test_visible_half")
    message = r"^measurement model 'test_visible_half': visible returned an array of shape \(2,\) for 3 measurements"
    with pytest.raises(MeasurementModelError, match=message):
        mbcal.simulate(model, plan, {"shelf.z": 1.05}, noise=0)


def _raise(error: Exception):
    def fail(*args):
        raise error

    return fail


@pytest.mark.parametrize("method", ["predict", "visible"])
def test_a_plugin_that_raises_is_named_with_its_error(method):
    """A plugin's exception came out raw: a traceback and exit status 1, which the command line
    documents as 'solved but not trustworthy'."""
    import mbcal
    from mbcal._jax import jnp
    from mbcal.errors import MeasurementModelError

    kind = f"test_raises_in_{method}"
    if method == "predict":
        _plugin(kind, ("value",), _raise(ValueError("plugin bug")))
    else:
        _plugin(kind, ("value",), lambda p: p[:, 2:3], visible=_raise(ValueError("plugin bug")))
    model, plan = _shelf_plan(kind)
    with pytest.raises(MeasurementModelError) as info:
        mbcal.simulate(model, plan, {"shelf.z": 1.05}, noise=0)
    assert info.value.message == f"measurement model '{kind}' failed in {method}: ValueError: plugin bug"
    assert isinstance(info.value.__cause__, ValueError)
    if method == "predict":
        data = plan.with_values([np.array([v]) for v in [1.0, 1.0, 1.0]] + [jnp.zeros(3)] * 3)
        with pytest.raises(MeasurementModelError, match=f"^measurement model '{kind}' failed in predict"):
            mbcal.calibrate(model, data, ["shelf.z"], restarts=1)


def test_a_plugin_whose_check_raises_is_named_at_the_measurement():
    import mbcal
    from mbcal.errors import MeasurementModelError

    class CheckRaises(MeasurementModel):
        kind = "test_check_raises"
        roles = (Role("point", "point"),)
        values = ("value",)

        def predict(self, scenes, batch):
            return scenes.points[batch.config, batch.refs["point"]][:, 2:3]

        def check(self, model, refs, data):
            raise KeyError("oops")

    register(CheckRaises)
    model = mbcal.load_model_text(SHELF.replace("KIND", "test_check_raises"))
    with pytest.raises(MeasurementModelError) as info:
        mbcal.measurements_from_records([{"kind": "test_check_raises", "point": "shelf.front", "value": 1}], model)
    assert "measurement model 'test_check_raises' failed in check: KeyError: 'oops'" in str(info.value)
    assert isinstance(info.value.__cause__, KeyError)


def test_a_plugin_failing_on_the_command_line_exits_2_naming_it_and_its_package(tmp_path):
    site = tmp_path / "site"
    (site / "boom_plugin").mkdir(parents=True)
    (site / "boom_plugin" / "__init__.py").write_text(
        textwrap.dedent(
            """
            from mbcal.measurements import MeasurementModel, Role

            class Boom(MeasurementModel):
                kind = "boom"
                roles = (Role("point", "point"),)
                values = ("value",)
                value_dimension = "length"

                def predict(self, scenes, batch):
                    raise ValueError("plugin bug")
            """
        )
    )
    dist = site / "boom_plugin-0.1.dist-info"
    dist.mkdir()
    (dist / "METADATA").write_text("Metadata-Version: 2.1\nName: boom-plugin\nVersion: 0.1\n")
    (dist / "entry_points.txt").write_text("[mbcal.measurements]\nboom = boom_plugin:Boom\n")
    (tmp_path / "shelf.mdl").write_text(SHELF.replace("KIND", "boom"))
    (tmp_path / "boom.csv").write_text("kind,point,value,sigma,unit\nboom,shelf.front,105.2,1,cm\n")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(site), os.environ.get("PYTHONPATH", "")])}
    out = subprocess.run(
        [sys.executable, "-m", "mbcal", "solve", "shelf.mdl", "boom.csv", "--estimate", "shelf.z"],
        capture_output=True,
        text=True,
        env=env,
        timeout=600,
        cwd=tmp_path,
    )
    assert out.returncode == 2, out.stderr[-3000:]
    assert "measurement model 'boom' (package boom-plugin) failed in predict: ValueError: plugin bug" in out.stderr
    assert "Traceback" not in out.stderr


def test_the_plugin_guide_s_example_model_and_measurements_solve_with_the_example_plugin(installed_plugin, tmp_path):
    """docs/plugins.md showed a measurement file of 'height' and no model to use it with; the
    model must list the kind in its 'measure' statement (every bundled model has one), or the
    file is refused.  The page's model, file and command run as written."""
    import re

    text = (ROOT / "docs" / "plugins.md").read_text(encoding="utf-8")
    fences = re.findall(r"^```(\w*)\n(.*?)^```", text, re.S | re.M)
    (model,) = [body for language, body in fences if language == "mdl"]
    assert re.search(r"^measure .*\bheight\b", model, re.M)
    (csv,) = [body for language, body in fences if not language and body.startswith("kind,point,value")]
    (command,) = [body for language, body in fences if language == "sh" and "heights.csv" in body]
    (tmp_path / "heights.csv").write_text(csv, encoding="utf-8")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(installed_plugin), os.environ.get("PYTHONPATH", "")])}
    args = command.split()
    assert args[0] == "mbcal"

    def solve(text: str) -> subprocess.CompletedProcess:
        (tmp_path / "shelf.mdl").write_text(text, encoding="utf-8")
        return subprocess.run(
            [sys.executable, "-m", "mbcal", *(a.strip("'") for a in args[1:]), "--quiet"],
            capture_output=True,
            text=True,
            env=env,
            timeout=600,
            cwd=tmp_path,
        )

    out = solve(model)
    assert out.returncode == 0, out.stderr[-3000:]
    refused = solve(model.replace(", height", ""))  # the kind not listed: the file is refused
    assert refused.returncode == 2 and "'height' is not one of them" in refused.stderr, refused.stderr[-3000:]


def test_registering_a_kind_mbcal_provides_is_refused_unless_replace_is_given(monkeypatch):
    """register() of a class whose kind was 'image_point' silently replaced the built-in for every
    model; a kind registered from Python before may still be registered again (a cell run again)."""
    import importlib

    registry_module = importlib.import_module("mbcal.measurements.registry")  # the package exports a function
    builtin = get_model("image_point")

    class Impostor(MeasurementModel):
        kind = "image_point"
        roles = ()
        values = ("value",)

        def predict(self, scenes, batch):
            raise AssertionError("never called")

    monkeypatch.setattr(registry_module, "_EXTRA", dict(registry_module._EXTRA))  # undone after
    with pytest.raises(ValueError, match=r"^register\(Impostor\): kind 'image_point' is one of mbcal's built-in"):
        register(Impostor)
    assert get_model("image_point") is builtin
    assert isinstance(register(Impostor, replace=True), Impostor)
    assert isinstance(get_model("image_point"), Impostor)

    class Mine(MeasurementModel):
        kind = "test_mine_again"
        roles = ()
        values = ("value",)

    first = register(Mine)
    second = register(type("Mine", (Mine,), {}))  # the same kind again, from a cell run again
    assert get_model("test_mine_again") is second is not first
