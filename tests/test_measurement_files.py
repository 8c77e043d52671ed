"""Measurement files and plans: CSV and JSON, units, covariances, and located errors."""

from __future__ import annotations

import json
import math
import re

import numpy as np
import pytest

from mbcal.errors import MeasurementFileError
from mbcal.language import load_model
from mbcal.measurements.io import read_measurements, write_measurements

from conftest import MEASUREMENTS, MODELS


@pytest.fixture(scope="module")
def room():
    return load_model(MODELS / "teleexistence.mdl")


@pytest.fixture(scope="module")
def arm():
    return load_model(MODELS / "arm7.mdl")


def write(tmp_path, name, text):
    path = tmp_path / name
    path.write_text(text, encoding="utf-8")
    return path


def test_bundled_plans_read_with_the_models(room, arm):
    plan = read_measurements(MEASUREMENTS / "room_plan.csv", room)
    assert len(plan) == 48 and plan.is_plan
    assert {m.refs["camera"] for m in plan} == {"robot.head.eyes.left", "robot.head.eyes.right"}
    arm_plan = read_measurements(MEASUREMENTS / "arm_plan.json", arm)
    assert len(arm_plan) == 84
    assert len(arm_plan.config_names) == 10
    assert set(arm_plan.configurations["pose01"]) >= {f"arm.q{i}" for i in range(1, 8)}


def test_csv_with_units_sigma_per_value_and_known_rows(tmp_path, room):
    path = write(
        tmp_path,
        "m.csv",
        "# a comment line\n"
        "id,kind,config,camera,point,u,v,sigma,sigma_u,sigma_v,unit,param,value,frame,x,y,z\n"
        "a,image_point,,left,lever.tip,100.5,200.25,0.5,,,,,,,,,\n"
        "b,image_point,,eyes.right,lever.hub,101,201,,0.3,0.7,px,,,,,,\n"
        "c,point3d,,,lever.tip,,,2,,,mm,,,room,10,20,30\n"
        ",known,,,,,,,,,,lever.angle,25 deg,,,,\n",
    )
    ms = read_measurements(path, room)
    a, b, c = ms.measurements
    assert a.refs == {"camera": "robot.head.eyes.left", "point": "room.valve.lever.tip"}
    np.testing.assert_array_equal(a.value, [100.5, 200.25])
    np.testing.assert_allclose(a.sigma, [0.5, 0.5])
    np.testing.assert_allclose(b.sigma, [0.3, 0.7])
    np.testing.assert_allclose(c.value, [0.01, 0.02, 0.03])
    np.testing.assert_allclose(c.sigma, [0.002] * 3)
    assert c.refs["frame"] == "room"
    assert ms.known == {"lever.angle": pytest.approx(math.radians(25))}


def test_json_with_covariance_configurations_and_value_lists(tmp_path, arm):
    doc = {
        "configurations": {"p1": {"arm.q1": "-60 deg", "arm.q4": -1.0}},
        "measurements": [
            {
                "id": "m1",
                "kind": "image_point",
                "config": "p1",
                "camera": "eyes.left",
                "point": "hand.tip",
                "value": [320.0, 240.0],
                "cov": [[0.25, 0.1], [0.1, 0.5]],
            },
            {
                "kind": "distance",
                "config": "p1",
                "a": "hand.tip",
                "b": "hand.wrist",
                "value": 18.9,
                "unit": "cm",
                "sigma": 1,
                "configuration": "p1",
            },
        ],
    }
    ms = read_measurements(write(tmp_path, "m.json", json.dumps(doc)), arm)
    m1, m2 = ms.measurements
    np.testing.assert_array_equal(m1.cov, [[0.25, 0.1], [0.1, 0.5]])
    assert m2.value == pytest.approx([0.189]) and m2.sigma == pytest.approx([0.01])
    assert ms.configurations["p1"]["arm.q1"] == pytest.approx(math.radians(-60))
    assert ms.config_names == ["p1"]


@pytest.mark.parametrize("suffix", ["csv", "json"])
def test_write_then_read_round_trips(tmp_path, arm, suffix):
    plan = read_measurements(MEASUREMENTS / "arm_plan.json", arm)
    rng = np.random.default_rng(0)
    ms = plan.with_values([rng.normal(300, 50, 2) for _ in plan])
    out = tmp_path / f"copy.{suffix}"
    write_measurements(ms, out)
    back = read_measurements(out, arm)
    assert [m.id for m in back] == [m.id for m in ms]
    for a, b in zip(ms, back):
        np.testing.assert_array_equal(a.value, b.value)
        np.testing.assert_array_equal(a.cov, b.cov)
        assert a.config == b.config and a.refs == b.refs
    assert back.configurations == ms.configurations


CSV_ERRORS = {
    "unknown_point_suggests": (
        "kind,camera,point,u,v\nimage_point,left,lever.tpi,1,2\n",
        "m.csv:2:18: 'point': the model has no point named 'lever.tpi'",
        "room.valve.lever.tip",
    ),
    "unknown_camera": (
        "kind,camera,point,u,v\nimage_point,middle,lever.tip,1,2\n",
        "m.csv:2:13: 'camera': the model has no camera named 'middle'",
        None,
    ),
    "nan_value": (
        "kind,camera,point,u,v\nimage_point,left,lever.tip,nan,2\n",
        "m.csv:2:28: value 'u': must be finite, got 'nan'",
        None,
    ),
    "inf_value": (
        "kind,camera,point,u,v\nimage_point,left,lever.tip,1,inf\n",
        "m.csv:2:30: value 'v': must be finite, got 'inf'",
        None,
    ),
    "missing_column_kind": (
        "camera,point,u,v\nleft,lever.tip,1,2\n",
        "m.csv:1:1: missing column 'kind' in the header",
        None,
    ),
    "unknown_column": (
        "kind,camera,point,u,v,weight\nimage_point,left,lever.tip,1,2,3\n",
        "m.csv:1:23: unknown column 'weight'",
        None,
    ),
    "half_a_value": (
        "kind,camera,point,u,v\nimage_point,left,lever.tip,1,\n",
        "m.csv:2:30: 'image_point' needs all of u, v; missing v",
        None,
    ),
    "duplicate_id": (
        "id,kind,camera,point,u,v\na,image_point,left,lever.tip,1,2\na,image_point,left,lever.hub,1,2\n",
        "m.csv:3:1: duplicate id 'a' (first at m.csv:2:1)",
        None,
    ),
    "unknown_kind": (
        "kind,camera,point,u,v\nimage_pt,left,lever.tip,1,2\n",
        "m.csv:2:1: unknown measurement kind 'image_pt'",
        "image_point",
    ),
    "bad_sigma": (
        "kind,camera,point,u,v,sigma\nimage_point,left,lever.tip,1,2,-1\n",
        "m.csv:2:32: sigma must be positive, got '-1'",
        None,
    ),
    # a variance that is not a number (1e300² overflowed, with a NumPy warning before the error)
    "huge_sigma": (
        "kind,camera,point,u,v,sigma\nimage_point,left,lever.tip,1,2,1e300\n",
        "m.csv:2:32: sigma '1e300' is out of range: its square is not a finite positive number",
        None,
    ),
    "tiny_sigma": (
        "kind,camera,point,u,v,sigma\nimage_point,left,lever.tip,1,2,1e-200\n",
        "m.csv:2:32: sigma '1e-200' is out of range: its square is not a finite positive number",
        None,
    ),
    "wrong_unit": (
        "kind,camera,point,u,v,unit\nimage_point,left,lever.tip,1,2,mm\n",
        "m.csv:2:32: 'image_point' values are in pixels; unit 'mm' does not apply",
        None,
    ),
    "not_a_number": (
        "kind,camera,point,u,v\nimage_point,left,lever.tip,one,2\n",
        "m.csv:2:28: value 'u': expected a number, got 'one'",
        None,
    ),
    "too_many_fields": (
        "kind,camera,point,u,v\nimage_point,left,lever.tip,1,2,3\n",
        "m.csv:2:1: row has 6 fields but the header has 5",
        None,
    ),
    # a row with too few cells was padded: a value shifted into another column, a σ left off read
    # as the default
    "too_few_fields": (
        "kind,camera,point,u,v,sigma\nimage_point,left,lever.tip,70.9,0.5\n",
        "m.csv:2:1: row has 5 fields but the header has 6",
        "an empty cell (',,') leaves a value out",
    ),
    "trailing_sigma_left_off": (
        "kind,camera,point,u,v,sigma\nimage_point,left,lever.tip,1,2,0.5\nimage_point,left,lever.hub,3,4\n",
        "m.csv:3:1: row has 5 fields but the header has 6",
        None,
    ),
    "missing_role": (
        "kind,point,u,v\nimage_point,lever.tip,1,2\n",
        "m.csv:2:1: 'image_point' needs 'camera' (a camera name)",
        None,
    ),
    "known_not_per_configuration": (
        "kind,config,param,value\nknown,c1,lever.angle,5 deg\n",
        "m.csv:2:10: 'lever.angle' is given for configuration 'c1' but is not declared 'per configuration' "
        "in the model",
        None,
    ),
    "underscore_number": (
        "kind,camera,point,u,v\nimage_point,left,lever.tip,1_000,2\n",
        "m.csv:2:28: value 'u': expected a number, got '1_000'",
        None,
    ),
    "cell_too_long": (
        "kind,camera,point,u,v\nimage_point,left,lever.tip," + "1" * 200_000 + ",2\n",
        "m.csv:2:1: unreadable CSV: field larger than field limit",
        None,
    ),
    "unclosed_quote": (
        'kind,camera,point,u,v\nimage_point,left,"lever.tip,1,2\nimage_point,left,lever.hub,1,2\n',
        "m.csv:2:1: unreadable CSV: a quoted cell opened in this row is never closed",
        None,
    ),
    "text_after_a_quote": (
        'kind,camera,point,u,v\nimage_point,left,"lever"tip,1,2\n',
        "m.csv:2:1: unreadable CSV: ',' expected after '\"'",
        None,
    ),
    "empty": ("", "m.csv:1:1: empty file: no header row", None),
    "header_only": ("kind,camera,point,u,v\n", "m.csv:1:1: no measurements", None),
}


@pytest.mark.parametrize("case", sorted(CSV_ERRORS))
def test_bad_csv_gives_a_located_error(case, tmp_path, room, monkeypatch):
    text, expected, hint = CSV_ERRORS[case]
    monkeypatch.chdir(tmp_path)
    write(tmp_path, "m.csv", text)
    with pytest.raises(MeasurementFileError) as info:
        read_measurements("m.csv", room)
    assert str(info.value).startswith(expected), str(info.value)
    if hint:
        assert hint in str(info.value)


def test_bad_json_is_located_by_line(tmp_path, room, monkeypatch):
    monkeypatch.chdir(tmp_path)
    write(
        tmp_path,
        "m.json",
        '{"measurements": [\n  {"kind": "image_point", "camera": "left", "point": "lever.tip",'
        ' "u": 1, "v": 2},\n  {"kind": "image_point", "camera": "left", "point": "nowhere", "u": 1, "v": 2}\n]}\n',
    )
    with pytest.raises(MeasurementFileError) as info:
        read_measurements("m.json", room)
    assert str(info.value).startswith("m.json:3:54: 'point': the model has no point named 'nowhere'")
    write(tmp_path, "broken.json", '{"measurements": [\n  {"kind": }\n]}')
    with pytest.raises(MeasurementFileError, match=r"^broken.json:2:12: invalid JSON"):
        read_measurements("broken.json", room)


def test_wrong_arity_in_json_value_list(tmp_path, room, monkeypatch):
    monkeypatch.chdir(tmp_path)
    write(tmp_path, "m.json", '[{"kind": "image_point", "camera": "left", "point": "lever.tip", "value": [1, 2, 3]}]')
    with pytest.raises(MeasurementFileError, match="'image_point' has 2 values \\(u, v\\), got 3"):
        read_measurements("m.json", room)


def test_missing_file_and_unknown_type(tmp_path, room):
    with pytest.raises(MeasurementFileError, match="file not found"):
        read_measurements(tmp_path / "nothere.csv", room)
    with pytest.raises(MeasurementFileError, match="unknown measurement file type"):
        read_measurements(write(tmp_path, "m.xlsx", "x"), room)


def test_kind_the_model_does_not_declare_is_refused(tmp_path, monkeypatch):
    from mbcal.language import load_model_text

    model = load_model_text("point p = (0, 0, 0)\npoint q = (1 m, 0, 0)\nmeasure point3d\n")
    monkeypatch.chdir(tmp_path)
    write(tmp_path, "m.csv", "kind,a,b,value\ndistance,p,q,1\n")
    with pytest.raises(MeasurementFileError) as info:
        read_measurements("m.csv", model)
    assert str(info.value).startswith(
        "m.csv:2:1: the model declares the measurement models point3d; 'distance' is not one of them"
    )


def test_csv_files_are_read_line_by_line_whatever_their_line_ends(room, tmp_path):
    """CSV files are streamed (docs/reliability.md): a byte-order mark, CRLF and bare CR line ends
    read the same, and bytes that are not UTF-8 are an error at their line."""
    rows = [
        "id,kind,camera,point,u,v",
        "m1,image_point,eyes.left,lever.tip,1,2",
        "m2,image_point,eyes.left,lever.hub,3,4",
    ]
    for name, data in (
        ("bom.csv", b"\xef\xbb\xbf" + "\r\n".join(rows).encode() + b"\r\n"),
        ("mac.csv", "\r".join(rows).encode() + b"\r"),
        ("unix.csv", "\n".join(rows).encode()),
    ):
        (tmp_path / name).write_bytes(data)
        ms = read_measurements(tmp_path / name, room)
        assert [m.id for m in ms] == ["m1", "m2"], name
        assert [m.where.line for m in ms] == [2, 3], name
    latin1 = "\n".join(rows).encode() + b"\nm3,image_point,eyes.left,lever.tip,5,6 \xb5m\n"
    (tmp_path / "latin1.csv").write_bytes(latin1)
    with pytest.raises(MeasurementFileError, match=r"latin1.csv:4:40: not UTF-8 text \(byte 40 of the line\)") as info:
        read_measurements(tmp_path / "latin1.csv", room)
    assert (info.value.span.line, info.value.span.column) == (4, 40)
    (tmp_path / "latin1.json").write_bytes('[\n {"id": "µ", "x": '.encode() + b'"\xb5m"}]')
    with pytest.raises(MeasurementFileError, match=r"latin1.json:2:20: not UTF-8 text \(byte 23\)") as info:
        read_measurements(tmp_path / "latin1.json", room)
    assert (info.value.span.line, info.value.span.column) == (2, 20)  # it said 1:1; µ is one character
    # bare CR line ends: the file comes as one piece; the bad byte was placed on line 1
    mac = "\r".join(rows).encode() + b"\rm3,image_point,eyes.left,lever.tip,5,6 \xb5m\r"
    (tmp_path / "latin1-mac.csv").write_bytes(mac)
    with pytest.raises(MeasurementFileError, match=r"latin1-mac.csv:4:40: not UTF-8 text \(byte 40 of the line\)"):
        read_measurements(tmp_path / "latin1-mac.csv", room)


def test_a_sets_columns_follow_its_measurements_and_give_the_problems_values(tmp_path, room):
    """MeasurementSet.columns(): the set as arrays per kind, cached while the set holds the same
    measurement objects, rebuilt when one is added or replaced; Problem.y reads it."""
    from dataclasses import replace

    from mbcal.problem import Problem

    plan = read_measurements(MEASUREMENTS / "room_plan.csv", room)
    rng = np.random.default_rng(0)
    data = plan.with_values([rng.normal(300.0, 50.0, 2) for _ in plan])
    columns = data.columns()
    assert data.columns() is columns  # kept
    col = columns.kinds["image_point"]
    assert list(col.members) == list(range(len(data)))
    assert col.names("camera") == [m.refs["camera"] for m in data]
    assert col.names("point") == [m.refs["point"] for m in data]
    assert [columns.config_names[c] for c in col.config] == [m.config for m in data]
    np.testing.assert_array_equal(col.values, np.stack([m.value for m in data]))
    np.testing.assert_array_equal(col.cov, np.stack([m.cov for m in data]))
    problem = Problem(room, data, ["room.x", "room.y"])
    np.testing.assert_array_equal(problem.y, np.concatenate([m.value for m in data]))
    for m, rows in zip(data, problem.measurement_rows):
        np.testing.assert_array_equal(problem.y[rows], m.value)

    # replaced in place (same length): rebuilt, and the new value is read
    data.measurements[3] = replace(data.measurements[3], value=np.array([1.0, 2.0]))
    assert data.columns() is not columns
    np.testing.assert_array_equal(data.columns().kinds["image_point"].values[3], [1.0, 2.0])
    # a plan row without a value: NaN in its row, has_value False
    data.measurements.append(plan.measurements[0])
    col = data.columns().kinds["image_point"]
    assert len(col.members) == len(plan) + 1 and not col.has_value[-1] and np.isnan(col.values[-1]).all()


# ---- known rows' unit cell, JSON keys, per-configuration values given in every configuration ---------


@pytest.fixture(scope="module")
def lever():
    return load_model(MODELS / "lever.mdl")


LEVER_ROWS = "hub,image_point,,eye,lever.hub,334.3,226.8,1,,,\ntip,image_point,,eye,lever.tip,223.3,70.9,1,,,\n"


def known_csv(tmp_path, value: str, unit: str, param: str = "lever.length"):
    return write(
        tmp_path,
        "k.csv",
        f"id,kind,config,camera,point,u,v,sigma,param,value,unit\n,known,,,,,,,{param},{value},{unit}\n" + LEVER_ROWS,
    )


@pytest.mark.parametrize(
    ("value", "unit", "param", "expected"),
    [
        ("25", "cm", "lever.length", 0.25),
        ("25 cm", "", "lever.length", 0.25),
        ("25 cm", "cm", "lever.length", 0.25),
        ("250", "mm", "lever.length", 0.25),
        ("0.25", "", "lever.length", 0.25),
        ("30", "deg", "lever.angle", math.radians(30)),
    ],
)
def test_a_known_rows_unit_cell_gives_its_values_unit(tmp_path, lever, value, unit, param, expected):
    """A CSV 'known' row's unit may be written in the value cell or in the unit cell: one meaning."""
    ms = read_measurements(known_csv(tmp_path, value, unit, param), lever)
    assert ms.known == {param: pytest.approx(expected)}


@pytest.mark.parametrize(
    ("value", "unit", "message"),
    [
        ("25", "deg", "k.csv:2:30: value of 'lever.length': 'deg' is not a length unit"),
        ("25", "furlong", "k.csv:2:30: value of 'lever.length': unknown unit 'furlong'"),
        ("25 cm", "mm", "k.csv:2:33: value of 'lever.length': '25 cm' says 'cm' but the unit column says 'mm'"),
    ],
)
def test_a_known_rows_unit_cell_that_does_not_fit_is_an_error_at_the_cell(
    tmp_path, lever, monkeypatch, value, unit, message
):
    monkeypatch.chdir(tmp_path)
    known_csv(tmp_path, value, unit)
    with pytest.raises(MeasurementFileError) as info:
        read_measurements("k.csv", lever)
    assert str(info.value).startswith(message), str(info.value)


def test_the_cli_refuses_a_known_rows_unit_that_does_not_fit(tmp_path, lever, monkeypatch):
    """The reviewer's case: 25 deg for a length was read as 25 m (and 25 cm as 25 m)."""
    from mbcal.cli import main

    monkeypatch.chdir(tmp_path)
    known_csv(tmp_path, "25", "deg")
    assert main(["solve", str(MODELS / "lever.mdl"), "k.csv", "--estimate", "lever.angle", "-q"]) == 2


def lever_json(tmp_path, **extra):
    records = [
        {"id": "hub", "kind": "image_point", "camera": "eye", "point": "lever.hub", "u": 334.3, "v": 226.8},
        {"id": "tip", "kind": "image_point", "camera": "eye", "point": "lever.tip", "u": 223.3, "v": 70.9},
    ]
    records[1].update(extra)
    text = '{"measurements": [\n' + ",\n".join("  " + json.dumps(r) for r in records) + "\n]}\n"
    return write(tmp_path, "m.json", text)


def _at(text: str, needle: str, start: int = 0) -> str:
    """line:col of the first ``needle`` in ``text`` from offset ``start``."""
    offset = text.index(needle, start)
    return f"{text.count(chr(10), 0, offset) + 1}:{offset - (text.rfind(chr(10), 0, offset) + 1) + 1}"


@pytest.mark.parametrize(
    ("extra", "where", "message", "hint"),
    [
        ({"sigam": 0.05}, '"sigam"', "unknown key 'sigam'", "'sigma'"),
        ({"Sigma_W": 0.05}, '"Sigma_W"', "unknown key 'sigma_w'", "did you mean 'sigma_"),
        ({"param": "lever.angle"}, '"param"', "unknown key 'param'", None),
        ({"config": "a", "configuration": "b"}, None, "'config' ('a') and 'configuration' ('b') name", None),
    ],
)
def test_unknown_keys_in_json_records_are_errors(tmp_path, lever, monkeypatch, extra, where, message, hint):
    """Like an unknown CSV column: a typo of 'sigma' would otherwise be the default σ = 1 px.  The
    error points at the key (it pointed at the record's '{'); one of the record as a whole at the
    record."""
    monkeypatch.chdir(tmp_path)
    text = lever_json(tmp_path, **extra).read_text()
    with pytest.raises(MeasurementFileError) as info:
        read_measurements("m.json", lever)
    assert str(info.value).startswith(f"m.json:{_at(text, where) if where else '3:3'}: {message}"), str(info.value)
    if hint:
        assert hint in str(info.value)


@pytest.mark.parametrize("layout", ["one line", "a line each", "records spread over lines"])
def test_a_json_records_error_names_its_line_and_column_however_the_file_is_laid_out(
    tmp_path, lever, monkeypatch, layout
):
    # Each record's line is counted on from the previous record's (counting from the file's start
    # was quadratic in the records); the column from the line's start, on one line too.
    monkeypatch.chdir(tmp_path)
    good = {"kind": "image_point", "camera": "eye", "point": "lever.hub", "u": 1.0, "v": 2.0}
    records = [json.dumps(good)] * 5 + [json.dumps({**good, "sigam": 1})] + [json.dumps(good)] * 2
    if layout == "one line":
        text = '{"measurements": [' + ", ".join(records) + "]}"
    elif layout == "a line each":
        text = '{"measurements": [\n' + ",\n".join("    " + r for r in records) + "\n]}\n"
    else:
        text = '{"measurements": [\n' + ",\n".join(r.replace(", ", ",\n  ") for r in records) + "\n]}\n"
    write(tmp_path, "m.json", text)
    with pytest.raises(MeasurementFileError) as info:
        read_measurements("m.json", lever)
    key = _at(text, '"sigam"')
    assert str(info.value).startswith(f"m.json:{key}: unknown key 'sigam'"), str(info.value)


@pytest.mark.parametrize(
    ("extra", "where", "message"),
    [
        ({"u": "abc"}, '"abc"', "value 'u': expected a number, got 'abc'"),
        ({"Sigma": -1}, "-1", "sigma must be positive, got -1"),
        ({"kind": "image_pint"}, '"image_pint"', "unknown measurement kind 'image_pint'"),
        ({"point": "lever.tap"}, '"lever.tap"', "'point': "),
    ],
)
def test_an_error_in_a_json_records_value_points_at_the_value(tmp_path, lever, monkeypatch, extra, where, message):
    """It pointed at the record's '{': in a record of a dozen keys the user had to find the one."""
    monkeypatch.chdir(tmp_path)
    text = lever_json(tmp_path, **extra).read_text()
    with pytest.raises(MeasurementFileError) as info:
        read_measurements("m.json", lever)
    at = _at(text, where, text.index('"tip"'))  # in the second record
    assert str(info.value).startswith(f"m.json:{at}: {message}"), str(info.value)


def test_a_json_file_of_another_format_is_refused_at_its_format(tmp_path, lever, monkeypatch):
    """'format' was not read: a file of another program or of a later mbcal was taken as ours."""
    monkeypatch.chdir(tmp_path)
    record = {"kind": "image_point", "camera": "eye", "point": "lever.hub", "u": 1.0, "v": 2.0}
    text = '{"measurements": [' + json.dumps(record) + '],\n "format": "mbcal-measurements-2"}\n'
    write(tmp_path, "m.json", text)
    with pytest.raises(MeasurementFileError) as info:
        read_measurements("m.json", lever)
    assert str(info.value).startswith(
        "m.json:2:12: 'format' is 'mbcal-measurements-2': this mbcal reads measurement files of format "
        "'mbcal-measurements-1'"
    ), str(info.value)
    write(tmp_path, "m.json", text.replace("-2", "-1"))
    assert len(read_measurements("m.json", lever).measurements) == 1


@pytest.mark.parametrize(
    ("text", "message"),
    [
        # the second 'sigma' of the second record: json would keep 3 px silently
        (
            '{"measurements": [\n  {"kind": "image_point", "camera": "eye", "point": "lever.hub", "u": 1, "v": 2},\n'
            '  {"kind": "image_point", "camera": "eye", "point": "lever.tip", "u": 1, "v": 2, "sigma": 0.5, '
            '"sigma": 3}\n]}\n',
            "m.json:3:96: key 'sigma' written twice in one object",
        ),
        # a nested object: the inner one is named, not the outer
        (
            '{"known": {"lever.length": 1, "lever.length": 2},\n "measurements": []}\n',
            "m.json:1:31: key 'lever.length' written twice in one object",
        ),
        # the top level
        ('{"measurements": [],\n "measurements": []}\n', "m.json:2:2: key 'measurements' written twice"),
        # keys of a record ignore case: 'Sigma' and 'sigma' are one key
        (
            '[\n  {"kind": "image_point", "camera": "eye", "point": "lever.hub", "u": 1, "v": 2, '
            '"Sigma": 1, "sigma": 2}\n]',
            "m.json:2:3: key 'sigma' written twice in measurements[0] (keys ignore case)",
        ),
    ],
)
def test_a_json_key_written_twice_is_an_error_at_the_second(tmp_path, lever, monkeypatch, text, message):
    """json.loads keeps the last of two equal keys silently: a record with two σ would be read with
    the second and the file would look fine."""
    monkeypatch.chdir(tmp_path)
    write(tmp_path, "m.json", text)
    with pytest.raises(MeasurementFileError) as info:
        read_measurements("m.json", lever)
    assert str(info.value).startswith(message), str(info.value)


def test_json_records_take_every_csv_column(tmp_path, lever):
    """The keys a JSON record may have are the CSV's columns, whatever the kind (and a comment)."""
    ms = read_measurements(
        lever_json(tmp_path, sigma_u=0.5, sigma_v=0.7, unit="px", configuration="default", comment="re-clicked"),
        lever,
    )
    np.testing.assert_allclose(ms.measurements[1].sigma, [0.5, 0.7])
    doc = {
        "measurements": [
            {
                "kind": "point3d",
                "point": "lever.tip",
                "frame": "room",
                "x": 1,
                "y": 2,
                "z": 3,
                "unit": "mm",
                "sigma": 1,
            },
            {"kind": "distance", "a": "lever.tip", "b": "lever.hub", "value": 25, "unit": "cm", "cov": [[1e-4]]},
            {"kind": "angle", "a": "lever.tip", "b": "lever.hub", "c": "lever.tip", "d": "room", "value": 0.1},
        ]
    }
    assert len(read_measurements(write(tmp_path, "keys.json", json.dumps(doc)))) == 3  # names as written


def test_the_documented_examples_read(tmp_path, lever):
    """docs/cli.md's CSV and JSON examples of the measurement file format are read as written."""
    import re

    from conftest import ROOT

    text = (ROOT / "docs" / "cli.md").read_text(encoding="utf-8")
    section = text[text.index("## Measurement files") :]
    for suffix in ("csv", "json"):
        (body,) = re.findall(rf"^```{suffix}\n(.*?)^```", section, re.S | re.M)
        ms = read_measurements(write(tmp_path, f"doc.{suffix}", body), lever)
        assert [m.id for m in ms] == ["hub", "tip"], suffix
        assert ms.known == {"lever.length": pytest.approx(0.25)}, suffix


def arm_data_without(tmp_path, config: str, name: str):
    doc = json.loads((MEASUREMENTS / "arm_plan.json").read_text(encoding="utf-8"))
    del doc["configurations"][config][name]
    text = json.dumps(doc, indent=1)
    return write(tmp_path, "arm.json", text), text


def test_a_per_configuration_value_left_out_of_one_configuration_is_an_error(tmp_path, arm, monkeypatch):
    """The reviewer's case: pose03 without arm.q4 would silently have had the nominal reading."""
    monkeypatch.chdir(tmp_path)
    _, text = arm_data_without(tmp_path, "pose03", "arm.q4")
    line = text[: text.index('"pose03"')].count("\n") + 1
    with pytest.raises(MeasurementFileError) as info:
        read_measurements("arm.json", arm)
    message = str(info.value)
    assert message.startswith(
        f"arm.json:{line}:3: configuration 'pose03' gives no value for 'arm.q4', which configurations "
        "'pose01', 'pose02', 'pose04' and 6 more give"
    ), message
    assert "nominal" in message
    with pytest.raises(MeasurementFileError, match="configuration 'pose03' gives no value for 'arm.q4'"):
        read_measurements("arm.json")  # without a model too


def test_the_cli_refuses_a_per_configuration_value_left_out(tmp_path, capsys):
    from mbcal.cli import main

    path, _ = arm_data_without(tmp_path, "pose03", "arm.q4")
    assert main(["observe", str(MODELS / "arm7.mdl"), str(path), "--estimate", "arm.offset*", "-q"]) == 2
    assert "configuration 'pose03' gives no value for 'arm.q4'" in capsys.readouterr().err


def test_a_configuration_only_measured_in_must_give_the_per_configuration_values_too(tmp_path, arm, monkeypatch):
    """CSV: the known rows of c1 give arm.q4; c2 is only measured in (its rows forgotten)."""
    monkeypatch.chdir(tmp_path)
    write(
        tmp_path,
        "m.csv",
        "id,kind,config,camera,point,param,value\n"
        ",known,c1,,,arm.q4,-60 deg\n"
        "a,image_point,c1,eyes.left,hand.tip,,\n"
        "b,image_point,c2,eyes.left,hand.tip,,\n",
    )
    with pytest.raises(MeasurementFileError) as info:
        read_measurements("m.csv", arm)
    assert str(info.value).startswith(
        "m.csv:4:1: configuration 'c2', which measurements are taken in, gives no value for 'arm.q4', which "
        "configuration 'c1' gives"
    ), str(info.value)
    # JSON: a configuration listed without values
    doc = {
        "configurations": {"c1": {"arm.q4": 0.1, "arm.q5": 0.2}, "c2": {}},
        "measurements": [{"kind": "image_point", "config": "c1", "camera": "eyes.left", "point": "hand.tip"}],
    }
    text = json.dumps(doc, indent=1)
    write(tmp_path, "m.json", text)
    line = text[: text.index('"c2"')].count("\n") + 1
    with pytest.raises(MeasurementFileError) as info:
        read_measurements("m.json", arm)
    assert str(info.value).startswith(
        f"m.json:{line}:3: configuration 'c2' gives no value for 'arm.q4' (nor for 'arm.q5')"
    ), str(info.value)


def test_files_given_together_must_give_per_configuration_values_in_every_configuration(
    tmp_path, arm, monkeypatch, capsys
):
    """Each file is complete alone (one gives the readings of c1 and c2, the other measures in c1,
    c2 and c3 and gives none); together c3 would have had the nominal reading in silence."""
    from mbcal.cli import main
    from mbcal.measurements.sets import merge_measurements

    monkeypatch.chdir(tmp_path)
    readings = {
        "configurations": {"c1": {"arm.q4": 0.1}, "c2": {"arm.q4": 0.2}},
        "measurements": [
            {"id": f"r{c}", "kind": "image_point", "config": c, "camera": "eyes.left", "point": "hand.tip"}
            for c in ("c1", "c2")
        ],
    }
    write(tmp_path, "readings.json", json.dumps(readings))
    write(
        tmp_path,
        "clicks.csv",
        "id,kind,config,camera,point\n"
        "a,image_point,c1,eyes.left,hand.wrist\n"
        "b,image_point,c2,eyes.left,hand.wrist\n"
        "c,image_point,c3,eyes.left,hand.wrist\n",
    )
    sets = [read_measurements(name, arm) for name in ("readings.json", "clicks.csv")]  # each alone: fine
    with pytest.raises(MeasurementFileError) as info:
        merge_measurements(sets, arm)
    assert str(info.value).startswith(
        "clicks.csv:4:1: configuration 'c3', which measurements are taken in, gives no value for 'arm.q4', "
        "which configurations 'c1', 'c2' give"
    ), str(info.value)
    argv = ["solve", str(MODELS / "arm7.mdl"), "readings.json", "clicks.csv", "--estimate", "arm.offset*", "-q"]
    assert main(argv) == 2
    assert "clicks.csv:4:1: configuration 'c3', which measurements" in capsys.readouterr().err
    # a third file that gives the value once for every configuration covers c3 (c1 keeps its own)
    write(
        tmp_path,
        "default.csv",
        "id,kind,config,camera,point,param,value\n,known,,,,arm.q4,0.5\nd,image_point,c3,eyes.left,hand.tip,,\n",
    )
    merged = merge_measurements([*sets, read_measurements("default.csv", arm)], arm)
    assert merged.known == {"arm.q4": 0.5} and merged.configurations["c1"] == {"arm.q4": 0.1}


def test_per_configuration_values_given_everywhere_or_nowhere_are_read(tmp_path, arm):
    """A parameter never given keeps its nominal value; one given once for every configuration is
    the value of the configurations that do not give their own."""
    records = [
        {"kind": "image_point", "config": c, "camera": "eyes.left", "point": "hand.tip"} for c in ("c1", "c2", "c3")
    ]
    doc = {
        "configurations": {"c1": {"arm.q4": 0.1}, "c2": {"arm.q4": 0.2}, "c3": {"arm.q4": 0.3}},
        "measurements": records,
    }
    ms = read_measurements(write(tmp_path, "all.json", json.dumps(doc)), arm)
    assert [ms.configurations[c]["arm.q4"] for c in ("c1", "c2", "c3")] == [0.1, 0.2, 0.3]
    doc = {"measurements": records}
    assert read_measurements(write(tmp_path, "none.json", json.dumps(doc)), arm).configurations == {}
    doc = {"known": {"arm.q4": 0.5}, "configurations": {"c2": {"arm.q4": 0.2}}, "measurements": records}
    ms = read_measurements(write(tmp_path, "default.json", json.dumps(doc)), arm)
    assert ms.known == {"arm.q4": 0.5} and ms.configurations == {"c2": {"arm.q4": 0.2}}


@pytest.mark.parametrize(
    ("row", "column", "message"),
    [
        ("m1,image_point,eye,lever.hub,nan,3,1", 30, "value 'u': must be finite"),
        ("m1,image_point,eye,lever.hubb,3,3,1", 20, "no point named 'lever.hubb'"),
        ("m1,image_point,eye,lever.hub,3,3,-1", 34, "sigma must be positive"),
        ("m1,image_pont,eye,lever.hub,3,3,1", 4, "unknown measurement kind 'image_pont'"),
        ("m1,image_point,,lever.hub,3,3,1", 16, "needs 'camera'"),
        ("m1,image_point,eye,lever.hub,3,,1", 32, "missing v"),
    ],
)
def test_a_csv_error_about_one_cell_points_at_that_cell(tmp_path, row, column, message):
    path = tmp_path / "bad.csv"
    path.write_text("id,kind,camera,point,u,v,sigma\n" + row + "\n")
    with pytest.raises(MeasurementFileError) as info:
        read_measurements(path, load_model(MODELS / "lever.mdl"))
    assert message in info.value.message
    assert (info.value.span.line, info.value.span.column) == (2, column)


def test_an_id_that_starts_like_a_comment_survives_a_csv_round_trip(tmp_path):
    """'#' starts a comment line in a CSV file: an id that starts with it is written quoted, and a
    quoted first cell is a value (the studio's click ids are the user's)."""
    from mbcal.measurements.sets import measurements_from_records

    model = load_model(MODELS / "lever.mdl")
    records = [
        {"id": "#1", "kind": "image_point", "camera": "eye", "point": "lever.hub", "u": 1.0, "v": 2.0},
        {"id": 'a"b', "kind": "image_point", "camera": "eye", "point": "lever.tip", "u": 3.0, "v": 4.0},
    ]
    path = tmp_path / "ids.csv"
    write_measurements(measurements_from_records(records, model), path)
    back = read_measurements(path, model)
    assert [m.id for m in back] == ["#1", 'a"b']
    np.testing.assert_array_equal(back.measurements[0].value, [1.0, 2.0])
    # an unquoted '#' line is still a comment
    path.write_text(path.read_text() + "# a note,image_point,default,eye,lever.hub,5,6,1\n")
    assert len(read_measurements(path, model)) == 2


def test_records_from_python_refuse_unknown_keys_as_files_do():
    from mbcal.measurements.sets import measurements_from_records

    model = load_model(MODELS / "lever.mdl")
    record = {"id": "a", "kind": "image_point", "camera": "eye", "point": "lever.hub", "u": 1.0, "v": 2.0}
    assert len(measurements_from_records([record], model)) == 1
    with pytest.raises(MeasurementFileError, match="record 1: unknown key 'sigam'") as info:
        measurements_from_records([{**record, "sigam": 0.05}], model)
    assert "sigma" in info.value.hint


def test_a_cell_of_another_kinds_column_is_an_error_not_ignored(tmp_path):
    """In a file of mixed kinds each row fills its own kind's columns; a σ written in a point3d
    column of an image-point row would be silently ignored."""
    model = load_model(MODELS / "teleexistence.mdl")
    header = "id,kind,camera,point,u,v,x,y,z,sigma,sigma_x,param,value\n"
    good = "a,image_point,eyes.left,lever.tip,1,2,,,,0.5,,,\nb,point3d,,lever.tip,,,1,2,3,,0.01,,\n"
    path = tmp_path / "mixed.csv"
    path.write_text(header + good)
    assert len(read_measurements(path, model)) == 2
    path.write_text(header + good + "c,image_point,eyes.left,lever.hub,1,2,,,,,0.2,,\n")
    with pytest.raises(MeasurementFileError) as info:
        read_measurements(path, model)
    assert "'sigma_x' does not apply to a 'image_point' measurement" in info.value.message
    assert (info.value.span.line, info.value.span.column) == (4, 43)  # the 0.2
    path.write_text(header + good + "d,image_point,eyes.left,lever.hub,1,2,,,,,,lever.angle,\n")
    with pytest.raises(MeasurementFileError, match="'param' does not apply"):
        read_measurements(path, model)


def test_json_numbers_beyond_a_float_and_nesting_beyond_pythons_are_located_errors(tmp_path, room, monkeypatch):
    """A legal JSON integer of 401 or 5,001 digits ended in OverflowError or Python's digit-limit
    ValueError, and an array nested 100,000 deep in RecursionError: tracebacks, not errors."""
    monkeypatch.chdir(tmp_path)
    for digits in (401, 5001):
        write(
            tmp_path,
            "m.json",
            '[{"kind": "image_point", "camera": "left", "point": "lever.tip", "u": 1, "v": ' + "7" * digits + "}]",
        )
        with pytest.raises(MeasurementFileError, match=r"^m.json:1:79: value 'v': must be finite"):
            read_measurements("m.json", room)
    write(tmp_path, "m.json", "[" * 100_000 + "]" * 100_000)
    with pytest.raises(MeasurementFileError, match=r"^m.json:1:1: invalid JSON: nested too deeply"):
        read_measurements("m.json", room)


def test_values_or_sigmas_given_two_ways_are_refused_and_numpy_arrays_are_values(tmp_path, room, monkeypatch):
    """'value' beside u, v (u, v were dropped) or 'cov' beside 'sigma' (sigma was ignored) was read
    one way without a word; a NumPy array in a record raised "truth value ... is ambiguous"."""
    from mbcal.measurements.sets import measurements_from_records

    monkeypatch.chdir(tmp_path)
    write(
        tmp_path,
        "m.json",
        '[{"kind": "image_point", "camera": "left", "point": "lever.tip", "u": 1, "v": 2,\n "value": [3, 4]}]',
    )
    with pytest.raises(
        MeasurementFileError, match=r"^m.json:1:\d+: the values are given twice: as 'value' and as 'u', 'v'"
    ):
        read_measurements("m.json", room)
    write(tmp_path, "m.csv", "kind,camera,point,u,v,sigma,cov\nimage_point,left,lever.tip,1,2,1,1;0;0;1\n")
    with pytest.raises(MeasurementFileError, match=r"^m.csv:2:\d+: both 'cov' and 'sigma' are given; give one"):
        read_measurements("m.csv", room)
    base = {"kind": "image_point", "camera": "left", "point": "lever.tip"}
    got = measurements_from_records([{**base, "value": np.array([1.0, 2.0]), "cov": 4 * np.eye(2)}], room)
    np.testing.assert_array_equal(got.measurements[0].value, [1.0, 2.0])
    np.testing.assert_array_equal(got.measurements[0].cov, 4 * np.eye(2))
    with pytest.raises(MeasurementFileError, match="record 1: expected a mapping"):
        measurements_from_records(["hello"], room)
    with pytest.raises(MeasurementFileError, match="configuration 'c1': expected a mapping"):
        measurements_from_records([base | {"u": 1, "v": 2}], room, configurations={"c1": 0.3})


def test_an_error_in_a_long_line_shows_the_part_around_its_column(tmp_path):
    """A one-line JSON file of 40 kB was echoed whole under its error."""
    from mbcal.errors import SourceSpan

    path = tmp_path / "long.json"
    path.write_text("x" * 20_000 + "BAD" + "y" * 20_000 + "\n")
    shown = MeasurementFileError("bad", SourceSpan(str(path), 1, 20_001)).render().splitlines()
    source, caret = shown[1], shown[2]
    assert len(source) < 200 and source[caret.index("^") : caret.index("^") + 3] == "BAD"


def test_a_long_bad_value_is_named_not_echoed_in_full(tmp_path, lever, monkeypatch):
    """A 100,000-character value was repeated whole in the message (the source line is cut to 160
    characters, the quoted value was not)."""
    monkeypatch.chdir(tmp_path)
    lever_json(tmp_path, u="x" * 100_000)
    with pytest.raises(MeasurementFileError) as info:
        read_measurements("m.json", lever)
    message = str(info.value)
    assert "value 'u': expected a number, got 'xxx" in message and "(100,002 characters)" in message
    assert len(message) < 200, len(message)


def test_a_long_name_is_cut_in_the_message_not_echoed_whole(tmp_path, lever, monkeypatch):
    """Values were cut (errors.shown) but names were not: an unknown key or camera of 100,000
    characters filled the terminal."""
    monkeypatch.chdir(tmp_path)
    long = "k" * 100_000
    write(tmp_path, "m.json", json.dumps({"measurements": [{"kind": "image_point", long: 1}]}))
    with pytest.raises(MeasurementFileError) as info:
        read_measurements("m.json", lever)
    message = str(info.value)
    assert "unknown key 'kkk" in message and "(100,002 characters)" in message, message[:300]
    assert len(message) < 400 and len(info.value.render()) < 800
    lever_json(tmp_path, camera="c" * 100_000)
    with pytest.raises(MeasurementFileError) as info:
        read_measurements("m.json", lever)
    assert len(str(info.value)) < 600 and "characters)" in str(info.value), str(info.value)[:300]
    # a path is a word too: a long one (a file name of 255 characters in a deep folder) stays whole
    path = str(tmp_path / ("d" * 200) / ("f" * 255))
    assert str(MeasurementFileError(f"cannot read {path}")) == f"cannot read {path}"


@pytest.mark.parametrize(
    ("top", "message_at"),
    [
        # a "measurements" key inside another top-level value drew the record offsets from it
        ('{"comment": {"measurements": [1, 2]},\n "measurements": [\n', "4:"),
        # the key written with an escape: found by its value, not by a text search
        ('{"\\u006deasurements": [\n', "3:"),
    ],
)
def test_a_record_error_is_located_whatever_else_the_top_level_holds(tmp_path, lever, monkeypatch, top, message_at):
    monkeypatch.chdir(tmp_path)
    good = {"kind": "image_point", "camera": "eye", "point": "lever.tip", "u": 1, "v": 2}
    text = top + " " + json.dumps(good) + ",\n " + json.dumps({**good, "sigma": "abc"}) + "\n]}\n"
    write(tmp_path, "m.json", text)
    with pytest.raises(MeasurementFileError) as info:
        read_measurements("m.json", lever)
    line = int(message_at.rstrip(":"))
    column = text.splitlines()[line - 1].index('"abc"') + 1
    assert str(info.value).startswith(f"m.json:{line}:{column}: 'sigma': expected a number"), str(info.value)


def test_an_unknown_top_level_key_is_located_also_when_it_differs_from_a_known_one_by_case(
    tmp_path, lever, monkeypatch
):
    monkeypatch.chdir(tmp_path)
    write(tmp_path, "m.json", '{\n "Format": "mbcal-measurements-1",\n "measurements": []}\n')
    with pytest.raises(MeasurementFileError) as info:
        read_measurements("m.json", lever)
    assert str(info.value).startswith("m.json:2:2: unknown key 'Format'"), str(info.value)  # it said 1:1


# ---- a unit converts values and measured coordinates, never an index ------------------------------


def test_a_unit_converts_a_ranges_value_but_never_its_ray_number(tmp_path, room):
    """A range row's 'unit' is the unit of its distance and σ: its ray number is an index (it was
    multiplied too, and ray 50 with unit mm read as ray 0)."""
    path = write(
        tmp_path,
        "r.csv",
        "id,kind,sensor,ray,value,sigma,unit\nr50,range,depth,50,1500,2,mm\nr100,range,depth,100,150,1,cm\n",
    )
    r50, r100 = read_measurements(path, room).measurements
    assert r50.data == {"ray": 50} and r100.data == {"ray": 100}
    np.testing.assert_allclose([r50.value[0], r100.value[0]], [1.5, 1.5])
    np.testing.assert_allclose([r50.sigma[0], r100.sigma[0]], [0.002, 0.01])
    doc = {"measurements": [{"id": "a", "kind": "range", "sensor": "depth", "ray": 100, "sigma": 1, "unit": "mm"}]}
    (tmp_path / "r.json").write_text(json.dumps(doc), encoding="utf-8")
    (a,) = read_measurements(tmp_path / "r.json", room).measurements
    assert a.data == {"ray": 100}
    # a ray the sensor does not have is refused whatever the unit (500 mm had read as ray 0.5 → 0)
    bad = write(tmp_path, "bad.csv", "id,kind,sensor,ray,sigma,unit\nr,range,depth,500,1,mm\n")
    with pytest.raises(MeasurementFileError, match="ray"):
        read_measurements(bad, room)


def test_a_unit_converts_a_measured_points_coordinates(tmp_path, room):
    path = write(
        tmp_path, "p.csv", "id,kind,object,frame,x,y,z,sigma,unit\np,point_to_surface,room,room,100,200,300,5,mm\n"
    )
    (p,) = read_measurements(path, room).measurements
    assert p.data == pytest.approx({"x": 0.1, "y": 0.2, "z": 0.3})
    np.testing.assert_allclose(p.sigma, [0.005])


# ---- a file's known values are checked as --set checks them ---------------------------------------

PLAIN_F = """param cam.f = 600 in [500, 700]
param lever.angle = 20 deg in [-90 deg, 90 deg]
param lever.length = 25 cm limits [10 cm, 40 cm]
object lever at (0, 0.8 m, 1.1 m) {
  joint revolute(-y, lever.angle)
  shape arm = box(2.5 cm, 1.5 cm, lever.length) at (0, 0, lever.length / 2)
  point hub = (0, 0, 0)
  point tip = (0, 0, lever.length)
}
camera eye(width = 669, height = 453, f = cam.f) at look_at(eye = (0, 0, 1.3 m), target = (0, 0.8 m, 1.1 m))
measure image_point
"""


@pytest.fixture(scope="module")
def plain_f(tmp_path_factory):
    path = tmp_path_factory.mktemp("plain") / "camf.mdl"
    path.write_text(PLAIN_F, encoding="utf-8")
    return load_model(path)


@pytest.mark.parametrize(
    ("param", "value", "unit", "message"),
    [
        # declared without a unit: a plain number ('600 mm' was read as a focal length of 0.6 px)
        ("cam.f", "600", "mm", "k.csv:2:24: value of 'cam.f': the unit 'mm' does not fit a plain number"),
        ("cam.f", "600 mm", "", "k.csv:2:20: value of 'cam.f': the unit 'mm' does not fit a plain number"),
        # outside the hard limits, at the value's cell (was taken as it was)
        (
            "lever.length",
            "45 cm",
            "",
            "k.csv:2:27: value of 'lever.length': 0.45 m is outside the hard limits of lever.length [0.1, 0.4] m",
        ),
        # an unknown name, at the name's cell (errors of known rows pointed at column 1)
        ("lever.lenth", "1", "", "k.csv:2:14: the model has no param named 'lever.lenth'"),
    ],
)
def test_a_known_value_from_a_file_is_checked_at_its_cell(tmp_path, plain_f, monkeypatch, param, value, unit, message):
    monkeypatch.chdir(tmp_path)
    known_csv(tmp_path, value, unit, param)
    with pytest.raises(MeasurementFileError) as info:
        read_measurements("k.csv", plain_f)
    assert str(info.value).startswith(message), str(info.value)
    # a plain number within the limits is read as it is
    ms = read_measurements(known_csv(tmp_path, "650", "", "cam.f"), plain_f)
    assert ms.known == {"cam.f": 650.0}


def test_a_files_known_values_keep_the_model_valid(tmp_path, lever, monkeypatch):
    """A negative length from a file made a box of negative size without a word (--set refuses it)."""
    from mbcal.errors import DimensionError

    monkeypatch.chdir(tmp_path)
    known_csv(tmp_path, "-25 cm", "")
    with pytest.raises(DimensionError, match="must be positive, got -0.25 m with the known values of k.csv"):
        read_measurements("k.csv", lever)


def test_the_cli_refuses_a_unit_for_a_parameter_declared_without_one(tmp_path, plain_f, capsys):
    from mbcal.cli import main

    model = tmp_path / "camf.mdl"
    model.write_text(PLAIN_F, encoding="utf-8")
    plan = write(tmp_path, "p.csv", "id,kind,camera,point,sigma\nhub,image_point,eye,lever.hub,1\n")
    assert main(["simulate", str(model), str(plan), "--set", "cam.f=600mm", "-o", str(tmp_path / "o.csv")]) == 2
    assert "--set cam.f: 'mm' is not a unit of cam.f, which is a plain number" in capsys.readouterr().err
    assert not (tmp_path / "o.csv").exists()
    assert main(["simulate", str(model), str(plan), "--set", "cam.f=650", "-o", str(tmp_path / "o.csv")]) == 0


def test_known_values_given_to_the_library_keep_within_the_hard_limits(plain_f):
    from mbcal.errors import ParameterError
    from mbcal.params import ParameterSet

    with pytest.raises(ParameterError, match=r"'lever.length': 0.45 m is outside the hard limits"):
        ParameterSet(plain_f, ["lever.angle"], known={"lever.length": 0.45})
    assert ParameterSet(plain_f, ["lever.angle"], known={"lever.length": 0.3}).size == 1


def test_a_parameter_declared_without_a_unit_takes_the_unit_its_places_require(tmp_path, monkeypatch, capsys):
    """A review of the fix above: 'param lever.length = 0.25' used as a box's size and a point's
    offset is a length in SI (a free literal), and '30 cm' for it was refused as 'a plain number'.
    What the places of such a parameter require decides (ParamInfo.given_dim); a focal length in
    pixels still refuses 'mm'."""
    from mbcal.cli import main

    text = (MODELS / "lever.mdl").read_text(encoding="utf-8")
    free = "\n".join(
        "param lever.length = 0.25" if ln.startswith("param lever.length") else ln for ln in text.splitlines()
    )
    model_path = write(tmp_path, "free.mdl", free + "\n")
    model = load_model(model_path)
    info = model.param("lever.length")
    assert info.dim is None and info.given_dim == load_model(MODELS / "lever.mdl").param("lever.length").dim
    monkeypatch.chdir(tmp_path)
    ms = read_measurements(known_csv(tmp_path, "30 cm", "", "lever.length"), model)
    assert ms.known == {"lever.length": pytest.approx(0.3)}
    plan = str(MEASUREMENTS / "lever_plan.csv")
    assert main(["simulate", str(model_path), plan, "--set", "lever.length=30cm", "-o", "s.csv", "-q"]) == 0
    assert main(["simulate", str(model_path), plan, "--set", "lever.length=30deg", "-o", "t.csv", "-q"]) == 2
    assert "'deg' is not a unit of lever.length, which is a length" in capsys.readouterr().err


def test_a_value_at_its_limit_after_a_unit_conversion_is_within_it():
    """'35 cm' is 0.35000000000000003 m: a limit of 0.35 m refused it, showing both as 0.35."""
    from mbcal.language.model import ParamInfo
    from mbcal.units import LENGTH

    info = ParamInfo("a", 0, 0.25, None, None, None, False, LENGTH, limit_lower=0.1, limit_upper=0.35)
    assert 35 * 0.01 > 0.35 and info.outside_limits(35 * 0.01) is None
    assert info.outside_limits(0.3500001) == "0.3500001 m is outside the hard limits of a [0.1, 0.35] m"


def test_a_plugins_length_data_are_converted_without_naming_them():
    """unit_data made the conversion of a length kind's data opt-in: a plugin written before it,
    with a measured point in its data, read '100, mm' as 100 m.  By default a length kind's data
    that are not whole-number indices are converted, as before; the indices never."""
    from mbcal.measurements.protocol import MeasurementModel

    class Older(MeasurementModel):
        kind = "older"
        values = ("distance",)
        data = ("x", "y", "z", "index")
        integer_data = ("index",)
        value_dimension = "length"

    class Angles(Older):
        value_dimension = "angle"

    class Explicit(Older):
        unit_data = ("x",)

    assert Older().converted_data == ("x", "y", "z")
    assert Angles().converted_data == () and Explicit().converted_data == ("x",)


@pytest.mark.parametrize(
    ("uses", "given"),
    [
        ("frame f at translate(a, 0, 0)", "length"),
        ("frame f at (a, 0, 0) * rot_z(30 deg)", "length"),  # a position in a product of transforms
        ("frame f at rot_z(atan2(a, 1 m))", "length"),  # beside a length in atan2
        ("point p = (hypot(a, 1 m), 0, 0)", "length"),
        ("frame f at translate(a + 5 cm, 0, 0)", "length"),
        ("frame f at rot_z(a)", "angle"),
        # used as two dimensions (one of them missed before, so the other's unit was taken): none
        ("frame f at (a, 0, 0) * rot_z(a)", None),
        ("frame f at rot_z(atan2(a, 1 m)) * rot_z(a)", None),
    ],
)
def test_where_a_parameter_without_a_unit_stands_decides_its_unit(uses, given):
    from mbcal.language import load_model_text
    from mbcal.units import ANGLE, LENGTH

    model = load_model_text(f"param a = 0.2\n{uses}\n", "m.mdl")
    assert model.param("a").given_dim == {"length": LENGTH, "angle": ANGLE, None: None}[given]


def test_a_models_own_limits_take_a_value_at_the_limit_in_another_unit():
    """'35 cm' against 'limits [0 m, 0.35 m]' was refused in the model too (as nominal and as override)."""
    from mbcal.language import load_model_text

    assert load_model_text("param a = 35 cm limits [0 m, 0.35 m]\n", "m.mdl").param("a").nominal > 0.35
    text = "param a = 0.3 m limits [0 m, 0.35 m]\noverride a = 35 cm\n"
    assert load_model_text(text, "m.mdl").param("a").nominal == pytest.approx(0.35)


@pytest.mark.parametrize(
    ("override", "error"),
    [
        ("override a = 30 cm", None),  # a is a point's coordinate: a length
        ("override a = 0.3", None),
        ("override a = 0.3 sigma 1 mm", None),
        ("override a = 30 deg", "'a' is declared without a unit and used as a length (m); the override is an angle"),
        ("override k = 600 mm", "'k' is declared without a unit and not used as one dimension"),  # k * 1 m
        ("override k = 6 sigma 1 mm", "the override's sigma is a length"),
    ],
)
def test_an_override_of_a_parameter_without_a_unit_reads_units_as_set_does(override, error):
    """The language's own 'override' of 'param k = 3' took '600 mm' as 0.6 (what --set and a
    measurement file's known values refuse): it is checked against the dimension the parameter's
    places require, known once the model is compiled, and located at the value."""
    from mbcal.errors import UnitError
    from mbcal.language import load_model_text

    points = "frame f {\n  point p = (a, 0, 0)\n  point q = (k * 1 m, 0, 0)\n}\n"
    text = f"param a = 0.25\nparam k = 3\n{points}{override}\n"
    if error is None:
        assert load_model_text(text, "m.mdl").param("a").nominal == pytest.approx(0.3)
        return
    with pytest.raises(UnitError, match=re.escape(error)) as info:
        load_model_text(text, "m.mdl")
    assert info.value.span is not None and info.value.span.line == 7


def _corner_rows(u, v, points):
    head = "id,kind,config,camera,point,u,v,sigma\n"
    return head + "".join(
        f"m{i},image_point,view1,cam,{p},{a},{b},0.5\n" for i, (p, a, b) in enumerate(zip(points, u, v))
    )


def test_image_points_mostly_outside_their_cameras_image_are_refused_at_the_first(tmp_path):
    """Corners with u, v doubled (1204 of Zhang's 1280 outside the 640×480 image) were calibrated:
    cx = 608 (its search range [220, 420]), 'consistent and well determined', exit 0."""
    model = load_model(MODELS / "camera_calibration.mdl")  # cam: 640×480
    points = model.target(None).points  # 54 corners
    rng = np.random.default_rng(0)
    u, v = rng.uniform(100, 540, len(points)), rng.uniform(80, 400, len(points))
    read_measurements(write(tmp_path, "inside.csv", _corner_rows(u, v, points)), model)
    # a margin of 10 % of the width and height: points just outside (-60 px, 700 px) are taken,
    # and a few far outside are left to the fit's outliers
    edge_u, edge_v = u.copy(), v.copy()
    edge_u[:5], edge_v[5:10] = -60.0, 520.0
    edge_u[10:20] = 5000.0
    read_measurements(write(tmp_path, "edge.csv", _corner_rows(edge_u, edge_v, points)), model)
    # doubled: most of them outside
    path = write(tmp_path, "x2.csv", _corner_rows(2 * u, 2 * v, points))
    first = int(np.argmax((2 * u > 704) | (2 * v > 528)))
    outside = int(np.sum((2 * u > 704) | (2 * v > 528)))
    assert outside > len(points) / 2
    with pytest.raises(MeasurementFileError) as info:
        read_measurements(path, model)
    assert f"{outside} of the 54 image points of camera 'cam' lie outside its 640×480 image" in str(info.value)
    assert f"measurement 'm{first}'" in str(info.value)
    assert (info.value.span.line, info.value.span.column) == (first + 2, 1)
    assert "another resolution, or scaled" in info.value.hint


def test_a_row_pasted_twice_is_read_with_a_located_warning(tmp_path, room):
    """A file with one row pasted twice (no ids) counted its measurement twice in silence."""
    import warnings

    from mbcal.errors import MeasurementFileWarning

    row = "image_point,robot.head.eyes.left,room.valve.lever.hub,263.8,276.7,1.0\n"
    other = "image_point,robot.head.eyes.right,room.valve.lever.hub,214.3,275.6,1.0\n"
    header = "kind,camera,point,u,v,sigma\n"
    path = write(tmp_path, "twice.csv", header + row + other + row + other + other)
    with pytest.warns(MeasurementFileWarning) as caught:
        data = read_measurements(path, room)
    assert len(data) == 5  # read as written: not refused
    assert [str(w.message) for w in caught] == [
        f"{path}:4: row repeats line 2 (same kind, names, configuration, values and σ: pasted twice?); both are "
        "used; 2 more rows repeat earlier ones (lines 5, 6)"
    ]
    records = [
        {"kind": "image_point", "camera": "robot.head.eyes.left", "point": "room.valve.lever.hub", "u": 1, "v": 2}
    ] * 2
    json_path = write(tmp_path, "twice.json", json.dumps({"measurements": records}, indent=1))
    with pytest.warns(MeasurementFileWarning, match=rf"^{re.escape(str(json_path))}:10: measurement repeats line 3 "):
        read_measurements(json_path, room)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        # not repeats: another value or σ, rows with ids of their own, a plan's rows (no values)
        read_measurements(write(tmp_path, "sigma.csv", header + row + row.replace(",1.0", ",2.0")), room)
        read_measurements(write(tmp_path, "ids.csv", "id," + header + "a," + row + "b," + row), room)
        read_measurements(
            write(tmp_path, "plan.csv", "kind,camera,point\n" + 2 * "image_point,eyes.left,lever.hub\n"), room
        )
