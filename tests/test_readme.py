"""The README's path works: its commands run as written from the root of a fresh clone.

The two set-up commands (a fresh virtual environment and an install) are left out: the test runs in
the environment they make.  Every other shell block (the first model's, with the lever) runs in a
scratch copy of the repository's ``models/`` and ``measurements/``; the development commands are
the ones CI runs (``.ci/run``).
"""

from __future__ import annotations

import os
import re
import shlex
import shutil
import subprocess
import sys

import pytest

import mbcal

from conftest import ROOT

README = ROOT / "README.md"
FENCE = re.compile(r"^```(\w[\w-]*)([^\n]*)\n(.*?)^```", re.S | re.M)


def sections() -> dict[str, list[tuple[str, str]]]:
    """Heading → its fenced blocks as (language, text)."""
    text = README.read_text(encoding="utf-8")
    out: dict[str, list[tuple[str, str]]] = {}
    parts = re.split(r"^## (.+)$", text, flags=re.M)
    for heading, body in zip(parts[1::2], parts[2::2]):
        out[heading.strip()] = [(m.group(1), m.group(3)) for m in FENCE.finditer(body)]
    return out


def commands(block: str) -> list[str]:
    """The commands of a shell block (comments and blank lines dropped, continuations joined)."""
    text = block.replace("\\\n", " ")
    lines = [line.split(" #")[0].strip() for line in text.splitlines()]
    return [line for line in lines if line and not line.startswith("#")]


def test_the_set_up_commands_are_the_two_documented_ones():
    setup = [b for lang, b in sections()["Set up on a fresh machine"] if lang == "sh"]
    assert [commands(b) for b in setup] == [
        ["python3 -m venv .venv && . .venv/bin/activate && pip install -e . && mbcal demo"],
        ['python3 -m venv .venv && . .venv/bin/activate && pip install -e ".[test]" && python -m pytest'],
    ]


def test_every_file_the_first_model_uses_is_in_the_repository():
    blocks = sections()["A model"]
    mdl = [b for lang, b in blocks if lang == "mdl"]
    assert mdl == [(ROOT / "models" / "lever.mdl").read_text(encoding="utf-8")]  # the README shows the file
    script = "\n".join(b for lang, b in blocks if lang == "sh")
    for path in re.findall(r"(?:models|measurements)/[\w./-]+", script):
        assert (ROOT / path).is_file(), path
    # The hand-written clicks shown inline read as measurements of the model.
    (csv,) = [b for lang, b in blocks if lang == "csv"]
    model = mbcal.load_model(ROOT / "models" / "lever.mdl")
    data = mbcal.measurements_from_records(
        [dict(zip(csv.splitlines()[0].split(","), row.split(","))) for row in csv.splitlines()[1:]], model
    )
    assert [m.id for m in data] == ["hub", "tip"]


@pytest.mark.slow
def test_the_readmes_commands_run_as_written(tmp_path):
    """Every shell block but the set-up and development ones, in order, from a fresh clone's root."""
    sh = {heading: [b for lang, b in blocks if lang == "sh"] for heading, blocks in sections().items()}
    skipped = ("Set up on a fresh machine", "Development")
    run = [(heading, b) for heading, bs in sh.items() if heading not in skipped for b in bs]
    assert len(sh["A model"]) >= 2
    shutil.copytree(ROOT / "models", tmp_path / "models")
    shutil.copytree(ROOT / "measurements", tmp_path / "measurements")
    env = {**os.environ, "PATH": f"{os.path.dirname(sys.executable)}:{os.environ.get('PATH', '')}"}
    outputs = {}
    for heading, block in run:
        for command in commands(block):
            result = subprocess.run(
                ["bash", "-e", "-c", command], cwd=tmp_path, capture_output=True, text=True, timeout=600, env=env
            )
            assert result.returncode == 0, f"{heading}: {command}\n{result.stdout[-3000:]}{result.stderr[-3000:]}"
            outputs[command] = result.stdout
    assert (tmp_path / "out" / "lever.png").is_file() and (tmp_path / "out" / "clicks.csv").is_file()
    (report,) = [out for command, out in outputs.items() if command.startswith("mbcal solve models/lever.mdl")]
    assert "lever.angle" in report and "consistent with the stated σ" in report
    angle = float(re.search(r"lever\.angle\s+([\d.]+) deg", report).group(1))
    assert abs(angle - 35) < 1.5  # the README says about 34.7°


def test_the_development_commands_are_those_ci_runs():
    """``python -m pytest`` with or without a marker is the suite itself; the others are .ci/run's lines."""
    ci = (ROOT / ".ci" / "run").read_text(encoding="utf-8")
    ci_lines = {line.strip() for line in ci.splitlines()}
    blocks = [b for lang, b in sections()["Development"] if lang == "sh"]
    cmds = [c for b in blocks for c in commands(b)]
    assert cmds
    for command in cmds:
        if command.startswith("python -m pytest"):
            args = shlex.split(command)[3:]
            assert args in ([], ["-m", "not slow"]), command
            continue
        for part in command.split("&&"):
            assert part.strip() in ci_lines, part
        for tool in {shlex.split(part)[0] for part in command.split("&&")}:
            assert shutil.which(tool, path=os.path.dirname(sys.executable)) or shutil.which(tool), tool


@pytest.mark.slow
def test_the_inner_loop_marker_selects_tests():
    result = subprocess.run(
        [sys.executable, "-m", "pytest", "-m", "not slow", "--collect-only", "-q", "-p", "no:cacheprovider"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert result.returncode == 0, result.stdout[-2000:] + result.stderr[-2000:]
    assert re.search(r"(\d+)/(\d+) tests collected", result.stdout), result.stdout[-500:]
