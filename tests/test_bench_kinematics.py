"""The kinematics and lever-task benchmark scripts keep working (small sizes, no timing asserted):
they write their sections into the pages and keep the rest of each page."""

from __future__ import annotations

import importlib.util
import shutil

import pytest

from conftest import ROOT
from conftest import run_python as run


@pytest.mark.slow
def test_kinematics_bench_writes_its_section_and_keeps_the_page(tmp_path):
    page = tmp_path / "performance.md"
    page.write_text("# Performance\n\nbench/run.py's part\n", encoding="utf-8")
    for _ in range(2):  # the second run replaces the section instead of adding one
        proc = run("bench/kinematics.py", "--configs", "200", "--repeats", "1", "--out", str(page))
        assert proc.returncode == 0, proc.stderr[-3000:]
    text = page.read_text(encoding="utf-8")
    assert text.startswith("# Performance\n\nbench/run.py's part\n")
    assert text.count("<!-- bench/kinematics.py: begin -->") == 1
    assert "| arm7.urdf | mbcal, one batch |" in text and "models/arm7.mdl" in text


def test_bench_run_keeps_the_kinematics_section(tmp_path):
    spec = importlib.util.spec_from_file_location("bench_run", ROOT / "bench" / "run.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    page = tmp_path / "performance.md"
    page.write_text(
        "old\n<!-- bench/kinematics.py: begin -->\nkept\n<!-- bench/kinematics.py: end -->\n", encoding="utf-8"
    )
    text = module.keep_other_sections("# Performance\nnew", page)
    assert text.startswith("# Performance\nnew") and "kept" in text and "old" not in text


@pytest.mark.slow
def test_lever_bench_writes_its_results_into_the_page(tmp_path):
    page = tmp_path / "control.md"
    shutil.copy(ROOT / "docs" / "control.md", page)
    proc = run("bench/lever.py", "--quick", "--restarts", "4", "--out", str(page), "--images", str(tmp_path / "images"))
    assert proc.returncode == 0, proc.stderr[-3000:]
    text = page.read_text(encoding="utf-8")
    assert text.count("<!-- bench/lever.py: begin -->") == 1 and "### The three runs" in text
    assert "| uncalibrated model, impedance control |" in text
    assert text.startswith((ROOT / "docs" / "control.md").read_text(encoding="utf-8").split("<!-- bench/lever.py")[0])
    for name in ("control_paths.png", "control_forces.png", "control_sweep.png"):
        assert (tmp_path / "images" / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
