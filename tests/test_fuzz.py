"""Fuzzing the parser and checker: every input parses or raises mbcal's typed, located error.

Two generators, about 10,000 inputs per run in all (``MBCAL_FUZZ_SCALE`` multiplies them):

* grammar-aware generation of models — parameters, lets, frames nested deep, templates and
  instances, shapes, joints, sensors, targets, includes — with good and bad names, arities and
  units, huge and tiny numbers, unicode, include cycles, includes of missing or binary files,
  and mesh files that are empty or corrupt;
* mutation of the bundled models: deleting, inserting, duplicating and swapping text, numbers
  replaced by extreme ones, truncation.

Each input must either load or raise :class:`mbcal.errors.MdlError` with a source location;
any other exception fails, and so does an input that takes more than a few seconds.
Hypothesis runs derandomised so that CI is reproducible; set ``MBCAL_FUZZ_RANDOM=1`` to explore.
"""

from __future__ import annotations

import os
import signal
from contextlib import contextmanager
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from mbcal.errors import MdlError
from mbcal.language import load_model_text

from conftest import MODELS

SCALE = float(os.environ.get("MBCAL_FUZZ_SCALE", "1"))
RANDOM = os.environ.get("MBCAL_FUZZ_RANDOM") == "1"
TIME_LIMIT_S = 10.0


def fuzz_settings(examples: int):
    return settings(
        max_examples=max(1, int(examples * SCALE)),
        deadline=None,
        derandomize=not RANDOM,
        database=None,
        suppress_health_check=list(HealthCheck),
    )


@contextmanager
def time_limit(seconds: float):
    def fail(signum, frame):
        raise TimeoutError(f"an input took more than {seconds} s")

    previous = signal.signal(signal.SIGALRM, fail)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)


@pytest.fixture(scope="module")
def workspace(tmp_path_factory) -> Path:
    """A folder with files the generated models include or load as meshes."""
    import trimesh

    root = tmp_path_factory.mktemp("fuzz")
    (root / "ok.mdl").write_text("param shared.h = 1 m\ntemplate dot() { point p = (0, 0, 0) }\n")
    (root / "cycle_a.mdl").write_text('include "cycle_b.mdl"\n')
    (root / "cycle_b.mdl").write_text('include "cycle_a.mdl"\n')
    (root / "self.mdl").write_text('include "self.mdl"\n')
    (root / "binary.mdl").write_bytes(bytes(range(256)) * 4)
    (root / "latin1.mdl").write_bytes("param caf\xe9 = 1".encode("latin-1"))
    (root / "empty.stl").write_bytes(b"")
    (root / "corrupt.stl").write_bytes(b"solid x\nfacet normal 0 0 1\n outer loop\n vertex 1 2\n")
    (root / "garbage.obj").write_bytes(os.urandom(512))
    trimesh.creation.box(extents=(1, 1, 1)).export(root / "good.obj")
    (root / "folder.mdl").mkdir()
    return root


def check(text: str, path: Path) -> None:
    """The property: it loads, or it raises a typed error that says where."""
    with time_limit(TIME_LIMIT_S):
        try:
            load_model_text(text, str(path))
        except MdlError as err:
            assert err.span is not None, f"{type(err).__name__} without a location: {err}"
            assert err.span.line >= 1 and err.span.column >= 1
            assert str(err).startswith(f"{err.span.path}:{err.span.line}:{err.span.column}: ")
            err.render()  # rendering the caret line must not fail either


# ---- grammar-aware generation ---------------------------------------------------------------------

NAMES = [
    "a",
    "b",
    "x",
    "room.x",
    "lever.angle",
    "q1",
    "len",
    "undefined_name",
    "pi",
    "m",
    "frame",
    "é",
    "a.b.c",
    "_x9",
    "q",
    "offset",
    "world",
    "sin",
]
UNITS = ["", " m", " cm", " mm", " deg", " rad", " inch", " um", "deg", " km"]
NUMBERS = [
    "0",
    "1",
    "2.5",
    "-3",
    "1e308",
    "1e-308",
    "1e999",
    "0.000001",
    "123456789012345678901234567890",
    "7",
    "3.14159",
    "0.0",
    "10",
    "1.5e3",
]
FUNCS = [
    "sin",
    "cos",
    "sqrt",
    "atan2",
    "min",
    "max",
    "abs",
    "translate",
    "rot_z",
    "rpy",
    "axis_angle",
    "look_at",
    "pose",
    "quat",
    "norm",
    "nosuch",
    "hypot",
    "log",
    "exp",
    "cross",
    "dot",
]
SHAPES = ["box", "cylinder", "cone", "sphere", "tube", "rectangle", "plane", "mesh", "torus"]
FILES = [
    "ok.mdl",
    "missing.mdl",
    "cycle_a.mdl",
    "self.mdl",
    "binary.mdl",
    "latin1.mdl",
    "folder.mdl",
    "../nowhere/x.mdl",
    "/abs/missing.mdl",
]
MESHES = ["good.obj", "empty.stl", "corrupt.stl", "garbage.obj", "missing.stl", "folder.mdl", "x.xyz"]
JUNK = ["$", "@", "{", "}", "(", ")", ",", ";", "=", "..", "±", "∞", "\u200b", "\t", "\\", '"', "#", "\x00", "🙂"]


def expressions(depth: int = 3):
    number = st.builds(lambda n, u: n + u, st.sampled_from(NUMBERS), st.sampled_from(UNITS))
    leaf = st.one_of(number, st.sampled_from(NAMES))
    if depth == 0:
        return leaf
    inner = expressions(depth - 1)
    return st.one_of(
        leaf,
        st.builds(lambda a, op, b: f"{a} {op} {b}", inner, st.sampled_from(["+", "-", "*", "/", "^"]), inner),
        st.builds(lambda a: f"-{a}", inner),
        st.builds(lambda a: f"({a})", inner),
        st.builds(lambda f, args: f"{f}({', '.join(args)})", st.sampled_from(FUNCS), st.lists(inner, max_size=4)),
        st.builds(lambda items: f"({', '.join(items)})", st.lists(inner, min_size=2, max_size=4)),
        st.builds(lambda items: f"[{', '.join(items)}]", st.lists(inner, max_size=3)),
    )


EXPR = expressions()
NAME = st.sampled_from(NAMES)
POSE = st.one_of(st.just(""), st.builds(lambda e: f" at {e}", EXPR))


def statements(depth: int = 3):
    simple = st.one_of(
        st.builds(
            lambda n, e, r, p: f"param {n} = {e}{r}{p}",
            NAME,
            EXPR,
            st.one_of(st.just(""), st.builds(lambda a, b: f" in [{a}, {b}]", EXPR, EXPR)),
            st.sampled_from(["", " per configuration", " sigma 1 cm", " ± 2"]),
        ),
        st.builds(lambda n, e: f"let {n} = {e}", NAME, EXPR),
        st.builds(lambda n, e: f"point {n} = {e}", NAME, EXPR),
        st.builds(
            lambda k, args, pose: f"shape {k}({', '.join(args)}){pose}",
            st.sampled_from(SHAPES),
            st.lists(EXPR, max_size=4),
            POSE,
        ),
        st.builds(lambda m, s: f'shape mesh("{m}", scale = {s})', st.sampled_from(MESHES), EXPR),
        st.builds(
            lambda k, a, q: f"joint {k}({a}, {q})",
            st.sampled_from(["revolute", "prismatic", "ball"]),
            st.sampled_from(["x", "-y", "z", "(0, 0, 0)", "(1, 2, 3)"]),
            EXPR,
        ),
        st.builds(lambda n, w, h, f: f"camera {n}(width = {w}, height = {h}, f = {f})", NAME, EXPR, EXPR, EXPR),
        st.builds(lambda n, d: f"range {n}(direction = {d})", NAME, EXPR),
        st.builds(
            lambda n, r, c: f"target {n} = chessboard(rows = {r}, cols = {c}, square = 2 cm)",
            NAME,
            st.sampled_from(["0", "3", "-1", "2.5", "1e9"]),
            st.sampled_from(["4", "0", "1e9"]),
        ),
        st.builds(lambda f: f'include "{f}"', st.sampled_from(FILES)),
        st.builds(lambda n: f"override {n} = 3", NAME),
        st.builds(lambda ks: f"measure {', '.join(ks)}", st.lists(NAME, min_size=1, max_size=3)),
        st.sampled_from(JUNK),
    )
    if depth == 0:
        return simple
    body = st.lists(statements(depth - 1), max_size=4).map(lambda items: "\n".join(items))
    return st.one_of(
        simple,
        st.builds(
            lambda kw, n, pose, b: f"{kw} {n}{pose} {{\n{b}\n}}",
            st.sampled_from(["frame", "object", "link"]),
            NAME,
            POSE,
            body,
        ),
        st.builds(
            lambda n, ps, b: f"template {n}({', '.join(ps)}) {{\n{b}\n}}",
            NAME,
            st.lists(st.sampled_from(["a", "b = 2 m", "len", "x = pi"]), max_size=3),
            body,
        ),
        st.builds(
            lambda n, t, args, pose: f"object {n} = {t}({', '.join(args)}){pose}",
            NAME,
            NAME,
            st.lists(EXPR, max_size=3),
            POSE,
        ),
    )


MODEL_TEXT = st.lists(statements(), min_size=1, max_size=8).map(lambda items: "\n".join(items))


@fuzz_settings(6000)
@given(text=MODEL_TEXT)
@pytest.mark.slow
def test_generated_models_load_or_fail_with_a_located_error(text, workspace):
    check(text, workspace / "generated.mdl")


# ---- extremes the generator reaches only rarely ----------------------------------------------------

EXTREMES = [
    "param a = " + "(" * 150 + "1" + ")" * 150,
    "param a = " + "(" * 5000 + "1" + ")" * 5000,
    "param a = " + "- " * 20000 + "1",
    "param a = " + " + ".join(["1"] * 30000),
    "param a = " + "1 ^ " * 5000 + "1",
    "frame f {\n" * 400 + "}\n" * 400,
    "frame f {\n" * 3000 + "}\n" * 3000,
    "param a = 2 ^ 10000",
    "param a = 10 ^ 400 m",
    "frame f { shape sphere(1e400 m) }",
    "point p = (1e308 m * 10, 0, 0)",
    "param " + "a" * 100000 + " = 1",
    "param a = 1\n" * 20000,
    "param x[1..100000] = 0",
    "param é = 1",
    "frame f { point p = (0, 0, 0) }  # ünïcödé 🙂 comment",
    'include "ok.mdl"\n' * 50,
    "\ufeffparam a = 1",
    "param a = 1\r\nparam b = 2\r\n",
    "",
    "   \n\n  ",
    "template t(a) { object x = t(a) }\nobject y = t(1)",
    "template t() { object x = u() }\ntemplate u() { object y = t() }\nobject z = t()",
    "range r(fov = (60 deg, 40 deg), rays = (100000, 100000))",
    "target t = chessboard(rows = 100000, cols = 100000, square = 1 mm)",
    "camera c(width = 1e30, height = 2, f = 1)",
]


@pytest.mark.parametrize("text", EXTREMES, ids=range(len(EXTREMES)))
def test_extreme_inputs_load_or_fail_with_a_located_error(text, workspace):
    check(text, workspace / "extreme.mdl")


# ---- mutation of the bundled models ------------------------------------------------------------------

BUNDLED = {p.name: p.read_text(encoding="utf-8") for p in sorted(MODELS.glob("*.mdl"))}
TOKENS = [
    "param",
    "frame",
    "{",
    "}",
    "(",
    ")",
    "=",
    ",",
    "at",
    "deg",
    "m",
    "1e309",
    "-",
    "*",
    "^",
    "include",
    '"cycle_a.mdl"',
    "template",
    "object",
    "..",
    "±",
    "é",
    "\x00",
    "\n",
    "#",
    "per configuration",
    'mesh("empty.stl")',
    "joint revolute(z, q)",
    "sigma",
    "in [",
    "]",
]


@st.composite
def mutated(draw):
    name = draw(st.sampled_from(sorted(BUNDLED)))
    text = BUNDLED[name]
    for _ in range(draw(st.integers(1, 4))):
        n = len(text)
        kind = draw(st.sampled_from(["delete", "insert", "duplicate", "swap", "number", "truncate"]))
        i = draw(st.integers(0, max(n - 1, 0)))
        if kind == "delete":
            j = min(n, i + draw(st.integers(1, 40)))
            text = text[:i] + text[j:]
        elif kind == "insert":
            token = draw(st.one_of(st.sampled_from(TOKENS), st.text(max_size=6)))
            text = text[:i] + " " + token + " " + text[i:]
        elif kind == "duplicate":
            lines = text.splitlines()
            k = draw(st.integers(0, max(len(lines) - 1, 0)))
            lines.insert(k, lines[k] if lines else "")
            text = "\n".join(lines)
        elif kind == "swap":
            lines = text.splitlines()
            if len(lines) > 1:
                a, b = draw(st.integers(0, len(lines) - 1)), draw(st.integers(0, len(lines) - 1))
                lines[a], lines[b] = lines[b], lines[a]
            text = "\n".join(lines)
        elif kind == "number":
            import re

            numbers = list(re.finditer(r"\d+(\.\d+)?", text))
            if numbers:
                m = numbers[draw(st.integers(0, len(numbers) - 1))]
                replacement = draw(st.sampled_from(["0", "1e308", "1e999", "-1", "0.0000001", "99999999"]))
                text = text[: m.start()] + replacement + text[m.end() :]
        else:
            text = text[:i]
    return name, text


@fuzz_settings(4000)
@given(case=mutated())
@pytest.mark.slow
def test_mutated_bundled_models_load_or_fail_with_a_located_error(case, workspace):
    name, text = case
    # Beside the real model files, so their includes and meshes resolve.
    check(text, MODELS / f"fuzz-{name}")
