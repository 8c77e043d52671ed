"""Shared fixtures: paths to the repository's models and to ../shared/data."""

from __future__ import annotations

import math
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
MODELS = ROOT / "models"
MEASUREMENTS = ROOT / "measurements"
SHARED_DATA = ROOT.parent / "shared" / "data"
# Debian's Chromium, driven by Playwright (its own browser download is impossible on these machines).
CHROMIUM = "/usr/bin/chromium"

# The suite's programs and parsed models go to a cache folder of this checkout's own, not to the
# user's (~/.cache/mbcal): a run traces and exports thousands of test problems, which would fill
# it and push out the entries of the user's own models.  Kept between runs (the second run is
# faster) and ignored by git; a run with MBCAL_CACHE_DIR set (as .ci/run does) uses that folder.
TEST_CACHE = ROOT / ".cache" / "mbcal"
if not os.environ.get("MBCAL_CACHE_DIR"):
    os.environ["MBCAL_CACHE_DIR"] = str(TEST_CACHE)

# A true pose of the factory corner that differs from its model by a few centimetres and degrees.
ROOM_TRUTH = {
    "room.x": 0.02,
    "room.y": 0.05,
    "room.z": 0.015,
    "room.roll": math.radians(0.8),
    "room.pitch": math.radians(-1.0),
    "room.yaw": math.radians(1.2),
}


@pytest.fixture(scope="module")
def room():
    """The bundled factory-corner model."""
    import mbcal

    return mbcal.load_model(MODELS / "teleexistence.mdl")


def shared_data(*parts: str) -> Path:
    """A path under ../shared/data, or skip the test when that folder is absent."""
    path = SHARED_DATA.joinpath(*parts)
    if not SHARED_DATA.is_dir():
        pytest.skip(f"../shared/data is not beside the checkout ({SHARED_DATA}); it holds the real data sets")
    if not path.exists():
        pytest.fail(f"{path} is missing from ../shared/data")
    return path


@pytest.fixture
def write_model(tmp_path, monkeypatch):
    """Write model text to a file in a temporary folder (the working directory) and return its name."""
    monkeypatch.chdir(tmp_path)

    def write(text: str, name: str = "model.mdl") -> str:
        path = tmp_path / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text, encoding="utf-8")
        return name

    return write


def run_python(*args: str) -> subprocess.CompletedProcess:
    """Run ``python ARGS`` from the repository root (the bench scripts' smoke tests)."""
    return subprocess.run([sys.executable, *args], cwd=ROOT, capture_output=True, text=True, timeout=900)


@pytest.fixture(scope="module")
def browser():
    """A headless Chromium for the module's page tests (.ci/run installs it when missing)."""
    missing = f"{CHROMIUM} is not installed (apt-get install chromium; .ci/run does it)"
    if not os.path.exists(CHROMIUM):
        # CI must run the page tests, never skip them: .ci/run sets MBCAL_REQUIRE_BROWSER.
        if os.environ.get("MBCAL_REQUIRE_BROWSER"):
            pytest.fail(missing)
        pytest.skip(missing)
    from playwright import sync_api  # in the test extra: a missing package is an error, not a skip

    with sync_api.sync_playwright() as p:
        b = p.chromium.launch(executable_path=CHROMIUM, args=["--no-sandbox"])
        yield b
        b.close()
