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
from mbcal.measurements import MeasurementModel, get_model, register, registry

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
